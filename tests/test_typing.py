"""mypy checks the group classes' annotations: tests/typing_groups.py asserts the precise return
types (the class itself for group-valued methods, torch.Tensor for the algebra maps)."""
from __future__ import annotations

from pathlib import Path

import mypy.api as mypy_api
import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def cache(tmp_path_factory) -> Path:
    """One mypy cache for the module: the second run reuses the analysis of torch."""
    return tmp_path_factory.mktemp("mypy_cache")


def _mypy(cache: Path, *targets: str) -> tuple[str, int]:
    """mypy's report and exit status on ``targets``, with the project's configuration; imported
    modules outside the targets are analysed but their own errors are not reported."""
    stdout, stderr, status = mypy_api.run([
        "--config-file", str(REPO / "pyproject.toml"),
        "--follow-imports=silent",
        "--cache-dir", str(cache),
        "--no-error-summary",
        *targets,
    ])
    return stdout + stderr, status


def test_group_api_types_check(cache):
    report, status = _mypy(cache, str(REPO / "tests" / "typing_groups.py"), str(REPO / "torchsgal" / "groups"))
    assert status == 0 and report.strip() == "", report


def test_a_wrong_type_is_reported(cache, tmp_path):
    """The check is live: assigning an SE3 to an SO3 name and an imprecise assert_type fail."""
    wrong = tmp_path / "wrong.py"
    wrong.write_text(
        "import torch\n"
        "from typing_extensions import assert_type\n"
        "import torchsgal as ts\n"
        "r: ts.SO3 = ts.SE3.exp(torch.zeros(6))\n"
        "assert_type(ts.SE3.identity().inverse(), ts.LieGroup)\n"
    )
    report, status = _mypy(cache, str(wrong))
    assert status == 1, report
    assert ('wrong.py:4: error: Incompatible types in assignment (expression has type "SE3", '
            'variable has type "SO3")') in report
    assert "wrong.py:5: error: Expression is of type \"SE3\", not \"LieGroup\"" in report
