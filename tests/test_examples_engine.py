"""The factor-graph engine's example runs: a noise scale learned through implicit gradients of
batched solves comes close to the simulated truth (from a start ten times too large)."""
from __future__ import annotations

import os
import re
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_learn_noise_scale_example():
    proc = subprocess.run(
        [sys.executable, "examples/learn_noise_scale.py", "--steps", "60", "--batch", "16",
         "--poses", "8", "--lr", "0.1"],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
        env=dict(os.environ, OMP_NUM_THREADS="1"),
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    m = re.search(r"start ([\d.]+), learned ([\d.]+), truth ([\d.]+)", proc.stdout)
    assert m, proc.stdout[-2000:]
    start, learned, truth = map(float, m.groups())
    assert start == 10 * truth
    # 60 steps of 16 graphs: the estimate still moves by ~ +-15% from batch to batch
    assert abs(learned - truth) < 0.3 * truth, (learned, truth)
