"""Conversions between torchsgal.imu and GTSAM's IMU preintegration, and the IMU-to-body
extrinsic (GTSAM's ``body_P_sensor``).

GTSAM is an optional dependency, imported inside the functions that need it.

Orders and charts.  torchsgal's increment tangent is [rho, nu, phi, iota] (position, velocity,
rotation, time) with the right perturbation Delta exp(eps) of SGal(3); its bias vector is
[b_g, b_a] (gyro first).  GTSAM's preintegrated vector is [theta, p, v] (rotation, position,
velocity) with Delta R = Exp(theta) and additive p, v, and its ``ConstantBias`` vector is
[b_a, b_g] (accelerometer first).  To first order (the order of a covariance)

    [rho, nu, phi] = [Delta R^T dp, Delta R^T dv, J_r(theta) dtheta],

the map of :func:`gtsam_tangent_map`: a permutation of the blocks times Delta R^T and J_r,
which are the chart difference (the two charts agree at first order at theta = 0 only up to
that rotation of p and v).  Time is exact in GTSAM: the iota row and column are zero.
"""
from __future__ import annotations

import numbers

import numpy as np
import torch

from .. import SE3, SO3, SGal3
from ..functional import checks
from .preintegration import Preintegration, _check_non_negative
from .streaming import StreamingPreintegration


def _np(x: torch.Tensor) -> np.ndarray:
    return x.detach().cpu().to(torch.float64).numpy()


def _axes(x, name: str) -> np.ndarray:
    """A density: a number >= 0 or a tensor (3,) of entries >= 0, as a numpy (3,)."""
    if isinstance(x, torch.Tensor):
        checks.vector(x, 3, name)
        if x.shape != (3,):
            raise ValueError(f"{name} must be a number or a tensor of shape (3,), got {tuple(x.shape)}")
        out = _np(x)
        if not (np.isfinite(out).all() and (out >= 0).all()):
            raise ValueError(f"{name} must be finite and >= 0, got {out.tolist()}")
        return out
    return np.full(3, checks.finite_number(x, name, ">= 0"))


# ------------------------------------------------------------------------- parameters
def to_gtsam_params(gravity: torch.Tensor, gyro_noise_density=0.0, acc_noise_density=0.0,
                    gyro_bias_random_walk=None, acc_bias_random_walk=None,
                    body_P_sensor: SE3 | None = None, integration_sigma: float = 0.0):
    """GTSAM's ``PreintegrationParams`` (or ``PreintegrationCombinedParams`` when both bias
    random walks are given) for torchsgal's model: gravity (3,) in the navigation frame, noise
    densities (numbers or (3,) per axis) as diagonal continuous-time covariances,
    ``body_P_sensor`` (SE3, the sensor's pose in the body frame) and GTSAM's integration sigma
    (an extra position noise torchsgal does not model; 0 by default)."""
    import gtsam

    checks.vector(gravity, 3, "gravity")
    if gravity.shape != (3,):
        raise ValueError(f"gravity must have shape (3,), got {tuple(gravity.shape)}")
    if not bool(gravity.isfinite().all()):
        raise ValueError(f"gravity must be finite, got {gravity.tolist()}")
    walks = (gyro_bias_random_walk, acc_bias_random_walk)
    if (walks[0] is None) != (walks[1] is None):
        raise ValueError("give both gyro_bias_random_walk and acc_bias_random_walk (combined "
                         "parameters) or neither")
    g = _np(gravity).reshape(3, 1)
    params = gtsam.PreintegrationParams(g)
    if walks[0] is not None:
        combined = gtsam.PreintegrationCombinedParams(g)
        combined.setBiasOmegaCovariance(np.diag(_axes(walks[0], "gyro_bias_random_walk") ** 2))
        combined.setBiasAccCovariance(np.diag(_axes(walks[1], "acc_bias_random_walk") ** 2))
        params = combined
    params.setGyroscopeCovariance(np.diag(_axes(gyro_noise_density, "gyro_noise_density") ** 2))
    params.setAccelerometerCovariance(np.diag(_axes(acc_noise_density, "acc_noise_density") ** 2))
    sigma = checks.finite_number(integration_sigma, "integration_sigma", ">= 0")
    params.setIntegrationCovariance(sigma**2 * np.eye(3))
    if body_P_sensor is not None:
        if not isinstance(body_P_sensor, SE3) or body_P_sensor.batch_shape != ():
            raise TypeError(f"body_P_sensor must be one SE3 (batch shape ()), got "
                            f"{type(body_P_sensor).__name__}")
        params.setBodyPSensor(gtsam.Pose3(_np(body_P_sensor.as_matrix())))
    return params


def _diagonal_sqrt(cov, name: str) -> np.ndarray:
    cov = np.asarray(cov, dtype=np.float64)
    if np.abs(cov - np.diag(np.diag(cov))).max() > 0:
        raise ValueError(f"{name} must be diagonal to be a per-axis density, got {cov.tolist()}")
    return np.sqrt(np.diag(cov))


def from_gtsam_params(params, dtype=torch.float64) -> dict:
    """The model of GTSAM parameters in torchsgal's terms: ``gravity`` (3,), per-axis
    ``gyro_noise_density``/``acc_noise_density`` (3,) (the square roots of GTSAM's diagonal
    covariances; a correlated covariance raises ValueError), ``body_P_sensor`` (SE3 or None),
    ``integration_covariance`` (3, 3) (not modelled by torchsgal) and, for combined parameters,
    ``gyro_bias_random_walk``/``acc_bias_random_walk`` (3,)."""
    import gtsam

    if not isinstance(params, gtsam.PreintegrationParams):
        raise TypeError(f"params must be gtsam.PreintegrationParams or PreintegrationCombinedParams, "
                        f"got {type(params).__name__}")
    dtype = checks.dtype_arg(dtype)
    t = lambda x: torch.tensor(np.asarray(x, dtype=np.float64), dtype=dtype)  # noqa: E731
    out: dict[str, object] = {
        "gravity": t(params.n_gravity).reshape(3),
        "gyro_noise_density": t(_diagonal_sqrt(params.getGyroscopeCovariance(), "gyroscope covariance")),
        "acc_noise_density": t(_diagonal_sqrt(params.getAccelerometerCovariance(), "accelerometer covariance")),
        "integration_covariance": t(params.getIntegrationCovariance()),
        "body_P_sensor": None}
    pose = params.getBodyPSensor()
    if pose is not None:
        out["body_P_sensor"] = SE3.from_matrix(t(pose.matrix()))
    if isinstance(params, gtsam.PreintegrationCombinedParams):
        out["gyro_bias_random_walk"] = t(_diagonal_sqrt(params.getBiasOmegaCovariance(), "bias omega covariance"))
        out["acc_bias_random_walk"] = t(_diagonal_sqrt(params.getBiasAccCovariance(), "bias acc covariance"))
    return out


def streaming_from_gtsam_params(params, batch_shape=(), gyro_bias=None, acc_bias=None,
                                dtype=torch.float64) -> StreamingPreintegration:
    """A :class:`StreamingPreintegration` with the noise model of GTSAM ``params`` (the bias
    random walks of combined parameters).  Gravity and ``body_P_sensor`` are not part of the
    increment: pass ``from_gtsam_params(params)["gravity"]`` to ``predict`` and the samples
    through :func:`sensor_to_body`."""
    m = from_gtsam_params(params, dtype)
    return StreamingPreintegration(
        batch_shape, gyro_bias=gyro_bias, acc_bias=acc_bias, gyro_noise_density=m["gyro_noise_density"],
        acc_noise_density=m["acc_noise_density"],
        gyro_bias_random_walk=m.get("gyro_bias_random_walk", 0.0),
        acc_bias_random_walk=m.get("acc_bias_random_walk", 0.0), dtype=dtype)


# ------------------------------------------------------------------------ tangents
def gtsam_tangent_map(delta_rotation: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """M (..., 10, 9) with eps = M [dtheta, dp, dv]: GTSAM's preintegrated-vector perturbation
    to torchsgal's right perturbation of the increment (first order; module docstring).
    delta_rotation (..., 3, 3) = Exp(theta), theta (..., 3)."""
    checks.matrix(delta_rotation, 3, "delta_rotation")
    checks.vector(theta, 3, "theta")
    checks.binary(delta_rotation, 2, theta, 1, "delta_rotation", "theta")
    Rt = delta_rotation.transpose(-1, -2)
    batch = checks.broadcast_shapes(Rt.shape[:-2], theta.shape[:-1])
    M = Rt.new_zeros(*batch, 10, 9)
    M[..., 0:3, 3:6] = Rt  # rho from dp
    M[..., 3:6, 6:9] = Rt  # nu from dv
    M[..., 6:9, 0:3] = SO3.jr(theta)  # phi from dtheta
    return M


def _bias_swap(like: torch.Tensor) -> torch.Tensor:
    """P (6, 6): [b_g, b_a] = P [b_a, b_g] (its own inverse)."""
    P = like.new_zeros(6, 6)
    P[0:3, 3:6] = torch.eye(3, dtype=like.dtype)
    P[3:6, 0:3] = torch.eye(3, dtype=like.dtype)
    return P


def _delta(pim, dtype) -> SGal3:
    t = lambda x: torch.tensor(np.asarray(x, dtype=np.float64), dtype=dtype)  # noqa: E731
    return SGal3.from_components(rotation=t(pim.deltaRij().matrix()), velocity=t(pim.deltaVij()),
                                 position=t(pim.deltaPij()), time=t(pim.deltaTij()))


def from_gtsam_pim(pim, dtype=torch.float64) -> Preintegration | tuple[Preintegration, torch.Tensor]:
    """A GTSAM ``PreintegratedImuMeasurements`` as a :class:`Preintegration` (delta with time
    ``deltaTij``, covariance (10, 10) mapped by :func:`gtsam_tangent_map` with a zero time row
    and column, bias Jacobian None: GTSAM's Python API does not expose it) or, for a
    ``PreintegratedCombinedMeasurements``, the pair (Preintegration, combined covariance
    (16, 16) in the order of :meth:`StreamingPreintegration.combined_covariance`); there the
    Preintegration's covariance is the combined one's (10, 10) block, which includes the bias
    random walk (GTSAM keeps no other), unlike :attr:`StreamingPreintegration.covariance`.

    GTSAM propagates its combined covariance with the bias blocks of its transition taken as
    the Jacobians with respect to the *measurements* (+d/d omega, +d/d a, CombinedImuFactor.cpp),
    which are minus those with respect to the biases: its cross terms are those of -db.  The
    cross block is returned in torchsgal's sign (that of +db), i.e. negated."""
    import gtsam

    combined = isinstance(pim, gtsam.PreintegratedCombinedMeasurements)
    if not (combined or isinstance(pim, gtsam.PreintegratedImuMeasurements)):
        raise TypeError(f"pim must be a gtsam PreintegratedImuMeasurements or "
                        f"PreintegratedCombinedMeasurements, got {type(pim).__name__}")
    dtype = checks.dtype_arg(dtype)
    delta = _delta(pim, dtype)
    theta = torch.tensor(np.asarray(pim.preintegrated(), dtype=np.float64)[:3], dtype=dtype) \
        if hasattr(pim, "preintegrated") else SO3.from_matrix(delta.rotation()).log()
    M = gtsam_tangent_map(delta.rotation(), theta)
    cov = torch.tensor(np.asarray(pim.preintMeasCov(), dtype=np.float64), dtype=dtype)
    bias = np.asarray(pim.biasHatVector(), dtype=np.float64)  # [b_a, b_g]
    gyro_bias = torch.tensor(bias[3:], dtype=dtype)
    acc_bias = torch.tensor(bias[:3], dtype=dtype)
    if not combined:
        return Preintegration(delta, M @ cov @ M.T, None, gyro_bias, acc_bias)
    T = cov.new_zeros(16, 15)
    T[:10, :9] = M
    T[10:, 9:] = -_bias_swap(cov)  # GTSAM's bias error is -db (see above)
    full = T @ cov @ T.T
    return Preintegration(delta, full[:10, :10], None, gyro_bias, acc_bias), full


def to_gtsam_covariance(covariance: torch.Tensor, delta: SGal3) -> np.ndarray:
    """torchsgal's (10, 10) increment covariance, or a (16, 16) combined covariance, in GTSAM's
    order and chart: (9, 9) over [theta, p, v] or (15, 15) over [theta, p, v, b_a, b_g] (with
    GTSAM's sign of the cross terms); the inverse of :func:`from_gtsam_pim` (the time row and
    column dropped: GTSAM's time is exact)."""
    if not isinstance(delta, SGal3) or delta.batch_shape != ():
        raise TypeError("delta must be one SGal3 (batch shape ())")
    checks.floating(covariance, "covariance")
    if covariance.shape not in ((10, 10), (16, 16)):
        raise ValueError(f"covariance must have shape (10, 10) or (16, 16), got {tuple(covariance.shape)}")
    checks.same_device_dtype(delta=delta.as_matrix(), covariance=covariance)
    theta = SO3.from_matrix(delta.rotation()).log()
    M = gtsam_tangent_map(delta.rotation(), theta)[:9]  # (9, 9), invertible
    Minv = torch.linalg.inv(M)
    if covariance.shape == (10, 10):
        return _np(Minv @ covariance[:9, :9] @ Minv.T)
    T = covariance.new_zeros(15, 16)
    T[:9, :9] = Minv
    T[9:, 10:] = -_bias_swap(covariance)
    return _np(T @ covariance @ T.T)


def to_gtsam_bias_jacobian(bias_jacobian: torch.Tensor, delta: SGal3) -> np.ndarray:
    """torchsgal's bias Jacobian (10, 6) (eps per [db_g, db_a]) as GTSAM's (9, 6): the
    derivative of its preintegrated vector [theta, p, v] with respect to its bias [b_a, b_g]
    (what ``biasCorrectedDelta`` adds, first order; the inverse of :func:`gtsam_tangent_map`
    on the rows, the bias swap on the columns)."""
    if not isinstance(delta, SGal3) or delta.batch_shape != ():
        raise TypeError("delta must be one SGal3 (batch shape ())")
    checks.floating(bias_jacobian, "bias_jacobian")
    if bias_jacobian.shape != (10, 6):
        raise ValueError(f"bias_jacobian must have shape (10, 6), got {tuple(bias_jacobian.shape)}")
    checks.same_device_dtype(delta=delta.as_matrix(), bias_jacobian=bias_jacobian)
    theta = SO3.from_matrix(delta.rotation()).log()
    Minv = torch.linalg.inv(gtsam_tangent_map(delta.rotation(), theta)[:9])
    return _np(Minv @ bias_jacobian[:9] @ _bias_swap(bias_jacobian))


# ------------------------------------------------------------------ replay into GTSAM
def gtsam_pim(gyro: torch.Tensor, acc: torch.Tensor, dt, params, gyro_bias=None, acc_bias=None):
    """One GTSAM preintegration (combined for combined ``params``) of the samples gyro, acc
    (K, 3), dt (K,) or a number: a loop over samples (a reference, not for speed)."""
    import gtsam

    checks.vector(gyro, 3, "gyro")
    checks.vector(acc, 3, "acc")
    if not isinstance(params, gtsam.PreintegrationParams):
        raise TypeError(f"params must be gtsam.PreintegrationParams or PreintegrationCombinedParams, "
                        f"got {type(params).__name__}")
    for name, b in (("gyro_bias", gyro_bias), ("acc_bias", acc_bias)):
        if b is not None and (checks.vector(b, 3, name).shape != (3,) or not bool(b.isfinite().all())):
            raise ValueError(f"{name} must be None or a finite tensor (3,), got shape {tuple(b.shape)}")
    if gyro.dim() != 2 or acc.shape != gyro.shape:
        raise ValueError(f"gyro and acc must have one shape (K, 3), got {tuple(gyro.shape)} and "
                         f"{tuple(acc.shape)}")
    K = gyro.shape[0]
    if isinstance(dt, numbers.Real):
        h = np.full(K, checks.finite_number(dt, "dt", "> 0"))
    else:
        h = _np(checks.floating(dt, "dt"))
    if h.shape != (K,):
        raise ValueError(f"dt must be a number or have shape ({K},), got {h.shape}")
    if not (np.isfinite(h) & (h > 0)).all():
        raise ValueError("dt must be finite and > 0 everywhere")
    bias = gtsam.imuBias.ConstantBias(np.zeros(3) if acc_bias is None else _np(acc_bias).reshape(3),
                                      np.zeros(3) if gyro_bias is None else _np(gyro_bias).reshape(3))
    pim: gtsam.PreintegratedCombinedMeasurements | gtsam.PreintegratedImuMeasurements
    if isinstance(params, gtsam.PreintegrationCombinedParams):
        pim = gtsam.PreintegratedCombinedMeasurements(params, bias)
    else:
        pim = gtsam.PreintegratedImuMeasurements(params, bias)
    g, a = _np(gyro), _np(acc)
    for k in range(K):
        pim.integrateMeasurement(a[k], g[k], float(h[k]))
    return pim


# -------------------------------------------------------------------------- extrinsic
def sensor_to_body(gyro: torch.Tensor, acc: torch.Tensor, body_P_sensor: SE3, dt=None,
                   angular_acceleration: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Body-frame rate and specific force from an IMU mounted at ``body_P_sensor`` (R_bs, r):
    omega_b = R_bs omega_s and, for a rigid body,

        f_b = R_bs f_s - omega_b x (omega_b x r) - alpha_b x r,

    the centripetal and Euler (lever-arm) terms.  gyro, acc (..., K, 3) bias-free (or
    bias-corrected) sensor samples; body_P_sensor's batch (...) broadcasts with theirs
    (ValueError naming it otherwise).  alpha_b (..., K, 3) is ``angular_acceleration`` if given,
    else, with ``dt`` (a number or (..., K)), the derivative of omega_b along the samples
    (central differences, one-sided at the ends; K >= 2), else 0 (GTSAM's
    ``correctMeasurementsBySensorPose`` keeps the centripetal term only).  ``angular_acceleration``
    must have gyro's dtype and device and broadcast to its shape; a tensor dt must be finite and
    > 0, checked where reading it costs no host sync (on CPU, outside torch.func transforms and
    compilation, as :func:`~torchsgal.imu.preintegrate`'s dt).  Biases estimated in
    the sensor frame map as R_bs b_g (the accelerometer bias mixes with the lever arm: convert
    bias-corrected samples)."""
    checks.vector(gyro, 3, "gyro")
    checks.vector(acc, 3, "acc")
    if gyro.dim() < 2:  # (3,) came back as (1, 3)
        raise ValueError(f"gyro must have shape (..., K, 3) with a sample axis K, got {tuple(gyro.shape)}")
    if acc.shape != gyro.shape:
        raise ValueError(f"acc must have gyro's shape {tuple(gyro.shape)}, got {tuple(acc.shape)}")
    if not isinstance(body_P_sensor, SE3):
        raise TypeError(f"body_P_sensor must be an SE3, got {type(body_P_sensor).__name__}")
    checks.same_device_dtype(gyro=gyro, acc=acc, body_P_sensor=body_P_sensor.as_matrix())
    pose_batch = tuple(body_P_sensor.batch_shape)
    try:
        torch.broadcast_shapes(pose_batch + (1,), gyro.shape[:-1])
    except RuntimeError:
        raise ValueError(f"body_P_sensor's batch shape {pose_batch} must broadcast with the "
                         f"windows' batch of gyro and acc (..., K, 3), got gyro and acc of shape "
                         f"{tuple(gyro.shape)}") from None
    R = body_P_sensor.rotation().unsqueeze(-3)  # (..., 1, 3, 3) over the samples
    r = body_P_sensor.position().unsqueeze(-2)  # (..., 1, 3)
    w = (R @ gyro.unsqueeze(-1)).squeeze(-1)
    f = (R @ acc.unsqueeze(-1)).squeeze(-1) - torch.linalg.cross(w, torch.linalg.cross(w, r.expand_as(w)))
    if angular_acceleration is None and dt is not None:
        if gyro.dim() < 2 or gyro.shape[-2] < 2:
            raise ValueError(f"differentiating the rate needs K >= 2 samples along gyro's axis -2, "
                             f"got shape {tuple(gyro.shape)}")
        if isinstance(dt, numbers.Real):
            h = torch.full(gyro.shape[:-1], checks.finite_number(dt, "dt", "> 0"), dtype=gyro.dtype,
                           device=gyro.device)
        else:
            checks.floating(dt, "dt")
            checks.same_device_dtype(gyro=gyro, dt=dt)
            try:
                h = dt.expand(gyro.shape[:-1])
            except RuntimeError:
                raise ValueError(f"dt must be a number or broadcast to {tuple(gyro.shape[:-1])}, "
                                 f"got shape {tuple(dt.shape)}") from None
            _check_non_negative(dt, "dt", positive=True)
        t = torch.cat((torch.zeros_like(h[..., :1]), h.cumsum(-1)[..., :-1]), -1)  # sample instants
        dw = torch.cat((w[..., 1:2, :] - w[..., 0:1, :], w[..., 2:, :] - w[..., :-2, :],
                        w[..., -1:, :] - w[..., -2:-1, :]), -2)
        dtt = torch.cat((t[..., 1:2] - t[..., 0:1], t[..., 2:] - t[..., :-2], t[..., -1:] - t[..., -2:-1]), -1)
        angular_acceleration = dw / dtt.unsqueeze(-1)
    elif angular_acceleration is not None:
        checks.vector(angular_acceleration, 3, "angular_acceleration")
        checks.same_device_dtype(gyro=gyro, angular_acceleration=angular_acceleration)
        if checks.broadcast_batch(gyro=f.shape, angular_acceleration=angular_acceleration.shape) != f.shape:
            raise ValueError(f"angular_acceleration must broadcast to the samples' shape {tuple(f.shape)} "
                             f"(gyro's, with body_P_sensor's batch), got {tuple(angular_acceleration.shape)}")
        angular_acceleration = angular_acceleration.expand_as(f)  # linalg.cross wants equal dims
    if angular_acceleration is not None:
        f = f - torch.linalg.cross(angular_acceleration, r.expand_as(f))
    return w, f
