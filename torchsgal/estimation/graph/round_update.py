"""A Levenberg-Marquardt or Gauss-Newton round's verdict and bookkeeping, per problem.

After a trial step, each running problem needs GTSAM's verdict on it (``verdict``: accepted,
given up, done, the next lambda; ``levenberg_marquardt``'s module docstring, steps 3-5), the
convergence test of the iteration (``converged``, step 5) and its new status
(``round_status``), iteration count, cost at the iteration's start and step norm.  As tensor
code that is some fifty operations on (B,) tensors per round, each costing more in its call
than in its arithmetic: a fixed cost per round that small batched problems feel.

``torch.ops.torchsgal.lm_round_update(cost, model_cost, new_cost, lin_change, solved, lam,
cost_start, iterations, status, params, codes)`` -> (success, lam, iterations, status,
cost_start) does it in one call: ``params`` = [eps, min_fidelity, lambda_factor, lambda_lower,
lambda_upper, judge_tol, error_tol, rel_tol, abs_tol] and ``codes`` = [damped,
max_iterations]; ``solved`` bool and ``iterations``, ``status`` int64, the rest of the
problems' dtype, all (B,).  Its CPU kernel (``estimation/_native_round.h``) follows the tensor
code (``_tensor_code``, the reference the tests compare it with) operation for operation, with
the parameters rounded to the problems' dtype as torch rounds a Python scalar, so both give the
same values bit for bit.  ``round_update``, the solvers' call, takes the operator where the
kernels run and nothing records (``factor_kernels.usable``), the tensor code elsewhere, and
adds the step norm sqrt(max(delta^T H delta, 0)) by torch (whose vectorised sqrt differs from
C's correctly rounded one in the last bit for some inputs).  No derivative is registered: the
outputs are decisions and counters (the cost that the gradient flows through is ``_accept``'s,
in the solver).
"""
from __future__ import annotations

import math

import torch

from ...functional import native
from ...functional.registration import operator
from .. import dense_solve
from ..solver import SolverStatus
from .factor_kernels import usable

__all__ = ["verdict", "converged", "round_status", "round_update", "lm_round_update"]

CONVERGED, MAX_ITERATIONS = int(SolverStatus.CONVERGED), int(SolverStatus.MAX_ITERATIONS)
DIVERGED = int(SolverStatus.DIVERGED)
N_PARAMS, N_CODES = 9, 2


def verdict(cost: torch.Tensor, model_cost: torch.Tensor, lam: torch.Tensor, o: dict,
            solved: torch.Tensor, lin_change: torch.Tensor, new_cost: torch.Tensor, eps: float,
            judge_tol: float) -> tuple:
    """GTSAM's verdict on one trial step per problem (``levenberg_marquardt``'s module
    docstring, steps 3-5): (success, gave_up, done, lambda for the next trial).  Damped: a step
    is taken where the model predicts a decrease that the cost confirms (fidelity); a cost change
    below ``judge_tol`` times the cost ends the search without a step; lambda grows until
    ``lambda_upper`` (gave up).  Undamped: every finite solved step is taken."""
    if not o["damped"]:
        success = solved & torch.isfinite(new_cost)
        return success, ~success, torch.ones_like(success), torch.zeros_like(lam)
    cost_change = cost - new_cost
    # a success needs lin_change > eps model_cost >= 0 (a sum of squares): a valid step, and the
    # fidelity quotient is read only where lin_change > 0
    success = (solved & (lin_change > eps * model_cost)
               & (cost_change / lin_change > o["min_fidelity"]) & torch.isfinite(new_cost))
    valid = solved & (lin_change >= 0)
    # valid and not a success (a success is valid): valid ^ success
    stop_search = (valid ^ success) & (cost_change.abs() < judge_tol * cost)
    lam_up = lam * o["lambda_factor"]
    lam = torch.where(success, (lam / o["lambda_factor"]).clamp_min(o["lambda_lower"]),
                      torch.where(stop_search, lam, lam_up))
    settled = success | stop_search
    done = settled | (lam_up >= o["lambda_upper"])
    return success, done ^ settled, done, lam  # gave up: done, not settled


def converged(cost_start: torch.Tensor, cost: torch.Tensor, o: dict) -> torch.Tensor:
    """GTSAM's checkConvergence(cost at the iteration's start, cost now), per problem."""
    decrease = cost_start - cost
    return ((cost <= o["error_tol"]) | (decrease <= o["rel_tol"] * cost_start)
            | (decrease <= o["abs_tol"]))


def round_status(status: torch.Tensor, done: torch.Tensor, gave_up: torch.Tensor | None,
                 converged: torch.Tensor, iterations: torch.Tensor, max_iterations: int) -> torch.Tensor:
    """The statuses after a round: where the round is ``done``, DIVERGED where the search gave up
    (``gave_up``; None: never), else CONVERGED where ``converged``, else MAX_ITERATIONS where the
    iterations reached ``max_iterations``; unchanged elsewhere."""
    ended = torch.where(converged, CONVERGED, torch.where(iterations >= max_iterations,
                                                          MAX_ITERATIONS, status))
    if gave_up is not None:
        ended = torch.where(gave_up, DIVERGED, ended)
    return torch.where(done, ended, status)


def _options(params: list[float], codes: list[int]) -> dict:
    eps, min_fidelity, factor, lower, upper, judge_tol, error_tol, rel_tol, abs_tol = params
    return dict(damped=bool(codes[0]), min_fidelity=min_fidelity, lambda_factor=factor,
                lambda_lower=lower, lambda_upper=upper, judge_tol=judge_tol, error_tol=error_tol,
                rel_tol=rel_tol, abs_tol=abs_tol, eps=eps, max_iterations=codes[1])


def _tensor_code(cost, model_cost, new_cost, lin_change, solved, lam, cost_start, iterations,
                 status, params, codes):
    o = _options(params, codes)
    success, gave_up, done, lam = verdict(cost, model_cost, lam, o, solved, lin_change, new_cost,
                                          o["eps"], o["judge_tol"])
    accepted = torch.where(success, new_cost, cost)  # the cost after the round (the solver's _accept)
    iterations = iterations + success  # int64 + bool: int64
    status = round_status(status, done, gave_up, converged(cost_start, accepted, o), iterations,
                          o["max_iterations"])
    return success, lam, iterations, status, torch.where(done, accepted, cost_start)


_SCHEMA = ("(Tensor cost, Tensor model_cost, Tensor new_cost, Tensor lin_change, Tensor solved, "
           "Tensor lam, Tensor cost_start, Tensor iterations, Tensor status, float[] params, "
           "int[] codes) -> (Tensor, Tensor, Tensor, Tensor, Tensor)")


_NAMES = ("cost", "model_cost", "new_cost", "lin_change", "solved", "lam", "cost_start",
          "iterations", "status")


def _check(*args) -> None:
    """The kernel reads (B,) arrays: every tensor's dtype, device and shape checked."""
    cost = args[0]
    if not isinstance(cost, torch.Tensor) or not cost.is_floating_point() or cost.dim() != 1:
        raise TypeError(f"lm_round_update: cost must be a floating tensor (B,), got "
                        f"{tuple(cost.shape) if isinstance(cost, torch.Tensor) else type(cost).__name__}")
    for name, t in zip(_NAMES, args):
        dtype = torch.bool if name == "solved" else torch.int64 if name in ("iterations", "status") \
            else cost.dtype
        if not isinstance(t, torch.Tensor) or t.dtype != dtype or t.device != cost.device \
                or t.shape != cost.shape:
            raise TypeError(f"lm_round_update: {name} must be a {dtype} tensor of shape "
                            f"{tuple(cost.shape)} on {cost.device}, got "
                            + (f"{t.dtype} {tuple(t.shape)} on {t.device}" if isinstance(t, torch.Tensor)
                               else type(t).__name__))
    params, codes = args[9], args[10]
    if len(params) != N_PARAMS or len(codes) != N_CODES:
        raise ValueError(f"lm_round_update: params must have {N_PARAMS} entries and codes "
                         f"{N_CODES}, got {len(params)} and {len(codes)}")
    # finite and within the problems' dtype (torch rounds each to it, as the kernel does)
    largest = torch.finfo(cost.dtype).max
    bad = [p for p in params if not math.isfinite(p) or abs(p) > largest]
    if bad:
        raise ValueError(f"lm_round_update: params must be finite numbers within the range of "
                         f"{cost.dtype}, got {bad[0]}")


@operator("torchsgal::lm_round_update", schema=_SCHEMA)
def lm_round_update(cost: torch.Tensor, model_cost: torch.Tensor, new_cost: torch.Tensor,
                    lin_change: torch.Tensor, solved: torch.Tensor, lam: torch.Tensor,
                    cost_start: torch.Tensor, iterations: torch.Tensor, status: torch.Tensor,
                    params: list[float], codes: list[int]) -> tuple:
    """(success, lam, iterations, status, cost_start) after a round (module docstring)."""
    args = (cost, model_cost, new_cost, lin_change, solved, lam, cost_start, iterations, status,
            params, codes)
    _check(*args)
    return _tensor_code(*args)


@lm_round_update.register_kernel("cpu")
def _kernel(cost, model_cost, new_cost, lin_change, solved, lam, cost_start, iterations, status,
            params, codes):
    args = (cost, model_cost, new_cost, lin_change, solved, lam, cost_start, iterations, status,
            params, codes)
    _check(*args)
    lib = dense_solve._lib
    if lib is None or not native.enabled() or cost.dtype not in (torch.float32, torch.float64):
        return _tensor_code(*args)
    ins = [t.contiguous() for t in args[:9]]  # held while the kernel reads them
    B = cost.shape[0]
    success = torch.empty(B, dtype=torch.bool)
    lam_out, cost_start_out = torch.empty(B, dtype=cost.dtype), torch.empty(B, dtype=cost.dtype)
    iterations_out, status_out = torch.empty(B, dtype=torch.int64), torch.empty(B, dtype=torch.int64)
    lib.lm_round_update(*[t.data_ptr() for t in ins],
                        *[t.data_ptr() for t in (success, lam_out, cost_start_out, iterations_out,
                                                 status_out)],
                        *[float(p) for p in params], B, *codes, CONVERGED, MAX_ITERATIONS, DIVERGED,
                        cost.dtype is torch.float64)
    return success, lam_out, iterations_out, status_out, cost_start_out


@lm_round_update.register_fake
def _fake(cost, model_cost, new_cost, lin_change, solved, lam, cost_start, iterations, status,
          params, codes):
    return (torch.empty_like(solved), torch.empty_like(cost), torch.empty_like(iterations),
            torch.empty_like(status), torch.empty_like(cost))


def round_update(s, o: dict, solved: torch.Tensor, lin_change: torch.Tensor, quad: torch.Tensor,
                 new_cost: torch.Tensor, eps: float, max_iterations: int) -> tuple:
    """(success, lam, iterations, status, cost_start, step_norm) after the trial step of every
    problem of the solver's state ``s`` (its ``lin.cost``, ``lin.model_cost``, ``lam``,
    ``cost_start``, ``iterations``, ``status``; ``quad`` = delta^T H delta), ``o`` the solver's
    options."""
    damped = o["damped"]
    params = [eps, o["min_fidelity"] if damped else 0.0, o["lambda_factor"] if damped else 1.0,
              o["lambda_lower"] if damped else 0.0, o["lambda_upper"] if damped else 0.0,
              o["rel_tol"], o["error_tol"], o["rel_tol"], o["abs_tol"]]
    args = (s.lin.cost, s.lin.model_cost, new_cost, lin_change, solved, s.lam, s.cost_start,
            s.iterations, s.status, params, [int(damped), max_iterations])
    if usable(*args[:4], s.lam, s.cost_start):
        out = torch.ops.torchsgal.lm_round_update(*args)
    else:
        out = _tensor_code(*args)
    return (*out, quad.clamp_min(0).sqrt())
