"""Scalar series of the SO(3) building blocks, with every small-angle threshold in one place.

All closed forms of this package reduce to the family (Barfoot, "Integral Forms", Sec. 3)

    c_m(theta) = sum_k (-1)^k theta^(2k) / (2k + m)!

    c_0 = cos, c_1 = sin/theta, c_2 = (1 - cos)/theta^2, c_3 = (theta - sin)/theta^3, ...
    c_m = (1/(m-2)! - c_(m-2)) / theta^2                       (upward, stable for theta >= 1)
    c_(m-2) = 1/(m-2)! - theta^2 c_m                           (downward, stable for theta < 1)

and its derivative e_m = c_m'(theta)/theta = m c_(m+2) - c_(m+1).

Below ``SERIES_THRESHOLD`` the two highest coefficients come from their Taylor series and the
lower ones from the downward recursion; above it, from sin/cos and the upward recursion.
Both branches are evaluated on safe inputs and merged with exact 0/1 masks (``select``), so
values and gradients stay finite everywhere (the "double where" trick).  Functions take
theta^2, never theta, so nothing differentiates sqrt at zero.  theta^2 overflows (and the
results are NaN) for rotation vectors longer than sqrt(finfo.max): 1.8e19 in float32, 1.3e154
in float64.
"""
from __future__ import annotations

import math
from typing import cast

import torch

from .._compat import fake_tensor_mode_active, mark_compile_constant
from . import checks
from ._blocking import _is_wrapped, is_compiling

# theta below which Taylor series are used (radians).  At theta = 1 the upward recursion
# to c_6 loses < 1e-13 relative; the Taylor series below converge to 1e-17 in TAYLOR_TERMS.
SERIES_THRESHOLD = 1.0
TAYLOR_TERMS = 11
# Highest c_m this module provides.
MAX_ORDER = 6
# theta below which the SO(3) inverse-Jacobian coefficient uses its Taylor series.
JINV_THRESHOLD = 0.5
# Series of jinv_coefficient below JINV_THRESHOLD: -B_2n / (2n)! for n >= 1 (in theta^2).
JINV_SERIES = (1 / 12, 1 / 720, 1 / 30240, 1 / 1209600, 1 / 47900160, 691 / 1307674368000,
               1 / 74724249600)
# cos(theta) below which SO(3) log takes the rotation axis from the symmetric part of C.
LOG_SYMMETRIC_COS = 0.0


def _constant(value: float):
    """A getter for ``value`` that torch.compile folds into its graph as a constant.

    The closed forms compare against the thresholds of this module through such getters, never
    by reading the module-level float: under torch.compile(dynamic=True) a float global becomes
    a symbolic value, and dynamo (torch 2.13) fails when one is shared by the graphs of two
    custom autograd.Functions (exp's forward and log's backward).  tests/test_autograd.py
    compiles with dynamic=True.

    The mark is that of ``torch.compiler.assume_constant_result`` (``_compat.mark_compile_constant``);
    tests/test_autograd.py checks that both agree.
    """
    return mark_compile_constant(lambda: value)


series_threshold_sq = _constant(SERIES_THRESHOLD**2)
jinv_threshold_sq = _constant(JINV_THRESHOLD**2)
log_symmetric_cos = _constant(LOG_SYMMETRIC_COS)


def select(mask: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``torch.where(mask, a, b)`` for a float 0/1 ``mask`` and finite a, b, as ``lerp(b, a, mask)``.

    Exact: torch's lerp evaluates b + w (a - b) for |w| < 0.5 and a - (a - b)(1 - w) otherwise,
    so w = 0 gives b and w = 1 gives a.  One kernel, several times cheaper than ``where`` on CPU
    (which is not vectorised there); the branches are always evaluated on safe inputs, so both
    are finite and so is every gradient.  ``mask`` broadcasts against a and b.
    """
    return torch.lerp(b, a, mask)


_CONSTANTS: dict = {}


def fresh_constants(device: torch.device) -> bool:
    """Whether constant tensors must be built anew rather than taken from (or put in) a cache:
    under a fake-tensor trace (FakeTensorMode, outside torch.compile) a cached real tensor cannot
    be mixed with the fake ones; under torch.compile a cached one would be a graph input whose
    size gets guarded (and, with dynamic shapes, equated with a batch size of the same length);
    while a CUDA graph is captured, the kernels that would fill a new constant are recorded,
    not run."""
    if is_compiling() or fake_tensor_mode_active():
        return True
    return device.type == "cuda" and torch.cuda.is_current_stream_capturing()


def _series_constants(order: int, dtype: torch.dtype, device: torch.device):
    """Taylor coefficients of c_(order-1), c_order, (TAYLOR_TERMS, 2), and 1/m! (order + 1,),
    as tensors (cached per dtype and device): tensor operands avoid the per-call conversion of
    Python scalars, which costs as much as the arithmetic at small batches."""
    key = (order, dtype, device)
    fresh = fresh_constants(device)  # built anew, cache untouched (compiled: folded into the graph)
    consts = None if fresh else _CONSTANTS.get(key)
    if consts is None:
        taylor = [[(-1.0) ** k / math.factorial(2 * k + m) for m in (order - 1, order)]
                  for k in range(TAYLOR_TERMS)]
        inv_fact = [1.0 / math.factorial(m) for m in range(order + 1)]
        consts = (torch.tensor(taylor, dtype=dtype, device=device),
                  torch.tensor(inv_fact, dtype=dtype, device=device))
        # Cache plain tensors only: not the fake or inference tensors of a tracing or
        # inference-mode first call, nor the wrappers of a first call inside a torch.func
        # transform (a cached wrapper broke every later transform of the process).
        if not fresh and all(
                type(t) is torch.Tensor and not t.is_inference()
                and not _is_wrapped(t) for t in consts):
            _CONSTANTS[key] = consts
    return consts


def series_coefficients(theta2: torch.Tensor, order: int = MAX_ORDER) -> list[torch.Tensor]:
    """[c_0, ..., c_order] evaluated at theta^2 (any shape), accurate for every theta."""
    if order > MAX_ORDER or order < 1:
        raise ValueError(f"order must be in [1, {MAX_ORDER}], got {order}")
    taylor, inv_fact = _series_constants(order, theta2.dtype, theta2.device)
    taylor = taylor.view((TAYLOR_TERMS, 2) + (1,) * theta2.dim())
    mask = (theta2 < series_threshold_sq()).to(theta2.dtype)
    t2_small = theta2 * mask  # 0 where the closed form is used
    t2_large = select(mask, torch.ones_like(theta2), theta2)

    # Small branch: the two highest by Taylor (Horner, both at once), the rest downwards.
    acc = taylor[-1]
    for k in range(TAYLOR_TERMS - 2, -1, -1):
        acc = torch.addcmul(taylor[k], acc, t2_small)
    lo: list[torch.Tensor | None] = [None] * (order + 1)
    lo[order - 1], lo[order] = acc.unbind(0)
    for m in range(order - 2, -1, -1):
        lo[m] = torch.addcmul(inv_fact[m], t2_small, cast(torch.Tensor, lo[m + 2]), value=-1.0)

    # Large branch: sin/cos of the half angle, then upwards.
    theta = torch.sqrt(t2_large)
    inv_t2 = torch.reciprocal(t2_large)
    half = 0.5 * theta
    hs, hc = torch.sin(half), torch.cos(half)
    two_hs2 = 2.0 * hs * hs  # 1 - cos, without cancellation
    hi: list[torch.Tensor] = [1.0 - two_hs2, 2.0 * hs * hc / theta]
    if order >= 2:
        hi.append(two_hs2 * inv_t2)
    for m in range(3, order + 1):
        hi.append((inv_fact[m - 2] - hi[m - 2]) * inv_t2)

    # every entry of lo is set above
    return [select(mask, a, b) for a, b in zip(cast("list[torch.Tensor]", lo), hi)]


def series_derivative(c: list[torch.Tensor], m: int) -> torch.Tensor:
    """e_m = c_m'(theta)/theta = m c_(m+2) - c_(m+1) (needs c up to m + 2)."""
    return m * c[m + 2] - c[m + 1]


def jinv_coefficient(theta2: torch.Tensor) -> torch.Tensor:
    """d(theta) = (1 - (theta/2) cot(theta/2)) / theta^2, the u^u^ term of D^-1 in (3.12).

    Written as 1/theta^2 - (1 + cos)/(2 theta sin) = 1/theta^2 - cot(theta/2)/(2 theta) for
    large theta (finite up to, not including, 2 pi); Bernoulli series below JINV_THRESHOLD.
    """
    small = theta2 < jinv_threshold_sq()
    mask = small.to(theta2.dtype)
    t2s = theta2 * mask
    t2l = select(mask, torch.ones_like(theta2), theta2)
    # (theta/2) cot(theta/2) = sum_n (-1)^n B_2n theta^2n / (2n)!  => d = -sum_{n>=1} ... / theta^2
    bern = JINV_SERIES
    taylor = torch.full_like(t2s, bern[-1])
    for a in reversed(bern[:-1]):
        taylor = taylor * t2s + a
    theta = torch.sqrt(t2l)
    half = 0.5 * theta
    closed = 1.0 / t2l - torch.cos(half) / (2.0 * theta * torch.sin(half))
    return select(mask, taylor, closed)
# sin(theta) below which SO(3) log uses theta/sin(theta) = 1 + theta^2/6 + 7 theta^4/360.
LOG_SIN_TAYLOR = 1e-4
log_sin_taylor = _constant(LOG_SIN_TAYLOR)


# ----------------------------------------------------------------------- IMU streaming
# The one-sample path of imu/stream_parts.py evaluates c_1 .. c_4 at p = theta^2 as one product of
# the powers p^1 .. p^(IMU_STREAM_TAYLOR_TERMS - 1) with their Taylor coefficients
# (``taylor_table``) wherever p <= IMU_STREAM_SERIES_THRESHOLD_SQ, so a typical sample (theta < 1.58)
# needs no sin/cos: the first term left out, p^12 / 25!, is below 4e-21 there.  Above it, the
# closed forms (cancellation error about 1e-16 / p).
IMU_STREAM_SERIES_THRESHOLD_SQ = 2.5
IMU_STREAM_TAYLOR_TERMS = 12


def taylor_table(orders: tuple[int, ...], terms: int) -> list[list[float]]:
    """Taylor coefficients of c_m for m in ``orders``: row k holds (-1)^k / (2k + m)!, the
    coefficient of theta^(2k), for k = 0 .. terms - 1."""
    return [[(-1.0) ** k / math.factorial(2 * k + m) for m in orders] for k in range(terms)]


# ----------------------------------------------------------------------------- Sim(3)
# The Sim(3) scalar families (Barfoot, "Integral Forms", Sec. 4.4, (90); docs/guide/sim3_jacobian.md).
# Moments of the scale weight w(a) = exp(-(1 - a) lambda) on [0, 1]:
#     q_j(x) = phi_(j+1)(x) = sum_n x^n / (n + j + 1)! = int_0^1 a^j/j! e^((1-a) x) da,  x = -lambda,
#     q_(j-1) = 1/j! + x q_j  (downward, stable for |x| < j),
#     q_j = (q_(j-1) - 1/j!) / x  (upward, stable for |x| > j), q_0 = expm1(x)/x.
# Index j takes the upward value where |x| > j + SCALE_UPWARD_MARGIN, else the downward one.
SCALE_UPWARD_MARGIN = 0.5
scale_upward_margin = _constant(SCALE_UPWARD_MARGIN)
# The downward recursion starts this many orders above the highest moment requested, from
# Taylor series of SCALE_TAYLOR_TERMS terms.
SCALE_EXTRA_ORDERS = 8
SCALE_TAYLOR_TERMS = 20
# theta below which the Sim(3) coefficients use their theta^2 series (with the moments above);
# above it, the complex closed forms in w = lambda + i theta (|w| >= theta >= 1).
SIM3_SERIES_THRESHOLD = 1.0
sim3_series_threshold_sq = _constant(SIM3_SERIES_THRESHOLD**2)
SIM3_SERIES_TERMS = 11
# The Jacobians need s M = e^lambda M(phi, lambda).  As lambda -> -inf, M ~ e^|lambda|/|lambda|
# overflows and s underflows (float64 beyond |lambda| ~ 709, float32 ~ 88) while s M ~ 1/|lambda|
# stays finite.  So with ``normalise``, sim3_coefficients returns below lambda = -SIM3_NORMALISE the
# coefficients times sigma = e^lambda: those of s M = int_0^1 e^(a lambda) C(a phi) da, whose weight
# is <= 1.  The threshold is above every moment's switch to the upward recursion (2 K + 2 + 1/2),
# so normalised moments come from that recursion alone, and far below overflow (e^30 ~ 1e13).
SIM3_NORMALISE = 30.0
sim3_normalise = _constant(SIM3_NORMALISE)
assert SIM3_NORMALISE > 2 * SIM3_SERIES_TERMS + 2 + SCALE_UPWARD_MARGIN


def scale_moments(x: torch.Tensor, order: int, em1: torch.Tensor | None = None,
                  sigma: torch.Tensor | None = None) -> list[torch.Tensor]:
    """The list (q_0(x), ..., q_order(x)) with q_j = sum_n x^n/(n + j + 1)! (phi-functions phi_(j+1)).

    Relative error ~1e-16 at every order for |x| <= 6, and at the orders Sim(3) weighs most
    up to |x| = 40 (tests/test_precision.py).  Both recursions run on safe inputs; each order
    takes the stable one (see the constants above), merged with exact 0/1 masks, so values
    and gradients stay finite.  The downward one runs on s_j = j! q_j,
    s_(j-1) = (1 + x s_j) / j, whose backward multiplies by x / j (< 1 where it is taken):
    on q_j itself it multiplies by x at each of its ~50 steps and overflowed float32 (NaN
    gradients for |x| in about [8, 24]).

    ``em1`` (optional, x's shape) is expm1(x), when the caller has it.  With ``sigma`` as well:
    sigma q_j(x), where sigma is 1 or e^-x per entry and em1 = sigma expm1(x).  Entries with
    sigma = e^-x must have x > order + SCALE_UPWARD_MARGIN, so they take the upward recursion
    alone, which then runs on the moments of the weight e^(-a x) <= 1 and does not overflow.
    """
    top = order + SCALE_EXTRA_ORDERS
    ax = x.abs()
    # Downward, on s_j = j! q_j, from the Taylor series of s_top (the same recursion from
    # s_(top + SCALE_TAYLOR_TERMS + 1) = 0); inputs with |x| > order + margin never use it.
    x_dn = torch.where(ax <= order + scale_upward_margin(), x, torch.zeros_like(x))
    one = torch.ones_like(x_dn)
    s = torch.zeros_like(x_dn)
    for j in range(top + SCALE_TAYLOR_TERMS + 1, order, -1):
        s = torch.addcmul(one, x_dn, s) / j
    down = [s * (1.0 / math.factorial(order))]  # q_j = s_j / j! (Python constants: no copy to the device)
    for j in range(order, 0, -1):
        s = torch.addcmul(one, x_dn, s) / j
        down.append(s if j == 1 else s * (1.0 / math.factorial(j - 1)))
    down.reverse()
    # Upward from expm1(x)/x; inputs with |x| <= SCALE_UPWARD_MARGIN never use it.
    x_up = torch.where(ax > scale_upward_margin(), x, torch.ones_like(x))
    up = [(torch.expm1(x_up) if em1 is None else em1) / x_up]  # em1 is finite where unused
    for j in range(1, order + 1):
        if sigma is None:
            up.append((up[-1] - 1.0 / math.factorial(j)) / x_up)
        else:
            up.append(torch.sub(up[-1], sigma, alpha=1.0 / math.factorial(j)) / x_up)
    # Order j takes the upward value where |x| > j + margin (one comparison for all orders).
    j_plus = torch.arange(order + 1, dtype=x.dtype, device=x.device) + scale_upward_margin()
    mask = (ax.unsqueeze(-1) > j_plus).to(x.dtype)
    merged = select(mask, torch.stack(up, dim=-1), torch.stack(down, dim=-1))
    return list(merged.unbind(-1))


def sim3_coefficients(theta2: torch.Tensor, lam: torch.Tensor, derivatives: bool = True,
                      normalise: bool = False) -> dict[str, torch.Tensor]:
    """The scalar coefficients of the Sim(3) translation block and its derivatives.

    M(phi, lambda) = int_0^1 e^(-(1-a) lambda) C(a phi) da = m0 I + m1 phi^ + m2 phi^ phi^,
    e_k = (dm_k/dtheta)/theta, p_k = dm_k/dlambda (docs/guide/sim3_jacobian.md).  Inputs broadcast.
    Returns a dict with keys m0, m1, m2, m_re = m0 - theta^2 m2 (computed without that
    cancellation) and, with ``derivatives``, e1, e2, p0, p1, p2.  With ``normalise`` every one
    of them is e^shift times its value, and the dict has the key shift: lambda where
    lambda < -SIM3_NORMALISE (there they are those of s M, which stay finite), else 0.
    """
    checks.boolean(derivatives, "derivatives")
    checks.boolean(normalise, "normalise")
    theta2, lam = torch.broadcast_tensors(theta2, lam)
    K = SIM3_SERIES_TERMS
    x = -lam
    if normalise:
        nm = (x > sim3_normalise()).to(lam.dtype)
        shift = lam * nm
        sigma = torch.exp(shift)
        # sigma expm1(x): -expm1(-x) where normalised (x -> -x and back, as x - 2 x nm).
        em1 = torch.expm1(torch.addcmul(x, x, nm, value=-2.0))
        em1 = torch.addcmul(em1, em1, nm, value=-2.0)
    else:
        sigma, em1 = None, torch.expm1(x)
    q = scale_moments(x, 2 * K + 2 if derivatives else 2 * K, em1, sigma)
    m0 = q[0]

    small = theta2 < sim3_series_threshold_sq()
    mask = small.to(theta2.dtype)
    # Small angle: series in u = -theta^2 with the moments as coefficients (Horner).
    u = -(theta2 * mask)

    def horner(coef):
        acc = coef(K - 1)
        for k in range(K - 2, -1, -1):
            acc = acc * u + coef(k)
        return acc

    s_m1 = horner(lambda k: q[2 * k + 1])
    s_m2 = horner(lambda k: q[2 * k + 2])

    # Large angle: K = int e^(-(1-a) lam) e^(i a theta) da = (e^(i theta) - e^(-lam)) / w,
    # K1 = int a (...) da = (e^(i theta) - K) / w, w = lam + i theta, |w| >= theta >= 1.
    # Normalised, e^(i theta) (the weight at a = 1) and e^-lam (at a = 0) are times sigma.
    t2 = select(mask, torch.ones_like(theta2), theta2)
    t = torch.sqrt(t2)
    sin = torch.sin(t)
    hs = torch.sin(0.5 * t)
    h2 = hs * hs  # (1 - cos) / 2 without cancellation
    if sigma is not None:
        sin, h2 = sigma * sin, sigma * h2
    # Divided by |w|^2 before the products: na ~ e^-lam, and na * lam overflows for
    # lam near the dtype's exp limit (-85 float32, -705 float64) where K itself is finite.
    w2 = lam * lam + t2
    lw, tw = lam / w2, t / w2
    # e^-lam - cos as (e^-lam - 1) + (1 - cos): both terms to full relative accuracy, so the
    # sum keeps it where they nearly cancel (theta near 2 pi k with lambda near 0, M nearly
    # singular); cos - exp(-lam) lost ~eps/|lambda| there.
    na = torch.add(em1, h2, alpha=2.0)  # -Re(numerator of K)
    k_re = sin * tw - na * lw
    k_im = sin * lw + na * tw
    l_m1 = k_im / t
    l_m2 = (m0 - k_re) / t2
    # m_re = m0 - theta^2 m2, the real part of M's eigenvalue m_re + i theta m1 on the rotation
    # plane.  Re K itself on the large-angle branch: m0 - theta^2 m2 from the rounded m2 cancels
    # to 0 at theta = 2 pi k, lambda = 0 (cos = 1), where M^-1 needs it most (poly_inverse).
    # Below theta = 1, theta^2 m2 <= (1 - cos 1) m0 and nothing cancels.
    s_re = torch.addcmul(m0, u, s_m2)
    out = {"m0": m0, "m1": select(mask, s_m1, l_m1), "m2": select(mask, s_m2, l_m2),
           "m_re": select(mask, s_re, k_re)}
    if normalise:
        out["shift"] = shift
    if not derivatives:
        return out

    p0 = q[1] - q[0]
    s_e1 = -horner(lambda k: 2 * (k + 1) * q[2 * k + 3])
    s_e2 = -horner(lambda k: 2 * (k + 1) * q[2 * k + 4])
    s_p1 = -horner(lambda k: q[2 * k + 1] - (2 * k + 2) * q[2 * k + 2])
    s_p2 = -horner(lambda k: q[2 * k + 2] - (2 * k + 3) * q[2 * k + 3])
    cos = torch.rsub(h2, 1.0, alpha=2.0) if sigma is None else torch.sub(sigma, h2, alpha=2.0)
    b_re = cos - k_re
    b_im = sin - k_im
    k1_re = b_re * lw + b_im * tw
    k1_im = b_im * lw - b_re * tw
    l_e1 = (k1_re - l_m1) / t2
    l_e2 = (k1_im / t - 2.0 * l_m2) / t2
    l_p1 = (k1_im - k_im) / t
    l_p2 = (p0 + k_re - k1_re) / t2

    out.update(
        p0=p0, e1=select(mask, s_e1, l_e1), e2=select(mask, s_e2, l_e2),
        p1=select(mask, s_p1, l_p1), p2=select(mask, s_p2, l_p2),
    )
    return out
