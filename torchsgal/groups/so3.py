from __future__ import annotations

import torch
from typing_extensions import Self

from ..functional import so3 as _so3
from ._components import prepare
from .base import LieGroup


class SO3(LieGroup):
    """Rotations, (..., 3, 3) matrices; tangent phi (..., 3)."""

    dof = 3
    matrix_dim = 3
    point_dim = 3  # size of the vectors act() takes
    _f = _so3
    __slots__ = ()

    @classmethod
    def from_rotation(cls, rotation: torch.Tensor, check: bool = False) -> Self:
        """The same as ``from_matrix(rotation, check)``."""
        return cls.from_matrix(rotation, check=check)

    @classmethod
    def from_quaternion(cls, q: torch.Tensor, *, order: str):
        """From quaternions q (..., 4), components in ``order``: "wxyz" (scalar first, as GTSAM
        and Eigen) or "xyzw" (scalar last, as scipy, pypose and ROS); no default, so that the
        order is always stated.  q is normalised at any length (a zero or non-finite quaternion
        raises where its values can be read); q and -q give the same rotation."""
        return cls._new(cls._f.from_quaternion(q, order))

    def as_quaternion(self, *, order: str) -> torch.Tensor:
        """Unit quaternions (..., 4) in ``order`` ("wxyz" or "xyzw"), scalar part >= 0."""
        return self._f.to_quaternion(self._matrix, order)

    @classmethod
    def from_components(cls, rotation: torch.Tensor) -> Self:
        """The rotation matrix (3, 3) itself (the one component; the same API as the other groups)."""
        (C,) = prepare(rotation=(rotation, (3, 3)))
        return cls._new(C)

    def act(self, p: torch.Tensor, point_axes: int = 0) -> torch.Tensor:
        """Points (..., 3): C p.
        ``point_axes``: how many axes of points before the coordinates every element maps whole
        (0: the batches broadcast as in torch; see "Acting on points" in LieGroup)."""
        return self._f.act(self._acting(p, "p", point_axes, self.point_dim), p)
