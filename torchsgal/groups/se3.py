from __future__ import annotations

import torch
from typing_extensions import Self

from ..functional import se3 as _se3
from ._components import prepare
from .base import LieGroup


class SE3(LieGroup):
    """Rigid motions [[C, r], [0, 1]]; tangent [rho, phi] (..., 6)."""

    dof = 6
    matrix_dim = 4
    point_dim = 3  # size of the vectors act() takes
    _f = _se3
    __slots__ = ()

    @classmethod
    def from_components(cls, rotation: torch.Tensor, position: torch.Tensor) -> Self:
        """rotation (..., 3, 3), position (..., 3), broadcast to one batch."""
        C, r = prepare(rotation=(rotation, (3, 3)), position=(position, (3,)))
        return cls._new(_se3.from_components(C, r))

    def position(self) -> torch.Tensor:
        """The position r (..., 3) (a view of the matrix)."""
        return self._matrix[..., :3, 3]

    def act(self, p: torch.Tensor, point_axes: int = 0) -> torch.Tensor:
        """Points (..., 3): C p + r.
        ``point_axes``: how many axes of points before the coordinates every element maps whole
        (0: the batches broadcast as in torch; see "Acting on points" in LieGroup)."""
        return self._f.act(self._acting(p, "p", point_axes, self.point_dim), p)
