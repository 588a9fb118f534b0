"""Gradients of a solution by implicit differentiation at the optimum.

At a solution x* the gradient of the cost with respect to the right perturbations vanishes:
g(x*, theta) = J~^T r~ = 0 (whitened, robust-corrected: g = sum rho'(s) J^T L^T L r), where
theta is every tensor the residuals read (the factors' data, their noise, tensors a residual
closes over).  Differentiating, dx*/dtheta = -H^-1 dg/dtheta, and in reverse mode, for an
incoming gradient w on the perturbation of x*:

    solve H v = w,     grad_theta = -(dg/dtheta)^T v,

one batched (or sparse) Cholesky solve with the engine's H at x*, then one vector-Jacobian
product of g, whose dependence on theta (through r~ AND through J~ and the robust weights) is
differentiated exactly by autograd.  The approximation is H: the engine's Gauss-Newton
information J~^T J~ stands for the Hessian of the cost, which drops sum r~_k d^2 r~_k and, for
robust losses with rho'' < 0, the loss curvature 2 rho'' (J^T r)(J^T r)^T.  The gradient is
therefore exact where those terms vanish: at zero residual, and for residuals linear in the
unknowns with the plain loss (or a loss in its quadratic region); elsewhere its error is of
the order of the residuals.

The result is attached as x* exp(d) with d = 0 in value and dd/dtheta = -H^-1 dg/dtheta (an
autograd function whose forward returns zeros): group-valued results carry the gradient
through ``exp`` at 0 and are bitwise the solver's values.
"""
from __future__ import annotations

import torch

from .linear_system import LinearSystem
from .linearize import linearize
from .problem import Problem

__all__ = ["attach_implicit"]


class _ImplicitStep(torch.autograd.Function):
    """d = 0 in value; backward: grad_g = -H^-1 grad_d (H at the solution)."""

    @staticmethod
    def forward(ctx, g: torch.Tensor, system: LinearSystem) -> torch.Tensor:
        ctx.system = system
        return torch.zeros_like(g)

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> tuple[torch.Tensor, None]:
        return -ctx.system.solve_information(grad), None


def attach_implicit(problem: Problem, system: LinearSystem, x: list[torch.Tensor],
                    status: torch.Tensor) -> list[torch.Tensor]:
    """The solution ``x`` (layout order, detached) as x exp(d(theta)) carrying the implicit
    gradient (module docstring), or ``x`` unchanged when no tensor the residuals read requires
    grad.  ``problem`` must keep its data attached (``Problem(graph, attach=True)``) and
    ``system`` hold H at x (``set_solution``).  Raises where H is singular at x (a gauge
    freedom: the solution is not a function of theta there)."""
    with torch.enable_grad():
        g = linearize(problem, x).g
    if not g.requires_grad:
        return x
    singular = system.singular()
    if bool(singular.any()):
        rows = singular.nonzero().squeeze(-1)
        raise ValueError(f"backward_mode='implicit': the information at the solution is singular "
                         f"for problem(s) {rows.tolist()} (status "
                         f"{status.index_select(0, rows).tolist()}): the "
                         f"solution does not determine its gradient there (add priors that fix "
                         f"the gauge, or use backward_mode='none')")
    delta = _ImplicitStep.apply(g, system)
    return problem.retract(x, delta)
