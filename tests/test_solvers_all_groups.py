"""The generic estimation solvers on unknowns of every group (the feature table's claim): the
nearest-element problem min |log(t^-1 x)|^2, whose answer (x = t) and Laplace covariance
(J = J_r^-1(0) = I, so the identity) are known exactly, with a Euclidean unknown beside it."""
from __future__ import annotations

import pytest
import torch

import torchsgal as ts
from torchsgal.estimation import gauss_helmert, gauss_newton
from torchsgal.estimation.lbfgs import lbfgs

F64 = torch.float64


def _problem(G, B=4, seed=0):
    gen = torch.Generator().manual_seed(seed)
    target = G.exp(torch.randn(B, G.dof, generator=gen, dtype=F64))
    start = target.rplus(0.3 * torch.randn(B, G.dof, generator=gen, dtype=F64))
    offset = torch.randn(B, 2, generator=gen, dtype=F64)
    return target, start, offset


@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=lambda G: G.__name__)
def test_gauss_newton_recovers_an_element_of_every_group(G):
    target, start, offset = _problem(G)

    def residual(x):
        g, y = x
        return torch.cat([g.rminus(target), y - offset], dim=-1)

    sol = gauss_newton(residual, (start, torch.zeros(4, 2, dtype=F64)))
    g, y = sol.x
    assert bool(sol.report.converged.all())
    assert g.rminus(target).abs().max() < 1e-12
    assert (y - offset).abs().max() < 1e-12
    eye = torch.eye(G.dof + 2, dtype=F64).expand(4, -1, -1)
    assert (sol.covariance - eye).abs().max() < 1e-10


@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=lambda G: G.__name__)
def test_lbfgs_recovers_an_element_of_every_group_and_reports_it(G):
    target, start, _ = _problem(G)
    x, _, report = lbfgs(lambda x, _e: x[0].rminus(target).square().sum(-1), (start,))
    # The status agrees with LBFGS's own stopping test (max-abs gradient): before, SGal3 and
    # Sim3 problems that LBFGS had stopped on reported MAX_ITERATIONS.
    assert bool(report.converged.all())
    # |gradient| = 2 |r| <= 1e-6 at convergence (gradient_tol), so |r| is at most ~5e-7.
    assert x[0].rminus(target).abs().max() < 1e-6


@pytest.mark.parametrize("variant", ["iterated", "paper"])
@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=lambda G: G.__name__)
def test_gauss_helmert_recovers_an_element_of_every_group(G, variant):
    """N noise-free observations y_n = t of one unknown, condition log((y_n exp(e_n))^-1 x) = 0
    with observation covariance s^2 I: x = t, e = 0 and the Laplace covariance s^2 I / N."""
    B, N, s2 = 3, 5, 0.04
    target, start, _ = _problem(G, B)
    obs = target.unsqueeze(-1).expand(B, N)

    def condition(x, e):
        g = x[0].unsqueeze(-1)
        y = obs if e is None else obs.rplus(e)
        z = g.rminus(y)  # log(y^-1 x)
        A = G.jr_inv(z)
        Bm = -G.jl_inv(z) if e is None else -G.jl_inv(z) @ G.jr(e)
        return z, A, Bm

    cov = s2 * torch.eye(G.dof, dtype=F64).expand(1, 1, -1, -1)
    sol = gauss_helmert(condition, (start,), cov, variant=variant)
    assert bool(sol.report.converged.all())
    assert sol.x[0].rminus(target).abs().max() < 1e-10
    assert (sol.covariance - s2 / N * torch.eye(G.dof, dtype=F64)).abs().max() < 1e-10


@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=lambda G: G.__name__)
def test_iterated_gauss_helmert_equals_gauss_newton_on_noisy_observations(G):
    """With noisy y_n the iterated variant's MAP minimises sum_n |log(y_n^-1 x)|^2 / s^2, the
    cost gauss_newton minimises directly: the two solutions and covariances agree (this
    exercises the condition's Jacobian in e at non-zero residuals)."""
    B, N, s2 = 3, 5, 0.04
    target, start, _ = _problem(G, B)
    gen = torch.Generator().manual_seed(1)
    obs = target.unsqueeze(-1).rplus(0.2 * torch.randn(B, N, G.dof, generator=gen, dtype=F64))

    def condition(x, e):
        g = x[0].unsqueeze(-1)
        y = obs if e is None else obs.rplus(e)
        z = g.rminus(y)
        return z, G.jr_inv(z), -G.jl_inv(z) if e is None else -G.jl_inv(z) @ G.jr(e)

    cov = s2 * torch.eye(G.dof, dtype=F64).expand(1, 1, -1, -1)
    gh = gauss_helmert(condition, (start,), cov, variant="iterated", step_tol=1e-12)
    # cost_tol=0: stop on the step only (a relative cost change of 1e-12, the default, stops
    # GN with a gradient of ~1e-7, ~1e-8 from the optimum)
    gn = gauss_newton(lambda x: x[0].unsqueeze(-1).rminus(obs).flatten(1) / s2 ** 0.5, (start,),
                      step_tol=1e-12, cost_tol=0.0)
    assert bool(gh.report.converged.all()) and bool(gn.report.converged.all())
    assert gh.x[0].rminus(gn.x[0]).abs().max() < 1e-9
    assert gh.x[0].rminus(target).abs().max() > 1e-3  # the noise moved the solution
    assert (gh.covariance - gn.covariance).abs().max() < 1e-9


def test_variable_helpers_take_one_block_alone_as_the_solvers_do():
    """The public helpers of estimation.variables take one block alone (what residual/jacobian
    receive) and return the same form; a group element is neither iterated over its batch
    (local (24,) instead of (4, 6)) nor asked for its truth value."""
    from torchsgal.estimation import autograd_jacobian
    from torchsgal.estimation import variables as V
    g = ts.SE3.exp(torch.randn(4, 6, generator=torch.Generator().manual_seed(0), dtype=F64))
    d = 0.1 * torch.ones(4, 6, dtype=F64)
    assert V.tangent_dim(g) == 6 and V.batch_size(g) == 4 and V.block_dims(g) == [6]
    moved = V.retract(g, d)
    assert isinstance(moved, ts.SE3) and moved.allclose(g.rplus(d), rtol=0, atol=1e-15)
    torch.testing.assert_close(V.local(g, moved), d, rtol=0, atol=1e-13)
    mask = torch.tensor([True, False, True, False])
    picked = V.select(mask, moved, g)
    assert isinstance(picked, ts.SE3)
    torch.testing.assert_close(picked.as_matrix()[1], g.as_matrix()[1], rtol=0, atol=0)
    torch.testing.assert_close(picked.as_matrix()[0], moved.as_matrix()[0], rtol=0, atol=0)
    assert isinstance(V.detach(g), ts.SE3) and bool(V.finite(g).all())
    assert isinstance(V.retract((g,), d), tuple)  # tuples stay tuples
    assert autograd_jacobian(lambda x: x.log(), g).shape == (4, 6, 6)
    with pytest.raises(TypeError, match="x must be a group element, a tensor or a tuple of them, got str"):
        autograd_jacobian(lambda x: x, "abc")
    with pytest.raises(ValueError, match=r"x \(SE3\) must have batch shape \(B,\)"):
        autograd_jacobian(lambda x: x.log(), ts.SE3.identity(dtype=F64))


@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=lambda G: G.__name__)
def test_solutions_of_every_group_carry_no_graph_and_one_nan_problem_stays_alone(G):
    """The solvers are not differentiable: with a target that requires gradients the estimate
    carries no graph, not even a partial one (the start is detached).  And one non-finite
    problem does not make every LBFGS problem of the batch NON_FINITE."""
    target, start, _ = _problem(G)
    xi = target.log().requires_grad_(True)
    tgt = G.exp(xi)
    sol = gauss_newton(lambda x: x.rminus(tgt), start)
    assert sol.x.as_matrix().grad_fn is None and not sol.covariance.requires_grad
    assert bool(sol.report.converged.all())
    bad = target.as_matrix().clone()
    bad[1] = float("nan")
    x, _, report = lbfgs(lambda x, _e: x.rminus(G(bad)).square().sum(-1), start)
    assert x.as_matrix().grad_fn is None
    assert report.status.tolist() == [0, 3, 0, 0]
    assert x[[0, 2, 3]].rminus(target[[0, 2, 3]]).abs().max() < 1e-6
