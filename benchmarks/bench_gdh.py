#!/usr/bin/env python
"""GDH chain benchmark: the 7-DoF iiwa, batched, against pytorch-kinematics and autograd.

One batch of ``--n`` (default 10,000) random configurations (q, qdot, qddot) of
``torchsgal.kinematics.iiwa7``, in float64 and float32.  What is timed (whole batch, milliseconds
per call; ns per configuration alongside):

(a) pose + end-effector velocity in the base frame

* ``GDH forward``      ``chain.forward(q, qdot)`` -> pose (4x4), dp/dt, w;
* ``pk FK + J qdot``   pytorch-kinematics ``forward_kinematics(q).get_matrix()`` plus
                       ``jacobian(q) @ qdot`` (two kinematic passes; the baseline of the brief);
* ``pk J(ret_pose) qdot``  ``jacobian(q, ret_eef_pose=True) @ qdot``: pk's own fused call (one
                       forward pass gives both), the strongest pk baseline;
* for reference, pose only: ``GDH forward(q)`` and ``pk FK``.

(b) end-effector acceleration (d2p/dt2, dw/dt)

* ``GDH acceleration`` ``chain.acceleration(q, qdot, qddot)`` (closed form);
* ``jvp(GDH velocity)``  ``torch.func.jvp`` of (q, qdot) -> [dp/dt, w] (``chain.forward``) along
                       (qdot, qddot): forward-mode autograd gives the same quantity;
* ``jvp(pk J qdot)``   the same through pk's ``jacobian(q) @ qdot`` (pk has no Jacobian
                       time-derivative, so autograd is the only way to get it from pk).

Timing method: the cases of a section are *interleaved* (round-robin, one call of each case per
round, order rotated every round) so that all cases see the same machine load; two untimed
warm-up calls per case; Python's GC is off while the clock runs; the figure is the median over
rounds, and each speed-up is the median over rounds of the per-round ratio.  The share of the
machine's CPU used by other processes during each section is recorded (``foreign_cpu``): on a
2-core machine any foreign load inflates multi-threaded torch timings.

Agreement on the benchmark batch (max abs difference) is recorded: GDH vs pk pose and velocity,
GDH acceleration vs both jvp's.

Usage::

    python benchmarks/bench_gdh.py                  # full run (~1-2 min on 2 cores)
    python benchmarks/bench_gdh.py --quick          # smoke run, n=1000, few rounds, no files
    python benchmarks/bench_gdh.py --wait-idle 60 --threads 2
    python benchmarks/bench_gdh.py --device cuda    # writes benchmarks/results/gdh_cuda.*

Devices: ``--device cuda[:i]`` builds both chains and the batch on that GPU and synchronises the
device before and after every timed call; the result files are ``gdh_cuda.*``.  When
pytorch-kinematics is not importable its cases, ratios and agreement rows are left out with a
note, and the GDH cases (forward, acceleration, jvp of GDH) are timed alone.
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
from _timing import (cpu_model, device_name, dist_version, environment, interleaved, loadavg,  # noqa: E402
                     paired_ratio, resolve_device, wait_for_idle)

from torchsgal.kinematics import iiwa7  # noqa: E402


def log(msg: str) -> None:
    print(msg, flush=True)


# -------------------------------------------------------------------------- cases
def build(dtype: torch.dtype, n: int, seed: int, device: torch.device, with_pk: bool):
    from torchsgal.kinematics.pk_interop import build_pk_chain

    chain = iiwa7(dtype=dtype, device=device)
    pk_chain = build_pk_chain(chain.a, chain.alpha, chain.d, chain.theta_offset,
                              chain.joint_types, dtype=dtype, device=device) if with_pk else None
    g = torch.Generator().manual_seed(seed)
    # joint angles uniform in (-pi, pi); rates and accelerations standard normal (drawn on the
    # CPU, so that the batch is the same on every device)
    kw = dict(dtype=dtype, device=device)
    q = ((torch.rand(n, 7, generator=g, dtype=torch.float64) * 2 - 1) * torch.pi).to(**kw)
    qd = torch.randn(n, 7, generator=g, dtype=torch.float64).to(**kw)
    qdd = torch.randn(n, 7, generator=g, dtype=torch.float64).to(**kw)
    return chain, pk_chain, q, qd, qdd


def make_functions(chain, pk_chain, q, qd, qdd):
    def gdh_forward():
        s = chain.forward(q, qd)
        return s.pose, s.linear_velocity, s.angular_velocity

    def gdh_pose():
        return chain.forward(q).pose

    def pk_fk_jac():
        T = pk_chain.forward_kinematics(q).get_matrix()
        twist = (pk_chain.jacobian(q) @ qd.unsqueeze(-1)).squeeze(-1)
        return T, twist[:, :3], twist[:, 3:]

    def pk_jac_fused():
        J, T = pk_chain.jacobian(q, ret_eef_pose=True)
        twist = (J @ qd.unsqueeze(-1)).squeeze(-1)
        return T, twist[:, :3], twist[:, 3:]

    def pk_fk():
        return pk_chain.forward_kinematics(q).get_matrix()

    def gdh_velocity(q_, qd_):
        s = chain.forward(q_, qd_)
        return torch.cat((s.linear_velocity, s.angular_velocity), dim=-1)

    def pk_velocity(q_, qd_):
        return (pk_chain.jacobian(q_) @ qd_.unsqueeze(-1)).squeeze(-1)

    def gdh_acc():
        return chain.acceleration(q, qd, qdd)

    def jvp_gdh():
        return torch.func.jvp(gdh_velocity, (q, qd), (qd, qdd))[1]

    def jvp_pk():
        return torch.func.jvp(pk_velocity, (q, qd), (qd, qdd))[1]

    sec_a = {
        "GDH forward(q, qdot)": gdh_forward,
        "pk FK + J(q) qdot": pk_fk_jac,
        "pk J(q, ret_eef_pose) qdot": pk_jac_fused,
        "GDH forward(q) [pose only]": gdh_pose,
        "pk FK [pose only]": pk_fk,
    }
    sec_b = {
        "GDH acceleration(q, qdot, qddot)": gdh_acc,
        "jvp(GDH velocity)": jvp_gdh,
        "jvp(pk J(q) qdot)": jvp_pk,
    }
    if pk_chain is None:  # pytorch-kinematics not available: the GDH cases alone
        sec_a = {k: v for k, v in sec_a.items() if "pk" not in k}
        sec_b = {k: v for k, v in sec_b.items() if "pk" not in k}
    return sec_a, sec_b


def agreement(sec_a: dict, sec_b: dict) -> dict:
    m = lambda x, y: (x - y).abs().max().item()  # noqa: E731
    with torch.no_grad():
        T_g, v_g, w_g = sec_a["GDH forward(q, qdot)"]()
    lin, ang = sec_b["GDH acceleration(q, qdot, qddot)"]()
    jg = sec_b["jvp(GDH velocity)"]()
    if "pk FK + J(q) qdot" not in sec_a:  # no pytorch-kinematics
        return {
            "linear acceleration GDH vs jvp(GDH)": m(lin, jg[:, :3]),
            "angular acceleration GDH vs jvp(GDH)": m(ang, jg[:, 3:]),
            "scale: max |dp/dt|, |w|": [v_g.abs().max().item(), w_g.abs().max().item()],
            "scale: max |d2p/dt2|, |dw/dt|": [lin.abs().max().item(), ang.abs().max().item()],
        }
    with torch.no_grad():
        T_p, v_p, w_p = sec_a["pk FK + J(q) qdot"]()
        T_f, v_f, w_f = sec_a["pk J(q, ret_eef_pose) qdot"]()
    jp = sec_b["jvp(pk J(q) qdot)"]()
    return {
        "pose (4x4) GDH vs pk FK": m(T_g, T_p),
        "position GDH vs pk FK": m(T_g[:, :3, 3], T_p[:, :3, 3]),
        "rotation GDH vs pk FK": m(T_g[:, :3, :3], T_p[:, :3, :3]),
        "linear velocity GDH vs pk J qdot": m(v_g, v_p),
        "angular velocity GDH vs pk J qdot": m(w_g, w_p),
        "pose GDH vs pk J(ret_eef_pose)": m(T_g, T_f),
        "twist GDH vs pk J(ret_eef_pose) qdot": max(m(v_g, v_f), m(w_g, w_f)),
        "linear acceleration GDH vs jvp(GDH)": m(lin, jg[:, :3]),
        "angular acceleration GDH vs jvp(GDH)": m(ang, jg[:, 3:]),
        "linear acceleration GDH vs jvp(pk)": m(lin, jp[:, :3]),
        "angular acceleration GDH vs jvp(pk)": m(ang, jp[:, 3:]),
        "scale: max |dp/dt|, |w|": [v_g.abs().max().item(), w_g.abs().max().item()],
        "scale: max |d2p/dt2|, |dw/dt|": [lin.abs().max().item(), ang.abs().max().item()],
    }


# --------------------------------------------------------------------------- main
def run_dtype(dtype, args, device, with_pk) -> dict:
    name = str(dtype).replace("torch.", "")
    chain, pk_chain, q, qd, qdd = build(dtype, args.n, args.seed, device, with_pk)
    sec_a, sec_b = make_functions(chain, pk_chain, q, qd, qdd)
    log(f"\n[{name}] agreement ...")
    agree = agreement(sec_a, sec_b)
    log(f"[{name}] (a) pose + velocity ...")
    st_a, t_a, load_a = interleaved(sec_a, target_s=args.target_a, min_rounds=args.min_rounds,
                                    max_rounds=args.max_rounds, device=device)
    log(f"[{name}] (b) acceleration ...")
    st_b, t_b, load_b = interleaved(sec_b, target_s=args.target_b,
                                    min_rounds=max(3, args.min_rounds // 2),
                                    max_rounds=args.max_rounds, device=device)
    gdh, acc = "GDH forward(q, qdot)", "GDH acceleration(q, qdot, qddot)"
    if with_pk:
        ratios = {
            "pk FK + J qdot / GDH forward": paired_ratio(t_a, "pk FK + J(q) qdot", gdh),
            "pk J(ret_eef_pose) qdot / GDH forward": paired_ratio(t_a, "pk J(q, ret_eef_pose) qdot", gdh),
            "pk FK / GDH forward [pose only]": paired_ratio(t_a, "pk FK [pose only]",
                                                            "GDH forward(q) [pose only]"),
            "jvp(GDH velocity) / GDH acceleration": paired_ratio(t_b, "jvp(GDH velocity)", acc),
            "jvp(pk J qdot) / GDH acceleration": paired_ratio(t_b, "jvp(pk J(q) qdot)", acc),
        }
    else:
        ratios = {"jvp(GDH velocity) / GDH acceleration": paired_ratio(t_b, "jvp(GDH velocity)", acc)}
    return {
        "dtype": name,
        "n": args.n,
        "pose_velocity": st_a,
        "acceleration": st_b,
        "foreign_cpu": {"pose_velocity": load_a, "acceleration": load_b},
        "speedup_ratios": ratios,
        "agreement_max_abs": agree,
    }


def fmt_ms(s: float) -> str:
    return f"{s * 1e3:.2f}"


def table_md(res: dict) -> list[str]:
    n = res["n"]
    out = [f"## iiwa7, {res['dtype']}, batch {n:,}", ""]
    for sec, title, ref in (
        ("pose_velocity", "(a) pose + end-effector velocity", "GDH forward(q, qdot)"),
        ("acceleration", "(b) end-effector acceleration", "GDH acceleration(q, qdot, qddot)"),
    ):
        out += [f"### {title}  (foreign CPU load during the section: "
                f"{_pct(res['foreign_cpu'][sec])})", "",
                "| case | ms / batch (median) | min–max ms | ns / config | time vs GDH | rounds |",
                "|---|---:|---:|---:|---:|---:|"]
        base = res[sec][ref]["median_s"]
        for k, v in res[sec].items():
            rel = "1 (ref)" if k == ref else f"{v['median_s'] / base:.2f}x"
            if "pose only" in k:
                rel = "–"
            out.append(f"| {k} | {fmt_ms(v['median_s'])} | {fmt_ms(v['min_s'])}–{fmt_ms(v['max_s'])} "
                       f"| {v['median_s'] / n * 1e9:,.0f} | {rel} | {v['rounds']} |")
        out.append("")
    out += ["### speed-ups of GDH (median over rounds of the per-round ratio; > 1: GDH faster)", "",
            "| ratio | value |", "|---|---:|"]
    out += [f"| {k} | {v:.2f} |" for k, v in res["speedup_ratios"].items()]
    out += ["", "### agreement on the benchmark batch (max abs difference)", "",
            "| quantity | max abs diff |", "|---|---:|"]
    for k, v in res["agreement_max_abs"].items():
        val = ", ".join(f"{x:.3g}" for x in v) if isinstance(v, list) else f"{v:.3e}"
        out.append(f"| {k} | {val} |")
    out.append("")
    return out


def _pct(x) -> str:
    return "n/a" if x is None else f"{100 * x:.0f}%"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="GDH chain (iiwa7) vs pytorch-kinematics and autograd")
    ap.add_argument("--n", type=int, default=10_000, help="batch of configurations")
    ap.add_argument("--dtypes", default="float64,float32")
    ap.add_argument("--target-a", type=float, default=12.0,
                    help="seconds of interleaved sampling for (a), per dtype")
    ap.add_argument("--target-b", type=float, default=15.0,
                    help="seconds of interleaved sampling for (b), per dtype")
    ap.add_argument("--min-rounds", type=int, default=10)
    ap.add_argument("--max-rounds", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=None,
                    help="torch.set_num_threads(N) (default: torch's default)")
    ap.add_argument("--wait-idle", type=float, default=0.0, metavar="SECONDS",
                    help="first wait up to SECONDS for the 1-min load average to drop below 0.5")
    ap.add_argument("--out-dir", type=Path, default=_HERE / "results")
    ap.add_argument("--device", default="cpu", help="cpu or cuda[:i] (default cpu)")
    ap.add_argument("--quick", action="store_true", help="n=1000, 3 rounds, no result files")
    args = ap.parse_args(argv)
    device = resolve_device(args.device)
    cuda = device.type == "cuda"
    if args.quick:
        args.n, args.target_a, args.target_b, args.min_rounds = 1000, 0.0, 0.0, 3
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    wait_for_idle(args.wait_idle)

    try:
        import pytorch_kinematics as pk
    except ImportError as e:
        pk, pk_missing = None, f"{type(e).__name__}: {e}"
        log(f"NOTE: pytorch-kinematics is not importable ({pk_missing}): its cases are skipped, "
            "GDH is timed alone")

    t_start = time.perf_counter()
    env = environment(
        "bench_gdh.py", argv,
        pytorch_kinematics=((getattr(pk, "__version__", None) or dist_version("pytorch-kinematics"))
                            if pk is not None else f"not importable ({pk_missing})"),
        robot="iiwa7 (KUKA LBR iiwa, 7 revolute joints, standard DH)",
        batch=args.n,
        method=("interleaved round-robin timing, 2 untimed warm-up calls per case, GC off, "
                "median over rounds; ratios are medians of per-round ratios; one process, "
                "same batch for every case"),
    )
    if cuda:
        env.update(device=str(device), device_name=device_name(device), torch_cuda=torch.version.cuda,
                   timing="the CUDA device synchronised before and after every timed call")
    where = f"{env['device_name']} ({device}), host {cpu_model()}" if cuda else env["cpu_model"]
    log(f"torch {env['torch']} | pk {env['pytorch_kinematics']} | {where} | "
        f"threads {env['torch_num_threads']} | n={args.n:,}")
    results = [run_dtype(getattr(torch, d.strip()), args, device, pk is not None)
               for d in args.dtypes.split(",")]
    env["wall_s"] = round(time.perf_counter() - t_start, 1)
    env["loadavg_at_end"] = loadavg()

    md = [f"# GDH chain benchmark: iiwa7, batch {args.n:,} ({where}, {env['date']})", "",
          "| | |", "|---|---|"]
    md += [f"| {k} | {v} |" for k, v in env.items()]
    md += ["", __doc__.split("Usage::")[0].split("\n", 2)[2].strip(), ""]
    if pk is None:
        md += [f"NOTE: pytorch-kinematics is not importable ({pk_missing}): its cases, ratios and "
               "agreement rows were not run.", ""]
    for res in results:
        md += table_md(res)
    verdict = []
    for res in results:
        if pk is None:
            verdict.append(f"- {res['dtype']}: not compared (pytorch-kinematics not importable).")
            continue
        r1 = res["speedup_ratios"]["pk FK + J qdot / GDH forward"]
        r2 = res["speedup_ratios"]["pk J(ret_eef_pose) qdot / GDH forward"]
        verdict.append(
            f"- {res['dtype']}: GDH pose+velocity is {r1:.2f}x faster than pk FK + J qdot "
            f"(target >= 2x: {'met' if r1 >= 2 else 'NOT met'}); {r2:.2f}x vs pk's fused "
            f"jacobian(ret_eef_pose=True) (no target: the issue's peer is FK + J qdot)."
        )
    md += ["## target: GDH at least 2x faster than pytorch-kinematics for pose + velocity", ""]
    md += verdict + [""]
    text = "\n".join(md)
    print("\n" + "\n".join(line for res in results for line in table_md(res)))
    print("\n".join(verdict))
    log(f"wall {env['wall_s']} s")
    if not args.quick:
        stem = f"gdh_{device.type}"
        args.out_dir.mkdir(parents=True, exist_ok=True)
        (args.out_dir / f"{stem}.json").write_text(
            json.dumps({"env": env, "results": results}, indent=2) + "\n")
        (args.out_dir / f"{stem}.md").write_text(text)
        log(f"wrote {args.out_dir / (stem + '.json')} and {args.out_dir / (stem + '.md')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
