"""The per-sample parts of streaming preintegration and their composition.

A sample of length h contributes its increment E = H H (H the half-sample factor, the exact
exp of the half sample's tangent), A = Ad(E^-1), the bias Jacobian J_k and the covariance S_k
of (C2); parts compose by (C1) and, with the bias random walk, (C3) (the rules in
``streaming``'s docstring and docs/guide/imu_streaming.md), pairwise in a log-depth tree.

A part is (E, A, J, S, X, B, C): S the increment's covariance without the random walk (C1),
and with it X, B and C, the blocks of the combined covariance [[C, X], [X^T, B]] (C3); X, B
and C are None without random walk.
"""
from __future__ import annotations

import torch

from ..functional import numerics

# Taylor coefficients of a = sin t / t, b = (1 - cos t)/t^2, c = (t - sin t)/t^3,
# d = (t^2/2 + cos t - 1)/t^4 (numerics' c_1 .. c_4) in powers of p = t^2, used for
# p <= _TAYLOR_LIMIT; above it the closed forms (numerics.IMU_STREAM_SERIES_THRESHOLD_SQ).
_TERMS = numerics.IMU_STREAM_TAYLOR_TERMS
_TAYLOR_LIMIT = numerics.IMU_STREAM_SERIES_THRESHOLD_SQ
_TAYLOR = numerics.taylor_table((1, 2, 3, 4), _TERMS)


class _Constants:
    """Small constant tensors of one dtype and device, made once per accumulator."""

    def __init__(self, dtype, device):
        kw = dict(dtype=dtype, device=device)
        self.powers = torch.arange(1, _TERMS, **kw)  # p^0 apart: its pow has a NaN derivative at 0
        taylor = torch.tensor(_TAYLOR, **kw)  # (12, 4)
        self.taylor0, self.taylor = taylor[0], taylor[1:]
        skew = torch.zeros(3, 3, 3, **kw)  # skew[i] = e_i^
        for i, j, k in ((0, 2, 1), (1, 0, 2), (2, 1, 0)):
            skew[i, j, k], skew[i, k, j] = 1.0, -1.0
        self.skew = skew.reshape(3, 9)
        self.eye3 = torch.eye(3, **kw)
        # [C | v | r] = base s0 + K (base s1) + K^2 (base s2), base = [I | nu | h nu]:
        # s0 = [1, 1, 1, 1, 1/2], s1 = [a, a, a, b, c], s2 = [b, b, b, c, d] from [a, b, c, d]
        self.s0 = torch.tensor([1.0, 1.0, 1.0, 1.0, 0.5], **kw)
        s12 = torch.zeros(4, 2, 5, **kw)
        s12[0, 0, :3] = s12[1, 0, 3] = s12[2, 0, 4] = 1.0
        s12[1, 1, :3] = s12[2, 1, 3] = s12[3, 1, 4] = 1.0
        self.s12 = s12.reshape(4, 10)
        bottom = torch.zeros(2, 2, 5, **kw)  # the rows [0 0 0 1 h], [0 0 0 0 1] = b0 + h b1
        bottom[0, 0, 3] = bottom[0, 1, 4] = bottom[1, 0, 4] = 1.0
        self.bottom = bottom.reshape(2, 10)
        # Ad(H^-1) = blockdiag(C^T, C^T, C^T, 1) Z, rows 0:9 of Z = Z0 + [h, r, v] L (kelly-giamou (3.16);
        # docs/guide/imu_streaming.md): Z = [[I, h I, -r^, -v], [0, I, -v^, 0], [0, 0, I, 0]]
        Z0 = torch.eye(10, **kw)[:9]
        L = torch.zeros(7, 9, 10, **kw)
        L[0, 0:3, 3:6] = torch.eye(3, **kw)
        for i in range(3):
            L[1 + i, 0:3, 6:9] = -skew[i]  # -r^
            L[4 + i, 3:6, 6:9] = -skew[i]  # -v^
            L[4 + i, i, 9] = -1.0  # -v
        self.z0, self.lz = Z0.reshape(90), L.reshape(7, 90)
        self.last_row = torch.eye(10, **kw)[9:]
        self.eye10 = torch.eye(10, **kw)
        gb = torch.zeros(10, 6, **kw)  # G_b: d tangent / d [b_g, b_a] = -[e_phi, e_nu]
        gb[6:9, 0:3] = -torch.eye(3, **kw)
        gb[3:6, 3:6] = -torch.eye(3, **kw)
        self.gb = gb
        self.gb2 = torch.cat((gb, 4.0 * gb))  # [G_b; 4 G_b] for [A | Ad(H^-1)]


_CONSTANTS: dict = {}


def _constants(dtype, device) -> _Constants:
    """The constants of a dtype and device, made once (they are never written to)."""
    key = (dtype, torch.device(device) if device is not None else torch.empty(0).device)
    if key not in _CONSTANTS:
        _CONSTANTS[key] = _Constants(*key)
    return _CONSTANTS[key]


def _coefficients(p: torch.Tensor, c: _Constants) -> torch.Tensor:
    """[a, b, c, d] (..., 4) of p = theta^2 (..., 1) (see _TAYLOR)."""
    series = p.pow(c.powers) @ c.taylor + c.taylor0
    exact_needed = bool((p > _TAYLOR_LIMIT).any()) if p.device.type == "cpu" else True
    if not exact_needed:
        return series
    big = p > _TAYLOR_LIMIT
    q = torch.where(big, p, torch.full_like(p, 2 * _TAYLOR_LIMIT))  # no 0/0 in the unused branch
    t = q.sqrt()
    a = t.sin() / t
    b = (1 - t.cos()) / q
    exact = torch.cat((a, b, (1 - a) / q, (0.5 - b) / q), dim=-1)
    return torch.where(big, exact, series)


def _half_factors(phi, nu, h, zh, bottom, c: _Constants):
    """H = exp([0, nu, phi, h]) (..., 5, 5) ((3.6) with rho = 0) and Ad(H^-1) (..., 10, 10) for
    half-sample tangents phi, nu (..., 3) and h (a float or (..., 1)), with zh = z0 + h L[0]
    (..., 90) and bottom = b0 + h b1 (..., 10) (_Constants) formed by the caller."""
    batch = phi.shape[:-1]
    coef = _coefficients((phi * phi).sum(-1, keepdim=True), c)
    K = (phi @ c.skew).view(*batch, 3, 3)
    KK = torch.stack((K, K @ K), dim=-3)  # (..., 2, 3, 3)
    base = torch.cat((c.eye3.expand(*batch, 3, 3), nu.unsqueeze(-1), (nu * h).unsqueeze(-1)), -1)
    s12 = (coef @ c.s12).view(*batch, 2, 1, 5)
    top = base * c.s0 + (KK @ (base.unsqueeze(-3) * s12)).sum(-3)  # [C | v | r] (..., 3, 5)
    H = torch.cat((top, bottom.view(*bottom.shape[:-1], 2, 5).expand(*batch, 2, 5)), dim=-2)
    Z = (zh + torch.cat((top[..., 4], top[..., 3]), -1) @ c.lz[1:]).view(*batch, 3, 3, 10)
    Ct = top[..., :3].mT
    Ad = torch.cat(((Ct.unsqueeze(-3) @ Z).flatten(-3, -2), c.last_row.expand(*batch, 1, 10)), -2)
    return H, Ad


def _noise_parts(A, Ah, w, sq2, Qd, c: _Constants):
    """(J_k, S_k) of (C2) from A = Ad(E^-1), Ah = Ad(H^-1), w = h / 6, sq2 = [sqrt(q), 2 sqrt(q)]
    (..., 1, 20) and Qd = diag(q): with M = [A | Ah], S_k = w (M diag(q, 4 q) M^T + Q)."""
    M = torch.cat((A, Ah), dim=-1)
    L = M * sq2
    return w * (M @ c.gb2 + c.gb), w * (L @ L.mT + Qd)


def _sample_parts(gyro, acc, dt, bias6, sq2, Qd, r_diag, c: _Constants):
    """Per sample (any leading shape): E (..., 5, 5), A = Ad(E^-1), J_k (..., 10, 6), S_k (10, 10)
    by (C2), and X_k = 0, B_k = R h (..., 6, 6), C_k = S_k (None without random walk)."""
    half = 0.5 * dt.unsqueeze(-1)
    zh = torch.addcmul(c.z0, half, c.lz[0])
    bottom = torch.addcmul(c.bottom[0], half, c.bottom[1])
    H, Ah = _half_factors((gyro - bias6[..., :3]) * half, (acc - bias6[..., 3:]) * half, half, zh, bottom, c)
    E, A = H @ H, Ah @ Ah
    J, S = _noise_parts(A, Ah, (dt / 6.0)[..., None, None], sq2, Qd, c)
    if r_diag is None:
        return E, A, J, S, None, None, None
    return E, A, J, S, torch.zeros_like(J), torch.diag_embed(r_diag * dt.unsqueeze(-1)), S


def _combine(first, second, need_a: bool = True):
    """A part appended to another, (C1) and (C3): parts (E, A, J, S, X, B, C), X, B and C None
    without random walk."""
    E1, A1, J1, S1, X1, B1, C1 = first
    E2, A2, J2, S2, X2, B2, C2 = second
    S = A2 @ S1 @ A2.mT + S2
    X = B = C = None
    if B1 is not None:
        AX, JB = A2 @ X1, J2 @ B1
        T = AX @ J2.mT
        C = A2 @ C1 @ A2.mT + C2 + T + T.mT + JB @ J2.mT
        X, B = AX + JB + X2, B1 + B2
    A = A2 @ A1 if need_a else None
    return E1 @ E2, A, A2 @ J1 + J2, S, X, B, C


def _along(parts, index):
    return tuple(None if p is None else p[(Ellipsis, index) + (slice(None),) * 2] for p in parts)


def _reduce(parts):
    """The parts of samples (..., K, ., .) combined along K by a log-depth tree (C1, C3)."""
    while parts[0].shape[-3] > 1:
        K = parts[0].shape[-3]
        pairs = _combine(_along(parts, slice(0, K - 1, 2)), _along(parts, slice(1, K, 2)))
        if K % 2:
            tail = _along(parts, slice(K - 1, K))
            pairs = tuple(None if p is None else torch.cat((p, t), dim=-3) for p, t in zip(pairs, tail))
        parts = pairs
    return _along(parts, 0)


def _prefix_products(E: torch.Tensor) -> torch.Tensor:
    """P_k = E_0 ... E_k along the axis -3 (a Hillis-Steele scan, log2 K levels)."""
    step = 1
    while step < E.shape[-3]:
        E = torch.cat((E[..., :step, :, :], E[..., :-step, :, :] @ E[..., step:, :, :]), dim=-3)
        step *= 2
    return E
