"""The total-least-squares problem of kelly-giamou Section 5, batched: the public names.

The problem, its SGal(3) condition and its checks are in ``tls_problem``, the SE_2(3) x R
baseline's readings and condition in ``tls_baseline``, and the Gauss-Helmert solvers on the
factor-graph engine (``solve_sgal3``, ``solve_baseline``) in ``tls_solvers``.  This module
gathers them and holds the costs the estimators minimise (``eiv_cost``, ``condition_cost``) and
the first-order solver of the paper variant (``solve_sgal3_lbfgs``).
"""
from __future__ import annotations

import torch

from ..functional import checks
from ..groups import SGal3
from . import variables as V
from .gauss_helmert import gauss_helmert
from .solver import Solution, SolverReport, SolverStatus
from .tls_baseline import (
    BASELINE_READINGS,
    baseline_condition,
    baseline_covariance,
    baseline_observations,
    baseline_start,
    check_reading,
    split_clock,
)
from .tls_problem import (
    E10,
    TLSProblem,
    _check_unknowns,
    _drift_sgal3,
    _empty_solution,
    sgal3_condition,
    subset,
)
from .tls_solvers import DEFAULT_OPTIONS, solve_baseline, solve_sgal3

__all__ = ["TLSProblem", "sgal3_condition", "subset", "E10", "BASELINE_READINGS", "split_clock",
           "check_reading", "baseline_observations", "baseline_start", "baseline_condition",
           "baseline_covariance", "solve_sgal3", "solve_baseline", "DEFAULT_OPTIONS", "eiv_cost",
           "condition_cost", "solve_sgal3_lbfgs"]


def eiv_cost(problem: TLSProblem):
    """The exact errors-in-variables cost of the SGal(3) model with the true frames a as
    nuisance variables F_ga_n = F~_ga_n exp(u_n):

        1/2 sum_n u_n^T Sigma_a^-1 u_n + 1/2 sum_n eps_b^T Sigma_b^-1 eps_b,
        eps_b = log(F~_gb_n^-1 F_ga_n A_n)  (F_gb_n = F_ga_n A_n exactly).

    Returns cost(x, u) -> (B,) with u (B, N+1, 10); the Gauss-Helmert iterated variant and
    the GTSAM factor graph minimise the same function."""
    n = problem.indices
    La = torch.linalg.cholesky(problem.cov_a)
    Lb = torch.linalg.cholesky(problem.cov_b)
    Fb_inv = problem.F_gb.inverse()

    def cost(x, u):
        F, dtau = x
        A = _drift_sgal3(F.unsqueeze(-1), n * dtau)
        eb = (Fb_inv @ problem.F_ga @ SGal3.exp(u) @ A).log()
        wa = torch.linalg.solve_triangular(La, u[..., None], upper=False)[..., 0]
        wb = torch.linalg.solve_triangular(Lb, eb[..., None], upper=False)[..., 0]
        return 0.5 * (wa.square().sum((-1, -2)) + wb.square().sum((-1, -2)))

    return cost


def condition_cost(problem: TLSProblem, weights_at=None):
    """The reduced cost of the Gauss-Helmert linearisation at zero observation residual,
    1/2 sum_n c_n^T S_n^-1 c_n with c_n = log(M_n A_n) and S_n = Ad(A_n^-1) Sigma_a Ad(A_n^-1)^T
    + Sigma_b ((5.23)-(5.24)).  With ``weights_at`` (unknowns x_ref) the weights S_n are frozen
    at x_ref: the paper variant's Gauss-Newton fixed point is the minimum of that cost with
    x_ref = the minimiser.  Without, S_n moves with x (a different, biased estimator)."""
    cond = sgal3_condition(problem)
    Sa, Sb = problem.cov_a, problem.cov_b

    def factor(x):
        c, _, Bm = cond(x, None)
        Ga = Bm[..., :10]
        # NaN where S is not positive definite (non-finite observations): the cost is NaN
        # there, which lbfgs reports NON_FINITE, instead of an exception for the batch.
        L, info = torch.linalg.cholesky_ex(Ga @ Sa @ Ga.transpose(-1, -2) + Sb)
        return torch.where((info == 0)[..., None, None], L, float("nan")), c

    frozen = None
    if weights_at is not None:
        # The condition's linearisation is returned multiplied by K = J_r(c), so the true
        # effective covariance is K^-1 S' K^-T and the frozen weight is K^T S'^-1 K.
        with torch.no_grad():
            L, c_ref = factor(V.detach(weights_at))
            frozen = (L, SGal3.jr(c_ref))

    def cost(x, _extra=None):
        if frozen is None:
            L, c = factor(x)  # K c = c: the factor K drops out of c^T S^-1 c
        else:
            L, K = frozen
            c, _, _ = cond(x, None)
            c = (K @ c[..., None])[..., 0]
        w = torch.linalg.solve_triangular(L, c[..., None], upper=False)[..., 0]
        return 0.5 * w.square().sum((-1, -2))

    return cost


def _put(x: tuple, idx: torch.Tensor, part: tuple) -> tuple:
    """x with the trials ``idx`` replaced by ``part`` (blockwise index_copy)."""
    out = []
    for full, p in zip(x, part):
        if isinstance(full, torch.Tensor):
            out.append(full.index_copy(0, idx, p))
        else:
            out.append(type(full).from_matrix(full.as_matrix().index_copy(0, idx, p.as_matrix())))
    return tuple(out)


def solve_sgal3_lbfgs(problem: TLSProblem, x0=None, dtau0=-1.0, batched: bool = False,
                      reweightings: int = 60, step_tol: float = 1e-4, **options) -> Solution:
    """The paper variant's estimate by a first-order method: ``torch.optim.LBFGS`` on the
    reduced condition cost 1/2 sum c^T S^-1 c with the weights S frozen, re-evaluated between
    LBFGS runs (at most ``reweightings`` times per trial, until its estimate moves by less
    than ``step_tol`` standard deviations), by autograd through the group operations.

    The tangent perturbation is preconditioned by the Cholesky factor of the Gauss-Newton
    covariance at the current weights (delta = L z; the identity where that covariance is
    not available, a SINGULAR or NON_FINITE trial, which then gets one LBFGS run).
    torch.optim.LBFGS has one line search and one stopping test, so by default the problems
    are solved one at a time (a Python loop over the batch; each trial's result is the one it
    gets alone); ``batched=True`` sums the trials still reweighting into one LBFGS problem
    instead, which couples them.  The covariance is the inverse Gauss-Newton information at
    the solution.  Report: status from the last LBFGS run, MAX_ITERATIONS for a converged
    trial still moving after ``reweightings`` rounds, and SINGULAR / NON_FINITE from the
    information at the solution (NON_FINITE wins); initial_cost is the cost at x0 (weights
    frozen at x0), cost and gradient_norm those of the last run, iterations the LBFGS
    iterations summed over the rounds, step_norm the last move in standard deviations (NaN
    where there is no covariance to measure it).  Not differentiable."""
    from .lbfgs import lbfgs
    batched = checks.boolean(batched, "batched")
    step_tol = checks.finite_number(step_tol, "step_tol", ">= 0")
    reweightings = checks.integer(reweightings, "reweightings", 1)
    x = problem.initial_guess(dtau0, "dtau0") if x0 is None else x0
    x = V.detach(_check_unknowns(problem, x, baseline=False))
    if problem.batch_size == 0:
        return _empty_solution(problem, x)
    cond = sgal3_condition(problem)
    options.setdefault("max_iterations", 200)

    def run(prob, x_start, scale):
        return lbfgs(condition_cost(prob, weights_at=x_start), x_start, scale=scale, **options)

    Bn = problem.batch_size
    like = problem.F_ga.as_matrix()
    nan = like.new_full((Bn,), float("nan"))
    iterations = torch.zeros(Bn, dtype=torch.int64, device=like.device)
    status = torch.full((Bn,), int(SolverStatus.MAX_ITERATIONS), dtype=torch.int64,
                        device=like.device)
    initial_cost, cost, gradient_norm, moved = nan.clone(), nan.clone(), nan.clone(), nan.clone()
    eye = torch.eye(11, dtype=like.dtype, device=like.device)
    active = torch.ones(Bn, dtype=torch.bool, device=like.device)
    for round_ in range(reweightings):
        idx = active.nonzero()[:, 0]
        if idx.numel() == 0:
            break
        sub = problem if idx.numel() == Bn else subset(problem, idx)
        xs = tuple(b[idx] for b in x)
        info = gauss_helmert(sgal3_condition(sub), xs, sub.covariance, variant="paper",
                             max_iterations=0)
        L, bad = torch.linalg.cholesky_ex(info.covariance)
        good = (bad == 0) & torch.isfinite(L).flatten(1).all(-1)
        scale = torch.where(good[:, None, None], L, eye)
        if batched:
            x_new, _, report = run(sub, xs, scale)
        else:
            parts = [run(subset(sub, slice(k, k + 1)), tuple(b[k:k + 1] for b in xs),
                         scale[k:k + 1]) for k in range(sub.batch_size)]
            x_new = tuple(type(parts[0][0][i]).stack([p[0][i] for p in parts]).reshape(-1)
                          if hasattr(parts[0][0][i], "as_matrix")
                          else torch.cat([p[0][i] for p in parts]) for i in range(len(x)))
            report = SolverReport(**{f: torch.cat([getattr(p[2], f) for p in parts])
                                     for f in ("status", "iterations", "initial_cost", "cost",
                                               "step_norm", "gradient_norm")})
        # The move in standard deviations of the covariance at the round's start: |L^-1 d|.
        d = torch.cat([x_new[0].rminus(xs[0]), x_new[1] - xs[1]], -1)
        w = torch.linalg.solve_triangular(scale, d[..., None], upper=False)[..., 0]
        step = torch.where(good, w.norm(dim=-1), float("nan"))
        x = _put(x, idx, x_new)
        iterations = iterations.index_add(0, idx, report.iterations)
        status = status.index_copy(0, idx, report.status)
        cost = cost.index_copy(0, idx, report.cost)
        gradient_norm = gradient_norm.index_copy(0, idx, report.gradient_norm)
        moved = moved.index_copy(0, idx, step)
        if round_ == 0:
            initial_cost = report.initial_cost  # every trial runs in the first round
        done = (step <= step_tol) | ~good | (report.status == SolverStatus.NON_FINITE)
        active = active.index_copy(0, idx, ~done)
    # Still moving after the last round: not settled.
    status = torch.where(active & (status == SolverStatus.CONVERGED),
                         SolverStatus.MAX_ITERATIONS, status)
    at = gauss_helmert(cond, x, problem.covariance, variant="paper", max_iterations=0)
    singular = at.report.status == SolverStatus.SINGULAR
    status = torch.where(singular & (status != SolverStatus.NON_FINITE), SolverStatus.SINGULAR,
                         status)
    status = torch.where(at.report.status == SolverStatus.NON_FINITE, SolverStatus.NON_FINITE,
                         status).to(torch.int64)
    non_finite = status == SolverStatus.NON_FINITE
    report = SolverReport(status=status, iterations=iterations,
                          initial_cost=torch.where(non_finite, float("nan"), initial_cost),
                          cost=torch.where(non_finite, float("nan"), cost),
                          step_norm=torch.where(non_finite, float("nan"), moved),
                          gradient_norm=torch.where(non_finite, float("nan"), gradient_norm))
    return Solution(x=x, covariance=at.covariance, report=report)
