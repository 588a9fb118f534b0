"""graph.GaussHelmert: errors-in-variables conditions in the factor-graph engine, against the
generic Gauss-Helmert solver, the closed-form total-least-squares line, forward mode against
the analytic TLS Jacobians, bad input and non-finite data."""
import pytest
import torch

from torchsgal.estimation import gauss_helmert as generic_gauss_helmert
from torchsgal.estimation import graph as fg
from torchsgal.estimation import study, tls, tls_solvers
from torchsgal.estimation.graph.gauss_helmert import _forward_jacobians
from torchsgal.estimation.solver import SolverStatus

f64 = torch.float64


def _line_data(B=4, E=30, seed=0, sigma=0.05):
    """Points (u, v) near lines v = a u + b with noise on both coordinates."""
    gen = torch.Generator().manual_seed(seed)
    a = torch.randn(B, 1, generator=gen, dtype=f64)
    b = torch.randn(B, 1, generator=gen, dtype=f64)
    u = 4 * torch.rand(B, E, generator=gen, dtype=f64) - 2
    v = a * u + b
    obs = torch.stack([u, v], -1) + sigma * torch.randn(B, E, 2, generator=gen, dtype=f64)
    return obs, torch.cat([a, b], -1)


def _line_condition(x, obs, e):
    """v + e_v - a (u + e_u) - b for x = (a, b)."""
    u, v = obs[..., 0] + e[..., 0], obs[..., 1] + e[..., 1]
    return (v - x[..., 0] * u - x[..., 1])[..., None]


def _line_graph(obs, cov, iterated, x0):
    B, E = obs.shape[:2]
    graph = fg.FactorGraph()
    graph.add_variable("x", x0[:, None, :])
    factor = fg.GaussHelmert(_line_condition, [("x", torch.zeros(E, dtype=torch.int64))], cov,
                             data=[obs], dim=1, iterated=iterated)
    graph.add(factor)
    return graph, factor


def _generic_line(obs, cov, variant, x0):
    def condition(x, e):
        e = torch.zeros_like(obs) if e is None else e
        c = _line_condition(x[:, None, :], obs, e)
        u = obs[..., 0] + e[..., 0]
        A = torch.stack([-u, -torch.ones_like(u)], -1)[..., None, :]
        Bm = torch.stack([-x[:, None, 0].expand_as(u), torch.ones_like(u)], -1)[..., None, :]
        return c, A, Bm
    S = cov if cov.dim() == 4 else cov.expand(obs.shape[:2] + cov.shape[-2:])
    return generic_gauss_helmert(condition, x0, S, variant=variant, step_tol=1e-12,
                                 max_iterations=100)


@pytest.mark.parametrize("iterated", [True, False])
@pytest.mark.parametrize("covariance", ["shared diagonal", "per point full"])
def test_line_fit_matches_the_generic_gauss_helmert_solver(iterated, covariance):
    """Forward-mode Jacobians of a user condition; the estimate, covariance, cost and the
    corrections equal the generic solver's (estimation.gauss_helmert): the paper-style form to
    1e-8 standard deviations, the iterated one to 1e-6 (measured 1e-7: it stops on its cost
    test at the rounding of the cost, the generic solver on its step)."""
    obs, truth = _line_data()
    B, E = obs.shape[:2]
    if covariance == "shared diagonal":
        cov = torch.diag(torch.tensor([0.05 ** 2, 0.08 ** 2], dtype=f64))
    else:
        gen = torch.Generator().manual_seed(3)
        A = 0.05 * torch.randn(B, E, 2, 2, generator=gen, dtype=f64)
        cov = A @ A.mT + 1e-3 * torch.eye(2, dtype=f64)
    x0 = truth + 0.3
    graph, factor = _line_graph(obs, cov, iterated, x0)
    result = fg.gauss_helmert(graph, damped=iterated, step_tol=1e-10, cost_tests=iterated,
                              relative_error_tol=1e-15, absolute_error_tol=0.0)
    ref = _generic_line(obs, cov, "iterated" if iterated else "paper", x0)
    assert result.report.converged.all() and ref.report.converged.all()
    x = result.values["x"][:, 0]
    sd = ref.covariance.diagonal(dim1=-2, dim2=-1).sqrt()
    tol = 1e-6 if iterated else 1e-8
    assert ((x - ref.x) / sd).abs().max() < tol
    P = torch.linalg.inv(result.information)
    assert ((P - ref.covariance) / (sd[:, :, None] * sd[:, None, :])).abs().max() < tol
    torch.testing.assert_close(result.report.cost, ref.report.cost, rtol=tol, atol=0)
    if iterated:  # in standard deviations of the observations
        assert (factor.corrections - ref.aux).abs().max() < tol * 0.05


@pytest.mark.parametrize("update_below", [None, 1.0])
def test_iterated_line_fit_with_isotropic_noise_is_the_orthogonal_regression(update_below):
    """Isotropic noise on both coordinates: the errors-in-variables line is the total-least-
    squares line of the centred points (the principal direction, from an eigendecomposition),
    with the corrections updated after every step (default) or after short steps only."""
    obs, truth = _line_data(B=3, E=40, seed=4, sigma=0.1)
    cov = 0.1 ** 2 * torch.eye(2, dtype=f64)
    graph, factor = _line_graph(obs, cov, True, truth + 0.2)
    result = fg.gauss_helmert(graph, step_tol=1e-10, relative_error_tol=1e-15,
                              absolute_error_tol=0.0, update_below=update_below)
    assert result.report.converged.all()
    mean = obs.mean(1, keepdim=True)
    C = (obs - mean).mT @ (obs - mean)
    direction = torch.linalg.eigh(C).eigenvectors[..., :, -1]  # (B, 2)
    a = direction[:, 1] / direction[:, 0]
    b = mean[:, 0, 1] - a * mean[:, 0, 0]
    x = result.values["x"][:, 0]
    torch.testing.assert_close(x, torch.stack([a, b], -1), rtol=0, atol=1e-8)
    # the corrected points lie on the line, and each correction is orthogonal to it
    corrected = obs + factor.corrections
    on_line = corrected[..., 1] - x[:, None, 0] * corrected[..., 0] - x[:, None, 1]
    assert on_line.abs().max() < 1e-7
    along = factor.corrections @ direction[:, :, None]
    assert along.abs().max() < 1e-7


@pytest.mark.parametrize("batched", [True, False])
@pytest.mark.parametrize("covariance", ["shared diagonal", "per point full"])
def test_corrections_update_is_that_of_the_linearised_problem(covariance, batched):
    """A linearisation leaves the corrections' update of the linearised problem for a step d,
    e'(d) = -Sigma Bm^T S^-1 (w + A d) (S as in kelly-giamou (5.23)), from Bm and S^-1 [w | A]: against
    the formula with the line's derivatives written out and a dense solve; and the cost at a
    trial point, which evaluates the condition alone with S and Bm e of the linearisation point
    held, against the same quantities written out."""
    from torchsgal.estimation.graph.gauss_helmert_solver import (
        _candidate,
        _iterated_blocks,
        _prepare_states,
        _take_fresh,
        _working_state,
    )
    from torchsgal.estimation.graph.linearize import Problem, evaluate_cost, linearize

    gen = torch.Generator().manual_seed(7)
    obs, truth = _line_data(B=3, E=6, seed=5)
    if covariance == "shared diagonal":
        cov = torch.diag(torch.tensor([0.05 ** 2, 0.08 ** 2], dtype=f64))
    else:
        R = 0.05 * torch.randn(3, 6, 2, 2, generator=gen, dtype=f64)
        cov = R @ R.mT + 1e-3 * torch.eye(2, dtype=f64)
    e0 = 0.03 * torch.randn(3, 6, 2, generator=gen, dtype=f64)
    x0 = truth + 0.2 * torch.randn(3, 2, generator=gen, dtype=f64)
    if not batched:  # one problem: its (E, ...) data
        obs, e0, x0 = obs[0], e0[0], x0[:1]
        cov = cov if cov.dim() == 2 else cov[0]
    graph = fg.FactorGraph()
    graph.add_variable("x", x0[:, None, :] if batched else x0)
    factor = fg.GaussHelmert(_line_condition, [("x", torch.zeros(6, dtype=torch.int64))], cov,
                             data=[obs], dim=1, corrections=e0)
    graph.add(factor)
    _prepare_states(graph)
    problem = Problem(graph)
    x = problem.initial(graph)
    linearize(problem, x)  # a new linearisation point: S, Bm e, point and gain
    blocks = _iterated_blocks(problem)
    rows = torch.arange(problem.B)
    _take_fresh(blocks, rows)  # as a round starts
    _working_state(blocks, rows)
    d = 0.1 * torch.randn(problem.B, 2, generator=gen, dtype=f64)
    # the line v + e_v - a (u + e_u) - b: A = [-(u + e_u), -1], Bm = [-a, 1] (rows of one)
    a, b = (x0[:, None, 0], x0[:, None, 1]) if batched else (x0[0, 0], x0[0, 1])
    u = obs[..., 0] + e0[..., 0]
    c = obs[..., 1] + e0[..., 1] - a * u - b
    Bm = torch.stack([-a.expand_as(u), torch.ones_like(u)], -1)[..., None, :]  # (..., 1, 2)
    A = torch.stack([-u, -torch.ones_like(u)], -1)[..., None, :]  # (..., 1, 2)
    w = c[..., None] - (Bm @ e0[..., None])[..., 0]
    S = Bm @ cov @ Bm.mT
    step = d[:, None, :, None] if batched else d[0, :, None]
    expected = -(cov @ Bm.mT @ torch.linalg.solve(S, w[..., None] + A @ step))[..., 0]
    point, got = _candidate(blocks[0], rows, d, batched)
    torch.testing.assert_close(got, expected, rtol=1e-12, atol=0)
    torch.testing.assert_close(point, -(cov @ Bm.mT @ torch.linalg.solve(S, w[..., None]))[..., 0],
                               rtol=1e-12, atol=0)
    # the cost at x + d with S and Bm e held: 1/2 sum (c(x + d, e) - Bm e)^2 / S
    x_new = problem.retract(x, d)
    xn = x_new[0].reshape(problem.B, 2)
    an, bn = (xn[:, None, 0], xn[:, None, 1]) if batched else (xn[0, 0], xn[0, 1])
    c_new = obs[..., 1] + e0[..., 1] - an * u - bn
    r = (c_new[..., None] - (Bm @ e0[..., None])[..., 0]) / S[..., 0].sqrt()
    cost = 0.5 * (r ** 2).flatten(-2).sum(-1)
    torch.testing.assert_close(evaluate_cost(problem, x_new), cost.reshape(-1), rtol=1e-13, atol=0)


@pytest.mark.parametrize("estimator", ["sgal3", "baseline"])
def test_forward_mode_jacobians_equal_the_analytic_tls_jacobians(estimator):
    """The TLS conditions' analytic Jacobians at non-zero corrections against the factor's
    forward mode: the exact derivatives times the left factor Q they return."""
    P = study.simulate(study.StudyConfig(trials=3, samples=5, seed=2)).problem
    F0, dt = P.initial_guess(-1.0)
    n = P.indices[:, None]
    e = 0.05 * torch.randn(3, 5, 20, generator=torch.Generator().manual_seed(1), dtype=f64)
    if estimator == "sgal3":
        variables, data = [F0.unsqueeze(-1), dt[:, None, :]], [P.M, n]
        terms, condition = tls_solvers._sgal3_terms, tls_solvers._sgal3_condition
    else:
        X0, t0 = tls.baseline_start(F0)
        M, dclock = tls.baseline_observations(P)
        variables = [X0.unsqueeze(-1), t0[:, None, None], dt[:, None, :]]
        data = [M, dclock[..., None], n]
        terms, condition = tls_solvers._baseline_terms, tls_solvers._baseline_condition
    c, As, Bm, Q = terms(*variables, *data, e)
    # the condition alone (the cost at trial points) gives the very same values as the terms
    assert torch.equal(condition(*variables, *data, e), c)
    assert torch.equal(condition(*variables, *data, None), terms(*variables, *data, None)[0])
    c2, As2, Bm2 = _forward_jacobians(condition, variables, data, e)
    torch.testing.assert_close(c, c2, rtol=0, atol=1e-13)
    # the Jacobians are the left factor Q they return times the exact derivatives
    for A, A2 in zip(As, As2):
        torch.testing.assert_close(A.expand_as(A2), Q @ A2, rtol=0, atol=1e-12)
    torch.testing.assert_close(Bm, Q @ Bm2, rtol=0, atol=1e-12)
    # J_r(c) c = c: the engine's reading of the condition, Q c, is c
    torch.testing.assert_close((Q @ c[..., None])[..., 0], c, rtol=0, atol=1e-13)


def test_non_finite_observation_spoils_only_its_problem():
    obs, truth = _line_data(B=3)
    cov = 0.05 ** 2 * torch.eye(2, dtype=f64)
    bad = obs.clone()
    bad[1, 4, 0] = float("nan")
    graph, _ = _line_graph(bad, cov, True, truth + 0.1)
    result = fg.gauss_helmert(graph, step_tol=1e-10)
    assert result.report.status.tolist() == [0, SolverStatus.NON_FINITE, 0]
    alone, _ = _line_graph(obs[2:], cov, True, truth[2:] + 0.1)
    ref = fg.gauss_helmert(alone, step_tol=1e-10)
    torch.testing.assert_close(result.values["x"][2], ref.values["x"][0], rtol=0, atol=1e-12)


def test_bad_input_names_the_argument():
    obs, truth = _line_data(B=2, E=5)
    idx = torch.zeros(5, dtype=torch.int64)
    cov = 0.05 ** 2 * torch.eye(2, dtype=f64)
    with pytest.raises(ValueError, match="covariance is not positive definite"):
        fg.GaussHelmert(_line_condition, [("x", idx)], -cov, data=[obs], dim=1)
    with pytest.raises(TypeError, match="iterated must be True or False"):
        fg.GaussHelmert(_line_condition, [("x", idx)], cov, data=[obs], dim=1, iterated=1)
    with pytest.raises(ValueError, match=r"corrections must have shape \(E, m\) or \(B, E, m\)"):
        fg.GaussHelmert(_line_condition, [("x", idx)], cov, data=[obs], dim=1,
                        corrections=torch.zeros(4, 2, dtype=f64))
    with pytest.raises(TypeError, match="condition must be callable"):
        fg.GaussHelmert(None, [("x", idx)], cov, data=[obs], dim=1)
    graph, _ = _line_graph(obs, cov, True, truth)
    with pytest.raises(RuntimeError, match=r"solve its graph with torchsgal.estimation.graph.gauss_helmert\(graph\)"):
        fg.levenberg_marquardt(graph)
    with pytest.raises(ValueError, match="step_tol must be a finite number >= 0"):
        fg.gauss_helmert(graph, step_tol=-1.0)
    with pytest.raises(ValueError, match="update_below must be a finite number > 0"):
        fg.gauss_helmert(graph, update_below=0.0)
    # the covariance and the corrections are named, with the sizes they must have
    with pytest.raises(ValueError, match=r"covariance must have shape \(m, m\), \(E, m, m\) or "
                                         r"\(B, E, m, m\) with E = 5 conditions, got \(3, 2, 2\)"):
        fg.GaussHelmert(_line_condition, [("x", idx)], cov.expand(3, 2, 2), data=[obs], dim=1)
    with pytest.raises(ValueError, match=r"covariance must have shape \(m, m\), .* got \(2,\)"):
        fg.GaussHelmert(_line_condition, [("x", idx)], cov.diagonal(), data=[obs], dim=1)
    with pytest.raises(TypeError, match="corrections has dtype torch.float32 but covariance has dtype torch.float64"):
        fg.GaussHelmert(_line_condition, [("x", idx)], cov, data=[obs], dim=1,
                        corrections=torch.zeros(5, 2))
    graph, _ = _line_graph(obs, cov, True, truth)
    graph.factors[0].corrections = torch.zeros(3, 5, 2, dtype=f64)
    with pytest.raises(ValueError, match=r"corrections of shape \(3, 5, 2\) for a graph of 2 problems: "
                                         r"give \(E, m\) = \(5, 2\) or \(B, E, m\) = \(2, 5, 2\)"):
        fg.gauss_helmert(graph)


def test_a_factor_added_with_a_loss_gets_the_corrections():
    """graph.add(factor, loss=...) stores a copy with the loss (the caller's factor keeps its
    own): the solver's corrections are given to the caller's factor too."""
    obs, truth = _line_data(B=2, E=6)
    cov = 0.05 ** 2 * torch.eye(2, dtype=f64)
    graph = fg.FactorGraph()
    graph.add_variable("x", torch.zeros_like(truth)[:, None, :])
    factor = fg.GaussHelmert(_line_condition, [("x", torch.zeros(6, dtype=torch.int64))], cov,
                             data=[obs], dim=1)
    graph.add(factor, loss=fg.Huber(3.0))
    assert graph.factors[0] is not factor and factor.loss is None
    fg.gauss_helmert(graph)
    assert factor.corrections is graph.factors[0].corrections
    assert factor.corrections.shape == (2, 6, 2) and bool(factor.corrections.abs().amax() > 0)


def _rigid2d(B=3, E=25, seed=3, sigma=0.02):
    """Points p and q = R(theta) p + t, noise on both (m = 4: e = [e_p, e_q])."""
    gen = torch.Generator().manual_seed(seed)
    theta = torch.rand(B, 1, generator=gen, dtype=f64) * 2 - 1
    t = torch.randn(B, 2, generator=gen, dtype=f64)
    p = torch.randn(B, E, 2, generator=gen, dtype=f64)
    c, s = theta.cos()[..., None], theta.sin()[..., None]
    q = torch.stack([c[..., 0] * p[..., 0] - s[..., 0] * p[..., 1],
                     s[..., 0] * p[..., 0] + c[..., 0] * p[..., 1]], -1) + t[:, None, :]
    noise = sigma * torch.randn(B, E, 4, generator=gen, dtype=f64)
    return torch.cat([p, q], -1) + noise, torch.cat([theta, t], -1)


def _rigid2d_condition(x, obs, e):
    """R(theta) (p + e_p) + t - (q + e_q), x = (theta, t) (..., 3)."""
    p, q = obs[..., :2] + e[..., :2], obs[..., 2:] + e[..., 2:]
    c, s = x[..., 0].cos(), x[..., 0].sin()
    Rp = torch.stack([c * p[..., 0] - s * p[..., 1], s * p[..., 0] + c * p[..., 1]], -1)
    return Rp + x[..., 1:] - q


def _rigid2d_jacobians(x, obs, e, scaled):
    """(c, [A], Bm) with the exact derivatives, or (c, [Q A], Q Bm, Q) with a Q that moves with
    the point (Q = [[2, c_0], [-c_0, 2]], invertible)."""
    e = torch.zeros(obs.shape, dtype=f64) if e is None else e
    p = obs[..., :2] + e[..., :2]
    c_, s_ = x[..., 0].cos(), x[..., 0].sin()
    cond = _rigid2d_condition(x, obs, e)
    dR = torch.stack([-s_ * p[..., 0] - c_ * p[..., 1], c_ * p[..., 0] - s_ * p[..., 1]], -1)
    eye = torch.eye(2, dtype=f64).expand(cond.shape[:-1] + (2, 2))
    A = torch.cat([dR[..., None], eye], -1)  # (..., 2, 3)
    R = torch.stack([torch.stack([c_, -s_], -1), torch.stack([s_, c_], -1)], -2).expand_as(eye)
    Bm = torch.cat([R, -eye], -1)  # (..., 2, 4)
    if not scaled:
        return cond, [A], Bm
    c0 = cond[..., 0]
    Q = torch.stack([torch.stack([2 + 0 * c0, c0], -1), torch.stack([-c0, 2 + 0 * c0], -1)], -2)
    return cond, [Q @ A], Q @ Bm, Q


@pytest.mark.parametrize("batched", [True, False])
@pytest.mark.parametrize("iterated", [True, False])
def test_left_factor_leaves_steps_corrections_and_solution_unchanged(iterated, batched):
    """The same problem with the exact Jacobians, with Q times them (left_factor=True, Q moving
    with the point) and with forward mode: the same solution, iterations and corrections.  The
    batched problems start at different distances, so they stop in different rounds and the
    working set (with its held L, Bm e and Q) shrinks; unbatched: one problem."""
    obs, truth = _rigid2d(B=4 if batched else 1)
    B, E = obs.shape[:2]
    cov = torch.diag(torch.tensor([1.0, 2.0, 0.5, 1.5], dtype=f64)) * 0.02 ** 2
    offset = torch.tensor([0.3, 0.5, -0.4], dtype=f64)
    x0 = truth + offset * torch.tensor([1.0, 0.0, 3.0, 1e-4], dtype=f64)[:B, None]
    results = []
    for mode in ("exact", "left factor", "forward"):
        graph = fg.FactorGraph()
        graph.add_variable("x", x0[:, None, :] if batched else x0[0, None, :])
        data = obs if batched else obs[0]
        scaled = mode == "left factor"
        jac = None if mode == "forward" else (
            lambda x, o, e, scaled=scaled: _rigid2d_jacobians(x, o, e, scaled))
        factor = fg.GaussHelmert(_rigid2d_condition, [("x", torch.zeros(E, dtype=torch.int64))],
                                 cov, data=[data], dim=2, jacobians=jac, iterated=iterated,
                                 left_factor=scaled)
        graph.add(factor)
        result = fg.gauss_helmert(graph, step_tol=1e-10, damped=iterated, cost_tests=iterated)
        assert (result.report.status == SolverStatus.CONVERGED).all(), mode
        results.append((result, factor.corrections))
    (ref, e_ref), others = results[0], results[1:]
    if batched:  # the problems stop in different rounds
        assert len(set(ref.report.iterations.tolist())) > 1, ref.report.iterations
    for result, e in others:
        torch.testing.assert_close(result.values["x"], ref.values["x"], rtol=0, atol=1e-11)
        assert torch.equal(result.report.iterations, ref.report.iterations)
        if iterated:
            torch.testing.assert_close(e, e_ref, rtol=0, atol=1e-12)
        torch.testing.assert_close(result.information, ref.information, rtol=1e-9, atol=0)
    x = ref.values["x"][:, 0] if batched else ref.values["x"][None, 0]
    assert (x - truth).abs().max() < 0.05


def test_left_factor_arguments():
    obs, truth = _rigid2d(B=1, E=4)
    cov = 0.02 ** 2 * torch.eye(4, dtype=f64)
    idx = [("x", torch.zeros(4, dtype=torch.int64))]
    with pytest.raises(ValueError, match="left_factor=True needs jacobians"):
        fg.GaussHelmert(_rigid2d_condition, idx, cov, data=[obs], dim=2, left_factor=True)
    with pytest.raises(TypeError, match="left_factor"):
        fg.GaussHelmert(_rigid2d_condition, idx, cov, data=[obs], dim=2, left_factor=1,
                        jacobians=lambda x, o, e: _rigid2d_jacobians(x, o, e, True))

    def solve(jac):
        graph = fg.FactorGraph()
        graph.add_variable("x", truth[:, None, :])
        graph.add(fg.GaussHelmert(_rigid2d_condition, idx, cov, data=[obs], dim=2,
                                  jacobians=jac, left_factor=True))
        return fg.gauss_helmert(graph)

    with pytest.raises(ValueError, match=r"jacobians must return 4 items .*got 3"):
        solve(lambda x, o, e: _rigid2d_jacobians(x, o, e, False))
    with pytest.raises(ValueError, match=r"Q of shape \(\.\.\., 2, 2\)"):
        solve(lambda x, o, e: _rigid2d_jacobians(x, o, e, True)[:3] + (torch.eye(3, dtype=f64),))


def test_a_solve_leaves_no_reference_cycle_and_a_copy_runs_its_own_methods():
    """The factor's residual and Jacobians are its methods bound on access: no reference cycle
    (factor -> bound method -> factor) keeps the factor and its linearisation's tensors alive
    after a solve (reference counting frees them, the cyclic collector kept off), and a copy
    (what graph.add makes to give it a loss) linearises itself, not the original."""
    import copy
    import gc
    import weakref

    obs, truth = _line_data()
    cov = torch.diag(torch.tensor([0.05, 0.05], dtype=f64) ** 2)
    # a first solve: torch imports modules at first use, and torch.fx.wrap keeps its importer's
    # frame (and the frames below it, with their locals) for good
    fg.gauss_helmert(_line_graph(obs, cov, True, torch.zeros_like(truth))[0])
    graph, factor = _line_graph(obs, cov, True, torch.zeros_like(truth))
    was = gc.isenabled()
    gc.disable()
    try:
        fg.gauss_helmert(graph)
        assert factor.linearisation is not None
        refs = [weakref.ref(factor)] + [weakref.ref(t) for t in factor.linearisation]
        del graph, factor
        alive = sum(r() is not None for r in refs)
    finally:
        if was:
            gc.enable()
    assert alive == 0, f"{alive} of the factor and its {len(refs) - 1} linearisation tensors survive"
    _, factor = _line_graph(obs, cov, True, torch.zeros_like(truth))
    twin = copy.copy(factor)
    assert twin.residual.__self__ is twin and twin.jacobians.__self__ is twin
    assert factor.residual.__self__ is factor
    with pytest.raises(AttributeError, match="residual"):
        factor.residual = _line_condition


def test_dim_is_required():
    """dim is the condition's size, required: None is refused by name (accepted, it would fail
    in the solve on a bare assertion)."""
    obs, _ = _line_data(B=2, E=5)
    idx = torch.zeros(5, dtype=torch.int64)
    with pytest.raises(TypeError, match="dim must be an integer >= 1, got None"):
        fg.GaussHelmert(_line_condition, [("x", idx)], torch.eye(2, dtype=f64), data=[obs], dim=None)


def test_other_solvers_refuse_an_iterated_graph_also_after_a_gauss_helmert_solve():
    """The iterated conditions' state is the solve's own: after ``gauss_helmert`` the other
    solvers refuse the graph as they do before it (with the state left, they would report
    NON_FINITE, with NaN costs, for finite data), and ``gauss_helmert`` solves it again from the
    estimated corrections."""
    obs, truth = _line_data(B=2, E=30)
    cov = 0.05 ** 2 * torch.eye(2, dtype=f64)
    graph, factor = _line_graph(obs, cov, True, truth + 0.3)
    first = fg.gauss_helmert(graph)
    assert (first.report.status == SolverStatus.CONVERGED).all()
    for solver in (fg.levenberg_marquardt, fg.gauss_newton, fg.dogleg):
        with pytest.raises(RuntimeError, match=r"solve its graph with torchsgal.estimation.graph.gauss_helmert\(graph\)"):
            solver(graph)
    again = fg.gauss_helmert(graph)
    assert (again.report.status == SolverStatus.CONVERGED).all()
    # the orthogonal regression of isotropic noise (the smallest principal axis of the points)
    centred = obs - obs.mean(1, keepdim=True)
    normal = torch.linalg.eigh(centred.mT @ centred)[1][..., 0]  # (B, 2), smallest eigenvalue
    slope = -normal[:, 0] / normal[:, 1]
    torch.testing.assert_close(again.values["x"][:, 0, 0], slope, rtol=1e-6, atol=1e-8)
