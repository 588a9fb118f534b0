"""The joint description, fixed transforms and the kinematic state of a serial chain.

``Joint`` is one actuated joint of a ``KinematicChain`` (kind, axis, fixed origin, limits),
``_transform`` reads a fixed transform argument (base, tool, link offsets);
``ChainState`` holds what ``KinematicChain.forward`` computes for its links: pose, linear and
angular velocity and acceleration in the base frame, and the body and spatial twists and the
extended pose derived from them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from ..functional import checks
from ..groups import SE3, SE23

REVOLUTE, CONTINUOUS, PRISMATIC = "revolute", "continuous", "prismatic"
JOINT_KINDS = (REVOLUTE, CONTINUOUS, PRISMATIC)


@dataclass(frozen=True)
class Joint:
    """An actuated joint of a :class:`KinematicChain`.

    name      the joint's name (URDF joint name, or ``q1 .. qn`` for DH tables).
    kind      "revolute", "continuous" (revolute without limits) or "prismatic".
    axis      axis (3 floats) in the joint frame; ``KinematicChain`` normalises it.
    origin    (4, 4) float64 tensor: the fixed transform from the previous actuated joint's
              frame (or the chain root) to this joint's frame at q = 0 (copied by the chain).
    lower, upper   position limits (rad or m); -inf / inf where the joint has none.
    velocity  velocity limit, >= 0 (inf where none is given).
    """

    name: str
    kind: str
    axis: tuple[float, float, float]
    origin: torch.Tensor = field(repr=False)
    lower: float = -math.inf
    upper: float = math.inf
    velocity: float = math.inf


@dataclass
class ChainState:
    """Kinematics of the chain's links (``KinematicChain.forward``).

    ``...`` is the batch shape of q (and qdot, qddot broadcast with it); with ``links`` given
    to ``forward`` every field has one more axis, (..., L), one entry per requested link.

    pose                  SE3: the link frame in the base frame.
    linear_velocity       (..., 3) dp/dt of the link origin, base frame; None without qdot.
    angular_velocity      (..., 3) w, base frame (dR/dt = [w]x R); None without qdot.
    linear_acceleration   (..., 3) d2p/dt2 (classical acceleration), base frame; None
                          without qddot.
    angular_acceleration  (..., 3) dw/dt, base frame; None without qddot.

    Properties: ``body_velocity`` (..., 6) = (R^T dp/dt, R^T w), the right-perturbation twist
    T^-1 dT/dt in SE3's [rho, phi] order; ``spatial_velocity`` (..., 6) = dT/dt T^-1;
    ``body_acceleration`` (..., 6), the derivative of ``body_velocity``;
    ``extended_pose``, the SE23 element [[R, dp/dt, p], [0, 1, 0], [0, 0, 1]].
    """

    pose: SE3
    linear_velocity: torch.Tensor | None = None
    angular_velocity: torch.Tensor | None = None
    linear_acceleration: torch.Tensor | None = None
    angular_acceleration: torch.Tensor | None = None

    def _needs(self, value: torch.Tensor | None, what: str) -> torch.Tensor:
        if value is None:
            raise ValueError(f"{what} needs {'qddot' if 'acceleration' in what else 'qdot'}: "
                             f"pass it to KinematicChain.forward")
        return value

    @property
    def body_velocity(self) -> torch.Tensor:
        """(..., 6) [R^T dp/dt, R^T w]: the body twist (T^-1 dT/dt)^vee."""
        v = self._needs(self.linear_velocity, "body_velocity")
        w = self._needs(self.angular_velocity, "body_velocity")
        R = self.pose.rotation()
        return torch.cat((_tmatvec(R, v), _tmatvec(R, w)), dim=-1)

    @property
    def spatial_velocity(self) -> torch.Tensor:
        """(..., 6) [dp/dt - w x p, w]: the spatial twist (dT/dt T^-1)^vee."""
        v = self._needs(self.linear_velocity, "spatial_velocity")
        w = self._needs(self.angular_velocity, "spatial_velocity")
        return torch.cat((v - _cross(w, self.pose.position()), w), dim=-1)

    @property
    def body_acceleration(self) -> torch.Tensor:
        """(..., 6) d/dt of ``body_velocity``: [R^T (d2p/dt2 - w x dp/dt), R^T dw/dt]."""
        a = self._needs(self.linear_acceleration, "body_acceleration")
        dw = self._needs(self.angular_acceleration, "body_acceleration")
        v = self._needs(self.linear_velocity, "body_acceleration")
        w = self._needs(self.angular_velocity, "body_acceleration")
        R = self.pose.rotation()
        return torch.cat((_tmatvec(R, a - _cross(w, v)), _tmatvec(R, dw)), dim=-1)

    @property
    def extended_pose(self) -> SE23:
        """SE23 [[R, dp/dt, p], [0, 1, 0], [0, 0, 1]]: pose and velocity as one extended pose."""
        v = self._needs(self.linear_velocity, "extended_pose")
        return SE23.from_components(self.pose.rotation(), v, self.pose.position())


def _cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return torch.linalg.cross(a, b, dim=-1)


def _tmatvec(M: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    return (x.unsqueeze(-2) @ M).squeeze(-2)


def _transform(value, name: str) -> torch.Tensor:
    """A fixed transform argument: None (identity), an SE3 element or a (4, 4) tensor, as a
    float64 CPU tensor (a copy: later changes to ``value`` do not reach it); ValueError naming
    the argument otherwise."""
    if value is None:
        return torch.eye(4, dtype=torch.float64)
    if isinstance(value, SE3):
        if value.batch_shape != ():
            raise ValueError(f"{name} must be one (unbatched) SE3 element, got batch shape "
                             f"{tuple(value.batch_shape)}")
        value = value.as_matrix()
    if not isinstance(value, torch.Tensor):
        raise TypeError(f"{name} must be None, an SE3 element or a (4, 4) tensor, got "
                        f"{type(value).__name__}")
    checks.floating(value, name)
    if tuple(value.shape) != (4, 4):
        raise ValueError(f"{name} must have shape (4, 4), got {tuple(value.shape)}")
    m = value.detach().to("cpu", torch.float64).clone()  # .to may alias the caller's tensor
    if not bool(torch.isfinite(m).all()):
        raise ValueError(f"{name} must be finite, got {m.tolist()}")
    R = m[:3, :3]
    err = (R.T @ R - torch.eye(3, dtype=torch.float64)).abs().max().item()
    if err > 1e-6 or abs(torch.linalg.det(R).item() - 1.0) > 1e-6 or \
            (m[3] - torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64)).abs().max() > 0:
        raise ValueError(f"{name} must be a rigid transform [[R, p], [0, 1]] with R a rotation, "
                         f"got {m.tolist()}")
    return m
