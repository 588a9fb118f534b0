"""How noise and bias errors at the samples move the preintegrated increment (preintegration.py).

To first order the right perturbation is eps = int_0^T Ad(F(s)) G n(s) ds with the nodes
F(s) = Delta^-1 Delta(s) and G the nu, phi, iota columns; Simpson's rule on each sample interval
turns it into weighted sums over the nodes F_j (the instants, the midpoints and the identity):
the covariance sum_j w_j Ad(F_j) G Q_c G^T Ad(F_j)^T (in closed form from a few node sums for
isotropic densities, node by node for per-axis ones) and the bias Jacobian
-sum_j w_j Ad(F_j) G.  The noise map Ad(F) G is the nu, phi and iota columns of kelly-giamou
(3.16)."""
from __future__ import annotations

import torch

from .. import SGal3
from ..functional import blocks as B
from ..functional import sgal3 as F


def _cross_columns(a: torch.Tensor, X: torch.Tensor) -> torch.Tensor:
    """a^ X for a (..., 3, N) and X (..., 3, m, N) (node axis last)."""
    a0, a1, a2 = (a[..., i, None, :] for i in range(3))
    x0, x1, x2 = X[..., 0, :, :], X[..., 1, :, :], X[..., 2, :, :]
    return torch.stack((a1 * x2 - a2 * x1, a2 * x0 - a0 * x2, a0 * x1 - a1 * x0), dim=-3)


def noise_map(nodes: SGal3, scale: torch.Tensor | None = None) -> torch.Tensor:
    """Ad(F) G for the N nodes of the last batch axis, laid out (..., 10, 7, N) (node axis last),
    optionally times ``scale`` (..., N): how tangent noise [nu, phi, iota] entering at a node
    moves the right perturbation.  These are the nu, phi and iota columns of kelly-giamou
    (3.16), Ad = [[C, -tau C, (r - tau v)^ C, v], [0, C, v^ C, 0], [0, 0, C, 0], [0, 0, 0, 1]]."""
    C = nodes.rotation().movedim(-3, -1)  # (..., 3, 3, N)
    v = nodes.velocity().movedim(-2, -1)  # (..., 3, N)
    r = nodes.position().movedim(-2, -1)
    tau = nodes.time().unsqueeze(-2)  # (..., 1, N)
    if scale is not None:
        C = C * scale[..., None, None, :]
        one = scale.unsqueeze(-2)
    else:
        one = torch.ones_like(tau)
    W = C.new_zeros(*C.shape[:-3], 10, 7, C.shape[-1])
    W[..., 0:3, 0:3, :] = -tau.unsqueeze(-2) * C
    W[..., 3:6, 0:3, :] = C
    W[..., 0:3, 3:6, :] = _cross_columns(r - tau * v, C)
    W[..., 3:6, 3:6, :] = _cross_columns(v, C)
    W[..., 6:9, 3:6, :] = C
    W[..., 0:3, 6, :] = v * one
    W[..., 9, 6, :] = one[..., 0, :]
    return W


def _eps_contract(Y: torch.Tensor) -> torch.Tensor:
    """sum_{k,l} eps_ikl Y[..., k, l, m] (eps the Levi-Civita symbol) for Y (..., 3, 3, m): with
    Y[k] = sum w a_k C this is sum w a^ C.  Written out: no constant tensor to bring to the
    device."""
    return torch.stack((Y[..., 1, 2, :] - Y[..., 2, 1, :], Y[..., 2, 0, :] - Y[..., 0, 2, :],
                        Y[..., 0, 1, :] - Y[..., 1, 0, :]), dim=-2)


def _node_sum(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """sum_n a[i, ..., n] b[j, ..., n] for a (I, ..., n), b (J, ..., n) -> (..., I, J): one
    batched matmul on strided views (unit stride along n: no copies)."""
    return a.movedim(0, -2) @ b.movedim(0, -1)


def _weights(dt: torch.Tensor):
    """Simpson weights (..., K + 1) of the instants and (..., K) of the midpoints."""
    zero = torch.zeros_like(dt[..., :1])
    return (torch.cat((dt, zero), -1) + torch.cat((zero, dt), -1)) / 6.0, 4.0 * dt / 6.0


def _node_moments(groups, w_identity: torch.Tensor) -> dict:
    """Weighted sums over the nodes F = X^-1 that the covariance and the bias Jacobian need;
    ``groups`` is a list of (X packed with the node axis last (16, ..., n), weights (..., n)),
    ``w_identity`` the weight of an extra node F = I.  With X = (C, v, r, tau): F has rotation
    C^T, velocity vh = -C^T v, lever (r - tau v of F) lh = -C^T r and time -tau."""
    sums: dict[str, torch.Tensor] = {}
    for X, w in groups:
        C, v, r, tau = X[0:9], X[9:12], X[12:15], X[15]
        Ct = [C[3 * j + i] for i in range(3) for j in range(3)]  # entries of C^T, row-major
        vh, lh, th = -B.matvec_entries(Ct, v), -B.matvec_entries(Ct, r), -tau  # (3, ..., n) x2, (..., n)
        lv = torch.cat((lh, vh), dim=0)  # (6, ..., n)
        wlv = w * lv
        wt = w * th
        coef = torch.cat((w[None], wt[None], wlv), dim=0)  # (8, ..., n)
        part = {"w": w.sum(-1), "wt": wt.sum(-1), "wtt": (wt * th).sum(-1),
                "wl": wlv[:3].sum(-1).movedim(0, -1), "wv": wlv[3:].sum(-1).movedim(0, -1),
                "outer": _node_sum(wlv, lv),  # sums of w [l; v][l; v]^T
                "Y": _node_sum(coef, C).unflatten(-1, (3, 3)).transpose(-1, -2)}  # sums of coef C^T
        sums = part if not sums else {k: sums[k] + part[k] for k in sums}
    sums["w"] = sums["w"] + w_identity
    eye = torch.eye(3, dtype=w_identity.dtype, device=w_identity.device)
    sums["Y"] = sums["Y"] + torch.cat((w_identity[..., None, None, None] * eye,
                                        torch.zeros_like(sums["Y"][..., 1:, :, :])), dim=-3)
    return sums


def _skew(a: torch.Tensor) -> torch.Tensor:
    o = torch.zeros_like(a[..., 0])
    x, y, z = a[..., 0], a[..., 1], a[..., 2]
    return torch.stack((o, -z, y, z, o, -x, -y, x, o), dim=-1).reshape(*a.shape[:-1], 3, 3)


def _isotropic_covariance(m: dict, s_a: torch.Tensor, s_g: torch.Tensor, s_t: torch.Tensor) -> torch.Tensor:
    """sum_j w_j Ad(F_j) G Q_c G^T Ad(F_j)^T for Q_c = diag(s_a^2 I, s_g^2 I, s_t^2) in closed form:
    with C C^T = I and a^ b^ = b a^T - (a.b) I only sums of scalars, vectors and outer products
    of the nodes' lever l and velocity v remain."""
    w = m["w"]
    eye = torch.eye(3, dtype=w.dtype, device=w.device)
    I = lambda x: x[..., None, None] * eye  # noqa: E731
    ll, lv, vv = m["outer"][..., :3, :3], m["outer"][..., :3, 3:], m["outer"][..., 3:, 3:]
    tr = lambda M: M.diagonal(dim1=-2, dim2=-1).sum(-1)  # noqa: E731
    a2, g2, t2 = s_a**2, s_g**2, s_t**2
    rr = a2 * I(m["wtt"]) + g2 * (I(tr(ll)) - ll) + t2 * vv
    rn = -a2 * I(m["wt"]) + g2 * (I(tr(lv)) - lv.transpose(-1, -2))
    rp = g2 * _skew(m["wl"])
    nn = a2 * I(w) + g2 * (I(tr(vv)) - vv)
    npb = g2 * _skew(m["wv"])
    pp = g2 * I(w)
    ri = (t2 * m["wv"]).unsqueeze(-1)
    z1 = torch.zeros_like(ri)
    rows = [
        torch.cat((rr, rn, rp, ri), -1),
        torch.cat((rn.transpose(-1, -2), nn, npb, z1), -1),
        torch.cat((rp.transpose(-1, -2), npb.transpose(-1, -2), pp, z1), -1),
        torch.cat((ri.transpose(-1, -2), z1.transpose(-1, -2), z1.transpose(-1, -2), (t2 * w)[..., None, None]), -1),
    ]
    return torch.cat(rows, dim=-2)


def _bias_jacobian(m: dict) -> torch.Tensor:
    """-sum_j w_j Ad(F_j) G over the gyro (phi) and accelerometer (nu) columns."""
    Y = m["Y"]
    sC, stC = Y[..., 0, :, :], Y[..., 1, :, :]
    slC = _eps_contract(Y[..., 2:5, :, :])  # sum w l^ C
    svC = _eps_contract(Y[..., 5:8, :, :])  # sum w v^ C
    z = torch.zeros_like(sC)
    gyro_cols = torch.cat((slC, svC, sC, z[..., :1, :]), dim=-2)
    acc_cols = torch.cat((-stC, sC, z, z[..., :1, :]), dim=-2)
    return -torch.cat((gyro_cols, acc_cols), dim=-1)


def _general_covariance(node_groups, w_identity, s_a, s_g, s_t) -> torch.Tensor:
    """sum_j w_j Ad(F_j) G Q_c G^T Ad(F_j)^T for per-axis densities, from the nodes F = X^-1 of
    ``node_groups`` (as in _node_moments) and the identity node of weight ``w_identity``."""
    eye = torch.eye(5, dtype=w_identity.dtype, device=w_identity.device).expand(*w_identity.shape, 1, 5, 5)
    suffixes = SGal3(torch.cat([F.unpack(X) for X, _ in node_groups] + [eye], dim=-3))
    weights = torch.cat([w for _, w in node_groups] + [w_identity[..., None]], dim=-1)
    W = noise_map(suffixes.inverse())  # (..., 10, 7, 2K + 1): Ad(node) G
    col = (*s_a.shape[:-1], 1)
    s_t = s_t.expand(col) if isinstance(s_t, torch.Tensor) else s_a.new_full(col, s_t)  # a number: a fill
    dens = torch.cat((s_a, s_g, s_t), dim=-1)
    Wq = W * dens[..., None, :, None]  # Ad(node) G sqrt(Q_c)
    # the weights unsquared (sqrt(w) had an infinite derivative at a zero dt: NaN gradients)
    return (Wq * weights[..., None, None, :]).flatten(-2) @ Wq.flatten(-2).transpose(-1, -2)
