"""Galilean IMU preintegration on SGal(3).

Model (mahony-kelly-weiss-galilean-symmetry-robotics.txt, (12)-(17) and Remark 6.2 (57)):
a Galilean frame X = (R, v, p, t) moves as Xdot = X (U(omega, a) + N) with the body rate
omega and the Galilean acceleration a.  Over a window of K samples with piecewise-constant
inputs the increment is, exactly,

    Delta = prod_k exp((U(omega_k - b_g, f_k - b_a) + N) dt_k),

the tangent of one factor being [rho, nu, phi, iota] = [0, (f_k - b_a) dt_k, (omega_k - b_g) dt_k,
dt_k] (CONVENTIONS.md order; U's (omega, a) are mahony's first two slots).  Delta is the
frame at the end of the window seen from the frame at its start, without gravity: its
rotation, velocity and position are the classical Delta R, Delta v, Delta p of preintegration
and its time is the window length.  Gravity (and the Earth's rotation) enter on the *left*
at prediction time, see :func:`predict` and docs/guide/imu.md.

Perturbations are on the right throughout: Delta_true = Delta exp(eps), eps ~ N(0, covariance),
and Delta(b + db) ~ Delta(b) exp(bias_jacobian db).
"""
from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import torch

from .. import SGal3
from ..functional import blocks as B
from ..functional import checks, unobserved
from ..functional import sgal3 as F
from ..functional._blocking import _is_wrapped, is_compiling
from . import _kernels  # registers torch.ops.torchsgal.imu_preintegrate

STANDARD_GRAVITY = 9.80665  # m/s^2
EARTH_RATE = 7.292115e-5  # rad/s, WGS-84


# ------------------------------------------------------------------------------ inputs
def _dt_arg(dt, gyro):
    """A number dt (one sampling interval for every sample) as a tensor (..., K) like gyro's,
    filled on its device; tensors are left to _check_stream."""
    if isinstance(dt, numbers.Real) and not isinstance(dt, bool) and isinstance(gyro, torch.Tensor):
        checks.floating(gyro, "gyro")
        dt = checks.finite_number(dt, "dt", ">= 0")  # inf gave a NaN increment
        return torch.full(gyro.shape[:-1], dt, dtype=gyro.dtype, device=gyro.device)
    if not isinstance(dt, torch.Tensor):
        raise TypeError(f"dt must be a number or a tensor (..., K), got {type(dt).__name__}")
    return dt


def _check_stream(gyro, acc, dt):
    checks.vector(gyro, 3, "gyro")
    checks.vector(acc, 3, "acc")
    checks.floating(dt, "dt")
    checks.same_device_dtype(gyro=gyro, acc=acc, dt=dt)
    if gyro.dim() < 2:
        raise ValueError(f"gyro must have shape (..., K, 3) with K samples, got {tuple(gyro.shape)}")
    if gyro.shape[-2] == 0:
        raise ValueError(f"gyro must hold at least one sample (K >= 1), got shape {tuple(gyro.shape)}")
    if gyro.shape != acc.shape:
        raise ValueError(f"acc must have the shape of gyro {tuple(gyro.shape)}, got {tuple(acc.shape)}")
    if dt.dim() < 1 or dt.shape[-1] != gyro.shape[-2]:
        raise ValueError(
            f"dt must have shape (..., K) with K = {gyro.shape[-2]} (the samples of gyro), "
            f"got {tuple(dt.shape)}"
        )
    batch = checks.broadcast_batch(gyro=gyro.shape[:-2], dt=dt.shape[:-1])
    if batch != gyro.shape[:-2]:
        raise ValueError(
            f"dt's batch shape {tuple(dt.shape[:-1])} must broadcast to gyro's {tuple(gyro.shape[:-2])}"
        )
    return batch


def _as_vector(x, like: torch.Tensor, name: str, batch, like_name: str = "gyro") -> torch.Tensor:
    """A bias or noise density: None (zero), a float, or a tensor (..., 3) broadcasting to batch;
    ``like_name`` names the tensor ``like`` whose dtype and device it must have."""
    if x is None:
        x = 0.0
    if not isinstance(x, torch.Tensor):
        if isinstance(x, bool) or not isinstance(x, numbers.Real):
            raise TypeError(f"{name} must be None, a float or a tensor (..., 3), got "
                            f"{type(x).__name__}")
        return torch.full((3,), checks.finite_number(x, name), dtype=like.dtype, device=like.device)
    checks.vector(x, 3, name)
    checks.same_device_dtype(**{like_name: like, name: x})
    checks.broadcast_batch(stream=batch, **{name: x.shape[:-1]})
    return x


def _readable(t: torch.Tensor) -> bool:
    """Whether a data check may read ``t``: a plain CPU tensor (no host sync), outside
    functorch transforms and compilation (the rule of functional/_blocking.unobserved, with
    autograd allowed: reading values does not disturb it)."""
    return (type(t) is torch.Tensor and t.device.type == "cpu" and not is_compiling()
            and not _is_wrapped(t))


def _check_non_negative(t: torch.Tensor, name: str) -> None:
    """Raise if a readable tensor has negative, infinite or NaN entries; see ``_readable``."""
    if _readable(t) and t.numel():
        ok = (t >= 0) & t.isfinite()
        if not bool(ok.all()):
            bad = t.detach()[~ok]
            raise ValueError(f"{name} must be finite and >= 0 everywhere, got {bad.numel()} "
                             f"negative, infinite or NaN entries (first {float(bad[0]):.3g})")


def increment_tangents(gyro, acc, dt, gyro_bias=None, acc_bias=None) -> torch.Tensor:
    """Tangents (..., K, 10) of the K factors exp((U(omega - b_g, f - b_a) + N) dt).

    gyro, acc (..., K, 3) body rate [rad/s] and specific force [m/s^2]; dt (..., K) [s];
    biases (..., 3) or None."""
    dt = _dt_arg(dt, gyro)
    batch = _check_stream(gyro, acc, dt)
    b_g = _as_vector(gyro_bias, gyro, "gyro_bias", batch).unsqueeze(-2)
    b_a = _as_vector(acc_bias, gyro, "acc_bias", batch).unsqueeze(-2)
    h = dt.unsqueeze(-1)
    # out of place: under vmap any one of the arguments may be the batched one
    nu, phi, hh = torch.broadcast_tensors((acc - b_a) * h, (gyro - b_g) * h, h)
    return torch.cat((torch.zeros_like(nu), nu, phi, hh[..., :1]), dim=-1)


# --------------------------------------------------------------------------- products
def _along(E: torch.Tensor, axis: int, index) -> torch.Tensor:
    """E indexed by ``index`` (an int or a slice) on ``axis`` (non-negative)."""
    return E[(slice(None),) * axis + (index,)]


def _pair_products(E: torch.Tensor, mul, axis: int) -> torch.Tensor:
    """E_0 E_1, E_2 E_3, ... along ``axis`` (an odd tail kept): ceil(K/2) factors."""
    K = E.shape[axis]
    head = mul(_along(E, axis, slice(0, K - 1, 2)), _along(E, axis, slice(1, K, 2)))
    if K % 2:
        head = torch.cat((head, _along(E, axis, slice(K - 1, None))), dim=axis)
    return head


def _window_product(E: torch.Tensor, mul, axis: int) -> torch.Tensor:
    while E.shape[axis] > 1:
        E = _pair_products(E, mul, axis)
    return _along(E, axis, 0)


def _suffix_products(E: torch.Tensor, mul, axis: int, identity: torch.Tensor) -> torch.Tensor:
    """S_k = E_k ... E_{K-1} along ``axis``; ``identity`` broadcasts against one factor."""
    K = E.shape[axis]
    if K == 1:
        return E
    S_pairs = _suffix_products(_pair_products(E, mul, axis), mul, axis, identity)  # S_pairs[j] = S_{2j}
    # S_{2j+1} = E_{2j+1} S_{2j+2}, with S_K = I.
    n_odd = K // 2
    one = identity.expand_as(_along(S_pairs, axis, slice(0, 1)))
    odd = mul(_along(E, axis, slice(1, None, 2)),
              _along(torch.cat((S_pairs, one), dim=axis), axis, slice(1, n_odd + 1)))
    inter = torch.stack((_along(S_pairs, axis, slice(0, n_odd)), odd), dim=axis + 1).flatten(axis, axis + 1)
    return torch.cat((inter, _along(S_pairs, axis, slice(n_odd, None))), dim=axis) if K % 2 else inter


def _check_chain(E, name: str = "E") -> None:
    checks.floating(E, name)
    if E.dim() < 3 or E.shape[-1] != E.shape[-2]:
        raise ValueError(f"{name} must have shape (..., K, n, n) (K square matrices), got "
                         f"{tuple(E.shape)}")


def window_product(E: torch.Tensor) -> torch.Tensor:
    """E_0 E_1 ... E_{K-1} of (..., K, n, n) by a log-depth tree of batched products; the
    identity (..., n, n) for an empty chain (K = 0)."""
    _check_chain(E)
    if E.shape[-3] == 0:
        eye = torch.eye(E.shape[-1], dtype=E.dtype, device=E.device)
        return eye.expand(*E.shape[:-3], *eye.shape).clone()
    return _window_product(E, torch.matmul, E.dim() - 3)


def suffix_products(E: torch.Tensor) -> torch.Tensor:
    """S_k = E_k E_{k+1} ... E_{K-1} for k = 0..K-1 of (..., K, n, n) (a work-efficient parallel
    scan: 2 log2 K levels of batched products, about 2K products in all); empty (..., 0, n, n)
    for an empty chain (K = 0)."""
    _check_chain(E)
    if E.shape[-3] == 0:
        return E.clone()
    eye = torch.eye(E.shape[-1], dtype=E.dtype, device=E.device)
    return _suffix_products(E, torch.matmul, E.dim() - 3, eye)


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


def _density(x, like: torch.Tensor, name: str):
    """A noise density: a finite number >= 0, returned as a Python float (no host-to-device copy
    of a scalar), or a tensor (0-d or per axis) of the dtype and device of ``like`` (the gyro),
    with its negative entries refused where reading them costs no host sync (``_readable``)."""
    if isinstance(x, torch.Tensor):
        checks.floating(x, name)
        checks.same_device_dtype(gyro=like, **{name: x})
        _check_non_negative(x, name)
        return x
    if isinstance(x, bool) or not isinstance(x, numbers.Real):
        raise TypeError(f"{name} must be a finite number >= 0 or a tensor (0-d or (..., 3)), got {x!r}")
    return checks.finite_number(x, name, ">= 0")


def _per_axis(s, like: torch.Tensor, name: str) -> torch.Tensor:
    """A density from ``_density`` as a tensor (..., 3): a number or a 0-d tensor on every axis."""
    if not isinstance(s, torch.Tensor):
        return like.new_full((3,), s)  # a fill on the device, no copy
    if s.dim() == 0:
        return s.expand(3)
    return checks.vector(s, 3, name)


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


# -------------------------------------------------------------------------- results
@dataclass
class Preintegration:
    """The result of :func:`preintegrate` for a batch of windows.

    delta          SGal3 (...): the increment (frame at the window's end seen from its start,
                   gravity-free; its time is the window length).
    covariance     (..., 10, 10) or None: right perturbation, Delta_true = delta exp(eps),
                   tangent [rho, nu, phi, iota].  With the default time_noise_density=0
                   (exact timestamps) its iota row and column are zero: it is singular
                   (rank 9).  ``ConcentratedGaussian(delta, covariance)`` takes it (the
                   zero row marks the exactly known time: sampling, a 9-dof NEES and the
                   density on the supported subspace); by hand, use the 9-dof block
                   ``covariance[..., :9, :9]`` with eps[..., :9], or integrate with a
                   time_noise_density > 0.
    bias_jacobian  (..., 10, 6) or None: Delta(b + db) ~ delta exp(bias_jacobian db) with
                   db = [db_g, db_a] (gyro bias first).
    gyro_bias, acc_bias (..., 3): the biases the window was integrated with.

    ``...`` is the batch shape of the windows (``batch_shape``).  Indexing (``pre[w]``,
    ``pre[:, w]``, ``pre[..., 0]``, a slice, an index or mask tensor) indexes those batch axes
    of every field alike and returns a Preintegration.  Window-by-window dead reckoning from
    windows of batch (R, W) (R runs of W consecutive windows), each predicted from the last:

        pre = preintegrate(gyro, acc, dt, gyro_noise_density=s_g, acc_noise_density=s_a,
                           time_noise_density=s_t)       # gyro, acc (R, W, K, 3), dt (R, W, K)
        X, P = start, start_covariance                   # SGal3 (R,), (R, 10, 10)
        for w in range(W):
            X, P = pre[:, w].predict(X, g), pre[:, w].predict_covariance(X, P, g)
    """

    delta: SGal3
    covariance: torch.Tensor | None
    bias_jacobian: torch.Tensor | None
    gyro_bias: torch.Tensor
    acc_bias: torch.Tensor

    @property
    def batch_shape(self) -> torch.Size:
        """The batch shape of the windows, that of ``delta``."""
        return self.delta.batch_shape

    def __getitem__(self, index) -> Preintegration:
        """The windows ``index`` of the batch (ints, slices, None, Ellipsis, index or mask
        tensors over the batch axes, as for ``SGal3``), every field indexed alike: delta
        (...'), covariance (...', 10, 10), bias_jacobian (...', 10, 6), the biases (...', 3),
        with ...' the indexed batch shape."""
        delta = self.delta[index]  # raises IndexError naming the batch shape if it does not fit
        batch = self.delta.batch_shape
        idx = index if isinstance(index, tuple) else (index,)

        def pick(t, tail, name):
            if t is None:
                return None
            try:
                t = t.expand(*batch, *tail)
            except RuntimeError:
                raise ValueError(f"{name} of shape {tuple(t.shape)} does not broadcast to the "
                                 f"batch shape {tuple(batch)} of delta (expected (..., "
                                 f"{', '.join(map(str, tail))}))") from None
            return t[idx + (slice(None),) * len(tail)]
        return Preintegration(delta, pick(self.covariance, (10, 10), "covariance"),
                              pick(self.bias_jacobian, (10, 6), "bias_jacobian"),
                              pick(self.gyro_bias, (3,), "gyro_bias"),
                              pick(self.acc_bias, (3,), "acc_bias"))

    def duration(self) -> torch.Tensor:
        """Window length (...), the time part of the increment."""
        return self.delta.time()

    def corrected(self, gyro_bias=None, acc_bias=None) -> SGal3:
        """First-order bias update without re-integration: delta exp(J [b_g - b_g0, b_a - b_a0]).

        A bias left as None keeps the integration value."""
        if self.bias_jacobian is None:
            raise ValueError("bias_jacobian is None: preintegrate with bias_jacobian=True")
        batch = self.delta.batch_shape
        like = "the preintegration (its delta)"
        g = self.gyro_bias if gyro_bias is None else _as_vector(gyro_bias, self.gyro_bias, "gyro_bias", batch, like)
        a = self.acc_bias if acc_bias is None else _as_vector(acc_bias, self.acc_bias, "acc_bias", batch, like)
        db = torch.cat(torch.broadcast_tensors(g - self.gyro_bias, a - self.acc_bias), dim=-1)
        return self.delta.rplus((self.bias_jacobian @ db.unsqueeze(-1)).squeeze(-1))

    def predict_covariance(self, start: SGal3, start_covariance: torch.Tensor, gravity: torch.Tensor,
                           earth_rate=None) -> torch.Tensor:
        """Covariance (..., 10, 10) of the predicted state (right perturbation), from the start's
        (right perturbation) and the increment's, taken independent:
        J_s Sigma_i J_s^T + J_d Sigma_Delta J_d^T with (J_s, J_d) = :func:`predict_jacobians`.
        It is singular in the time component when both the start's time variance and the
        increment's (time_noise_density=0) are zero; see :class:`Preintegration`."""
        if self.covariance is None:
            raise ValueError("covariance is None: preintegrate with covariance=True")
        checks.matrix(start_covariance, 10, "start_covariance")
        checks.same_device_dtype(delta=self.delta.as_matrix(), start_covariance=start_covariance)
        J_start, J_delta = predict_jacobians(start, self.delta, gravity, earth_rate)
        checks.broadcast_batch(prediction=J_start.shape[:-2],
                               start_covariance=start_covariance.shape[:-2])
        return (J_start @ start_covariance @ J_start.transpose(-1, -2)
                + J_delta @ self.covariance @ J_delta.transpose(-1, -2))

    def predict(self, start: SGal3, gravity: torch.Tensor, earth_rate=None,
                gyro_bias=None, acc_bias=None) -> SGal3:
        """The state at the window's end; see :func:`predict`.  With biases given, the
        increment is first corrected to them (:meth:`corrected`)."""
        delta = self.delta if gyro_bias is None and acc_bias is None else self.corrected(gyro_bias, acc_bias)
        return predict(start, delta, gravity, earth_rate)


# ------------------------------------------------------------------------ preintegrate
def preintegrate(
    gyro: torch.Tensor,
    acc: torch.Tensor,
    dt: torch.Tensor,
    gyro_bias=None,
    acc_bias=None,
    gyro_noise_density=0.0,
    acc_noise_density=0.0,
    time_noise_density=0.0,
    covariance: bool = True,
    bias_jacobian: bool = True,
) -> Preintegration:
    """Batched Galilean preintegration of windows of K samples.

    gyro (..., K, 3) [rad/s] and acc (..., K, 3) [m/s^2, specific force] in the body frame,
    constant over sample k's interval dt (..., K) [s] (a number: the same for every sample;
    dt may vary; dt >= 0, zero allowed: a
    negative or non-finite dt raises ValueError, checked where reading it costs no host sync,
    that is on CPU outside torch.func transforms and compilation).  Biases (..., 3) or None.

    Noise densities (continuous time), each >= 0: gyro [rad/s/sqrt(Hz)] and accelerometer
    [m/s^2/sqrt(Hz)] as numbers or 0-d tensors (isotropic: the covariance is then summed in closed
    form, since C C^T = I) or per-axis tensors (..., 3) (general path: 6-10x slower than the
    isotropic one, 1,000 windows x 200 samples on one CPU thread);
    a per-axis density's batch broadcasts with the windows' and widens the result's batch, as a
    bias's does.  The clock [s/s/sqrt(Hz)] (a number or a 0-d tensor: white noise on the rate of
    time, entering iota; 0 = exact timestamps).  A tensor density must have gyro's dtype and
    device; a number is used as a Python float (no copy to the device); a negative or
    non-finite number raises ValueError, and so do negative or non-finite tensor entries where
    reading them costs no host sync (as for dt).  The model is continuous-time white noise n(s) on the
    signals, entering the tangent as G n = [0, -n_a, -n_g, n_t] (Q_c = diag(s_a^2, s_g^2, s_t^2)).
    With time_noise_density=0 (the default) the window length is exact, so the covariance's
    iota row and column are zero and the 10 x 10 covariance is singular (rank 9): invert or
    Cholesky-factor only its 9-dof block ``covariance[..., :9, :9]`` (and use eps[..., :9] in a
    NEES), use ``ConcentratedGaussian``, which treats the zero row as a known direction, or
    give a time_noise_density > 0.

    Covariance (right perturbation, Delta_true = Delta exp(eps), tangent [rho, nu, phi, iota]):
    to first order eps = int_0^T Ad(Delta^-1 Delta(s)) G n(s) ds, so
    Sigma = int_0^T Ad(Delta^-1 Delta(s)) G Q_c G^T Ad(Delta^-1 Delta(s))^T ds (G: the nu, phi,
    iota columns); per sample, the recursion Sigma_{k+1} = Ad(E_k^-1) Sigma_k Ad(E_k^-1)^T + Q_k
    with Q_k the integral over sample k alone.  A sampled IMU's noise, held constant over each
    sample (variance s^2 / dt, as GTSAM and the tests' Monte Carlo model it), gives a slightly
    smaller position block: at rest, the accelerometer part is s_a^2 dt^3 (K^3/3 - K/12)
    there against s_a^2 dt^3 K^3/3 here, a factor 1 / (1 - 1/(4 K^2)) (4/3 for K = 1, 1.004
    for K = 8, 1 + 2.5e-5 for K = 100); on windows of a few samples, prefer the
    held-noise model if that is how the noise arises.  The integral is evaluated by
    Simpson's rule on each sample interval (nodes at the instants and midpoints): exact for the
    parts of the integrand that are cubic in time, error O(dt^4) over the window.  (On a
    one-sample window the gyro-noise part of the position block, quartic in time, is 1/24 of
    itself off the integral.)  The bias Jacobian is the same integral of Ad(Delta^-1 Delta(s)) G
    (minus the gyro and accelerometer columns), on the same nodes.

    Accuracy: the increment is exact for piecewise-constant inputs, for any dt.  The covariance
    and the bias Jacobian are not: Simpson's error on a sample grows with its rotation angle
    |omega - b_g| dt, as its fourth power where it exceeds the rotation-free O(dt^4) terms.
    Measured on 4-sample windows (dt = 0.05 s, specific force ~5 m/s^2) against a fine
    quadrature of the integral and central differences of re-integration, for an angle per
    sample of 0.1 / 1 / pi / 2 pi rad: covariance error 5e-7 / 6e-6 / 2e-4 / 1.3e-3 (entries
    over the product of the standard deviations), bias Jacobian error 9e-8 / 2.5e-4 /
    2e-2 to 5e-2 / 0.6 (relative to its largest entry).  Keep the angle per sample well below
    1 rad where these matter.

    Products: one batched SGal3 exp over all samples, then a log-depth tree product (increment
    only) or, with covariance or bias Jacobians, the exps of the half-sample tangents, squared,
    and a work-efficient parallel scan over K; no loop over samples or windows.  The factors
    stay in SGal3's packed component layout (functional.sgal3.exp_packed / compose_packed),
    where a product is elementwise: several times faster on CPU than batched 5x5 matmuls.
    On CPU with nothing recording (no autograd, functorch transform or compile) the same
    arithmetic runs in place and in blocks of windows (_integrate_fast, docs/guide/imu.md), or, where
    the optional C kernels were built and the covariance is isotropic or not asked for, as a C
    loop over each window's samples in double precision (imu/_native_imu.h), both through the
    torch operator torch.ops.torchsgal.imu_preintegrate (imu/_kernels.py).
    """
    covariance = checks.boolean(covariance, "covariance")
    bias_jacobian = checks.boolean(bias_jacobian, "bias_jacobian")
    dt = _dt_arg(dt, gyro)
    batch = _check_stream(gyro, acc, dt)
    _check_non_negative(dt, "dt")
    b_g = _as_vector(gyro_bias, gyro, "gyro_bias", batch)
    b_a = _as_vector(acc_bias, gyro, "acc_bias", batch)
    batch = torch.broadcast_shapes(batch, b_g.shape[:-1], b_a.shape[:-1])
    s_t = _density(time_noise_density, gyro, "time_noise_density")
    if isinstance(s_t, torch.Tensor) and s_t.dim() != 0:
        raise ValueError(f"time_noise_density must be a float or a 0-d tensor, got shape {tuple(s_t.shape)}")
    s_a = _density(acc_noise_density, gyro, "acc_noise_density")
    s_g = _density(gyro_noise_density, gyro, "gyro_noise_density")
    isotropic = all(not isinstance(d, torch.Tensor) or d.dim() == 0 for d in (s_a, s_g))
    if not isotropic:
        s_a, s_g = _per_axis(s_a, gyro, "acc_noise_density"), _per_axis(s_g, gyro, "gyro_noise_density")
        # the densities' batch widens the windows' like the biases' does
        batch = checks.broadcast_batch(stream=batch, acc_noise_density=s_a.shape[:-1],
                                       gyro_noise_density=s_g.shape[:-1])
        s_a, s_g = s_a.expand(*batch, 3), s_g.expand(*batch, 3)
    b_g, b_a = b_g.expand(*batch, 3), b_a.expand(*batch, 3)
    args = (gyro, acc, dt, b_g, b_a, s_a, s_g)
    if unobserved([a for a in args + (s_t,) if isinstance(a, torch.Tensor)]) and math.prod(batch) > 0:
        delta, cov, jac = _integrate_fast(args, batch, s_t, isotropic, covariance, bias_jacobian)
    else:
        delta, cov, jac = _integrate(*args, s_t, isotropic, covariance, bias_jacobian)
    return Preintegration(SGal3(delta), cov, jac, b_g, b_a)


# ------------------------------------------------------------------- fast CPU path
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


def _weights(dt: torch.Tensor):
    """Simpson weights (..., K + 1) of the instants and (..., K) of the midpoints."""
    zero = torch.zeros_like(dt[..., :1])
    return (torch.cat((dt, zero), -1) + torch.cat((zero, dt), -1)) / 6.0, 4.0 * dt / 6.0


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


def _integrate(gyro, acc, dt, b_g, b_a, s_a, s_g, s_t, isotropic, covariance, bias_jacobian):
    """(delta matrices (..., 5, 5), covariance or None, bias Jacobian or None) of the windows;
    biases (..., 3) broadcast to the windows' batch; densities validated by preintegrate."""
    xi = increment_tangents(gyro, acc, dt, b_g, b_a)
    batch, K = xi.shape[:-2], xi.shape[-2]
    # Products in the packed layout (16, K, ...): chain axis first, contiguous halves for the scans.
    if not (covariance or bias_jacobian):
        E = F.exp_packed(xi.movedim(-2, 0))
        return F.unpack(_window_product(E, F.compose_packed, 1)), None, None

    H = F.exp_packed(0.5 * xi.movedim(-2, 0))  # half-sample factors: E_k = H_k H_k exactly
    S = _suffix_products(F.compose_packed(H, H), F.compose_packed, 1, F.packed_identity(H))  # E_k ... E_{K-1}
    delta = F.unpack(S[:, 0])
    # Simpson nodes of the noise integral in the right perturbation: at the sample instants
    # Delta^-1 Delta(t_k) = S_k^-1 (S_K = I) and at the midpoints (H_k S_{k+1})^-1.
    w_instants, w_mid = _weights(dt.expand(*batch, K))  # K + 1, K
    last = lambda P: P.movedim(1, -1).contiguous()  # noqa: E731  node axis last, for the sums over nodes
    node_groups = [  # (packed suffixes X (16, ..., n), weights (..., n)): the nodes are X^-1
        (last(S), w_instants[..., :K]),  # instants 0 .. K-1
        (last(H[:, K - 1 :]), w_mid[..., K - 1 :]),  # last midpoint: H_{K-1} S_K = H_{K-1}
    ]
    if K > 1:
        node_groups.append((last(F.compose_packed(H[:, : K - 1], S[:, 1:])), w_mid[..., : K - 1]))
    # instant K is the identity: its node map is G itself, weight w_instants[..., K]
    cov = jac = None
    if covariance and not isotropic:
        cov = _general_covariance(node_groups, w_instants[..., K], s_a, s_g, s_t)
    if (covariance and isotropic) or bias_jacobian:
        moments = _node_moments(node_groups, w_instants[..., K])
        if covariance and isotropic:
            cov = _isotropic_covariance(moments, s_a, s_g, s_t)
        if bias_jacobian:
            jac = _bias_jacobian(moments)
    return delta, cov, jac


# ---------------------------------------------------------------------------- gravity
def gravity_vector(frame: str = "z_up", magnitude: float = STANDARD_GRAVITY, dtype=None, device=None):
    """Gravity in the navigation frame: z-up (ENU) (0, 0, -g) or NED (0, 0, +g)."""
    if frame not in ("z_up", "ned"):
        raise ValueError(f"frame must be 'z_up' or 'ned', got {frame!r}")
    magnitude = checks.finite_number(magnitude, "magnitude")
    dtype = checks.dtype_arg(dtype or torch.get_default_dtype())
    sign = -1.0 if frame == "z_up" else 1.0
    return _filled_vector([0.0, 0.0, sign * magnitude], dtype, device)


def earth_rate_vector(latitude: float, frame: str = "z_up", rate: float = EARTH_RATE, dtype=None, device=None):
    """The Earth's rotation in a local-level frame at ``latitude`` [rad]: ENU (x east, y north,
    z up) (0, W cos L, W sin L); NED (W cos L, 0, -W sin L)."""
    if frame not in ("z_up", "ned"):
        raise ValueError(f"frame must be 'z_up' or 'ned', got {frame!r}")
    latitude = checks.finite_number(latitude, "latitude")
    rate = checks.finite_number(rate, "rate")
    dtype = checks.dtype_arg(dtype or torch.get_default_dtype())
    c, s = rate * math.cos(latitude), rate * math.sin(latitude)
    return _filled_vector([0.0, c, s] if frame == "z_up" else [c, 0.0, -s], dtype, device)


def _filled_vector(values: list, dtype, device) -> torch.Tensor:
    """A small constant vector filled on the device (torch.tensor(list, device=cuda) is a
    blocking host-to-device copy)."""
    vec = torch.zeros(len(values), dtype=dtype, device=device)
    for i, v in enumerate(values):
        if v:
            vec[i].fill_(v)  # vec[i] = v would copy a CPU scalar tensor (blocking on CUDA)
    return vec


def _time_shift(t: torch.Tensor) -> SGal3:
    """S(t) = exp(t N): the pure time translation."""
    z = torch.zeros(*t.shape, 9, dtype=t.dtype, device=t.device)
    return SGal3.exp(torch.cat((z, t.unsqueeze(-1)), dim=-1))


def predict(start: SGal3, delta: SGal3, gravity: torch.Tensor, earth_rate=None) -> SGal3:
    """State at the window's end from the state X_i = (R, v, p, t) at its start.

    The navigation frame is a local-level frame with constant gravity g (..., 3) (from
    :func:`gravity_vector`) and optionally rotating at the constant rate Omega (..., 3)
    (mahony (29), with the sign of g_A e3 corrected, see docs/guide/imu.md):

        Xdot = X (U(omega, f) + N) - U(Omega, 0) X + [[0, g, 0], [0, 0, 0], [0, 0, 0]].

    Its exact solution for piecewise-constant inputs is X_j = L X_i Delta with

        L = S(t_j) exp([0, g T, -Omega T, -T]) S(-t_i),   T = Delta's time, t_j = t_i + T,

    where S(t) = exp(t N) is a time shift: gravity and the Earth's rotation are left factors,
    the IMU increment a right factor.  Without Earth rotation this is R_j = R_i dR,
    v_j = v_i + g T + R_i dv, p_j = p_i + v_i T + g T^2 / 2 + R_i dp, t_j = t_i + T.
    """
    A, t_i, start0 = _prediction_factors(start, delta, gravity, earth_rate)
    return _time_shift(t_i).compose(A).compose(start0).compose(delta)  # compose: traceable by dynamo


def _prediction_factors(start, delta, gravity, earth_rate):
    """(A, t_i, X_i0) with X_j = S(t_i) A X_i0 Delta: A = S(T) exp([0, g T, -Omega T, -T]) and
    X_i0 = S(-t_i) X_i (the start with its time set to zero)."""
    if not isinstance(start, SGal3):
        raise TypeError(f"start must be a SGal3, got {type(start).__name__}")
    if not isinstance(delta, SGal3):
        raise TypeError(f"delta must be a SGal3, got {type(delta).__name__}")
    ref = delta.as_matrix()
    checks.same_device_dtype(delta=ref, start=start.as_matrix())
    checks.vector(gravity, 3, "gravity")
    checks.same_device_dtype(delta=ref, gravity=gravity)
    if earth_rate is None:
        earth_rate = torch.zeros_like(gravity)
    else:
        checks.vector(earth_rate, 3, "earth_rate")
        checks.same_device_dtype(delta=ref, earth_rate=earth_rate)
    batch = checks.broadcast_batch(start=start.batch_shape, delta=delta.batch_shape,
                                   gravity=gravity.shape[:-1], earth_rate=earth_rate.shape[:-1])
    g, w = torch.broadcast_tensors(gravity.expand(*batch, 3), earth_rate.expand(*batch, 3))
    T = delta.time().unsqueeze(-1).expand(*batch, 1)
    A = _time_shift(T[..., 0]).compose(SGal3.exp(torch.cat((torch.zeros_like(g), g * T, -w * T, -T), dim=-1)))
    t_i = start.time().expand(batch)
    return A, t_i, _time_shift(-t_i).compose(start)


def predict_jacobians(start: SGal3, delta: SGal3, gravity: torch.Tensor, earth_rate=None):
    """(J_start, J_delta), each (..., 10, 10): first-order maps of right perturbations
    X_i exp(e_i) and Delta exp(d) to the predicted state's, X_j exp(J_start e_i + J_delta d).

    Both time perturbations move the left factor: with A(T) = S(T) exp(T h), h = [0, g, -Omega, -1],
    S(iota) A S(-iota) = A exp(iota (Ad(A^-1) - I) e_iota) and A(T + iota) = S(iota) A exp(iota h),
    so besides Ad(Delta^-1) and I the iota columns gain Ad((X_i0 Delta)^-1) u with
    u = Ad(A^-1) e_iota - e_iota (start) and u + [0, g, -Omega, 0] (increment)."""
    A, _, start0 = _prediction_factors(start, delta, gravity, earth_rate)
    batch = A.batch_shape
    back = start0.compose(delta).inverse().adjoint()  # Ad((X_i0 Delta)^-1)
    u = A.inverse().adjoint()[..., :, 9].clone()
    u[..., 9] -= 1.0
    g = gravity.expand(*batch, 3)
    w = earth_rate.expand(*batch, 3) if earth_rate is not None else torch.zeros_like(g)
    u_delta = u + torch.cat((torch.zeros_like(g), g, -w, torch.zeros_like(g[..., :1])), dim=-1)
    # the iota columns built out of place (under vmap any argument may be the batched one)
    Ad = delta.inverse().adjoint().expand(*batch, 10, 10)
    eye = torch.eye(10, dtype=u.dtype, device=u.device).expand(*batch, 10, 10)
    J_start = torch.cat((Ad[..., :9], Ad[..., 9:] + back @ u.unsqueeze(-1)), dim=-1)
    J_delta = torch.cat((eye[..., :9], eye[..., 9:] + back @ u_delta.unsqueeze(-1)), dim=-1)
    return J_start, J_delta
