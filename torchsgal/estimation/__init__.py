"""Batched estimation on the groups.

* ``graph``: factor graphs over group and Euclidean variables (vectorised factors,
  errors-in-variables conditions, robust losses, Gauss-Newton and Levenberg-Marquardt with
  GTSAM's trust-region rules, dense batched and sparse solves, marginal covariances);
  ``sparse``: the sparse Cholesky it uses; ``g2o``: g2o/iSAM/TORO pose-graph files.
* ``gauss_newton``, ``gauss_helmert``, ``lbfgs``: solvers over a residual function of the
  unknowns, and the total-least-squares problem of kelly-giamou Section 5 with its Monte Carlo
  study (``python -m torchsgal tls``).
"""
from . import g2o, graph, metrics, sparse, study, tls, variables
from .g2o import PoseGraph, odometry_initial_guess, read_pose_graph, write_pose_graph
from .gauss_helmert import gauss_helmert
from .graph import (
           Between,
           Cauchy,
           Factor,
           FactorGraph,
           GaussHelmert,
           GemanMcClure,
           GraphResult,
           Huber,
           PointObservation,
           Prior,
           RobustLoss,
           TrivialLoss,
           Tukey,
           levenberg_marquardt,
)
from .solver import Solution, SolverReport, SolverStatus, autograd_jacobian, gauss_newton
from .sparse import NotPositiveDefiniteError, SparseCholesky
from .tls import TLSProblem, solve_baseline, solve_sgal3

__all__ = ["FactorGraph", "Factor", "GaussHelmert", "Prior", "Between", "PointObservation", "RobustLoss", "TrivialLoss",
           "Huber", "Cauchy", "GemanMcClure", "Tukey", "levenberg_marquardt", "GraphResult",
           "SparseCholesky", "NotPositiveDefiniteError", "PoseGraph", "read_pose_graph", "write_pose_graph",
           "odometry_initial_guess", "gauss_newton", "gauss_helmert", "autograd_jacobian", "Solution",
           "SolverReport", "SolverStatus", "TLSProblem", "solve_sgal3", "solve_baseline", "graph", "sparse",
           "g2o", "metrics", "study", "tls", "variables"]
