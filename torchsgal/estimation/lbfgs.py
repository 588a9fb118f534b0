"""A first-order alternative: ``torch.optim.LBFGS`` on tangent-space perturbations.

The unknowns move as x = retract(x0, S z) with z the optimisation variable and S a fixed
per-coordinate scaling (a diagonal preconditioner); the cost is differentiated by autograd
through the group operations (their exp/log have closed-form backward passes).  The problems
of a batch are independent, so their summed cost is minimised; they share LBFGS's line search
and stopping test, which is the price of batching a first-order method this way.  Each
problem's status comes from its own gradient norm at the end.  A problem whose cost or
gradient is non-finite (at x0, or at any point LBFGS evaluates) is masked out of the summed
cost from then on (``torch.where``, no data-dependent indexing) and reported NON_FINITE, so it
does not turn the others into NaN.  Not differentiable: the results carry no autograd graph.
"""
from __future__ import annotations

from collections.abc import Callable

import torch

from ..functional import checks
from ..functional._blocking import values_readable
from . import variables as V
from .solver import SolverReport, SolverStatus


def _rows(mask: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """The (B,) mask shaped to broadcast over the rows of t (B, ...)."""
    return mask.reshape(mask.shape + (1,) * (t.dim() - 1))


def _check_scale(scale, Bn: int, d: int, ref: torch.Tensor) -> torch.Tensor:
    if scale is None:
        return torch.ones(d, dtype=ref.dtype, device=ref.device)
    checks.floating(scale, "scale")
    checks.same_device_dtype(x0=ref, scale=scale)
    if tuple(scale.shape) not in ((d,), (Bn, d), (Bn, d, d)):
        raise ValueError(f"scale must have shape (d,) = ({d},), (B, d) = ({Bn}, {d}) or "
                         f"(B, d, d) = ({Bn}, {d}, {d}) (d the tangent size of x0), got "
                         f"{tuple(scale.shape)}")
    scale = scale.detach()
    if scale.numel() and values_readable(scale):  # one read: a singular scale freezes directions
        invertible = torch.linalg.slogdet(scale)[0] != 0 if scale.dim() == 3 else scale != 0
        if not bool(torch.isfinite(scale).all() & invertible.all()):
            raise ValueError("scale must be finite and invertible (no zero coordinate, no singular "
                             "matrix): LBFGS would not move the directions it maps to zero")
    return scale


def _check_extra(extra, extra_scale, Bn: int, ref: torch.Tensor):
    if extra is None:
        if extra_scale is not None:
            raise ValueError("extra_scale was given without extra")
        return None, None
    checks.floating(extra, "extra")
    checks.same_device_dtype(x0=ref, extra=extra)
    if extra.dim() < 2 or extra.shape[0] != Bn:
        raise ValueError(f"extra must have shape (B, ..., k) with B = {Bn}, got "
                         f"{tuple(extra.shape)}")
    if extra_scale is not None:
        k = extra.shape[-1]
        checks.matrix(extra_scale, k, "extra_scale")
        checks.same_device_dtype(x0=ref, extra_scale=extra_scale)
        checks.broadcast_batch(extra=extra.shape[:-1], extra_scale=extra_scale.shape[:-2])
        extra_scale = extra_scale.detach()
    return extra.detach(), extra_scale


def lbfgs(
    cost: Callable,
    x0,
    *,
    scale: torch.Tensor | None = None,
    extra: torch.Tensor | None = None,
    extra_scale: torch.Tensor | None = None,
    max_iterations: int = 200,
    history_size: int = 20,
    gradient_tol: float = 1e-6,
):
    """Minimises cost(x, extra) -> (B,) for every problem of a batch.

    x0: the unknowns, as in ``gauss_newton``: a group element (B,) or (B, K), a tensor (B, k)
    or (B, K, k), or a tuple of them; ``cost`` receives x, and the returned x comes back, in
    the same form (a block given alone arrives alone); scale: the preconditioner of their tangent
    perturbation, delta = scale z: (B, d) or (d,) per coordinate, or (B, d, d) a matrix
    (default 1); extra: optional additional Euclidean variables (B, ..., k) that the cost also
    takes (for example nuisance parameters), moved as extra + extra_scale @ z_e with
    extra_scale (B, ..., k, k) (default: unscaled).
    max_iterations: LBFGS iterations (an integer >= 0; 0 evaluates x0 only); history_size
    (>= 1) and gradient_tol (>= 0) as in ``torch.optim.LBFGS``.
    Returns (x, extra, report): the status is CONVERGED where the largest component of the
    problem's gradient with respect to its scaled variables is at most ``gradient_tol``, the
    test LBFGS itself stops on (max-abs; an absolute test, so a constant added to the cost
    leaves the status alone);
    otherwise MAX_ITERATIONS where LBFGS used up ``max_iterations`` (or its 4 x
    max_iterations evaluations), DIVERGED where it stopped before (no further decrease: a
    stalled line search or loss change below its tolerance); NON_FINITE where the cost or
    its gradient was non-finite at x0 or at any point evaluated (that problem is left out
    of the summed cost from then on, so the others are solved as they would be without it;
    its costs and gradient_norm are NaN).  ``report.gradient_norm`` is that gradient's
    Euclidean norm, ``report.iterations`` LBFGS's iteration count (shared by the batch).
    Not differentiable: x0, scale, extra and extra_scale are detached, the results carry no
    graph, and the gradients are taken with respect to LBFGS's own variables only (nothing
    accumulates in the ``.grad`` of tensors the cost captures).
    """
    checks.integer(max_iterations, "max_iterations", 0)
    checks.integer(history_size, "history_size", 1)
    checks.finite_number(gradient_tol, "gradient_tol", ">= 0")
    single = V.is_single(x0)
    cost = V.unwrapped(cost, single)
    x0 = V.detach(V.check_values(x0))
    Bn, d = V.batch_size(x0), V.tangent_dim(x0)
    ref = x0[0].as_matrix() if hasattr(x0[0], "as_matrix") else x0[0]
    S = _check_scale(scale, Bn, d, ref)
    extra, extra_scale = _check_extra(extra, extra_scale, Bn, ref)
    z = torch.zeros(Bn, d, dtype=ref.dtype, device=ref.device, requires_grad=True)

    def step(zv):
        return (S @ zv[..., None])[..., 0] if S.dim() == 3 else S * zv
    params = [z] + ([torch.zeros_like(extra, requires_grad=True)] if extra is not None else [])

    def extra_at(ze):
        if extra is None:
            return None
        return extra + ((extra_scale @ ze[..., None])[..., 0] if extra_scale is not None else ze)
    max_eval = 4 * max_iterations
    opt = torch.optim.LBFGS(params, lr=1.0, max_iter=max_iterations, max_eval=max_eval,
                            history_size=history_size,
                            tolerance_grad=gradient_tol, tolerance_change=1e-14,
                            line_search_fn="strong_wolfe")
    with torch.no_grad():
        initial = cost(x0, extra)
    if not isinstance(initial, torch.Tensor) or tuple(initial.shape) != (Bn,):
        got = tuple(initial.shape) if isinstance(initial, torch.Tensor) else type(initial).__name__
        raise ValueError(f"cost(x, extra) must return a tensor of shape (B,) = ({Bn},), got {got}")
    checks.same_device_dtype(x0=ref, **{"cost(x, extra)": initial})
    # The problems still in the summed cost: finite there so far.
    active = torch.isfinite(initial) & V.finite(x0)
    if extra is not None:
        active = active & torch.isfinite(extra).flatten(1).all(-1)
    state = {"active": active}

    def gradients(c, active, wrt):
        """The per-problem gradients of the costs ``c`` of the active problems with respect to
        the tensors ``wrt`` (zeros for one the cost does not use)."""
        total = torch.where(active, c, 0).sum()
        if not total.requires_grad:  # a cost that reads none of them (an empty tangent)
            return [torch.zeros_like(p) for p in wrt]
        grads = torch.autograd.grad(total, wrt, allow_unused=True)
        return [torch.zeros_like(p) if g is None else g for p, g in zip(wrt, grads)]

    def closure():
        c = cost(V.retract(x0, step(z)), extra_at(params[1]) if extra is not None else None)
        active = state["active"] & torch.isfinite(c)
        grads = gradients(c, active, params)
        for g in grads:
            active = active & torch.isfinite(g).flatten(1).all(-1)
        state["active"] = active
        # A masked problem's gradient is zero: LBFGS's direction never moves it.
        for p, g in zip(params, grads):
            p.grad = torch.where(_rows(active, g), g, 0)
        return torch.where(active, c.detach(), 0).sum()

    if max_iterations > 0 and sum(p.numel() for p in params) > 0:  # else nothing can move
        opt.step(closure)
    x = V.retract(x0, step(z.detach()))
    # Per-problem gradient at the end.
    zz = z.detach().clone().requires_grad_(True)
    ee = params[1].detach().clone().requires_grad_(True) if extra is not None else None
    c = cost(V.retract(x0, step(zz)), extra_at(ee))
    active = state["active"] & torch.isfinite(c)
    grads = gradients(c, active, [zz] + ([ee] if ee is not None else []))
    g = torch.cat([grads[0]] + ([grads[1].flatten(1)] if ee is not None else []), dim=-1)
    gnorm = g.norm(dim=-1)
    gmax = g.abs().amax(-1) if g.shape[-1] else torch.zeros_like(gnorm)
    c = c.detach()
    finite = active & torch.isfinite(gnorm) & V.finite(x)
    st = opt.state[z]
    it = st.get("n_iter", 0)
    exhausted = it >= max_iterations or st.get("func_evals", 0) >= max_eval
    # The max-abs test of torch.optim.LBFGS: a batch it stopped as converged reports CONVERGED
    # for every problem (the Euclidean norm can exceed it by sqrt(d)).  A batch it stopped
    # early otherwise (loss or step change below tolerance_change) has stalled: DIVERGED.
    status = torch.where(gmax <= gradient_tol, SolverStatus.CONVERGED,
                         SolverStatus.MAX_ITERATIONS if exhausted else SolverStatus.DIVERGED)
    status = torch.where(finite, status, SolverStatus.NON_FINITE).to(torch.int64)
    nan = float("nan")
    report = SolverReport(status=status,
                          iterations=torch.full((Bn,), it, dtype=torch.int64, device=c.device),
                          initial_cost=torch.where(finite, initial.detach(), nan),
                          cost=torch.where(finite, c, nan),
                          step_norm=torch.where(finite, torch.zeros_like(c), nan),
                          gradient_norm=torch.where(finite, gnorm.detach(), nan))
    x = V.detach(x)
    return x[0] if single else x, (extra_at(ee).detach() if ee is not None else None), report
