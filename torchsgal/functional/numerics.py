"""Scalar series of the SO(3) building blocks, with every small-angle threshold in one place.

All closed forms of this package reduce to the family (Barfoot, "Integral Forms", Sec. 3)

    c_m(theta) = sum_k (-1)^k theta^(2k) / (2k + m)!

    c_0 = cos, c_1 = sin/theta, c_2 = (1 - cos)/theta^2, c_3 = (theta - sin)/theta^3, ...
    c_m = (1/(m-2)! - c_(m-2)) / theta^2                       (upward, stable for theta >= 1)
    c_(m-2) = 1/(m-2)! - theta^2 c_m                           (downward, stable for theta < 1)

and its derivative e_m = c_m'(theta)/theta = m c_(m+2) - c_(m+1).

Below ``SERIES_THRESHOLD`` the two highest coefficients come from their Taylor series and the
lower ones from the downward recursion; above it, from sin/cos and the upward recursion.
Both branches are evaluated on safe inputs and merged with ``torch.where``, so values and
gradients stay finite everywhere (the "double where" trick).  Functions take theta^2, never
theta, so nothing differentiates sqrt at zero.
"""
from __future__ import annotations

import math

import torch

# theta below which Taylor series are used (radians).  At theta = 1 the upward recursion
# to c_6 loses < 1e-13 relative; the Taylor series below converge to 1e-17 in TAYLOR_TERMS.
SERIES_THRESHOLD = 1.0
TAYLOR_TERMS = 11
# Highest c_m this module provides.
MAX_ORDER = 6
# theta below which the SO(3) inverse-Jacobian coefficient uses its Taylor series.
JINV_THRESHOLD = 0.5
# cos(theta) below which SO(3) log takes the rotation axis from the symmetric part of C.
LOG_SYMMETRIC_COS = 0.0


def _taylor_c(theta2: torch.Tensor, m: int) -> torch.Tensor:
    """Taylor series of c_m in theta^2 (Horner)."""
    coeffs = [(-1.0) ** k / math.factorial(2 * k + m) for k in range(TAYLOR_TERMS)]
    out = torch.full_like(theta2, coeffs[-1])
    for a in reversed(coeffs[:-1]):
        out = out * theta2 + a
    return out


def select(mask: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``torch.where(mask, a, b)`` for a float 0/1 ``mask`` and finite a, b, as mask*a + (1-mask)*b.

    Exact (x*1 = x, x*0 = 0) and several times cheaper than ``where`` on CPU; the branches are
    always evaluated on safe inputs, so both are finite and so is every gradient.
    """
    return mask * a + (1.0 - mask) * b


def series_coefficients(theta2: torch.Tensor, order: int = MAX_ORDER) -> list[torch.Tensor]:
    """[c_0, ..., c_order] evaluated at theta^2 (any shape), accurate for every theta."""
    if order > MAX_ORDER or order < 1:
        raise ValueError(f"order must be in [1, {MAX_ORDER}], got {order}")
    small = theta2 < SERIES_THRESHOLD**2
    mask = small.to(theta2.dtype)
    t2_small = theta2 * mask  # 0 where the closed form is used
    t2_large = torch.where(small, torch.ones_like(theta2), theta2)

    # Small branch: the two highest by Taylor, the rest downwards.
    lo: list[torch.Tensor | None] = [None] * (order + 1)
    lo[order] = _taylor_c(t2_small, order)
    lo[order - 1] = _taylor_c(t2_small, order - 1)
    for m in range(order - 2, -1, -1):
        lo[m] = 1.0 / math.factorial(m) - t2_small * lo[m + 2]

    # Large branch: sin/cos of the half angle, then upwards.
    theta = torch.sqrt(t2_large)
    inv_t2 = 1.0 / t2_large
    hs, hc = torch.sin(0.5 * theta), torch.cos(0.5 * theta)
    two_hs2 = 2.0 * hs * hs  # 1 - cos, without cancellation
    hi: list[torch.Tensor] = [1.0 - two_hs2, 2.0 * hs * hc / theta]
    if order >= 2:
        hi.append(two_hs2 * inv_t2)
    for m in range(3, order + 1):
        hi.append((1.0 / math.factorial(m - 2) - hi[m - 2]) * inv_t2)

    return [select(mask, a, b) for a, b in zip(lo, hi)]


def series_derivative(c: list[torch.Tensor], m: int) -> torch.Tensor:
    """e_m = c_m'(theta)/theta = m c_(m+2) - c_(m+1) (needs c up to m + 2)."""
    return m * c[m + 2] - c[m + 1]


def jinv_coefficient(theta2: torch.Tensor) -> torch.Tensor:
    """d(theta) = (1 - (theta/2) cot(theta/2)) / theta^2, the u^u^ term of D^-1 in (3.12).

    Written as 1/theta^2 - (1 + cos)/(2 theta sin) = 1/theta^2 - cot(theta/2)/(2 theta) for
    large theta (finite up to, not including, 2 pi); Bernoulli series below JINV_THRESHOLD.
    """
    small = theta2 < JINV_THRESHOLD**2
    mask = small.to(theta2.dtype)
    t2s = theta2 * mask
    t2l = torch.where(small, torch.ones_like(theta2), theta2)
    # (theta/2) cot(theta/2) = sum_n (-1)^n B_2n theta^2n / (2n)!  => d = -sum_{n>=1} ... / theta^2
    bern = [1 / 12, 1 / 720, 1 / 30240, 1 / 1209600, 1 / 47900160, 691 / 1307674368000,
            1 / 74724249600]
    taylor = torch.full_like(t2s, bern[-1])
    for a in reversed(bern[:-1]):
        taylor = taylor * t2s + a
    theta = torch.sqrt(t2l)
    half = 0.5 * theta
    closed = 1.0 / t2l - torch.cos(half) / (2.0 * theta * torch.sin(half))
    return select(mask, taylor, closed)
# sin(theta) below which SO(3) log uses theta/sin(theta) = 1 + theta^2/6 + 7 theta^4/360.
LOG_SIN_TAYLOR = 1e-4
