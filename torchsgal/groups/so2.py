from __future__ import annotations

import torch

from ..functional import so2 as _so2
from ._components import prepare
from .base import LieGroup


class SO2(LieGroup):
    """Planar rotations, (..., 2, 2) matrices; tangent theta (..., 1)."""

    dof = 1
    matrix_dim = 2
    point_dim = 2
    rotation_dim = 2
    _f = _so2
    __slots__ = ()

    @classmethod
    def from_components(cls, rotation: torch.Tensor):
        """The rotation matrix (2, 2) itself (the one component; the same API as the other groups)."""
        (C,) = prepare(rotation=(rotation, (2, 2)))
        return cls._new(C)

    def angle(self) -> torch.Tensor:
        """theta in (-pi, pi] (...)."""
        return self.log()[..., 0]

    def act(self, p: torch.Tensor) -> torch.Tensor:
        """Points (..., 2): C p."""
        return self._f.act(self._matrix, p)
