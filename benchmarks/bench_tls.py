"""Total-least-squares benchmark (kelly-giamou Section 5): the batched Gauss-Helmert solver
against the same trials solved one at a time, the LBFGS variant, and GTSAM's factor graph.

Every figure comes from one run on the same simulated trials (``study.simulate``, the
defaults of ``python -m torchsgal tls``).  Batched wall times are medians of ``--repeats`` (3)
timed solves; the one-at-a-time, LBFGS and GTSAM solves run on subsets and are reported per
trial (LBFGS and GTSAM: after one untimed warm-up solve, medians of ``--repeats`` passes).  The
batched speed-up over one-at-a-time solves is paired: each repeat times a batched pass over all
trials and then the one-at-a-time subset, and the reported ratio is the median of the repeats'
ratios.  The stress test restarts every trial from a bad initial guess (rotation
error uniform up to 90 degrees about a random axis, dtau off by a factor uniform in
[0.5, 1.5]) and counts a success when the solver converges to the well-initialised solution
(within 1e-3 standard deviations).

Usage::

    python benchmarks/bench_tls.py [--trials 1200] [--serial 40] [--gtsam 40] [--lbfgs 20]
    python benchmarks/bench_tls.py --device cuda [--trials 1200]

With ``--device cuda`` it times the four batched solves (both estimators, both variants) with
every trial in one batch on the device, and the same solves on the host CPU (``--chunk``
trials at a time, as above) in the same run, checks that both give the same solutions (in
standard deviations) and writes ``tls_cuda.{json,md}``.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import time

import torch

from torchsgal.estimation import study, tls
from torchsgal.load import keep_freed_memory

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
from _timing import cpu_model, eager_call_us  # noqa: E402


def timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def deviation_in_sigma(F_a, dt_a, F_b, dt_b, cov):
    """max over trials and components of |difference| / standard deviation."""
    sd = cov.diagonal(dim1=-2, dim2=-1).sqrt()
    d = torch.cat([F_b.rminus(F_a), (dt_b - dt_a)], -1)
    return float((d / sd).abs().max())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("Usage::")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trials", type=int, default=1200)
    ap.add_argument("--serial", type=int, default=40, help="trials solved one at a time")
    ap.add_argument("--gtsam", type=int, default=40, help="trials solved with GTSAM")
    ap.add_argument("--lbfgs", type=int, default=20, help="trials solved with LBFGS (one at a time)")
    ap.add_argument("--chunk", type=int, default=400)
    ap.add_argument("--repeats", type=int, default=3, help="timed repeats (medians are reported)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=os.path.join(HERE, "results"),
                    help="folder for tls_cpu.{json,md} (default benchmarks/results)")
    ap.add_argument("--release-memory", action="store_true",
                    help="leave the C allocator's defaults (as the command line, the process "
                         "keeps the large blocks it frees: torchsgal.load.keep_freed_memory)")
    ap.add_argument("--device", default="cpu",
                    help="cuda: the batched solves on that device against the host CPU (tls_cuda)")
    args = ap.parse_args(argv)
    if args.device != "cpu":
        return device_main(args)
    kept = 0 if args.release_memory else keep_freed_memory()  # glibc's mmap threshold set, or 0

    cfg = study.StudyConfig(trials=args.trials, seed=args.seed)
    trials = study.simulate(cfg)
    P = trials.problem
    K = args.trials
    res = {"config": vars(args), "threads": torch.get_num_threads(), "torch": torch.__version__,
           "cpu": cpu_model(), "eager_call_us": eager_call_us(), "date": time.strftime("%Y-%m-%d"),
           "time_utc": time.strftime("%H:%M", time.gmtime()), "loadavg_at_start": os.getloadavg(),
           "keep_freed_memory": kept}

    def batched(solve, variant):
        xs, covs, status, its = [], [], [], []
        t = 0.0
        # one untimed solve first: first-call costs (lazy imports, caches, the heap's growth)
        # stay out of the timings, as they do for the paired passes below
        solve(tls.subset(P, slice(0, args.chunk)), variant=variant, dtau0=cfg.nominal_dtau)
        for s in range(0, K, args.chunk):
            runs = [timed(lambda: solve(tls.subset(P, slice(s, s + args.chunk)), variant=variant,
                                        dtau0=cfg.nominal_dtau)) for _ in range(args.repeats)]
            sol = runs[0][0]
            t += statistics.median(r[1] for r in runs)
            xs.append(sol.x)
            covs.append(sol.covariance)
            status.append(sol.report.status)
            its.append(sol.report.iterations)
        x = tuple(type(xs[0][i]).stack([c[i] for c in xs]) if hasattr(xs[0][i], "as_matrix")
                  else torch.cat([c[i] for c in xs]) for i in range(len(xs[0])))
        x = tuple(b.reshape(-1) if hasattr(b, "as_matrix") else b for b in x)
        return x, torch.cat(covs), torch.cat(status), torch.cat(its), t

    print(f"{K} trials, {P.F_ga.batch_shape[1]} samples, {torch.get_num_threads()} threads",
          file=sys.stderr)
    batch = {}
    for name, solve in (("SGal(3)", tls.solve_sgal3), ("SE_2(3) x R", tls.solve_baseline)):
        for variant in ("iterated", "paper"):
            x, cov, status, its, t = batched(solve, variant)
            batch[(name, variant)] = (x, cov, status)
            res.setdefault("batched", {})[f"{name} {variant}"] = {
                "time_s": t, "per_trial_ms": 1e3 * t / K, "converged": int((status == 0).sum()),
                "iterations_median": float(its.double().median())}
            print(f"batched {name} {variant}: {t:.2f} s", file=sys.stderr)
    total = sum(v["time_s"] for v in res["batched"].values())
    res["study_solve_time_s"] = total

    # One trial at a time (same solver, batch of one), paired with batched passes: each repeat
    # times one batched pass over all trials and then the one-at-a-time subset, and the speed-up
    # is the median of the repeats' ratios (the machine's speed drifts between passes).
    S = min(args.serial, K)
    serial = {}
    for variant in ("iterated", "paper"):
        times, batched_times, ratios = [], [], []
        for _ in range(args.repeats):
            tb = 0.0
            for s in range(0, K, args.chunk):
                tb += timed(lambda: tls.solve_sgal3(tls.subset(P, slice(s, s + args.chunk)), variant=variant,
                                                    dtau0=cfg.nominal_dtau))[1]
            t0 = time.perf_counter()
            xs = [tls.solve_sgal3(tls.subset(P, slice(k, k + 1)), variant=variant,
                                  dtau0=cfg.nominal_dtau).x for k in range(S)]
            times.append(time.perf_counter() - t0)
            batched_times.append(tb)
            ratios.append((times[-1] / S) / (tb / K))
        t = statistics.median(times)
        F1 = type(xs[0][0]).stack([x[0] for x in xs]).reshape(-1)
        dt1 = torch.cat([x[1] for x in xs])
        xb, covb, _ = batch[("SGal(3)", variant)]
        dev = deviation_in_sigma(xb[0][:S], xb[1][:S], F1, dt1, covb[:S])
        serial[variant] = {"trials": S, "per_trial_ms": 1e3 * t / S,
                           "batched_per_trial_ms": 1e3 * statistics.median(batched_times) / K,
                           "speedup_batched": statistics.median(ratios),
                           "speedup_batched_repeats": ratios, "max_deviation_sigma": dev}
        print(f"serial SGal(3) {variant}: {1e3 * t / S:.1f} ms/trial, batched is "
              f"{serial[variant]['speedup_batched']:.1f}x faster ({', '.join(f'{r:.1f}' for r in ratios)})",
              file=sys.stderr)
    res["serial"] = serial

    # LBFGS (the paper variant's cost, reweighted) on a subset, one trial at a time.
    L = min(args.lbfgs, K)
    if L:
        tls.solve_sgal3_lbfgs(tls.subset(P, slice(0, 1)), dtau0=cfg.nominal_dtau)  # warm-up, untimed
        runs = [timed(lambda: tls.solve_sgal3_lbfgs(tls.subset(P, slice(0, L)), dtau0=cfg.nominal_dtau))
                for _ in range(args.repeats)]
        sol, t = runs[0][0], statistics.median(r[1] for r in runs)
        xb, covb, _ = batch[("SGal(3)", "paper")]
        res["lbfgs"] = {"trials": L, "time_s": t, "per_trial_ms": 1e3 * t / L,
                        "converged": int(sol.report.converged.sum()),
                        "iterations_median": float(sol.report.iterations.double().median()),
                        "speedup_batched": (1e3 * t / L) / res["batched"]["SGal(3) paper"]["per_trial_ms"],
                        "max_deviation_sigma": deviation_in_sigma(xb[0][:L], xb[1][:L], sol.x[0],
                                                                  sol.x[1], covb[:L])}
        print(f"lbfgs: {res['lbfgs']}", file=sys.stderr)

    # GTSAM factor graph, one trial at a time.
    G = min(args.gtsam, K)
    try:
        from torchsgal.estimation import gtsam_peer
        F0, dt0 = P.initial_guess(cfg.nominal_dtau)

        def gtsam_pass(n):
            Fs, dts = [], []
            for k in range(n):
                F, dtau, _, _ = gtsam_peer.solve_trial(
                    P.F_ga.as_matrix()[k].numpy(), P.F_gb.as_matrix()[k].numpy(), P.cov_a.numpy(),
                    P.cov_b.numpy(), F0.as_matrix()[k].numpy(), float(dt0[k, 0]))
                Fs.append(torch.tensor(F))
                dts.append(dtau)
            return Fs, dts

        gtsam_pass(1)  # warm-up, untimed: gtsam's import and first-call setup (~0.2 s)
        runs = [timed(lambda: gtsam_pass(G)) for _ in range(args.repeats)]
        (Fs, dts), t = runs[0][0], statistics.median(r[1] for r in runs)
        from torchsgal import SGal3
        xb, covb, _ = batch[("SGal(3)", "iterated")]
        dev = deviation_in_sigma(xb[0][:G], xb[1][:G], SGal3(torch.stack(Fs)),
                                 torch.tensor(dts, dtype=torch.float64)[:, None], covb[:G])
        b_per = res["batched"]["SGal(3) iterated"]["per_trial_ms"]
        res["gtsam"] = {"trials": G, "per_trial_ms": 1e3 * t / G,
                        "speedup_batched": (1e3 * t / G) / b_per, "max_deviation_sigma": dev}
        print(f"gtsam: {res['gtsam']}", file=sys.stderr)
    except ImportError as exc:
        res["gtsam"] = {"skipped": f"gtsam not installed ({exc})"}

    # Stress: bad initial guesses, all trials, iterated variant.
    gen = torch.Generator().manual_seed(args.seed + 1)
    axis = torch.randn(K, 3, generator=gen, dtype=torch.float64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    angle = (math.pi / 2) * torch.rand(K, generator=gen, dtype=torch.float64)
    delta = torch.zeros(K, 10, dtype=torch.float64)
    delta[:, 6:9] = axis * angle[:, None]
    F_bad = trials.F_true.rplus(delta)
    dt_bad = (trials.dtau_true * (0.5 + torch.rand(K, generator=gen, dtype=torch.float64)))[:, None]
    xs, ok, t = [], [], 0.0
    xb, covb, _ = batch[("SGal(3)", "iterated")]
    for s in range(0, K, args.chunk):
        sl = slice(s, s + args.chunk)
        sol, dt = timed(lambda: tls.solve_sgal3(tls.subset(P, sl), x0=(F_bad[sl], dt_bad[sl]),
                                                variant="iterated", max_iterations=100))
        t += dt
        sd = covb[sl].diagonal(dim1=-2, dim2=-1).sqrt()
        d = torch.cat([sol.x[0].rminus(xb[0][sl]), sol.x[1] - xb[1][sl]], -1) / sd
        ok.append(sol.report.converged & (d.abs().amax(-1) < 1e-3))
    ok = torch.cat(ok)
    res["stress"] = {"trials": K, "success": int(ok.sum()), "success_rate": float(ok.double().mean()),
                     "time_s": t}
    print(f"stress: {res['stress']}", file=sys.stderr)

    res["loadavg_at_end"] = os.getloadavg()
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "tls_cpu.json"), "w") as f:
        json.dump(res, f, indent=2)
    md = [f"# TLS benchmark ({res['cpu']}, torch {res['torch']}, {res['threads']} threads, "
          f"{res['date']})", "",
          f"{K} trials of {P.F_ga.batch_shape[1]} paired observations (defaults of "
          "`python -m torchsgal tls`).  Started at "
          f"{res['time_utc']} UTC; load average (1, 5, 15 min) at start "
          f"{tuple(round(x, 2) for x in res['loadavg_at_start'])}, at end "
          f"{tuple(round(x, 2) for x in res['loadavg_at_end'])}; an eager `x * 2` on 1,000 float64 "
          f"elements takes {res['eager_call_us']:.1f} us on one thread (the per-call cost that the one-at-a-time "
          "and GTSAM solves pay most).  Freed large blocks "
          + ("kept for reuse (`torchsgal.load.keep_freed_memory()`, as the command line)." if kept
             else "returned to the system (the C allocator's defaults)."), "",
          "| solver | trials | time | per trial | converged | median iterations |",
          "|---|---|---|---|---|---|"]
    for k, v in res["batched"].items():
        md.append(f"| batched {k} | {K} | {v['time_s']:.2f} s | {v['per_trial_ms']:.2f} ms | "
                  f"{v['converged']} | {v['iterations_median']:.0f} |")
    md += ["", f"Whole study (both estimators, both variants): **{total:.1f} s** of solving.", "",
           "| comparison (SGal(3)) | trials | per trial | batched speed-up | max deviation |",
           "|---|---|---|---|---|"]
    for v, s in serial.items():
        md.append(f"| one at a time, {v} (paired batched passes: {s['batched_per_trial_ms']:.2f} ms "
                  f"per trial) | {s['trials']} | {s['per_trial_ms']:.1f} ms | "
                  f"{s['speedup_batched']:.1f}x "
                  f"(repeats: {', '.join(f'{r:.1f}' for r in s['speedup_batched_repeats'])}) | "
                  f"{s['max_deviation_sigma']:.1e} sd |")
    g = res["gtsam"]
    if "per_trial_ms" in g:
        md.append(f"| GTSAM factor graph (LM), vs iterated | {g['trials']} | "
                  f"{g['per_trial_ms']:.1f} ms | {g['speedup_batched']:.1f}x | "
                  f"{g['max_deviation_sigma']:.1e} sd |")
    if "lbfgs" in res:
        lb = res["lbfgs"]
        md.append(f"| LBFGS, reweighted, one at a time, vs paper-style | {lb['trials']} | "
                  f"{lb['per_trial_ms']:.1f} ms | {lb['speedup_batched']:.0f}x | "
                  f"{lb['max_deviation_sigma']:.1e} sd ({lb['converged']}/{lb['trials']} converged, "
                  f"median {lb['iterations_median']:.0f} LBFGS iterations) |")
    st = res["stress"]
    md += ["", f"Stress (rotation error up to 90 deg, dtau x [0.5, 1.5]): {st['success']}/{st['trials']}"
           f" = {100 * st['success_rate']:.1f}% reach the well-initialised solution "
           f"({st['time_s']:.1f} s).", ""]
    with open(os.path.join(args.out, "tls_cpu.md"), "w") as f:
        f.write("\n".join(md))
    print("\n".join(md))
    return 0


def device_main(args) -> int:
    """The four batched solves on ``args.device`` (all trials at once) and on the host CPU."""
    device = torch.device(args.device)
    kept = 0 if args.release_memory else keep_freed_memory()  # for the host rows, as above
    cfg = study.StudyConfig(trials=args.trials, seed=args.seed)
    P = study.simulate(cfg).problem
    K = args.trials
    Pd = tls.TLSProblem(P.F_ga.to(device), P.F_gb.to(device), P.cov_a.to(device), P.cov_b.to(device),
                        indices=P.indices.to(device))

    def sync():
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    def on_device(solve, variant):
        def run():
            out = solve(Pd, variant=variant, dtau0=cfg.nominal_dtau)
            sync()
            return out
        run()  # warm-up, untimed (the device's libraries, first launches)
        runs = [timed(run) for _ in range(args.repeats)]
        return runs[0][0], statistics.median(r[1] for r in runs)

    def on_host(solve, variant):
        parts, t = [], 0.0
        for s in range(0, K, args.chunk):
            runs = [timed(lambda: solve(tls.subset(P, slice(s, s + args.chunk)), variant=variant,
                                        dtau0=cfg.nominal_dtau)) for _ in range(args.repeats)]
            parts.append(runs[0][0])
            t += statistics.median(r[1] for r in runs)
        return parts, t

    res = {"config": vars(args), "torch": torch.__version__, "cpu": cpu_model(),
           "device_name": torch.cuda.get_device_name(device) if device.type == "cuda" else str(device),
           "host_threads": torch.get_num_threads(), "date": time.strftime("%Y-%m-%d"),
           "keep_freed_memory": kept, "rows": {}}
    for name, solve in (("SGal(3)", tls.solve_sgal3), ("SE_2(3) x R", tls.solve_baseline)):
        for variant in ("iterated", "paper"):
            dev, t_dev = on_device(solve, variant)
            host, t_host = on_host(solve, variant)
            diffs = []
            for i, x_dev in enumerate(dev.x):
                if hasattr(x_dev, "as_matrix"):
                    x_host = type(x_dev).stack([h.x[i] for h in host]).reshape(-1)
                    diffs.append(x_dev.to("cpu").rminus(x_host))
                else:
                    diffs.append(x_dev.cpu() - torch.cat([h.x[i] for h in host]))
            cov = torch.cat([h.covariance for h in host])
            status = torch.cat([h.report.status for h in host])
            sd = cov.diagonal(dim1=-2, dim2=-1).sqrt()
            d = torch.cat(diffs, -1) / sd
            res["rows"][f"{name} {variant}"] = {
                "device_s": t_dev, "host_s": t_host, "speedup": t_host / t_dev,
                "same_status": bool(torch.equal(dev.report.status.cpu(), status)),
                "max_deviation_sigma": float(d.abs().max())}
            print(f"{name} {variant}: {res['rows'][f'{name} {variant}']}", file=sys.stderr)
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, f"tls_{device.type}.json"), "w") as f:
        json.dump(res, f, indent=2)
    md = [f"# TLS benchmark on {res['device_name']} (torch {res['torch']}, {res['date']})", "",
          f"{K} trials of {P.F_ga.batch_shape[1]} paired observations (defaults of "
          f"`python -m torchsgal tls`): all trials in one batch on the device, against the host "
          f"CPU ({res['cpu']}, {res['host_threads']} threads, {args.chunk} trials a batch as in "
          f"`tls_cpu.md`) in the same run; medians of {args.repeats} solves after an untimed one.  "
          "On the host, freed large blocks "
          + ("kept for reuse (`torchsgal.load.keep_freed_memory()`, as the command line)." if kept
             else "returned to the system (the C allocator's defaults)."),
          "", "| solver | device | host CPU | device speed-up | same status | max deviation |",
          "|---|---|---|---|---|---|"]
    for k, v in res["rows"].items():
        md.append(f"| batched {k} | {v['device_s']:.3f} s | {v['host_s']:.2f} s | "
                  f"{v['speedup']:.1f}x | {'yes' if v['same_status'] else 'no'} | "
                  f"{v['max_deviation_sigma']:.1e} sd |")
    total_dev = sum(v["device_s"] for v in res["rows"].values())
    total_host = sum(v["host_s"] for v in res["rows"].values())
    md += ["", f"The four solves: **{total_dev:.2f} s** on the device, {total_host:.1f} s on the "
           "host CPU.", ""]
    with open(os.path.join(args.out, f"tls_{device.type}.md"), "w") as f:
        f.write("\n".join(md))
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    sys.exit(main())
