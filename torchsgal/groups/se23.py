from __future__ import annotations

import torch
from typing_extensions import Self

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
    def from_components(
        cls, rotation: torch.Tensor, velocity: torch.Tensor, position: torch.Tensor
    ) -> Self:
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

    def act(self, p: torch.Tensor, point_axes: int = 0) -> torch.Tensor:
        """Points (..., 3): C p + r.
        ``point_axes``: how many axes of points before the coordinates every element maps whole
        (0: the batches broadcast as in torch; see "Acting on points" in LieGroup)."""
        return self._f.act(self._acting(p, "p", point_axes, self.point_dim), p)

    def act_velocity(self, u: torch.Tensor, point_axes: int = 0) -> torch.Tensor:
        """Velocities (..., 3), homogeneous [u, 1, 0]: C u + v.
        ``point_axes`` as in ``act``."""
        return self._f.act_velocity(self._acting(u, "u", point_axes, 3), u)
