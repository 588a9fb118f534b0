"""The uncertainty examples run: the dumpling distribution (Kelly and Giamou, Figure 2)."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_dumpling_distribution_example(tmp_path):
    pytest.importorskip("matplotlib")
    out_png = tmp_path / "dumpling.png"
    proc = subprocess.run(
        [sys.executable, "examples/dumpling_distribution.py", "--out", str(out_png), "--seed", "0"],
        cwd=ROOT, capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert out_png.exists() and out_png.stat().st_size > 0
    assert out_png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "corr(t,x)" in proc.stdout
