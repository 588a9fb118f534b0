"""Streaming Galilean preintegration: samples added as they arrive, batched over IMUs.

The window function :func:`~torchsgal.imu.preintegrate` integrates a whole window at once;
:class:`StreamingPreintegration` holds the running increment, its covariance and its bias
Jacobian and folds in one sample or a chunk of samples per call, with the same maths.

Composition rules (docs/guide/imu_streaming.md).  Split a window at an instant into a first
part (increment D1, covariance S1, bias Jacobian J1) and a second (D2, S2, J2).  The
covariance of the window is the integral of Ad(Delta^-1 Delta(s)) G Q_c G^T Ad(.)^T
(preintegration.py); for s in the first part Delta^-1 Delta(s) = D2^-1 (D1^-1 Delta(s)), for
s in the second it is the second part's own integrand, so

    Delta = D1 D2,   S = Ad(D2^-1) S1 Ad(D2^-1)^T + S2,   J = Ad(D2^-1) J1 + J2      (C1)

and the same for the bias Jacobian, the same integral of Ad(.) G_b.  The window function
evaluates the integral by Simpson's rule on each sample interval, so (C1) reproduces it to
rounding for any split at sample instants.  One sample of length h with half-sample factor H
(E = H H, the exact exp of the sample's tangent) contributes, with A = Ad(E^-1):

    S_k = h/6 (A Q A^T + 4 Ad(H^-1) Q Ad(H^-1)^T + Q),   J_k = h/6 (A + 4 Ad(H^-1) + I) G_b  (C2)

(Q = G Q_c G^T = diag(0, s_a^2 I, s_g^2 I, s_t^2), G_b = d tangent / d [b_g, b_a]).

Bias random walk: the bias deviation db (gyro first) is constant over each sample and takes a
step of covariance R h (R = diag(s_bg^2 I, s_ba^2 I)) at each sample's end, as in GTSAM's
PreintegratedCombinedMeasurements.  The error state [eps, db] then moves by
Phi = [[Ad(E^-1), J_k], [0, I]], and the combined covariance P = [[S, X], [X^T, B]] composes as

    S' = A S A^T + A X J^T + J X^T A^T + J B J^T + S_c,
    X' = A X + J B + X_c,   B' = B + B_c                                          (C3)

for a part (E, A = Ad(E^-1), J, S_c, X_c, B_c) appended to the running one: (C1) with the
cross terms.  Both are associative, so chunks are reduced by a log-depth tree over samples
(the parts and their composition: ``stream_parts``).  This S is the combined block
(``combined_covariance``); ``covariance`` and ``result()`` keep the (C1) S without the walk,
as ``preintegrate``'s (an ``ImuFactor`` beside a ``BiasRandomWalkFactor`` would count it twice).
"""
from __future__ import annotations

import numbers

import torch

from .. import SGal3
from ..functional import checks
from .preintegration import Preintegration, _increment_tangents, preintegrate
from .stream_parts import (
    _along,
    _combine,
    _constants,
    _half_factors,
    _noise_parts,
    _prefix_products,
    _reduce,
    _sample_parts,
)


def _density_vector(x, name: str, kw: dict) -> torch.Tensor:
    """A noise density: a number >= 0 or a tensor (..., 3) of entries >= 0, as a tensor (..., 3)."""
    if isinstance(x, torch.Tensor):
        checks.vector(x, 3, name)
        if x.dtype != kw["dtype"] or x.device != kw["device"]:
            raise TypeError(f"{name} must have dtype {kw['dtype']} on {kw['device']} (the "
                            f"accumulator's), got {x.dtype} on {x.device}")
        if x.device.type == "cpu" and not bool(((x >= 0) & x.isfinite()).all()):
            raise ValueError(f"{name} must be finite and >= 0 everywhere")
        return x.clone()
    return torch.full((3,), checks.finite_number(x, name, ">= 0"), **kw)


class StreamingPreintegration:
    """Preintegration of IMU samples as they arrive, for a batch of independent IMUs.

    ``batch_shape`` is the shape of the batch of IMUs; every call to :meth:`integrate` gives
    one sample per IMU (gyro, acc (*batch_shape, 3), dt (*batch_shape) or a number) or a chunk
    of K samples per IMU (gyro, acc (*batch_shape, K, 3), dt (*batch_shape, K) or a number).
    The running increment, covariance and bias Jacobian equal those of
    :func:`~torchsgal.imu.preintegrate` on all the samples so far, to rounding, however they
    were split into calls (the composition rules of this module's docstring).

    Biases (*batch_shape, 3) or numbers: the linearisation point, fixed until :meth:`reset`;
    a later bias estimate enters to first order through the bias Jacobian (:meth:`corrected`,
    :meth:`predict`, as GTSAM's ``biasCorrectedDelta`` / ``predict``).  Noise densities as in
    :func:`~torchsgal.imu.preintegrate` (numbers or per-axis tensors (..., 3)); bias random
    walks [rad/s^2/sqrt(Hz)], [m/s^3/sqrt(Hz)] give the combined covariance of
    :meth:`combined_covariance`.  ``validate`` (default True) checks each call's dt for
    finite, positive values and bias tensors for finite ones (one host read each on a GPU);
    False skips those reads.
    ``buffer_size`` samples are held before they are folded in (1: each call at once); any
    read (``delta``, ``covariance``, ``result()``, ...) folds in the held ones first.
    """

    def __init__(self, batch_shape=(), *, gyro_bias=None, acc_bias=None, gyro_noise_density=0.0,
                 acc_noise_density=0.0, time_noise_density=0.0, gyro_bias_random_walk=0.0,
                 acc_bias_random_walk=0.0, buffer_size: int = 256, dtype=None, device=None,
                 validate: bool = True):
        self.validate = checks.boolean(validate, "validate")
        self.buffer_size = checks.integer(buffer_size, "buffer_size", 1)
        if isinstance(batch_shape, numbers.Integral) and not isinstance(batch_shape, bool):
            batch_shape = (batch_shape,)
        if not isinstance(batch_shape, (tuple, list, torch.Size)) or not all(
                isinstance(n, numbers.Integral) and not isinstance(n, bool) and int(n) >= 0 for n in batch_shape):
            raise TypeError(f"batch_shape must be a tuple of integers >= 0, got {batch_shape!r}")
        self.batch_shape = torch.Size(batch_shape)
        dtype = checks.dtype_arg(dtype or torch.get_default_dtype())
        self._c = _constants(dtype, device)
        self._device = self._c.eye10.device
        kw = dict(dtype=dtype, device=self._device)
        self._kw = kw
        s_a = _density_vector(acc_noise_density, "acc_noise_density", kw)
        s_g = _density_vector(gyro_noise_density, "gyro_noise_density", kw)
        s_t = checks.finite_number(time_noise_density, "time_noise_density", ">= 0")
        batch = checks.broadcast_batch(imus=self.batch_shape, acc_noise_density=s_a.shape[:-1],
                                       gyro_noise_density=s_g.shape[:-1])
        if batch != self.batch_shape:
            raise ValueError(f"the noise densities' batch must broadcast to batch_shape "
                             f"{tuple(self.batch_shape)}, got {tuple(batch)}")
        self._dens = tuple(x if not isinstance(x, torch.Tensor) else d.expand(*batch, 3)
                           for x, d in ((acc_noise_density, s_a), (gyro_noise_density, s_g))) + (s_t,)
        s_a, s_g = s_a.expand(*batch, 3), s_g.expand(*batch, 3)
        zero = torch.zeros(*batch, 3, **kw)
        q = torch.cat((zero, s_a**2, s_g**2, torch.full((*batch, 1), s_t**2, **kw)), -1)
        sq = q.sqrt()
        self._sq2 = torch.cat((sq, 2.0 * sq), -1).unsqueeze(-2)  # (*batch, 1, 20), see _noise_parts
        self._Qd = torch.diag_embed(q)
        self._float_cache: dict = {}
        r_g = _density_vector(gyro_bias_random_walk, "gyro_bias_random_walk", kw)
        r_a = _density_vector(acc_bias_random_walk, "acc_bias_random_walk", kw)
        checks.broadcast_batch(imus=self.batch_shape, gyro_bias_random_walk=r_g.shape[:-1],
                               acc_bias_random_walk=r_a.shape[:-1])
        r = torch.cat(torch.broadcast_tensors(r_g, r_a), -1).expand(*batch, 6) ** 2
        zero_walk = r.device.type == "cpu" and not bool(r.any())
        self._r = None if zero_walk else r
        self.reset(gyro_bias, acc_bias)

    # ------------------------------------------------------------------------ state
    def reset(self, gyro_bias=None, acc_bias=None) -> None:
        """Start a new window (identity increment, zero covariance and bias Jacobian), with new
        biases if given (otherwise the current ones)."""
        kw, batch = self._kw, self.batch_shape
        old = getattr(self, "_bias", None)
        g = self._bias_arg(gyro_bias, "gyro_bias", None if old is None else old[..., :3])
        a = self._bias_arg(acc_bias, "acc_bias", None if old is None else old[..., 3:])
        self._bias = torch.cat((g, a), -1)
        self._delta = torch.eye(5, **kw).expand(*batch, 5, 5).clone()
        self._S = torch.zeros(*batch, 10, 10, **kw)
        self._J = torch.zeros(*batch, 10, 6, **kw)
        self._X = None if self._r is None else torch.zeros(*batch, 10, 6, **kw)
        self._B = None if self._r is None else torch.zeros(*batch, 6, 6, **kw)
        self._C = None if self._r is None else torch.zeros(*batch, 10, 10, **kw)
        self._count = 0
        self._pending: list = []
        self._pending_count = 0
        self._bias6 = self._bias.unsqueeze(-2)
        self._r6 = None if self._r is None else self._r.unsqueeze(-2)

    def _bias_arg(self, b, name: str, current) -> torch.Tensor:
        kw, batch = self._kw, self.batch_shape
        if b is None:
            return current if current is not None else torch.zeros(*batch, 3, **kw)
        if not isinstance(b, torch.Tensor):
            if isinstance(b, bool) or not isinstance(b, numbers.Real):
                raise TypeError(f"{name} must be None, a number or a tensor (*batch_shape, 3), got "
                                f"{type(b).__name__}")
            return torch.full((*batch, 3), checks.finite_number(b, name), **kw)
        checks.vector(b, 3, name)
        if b.dtype != kw["dtype"] or b.device != self._device:
            raise TypeError(f"{name} must have dtype {kw['dtype']} on {self._device} (the "
                            f"accumulator's), got {b.dtype} on {b.device}")
        if self.validate and not bool(b.isfinite().all()):  # once per window (a host read)
            raise ValueError(f"{name} must be finite, got non-finite entries")
        try:
            return b.expand(*batch, 3).clone()
        except RuntimeError:
            raise ValueError(f"{name} of shape {tuple(b.shape)} must broadcast to "
                             f"({', '.join(map(str, batch))}{', ' if batch else ''}3)") from None

    @property
    def num_samples(self) -> int:
        """The samples integrated since the last :meth:`reset`."""
        return self._count + self._pending_count

    @property
    def delta(self) -> SGal3:
        """The increment (*batch_shape) so far (the identity after :meth:`reset`)."""
        self._flush()
        return SGal3(self._delta)

    @property
    def covariance(self) -> torch.Tensor:
        """Covariance (*batch_shape, 10, 10) of the increment's right perturbation, as
        :func:`~torchsgal.imu.preintegrate`'s (bias random walk not included: the biases are
        those of the linearisation point, the walk is for a ``BiasRandomWalkFactor``; the
        combined model's block is ``combined_covariance()[..., :10, :10]``)."""
        self._flush()
        return self._S

    @property
    def bias_jacobian(self) -> torch.Tensor:
        """(*batch_shape, 10, 6): delta(b + db) ~ delta exp(J db), db = [db_g, db_a]."""
        self._flush()
        return self._J

    @property
    def gyro_bias(self) -> torch.Tensor:
        """The gyro bias (*batch_shape, 3) of the linearisation point."""
        return self._bias[..., :3]

    @property
    def acc_bias(self) -> torch.Tensor:
        """The accelerometer bias (*batch_shape, 3) of the linearisation point."""
        return self._bias[..., 3:]

    def combined_covariance(self) -> torch.Tensor:
        """(*batch_shape, 16, 16): the covariance of [eps, db_g, db_a] at the window's end, the
        increment's right perturbation eps (10) and the bias deviation (6) accumulated by the
        random walk over the window (model (C3); GTSAM's PreintegratedCombinedMeasurements
        in torchsgal's tangent and bias orders: see gtsam_interop)."""
        self._flush()
        kw, batch = self._kw, self.batch_shape
        if self._C is None or self._X is None or self._B is None:  # no random walk
            S, X, B = self._S, torch.zeros(*batch, 10, 6, **kw), torch.zeros(*batch, 6, 6, **kw)
        else:
            S, X, B = self._C, self._X, self._B
        return torch.cat((torch.cat((S, X), -1), torch.cat((X.mT, B), -1)), -2)

    def result(self) -> Preintegration:
        """The window so far as a :class:`~torchsgal.imu.Preintegration` (its ``corrected``,
        ``predict`` and ``predict_covariance`` apply), with :attr:`covariance` (no random walk)."""
        self._flush()
        return Preintegration(SGal3(self._delta), self._S, self._J, self.gyro_bias, self.acc_bias)

    def corrected(self, gyro_bias=None, acc_bias=None) -> SGal3:
        """The increment for other biases without re-integration, to first order:
        delta exp(J [b_g - b_g0, b_a - b_a0]) (error O(|db|^2))."""
        return self.result().corrected(gyro_bias, acc_bias)

    def predict(self, start: SGal3, gravity: torch.Tensor, earth_rate=None, gyro_bias=None,
                acc_bias=None) -> SGal3:
        """The state at the end of the window so far; see :func:`~torchsgal.imu.predict`."""
        return self.result().predict(start, gravity, earth_rate, gyro_bias, acc_bias)

    # -------------------------------------------------------------------- integrate
    def integrate(self, gyro: torch.Tensor, acc: torch.Tensor, dt: float | torch.Tensor,
                  intermediate: bool = False) -> SGal3 | None:
        """Add one sample per IMU (gyro, acc (*batch_shape, 3), dt (*batch_shape) or a number)
        or a chunk (gyro, acc (*batch_shape, K, 3), dt (*batch_shape, K) or a number)
        [rad/s, m/s^2, s], dt > 0.  With ``intermediate`` the increments after each sample of
        the call are returned, SGal3 (*batch_shape, K) (K = 1 for one sample), else None.

        Samples are held (copied) until ``buffer_size`` of them are pending or a result is
        read, then folded in as one chunk: the same result as folding each in at once."""
        intermediate = checks.boolean(intermediate, "intermediate")
        sample, dt, K, one = self._check_samples(gyro, acc, dt)
        if intermediate or self.buffer_size <= K:
            self._flush()
            if K == 1 and not intermediate:
                self._fold_one(sample if one else sample[..., 0, :],
                               dt if not isinstance(dt, torch.Tensor) else dt[..., 0])
                return None
            return self._fold(sample.unsqueeze(-2) if one else sample, self._dt_tensor([(dt, K)]),
                              intermediate)
        self._pending.append((sample, dt, K, one))
        self._pending_count += K
        if self._pending_count >= self.buffer_size:
            self._flush()
        return None

    def _dt_tensor(self, dts) -> torch.Tensor:
        """(*batch, K) from a list of (dt: float or tensor (*batch, k), k)."""
        kw, batch = self._kw, self.batch_shape
        if all(not isinstance(h, torch.Tensor) for h, _ in dts):
            runs: list = []  # (h, count) of equal consecutive dt: one fill each, no host copy
            for h, k in dts:
                if runs and runs[-1][0] == h:
                    runs[-1][1] += k
                else:
                    runs.append([h, k])
            flat = torch.cat([torch.full((k,), h, **kw) for h, k in runs]) if len(runs) > 1 \
                else torch.full((runs[0][1],), runs[0][0], **kw)
            return flat.expand(*batch, flat.shape[0])
        parts = [h if isinstance(h, torch.Tensor) else torch.full((*batch, k), h, **kw) for h, k in dts]
        return parts[0] if len(parts) == 1 else torch.cat(parts, -1)

    def _flush(self) -> None:
        if not self._pending:
            return
        pend, self._pending, self._pending_count = self._pending, [], 0
        if len(pend) == 1 and pend[0][2] == 1:
            sample, dt, _, one = pend[0]
            self._fold_one(sample if one else sample[..., 0, :],
                           dt if not isinstance(dt, torch.Tensor) else dt[..., 0])
            return
        if len(pend) == 1:  # one chunk (a single sample was folded above)
            sample = pend[0][0]
        elif all(p[3] for p in pend):  # single samples (*batch, 6): one stack along the sample axis
            sample = torch.stack([p[0] for p in pend], -2)
        else:
            sample = torch.cat([p[0].unsqueeze(-2) if p[3] else p[0] for p in pend], -2)
        self._fold(sample, self._dt_tensor([(h, k) for _, h, k, _ in pend]), False)

    def _fold(self, sample: torch.Tensor, dt: torch.Tensor, intermediate: bool):
        """Fold samples [gyro, acc] (*batch, K, 6), dt (*batch, K) into the state: one sample by
        (C2), a chunk by the window function (no random walk) or the tree of (C2) parts (C3),
        then (C1)/(C3) onto the running part."""
        gyro, acc = sample[..., :3], sample[..., 3:]
        K = sample.shape[-2]
        if K > 1 and self._r is None:
            pre = preintegrate(gyro, acc, dt, gyro_bias=self.gyro_bias, acc_bias=self.acc_bias,
                               gyro_noise_density=self._dens[1], acc_noise_density=self._dens[0],
                               time_noise_density=self._dens[2])
            E = pre.delta.as_matrix()
            A = SGal3(E).inverse().adjoint()
            chunk = (E, A, pre.bias_jacobian, pre.covariance, None, None, None)
            factors = None
        else:
            factors = _sample_parts(gyro, acc, dt, self._bias6, self._sq2.unsqueeze(-3), self._Qd.unsqueeze(-3),
                                    self._r6, self._c)
            chunk = _along(factors, 0) if K == 1 else _reduce(factors)
        before = self._delta
        state = (self._delta, None, self._J, self._S, self._X, self._B, self._C)
        self._delta, _, self._J, self._S, self._X, self._B, self._C = _combine(state, chunk, need_a=False)
        self._count += K
        if not intermediate:
            return None
        if factors is None:
            xi = _increment_tangents(gyro, acc, dt, self.gyro_bias, self.acc_bias)
            steps = SGal3.exp(xi).as_matrix()
        else:
            steps = factors[0]
        return SGal3(before.unsqueeze(-3) @ _prefix_products(steps))

    def _fold_one(self, sample: torch.Tensor, dt) -> None:
        """Fold in one sample [gyro, acc] (*batch, 6), dt a float or (*batch): (C2) and (C1)/(C3)
        written out for one sample (fewer operations than _fold's chunk path, the same maths)."""
        c = self._c
        if isinstance(dt, torch.Tensor):
            half = 0.5 * dt.unsqueeze(-1)
            zh, bottom = torch.addcmul(c.z0, half, c.lz[0]), torch.addcmul(c.bottom[0], half, c.bottom[1])
            w = (dt / 6.0)[..., None, None]
        else:
            half, w = 0.5 * dt, dt / 6.0
            if half not in self._float_cache:  # a constant rate: formed once
                self._float_cache = {half: (c.z0 + half * c.lz[0], c.bottom[0] + half * c.bottom[1])}
            zh, bottom = self._float_cache[half]
        xh = (sample - self._bias) * half
        H, Ah = _half_factors(xh[..., :3], xh[..., 3:], half, zh, bottom, c)
        E, A = H @ H, Ah @ Ah
        J, S = _noise_parts(A, Ah, w, self._sq2, self._Qd, c)
        if self._r is None:
            self._S = A @ self._S @ A.mT + S
        else:
            rh = self._r * (dt.unsqueeze(-1) if isinstance(dt, torch.Tensor) else dt)
            part = (E, A, J, S, torch.zeros_like(J), torch.diag_embed(rh), S)
            state = (self._delta, None, self._J, self._S, self._X, self._B, self._C)
            _, _, _, self._S, self._X, self._B, self._C = _combine(state, part, need_a=False)
        self._J = A @ self._J + J
        self._delta = self._delta @ E
        self._count += 1

    def _check_samples(self, gyro, acc, dt):
        """([gyro, acc] (a new tensor: (*batch, 6) for one sample, (*batch, K, 6) for a chunk),
        dt (a float or a tensor (*batch, K)), K, whether it is one sample) from one sample or a
        chunk."""
        if not isinstance(gyro, torch.Tensor) or gyro.dtype != self._kw["dtype"] or gyro.device != self._device:
            checks.floating(gyro, "gyro")
            raise TypeError(f"gyro must have dtype {self._kw['dtype']} on {self._device} (the "
                            f"accumulator's), got {gyro.dtype} on {gyro.device}")
        if not isinstance(acc, torch.Tensor) or acc.shape != gyro.shape or acc.dtype != gyro.dtype \
                or acc.device != gyro.device:
            checks.floating(acc, "acc")
            raise ValueError(f"acc must have gyro's shape, dtype and device {tuple(gyro.shape)}, "
                             f"{gyro.dtype}, {gyro.device}; got {tuple(acc.shape)}, {acc.dtype}, {acc.device}")
        batch = self.batch_shape
        nb = len(batch)
        one = gyro.dim() == nb + 1
        if not (one or gyro.dim() == nb + 2) or gyro.shape[:nb] != batch or gyro.shape[-1] != 3:
            raise ValueError(f"gyro must have shape (*batch_shape, 3) (one sample) or (*batch_shape, "
                             f"K, 3) (a chunk) with batch_shape {tuple(batch)}, got {tuple(gyro.shape)}")
        K = 1 if one else gyro.shape[-2]
        if K == 0:
            raise ValueError(f"gyro must hold at least one sample (K >= 1), got shape {tuple(gyro.shape)}")
        sample = torch.cat((gyro, acc), -1)
        if not isinstance(dt, torch.Tensor):
            return sample, checks.finite_number(dt, "dt", "> 0"), K, one
        checks.floating(dt, "dt")
        if dt.dtype != gyro.dtype or dt.device != gyro.device:
            raise TypeError(f"dt must have gyro's dtype and device ({gyro.dtype}, {gyro.device}), "
                            f"got {dt.dtype}, {dt.device}")
        want = (*batch, K)
        try:
            dt = (dt.unsqueeze(-1) if one else dt).expand(want)
        except RuntimeError:
            raise ValueError(f"dt must have shape {tuple(want[:-1]) if one else want} (or broadcast "
                             f"to it), got {tuple(dt.shape)}") from None
        if self.validate and not bool(((dt > 0) & dt.isfinite()).all()):
            bad = dt[~((dt > 0) & dt.isfinite())]
            raise ValueError(f"dt must be finite and > 0 everywhere, got {bad.numel()} other "
                             f"entries (first {float(bad[0])!r})")
        return sample, dt.clone(), K, one
