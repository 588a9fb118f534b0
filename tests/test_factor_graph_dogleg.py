"""``dogleg`` against GTSAM's ``DoglegOptimizer`` on the batch of small SE(3) pose graphs of
``test_factor_graph_gtsam`` (final costs, iteration counts, poses, statuses), with a robust
loss, the sparse solve against the dense one, a gauge freedom, gradients and bad arguments."""
import numpy as np
import pytest
import torch
from peers import gtsam_map
from test_factor_graph import EDGES_I, EDGES_J, SIGMA, _graph, _gtsam_graph, _gtsam_values, pose_graphs

import torchsgal as ts
from torchsgal.estimation import SolverStatus
from torchsgal.estimation import graph as fg

f64 = torch.float64


def _gtsam_dogleg(graph, values, delta_initial=1.0):
    gtsam = pytest.importorskip("gtsam")

    params = gtsam.DoglegParams()
    params.setDeltaInitial(delta_initial)
    opt = gtsam.DoglegOptimizer(graph, values, params)
    result = opt.optimize()
    return graph.error(result), opt.iterations(), result


@pytest.mark.parametrize("case", ["near", "far", "far-small-delta", "far-large-delta"])
def test_pose_graphs_match_gtsam_dogleg(case):
    """far: initial poses ~1 rad and ~1 m off, where the trust region shrinks and some problems
    run to the iteration limit; Delta starting at 0.1, or at 100: full Gauss-Newton steps from
    far raise the cost, so Delta is halved and the same linearisation tried again (rho < 0)."""
    far = case != "near"
    delta0 = {"far-small-delta": 0.1, "far-large-delta": 100.0}.get(case, 1.0)
    _, Z, Z0, x0 = pose_graphs(seed=2 if far else 0, init_noise=1.0 if far else 0.3)
    result = fg.dogleg(_graph(Z, Z0, x0), delta_initial=delta0)
    costs, iterations, poses = [], [], []
    for b in range(Z.batch_shape[0]):
        g = _gtsam_graph(Z, Z0, b)
        cost, its, values = _gtsam_dogleg(g, _gtsam_values(x0, b), delta0)
        costs.append(cost)
        iterations.append(its)
        poses.append(np.stack([values.atPose3(n).matrix() for n in range(8)]))
    rep = result.report
    assert rep.iterations.tolist() == iterations
    if far:  # the far start exercises the retries and the iteration limit
        assert max(iterations) == 100 and min(iterations) < 100
    expected = [SolverStatus.MAX_ITERATIONS if n == 100 else SolverStatus.CONVERGED for n in iterations]
    assert rep.status.tolist() == expected
    torch.testing.assert_close(rep.cost, torch.tensor(costs, dtype=f64), rtol=1e-6, atol=0)
    torch.testing.assert_close(result.values["x"].as_matrix(), torch.tensor(np.stack(poses)),
                               rtol=0, atol=1e-8)
    g0 = _gtsam_graph(Z, Z0, 0)
    torch.testing.assert_close(rep.initial_cost[0], torch.tensor(g0.error(_gtsam_values(x0, 0)),
                                                                 dtype=f64), rtol=1e-12, atol=0)


def test_robust_pose_graphs_match_gtsam_dogleg():
    """Huber on the between factors (one corrupted edge per graph): the model decrease of the
    reweighted system, as GTSAM's Bayes net of the robust linearisation."""
    gtsam = pytest.importorskip("gtsam")

    _, Z, Z0, x0 = pose_graphs(B=16, seed=8, init_noise=0.3)
    m = Z.as_matrix().clone()
    m[:, 3] = (Z[:, 3] @ ts.SE3.exp(torch.tensor([0.5, -0.3, 0.2, 0.3, 0.2, -0.1], dtype=f64))).as_matrix()
    Z = ts.SE3(m)
    W = torch.diag(SIGMA ** -2)
    graph = fg.FactorGraph()
    graph.add_variable("x", x0)
    graph.add(fg.Prior("x", 0, Z0, information=W))
    graph.add(fg.Between("x", EDGES_I, EDGES_J, Z, information=W), loss=fg.Huber(2.0))
    result = fg.dogleg(graph)
    P = gtsam_map.PERM["SE3"]
    gauss = gtsam.noiseModel.Gaussian.Information(W.numpy()[np.ix_(P, P)])
    robust = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(2.0), gauss)
    costs, iterations = [], []
    for b in range(16):
        g = gtsam.NonlinearFactorGraph()
        g.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(Z0[b, 0].as_matrix().numpy()), gauss))
        for e in range(len(EDGES_I)):
            g.add(gtsam.BetweenFactorPose3(int(EDGES_I[e]), int(EDGES_J[e]),
                                           gtsam.Pose3(Z[b, e].as_matrix().numpy()), robust))
        cost, its, _ = _gtsam_dogleg(g, _gtsam_values(x0, b))
        costs.append(cost)
        iterations.append(its)
    torch.testing.assert_close(result.report.cost, torch.tensor(costs, dtype=f64), rtol=1e-6, atol=0)
    assert result.report.iterations.tolist() == iterations


def test_sparse_matches_dense():
    _, Z, Z0, x0 = pose_graphs(B=1, seed=2, init_noise=1.0)
    graph = _graph(Z[0], Z0[0], x0[0])
    a = fg.dogleg(graph, linear_solver="dense")
    b = fg.dogleg(graph, linear_solver="sparse")
    assert type(a.system).__name__ == "DenseSystem" and type(b.system).__name__ == "SparseSystem"
    assert a.report.iterations.item() > 5  # retries and a shrinking trust region on the way
    assert a.report.iterations.tolist() == b.report.iterations.tolist()
    torch.testing.assert_close(b.report.cost, a.report.cost, rtol=1e-10, atol=0)
    torch.testing.assert_close(b.values["x"].as_matrix(), a.values["x"].as_matrix(), rtol=0, atol=1e-10)
    torch.testing.assert_close(b.marginal_covariance("x", [1, 6]), a.marginal_covariance("x", [1, 6]),
                               rtol=1e-8, atol=1e-14)


@pytest.mark.parametrize("linear_solver", ["dense", "sparse"])
def test_gauge_freedom_converges_rank_deficient(linear_solver):
    """No prior: H is singular (6 gauge directions); the relative poses are those of the
    anchored graph and the status says the information is rank-deficient."""
    B = 4 if linear_solver == "dense" else 1
    _, Z, Z0, x0 = pose_graphs(B=B, seed=4)
    tight = dict(relative_error_tol=1e-12, absolute_error_tol=1e-12)
    if linear_solver == "sparse":
        Z, Z0, x0 = Z[0], Z0[0], x0[0]
    result = fg.dogleg(_graph(Z, Z0, x0, prior=False), linear_solver=linear_solver, **tight)
    rep = result.report
    assert (rep.status == SolverStatus.CONVERGED_RANK_DEFICIENT).all(), rep.status
    assert rep.cost.lt(rep.initial_cost).all()
    anchored = fg.dogleg(_graph(Z, Z0, x0), linear_solver=linear_solver, **tight)
    assert (anchored.report.status == SolverStatus.CONVERGED).all()
    free, fixed = result.values["x"], anchored.values["x"]
    rel_free = free[..., :1].inverse() @ free
    rel_fixed = fixed[..., :1].inverse() @ fixed
    torch.testing.assert_close(rel_free.as_matrix(), rel_fixed.as_matrix(), rtol=0, atol=1e-8)
    torch.testing.assert_close(rep.cost, anchored.report.cost, rtol=1e-9, atol=0)
    assert torch.isnan(result.marginal_covariance("x", 0)).all()


def test_trust_region_stops_at_minimum_delta():
    """A wall the linear model does not see: r = 1 + x for x > 0, larger for x <= 0.  Steps
    that cross it raise the cost, so Delta halves until it is <= 1e-5, where the iteration ends
    without a step (DoglegOptimizerImpl::Iterate) and the zero decrease converges: the last
    failed step of length Delta <= 1e-5 crossed the wall, so 0 < x <= 1e-5."""

    def walled(x):
        return torch.where(x > 0, 1 + x, 2 - 1000 * x)

    graph = fg.FactorGraph()
    graph.add_variable("x", torch.tensor([[[0.5]], [[0.8]]], dtype=f64))
    graph.add(fg.Factor(walled, variables=[("x", torch.zeros(1, dtype=torch.int64))], dim=1))
    result = fg.dogleg(graph, relative_error_tol=0.0, absolute_error_tol=0.0)
    x = result.values["x"].flatten()
    assert (result.report.status == SolverStatus.CONVERGED).all()
    assert (result.report.iterations < 100).all()
    assert (x > 0).all() and (x <= 1e-5).all(), x
    torch.testing.assert_close(result.report.cost, 0.5 * (1 + x) ** 2, rtol=1e-12, atol=0)


@pytest.mark.parametrize("backward_mode", ["implicit", "unroll"])
def test_gradient_matches_finite_differences(backward_mode):
    """d(solution)/d(measurement) against central differences of tightly converged solves, on
    consistent measurements (zero residual at the solution, where the implicit gradient's
    Gauss-Newton information is the exact Hessian); "unroll" differentiates the iterations."""
    truth, _, Z0, x0 = pose_graphs(B=2, seed=5)
    Z = truth[:, EDGES_I].inverse() @ truth[:, EDGES_J]
    W = torch.diag(SIGMA ** -2)
    tight = dict(relative_error_tol=1e-14, absolute_error_tol=1e-14)
    xi = torch.zeros(6, dtype=f64, requires_grad=True)

    def solve(perturbation, backward_mode):
        Zp = ts.SE3(torch.cat([(Z[:, :1] @ ts.SE3.exp(perturbation)).as_matrix(),
                               Z.as_matrix()[:, 1:]], dim=1))  # edge 0 perturbed
        graph = fg.FactorGraph()
        graph.add_variable("x", x0)
        graph.add(fg.Prior("x", 0, Z0, information=W))
        graph.add(fg.Between("x", EDGES_I, EDGES_J, Zp, information=W))
        return fg.dogleg(graph, backward_mode=backward_mode, **tight).values["x"]

    out = solve(xi, backward_mode)[:, 7].log()[:, 3]  # a rotation coordinate of the last pose
    (grad,) = torch.autograd.grad(out.sum(), xi)
    h = 1e-6
    fd = torch.stack([(solve(h * e, "none")[:, 7].log()[:, 3]
                       - solve(-h * e, "none")[:, 7].log()[:, 3]).sum() / (2 * h)
                      for e in torch.eye(6, dtype=f64)])
    assert grad.abs().max() > 1e-3
    torch.testing.assert_close(grad, fd, rtol=1e-4, atol=1e-7)
    assert not solve(xi, "none").as_matrix().requires_grad


def test_bad_arguments():
    _, Z, Z0, x0 = pose_graphs(B=2, seed=1)
    graph = _graph(Z, Z0, x0)
    for value in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="delta_initial"):
            fg.dogleg(graph, delta_initial=value)
    with pytest.raises((TypeError, ValueError), match="delta_initial"):
        fg.dogleg(graph, delta_initial="1")
    with pytest.raises(ValueError, match="max_iterations"):
        fg.dogleg(graph, max_iterations=-1)
    with pytest.raises((TypeError, ValueError), match="max_iterations"):
        fg.dogleg(graph, max_iterations=2.5)
    with pytest.raises(ValueError, match="relative_error_tol"):
        fg.dogleg(graph, relative_error_tol=-1e-5)
    with pytest.raises(ValueError, match="absolute_error_tol"):
        fg.dogleg(graph, absolute_error_tol=float("nan"))
    with pytest.raises(ValueError, match="linear_solver"):
        fg.dogleg(graph, linear_solver="qr")
    with pytest.raises(ValueError, match="backward_mode"):
        fg.dogleg(graph, backward_mode="adjoint")
    with pytest.raises(ValueError, match="one problem"):
        fg.dogleg(graph, linear_solver="sparse")
    with pytest.raises(TypeError, match="FactorGraph"):
        fg.dogleg(x0)
    # no iterations: the initial values, MAX_ITERATIONS, the graph's inputs untouched
    before = x0.as_matrix().clone()
    result = fg.dogleg(graph, max_iterations=0)
    assert (result.report.status == SolverStatus.MAX_ITERATIONS).all()
    assert torch.equal(result.values["x"].as_matrix(), before)
    assert torch.equal(x0.as_matrix(), before)
