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

``gauss_helmert_solver.gauss_helmert(graph)`` solves a graph of such factors, updating the
iterated conditions' state between rounds.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence

import torch

from ...functional import checks
from ...groups import LieGroup
from ...uncertainty.covariance import covariance_factor
from ..dense_solve import gram_cholesky_solve, triangular_solve
from .factors import Data, Factor

__all__ = ["GaussHelmert"]


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
                   for an unbatched graph), also where the graph holds a copy of the factor
                   (``graph.add(factor, loss=...)``).
    """

    def __init__(self, condition: Callable, variables: Sequence[tuple[str, object]],
                 covariance: torch.Tensor, *, data: Sequence[Data] = (), dim: int,
                 jacobians: Callable | None = None, iterated: bool = True,
                 corrections: torch.Tensor | None = None, left_factor: bool = False):
        if not callable(condition):
            raise TypeError(f"condition must be callable, got {type(condition).__name__}")
        if jacobians is not None and not callable(jacobians):
            raise TypeError(f"jacobians must be callable or None, got {type(jacobians).__name__}")
        dim = checks.integer(dim, "dim", 1)  # required: the condition's size
        self.iterated = checks.boolean(iterated, "iterated")
        self.left_factor = checks.boolean(left_factor, "left_factor")
        if self.left_factor and jacobians is None:
            raise ValueError("left_factor=True needs jacobians (they return the factor Q)")
        self.condition = condition
        self.condition_jacobians = jacobians
        if not isinstance(covariance, torch.Tensor) or not 2 <= covariance.dim() <= 4:
            got = tuple(covariance.shape) if isinstance(covariance, torch.Tensor) else type(covariance).__name__
            raise ValueError(f"covariance must have shape (m, m), (E, m, m) or (B, E, m, m), got {got}")
        self.diagonal, factor = covariance_factor(covariance, "covariance")
        self.m = covariance.shape[-1]
        if covariance.dim() == 2:
            factor = factor[None]  # one for every condition: leading size 1
        self.user_data = tuple(data)
        super().__init__(self._residual, variables, data=(*self.user_data, factor),
                         dim=dim, jacobians=self._jacobians)
        if covariance.dim() >= 3 and covariance.shape[-3] != self.size:
            raise ValueError(f"covariance must have shape (m, m), (E, m, m) or (B, E, m, m) with "
                             f"E = {self.size} conditions, got {tuple(covariance.shape)}")
        self.covariance = covariance
        if corrections is not None:
            corrections = checks.floating(corrections, "corrections")
            if corrections.dim() not in (2, 3) or corrections.shape[-1] != self.m or \
                    corrections.shape[-2] != self.size:
                raise ValueError(f"corrections must have shape (E, m) or (B, E, m) = (..., "
                                 f"{self.size}, {self.m}), got {tuple(corrections.shape)}")
            checks.same_device_dtype(covariance=covariance, corrections=corrections)
            corrections = corrections.detach().clone()
        self.corrections: torch.Tensor | None = corrections
        # the caller's factor where the graph holds a copy (graph.add with a loss): the solver's
        # corrections are also given to it
        self.source: GaussHelmert | None = None
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
                               "torchsgal.estimation.graph.gauss_helmert updates after each step: solve "
                               "its graph with torchsgal.estimation.graph.gauss_helmert(graph) (or give "
                               "iterated=False)")
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
                shape = checks.broadcast_shapes(*[_batch(v) for v in variables],
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
        batch = checks.broadcast_shapes(c.shape[:-1], *([] if state is None else [state[0].shape[:-1]]))
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

    # The residual and the Jacobians are this factor's methods, bound on every access: stored on
    # the instance, a bound method would make a reference cycle (the factor, its method, the
    # factor) that holds the linearisation's tensors (hundreds of MB in a TLS solve of 400 trials)
    # until Python's cyclic collector runs, and a copy (graph.add with a loss) would call the
    # original's methods.
    @property
    def residual(self):
        return self._residual

    @residual.setter
    def residual(self, value) -> None:
        if not _own_method(self, value, GaussHelmert._residual):
            raise AttributeError("a GaussHelmert factor's residual is its own condition's")

    @property
    def jacobians(self):
        return self._jacobians

    @jacobians.setter
    def jacobians(self, value) -> None:
        if not _own_method(self, value, GaussHelmert._jacobians):
            raise AttributeError("a GaussHelmert factor's Jacobians are its own condition's")


def _own_method(factor: GaussHelmert, value, function) -> bool:
    """Whether ``value`` is ``function`` bound to ``factor`` (what Factor.__init__ assigns)."""
    return getattr(value, "__self__", None) is factor and getattr(value, "__func__", None) is function


def _batch(v) -> torch.Size:
    if isinstance(v, LieGroup):
        return v.batch_shape
    return v.shape[:-1] if isinstance(v, torch.Tensor) and v.dim() else torch.Size()


def _forward_jacobians(condition: Callable, variables, data, e):
    """(c, [A_j], Bm) by forward mode: the derivatives along every tangent direction of the
    variables (right perturbations) and of e, one ``jvp`` each, batched under ``vmap``."""
    sizes = [v.dof if isinstance(v, LieGroup) else v.shape[-1] for v in variables] + [e.shape[-1]]
    batch = checks.broadcast_shapes(e.shape[:-1], *[_batch(v) for v in variables])
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
