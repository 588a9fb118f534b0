"""The fast CPU path of :func:`~torchsgal.imu.preintegrate`: the arithmetic of the plain path
(preintegration._integrate) with its SGal3 products written in place in the packed layout,
over blocks of windows, and the tensor code of the operator torch.ops.torchsgal.imu_preintegrate
(imu/_kernels.py) where its C loop does not run (docs/guide/imu.md)."""
from __future__ import annotations

import math

import torch

from ..functional import sgal3 as F
from . import _kernels  # registers torch.ops.torchsgal.imu_preintegrate
from .moments import _bias_jacobian, _general_covariance, _isotropic_covariance, _weights

# Where nothing can observe it (functional/_blocking.py: CPU, no autograd recording, no functorch
# transform, no compile) the same arithmetic runs with its products written in place (no stack or
# cat copies) and, for large batches, over groups of windows of about _BLOCK_BYTES per component:
# temporaries of that size are recycled by the allocator instead of being faulted in fresh
# (benchmarks/bench_imu.py).  Elsewhere the plain code (_integrate) runs, for autograd and vmap.
_BLOCK_BYTES = 1 << 18  # per component: 32768 float64 / 65536 float32 samples (best of 64 kB-4 MB)


def _compose_into(P1: torch.Tensor, P2: torch.Tensor, out: torch.Tensor) -> None:
    """out = P1 P2 in the packed layout: F.compose_packed's arithmetic, in the same order (bitwise
    equal), in 9 broadcast operations instead of 55 (C1 C2 = sum_k C1[:, k] C2[k, :], and the
    same for the columns [v2, r2]), written into ``out`` (which must not overlap P1 or P2)."""
    C1c = P1[0:9].unflatten(0, (3, 3, 1)).unbind(1)  # columns of C1, (3, 1, ...)
    C1r = P1[0:9].unflatten(0, (1, 3, 3)).unbind(2)  # the same as (1, 3, ...)
    C2r = P2[0:9].unflatten(0, (1, 3, 3)).unbind(1)  # rows of C2, (1, 3, ...)
    vr2 = P2[9:15].unflatten(0, (2, 3, 1)).unbind(1)  # components k of [v2, r2], (2, 1, ...)
    oC, ovr = out[0:9].unflatten(0, (3, 3)), out[9:15].unflatten(0, (2, 3))
    torch.mul(C1c[0], C2r[0], out=oC).addcmul_(C1c[1], C2r[1]).addcmul_(C1c[2], C2r[2])
    torch.mul(C1r[0], vr2[0], out=ovr).addcmul_(C1r[1], vr2[1]).addcmul_(C1r[2], vr2[2])
    ovr.add_(P1[9:15].unflatten(0, (2, 3)))
    out[12:15].addcmul_(P2[15:16], P1[9:12])
    torch.add(P1[15], P2[15], out=out[15])


class _Scratch:
    """Buffers reused from block to block: a fresh tensor of several MB is paid in page faults
    each time (functional/_blocking.py), a reused one is not."""

    def __init__(self, like: torch.Tensor):
        self.like = like
        self.bufs: dict[str | tuple[str, int], torch.Tensor] = {}  # by name (and size)

    def __call__(self, key, shape) -> torch.Tensor:
        n = math.prod(shape)
        buf = self.bufs.get(key)
        if buf is None or buf.numel() < n:
            buf = self.bufs[key] = self.like.new_empty(n)
        return buf[:n].view(shape)


def _pairs_into(E: torch.Tensor, ws: _Scratch) -> torch.Tensor:
    """_pair_products of packed (16, m, ...) along axis 1, written into a scratch tensor."""
    m = E.shape[1]
    half = m // 2
    P = ws(("pairs", m), (16, m - half) + E.shape[2:])
    _compose_into(E[:, 0 : 2 * half : 2], E[:, 1 : 2 * half : 2], P[:, :half])
    if m % 2:
        P[:, half] = E[:, m - 1]
    return P


def _scan_into(E: torch.Tensor, out: torch.Tensor, ws: _Scratch | None = None) -> None:
    """_suffix_products of packed (16, m, ...) along axis 1, written into ``out`` (a view, strided
    along axis 1 in the recursion): S_2j from the scan of the pairs, S_2j+1 = E_2j+1 S_2j+2."""
    m = E.shape[1]
    if m == 1:
        out.copy_(E)
        return
    ws = ws or _Scratch(E)
    _scan_into(_pairs_into(E, ws), out[:, 0::2], ws)
    n_odd = (m - 1) // 2  # odd k with S_{k+1} inside the chain
    _compose_into(E[:, 1 : 2 * n_odd : 2], out[:, 2 : 2 * n_odd + 1 : 2], out[:, 1 : 2 * n_odd : 2])
    if m % 2 == 0:
        out[:, m - 1] = E[:, m - 1]  # S_{m-1} = E_{m-1} S_m, S_m = I


def _exp_streams(gyro, acc, dt, b_g, b_a, scale: float, ws: _Scratch) -> torch.Tensor:
    """F.exp_packed of the tangents [0, (f - b_a) h, (omega - b_g) h, h], h = scale dt (scale 1 or
    1/2: exact), as packed (16, K, n) straight from gyro, acc (n, K, 3), dt (n, K), biases (n, 3):
    (3.6) with rho = 0 (F.exp_parts; the Gamma_1 rho term is an exact zero)."""
    h = (dt * scale).t()  # (K, n)
    nu, phi = ws("nu", (3,) + h.shape), ws("phi", (3,) + h.shape)
    torch.mul((acc - b_a.unsqueeze(-2)).permute(2, 1, 0), h, out=nu)
    torch.mul((gyro - b_g.unsqueeze(-2)).permute(2, 1, 0), h, out=phi)
    C, v, r = F.exp_parts(nu, phi, h)
    out = ws("H", (16,) + h.shape)
    torch.stack(C, out=out[0:9])
    out[9:12] = v
    out[12:15] = r
    out[15] = h
    return out


def _node_major(P: torch.Tensor, out: torch.Tensor) -> torch.Tensor:
    """Packed (16, K, n) -> ``out`` (16, n, K), node axis last for the sums over nodes (one
    copy: faster than a cache-blocked 2-D transpose per component)."""
    return out.copy_(P.transpose(1, 2))


def _nodes_fast(gyro, acc, dt, b_g, b_a, ws: _Scratch):
    """One block of n windows: (delta packed (16, n), node groups [(X (16, n, K), weights (n, K))]
    for the instants 0 .. K-1 and the midpoints 0 .. K-1 (node axis last), the weight (n,) of
    the identity node); see _integrate."""
    K = dt.shape[-1]
    H = _exp_streams(gyro, acc, dt, b_g, b_a, 0.5, ws)
    E = ws("E", H.shape)
    _compose_into(H, H, E)
    S = ws("S", H.shape)
    _scan_into(E, S, ws)
    mid = E  # E is consumed: the midpoints H_k S_{k+1}, S_K = I
    _compose_into(H[:, : K - 1], S[:, 1:], mid[:, : K - 1])
    mid[:, K - 1] = H[:, K - 1]
    w_instants, w_mid = _weights(dt)
    n = H.shape[2]
    groups = [(_node_major(S, ws("XS", (16, n, K))), w_instants[:, :K]),
              (_node_major(mid, ws("XM", (16, n, K))), w_mid)]
    return S[:, 0], groups, w_instants[:, K]


def _node_moments_fast(groups, w_identity: torch.Tensor, ws: _Scratch) -> dict:
    """_node_moments of groups of X (16, n, N) (overwritten) and w (n, N): every weighted sum in
    one batched product per group.  X becomes [C, vh, lh, th] (_node_moments' names),
    A = [w, w th, w vh, w lh], and the sums over the nodes of A_a X_b are read off the
    (n, 8, 16) product."""
    P = None
    for X, w in groups:
        LV = ws("LV", (2, 3) + X.shape[1:])  # [C^T v, C^T r]
        C, VR = X[0:9].unflatten(0, (3, 3)), X[9:15].unflatten(0, (2, 3))
        torch.mul(C[0, None], VR[:, 0, None], out=LV)
        LV.addcmul_(C[1, None], VR[:, 1, None]).addcmul_(C[2, None], VR[:, 2, None])
        torch.neg(LV.flatten(0, 1), out=X[9:15])
        X[15].neg_()
        A = ws("A", (8,) + X.shape[1:])
        A[0] = w
        torch.mul(w, X[15], out=A[1])
        torch.mul(w, X[9:15], out=A[2:8])
        a, x = A.movedim(0, -2), X.movedim(0, -1)
        P = a @ x if P is None else torch.baddbmm(P, a, x)  # (n, 8, 16)
    assert P is not None  # groups is never empty
    rows = [0, 1, 5, 6, 7, 2, 3, 4]  # coefficients in _node_moments' order [w, w t, w l, w v]
    sums = {"w": sum(w.sum(-1) for _, w in groups) + w_identity, "wt": P[:, 0, 15], "wtt": P[:, 1, 15],
            "wl": P[:, 0, 12:15], "wv": P[:, 0, 9:12],
            "outer": P[:, rows[2:]][:, :, [12, 13, 14, 9, 10, 11]],
            "Y": P[:, rows, 0:9].unflatten(-1, (3, 3)).transpose(-1, -2).clone()}
    sums["Y"][:, 0] += w_identity[:, None, None] * torch.eye(3, dtype=P.dtype, device=P.device)
    return sums


def _integrate_fast(args, batch, s_t, isotropic, covariance, bias_jacobian):
    """_integrate's results by the fast path: the windows flattened and preintegrated by the
    operator torch.ops.torchsgal.imu_preintegrate (imu/_kernels.py: the C loop, or the blocked
    tensor code ``_blocked``), whose node sums give the (small) covariance and bias Jacobian;
    a general (per-axis) covariance needs every node, so it runs ``_blocked`` here."""
    gyro, acc, dt, b_g, b_a, s_a, s_g = args
    K = gyro.shape[-2]
    n = math.prod(batch)
    flat = [gyro.expand(*batch, K, 3).reshape(n, K, 3), acc.expand(*batch, K, 3).reshape(n, K, 3),
            dt.expand(*batch, K).reshape(n, K), b_g.reshape(n, 3), b_a.reshape(n, 3)]
    if covariance and not isotropic:
        general = tuple(s.expand(*batch, 3).reshape(n, 3) for s in (s_a, s_g)) + (s_t,)
        delta, m, cov = _blocked(*flat, bias_jacobian, general)
        jac = _bias_jacobian(m).reshape(*batch, 10, 6) if bias_jacobian else None
        assert cov is not None  # general is given
        return delta.reshape(*batch, 5, 5), cov.reshape(*batch, 10, 10), jac
    nodes = covariance or bias_jacobian
    delta, packed = torch.ops.torchsgal.imu_preintegrate(*flat, nodes)
    return _finish(delta.reshape(*batch, 5, 5), _kernels.node_sums(packed) if nodes else None, batch,
                   s_a, s_g, s_t, covariance, bias_jacobian)


def _blocked(gyro, acc, dt, b_g, b_a, moments: bool, general=None):
    """The fast path's tensor code for n >= 1 flattened windows, gyro, acc (n, K, 3), dt (n, K),
    biases (n, 3): (delta (n, 5, 5), the node sums of _node_moments or None, the general
    covariance (n, 10, 10) or None).  ``moments``: the node sums are wanted; ``general``: the
    densities (s_a (n, 3), s_g (n, 3), s_t) of a general covariance, or None.  Run in blocks of
    about _BLOCK_BYTES per component with one set of scratch buffers."""
    n, K = dt.shape
    per = -(-n // min(n, max(1, n * K * gyro.element_size() // _BLOCK_BYTES)))  # windows per block, balanced
    delta = gyro.new_empty((16, n))
    covs, sums, ws = [], [], _Scratch(gyro)
    for start in range(0, n, per):
        g, a, h, bg, ba = (x[start : start + per] for x in (gyro, acc, dt, b_g, b_a))
        if not (moments or general is not None):
            delta[:, start : start + per] = _tree_product(_exp_streams(g, a, h, bg, ba, 1.0, ws), ws)
            continue
        d, groups, w_id = _nodes_fast(g, a, h, bg, ba, ws)
        delta[:, start : start + per] = d
        if general is not None:
            s_a, s_g, s_t = general
            covs.append(_general_covariance(groups, w_id, s_a[start : start + per], s_g[start : start + per], s_t))
        if moments:
            sums.append(_node_moments_fast(groups, w_id, ws))  # the groups' X overwritten
    m = None
    if sums:
        m = {k: torch.cat([x[k] for x in sums]) for k in sums[0]} if len(sums) > 1 else sums[0]
    cov = (torch.cat(covs) if len(covs) > 1 else covs[0]) if covs else None
    return F.unpack(delta), m, cov


def _finish(delta, m, batch, s_a, s_g, s_t, isotropic_covariance, bias_jacobian):
    """(delta, covariance or None, bias Jacobian or None) from the node sums ``m`` of the flattened
    windows (None: neither is wanted, or the covariance is the general one)."""
    cov = _isotropic_covariance(m, s_a, s_g, s_t).reshape(*batch, 10, 10) if isotropic_covariance else None
    jac = _bias_jacobian(m).reshape(*batch, 10, 6) if bias_jacobian else None
    return delta, cov, jac


def _tree_product(E: torch.Tensor, ws: _Scratch | None = None) -> torch.Tensor:
    """_window_product of packed (16, K, ...) along axis 1, with the products written in place."""
    ws = ws or _Scratch(E)
    while E.shape[1] > 1:
        E = _pairs_into(E, ws)
    return E[:, 0]

