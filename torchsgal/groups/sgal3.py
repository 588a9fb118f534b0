from __future__ import annotations

import torch
from typing_extensions import Self

from ..functional import sgal3 as _sgal3
from ._components import prepare
from .base import LieGroup


class SGal3(LieGroup):
    """Special Galilean transformations [[C, v, r], [0, 1, tau], [0, 0, 1]];
    tangent [rho, nu, phi, iota] (..., 10)."""

    dof = 10
    matrix_dim = 5
    point_dim = 4  # size of the vectors act() takes
    _f = _sgal3
    __slots__ = ()

    @classmethod
    def from_components(
        cls,
        rotation: torch.Tensor,
        velocity: torch.Tensor,
        position: torch.Tensor,
        time: torch.Tensor,
    ) -> Self:
        """rotation (..., 3, 3), velocity (..., 3), position (..., 3), time (...).  The batch
        shapes broadcast as in torch: a time of shape (B, 1) with components of batch (B,) gives a
        (B, B) batch (take ``time[..., 0]``, e.g. for the (B, 1) ``dtau`` of the TLS solvers)."""
        C, v, r, tau = prepare(
            rotation=(rotation, (3, 3)),
            velocity=(velocity, (3,)),
            position=(position, (3,)),
            time=(time, ()),
        )
        return cls._new(_sgal3.from_components(C, v, r, tau))

    def velocity(self) -> torch.Tensor:
        """The velocity v (..., 3) (a view of the matrix)."""
        return self._matrix[..., :3, 3]

    def position(self) -> torch.Tensor:
        """The position r (..., 3) (a view of the matrix)."""
        return self._matrix[..., :3, 4]

    def time(self) -> torch.Tensor:
        """The time offset tau (...) (a view of the matrix)."""
        return self._matrix[..., 3, 4]

    def act(self, e: torch.Tensor, point_axes: int = 0) -> torch.Tensor:
        """Events (..., 4) = (x, t): (C x + v t + r, t + tau), (3.31).
        ``point_axes``: how many axes of points before the coordinates every element maps whole
        (0: the batches broadcast as in torch; see "Acting on points" in LieGroup)."""
        return self._f.act(self._acting(e, "e", point_axes, self.point_dim), e)

    def act_velocity(self, u: torch.Tensor, point_axes: int = 0) -> torch.Tensor:
        """Velocities (..., 3), homogeneous [u, 1, 0]: C u + v.
        ``point_axes`` as in ``act``."""
        return self._f.act_velocity(self._acting(u, "u", point_axes, 3), u)
