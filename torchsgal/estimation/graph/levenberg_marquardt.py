"""Levenberg-Marquardt and Gauss-Newton on a ``FactorGraph``, for a batch of problems.

The trust-region updates are GTSAM's ``LevenbergMarquardtOptimizer`` (``tryLambda``, the
state's ``increaseLambda``/``decreaseLambda`` and ``NonlinearOptimizer::defaultOptimize``'s
``checkConvergence``), step by step, per problem:

1. solve (H + lambda I) delta = -g (``diagonal_damping``: lambda clamp(diag H, 1e-6, 1e32));
   a failed Cholesky counts as a rejected step;
2. the linear model's decrease ``dl = -(g^T delta + 1/2 delta^T H delta)``; the step is valid
   if ``dl >= 0``; then the cost change ``dc = cost - cost(x exp(delta))``;
3. accepted if ``dl > eps * model_cost`` and ``dc / dl > min_model_fidelity``: lambda /= factor
   (not below ``lambda_lower``), one more iteration;
4. otherwise, if ``|dc| < relative_error_tol * cost`` the iteration ends without a step;
   else lambda *= factor, and at ``lambda >= lambda_upper`` the problem gives up (DIVERGED);
5. after each iteration: converged if cost <= ``error_tol``, or the decrease over the
   iteration is <= ``absolute_error_tol`` or <= ``relative_error_tol`` times the cost before
   it; otherwise MAX_ITERATIONS once ``max_iterations`` steps were accepted.

``iterations`` counts accepted steps, as GTSAM's ``optimizer.iterations()``.  Problems that
have stopped leave the working set (index_select once per change), so they cost nothing more;
the dense and block-sparse (batched) paths read one value per round on the host (how many
problems still run).  The sparse path (one problem) runs its factorisation on the host and
linearises a trial point only once its step is accepted.

Differentiable solves (``backward_mode``): "none" (default) returns values without gradient;
"implicit" attaches the gradient of the solution with respect to every tensor the residuals
read (data, noise, closed-over tensors) by implicit differentiation at the solution
(``implicit``); "unroll" runs the iterations under autograd (dense solver only).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from ...functional import checks
from ...groups import LieGroup
from ..block_cholesky import uses_kernel as uses_block_kernel
from ..solver import SolverReport, SolverStatus
from .factors import _indices
from .graph import FactorGraph
from .implicit import attach_implicit
from .linear_system import (
    BlockSparseSystem,
    DenseSystem,
    LinearSystem,
    SparseSystem,
    _finite_rows,
    block_layout,
)
from .linearize import Linearization, evaluate_cost, linearize
from .problem import Problem
from .round_update import round_update

__all__ = ["GraphResult", "levenberg_marquardt", "gauss_newton"]

RUNNING = int(SolverStatus.RUNNING)
MAX_ITERATIONS = int(SolverStatus.MAX_ITERATIONS)
SPARSE_ABOVE = 1000  # linear_solver="auto": one problem with more unknowns takes SparseCholesky
# linear_solver="auto": the block-sparse factorisation where its multiply-adds are at most this
# share of the dense one's (and its kernel runs)
BLOCK_BELOW = 0.5
LINEAR_SOLVERS = ("auto", "dense", "block", "sparse", "cholmod", "cholespy", "scipy")
BACKWARD_MODES = ("none", "implicit", "unroll")


@dataclass
class GraphResult:
    """values       {name: value at the solution}, in the form the graph was given (group
                    elements of batch (N,) or (B, N), tensors (N, k) or (B, N, k)).
    report          ``SolverReport`` (per problem: status, iterations, costs, norms).
    problem         the graph's layout (``problem.Problem``: variables in insertion order,
                    element-major tangents).
    system          the linear system at the solution (``linear_system.DenseSystem`` or
                    ``SparseSystem``), which gives the marginals.
    """

    values: dict
    report: SolverReport
    problem: Problem
    system: LinearSystem

    @property
    def information(self) -> torch.Tensor:
        """(B, D, D) H = J~^T J~ at the solution (dense; builds it for the sparse path)."""
        return self.system.dense_information()

    def marginal_covariance(self, name: str, index=None) -> torch.Tensor:
        """Laplace covariances (B, K, dof, dof) (or (K, dof, dof) for an unbatched graph) of the
        elements ``index`` (int64 (K,), default all) of variable ``name``, over right
        perturbations: diagonal blocks of H^-1 at the solution.  NaN for problems whose
        information is singular (status CONVERGED_RANK_DEFICIENT, or a singular H)."""
        p = self.problem
        if name not in p.index:
            raise KeyError(f"no variable {name!r} in the graph")
        info = p.variables[p.index[name]]
        if index is None:
            index = torch.arange(info.size, device=p.device)
        index = _indices(index, "index").to(p.device)
        if index.numel() and (int(index.min()) < 0 or int(index.max()) >= info.size):
            raise IndexError(f"index must be in [0, {info.size}) for {name!r}, got "
                             f"[{int(index.min())}, {int(index.max())}]")
        blocks = self.system.marginal_blocks(info.offset + index * info.dof, info.dof)
        return blocks if p.batched else blocks[0]


def _values(problem: Problem, graph: FactorGraph, x: list[torch.Tensor]) -> dict:
    out = {}
    for info, xv in zip(problem.variables, x):
        given = graph.variables[info.name]
        leaf = xv if problem.batched else xv[0]
        out[info.name] = type(given)._new(leaf) if isinstance(given, LieGroup) else leaf
    return out


def _check(max_iterations, lambda_initial, lambda_factor, lambda_upper, lambda_lower,
           min_model_fidelity, relative_error_tol, absolute_error_tol, error_tol, diagonal_damping,
           linear_solver, backward_mode):
    if backward_mode not in BACKWARD_MODES:
        raise ValueError(f"backward_mode must be one of {BACKWARD_MODES}, got {backward_mode!r}")
    if backward_mode == "unroll" and linear_solver not in ("auto", "dense", "block"):
        raise ValueError(f"backward_mode='unroll' needs the dense linear solver, got "
                         f"linear_solver={linear_solver!r}")
    checks.integer(max_iterations, "max_iterations", 0)
    checks.finite_number(lambda_initial, "lambda_initial", "> 0")
    checks.finite_number(lambda_factor, "lambda_factor", "> 0")
    if lambda_factor <= 1:
        raise ValueError(f"lambda_factor must be > 1, got {lambda_factor}")
    checks.finite_number(lambda_upper, "lambda_upper", "> 0")
    checks.finite_number(lambda_lower, "lambda_lower", ">= 0")
    if not lambda_lower <= lambda_initial <= lambda_upper:
        raise ValueError(f"lambda_initial must lie in [lambda_lower, lambda_upper] = "
                         f"[{lambda_lower}, {lambda_upper}], got {lambda_initial}")
    checks.finite_number(min_model_fidelity, "min_model_fidelity")
    checks.finite_number(relative_error_tol, "relative_error_tol", ">= 0")
    checks.finite_number(absolute_error_tol, "absolute_error_tol", ">= 0")
    checks.finite_number(error_tol, "error_tol", ">= 0")
    checks.boolean(diagonal_damping, "diagonal_damping")
    if linear_solver not in LINEAR_SOLVERS:
        raise ValueError(f"linear_solver must be one of {LINEAR_SOLVERS}, got {linear_solver!r}")


def levenberg_marquardt(graph: FactorGraph, max_iterations: int = 100, *,
                        lambda_initial: float = 1e-5, lambda_factor: float = 10.0,
                        lambda_upper: float = 1e5, lambda_lower: float = 0.0,
                        min_model_fidelity: float = 1e-3, diagonal_damping: bool = False,
                        relative_error_tol: float = 1e-5, absolute_error_tol: float = 1e-5,
                        error_tol: float = 0.0, linear_solver: str = "auto",
                        backward_mode: str = "none") -> GraphResult:
    """Levenberg-Marquardt with GTSAM's trust-region rules and defaults (module docstring),
    for every problem of the graph's batch.  Returns a ``GraphResult``.

    backward_mode  "none": values without gradient; "implicit": values that carry the
                   gradient of the solution with respect to the factors' data, noise and the
                   tensors their residuals close over, by implicit differentiation at the
                   solution (``implicit``; Gauss-Newton information in place of the Hessian:
                   exact at zero residual); "unroll": autograd through every iteration (dense
                   solver only; memory grows with the iterations).

    linear_solver  "dense" (batched Cholesky of H (B, D, D)), "block" (batched block-sparse
                   Cholesky: ``estimation.block_cholesky``, one analysis of H's pattern for the
                   batch), "sparse" (one problem: ``estimation.sparse.SparseCholesky``, its first
                   available backend), a ``SparseCholesky`` backend name, or "auto": sparse for
                   one problem with more than ``SPARSE_ABOVE`` unknowns; otherwise block where
                   its kernel runs and the pattern's factorisation costs at most ``BLOCK_BELOW``
                   of the dense one and the iterations are not differentiated
                   (``backward_mode="unroll"`` solves each step densely), dense elsewhere."""
    _check(max_iterations, lambda_initial, lambda_factor, lambda_upper, lambda_lower,
           min_model_fidelity, relative_error_tol, absolute_error_tol, error_tol, diagonal_damping,
           linear_solver, backward_mode)
    return _solve(graph, max_iterations, backward_mode, dict(
        damped=True, lambda_initial=lambda_initial, lambda_factor=lambda_factor,
        lambda_upper=lambda_upper, lambda_lower=lambda_lower, min_fidelity=min_model_fidelity,
        diagonal=diagonal_damping, rel_tol=relative_error_tol, abs_tol=absolute_error_tol,
        error_tol=error_tol, linear_solver=linear_solver))


def gauss_newton(graph: FactorGraph, max_iterations: int = 100, *,
                 relative_error_tol: float = 1e-5, absolute_error_tol: float = 1e-5,
                 error_tol: float = 0.0, linear_solver: str = "auto",
                 backward_mode: str = "none") -> GraphResult:
    """Gauss-Newton (GTSAM's ``GaussNewtonOptimizer``): every solvable step is taken; an
    unsolvable (singular) system stops the problem as DIVERGED.  Convergence,
    ``linear_solver`` and ``backward_mode`` as for ``levenberg_marquardt``."""
    _check(max_iterations, 1.0, 10.0, 1.0, 0.0, 0.0, relative_error_tol, absolute_error_tol,
           error_tol, False, linear_solver, backward_mode)
    return _solve(graph, max_iterations, backward_mode, dict(
        damped=False, rel_tol=relative_error_tol, abs_tol=absolute_error_tol, error_tol=error_tol,
        linear_solver=linear_solver))


@dataclass
class _State:
    """The working set's per-problem state (all leading axes = active problems)."""

    rows: torch.Tensor  # indices into the full batch
    x: list[torch.Tensor]
    lin: Linearization
    cost_start: torch.Tensor  # cost at the start of the current iteration
    lam: torch.Tensor
    iterations: torch.Tensor
    step_norm: torch.Tensor
    status: torch.Tensor

    def take(self, keep: torch.Tensor) -> _State:
        lin = Linearization(*[t.index_select(0, keep) for t in
                              (self.lin.values, self.lin.g, self.lin.cost, self.lin.model_cost)])
        return _State(self.rows.index_select(0, keep), [v.index_select(0, keep) for v in self.x],
                      lin, *[getattr(self, n).index_select(0, keep) for n in
                             ("cost_start", "lam", "iterations", "step_norm", "status")])


def _where(mask: torch.Tensor, a: torch.Tensor, b: torch.Tensor,
           out: torch.Tensor | None = None) -> torch.Tensor:
    """``a`` where ``mask`` (one flag per problem), else ``b``; into ``out`` if given."""
    if a.dim() > 1:
        mask = mask.reshape(mask.shape + (1,) * (a.dim() - 1))
    return torch.where(mask, a, b) if out is None else torch.where(mask, a, b, out=out)


def _solve(graph: FactorGraph, max_iterations: int, backward_mode: str, o: dict) -> GraphResult:
    if not isinstance(graph, FactorGraph):
        raise TypeError(f"graph must be a FactorGraph, got {type(graph).__name__}")
    # the layout, with the data and noise in the autograd graph unless no gradient is asked
    problem = Problem(graph, attach=backward_mode != "none")
    if backward_mode == "unroll":
        return _iterate(graph, problem, max_iterations, o)[0]
    with torch.no_grad():
        result, x = _iterate(graph, problem, max_iterations, o)
    if backward_mode == "implicit" and torch.is_grad_enabled():
        x = attach_implicit(result.problem, result.system, x, result.report.status)
        result.values = _values(result.problem, graph, x)
    return result


def _iterate(graph: FactorGraph, full: Problem, max_iterations: int, o: dict
             ) -> tuple[GraphResult, list[torch.Tensor]]:
    """The solver's rounds (module docstring; ``o["round"]`` replaces ``_round``, and the
    state's ``lam`` starts at ``o["lambda_initial"]``) on the graph's problems (layout
    ``full``), and the solution in layout order."""
    B = full.B
    system = _system(full, o["linear_solver"], unrolled=full.attach and torch.is_grad_enabled())
    x0 = full.initial(graph)
    lin = linearize(full, x0, system.layout)
    dev, dt = x0[0].device, x0[0].dtype
    finite = torch.isfinite(lin.cost) & _finite_rows(lin.values) & _finite_rows(lin.g)
    status = torch.where(finite, torch.where(lin.cost <= o["error_tol"], int(SolverStatus.CONVERGED),
                                             MAX_ITERATIONS if max_iterations == 0 else RUNNING),
                         int(SolverStatus.NON_FINITE))
    zeros = torch.zeros(B, dtype=dt, device=dev)
    state = _State(torch.arange(B, device=dev), x0, lin, lin.cost,
                   torch.full((B,), o.get("lambda_initial", 0.0), dtype=dt, device=dev),
                   torch.zeros(B, dtype=torch.int64, device=dev), zeros, status)
    out: _State | None = None  # the full batch's results, from the first change of the working set
    initial_cost = lin.cost.clone()
    problem, working = full, system
    eps = torch.finfo(dt).eps
    while True:
        running = state.status == RUNNING
        n_running = int(running.sum())  # the one host read per round
        if n_running < state.rows.numel():
            out = _write_back(out, state)
            if n_running == 0:
                break
            state = state.take(running.nonzero().squeeze(-1))
            problem = full.select(state.rows)
            working = system.select(problem)
        state = o.get("round", _round)(problem, working, state, o, max_iterations, eps)
    assert out is not None  # the loop ends with every problem written back
    system.set_solution(out.lin.values.detach())
    status = out.status
    status = torch.where((status == SolverStatus.CONVERGED) & system.singular(),
                         int(SolverStatus.CONVERGED_RANK_DEFICIENT), status)
    nan = float("nan")
    bad = status == SolverStatus.NON_FINITE
    report = SolverReport(status, out.iterations, torch.where(bad, nan, initial_cost.detach()),
                          torch.where(bad, nan, out.lin.cost.detach()),
                          torch.where(bad, nan, out.step_norm.detach()),
                          torch.where(bad, nan, out.lin.g.detach().norm(dim=-1)))
    return GraphResult(_values(full, graph, out.x), report, full, system), out.x


def _system(problem: Problem, linear_solver: str, unrolled: bool = False) -> LinearSystem:
    """The linear system of ``linear_solver`` (``levenberg_marquardt``'s docstring); "auto" takes
    the dense one where the iterations are differentiated (``unrolled``: every step is a dense
    differentiable solve)."""
    if linear_solver == "block":
        return BlockSparseSystem(problem)
    if linear_solver == "auto" and (problem.B > 1 or problem.D <= SPARSE_ABOVE):
        like = torch.empty(0, dtype=problem.dtype, device=problem.device)
        layout = (block_layout(problem, max_share=BLOCK_BELOW)
                  if uses_block_kernel(like) and not unrolled else None)
        return DenseSystem(problem) if layout is None else BlockSparseSystem(problem, *layout)
    if linear_solver == "dense":
        return DenseSystem(problem)
    return SparseSystem(problem, "auto" if linear_solver in ("auto", "sparse") else linear_solver)


def _write_back(out: _State | None, state: _State) -> _State:
    """Copies the working set's state into the full-batch results (rows ``state.rows``) and
    returns them.  The first call (``out`` None, the working set still the full batch) takes
    the state itself, or a copy where autograd records (the later in-place copies would
    modify tensors that the recorded graph holds)."""
    if out is None:
        if not torch.is_grad_enabled():
            return state
        lin = state.lin
        return _State(state.rows, [v.clone() for v in state.x],
                      Linearization(*[t.clone() for t in (lin.values, lin.g, lin.cost, lin.model_cost)]),
                      state.cost_start, state.lam,
                      *[t.clone() for t in (state.iterations, state.step_norm, state.status)])
    r = state.rows
    for o_v, s_v in zip(out.x, state.x):
        o_v.index_copy_(0, r, s_v)
    for n in ("values", "g", "cost", "model_cost"):
        getattr(out.lin, n).index_copy_(0, r, getattr(state.lin, n))
    for n in ("iterations", "step_norm", "status"):
        getattr(out, n).index_copy_(0, r, getattr(state, n))
    return out


def _round(problem: Problem, system: LinearSystem, s: _State, o: dict, max_iterations: int, eps: float) -> _State:
    """One tryLambda per running problem (module docstring, steps 1-5)."""
    lam = s.lam if o["damped"] else torch.zeros_like(s.lam)
    delta, solved, quad = system.solve(s.lin.values, s.lin.g, lam, o.get("diagonal", False))
    lin_change = -((s.lin.g * delta).sum(-1) + 0.5 * quad)
    x_new, lin_new, new_cost = _trial(problem, system, s, delta)
    success, lam, iterations, status, cost_start, step_norm = round_update(
        s, o, solved, lin_change, quad, new_cost, eps, max_iterations)
    x, lin = _accept(problem, system, s, success, x_new, lin_new, new_cost)
    return _State(s.rows, x, lin, cost_start, lam, iterations, step_norm, status)


def _trial(problem: Problem, system: LinearSystem, s: _State, delta: torch.Tensor
           ) -> tuple[list[torch.Tensor], Linearization | None, torch.Tensor]:
    """The trial point x exp(delta) and its cost.  A batch linearises every trial point at once
    (the Jacobians serve where the step is accepted); one large problem evaluates the cost first
    and linearises only an accepted step (``_accept``)."""
    x_new = problem.retract(s.x, delta)
    if system.cost_first:
        return x_new, None, evaluate_cost(problem, x_new)
    lin_new = linearize(problem, x_new, system.layout)
    return x_new, lin_new, lin_new.cost


def _accept(problem: Problem, system: LinearSystem, s: _State, success: torch.Tensor,
            x_new: list[torch.Tensor], lin_new: Linearization | None, new_cost: torch.Tensor
            ) -> tuple[list[torch.Tensor], Linearization]:
    """The unknowns and linearisation after a trial: the trial's where ``success``, else the
    current ones."""
    if lin_new is None:  # cost_first: one problem
        lin_new = linearize(problem, x_new, system.layout) if bool(success[0]) else s.lin
    x = [_take_trial(success, a, b) for a, b in zip(x_new, s.x)]
    lin = Linearization(*[_take_trial(success, a, b) for a, b in
                          ((lin_new.values, s.lin.values), (lin_new.g, s.lin.g),
                           (new_cost, s.lin.cost), (lin_new.model_cost, s.lin.model_cost))])
    return x, lin


def _take_trial(success: torch.Tensor, trial: torch.Tensor, current: torch.Tensor) -> torch.Tensor:
    """``trial`` where ``success``, else ``current``: written into ``trial`` (the trial's own
    tensor, or ``current`` itself) where nothing records gradients, so that a round allocates
    no further copy of the normal equations."""
    if torch.is_grad_enabled() and (trial.requires_grad or current.requires_grad):
        return _where(success, trial, current)
    return _where(success, trial, current, out=trial)
