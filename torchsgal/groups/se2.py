from __future__ import annotations

import torch
from typing_extensions import Self

from ..functional import se2 as _se2
from ._components import prepare
from .base import LieGroup


class SE2(LieGroup):
    """Planar rigid motions [[C, r], [0, 1]] (..., 3, 3); tangent [rho (2), theta] (..., 3)."""

    dof = 3
    matrix_dim = 3
    point_dim = 2
    rotation_dim = 2
    _f = _se2
    __slots__ = ()

    @classmethod
    def from_components(cls, rotation: torch.Tensor, position: torch.Tensor) -> Self:
        """rotation (..., 2, 2), position (..., 2), broadcast to one batch."""
        C, r = prepare(rotation=(rotation, (2, 2)), position=(position, (2,)))
        return cls._new(_se2.from_components(C, r))

    def position(self) -> torch.Tensor:
        """The position r (..., 2) (a view of the matrix)."""
        return self._matrix[..., :2, 2]

    def act(self, p: torch.Tensor, point_axes: int = 0) -> torch.Tensor:
        """Points (..., 2): C p + r.
        ``point_axes``: how many axes of points before the coordinates every element maps whole
        (0: the batches broadcast as in torch; see "Acting on points" in LieGroup)."""
        return self._f.act(self._acting(p, "p", point_axes, self.point_dim), p)
