"""Residual r = log(E) and both inverse Jacobians J_r^-1(r), J_l^-1(r), for SE(3) and SE(2).

The built-in priors and betweens need, per factor, the log of the error E and the inverse
Jacobians at it.  On SE(3) these are the group's operators (``torchsgal::se3_log`` and
``torchsgal::se3_jl_inv``, C kernels on the CPU): r = log(E), J_l^-1(r), and J_r^-1(r) =
J_l^-1(-r), three calls whatever the batch.  On SE(2) one pass of whole-batch tensor operations
(``se2_log_jacobians``): with h = (theta/2) cot(theta/2) and d = (1 - h)/theta^2 (the d of
J^-1 of SO(3), Kelly-Giamou (3.12)); below theta = 1, d comes from its Bernoulli series.
"""
from __future__ import annotations

from fractions import Fraction
from math import comb, factorial

import torch

from ...functional import se3

__all__ = ["se3_log_jacobians", "se2_log_jacobians", "se3_inverse", "SERIES_THRESHOLD"]

SERIES_THRESHOLD = 1.0  # theta below which d comes from its series
SERIES_TERMS = 14  # terms of the series: the last is below 1e-20 of the first at theta = 1


def _bernoulli(n: int) -> list[Fraction]:
    """B_0 .. B_n (B_1 = -1/2), by the recurrence sum_k C(m+1, k) B_k = 0."""
    B = [Fraction(1)]
    for m in range(1, n + 1):
        B.append(-sum((comb(m + 1, k) * B[k] for k in range(m)), Fraction(0)) / (m + 1))
    return B


def _series() -> list[float]:
    """Coefficients of theta^(2j) in d: with g_k = B_2k/(2k)!, d = -sum_k>=1 (-1)^k g_k theta^(2k-2)."""
    B = _bernoulli(2 * SERIES_TERMS)
    return [float(-(-1) ** (j + 1) * B[2 * j + 2] / factorial(2 * j + 2)) for j in range(SERIES_TERMS)]


_SERIES = _series()
_CONSTANTS: dict[tuple[torch.dtype, torch.device], torch.Tensor] = {}


def _constants(like: torch.Tensor) -> torch.Tensor:
    """The series of d (SERIES_TERMS,) per dtype and device (no per-call conversion)."""
    key = (like.dtype, like.device)
    series = _CONSTANTS.get(key)
    if series is None:
        series = torch.tensor(_SERIES, dtype=like.dtype, device=like.device)
        if type(like) is torch.Tensor and not like.is_inference():
            _CONSTANTS[key] = series
    return series


def _coefficient(theta2: torch.Tensor, series: torch.Tensor) -> torch.Tensor:
    """d (...) at theta^2 (module docstring); both branches evaluated on safe inputs and
    selected with ``torch.where`` (finite values and gradients everywhere)."""
    small = theta2 < SERIES_THRESHOLD ** 2
    t2s = torch.where(small, theta2, torch.zeros_like(theta2))
    t2l = torch.where(small, torch.ones_like(theta2), theta2)
    # 1, t2, t2^2, ... by a running product (one kernel), then the series by one product
    powers = torch.cat([torch.ones_like(t2s).unsqueeze(-1),
                        t2s.unsqueeze(-1).expand(t2s.shape + (SERIES_TERMS - 1,))], dim=-1)
    taylor = powers.cumprod(dim=-1) @ series
    theta = t2l.sqrt()
    h = theta * torch.cos(0.5 * theta) / (2.0 * torch.sin(0.5 * theta))  # (theta/2) cot(theta/2)
    return torch.where(small, taylor, (1.0 - h) / t2l)


def se3_log_jacobians(E: torch.Tensor, want_jacobians: bool
                      ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
    """(r = log(E) (..., 6), J_r^-1(r) (..., 6, 6), J_l^-1(r) (..., 6, 6)) for SE(3) matrices
    E (..., 4, 4); the Jacobians are None unless ``want_jacobians``."""
    r = se3.log(E)
    if not want_jacobians:
        return r, None, None
    return r, se3.jl_inv(-r), se3.jl_inv(r)


def se3_inverse(M: torch.Tensor) -> torch.Tensor:
    """[[C^T, -C^T r], [0, 1]] (..., 4, 4) for SE(3) matrices M = [[C, r], [0, 1]]."""
    Ct = M[..., :3, :3].mT
    out = torch.zeros_like(M)
    out[..., :3, :3] = Ct
    out[..., :3, 3] = -(Ct * M[..., None, :3, 3]).sum(-1)
    out[..., 3, 3] = 1.0
    return out


def se2_log_jacobians(E: torch.Tensor, want_jacobians: bool
                      ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
    """(r = log(E) (..., 3), J_r^-1(r), J_l^-1(r) (..., 3, 3)) for SE(2) matrices E (..., 3, 3),
    tangent [rho, theta].  On se(2) ad = [[theta J, -J rho], [0, 0]] satisfies ad^3 + theta^2 ad
    = 0, so J_l^-1 = I - ad/2 + d ad^2 with the d of SO(3) (module docstring) and
    ad^2 = [[-theta^2 I, theta rho], [0, 0]]:

        J_r^-1, J_l^-1 = [[h I +- (theta/2) J, d theta rho -+ (1/2) J rho], [0, 1]],

    h = 1 - d theta^2 = (theta/2) cot(theta/2); rho = V^-1 t = h t - (theta/2) J t (Barfoot,
    "Integral Forms", Sec. 4.5).  The Jacobians are None unless ``want_jacobians``."""
    series = _constants(E)
    theta = torch.atan2(0.5 * (E[..., 1, 0] - E[..., 0, 1]), 0.5 * (E[..., 0, 0] + E[..., 1, 1]))
    theta2 = theta * theta
    d = _coefficient(theta2, series)
    h = 1.0 - d * theta2
    t0, t1 = E[..., 0, 2], E[..., 1, 2]
    half = 0.5 * theta
    rho0, rho1 = h * t0 + half * t1, h * t1 - half * t0  # J t = (-t1, t0)
    r = torch.stack([rho0, rho1, theta], dim=-1)
    if not want_jacobians:
        return r, None, None
    dt = d * theta
    u0, u1 = dt * rho0, dt * rho1  # d theta rho; (1/2) J rho = (-rho1, rho0) / 2
    zero, one = torch.zeros_like(theta), torch.ones_like(theta)
    J = torch.stack([h, -half, u0 + 0.5 * rho1, half, h, u1 - 0.5 * rho0, zero, zero, one,
                     h, half, u0 - 0.5 * rho1, -half, h, u1 + 0.5 * rho0, zero, zero, one],
                    dim=-1).unflatten(-1, (2, 3, 3))
    return r, J[..., 0, :, :], J[..., 1, :, :]
