"""Shared test machinery: one decorator runs a property over every group, several batch
shapes and both float dtypes; every batch of 5 or more elements covers the small-angle, closed-form and
near-pi bands (see ANGLES)."""
from __future__ import annotations

import math
import os
import sys

import numpy as np
import pytest
import torch

sys.path.insert(0, os.path.dirname(__file__))

import torchsgal as ts  # noqa: E402

# Under pytest-xdist each worker takes its share of the cores, so that the workers' torch threads
# do not outnumber them (oversubscribed OpenMP threads spin against each other).
if os.environ.get("PYTEST_XDIST_WORKER_COUNT") and not os.environ.get("OMP_NUM_THREADS"):
    torch.set_num_threads(max(1, (os.cpu_count() or 1) // int(os.environ["PYTEST_XDIST_WORKER_COUNT"])))

GROUP_CLASSES = list(ts.ALL_GROUPS)
BATCH_SHAPES = [(), (5,), (2, 3, 1)]
DTYPES = [torch.float64, torch.float32]

# Rotation angles cycled over a batch.  Interleaved so that every batch of >= 5 elements
# (BATCH_SHAPES has (5,) and (2, 3, 1)) covers the identity, the Taylor branches (an angle
# below numerics.JINV_THRESHOLD = 0.5 and one between it and SERIES_THRESHOLD = 1), the sin/cos
# closed form past pi/2 (where log takes the axis from the symmetric part) and near pi; from 6
# elements on also theta = 1 (closed form, cos > 0), then the other small and moderate angles.
ANGLES = [0.0, 2.0, 1e-5, math.pi - 1e-6, 0.7, 1.0, 1e-9, 3.0, 1e-3, 0.3, 1e-12, 1e-6]
# The single angle of an unbatched sample, chosen by the seed (seed 0: 1e-6), so that the
# unbatched cases of different tests do not all sit in one branch.
UNBATCHED_ANGLES = [1e-6, 1.0, 1e-9, 2.5, 1e-3, math.pi - 1e-6, 0.7, 3.0]


def angles_for(batch_shape, seed=0) -> np.ndarray:
    if not batch_shape:
        return np.array([UNBATCHED_ANGLES[seed % len(UNBATCHED_ANGLES)]])
    n = int(np.prod(batch_shape))
    return np.array([ANGLES[i % len(ANGLES)] for i in range(n)])


def sample_tangent(G, batch_shape, dtype, seed=0, scale=1.0, angles=None) -> torch.Tensor:
    """Tangent vectors whose rotation angles are ``angles`` (default: the cycle above)."""
    rng = np.random.default_rng(seed)
    ang = angles_for(batch_shape, seed) if angles is None else np.asarray(angles, dtype=float)
    n = ang.size
    xi = scale * rng.standard_normal((n, G.dof))
    phi_slice = G._f.PHI
    axis = rng.standard_normal((n, phi_slice.stop - phi_slice.start))  # a sign for SO2/SE2
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    xi[:, phi_slice] = axis * ang[:, None]
    return torch.tensor(xi.reshape(*batch_shape, G.dof) if batch_shape else xi[0], dtype=dtype)


def sample_group(G, batch_shape, dtype, seed=0):
    return G.exp(sample_tangent(G, batch_shape, dtype, seed))


def tol(dtype) -> float:
    """Relative-to-magnitude tolerance: CONVENTIONS.md, Numerics."""
    return 1e-10 if dtype == torch.float64 else 2e-5


def assert_close(actual, expected, dtype, scale=None, factor=1.0, msg=""):
    actual = np.asarray(actual.detach().cpu().numpy() if torch.is_tensor(actual) else actual)
    expected = np.asarray(
        expected.detach().cpu().numpy() if torch.is_tensor(expected) else expected, dtype=float
    )
    assert actual.shape == expected.shape, f"shape {actual.shape} != {expected.shape} {msg}"
    if scale is None:
        scale = max(1.0, float(np.abs(expected).max(initial=0.0)))
    err = float(np.abs(actual.astype(float) - expected).max(initial=0.0))
    assert np.isfinite(actual).all(), f"non-finite values {msg}"
    assert err <= factor * tol(dtype) * scale, f"max error {err:.3g} > {factor * tol(dtype) * scale:.3g} {msg}"


def all_groups(fn=None, *, batch_shapes=BATCH_SHAPES, dtypes=DTYPES):
    """Runs a test over every (group, batch_shape, dtype)."""

    def wrap(f):
        f = pytest.mark.parametrize("dtype", dtypes, ids=lambda d: str(d).split(".")[-1])(f)
        f = pytest.mark.parametrize("batch_shape", batch_shapes, ids=lambda b: "b" + "x".join(map(str, b)))(f)
        return pytest.mark.parametrize("G", GROUP_CLASSES, ids=lambda g: g.__name__)(f)

    return wrap(fn) if fn is not None else wrap


def gname(G) -> str:
    return G.__name__


def np64(t: torch.Tensor) -> np.ndarray:
    return t.detach().cpu().double().numpy()


def needs_robot_data() -> None:
    """Skips the calling test where example-robot-data's URDF files are not installed (a
    failure under TORCHSGAL_NO_SKIPS=1, like every skip)."""
    from torchsgal.kinematics.urdf import example_robot_data_dir

    try:
        example_robot_data_dir()
    except FileNotFoundError as e:
        pytest.skip(str(e))


def _no_skips() -> bool:
    return os.environ.get("TORCHSGAL_NO_SKIPS") == "1"


# Reports of tests that did not run as passing tests: skipped (at collection or at run time),
# xfailed and xpassed.  Collected by these hooks rather than read from the terminal reporter, so
# the rule holds with -p no:terminal too.
_NOT_RUN: list = []


def _record(report):
    if report.skipped or hasattr(report, "wasxfail"):
        _NOT_RUN.append(report)


def pytest_runtest_logreport(report):
    _record(report)


def pytest_collectreport(report):
    _record(report)


def pytest_sessionfinish(session, exitstatus):
    """With TORCHSGAL_NO_SKIPS=1 (set by .ci/run) a skipped, xfailed or xpassed test fails the
    run: in CI every optional dependency (the peers, matplotlib, scipy) is installed, so a skip
    or an expected failure is a test that did not run or did not check, and must not count as
    passing."""
    if _no_skips() and _NOT_RUN and exitstatus in (pytest.ExitCode.OK, pytest.ExitCode.NO_TESTS_COLLECTED):
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


def _reason(rep) -> str:
    if hasattr(rep, "wasxfail"):
        return ("xpassed: " if rep.passed else "xfailed: ") + str(rep.wasxfail)
    return str(rep.longrepr[-1] if isinstance(rep.longrepr, tuple) else rep.longrepr)


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    if _no_skips() and _NOT_RUN:
        terminalreporter.write_line(
            f"TORCHSGAL_NO_SKIPS=1: {len(_NOT_RUN)} skipped/xfailed/xpassed test(s) fail this run:", red=True)
        for rep in _NOT_RUN[:20]:
            terminalreporter.write_line(f"  {rep.nodeid}: {_reason(rep)}")


# tests/test_cuda.py compares the library on a CUDA device with the CPU; it is collected only
# where torch sees a GPU (CI has none: it runs on a lent GPU machine) or where
# TORCHSGAL_CUDA_TEST_DEVICE names another device to exercise the harness.  Not a skip: the
# terminal summary says that it was left out and why.
_CUDA_FILE_COLLECTED = torch.cuda.is_available() or bool(os.environ.get("TORCHSGAL_CUDA_TEST_DEVICE"))
collect_ignore = [] if _CUDA_FILE_COLLECTED else ["test_cuda.py", "test_cuda_engine.py"]


def pytest_report_header(config):
    return [f"torch {torch.__version__}, numpy {np.__version__}", _cuda_header()]


def _cuda_header() -> str:
    return ("tests/test_cuda.py, test_cuda_engine.py: collected (device "
            + os.environ.get("TORCHSGAL_CUDA_TEST_DEVICE", "cuda") + ")" if _CUDA_FILE_COLLECTED
            else "tests/test_cuda.py, test_cuda_engine.py: not collected, no CUDA device (they run on a GPU "
            "machine)")
