from __future__ import annotations

import torch
from typing_extensions import Self

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
    def from_components(cls, rotation: torch.Tensor) -> Self:
        """The rotation matrix (2, 2) itself (the one component; the same API as the other groups)."""
        (C,) = prepare(rotation=(rotation, (2, 2)))
        return cls._new(C)

    def angle(self) -> torch.Tensor:
        """theta in [-pi, pi] (...), the log's: -pi at a half turn whose sine entry is -0 or rounds
        below zero (SO2.exp(-pi)), as atan2 gives it."""
        return self.log()[..., 0]

    def act(self, p: torch.Tensor, point_axes: int = 0) -> torch.Tensor:
        """Points (..., 2): C p.
        ``point_axes``: how many axes of points before the coordinates every element maps whole
        (0: the batches broadcast as in torch; see "Acting on points" in LieGroup)."""
        return self._f.act(self._acting(p, "p", point_axes, self.point_dim), p)
