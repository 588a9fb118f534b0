"""Loading real IMU recordings: ROS ``sensor_msgs/Imu`` CSV exports (``rostopic echo -p``).

Real recordings have irregular stamps, gaps (dropped messages) and repeated stamps; the
loader makes each of these an explicit choice: repeated stamps raise or are dropped
(``duplicates``), decreasing stamps raise, and gaps longer than ``max_gap`` split the
recording into segments that should be preintegrated separately (a sample is held only over
its own interval).
"""
from __future__ import annotations

import csv
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..functional import checks

_COLUMNS = {
    "stamp": ["field.header.stamp"],
    "orientation": ["field.orientation.x", "field.orientation.y", "field.orientation.z", "field.orientation.w"],
    "gyro": ["field.angular_velocity.x", "field.angular_velocity.y", "field.angular_velocity.z"],
    "acc": ["field.linear_acceleration.x", "field.linear_acceleration.y", "field.linear_acceleration.z"],
}


@dataclass
class ImuRecording:
    """An IMU recording of N samples.

    stamps       (N,) int64: the message stamps [ns].
    time         (N,) seconds since the first stamp (the recording's dtype).
    gyro, acc    (N, 3): angular velocity [rad/s] and specific force [m/s^2], sensor frame.
    orientation  (N, 4): the recorded attitude quaternion (x, y, z, w), sensor to world.
    segments     [(start, stop)]: index ranges of runs without a gap longer than max_gap
                 (one segment covering everything without max_gap).
    dropped      how many samples with a repeated stamp were dropped.
    """

    stamps: torch.Tensor
    time: torch.Tensor
    gyro: torch.Tensor
    acc: torch.Tensor
    orientation: torch.Tensor
    segments: list
    dropped: int = 0

    def intervals(self) -> torch.Tensor:
        """dt (N - 1,) [s]: the interval from each sample to the next (sample k is held over
        [t_k, t_(k+1)), so the last sample has none)."""
        return torch.diff(self.time)


def load_ros_imu_csv(path, duplicates: str = "error", max_gap: float | None = None,
                     dtype=torch.float64) -> ImuRecording:
    """Read a ROS ``sensor_msgs/Imu`` CSV export (a header row naming ``field.header.stamp``,
    ``field.orientation.x`` .. ``w``, ``field.angular_velocity.x`` .. ``z`` and
    ``field.linear_acceleration.x`` .. ``z``; other columns are ignored).

    ``duplicates``: "error" (a repeated stamp raises ValueError naming its rows) or "drop"
    (the later samples with a repeated stamp are dropped; ``dropped`` counts them).  Stamps
    that decrease raise ValueError.  ``max_gap`` [s]: intervals longer than it split the
    recording into ``segments`` (None: one segment).  Non-finite values raise ValueError
    naming the first row (1-based, the header is row 1)."""
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path must be a str or an os.PathLike, got {type(path).__name__}")
    path = Path(path)
    if duplicates not in ("error", "drop"):
        raise ValueError(f"duplicates must be 'error' or 'drop', got {duplicates!r}")
    if max_gap is not None:
        max_gap = checks.finite_number(max_gap, "max_gap", "> 0")
    dtype = checks.dtype_arg(dtype)
    if not path.is_file():
        raise FileNotFoundError(f"no IMU recording at {path}")
    with path.open(newline="") as f:
        reader = csv.reader(f)
        header = next(reader, None)
        if header is None:
            raise ValueError(f"{path} is empty (expected a header row)")
        index = {name: i for i, name in enumerate(header)}
        missing = [c for cols in _COLUMNS.values() for c in cols if c not in index]
        if missing:
            raise ValueError(f"{path} lacks the columns {missing} of a sensor_msgs/Imu export")
        rows = [r for r in reader if r]
    if not rows:
        raise ValueError(f"{path} has a header but no samples")
    stamp_col = index[_COLUMNS["stamp"][0]]
    try:
        stamps = np.array([int(r[stamp_col]) for r in rows], dtype=np.int64)
        values = {k: np.array([[float(r[index[c]]) for c in cols] for r in rows])
                  for k, cols in _COLUMNS.items() if k != "stamp"}
    except (ValueError, IndexError) as error:
        raise ValueError(f"{path}: a row could not be read as numbers ({error})") from None
    for field, v in values.items():
        bad = ~np.isfinite(v).all(axis=1)
        if bad.any():
            raise ValueError(f"{path}: non-finite {field} in row {int(np.argmax(bad)) + 2}")
    step = np.diff(stamps)
    if (step < 0).any():
        k = int(np.argmax(step < 0))
        raise ValueError(f"{path}: stamps decrease from row {k + 2} to row {k + 3} "
                         f"({stamps[k]} -> {stamps[k + 1]} ns); sort the recording first")
    dropped = 0
    if (step == 0).any():
        if duplicates == "error":
            rep = np.flatnonzero(step == 0)
            raise ValueError(f"{path}: {rep.size} repeated stamps (first rows {int(rep[0]) + 2} and "
                             f"{int(rep[0]) + 3}, {stamps[rep[0]]} ns); pass duplicates='drop' to keep the "
                             f"first sample of each stamp")
        keep = np.concatenate(([True], step != 0))
        dropped = int((~keep).sum())
        stamps = stamps[keep]
        values = {name: v[keep] for name, v in values.items()}
    seconds = (stamps - stamps[0]) * 1e-9
    segments = [(0, len(stamps))]
    if max_gap is not None:
        cut = np.flatnonzero(np.diff(seconds) > max_gap) + 1
        bounds = [0, *cut.tolist(), len(stamps)]
        segments = [(a, b) for a, b in zip(bounds, bounds[1:])]
    t = lambda x: torch.tensor(x, dtype=dtype)  # noqa: E731
    return ImuRecording(torch.tensor(stamps), t(seconds), t(values["gyro"]), t(values["acc"]),
                        t(values["orientation"]), segments, dropped)


MAX_WINDOWS = 10**8  # windows' bound on the number of windows (a tiny length is a mistake)


def windows(recording: ImuRecording, length: float) -> list[tuple[int, int]]:
    """Consecutive windows of about ``length`` seconds inside each segment, as index ranges
    [(start, stop)] with stop - start >= 2 (a window integrates samples start .. stop - 2 over
    the intervals to stop - 1: the increment between the instants of samples start and
    stop - 1)."""
    if not isinstance(recording, ImuRecording):
        raise TypeError(f"recording must be an ImuRecording, got {type(recording).__name__}")
    length = checks.finite_number(length, "length", "> 0")
    duration = float(recording.time[-1] - recording.time[0]) if recording.time.numel() else 0.0
    if duration / length > MAX_WINDOWS:  # also keeps the window count finite for a tiny length
        raise ValueError(f"length must give at most {MAX_WINDOWS} windows over the recording's "
                         f"{duration:g} s, got {length!r}")
    out = []
    for a, b in recording.segments:
        t = recording.time[a:b]
        if b - a < 2:
            continue
        n = int(math.floor(float(t[-1] - t[0]) / length))
        edges = torch.searchsorted(t, t[0] + length * torch.arange(n + 1, dtype=t.dtype)).tolist()
        out += [(a + s, a + e + 1) for s, e in zip(edges, edges[1:]) if e + 1 - s >= 2 and a + e + 1 <= b]
    return out
