"""Factor graphs (torchsgal.estimation.graph): Jacobians of the built-in factors against
forward mode and finite differences, the engine's normal equations, a user factor (rigid fit)
against the closed form, robust fits, statuses, the sparse path, host syncs and input errors
(comparisons with GTSAM: ``test_factor_graph_gtsam.py``).  The problem generators here are
shared with that file and ``benchmarks/bench_factor_graph.py``."""
import numpy as np
import pytest
import torch
from host_syncs import solve_loop_reads
from peers import gtsam_map

import torchsgal as ts
from torchsgal.estimation import SolverStatus
from torchsgal.estimation import graph as fg
from torchsgal.estimation.graph import factors as F
from torchsgal.estimation.graph.layout import dense
from torchsgal.estimation.graph.linearize import Problem, evaluate_cost, linearize

f64 = torch.float64


def _elements(G, shape, gen, scale=0.5):
    return G.exp(scale * torch.randn(*shape, G.dof, generator=gen, dtype=f64))


def _rplus_fd(fn, elements, eps=1e-6):
    """Central finite differences of fn(*elements) (..., m) with respect to the right
    perturbation of each element: a list of (..., m, dof)."""
    out = []
    for k, g in enumerate(elements):
        cols = []
        for a in range(g.dof):
            d = torch.zeros(g.batch_shape + (g.dof,), dtype=f64)
            d[..., a] = eps
            plus = [e.rplus(d) if n == k else e for n, e in enumerate(elements)]
            minus = [e.rplus(-d) if n == k else e for n, e in enumerate(elements)]
            cols.append((fn(*plus) - fn(*minus)) / (2 * eps))
        out.append(torch.stack(cols, dim=-1))
    return out


def _rplus_jacfwd(fn, elements):
    """Forward-mode Jacobians of d -> fn(g_k exp(d_k)) at d = 0 (torch.func.jacfwd through exp)."""
    out = []
    for k, g in enumerate(elements):
        def moved(d, k=k):
            return fn(*[e.rplus(d) if n == k else e for n, e in enumerate(elements)])
        zero = torch.zeros(g.dof, dtype=f64)
        out.append(torch.func.jacfwd(moved)(zero))
    return out


@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=lambda G: G.__name__)
def test_between_and_prior_jacobians_match_forward_mode_and_finite_differences(G):
    gen = torch.Generator().manual_seed(1)
    for _ in range(3):
        Ti, Tj, Z = (_elements(G, (), gen) for _ in range(3))
        r, (Ji, Jj) = F._between_jacobians(Ti, Tj, Z)
        fwd = _rplus_jacfwd(F._between_residual, [Ti, Tj, Z])
        fd = _rplus_fd(F._between_residual, [Ti, Tj, Z])
        for J, Jf, Jd in zip((Ji, Jj), fwd, fd):
            torch.testing.assert_close(J, Jf, rtol=1e-10, atol=1e-10)
            torch.testing.assert_close(J, Jd, rtol=1e-7, atol=1e-7)
        torch.testing.assert_close(r, (Z.inverse() @ Ti.inverse() @ Tj).log())
        r, (J,) = F._prior_jacobians(Ti, Z)
        torch.testing.assert_close(J, _rplus_jacfwd(F._prior_residual, [Ti, Z])[0], rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(J, _rplus_fd(F._prior_residual, [Ti, Z])[0], rtol=1e-7, atol=1e-7)


@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=lambda G: G.__name__)
def test_engine_forward_mode_normal_equations_match_analytic_factors(G):
    """The same pose graph with the built-in factors (analytic Jacobians) and with user
    factors of the same residual (forward-mode autodiff in the engine): equal H, g, cost."""
    gen = torch.Generator().manual_seed(2)
    B, N = 3, 5
    x = _elements(G, (B, N), gen, 1.0)
    i, j = torch.tensor([0, 1, 2, 3, 0]), torch.tensor([1, 2, 3, 4, 3])
    Z = _elements(G, (B, 5), gen, 1.0)
    L = torch.randn(5, G.dof, G.dof, generator=gen, dtype=f64) + 3 * torch.eye(G.dof, dtype=f64)
    graphs = []
    for analytic in (True, False):
        graph = fg.FactorGraph()
        graph.add_variable("x", x)
        if analytic:
            graph.add(fg.Between("x", i, j, Z, sqrt_information=L))
            graph.add(fg.Prior("x", 0, Z[:, :1]))
        else:
            graph.add(fg.Factor(F._between_residual, [("x", i), ("x", j)], [Z], dim=G.dof,
                                sqrt_information=L))
            graph.add(fg.Factor(F._prior_residual, [("x", 0)], [Z[:, :1]], dim=G.dof))
        graphs.append(graph)
    lins = []
    for graph in graphs:
        p = Problem(graph)
        lin = linearize(p, p.initial(graph))
        lins.append((dense(p.layout, lin.values), lin.g, lin.cost))
    for a, b in zip(*lins):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-9)
    # and against finite differences of the cost's gradient: g = dC/dd
    p = Problem(graphs[0])
    x0 = p.initial(graphs[0])
    eps, k = 1e-6, p.D - 2
    d = torch.zeros(B, p.D, dtype=f64)
    d[:, k] = eps
    fd = (evaluate_cost(p, p.retract(x0, d)) - evaluate_cost(p, p.retract(x0, -d))) / (2 * eps)
    torch.testing.assert_close(lins[0][1][:, k], fd, rtol=1e-6, atol=1e-6)


# ----------------------------------------------------------------- pose graphs vs GTSAM
EDGES_I = torch.tensor([0, 1, 2, 3, 4, 5, 6, 0, 2, 1])
EDGES_J = torch.tensor([1, 2, 3, 4, 5, 6, 7, 4, 6, 7])
SIGMA = torch.tensor([0.05, 0.05, 0.05, 0.02, 0.02, 0.02], dtype=f64)


def pose_graphs(B=64, N=8, seed=0, init_noise=0.3):
    """B small SE(3) pose graphs: N poses, 10 relative-pose edges, a prior on pose 0."""
    gen = torch.Generator().manual_seed(seed)
    truth = ts.SE3.exp(torch.randn(B, N, 6, generator=gen, dtype=f64)
                       * torch.tensor([2.0, 2, 2, 0.5, 0.5, 0.5], dtype=f64))
    Z = (truth[:, EDGES_I].inverse() @ truth[:, EDGES_J]
         @ ts.SE3.exp(torch.randn(B, len(EDGES_I), 6, generator=gen, dtype=f64) * SIGMA))
    x0 = truth @ ts.SE3.exp(torch.randn(B, N, 6, generator=gen, dtype=f64) * init_noise)
    return truth, Z, truth[:, :1], x0


def _graph(Z, Z0, x0, prior=True):
    W = torch.diag(SIGMA ** -2)
    graph = fg.FactorGraph()
    graph.add_variable("x", x0)
    if prior:
        graph.add(fg.Prior("x", 0, Z0, information=W))
    graph.add(fg.Between("x", EDGES_I, EDGES_J, Z, information=W))
    return graph


def _gtsam_graph(Z, Z0, b):
    import gtsam

    P = gtsam_map.PERM["SE3"]
    noise = gtsam.noiseModel.Gaussian.Information(torch.diag(SIGMA ** -2).numpy()[np.ix_(P, P)])
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(Z0[b, 0].as_matrix().numpy()), noise))
    for e in range(len(EDGES_I)):
        graph.add(gtsam.BetweenFactorPose3(int(EDGES_I[e]), int(EDGES_J[e]),
                                           gtsam.Pose3(Z[b, e].as_matrix().numpy()), noise))
    return graph


def _gtsam_values(x0, b):
    import gtsam

    values = gtsam.Values()
    for n in range(x0.batch_shape[1]):
        values.insert(n, gtsam.Pose3(x0[b, n].as_matrix().numpy()))
    return values


def test_gauge_freedom_converges_rank_deficient_not_failure():
    _, Z, Z0, x0 = pose_graphs(B=4, seed=4)
    tight = dict(relative_error_tol=1e-12, absolute_error_tol=1e-12)
    result = fg.levenberg_marquardt(_graph(Z, Z0, x0, prior=False), **tight)
    rep = result.report
    assert (rep.status == SolverStatus.CONVERGED_RANK_DEFICIENT).all(), rep.status
    # the relative poses are still estimated: the same as with the prior.  Each solve stops where
    # a step changes the cost by a few eps of itself (~1e-14 here), and rounding decides whether
    # that last step is taken: it moves the poses by up to ~1e-8 at these costs' curvature, the
    # resolution of a float64 cost, so the two solutions are compared to 1e-7.
    anchored = fg.levenberg_marquardt(_graph(Z, Z0, x0), **tight).values["x"]
    free = result.values["x"]
    rel_free = free[:, :1].inverse() @ free
    rel_anchored = anchored[:, :1].inverse() @ anchored
    torch.testing.assert_close(rel_free.as_matrix(), rel_anchored.as_matrix(), rtol=0, atol=1e-7)
    assert torch.isnan(result.marginal_covariance("x", 0)).all()
    assert rep.cost.lt(rep.initial_cost).all()


def test_unbatched_graph_returns_unbatched_values():
    _, Z, Z0, x0 = pose_graphs(B=1, seed=5)
    graph = fg.FactorGraph()
    graph.add_variable("x", x0[0])
    W = torch.diag(SIGMA ** -2)
    graph.add(fg.Prior("x", 0, Z0[0], information=W))
    graph.add(fg.Between("x", EDGES_I, EDGES_J, Z[0], information=W))
    result = fg.levenberg_marquardt(graph)
    batched = fg.levenberg_marquardt(_graph(Z, Z0, x0))
    assert result.values["x"].batch_shape == (8,)
    torch.testing.assert_close(result.values["x"].as_matrix(), batched.values["x"].as_matrix()[0])
    assert result.marginal_covariance("x").shape == (8, 6, 6)
    assert x0.as_matrix().equal(_graph(Z, Z0, x0).variables["x"].as_matrix())  # input not mutated


def test_dense_marginals_are_the_blocks_of_the_inverse_information():
    """The batched marginals (solves with the needed unit columns) against the diagonal blocks
    of inv(H), for indices in any order and repeated."""
    _, Z, Z0, x0 = pose_graphs(B=3, seed=7)
    result = fg.levenberg_marquardt(_graph(Z, Z0, x0))
    P = torch.linalg.inv(result.information)
    index = torch.tensor([6, 1, 1, 7])
    expected = torch.stack([P[:, 6 * n:6 * n + 6, 6 * n:6 * n + 6] for n in index.tolist()], dim=1)
    torch.testing.assert_close(result.marginal_covariance("x", index), expected, rtol=1e-10, atol=0)
    assert result.marginal_covariance("x", torch.zeros(0, dtype=torch.int64)).shape == (3, 0, 6, 6)


# ----------------------------------------------------------------- a user factor
def _kabsch(p, q):
    """Closed-form argmin_T sum |T p - q|^2 (Umeyama without scale)."""
    mp, mq = p.mean(-2, keepdim=True), q.mean(-2, keepdim=True)
    S = (q - mq).mT @ (p - mp)
    U, _, Vh = torch.linalg.svd(S)
    d = torch.linalg.det(U @ Vh)
    D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], -1))
    C = U @ D @ Vh
    r = mq.squeeze(-2) - (C @ mp.mT).squeeze(-1)
    return ts.SE3.from_components(C, r)


def rigid_fit_problem(B=256, K=100, seed=0, noise=0.01, outliers=0):
    gen = torch.Generator().manual_seed(seed)
    T = ts.SE3.exp(torch.randn(B, 6, generator=gen, dtype=f64))
    p = torch.randn(B, K, 3, generator=gen, dtype=f64)
    q = T[:, None].act(p) + noise * torch.randn(B, K, 3, generator=gen, dtype=f64)
    if outliers:
        q[:, :outliers] += 5.0 * torch.randn(B, outliers, 3, generator=gen, dtype=f64)
    return T, p, q


def rigid_fit_graph(p, q, loss=None):
    B, K = p.shape[:2]
    graph = fg.FactorGraph()
    graph.add_variable("T", ts.SE3.identity((B, 1), dtype=f64))
    graph.add(fg.Factor(lambda T, a, b: T.act(a) - b, [("T", torch.zeros(K, dtype=torch.int64))],
                        [p, q], dim=3), loss=loss)
    return graph


def test_user_factor_rigid_fit_matches_closed_form():
    _, p, q = rigid_fit_problem()
    result = fg.levenberg_marquardt(rigid_fit_graph(p, q), relative_error_tol=1e-10, absolute_error_tol=0)
    expected = _kabsch(p, q)
    assert (result.report.status == SolverStatus.CONVERGED).all()
    torch.testing.assert_close(result.values["T"][:, 0].as_matrix(), expected.as_matrix(), rtol=0, atol=1e-9)


def test_robust_loss_recovers_a_pose_that_the_plain_loss_does_not():
    T, p, q = rigid_fit_problem(B=8, K=60, seed=6, noise=0.005, outliers=15)
    plain = fg.levenberg_marquardt(rigid_fit_graph(p, q)).values["T"][:, 0]
    robust = fg.levenberg_marquardt(rigid_fit_graph(p / 1, q, loss=fg.Cauchy(0.02))).values["T"][:, 0]
    err_plain = T.rminus(plain).norm(dim=-1)
    err_robust = T.rminus(robust).norm(dim=-1)
    assert (err_robust < 5e-3).all(), err_robust
    assert (err_plain > 5e-2).all(), err_plain


# ----------------------------------------------------------------- errors
def test_bad_input_names_the_argument():
    _, Z, Z0, x0 = pose_graphs(B=2)
    graph = fg.FactorGraph()
    graph.add_variable("x", x0)
    with pytest.raises(ValueError, match="already"):
        graph.add_variable("x", x0)
    with pytest.raises(ValueError, match="batch of 3"):
        graph.add_variable("y", ts.SE3.identity((3, 2), dtype=f64))
    with pytest.raises(KeyError, match="'z'"):
        graph.add(fg.Prior("z", 0, Z0))
    with pytest.raises(IndexError, match=r"\[0, 8\)"):
        graph.add(fg.Between("x", torch.tensor([0]), torch.tensor([8]), Z[:, :1]))
    with pytest.raises(TypeError, match="measured"):
        fg.Prior("x", 0, torch.eye(4, dtype=f64))
    with pytest.raises(TypeError, match="index"):
        fg.Prior("x", torch.tensor([0.0]), Z0)
    with pytest.raises(ValueError, match="not both"):
        fg.Prior("x", 0, Z0, information=torch.eye(6, dtype=f64), sqrt_information=torch.eye(6, dtype=f64))
    with pytest.raises(ValueError, match="information"):  # of another size: refused at once
        fg.Prior("x", 0, Z0, information=torch.eye(5, dtype=f64))
    with pytest.raises(ValueError, match="max_iterations"):
        fg.levenberg_marquardt(_graph(Z, Z0, x0), max_iterations=-1)
    with pytest.raises(TypeError, match="diagonal_damping"):
        fg.levenberg_marquardt(_graph(Z, Z0, x0), diagonal_damping=1)
    bad = fg.FactorGraph()
    bad.add_variable("x", x0)
    bad.add(fg.Prior("x", 0, Z0, information=-torch.eye(6, dtype=f64)))
    with pytest.raises(ValueError, match="positive definite"):
        fg.levenberg_marquardt(bad)


def test_non_finite_start_is_reported_per_problem():
    _, Z, Z0, x0 = pose_graphs(B=3)
    m = x0.as_matrix().clone()
    m[1, 2, 0, 3] = float("nan")
    result = fg.levenberg_marquardt(_graph(Z, Z0, ts.SE3(m)))
    st = result.report.status.tolist()
    assert st[1] == SolverStatus.NON_FINITE and st[0] == st[2] == SolverStatus.CONVERGED
    assert torch.isnan(result.report.cost[1]) and torch.isfinite(result.report.cost[[0, 2]]).all()


@pytest.mark.parametrize("backend", ["sparse", "scipy"])
def test_sparse_linear_solver_matches_dense(backend):
    from torchsgal.estimation.sparse import available_backends

    assert backend == "sparse" or backend in available_backends()
    _, Z, Z0, x0 = pose_graphs(B=1, seed=7)
    W = torch.diag(SIGMA ** -2)
    results = {}
    for solver in ("dense", backend):
        graph = fg.FactorGraph()
        graph.add_variable("x", x0[0])
        graph.add(fg.Prior("x", 0, Z0[0], information=W))
        graph.add(fg.Between("x", EDGES_I, EDGES_J, Z[0], information=W))
        results[solver] = fg.levenberg_marquardt(graph, linear_solver=solver)
        results["gn " + solver] = fg.gauss_newton(graph, linear_solver=solver)
    a, b = results["dense"], results[backend]
    gn_a, gn_b = results["gn dense"], results["gn " + backend]
    assert gn_a.report.iterations.tolist() == gn_b.report.iterations.tolist()
    torch.testing.assert_close(gn_b.report.cost, gn_a.report.cost, rtol=1e-10, atol=0)
    assert type(b.system).__name__ == "SparseSystem"
    assert a.report.iterations.tolist() == b.report.iterations.tolist()
    torch.testing.assert_close(b.report.cost, a.report.cost, rtol=1e-10, atol=0)
    torch.testing.assert_close(b.values["x"].as_matrix(), a.values["x"].as_matrix(), rtol=0, atol=1e-10)
    torch.testing.assert_close(b.marginal_covariance("x", [1, 6]), a.marginal_covariance("x", [1, 6]),
                               rtol=1e-8, atol=1e-14)
    # without the prior: rank-deficient through the sparse factorisation too
    graph = fg.FactorGraph()
    graph.add_variable("x", x0[0])
    graph.add(fg.Between("x", EDGES_I, EDGES_J, Z[0], information=W))
    free = fg.levenberg_marquardt(graph, linear_solver=backend)
    assert free.report.status.item() == SolverStatus.CONVERGED_RANK_DEFICIENT
    assert torch.isnan(free.marginal_covariance("x", 0)).all()
    with pytest.raises(ValueError, match="linear_solver"):
        fg.levenberg_marquardt(graph, linear_solver="qr")
    with pytest.raises(ValueError, match="one problem"):
        fg.levenberg_marquardt(_graph(Z, Z0, x0.expand(2, 8)), linear_solver="sparse")


def test_point_observations_recover_poses_and_points():
    """Poses (two with priors) observing points: noise-free data, the solution reproduces the
    truth; the engine's gradient of the point block matches finite differences."""
    gen = torch.Generator().manual_seed(9)
    B, N, M = 2, 4, 12
    poses = ts.SE3.exp(torch.randn(B, N, 6, generator=gen, dtype=f64))
    points = 3 * torch.randn(B, M, 3, generator=gen, dtype=f64)
    i = torch.arange(N).repeat_interleave(M)
    j = torch.arange(M).repeat(N)
    z = poses[:, i].inverse().act(points[:, j])  # points seen in the pose frames: T^-1 p
    graph = fg.FactorGraph()
    graph.add_variable("T", poses.inverse() @ ts.SE3.exp(0.1 * torch.randn(B, N, 6, generator=gen, dtype=f64)))
    graph.add_variable("p", points + 0.2 * torch.randn(B, M, 3, generator=gen, dtype=f64))
    graph.add(fg.Prior("T", torch.tensor([0, 1]), poses[:, :2].inverse(), information=1e4 * torch.eye(6, dtype=f64)))
    graph.add(fg.PointObservation("T", i, "p", j, z, sqrt_information=10 * torch.eye(3, dtype=f64)))
    p = Problem(graph)
    x = p.initial(graph)
    lin = linearize(p, x)
    k = p.variables[1].offset + 7  # a coordinate of the point block
    d = torch.zeros(B, p.D, dtype=f64)
    d[:, k] = 1e-6
    fd = (evaluate_cost(p, p.retract(x, d)) - evaluate_cost(p, p.retract(x, -d))) / 2e-6
    torch.testing.assert_close(lin.g[:, k], fd, rtol=1e-6, atol=1e-6)
    result = fg.levenberg_marquardt(graph, relative_error_tol=0, absolute_error_tol=1e-20, error_tol=1e-20)
    assert (result.report.status == SolverStatus.CONVERGED).all(), result.report.status
    torch.testing.assert_close(result.values["T"].as_matrix(), poses.inverse().as_matrix(), rtol=0, atol=1e-8)
    torch.testing.assert_close(result.values["p"], points, rtol=0, atol=1e-8)


@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=lambda G: G.__name__)
def test_point_observation_jacobians_are_the_forward_mode_ones(G):
    """PointObservation's analytic Jacobians (act_jacobians) give the normal equations of the
    same residual differentiated in forward mode, with one pose read by every factor and with
    a pose per factor."""
    gen = torch.Generator().manual_seed(17)
    B, N, M = 2, 3, 8
    poses = G.exp(torch.randn(B, N, G.dof, generator=gen, dtype=f64))
    points = torch.randn(B, M, G.point_dim, generator=gen, dtype=f64)
    z = torch.randn(B, 2 * M, G.point_dim, generator=gen, dtype=f64)
    i = torch.cat([torch.zeros(M, dtype=torch.int64), torch.arange(M) % N])
    j = torch.cat([torch.arange(M), torch.arange(M)])
    W = torch.eye(G.point_dim, dtype=f64) * 4
    lins = []
    for analytic in (True, False):
        graph = fg.FactorGraph()
        graph.add_variable("T", poses)
        graph.add_variable("p", points)
        if analytic:
            graph.add(fg.PointObservation("T", i, "p", j, z, information=W))
        else:
            graph.add(fg.Factor(lambda T, p, zz: T.act(p) - zz, [("T", i), ("p", j)], [z],
                                dim=G.point_dim, information=W))
        problem = Problem(graph)
        assert (problem.blocks[0].factor.jacobians is not None) == analytic
        lins.append(linearize(problem, problem.initial(graph)))
    torch.testing.assert_close(lins[0].values, lins[1].values, rtol=1e-13, atol=1e-12)
    torch.testing.assert_close(lins[0].g, lins[1].g, rtol=1e-13, atol=1e-12)
    torch.testing.assert_close(lins[0].cost, lins[1].cost, rtol=1e-14, atol=0)


def test_per_problem_per_factor_noise_and_cost_by_hand():
    """Square-root information (B, E, m, m): the cost is 1/2 sum |L r|^2, summed here factor by
    factor with the group operations."""
    _, Z, Z0, x0 = pose_graphs(B=3, seed=10)
    gen = torch.Generator().manual_seed(10)
    L = torch.randn(3, 10, 6, 6, generator=gen, dtype=f64) + 4 * torch.eye(6, dtype=f64)
    W0 = torch.diag(SIGMA ** -2)
    graph = fg.FactorGraph()
    graph.add_variable("x", x0)
    graph.add(fg.Prior("x", 0, Z0, information=W0))
    graph.add(fg.Between("x", EDGES_I, EDGES_J, Z, sqrt_information=L))
    result = fg.levenberg_marquardt(graph, max_iterations=0)
    assert (result.report.status == SolverStatus.MAX_ITERATIONS).all()
    for b in range(3):
        expected = 0.0
        r0 = Z0[b, 0].inverse().compose(x0[b, 0]).log()
        expected += 0.5 * float(r0 @ W0 @ r0)
        for e in range(10):
            r = (Z[b, e].inverse() @ x0[b, int(EDGES_I[e])].inverse() @ x0[b, int(EDGES_J[e])]).log()
            expected += 0.5 * float(((L[b, e] @ r) ** 2).sum())
        assert abs(float(result.report.cost[b]) - expected) <= 1e-12 * expected
    solved = fg.levenberg_marquardt(graph)
    assert (solved.report.status == SolverStatus.CONVERGED).all()
    assert (solved.report.cost < result.report.cost).all()


def test_residual_shape_is_checked():
    _, Z, Z0, x0 = pose_graphs(B=2)
    graph = fg.FactorGraph()
    graph.add_variable("x", x0)
    graph.add(fg.Factor(lambda T, Zk: Zk.rminus(T)[..., :3], [("x", 0)], [Z0], dim=6))
    with pytest.raises(ValueError, match=r"expected \(\.\.\., 6\)"):
        fg.levenberg_marquardt(graph)


def test_host_syncs_are_one_per_round_outside_the_setup():
    """The solve loop reads one value per round (how many problems still run) and the active
    set's indices when it shrinks; linearisation, retraction and the dense solves read none."""
    _, Z, Z0, x0 = pose_graphs(B=16, seed=11)
    graph = _graph(Z, Z0, x0)
    result, in_hot, loop = solve_loop_reads(lambda: fg.levenberg_marquardt(graph))
    assert not in_hot, in_hot
    rounds = int(result.report.iterations.max()) + 2
    assert 0 < len(loop) <= 2 * rounds, loop


def test_float32_and_inputs_that_require_grad():
    """float32 graphs solve to the float64 optimum within float32 accuracy; inputs that require
    gradients give detached results and are left as they were (values, the factor's loss).
    float32 residuals resolve the cost to about 1e-6 of itself, so where a float32 solve stops
    inside the relative tolerance 1e-5 is decided by rounding: the cost is the quantity held to
    that tolerance (in float64, at the float32 solution), and the poses then lie within
    sqrt(2 dcost / lambda_min(H)) of the optimum (up to 3e-4 here)."""
    _, Z, Z0, x0 = pose_graphs(B=4, seed=12)
    solved = fg.levenberg_marquardt(_graph(Z, Z0, x0))
    ref = solved.values["x"]
    W = torch.diag(SIGMA ** -2).float()
    graph = fg.FactorGraph()
    graph.add_variable("x", ts.SE3(x0.as_matrix().float()))
    graph.add(fg.Prior("x", 0, ts.SE3(Z0.as_matrix().float()), information=W))
    between = fg.Between("x", EDGES_I, EDGES_J, ts.SE3(Z.as_matrix().float()), information=W)
    graph.add(between, loss=fg.Huber(100.0))
    result = fg.levenberg_marquardt(graph)
    assert between.loss is None
    assert (result.report.status == SolverStatus.CONVERGED).all()
    assert result.values["x"].dtype == torch.float32
    at_f32 = ts.SE3(result.values["x"].as_matrix().double())
    cost = fg.levenberg_marquardt(_graph(Z, Z0, at_f32), max_iterations=0).report.cost
    assert ((cost - solved.report.cost) / solved.report.cost).abs().max() < 1e-5
    torch.testing.assert_close(at_f32.as_matrix(), ref.as_matrix(), rtol=0, atol=5e-4)
    m = x0.as_matrix().clone().requires_grad_(True)
    before = m.detach().clone()
    graph = fg.FactorGraph()
    graph.add_variable("x", ts.SE3(m))
    graph.add(fg.Prior("x", 0, Z0, information=torch.diag(SIGMA ** -2).requires_grad_(True)))
    graph.add(fg.Between("x", EDGES_I, EDGES_J, Z, information=torch.diag(SIGMA ** -2)))
    out = fg.levenberg_marquardt(graph)
    assert not out.values["x"].as_matrix().requires_grad and not out.report.cost.requires_grad
    assert torch.equal(m.detach(), before)
    torch.testing.assert_close(out.values["x"].as_matrix(), ref.as_matrix(), rtol=0, atol=1e-12)


def test_one_pose_read_by_every_factor_beside_per_factor_points():
    """A slot whose factors all read one element (passed with batch (B, 1)) beside a slot with
    one element per factor: gradient and information against finite differences of the cost."""
    gen = torch.Generator().manual_seed(13)
    B, M = 3, 9
    T = ts.SE3.exp(torch.randn(B, 1, 6, generator=gen, dtype=f64))
    points = torch.randn(B, M, 3, generator=gen, dtype=f64)
    z = T.act(points) + 0.05 * torch.randn(B, M, 3, generator=gen, dtype=f64)
    graph = fg.FactorGraph()
    graph.add_variable("T", T @ ts.SE3.exp(0.1 * torch.randn(B, 1, 6, generator=gen, dtype=f64)))
    graph.add_variable("p", points + 0.1 * torch.randn(B, M, 3, generator=gen, dtype=f64))
    graph.add(fg.PointObservation("T", torch.zeros(M, dtype=torch.int64), "p", torch.arange(M), z))
    graph.add(fg.Factor(lambda p, q: p - q, [("p", torch.arange(M))], [points], dim=3))
    p = Problem(graph)
    assert p.blocks[0].uniform == [0, None] and not p.blocks[0].reduced
    x = p.initial(graph)
    lin = linearize(p, x)
    H = dense(p.layout, lin.values)
    eps = 1e-5
    for k in (2, 4, 6 + 5):  # pose translation and rotation coordinates, a point coordinate
        d = torch.zeros(B, p.D, dtype=f64)
        d[:, k] = eps
        up, down = linearize(p, p.retract(x, d)), linearize(p, p.retract(x, -d))
        torch.testing.assert_close(lin.g[:, k], (up.cost - down.cost) / (2 * eps), rtol=1e-6, atol=1e-8)
        if k >= 6:  # the point rows of g = J^T r are linear in the points: H's column there
            torch.testing.assert_close(H[:, 6:, k], (up.g - down.g)[:, 6:] / (2 * eps), rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("kind", ["DenseSystem", "BlockSparseSystem"])
def test_rank_test_flags_non_finite_information_per_problem(kind):
    """``singular`` at a solution whose H has one infinite or NaN off-diagonal entry (its
    diagonal and Cholesky pivots untouched in the other problems): exactly those problems are
    flagged, whichever triangle the entry is in (the block system stores one)."""
    from torchsgal.estimation.graph import linear_system

    _, Z, Z0, x0 = pose_graphs(B=4, seed=13)
    problem = Problem(_graph(Z, Z0, x0))
    system = getattr(linear_system, kind)(problem)
    values = linearize(problem, problem.initial(_graph(Z, Z0, x0)), system.layout).values
    rows, cols = problem.h_index // problem.D, problem.h_index % problem.D
    for upper in (True, False):  # an entry off the diagonal blocks, in either triangle
        far = ((rows - cols).abs() > 6) & ((rows < cols) if upper else (rows > cols))
        k = int(system.layout.slots[int(far.nonzero()[0, 0])])  # its column in the layout
        v = values.clone()
        v[1, k], v[2, k], v[3, k] = float("inf"), float("nan"), -float("inf")
        system.set_solution(v)
        assert system.singular().tolist() == [False, True, True, True], upper


@pytest.mark.parametrize("linear_solver", ["dense", "block", "sparse"])
def test_float32_graph_with_standard_deviations_100_apart_is_full_rank(linear_solver):
    """A prior of sigma 0.01 and betweens of sigma 1 (diagonal entries 1e4 apart): the
    diagonal test flags only entries within eps of the largest, the level of a direction no
    residual sees (it flagged entries within 1e3 eps, 1.2e-4 in float32: this graph came back
    CONVERGED_RANK_DEFICIENT with NaN marginals); the marginals equal float64's.  A variable no
    factor reads is still flagged."""
    gen = torch.Generator().manual_seed(0)
    x64 = ts.SE3.exp(0.3 * torch.randn(3, 6, dtype=torch.float64, generator=gen))
    marginals = {}
    for dt in (torch.float64, torch.float32):
        x = x64.to(dt)
        graph = fg.FactorGraph()
        graph.add_variable("x", x)
        graph.add(fg.Prior("x", 0, x[:1], information=1e4 * torch.eye(6, dtype=dt)))
        graph.add(fg.Between("x", torch.tensor([0, 1]), torch.tensor([1, 2]), x[:2].inverse() @ x[1:],
                             information=torch.eye(6, dtype=dt)))
        result = fg.levenberg_marquardt(graph, linear_solver=linear_solver)
        assert result.report.status.tolist() == [int(SolverStatus.CONVERGED)], dt
        marginals[dt] = result.marginal_covariance("x", torch.tensor([2]))[0]
    torch.testing.assert_close(marginals[torch.float32].double(), marginals[torch.float64], rtol=1e-4, atol=1e-6)
    graph = fg.FactorGraph()
    graph.add_variable("x", x64.to(torch.float32))
    graph.add_variable("unseen", torch.zeros(1, 2))
    graph.add(fg.Prior("x", torch.arange(3), x64.to(torch.float32), information=torch.eye(6)))
    graph.add(fg.Factor(lambda v: 0.0 * v, variables=[("unseen", torch.zeros(1, dtype=torch.int64))], dim=2))
    status = fg.levenberg_marquardt(graph, linear_solver=linear_solver).report.status
    assert status.tolist() == [int(SolverStatus.CONVERGED_RANK_DEFICIENT)]
