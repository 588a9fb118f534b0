"""The IMU preintegration example runs with small settings and writes its outputs."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_imu_example(tmp_path):
    pytest.importorskip("matplotlib")
    pytest.importorskip("gtsam")
    pytest.importorskip("pypose")
    out = subprocess.run(
        [sys.executable, "examples/imu_preintegration.py", "--out", str(tmp_path), "--dts", "0.02", "0.01",
         "--windows", "3", "--runs", "200", "--chain", "4"],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    for name in ("imu_accuracy.md", "imu_error_vs_dt.png", "imu_trajectory.png"):
        assert (tmp_path / name).exists(), name
    table = (tmp_path / "imu_accuracy.md").read_text()
    assert "| 0.01 |" in table and "Observed order of the position error" in table
    assert table in out.stdout
