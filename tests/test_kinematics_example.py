"""examples/robot_arm.py runs small: the Panda from its URDF, kinematics and IK, the figure."""
from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_robot_arm_example(tmp_path):
    pytest.importorskip("matplotlib")
    pytest.importorskip("yourdfpy")
    out = subprocess.run([sys.executable, "examples/robot_arm.py", "--no-show", "--out",
                          str(tmp_path), "--samples", "201", "--targets", "8", "--seeds", "4"],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    assert (tmp_path / "robot_arm.png").stat().st_size > 10_000
    # finite differences at h = 0.02 s agree to O(h^2): well under 1e-2
    v_err, a_err = (float(x) for x in re.search(
        r"velocity vs finite differences (\S+) m/s, acceleration (\S+) m/s", out.stdout).groups())
    assert v_err < 1e-2 and a_err < 1e-1
    solved = int(re.search(r"IK: (\d+)/8 targets", out.stdout).group(1))
    assert solved >= 6 and "all within the joint limits: True" in out.stdout
