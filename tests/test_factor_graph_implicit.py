"""Differentiable solves of the factor-graph engine (``backward_mode``): implicit gradients
against ``torch.autograd.gradcheck`` (finite differences of whole solves), against unrolled
differentiation, per problem in a batch, with a robust loss (against the stated formula and
the exact derivative) and at a gauge freedom (a clear error)."""
import pytest
import torch

import torchsgal as ts
from torchsgal.estimation import SolverStatus
from torchsgal.estimation import graph as fg

f64 = torch.float64
EDGES_I = torch.tensor([0, 1, 2, 0, 1])
EDGES_J = torch.tensor([1, 2, 3, 3, 3])
TIGHT = dict(relative_error_tol=0.0, absolute_error_tol=0.0)  # iterate to the last digit


def _poses(N=4, B=None, seed=0):
    gen = torch.Generator().manual_seed(seed)
    shape = (N,) if B is None else (B, N)
    truth = ts.SE3.exp(torch.randn(shape + (6,), generator=gen, dtype=f64))
    start = truth @ ts.SE3.exp(0.1 * torch.randn(shape + (6,), generator=gen, dtype=f64))
    return truth, start


def _pose_graph(truth, start, xi, prior=True, loss=None, info_scale=None):
    """Between measurements Z exp(xi) of the truth's relative poses (xi = 0: zero residual)."""
    Z = truth[..., EDGES_I].inverse() @ truth[..., EDGES_J] @ ts.SE3.exp(xi)
    graph = fg.FactorGraph()
    graph.add_variable("x", start)
    if prior:
        graph.add(fg.Prior("x", 0, truth[..., :1], information=1e2 * torch.eye(6, dtype=f64)))
    W = None if info_scale is None else info_scale * torch.eye(6, dtype=f64)
    graph.add(fg.Between("x", EDGES_I, EDGES_J, Z, information=W), loss=loss)
    return graph


def test_gradcheck_between_measurement_tangent():
    truth, start = _poses()
    xi = torch.zeros(len(EDGES_I), 6, dtype=f64, requires_grad=True)

    def solve(xi):
        return fg.gauss_newton(_pose_graph(truth, start, xi), 30, backward_mode="implicit",
                               **TIGHT).values["x"].as_matrix()

    assert torch.autograd.gradcheck(solve, (xi,), eps=1e-6, atol=1e-6)


def test_values_are_the_plain_solution_and_inputs_unchanged():
    truth, start = _poses()
    xi = (0.05 * torch.randn(len(EDGES_I), 6, dtype=f64)).requires_grad_(True)
    before = xi.detach().clone()
    plain = fg.levenberg_marquardt(_pose_graph(truth, start, xi)).values["x"].as_matrix()
    out = fg.levenberg_marquardt(_pose_graph(truth, start, xi), backward_mode="implicit")
    m = out.values["x"].as_matrix()
    assert m.requires_grad and not plain.requires_grad
    assert torch.equal(m.detach(), plain)
    assert torch.equal(xi.detach(), before)
    assert not out.report.cost.requires_grad
    with torch.no_grad():  # no gradient asked: plain values
        assert not fg.levenberg_marquardt(_pose_graph(truth, start, xi),
                                          backward_mode="implicit").values["x"].as_matrix().requires_grad


def _point_graph(z, lever, B=None):
    """Two poses with priors observing 3 points (Euclidean unknowns), a sensor with a lever
    arm ``lever`` the residual closes over: r = T (p + lever) - z."""
    gen = torch.Generator().manual_seed(3)
    poses = ts.SE3.exp(torch.randn(2, 6, generator=gen, dtype=f64))
    points = 2 * torch.randn(3, 3, generator=gen, dtype=f64)
    i = torch.tensor([0, 0, 0, 1, 1, 1])
    j = torch.tensor([0, 1, 2, 0, 1, 2])
    graph = fg.FactorGraph()
    graph.add_variable("T", poses @ ts.SE3.exp(0.05 * torch.randn(2, 6, generator=gen, dtype=f64)))
    graph.add_variable("p", points + 0.1 * torch.randn(3, 3, generator=gen, dtype=f64))
    graph.add(fg.Prior("T", torch.tensor([0, 1]), poses, information=1e2 * torch.eye(6, dtype=f64)))
    graph.add(fg.Factor(lambda T, p, z: T.act(p + lever) - z, [("T", i), ("p", j)], data=[z], dim=3))
    return graph, poses, points, i, j


def test_gradcheck_point_observation_and_closed_over_lever_arm():
    lever0 = torch.tensor([0.1, -0.2, 0.3], dtype=f64)
    _, poses, points, i, j = _point_graph(torch.zeros(6, 3, dtype=f64), lever0)
    z0 = poses[i].act(points[j] + lever0)  # noise-free observations

    def solve(z, lever):
        graph = _point_graph(z, lever)[0]
        out = fg.gauss_newton(graph, 30, backward_mode="implicit", **TIGHT).values
        return out["T"].as_matrix(), out["p"]

    z = z0.clone().requires_grad_(True)
    lever = lever0.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(solve, (z, lever), eps=1e-6, atol=1e-6)
    # the lever arm is not observable from the points alone: the points absorb it exactly
    p = solve(z0, lever)[1]
    (grad,) = torch.autograd.grad(p.sum(), lever)
    torch.testing.assert_close(grad, -3 * torch.ones(3, dtype=f64), rtol=0, atol=1e-9)


def _linear_graph(z, s, loss=None):
    """Euclidean positions on a line graph with a loop: r = p_j - p_i - z (linear in the
    unknowns), a prior on p_0, edge noise sqrt_information s I: the Gauss-Newton information
    is the Hessian, so the implicit gradient is exact at any residual for the plain loss."""
    i = torch.tensor([0, 1, 2, 0, 1])
    j = torch.tensor([1, 2, 3, 3, 3])
    graph = fg.FactorGraph()
    graph.add_variable("p", torch.zeros(4, 2, dtype=f64))
    graph.add(fg.Factor(lambda pi, pj, zz: pj - pi - zz, [("p", i), ("p", j)], data=[z], dim=2,
                        sqrt_information=s * torch.eye(2, dtype=f64)[None].expand(5, 2, 2)),
              loss=loss)
    graph.add(fg.Factor(lambda p0: p0, [("p", 0)], dim=2))
    return graph, i, j


def test_gradcheck_noise_scale_and_measurements_at_nonzero_residual():
    gen = torch.Generator().manual_seed(5)
    z = torch.randn(5, 2, generator=gen, dtype=f64).requires_grad_(True)  # inconsistent loop
    s = torch.tensor([1.0, 2.0, 0.5, 3.0, 1.5], dtype=f64).requires_grad_(True)

    def solve(z, s):
        graph = _linear_graph(z, s[:, None, None])[0]
        return fg.gauss_newton(graph, 5, backward_mode="implicit", **TIGHT).values["p"]

    assert torch.autograd.gradcheck(solve, (z, s), eps=1e-6, atol=1e-7)


def test_robust_loss_gradient_is_the_stated_formula():
    """Cauchy loss at an outlier: the implicit gradient is -H_GN^-1 dg/dz with g = sum rho' J^T r
    differentiated exactly (the weights' derivative included) and H_GN = sum rho' J^T J (the
    engine's IRLS information); the exact derivative (finite differences of solves) adds the
    loss curvature 2 rho'' (J^T r)(J^T r)^T to H.  Both formulas are built here by hand."""
    gen = torch.Generator().manual_seed(6)
    z0 = 0.1 * torch.randn(5, 2, generator=gen, dtype=f64)
    z0[3] += torch.tensor([3.0, -2.0], dtype=f64)  # an outlier edge
    s = torch.ones(5, 1, 1, dtype=f64)
    loss = fg.Cauchy(1.0)

    def solve(z):
        graph, i, j = _linear_graph(z, s, loss)
        return fg.gauss_newton(graph, 50, backward_mode="implicit", **TIGHT).values["p"], i, j

    z = z0.clone().requires_grad_(True)
    p, i, j = solve(z)
    w = torch.randn(4, 2, generator=gen, dtype=f64)
    (grad,) = torch.autograd.grad((p * w).sum(), z)
    # by hand: r_e = p_j - p_i - z_e, J_e = [.. -I (at i) .. I (at j) ..], prior r = p_0
    p = p.detach()
    A = torch.zeros(5, 2, 8, dtype=f64)
    for e in range(5):
        A[e, :, 2 * i[e]:2 * i[e] + 2] -= torch.eye(2, dtype=f64)
        A[e, :, 2 * j[e]:2 * j[e] + 2] += torch.eye(2, dtype=f64)
    r = p[j] - p[i] - z0
    sq = (r * r).sum(-1)
    d1, d2 = 1 / (1 + sq), -1 / (1 + sq) ** 2  # Cauchy rho', rho'' (scale 1)
    prior = torch.zeros(2, 8, dtype=f64)
    prior[:, :2] = torch.eye(2, dtype=f64)
    H_gn = prior.T @ prior + torch.einsum("e,eai,eaj->ij", d1, A, A)
    Jr = torch.einsum("eai,ea->ei", A, r)
    H_exact = H_gn + torch.einsum("e,ei,ej->ij", 2 * d2, Jr, Jr)
    # dg/dz_e (8 x 2): d/dz of rho'(s) A^T r with dr/dz = -I, ds/dz = -2 r^T
    dg = -(d1[:, None, None] * A.mT + 2 * d2[:, None, None] * Jr[:, :, None] * r[:, None, :])
    dg = dg.permute(1, 0, 2).reshape(8, 10)
    expect_gn = -(torch.linalg.solve(H_gn, dg)).T @ w.reshape(8)
    expect_exact = -(torch.linalg.solve(H_exact, dg)).T @ w.reshape(8)
    torch.testing.assert_close(grad.reshape(10), expect_gn, rtol=1e-9, atol=1e-9)
    # finite differences of whole solves give the exact derivative, not the GN one
    eps, fd = 1e-3, torch.zeros(10, dtype=f64)  # above the solves' accuracy (|g| ~ 1e-9)
    for k in range(10):
        dz = torch.zeros(10, dtype=f64)
        dz[k] = eps
        with torch.no_grad():
            hi = solve(z0 + dz.reshape(5, 2))[0]
            lo = solve(z0 - dz.reshape(5, 2))[0]
        fd[k] = ((hi - lo) * w).sum() / (2 * eps)
    # central differences: truncation O(eps^2) ~ 1e-5 here, far below the GN term (~ 0.5)
    torch.testing.assert_close(fd, expect_exact, rtol=1e-4, atol=1e-4)
    assert (expect_exact - expect_gn).abs().max() > 0.1  # the approximation is visible here


def test_robust_loss_gradcheck_at_zero_residual():
    truth, start = _poses(seed=2)
    xi = torch.zeros(len(EDGES_I), 6, dtype=f64, requires_grad=True)

    def solve(xi):
        graph = _pose_graph(truth, start, xi, loss=fg.Huber(0.1))
        return fg.gauss_newton(graph, 30, backward_mode="implicit", **TIGHT).values["x"].as_matrix()

    assert torch.autograd.gradcheck(solve, (xi,), eps=1e-6, atol=1e-6)


@pytest.mark.parametrize("sigma, tol", [(0.0, 1e-8), (1e-3, 1e-2)])
def test_implicit_agrees_with_unrolled(sigma, tol):
    """A converged Levenberg-Marquardt solve: unrolled differentiation converges to the exact
    derivative -H^-1 dg/dtheta (H the Hessian), the implicit one uses the Gauss-Newton H: equal
    at zero residual (to the solve's accuracy), apart by O(residual) otherwise (relative tol
    1e-2 at whitened residuals ~ 1e-3 * 10)."""
    truth, start = _poses(seed=4)
    gen = torch.Generator().manual_seed(8)
    xi = (sigma * torch.randn(len(EDGES_I), 6, generator=gen, dtype=f64)).requires_grad_(True)
    w = torch.randn(4, 4, 4, generator=gen, dtype=f64)
    grads = {}
    for mode in ("implicit", "unroll"):
        # relative_error_tol 1e-12: the cost (~1e-3) is rounded to ~1e-16, so a step's cost
        # change is +-1e-16 (1e-13 relative) once converged; a smaller tolerance leaves the stop
        # to rounding (the damping then grows to its limit: DIVERGED at the same values)
        out = fg.levenberg_marquardt(_pose_graph(truth, start, xi, info_scale=100.0), 100,
                                     backward_mode=mode, relative_error_tol=1e-12,
                                     absolute_error_tol=1e-20)
        assert (out.report.status == SolverStatus.CONVERGED).all()
        grads[mode] = torch.autograd.grad((out.values["x"].as_matrix() * w).sum(), xi)[0]
    scale = grads["unroll"].abs().max()
    assert (grads["implicit"] - grads["unroll"]).abs().max() <= tol * scale


def test_batched_gradients_equal_one_at_a_time():
    truth, start = _poses(B=3, seed=10)
    gen = torch.Generator().manual_seed(11)
    xi = (0.02 * torch.randn(3, len(EDGES_I), 6, generator=gen, dtype=f64)).requires_grad_(True)
    w = torch.randn(3, 4, 4, 4, generator=gen, dtype=f64)
    out = fg.levenberg_marquardt(_pose_graph(truth, start, xi), backward_mode="implicit", **TIGHT)
    (batched,) = torch.autograd.grad((out.values["x"].as_matrix() * w).sum(), xi)
    for b in range(3):
        xb = xi[b].detach().clone().requires_grad_(True)
        one = fg.levenberg_marquardt(_pose_graph(truth[b], start[b], xb), backward_mode="implicit",
                                     **TIGHT)
        (g,) = torch.autograd.grad((one.values["x"].as_matrix() * w[b]).sum(), xb)
        torch.testing.assert_close(batched[b], g, rtol=1e-8, atol=1e-10)


def test_sparse_solver_gives_the_dense_gradient():
    truth, start = _poses(seed=12)
    xi = (0.02 * torch.randn(len(EDGES_I), 6, dtype=f64)).requires_grad_(True)
    grads = []
    for solver in ("dense", "sparse"):
        out = fg.levenberg_marquardt(_pose_graph(truth, start, xi), backward_mode="implicit",
                                     linear_solver=solver, **TIGHT)
        grads.append(torch.autograd.grad(out.values["x"].as_matrix().sum(), xi)[0])
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-8, atol=1e-10)


def test_gauge_freedom_is_a_clear_error():
    """Without a prior the solution is not unique (any global motion): no gradient exists, and
    the implicit mode says so instead of returning NaN; the plain solve still works."""
    truth, start = _poses(seed=13)
    xi = torch.zeros(len(EDGES_I), 6, dtype=f64, requires_grad=True)
    with pytest.raises(ValueError, match="singular for problem"):
        fg.levenberg_marquardt(_pose_graph(truth, start, xi, prior=False), backward_mode="implicit")
    out = fg.levenberg_marquardt(_pose_graph(truth, start, xi, prior=False))
    assert (out.report.status == SolverStatus.CONVERGED_RANK_DEFICIENT).all()


def test_bad_backward_mode_names_the_argument():
    truth, start = _poses()
    graph = _pose_graph(truth, start, torch.zeros(len(EDGES_I), 6, dtype=f64))
    with pytest.raises(ValueError, match="backward_mode must be one of"):
        fg.levenberg_marquardt(graph, backward_mode="adjoint")
    with pytest.raises(ValueError, match="backward_mode='unroll' needs the dense"):
        fg.gauss_newton(graph, backward_mode="unroll", linear_solver="sparse")
