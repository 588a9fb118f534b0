"""The damped normal equations (H + lambda D) delta = -g of a linearised graph.

``DenseSystem``: a batch of small problems; H (B, D, D) assembled from the factors' blocks
(``linearize.dense``) and factored by a batched ``torch.linalg.cholesky_ex`` (no host sync per
problem).  ``SparseSystem``: one large problem; the lower triangle of H's block pattern is
analysed once by ``estimation.sparse.SparseCholesky`` (fill-reducing ordering) and refactored
numerically at each step.

Both answer the same questions: ``solve(values, g, lam, diagonal)`` -> (delta, solved),
``quadratic(values, delta)`` = delta^T H delta, ``singular(values)`` and ``marginal_blocks``
(diagonal blocks of H^-1 at the last ``set_solution``).  Rank deficiency: the Jacobi-scaled
H (unit diagonal) has a Cholesky pivot at or below ``RCOND`` (or no Cholesky), or a diagonal
entry at or below ``RCOND`` times the largest (a direction no factor sees).
"""
from __future__ import annotations

import torch

from .linearize import Problem, dense

RCOND_FACTOR = 1e3  # RCOND = RCOND_FACTOR * eps of the dtype
DIAGONAL_CLAMP = (1e-6, 1e32)  # GTSAM's minDiagonal, maxDiagonal for diagonal damping


def _scaled(H: torch.Tensor, rcond: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(H with unit diagonal, (B,) True where a diagonal entry is <= rcond times the largest
    or non-finite)."""
    d = H.diagonal(dim1=-2, dim2=-1)
    tiny = (d <= rcond * d.amax(dim=-1, keepdim=True)).any(dim=-1) | ~torch.isfinite(H).all(
        dim=(-1, -2))
    s = torch.where(d > 0, d, torch.ones_like(d)).rsqrt()
    return H * s[..., :, None] * s[..., None, :], tiny


class DenseSystem:
    """Dense batched normal equations (module docstring)."""

    cost_first = False  # the solver linearises every trial point (one pass for the batch)

    def __init__(self, problem: Problem):
        self.problem = problem
        self.eye = torch.eye(problem.D, dtype=problem.dtype, device=problem.device)
        self.rcond = RCOND_FACTOR * torch.finfo(problem.dtype).eps
        self._H: torch.Tensor | None = None

    def select(self, problem: Problem) -> DenseSystem:
        """The system of a subset of the problems (the solver's active set)."""
        return DenseSystem(problem)

    def solve(self, values: torch.Tensor, g: torch.Tensor, lam: torch.Tensor, diagonal: bool
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(delta (B, D), solved (B,) bool, delta^T H delta (B,)); lam (B,) (0: undamped)."""
        Hd = dense(self.problem, values)  # a new tensor: damped in place (no (B, D, D) copies)
        diag = Hd.diagonal(dim1=-2, dim2=-1)
        damp = lam[:, None] * (diag.clamp(*DIAGONAL_CLAMP) if diagonal else torch.ones_like(diag))
        diag.add_(damp)
        L, info = torch.linalg.cholesky_ex(Hd)
        delta = torch.cholesky_solve(-g.unsqueeze(-1), L).squeeze(-1)
        solved = (info == 0) & torch.isfinite(delta).all(dim=-1)
        delta = torch.where(solved[:, None], delta, torch.zeros_like(delta))
        # delta^T H delta = delta^T (H + damping) delta - delta^T damping delta
        quad = (delta * (Hd @ delta.unsqueeze(-1)).squeeze(-1)).sum(-1) - (damp * delta * delta).sum(-1)
        return delta, solved, quad

    def set_solution(self, values: torch.Tensor) -> None:
        """Keeps H at the solution for ``singular``, ``marginal_blocks``, ``dense_information``."""
        self._H = dense(self.problem, values)

    def _solution(self) -> torch.Tensor:
        if self._H is None:
            raise RuntimeError("set_solution(values) first")
        return self._H

    def dense_information(self) -> torch.Tensor:
        """(B, D, D) H at the solution."""
        return self._solution()

    def singular(self) -> torch.Tensor:
        """(B,) True where H at the solution is numerically rank-deficient."""
        Hs, tiny = _scaled(self._solution(), self.rcond)
        L, info = torch.linalg.cholesky_ex(torch.where(tiny[:, None, None], self.eye, Hs))
        pivots = L.diagonal(dim1=-2, dim2=-1) ** 2
        return tiny | (info != 0) | (pivots.amin(dim=-1) <= self.rcond)

    def marginal_blocks(self, starts: torch.Tensor, block: int) -> torch.Tensor:
        """(B, K, block, block) diagonal blocks of H^-1; NaN where H is singular."""
        singular = self.singular()
        L, info = torch.linalg.cholesky_ex(torch.where(singular[:, None, None], self.eye,
                                                       self._solution()))
        P = torch.cholesky_inverse(L)
        pos = starts[:, None] + torch.arange(block, device=starts.device)
        out = P[:, pos[:, :, None], pos[:, None, :]]
        nan = (singular | (info != 0))[:, None, None, None]
        return torch.where(nan, torch.full_like(out, float("nan")), out)


class SparseSystem:
    """Sparse normal equations of one problem (B = 1), through ``SparseCholesky``."""

    cost_first = True  # the solver evaluates a trial point's cost before linearising it

    def __init__(self, problem: Problem, backend: str = "auto"):
        from ..sparse import SparseCholesky

        if problem.B != 1:
            raise ValueError(f"the sparse linear solver takes one problem (B = 1), got B = "
                             f"{problem.B}: use linear_solver='dense' for batches")
        self.problem = problem
        D = problem.D
        rows, cols = problem.h_index // D, problem.h_index % D
        self.rows, self.cols = rows, cols
        self.lower = (rows >= cols).nonzero().squeeze(-1)  # the pattern, once
        self.on_diagonal = (rows == cols).nonzero().squeeze(-1)
        diag = torch.arange(D, device=problem.device)
        self.factorization = SparseCholesky(torch.cat([rows[self.lower], diag]),
                                            torch.cat([cols[self.lower], diag]), D, backend)
        self.backend = self.factorization.backend
        self.rcond = RCOND_FACTOR * torch.finfo(problem.dtype).eps
        self._values: torch.Tensor | None = None
        self._singular: torch.Tensor | None = None

    def select(self, problem: Problem) -> SparseSystem:
        """Itself (one problem: no active set to shrink)."""
        return self

    def _diagonal(self, v: torch.Tensor) -> torch.Tensor:
        D = self.problem.D
        return v.new_zeros(D).index_add_(0, self.rows[self.on_diagonal], v[self.on_diagonal])

    def _factor(self, v: torch.Tensor, damping: torch.Tensor) -> bool:
        from ..sparse import NotPositiveDefiniteError

        try:
            self.factorization.factor(torch.cat([v[self.lower], damping]))
        except (NotPositiveDefiniteError, ValueError):
            return False
        return True

    def solve(self, values: torch.Tensor, g: torch.Tensor, lam: torch.Tensor, diagonal: bool
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """As ``DenseSystem.solve`` for B = 1, through the sparse factorisation."""
        v = values[0]
        D = self.problem.D
        damp = self._diagonal(v).clamp(*DIAGONAL_CLAMP) if diagonal else v.new_ones(D)
        ok = self._factor(v, lam[0] * damp)
        delta = self.factorization.solve(-g[0]) if ok else torch.zeros_like(g[0])
        ok = ok and bool(torch.isfinite(delta).all())
        if not ok:
            delta = torch.zeros_like(delta)
        Hdelta = v.new_zeros(D).index_add_(0, self.rows, v * delta[self.cols])
        quad = (delta * Hdelta).sum()
        return delta[None], torch.tensor([ok], device=v.device), quad[None]

    def set_solution(self, values: torch.Tensor) -> None:
        """Factors H at the solution (undamped) for ``singular`` and ``marginal_blocks``."""
        v = values[0]
        d = self._diagonal(v)
        tiny = bool((d <= self.rcond * d.max()).any()) or not bool(torch.isfinite(v).all())
        ok = not tiny and self._factor(v, v.new_zeros(self.problem.D))
        self._values = values
        self._singular = torch.tensor([not ok], device=v.device)

    def _solution(self) -> tuple[torch.Tensor, torch.Tensor]:
        if self._values is None or self._singular is None:
            raise RuntimeError("set_solution(values) first")
        return self._values, self._singular

    def dense_information(self) -> torch.Tensor:
        """(1, D, D) H at the solution (dense: for small problems and checks)."""
        return dense(self.problem, self._solution()[0])

    def singular(self) -> torch.Tensor:
        """(1,) True where H at the solution is not positive definite (``SparseCholesky``)."""
        return self._solution()[1]

    def marginal_blocks(self, starts: torch.Tensor, block: int) -> torch.Tensor:
        """(1, K, block, block) diagonal blocks of H^-1 (``SparseCholesky.marginal_blocks``)."""
        if bool(self.singular()[0]):
            return torch.full((1, starts.numel(), block, block), float("nan"),
                              dtype=self.problem.dtype, device=self.problem.device)
        return self.factorization.marginal_blocks(starts, block)[None]


LinearSystem = DenseSystem | SparseSystem
