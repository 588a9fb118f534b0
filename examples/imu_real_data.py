#!/usr/bin/env python
"""Preintegration of a real IMU recording with torchsgal and GTSAM.

The recording (``quadraped_imu_data.csv``: a legged robot's IMU at 400 Hz, a ROS
``sensor_msgs/Imu`` export with the attitude of the robot's own filter) is loaded with
``torchsgal.imu.data.load_ros_imu_csv`` and cut into windows of ``--window`` seconds.  Each
window is preintegrated by

* torchsgal ``preintegrate`` (the exact product for samples held over their intervals) and
  ``StreamingPreintegration`` fed one sample per call (the same increment);
* GTSAM ``PreintegratedImuMeasurements`` (a first-order scheme: its velocity and position
  differ from the exact increment by O(dt)).

The comparison shows (1) the differences to GTSAM are its discretisation error: splitting
every sample into two halves (the same held signal) leaves torchsgal's increment unchanged
(to rounding) and halves GTSAM's difference to it (rotation, velocity and position), and (2)
the attitude increment agrees with the recorded orientation up to gyro drift (the recorded
attitude comes from the robot's filter, which also uses the accelerometer).

Writes ``imu_real_data.png`` and ``imu_real_data.md`` to ``--out``.

Usage::

    python examples/imu_real_data.py --no-show
    python examples/imu_real_data.py --data ../shared/data/quadraped_imu_data.csv --out /tmp/imu
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

_HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(_HERE.parent))  # run against the checkout this script lives in

from _cli import output_folder, positive_float  # noqa: E402

from torchsgal import SO3  # noqa: E402
from torchsgal.imu import (  # noqa: E402
    StreamingPreintegration,
    gravity_vector,
    gtsam_interop,  # noqa: E402
    preintegrate,
)
from torchsgal.imu.data import ImuRecording, load_ros_imu_csv, windows  # noqa: E402

DATA = _HERE.parent.parent / "shared" / "data" / "quadraped_imu_data.csv"
F64 = torch.float64


def _angle(R: torch.Tensor) -> float:
    return float(SO3.from_matrix(R).log().norm())


def load(path=DATA) -> ImuRecording:
    """The recording: repeated stamps dropped, split at gaps longer than 0.05 s."""
    return load_ros_imu_csv(path, duplicates="drop", max_gap=0.05)


def compute(path=DATA, window: float = 0.5) -> dict:
    """Per window: start time [s], torchsgal's rotation angle [rad], its differences to GTSAM
    (rotation [rad], velocity [m/s], position [m]) on the samples and on the samples split in
    halves, the streaming/window difference, and the attitude difference to the recorded
    orientation [rad].  ``path``: the CSV, or its recording from ``load``."""
    rec = path if isinstance(path, ImuRecording) else load(path)
    dt_all = rec.intervals()
    params = gtsam_interop.to_gtsam_params(gravity_vector(dtype=F64), 1e-3, 1e-2)
    R_rec = SO3.from_quaternion(rec.orientation, order="xyzw").as_matrix()
    rows = []
    for a, b in windows(rec, window):
        gyro, acc, dt = rec.gyro[a:b - 1], rec.acc[a:b - 1], dt_all[a:b - 1]
        ours = preintegrate(gyro, acc, dt, covariance=False, bias_jacobian=False).delta
        stream = StreamingPreintegration(dtype=F64, buffer_size=1)
        for k in range(gyro.shape[0]):
            stream.integrate(gyro[k], acc[k], dt[k])
        split = lambda x: x.repeat_interleave(2, dim=0)  # noqa: E731  each sample held over two halves
        split_ours = preintegrate(split(gyro), split(acc), split(dt) / 2, covariance=False,
                                  bias_jacobian=False).delta
        diffs = []
        for g, f, h in ((gyro, acc, dt), (split(gyro), split(acc), split(dt) / 2)):
            peer = gtsam_interop.from_gtsam_pim(gtsam_interop.gtsam_pim(g, f, h, params)).delta
            diffs.append((_angle(ours.rotation().T @ peer.rotation()),
                          float((ours.velocity() - peer.velocity()).norm()),
                          float((ours.position() - peer.position()).norm())))
        recorded = R_rec[a].T @ R_rec[b - 1]
        rows.append(dict(
            start=float(rec.time[a]), samples=b - 1 - a, angle=float(ours.log()[6:9].norm()),
            gtsam=diffs[0], gtsam_split=diffs[1],
            split_change=float((split_ours.as_matrix() - ours.as_matrix()).abs().max()),
            streaming_change=float((stream.delta.as_matrix() - ours.as_matrix()).abs().max()),
            attitude=_angle(ours.rotation().T @ recorded)))
    return dict(rows=rows, samples=rec.gyro.shape[0], dropped=rec.dropped, segments=len(rec.segments),
                duration=float(rec.time[-1]))


def table(result: dict) -> str:
    rows = result["rows"]
    lines = [f"Recording: {result['samples']} samples over {result['duration']:.2f} s, "
             f"{result['segments']} segment(s), {result['dropped']} repeated stamps dropped; "
             f"{len(rows)} windows.", "",
             "| start [s] | samples | rotation [rad] | GTSAM rot diff [rad] | GTSAM vel diff [m/s] | "
             "GTSAM pos diff [m] | split samples: rot, vel, pos diff | vel ratio | attitude vs recorded [rad] |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        ratio = r["gtsam"][1] / r["gtsam_split"][1] if r["gtsam_split"][1] > 0 else float("nan")
        lines.append(f"| {r['start']:.2f} | {r['samples']} | {r['angle']:.1e} | {r['gtsam'][0]:.1e} | "
                     f"{r['gtsam'][1]:.2e} | {r['gtsam'][2]:.2e} | {r['gtsam_split'][0]:.1e}, "
                     f"{r['gtsam_split'][1]:.2e}, {r['gtsam_split'][2]:.2e} | {ratio:.2f} | {r['attitude']:.2e} |")
    worst = max(max(r["split_change"], r["streaming_change"]) for r in rows)
    lines += ["", f"torchsgal's increment on split samples and streamed one sample per call: "
              f"largest change {worst:.1e} (rounding)."]
    return "\n".join(lines)


def plot(result: dict, out: Path, show: bool) -> Path:
    import matplotlib
    if not show:
        matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    rows = result["rows"]
    t = [r["start"] for r in rows]
    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    ax[0].semilogy(t, [r["gtsam"][1] for r in rows], "o-", label="velocity, samples")
    ax[0].semilogy(t, [r["gtsam_split"][1] for r in rows], "s--", label="velocity, split samples")
    ax[0].semilogy(t, [r["gtsam"][2] for r in rows], "^-", label="position, samples")
    ax[0].set(xlabel="window start [s]", ylabel="|torchsgal - GTSAM|", title="GTSAM's discretisation error")
    ax[0].legend()
    ax[1].plot(t, [r["attitude"] for r in rows], "o-", label="vs recorded orientation")
    ax[1].plot(t, [r["angle"] for r in rows], "x:", label="rotation of the window")
    ax[1].set(xlabel="window start [s]", ylabel="angle [rad]", title="attitude increment")
    ax[1].set_yscale("log")
    ax[1].legend()
    fig.tight_layout()
    out.mkdir(parents=True, exist_ok=True)
    path = out / "imu_real_data.png"
    fig.savefig(path, dpi=120)
    if show:
        plt.show()
    plt.close(fig)
    return path


def existing_file(text: str) -> Path:
    """An argparse type: the path of an existing file."""
    if not Path(text).is_file():
        raise argparse.ArgumentTypeError(f"no such file: {text!r}")
    return Path(text)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=existing_file, default=DATA, help="the ROS IMU CSV")
    ap.add_argument("--window", type=positive_float, default=0.5, help="window length [s]")
    ap.add_argument("--out", type=Path, default=_HERE / "output", help="output folder")
    ap.add_argument("--no-show", action="store_true", help="do not open a window")
    args = ap.parse_args(argv)
    output_folder(ap, args.out)
    try:
        rec = load(args.data)
    except (OSError, ValueError) as error:
        ap.error(f"argument --data: {error}")
    try:
        fits = bool(windows(rec, args.window))
    except ValueError as error:
        ap.error(f"argument --window: {error}")
    if not fits:
        longest = max((float(rec.time[b - 1] - rec.time[a]) for a, b in rec.segments), default=0.0)
        ap.error(f"argument --window: {args.window:g} s does not fit in a gap-free segment of the "
                 f"recording (the longest spans {longest:.2f} s)")
    result = compute(rec, args.window)
    text = table(result)
    print(text)
    (args.out / "imu_real_data.md").write_text(text + "\n")
    plot(result, args.out, not args.no_show)


if __name__ == "__main__":
    main()
