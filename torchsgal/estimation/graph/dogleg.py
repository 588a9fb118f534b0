"""Powell's dogleg on a ``FactorGraph``, for a batch of problems: GTSAM's ``DoglegOptimizer``.

Each iteration follows ``DoglegOptimizer::iterate`` and ``DoglegOptimizerImpl::Iterate`` (mode
``ONE_STEP_PER_ITERATION``), per problem, with its own trust-region radius ``Delta``
(``DoglegParams.deltaInitial`` = 1):

1. at the linearisation (H, g): the Gauss-Newton point ``dx_n = -H^-1 g`` and the
   steepest-descent (Cauchy) point ``dx_u = -(g^T g / g^T H g) g`` (``optimizeGradientSearch``);
2. the dogleg point (``ComputeDoglegPoint``): ``Delta / |dx_u| dx_u`` if ``Delta < |dx_u|``;
   else ``(1 - tau) dx_u + tau dx_n`` on the boundary ``|.| = Delta`` if ``Delta < |dx_n|``
   (``ComputeBlend``: the root tau of the quadratic in [0, 1]); else ``dx_n``;
3. rho = (f(x) - f(x exp(dx))) / (M(0) - M(dx)), the actual over the model's decrease
   ``M(0) - M(dx) = -(g^T dx + 1/2 dx^T H dx)``, and 0.5 where either is below 1e-15;
4. rho >= 0.75: the step is taken, Delta = max(Delta, 3 |dx|); 0.25 <= rho < 0.75: taken,
   Delta kept; 0 <= rho < 0.25: taken, Delta halved (while Delta > 1e-5); rho < 0 (the cost
   increased, or is not finite): Delta halved and the same linearisation tried again, or, at
   Delta <= 1e-5, the iteration ends without a step;
5. after each iteration (``iterations`` counts them, as GTSAM's ``optimizer.iterations()``):
   converged if cost <= ``error_tol`` or the decrease is <= ``absolute_error_tol`` or <=
   ``relative_error_tol`` times the cost before it; MAX_ITERATIONS after ``max_iterations``.

Where H has no Cholesky factor (a gauge freedom), the Gauss-Newton point is solved with the
damping ``RCOND * max diag(H)`` (the minimum-norm step up to that damping: g has no part in
H's null space; in a batch from the next round on, the first round taking the Cauchy point);
the problem then reports ``CONVERGED_RANK_DEFICIENT`` at convergence.  The
rounds, the active set, the dense/sparse solves and ``backward_mode`` are those of
``levenberg_marquardt`` (one trial per running problem per round, no host read in the dense
round).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from ...functional import checks
from .graph import FactorGraph
from .layout import diagonal, times
from .levenberg_marquardt import GraphResult, _accept, _check, _solve, _State, _trial, _where
from .linear_system import LinearSystem
from .linearize import Linearization
from .problem import Problem
from .round_update import converged as cost_converged
from .round_update import round_status

__all__ = ["dogleg"]

MIN_DELTA = 1e-5  # Delta is not halved below this (DoglegOptimizerImpl::Iterate)
TINY_CHANGE = 1e-15  # a cost or model change below this gives rho = 0.5 (idem)


def dogleg(graph: FactorGraph, max_iterations: int = 100, *, delta_initial: float = 1.0,
           relative_error_tol: float = 1e-5, absolute_error_tol: float = 1e-5,
           error_tol: float = 0.0, linear_solver: str = "auto",
           backward_mode: str = "none") -> GraphResult:
    """Powell's dogleg with GTSAM's trust-region rules and defaults (module docstring), for
    every problem of the graph's batch.  Returns a ``GraphResult``.

    delta_initial  the initial trust-region radius (``DoglegParams.deltaInitial``), > 0, in
                   the units of the stacked tangent vector.
    Convergence tolerances, ``linear_solver`` and ``backward_mode`` as for
    ``levenberg_marquardt``."""
    checks.finite_number(delta_initial, "delta_initial", "> 0")
    _check(max_iterations, 1.0, 10.0, 1.0, 0.0, 0.0, relative_error_tol, absolute_error_tol,
           error_tol, False, linear_solver, backward_mode)
    return _solve(graph, max_iterations, backward_mode, dict(
        round=_dogleg_round, lambda_initial=float(delta_initial), rel_tol=relative_error_tol,
        abs_tol=absolute_error_tol, error_tol=error_tol, linear_solver=linear_solver))


@dataclass
class _DoglegState(_State):
    """The solver state and, per problem, whether its H had no Cholesky factor (then damped)."""

    damped: torch.Tensor

    def take(self, keep: torch.Tensor) -> _DoglegState:
        b = super().take(keep)
        return _DoglegState(b.rows, b.x, b.lin, b.cost_start, b.lam, b.iterations, b.step_norm,
                            b.status, self.damped.index_select(0, keep))


def _steps(system: LinearSystem, lin: Linearization, damped: torch.Tensor
           ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(dx_u, dx_n, damped): the Cauchy and Gauss-Newton points (module docstring, step 1).
    Where H has no Cholesky factor (a gauge freedom) the Gauss-Newton point is that of
    H + RCOND max diag(H) I: at once for one problem on the host; in a batch, from the next
    round on (``damped``), this round taking the Cauchy point."""
    g, values = lin.g, lin.values
    damping = system.rcond * diagonal(system.layout, values).amax(dim=-1).clamp_min(0)
    dx_n, solved, _ = system.solve(values, g, torch.where(damped, damping, torch.zeros_like(damping)),
                                   False)
    if system.cost_first and not bool(solved[0]):
        dx_n, solved, _ = system.solve(values, g, damping, False)
    damped = damped | ~solved
    gg = (g * g).sum(-1)
    gHg = (g * times(system.layout, values, g)).sum(-1)
    curved = gHg > 0
    alpha = gg / torch.where(curved, gHg, torch.ones_like(gHg))
    dx_u = -torch.where(curved, alpha, torch.zeros_like(alpha))[:, None] * g
    return dx_u, _where(solved, dx_n, dx_u), damped


def _dogleg_point(delta: torch.Tensor, dx_u: torch.Tensor, dx_n: torch.Tensor) -> torch.Tensor:
    """ComputeDoglegPoint / ComputeBlend (module docstring, step 2) for each problem."""
    uu, nn, un = (dx_u * dx_u).sum(-1), (dx_n * dx_n).sum(-1), (dx_u * dx_n).sum(-1)
    d2 = delta * delta
    one = torch.ones_like(uu)
    steepest = d2 < uu
    blend = ~steepest & (d2 < nn)
    scaled = (d2 / torch.where(steepest, uu, one)).sqrt()
    a = uu - 2 * un + nn
    b = 2 * (un - uu)
    c = uu - d2
    a = torch.where(blend & (a > 0), a, one)
    root = (b * b - 4 * a * c).clamp_min(0).sqrt()
    tau1, tau2 = (-b + root) / (2 * a), (-b - root) / (2 * a)
    tau = torch.where((tau1 >= 0) & (tau1 <= 1), tau1, tau2)
    tau = torch.where(blend, tau, torch.zeros_like(tau))
    blended = (1 - tau)[:, None] * dx_u + tau[:, None] * dx_n
    return _where(steepest, scaled[:, None] * dx_u, _where(blend, blended, dx_n))


def _dogleg_round(problem: Problem, system: LinearSystem, s: _State, o: dict,
                  max_iterations: int, eps: float) -> _State:
    """One trial per running problem (module docstring, steps 1-5); ``s.lam`` holds Delta."""
    delta = s.lam
    damped = s.damped if isinstance(s, _DoglegState) else torch.zeros_like(s.status, dtype=torch.bool)
    dx_u, dx_n, damped = _steps(system, s.lin, damped)
    dx = _dogleg_point(delta, dx_u, dx_n)
    quad = (dx * times(system.layout, s.lin.values, dx)).sum(-1)
    model_change = -((s.lin.g * dx).sum(-1) + 0.5 * quad)
    x_new, lin_new, new_cost = _trial(problem, system, s, dx)
    cost = s.lin.cost
    cost_change = cost - new_cost
    tiny = (cost_change.abs() < TINY_CHANGE) | (model_change.abs() < TINY_CHANGE)
    rho = torch.where(tiny, torch.full_like(cost, 0.5),
                      cost_change / torch.where(tiny, torch.ones_like(cost), model_change))
    rho = torch.where(torch.isfinite(new_cost), rho, torch.full_like(rho, -1.0))
    grow = rho >= 0.75
    keep = (rho >= 0.25) & (rho < 0.75)
    shrink = (rho >= 0) & (rho < 0.25)
    success = grow | keep | shrink
    above = delta > MIN_DELTA
    delta_new = torch.where(grow, torch.maximum(delta, 3 * dx.norm(dim=-1)),
                            torch.where((shrink | ~success) & above, 0.5 * delta, delta))
    done = success | ~above  # otherwise: the same linearisation again with Delta / 2
    x, lin = _accept(problem, system, s, success, x_new, lin_new, new_cost)
    iterations = s.iterations + done.to(torch.int64)
    converged = cost_converged(s.cost_start, lin.cost, o)
    status = round_status(s.status, done, None, converged, iterations, max_iterations)
    cost_start = torch.where(done, lin.cost, s.cost_start)
    return _DoglegState(s.rows, x, lin, cost_start, delta_new, iterations,
                        quad.clamp_min(0).sqrt(), status, damped)
