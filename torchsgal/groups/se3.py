from __future__ import annotations

import torch

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
    def from_components(cls, rotation: torch.Tensor, position: torch.Tensor):
        """rotation (..., 3, 3), position (..., 3), broadcast to one batch."""
        C, r = prepare(rotation=(rotation, (3, 3)), position=(position, (3,)))
        return cls._new(_se3.from_components(C, r))

    def position(self) -> torch.Tensor:
        """The position r (..., 3) (a view of the matrix)."""
        return self._matrix[..., :3, 3]

    def act(self, p: torch.Tensor) -> torch.Tensor:
        """Points (..., 3): C p + r."""
        return self._f.act(self._matrix, p)
