"""Euler angles: rotations from and to three angles about coordinate axes, with the axis
sequence and the intrinsic/extrinsic choice always named (no default).

- ``frame="intrinsic"``: rotate about the axes of the moving frame, the first angle first:
  ``R = R_a(t1) R_b(t2) R_c(t3)`` for the sequence "abc" (scipy's upper-case sequences).
- ``frame="extrinsic"``: rotate about the fixed axes, the first angle first:
  ``R = R_c(t3) R_b(t2) R_a(t1)`` (scipy's lower-case sequences).

The sequence is three letters from x, y, z with no axis twice in a row: the six Tait-Bryan
("zyx", ...) and six proper Euler ("zxz", ...) sequences.  Its case must agree with scipy's
meaning of it (upper case intrinsic, lower case extrinsic), so that a sequence copied from
scipy cannot silently mean the other frame.

GTSAM: ``Rot3.Ypr(y, p, r)`` is ``from_euler([y, p, r], sequence="ZYX", frame="intrinsic")``;
``Rot3.RzRyRx(x, y, z)`` (= ``Rot3.Ypr(z, y, x)``) is ``from_euler([x, y, z], sequence="xyz",
frame="extrinsic")``; ``Rot3.ypr()`` and ``rpy()`` read the same angles back.

``as_euler`` returns the first and third angles in [-pi, pi] and the middle one in
[-pi/2, pi/2] (Tait-Bryan) or [0, pi] (proper Euler), as scipy's ``as_euler``.  At gimbal lock
only the sum or difference of the other two is defined: there the third angle is set to 0, as
scipy does.  The angles come from the quaternion (Bernardes and Viollet's direct method).
Gimbal lock is declared where the middle angle is within ``GIMBAL_TOL`` (1e-12 in float64,
1e-6 in float32: rounding level, so that ``from_euler`` of the result is the rotation to within
about pi times that; scipy uses 1e-7) of its singular values.  Near it, the first and third
angles are ill-conditioned one by one, but ``from_euler`` of them gives the rotation back to
rounding.
"""
from __future__ import annotations

import math

import torch

from ..functional import checks
from ..functional import so3 as _so3
from ..groups import SO3

FRAMES = ("intrinsic", "extrinsic")
GIMBAL_TOL = {torch.float64: 1e-12, torch.float32: 1e-6}
_AXES = {"x": 0, "y": 1, "z": 2}


def _sequence(sequence, frame) -> tuple[int, int, int]:
    """The axis indices of a valid sequence whose case agrees with ``frame``."""
    if not isinstance(frame, str) or frame not in FRAMES:
        raise ValueError(f"frame must be 'intrinsic' or 'extrinsic', got {frame!r}")
    if (not isinstance(sequence, str) or len(sequence) != 3 or sequence.lower() != sequence
            and sequence.upper() != sequence or any(c not in _AXES for c in sequence.lower())):
        raise ValueError(f"sequence must be three of the letters x, y, z (all lower case or all "
                         f"upper case), e.g. 'zyx', got {sequence!r}")
    a, b, c = (_AXES[letter] for letter in sequence.lower())
    axes = (a, b, c)
    if axes[0] == axes[1] or axes[1] == axes[2]:
        raise ValueError(f"sequence must not repeat an axis in consecutive places, got {sequence!r}")
    upper = sequence.upper() == sequence
    if upper != (frame == "intrinsic"):
        raise ValueError(
            f"sequence {sequence!r} with frame={frame!r}: scipy reads upper-case sequences as "
            f"intrinsic and lower-case ones as extrinsic; write "
            f"{sequence.upper() if frame == 'intrinsic' else sequence.lower()!r} for {frame} rotations")
    return axes


def _axis_rotation(axis: int, angle: torch.Tensor) -> torch.Tensor:
    """R (..., 3, 3) about the coordinate axis ``axis`` by ``angle`` (...)."""
    c, s = torch.cos(angle), torch.sin(angle)
    one, zero = torch.ones_like(c), torch.zeros_like(c)
    if axis == 0:
        rows = ((one, zero, zero), (zero, c, -s), (zero, s, c))
    elif axis == 1:
        rows = ((c, zero, s), (zero, one, zero), (-s, zero, c))
    else:
        rows = ((c, -s, zero), (s, c, zero), (zero, zero, one))
    return torch.stack([torch.stack(r, dim=-1) for r in rows], dim=-2)


def from_euler(angles: torch.Tensor, *, sequence: str, frame: str) -> SO3:
    """Rotations of Euler angles (..., 3) (radians; the first angle is about ``sequence[0]``)."""
    axes = _sequence(sequence, frame)
    checks.vector(angles, 3, "angles")
    R = [_axis_rotation(a, angles[..., i]) for i, a in enumerate(axes)]
    C = R[0] @ R[1] @ R[2] if frame == "intrinsic" else R[2] @ R[1] @ R[0]
    return SO3.from_matrix(C)


def _polar(y: torch.Tensor, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(atan2(y, x), hypot(y, x)) with finite gradients at y = x = 0 (angle 0, a zero
    subgradient), where the angle is undefined and gimbal lock uses the other pair."""
    zero = (x == 0) & (y == 0)
    xs = torch.where(zero, torch.ones_like(x), x)
    ys = torch.where(zero, torch.zeros_like(y), y)
    return torch.atan2(ys, xs), torch.where(zero, torch.zeros_like(x), torch.hypot(ys, xs))


def _wrap(x: torch.Tensor) -> torch.Tensor:
    """Into [-pi, pi] (inputs in (-2 pi, 2 pi])."""
    x = torch.where(x < -math.pi, x + 2 * math.pi, x)
    return torch.where(x > math.pi, x - 2 * math.pi, x)


def as_euler(rotation: SO3, *, sequence: str, frame: str) -> torch.Tensor:
    """Euler angles (..., 3) of the rotations, for ``sequence`` and ``frame`` (see the module
    docstring for the ranges and gimbal lock).  Differentiable away from gimbal lock; at it, where
the angles are not differentiable, the gradients are finite (a zero subgradient)."""
    axes = _sequence(sequence, frame)
    if not isinstance(rotation, SO3):
        raise TypeError(f"rotation must be an SO3, got {type(rotation).__name__}")
    intrinsic = frame == "intrinsic"
    # intrinsic "abc" with angles (t1, t2, t3) is extrinsic "cba" with (t3, t2, t1)
    i, j, k = axes[::-1] if intrinsic else axes
    symmetric = i == k
    if symmetric:
        k = 3 - i - j
    sign = (i - j) * (j - k) * (k - i) // 2  # the permutation's parity, +-1
    q = _so3.to_quaternion(rotation.as_matrix(), "xyzw")
    w, qi, qj, qk = q[..., 3], q[..., i], q[..., j], sign * q[..., k]
    if symmetric:
        a, b, c, d = w, qi, qj, qk
    else:  # rotate the Tait-Bryan sequence onto a proper one (Bernardes and Viollet)
        a, b, c, d = w - qj, qi + qk, qj + w, qk - qi
    half_sum, norm_ab = _polar(b, a)
    half_diff, norm_cd = _polar(d, c)
    middle = 2 * torch.atan2(norm_cd, norm_ab)  # in [0, pi]
    tol = GIMBAL_TOL[q.dtype]
    at_zero, at_pi = middle <= tol, middle >= math.pi - tol
    # only half_sum (at 0) or half_diff (at pi) is defined: the third angle of the user's
    # sequence (the first here for intrinsic) is set to 0, the other carries the rotation
    first = half_sum - half_diff
    third = half_sum + half_diff
    if intrinsic:
        first = torch.where(at_zero | at_pi, torch.zeros_like(first), first)
        third = torch.where(at_zero, 2 * half_sum, torch.where(at_pi, 2 * half_diff, third))
    else:
        first = torch.where(at_zero, 2 * half_sum, torch.where(at_pi, -2 * half_diff, first))
        third = torch.where(at_zero | at_pi, torch.zeros_like(third), third)
    if not symmetric:
        third = sign * third
        middle = middle - math.pi / 2
    angles = torch.stack((_wrap(first), middle, _wrap(third)), dim=-1)
    return angles.flip(-1) if intrinsic else angles
