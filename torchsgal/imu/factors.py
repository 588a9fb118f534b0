"""Factors for inertial navigation with the factor-graph engine (``estimation.graph``): IMU
preintegration between navigation states, the bias random walk, and GNSS positions.

States are Galilean frames X = (R, v, p, t) (``SGal3``) or extended poses (``SE23``, times
known); biases a Euclidean variable of 6-vectors ``[b_g, b_a]`` (gyro first, as
``Preintegration.bias_jacobian``).  Residuals are right-perturbation errors; noise is given as
the residual's covariance (GNSS: or its information), passed to the engine as a square-root
information.
Guide: ``docs/guide/imu_factors.md``.

IMU residual (docs/guide/imu.md, "Prediction"; mahony (57), Remark 6.2): the states imply the
gravity-free increment

    D(X_i, X_j) = X_i^-1 S(t_i) A(tau)^-1 S(-t_i) X_j,   tau = t_j - t_i,
    A(tau) = S(tau) exp([0, g tau, -Omega tau, -tau]),   S(t) = exp(t N),

the inverse of ``predict`` (X_j = S(t_i) A(T) S(-t_i) X_i Delta), and the residual compares it
with the preintegrated increment corrected to first order for the bias b_i of the window's
start (``Preintegration.corrected``):

    r = log(Delta(b_i)^-1 D(X_i, X_j)),   Delta(b_i) = Delta exp(J_b (b_i - b_lin)).

With the model's increment Delta_true = Delta exp(eps), r = eps exactly, so the noise of r
is the preintegrated covariance itself (GTSAM's ``ImuFactor`` likewise whitens its error in
the preintegrated-measurement space by ``preintMeasCov``).
"""
from __future__ import annotations

import math
import numbers

import torch

from .. import SE3, SE23, SO3, SGal3
from ..estimation.graph.factors import Factor
from ..functional import checks
from ..groups import LieGroup
from ..uncertainty.covariance import covariance_factor
from .preintegration import Preintegration

__all__ = ["ImuFactor", "BiasRandomWalkFactor", "GnssPositionFactor", "imu_residual",
           "imu_jacobians", "implied_increment", "sqrt_information_from_covariance"]


# ------------------------------------------------------------------------------ helpers
def sqrt_information_from_covariance(covariance: torch.Tensor, name: str = "covariance"
                                     ) -> torch.Tensor:
    """L (..., m, m) with L^T L = covariance^-1: L = C^-1 for the Cholesky factor C C^T =
    covariance (1 / sqrt of the diagonal where every matrix is diagonal).  Raises naming
    ``name`` unless the covariance is symmetric positive definite
    (``uncertainty.covariance.covariance_factor``: one read, which also gives C)."""
    checks.floating(covariance, name)
    diagonal, C = covariance_factor(covariance, name)
    if diagonal:
        return torch.diag_embed(C.reciprocal())
    eye = torch.eye(covariance.shape[-1], dtype=covariance.dtype, device=covariance.device)
    return torch.linalg.solve_triangular(C, eye.expand_as(C), upper=False)


def _time_shift(t: torch.Tensor) -> SGal3:
    """S(t) = exp(t N), the pure time translation, for t (...)."""
    zero = torch.zeros(t.shape + (9,), dtype=t.dtype, device=t.device)
    return SGal3.exp(torch.cat((zero, t.unsqueeze(-1)), dim=-1))


def _left_factor_inverse(tau: torch.Tensor, gravity: torch.Tensor, earth_rate: torch.Tensor
                         ) -> SGal3:
    """A(tau)^-1 = exp(-[0, g tau, -Omega tau, -tau]) S(-tau) (``predict``'s left factor)."""
    h = tau.unsqueeze(-1)
    g, w, h = torch.broadcast_tensors(gravity * h, earth_rate * h, h)
    xi = torch.cat((torch.zeros_like(g), g, -w, -h[..., :1]), dim=-1)
    return SGal3.exp(-xi).compose(_time_shift(-tau))


def implied_increment(start: SGal3, end: SGal3, gravity: torch.Tensor,
                      earth_rate: torch.Tensor | None = None) -> SGal3:
    """D = X_i^-1 S(t_i) A(t_j - t_i)^-1 S(-t_i) X_j: the gravity-free increment that carries
    ``start`` X_i to ``end`` X_j under ``predict``'s model (``predict(start, D, gravity,
    earth_rate) == end``).  gravity, earth_rate (..., 3) in the navigation frame."""
    if not isinstance(start, SGal3) or not isinstance(end, SGal3):
        raise TypeError(f"start and end must be SGal3, got {type(start).__name__} and "
                        f"{type(end).__name__}")
    checks.vector(gravity, 3, "gravity")
    if earth_rate is None:
        earth_rate = torch.zeros_like(gravity)
    checks.vector(earth_rate, 3, "earth_rate")
    checks.same_device_dtype(start=start.as_matrix(), end=end.as_matrix(), gravity=gravity,
                             earth_rate=earth_rate)
    checks.broadcast_batch(start=start.batch_shape, end=end.batch_shape,
                           gravity=gravity.shape[:-1], earth_rate=earth_rate.shape[:-1])
    t_i = start.time()
    middle = _time_shift(t_i).compose(_left_factor_inverse(end.time() - t_i, gravity, earth_rate))
    return start.inverse().compose(middle).compose(_time_shift(-t_i)).compose(end)


def _as_galilean(X: SE23 | SGal3, t: torch.Tensor) -> SGal3:
    """An SE_2(3) state as the Galilean frame of its rotation, velocity and position at time t."""
    return SGal3.from_components(rotation=X.rotation(), velocity=X.velocity(),
                                 position=X.position(), time=t)


def _check_factor_args(X_i, X_j, bias_i, delta, bias_jacobian, linearization_bias, gravity,
                       earth_rate) -> None:
    """imu_residual's arguments: states of one group (SGal3 or SE23), the rest of their dtype
    and device, with batches that broadcast (metadata only)."""
    if not (isinstance(X_i, (SGal3, SE23)) and type(X_j) is type(X_i)):
        raise TypeError(f"X_i and X_j must be both SGal3 or both SE23, got {type(X_i).__name__} "
                        f"and {type(X_j).__name__}")
    if not isinstance(delta, SGal3):
        raise TypeError(f"delta must be an SGal3, got {type(delta).__name__}")
    checks.vector(bias_i, 6, "bias_i")
    checks.vector(linearization_bias, 6, "linearization_bias")
    checks.floating(bias_jacobian, "bias_jacobian")
    if bias_jacobian.dim() < 2 or bias_jacobian.shape[-2:] != (10, 6):
        raise ValueError(f"bias_jacobian must have shape (..., 10, 6), got {tuple(bias_jacobian.shape)}")
    checks.vector(gravity, 3, "gravity")
    checks.vector(earth_rate, 3, "earth_rate")
    checks.same_device_dtype(X_i=X_i.as_matrix(), X_j=X_j.as_matrix(), delta=delta.as_matrix(),
                             bias_i=bias_i, bias_jacobian=bias_jacobian,
                             linearization_bias=linearization_bias, gravity=gravity, earth_rate=earth_rate)
    checks.broadcast_batch(X_i=X_i.batch_shape, X_j=X_j.batch_shape, delta=delta.batch_shape,
                           bias_i=bias_i.shape[:-1], bias_jacobian=bias_jacobian.shape[:-2],
                           linearization_bias=linearization_bias.shape[:-1],
                           gravity=gravity.shape[:-1], earth_rate=earth_rate.shape[:-1])


def imu_residual(X_i: SGal3 | SE23, X_j: SGal3 | SE23, bias_i: torch.Tensor, delta: SGal3,
                 bias_jacobian: torch.Tensor, linearization_bias: torch.Tensor,
                 gravity: torch.Tensor, earth_rate: torch.Tensor) -> torch.Tensor:
    """r = log(Delta(b_i)^-1 D(X_i, X_j)) (module docstring): (..., 10) for SGal3 states,
    (..., 9) = [rho, nu, phi] for SE23 states (placed at times 0 and the window length T, so
    that r's time component is an exact zero).  One factor, broadcasting over batch axes."""
    _check_factor_args(X_i, X_j, bias_i, delta, bias_jacobian, linearization_bias, gravity, earth_rate)
    db = bias_i - linearization_bias
    corrected = delta.rplus((bias_jacobian @ db.unsqueeze(-1)).squeeze(-1))
    if isinstance(X_i, SGal3) and isinstance(X_j, SGal3):
        D = implied_increment(X_i, X_j, gravity, earth_rate)
        return corrected.inverse().compose(D).log()
    T = delta.time()
    start = _as_galilean(X_i, torch.zeros_like(T))
    D = implied_increment(start, _as_galilean(X_j, T), gravity, earth_rate)
    return corrected.inverse().compose(D).log()[..., :9]


def imu_jacobians(X_i: SGal3 | SE23, X_j: SGal3 | SE23, bias_i: torch.Tensor, delta: SGal3,
                  bias_jacobian: torch.Tensor, linearization_bias: torch.Tensor,
                  gravity: torch.Tensor, earth_rate: torch.Tensor
                  ) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """(r, [J_i, J_j, J_b]): ``imu_residual`` and its Jacobians with respect to the right
    perturbations of X_i and X_j and to the bias b_i.  With D = P Q, P = X_i^-1 S(t_i),
    Q = A(tau)^-1 S(-t_i) X_j, E = Delta(b_i)^-1 D, h = [0, g, -Omega, -1], n = e_iota and
    A(tau + s) = S(s) A(tau) exp(s h) (``predict_jacobians``):

        J_j = J_r^-1(r) (I - (Ad(Q^-1) h + Ad(X_j^-1) n) n^T)
        J_i = J_r^-1(r) (-Ad(D^-1) + (Ad(Q^-1) h + Ad((X_i D)^-1) n) n^T)
        J_b = -J_r^-1(r) Ad(E^-1) J_r(J_b (b_i - b_lin)) J_b

    (the n^T columns: a state's time moves tau and the time shifts).  SE23 states: the
    [rho, nu, phi] block, their times being fixed."""
    _check_factor_args(X_i, X_j, bias_i, delta, bias_jacobian, linearization_bias, gravity, earth_rate)
    phi_b = (bias_jacobian @ (bias_i - linearization_bias).unsqueeze(-1)).squeeze(-1)
    corrected = delta.rplus(phi_b)
    start: SGal3
    end: SGal3
    galilean = isinstance(X_i, SGal3) and isinstance(X_j, SGal3)
    if isinstance(X_i, SGal3) and isinstance(X_j, SGal3):
        start, end = X_i, X_j
    else:
        T = delta.time()
        start, end = _as_galilean(X_i, torch.zeros_like(T)), _as_galilean(X_j, T)
    t_i = start.time()
    tau = end.time() - t_i
    Q = _left_factor_inverse(tau, gravity, earth_rate).compose(_time_shift(-t_i)).compose(end)
    D = start.inverse().compose(_time_shift(t_i)).compose(Q)
    E = corrected.inverse().compose(D)
    r = E.log()
    Jr_inv = SGal3.jr_inv(r)
    g, w = torch.broadcast_tensors(gravity, earth_rate)
    h = torch.cat((torch.zeros_like(g), g, -w, -torch.ones_like(g[..., :1])), dim=-1)
    Qh = (Q.inverse().adjoint() @ h.unsqueeze(-1)).squeeze(-1)  # Ad(Q^-1) h
    n_j = end.inverse().adjoint()[..., :, 9]  # Ad(X_j^-1) n
    n_i = start.compose(D).inverse().adjoint()[..., :, 9]  # Ad((X_i D)^-1) n
    eye = torch.eye(10, dtype=r.dtype, device=r.device)
    col_j = eye[:, 9:] - (Qh + n_j).unsqueeze(-1)
    J_j = torch.cat((eye[:, :9].expand(col_j.shape[:-1] + (9,)), col_j), dim=-1)
    minus_Ad = -D.inverse().adjoint()
    col_i = minus_Ad[..., 9:] + (Qh + n_i).unsqueeze(-1)
    J_i = torch.cat((minus_Ad[..., :9].expand(col_i.shape[:-1] + (9,)), col_i), dim=-1)
    J_b = -E.inverse().adjoint() @ SGal3.jr(phi_b) @ bias_jacobian
    J_i, J_j, J_b = Jr_inv @ J_i, Jr_inv @ J_j, Jr_inv @ J_b
    if galilean:
        return r, [J_i, J_j, J_b]
    return r[..., :9], [J_i[..., :9, :9], J_j[..., :9, :9], J_b[..., :9, :]]


def _vector3(x, name: str, like: torch.Tensor, batch: torch.Size) -> torch.Tensor:
    """x (..., 3) of like's dtype and device, expanded to (*batch, 3)."""
    checks.vector(x, 3, name)
    checks.same_device_dtype(**{"the preintegration": like, name: x})
    if checks.broadcast_batch(**{"the preintegration": batch, name: x.shape[:-1]}) != batch:
        raise ValueError(f"{name} of shape {tuple(x.shape)} must broadcast to the preintegration's "
                         f"batch {tuple(batch)} + (3,)")
    return x.expand(*batch, 3)


# ----------------------------------------------------------------------------- factors
class ImuFactor(Factor):
    """E IMU factors ``r = log(Delta(b_i)^-1 D(X_i, X_j))`` (module docstring) between the
    elements ``i`` and ``j`` (E,) of the state variable ``states`` and the element
    ``bias_index`` (E,) of the Euclidean bias variable ``bias`` ((N_b, 6) ``[b_g, b_a]``: one
    per state, or one per window, or one shared: the indices say which).

    preintegration  a ``Preintegration`` of batch (E,) (shared by the problems) or (B, E),
                    with its covariance and bias Jacobian (``preintegrate``'s defaults).
    gravity         (3,) or broadcasting to the preintegration's batch, in the navigation
                    frame (``gravity_vector``); ``earth_rate`` likewise, or None.
    state_group     ``SGal3`` (the states' times are estimated; 10-dimensional residual) or
                    ``SE23`` (times known: state i at 0 and j at the window length;
                    9-dimensional residual [rho, nu, phi]).
    time_sigma      [s] SGal3 states only: an extra standard deviation on the residual's time
                    component, added to the preintegrated time variance.  Rule for the clock:
                    with ``time_noise_density > 0`` the covariance is regular and
                    ``time_sigma`` may stay None; with an exact clock (time variance zero,
                    ``preintegrate``'s default) the residual's time component t_j - t_i - T
                    needs a ``time_sigma > 0`` (a stiff constraint, e.g. 1e-6 s; the
                    component is linear in the times, so in float64 a stiff weight costs the
                    solvers no accuracy); else a ValueError says so.

    Noise: information = (Sigma + time_sigma^2 e_iota e_iota^T)^-1 (SGal3) or
    Sigma[:9, :9]^-1 (SE23), Sigma the preintegrated covariance.  Jacobians: analytic
    (``imu_jacobians``), or with ``analytic_jacobians=False`` the engine's forward-mode
    autodiff.
    """

    def __init__(self, states: str, i, j, bias: str, bias_index, preintegration: Preintegration,
                 gravity: torch.Tensor, earth_rate: torch.Tensor | None = None, *,
                 state_group: type[LieGroup] = SGal3, time_sigma: float | None = None,
                 analytic_jacobians: bool = True, loss=None):
        if not isinstance(preintegration, Preintegration):
            raise TypeError(f"preintegration must be a Preintegration, got "
                            f"{type(preintegration).__name__}")
        pre = preintegration
        if pre.covariance is None or pre.bias_jacobian is None:
            raise ValueError("preintegration must carry its covariance and bias_jacobian "
                             "(preintegrate with covariance=True, bias_jacobian=True)")
        if len(pre.batch_shape) not in (1, 2):
            raise ValueError(f"preintegration must have batch (E,) or (B, E), got "
                             f"{tuple(pre.batch_shape)}")
        if state_group not in (SGal3, SE23):
            raise ValueError(f"state_group must be SGal3 or SE23, got {state_group!r}")
        analytic = checks.boolean(analytic_jacobians, "analytic_jacobians")
        batch = pre.batch_shape
        like = pre.delta.as_matrix()
        gravity = _vector3(gravity, "gravity", like, batch)
        earth_rate = (torch.zeros_like(gravity) if earth_rate is None
                      else _vector3(earth_rate, "earth_rate", like, batch))
        cov = pre.covariance.expand(*batch, 10, 10)
        if state_group is SE23:
            if time_sigma is not None:
                raise ValueError("time_sigma applies to SGal3 states only (SE23 states have "
                                 "known times)")
            L = sqrt_information_from_covariance(cov[..., :9, :9], "preintegration.covariance")
        else:
            if time_sigma is not None:
                sigma = checks.finite_number(time_sigma, "time_sigma", "> 0")
                info = torch.finfo(cov.dtype)
                if not math.sqrt(info.tiny) / info.eps <= sigma <= math.sqrt(info.max) * info.eps:
                    # sigma^2 must be a normal number that the information can still invert
                    raise ValueError(f"time_sigma must lie in [{math.sqrt(info.tiny) / info.eps:.3g}, "
                                     f"{math.sqrt(info.max) * info.eps:.3g}] s in {cov.dtype}, got {sigma:g}")
                cov = cov.clone()
                cov[..., 9, 9] += sigma**2
            elif bool((cov[..., 9, 9] <= 0).any()):
                raise ValueError("the preintegrated covariance has a zero time variance (an exact "
                                 "clock): give time_sigma > 0 (a stiff constraint t_j - t_i = T) "
                                 "or use SE23 states with known times")
            L = sqrt_information_from_covariance(cov, "preintegration.covariance")
        b_lin = torch.cat(torch.broadcast_tensors(pre.gyro_bias, pre.acc_bias), dim=-1)
        self.state_group = state_group
        self.variable_kinds = (state_group, state_group, 6)
        super().__init__(imu_residual, [(states, i), (states, j), (bias, bias_index)],
                         data=[pre.delta, pre.bias_jacobian.expand(*batch, 10, 6),
                               b_lin.expand(*batch, 6), gravity, earth_rate],
                         dim=10 if state_group is SGal3 else 9, sqrt_information=L, loss=loss,
                         jacobians=imu_jacobians if analytic else None)
        if batch[-1] not in (self.size, 1):
            raise ValueError(f"preintegration has batch {tuple(batch)}: its last size must be the "
                             f"number of factors E = {self.size} given by the indices (or 1)")


def _random_walk_residual(b_i: torch.Tensor, b_j: torch.Tensor) -> torch.Tensor:
    """r = b_j - b_i."""
    return b_j - b_i


def _random_walk_jacobians(b_i: torch.Tensor, b_j: torch.Tensor):
    r = b_j - b_i
    eye = torch.eye(r.shape[-1], dtype=r.dtype, device=r.device)
    return r, [-eye, eye]


def _density_axes(x, name: str, like: torch.Tensor) -> torch.Tensor:
    """A random-walk density: a number > 0 or a tensor (3,) of entries > 0, as (3,)."""
    if isinstance(x, torch.Tensor):
        checks.vector(x, 3, name)
        checks.same_device_dtype(duration=like, **{name: x})
        if x.shape != (3,):
            raise ValueError(f"{name} must be a number or a tensor of shape (3,), got "
                             f"{tuple(x.shape)}")
        if not bool(((x > 0) & x.isfinite()).all()):
            raise ValueError(f"{name} must be finite and > 0, got {x.tolist()}")
        return x
    if isinstance(x, bool) or not isinstance(x, numbers.Real):
        raise TypeError(f"{name} must be a number > 0 or a tensor (3,), got {type(x).__name__}")
    value = checks.finite_number(x, name, "> 0")
    if value > torch.finfo(like.dtype).max:
        raise ValueError(f"{name} must be representable in {like.dtype} (duration's dtype), got {value:g}")
    return like.new_full((3,), value)


class BiasRandomWalkFactor(Factor):
    """E factors ``r = b_j - b_i`` between elements ``i`` and ``j`` (E,) of the Euclidean bias
    variable ``bias`` ([b_g, b_a], (N, 6)): the bias random walk over a window of length
    ``duration`` dt (E,) or (B, E) [s] (a tensor, e.g. ``preintegration.duration()``, > 0).

    Covariance diag(s_g^2 I, s_a^2 I) dt with the continuous-time random-walk densities
    ``gyro_random_walk`` s_g [rad/s^2/sqrt(Hz)] and ``acc_random_walk`` s_a [m/s^3/sqrt(Hz)]
    (numbers or per-axis tensors (3,)): GTSAM's ``CombinedImuFactor`` bias block
    (``biasOmegaCovariance dt``, ``biasAccCovariance dt``), or a ``BetweenFactor<ConstantBias>``
    with sigmas ``sqrt(dt) s``.  Analytic Jacobians [-I, I]."""

    def __init__(self, bias: str, i, j, duration: torch.Tensor, gyro_random_walk,
                 acc_random_walk, *, loss=None):
        checks.floating(duration, "duration")
        if duration.dim() not in (1, 2):
            raise ValueError(f"duration must have shape (E,) or (B, E), got {tuple(duration.shape)}")
        if not bool(((duration > 0) & duration.isfinite()).all()):
            raise ValueError("duration must be finite and > 0 everywhere")
        s = torch.cat((_density_axes(gyro_random_walk, "gyro_random_walk", duration),
                       _density_axes(acc_random_walk, "acc_random_walk", duration)))
        L = torch.diag_embed(1.0 / (s * duration.unsqueeze(-1).sqrt()))  # (E, 6, 6) / (B, E, 6, 6)
        if not bool(torch.isfinite(L * L).all()):  # the information 1 / (s^2 dt)
            raise ValueError("the random walks' information 1 / (s^2 duration) overflows: "
                             "gyro_random_walk, acc_random_walk or duration too small for "
                             f"{duration.dtype}")
        self.variable_kinds = (6, 6)
        super().__init__(_random_walk_residual, [(bias, i), (bias, j)], dim=6,
                         sqrt_information=L, loss=loss, jacobians=_random_walk_jacobians)
        if duration.shape[-1] != self.size:
            raise ValueError(f"duration must have shape (E,) or (B, E) with E = {self.size} (the "
                             f"length of i and j), got {tuple(duration.shape)}")


def _gnss_residual(X: SE3 | SE23 | SGal3, measured: torch.Tensor, lever_arm: torch.Tensor) -> torch.Tensor:
    """r = p + R l - z."""
    return X.position() + (X.rotation() @ lever_arm.unsqueeze(-1)).squeeze(-1) - measured


def _gnss_jacobians(X: SE3 | SE23 | SGal3, measured: torch.Tensor, lever_arm: torch.Tensor):
    """X exp(d) moves p by R rho (+ v iota for SGal3) and R l by -R l^ phi (first order)."""
    R = X.rotation()
    r = _gnss_residual(X, measured, lever_arm)
    Rl = -R @ SO3.hat(lever_arm)
    R, Rl = torch.broadcast_tensors(R, Rl)
    if isinstance(X, SE3):  # [rho, phi]
        return r, [torch.cat((R, Rl), dim=-1)]
    zero = torch.zeros_like(R)
    if isinstance(X, SE23):  # [rho, nu, phi]
        return r, [torch.cat((R, zero, Rl), dim=-1)]
    v = X.velocity().unsqueeze(-1).expand(R.shape[:-1] + (1,))
    return r, [torch.cat((R, zero, Rl, v), dim=-1)]  # SGal3: [rho, nu, phi, iota]


class GnssPositionFactor(Factor):
    """E GNSS position factors ``r = p_k + R_k l - z`` on elements ``index`` (E,) of the state
    variable ``states`` (SE3, SE23 or SGal3: the antenna at lever arm ``lever_arm`` l in the
    body frame, (3,) or (E, 3), default zero; GTSAM's ``GPSFactorArm``); ``measured`` z (E, 3)
    or (B, E, 3) in the navigation frame.  Noise: ``covariance`` or ``information``, (3, 3),
    (E, 3, 3) or (B, E, 3, 3).  Analytic Jacobians: R, -R l^ (and v for the time of SGal3)."""

    def __init__(self, states: str, index, measured: torch.Tensor, *,
                 covariance: torch.Tensor | None = None, information: torch.Tensor | None = None,
                 lever_arm: torch.Tensor | None = None, loss=None):
        checks.vector(measured, 3, "measured")
        if measured.dim() not in (2, 3):
            raise ValueError(f"measured must have shape (E, 3) or (B, E, 3), got "
                             f"{tuple(measured.shape)}")
        if lever_arm is None:
            lever_arm = measured.new_zeros(3)  # one for every factor (and every problem)
        checks.vector(lever_arm, 3, "lever_arm")
        checks.same_device_dtype(measured=measured, lever_arm=lever_arm)
        given_lever_arm = tuple(lever_arm.shape)
        if lever_arm.dim() == 1:
            lever_arm = lever_arm.unsqueeze(0)
        if (covariance is None) == (information is None):
            raise ValueError("give exactly one of covariance and information")
        for name, noise in (("covariance", covariance), ("information", information)):
            if noise is not None:
                checks.matrix(noise, 3, name)
                checks.same_device_dtype(measured=measured, **{name: noise})
        kw: dict[str, torch.Tensor] = {}
        if covariance is not None:
            kw["sqrt_information"] = sqrt_information_from_covariance(covariance)
        elif information is not None:
            kw["information"] = information
        self.variable_kinds = ((SE3, SE23, SGal3),)
        super().__init__(_gnss_residual, [(states, index)], data=[measured, lever_arm], dim=3,
                         loss=loss, jacobians=_gnss_jacobians, **kw)
        E = self.size  # the factors, from index: measured and lever_arm are checked against it
        if measured.shape[-2] != E:
            raise ValueError(f"measured must have shape (E, 3) or (B, E, 3) with E = {E} (index's "
                             f"length), got {tuple(measured.shape)}")
        if lever_arm.dim() != 2 or lever_arm.shape[0] not in (1, E):
            raise ValueError(f"lever_arm must have shape (3,) or (E, 3) = ({E}, 3), got {given_lever_arm}")
