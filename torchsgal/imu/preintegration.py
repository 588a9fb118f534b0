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

This module holds the input checks, :func:`preintegrate` with its plain (differentiable) path
and the :class:`Preintegration` result; the chain products are in products.py, the noise map and
the node sums of the covariance and bias Jacobian in moments.py, the fast CPU path in
_fast_path.py and the prediction with gravity in prediction.py.
"""
from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import torch

from .. import SGal3
from ..functional import checks, unobserved
from ..functional import sgal3 as F
from ..functional._blocking import _is_wrapped, is_compiling

# ``name as name``: the public names of products.py, moments.py and prediction.py stay
# importable from this module
from ._fast_path import _integrate_fast
from .moments import _bias_jacobian, _general_covariance, _isotropic_covariance, _node_moments, _weights
from .moments import noise_map as noise_map
from .prediction import EARTH_RATE as EARTH_RATE
from .prediction import STANDARD_GRAVITY as STANDARD_GRAVITY
from .prediction import earth_rate_vector as earth_rate_vector
from .prediction import gravity_vector as gravity_vector
from .prediction import predict, predict_jacobians
from .products import _suffix_products, _window_product
from .products import suffix_products as suffix_products
from .products import window_product as window_product


# ------------------------------------------------------------------------------ inputs
def _dt_arg(dt, gyro):
    """A number dt (one sampling interval for every sample) as a tensor (..., K) like gyro's,
    filled on its device; tensors are left to _check_stream."""
    if isinstance(dt, numbers.Real) and not isinstance(dt, bool):
        checks.floating(gyro, "gyro")  # a non-tensor gyro is named (not the valid number dt)
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


def _check_non_negative(t: torch.Tensor, name: str, positive: bool = False) -> None:
    """Raise if a readable tensor has negative (with ``positive``: or zero), infinite or NaN
    entries; see ``_readable``."""
    if _readable(t) and t.numel():
        ok = ((t > 0) if positive else (t >= 0)) & t.isfinite()
        if not bool(ok.all()):
            bad = t.detach()[~ok]
            raise ValueError(f"{name} must be finite and {'>' if positive else '>='} 0 everywhere, "
                             f"got {bad.numel()} {'zero, ' if positive else ''}negative, infinite "
                             f"or NaN entries (first {float(bad[0]):.3g})")


def increment_tangents(gyro, acc, dt, gyro_bias=None, acc_bias=None) -> torch.Tensor:
    """Tangents (..., K, 10) of the K factors exp((U(omega - b_g, f - b_a) + N) dt).

    gyro, acc (..., K, 3) body rate [rad/s] and specific force [m/s^2]; dt (..., K) [s] or a
    number, checked as :func:`preintegrate`'s (>= 0 and finite, ValueError naming it);
    biases (..., 3) or None."""
    return _increment_tangents(gyro, acc, dt, gyro_bias, acc_bias, check_dt=True)


def _increment_tangents(gyro, acc, dt, gyro_bias=None, acc_bias=None,
                        check_dt: bool = False) -> torch.Tensor:
    """``increment_tangents``; dt's values are checked with ``check_dt`` (the library's callers
    checked them already)."""
    dt = _dt_arg(dt, gyro)
    batch = _check_stream(gyro, acc, dt)
    if check_dt:
        _check_non_negative(dt, "dt")
    b_g = _as_vector(gyro_bias, gyro, "gyro_bias", batch).unsqueeze(-2)
    b_a = _as_vector(acc_bias, gyro, "acc_bias", batch).unsqueeze(-2)
    h = dt.unsqueeze(-1)
    # out of place: under vmap any one of the arguments may be the batched one
    nu, phi, hh = torch.broadcast_tensors((acc - b_a) * h, (gyro - b_g) * h, h)
    return torch.cat((torch.zeros_like(nu), nu, phi, hh[..., :1]), dim=-1)


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
    batch = checks.broadcast_shapes(batch, b_g.shape[:-1], b_a.shape[:-1])
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
    # copies: the result must not follow in-place updates of the caller's biases
    b_g, b_a = b_g.expand(*batch, 3).clone(), b_a.expand(*batch, 3).clone()
    args = (gyro, acc, dt, b_g, b_a, s_a, s_g)
    if unobserved([a for a in args + (s_t,) if isinstance(a, torch.Tensor)]) and math.prod(batch) > 0:
        delta, cov, jac = _integrate_fast(args, batch, s_t, isotropic, covariance, bias_jacobian)
    else:
        delta, cov, jac = _integrate(*args, s_t, isotropic, covariance, bias_jacobian)
    return Preintegration(SGal3(delta), cov, jac, b_g, b_a)


def _integrate(gyro, acc, dt, b_g, b_a, s_a, s_g, s_t, isotropic, covariance, bias_jacobian):
    """(delta matrices (..., 5, 5), covariance or None, bias Jacobian or None) of the windows;
    biases (..., 3) broadcast to the windows' batch; densities validated by preintegrate."""
    xi = _increment_tangents(gyro, acc, dt, b_g, b_a)
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
