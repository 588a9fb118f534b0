from __future__ import annotations

import torch
from typing_extensions import Self

from ..functional import sim3 as _sim3
from ._components import prepare
from .base import LieGroup


class Sim3(LieGroup):
    """Similarity transformations [[C, r], [0, 1/s]] (..., 4, 4), scale s = exp(lambda) > 0;
    tangent [rho, phi, lambda] (..., 7) (Barfoot's (78); GTSAM's Similarity3 matrix).

    ``act`` maps points p -> s (C p + r); ``act_direction`` rotates directions, d -> C d.

    Range of lambda: L = log(finfo.max) (709.78 float64, 88.72 float32).  The matrix stores
    1/s = e^-lambda, so ``exp`` needs lambda >= -L (below, M[3, 3] is inf and the element is not
    representable; its translation is inf or NaN).  Above lambda = -log(finfo.tiny) (708.4, 87.3)
    1/s is subnormal and loses digits, and so does ``log``'s lambda; beyond 745.1 (103.3) it is
    0, not an element either.  ``jl_inv`` and ``jr_inv`` are finite for every finite lambda,
    ``jl`` for lambda < L and ``jr`` for lambda > -L; beyond, their block s M ~ e^|lambda|/|lambda|
    overflows (inf, NaN where inf meets a zero), and their gradients do within a few units of L."""

    dof = 7
    matrix_dim = 4
    point_dim = 3  # size of the vectors act() takes
    log_scale_slice = _sim3.SCALE  # lambda: the matrix stores exp(-lambda)
    _f = _sim3
    __slots__ = ()

    @classmethod
    def from_components(
        cls, rotation: torch.Tensor, position: torch.Tensor, scale: torch.Tensor
    ) -> Self:
        """rotation (..., 3, 3), position r (..., 3), scale s (...) (0-dim for one element).
        Only shapes, dtypes and devices are checked, not values: s must be positive, and C a
        rotation (``from_matrix(M, check=True)`` checks the values of a matrix)."""
        C, r, s = prepare(rotation=(rotation, (3, 3)), position=(position, (3,)), scale=(scale, ()))
        return cls._new(_sim3.from_components(C, r, s))

    _fixed_note = " (|M[3, :3]| relative to |M[3, 3]|)"

    @classmethod
    def _fixed_deviation(cls, M: torch.Tensor) -> torch.Tensor:
        """Only the zeros of the bottom row [0, 0, 0, 1/s] are fixed, and they are measured
        relative to M[3, 3] = 1/s (free, any positive value, checked below): max |M[3, :3]| /
        |M[3, 3]|.  That ratio is what a composition sees (the product's M[3, 3] gains M[3, :3]
        times the other's translation), and compared absolutely, row entries far larger than a
        tiny 1/s passed and a rounding error beside a huge 1/s failed.  1/s = 0 gives inf or NaN
        here and is refused by the positivity check."""
        return M[..., 3, :3].abs().amax(dim=-1) / M[..., 3, 3].abs()

    @classmethod
    def _extra_measures(cls, M: torch.Tensor) -> tuple:
        return (M[..., 3, 3].min(),)

    @classmethod
    def _check_extra_measures(cls, values: list) -> None:
        if values[0] <= 0:
            raise ValueError(f"matrix is not in Sim3: M[3, 3] = 1/s must be positive, got {values[0]:.3g}")

    def position(self) -> torch.Tensor:
        """r (..., 3), the translation column of the matrix (a view of it)."""
        return self._matrix[..., :3, 3]

    def scale(self) -> torch.Tensor:
        """s = exp(lambda) (...) = 1 / M[3, 3]."""
        return 1.0 / self._matrix[..., 3, 3]

    def act(self, p: torch.Tensor, point_axes: int = 0) -> torch.Tensor:
        """Points (..., 3): s (C p + r).
        ``point_axes``: how many axes of points before the coordinates every element maps whole
        (0: the batches broadcast as in torch; see "Acting on points" in LieGroup)."""
        return self._f.act(self._acting(p, "p", point_axes, self.point_dim), p)

    def act_jacobians(self, p: torch.Tensor, /, point_axes: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
        """As ``LieGroup.act_jacobians`` for y = s (C p + r): J_g by the quotient rule
        (``functional.sim3.act_jacobian``), J_x = s C (a new tensor per element, expanded over
        the points where one element acts on many, as ``LieGroup.act_jacobians`` says)."""
        M = self._acting(p, "p", point_axes, self.point_dim)
        J_g = self._f.act_jacobian(M, p)
        return J_g, (M[..., :3, :3] / M[..., 3, 3, None, None]).expand(J_g.shape[:-1] + (3,))
