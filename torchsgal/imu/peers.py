"""Conversions to and from GTSAM and pypose, and reference runs of their preintegrators.

The peers are optional dependencies: they are imported inside the functions.  These helpers
loop over windows (GTSAM has no batching); they serve comparisons, not speed.

Frames: GTSAM's ``NavState(R, p, v)`` and pypose's ``{'rot', 'vel', 'pos'}`` hold the same
rotation, velocity and position as a Galilean frame (R, v, p, t); the time is dropped going
out and given separately coming back.  An increment Delta converts to GTSAM's
``deltaXij()`` (Delta R, Delta p, Delta v), which has the same meaning.
"""
from __future__ import annotations

import numpy as np
import torch

from .. import SGal3
from ..functional import checks
from .prediction import STANDARD_GRAVITY


def _frames(x, name: str) -> SGal3:
    if not isinstance(x, SGal3):
        raise TypeError(f"{name} must be SGal3, got {type(x).__name__}")
    return x


def _stream(gyro, acc, dt) -> None:
    """gyro, acc (..., K, 3) of one shape with K >= 1, dt (..., K)."""
    checks.vector(gyro, 3, "gyro")
    checks.vector(acc, 3, "acc")
    checks.floating(dt, "dt")
    if gyro.dim() < 2 or gyro.shape[-2] < 1:
        raise ValueError(f"gyro must have shape (..., K, 3) with at least one sample (K >= 1), "
                         f"got {tuple(gyro.shape)}")
    if acc.shape != gyro.shape:
        raise ValueError(f"acc must have the shape of gyro {tuple(gyro.shape)}, got {tuple(acc.shape)}")
    if dt.dim() < 1 or dt.shape[-1] != gyro.shape[-2]:
        raise ValueError(f"dt must have shape (..., K) with K = {gyro.shape[-2]}, got {tuple(dt.shape)}")


def _np(x: torch.Tensor) -> np.ndarray:
    return x.detach().cpu().to(torch.float64).numpy()


def to_gtsam_navstate(frames: SGal3) -> list:
    """A flat list of ``gtsam.NavState`` (row-major over the batch; time dropped)."""
    import gtsam

    _frames(frames, "frames")
    R = _np(frames.rotation()).reshape(-1, 3, 3)
    v = _np(frames.velocity()).reshape(-1, 3)
    p = _np(frames.position()).reshape(-1, 3)
    return [gtsam.NavState(gtsam.Rot3(R[i]), p[i], v[i]) for i in range(R.shape[0])]


def from_gtsam_navstate(states, time: torch.Tensor) -> SGal3:
    """SGal3 of batch ``time.shape`` from a flat list of NavState (row-major) and the times
    (a float32 or float64 tensor, whose dtype and device the result takes)."""
    checks.floating(time, "time")
    n = time.numel()
    if len(states) != n:
        raise ValueError(f"states must have {n} entries (time.numel()), got {len(states)}")
    R = np.stack([s.attitude().matrix() for s in states]) if n else np.zeros((0, 3, 3))
    v = np.stack([np.asarray(s.velocity()) for s in states]) if n else np.zeros((0, 3))
    p = np.stack([np.asarray(s.position()) for s in states]) if n else np.zeros((0, 3))
    shape = tuple(time.shape)
    return SGal3.from_components(
        rotation=torch.tensor(R, dtype=time.dtype, device=time.device).reshape(*shape, 3, 3),
        velocity=torch.tensor(v, dtype=time.dtype, device=time.device).reshape(*shape, 3),
        position=torch.tensor(p, dtype=time.dtype, device=time.device).reshape(*shape, 3),
        time=time,
    )


def to_pypose_state(frames: SGal3) -> dict:
    """pypose's ``init_state`` for ``IMUPreintegrator``: rot (pp.SO3, (..., 1, 4)), vel, pos
    (..., 1, 3), in the frames' dtype."""
    import pypose as pp

    _frames(frames, "frames")
    return {
        "rot": pp.mat2SO3(frames.rotation().unsqueeze(-3), check=False),
        "vel": frames.velocity().unsqueeze(-2),
        "pos": frames.position().unsqueeze(-2),
    }


def gtsam_params(frame: str = "z_up", magnitude: float = STANDARD_GRAVITY,
                 gyro_noise_density: float = 1e-3, acc_noise_density: float = 1e-2,
                 integration_sigma: float = 0.0):
    """``PreintegrationParams`` (MakeSharedU for z-up, MakeSharedD for NED) with isotropic
    continuous-time noise densities; the magnitude, densities and integration sigma are finite
    numbers >= 0 (ValueError naming them otherwise)."""
    if frame not in ("z_up", "ned"):
        raise ValueError(f"frame must be 'z_up' or 'ned', got {frame!r}")
    # checked before GTSAM sees them: a negative density would be squared into a valid covariance
    magnitude = checks.finite_number(magnitude, "magnitude", ">= 0")
    gyro_noise_density = checks.finite_number(gyro_noise_density, "gyro_noise_density", ">= 0")
    acc_noise_density = checks.finite_number(acc_noise_density, "acc_noise_density", ">= 0")
    integration_sigma = checks.finite_number(integration_sigma, "integration_sigma", ">= 0")
    import gtsam

    params = (gtsam.PreintegrationParams.MakeSharedU if frame == "z_up"
              else gtsam.PreintegrationParams.MakeSharedD)(magnitude)
    params.setGyroscopeCovariance(gyro_noise_density**2 * np.eye(3))
    params.setAccelerometerCovariance(acc_noise_density**2 * np.eye(3))
    params.setIntegrationCovariance(integration_sigma**2 * np.eye(3))
    return params


def gtsam_preintegrate(gyro, acc, dt, params, gyro_bias=None, acc_bias=None) -> list:
    """One ``PreintegratedImuMeasurements`` per window (a loop over windows and samples).

    gyro, acc (..., K, 3), dt (..., K); biases (3,) or None (one bias for all windows)."""
    import gtsam

    _stream(gyro, acc, dt)
    for name, b in (("gyro_bias", gyro_bias), ("acc_bias", acc_bias)):
        if b is not None and tuple(getattr(b, "shape", ())) != (3,):
            raise ValueError(f"{name} must be a tensor of shape (3,) (one bias for all windows) or "
                             f"None, got {tuple(b.shape) if hasattr(b, 'shape') else type(b).__name__}")
    g, a, h = _np(gyro).reshape(-1, gyro.shape[-2], 3), _np(acc).reshape(-1, gyro.shape[-2], 3), _np(dt)
    h = np.broadcast_to(h, gyro.shape[:-1]).reshape(-1, gyro.shape[-2])
    bias = gtsam.imuBias.ConstantBias(
        np.zeros(3) if acc_bias is None else _np(acc_bias).reshape(3),
        np.zeros(3) if gyro_bias is None else _np(gyro_bias).reshape(3),
    )
    pims = []
    for w in range(g.shape[0]):
        pim = gtsam.PreintegratedImuMeasurements(params, bias)
        for k in range(g.shape[1]):
            pim.integrateMeasurement(a[w, k], g[w, k], float(h[w, k]))
        pims.append(pim)
    return pims


def gtsam_predict(pims: list, start: SGal3) -> SGal3:
    """GTSAM's prediction from ``start`` (batch (B,) or broadcast), with each window's bias."""
    _frames(start, "start")
    starts = to_gtsam_navstate(start.expand(len(pims)) if start.batch_shape != (len(pims),) else start)
    out = [pim.predict(s, pim.biasHat()) for pim, s in zip(pims, starts)]
    T = torch.tensor([pim.deltaTij() for pim in pims], dtype=start.dtype, device=start.device)
    return from_gtsam_navstate(out, start.time().expand(len(pims)) + T)


def gtsam_covariance(pim, dtype=torch.float64) -> torch.Tensor:
    """GTSAM's ``preintMeasCov()`` mapped to torchsgal's right perturbation of the increment,
    9 x 9 in the order [rho, nu, phi] (the time row/column, exact in GTSAM, left out).

    GTSAM (tangent preintegration) perturbs its vector [theta, p, v] additively, with
    Delta R = Exp(theta); ours is Delta exp(eps), so to first order
    [rho, nu, phi] = [R^T dp, R^T dv, J_r(theta) dtheta]."""
    from .. import SO3

    cov = torch.tensor(np.asarray(pim.preintMeasCov()), dtype=dtype)
    theta = torch.tensor(np.asarray(pim.preintegrated())[:3], dtype=dtype)
    Rt = torch.tensor(pim.deltaRij().matrix(), dtype=dtype).T
    M = torch.zeros(9, 9, dtype=dtype)
    M[0:3, 3:6] = Rt  # rho from dp
    M[3:6, 6:9] = Rt  # nu from dv
    M[6:9, 0:3] = SO3.jr(theta)  # phi from dtheta
    return M @ cov @ M.T


def pypose_predict(gyro, acc, dt, start: SGal3, frame: str = "z_up",
                   magnitude: float = STANDARD_GRAVITY) -> SGal3:
    """pypose ``IMUPreintegrator`` (batched over windows, reset each call) from ``start`` (B,):
    the state at the end of each window.  gyro, acc (B, K, 3), dt (B, K) and start of one
    dtype and device."""
    if frame not in ("z_up", "ned"):
        raise ValueError(f"frame must be 'z_up' or 'ned', got {frame!r}")
    _stream(gyro, acc, dt)
    _frames(start, "start")
    # pypose's own error on mixed dtypes ("expected scalar type Float ...") names no argument
    checks.same_device_dtype(gyro=gyro, acc=acc, dt=dt, start=start.as_matrix())
    import pypose as pp

    gravity = magnitude if frame == "z_up" else -magnitude  # pypose subtracts R^T [0, 0, gravity]
    integrator = pp.module.IMUPreintegrator(gravity=gravity, prop_cov=False, reset=True).to(gyro.dtype)
    out = integrator(dt.unsqueeze(-1), gyro, acc, init_state=to_pypose_state(start))
    R = out["rot"][:, -1].matrix()
    return SGal3.from_components(rotation=R, velocity=out["vel"][:, -1], position=out["pos"][:, -1],
                                 time=start.time() + dt.sum(-1))
