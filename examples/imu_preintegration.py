#!/usr/bin/env python
"""Galilean IMU preintegration against GTSAM and pypose on the same IMU streams.

A body follows a smooth trajectory with analytic ground truth (``SinusoidalTrajectory``:
sinusoidal rotation vector and position, gravity 9.80665 m/s^2, z-up).  Its gyro and
accelerometer are sampled every dt, each sample held over its interval, and three
preintegrators predict the state 1 s later from the true state at the window's start:

* torchsgal   ``torchsgal.imu.preintegrate(...).predict(X0, g)`` (the exact SGal(3) product);
* GTSAM       ``PreintegratedImuMeasurements`` (``PreintegrationParams.MakeSharedU``) + ``predict``;
* pypose      ``pp.module.IMUPreintegrator`` (batched, ``init_state`` = X0).

Two sampling schemes: ``midpoint`` (each sample taken at the middle of its interval) and
``left`` (at its start).  The table reports the worst end-state error over ``--windows``
windows: rotation [rad], velocity [m/s], position [m].  On midpoint samples the exact
increment is second order in dt and the peers first order; on left samples the sampling
error dominates and all three are first order.

It also runs a Monte Carlo of noisy streams (``--runs``) and reports the mean NEES of the
increment's right-perturbation error under the predicted covariance, with the chi-square 95%
band, and dead-reckons ``--chain`` consecutive 0.25 s windows to plot a trajectory.

Writes to ``--out`` (default examples/output/): imu_accuracy.md (the table, also printed),
imu_error_vs_dt.png, imu_trajectory.png.

Usage::

    python examples/imu_preintegration.py
    python examples/imu_preintegration.py --dts 0.02 0.01 --runs 100 --out /tmp/imu
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
import scipy.stats
import torch

_HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(_HERE.parent))  # run against the checkout this script lives in

from _cli import int_at_least, output_folder  # noqa: E402

from torchsgal import SGal3  # noqa: E402
from torchsgal.imu import (  # noqa: E402
    gravity_vector,
    increment_tangents,
    peers,  # noqa: E402
    preintegrate,
    window_product,
)
from torchsgal.imu.trajectory import SinusoidalTrajectory  # noqa: E402

DTYPE = torch.float64
G = 9.80665
METHODS = ("torchsgal", "GTSAM", "pypose")


def end_errors(pred: SGal3, truth: SGal3) -> np.ndarray:
    """Worst rotation [rad], velocity [m/s] and position [m] error over the batch."""
    rot = pred.between(truth).log()[..., 6:9].norm(dim=-1).max()
    vel = (pred.velocity() - truth.velocity()).norm(dim=-1).max()
    pos = (pred.position() - truth.position()).norm(dim=-1).max()
    return np.array([float(rot), float(vel), float(pos)])


def predict_all(traj, X0, g, h, sampling, window=1.0):
    gyro, acc, dt = traj.stream(X0.time(), window, h, g, sample=sampling)
    params = peers.gtsam_params("z_up", G)
    return {
        "torchsgal": preintegrate(gyro, acc, dt, covariance=False, bias_jacobian=False).predict(X0, g),
        "GTSAM": peers.gtsam_predict(peers.gtsam_preintegrate(gyro, acc, dt, params), X0),
        "pypose": peers.pypose_predict(gyro, acc, dt, X0, "z_up", G),
    }


def accuracy(traj, g, dts, windows):
    starts = torch.linspace(0.0, 5.0, windows, dtype=DTYPE)
    X0, X1 = traj.state(starts), traj.state(starts + 1.0)
    res = {}
    for sampling in ("midpoint", "left"):
        res[sampling] = {m: [] for m in METHODS}
        for h in dts:
            for m, pred in predict_all(traj, X0, g, h, sampling).items():
                res[sampling][m].append(end_errors(pred, X1))
        res[sampling] = {m: np.array(v) for m, v in res[sampling].items()}
    return res


def markdown_table(res, dts) -> str:
    lines = []
    for sampling, by_method in res.items():
        lines += [f"**{sampling} samples** (worst over the windows; rotation rad, velocity m/s, position m)", ""]
        head = "| dt [s] | " + " | ".join(f"{m} rot | {m} vel | {m} pos" for m in METHODS) + " |"
        lines += [head, "|" + "---|" * (1 + 3 * len(METHODS))]
        for i, h in enumerate(dts):
            cells = [f"{by_method[m][i][j]:.2e}" for m in METHODS for j in range(3)]
            lines.append(f"| {h:g} | " + " | ".join(cells) + " |")
        orders = []
        for m in METHODS:
            e = by_method[m][:, 2]
            if len(dts) > 1:
                orders.append(f"{m} {np.polyfit(np.log(dts), np.log(e), 1)[0]:.2f}")
        lines += ["", "Observed order of the position error in dt: " + ", ".join(orders), ""]
    return "\n".join(lines)


def nees_monte_carlo(traj, g, runs, h, time_noise, seed=0):
    """Mean NEES of the increment over ``runs`` noisy copies of one window's stream."""
    s_g, s_a = 0.01, 0.1  # rad/s/sqrt(Hz), m/s^2/sqrt(Hz): a consumer-grade IMU, exaggerated
    gyro, acc, dt = traj.stream(torch.tensor([0.5], dtype=DTYPE), 1.0, h, g)
    r = preintegrate(gyro, acc, dt, gyro_noise_density=s_g, acc_noise_density=s_a, time_noise_density=time_noise)
    K = dt.shape[-1]
    gen = torch.Generator().manual_seed(seed)
    root = dt.sqrt().unsqueeze(-1)
    n_g = s_g / root * torch.randn(runs, K, 3, generator=gen, dtype=DTYPE)
    n_a = s_a / root * torch.randn(runs, K, 3, generator=gen, dtype=DTYPE)
    xi = increment_tangents(gyro - n_g, acc - n_a, dt.expand(runs, K))
    n_t = time_noise * dt.sqrt() * torch.randn(runs, K, generator=gen, dtype=DTYPE)
    xi = torch.cat((xi[..., :9], xi[..., 9:] + n_t.unsqueeze(-1)), dim=-1)
    true = SGal3(window_product(SGal3.exp(xi).as_matrix()))
    eps = true.rminus(r.delta.expand(runs))
    d = 10 if time_noise > 0 else 9
    P = r.covariance[0, :d, :d]
    nees = (eps[:, :d] * torch.linalg.solve(P, eps[:, :d].T).T).sum(-1)
    lo, hi = scipy.stats.chi2.ppf([0.025, 0.975], runs * d) / runs
    return float(nees.mean()), d, lo, hi


def chained(traj, g, h, n_windows, window=0.25):
    """Dead reckoning over consecutive windows, each method from its own estimate."""
    t = torch.tensor([0.0], dtype=DTYPE)
    est = {m: traj.state(t) for m in METHODS}
    path = {m: [est[m].position()[0].numpy()] for m in METHODS}
    params = peers.gtsam_params("z_up", G)
    for _ in range(n_windows):
        gyro, acc, dt = traj.stream(est["torchsgal"].time(), window, h, g)
        pre = preintegrate(gyro, acc, dt, covariance=False, bias_jacobian=False)
        est["torchsgal"] = pre.predict(est["torchsgal"], g)
        est["GTSAM"] = peers.gtsam_predict(peers.gtsam_preintegrate(gyro, acc, dt, params), est["GTSAM"])
        est["pypose"] = peers.pypose_predict(gyro, acc, dt, est["pypose"], "z_up", G)
        for m in METHODS:
            path[m].append(est[m].position()[0].numpy())
    t_end = est["torchsgal"].time()
    truth = traj.state(torch.linspace(0.0, float(t_end), 400, dtype=DTYPE)).position().numpy()
    final = {m: end_errors(est[m], traj.state(t_end))[2] for m in METHODS}
    return {m: np.array(p) for m, p in path.items()}, truth, final


def plots(res, dts, path, truth, out: Path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharey=True)
    for ax, (sampling, by_method) in zip(axes, res.items()):
        for m, mk in zip(METHODS, ("o-", "s--", "^:")):
            ax.loglog(dts, by_method[m][:, 2], mk, label=m)
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_title(f"{sampling} samples")
        ax.set_xlabel("dt [s]")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel("position error after 1 s [m]")
    axes[0].legend()
    fig.tight_layout()
    fig.savefig(out / "imu_error_vs_dt.png", dpi=110)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(6, 5))
    ax.plot(truth[:, 0], truth[:, 1], "k-", lw=1, label="truth")
    for m, mk in zip(METHODS, ("o-", "s--", "^:")):
        ax.plot(path[m][:, 0], path[m][:, 1], mk, ms=3, lw=1, label=m)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title("dead reckoning over 0.25 s windows, dt = 0.01 s")
    ax.axis("equal")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "imu_trajectory.png", dpi=110)
    plt.close(fig)


def sample_interval(text: str) -> float:
    """An argparse type: a sample interval dt [s], finite, > 0 and dividing the 1 s window."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a finite number > 0, got {text!r}")
    k = round(1.0 / value)
    if k < 1 or abs(k * value - 1.0) > 1e-9:
        raise argparse.ArgumentTypeError(f"expected a dt that divides the 1 s window, got {text!r}")
    return value


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=_HERE / "output", help="output folder")
    ap.add_argument("--dts", type=sample_interval, nargs="+", default=[0.04, 0.02, 0.01, 0.005, 0.0025, 0.00125],
                    help="sample intervals [s], each dividing the 1 s window")
    ap.add_argument("--windows", type=int_at_least(1), default=16, help="windows (start times) per dt")
    ap.add_argument("--runs", type=int_at_least(1), default=2000, help="Monte Carlo runs for the NEES")
    ap.add_argument("--chain", type=int_at_least(1), default=32,
                    help="0.25 s windows dead-reckoned in the trajectory plot")
    ap.add_argument("--no-plot", action="store_true", help="skip the figures")
    args = ap.parse_args(argv)
    output_folder(ap, args.out)

    traj = SinusoidalTrajectory()
    g = gravity_vector("z_up", G, dtype=DTYPE)
    res = accuracy(traj, g, args.dts, args.windows)
    table = markdown_table(res, args.dts)

    nees_lines = ["**NEES of the increment** (Monte Carlo, 1 s window at dt = 0.01 s, "
                  "gyro 0.01 rad/s/sqrt(Hz), accelerometer 0.1 m/s^2/sqrt(Hz))", "",
                  "| clock noise [s/s/sqrt(Hz)] | dof | runs | mean NEES | chi-square 95% band | inside |",
                  "|---|---|---|---|---|---|"]
    for tn in (0.0, 1e-3):
        mean, d, lo, hi = nees_monte_carlo(traj, g, args.runs, 0.01, tn)
        nees_lines.append(f"| {tn:g} | {d} | {args.runs} | {mean:.3f} | [{lo:.3f}, {hi:.3f}] | {lo < mean < hi} |")

    path, truth, drift = chained(traj, g, 0.01, args.chain)
    drift_line = (f"Dead reckoning over {args.chain} windows of 0.25 s (dt = 0.01 s, midpoint samples), final "
                  "position error [m]: " + ", ".join(f"{m} {drift[m]:.2e}" for m in METHODS))
    report = "\n".join(["# IMU preintegration: error versus dt", "", table, "\n".join(nees_lines), "", drift_line, ""])
    (args.out / "imu_accuracy.md").write_text(report)
    print(report)
    if not args.no_plot:
        plots(res, args.dts, path, truth, args.out)
        print(f"figures: {args.out / 'imu_error_vs_dt.png'}, {args.out / 'imu_trajectory.png'}")


if __name__ == "__main__":
    main()
