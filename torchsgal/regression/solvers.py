"""Batched least-squares solvers on a group origin and Euclidean coefficients.

A *model* (see ``models.py``) maps an origin p (a group matrix, batch (...)) and coefficients
x (..., m) to weighted residuals r (..., R) and, for Gauss-Newton, their Jacobian
J (..., R, P) with respect to the increment [dp, dx] of the retraction
p <- p exp(dp), x <- x + dx (right perturbation, CONVENTIONS.md).  ``model.fix_origin``
drops dp.  Every batch element is an independent problem: steps are accepted or rejected
per element with ``torch.where``; the only host sync is the stopping test, once per iteration.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from ..functional import checks


@dataclass
class SolverState:
    origin: torch.Tensor  # group matrices (..., n, n)
    coefficients: torch.Tensor  # (..., m)
    cost: torch.Tensor  # (...) sum of squared weighted residuals
    converged: torch.Tensor  # (...) bool
    iterations: int


def _retract(model, origin, x, step):
    dof = model.G.dof
    if model.fix_origin:
        return origin, x + step
    new_origin = origin @ model.G.exp(step[..., :dof]).as_matrix()
    return new_origin, x + step[..., dof:]


def gauss_newton(model, origin: torch.Tensor, x: torch.Tensor, max_iterations: int = 50,
                 tolerance: float = 1e-10, damping: float = 1e-4) -> SolverState:
    """Levenberg-Marquardt (Marquardt's diagonal scaling) on every batch element at once.

    An element has converged when a step is shorter than ``tolerance * (1 + |x|)`` or its
    cost falls below ``tolerance**2 * 1e-10``; the loop stops when all have, or when the
    damping of the rest exceeds 1e16 (stalled, reported as not converged).
    """
    checks.integer(max_iterations, "max_iterations", 0)
    checks.finite_number(tolerance, "tolerance", ">= 0")
    checks.finite_number(damping, "damping", "> 0")
    r, J = model.linearize(origin, x)
    cost = (r * r).sum(-1)
    lam = torch.full_like(cost, damping)
    converged = torch.zeros_like(cost, dtype=torch.bool)
    floor = torch.finfo(cost.dtype).tiny ** 0.5
    it = 0
    for it in range(1, max_iterations + 1):  # noqa: B007 (it counts the iterations run, read after the loop)
        Jt = J.transpose(-1, -2)
        H = Jt @ J
        g = (Jt @ r.unsqueeze(-1)).squeeze(-1)
        diag = H.diagonal(dim1=-2, dim2=-1)
        scale = diag + 1e-9 * diag.amax(-1, keepdim=True) + floor
        A = H + torch.diag_embed(lam.unsqueeze(-1) * scale)
        # solve_ex: no host sync; a singular system gives a non-finite step, rejected below
        step = -torch.linalg.solve_ex(A, g.unsqueeze(-1))[0].squeeze(-1)
        step = torch.where(converged.unsqueeze(-1), torch.zeros_like(step), step)
        o_new, x_new = _retract(model, origin, x, step)
        r_new, J_new = model.linearize(o_new, x_new)
        cost_new = (r_new * r_new).sum(-1)
        # A change of the cost within its rounding still counts as a decrease, so that the last
        # (Gauss-Newton) steps reach the optimum instead of stalling about sqrt(eps) from it.
        no_worse = cost_new <= cost * (1.0 + 16 * torch.finfo(cost.dtype).eps)
        accept = no_worse & torch.isfinite(cost_new) & ~converged
        small = step.norm(dim=-1) <= tolerance * (1.0 + x.norm(dim=-1))
        tiny = cost_new <= 1e-10 * tolerance ** 2
        a = accept
        origin = torch.where(a[..., None, None], o_new, origin)
        x = torch.where(a[..., None], x_new, x)
        r = torch.where(a[..., None], r_new, r)
        J = torch.where(a[..., None, None], J_new, J)
        cost = torch.where(a, cost_new, cost)
        lam = torch.where(a, (lam / 3).clamp_min(1e-12), lam * 4)
        # A short step, accepted or not (a rejected short step means no decrease is possible
        # at working precision), or a vanishing cost.
        converged = converged | small | (a & tiny)
        if bool((converged | (lam > 1e16)).all()):
            break
    return SolverState(origin, x, cost, converged, it)


def lbfgs(model, origin: torch.Tensor, x: torch.Tensor, max_iterations: int = 500,
          tolerance: float = 1e-10, rounds: int = 3) -> SolverState:
    """``torch.optim.LBFGS`` (strong Wolfe line search) on the tangent perturbation dp of the
    origin and on x, the cost summed over the batch (the problems stay independent: the
    gradient of the sum is each problem's gradient), with the gradient 2 J^T r from the
    model's Jacobian.  After each round the origin is
    re-anchored, p <- p exp(dp), and dp reset to zero.  An empty batch returns at once (as
    from ``gauss_newton``)."""
    checks.integer(max_iterations, "max_iterations", 0)
    checks.finite_number(tolerance, "tolerance", ">= 0")
    checks.integer(rounds, "rounds", 0)
    dof = model.G.dof
    it = 0
    if origin.shape[:-2].numel() == 0 or max_iterations == 0:
        rounds = 0  # torch.optim.LBFGS fails on empty parameters; 0 iterations: the start
    for _ in range(rounds):
        delta = torch.zeros(origin.shape[:-2] + (dof,), dtype=x.dtype, device=x.device,
                            requires_grad=not model.fix_origin)
        xv = x.detach().clone().requires_grad_(True)
        params = [xv] if model.fix_origin else [delta, xv]
        opt = torch.optim.LBFGS(params, lr=1.0, max_iter=max_iterations, history_size=20,
                                tolerance_grad=tolerance, tolerance_change=tolerance ** 2,
                                line_search_fn="strong_wolfe")

        def closure():
            # Gradient from the model's Jacobian, not autograd: d cost / d(dp) at p exp(delta)
            # is J_r(delta)^T (2 J_p^T r) (exp(delta + e) ~ exp(delta) exp(J_r(delta) e)).
            with torch.no_grad():
                o = origin if model.fix_origin else origin @ model.G.exp(delta).as_matrix()
                r, J = model.linearize(o, xv)
                g = 2 * (J.transpose(-1, -2) @ r.unsqueeze(-1)).squeeze(-1)
                if model.fix_origin:
                    xv.grad = g
                else:
                    gp = (model.G.jr(delta).transpose(-1, -2) @ g[..., :dof, None]).squeeze(-1)
                    delta.grad, xv.grad = gp, g[..., dof:].contiguous()
                return (r * r).sum()

        opt.step(closure)
        it += opt.state[params[0]].get("n_iter", 0)
        with torch.no_grad():
            if not model.fix_origin:
                origin = origin @ model.G.exp(delta.detach()).as_matrix()
            x = xv.detach()
    with torch.no_grad():
        r = model.residuals(origin, x)
        cost = (r * r).sum(-1)
        _, J = model.linearize(origin, x)
        Jt = J.transpose(-1, -2)
        H = Jt @ J
        g = (Jt @ r.unsqueeze(-1)).squeeze(-1)
        diag = H.diagonal(dim1=-2, dim2=-1)
        H = H + torch.diag_embed(1e-12 * diag + torch.finfo(cost.dtype).tiny ** 0.5)
        # Converged when the Gauss-Newton step from the final point (an estimate of the
        # distance to the optimum) is shorter than 0.1 sqrt(tolerance) (1 + |x|): a line
        # search on the cost resolves the parameters to about sqrt(eps) only.
        gn_step = torch.linalg.solve_ex(H, g.unsqueeze(-1))[0].squeeze(-1).norm(dim=-1)
        converged = gn_step <= 0.1 * tolerance ** 0.5 * (1.0 + x.norm(dim=-1))
    return SolverState(origin, x, cost, converged, it)
