"""The ```python examples of the documentation pages run: each page's blocks in order, in one
namespace, in a scratch directory (blocks may write files), and the results the page states in
its prose or comments hold.  docs/guide/factor_graphs.md (test_factor_graph_guide.py) and
README.md (test_examples.py) have their own tests.

Each page runs on one torch thread (docs/guide/threads.md: a loaded machine collapses multi-
threaded small operations) with torch's seed 0, both restored afterwards."""
from __future__ import annotations

import os
import re
import shutil
from pathlib import Path

import pytest
import torch
from conftest import needs_robot_data

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
DATA = ROOT.parent / "shared" / "data"
TESTED_ELSEWHERE = {"guide/factor_graphs.md"}
# a fence indented inside a list item (threads.md) is dedented by its own indentation
FENCE = re.compile(r"(?ms)^([ \t]*)```python\n(.*?)^[ \t]*```")


def python_blocks(page: str) -> list[str]:
    text = (DOCS / page).read_text(encoding="utf-8")
    return [re.sub(r"(?m)^" + re.escape(indent), "", body) for indent, body in FENCE.findall(text)]


def run_page(page: str, tmp_path, capsys, size: dict[int, tuple[str, str]] | None = None) -> tuple[dict, str]:
    """Runs the page's blocks; ``size`` maps a block's index to (text, replacement): a size that
    the page names as a parameter, made smaller (the replacement must occur exactly once)."""
    blocks = python_blocks(page)
    for index, (old, new) in (size or {}).items():
        assert blocks[index].count(old) == 1, f"{page} block {index} no longer holds {old!r}"
        blocks[index] = blocks[index].replace(old, new)
    namespace: dict = {"__name__": "__docs_example__"}
    threads, cwd, rng = torch.get_num_threads(), os.getcwd(), torch.get_rng_state()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    os.chdir(tmp_path)
    try:
        for block in blocks:
            exec(compile(block, str(DOCS / page), "exec"), namespace)
    finally:
        os.chdir(cwd)
        torch.set_num_threads(threads)
        torch.set_rng_state(rng)
    return namespace, capsys.readouterr().out


def test_every_page_with_python_blocks_is_covered():
    pages = {page for page in (p.relative_to(DOCS).as_posix() for p in DOCS.rglob("*.md"))
             if python_blocks(page)}
    covered = {name.removeprefix("test_page_").replace("__", "/") + ".md"
               for name in globals() if name.startswith("test_page_")}
    assert pages - TESTED_ELSEWHERE == covered


def test_page_guide__groups(tmp_path, capsys):
    n, _ = run_page("guide/groups.md", tmp_path, capsys)
    F = n["F"]
    assert F.batch_shape == (1024,) and F.log().shape == (1024, 10) and F.as_matrix().shape == (1024, 5, 5)
    assert F.adjoint().shape == (1024, 10, 10)
    assert n["J_F"].shape == (1024, 4, 10) and n["J_e"].shape == (1024, 4, 4)
    assert (n["ts"].SGal3.random((4, 1)) @ n["ts"].SGal3.random((3,))).batch_shape == (4, 3)
    assert torch.load(tmp_path / "F.pt").allclose(F, rtol=0, atol=0)     # saved in the directory
    assert torch.func.vmap(torch.func.jacfwd(n["ts"].functional.sgal3.exp))(F[:2].log()).shape == (2, 5, 5, 10)
    # "the estimate: T0.rplus(d), 1e-7 to 1e-5 off"
    assert n["T0"].rplus(n["d"]).rminus(n["target"]).abs().max() < 1e-5
    # Sim(3): scale = exp(lambda)
    T = n["T"]
    torch.testing.assert_close(T.scale(), T.log()[..., 6].exp(), rtol=1e-12, atol=0)


def test_page_guide__estimation(tmp_path, capsys):
    # the Table-1 study's second block solves 400 trials four times; StudyConfig(trials=...) is
    # the study's size (the page: `--trials`), run here with 40; the frame-change block keeps
    # its 400, whose printed ANEES the page's table states
    n, out = run_page("guide/estimation.md", tmp_path, capsys,
                      size={1: ("StudyConfig(trials=400)", "StudyConfig(trials=40)")})
    first = n["target"]
    assert first.batch_shape == (8,)
    F_hat, dtau_hat = n["F_hat"], n["dtau_hat"]          # "SGal3 (400,), (400, 1)" per trial
    assert F_hat.batch_shape == (40,) and dtau_hat.shape == (40, 1)
    problem = n["problem"]
    sol = n["solve_sgal3"](problem, dtau0=-1.0)
    assert sol.covariance.shape == (40, 11, 11) and sol.report.status.shape == (40,)
    assert sol.report.converged.all()
    # the first block: "~0, (8, 6, 6)" and converged
    g0 = n["gauss_newton"](lambda x: x.rminus(first), first.rplus(0.1 * torch.ones(8, 6, dtype=torch.float64)))
    assert g0.x.rminus(first).abs().max() < 1e-12 and g0.covariance.shape == (8, 6, 6)
    assert g0.report.converged.all()
    # the table "a boost of 20 m/s along x": invariant 150.7, product 520.7 (paper-style)
    printed = dict(re.findall(r"^(invariant|product) tensor\(([-0-9.e+]+)", out, flags=re.M))
    assert float(printed["invariant"]) == pytest.approx(150.7, abs=0.05)
    assert float(printed["product"]) == pytest.approx(520.7, abs=0.05)


def test_page_guide__imu(tmp_path, capsys):
    n, _ = run_page("guide/imu.md", tmp_path, capsys)
    pre = n["pre"]
    assert pre.delta.batch_shape == (1000,)
    assert pre.covariance.shape == (1000, 10, 10) and pre.bias_jacobian.shape == (1000, 10, 6)
    assert pre[:10].delta.batch_shape == (10,)
    torch.testing.assert_close(pre.delta.time(), torch.full((1000,), 1.0, dtype=torch.float64),
                               rtol=1e-12, atol=0)                # 200 samples of 5 ms
    # "with the default time_noise_density=0 the covariance has a zero iota row/column (rank 9)"
    assert (pre.covariance[..., 9, :] == 0).all() and (pre.covariance[..., :, 9] == 0).all()
    assert (torch.linalg.matrix_rank(pre.covariance[:5]) == 9).all()
    assert n["X1"].batch_shape == (1000,) and n["P1"].shape == (1000, 10, 10)


def test_page_guide__imu_factors(tmp_path, capsys):
    n, _ = run_page("guide/imu_factors.md", tmp_path, capsys)   # the block asserts its accuracy
    assert n["cov"].shape == (1, 10, 10)
    # "as close to the truth as in float64 (1.6e-5 m)"
    err = (n["x"].position() - n["truth"].position()).norm(dim=-1).max()
    assert float(err) == pytest.approx(1.6e-5, abs=0.05e-5)


def test_page_guide__imu_streaming(tmp_path, capsys):
    n, _ = run_page("guide/imu_streaming.md", tmp_path, capsys)
    pre, f64 = n["pre"], torch.float64
    # "the same increment, covariance and bias Jacobian as the window function" (1e-12)
    from torchsgal.imu import preintegrate
    window = preintegrate(n["gyros"], n["accs"], 0.005, gyro_noise_density=1e-3, acc_noise_density=1e-2)
    torch.testing.assert_close(pre.delta.as_matrix(), window.delta.as_matrix(), rtol=0, atol=1e-12)
    torch.testing.assert_close(pre.covariance, window.covariance, rtol=0, atol=1e-12)
    torch.testing.assert_close(pre.bias_jacobian, window.bias_jacobian, rtol=0, atol=1e-12)
    # predict with a new bias uses the corrected increment, without re-integration
    g = n["gravity_vector"](dtype=f64)
    expected = pre.predict(n["X_i"], g, gyro_bias=n["new_bg"])
    assert n["X_j"].allclose(expected, rtol=0, atol=1e-12)
    # after reset: an empty window at the new linearisation point
    assert n["imu"].result().delta.allclose(n["SGal3"].identity(dtype=f64), rtol=0, atol=0)


def test_page_guide__interop(tmp_path, capsys):
    pytest.importorskip("gtsam")
    pytest.importorskip("pypose")
    n, _ = run_page("guide/interop.md", tmp_path, capsys)     # every block asserts its results
    assert n["back"].batch_shape == (2, 3) and n["P1"].shape == (6, 6)


def test_page_guide__kinematics(tmp_path, capsys):
    n, _ = run_page("guide/kinematics.md", tmp_path, capsys)
    state = n["state"]
    assert state.pose.shape == (10000, 4, 4)
    assert state.linear_velocity.shape == (10000, 3) and state.angular_velocity.shape == (10000, 3)
    assert state.frames.batch_shape == (10000, 7)
    assert n["lin_acc"].shape == (10000, 3) and n["ang_acc"].shape == (10000, 3)


def test_page_guide__pose_graph_io(tmp_path, capsys):
    # the page reads sphere2500.txt from the current directory; a missing data folder fails
    # (it is part of the checkout's environment, as in test_g2o.py), never skips
    assert (DATA / "sphere2500.txt").is_file(), f"shared data not found at {DATA}"
    shutil.copy(DATA / "sphere2500.txt", tmp_path)
    n, _ = run_page("guide/pose_graph_io.md", tmp_path, capsys)
    graph = n["graph"]
    assert graph.group is n["ts"].SE3 and graph.edge_tag == "EDGE3"
    N, E = graph.ids.shape[0], graph.edges.shape[0]
    assert N == 2500 and graph.poses is None                  # no vertex lines: chained odometry
    assert graph.edge_ids.shape == (E, 2) and graph.measurements.batch_shape == (E,)
    assert graph.information.shape == (E, 6, 6) and n["initial"].batch_shape == (N,)
    # the sparse Cholesky: the tridiagonal [-1, 4, -1] of size 12, from its lower triangle
    size, f64 = 12, torch.float64
    off = torch.ones(size - 1, dtype=f64)
    A = 4 * torch.eye(size, dtype=f64) - off.diag(-1) - off.diag(1)
    torch.testing.assert_close(A @ n["x"], torch.ones(size, dtype=f64), rtol=0, atol=1e-14)
    inverse = torch.linalg.inv(A)
    torch.testing.assert_close(n["C"], torch.stack([inverse[:6, :6], inverse[6:, 6:]]), rtol=0, atol=1e-14)
    # "auto" takes the first installed backend in the order of the table
    from torchsgal.estimation import sparse
    installed = [b for b in sparse.BACKENDS if b == "dense" or _installed(b)]
    assert n["S"].backend == installed[0]


def _installed(backend: str) -> bool:
    module = {"cholmod": "sksparse.cholmod", "cholespy": "cholespy", "scipy": "scipy.sparse.linalg"}[backend]
    try:
        __import__(module)
    except ImportError:
        return False
    return True


def test_page_guide__regression(tmp_path, capsys):
    n, _ = run_page("guide/regression.md", tmp_path, capsys)
    fit = n["fit"]
    assert n["y"].batch_shape == (20, 25)
    assert fit.origin.batch_shape == (20,) and fit.coefficients[..., 0, :].shape == (20, 6)
    assert fit.converged.all()
    assert fit(torch.tensor([1.5], dtype=torch.float64)).batch_shape == (20, 1)
    # "clock rate iota (8,) = 1"
    rate = n["wl"].coefficients[..., 0, 9]
    torch.testing.assert_close(rate, torch.ones(8, dtype=torch.float64), rtol=0, atol=1e-10)
    # "R^2 >= 0"
    reg = n["reg"]
    assert (reg.r_squared(n["y"], n["geo"](n["sim"].times[0]), n["w"]) >= 0).all()


def test_page_guide__robots(tmp_path, capsys):
    needs_robot_data()
    pytest.importorskip("yourdfpy")
    pytest.importorskip("pytorch_kinematics")
    n, _ = run_page("guide/robots.md", tmp_path, capsys)
    arm, s = n["arm"], n["s"]
    assert arm.end_link == "panda_hand_tcp" and arm.n_joints == 7
    assert n["ur5"].end_link == "tool0" and n["ur5"].n_joints == 6
    assert n["mdh"].n_joints == 4 and n["dh"].n_joints == 4
    assert s.pose.batch_shape == (10000,) and s.extended_pose.batch_shape == (10000,)
    assert arm.forward(n["q"][:3], n["qd"][:3], all_links=True).pose.batch_shape[0] == 3
    # IK: success is decided by the tolerances; the Panda reaches about 92% with 4 seeds
    res = n["res"]
    assert res.q.shape == (100, 7) and res.success.shape == (100,)
    assert (res.position_error[res.success] <= 1e-4).all() and (res.rotation_error[res.success] <= 1e-3).all()
    assert res.success_rate >= 0.9
    assert arm.within_limits(res.q).all()


def test_page_guide__threads(tmp_path, capsys, monkeypatch):
    import torchsgal

    # "sets torch.set_num_threads to the number of idle cores ... at least one, and returns it":
    # the call the page makes is observed (run_page restores the thread count afterwards)
    calls = []
    original = torchsgal.load.use_threads_for_load

    def observed(*args, **kwargs):
        count = original(*args, **kwargs)
        calls.append((count, torch.get_num_threads()))
        return count

    monkeypatch.setattr(torchsgal.load, "use_threads_for_load", observed)
    run_page("guide/threads.md", tmp_path, capsys)
    assert len(calls) == 1
    count, set_to = calls[0]
    assert count == set_to and 1 <= count <= (os.cpu_count() or 1)


def test_page_guide__training(tmp_path, capsys):
    n, out = run_page("guide/training.md", tmp_path, capsys)
    # "small: the poses are found"
    error = float(re.search(r"tensor\(([-0-9.e+]+)", out).group(1))
    assert error < 1e-5
    assert n["observed"].shape == (8, 50, 3)


def test_page_guide__uncertainty(tmp_path, capsys):
    n, _ = run_page("guide/uncertainty.md", tmp_path, capsys)
    d, F = n["d"], n["F"]
    assert F.batch_shape == (1200,)
    # the density is "the same on either side"
    left = d.to_side("left")
    torch.testing.assert_close(left.log_prob(F), d.log_prob(F), rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(left.mahalanobis(F), d.mahalanobis(F), rtol=1e-10, atol=1e-10)
