"""Poses as quaternion + translation (ROS ``geometry_msgs/Pose``, TUM trajectories, Eigen):
SE3 to and from the pair ``(q, t)`` and the 7-vector ``[t, q]``, with the quaternion's order
always named: "wxyz" (scalar first: GTSAM, Eigen's constructor) or "xyzw" (scalar last: ROS,
scipy, pypose, TUM files).  Batched and differentiable; quaternions are normalised on the way
in (q and -q give the same rotation) and come out with a non-negative scalar part.
Rotations alone: ``SO3.from_quaternion(q, order=...)`` and ``SO3.as_quaternion(order=...)``.
"""
from __future__ import annotations

import torch

from ..functional import checks
from ..functional import so3 as _so3
from ..groups import SE3


def _se3(g, name: str) -> SE3:
    if not isinstance(g, SE3):
        raise TypeError(f"{name} must be an SE3, got {type(g).__name__}")
    return g


def from_quaternion_translation(q: torch.Tensor, t: torch.Tensor, *, order: str) -> SE3:
    """SE3 of rotations given as quaternions q (..., 4) in ``order`` ("wxyz" or "xyzw") and
    translations t (..., 3) (the batches broadcast): the pose x -> R(q) x + t."""
    return _from_parts(q, t, order, "q", "t")


def _from_parts(q: torch.Tensor, t: torch.Tensor, order: str, q_name: str, t_name: str) -> SE3:
    checks.vector(t, 3, t_name)
    checks.vector(q, 4, q_name)
    checks.same_device_dtype(**{q_name: q, t_name: t})
    checks.broadcast_batch(**{q_name: q.shape[:-1], t_name: t.shape[:-1]})
    return SE3.from_components(rotation=_so3.from_quaternion(q, order, q_name), position=t)


def as_quaternion_translation(g: SE3, *, order: str) -> tuple[torch.Tensor, torch.Tensor]:
    """(q (..., 4) in ``order``, scalar part >= 0; t (..., 3)) of the poses g."""
    _se3(g, "g")
    return _so3.to_quaternion(g.rotation(), order), g.position()


def from_pose7(pose: torch.Tensor, *, order: str) -> SE3:
    """SE3 of 7-vectors ``[tx, ty, tz, q]`` (..., 7), the quaternion in ``order`` ("xyzw" is the
    TUM and pypose layout ``[t, qx, qy, qz, qw]``; "wxyz" gives ``[t, qw, qx, qy, qz]``)."""
    checks.vector(pose, 7, "pose")
    return _from_parts(pose[..., 3:7], pose[..., 0:3], order, "pose[..., 3:7]", "pose[..., 0:3]")


def as_pose7(g: SE3, *, order: str) -> torch.Tensor:
    """7-vectors ``[t, q]`` (..., 7) of the poses g, the quaternion in ``order`` (scalar >= 0)."""
    q, t = as_quaternion_translation(g, order=order)
    return torch.cat((t, q), dim=-1)
