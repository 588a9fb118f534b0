"""The generic batched solvers on small problems with known answers."""
import math

import numpy as np
import pytest
import torch

import torchsgal as ts
from torchsgal.estimation import SolverStatus, autograd_jacobian, gauss_helmert, gauss_newton, metrics, study
from torchsgal.estimation import variables as V
from torchsgal.estimation.lbfgs import lbfgs

f64 = torch.float64


def _time_flow_problem(B=4, K=6, seed=0, noise=0.0):
    """Unknowns (g in SGal3, s in R): data Y_k = g exp(t_k s e_10) (+ noise)."""
    gen = torch.Generator().manual_seed(seed)
    g_true = ts.SGal3(ts.functional.sgal3.random((B,), f64, None, gen))
    s_true = torch.randn(B, 1, generator=gen, dtype=f64)
    t = torch.linspace(-1, 2, K, dtype=f64)

    def flow(g, s):
        xi = torch.zeros(B, K, 10, dtype=f64)
        xi = torch.cat([xi[..., :9], (t * s)[..., None]], -1)
        return g.unsqueeze(-1) @ ts.SGal3.exp(xi)

    Y = flow(g_true, s_true)
    if noise:
        Y = Y.rplus(noise * torch.randn(B, K, 10, generator=gen, dtype=f64))

    def residual(x):
        g, s = x
        return Y.rminus(flow(g, s)).reshape(B, K * 10)

    return residual, (g_true, s_true)


def test_gauss_newton_recovers_group_and_scalar_unknowns():
    residual, (g_true, s_true) = _time_flow_problem()
    step = 0.3 * torch.randn(4, 10, dtype=f64, generator=torch.Generator().manual_seed(41))
    x0 = (g_true.rplus(step), s_true + 0.5)
    sol = gauss_newton(residual, x0)
    assert sol.report.converged.all()
    # noise-free: Gauss-Newton ends at rounding (measured 4.4e-16, cost 1.4e-30)
    assert g_true.rminus(sol.x[0]).abs().max() < 1e-13
    assert (sol.x[1] - s_true).abs().max() < 1e-13
    assert sol.report.cost.max() < 1e-26


def test_autograd_jacobian_matches_finite_differences():
    residual, (g, s) = _time_flow_problem(B=2, K=3, noise=0.1)
    x = (g.rplus(0.2 * torch.ones(2, 10, dtype=f64)), s)
    J = autograd_jacobian(residual, x)
    h = 1e-6
    cols = []
    for j in range(11):
        d = torch.zeros(2, 11, dtype=f64)
        d[:, j] = h
        cols.append((residual(V.retract(x, d)) - residual(V.retract(x, -d))) / (2 * h))
    fd = torch.stack(cols, -1)
    assert (J - fd).abs().max() < 1e-7


def test_linear_least_squares_solution_and_covariance_match_lstsq():
    gen = torch.Generator().manual_seed(1)
    B, m, d = 5, 12, 3
    A = torch.randn(B, m, d, generator=gen, dtype=f64)
    y = torch.randn(B, m, generator=gen, dtype=f64)
    ref = torch.linalg.lstsq(A, y[..., None]).solution[..., 0]
    P = torch.linalg.inv(A.transpose(-1, -2) @ A)
    # Plain Gauss-Newton (damping=None): the first step solves a linear problem exactly.
    sol = gauss_newton(lambda x: (A @ x[0][..., None])[..., 0] - y, (torch.zeros(B, d, dtype=f64),),
                       jacobian=lambda x: A, damping=None)
    assert (sol.x[0] - ref).abs().max() < 1e-12  # measured 4e-15
    assert (sol.covariance - P).abs().max() < 1e-14  # measured 2.8e-17 (entries ~0.1)
    assert sol.report.converged.all()
    # Levenberg-Marquardt (the default) accepts a step only if the cost does not rise: near the
    # optimum, where a step's decrease 1/2 |e|_H^2 falls below the rounding of the cost, steps
    # are rejected at random and the point stops within that resolution (seen: 4e-15 on one CPU,
    # 1.4e-9 after 9 iterations on another).  The error in the information metric is bounded by
    # the cost comparison's resolution, sqrt(2 * k * eps * cost), k = 16 roundings.
    sol = gauss_newton(lambda x: (A @ x[0][..., None])[..., 0] - y, (torch.zeros(B, d, dtype=f64),),
                       jacobian=lambda x: A)
    assert sol.report.converged.all()
    e = (sol.x[0] - ref)[..., None]
    err_h = (e.mT @ A.mT @ A @ e).squeeze((-1, -2)).sqrt()
    cost = 0.5 * ((A @ ref[..., None])[..., 0] - y).square().sum(-1)
    assert (err_h <= (2 * 16 * torch.finfo(f64).eps * cost).sqrt()).all(), (err_h, cost)
    assert (sol.covariance - P).abs().max() < 1e-14


def test_one_bad_problem_does_not_spoil_the_batch():
    residual, (g_true, s_true) = _time_flow_problem(B=4)
    M = g_true.as_matrix().clone()
    x0 = (g_true.rplus(0.1 * torch.ones(4, 10, dtype=f64)), s_true + 0.2)
    m0 = x0[0].as_matrix().clone()
    m0[2, 0, 0] = float("nan")
    sol = gauss_newton(residual, (ts.SGal3(m0), x0[1]))
    status = sol.report.status.tolist()
    assert status[2] == SolverStatus.NON_FINITE
    assert sol.report.counts() == {"CONVERGED": 3, "NON_FINITE": 1}
    ok = [0, 1, 3]
    assert all(status[i] == SolverStatus.CONVERGED for i in ok)
    assert ts.SGal3(M[ok]).rminus(sol.x[0][ok]).abs().max() < 1e-12  # measured 7.3e-14
    assert torch.isnan(sol.covariance[2]).all() and torch.isfinite(sol.covariance[ok]).all()


def test_unobservable_direction_is_reported_singular():
    gen = torch.Generator().manual_seed(2)
    A = torch.randn(3, 6, 2, generator=gen, dtype=f64)
    A[1, :, 1] = 2 * A[1, :, 0]  # problem 1: rank deficient
    y = torch.randn(3, 6, generator=gen, dtype=f64)
    sol = gauss_newton(lambda x: (A @ x[0][..., None])[..., 0] - y, (torch.zeros(3, 2, dtype=f64),),
                       jacobian=lambda x: A)
    assert sol.report.status.tolist() == [SolverStatus.CONVERGED, SolverStatus.SINGULAR,
                                          SolverStatus.CONVERGED]


@pytest.mark.parametrize("damping", [None, 1e-3])
def test_solver_loop_reads_the_host_once_per_iteration(damping):
    """The stop test and the all-accepted shortcut share one read per iteration (not one each):
    on CUDA each is a host sync.  Outside the loop: the first count, and eigh's of the
    singularity test."""
    from host_syncs import HostSyncs

    residual, (g_true, s_true) = _time_flow_problem()
    x0 = (g_true.rplus(0.3 * torch.ones(4, 10, dtype=f64)), s_true + 0.3)
    for max_iterations in (1, 4):
        with HostSyncs() as syncs:
            sol = gauss_newton(residual, x0, max_iterations=max_iterations, damping=damping)
        loop = [e for e in syncs.events if "solver.py" in e[1] and "eigh" not in e[0]]
        n = int(sol.report.iterations.max())
        assert n == max_iterations and len(loop) == n + 1, syncs.events


def test_max_iterations_status():
    residual, (g_true, s_true) = _time_flow_problem()
    x0 = (g_true.rplus(0.5 * torch.ones(4, 10, dtype=f64)), s_true + 0.5)
    sol = gauss_newton(residual, x0, max_iterations=1)
    assert (sol.report.status == SolverStatus.MAX_ITERATIONS).all()


def test_errors_name_the_argument():
    r = lambda x: x[0]
    # a block given alone is named x0 (not x0[0], as if a tuple had been passed)
    with pytest.raises(ValueError, match=r"x0 must be a tensor of shape \(B, k\) or \(B, K, k\)"):
        gauss_newton(r, torch.zeros(3, dtype=f64))
    with pytest.raises(ValueError, match="batch size"):
        gauss_newton(r, (torch.zeros(3, 2, dtype=f64), torch.zeros(4, 1, dtype=f64)))
    with pytest.raises(TypeError, match=r"x0 must be floating point"):
        gauss_newton(r, torch.zeros(3, 2, dtype=torch.int64))
    with pytest.raises(TypeError, match=r"x0\[1\] must be floating point"):
        gauss_newton(r, (torch.zeros(3, 2, dtype=f64), torch.zeros(3, 2, dtype=torch.int64)))
    g = ts.SE3.identity((3, 2, 4), dtype=f64)
    for solve in (lambda x: gauss_newton(r, x), lambda x: lbfgs(lambda x, _: r(x), x),
                  lambda x: gauss_helmert(lambda x, e: r(x), x, torch.eye(2, dtype=f64))):
        with pytest.raises(ValueError, match=r"x0 \(SE3\) must have batch shape \(B,\) .* or "
                                             r"\(B, K\) .*, got \(3, 2, 4\)"):
            solve(g)
        with pytest.raises(ValueError, match=r"x0\[1\] \(SE3\) must have batch shape"):
            solve((torch.zeros(3, 1, dtype=f64), g))
    with pytest.raises(ValueError, match=r"residual\(x\) must return \(B, m\)"):
        gauss_newton(lambda x: x[0].sum(-1), torch.zeros(3, 2, dtype=f64))
    with pytest.raises(ValueError, match=r"jacobian\(x\) must return"):
        gauss_newton(r, (torch.zeros(3, 2, dtype=f64),), jacobian=lambda x: torch.zeros(3, 2, 5))


# ------------------------------------------------------------------ errors in variables
def _line_data(B=3, K=40, seed=3, sigma=0.3):
    gen = torch.Generator().manual_seed(seed)
    a, b = torch.randn(B, generator=gen, dtype=f64), torch.randn(B, generator=gen, dtype=f64)
    u = 4 * torch.rand(B, K, generator=gen, dtype=f64) - 2
    x = u + sigma * torch.randn(B, K, generator=gen, dtype=f64)
    y = a[:, None] * u + b[:, None] + sigma * torch.randn(B, K, generator=gen, dtype=f64)
    return x, y


def _line_condition(x, y):
    """c = (y + e_y) - a (x + e_x) - b; unknowns (a, b); e = (e_x, e_y)."""
    def condition(p, e):
        ab = p[0]
        a, b = ab[:, 0:1], ab[:, 1:2]
        ex = 0 if e is None else e[..., 0]
        ey = 0 if e is None else e[..., 1]
        c = (y + ey - a * (x + ex) - b)[..., None]
        A = torch.stack([-(x + ex), -torch.ones_like(x)], -1)[..., None, :]
        Bm = torch.stack([-a.expand_as(x), torch.ones_like(x)], -1)[..., None, :]
        return c, A, Bm
    return condition


def _orthogonal_regression(x, y):
    D = np.stack([x.numpy(), y.numpy()], -1)
    D = D - D.mean(0)
    n = np.linalg.svd(D)[2][-1]  # normal of the line
    slope = -n[0] / n[1]
    return slope, y.mean().item() - slope * x.mean().item()


def test_gauss_helmert_iterated_line_fit_is_orthogonal_regression():
    """With equal isotropic noise on x and y, the errors-in-variables optimum is the
    orthogonal-regression line: the smallest right singular vector of the centred data."""
    x, y = _line_data()
    cov = 0.09 * torch.eye(2, dtype=f64)
    # It converges linearly here: ask for a step below 1e-10 standard deviations.
    sol = gauss_helmert(_line_condition(x, y), (torch.zeros(3, 2, dtype=f64),), cov,
                        step_tol=1e-10, max_iterations=100)
    assert sol.report.converged.all()
    for k in range(3):
        slope, icpt = _orthogonal_regression(x[k], y[k])
        assert abs(sol.x[0][k, 0].item() - slope) < 1e-8
        assert abs(sol.x[0][k, 1].item() - icpt) < 1e-8
    # The estimated residuals satisfy the conditions.
    c, _, _ = _line_condition(x, y)(sol.x, sol.aux)
    assert c.abs().max() < 1e-8


def test_gauss_helmert_paper_variant_reaches_its_own_fixed_point():
    """Linearising at e = 0 every time keeps A = -[x, 1] at the observed x: the fixed point
    solves sum A^T S^-1 c(x, 0) = 0 with S = Bm Sigma Bm^T, which is not the optimum."""
    x, y = _line_data()
    cov = 0.09 * torch.eye(2, dtype=f64)
    cond = _line_condition(x, y)
    sol = gauss_helmert(cond, (torch.zeros(3, 2, dtype=f64),), cov, variant="paper")
    assert sol.report.converged.all()
    c, A, Bm = cond(sol.x, None)
    S = Bm @ cov @ Bm.transpose(-1, -2)
    g = (A.transpose(-1, -2) @ torch.linalg.solve(S, c[..., None])).sum(1)[..., 0]
    assert g.abs().max() < 1e-6
    slope, _ = _orthogonal_regression(x[0], y[0])
    assert abs(sol.x[0][0, 0].item() - slope) > 1e-3


def test_gauss_helmert_covariance_checks():
    x, y = _line_data()
    cond = _line_condition(x, y)
    x0 = (torch.zeros(3, 2, dtype=f64),)
    with pytest.raises(ValueError, match="not symmetric"):
        gauss_helmert(cond, x0, torch.tensor([[1.0, 0.5], [0.0, 1.0]], dtype=f64))
    with pytest.raises(ValueError, match="not positive definite"):
        gauss_helmert(cond, x0, torch.tensor([[1.0, 2.0], [2.0, 1.0]], dtype=f64))
    with pytest.raises(ValueError, match=r"\(\.\.\., m, m\)"):
        gauss_helmert(cond, x0, torch.ones(2, dtype=f64))
    with pytest.raises(ValueError, match="variant"):
        gauss_helmert(cond, x0, torch.eye(2, dtype=f64), variant="exact")
    with pytest.raises(ValueError, match="observation covariance has size 3"):
        gauss_helmert(cond, x0, torch.eye(3, dtype=f64))


def test_gauss_helmert_checks_e0_observation_count_at_entry():
    """An e0 with another number of observations N than the condition's (40) is named with the
    expected and given shapes before the condition sees it (without the check, a RuntimeError
    from inside the user's condition)."""
    x, y = _line_data()
    cond = _line_condition(x, y)
    seen = []

    def recording(p, e):
        seen.append(None if e is None else tuple(e.shape))
        return cond(p, e)
    x0 = (torch.zeros(3, 2, dtype=f64),)
    cov = torch.eye(2, dtype=f64)
    for n in (39, 1, 41):
        seen.clear()
        with pytest.raises(ValueError, match=rf"e0 must have shape \(B, N, m\) = \(3, 40, 2\), "
                                             rf"got \(3, {n}, 2\)"):
            gauss_helmert(recording, x0, cov, e0=torch.zeros(3, n, 2, dtype=f64))
        assert (3, n, 2) not in seen  # the condition never received the bad e0
    # a right e0 (the residuals of a converged solve) is accepted and gives the same solution
    ref = gauss_helmert(cond, x0, cov, step_tol=1e-10, max_iterations=100)
    warm = gauss_helmert(cond, x0, cov, e0=ref.aux, step_tol=1e-10, max_iterations=100)
    slope, icpt = _orthogonal_regression(x[0], y[0])
    assert abs(warm.x[0][0, 0].item() - slope) < 1e-8 and abs(warm.x[0][0, 1].item() - icpt) < 1e-8


def test_gauss_helmert_checks_its_inputs_and_the_condition():
    x, y = _line_data()
    cond = _line_condition(x, y)
    x0 = (torch.zeros(3, 2, dtype=f64),)
    cov = torch.eye(2, dtype=f64)
    with pytest.raises(ValueError, match=r"observation_covariance must have shape .* m >= 1"):
        gauss_helmert(cond, x0, torch.zeros(0, 0, dtype=f64))
    with pytest.raises(ValueError, match=r"do not broadcast: conditions \(3, 40\), "
                                         r"observation_covariance \(2, 1\)"):
        gauss_helmert(cond, x0, cov.expand(2, 1, 2, 2))
    with pytest.raises(TypeError, match="observation_covariance has dtype torch.float32"):
        gauss_helmert(cond, x0, cov.float())
    with pytest.raises(ValueError, match=r"e0 must have shape \(B, N, m\)"):
        gauss_helmert(cond, x0, cov, e0=torch.zeros(3, 40, 5, dtype=f64))
    with pytest.raises(TypeError, match="e0 has dtype torch.float32"):
        gauss_helmert(cond, x0, cov, e0=torch.zeros(3, 40, 2))

    def flat(p, e):
        c, A, Bm = cond(p, e)
        return c[..., 0], A, Bm
    with pytest.raises(ValueError, match=r"condition must return c of shape \(B, N, k\)"):
        gauss_helmert(flat, x0, cov)

    def float32(p, e):
        c, A, Bm = cond(p, e)
        return c.float(), A, Bm
    with pytest.raises(TypeError, match="c has dtype torch.float32"):
        gauss_helmert(float32, x0, cov)


def test_solver_options_are_checked():
    residual, (g_true, s_true) = _time_flow_problem(B=2)
    x0 = (g_true, s_true)
    for option, value in (("max_iterations", -1), ("damping", -1.0), ("damping", math.nan),
                          ("step_tol", -1e-6), ("step_tol", math.inf), ("cost_tol", -1.0),
                          ("accept_tol", -0.1), ("always_accept_below", -1.0),
                          ("max_damping", 0.0), ("stop_below_fraction", 1.5),
                          ("stop_below_fraction", -0.5)):
        with pytest.raises(ValueError, match=f"{option} must be .*, got {value!r}"):
            gauss_newton(residual, x0, **{option: value})
    for option, value in (("max_iterations", 2.5), ("max_iterations", True), ("damping", "1e-4"),
                          ("cost_tol", None), ("stop_below_fraction", False)):
        with pytest.raises(TypeError, match=f"{option} must be .*, got {value!r}"):
            gauss_newton(residual, x0, **{option: value})
    # The edge values are legitimate: no iteration, undamped, zero tolerances.
    sol = gauss_newton(residual, x0, max_iterations=0, damping=0.0, step_tol=0.0, cost_tol=0.0)
    assert (sol.report.iterations == 0).all()
    assert gauss_newton(residual, x0, damping=None).report.converged.all()


def test_residual_and_jacobian_must_match_the_unknowns():
    x0 = torch.zeros(2, 3, dtype=f64)
    eye = torch.eye(3, dtype=f64).expand(2, 3, 3)
    with pytest.raises(TypeError, match=r"residual\(x\) has dtype torch.float32 but x0 has "
                                        r"dtype torch.float64"):
        gauss_newton(lambda x: (x - 1).float(), x0, jacobian=lambda x: eye)
    with pytest.raises(TypeError, match=r"jacobian\(x\) has dtype torch.float32"):
        gauss_newton(lambda x: x - 1, x0, jacobian=lambda x: eye.float())
    with pytest.raises(ValueError, match=r"jacobian\(x\) is on meta"):
        gauss_newton(lambda x: x - 1, x0, jacobian=lambda x: eye.to("meta"))
    # An empty batch is solved trivially.
    sol = gauss_newton(lambda x: x - 1, x0[:0], jacobian=lambda x: eye[:0])
    assert sol.covariance.shape == (0, 3, 3) and sol.report.status.shape == (0,)
    # Unknowns without a tangent (nothing to solve for) are refused by name; unchecked, they
    # would fail with an IndexError of amax deep in the loop.
    none = torch.zeros(2, 0, dtype=f64)
    with pytest.raises(ValueError, match=r"x0 must have at least one unknown .* got tangent "
                                         r"sizes \[0\]"):
        gauss_newton(lambda x: torch.ones(2, 3, dtype=f64), none)
    with pytest.raises(ValueError, match=r"x0 must have at least one unknown .* got tangent "
                                         r"sizes \[0, 0\]"):
        gauss_helmert(lambda x, e: (torch.ones(2, 4, 1, dtype=f64), torch.zeros(2, 4, 1, 0, dtype=f64),
                                    torch.ones(2, 4, 1, 1, dtype=f64)),
                      (none, none), torch.eye(1, dtype=f64))


def test_lbfgs_matches_gauss_newton_on_a_group_problem():
    residual, (g_true, s_true) = _time_flow_problem(B=3, noise=0.05)
    x0 = (g_true.rplus(0.2 * torch.ones(3, 10, dtype=f64)), s_true + 0.1)
    gn = gauss_newton(residual, x0)
    x, _, rep = lbfgs(lambda x, _: 0.5 * residual(x).square().sum(-1), x0, max_iterations=300)
    assert rep.converged.all()
    assert gn.x[0].rminus(x[0]).abs().max() < 1e-6
    assert (gn.x[1] - x[1]).abs().max() < 1e-6


def test_chi2_band_and_expected_mmd_against_scipy():
    stats = pytest.importorskip("scipy.stats")
    lo, hi = metrics.anees_band(1200, 11)
    assert lo == pytest.approx(stats.chi2.ppf(0.025, 13200) / 1200, rel=1e-6)
    assert hi == pytest.approx(stats.chi2.ppf(0.975, 13200) / 1200, rel=1e-6)
    assert metrics.expected_mmd(11) == pytest.approx(stats.chi(11).mean(), rel=1e-12)
    # The paper's band (10.74, 11.27) and expected MMD (3.24), to the digits it prints.
    assert (round(lo, 2), round(hi, 2)) == (10.74, 11.27)
    assert round(metrics.expected_mmd(11), 2) == 3.24
    P = torch.diag(torch.tensor([4.0, 9.0], dtype=f64))[None]
    e = torch.tensor([[2.0, 3.0]], dtype=f64)
    assert metrics.nees(e, P).item() == pytest.approx(2.0)
    assert math.isclose(metrics.rmse(torch.tensor([[3.0, 4.0], [0.0, 0.0]])).item(), math.sqrt(12.5))


def test_metrics_at_the_edges_of_their_domains():
    """The chi-square quantile is never negative (Wilson-Hilferty's cube falls below 0 at small
    dof and very negative p_z), a normal quantile beyond 40 is refused (its cube overflowed),
    the expected MMD stays exact for large dof (its lgamma difference lost digits, then
    overflowed) and the NEES refuses an asymmetric covariance (Cholesky reads one triangle)."""
    mpmath = pytest.importorskip("mpmath")
    assert metrics.anees_band(1, 1)[0] == 0.0 and metrics.chi2_quantile(-1.96, 0.1) == 0.0
    with pytest.raises(ValueError, match=r"p_z must be a finite number in \[-40, 40\], got 1e\+200"):
        metrics.chi2_quantile(1e200, 1)
    mpmath.mp.dps = 40
    for k in (50.0, 2999.0, 3001.0, 1e4, 1e6, 1e12):
        exact = mpmath.sqrt(2) * mpmath.gamma((k + 1) / mpmath.mpf(2)) / mpmath.gamma(k / mpmath.mpf(2))
        assert metrics.expected_mmd(k) == pytest.approx(float(exact), rel=3e-12), k
    assert metrics.expected_mmd(1e308) == pytest.approx(1e154, rel=1e-15)
    with pytest.raises(ValueError, match=r"covariance is not symmetric: max \|P - P\^T\| = 5"):
        metrics.nees(torch.ones(1, 3, dtype=f64), torch.tensor([[[1.0, 5, 0], [0, 1, 0], [0, 0, 1]]], dtype=f64))
    nan_cov = torch.stack([torch.eye(3, dtype=f64), torch.full((3, 3), float("nan"), dtype=f64)])
    assert torch.equal(metrics.nees(torch.ones(2, 3, dtype=f64), nan_cov).isnan(), torch.tensor([False, True]))


def test_study_summarise_checks_its_arguments():
    """Errors of another width (the interval column read as empty), trials of different counts
    and a status that is not an int64 tensor are named (an IndexError or a misleading message
    from the NEES before)."""
    err, cov = torch.full((4, 11), 0.1, dtype=f64), torch.eye(11, dtype=f64).expand(4, 11, 11)
    ok = torch.zeros(4, dtype=torch.int64)
    with pytest.raises(ValueError, match=r"err must have shape \(K, 11\), got \(4, 10\)"):
        study.summarise(err[:, :10], cov, ok)
    with pytest.raises(ValueError, match=r"cov must have shape \(K, 11, 11\) = \(3, 11, 11\)"):
        study.summarise(err[:3], cov, ok)
    with pytest.raises(ValueError, match=r"status must have shape \(K,\) = \(4,\), got \(3,\)"):
        study.summarise(err, cov, ok[:3])
    with pytest.raises(TypeError, match="status must be an int64 tensor of SolverStatus codes, got list"):
        study.summarise(err, cov, [0, 0, 0, 0])
    assert study.summarise(err, cov, ok)["ANEES"] == pytest.approx(0.11)


def _summarise_case():
    """6 trials, 2 of them not converged with garbage (NaN error, NaN or asymmetric covariance)
    that a summary must ignore."""
    g = torch.Generator().manual_seed(3)
    K = 6
    err = torch.randn(K, 11, generator=g, dtype=f64)
    A = torch.randn(K, 11, 11, generator=g, dtype=f64)
    cov = A @ A.mT + 0.5 * torch.eye(11, dtype=f64)
    status = torch.full((K,), int(SolverStatus.CONVERGED), dtype=torch.int64)
    status[1] = int(SolverStatus.MAX_ITERATIONS)
    status[4] = int(SolverStatus.SINGULAR)
    err[1, 2] = float("nan")
    cov[1, 0, 5] = 7.0  # not symmetric
    cov[4] = float("nan")
    return err, cov, status


def test_study_summarise_equals_direct_computation_over_converged_trials():
    err, cov, status = _summarise_case()
    out = study.summarise(err, cov, status)
    E, P = err.numpy(), cov.numpy()
    ok = [k for k in range(E.shape[0]) if int(status[k]) == int(SolverStatus.CONVERGED)]
    assert ok == [0, 2, 3, 5]
    comps = {"position": (0, 3), "velocity": (3, 6), "orientation": (6, 9), "time_offset": (9, 10),
             "interval": (10, 11)}
    for name, (a, b) in comps.items():
        expect = math.sqrt(sum(float(E[k, a:b] @ E[k, a:b]) for k in ok) / len(ok))
        assert out[name] == pytest.approx(expect, rel=1e-13, abs=0), name
    q = [float(E[k] @ np.linalg.solve(P[k], E[k])) for k in ok]
    assert out["nees"] == pytest.approx(q, rel=1e-10)
    assert out["ANEES"] == pytest.approx(sum(q) / len(q), rel=1e-10)
    assert out["MMD"] == pytest.approx(sum(math.sqrt(v) for v in q) / len(q), rel=1e-10)
    assert out["converged"] == 4 and out["trials"] == 6
    # no converged trial: NaN statistics, as the mean of nothing (and no error)
    none = study.summarise(err, cov, torch.full((6,), int(SolverStatus.MAX_ITERATIONS), dtype=torch.int64))
    assert math.isnan(none["position"]) and math.isnan(none["ANEES"]) and math.isnan(none["MMD"])
    assert none["converged"] == 0 and none["nees"] == []


class _NoDataDependentShapes(torch.overrides.TorchFunctionMode):
    """Refuses the ops whose output shape depends on tensor values (boolean-mask indexing,
    masked_select, nonzero), which break vmap and torch.compile."""

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func in (torch.Tensor.__getitem__, torch.Tensor.__setitem__):
            index = args[1] if isinstance(args[1], tuple) else (args[1],)
            if any(isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in index):
                raise AssertionError("boolean-mask indexing")
        if func in (torch.masked_select, torch.Tensor.masked_select, torch.nonzero, torch.Tensor.nonzero,
                    torch.argwhere, torch.Tensor.argwhere):
            raise AssertionError(f"data-dependent shape: {func.__name__}")
        return func(*args, **kwargs)


def test_study_summarise_uses_no_data_dependent_shapes():
    err, cov, status = _summarise_case()
    expect = study.summarise(err, cov, status)
    with _NoDataDependentShapes():
        out = study.summarise(err, cov, status)
    assert out == expect or all(
        (out[k] == expect[k]) or (isinstance(out[k], float) and math.isnan(out[k]) and math.isnan(expect[k]))
        for k in expect)


def test_metrics_check_their_arguments():
    with pytest.raises(ValueError, match="dof must be a finite number > 0, got 0"):
        metrics.chi2_quantile(1.96, 0)
    with pytest.raises(ValueError, match=r"p_z must be a finite number in \[-40, 40\], got nan"):
        metrics.chi2_quantile(math.nan, 11)
    with pytest.raises(ValueError, match="trials must be an integer >= 1, got 0"):
        metrics.anees_band(0, 11)
    with pytest.raises(ValueError, match="dof must be an integer >= 1, got -1"):
        metrics.anees_band(10, -1)
    with pytest.raises(ValueError, match="dof must be a finite number > 0, got 0"):
        metrics.expected_mmd(0)
    e = torch.zeros(3, 2, dtype=f64)
    with pytest.raises(ValueError, match=r"covariance must have shape \(\.\.\., 2, 2\), got \(3, 3, 3\)"):
        metrics.nees(e, torch.eye(3, dtype=f64).expand(3, 3, 3))
    with pytest.raises(TypeError, match="covariance has dtype torch.float32 but error has dtype torch.float64"):
        metrics.nees(e, torch.eye(2).expand(3, 2, 2))
    with pytest.raises(ValueError, match=r"batch shapes do not broadcast: error \(3,\), covariance \(4,\)"):
        metrics.nees(e, torch.eye(2, dtype=f64).expand(4, 2, 2))
    with pytest.raises(TypeError, match="error must have a floating dtype"):
        metrics.rmse(torch.zeros(3, 2, dtype=torch.int64))
    with pytest.raises(ValueError, match=r"error must have shape \(K, k\), got \(3,\)"):
        metrics.rmse(torch.zeros(3, dtype=f64))
    assert math.isnan(metrics.rmse(torch.zeros(0, 3, dtype=f64)).item())  # no trials: undefined


def test_variables_check_blocks_and_shapes():
    F, E = ts.SGal3.identity((4,), dtype=f64), torch.zeros(4, 1, dtype=f64)
    with pytest.raises(ValueError, match=r"delta must have shape \(B, 11\) .* got \(4, 12\)"):
        V.retract((F, E), torch.zeros(4, 12, dtype=f64))  # the extra column must not be ignored
    with pytest.raises(ValueError, match="x and y must have the same number of blocks, got 2 and 1"):
        V.local((F, E), (F,))  # zip would truncate it silently
    with pytest.raises(TypeError, match=r"y\[0\] must be of the kind of x\[0\] \(SGal3\), got Tensor"):
        V.local((F, E), (E, F))
    with pytest.raises(ValueError, match=r"mask must be a bool tensor of shape \(B,\) = \(4,\)"):
        V.select(torch.ones(3, dtype=torch.bool), (F, E), (F, E))
    with pytest.raises(ValueError, match="new and old must have the same number of blocks"):
        V.select(torch.ones(4, dtype=torch.bool), (F, E), (F,))
    with pytest.raises(ValueError, match="x must hold at least one block, got none"):
        V.batch_size(())
    d = 0.1 * torch.arange(44, dtype=f64).reshape(4, 11) / 44
    assert torch.allclose(V.local((F, E), V.retract((F, E), d)), d, rtol=0, atol=1e-12)
    sel = V.select(torch.tensor([True, False, True, False]), (F, E + 1), (F, E))
    assert torch.equal(sel[1][:, 0], torch.tensor([1.0, 0.0, 1.0, 0.0], dtype=f64))


def test_single_unknown_reaches_the_residual_and_the_solution_unwrapped():
    """x0 given as one block alone (a group element or a tensor): residual, jacobian and
    condition receive it alone and Solution.x is that block (not a 1-tuple,
    on which ``lambda x: x.rminus(t)`` would raise AttributeError)."""
    gen = torch.Generator().manual_seed(7)
    target = ts.SE3(ts.functional.se3.random((4,), f64, None, gen))
    start = target.rplus(0.3 * torch.randn(4, 6, generator=gen, dtype=f64))
    seen = []

    def residual(x):
        seen.append(type(x))
        return x.rminus(target)
    sol = gauss_newton(residual, start)
    assert set(seen) == {ts.SE3} and type(sol.x) is ts.SE3 and sol.report.converged.all()
    assert target.rminus(sol.x).abs().max() < 1e-12
    assert sol.covariance.shape == (4, 6, 6)
    # the same problem as a 1-tuple: the tuple convention is unchanged
    sol1 = gauss_newton(lambda x: x[0].rminus(target), (start,))
    assert type(sol1.x) is tuple and torch.equal(sol1.x[0].as_matrix(), sol.x.as_matrix())
    # autograd_jacobian takes either form; at the solution J = J_r^-1(0) = I
    J = autograd_jacobian(lambda x: x.rminus(target), target)
    assert torch.equal(J, autograd_jacobian(lambda x: x[0].rminus(target), (target,)))
    assert (J - torch.eye(6, dtype=f64)).abs().max() < 1e-12
    # a tensor alone, with a given Jacobian that also receives it alone
    A = torch.randn(4, 9, 3, generator=gen, dtype=f64)
    y = torch.randn(4, 9, generator=gen, dtype=f64)
    lin = gauss_newton(lambda x: (A @ x[..., None])[..., 0] - y, torch.zeros(4, 3, dtype=f64),
                       jacobian=lambda x: A.expand(x.shape[0], 9, 3))
    assert type(lin.x) is torch.Tensor and lin.x.shape == (4, 3)
    assert (lin.x - torch.linalg.lstsq(A, y[..., None]).solution[..., 0]).abs().max() < 1e-12
    # lbfgs and gauss_helmert follow the same rule
    x, _, rep = lbfgs(lambda x, _: 0.5 * x.rminus(target).square().sum(-1), start)
    assert type(x) is ts.SE3 and rep.converged.all() and target.rminus(x).abs().max() < 1e-6
    xs, ys = _line_data()
    line = _line_condition(xs, ys)
    gh = gauss_helmert(lambda p, e: line((p,), e), torch.zeros(3, 2, dtype=f64),
                       0.09 * torch.eye(2, dtype=f64), step_tol=1e-10, max_iterations=100)
    ref = gauss_helmert(line, (torch.zeros(3, 2, dtype=f64),), 0.09 * torch.eye(2, dtype=f64),
                        step_tol=1e-10, max_iterations=100)
    assert type(gh.x) is torch.Tensor and torch.equal(gh.x, ref.x[0])


def _pose_chain(B=3, N=5, seed=11):
    """A batch of SE3 pose chains: prior on pose 0, odometry i -> i+1, a loop closure 0 -> N-1.
    Returns (residual(pose), x0 poses): ``pose(i)`` gives pose i (B,) of the unknowns."""
    gen = torch.Generator().manual_seed(seed)
    rnd = lambda *shape: torch.randn(*shape, generator=gen, dtype=f64)  # noqa: E731
    X = [ts.SE3.exp(rnd(B, 6))]
    for _ in range(N - 1):
        X.append(X[-1] @ ts.SE3.exp(rnd(B, 6)))
    s, sp = 0.05, 0.1
    prior = X[0].rplus(sp * rnd(B, 6))
    edges = [(i, i + 1) for i in range(N - 1)] + [(0, N - 1)]
    Z = [X[i].between(X[j]).rplus(s * rnd(B, 6)) for i, j in edges]

    def residual(pose):
        r = [pose(0).rminus(prior) / sp]
        r += [pose(i).between(pose(j)).rminus(z) / s for (i, j), z in zip(edges, Z)]
        return torch.cat(r, dim=-1)

    x0 = [prior]
    for z in Z[:N - 1]:
        x0.append(x0[-1] @ z)
    return residual, x0


def test_group_block_of_k_variables_solves_as_the_tuple_of_its_variables():
    """A (B, K) SE3 block (the K poses of each problem's pose graph): tangent K * 6 ordered
    variable-major, each pose moved by its own right perturbation; the same solution and
    covariance as the tuple of the K (B,) blocks, in gauss_newton, autograd_jacobian and lbfgs."""
    residual, x0 = _pose_chain()
    B, N = x0[0].batch_shape[0], len(x0)
    stacked = ts.SE3.stack(x0, dim=1)
    assert stacked.batch_shape == (B, N)
    r_tuple = lambda x: residual(lambda i: x[i])  # noqa: E731
    r_block = lambda x: residual(lambda i: x[:, i])  # noqa: E731
    J_t, J_b = autograd_jacobian(r_tuple, tuple(x0)), autograd_jacobian(r_block, stacked)
    assert J_b.shape == (B, 6 * (1 + N), 6 * N)  # prior + N edges
    torch.testing.assert_close(J_b, J_t, rtol=0, atol=1e-12)
    tup, blk = (gauss_newton(r_tuple, tuple(x0), step_tol=1e-3),
                gauss_newton(r_block, stacked, step_tol=1e-3))
    assert torch.equal(blk.report.iterations, tup.report.iterations)
    assert blk.report.converged.all() and tup.report.converged.all()
    assert type(blk.x) is ts.SE3 and blk.x.batch_shape == (B, N)
    assert blk.covariance.shape == (B, 6 * N, 6 * N)
    for i in range(N):
        torch.testing.assert_close(blk.x[:, i].as_matrix(), tup.x[i].as_matrix(), rtol=0, atol=1e-10)
    torch.testing.assert_close(blk.covariance, tup.covariance, rtol=1e-8, atol=1e-12)
    torch.testing.assert_close(blk.report.cost, tup.report.cost, rtol=1e-10, atol=0)
    # the covariance is over the stacked right perturbation, variable-major: the solution's
    # Hessian J^T J inverted (J by finite differences of the retraction, independent of the ordering)
    h, d = 1e-6, 6 * N
    J_fd = torch.stack([(r_block(V.retract((blk.x,), h * e)[0]) - r_block(V.retract((blk.x,), -h * e)[0]))
                        / (2 * h) for e in torch.eye(d, dtype=f64).expand(B, d, d).unbind(-1)], -1)
    P_fd = torch.linalg.inv(J_fd.mT @ J_fd)
    torch.testing.assert_close(blk.covariance, P_fd, rtol=1e-5, atol=1e-10)
    # lbfgs: the same iterates (a few steps; this problem is too ill-conditioned for it to converge fast)
    xb, _, rb = lbfgs(lambda x, _: 0.5 * r_block(x).square().sum(-1), stacked, max_iterations=5)
    xt, _, rt = lbfgs(lambda x, _: 0.5 * r_tuple(x).square().sum(-1), tuple(x0), max_iterations=5)
    assert type(xb) is ts.SE3 and xb.batch_shape == (B, N)
    assert (rb.cost < 0.5 * rb.initial_cost).all()
    torch.testing.assert_close(rb.cost, rt.cost, rtol=1e-8, atol=0)
    for i in range(N):
        torch.testing.assert_close(xb[:, i].as_matrix(), xt[i].as_matrix(), rtol=0, atol=1e-8)


def test_blocks_of_k_variables_in_variables_and_gauss_helmert():
    """(B, K) group and (B, K, k) tensor blocks through retract/local/select/finite, and a
    (B, 1, 2) tensor block in gauss_helmert (the line fit) equal to the (B, 2) one."""
    gen = torch.Generator().manual_seed(3)
    G = ts.SGal3(ts.functional.sgal3.random((4, 3), f64, None, gen))
    E = torch.randn(4, 2, 5, generator=gen, dtype=f64)
    x = (G, E)
    assert V.block_dims(x) == [30, 10] and V.tangent_dim(x) == 40 and V.batch_size(x) == 4
    d = 0.1 * torch.randn(4, 40, generator=gen, dtype=f64)
    y = V.retract(x, d)
    for k in range(3):  # variable k moves by d[:, 10 k : 10 k + 10]
        torch.testing.assert_close(y[0][:, k].as_matrix(), G[:, k].rplus(d[:, 10 * k:10 * k + 10]).as_matrix(),
                                   rtol=0, atol=1e-14)
    torch.testing.assert_close(y[1], E + d[:, 30:].reshape(4, 2, 5), rtol=0, atol=0)
    torch.testing.assert_close(V.local(x, y), d, rtol=0, atol=1e-12)
    mask = torch.tensor([True, False, True, False])
    sel = V.select(mask, y, x)
    assert torch.equal(sel[0].as_matrix()[1], G.as_matrix()[1]) and torch.equal(sel[1][2], y[1][2])
    E_bad = E.clone()
    E_bad[1, 1, 4] = float("nan")
    assert V.finite((G, E_bad)).tolist() == [True, False, True, True]
    xs, ys = _line_data()
    line = _line_condition(xs, ys)
    cov = 0.09 * torch.eye(2, dtype=f64)
    gh = gauss_helmert(lambda p, e: line((p[:, 0],), e), torch.zeros(3, 1, 2, dtype=f64), cov,
                       step_tol=1e-10, max_iterations=100)
    ref = gauss_helmert(line, (torch.zeros(3, 2, dtype=f64),), cov, step_tol=1e-10,
                        max_iterations=100)
    assert gh.x.shape == (3, 1, 2)
    torch.testing.assert_close(gh.x[:, 0], ref.x[0], rtol=0, atol=1e-12)
    torch.testing.assert_close(gh.covariance, ref.covariance, rtol=0, atol=1e-12)


def test_lbfgs_report_is_on_the_unknowns_device():
    """report.iterations is on the unknowns' device, as SolverReport says every field is (made on
    the CPU, report.iterations + report.status would fail on another device).
    torch.optim.LBFGS reads values, so its step is stubbed to run on 'meta'."""
    from unittest import mock

    import torchsgal as ts
    from torchsgal.estimation.lbfgs import lbfgs

    x0 = ts.SE3.identity(5, dtype=torch.float64, device="meta")
    target = ts.SE3.identity(5, dtype=torch.float64, device="meta")
    with mock.patch.object(torch.optim.LBFGS, "step", lambda self, closure: None):
        _, _, report = lbfgs(lambda x, e: x.rminus(target).square().sum(-1), x0)
    for name in ("status", "iterations", "initial_cost", "cost", "step_norm", "gradient_norm"):
        assert getattr(report, name).device.type == "meta", name


# ------------------------------------------------------------------ robustness of the reports
def _event_fit(B=4, n=12, sig=0.01, seed=1):
    """B SGal(3) fits to events: data F_true (x, t) + noise; the whitened residual and cost."""
    gen = torch.Generator().manual_seed(seed)
    F_true = ts.SGal3(ts.functional.sgal3.random((B,), f64, None, gen))
    P = 2 * torch.randn(B, n, 4, generator=gen, dtype=f64)
    obs = F_true.unsqueeze(-1).act(P) + sig * torch.randn(B, n, 4, generator=gen, dtype=f64)
    F0 = F_true.rplus(0.05 * torch.randn(B, 10, generator=gen, dtype=f64))

    def make(data):
        def residual(F):
            return ((F.unsqueeze(-1).act(P) - data) / sig).flatten(1)
        return residual, lambda F, _e=None: 0.5 * residual(F).square().sum(-1)
    return make, obs, F0


def test_lbfgs_masks_a_non_finite_problem_out_of_the_batch():
    """One NaN observation made the summed cost NaN, and every problem of the batch came back
    NON_FINITE with non-finite x.  The problem is left out of the sum: it stays at x0 with
    NaN costs, and the others are solved as they are without it."""
    make, obs, F0 = _event_fit()
    residual, cost = make(obs)
    L = torch.linalg.cholesky(gauss_newton(residual, F0).covariance)
    bad = obs.clone()
    bad[2, 0, 0] = float("nan")
    x, _, rep = lbfgs(make(bad)[1], F0, scale=L)
    assert rep.status.tolist() == [0, 0, SolverStatus.NON_FINITE, 0]
    assert torch.isfinite(x.as_matrix()).all()
    assert F0[2:3].rminus(x[2:3]).abs().max() < 1e-14
    for name in ("initial_cost", "cost", "step_norm", "gradient_norm"):
        value = getattr(rep, name)
        assert torch.isnan(value[2]) and torch.isfinite(value[[0, 1, 3]]).all(), name
    # The three good problems alone (problem 2's row of the residual filled in and dropped).
    ok = [0, 1, 3]

    def cost3(F, _e=None):
        full = ts.SGal3(torch.cat([F.as_matrix()[:2], F0.as_matrix()[2:3], F.as_matrix()[2:]]))
        return 0.5 * residual(full)[ok].square().sum(-1)
    x3, _, rep3 = lbfgs(cost3, F0[ok], scale=L[ok])
    assert rep3.converged.all()
    assert x3.rminus(x[ok]).abs().max() < 1e-12
    torch.testing.assert_close(rep.cost[ok], rep3.cost, rtol=1e-12, atol=0)


def test_lbfgs_checks_its_options_and_reports_an_early_stop():
    make, obs, F0 = _event_fit()
    _, cost = make(obs)
    with pytest.raises(ValueError, match="max_iterations must be an integer >= 0, got -1"):
        lbfgs(cost, F0, max_iterations=-1)
    with pytest.raises(ValueError, match="history_size must be an integer >= 1, got 0"):
        lbfgs(cost, F0, history_size=0)
    with pytest.raises(ValueError, match="gradient_tol must be a finite number >= 0"):
        lbfgs(cost, F0, gradient_tol=-1.0)
    with pytest.raises(ValueError, match=r"scale must have shape \(d,\) = \(10,\), \(B, d\) = "
                                         r"\(4, 10\) or \(B, d, d\) = \(4, 10, 10\) .*got \(3,\)"):
        lbfgs(cost, F0, scale=torch.ones(3, dtype=f64))
    with pytest.raises(TypeError, match="scale has dtype torch.float32"):
        lbfgs(cost, F0, scale=torch.ones(10))
    with pytest.raises(ValueError, match=r"extra must have shape \(B, \.\.\., k\) with B = 4"):
        lbfgs(cost, F0, extra=torch.zeros(3, 2, dtype=f64))
    with pytest.raises(ValueError, match=r"cost\(x, extra\) must return a tensor of shape "
                                         r"\(B,\) = \(4,\), got \(4, 1\)"):
        lbfgs(lambda F, _e: cost(F)[:, None], F0)
    # max_iterations=0 evaluates x0 only (it runs no iteration).
    x, _, rep = lbfgs(cost, F0, max_iterations=0)
    assert F0.rminus(x).abs().max() < 1e-15 and (rep.iterations == 0).all()
    assert (rep.status == SolverStatus.MAX_ITERATIONS).all()
    # Unpreconditioned, LBFGS stops on its loss-change tolerance long before max_iterations
    # with the gradient test failed: stalled (DIVERGED), not MAX_ITERATIONS.
    x, _, rep = lbfgs(cost, F0, max_iterations=200)
    assert (rep.iterations < 200).all()
    assert (rep.status == SolverStatus.DIVERGED).all()
    assert (rep.cost < rep.initial_cost).all()


def test_solutions_carry_no_autograd_graph():
    """Results carry no graph at all: the start is detached (attached, it would give
    d x_hat / d x0 = 1 where it is 0, and silently drop the gradients with respect to the data)."""
    b = torch.randn(3, 2, dtype=f64, requires_grad=True)
    x0 = torch.zeros(3, 2, dtype=f64, requires_grad=True)
    sol = gauss_newton(lambda x: x - b, x0)
    assert (sol.x - b).abs().max() < 1e-12
    for t in (sol.x, sol.covariance, sol.report.cost, sol.report.initial_cost,
              sol.report.gradient_norm, sol.report.step_norm):
        assert not t.requires_grad and t.grad_fn is None
    xs, ys = _line_data()
    cov = (0.09 * torch.eye(2, dtype=f64)).requires_grad_(True)
    for variant in ("iterated", "paper"):
        gh = gauss_helmert(_line_condition(xs, ys), (torch.zeros(3, 2, dtype=f64).requires_grad_(),),
                           cov, variant=variant)
        for t in (gh.x[0], gh.covariance, gh.aux, gh.report.cost):
            assert not t.requires_grad and t.grad_fn is None
    make, obs, F0 = _event_fit(B=2)
    data = obs.clone().requires_grad_(True)
    _, cost = make(data)
    scale = torch.ones(2, 10, dtype=f64, requires_grad=True)
    x, _, rep = lbfgs(cost, F0, scale=scale, max_iterations=5)
    assert not x.as_matrix().requires_grad and not rep.cost.requires_grad
    assert data.grad is None and scale.grad is None  # nothing accumulated in the caller's tensors


def test_non_finite_problem_reports_nan_costs_not_a_perfect_fit():
    """A NON_FINITE problem is sanitised to zeros while the batch iterates; its report said
    cost 0, initial_cost 0, gradient_norm 0, as if it fitted perfectly."""
    residual, (g_true, s_true) = _time_flow_problem(B=4)
    x0 = (g_true.rplus(0.1 * torch.ones(4, 10, dtype=f64)), s_true + 0.2)
    m0 = x0[0].as_matrix().clone()
    m0[2, 0, 0] = float("nan")
    rep = gauss_newton(residual, (ts.SGal3(m0), x0[1])).report
    assert rep.status[2] == SolverStatus.NON_FINITE
    for name in ("initial_cost", "cost", "step_norm", "gradient_norm"):
        value = getattr(rep, name)
        assert torch.isnan(value[2]) and torch.isfinite(value[[0, 1, 3]]).all(), name
    assert (rep.initial_cost[[0, 1, 3]] > 0).all()


@pytest.mark.parametrize("damping", [None, 1e-3])
def test_cost_that_overflows_at_x0_is_non_finite(damping):
    """Finite residuals whose cost overflows at x0 (|r| ~ 1e200: 1/2 |r|^2 = inf) are
    NON_FINITE with NaN costs (SolverStatus), not SINGULAR with an infinite cost (whose
    information, inf, would make the covariance NaN for the wrong reason)."""
    t = torch.tensor([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]], dtype=f64)
    scale = torch.tensor([1.0, 1e200, 1.0], dtype=f64)[:, None]
    sol = gauss_newton(lambda x: (x - t) * scale, torch.zeros(3, 2, dtype=f64),
                       jacobian=lambda x: torch.diag_embed(scale.expand(3, 2)), damping=damping)
    rep = sol.report
    assert rep.status.tolist() == [SolverStatus.CONVERGED, SolverStatus.NON_FINITE,
                                   SolverStatus.CONVERGED]
    for name in ("initial_cost", "cost", "step_norm", "gradient_norm"):
        value = getattr(rep, name)
        assert torch.isnan(value[1]) and torch.isfinite(value[[0, 2]]).all(), name
    assert (sol.x[[0, 2]] - t[[0, 2]]).abs().max() < 1e-9  # the others solved (a linear problem)
    assert torch.isnan(sol.covariance[1]).all()


def _sim3_alignment(M=40, N=10, seed=0):
    """Sim(3) alignment of noisy point pairs q = S p with errors in both (Gauss-Helmert)."""
    gen = torch.Generator().manual_seed(seed)
    S_true = ts.Sim3.exp(torch.tensor([0.5, -1.0, 2.0, 0.3, -0.6, 0.9, 0.2], dtype=f64))
    p = 3 * torch.randn(N, 3, generator=gen, dtype=f64)
    sp, sq = 0.01, 0.02
    p_obs = p + sp * torch.randn(M, N, 3, generator=gen, dtype=f64)
    q_obs = S_true.act(p) + sq * torch.randn(M, N, 3, generator=gen, dtype=f64)
    cov = torch.diag(torch.tensor([sp ** 2] * 3 + [sq ** 2] * 3, dtype=f64))

    def condition(S, e):
        e = torch.zeros(M, N, 6, dtype=f64) if e is None else e
        x = p_obs + e[..., :3]
        c = S.unsqueeze(-1).act(x) - (q_obs + e[..., 3:])
        A = torch.func.jacrev(lambda d: S.rplus(d).unsqueeze(-1).act(x).sum(0))(
            torch.zeros(M, 7, dtype=f64)).permute(2, 0, 1, 3)
        z = S.act(torch.zeros(M, 3, dtype=f64))
        lin = torch.stack([S.act(torch.eye(3, dtype=f64)[j].expand(M, 3)) - z for j in range(3)], -1)
        Bm = torch.cat([lin[:, None].expand(M, N, 3, 3),
                        -torch.eye(3, dtype=f64).expand(M, N, 3, 3)], -1)
        return c, A, Bm
    S0 = ts.Sim3(S_true.as_matrix().expand(M, 4, 4)).rplus(
        0.05 * torch.randn(M, 7, generator=gen, dtype=f64))
    return condition, S0, cov


def test_gauss_helmert_paper_variant_takes_plain_gauss_newton_steps_by_default():
    """With the generic solver's default damping (1e-4) the paper variant's Levenberg-Marquardt
    cost test stalled well-posed problems at its fixed point and reported DIVERGED (~10% of
    Sim(3) alignments); only the TLS solvers set damping=None.  An explicit damping is kept."""
    condition, S0, cov = _sim3_alignment()
    sol = gauss_helmert(condition, S0, cov, variant="paper")
    assert sol.report.converged.all()
    damped = gauss_helmert(condition, S0, cov, variant="paper", damping=1e-4)
    assert (damped.report.status == SolverStatus.DIVERGED).any()
    ref = gauss_helmert(condition, S0, cov, variant="paper", damping=None)
    assert torch.equal(ref.x.as_matrix(), sol.x.as_matrix())


def test_lbfgs_status_edges():
    """CONVERGED is LBFGS's absolute gradient test (a constant added to the cost changes
    nothing, and an unbounded cost is never converged); an empty batch or tangent returns an
    empty or trivial report; a singular scale is refused (its directions could not move)."""
    t = torch.tensor([[0.0, 1.0, 2.0]] * 4, dtype=f64)
    for offset in (0.0, 1e6):
        _, _, r = lbfgs(lambda x, _: (x - t).square().sum(-1) + offset, torch.zeros(4, 3, dtype=f64),
                        max_iterations=1)
        assert (r.status == SolverStatus.MAX_ITERATIONS).all(), offset
    _, _, r = lbfgs(lambda x, _: x.sum(-1), torch.zeros(4, 3, dtype=f64), max_iterations=5)
    assert not r.converged.any()
    x, _, r = lbfgs(lambda x, _: x.sum(-1), torch.zeros(0, 3, dtype=f64))
    assert x.shape == (0, 3) and r.status.shape == (0,)
    x, _, r = lbfgs(lambda x, _: x.new_ones(x.shape[0]), torch.zeros(4, 0, dtype=f64))
    assert r.converged.all() and torch.equal(r.cost, torch.ones(4, dtype=f64))
    for scale in (torch.tensor([1.0, 0.0, 1.0], dtype=f64), torch.zeros(4, 3, 3, dtype=f64)):
        with pytest.raises(ValueError, match="scale must be finite and invertible"):
            lbfgs(lambda x, _: (x - t).square().sum(-1), torch.zeros(4, 3, dtype=f64), scale=scale)


def test_undamped_levenberg_marquardt_recovers_from_a_rejected_step():
    """damping=0 starts undamped; a rejected step raises the damping (if it stayed 0, the same
    step would be rejected to the iteration limit)."""
    sol = gauss_newton(torch.atan, torch.full((1, 1), 2.0, dtype=f64), damping=0.0)
    assert sol.report.converged.all() and sol.x.abs().max() < 1e-10


def test_covariance_from_information_checks_and_refuses_to_invert_what_cholesky_did_not():
    from torchsgal.estimation.solver import covariance_from_information as cov
    H = torch.stack([torch.tensor([[1.0, 2.0], [2.0, 1.0]], dtype=f64), torch.zeros(2, 2, dtype=f64),
                     2 * torch.eye(2, dtype=f64)])
    out = cov(H, torch.tensor([False, False, False]))
    assert out[:2].isnan().all()
    torch.testing.assert_close(out[2], 0.5 * torch.eye(2, dtype=f64), rtol=1e-15, atol=0)
    with pytest.raises(TypeError, match="singular must be a bool tensor"):
        cov(H, False)
    with pytest.raises(ValueError, match=r"H must have shape \(\.\.\., d, d\), got \(2, 3\)"):
        cov(torch.zeros(2, 3, dtype=f64), torch.tensor([False]))
