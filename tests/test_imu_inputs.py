"""Real IMU data input (torchsgal.imu.data): the ROS CSV loader on the recording in
shared/data and on edited copies with repeated stamps, decreasing stamps, gaps, missing
columns and non-finite values."""
from __future__ import annotations

import csv
from pathlib import Path

import pytest
import torch

from torchsgal.imu import preintegrate
from torchsgal.imu.data import load_ros_imu_csv, windows

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "quadraped_imu_data.csv"


def rows():
    assert DATA.is_file(), f"the IMU recording is missing: {DATA}"
    with DATA.open(newline="") as f:
        return list(csv.reader(f))


def write(tmp_path, table, name="imu.csv"):
    path = tmp_path / name
    with path.open("w", newline="") as f:
        csv.writer(f).writerows(table)
    return path


def test_loads_the_recording():
    rec = load_ros_imu_csv(DATA)
    table = rows()
    head = table[0]
    assert rec.gyro.shape == (2635, 3) and rec.acc.shape == (2635, 3) and rec.orientation.shape == (2635, 4)
    assert rec.stamps.dtype == torch.int64 and int(rec.stamps[0]) == int(table[1][head.index("field.header.stamp")])
    k = 100
    assert float(rec.gyro[k, 2]) == float(table[k + 1][head.index("field.angular_velocity.z")])
    assert float(rec.acc[k, 0]) == float(table[k + 1][head.index("field.linear_acceleration.x")])
    assert float(rec.orientation[k, 3]) == float(table[k + 1][head.index("field.orientation.w")])
    assert torch.allclose(rec.intervals(), torch.full((2634,), 0.0025, dtype=torch.float64), rtol=0, atol=1e-12)
    assert rec.segments == [(0, 2635)] and rec.dropped == 0
    ws = windows(rec, 0.5)
    assert len(ws) == 13 and all(b - a == 201 for a, b in ws)
    a, b = ws[0]
    pre = preintegrate(rec.gyro[a:b - 1], rec.acc[a:b - 1], rec.intervals()[a:b - 1])
    assert abs(float(pre.duration()) - 0.5) < 1e-12


def test_repeated_stamps_raise_or_are_dropped(tmp_path):
    table = rows()[:50]
    table.insert(11, list(table[10]))  # row 10 repeated
    path = write(tmp_path, table)
    with pytest.raises(ValueError, match=r"1 repeated stamps \(first rows 11 and 12.*duplicates='drop'"):
        load_ros_imu_csv(path)
    rec = load_ros_imu_csv(path, duplicates="drop")
    assert rec.dropped == 1 and rec.gyro.shape[0] == 49
    assert torch.equal(rec.gyro, load_ros_imu_csv(write(tmp_path, rows()[:50], "clean.csv")).gyro)
    with pytest.raises(ValueError, match="duplicates must be 'error' or 'drop'"):
        load_ros_imu_csv(path, duplicates="keep")


def test_gaps_split_segments_and_windows(tmp_path):
    table = rows()[:101]
    del table[40:45]  # a 15 ms gap after sample 38
    path = write(tmp_path, table)
    rec = load_ros_imu_csv(path, max_gap=0.01)
    assert rec.segments == [(0, 39), (39, 95)]
    assert load_ros_imu_csv(path).segments == [(0, 95)]
    for a, b in windows(rec, 0.05):
        assert (rec.intervals()[a:b - 1] < 0.01).all()  # no window spans the gap
    with pytest.raises(ValueError, match="max_gap must be a finite number > 0"):
        load_ros_imu_csv(path, max_gap=0.0)


def test_bad_files_raise_clear_errors(tmp_path):
    table = rows()[:20]
    swapped = [list(r) for r in table]
    swapped[5], swapped[6] = swapped[6], swapped[5]
    with pytest.raises(ValueError, match=r"stamps decrease from row 6 to row 7"):
        load_ros_imu_csv(write(tmp_path, swapped, "swapped.csv"))
    col = table[0].index("field.angular_velocity.y")
    cut = [r[:col] + r[col + 1:] for r in table]
    with pytest.raises(ValueError, match=r"lacks the columns \['field.angular_velocity.y'\]"):
        load_ros_imu_csv(write(tmp_path, cut, "cut.csv"))
    nan = [list(r) for r in table]
    nan[8][table[0].index("field.linear_acceleration.z")] = "nan"
    with pytest.raises(ValueError, match=r"non-finite acc in row 9"):
        load_ros_imu_csv(write(tmp_path, nan, "nan.csv"))
    text = [list(r) for r in table]
    text[3][col] = "abc"
    with pytest.raises(ValueError, match="could not be read as numbers"):
        load_ros_imu_csv(write(tmp_path, text, "text.csv"))
    with pytest.raises(ValueError, match="has a header but no samples"):
        load_ros_imu_csv(write(tmp_path, table[:1], "empty.csv"))
    with pytest.raises(FileNotFoundError, match="no IMU recording at"):
        load_ros_imu_csv(tmp_path / "absent.csv")
