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

Usage::

    python benchmarks/bench_imu.py                 # full run, writes benchmarks/results/imu_cpu.*
    python benchmarks/bench_imu.py --quick         # 100 windows, few rounds, no files
    python benchmarks/bench_imu.py --threads 1 --wait-idle 60
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
from _timing import dist_version, environment, interleaved, loadavg, paired_ratio, wait_for_idle  # noqa: E402

from torchsgal.imu import gravity_vector, preintegrate  # noqa: E402
from torchsgal.imu import peers  # noqa: E402
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


def accuracy(traj, g, t0, gyro, acc, h) -> dict:
    X0, X1 = traj.state(t0), traj.state(t0 + h.sum(-1))
    preds = {
        "torchsgal": preintegrate(gyro, acc, h, covariance=False, bias_jacobian=False).predict(X0, g),
        "pypose": peers.pypose_predict(gyro, acc, h, X0, "z_up", G),
        "GTSAM": peers.gtsam_predict(peers.gtsam_preintegrate(gyro, acc, h, peers.gtsam_params("z_up", G)), X0),
    }
    out = {}
    for name, P in preds.items():
        pos = (P.position() - X1.position()).norm(dim=-1)
        vel = (P.velocity() - X1.velocity()).norm(dim=-1)
        rot = P.between(X1).log()[..., 6:9].norm(dim=-1)
        out[name] = {"pos_median_m": float(pos.median()), "pos_max_m": float(pos.max()),
                     "vel_median_mps": float(vel.median()), "vel_max_mps": float(vel.max()),
                     "rot_median_rad": float(rot.median()), "rot_max_rad": float(rot.max())}
    return out


def run(args) -> dict:
    import gtsam
    import pypose as pp

    traj, g, t0, gyro64, acc64, h64 = build(args.windows, args.samples, args.dt)
    log("accuracy on the benchmark batch ...")
    acc_res = accuracy(traj, g, t0, gyro64, acc64, h64)
    params = peers.gtsam_params("z_up", G, SIGMA_G, SIGMA_A)
    g_np, a_np, h_np = gyro64.numpy(), acc64.numpy(), h64.numpy()
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
        gyro, acc, h = gyro64.to(dtype), acc64.to(dtype), h64.to(dtype)
        hh = h.unsqueeze(-1)
        pp_cov = pp.module.IMUPreintegrator(gravity=G, gyro_cov=SIGMA_G**2 / args.dt, acc_cov=SIGMA_A**2 / args.dt,
                                            prop_cov=True, reset=True).to(dtype)
        pp_inc = pp.module.IMUPreintegrator(gravity=G, prop_cov=False, reset=True).to(dtype)
        full = {
            "torchsgal": lambda: preintegrate(gyro, acc, h, gyro_noise_density=SIGMA_G, acc_noise_density=SIGMA_A),
            "pypose": lambda: pp_cov(hh, gyro, acc),
            "GTSAM": gtsam_loop,
        }
        inc = {
            "torchsgal": lambda: preintegrate(gyro, acc, h, covariance=False, bias_jacobian=False),
            "pypose": lambda: pp_inc(hh, gyro, acc),
        }
        with torch.no_grad():
            log(f"[{name}] (a) increment + covariance ...")
            st_a, t_a, load_a = interleaved(full, target_s=args.target, min_rounds=args.min_rounds,
                                            max_rounds=args.max_rounds)
            log(f"[{name}] (b) increment only ...")
            st_b, t_b, load_b = interleaved(inc, target_s=args.target / 2, min_rounds=args.min_rounds,
                                            max_rounds=args.max_rounds)
        gtsam_median = st_a["GTSAM"]["median_s"]
        sections[name] = {
            "increment_covariance": st_a,
            "increment_only": st_b,
            "foreign_cpu": {"increment_covariance": load_a, "increment_only": load_b},
            "ratios": {
                "(a) pypose / torchsgal": paired_ratio(t_a, "pypose", "torchsgal"),
                "(a) GTSAM / torchsgal": paired_ratio(t_a, "GTSAM", "torchsgal"),
                "(b) pypose / torchsgal": paired_ratio(t_b, "pypose", "torchsgal"),
                "(b) GTSAM (a) median / torchsgal (b) median": gtsam_median / st_b["torchsgal"]["median_s"],
            },
        }
    return {"accuracy": acc_res, "timing": sections}


def fmt_ms(s: float) -> str:
    return f"{s * 1e3:,.1f}"


def _pct(x) -> str:
    return "n/a" if x is None else f"{100 * x:.0f}%"


def tables(res: dict, args) -> list[str]:
    out = [f"## accuracy at equal dt ({args.windows:,} windows of {args.samples} samples, dt = {args.dt} s, "
           "midpoint samples, float64)", "",
           "| method | position median [m] | position max [m] | velocity max [m/s] | rotation max [rad] |",
           "|---|---:|---:|---:|---:|"]
    for m, a in res["accuracy"].items():
        out.append(f"| {m} | {a['pos_median_m']:.2e} | {a['pos_max_m']:.2e} | {a['vel_max_mps']:.2e} "
                   f"| {a['rot_max_rad']:.2e} |")
    out.append("")
    for dtype, sec in res["timing"].items():
        for key, title in (("increment_covariance", "(a) increment + covariance (+ bias Jacobians)"),
                           ("increment_only", "(b) increment only")):
            out += [f"### {dtype}: {title}  (foreign CPU load: {_pct(sec['foreign_cpu'][key])})", "",
                    "| method | ms / batch (median) | min–max ms | µs / sample | rounds |", "|---|---:|---:|---:|---:|"]
            n = args.windows * args.samples
            for m, v in sec[key].items():
                out.append(f"| {m} | {fmt_ms(v['median_s'])} | {fmt_ms(v['min_s'])}–{fmt_ms(v['max_s'])} "
                           f"| {v['median_s'] / n * 1e6:.3f} | {v['rounds']} |")
            out.append("")
        out += [f"### {dtype}: speed-ups of torchsgal (> 1: torchsgal faster)", "", "| ratio | value |", "|---|---:|"]
        out += [f"| {k} | {v:.2f} |" for k, v in sec["ratios"].items()]
        out.append("")
    return out


def verdict(res: dict) -> list[str]:
    lines = []
    acc = res["accuracy"]
    better = all(acc["torchsgal"]["pos_max_m"] < acc[m]["pos_max_m"] for m in ("pypose", "GTSAM"))
    lines.append(f"- accuracy: torchsgal's worst position error {acc['torchsgal']['pos_max_m']:.2e} m vs "
                 f"pypose {acc['pypose']['pos_max_m']:.2e} m, GTSAM {acc['GTSAM']['pos_max_m']:.2e} m "
                 f"(better than both: {'met' if better else 'NOT met'})")
    for dtype, sec in res["timing"].items():
        r = sec["ratios"]
        lines.append(
            f"- {dtype}: (a) {r['(a) pypose / torchsgal']:.2f}x pypose, {r['(a) GTSAM / torchsgal']:.2f}x GTSAM; "
            f"(b) {r['(b) pypose / torchsgal']:.2f}x pypose, "
            f"{r['(b) GTSAM (a) median / torchsgal (b) median']:.2f}x GTSAM. Targets: >= 1x pypose "
            f"({'met' if min(r['(a) pypose / torchsgal'], r['(b) pypose / torchsgal']) >= 1 else 'NOT met'}), "
            f">= 10x GTSAM ((a) {'met' if r['(a) GTSAM / torchsgal'] >= 10 else 'NOT met'}, "
            f"(b) {'met' if r['(b) GTSAM (a) median / torchsgal (b) median'] >= 10 else 'NOT met'})")
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
    ap.add_argument("--quick", action="store_true", help="100 windows, 2 rounds, no result files")
    args = ap.parse_args(argv)
    if args.quick:
        args.windows, args.target, args.min_rounds = 100, 0.0, 2
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    wait_for_idle(args.wait_idle)
    import gtsam  # noqa: F401
    import pypose

    t_start = time.perf_counter()
    env = environment(
        "bench_imu.py", argv,
        pypose=getattr(pypose, "__version__", None),
        gtsam=dist_version("gtsam"),
        windows=args.windows,
        samples=args.samples,
        dt=args.dt,
        noise_densities=f"gyro {SIGMA_G} rad/s/sqrt(Hz), accelerometer {SIGMA_A} m/s^2/sqrt(Hz) (isotropic)",
    )
    log(f"torch {env['torch']} | pypose {env['pypose']} | gtsam {env['gtsam']} | {env['cpu_model']} | "
        f"threads {env['torch_num_threads']} | {args.windows} x {args.samples}")
    res = run(args)
    env["wall_s"] = round(time.perf_counter() - t_start, 1)
    env["loadavg_at_end"] = loadavg()
    body = tables(res, args)
    ver = verdict(res)
    print("\n" + "\n".join(body))
    print("\n".join(ver))
    log(f"wall {env['wall_s']} s")
    if not args.quick:
        md = [f"# IMU preintegration benchmark: {args.windows:,} windows x {args.samples} samples "
              f"({env['cpu_model']}, {env['date']})", "", "| | |", "|---|---|"]
        md += [f"| {k} | {v} |" for k, v in env.items()]
        md += ["", __doc__.split("Usage::")[0].split("\n", 2)[2].strip(), ""] + body
        md += ["## targets", ""] + ver + [""]
        args.out_dir.mkdir(parents=True, exist_ok=True)
        (args.out_dir / "imu_cpu.json").write_text(json.dumps({"env": env, "results": res}, indent=2) + "\n")
        (args.out_dir / "imu_cpu.md").write_text("\n".join(md))
        log(f"wrote {args.out_dir / 'imu_cpu.json'} and {args.out_dir / 'imu_cpu.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
