"""Factor graphs: batched nonlinear least squares over group and Euclidean variables.

A problem is a ``FactorGraph`` of named variables, each a block of N group elements (any of
``torchsgal.ALL_GROUPS``) or Euclidean vectors, optionally for a batch of B independent
problems of one structure, and factors.  A factor type's residual is written once, for one
factor, on group elements; the engine evaluates all factors of a type together (the group
operations broadcast over the batch (B, E)) and differentiates them with respect to right
perturbations ``x exp(d)`` by forward-mode autodiff, or uses the type's analytic Jacobians.

    import torchsgal as ts
    from torchsgal.estimation import graph as fg

    graph = fg.FactorGraph()
    graph.add_variable("x", poses)                            # SE3 of batch (N,) or (B, N)
    graph.add(fg.Prior("x", 0, Z0, information=W0))            # Z0 of batch (1,) or (B, 1)
    graph.add(fg.Between("x", i, j, Z, information=W))          # i, j int64 (E,), Z (E,)/(B, E)
    graph.add(fg.Factor(residual, variables=[("x", i), ("x", j)], data=[Z], dim=6),
              loss=fg.Huber(1.0))
    result = fg.levenberg_marquardt(graph, max_iterations=100)
    result.values["x"]                # same form as given
    result.report.status              # (B,) SolverStatus codes; .iterations, .cost, ...
    result.marginal_covariance("x", idx)   # (B, K, dof, dof) Laplace covariances

Conventions: residuals r = log(Z^-1 h(x)), cost 1/2 sum rho(|L r|^2) (``rho(s) = s`` for the
plain loss, so 1/2 r^T W r as GTSAM's ``error``), noise as information W or square-root
information L (W = L^T L), shared or per factor.  The solvers follow GTSAM's
``LevenbergMarquardtOptimizer`` (``levenberg_marquardt``), ``GaussNewtonOptimizer``
(``gauss_newton``) and ``DoglegOptimizer`` (``dogleg``: Powell's dogleg, a per-problem trust
region) with GTSAM's defaults; a problem whose information is singular at the
solution (a gauge freedom: no prior) reports ``SolverStatus.CONVERGED_RANK_DEFICIENT``.

Differentiable solves: ``backward_mode="implicit"`` returns values that carry the gradient
with respect to every tensor the residuals read (measurements and other data, noise, tensors a
residual closes over) by implicit differentiation at the solution (``implicit``: one solve with
the Gauss-Newton information, exact at zero residual); ``"unroll"`` differentiates through the
iterations; ``"none"`` (default) returns detached values.

Batches and problems of up to 1000 unknowns use the batched block-sparse Cholesky of
``estimation.block_cholesky`` where their pattern pays (``linear_solver="block"``), else a
dense batched Cholesky (``"dense"``); one large problem (more than 1000 unknowns, or
``linear_solver="sparse"``) the sparse Cholesky of ``estimation.sparse``.

Errors-in-variables conditions f(x, l) = 0 with the observation corrections eliminated per
condition are ``GaussHelmert`` factors, solved by ``gauss_helmert`` (``gauss_helmert`` module).

Modules: ``factors`` (Factor, Prior, Between, PointObservation), ``robust`` (losses),
``graph`` (FactorGraph), ``linearize`` (evaluation and assembly of the normal equations),
``linear_system`` (dense and sparse solves, rank test, marginals), ``levenberg_marquardt``
(the solvers and ``GraphResult``), ``dogleg`` (the dogleg solver), ``implicit`` (the implicit
gradient).  User guide: ``docs/guide/factor_graphs.md``.
"""
from .dogleg import dogleg
from .factors import Between, Factor, PointObservation, Prior
from .gauss_helmert import GaussHelmert
from .gauss_helmert_solver import gauss_helmert
from .graph import FactorGraph
from .levenberg_marquardt import GraphResult, gauss_newton, levenberg_marquardt
from .robust import Cauchy, GemanMcClure, Huber, RobustLoss, TrivialLoss, Tukey

__all__ = ["FactorGraph", "Factor", "Prior", "Between", "PointObservation", "RobustLoss",
           "TrivialLoss", "Huber", "Cauchy", "GemanMcClure", "Tukey", "levenberg_marquardt",
           "gauss_newton", "dogleg", "GraphResult", "GaussHelmert", "gauss_helmert"]
