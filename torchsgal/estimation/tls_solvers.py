"""The total-least-squares estimators on the factor-graph engine.

Each trial is a graph with the unknowns as variables (SGal(3): F (1 element) and dtau;
SE_2(3) x R: X', tau0 and dtau) and one ``graph.GaussHelmert`` factor of N + 1 conditions, the
batch of trials one batched graph.  The conditions are those of ``tls_problem.sgal3_condition``
and ``tls_baseline.baseline_condition`` written per condition, with their analytic Jacobians,
and the observation covariance
blockdiag(Sigma_a, Sigma_b) (the baseline's ``baseline_covariance``).  Their Jacobians are
J_r(c) times the exact derivatives: the paper-style variant may take any such factor
(``GaussHelmert``), and the iterated one, which holds each linearisation point while x moves,
gives it to the engine as its left factor (``left_factor=True``: the condition read as
J_r(c) c, the factor held with the linearisation point).  The iterated variant
runs Levenberg-Marquardt with the corrections updated after each accepted step, the paper
variant Gauss-Newton at zero corrections (kelly-giamou (5.18)); ``graph.gauss_helmert``.
"""
from __future__ import annotations

import torch

from ..functional import checks
from ..groups import SE23, SGal3
from .gauss_helmert import VARIANTS
from .graph import FactorGraph, GaussHelmert
from .graph.gauss_helmert_solver import gauss_helmert
from .solver import Solution, SolverReport, SolverStatus, covariance_from_information, information_is_singular
from .tls_baseline import _drift, baseline_covariance, baseline_observations, baseline_start, check_reading
from .tls_problem import (
    E10,
    TLSProblem,
    _ad_time_left,
    _ad_time_right_inverse,
    _check_unknowns,
    _drift_sgal3,
    _empty_solution,
)

# The options of solve_sgal3 / solve_baseline and their defaults: graph.gauss_helmert's, with
# convergence on the step (in standard deviations of the estimate) as well as on the cost.
DEFAULT_OPTIONS = {"max_iterations": 50, "step_tol": 1e-6, "relative_error_tol": 1e-14,
                   "absolute_error_tol": 0.0, "lambda_initial": 1e-5, "corrections_tol": 1e-6}


def _sgal3_terms(F, dtau, M, n, e):
    """(c (B, E, 10), [dc/dF (B, E, 10, 10), dc/ddtau (B, E, 10, 1)], Bm (B, E, 10, 20)) of
    the conditions log(M_n exp(eps_a) A_n exp(-eps_b)) (the formulas of ``sgal3_condition``);
    F (B, 1), dtau (B, 1, 1), M (B, E), n (E, 1), e (B, E, 20) or None.  Every Jacobian is
    J_r(c) times the exact derivative: at e = None (the paper-style form) this leaves the
    solution unchanged; otherwise (the iterated form) J_r(c) comes back as a fourth item, the
    factor's left factor Q (``GaussHelmert(left_factor=True)``).  The rows are those of
    ``sgal3_condition``: [Ad(Eb) Ad(T^n), Ad(Eb) d_t] and [Ad(Eb A_n^-1) J_r(eps_a),
    -J_l(eps_b)] (Eb = exp(eps_b); at e = None, Ad(A_n^-1) and -I)."""
    n = n[..., 0]
    s = n * dtau[..., 0]  # (B, E)
    eye = torch.eye(10, dtype=s.dtype, device=s.device)
    A = _drift_sgal3(F, s)
    # n (Ad(T^n F^-1) - I) e_10: the iota column of Ad(F^-1), moved by Ad(T^n)
    d_t = n[:, None, None] * (_ad_time_left(s, F.inverse().adjoint()[..., E10:E10 + 1])
                              - eye[E10][:, None])
    if e is None:
        c = (M @ A).log()
        d_a, d_b = A.inverse().adjoint(), -eye.expand(c.shape + (10,))  # Ad(A_n^-1), -I
        Bm = torch.cat([d_a.expand(c.shape + (10,)), d_b], -1)
        return c, [_ad_time_left(s, eye), d_t], Bm
    ea, eb = e[..., :10], e[..., 10:]
    Eb = SGal3.exp(eb)
    c = (M @ SGal3.exp(ea) @ A @ Eb.inverse()).log()
    left = Eb.adjoint()
    d_a = (Eb @ A.inverse()).adjoint() @ SGal3.jr(ea)  # Ad(Eb) Ad(A_n^-1) J_r(eps_a)
    d_F = _ad_time_right_inverse(left, -s)  # Ad(Eb) Ad(T^n), elementwise
    Bm = torch.cat([d_a, -SGal3.jl(eb)], -1)
    return c, [d_F, left @ d_t], Bm, SGal3.jr(c)


def _sgal3_condition(F, dtau, M, n, e):
    """c of ``_sgal3_terms`` alone (the same operations: the same values)."""
    A = _drift_sgal3(F, n[..., 0] * dtau[..., 0])
    if e is None:
        return (M @ A).log()
    return (M @ SGal3.exp(e[..., :10]) @ A @ SGal3.exp(e[..., 10:]).inverse()).log()


def _baseline_terms(X, tau0, dtau, M, dclock, n, e):
    """The baseline's conditions (``baseline_condition``) per condition: X (B, 1) SE23,
    tau0, dtau (B, 1, 1), M (B, E) SE23, dclock (B, E, 1), n (E, 1), e (B, E, 20) or None;
    the spatial rows' Jacobians are J_r(c') times the exact derivatives (c' the spatial part;
    the clock row is exact), as ``_sgal3_terms``: at e = None that leaves the solution
    unchanged, otherwise Q = blockdiag(J_r(c'), 1) comes back as a fourth item."""
    n = n[..., 0]
    s = n * dtau[..., 0]  # (B, E)
    eye9 = torch.eye(9, dtype=s.dtype, device=s.device)
    A = _drift(X, s)
    Cv = (X.rotation().mT @ X.velocity()[..., None])[..., 0]  # (B, 1, 3)
    nCv = -n[:, None] * Cv  # (B, E, 3): d rho / d dtau
    dt_col = torch.cat([nCv, torch.zeros_like(nCv), torch.zeros_like(nCv)], -1)[..., None]
    Q = None
    if e is None:
        c9 = (M @ A).log()
        d_a, d_b = A.inverse().adjoint(), -eye9.expand(c9.shape + (9,))  # Ad(A'_n^-1), -I
        P = _ad_time_left(s, eye9)
        ia = ib = 0.0
    else:
        ea, eb = e[..., :9], e[..., 10:19]
        ia, ib = e[..., 9], e[..., 19]
        Eb = SE23.exp(eb)
        c9 = (M @ SE23.exp(ea) @ A @ Eb.inverse()).log()
        left = Eb.adjoint()
        d_a = (Eb @ A.inverse()).adjoint() @ SE23.jr(ea)  # Ad(Eb) Ad(A'_n^-1) J_r(eps'_a)
        d_b = -SE23.jl(eb)
        P, dt_col = _ad_time_right_inverse(left, -s), left @ dt_col  # Ad(Eb) Ad(T^n), elementwise
        Q = c9.new_zeros(c9.shape[:-1] + (10, 10))
        Q[..., :9, :9] = SE23.jr(c9)
        Q[..., 9, 9] = 1.0
    ct = dclock[..., 0] + ia + tau0[..., 0] - ib  # (B, E)
    c = torch.cat([c9, ct[..., None]], dim=-1)
    shape = c.shape
    A_X = c.new_zeros(shape + (9,))
    A_X[..., :9, :] = P
    A_t0 = c.new_zeros(shape + (1,))
    A_t0[..., 9, 0] = 1.0
    A_dt = c.new_zeros(shape + (1,))
    A_dt[..., :9, :] = dt_col
    Bm = c.new_zeros(shape + (20,))  # [eps'_a, iota_a, eps'_b, iota_b]
    Bm[..., :9, :9] = d_a
    Bm[..., 9, 9] = 1.0
    Bm[..., :9, 10:19] = d_b
    Bm[..., 9, 19] = -1.0
    return (c, [A_X, A_t0, A_dt], Bm) if Q is None else (c, [A_X, A_t0, A_dt], Bm, Q)


def _baseline_condition(X, tau0, dtau, M, dclock, n, e):
    """c of ``_baseline_terms`` alone (the same operations: the same values)."""
    A = _drift(X, n[..., 0] * dtau[..., 0])
    if e is None:
        c9, ct = (M @ A).log(), dclock[..., 0] + 0.0 + tau0[..., 0] - 0.0
    else:
        c9 = (M @ SE23.exp(e[..., :9]) @ A @ SE23.exp(e[..., 10:19]).inverse()).log()
        ct = dclock[..., 0] + e[..., 9] + tau0[..., 0] - e[..., 19]
    return torch.cat([c9, ct[..., None]], dim=-1)


def _observation_covariance(cov_a: torch.Tensor, cov_b: torch.Tensor, B: int, E: int
                            ) -> torch.Tensor:
    """blockdiag(cov_a, cov_b) in the factor's layout: (20, 20) shared, (E, 20, 20) per
    condition or (B, E, 20, 20) per trial and condition."""
    shape = checks.broadcast_shapes(cov_a.shape[:-2], cov_b.shape[:-2])
    S = cov_a.new_zeros(shape + (20, 20))
    S[..., :10, :10] = cov_a
    S[..., 10:, 10:] = cov_b
    S = S.reshape((1,) * (4 - S.dim()) + S.shape)  # (b, e, 20, 20), b in (1, B), e in (1, E)
    if S.shape[0] != 1:
        return S.expand(B, E, 20, 20)
    return S[0, 0] if S.shape[1] == 1 else S[0]


def _options(options: dict) -> dict:
    unknown = sorted(set(options) - set(DEFAULT_OPTIONS))
    if unknown:
        raise TypeError(f"unknown solver option(s) {unknown}; the TLS solvers take "
                        f"{sorted(DEFAULT_OPTIONS)}")
    return {**DEFAULT_OPTIONS, **options}


def _solve(problem: TLSProblem, graph: FactorGraph, factor: GaussHelmert, names: list,
           iterated: bool, options: dict) -> Solution:
    """Solves the graph, then the solution in the layout of ``Solution``: the status SINGULAR
    (``solver.information_is_singular``) with a NaN covariance where the information at the
    solution is singular, the corrections (B, N+1, 20) in ``aux`` (iterated variant)."""
    o = _options(options)
    result = gauss_helmert(graph, o["max_iterations"], damped=iterated,
                           lambda_initial=o["lambda_initial"], step_tol=o["step_tol"],
                           relative_error_tol=o["relative_error_tol"],
                           absolute_error_tol=o["absolute_error_tol"], cost_tests=iterated,
                           corrections_tol=o["corrections_tol"])
    H = result.information
    report = result.report
    non_finite = report.status == SolverStatus.NON_FINITE
    singular = information_is_singular(H) & ~non_finite
    status = torch.where(singular | (report.status == SolverStatus.CONVERGED_RANK_DEFICIENT),
                         SolverStatus.SINGULAR, report.status).to(torch.int64)
    P = covariance_from_information(H, singular | non_finite)
    x = []
    for name in names:
        v = result.values[name]
        x.append(v[:, 0] if isinstance(v, (SGal3, SE23)) else v[:, 0, :])
    report = SolverReport(status=status, iterations=report.iterations,
                          initial_cost=report.initial_cost, cost=report.cost,
                          step_norm=report.step_norm, gradient_norm=report.gradient_norm)
    aux = factor.corrections if iterated else None
    return Solution(x=tuple(x), covariance=P, report=report, aux=aux)


def _indices(problem: TLSProblem) -> tuple[torch.Tensor, torch.Tensor]:
    """(the variables' element index of every condition, all 0 (E,); the sample indices n as
    data (E, 1))."""
    n = problem.indices
    assert n is not None  # set by TLSProblem
    return torch.zeros(n.shape[0], dtype=torch.int64, device=n.device), n[:, None]


def _check_variant(variant: str) -> bool:
    if variant not in VARIANTS:
        raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
    return variant == "iterated"


def solve_sgal3(problem: TLSProblem, x0=None, dtau0=-1.0, variant: str = "iterated",
                **options) -> Solution:
    """Estimates (F_a0b0, dtau) on SGal(3); covariance (B, 11, 11) over [dxi (10), ddtau].
    x0: (F SGal3 (B,), dtau (B, 1)); by default F from the first pair and ``dtau0`` (a scalar
    or (B,)).  variant: "iterated" (the errors-in-variables optimum; ``aux`` holds the
    estimated observation corrections (B, N+1, 20) = (eps_a, eps_b)) or "paper" (kelly-giamou
    (5.18): linearised at the raw observations, Gauss-Newton).  options (``DEFAULT_OPTIONS``):
    max_iterations, step_tol (a step below this many standard deviations converges),
    relative_error_tol and absolute_error_tol (GTSAM's cost tests), lambda_initial and
    corrections_tol (iterated: the last update of the corrections below this many standard
    deviations of the observations; ``graph.gauss_helmert``).  A problem
    without trials (B = 0) gives an empty solution.

    Use float64.  The information of this problem is badly scaled: its diagonal spans about
    six decades, below the SINGULAR test's threshold in float32 (1e3 eps relative), so float32
    problems are reported SINGULAR (with NaN covariances) even where the estimate is fine.
    Not differentiable."""
    iterated = _check_variant(variant)
    x0 = problem.initial_guess(dtau0, "dtau0") if x0 is None else x0
    x0 = _check_unknowns(problem, x0, baseline=False)
    if problem.batch_size == 0:
        return _empty_solution(problem, x0)
    Bn, N1 = problem.F_ga.batch_shape
    with torch.no_grad():
        graph = FactorGraph()
        graph.add_variable("F", x0[0].detach().unsqueeze(-1))
        graph.add_variable("dtau", x0[1].detach()[:, None, :])
        idx, n = _indices(problem)
        factor = GaussHelmert(_sgal3_condition, [("F", idx), ("dtau", idx)],
                              _observation_covariance(problem.cov_a, problem.cov_b, Bn, N1),
                              data=[problem.M, n], dim=10,
                              jacobians=_sgal3_terms, iterated=iterated, left_factor=iterated)
        graph.add(factor)
        return _solve(problem, graph, factor, ["F", "dtau"], iterated, options)


def solve_baseline(problem: TLSProblem, x0=None, dtau0=-1.0, variant: str = "iterated",
                   reading: str = "invariant", **options) -> Solution:
    """Estimates (X' in SE_2(3), tau0, dtau) on SE_2(3) x R; covariance (B, 11, 11) over
    [dxi' (9), dtau0, ddtau].  ``reading`` (``BASELINE_READINGS``): "invariant" (default) reads
    the relative transforms F~_gb^-1 F~_ga, composed in SGal(3), in the product group, and is
    unchanged by a Galilean change of the global frame; "product" composes the observations in
    the product group, and depends on the global frame's velocity (``baseline_observations``).
    x0: (X' SE23 (B,), tau0 (B, 1), dtau (B, 1)); by default ``baseline_start`` of the first
    pair and ``dtau0``.  Variants, options, B = 0 and float32: as ``solve_sgal3``."""
    iterated = _check_variant(variant)
    check_reading(reading)
    if x0 is None:
        F0, dt = problem.initial_guess(dtau0, "dtau0")
        X0, t0 = baseline_start(F0, reading)
        x0 = (X0, t0[:, None], dt)
    x0 = _check_unknowns(problem, x0, baseline=True)
    if problem.batch_size == 0:
        return _empty_solution(problem, x0)
    Bn, N1 = problem.F_ga.batch_shape
    with torch.no_grad():
        M, dclock = baseline_observations(problem, reading)
        ca, cb = baseline_covariance(problem)
        graph = FactorGraph()
        graph.add_variable("X", x0[0].detach().unsqueeze(-1))
        graph.add_variable("tau0", x0[1].detach()[:, None, :])
        graph.add_variable("dtau", x0[2].detach()[:, None, :])
        idx, n = _indices(problem)
        factor = GaussHelmert(_baseline_condition, [("X", idx), ("tau0", idx), ("dtau", idx)],
                              _observation_covariance(ca, cb, Bn, N1),
                              data=[M, dclock[..., None], n], dim=10,
                              jacobians=_baseline_terms, iterated=iterated, left_factor=iterated)
        graph.add(factor)
        return _solve(problem, graph, factor, ["X", "tau0", "dtau"], iterated, options)


__all__ = ["solve_sgal3", "solve_baseline", "DEFAULT_OPTIONS"]
