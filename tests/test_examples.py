"""The README's commands run: the main job, the API tour and the examples."""
from __future__ import annotations

import importlib.util
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


# One or two bad options per example script, all rejected while parsing (before any
# computation): "FILE" stands for a path that is a file, so no folder can be made there.
BAD_OPTIONS = [
    ("api_tour.py", ["--bogus"], "--bogus"),
    ("dumpling_distribution.py", ["--samples", "0"], "--samples"),
    ("dumpling_distribution.py", ["--out", "FILE/x.png"], "--out"),
    ("gdh_manipulator.py", ["--seconds", "nan"], "--seconds"),
    ("gdh_manipulator.py", ["--out", "FILE"], "--out"),
    ("gnss_ins_smoother.py", ["--runs", "0"], "--runs"),
    ("gnss_ins_smoother.py", ["--out", "FILE"], "--out"),
    ("imu_preintegration.py", ["--dts", "0.01", "inf"], "--dts"),
    ("imu_preintegration.py", ["--chain", "-1"], "--chain"),
    ("imu_preintegration.py", ["--out", "FILE"], "--out"),
    ("imu_real_data.py", ["--window", "nan"], "--window"),
    ("imu_real_data.py", ["--data", "FILE.missing.csv"], "--data"),
    ("imu_real_data.py", ["--out", "FILE"], "--out"),
    ("learn_noise_scale.py", ["--lr", "inf"], "--lr"),
    ("learn_noise_scale.py", ["--poses", "1"], "--poses"),
    ("regression_table.py", ["--worldline-trials", "0"], "--worldline-trials"),
    ("regression_table.py", ["--out", "FILE"], "--out"),
    ("robot_arm.py", ["--seconds", "inf"], "--seconds"),
    ("robot_arm.py", ["--no-show", "--out", "FILE"], "--out"),
    ("timestamp_fusion.py", ["--dt", "nan"], "--dt"),
    ("timestamp_fusion.py", ["--out", "FILE"], "--out"),
    ("train_manifold_parameter.py", ["--points", "0"], "--points"),
    ("train_manifold_parameter.py", ["--steps", "-1"], "--steps"),
]


def _example_module(script: str):
    """The example script as a module (its main(argv) not run), loaded once per process."""
    name = f"_example_{script[:-3]}"
    folder = os.path.join(ROOT, "examples")  # the scripts import their shared _cli module
    if folder not in sys.path:
        sys.path.insert(0, folder)
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, os.path.join(ROOT, "examples", script))
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return sys.modules[name]


@pytest.mark.parametrize("script, args, option", BAD_OPTIONS,
                         ids=[f"{s[:-3]}{a[0]}" for s, a, _ in BAD_OPTIONS])
def test_example_bad_option_is_a_usage_error(script, args, option, tmp_path, capsys):
    """A bad option ends as an argparse usage error (exit code 2, one 'error:' line naming the
    option; any other exception fails the test) and writes nothing.  In this process, through
    the script's main(argv) (api_tour.py, which runs at import, in a subprocess)."""
    file = tmp_path / "a_file"
    file.write_text("")
    args = [a.replace("FILE", str(file)) for a in args]
    if script == "api_tour.py":
        out = subprocess.run([sys.executable, f"examples/{script}", *args], cwd=ROOT, capture_output=True,
                             text=True, timeout=120)
        code, stderr = out.returncode, out.stderr
        assert "Traceback" not in stderr, stderr[-3000:]
    else:
        with pytest.raises(SystemExit) as exit_info:
            _example_module(script).main(args)
        code, stderr = exit_info.value.code, capsys.readouterr().err
    assert code == 2, (code, stderr[-3000:])
    errors = [line for line in stderr.splitlines() if "error:" in line]
    assert len(errors) == 1 and option in errors[0], stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file"]


def test_example_help():
    """api_tour.py has a --help; gnss_ins_smoother.py's default --out is examples/output/, as
    the other examples'."""
    assert "The API tour of docs/guide/groups.md" in _run("examples/api_tour.py", "--help")
    assert "default examples/output/" in _run("examples/gnss_ins_smoother.py", "--help")
