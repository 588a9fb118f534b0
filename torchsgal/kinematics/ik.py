"""Batched inverse kinematics on the library's Gauss-Newton / Levenberg-Marquardt solver.

Each (target, seed) pair is one problem of ``torchsgal.estimation.gauss_newton``.  The
residual of a problem is the position error and the rotation error in the link's frame,

    r = (p(q) - p*,  w log(R*^T R(q)))          (w = ``orientation_weight``, metres per radian)

(either part alone for position-only or orientation-only targets), with the analytic Jacobian
(J_lin, w J_r^-1(log(R*^T R)) R^T J_ang) from the chain's geometric Jacobian.  Joint limits
are kept by a bounded parameterisation, so every iterate is within them: a joint with both
limits is q = c + h sin(u), c and h the middle and half-range of its limits; one with a lower
limit only is q = lower + sqrt(u^2 + 1) - 1, with an upper only q = upper - sqrt(u^2 + 1) + 1
(MINUIT's transformations); one with lower == upper is held there.  A first stage adds the
residual ``centering`` (q - c) / h of the joints with both limits, which keeps the iterates away
from the limits (where a bounded joint's local minima lie); the second solves the pose alone
from its result.

Success is decided by the pose error against the user's tolerances, never by the solver's
status: a redundant arm (7 joints for a 6-dof pose) has a rank-deficient information matrix
at every solution, which the solver reports as SINGULAR although the target is reached.
Among the seeds of a target the one with the smallest error (relative to the tolerances) is
returned.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..estimation import gauss_newton
from ..functional import checks
from ..functional._blocking import values_readable
from ..groups import SE3, SO3
from .chain import KinematicChain

_COST_TOL = 1e-10  # relative cost decrease below which a problem has converged
_CENTER_ITERATIONS = 20


@dataclass
class IKResult:
    """Inverse-kinematics solutions for a batch of B targets (every field has batch (B,)).

    q               (B, n) joint positions, the best seed's solution (within the joint limits
                    when ``respect_limits``).
    success         bool: the position error is at most ``position_tol`` and the rotation
                    error at most ``rotation_tol`` (those that were asked for).
    position_error  |p(q) - p*| in metres (0 for orientation-only targets).
    rotation_error  the angle of R*^T R(q) in radians (0 for position-only targets).
    seed            int64, the index of the chosen seed.
    iterations      int64, the solver's steps for the chosen seed.
    solver_status   int64 ``SolverStatus`` code of the chosen seed, for information only:
                    SINGULAR is the normal code of a redundant arm that reached its target.
    """

    q: torch.Tensor
    success: torch.Tensor
    position_error: torch.Tensor
    rotation_error: torch.Tensor
    seed: torch.Tensor
    iterations: torch.Tensor
    solver_status: torch.Tensor

    @property
    def success_rate(self) -> float:
        """The fraction of targets solved (one host read)."""
        return self.success.to(torch.float64).mean().item()


def _targets(chain: KinematicChain, target, position: bool, orientation: bool):
    """(B, 3) positions and (B, 3, 3) rotations (None where not used) of the targets."""
    if isinstance(target, SE3):
        if target.batch_shape == ():
            target = target.unsqueeze(0)
        if len(target.batch_shape) != 1:
            raise ValueError(f"target must have batch shape (B,), got {tuple(target.batch_shape)}")
        m = target.as_matrix()
        _rigid(chain, m)
        R, p = m[:, :3, :3], m[:, :3, 3]
    elif isinstance(target, torch.Tensor):
        checks.floating(target, "target")
        if target.dim() in (2, 3) and tuple(target.shape[-2:]) == (4, 4):
            m = target.reshape(-1, 4, 4)
            _rigid(chain, m)
            R, p = m[:, :3, :3], m[:, :3, 3]
        elif target.dim() > 3 and tuple(target.shape[-2:]) == (4, 4):
            raise ValueError(f"target must be a (4, 4) or (B, 4, 4) tensor (one batch axis), "
                             f"got shape {tuple(target.shape)}")
        elif target.shape[-1:] == (3,) and target.dim() <= 2:
            if orientation:
                raise ValueError("target is a position (..., 3): pass orientation=False for "
                                 "position-only targets, or give SE3 poses")
            p, R = target.reshape(-1, 3), None
        else:
            raise ValueError(f"target must be SE3 poses (B,), a (B, 4, 4) tensor or positions "
                             f"(B, 3), got a tensor of shape {tuple(target.shape)}")
    else:
        raise TypeError(f"target must be an SE3 element or a tensor, got {type(target).__name__}")
    ref = chain.lower
    checks.same_device_dtype(**{f"the chain {chain.name!r}": ref, "target": p})
    if R is None:  # poses were checked finite (and rigid) by _rigid
        _finite(p, "target")
    return p, R


def _rigid(chain: KinematicChain, m: torch.Tensor) -> None:
    """ValueError naming ``target`` unless every (4, 4) of m is a rigid transform (the check of
    ``SE3.from_matrix(check=True)``, default tolerance; where the values can be read)."""
    checks.same_device_dtype(**{f"the chain {chain.name!r}": chain.lower, "target": m})
    try:
        SE3.from_matrix(m, check=True)
    except ValueError as err:
        raise ValueError(f"target must be rigid transforms [[R, p], [0, 1]]: {err}") from None


def _finite(x: torch.Tensor, name: str) -> None:
    """ValueError naming ``name`` where x has a NaN or an infinite entry (one host read, at
    validation; skipped where the values cannot be read)."""
    if values_readable(x) and not bool(torch.isfinite(x).all()):
        raise ValueError(f"{name} must be finite, got non-finite entries in a tensor of shape "
                         f"{tuple(x.shape)}")


def _seeds(chain: KinematicChain, q0, B: int, num_seeds: int | None, generator) -> torch.Tensor:
    """(B, S, n) starting joint positions (the reading of q0 in ``inverse_kinematics``)."""
    n = chain.n_joints
    if q0 is None:
        return chain.random_configuration((B, 8 if num_seeds is None else num_seeds),
                                          generator=generator)
    q0 = chain._joint_tensor(q0, "q0")
    _finite(q0, "q0")
    given = tuple(q0.shape)
    if q0.dim() == 1:
        q0 = q0.expand(B, 1, n)
    elif q0.dim() == 2:
        per_target = q0.shape[0] == B and (num_seeds is None or num_seeds == 1)
        q0 = q0[:, None, :] if per_target else q0.expand(B, *q0.shape)
    elif q0.dim() != 3 or q0.shape[0] != B:
        raise ValueError(f"q0 must be (n,), (S, n), (B, n) or (B, S, n) with B = {B} targets, "
                         f"got {tuple(q0.shape)}")
    if num_seeds is not None and num_seeds != q0.shape[1]:
        raise ValueError(f"num_seeds ({num_seeds}) conflicts with q0 of shape "
                         f"{given}: q0 gives {q0.shape[1]} seed(s) per "
                         f"target for B = {B} targets; leave num_seeds=None with q0")
    return q0


def _sqrt_inv(x: torch.Tensor) -> torch.Tensor:
    """u >= 0 with sqrt(u^2 + 1) - 1 = x, for x >= 0: sqrt(x (x + 2))."""
    return torch.sqrt(x) * torch.sqrt(x + 2.0)


def inverse_kinematics(
    chain: KinematicChain,
    target,
    *,
    q0: torch.Tensor | None = None,
    num_seeds: int | None = None,
    link: str | None = None,
    position: bool = True,
    orientation: bool = True,
    orientation_weight: float = 1.0,
    position_tol: float = 1e-4,
    rotation_tol: float = 1e-3,
    respect_limits: bool = True,
    centering: float = 0.5,
    max_iterations: int = 50,
    damping: float = 1e-3,
    generator: torch.Generator | None = None,
) -> IKResult:
    """Joint positions that put ``link`` (default the end link with the tool) at ``target``.

    Args:
        chain: a :class:`KinematicChain`.
        target: SE3 poses of batch (B,) (or one pose), a (B, 4, 4) or (4, 4) tensor, or
            positions (B, 3) with ``orientation=False``; in the chain's base frame, dtype and
            device.  Poses must be rigid transforms (``SE3.from_matrix(check=True)``,
            ValueError naming ``target``), positions finite (ValueError naming ``target``).
        q0: starting joint positions: (n,) (one seed for every target), (B, n) (one seed per
            target), (S, n) (S seeds shared by all targets) or (B, S, n).  A 2-D q0 with
            q0.shape[0] == B is read as (B, n), one seed per target, unless ``num_seeds``
            equals B (> 1), which selects the shared (S, n) reading; (B, S, n) is never
            ambiguous.  Finite (ValueError naming ``q0``).
        num_seeds: the number of random seeds per target within the limits (default 8) when
            q0 is None.  With q0 it is not needed (None); if given it must equal the number of
            seeds per target of q0's reading (ValueError otherwise).
        position, orientation: which parts of the pose to reach (at least one).
        orientation_weight: metres per radian in the residual (module doc).
        position_tol (m), rotation_tol (rad): the errors below which a target is solved.
        respect_limits: keep every joint within its finite limits, one-sided ones included,
            and a joint with lower == upper at that value (bounded parameterisation).
        centering: weight of a first stage (20 iterations) whose residual also pulls the
            joints with both limits towards the middle of their range, (q - mid) / half: it
            keeps the iterates away from the limits, where a bounded joint's local minima are;
            the second stage solves the pose alone from there.  0 skips it.
        max_iterations, damping: of the Levenberg-Marquardt solver.
        generator: for the random seeds.
    Returns an :class:`IKResult`.  Not differentiable.
    """
    if not isinstance(chain, KinematicChain):
        raise TypeError(f"chain must be a KinematicChain, got {type(chain).__name__}")
    position = checks.boolean(position, "position")
    orientation = checks.boolean(orientation, "orientation")
    respect_limits = checks.boolean(respect_limits, "respect_limits")
    if not (position or orientation):
        raise ValueError("position and orientation are both False: nothing to reach")
    w = checks.finite_number(orientation_weight, "orientation_weight", "> 0")
    centering = checks.finite_number(centering, "centering", ">= 0")
    pos_tol = checks.finite_number(position_tol, "position_tol", "> 0")
    rot_tol = checks.finite_number(rotation_tol, "rotation_tol", "> 0")
    if num_seeds is not None:
        num_seeds = checks.integer(num_seeds, "num_seeds", 1)
    if generator is not None and not isinstance(generator, torch.Generator):
        raise TypeError(f"generator must be None or a torch.Generator, got {type(generator).__name__}")
    link = chain._one_link(link)
    p_t, R_t = _targets(chain, target, position, orientation)
    B, n = p_t.shape[0], chain.n_joints
    seeds = _seeds(chain, q0, B, num_seeds, generator)
    S = seeds.shape[1]
    q_start = seeds.reshape(B * S, n)
    p_rep = p_t.repeat_interleave(S, dim=0)
    R_rep = None if R_t is None else R_t.repeat_interleave(S, dim=0)

    lo, hi = chain.lower, chain.upper
    has_lo, has_hi = torch.isfinite(lo), torch.isfinite(hi)
    limited = has_lo & has_hi & (hi > lo)  # two-sided: mid + half sin(u)
    fixed = has_lo & has_hi & (hi == lo)  # q = lower = upper
    lower_only, upper_only = has_lo & ~has_hi, has_hi & ~has_lo
    mid = torch.where(limited, (lo + hi) / 2, 0.0)
    half = torch.where(limited, (hi - lo) / 2, 1.0)
    lo0, hi0 = torch.where(has_lo, lo, 0.0), torch.where(has_hi, hi, 0.0)  # no inf arithmetic
    none = torch.zeros_like(limited)
    one = torch.ones_like(lo)
    kinds = (limited, fixed, lower_only, upper_only) if respect_limits else (none,) * 4

    def solve(q_init, iterations, centering=0.0):
        """Levenberg-Marquardt from q_init (B S, n) over u (module doc); ``centering`` > 0 adds
        the residual centering (q - mid) / half of the two-sided limited joints."""
        two, held, low, up = kinds

        def to_q(u):
            q = torch.where(two, mid + half * torch.sin(u), u)
            r = u * (u / (torch.hypot(u, one) + 1.0))  # sqrt(u^2 + 1) - 1 without cancellation
            q = torch.where(low, lo0 + r, q)
            q = torch.where(up, hi0 - r, q)
            return torch.where(held, lo0, q)

        # strictly inside the limits: at a limit dq/du = 0 would freeze the joint there
        ratio = ((q_init - mid) / half).clamp(-1.0 + 1e-6, 1.0 - 1e-6)
        u0 = torch.where(two, torch.asin(ratio), q_init)
        u0 = torch.where(low, _sqrt_inv((q_init - lo0).clamp_min(1e-6)), u0)
        u0 = torch.where(up, _sqrt_inv((hi0 - q_init).clamp_min(1e-6)), u0)
        u0 = torch.where(held, 0.0, u0)

        def parts(u):
            q = to_q(u)
            pose, J = chain.pose_and_jacobian(q, link=link, frame="base")
            dq_du = torch.where(two, half * torch.cos(u), 1.0)
            dr = u / torch.hypot(u, one)
            dq_du = torch.where(low, dr, dq_du)
            dq_du = torch.where(up, -dr, dq_du)
            dq_du = torch.where(held, 0.0, dq_du)
            res, jac = [], []
            if position:
                res.append(pose.position() - p_rep)
                jac.append(J[..., :3, :])
            if orientation:
                R = pose.rotation()
                phi = SO3.from_matrix(R_rep.transpose(-1, -2) @ R).log()
                Jb = R.transpose(-1, -2) @ J[..., 3:, :]  # body angular Jacobian
                res.append(w * phi)
                jac.append(w * (SO3.jr_inv(phi) @ Jb))
            if centering > 0:
                k = centering * limited.to(q.dtype)
                res.append(k * (q - mid) / half)
                jac.append(torch.diag_embed((k / half).expand_as(q)))
            return torch.cat(res, dim=-1), torch.cat(jac, dim=-2) * dq_du[..., None, :]

        cache = {}

        def residual(u):
            r, J = parts(u)
            cache["u"], cache["J"] = u, J
            return r

        def jacobian(u):
            return cache["J"] if cache.get("u") is u else parts(u)[1]

        sol = gauss_newton(residual, u0, jacobian=jacobian, max_iterations=iterations,
                           damping=damping, step_tol=1e-10, cost_tol=_COST_TOL)
        q = to_q(sol.x)
        return (q.clamp(lo, hi) if respect_limits else q), sol.report  # clamp: rounding only

    if centering > 0:
        q_start, _ = solve(q_start, _CENTER_ITERATIONS, centering)
    q_sol, report = solve(q_start, max_iterations)
    with torch.no_grad():
        q = q_sol
        pose = chain.pose(q, link=link)
        zero = torch.zeros(B * S, dtype=q.dtype, device=q.device)
        e_pos = (pose.position() - p_rep).norm(dim=-1) if position else zero
        if orientation and R_rep is not None:  # R_rep is None only for position targets
            e_rot = SO3.from_matrix(R_rep.transpose(-1, -2) @ pose.rotation()).log().norm(dim=-1)
        else:
            e_rot = zero
        score = torch.maximum(e_pos / pos_tol, e_rot / rot_tol)
        score = torch.where(torch.isfinite(score), score, math.inf).reshape(B, S)
        best = score.argmin(dim=1)
        pick = best[:, None]

        def choose(x):
            x = x.reshape(B, S, *x.shape[1:])
            idx = pick.reshape(B, 1, *([1] * (x.dim() - 2))).expand(B, 1, *x.shape[2:])
            return x.gather(1, idx)[:, 0]

        q_best = choose(q)
        return IKResult(q=q_best, success=score.gather(1, pick)[:, 0] <= 1.0,
                        position_error=choose(e_pos), rotation_error=choose(e_rot), seed=best,
                        iterations=choose(report.iterations),
                        solver_status=choose(report.status))
