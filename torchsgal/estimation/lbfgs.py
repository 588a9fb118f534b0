"""A first-order alternative: ``torch.optim.LBFGS`` on tangent-space perturbations.

The unknowns move as x = retract(x0, S z) with z the optimisation variable and S a fixed
per-coordinate scaling (a diagonal preconditioner); the cost is differentiated by autograd
through the group operations (their exp/log have closed-form backward passes).  The problems
of a batch are independent, so their summed cost is minimised; they share LBFGS's line search
and stopping test, which is the price of batching a first-order method this way.  Each
problem's status comes from its own gradient norm at the end.
"""
from __future__ import annotations

from typing import Callable

import torch

from . import variables as V
from .solver import SolverReport, SolverStatus


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
    Returns (x, extra, report): the status is CONVERGED where the largest component of the
    problem's gradient with respect to its scaled variables is below ``gradient_tol`` times
    (1 + its cost), the test LBFGS itself stops on (max-abs, over the summed cost);
    ``report.gradient_norm`` is that gradient's Euclidean norm.
    """
    single = V.is_single(x0)
    cost = V.unwrapped(cost, single)
    x0 = V.detach(V.check_values(x0))
    Bn, d = V.batch_size(x0), V.tangent_dim(x0)
    ref = x0[0].as_matrix() if hasattr(x0[0], "as_matrix") else x0[0]
    z = torch.zeros(Bn, d, dtype=ref.dtype, device=ref.device, requires_grad=True)
    S = torch.ones(d, dtype=ref.dtype, device=ref.device) if scale is None else scale

    def step(zv):
        return (S @ zv[..., None])[..., 0] if S.dim() == 3 else S * zv
    params = [z] + ([torch.zeros_like(extra, requires_grad=True)] if extra is not None else [])

    def extra_at(ze):
        if extra is None:
            return None
        return extra + ((extra_scale @ ze[..., None])[..., 0] if extra_scale is not None else ze)
    opt = torch.optim.LBFGS(params, lr=1.0, max_iter=max_iterations, max_eval=4 * max_iterations,
                            history_size=history_size,
                            tolerance_grad=gradient_tol, tolerance_change=1e-14,
                            line_search_fn="strong_wolfe")
    with torch.no_grad():
        initial = cost(x0, extra)

    def closure():
        opt.zero_grad()
        c = cost(V.retract(x0, step(z)), extra_at(params[1]) if extra is not None else None)
        total = c.sum()
        total.backward()
        return total

    opt.step(closure)
    x = V.retract(x0, step(z.detach()))
    # Per-problem gradient at the end.
    zz = z.detach().clone().requires_grad_(True)
    ee = params[1].detach().clone().requires_grad_(True) if extra is not None else None
    c = cost(V.retract(x0, step(zz)), extra_at(ee))
    grads = torch.autograd.grad(c.sum(), [zz] + ([ee] if ee is not None else []))
    g = torch.cat([grads[0]] + ([grads[1].flatten(1)] if ee is not None else []), dim=-1)
    gnorm = g.norm(dim=-1)
    gmax = g.abs().amax(-1) if g.shape[-1] else torch.zeros_like(gnorm)
    c = c.detach()
    finite = torch.isfinite(c) & torch.isfinite(gnorm) & V.finite(x)
    # The max-abs test of torch.optim.LBFGS: a batch it stopped as converged reports CONVERGED
    # for every problem (the Euclidean norm can exceed it by sqrt(d)).
    status = torch.where(gmax <= gradient_tol * (1 + c.abs()), SolverStatus.CONVERGED,
                         SolverStatus.MAX_ITERATIONS)
    status = torch.where(finite, status, SolverStatus.NON_FINITE).to(torch.int64)
    it = opt.state[z].get("n_iter", 0)
    report = SolverReport(status=status, iterations=torch.full((Bn,), it, dtype=torch.int64, device=c.device),
                          initial_cost=initial.detach(), cost=c, step_norm=torch.zeros_like(c),
                          gradient_norm=gnorm.detach())
    return x[0] if single else x, (extra_at(ee).detach() if ee is not None else None), report
