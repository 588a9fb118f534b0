#!/usr/bin/env python
"""IMU preintegration benchmark: torchsgal (batched) vs pypose (batched) vs GTSAM (loop).

``--windows`` (default 1,000) windows of ``--samples`` (default 200) IMU samples at
dt = ``--dt`` (default 0.005 s, so 1 s windows), from the analytic ``SinusoidalTrajectory``
(midpoint samples, gravity z-up), the same stream for every method.  What is timed (whole
batch, milliseconds per call):

(a) increment + covariance (+ bias Jacobians where the method has them)

* ``torchsgal``  ``preintegrate(gyro, acc, dt, gyro_noise_density=..., acc_noise_density=...)``:
                 the SGal(3) increment, its 10x10 covariance and the 10x6 bias Jacobian;
* ``pypose``     ``pp.module.IMUPreintegrator(prop_cov=True, reset=True)(dt, gyro, acc)``:
                 its increments (every prefix) and 9x9 covariance (no bias Jacobians);
* ``GTSAM``      a Python loop over windows of ``PreintegratedImuMeasurements.integrateMeasurement``
                 over the samples (increment, 9x9 covariance and bias Jacobians, in C++).

(b) increment only

* ``torchsgal``  ``preintegrate(..., covariance=False, bias_jacobian=False)`` (tree product);
* ``pypose``     ``IMUPreintegrator(prop_cov=False, reset=True)``;
* GTSAM has no increment-only mode: its (a) time is the reference for both sections.

torchsgal and pypose run in float64 and float32; GTSAM in double.  Timing method: the cases
of a section are interleaved (round-robin, one call of each per round, order rotated), two
untimed warm-up calls each, GC off, medians over rounds; ratios are medians of per-round
ratios.  The share of the CPU used by other processes during each section is recorded.

Accuracy at equal dt is measured on the same batch: the state predicted at each window's end
from the true state at its start (gravity included) against the analytic truth.

(c) streaming (float64, CPU; ``--stream-calls`` calls per timed run), every case fed the same
samples:

* one IMU, one sample per call (pypose: 64 calls per run, it takes ~10 ms a call):
  ``StreamingPreintegration.integrate`` (samples held and
  folded in chunks of 256, the result read at the end of the run), the same with
  ``buffer_size=1`` (each call folded at once, for a reader of every sample), GTSAM's
  ``integrateMeasurement`` (C++ from Python), pypose ``IMUPreintegrator(reset=False)`` one
  sample per call;
* one IMU, chunks of 10 samples per call (per sample): torchsgal, pypose;
* one window of 400 samples (latency): ``preintegrate``, one ``integrate`` call, GTSAM's loop,
  pypose;
* 1,000 IMUs, one sample per call (per IMU-sample): torchsgal batched, pypose batched,
  GTSAM (one object per IMU, a Python loop).

Usage::

    python benchmarks/bench_imu.py                 # full run, writes benchmarks/results/imu_cpu.*
    python benchmarks/bench_imu.py --quick         # 100 windows, few rounds, no files
    python benchmarks/bench_imu.py --threads 1 --wait-idle 60
    python benchmarks/bench_imu.py --device cuda   # writes benchmarks/results/imu_cuda.*

Devices: ``--device cuda[:i]`` runs torchsgal and pypose on that GPU (the device synchronised
around every timed call); GTSAM stays on the CPU (its C++ loop is the peer); the result files
are ``imu_cuda.*``.  On CUDA torchsgal takes its plain batched path (``_integrate``): the in-place,
blocked fast path (``_integrate_fast``) is CPU-only.  The accuracy of torchsgal is then measured
on the device too; pypose's (``peers.pypose_predict``) and GTSAM's on the CPU.  A peer that is not
importable (gtsam, pypose) is left out with a note; torchsgal is timed alone if need be.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

_HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(_HERE))
sys.path.insert(1, str(_HERE.parent))  # benchmark the checkout this script lives in
from _timing import (  # noqa: E402
    cpu_model,
    device_name,
    dist_version,
    environment,
    interleaved,
    loadavg,
    paired_ratio,
    resolve_device,
    wait_for_idle,
)

from torchsgal.imu import (  # noqa: E402
    StreamingPreintegration,
    gravity_vector,
    peers,  # noqa: E402
    preintegrate,
)
from torchsgal.imu.trajectory import SinusoidalTrajectory  # noqa: E402

G = 9.80665
SIGMA_G, SIGMA_A = 1e-3, 1e-2  # rad/s/sqrt(Hz), m/s^2/sqrt(Hz)


def log(msg: str) -> None:
    print(msg, flush=True)


def build(windows: int, samples: int, dt: float):
    traj = SinusoidalTrajectory()
    g = gravity_vector("z_up", G, dtype=torch.float64)
    t0 = torch.linspace(0.0, 20.0, windows, dtype=torch.float64)
    gyro, acc, h = traj.stream(t0, samples * dt, dt, g)
    return traj, g, t0, gyro, acc, h


def import_peers() -> tuple[dict, dict]:
    """({"pypose": module or None, "gtsam": module or None}, {name: why not importable})."""
    mods, missing = {}, {}
    for name in ("pypose", "gtsam"):
        try:
            mods[name] = __import__(name)
        except ImportError as e:
            mods[name], missing[name] = None, f"{type(e).__name__}: {e}"
            log(f"NOTE: {name} is not importable ({missing[name]}): its peer cases are skipped")
    return mods, missing


def accuracy(traj, g, t0, gyro, acc, h, device, mods) -> dict:
    X0, X1 = traj.state(t0), traj.state(t0 + h.sum(-1))
    if device.type == "cpu":
        ours = preintegrate(gyro, acc, h, covariance=False, bias_jacobian=False).predict(X0, g)
    else:
        d = {"device": device}
        ours = preintegrate(gyro.to(**d), acc.to(**d), h.to(**d), covariance=False,
                            bias_jacobian=False).predict(X0.to(**d), g.to(**d)).cpu()
    preds = {"torchsgal": ours}
    if mods["pypose"] is not None:
        preds["pypose"] = peers.pypose_predict(gyro, acc, h, X0, "z_up", G)
    if mods["gtsam"] is not None:
        preds["GTSAM"] = peers.gtsam_predict(
            peers.gtsam_preintegrate(gyro, acc, h, peers.gtsam_params("z_up", G)), X0)
    out = {}
    for name, P in preds.items():
        pos = (P.position() - X1.position()).norm(dim=-1)
        vel = (P.velocity() - X1.velocity()).norm(dim=-1)
        rot = P.between(X1).log()[..., 6:9].norm(dim=-1)
        out[name] = {"pos_median_m": float(pos.median()), "pos_max_m": float(pos.max()),
                     "vel_median_mps": float(vel.median()), "vel_max_mps": float(vel.max()),
                     "rot_median_rad": float(rot.median()), "rot_max_rad": float(rot.max())}
    return out


def run(args, device, mods) -> dict:
    gtsam, pp = mods["gtsam"], mods["pypose"]

    traj, g, t0, gyro64, acc64, h64 = build(args.windows, args.samples, args.dt)
    log("accuracy on the benchmark batch ...")
    acc_res = accuracy(traj, g, t0, gyro64, acc64, h64, device, mods)
    g_np, a_np, h_np = gyro64.numpy(), acc64.numpy(), h64.numpy()  # GTSAM's input, on the CPU
    if gtsam is not None:
        params = peers.gtsam_params("z_up", G, SIGMA_G, SIGMA_A)
        bias = gtsam.imuBias.ConstantBias()

    def gtsam_loop():
        out = []
        for w in range(g_np.shape[0]):
            pim = gtsam.PreintegratedImuMeasurements(params, bias)
            for k in range(g_np.shape[1]):
                pim.integrateMeasurement(a_np[w, k], g_np[w, k], float(h_np[w, k]))
            out.append(pim)
        return out

    sections = {}
    for dtype in [getattr(torch, d.strip()) for d in args.dtypes.split(",")]:
        name = str(dtype).replace("torch.", "")
        gyro, acc, h = (x.to(dtype=dtype, device=device) for x in (gyro64, acc64, h64))
        hh = h.unsqueeze(-1)
        full = {
            "torchsgal": lambda: preintegrate(gyro, acc, h, gyro_noise_density=SIGMA_G, acc_noise_density=SIGMA_A),
        }
        inc = {
            "torchsgal": lambda: preintegrate(gyro, acc, h, covariance=False, bias_jacobian=False),
        }
        if pp is not None:
            pp_cov = pp.module.IMUPreintegrator(gravity=G, gyro_cov=SIGMA_G**2 / args.dt,
                                                acc_cov=SIGMA_A**2 / args.dt, prop_cov=True,
                                                reset=True).to(dtype=dtype, device=device)
            pp_inc = pp.module.IMUPreintegrator(gravity=G, prop_cov=False,
                                                reset=True).to(dtype=dtype, device=device)
            full["pypose"] = lambda: pp_cov(hh, gyro, acc)
            inc["pypose"] = lambda: pp_inc(hh, gyro, acc)
        if gtsam is not None:
            full["GTSAM"] = gtsam_loop
        with torch.no_grad():
            log(f"[{name}] (a) increment + covariance ...")
            st_a, t_a, load_a = interleaved(full, target_s=args.target, min_rounds=args.min_rounds,
                                            max_rounds=args.max_rounds, device=device)
            log(f"[{name}] (b) increment only ...")
            st_b, t_b, load_b = interleaved(inc, target_s=args.target / 2, min_rounds=args.min_rounds,
                                            max_rounds=args.max_rounds, device=device)
        ratios = {}
        if pp is not None:
            ratios["(a) pypose / torchsgal"] = paired_ratio(t_a, "pypose", "torchsgal")
        if gtsam is not None:
            ratios["(a) GTSAM / torchsgal"] = paired_ratio(t_a, "GTSAM", "torchsgal")
        if pp is not None:
            ratios["(b) pypose / torchsgal"] = paired_ratio(t_b, "pypose", "torchsgal")
        if gtsam is not None:
            ratios["(b) GTSAM (a) median / torchsgal (b) median"] = (
                st_a["GTSAM"]["median_s"] / st_b["torchsgal"]["median_s"])
        sections[name] = {
            "increment_covariance": st_a,
            "increment_only": st_b,
            "foreign_cpu": {"increment_covariance": load_a, "increment_only": load_b},
            "ratios": ratios,
        }
    return {"accuracy": acc_res, "timing": sections}


def streaming(args, mods) -> dict:
    """Section (c): per-call and per-sample costs of streaming preintegration (float64, CPU)."""
    gtsam, pp = mods["gtsam"], mods["pypose"]
    F64, n, dt = torch.float64, args.stream_calls, args.dt
    gen = torch.Generator().manual_seed(0)
    gyro = 0.5 * torch.randn(n, 3, generator=gen, dtype=F64)
    acc = torch.randn(n, 3, generator=gen, dtype=F64) + torch.tensor([0.0, 0.0, G], dtype=F64)
    dens = dict(gyro_noise_density=SIGMA_G, acc_noise_density=SIGMA_A, dtype=F64)
    rows = list(zip(gyro.unbind(0), acc.unbind(0)))
    chunk = 10
    n_pp = min(n, 64)
    counts = {("one_sample_per_call", "pypose"): n_pp, ("chunks_of_10", "pypose"): n_pp * chunk}

    def ours(buffer_size):
        def go():
            s = StreamingPreintegration(buffer_size=buffer_size, **dens)
            for g_k, a_k in rows:
                s.integrate(g_k, a_k, dt)
            return s.result()
        return go

    def ours_chunks():
        s = StreamingPreintegration(**dens)
        for i in range(0, n, chunk):
            s.integrate(gyro[i:i + chunk], acc[i:i + chunk], dt)
        return s.result()

    single, chunked, window, batch = {}, {}, {}, {}
    single["torchsgal (held, 256)"] = ours(256)
    single["torchsgal (buffer_size=1)"] = ours(1)
    chunked["torchsgal"] = ours_chunks
    K, B = 400, 1000
    gw, aw, hw = gyro[:K], acc[:K], torch.full((K,), dt, dtype=F64)
    window["torchsgal preintegrate"] = lambda: preintegrate(gw, aw, hw, gyro_noise_density=SIGMA_G,
                                                            acc_noise_density=SIGMA_A)

    def ours_window():
        s = StreamingPreintegration(**dens)
        s.integrate(gw, aw, dt)
        return s.result()
    window["torchsgal integrate (one call)"] = ours_window
    gb = 0.5 * torch.randn(args.stream_batch_calls, B, 3, generator=gen, dtype=F64)
    ab = torch.randn(args.stream_batch_calls, B, 3, generator=gen, dtype=F64) + torch.tensor([0, 0, G], dtype=F64)

    def ours_batch():
        s = StreamingPreintegration((B,), **dens)
        for k in range(gb.shape[0]):
            s.integrate(gb[k], ab[k], dt)
        return s.result()
    batch["torchsgal"] = ours_batch
    if gtsam is not None:
        params = peers.gtsam_params("z_up", G, SIGMA_G, SIGMA_A)
        bias = gtsam.imuBias.ConstantBias()
        g_np, a_np = gyro.numpy(), acc.numpy()

        def gtsam_stream(count):
            def go():
                pim = gtsam.PreintegratedImuMeasurements(params, bias)
                for k in range(count):
                    pim.integrateMeasurement(a_np[k], g_np[k], dt)
                return pim
            return go
        single["GTSAM"] = gtsam_stream(n)
        window["GTSAM"] = gtsam_stream(K)
        gb_np, ab_np = gb.numpy(), ab.numpy()

        def gtsam_batch():
            pims = [gtsam.PreintegratedImuMeasurements(params, bias) for _ in range(B)]
            for k in range(gb_np.shape[0]):
                for i, pim in enumerate(pims):
                    pim.integrateMeasurement(ab_np[k, i], gb_np[k, i], dt)
            return pims
        batch["GTSAM"] = gtsam_batch
    if pp is not None:
        def pypose_stream(count, size, batch_size=1, g=gyro, a=acc):
            integ = pp.module.IMUPreintegrator(gravity=G, gyro_cov=SIGMA_G**2 / dt, acc_cov=SIGMA_A**2 / dt,
                                               prop_cov=True, reset=False).to(F64)
            h = torch.full((batch_size, size, 1), dt, dtype=F64)

            def go():
                integ.__init__(gravity=G, gyro_cov=SIGMA_G**2 / dt, acc_cov=SIGMA_A**2 / dt, prop_cov=True,
                               reset=False)
                integ.to(F64)
                for i in range(0, count, size):
                    integ(h, g[i:i + size].reshape(batch_size, size, 3), a[i:i + size].reshape(batch_size, size, 3))
                return integ
            return go
        single["pypose"] = pypose_stream(n_pp, 1)  # fewer calls: ~10 ms each
        chunked["pypose"] = pypose_stream(n_pp * chunk, chunk)
        window["pypose"] = pypose_stream(K, K)

        def pypose_batch():
            integ = pp.module.IMUPreintegrator(gravity=G, gyro_cov=SIGMA_G**2 / dt, acc_cov=SIGMA_A**2 / dt,
                                               prop_cov=True, reset=False).to(F64)
            h = torch.full((B, 1, 1), dt, dtype=F64)
            for k in range(gb.shape[0]):
                integ(h, gb[k].unsqueeze(1), ab[k].unsqueeze(1))
            return integ
        batch["pypose"] = pypose_batch
    out = {}
    with torch.no_grad():
        for key, cases, per in (("one_sample_per_call", single, n), ("chunks_of_10", chunked, n),
                                ("window_400", window, 1), ("batch_1000_imus", batch, gb.shape[0] * B)):
            log(f"(c) streaming: {key} ...")
            st, _, load = interleaved(cases, target_s=args.stream_target, min_rounds=args.min_rounds,
                                      max_rounds=args.max_rounds)
            pers = {m: counts.get((key, m), per) for m in st}
            out[key] = {"per": pers, "foreign_cpu": load,
                        "cases": {m: dict(v, per_us=v["median_s"] / pers[m] * 1e6) for m, v in st.items()}}
    return out


def stream_tables(res: dict, args) -> list[str]:
    titles = {"one_sample_per_call": f"one IMU, one sample per call ({args.stream_calls} calls): µs per call",
              "chunks_of_10": f"one IMU, chunks of 10 samples ({args.stream_calls} samples): µs per sample",
              "window_400": "one window of 400 samples: µs per window",
              "batch_1000_imus": f"1,000 IMUs, one sample each per call ({args.stream_batch_calls} calls): "
                                 "µs per IMU-sample"}
    out = []
    for key, sec in res.items():
        out += [f"### (c) streaming, float64: {titles[key]}  (foreign CPU load: {_pct(sec['foreign_cpu'])})", "",
                "| method | µs (median) | min–max µs | rounds |", "|---|---:|---:|---:|"]
        for m, v in sec["cases"].items():
            per = sec["per"][m]
            out.append(f"| {m} | {v['per_us']:,.2f} | {v['min_s'] / per * 1e6:,.2f}–"
                       f"{v['max_s'] / per * 1e6:,.2f} | {v['rounds']} |")
        out.append("")
    return out


def fmt_ms(s: float) -> str:
    return f"{s * 1e3:,.1f}"


def _pct(x) -> str:
    return "n/a" if x is None else f"{100 * x:.0f}%"


def tables(res: dict, args) -> list[str]:
    label = lambda m: args.labels.get(m, m)  # noqa: E731  (where each method ran, on CUDA)
    acc_label = lambda m: args.accuracy_labels.get(m, m)  # noqa: E731
    out = [f"## accuracy at equal dt ({args.windows:,} windows of {args.samples} samples, dt = {args.dt} s, "
           "midpoint samples, float64)", "",
           "| method | position median [m] | position max [m] | velocity max [m/s] | rotation max [rad] |",
           "|---|---:|---:|---:|---:|"]
    for m, a in res["accuracy"].items():
        out.append(f"| {acc_label(m)} | {a['pos_median_m']:.2e} | {a['pos_max_m']:.2e} | {a['vel_max_mps']:.2e} "
                   f"| {a['rot_max_rad']:.2e} |")
    out.append("")
    for dtype, sec in res["timing"].items():
        for key, title in (("increment_covariance", "(a) increment + covariance (+ bias Jacobians)"),
                           ("increment_only", "(b) increment only")):
            out += [f"### {dtype}: {title}  (foreign CPU load: {_pct(sec['foreign_cpu'][key])})", "",
                    "| method | ms / batch (median) | min–max ms | µs / sample | rounds |", "|---|---:|---:|---:|---:|"]
            n = args.windows * args.samples
            for m, v in sec[key].items():
                out.append(f"| {label(m)} | {fmt_ms(v['median_s'])} | {fmt_ms(v['min_s'])}–{fmt_ms(v['max_s'])} "
                           f"| {v['median_s'] / n * 1e6:.3f} | {v['rounds']} |")
            out.append("")
        out += [f"### {dtype}: speed-ups of torchsgal (> 1: torchsgal faster)", "", "| ratio | value |", "|---|---:|"]
        out += [f"| {k} | {v:.2f} |" for k, v in sec["ratios"].items()]
        if not sec["ratios"]:
            out.append("| (no peer available) | – |")
        out.append("")
    return out


def verdict(res: dict, missing: dict) -> list[str]:
    """The targets, for the peers that ran; ``missing`` (peer module -> why) names the others."""
    lines = []
    acc = res["accuracy"]
    others = [m for m in ("pypose", "GTSAM") if m in acc]
    worst = f"- accuracy: torchsgal's worst position error {acc['torchsgal']['pos_max_m']:.2e} m"
    if others:
        better = all(acc["torchsgal"]["pos_max_m"] < acc[m]["pos_max_m"] for m in others)
        lines.append(worst + " vs " + ", ".join(f"{m} {acc[m]['pos_max_m']:.2e} m" for m in others)
                     + f" (better than {'both' if len(others) == 2 else others[0]}: "
                     f"{'met' if better else 'NOT met'})")
    else:
        lines.append(worst + " (no peer available to compare)")
    for dtype, sec in res["timing"].items():
        r = sec["ratios"]
        a_parts, b_parts, targets = [], [], []
        if "(a) pypose / torchsgal" in r:
            a_parts.append(f"{r['(a) pypose / torchsgal']:.2f}x pypose")
        if "(a) GTSAM / torchsgal" in r:
            a_parts.append(f"{r['(a) GTSAM / torchsgal']:.2f}x GTSAM")
        if "(b) pypose / torchsgal" in r:
            b_parts.append(f"{r['(b) pypose / torchsgal']:.2f}x pypose")
            pp_min = min(r["(a) pypose / torchsgal"], r["(b) pypose / torchsgal"])
            targets.append(f">= 1x pypose ({'met' if pp_min >= 1 else 'NOT met'})")
        gb = "(b) GTSAM (a) median / torchsgal (b) median"
        if gb in r:
            b_parts.append(f"{r[gb]:.2f}x GTSAM")
            targets.append(f">= 10x GTSAM ((a) {'met' if r['(a) GTSAM / torchsgal'] >= 10 else 'NOT met'}, "
                           f"(b) {'met' if r[gb] >= 10 else 'NOT met'})")
        if a_parts:
            line = (f"- {dtype}: (a) {', '.join(a_parts)}; (b) {', '.join(b_parts)}. "
                    f"Targets: {', '.join(targets)}")
        else:
            line = f"- {dtype}: torchsgal timed alone"
        if missing:
            line += " [not compared: " + "; ".join(f"{k} not importable" for k in missing) + "]"
        lines.append(line)
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="IMU preintegration: torchsgal vs pypose vs GTSAM")
    ap.add_argument("--windows", type=int, default=1000)
    ap.add_argument("--samples", type=int, default=200)
    ap.add_argument("--dt", type=float, default=0.005)
    ap.add_argument("--dtypes", default="float64,float32")
    ap.add_argument("--target", type=float, default=20.0, help="seconds of interleaved sampling for (a), per dtype")
    ap.add_argument("--min-rounds", type=int, default=5)
    ap.add_argument("--max-rounds", type=int, default=100)
    ap.add_argument("--threads", type=int, default=None, help="torch.set_num_threads(N)")
    ap.add_argument("--wait-idle", type=float, default=0.0, metavar="SECONDS",
                    help="first wait up to SECONDS for the 1-min load average to drop below 0.5")
    ap.add_argument("--out-dir", type=Path, default=_HERE / "results")
    ap.add_argument("--device", default="cpu",
                    help="cpu or cuda[:i] for torchsgal and pypose (GTSAM always runs on the CPU; default cpu)")
    ap.add_argument("--quick", action="store_true", help="100 windows, 2 rounds, no result files")
    ap.add_argument("--stream-calls", type=int, default=1000, help="(c): samples per streaming run")
    ap.add_argument("--stream-batch-calls", type=int, default=50, help="(c): calls of the 1,000-IMU run")
    ap.add_argument("--stream-target", type=float, default=4.0, help="(c): seconds of sampling per case group")
    ap.add_argument("--no-batch-sections", action="store_true",
                    help="skip (a) and (b) (the batched windows), run (c) only")
    args = ap.parse_args(argv)
    device = resolve_device(args.device)
    cuda = device.type == "cuda"
    if args.quick:
        args.windows, args.target, args.min_rounds = 100, 0.0, 2
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    wait_for_idle(args.wait_idle)
    mods, missing = import_peers()
    # where each method runs, written next to its name in the tables (CUDA runs only); the
    # accuracy of pypose is computed on the CPU (peers.pypose_predict keeps its module there)
    args.labels = {"torchsgal": f"torchsgal [{device}, plain path]", "pypose": f"pypose [{device}]",
                   "GTSAM": "GTSAM [CPU, C++]"} if cuda else {}
    args.accuracy_labels = dict(args.labels, pypose="pypose [CPU]") if cuda else {}

    t_start = time.perf_counter()
    env = environment(
        "bench_imu.py", argv,
        pypose=(getattr(mods["pypose"], "__version__", None) if mods["pypose"] is not None
                else f"not importable ({missing['pypose']})"),
        gtsam=(dist_version("gtsam") if mods["gtsam"] is not None
               else f"not importable ({missing['gtsam']})"),
        windows=args.windows,
        samples=args.samples,
        dt=args.dt,
        noise_densities=f"gyro {SIGMA_G} rad/s/sqrt(Hz), accelerometer {SIGMA_A} m/s^2/sqrt(Hz) (isotropic)",
    )
    if cuda:
        env.update(
            device=str(device), device_name=device_name(device), torch_cuda=torch.version.cuda,
            placement=(f"torchsgal on {device} (the plain batched path, _integrate: the in-place blocked "
                       f"fast path is CPU-only); pypose on {device}; GTSAM on the CPU (C++, Python loop "
                       "over windows); accuracy: torchsgal on the device, pypose and GTSAM on the CPU"),
            timing="interleaved rounds, the CUDA device synchronised before and after every timed call",
        )
    where = f"{env['device_name']} ({device}), host {cpu_model()}" if cuda else env["cpu_model"]
    log(f"torch {env['torch']} | pypose {env['pypose']} | gtsam {env['gtsam']} | {where} | "
        f"threads {env['torch_num_threads']} | {args.windows} x {args.samples}")
    res = {"accuracy": {}, "timing": {}} if args.no_batch_sections else run(args, device, mods)
    if not cuda:
        res["streaming"] = streaming(args, mods)
    env["wall_s"] = round(time.perf_counter() - t_start, 1)
    env["loadavg_at_end"] = loadavg()
    body = (tables(res, args) if res["timing"] else []) + stream_tables(res.get("streaming", {}), args)
    ver = verdict(res, missing) if res["timing"] else []
    print("\n" + "\n".join(body))
    print("\n".join(ver))
    log(f"wall {env['wall_s']} s")
    if not args.quick:
        md = [f"# IMU preintegration benchmark: {args.windows:,} windows x {args.samples} samples "
              f"({where}, {env['date']})", "", "| | |", "|---|---|"]
        md += [f"| {k} | {v} |" for k, v in env.items()]
        md += ["", __doc__.split("Usage::")[0].split("\n", 2)[2].strip(), ""]
        md += [f"NOTE: {k} is not importable ({v}): its peer cases were not run." for k, v in missing.items()]
        md += [""] * bool(missing) + body
        md += ["## targets", ""] + ver + [""]
        stem = f"imu_{device.type}"
        args.out_dir.mkdir(parents=True, exist_ok=True)
        out = {"env": env, "results": res}
        if missing:
            out["peers_not_available"] = missing
        (args.out_dir / f"{stem}.json").write_text(json.dumps(out, indent=2) + "\n")
        (args.out_dir / f"{stem}.md").write_text("\n".join(md))
        log(f"wrote {args.out_dir / (stem + '.json')} and {args.out_dir / (stem + '.md')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
