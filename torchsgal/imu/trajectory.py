"""Smooth trajectories with analytic ground truth, and the IMU streams they produce."""
from __future__ import annotations

from dataclasses import dataclass

import torch

from .. import SO3, SGal3
from ..functional import checks

_PARAMS = ("rot_amplitude", "rot_frequency", "rot_phase", "pos_amplitude", "pos_frequency",
           "pos_phase")


def _param(value, name: str, t: torch.Tensor) -> torch.Tensor:
    """A parameter as a tensor of t's dtype and device; numbers are checked on the host (real,
    finite), tensors are taken as they are."""
    if isinstance(value, torch.Tensor):
        return value.to(dtype=t.dtype, device=t.device)
    message = f"{name} must be a 3-vector of real numbers (a tuple or a tensor), got {value!r}"
    if isinstance(value, (str, bytes)):
        raise TypeError(message)
    try:
        x = torch.as_tensor(value, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError):
        raise TypeError(message) from None
    if not bool(torch.isfinite(x).all()):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return x.to(dtype=t.dtype, device=t.device)


@dataclass
class SinusoidalTrajectory:
    """R(t) = Exp(phi(t)), phi_i(t) = A_i sin(w_i t + c_i); p_i(t) = B_i sin(u_i t + d_i).

    All parameters are 3-vectors (finite real numbers or tensors (..., 3) whose batch
    broadcasts with the times'; TypeError or ValueError naming the parameter otherwise); the
    navigation frame is inertial with constant gravity (prediction's model without Earth
    rotation).  Body rate
    omega = J_r(phi) phi_dot (so that R_dot = R omega^), specific force f = R^T (p_ddot - g).
    """

    rot_amplitude: tuple = (0.3, 0.4, 0.8)
    rot_frequency: tuple = (1.1, 0.7, 0.5)
    rot_phase: tuple = (0.2, -0.4, 0.9)
    pos_amplitude: tuple = (2.0, 1.5, 0.4)
    pos_frequency: tuple = (0.8, 1.3, 2.1)
    pos_phase: tuple = (0.0, 0.5, -0.3)

    def _params(self, t: torch.Tensor, name: str = "t"):
        checks.floating(t, name)
        out = []
        for field in _PARAMS:
            x = _param(getattr(self, field), field, t)
            if x.dim() < 1 or x.shape[-1] != 3:
                raise ValueError(f"{field} must be a 3-vector (shape (..., 3)), got shape "
                                 f"{tuple(x.shape)}")
            out.append(x)
        # a tensor parameter's batch broadcasts with the times' (torch's error named neither)
        checks.broadcast_batch(**{name: t.shape}, **{f: x.shape[:-1] for f, x in zip(_PARAMS, out)})
        return out

    def state(self, t: torch.Tensor) -> SGal3:
        """Galilean frames (R, v, p, t) at times t (...)."""
        A, w, c, Bp, u, d = self._params(t)
        tt = t.unsqueeze(-1)
        R = SO3.exp(A * torch.sin(w * tt + c)).as_matrix()
        p = Bp * torch.sin(u * tt + d)
        v = Bp * u * torch.cos(u * tt + d)
        return SGal3.from_components(rotation=R, velocity=v, position=p, time=t)

    def imu(self, t: torch.Tensor, gravity: torch.Tensor):
        """(gyro, acc) (..., 3) at times t: body rate and specific force R^T (a - g).
        ``gravity`` (..., 3) has the dtype and device of ``t`` and a batch broadcasting with it."""
        A, w, c, Bp, u, d = self._params(t)
        checks.vector(gravity, 3, "gravity")
        checks.same_device_dtype(t=t, gravity=gravity)
        checks.broadcast_batch(t=t.shape, gravity=gravity.shape[:-1])
        tt = t.unsqueeze(-1)
        phi = A * torch.sin(w * tt + c)
        phi_dot = A * w * torch.cos(w * tt + c)
        gyro = (SO3.jr(phi) @ phi_dot.unsqueeze(-1)).squeeze(-1)
        acc_world = -Bp * u**2 * torch.sin(u * tt + d)
        R = SO3.exp(phi).as_matrix()
        acc = (R.transpose(-1, -2) @ (acc_world - gravity).unsqueeze(-1)).squeeze(-1)
        return gyro, acc

    def stream(self, t0: torch.Tensor, duration: float, dt: float, gravity: torch.Tensor,
               sample: str = "midpoint"):
        """Samples over [t0, t0 + duration] every dt: (gyro, acc, dt) of shapes (..., K, 3),
        (..., K, 3), (..., K).  ``sample``: 'midpoint' (each sample taken at the middle of its
        interval) or 'left' (at its start, as a sensor latching at the tick).  ``t0`` is a
        floating tensor (...); ``duration`` and ``dt`` finite numbers > 0, ``duration`` a
        multiple of ``dt``; ``gravity`` (3,), or (..., 3) broadcasting with the sample times
        (..., K), of the dtype and device of ``t0``."""
        if sample not in ("midpoint", "left"):
            raise ValueError(f"sample must be 'midpoint' or 'left', got {sample!r}")
        checks.floating(t0, "t0")
        checks.vector(gravity, 3, "gravity")
        checks.same_device_dtype(t0=t0, gravity=gravity)
        duration = checks.finite_number(duration, "duration", "> 0")
        dt = checks.finite_number(dt, "dt", "> 0")
        K = int(round(duration / dt))
        if K < 1 or abs(K * dt - duration) > 1e-9 * max(1.0, duration):
            raise ValueError(f"duration ({duration}) must be a positive multiple of dt ({dt})")
        offset = 0.5 if sample == "midpoint" else 0.0
        k = torch.arange(K, dtype=t0.dtype, device=t0.device)
        times = t0.unsqueeze(-1) + (k + offset) * dt
        gyro, acc = self.imu(times, gravity)
        return gyro, acc, torch.full(times.shape, dt, dtype=t0.dtype, device=t0.device)
