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
one host read per round (how many problems still run).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from ...functional import checks
from ...groups import LieGroup
from ..solver import SolverReport, SolverStatus, information_is_singular
from .graph import FactorGraph
from .linearize import Linearization, Problem, dense, linearize

__all__ = ["GraphResult", "levenberg_marquardt", "gauss_newton"]

RUNNING = int(SolverStatus.RUNNING)


@dataclass
class GraphResult:
    """values       {name: value at the solution}, in the form the graph was given (group
                    elements of batch (N,) or (B, N), tensors (N, k) or (B, N, k)).
    report          ``SolverReport`` (per problem: status, iterations, costs, norms).
    information     (B, D, D) H = J~^T J~ at the solution (dense path), the layout of
                    ``Problem`` (variables in insertion order, element-major).
    """

    values: dict
    report: SolverReport
    information: torch.Tensor
    problem: Problem

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
        index = torch.as_tensor(index, dtype=torch.int64, device=p.device).reshape(-1)
        H = self.information
        singular = information_is_singular(H)
        eye = torch.eye(H.shape[-1], dtype=H.dtype, device=H.device)
        L, bad = torch.linalg.cholesky_ex(torch.where(singular[:, None, None], eye, H))
        P = torch.cholesky_inverse(L)
        pos = info.offset + index[:, None] * info.dof + torch.arange(info.dof, device=p.device)
        blocks = P[:, pos[:, :, None], pos[:, None, :]]  # (B, K, dof, dof)
        nan = (singular | (bad != 0))[:, None, None, None]
        blocks = torch.where(nan, torch.full_like(blocks, float("nan")), blocks)
        return blocks if p.batched else blocks[0]


def _values(problem: Problem, graph: FactorGraph, x: list[torch.Tensor]) -> dict:
    out = {}
    for info, xv in zip(problem.variables, x):
        given = graph.variables[info.name]
        leaf = xv if problem.batched else xv[0]
        out[info.name] = type(given)._new(leaf) if isinstance(given, LieGroup) else leaf
    return out


def _check(max_iterations, lambda_initial, lambda_factor, lambda_upper, lambda_lower,
           min_model_fidelity, relative_error_tol, absolute_error_tol, error_tol, diagonal_damping):
    checks.integer(max_iterations, "max_iterations", 0)
    checks.finite_number(lambda_initial, "lambda_initial", "> 0")
    checks.finite_number(lambda_factor, "lambda_factor", "> 0")
    if lambda_factor <= 1:
        raise ValueError(f"lambda_factor must be > 1, got {lambda_factor}")
    checks.finite_number(lambda_upper, "lambda_upper", "> 0")
    checks.finite_number(lambda_lower, "lambda_lower", ">= 0")
    checks.finite_number(min_model_fidelity, "min_model_fidelity")
    checks.finite_number(relative_error_tol, "relative_error_tol", ">= 0")
    checks.finite_number(absolute_error_tol, "absolute_error_tol", ">= 0")
    checks.finite_number(error_tol, "error_tol", ">= 0")
    checks.boolean(diagonal_damping, "diagonal_damping")


def levenberg_marquardt(graph: FactorGraph, max_iterations: int = 100, *,
                        lambda_initial: float = 1e-5, lambda_factor: float = 10.0,
                        lambda_upper: float = 1e5, lambda_lower: float = 0.0,
                        min_model_fidelity: float = 1e-3, diagonal_damping: bool = False,
                        relative_error_tol: float = 1e-5, absolute_error_tol: float = 1e-5,
                        error_tol: float = 0.0) -> GraphResult:
    """Levenberg-Marquardt with GTSAM's trust-region rules and defaults (module docstring),
    for every problem of the graph's batch.  Returns a ``GraphResult``."""
    _check(max_iterations, lambda_initial, lambda_factor, lambda_upper, lambda_lower,
           min_model_fidelity, relative_error_tol, absolute_error_tol, error_tol, diagonal_damping)
    return _solve(graph, max_iterations, dict(
        damped=True, lambda_initial=lambda_initial, lambda_factor=lambda_factor,
        lambda_upper=lambda_upper, lambda_lower=lambda_lower, min_fidelity=min_model_fidelity,
        diagonal=diagonal_damping, rel_tol=relative_error_tol, abs_tol=absolute_error_tol,
        error_tol=error_tol))


def gauss_newton(graph: FactorGraph, max_iterations: int = 100, *,
                 relative_error_tol: float = 1e-5, absolute_error_tol: float = 1e-5,
                 error_tol: float = 0.0) -> GraphResult:
    """Gauss-Newton (GTSAM's ``GaussNewtonOptimizer``): every solvable step is taken; an
    unsolvable (singular) system stops the problem as DIVERGED.  Convergence as for LM."""
    _check(max_iterations, 1.0, 10.0, 1.0, 0.0, 0.0, relative_error_tol, absolute_error_tol,
           error_tol, False)
    return _solve(graph, max_iterations, dict(
        damped=False, rel_tol=relative_error_tol, abs_tol=absolute_error_tol, error_tol=error_tol))


@dataclass
class _State:
    """The working set's per-problem state (all leading axes = active problems)."""

    rows: torch.Tensor  # indices into the full batch
    x: list[torch.Tensor]
    lin: Linearization
    H: torch.Tensor
    cost: torch.Tensor
    cost_start: torch.Tensor  # cost at the start of the current iteration
    lam: torch.Tensor
    iterations: torch.Tensor
    step_norm: torch.Tensor
    status: torch.Tensor

    def take(self, keep: torch.Tensor) -> "_State":
        lin = Linearization(self.lin.values.index_select(0, keep), self.lin.g.index_select(0, keep),
                            self.lin.cost.index_select(0, keep),
                            self.lin.model_cost.index_select(0, keep))
        return _State(self.rows.index_select(0, keep), [v.index_select(0, keep) for v in self.x],
                      lin, self.H.index_select(0, keep),
                      *[getattr(self, n).index_select(0, keep) for n in
                        ("cost", "cost_start", "lam", "iterations", "step_norm", "status")])


def _where(mask: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return torch.where(mask.reshape(mask.shape + (1,) * (a.dim() - 1)), a, b)


def _solve(graph: FactorGraph, max_iterations: int, o: dict) -> GraphResult:
    if not isinstance(graph, FactorGraph):
        raise TypeError(f"graph must be a FactorGraph, got {type(graph).__name__}")
    full = Problem(graph)
    B, D = full.B, full.D
    x0 = full.initial(graph)
    lin = linearize(full, x0)
    H = dense(full, lin.values)
    dev, dt = x0[0].device, x0[0].dtype
    finite = torch.isfinite(lin.cost) & torch.isfinite(H).all(dim=(-1, -2)) & torch.isfinite(
        lin.g).all(dim=-1)
    status = torch.full((B,), RUNNING, dtype=torch.int64, device=dev)
    status = torch.where(finite, status, torch.full_like(status, SolverStatus.NON_FINITE))
    status = torch.where(finite & (lin.cost <= o["error_tol"]),
                         torch.full_like(status, SolverStatus.CONVERGED), status)
    if max_iterations == 0:
        status = torch.where(status == RUNNING, torch.full_like(status, SolverStatus.MAX_ITERATIONS),
                             status)
    lam0 = o.get("lambda_initial", 0.0)
    state = _State(torch.arange(B, device=dev), x0, lin, H, lin.cost, lin.cost,
                   torch.full((B,), lam0, dtype=dt, device=dev),
                   torch.zeros(B, dtype=torch.int64, device=dev), torch.zeros(B, dtype=dt, device=dev),
                   status)
    out_lin = Linearization(lin.values, lin.g.clone(), lin.cost, lin.model_cost)
    out = _State(state.rows, [v.clone() for v in x0], out_lin, H.clone(), lin.cost.clone(),
                 lin.cost.clone(), state.lam.clone(), state.iterations.clone(),
                 state.step_norm.clone(), status.clone())
    initial_cost = lin.cost.clone()
    problem = full
    eye = torch.eye(D, dtype=dt, device=dev)
    eps = torch.finfo(dt).eps
    while True:
        running = state.status == RUNNING
        n_running = int(running.sum())  # the one host read per round
        if n_running < state.rows.numel():
            _write_back(out, state)
            if n_running == 0:
                break
            keep = running.nonzero().squeeze(-1)
            state = state.take(keep)
            problem = full.select(state.rows)
        state = _round(problem, state, o, max_iterations, eye, eps)
    singular = information_is_singular(out.H)
    status = out.status
    status = torch.where((status == SolverStatus.CONVERGED) & singular,
                         torch.full_like(status, SolverStatus.CONVERGED_RANK_DEFICIENT), status)
    nan = torch.full_like(initial_cost, float("nan"))
    bad = status == SolverStatus.NON_FINITE
    report = SolverReport(status, out.iterations, torch.where(bad, nan, initial_cost),
                          torch.where(bad, nan, out.cost), torch.where(bad, nan, out.step_norm),
                          torch.where(bad, nan, out.lin.g.norm(dim=-1)))
    return GraphResult(_values(full, graph, out.x), report, out.H, full)


def _write_back(out: _State, state: _State) -> None:
    """Copies the working set's state into the full-batch results (rows ``state.rows``)."""
    r = state.rows
    for o_v, s_v in zip(out.x, state.x):
        o_v.index_copy_(0, r, s_v)
    out.H.index_copy_(0, r, state.H)
    out.lin.g.index_copy_(0, r, state.lin.g)
    for n in ("cost", "iterations", "step_norm", "status"):
        getattr(out, n).index_copy_(0, r, getattr(state, n))


def _round(problem: Problem, s: _State, o: dict, max_iterations: int, eye: torch.Tensor,
           eps: float) -> _State:
    """One tryLambda per running problem (module docstring, steps 1-5)."""
    H, g = s.H, s.lin.g
    if o["damped"]:
        if o["diagonal"]:
            damp = H.diagonal(dim1=-2, dim2=-1).clamp(1e-6, 1e32)
            Hd = H + torch.diag_embed(s.lam[:, None] * damp)
        else:
            Hd = H + s.lam[:, None, None] * eye
    else:
        Hd = H
    L, info = torch.linalg.cholesky_ex(Hd)
    solved = info == 0
    delta = torch.cholesky_solve(-g.unsqueeze(-1), L).squeeze(-1)
    delta = torch.where(solved[:, None] & torch.isfinite(delta), delta, torch.zeros_like(delta))
    Hdelta = (H @ delta.unsqueeze(-1)).squeeze(-1)
    quad = (delta * Hdelta).sum(-1)
    lin_change = -((g * delta).sum(-1) + 0.5 * quad)
    x_new = problem.retract(s.x, delta)
    lin_new = linearize(problem, x_new)
    new_cost = lin_new.cost
    cost_change = s.cost - new_cost
    if o["damped"]:
        valid = solved & (lin_change >= 0)
        fidelity = cost_change / torch.where(lin_change > 0, lin_change, torch.ones_like(lin_change))
        success = valid & (lin_change > eps * s.lin.model_cost) & (fidelity > o["min_fidelity"])
        success = success & torch.isfinite(new_cost)
        stop_search = valid & ~success & (cost_change.abs() < o["rel_tol"] * s.cost)
        lam_up = s.lam * o["lambda_factor"]
        lam = torch.where(success, (s.lam / o["lambda_factor"]).clamp_min(o["lambda_lower"]),
                          torch.where(stop_search, s.lam, lam_up))
        gave_up = ~success & ~stop_search & (lam_up >= o["lambda_upper"])
        done = success | stop_search | gave_up
    else:
        success = solved & torch.isfinite(new_cost)
        gave_up = ~success
        lam, done = s.lam, torch.ones_like(success)
    x = [_where(success, a, b) for a, b in zip(x_new, s.x)]
    H_new = dense(problem, lin_new.values)
    lin = Linearization(_where(success, lin_new.values, s.lin.values),
                        _where(success, lin_new.g, s.lin.g), _where(success, new_cost, s.cost),
                        _where(success, lin_new.model_cost, s.lin.model_cost))
    H = _where(success, H_new, H)
    cost = lin.cost
    iterations = s.iterations + success.to(torch.int64)
    # checkConvergence(cost_start, cost) after a finished iteration
    decrease = s.cost_start - cost
    converged = (cost <= o["error_tol"]) | (decrease <= o["rel_tol"] * s.cost_start) | (
        decrease <= o["abs_tol"])
    status = s.status
    status = torch.where(done & gave_up, torch.full_like(status, SolverStatus.DIVERGED), status)
    status = torch.where(done & ~gave_up & converged,
                         torch.full_like(status, SolverStatus.CONVERGED), status)
    status = torch.where(done & ~gave_up & ~converged & (iterations >= max_iterations),
                         torch.full_like(status, SolverStatus.MAX_ITERATIONS), status)
    cost_start = torch.where(done, cost, s.cost_start)
    step_norm = quad.clamp_min(0).sqrt()
    return _State(s.rows, x, lin, H, cost, cost_start, lam, iterations, step_norm, status)
