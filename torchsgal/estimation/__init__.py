"""Batched estimation on the groups: Gauss-Newton/Levenberg-Marquardt, errors-in-variables
(Gauss-Helmert) and LBFGS solvers, and the total-least-squares problem of kelly-giamou
Section 5 with its Monte Carlo study (``python -m torchsgal tls``)."""
from . import metrics, study, tls, variables
from .gauss_helmert import gauss_helmert
from .solver import Solution, SolverReport, SolverStatus, autograd_jacobian, gauss_newton
from .tls import TLSProblem, solve_baseline, solve_sgal3

__all__ = ["gauss_newton", "gauss_helmert", "autograd_jacobian", "Solution", "SolverReport",
           "SolverStatus", "TLSProblem", "solve_sgal3", "solve_baseline", "metrics", "study",
           "tls", "variables"]
