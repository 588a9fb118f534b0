"""The Gauss-Helmert solve: the engine's rounds with the iterated conditions' state updated.

``gauss_helmert(graph)`` runs the engine's Levenberg-Marquardt (or Gauss-Newton) rounds with
the update of the iterated conditions' state (``GaussHelmert``: the corrections, and S's
Cholesky factor and Bm e at the linearisation point): after each accepted step d (or, with
``update_below``, only after those shorter than that many standard deviations) the
corrections become those of the
linearised problem, e' = -Sigma Bm^T S^-1 (w + A d) (the classical Gauss-Helmert update,
S as in (5.23); its fixed point is the constrained optimum), and the linearisation point moves
to the new x and e'.  Each linearisation keeps what this update needs per condition, Bm and
F = S^-1 [w | A] (e'(d) = -Sigma Bm^T F [1, d]), so a round evaluates the conditions'
Jacobians once.  A step whose predicted decrease is within the cost's rounding is taken
unjudged (near the fixed point the cost cannot tell it apart; the step test can).  A problem
converges when the engine's tests hold for the step (or the round ended without one) and its
last update moved no correction by more than ``corrections_tol`` standard deviations.
For a graph without iterated conditions it is ``levenberg_marquardt`` (``gauss_newton`` with
``damped=False``), with a step test added.
"""
from __future__ import annotations

import math

import torch

from ...functional import checks
from ...groups import LieGroup
from .gauss_helmert import GaussHelmert
from .graph import FactorGraph
from .levenberg_marquardt import (
    GraphResult,
    _accept,
    _check,
    _solve,
    _State,
    _trial,
    _where,
)
from .linear_system import LinearSystem
from .linearize import Linearization, evaluate_cost, linearize
from .problem import Problem
from .round_update import converged as cost_converged
from .round_update import round_status, verdict

__all__ = ["gauss_helmert"]


def gauss_helmert(graph: FactorGraph, max_iterations: int = 100, *, damped: bool = True,
                  lambda_initial: float = 1e-5, lambda_factor: float = 10.0,
                  lambda_upper: float = 1e5, lambda_lower: float = 0.0,
                  min_model_fidelity: float = 1e-3, diagonal_damping: bool = False,
                  relative_error_tol: float = 1e-5, absolute_error_tol: float = 1e-5,
                  error_tol: float = 0.0, step_tol: float = 0.0, cost_tests: bool = True,
                  update_below: float | None = None, corrections_tol: float = 1e-6,
                  linear_solver: str = "auto") -> GraphResult:
    """Solves a graph with ``GaussHelmert`` conditions (and any other factors) for every
    problem of its batch: Levenberg-Marquardt (``damped=True``, GTSAM's rules as
    ``levenberg_marquardt``) or Gauss-Newton (``damped=False``) rounds, the iterated
    conditions' corrections updated after each accepted step (module docstring).  The paper-
    style form is a Gauss-Newton fixed point that does not minimise the cost it evaluates (the
    weights S move with x), so solve it with ``damped=False``.

    Each problem converges when the step's cost decrease is within ``relative_error_tol``
    (relative) or ``absolute_error_tol``, or an accepted step is shorter than ``step_tol``
    standard deviations (sqrt(delta^T H delta); 0: this test off), or the round ended without
    a step (a cost change within ``relative_error_tol``), and the corrections' update after it
    moved none of them by more than ``corrections_tol``.  ``cost_tests=False`` leaves the
    step test alone (the paper-style form: its cost is not minimised, and rises and falls as
    its fixed point is approached).  The corrections are updated after every accepted step
    (the classical Gauss-Helmert iteration), or, with ``update_below`` a number, after
    accepted steps shorter than that many standard deviations only: a problem then starts as
    the paper-style form and turns iterated as it approaches its solution (a guard for
    conditions far from linear over the corrections a large misclosure gives).  An iterated
    problem converges only once its last update moved no correction by more than
    ``corrections_tol`` standard deviations of its observation (Sigma^(1/2)).  The iterated
    factors' ``corrections`` hold the estimate afterwards.  The solution carries no gradient."""
    _check(max_iterations, lambda_initial, lambda_factor, lambda_upper, lambda_lower,
           min_model_fidelity, relative_error_tol, absolute_error_tol, error_tol,
           diagonal_damping, linear_solver, "none")
    checks.boolean(damped, "damped")
    checks.finite_number(step_tol, "step_tol", ">= 0")
    checks.boolean(cost_tests, "cost_tests")
    if update_below is not None:
        checks.finite_number(update_below, "update_below", "> 0")
    checks.finite_number(corrections_tol, "corrections_tol", ">= 0")
    if not isinstance(graph, FactorGraph):
        raise TypeError(f"graph must be a FactorGraph, got {type(graph).__name__}")
    o = dict(damped=damped, lambda_initial=lambda_initial if damped else 0.0,
             lambda_factor=lambda_factor, lambda_upper=lambda_upper, lambda_lower=lambda_lower,
             min_fidelity=min_model_fidelity, diagonal=diagonal_damping,
             rel_tol=relative_error_tol, abs_tol=absolute_error_tol, error_tol=error_tol,
             step_tol=step_tol, cost_tests=cost_tests,
             update_below=math.inf if update_below is None else update_below,
             corrections_tol=corrections_tol, linear_solver=linear_solver, round=_gauss_helmert_round)
    try:
        _prepare_states(graph)
        solution = _solve(graph, max_iterations, "none", o)
    finally:
        _release_states(graph)
    for f in graph.factors:  # the caller's factors behind the graph's copies
        if isinstance(f, GaussHelmert) and f.iterated and f.source is not None:
            f.source.corrections = f.corrections
    return solution


def _prepare_states(graph: FactorGraph) -> None:
    """The iterated conditions' state as data, owned by the factor: the corrections e
    (B, E, m), the Cholesky factor L (B, E, k, k) of S and Bm e (B, E, k) at the linearisation
    point ((E, ...) for an unbatched graph).  The engine's first linearisation computes L and
    Bm e (``_refresh``); the rounds then update the state (in place where only part of the
    batch is still running, by replacing the tensors where all of it is)."""
    first = next(iter(graph.variables.values()), None)
    if first is None:
        return
    leaf = first.as_matrix() if isinstance(first, LieGroup) else first
    B = graph.batch_size
    lead = ((B,) if B is not None else ())
    for f in graph.factors:
        if not isinstance(f, GaussHelmert) or not f.iterated:
            continue
        k = f.dim
        assert k is not None  # required by GaussHelmert
        shape = lead + (f.size, f.m)
        e = f.corrections
        if e is not None and e.dim() == 3 and (B is None or e.shape[0] != B):
            raise ValueError(f"{f!r}: corrections of shape {tuple(e.shape)} for a graph of "
                             f"{'no batch' if B is None else f'{B} problems'}: give (E, m) = "
                             f"({f.size}, {f.m}){'' if B is None else f' or (B, E, m) = ({B}, {f.size}, {f.m})'}")
        e = leaf.new_zeros(shape) if e is None else e.to(leaf).expand(shape).clone()
        f.corrections = e
        f.linearisation = (leaf.new_zeros(lead + (f.size, k, k)), leaf.new_zeros(lead + (f.size, k)))
        if f.left_factor:
            f.linearisation += (leaf.new_zeros(lead + (f.size, k, k)),)
        f.data = (*f.user_data, f.data[len(f.user_data)], e, *f.linearisation)
        Dk = sum(graph.dof(name) for name, _ in f.slots)
        f._refresh, f._fresh = True, None
        f._update = (leaf.new_zeros(lead + (f.size, k, f.m)), leaf.new_zeros(lead + (f.size, k, 1 + Dk)))


def _release_states(graph: FactorGraph) -> None:
    """The iterated conditions' data without the solve's state (the corrections stay): the
    other solvers refuse such a factor, as they do before the solve (were the state left, they
    would evaluate it with a stale linearisation: NaN), and the next ``gauss_helmert`` prepares
    it anew from the corrections."""
    for f in graph.factors:
        if isinstance(f, GaussHelmert) and f.iterated:
            f.data = f.data[:len(f.user_data) + 1]  # the user's data and the covariance factor


def _iterated_blocks(problem: Problem) -> list:
    return [b for b in problem.blocks if isinstance(b.factor, GaussHelmert) and b.factor.iterated]


def _store(state: torch.Tensor, rows: torch.Tensor, new: torch.Tensor) -> None:
    """Writes the working set's rows ``rows`` of a state tensor in place (``new`` holds every
    problem where the whole batch runs, and for an unbatched graph)."""
    if new.shape == state.shape:
        state.copy_(new)
    else:
        state.index_copy_(0, rows, new)


def _kept(state: torch.Tensor, rows: torch.Tensor, new: torch.Tensor) -> torch.Tensor:
    """``state`` with the working set's rows from ``new``: ``new`` itself where it holds
    every problem (no copy), else ``state`` written in place."""
    if state.dim() != new.dim():
        return new.reshape(state.shape)
    if new.shape == state.shape:
        return new.contiguous()
    return state.index_copy_(0, rows, new)


def _take_fresh(blocks: list, rows: torch.Tensor) -> None:
    """The linearisation (L, Bm e, the corrections' update) that the last refreshing
    evaluation computed, into the factors' state; later evaluations use it until the next
    refresh."""
    for b in blocks:
        f = b.factor
        if f._fresh is not None:
            assert f._update is not None  # _prepare_states
            kept = [_kept(state, rows, new) for state, new in
                    zip((*f.linearisation, *f._update), f._fresh)]
            held = len(f.linearisation)
            f.linearisation, f._update = tuple(kept[:held]), (kept[held], kept[held + 1])
        f._refresh, f._fresh = False, None


def _working_state(blocks: list, rows: torch.Tensor) -> None:
    """The working set's state (corrections, L, Bm e, Q) as the blocks' data, from the factors."""
    for b in blocks:
        f = b.factor
        start = len(f.user_data) + 1  # after the user's data and the covariance factor
        for j, state in enumerate((f.corrections, *f.linearisation)):
            matrix = j in (1, 3)  # L and Q; the corrections and Bm e are vectors
            everyone = state.dim() == 2 + matrix or rows.numel() == state.shape[0]
            b.data[start + j] = state if everyone else state.index_select(0, rows)


def _candidate(block, rows: torch.Tensor, delta: torch.Tensor, batched: bool
               ) -> tuple[torch.Tensor, torch.Tensor]:
    """(the corrections' update at the linearisation point, and after the step ``delta``
    (B, D)) for the working set's rows: e'(d) = -Sigma Bm^T F [1, d], d the step of the block's
    slots (``Block.g_index``: each condition's, or every condition's one for a reduced block),
    as two matrix-vector products per condition."""
    f = block.factor
    assert f._update is not None  # set by the first linearisation
    Bm, F = f._update
    if batched and F.shape[0] != rows.numel():
        Bm, F = Bm.index_select(0, rows), F.index_select(0, rows)
    d = delta[:, block.g_index].unflatten(1, (-1, F.shape[-1] - 1))  # (B, E or 1, Dk)
    if not batched:
        d = d[0]
    R = block.data[len(f.user_data)]  # the covariance's square-root diagonal or Cholesky factor

    # Sigma Bm^T y for y = F [1, 0] and F [0, d] side by side (Sigma = R R^T); Bm^T y as
    # (y^T Bm)^T, the (2 x k) by (k x m) form of the batched product (half the time of the other)
    y = torch.stack([F[..., 0], (F[..., 1:] @ d[..., None])[..., 0]], -1)
    z = (y.mT @ Bm).mT
    z = z * (R * R)[..., None] if f.diagonal else R @ (R.mT @ z)
    point = -z[..., 0]
    return point, point - z[..., 1]


def _gauss_helmert_round(problem: Problem, system: LinearSystem, s: _State, o: dict,
                         max_iterations: int, eps: float) -> _State:
    """One Levenberg-Marquardt trial (``levenberg_marquardt._round``) with the iterated
    conditions' linearisation point fixed (their corrections e, S and Bm e: a least-squares
    cost of x whose Jacobian is exact), then, where the step was accepted, the corrections'
    update and a new linearisation point there."""
    blocks = _iterated_blocks(problem)
    _take_fresh(blocks, s.rows)  # the engine's first linearisation, or the last round's
    _working_state(blocks, s.rows)
    lam = s.lam if o["damped"] else torch.zeros_like(s.lam)
    delta, solved, quad = system.solve(s.lin.values, s.lin.g, lam, o.get("diagonal", False))
    lin_change = -((s.lin.g * delta).sum(-1) + 0.5 * quad)
    if blocks:
        # the round ends by linearising every problem again (at its new corrections), so the
        # trial point needs its cost only (the condition, with L and Bm e held)
        x_new = problem.retract(s.x, delta)
        new_cost = evaluate_cost(problem, x_new)
    else:
        x_new, lin_new, new_cost = _trial(problem, system, s, delta)
    # a cost change within the rounding of the cost (1e3 eps relative) cannot be judged: the
    # iteration ends without a step, as GTSAM's below ``relative_error_tol``
    rounding = 1e3 * eps
    success, gave_up, done, lam = verdict(s.lin.cost, s.lin.model_cost, s.lam, o, solved, lin_change,
                                          new_cost, eps, max(o["rel_tol"], rounding))
    in_place = done & ~success & ~gave_up
    if blocks:  # only the cost of ``lin`` is read before it is replaced below
        # a step whose predicted decrease is itself within the cost's rounding is taken
        # unjudged (Gauss-Newton at the fixed point: the cost cannot tell it apart, the step
        # and corrections tests can)
        unjudged = in_place & (lin_change <= rounding * s.lin.cost)
        success, in_place = success | unjudged, in_place & ~unjudged
        x = [_where(success, a, b) for a, b in zip(x_new, s.x)]
        lin = Linearization(s.lin.values, s.lin.g, _where(success, new_cost, s.lin.cost), s.lin.model_cost)
    else:
        x, lin = _accept(problem, system, s, success, x_new, lin_new, new_cost)
    short = success & (quad.clamp_min(0).sqrt() <= o["step_tol"])
    converged = (cost_converged(s.cost_start, lin.cost, o) if o["cost_tests"]
                 else torch.zeros_like(short)) | short
    # the corrections' update after accepted steps (shorter than ``update_below`` standard
    # deviations where that is set); a round that ends without a step updates them at the
    # current point
    update = success & (quad.clamp_min(0).sqrt() <= o["update_below"])
    moved = torch.zeros_like(lam)  # the largest change of a correction, in standard deviations
    if blocks:
        for b in blocks:
            start = len(b.factor.user_data)  # the covariance factor, then the corrections
            old = b.data[start + 1]
            point, cand = _candidate(b, s.rows, delta, old.dim() == 3)
            if old.dim() == 3:
                new = _where(update, cand, _where(in_place, point, old))
            else:
                new = torch.where(update[0], cand, torch.where(in_place[0], point, old))
            R = b.data[start]  # the covariance's square-root diagonal or Cholesky factor
            change = new - old  # before the store: ``old`` may be the state itself
            change = change / R if b.factor.diagonal else torch.linalg.solve_triangular(
                R, change[..., None], upper=False)[..., 0]
            moved = torch.maximum(moved, change.abs().flatten(1).amax(-1) if change.dim() == 3
                                  else change.abs().amax().expand_as(moved))
            _store(b.factor.corrections, s.rows, new)
            b.data[start + 1] = new
            b.factor._refresh = True
        updated = linearize(problem, x, system.layout)  # at the new corrections: L, Bm e refreshed
        # converged where the corrections hardly moved and either the step just taken passed
        # ``levenberg_marquardt``'s tests or the round ended without a step (its cost change
        # was within the cost tolerance: with the corrections unchanged, the next round would
        # repeat it; GTSAM's iteration without a step converges alike)
        converged = ((update & converged) | in_place) & (moved <= o["corrections_tol"])
        lin = updated
    iterations = s.iterations + (success | in_place).to(torch.int64) if blocks else \
        s.iterations + success.to(torch.int64)
    status = round_status(s.status, done, gave_up, converged, iterations, max_iterations)
    cost_start = torch.where(done, lin.cost, s.cost_start)
    if blocks:  # the refreshed linearisation into the state now: the working set may shrink
        _take_fresh(blocks, s.rows)
    return _State(s.rows, x, lin, cost_start, lam, iterations, quad.clamp_min(0).sqrt(), status)
