"""A Levenberg-Marquardt step's damped normal equations, for a batch of small dense systems.

``torch.ops.torchsgal.damped_solve(H, g, lam, diagonal)`` -> (delta, solved, quad): H (B, D, D)
symmetric, g (B, D), lam (B,) of one floating dtype; (H + lam D) delta = -g with D = I, or with
``diagonal`` D = diag(H) clamped to ``DIAGONAL_CLAMP`` (GTSAM's minDiagonal, maxDiagonal);
``solved`` (B,) bool where the Cholesky factor exists and delta is finite (elsewhere delta = 0),
``quad`` (B,) = delta^T H delta (the undamped H), which the solver's model decrease reads.

As tensor code (``_tensor_code``, the reference the tests compare the kernel with, and the
differentiable form ``DenseSystem`` runs where autograd records) the step is some twenty
operations: the damped copy, the factor, two triangular solves, the finiteness test and the
products of ``quad``.  The CPU kernel (``damped_solve_range`` of
``estimation/_native_cholesky.h``) does it in one pass, several systems at once (one per vector
lane), the batch split over ``torch.get_num_threads()`` threads; ``DenseSystem.solve`` takes the
operator where ``dense_solve.uses_kernel`` holds for the batch (systems of up to
``dense_solve.KERNEL_MAX_SIZE`` unknowns, at least ``dense_solve.MIN_BATCH`` of them) and nothing
records (``factor_kernels.usable``).  No derivative is registered.
"""
from __future__ import annotations

import torch

from ...functional.registration import operator
from .. import dense_solve
from .factor_kernels import usable

__all__ = ["damped_solve", "damping", "uses_damped_kernel", "DIAGONAL_CLAMP"]

DIAGONAL_CLAMP = (1e-6, 1e32)  # GTSAM's minDiagonal, maxDiagonal for diagonal damping


def damping(lam: torch.Tensor, d: torch.Tensor | None, n: int) -> torch.Tensor:
    """The damping (B, n) added to H's diagonal: lam clamp(d) for diagonal damping (d (B, n) the
    diagonal's values), else (d None) lam broadcast over the n entries (a view)."""
    lam = lam.unsqueeze(-1)
    return lam.expand(-1, n) if d is None else lam * d.clamp(*DIAGONAL_CLAMP)


def _check(H, g, lam, diagonal) -> None:
    for name, t in (("H", H), ("g", g), ("lam", lam)):
        if not isinstance(t, torch.Tensor) or not t.is_floating_point():
            raise TypeError(f"damped_solve: {name} must be a floating tensor, got "
                            f"{t.dtype if isinstance(t, torch.Tensor) else type(t).__name__}")
    if H.dim() != 3 or H.shape[1] != H.shape[2]:
        raise ValueError(f"damped_solve: H must have shape (B, D, D), got {tuple(H.shape)}")
    B, D = H.shape[:2]
    if tuple(g.shape) != (B, D) or tuple(lam.shape) != (B,):
        raise ValueError(f"damped_solve: g must have shape {(B, D)} and lam {(B,)}, got "
                         f"{tuple(g.shape)} and {tuple(lam.shape)}")
    if g.dtype != H.dtype or lam.dtype != H.dtype or g.device != H.device or lam.device != H.device:
        raise TypeError(f"damped_solve: H, g and lam must share a dtype and device, got "
                        f"{H.dtype}/{g.dtype}/{lam.dtype} on {H.device}/{g.device}/{lam.device}")
    if not isinstance(diagonal, bool):
        raise TypeError(f"damped_solve: diagonal must be True or False, got {diagonal!r}")


def _tensor_code(H: torch.Tensor, g: torch.Tensor, lam: torch.Tensor, diagonal: bool):
    damp = damping(lam, H.diagonal(dim1=-2, dim2=-1) if diagonal else None, H.shape[-1])
    L, info = torch.linalg.cholesky_ex(H + torch.diag_embed(damp))
    # LAPACK takes an infinite pivot, which the kernel refuses
    ok = (info == 0) & torch.isfinite(L.diagonal(dim1=-2, dim2=-1)).all(-1)
    L = torch.where(ok[:, None, None], L, torch.eye(H.shape[-1], dtype=H.dtype, device=H.device))
    delta = torch.cholesky_solve(-g.unsqueeze(-1), L).squeeze(-1)
    solved = ok & torch.isfinite(delta).all(dim=-1)
    delta = torch.where(solved[:, None], delta, torch.zeros_like(delta))
    quad = (delta * (H @ delta.unsqueeze(-1)).squeeze(-1)).sum(-1)
    return delta, solved, torch.where(solved, quad, 0.0)  # 0 H 0 = 0 where H is not finite


@operator("torchsgal::damped_solve",
          schema="(Tensor H, Tensor g, Tensor lam, bool diagonal) -> (Tensor, Tensor, Tensor)")
def damped_solve(H: torch.Tensor, g: torch.Tensor, lam: torch.Tensor, diagonal: bool) -> tuple:
    """(delta, solved, quad) of the damped normal equations (module docstring)."""
    _check(H, g, lam, diagonal)
    return _tensor_code(H, g, lam, diagonal)


@damped_solve.register_kernel("cpu")
def _kernel(H, g, lam, diagonal):
    _check(H, g, lam, diagonal)
    if not uses_damped_kernel(H):
        return _tensor_code(H, g, lam, diagonal)
    B, D = H.shape[:2]
    H, g, lam = (t.resolve_neg().contiguous() for t in (H, g, lam))
    delta, quad = torch.empty(B, D, dtype=H.dtype), torch.empty(B, dtype=H.dtype)
    solved = torch.empty(B, dtype=torch.bool)
    clamp = _clamp_bounds()
    dense_solve._lib.damped_solve(H.data_ptr(), g.data_ptr(), lam.data_ptr(), delta.data_ptr(),
                                  solved.data_ptr(), quad.data_ptr(), clamp.data_ptr(), B, D,
                                  int(diagonal), torch.get_num_threads(), H.dtype is torch.float64)
    return delta, solved, quad


_CLAMP: list = []


def _clamp_bounds() -> torch.Tensor:
    """DIAGONAL_CLAMP as a float64 tensor for the kernel (made once)."""
    if not _CLAMP:
        _CLAMP.append(torch.tensor(DIAGONAL_CLAMP, dtype=torch.float64))
    return _CLAMP[0]


@damped_solve.register_fake
def _fake(H, g, lam, diagonal):
    _check(H, g, lam, diagonal)
    return g.new_empty(g.shape), lam.new_empty(lam.shape, dtype=torch.bool), lam.new_empty(lam.shape)


def uses_damped_kernel(H: torch.Tensor) -> bool:
    """Whether the operator runs its C kernel for H (B, D, D): CPU float32/float64, the dense
    kernels' size rule (``dense_solve``), kernels built and on in the calling thread."""
    return H.shape[0] >= dense_solve.MIN_BATCH and dense_solve.uses_kernel(H)


def solve_damped(H: torch.Tensor, g: torch.Tensor, lam: torch.Tensor, diagonal: bool):
    """The solver's call: the operator where its kernel runs and nothing records, else None
    (the caller's own path)."""
    if uses_damped_kernel(H) and usable(H, g, lam):
        return torch.ops.torchsgal.damped_solve(H, g, lam, diagonal)
    return None
