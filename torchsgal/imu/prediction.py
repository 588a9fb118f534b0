"""Prediction with gravity and the Earth's rotation: the state at a window's end,
X_j = L X_i Delta, from the state X_i at its start and the gravity-free increment Delta of
:func:`~torchsgal.imu.preintegrate` (mahony (29), docs/guide/imu.md), its first-order
Jacobians, and the gravity and Earth-rate vectors of a local-level navigation frame."""
from __future__ import annotations

import math

import torch

from .. import SGal3
from ..functional import checks

STANDARD_GRAVITY = 9.80665  # m/s^2
EARTH_RATE = 7.292115e-5  # rad/s, WGS-84


def gravity_vector(frame: str = "z_up", magnitude: float = STANDARD_GRAVITY, dtype=None, device=None):
    """Gravity in the navigation frame: z-up (ENU) (0, 0, -g) or NED (0, 0, +g); the magnitude
    g is a finite number >= 0 (the frame gives the sign)."""
    if frame not in ("z_up", "ned"):
        raise ValueError(f"frame must be 'z_up' or 'ned', got {frame!r}")
    magnitude = checks.finite_number(magnitude, "magnitude", ">= 0")
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
