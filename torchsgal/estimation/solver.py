"""Batched Gauss-Newton / Levenberg-Marquardt over group and Euclidean unknowns.

Every problem of the batch has its own damping, step, cost and status, kept with
``torch.where``, so one bad problem never spoils the others.  The loop stops when no problem
is still running.  Host syncs, outside the group ops: two per iteration (the stop test, and
whether every problem accepted its step, which spares the selection copies), and one after
the loop (the singularity test of the covariance, an eigvalsh).

The normal equations use the whitened residual r (B, m) and its Jacobian J (B, m, d) with
respect to right perturbations of the unknowns (``variables.retract``):
(J^T J + lambda diag(J^T J)) delta = -J^T r.  The Laplace covariance of the solution is
(J^T J)^-1 at the last linearisation point.  A linearisation may give J^T J, J^T r and
1/2 |r|^2 directly instead of r and J (``Linearisation.H``).
"""
from __future__ import annotations

import enum
from collections.abc import Callable
from dataclasses import dataclass
from typing import cast

import torch

from ..functional import checks
from . import variables as V


class SolverStatus(enum.IntEnum):
    """Per-problem outcome codes of ``SolverReport.status`` (int64 tensors; compare with
    ``report.status == SolverStatus.CONVERGED`` or use ``report.converged``)."""

    RUNNING = -1  # only while iterating: never in a returned report
    CONVERGED = 0
    MAX_ITERATIONS = 1
    DIVERGED = 2  # stalled: the damping grew past its limit without an acceptable step (plain
    # Gauss-Newton: an unsolvable or non-finite step; lbfgs: stopped early, gradient test failed)
    NON_FINITE = 3  # non-finite unknowns, residuals or Jacobians at the start, or a cost
    # that overflows there (finite residuals beyond ~1e154): costs NaN
    SINGULAR = 4  # the information J^T J is singular at the solution (unobservable directions);
    # takes precedence over CONVERGED / MAX_ITERATIONS / DIVERGED, and the covariance is NaN
    CONVERGED_RANK_DEFICIENT = 5  # converged (graph solvers), but the information is singular
    # (a gauge freedom or unobserved directions): the estimate is one of many, covariances NaN


@dataclass
class SolverReport:
    """Per-problem outcome of a solver; every field is a tensor of shape (B,), one entry per
    problem of the batch, on the unknowns' device.

    status         int64 ``SolverStatus`` codes: CONVERGED (0), MAX_ITERATIONS (1), DIVERGED
                   (2: the damping grew past ``max_damping`` without an acceptable step; with
                   ``damping=None``, a step that could not be solved or gave non-finite
                   values; ``lbfgs``: LBFGS stopped before ``max_iterations`` (no further
                   decrease) without passing the gradient test), NON_FINITE (3: non-finite
                   unknowns, residuals or Jacobians at x0, or a cost that overflows there;
                   ``lbfgs``: a non-finite cost or
                   gradient at x0 or at any point LBFGS evaluated, or at the end), SINGULAR
                   (4: the information J^T J is singular at the solution; it replaces the
                   other codes, the problem may have converged, its covariance is NaN).
                   Where the status is NON_FINITE, initial_cost, cost, step_norm and
                   gradient_norm are NaN (unknown), not the zeros the solver iterated on.
    iterations     int64, the steps taken by that problem, accepted and rejected (``lbfgs``:
                   LBFGS's iteration count, shared by the batch).
    initial_cost   the cost at x0; cost = 1/2 |r|^2 of the whitened residual r, so that
                   2 cost is the chi-square of the fit (``gauss_helmert``: the linearised
                   errors-in-variables cost 1/2 w^T S^-1 w; ``lbfgs``: cost(x0)).
    cost           the same at the solution.
    step_norm      sqrt(delta^T J^T J delta) of the last step tried, in standard deviations
                   of the Laplace posterior (the quantity tested against ``step_tol``);
                   ``lbfgs``: zeros.
    gradient_norm  |J^T r|, the Euclidean norm of the cost's gradient at the solution with
                   respect to the right perturbation (``lbfgs``: with respect to its scaled
                   variables).

    ``converged`` (property) is the bool mask status == CONVERGED; ``counts()`` the number of
    problems per status (host syncs).  No field carries autograd history.
    """

    status: torch.Tensor  # SolverStatus codes (int64)
    iterations: torch.Tensor  # accepted + rejected steps taken
    initial_cost: torch.Tensor  # 1/2 |r|^2 at x0
    cost: torch.Tensor  # 1/2 |r|^2 at the solution
    step_norm: torch.Tensor  # sqrt(delta^T J^T J delta) of the last step (in standard deviations)
    gradient_norm: torch.Tensor  # |J^T r| at the solution

    @property
    def converged(self) -> torch.Tensor:
        """(B,) bool: True where status is CONVERGED."""
        return self.status == SolverStatus.CONVERGED

    def counts(self) -> dict[str, int]:
        """{status name: number of problems} for the statuses that occur (one host read)."""
        n = torch.stack([(self.status == s).sum() for s in SolverStatus]).tolist()
        return {s.name: k for s, k in zip(SolverStatus, n) if s != SolverStatus.RUNNING and k}


@dataclass
class Solution:
    """The result of ``gauss_newton`` and ``gauss_helmert`` (and ``tls.solve_sgal3`` /
    ``solve_baseline``) for a batch of B problems.

    x           the unknowns at the solution, in the form x0 was given: one block alone (a
                group element of batch (B,) or (B, K), a tensor (B, k) or (B, K, k)), or a tuple
                of the same blocks.  Problems that did not converge hold their last accepted
                point (see ``report.status``).
    covariance  (B, d, d), d the tangent size of the unknowns (the blocks' tangents
                concatenated in order, a (B, K) block variable-major): the Laplace
                covariance (J^T J)^-1 at the solution, over the right perturbations
                x_true = x exp(eps) of group blocks (additive for tensor blocks), in the units
                of the unknowns (the residual is whitened).  NaN where the status is SINGULAR
                or NON_FINITE.
    report      ``SolverReport``: per-problem status, iterations, costs and norms.
    aux         solver-specific state: ``gauss_helmert``, the estimated observation residuals
                e (B, N, m); None for ``gauss_newton``.

    The solvers are not differentiable: every tensor of a Solution is detached (no
    ``grad_fn``, ``requires_grad`` False), whether or not x0, the data or the covariances
    require gradients.  For the derivative of an estimate with respect to the data use the
    implicit function theorem at the solution (d x_hat = -(J^T J)^-1 J^T (dr/d data) d data).
    """

    x: object  # the unknowns, as x0 was given: one block alone, or a tuple of the same blocks
    covariance: torch.Tensor  # (B, d, d) Laplace covariance (J^T J)^-1, right perturbations
    report: SolverReport
    aux: object = None  # solver-specific state (the observation residuals for Gauss-Helmert)


@dataclass
class Linearisation:
    """The whitened residual and its Jacobian, or (when ``H`` is given) the normal equations
    themselves: a linearisation that can sum J^T J over its residuals more cheaply than forming
    J (``tls``) gives H, g and cost and may leave r and J None.  What ``iterate``'s
    ``linearise(x, aux)`` returns (internal to the solvers; d the tangent size of x).

    r      (B, m) whitened residual, or None when H is given.
    J      (B, m, d) its Jacobian with respect to the right perturbation, or None.
    extra  anything the ``post_step`` hook needs (Gauss-Helmert: the factors of S).
    H      (B, d, d) J^T J;  g  (B, d) J^T r;  cost  (B,) 1/2 |r|^2 (``normal_equations``
           fills them from r and J).
    """

    r: torch.Tensor | None  # (B, m) whitened residual
    J: torch.Tensor | None  # (B, m, d)
    extra: object = None  # passed to the post-step hook
    H: torch.Tensor | None = None  # (B, d, d) J^T J
    g: torch.Tensor | None = None  # (B, d) J^T r
    cost: torch.Tensor | None = None  # (B,) 1/2 |r|^2

    def normal_equations(self) -> Linearisation:
        """Fills H, g and cost from r and J (once)."""
        if self.H is None:
            assert self.r is not None and self.J is not None  # r and J, or H, g and cost
            Jt = self.J.transpose(-1, -2)
            self.H = Jt @ self.J
            self.g = (Jt @ self.r[..., None])[..., 0]
            self.cost = 0.5 * self.r.square().sum(dim=-1)
        return self

    def finite(self) -> torch.Tensor:
        """(B,) residuals and Jacobians finite (the normal equations when there is no J)."""
        if self.J is not None:
            assert self.r is not None  # given with J
            return torch.isfinite(self.r).all(-1) & torch.isfinite(self.J).flatten(1).all(-1)
        assert self.H is not None and self.g is not None and self.cost is not None
        return (torch.isfinite(self.H).flatten(1).all(-1) & torch.isfinite(self.g).all(-1)
                & torch.isfinite(self.cost))

    def select(self, mask: torch.Tensor, other: Linearisation) -> Linearisation:
        """Per problem: this one where ``mask``, else ``other`` (both with normal equations)."""
        def pick(a, b):
            if a is None or b is None:
                return None
            return torch.where(mask.reshape(mask.shape + (1,) * (a.dim() - 1)), a, b)
        return Linearisation(pick(self.r, other.r), pick(self.J, other.J),
                             _select_aux(mask, self.extra, other.extra), pick(self.H, other.H),
                             pick(self.g, other.g), pick(self.cost, other.cost))


def information_is_singular(H: torch.Tensor, rcond: float | None = None,
                            diagonal_rcond: float | None = None) -> torch.Tensor:
    """(B,) True where the information is numerically singular: a diagonal entry at most
    ``diagonal_rcond`` times the largest (a direction that no residual sees: its information
    is then rounding noise, O(eps^2) of the largest, which the Jacobi scaling below would blow
    up to 1), or the Jacobi-scaled matrix with reciprocal condition below ``rcond`` (collinear
    directions, a test that does not depend on the units), or non-finite entries.  Defaults:
    rcond 1e3 eps, diagonal_rcond eps.

    The diagonal test compares unknowns with each other, so it depends on their units: an
    unknown whose standard deviation is 1/sqrt(diagonal_rcond) times another's (6.7e7 in
    float64, 2,900 in float32) is flagged.  Express the unknowns in commensurate units where
    that happens."""
    if rcond is None:
        rcond = 1e3 * torch.finfo(H.dtype).eps
    if diagonal_rcond is None:
        diagonal_rcond = torch.finfo(H.dtype).eps
    d = H.diagonal(dim1=-2, dim2=-1)
    s = torch.where(d > 0, d, torch.ones_like(d)).rsqrt()
    Hs = H * s[..., :, None] * s[..., None, :]
    finite = torch.isfinite(Hs).all(dim=(-1, -2))
    ev = torch.linalg.eigvalsh(torch.where(finite[..., None, None], Hs, torch.eye(
        H.shape[-1], dtype=H.dtype, device=H.device)))
    tiny = d <= diagonal_rcond * d.amax(dim=-1, keepdim=True)
    return ~finite | tiny.any(dim=-1) | (ev[..., 0] <= rcond * ev[..., -1])


def covariance_from_information(H: torch.Tensor, singular: torch.Tensor) -> torch.Tensor:
    """H^-1 (..., d, d) by Cholesky of the information H (..., d, d); NaN where ``singular``
    (a bool tensor (...); the report's status says SINGULAR there) and where H is not positive
    definite (its Cholesky fails: never an inverse of a matrix the factorisation did not
    finish)."""
    checks.floating(H, "H")
    if H.dim() < 2 or H.shape[-1] != H.shape[-2]:
        raise ValueError(f"H must have shape (..., d, d), got {tuple(H.shape)}")
    if not isinstance(singular, torch.Tensor) or singular.dtype != torch.bool:
        got = singular.dtype if isinstance(singular, torch.Tensor) else type(singular).__name__
        raise TypeError(f"singular must be a bool tensor (...), got {got}")
    checks.broadcast_batch(H=H.shape[:-2], singular=singular.shape)
    eye = torch.eye(H.shape[-1], dtype=H.dtype, device=H.device)
    Hs = torch.where(singular[..., None, None], eye, H)
    L, info = torch.linalg.cholesky_ex(Hs)
    bad = singular | (info != 0)
    P = torch.cholesky_inverse(torch.where(bad[..., None, None], eye, L))
    return torch.where(bad[..., None, None], torch.full_like(P, float("nan")), P)


def _check_options(max_iterations, damping, max_damping, stop_below_fraction, **tolerances) -> None:
    """The solver options of ``iterate``: raise naming the option (host-side numbers only)."""
    checks.integer(max_iterations, "max_iterations", 0)
    if damping is not None:  # None: plain Gauss-Newton
        checks.finite_number(damping, "damping", ">= 0")
    checks.finite_number(max_damping, "max_damping", "> 0")
    checks.finite_number(stop_below_fraction, "stop_below_fraction", "in [0, 1]")
    for name, value in tolerances.items():
        checks.finite_number(value, name, ">= 0")


def iterate(
    linearise: Callable,
    x0,
    aux0=None,
    post_step: Callable | None = None,
    *,
    max_iterations: int = 50,
    damping: float | None = 1e-4,
    step_tol: float = 1e-6,
    cost_tol: float = 1e-12,
    accept_tol: float = 0.0,
    always_accept_below: float = 0.0,
    max_damping: float = 1e10,
    stop_below_fraction: float = 0.0,
) -> Solution:
    """The shared loop of ``gauss_newton`` and ``gauss_helmert``.

    ``linearise(x, aux) -> Linearisation`` at the current point; ``post_step(x, aux, lin,
    delta) -> aux`` gives the solver state that goes with the new point (None: unchanged).
    ``damping=None`` takes plain Gauss-Newton steps (every step accepted); otherwise
    Levenberg-Marquardt with per-problem damping starting at ``damping`` (0: undamped until a
    step is rejected), divided by 10 after an accepted step and multiplied by 10 after a
    rejected one, never below 1e-12 after the first step.
    ``stop_below_fraction``: leave the loop (the problems still running get MAX_ITERATIONS)
    once at most this fraction of the batch is running, so that a caller can finish the
    stragglers in a smaller batch instead of iterating the whole batch for them.  A step is accepted
    when the new cost is at most (1 + accept_tol) times the old one, or when the step is
    shorter than ``always_accept_below`` standard deviations.  A problem converges when
    an accepted step is shorter than ``step_tol`` in the metric of the information,
    sqrt(delta^T J^T J delta) (that is, in standard deviations of the Laplace posterior, a
    dimensionless test), or when the cost falls by less than ``cost_tol`` relative.
    Raises ValueError for a negative ``max_iterations``, ``damping`` or tolerance, and for
    unknowns without a tangent (nothing to solve for).
    Host reads (syncs on CUDA): one per iteration (the stop test), one before the loop and the
    singularity test's eigenvalues at the end.
    Not differentiable: x0 and aux0 are detached, and the solution carries no graph.
    """
    _check_options(max_iterations, damping, max_damping, stop_below_fraction, step_tol=step_tol,
                   cost_tol=cost_tol, accept_tol=accept_tol, always_accept_below=always_accept_below)
    # The solvers are not differentiable: the start is detached (a graph through x0 would
    # give d x_hat / d x0 = 1, and one through the data would be incomplete), and so is
    # everything returned.
    x = V.detach(V.check_values(x0))
    if V.tangent_dim(x) == 0:
        raise ValueError(f"x0 must have at least one unknown (a tangent of size >= 1), got "
                         f"tangent sizes {V.block_dims(x)}")
    aux = _detach(aux0)
    lin = linearise(x, aux)
    Bn = V.batch_size(x)
    d = V.tangent_dim(x)
    ref = lin.J if lin.J is not None else lin.H
    dtype, device = ref.dtype, ref.device
    eye = torch.eye(d, dtype=dtype, device=device)

    ok0 = V.finite(x) & lin.finite()
    if lin.J is not None:  # finite residuals whose cost overflows (|r| beyond ~1e154)
        assert lin.r is not None  # given with J
        cost0 = 0.5 * torch.where(ok0[:, None], lin.r, 0).square().sum(dim=-1)
        ok0 = ok0 & torch.isfinite(cost0)
    status = torch.where(ok0, SolverStatus.RUNNING, SolverStatus.NON_FINITE).to(torch.int64)
    # Sanitise non-finite problems so that they cannot poison shared reductions.
    if lin.J is not None:
        lin = Linearisation(torch.where(ok0[:, None], lin.r, torch.zeros_like(lin.r)),
                            torch.where(ok0[:, None, None], lin.J, torch.zeros_like(lin.J)),
                            lin.extra)
    else:
        lin = Linearisation(None, None, lin.extra, torch.where(ok0[:, None, None], lin.H, 0),
                            torch.where(ok0[:, None], lin.g, 0), torch.where(ok0, lin.cost, 0))
    lin.normal_equations()
    cost = lin.cost
    assert cost is not None  # normal_equations filled it
    initial_cost = cost.clone()
    lam = torch.full((Bn,), damping if damping is not None else 0.0, dtype=dtype, device=device)
    iterations = torch.zeros(Bn, dtype=torch.int64, device=device)
    step_norm = torch.zeros(Bn, dtype=dtype, device=device)

    n_running = int((status == SolverStatus.RUNNING).sum())  # then one read per iteration, below
    for it in range(max_iterations):
        if n_running == 0 or (it > 0 and n_running <= stop_below_fraction * Bn):
            break
        running = status == SolverStatus.RUNNING
        H, g = lin.H, lin.g
        assert H is not None and g is not None  # normal_equations filled them
        diag = H.diagonal(dim1=-2, dim2=-1)
        # Damping scaled by the diagonal, floored so that unobservable directions stay solvable.
        floor = 1e-12 * diag.amax(dim=-1, keepdim=True).clamp_min(torch.finfo(dtype).tiny)
        Hd = H + torch.diag_embed(lam[:, None] * torch.maximum(diag, floor)) if damping is not None else H
        L, info = torch.linalg.cholesky_ex(torch.where(running[:, None, None], Hd, eye))
        solvable = info == 0
        delta = -torch.cholesky_solve(g[..., None], L)[..., 0]
        delta = torch.where((running & solvable)[:, None], delta, torch.zeros_like(delta))
        x_new = V.retract(x, delta)
        # A problem that is not running keeps its point and linearisation whatever the new ones are.
        aux_new = post_step(x, aux, lin, delta) if post_step is not None else aux
        lin_new = linearise(x_new, aux_new)
        finite_new = V.finite(x_new) & lin_new.finite()
        lin_new.normal_equations()
        cost_new = lin_new.cost
        assert cost_new is not None  # normal_equations filled it
        finite_new = finite_new & torch.isfinite(cost_new)
        step = (delta * (H @ delta[..., None])[..., 0]).sum(-1).clamp_min(0).sqrt()
        if damping is None:
            accept = running & solvable & finite_new
        else:
            accept = running & solvable & finite_new & (
                (cost_new <= cost * (1 + accept_tol)) | (step <= always_accept_below))
        iterations = iterations + running.to(torch.int64)
        step_norm = torch.where(running, step, step_norm)
        old_cost = cost
        cost = torch.where(accept, cost_new, cost)
        if damping is not None:
            # 1e-12 at least on both sides: a start at 0 (undamped) still grows after a rejection
            lam = torch.where(accept, (lam / 10).clamp_min(1e-12), (lam * 10).clamp_min(1e-12))
        decrease = old_cost - cost
        converged = running & accept & (
            (step <= step_tol) | ((decrease >= 0) & (decrease <= cost_tol * old_cost)))
        diverged = running & ~converged & (
            (lam > max_damping) if damping is not None else ~(solvable & finite_new))
        status = torch.where(converged, SolverStatus.CONVERGED, status)
        status = torch.where(diverged, SolverStatus.DIVERGED, status)
        # The iteration's one host read: the next stop test's count, and whether every problem
        # accepted its step (the common case, which needs no selection copies).
        n_running, all_accepted = torch.stack(
            ((status == SolverStatus.RUNNING).sum(), accept.all().to(torch.int64))).tolist()
        # Keep the accepted problems' new point; the others keep theirs.
        if all_accepted:
            x, aux, lin = x_new, aux_new, lin_new
        else:
            x = V.select(accept, x_new, x)
            if aux is not None or aux_new is not None:
                aux = _select_aux(accept, aux_new, aux)
            lin = lin_new.select(accept, lin)
    status = torch.where(status == SolverStatus.RUNNING, SolverStatus.MAX_ITERATIONS, status)

    H, g = lin.H, lin.g
    assert H is not None and g is not None  # normal_equations filled them
    singular = information_is_singular(H) & (status != SolverStatus.NON_FINITE)
    status = torch.where(singular, SolverStatus.SINGULAR, status)
    non_finite = status == SolverStatus.NON_FINITE
    P = covariance_from_information(H, singular | non_finite)
    # A NON_FINITE problem was sanitised to zeros above: its costs and norms are unknown, not 0.
    nan = float("nan")
    report = SolverReport(status=status, iterations=iterations,
                          initial_cost=torch.where(non_finite, nan, initial_cost),
                          cost=torch.where(non_finite, nan, cost),
                          step_norm=torch.where(non_finite, nan, step_norm),
                          gradient_norm=torch.where(non_finite, nan, g.norm(dim=-1)))
    report = SolverReport(**{f: getattr(report, f).detach() for f in _REPORT_FIELDS})
    return Solution(x=V.detach(x), covariance=P.detach(), report=report, aux=_detach(aux))


_REPORT_FIELDS = ("status", "iterations", "initial_cost", "cost", "step_norm", "gradient_norm")


def _detach(state):
    """Solver state without autograd history: tensors detached, tuples, lists and dicts
    entry by entry; anything else as it is."""
    if isinstance(state, torch.Tensor):
        return state.detach()
    if isinstance(state, (tuple, list)):
        return type(state)(_detach(a) for a in state)
    if isinstance(state, dict):
        return {k: _detach(v) for k, v in state.items()}
    return state


def _select_aux(mask, new, old):
    """Per-problem selection of solver state; a state of None stands for zeros (the
    Gauss-Helmert residual estimate before the first step)."""
    if hasattr(new, "select") and not isinstance(new, torch.Tensor):
        return new.select(mask, old)
    if isinstance(new, torch.Tensor) and old is None:
        old = torch.zeros_like(new)
    if new is None or old is None:
        return new if old is None else old
    if isinstance(new, torch.Tensor):
        m = mask.reshape(mask.shape + (1,) * (new.dim() - 1))
        return torch.where(m, new, old)
    if isinstance(new, (tuple, list)):
        return type(new)(_select_aux(mask, a, b) for a, b in zip(new, old))
    if isinstance(new, dict):
        return {k: _select_aux(mask, new[k], old[k]) for k in new}
    raise TypeError(f"cannot select solver state of type {type(new).__name__}")


def autograd_jacobian(residual: Callable, x) -> torch.Tensor:
    """J (B, m, d) of residual(retract(x, delta)) at delta = 0 by reverse-mode autodiff; ``x``
    and what ``residual`` receives as in ``gauss_newton`` (one block alone, or a tuple; (B, K)
    blocks variable-major).

    The problems are independent, so the Jacobian of the batch-summed residual with respect
    to the batched perturbation holds every problem's Jacobian; one ``jacrev`` call."""
    residual = V.unwrapped(residual, V.is_single(x))
    x = V.detach(V.check_values(x, "x"))
    Bn, d = V.batch_size(x), V.tangent_dim(x)
    ref = x[0].as_matrix() if hasattr(x[0], "as_matrix") else x[0]
    zero = torch.zeros(Bn, d, dtype=ref.dtype, device=ref.device)
    J = torch.func.jacrev(lambda dl: residual(V.retract(x, dl)).sum(0))(zero)  # (m, B, d)
    return J.permute(1, 0, 2)


def gauss_newton(
    residual: Callable,
    x0,
    jacobian: Callable | None = None,
    **options,
) -> Solution:
    """Minimises 1/2 |residual(x)|^2 for every problem of a batch.

    residual: x -> (B, m), whitened (divide by the noise's square root yourself).
    x0: the unknowns: a group element of batch shape (B,), a tensor (B, k), or a tuple of them
        (the first axis is the problems; B shared by the blocks).  A group element of batch
        shape (B, K) (or a tensor (B, K, k)) is one block of K variables per problem, e.g. the
        poses of a pose graph: its tangent is K dof coordinates, variable-major, and it solves
        as the tuple of its K (B,) blocks would (``variables``).  ``residual`` and ``jacobian``
        receive x as x0 was given: a block given alone arrives alone (``x.rminus(target)``,
        ``x[:, i]`` for variable i of a (B, K) block), a tuple as a tuple of the same blocks
        (``g, s = x``); ``Solution.x`` likewise.
    jacobian: x -> (B, m, d) with respect to right perturbations (``variables.retract``; d the
        sum of the blocks' tangent sizes, in order); by default autodiff through ``residual``
        (``autograd_jacobian``).
    options: see ``iterate`` (max_iterations, damping, step_tol, cost_tol, ...).
    Returns a ``Solution`` with the unknowns, the Laplace covariance and the per-problem report.
    Not differentiable: the solution carries no autograd graph (x0 is detached; gradients
    with respect to x0 or to data captured by ``residual`` are not propagated).
    """
    single = V.is_single(x0)
    residual, jacobian = V.unwrapped(residual, single), V.unwrapped(jacobian, single)
    x0 = V.check_values(x0)
    ref = x0[0].as_matrix() if hasattr(x0[0], "as_matrix") else x0[0]

    def linearise(x, _aux):
        with torch.no_grad():
            r = residual(x)
        if not isinstance(r, torch.Tensor):
            raise TypeError(f"residual(x) must return a tensor (B, m), got {type(r).__name__}")
        if r.dim() != 2 or r.shape[0] != V.batch_size(x):
            raise ValueError(f"residual(x) must return (B, m) with B = {V.batch_size(x)}, "
                             f"got {tuple(r.shape)}")
        checks.same_device_dtype(x0=ref, **{"residual(x)": r})
        J = jacobian(x) if jacobian is not None else autograd_jacobian(residual, x)
        if not isinstance(J, torch.Tensor):
            raise TypeError(f"jacobian(x) must return a tensor (B, m, d), got {type(J).__name__}")
        expected = (r.shape[0], r.shape[1], V.tangent_dim(x))
        if tuple(J.shape) != expected:
            raise ValueError(f"jacobian(x) must return {expected}, got {tuple(J.shape)}")
        checks.same_device_dtype(x0=ref, **{"jacobian(x)": J})
        return Linearisation(r, J)

    return _as_given(iterate(linearise, x0, **options), single)


def _as_given(solution: Solution, single: bool) -> Solution:
    """The solution's unknowns unwrapped when x0 was one block alone."""
    if single:
        solution.x = cast(tuple, solution.x)[0]  # iterate returns the tuple form
    return solution
