"""The README's commands run: the main job, the API tour and the examples."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest
from conftest import needs_robot_data

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _run(*args, timeout=120):
    out = subprocess.run([sys.executable, *args], cwd=ROOT, capture_output=True, text=True, timeout=timeout)
    assert out.returncode == 0, out.stderr[-3000:]
    return out.stdout


def test_main_job_demo():
    out = _run("-m", "torchsgal")
    assert "[3.0, 2.0, 0.0, 1.0]" in out  # the worked event example


def test_api_tour():
    assert "grad finite: True" in _run("examples/api_tour.py")


def test_gdh_example(tmp_path):
    pytest.importorskip("matplotlib")
    out = _run("examples/gdh_manipulator.py", "--out", str(tmp_path), "--samples", "401")
    assert (tmp_path / "gdh_scara.png").exists() and (tmp_path / "gdh_iiwa7.png").exists()
    assert "PAPER product column" in out


def _readme_python_blocks():
    import re
    with open(os.path.join(ROOT, "README.md"), encoding="utf-8") as f:
        return re.findall(r"```python\n(.*?)```", f.read(), re.S)


@pytest.mark.parametrize("index", range(len(_readme_python_blocks())))
def test_readme_python_block_runs(index, tmp_path):
    """Every ```python block of the README runs as it is (in a scratch directory, so that
    nothing it writes lands in the repository)."""
    code = _readme_python_blocks()[index]
    if "load_robot" in code:
        needs_robot_data()
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, f"README python block {index}:\n{code}\n{out.stderr[-3000:]}"


def test_readme_has_python_blocks():
    assert len(_readme_python_blocks()) >= 5
