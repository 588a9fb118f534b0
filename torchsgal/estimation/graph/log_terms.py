"""Residual r = log(E) and both inverse Jacobians J_r^-1(r), J_l^-1(r), for SE(3) and SE(2).

The built-in priors and betweens need, per factor, the log of the error E and the inverse
Jacobians at it.  Where nothing observes the tensors the engine takes them, with the products
around them, from one operator per block (``factor_kernels``); the forms here serve the other
cases (autograd recording, torch.func transforms, other devices, kernels off) and are the
tensor code of those operators.  On SE(3) they are the group's operators (``torchsgal::se3_log``,
``torchsgal::se3_jl_inv``: C kernels on the CPU), r = log(E), J_l^-1(r) and J_r^-1(r) =
J_l^-1(-r), three calls whatever the batch.  Where autograd records (a differentiable solve)
the Jacobians come instead from one pass of whole-batch tensor operations sharing one
evaluation of two scalar coefficients (``_se3_one_pass``, below), whose backward costs about a
third of the operators' (the derivatives of their closed forms); the two agree to rounding
(tests/test_factor_graph_log_terms.py checks both against the closed forms and the series).

SE(3): with xi = [rho, phi] = log(E), theta = |phi|, W = phi^, P = rho^ and ad = ad(xi) =
[[W, P], [0, W]]: ad satisfies its minimal polynomial ad^5 + 2 theta^2 ad^3 + theta^4 ad = 0
(Barfoot, "Integral Forms", (31)), so the Bernoulli series J_l^-1 = sum_n B_n/n! ad^n reduces to

    J_l^-1(xi) = I - ad/2 + alpha ad^2 + beta ad^4,   J_r^-1(xi) = J_l^-1(-xi) = I + ad/2 + ...

whose blocks are, since W phi = 0 and W^3 = -theta^2 W,

    diagonal      I -+ W/2 + d W^2                          (J^-1 of SO(3), Kelly-Giamou (3.12))
    upper right   -+ P/2 + d S - 2 beta (phi . rho) W^2,    S = phi rho^T + rho phi^T - 2 (phi . rho) I

with h = (theta/2) cot(theta/2), d = (1 - h)/theta^2 = alpha - beta theta^2 and
beta = (1 - h + theta h'/2)/theta^4 (the Hermite interpolation of x/2 coth(x/2) at +-i theta).
(The log, rho = J^-1(phi) t, uses the d of ``numerics``.)  Below theta = 1 the two
coefficients come from their Bernoulli series.  SE(2): ``se2_log_jacobians`` (the same d).
"""
from __future__ import annotations

from fractions import Fraction
from math import comb, factorial
from typing import NamedTuple

import torch

from ...functional import se3
from ...functional.blocks import last_axis_dot

__all__ = ["se3_log_jacobians", "se2_log_jacobians", "se3_inverse", "SERIES_THRESHOLD"]

SERIES_THRESHOLD = 1.0  # theta below which d and beta come from their series
SERIES_TERMS = 14  # terms of each series: the last is below 1e-20 of the first at theta = 1


def _bernoulli(n: int) -> list[Fraction]:
    """B_0 .. B_n (B_1 = -1/2), by the recurrence sum_k C(m+1, k) B_k = 0."""
    B = [Fraction(1)]
    for m in range(1, n + 1):
        B.append(-sum((comb(m + 1, k) * B[k] for k in range(m)), Fraction(0)) / (m + 1))
    return B


def _series() -> list[tuple[float, float]]:
    """Coefficients of theta^(2j) in d and beta: with g_k = B_2k/(2k)!,
    d = -sum_k>=1 (-1)^k g_k theta^(2k-2), beta = sum_k>=2 (k-1) (-1)^k g_k theta^(2k-4)."""
    B = _bernoulli(2 * SERIES_TERMS + 2)
    g = [B[2 * k] / factorial(2 * k) for k in range(SERIES_TERMS + 2)]
    return [(float(-(-1) ** (j + 1) * g[j + 1]), float((j + 1) * (-1) ** (j + 2) * g[j + 2]))
            for j in range(SERIES_TERMS)]


_SERIES = _series()
_CONSTANTS: dict[tuple[torch.dtype, torch.device], _Constants] = {}
# ad(xi) from [0, xi, -xi] (indices into that 13-vector, row-major 6 x 6): [[phi^, rho^], [0, phi^]]
_AD_INDEX = (0, 12, 5, 0, 9, 2,
             6, 0, 10, 3, 0, 7,
             11, 4, 0, 8, 1, 0,
             0, 0, 0, 0, 12, 5,
             0, 0, 0, 6, 0, 10,
             0, 0, 0, 11, 4, 0)


class _Constants(NamedTuple):
    series: torch.Tensor  # (SERIES_TERMS, 2): d, beta
    ad_index: torch.Tensor  # (36,)
    eye: torch.Tensor  # (3, 3)


def _constants(like: torch.Tensor) -> _Constants:
    """The constants per dtype and device (tensors: no per-call conversion of Python values)."""
    key = (like.dtype, like.device)
    consts = _CONSTANTS.get(key)
    if consts is None:
        def index(values):
            return torch.tensor(values, dtype=torch.int64, device=like.device)

        consts = _Constants(torch.tensor(_SERIES, dtype=like.dtype, device=like.device),
                            index(_AD_INDEX), torch.eye(3, dtype=like.dtype, device=like.device))
        if type(like) is torch.Tensor and not like.is_inference():
            _CONSTANTS[key] = consts
    return consts


def _coefficients(theta2: torch.Tensor, series: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(d, beta) (...) at theta^2 (module docstring); both branches evaluated on safe inputs
    and selected with ``torch.where`` (finite values and gradients everywhere)."""
    small = theta2 < SERIES_THRESHOLD ** 2
    t2s = torch.where(small, theta2, torch.zeros_like(theta2))
    t2l = torch.where(small, torch.ones_like(theta2), theta2)
    # 1, t2, t2^2, ... by a running product (one kernel), then both series by one product
    powers = torch.cat([torch.ones_like(t2s).unsqueeze(-1),
                        t2s.unsqueeze(-1).expand(t2s.shape + (SERIES_TERMS - 1,))], dim=-1)
    taylor = powers.cumprod(dim=-1) @ series  # (..., 2): d, beta
    theta = t2l.sqrt()
    s, c = torch.sin(0.5 * theta), torch.cos(0.5 * theta)
    h = theta * c / (2.0 * s)  # (theta/2) cot(theta/2)
    d = (1.0 - h) / t2l
    # beta = (1 - theta (theta + sin theta) / (4 (1 - cos theta))) / theta^4, half angles
    beta = (1.0 - theta * (theta + 2.0 * s * c) / (8.0 * s * s)) / (t2l * t2l)
    return torch.where(small, taylor[..., 0], d), torch.where(small, taylor[..., 1], beta)


def se3_log_jacobians(E: torch.Tensor, want_jacobians: bool
                      ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
    """(r = log(E) (..., 6), J_r^-1(r) (..., 6, 6), J_l^-1(r) (..., 6, 6)) for SE(3) matrices
    E (..., 4, 4); the Jacobians are None unless ``want_jacobians``."""
    r = se3.log(E)  # the operator torchsgal::se3_log: its C kernel on the CPU
    if not want_jacobians:
        return r, None, None
    if torch.is_grad_enabled() and E.requires_grad:
        return (r, *_se3_one_pass(r))
    return r, se3.jl_inv(-r), se3.jl_inv(r)


def _se3_one_pass(r: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(J_r^-1(r), J_l^-1(r)) (..., 6, 6) in one pass (module docstring)."""
    k = _constants(r)
    I3 = k.eye
    rho, phi = r[..., :3], r[..., 3:]
    theta2 = last_axis_dot(phi, phi)
    d, beta = _coefficients(theta2, k.series)
    d_, t2_ = d.unsqueeze(-1), theta2.unsqueeze(-1)
    ad = torch.cat([torch.zeros_like(r[..., :1]), r, -r], dim=-1)[..., k.ad_index].unflatten(
        -1, (6, 6))
    pr = last_axis_dot(phi, rho)[..., None, None]
    outer = phi[..., :, None, None] * torch.stack([phi, rho], dim=-2).unsqueeze(-3)  # (..., 3, 2, 3)
    W2 = outer[..., 0, :] - t2_.unsqueeze(-1) * I3  # phi phi^T - theta^2 I = W^2
    S = outer[..., 1, :] + outer[..., 1, :].mT - 2.0 * pr * I3
    diagonal = I3 + d_.unsqueeze(-1) * W2
    upper = d_.unsqueeze(-1) * S - (2.0 * beta[..., None, None]) * pr * W2
    even = r.new_zeros(r.shape[:-1] + (6, 6))
    even[..., :3, :3] = diagonal
    even[..., 3:, 3:] = diagonal
    even[..., :3, 3:] = upper
    half_ad = 0.5 * ad
    return even + half_ad, even - half_ad


def se3_inverse(M: torch.Tensor) -> torch.Tensor:
    """[[C^T, -C^T r], [0, 1]] (..., 4, 4) for SE(3) matrices M = [[C, r], [0, 1]]."""
    Ct = M[..., :3, :3].mT
    out = torch.zeros_like(M)
    out[..., :3, :3] = Ct
    out[..., :3, 3] = -(Ct @ M[..., :3, 3, None]).squeeze(-1)
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
    k = _constants(E)
    theta = torch.atan2(0.5 * (E[..., 1, 0] - E[..., 0, 1]), 0.5 * (E[..., 0, 0] + E[..., 1, 1]))
    theta2 = theta * theta
    d, _ = _coefficients(theta2, k.series)
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
