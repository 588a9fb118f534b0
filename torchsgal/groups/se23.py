from __future__ import annotations

import torch

from ..functional import se23 as _se23
from ._components import prepare
from .base import LieGroup


class SE23(LieGroup):
    """Extended poses [[C, v, r], [0, 1, 0], [0, 0, 1]]; tangent [rho, nu, phi] (..., 9)."""

    dof = 9
    matrix_dim = 5
    point_dim = 3  # size of the vectors act() takes
    _f = _se23
    __slots__ = ()

    @classmethod
    def from_components(cls, rotation: torch.Tensor, velocity: torch.Tensor, position: torch.Tensor):
        """rotation (..., 3, 3), velocity (..., 3), position (..., 3), broadcast to one batch."""
        C, v, r = prepare(
            rotation=(rotation, (3, 3)), velocity=(velocity, (3,)), position=(position, (3,))
        )
        return cls._new(_se23.from_components(C, v, r))

    def velocity(self) -> torch.Tensor:
        """The velocity v (..., 3) (a view of the matrix)."""
        return self._matrix[..., :3, 3]

    def position(self) -> torch.Tensor:
        """The position r (..., 3) (a view of the matrix)."""
        return self._matrix[..., :3, 4]

    def act(self, p: torch.Tensor) -> torch.Tensor:
        """Points (..., 3): C p + r."""
        return self._f.act(self._matrix, p)

    def act_velocity(self, u: torch.Tensor) -> torch.Tensor:
        """Velocities (..., 3), homogeneous [u, 1, 0]: C u + v."""
        return self._f.act_velocity(self._matrix, u)
