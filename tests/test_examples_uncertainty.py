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


def _anees_row(table: str, label: str) -> list[float]:
    """The ANEES numbers (state, position, ...) of the markdown row starting with ``label``."""
    for line in table.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if cells and cells[0] == label:
            return [float(c.split()[0]) for c in cells[1:]]
    raise AssertionError(f"no row {label!r} in the table:\n{table}")


def test_timestamp_fusion_example(tmp_path):
    """Mahony, Kelly and Weiss Figure 5 + Monte Carlo: classical fusion (timestamps taken as
    exact) is overconfident, Galilean fusion is consistent in position."""
    pytest.importorskip("matplotlib")
    pytest.importorskip("scipy")
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    proc = subprocess.run(
        [sys.executable, "examples/timestamp_fusion.py", "--trials", "300", "--seed", "1",
         "--out", str(tmp_path)],
        cwd=root, capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    png = tmp_path / "timestamp_fusion.png"
    assert png.exists() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    table = (tmp_path / "timestamp_fusion.md").read_text()
    assert table in proc.stdout
    gal = _anees_row(table, "Galilean (torchsgal)")
    paper = _anees_row(table, "Galilean as printed (time row, paper)")
    cls = _anees_row(table, "Classical (timestamps exact)")
    # columns: state (10), position (3), nav without time (9), time (1); 300 trials
    assert cls[0] > 100 * gal[0]      # the truth's time error against a 1e-12 s^2 variance
    assert cls[1] > 2.0 * gal[1]      # along-track error v mu_t missing from the classical model
    assert 2.6 < gal[1] < 3.4         # Galilean position ANEES at its dof (band ~[2.72, 3.29])
    assert 8.9 < gal[0] < 11.1        # full state at its dof (band ~[9.50, 10.52])
    assert 0.8 < gal[3] < 1.2         # time consistent
    assert 1.5 < paper[3] < 2.6       # as printed, the time row counts the prior twice (~2)


def test_dumpling_distribution_reports_the_file_it_writes(tmp_path):
    """--out without a suffix: matplotlib adds .png, and the script says so."""
    pytest.importorskip("matplotlib")
    proc = subprocess.run(
        [sys.executable, "examples/dumpling_distribution.py", "--out", str(tmp_path / "fig"),
         "--samples", "50"],
        cwd=ROOT, capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert f"wrote {tmp_path / 'fig.png'} in" in proc.stdout
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fig.png"]
