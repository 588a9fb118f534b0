"""Errors-in-variables (Gauss-Helmert) conditions as factors of the engine.

A condition ``f(x, l) = 0`` ties unknowns x (graph variables) to observations l with
covariance Sigma.  The observations are corrected, l_hat = l + e (e in the parametrisation the
condition function reads, e.g. right perturbations of observed group elements), and the cost
is 1/2 sum e^T Sigma^-1 e subject to the conditions.  Linearising the condition at (x, l_hat)

    f(x exp(d), l + e') ~ c + A d + Bm (e' - e),   c = f(x, l_hat),  A = df/dx,  Bm = df/de,

and eliminating e' per condition (Lagrange multipliers; kelly-giamou (5.23)-(5.24)) leaves the
reduced, whitened residual and its Jacobian in x

    r = L^-1 w,   J = L^-1 A,   w = c - Bm e,   S = Bm Sigma Bm^T = L L^T,          (5.24)

with the updated corrections e' = -Sigma Bm^T S^-1 (w + A d).  ``GaussHelmert`` is a
``Factor`` whose residual is r (its cost 1/2 |r|^2 = 1/2 w^T S^-1 w is the linearised
errors-in-variables cost) and whose Jacobians are J, analytic (``jacobians``) or by
forward-mode differentiation of the condition (one ``jvp`` per tangent direction, batched over
every condition and problem under ``vmap``).

Two forms (``iterated``).  The paper-style form (kelly-giamou (5.18)) always linearises at the
raw observations, e = 0, with S at the current x; its Gauss-Newton fixed point is not the
minimum of the cost it evaluates, so it is solved undamped and converges on the step.  The
iterated form linearises at the corrected observations, which the factor carries as state
(``corrections`` (B, E, m), with S's Cholesky factor and Bm e at the linearisation point):
between updates the cost 1/2 |L^-1 (c(x, e) - Bm e)|^2 of x, with L and Bm e held, is an
ordinary least-squares cost whose Jacobian L^-1 A is exact, so Levenberg-Marquardt's tests
apply (the condition's Jacobians must then be its exact derivatives).  A trial point's cost
needs the condition alone (``condition``, not ``jacobians``).

``gauss_helmert(graph)`` runs the engine's Levenberg-Marquardt (or Gauss-Newton) rounds with
the update of that state: after each accepted step d (or, with ``update_below``, only after
those shorter than that many standard deviations) the corrections become those of the
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
from collections.abc import Callable, Sequence

import torch

from ...functional import checks
from ...groups import LieGroup
from ..dense_solve import gram_cholesky_solve, triangular_solve
from ..gauss_helmert import check_covariance
from ..solver import SolverStatus
from .factors import Data, Factor
from .graph import FactorGraph
from .levenberg_marquardt import (
    GraphResult,
    _accept,
    _check,
    _converged,
    _decide,
    _full,
    _solve,
    _State,
    _trial,
    _where,
)
from .linear_system import LinearSystem
from .linearize import Linearization, evaluate_cost, linearize
from .problem import Problem

__all__ = ["GaussHelmert", "gauss_helmert"]


class GaussHelmert(Factor):
    """E errors-in-variables conditions ``f(x, l) = 0`` with the observation corrections
    eliminated per condition (module docstring).

    condition      ``f(*variables, *data, e) -> c (..., k)``: the condition of ONE factor at
                   the corrected observations (correction ``e`` (..., m)), written on group
                   elements / tensors, broadcasting over leading batch axes (the engine passes
                   (B, E)).  The iterated form evaluates it alone for the cost of trial
                   points: with ``jacobians`` given, it must give the same c.
    variables      ``[(name, index), ...]`` as for ``Factor``.
    covariance     Sigma of the observations: (m, m) shared, (E, m, m) per condition or
                   (B, E, m, m) per problem and condition; symmetric positive definite
                   (a diagonal Sigma is detected and used elementwise).
    data           the observations and other data, as for ``Factor`` ((E, ...) or (B, E, ...)).
    dim            k, the size of the condition.
    jacobians      optional ``g(*variables, *data, e) -> (c, [A_1, ...], Bm)``, A_j (..., k, dof_j)
                   the derivative with respect to the right perturbation of variable j
                   (additive for Euclidean ones), Bm (..., k, m) with respect to e; the
                   paper-style form passes e = None (zero corrections).  The iterated form
                   needs the exact derivatives of c (it holds S and Bm e while x moves), or Q
                   times them with ``left_factor``; in
                   the paper-style form any invertible (k, k) factor per condition may
                   multiply the linearisation (every A_j and Bm, and c's linear part) without
                   changing the solution.  Default: forward mode (exact).
    left_factor    True: ``jacobians`` returns ``(c, [A_1, ...], Bm, Q)`` with Q (..., k, k)
                   invertible and every A_j and Bm Q times the exact derivative of c; the
                   engine reads the condition as Q c, with Q held at the linearisation point
                   while x moves (the iterated form), which leaves every step, correction and
                   solution unchanged.  For a condition c = log(E) on a Lie group, whose exact
                   derivatives all carry J_r(c)^-1, Q = J_r(c) saves that product (and
                   J_r(c) c = c).  Default False.
    iterated       True (default): re-linearise at the corrected observations, carried in
                   ``corrections``; False: the paper-style form, always at e = 0.
    corrections    the initial corrections (E, m) or (B, E, m); default zeros.  After
                   ``gauss_helmert`` it holds the estimated corrections (B, E, m) (or (E, m)
                   for an unbatched graph).
    """

    def __init__(self, condition: Callable, variables: Sequence[tuple[str, object]],
                 covariance: torch.Tensor, *, data: Sequence[Data] = (), dim: int,
                 jacobians: Callable | None = None, iterated: bool = True,
                 corrections: torch.Tensor | None = None, left_factor: bool = False):
        if not callable(condition):
            raise TypeError(f"condition must be callable, got {type(condition).__name__}")
        if jacobians is not None and not callable(jacobians):
            raise TypeError(f"jacobians must be callable or None, got {type(jacobians).__name__}")
        self.iterated = checks.boolean(iterated, "iterated")
        self.left_factor = checks.boolean(left_factor, "left_factor")
        if self.left_factor and jacobians is None:
            raise ValueError("left_factor=True needs jacobians (they return the factor Q)")
        self.condition = condition
        self.condition_jacobians = jacobians
        check_covariance(covariance, covariance.shape[-1] if isinstance(covariance, torch.Tensor)
                         and covariance.dim() >= 2 else 0, "covariance")
        if covariance.dim() > 4:
            raise ValueError(f"covariance must have shape (m, m), (E, m, m) or (B, E, m, m), got "
                             f"{tuple(covariance.shape)}")
        self.m = covariance.shape[-1]
        off = covariance - torch.diag_embed(covariance.diagonal(dim1=-2, dim2=-1))
        self.diagonal = not bool(off.any())
        factor = (covariance.diagonal(dim1=-2, dim2=-1).sqrt() if self.diagonal
                  else torch.linalg.cholesky(covariance))
        if covariance.dim() == 2:
            factor = factor[None]  # one for every condition: leading size 1
        self.user_data = tuple(data)
        super().__init__(self._residual, variables, data=(*self.user_data, factor),
                         dim=dim, jacobians=self._jacobians)
        self.covariance = covariance
        if corrections is not None:
            corrections = checks.floating(corrections, "corrections")
            if corrections.dim() not in (2, 3) or corrections.shape[-1] != self.m or \
                    corrections.shape[-2] != self.size:
                raise ValueError(f"corrections must have shape (E, m) or (B, E, m) = (..., "
                                 f"{self.size}, {self.m}), got {tuple(corrections.shape)}")
            corrections = corrections.detach().clone()
        self.corrections: torch.Tensor | None = corrections
        # (L, Bm e) of the iterated form at its linearisation point, and Q with left_factor
        self.linearisation: tuple[torch.Tensor, ...] | None = None
        # between the engine's calls: whether to re-linearise S and Bm e at the current point,
        # and what that gave
        self._refresh = True
        self._fresh: tuple[torch.Tensor, ...] | None = None
        # the corrections' update of the linearised problem at the linearisation point,
        # e'(d) = -Sigma Bm^T F [1, d] for a step d of the slots: (Bm (B, E, k, m),
        # F = S^-1 [w | A] (B, E, k, 1 + Dk))
        self._update: tuple[torch.Tensor, torch.Tensor] | None = None

    # ------------------------------------------------------------------ evaluation
    def _split(self, args):
        """(variables, user data, covariance factor, state) of an engine call; the state is
        (corrections, L, v) for the iterated form (and Q with ``left_factor``), None for the
        paper-style one."""
        nv, nd = len(self.slots), len(self.user_data)
        variables, rest = args[:nv], args[nv:]
        state = tuple(rest[nd + 1:nd + 4 + self.left_factor]) if self.iterated else None
        if state == ():
            raise RuntimeError("an iterated GaussHelmert factor carries state that "
                               "graph.gauss_helmert updates after each step: solve its graph "
                               "with graph.gauss_helmert (or give iterated=False)")
        return variables, rest[:nd], rest[nd], state

    def _linearise(self, args, want_jacobian: bool):
        variables, data, factor, state = self._split(args)
        if state is not None and not self._refresh and not want_jacobian:
            # the cost at a trial point, with the linearisation point's L and Bm e (and Q) held:
            # the condition alone
            e, L, v = state[:3]
            c = self.condition(*variables, *data, e)
            w = (c if not self.left_factor else (state[3] @ c[..., None])[..., 0]) - v
            return triangular_solve(L, w[..., None])[..., 0], None
        refresh = state is not None and self._refresh
        Q = None
        if state is None:  # paper-style: at the raw observations, S at the current x
            if self.condition_jacobians is not None:  # the condition may take a cheaper path
                c, As, Bm, Q = self._user_jacobians(variables, data, None)
            else:
                shape = torch.broadcast_shapes(*[_batch(v) for v in variables],
                                               *[_batch(d) for d in data])
                c, As, Bm = _forward_jacobians(self.condition, variables, data,
                                               factor.new_zeros(shape + (self.m,)))
            w, L = c, None
        else:
            e, L, v = state[:3]
            if self.condition_jacobians is not None:
                c, As, Bm, Q = self._user_jacobians(variables, data, e)
            else:
                c, As, Bm = _forward_jacobians(self.condition, variables, data, e)
            if Q is not None and not refresh:
                raise RuntimeError("a GaussHelmert factor with left_factor=True takes its "
                                   "Jacobians only at a new linearisation point (graph.gauss_helmert)")
            if refresh:  # a new linearisation point: S and Bm e from here on
                v = (Bm @ e[..., None])[..., 0]
                L = None
            w = c - v
        batch = torch.broadcast_shapes(c.shape[:-1], *([] if state is None else [state[0].shape[:-1]]))
        w, Bm = w.expand(batch + w.shape[-1:]), Bm.expand(batch + Bm.shape[-2:])
        cols = [w[..., None]]
        if want_jacobian or refresh:
            cols += [A.expand(batch + A.shape[-2:]) for A in As]
        rhs = torch.cat(cols, -1)
        if L is None:
            # S = Bm Sigma Bm^T = L L^T (Sigma = R R^T: G diag(R^2) G^T with G = Bm for a
            # diagonal Sigma, R its root, else G = Bm R); sol = L^-1 [w | A], full = S^-1 [w | A]
            # at a refresh; a non-positive-definite S (non-finite data) gives NaN, reported
            # NON_FINITE
            if self.diagonal:
                G, d = Bm, factor * factor
            else:
                G, d = Bm @ factor, factor.new_ones(()).expand(self.m)
            L, sol, full, _ = gram_cholesky_solve(G, d, rhs, back=refresh)
        else:
            sol, full = triangular_solve(L, rhs), None
        r = sol[..., 0]
        if refresh:
            # the corrections of the linearised problem for a step d of the slots (S of (5.23)):
            # e'(d) = -Sigma Bm^T S^-1 (w + A d) = -Sigma Bm^T F [1, d] with F = S^-1 [w | A]
            assert full is not None  # back substitution at a refresh
            held: tuple[torch.Tensor, ...] = (L, v.expand(batch + v.shape[-1:]))
            if self.left_factor:
                assert Q is not None  # _user_jacobians
                held += (Q.expand(batch + Q.shape[-2:]),)
            self._fresh = (*held, Bm, full)
        if not want_jacobian:
            return r, None
        return r, sol[..., 1:]  # the slots' Jacobians side by side

    def _user_jacobians(self, variables, data, e):
        """(Q c, [A_j], Bm, Q) from ``jacobians`` (Q None without ``left_factor``)."""
        out = self.condition_jacobians(*variables, *data, e)
        if not isinstance(out, (tuple, list)) or len(out) != 3 + self.left_factor:
            got = len(out) if isinstance(out, (tuple, list)) else type(out).__name__
            raise ValueError(f"jacobians must return {3 + self.left_factor} items "
                             f"({'(c, [A_j], Bm, Q)' if self.left_factor else '(c, [A_j], Bm)'}, "
                             f"left_factor={self.left_factor}), got {got}")
        if not self.left_factor:
            return (*out, None)
        c, As, Bm, Q = out
        k = c.shape[-1]
        if not isinstance(Q, torch.Tensor) or Q.shape[-2:] != (k, k):
            raise ValueError(f"jacobians must return Q of shape (..., {k}, {k}) (left_factor=True), "
                             f"got {tuple(getattr(Q, 'shape', ()))}")
        return (Q @ c[..., None])[..., 0], As, Bm, Q

    def _residual(self, *args):
        return self._linearise(args, False)[0]

    def _jacobians(self, *args):
        return self._linearise(args, True)


def _batch(v) -> torch.Size:
    if isinstance(v, LieGroup):
        return v.batch_shape
    return v.shape[:-1] if isinstance(v, torch.Tensor) and v.dim() else torch.Size()


def _forward_jacobians(condition: Callable, variables, data, e):
    """(c, [A_j], Bm) by forward mode: the derivatives along every tangent direction of the
    variables (right perturbations) and of e, one ``jvp`` each, batched under ``vmap``."""
    sizes = [v.dof if isinstance(v, LieGroup) else v.shape[-1] for v in variables] + [e.shape[-1]]
    batch = torch.broadcast_shapes(e.shape[:-1], *[_batch(v) for v in variables])
    zeros = tuple(e.new_zeros(batch + (s,)) for s in sizes)
    total = sum(sizes)
    eye = torch.eye(total, dtype=e.dtype, device=e.device)
    tangents, start = [], 0
    for s in sizes:  # (total, *batch, s): column j of the basis, restricted to this argument
        tangents.append(eye[:, start:start + s].reshape((total,) + (1,) * len(batch) + (s,))
                        .expand((total,) + batch + (s,)))
        start += s

    def fn(*ds):
        moved = [v.compose(type(v).exp(d)) if isinstance(v, LieGroup) else v + d
                 for v, d in zip(variables, ds[:-1])]
        return condition(*moved, *data, e + ds[-1])

    def column(*ts):
        return torch.func.jvp(fn, zeros, ts)

    out_dims: tuple = (None, 0)  # the condition once, its derivatives along the basis
    c, dc = torch.func.vmap(column, out_dims=out_dims)(*tangents)
    dc = dc.movedim(0, -1)  # (..., k, total)
    parts, start = [], 0
    for s in sizes:
        parts.append(dc[..., start:start + s])
        start += s
    return c, parts[:-1], parts[-1]


# ---------------------------------------------------------------------------------- solver
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
    _prepare_states(graph)
    o = dict(damped=damped, lambda_initial=lambda_initial if damped else 0.0,
             lambda_factor=lambda_factor, lambda_upper=lambda_upper, lambda_lower=lambda_lower,
             min_fidelity=min_model_fidelity, diagonal=diagonal_damping,
             rel_tol=relative_error_tol, abs_tol=absolute_error_tol, error_tol=error_tol,
             step_tol=step_tol, cost_tests=cost_tests,
             update_below=math.inf if update_below is None else update_below,
             corrections_tol=corrections_tol, linear_solver=linear_solver, round=_gauss_helmert_round)
    return _solve(graph, max_iterations, "none", o)


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
        e = leaf.new_zeros(shape) if e is None else e.to(leaf).expand(shape).clone()
        f.corrections = e
        f.linearisation = (leaf.new_zeros(lead + (f.size, k, k)), leaf.new_zeros(lead + (f.size, k)))
        if f.left_factor:
            f.linearisation += (leaf.new_zeros(lead + (f.size, k, k)),)
        f.data = (*f.user_data, f.data[len(f.user_data)], e, *f.linearisation)
        Dk = sum(graph.dof(name) for name, _ in f.slots)
        f._refresh, f._fresh = True, None
        f._update = (leaf.new_zeros(lead + (f.size, k, f.m)), leaf.new_zeros(lead + (f.size, k, 1 + Dk)))


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
    success, gave_up, done, lam = _decide(s, o, solved, lin_change, new_cost, eps,
                                          max(o["rel_tol"], rounding))
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
    converged = (_converged(s, lin, o) if o["cost_tests"] else torch.zeros_like(short)) | short
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
    status = s.status
    status = torch.where(done & gave_up, _full(status, SolverStatus.DIVERGED), status)
    status = torch.where(done & ~gave_up & converged, _full(status, SolverStatus.CONVERGED), status)
    status = torch.where(done & ~gave_up & ~converged & (iterations >= max_iterations),
                         _full(status, SolverStatus.MAX_ITERATIONS), status)
    cost_start = torch.where(done, lin.cost, s.cost_start)
    if blocks:  # the refreshed linearisation into the state now: the working set may shrink
        _take_fresh(blocks, s.rows)
    return _State(s.rows, x, lin, cost_start, lam, iterations, quad.clamp_min(0).sqrt(), status)
