"""Cholesky factor and its inverse for many small matrices at once.

torch's CPU ``linalg.cholesky`` / ``solve_triangular`` call LAPACK once
per matrix, which dominates for batches of 10^4-10^5 matrices of size ~10.  Here the loops run
over the (few) columns and every operation is vectorised over the batch, held in the last
dimension (``*_t`` functions: matrices (n, n, *batch), contiguous), where each operation
reads contiguous memory.

Failure semantics follow ``torch.linalg.cholesky_ex``: ``info`` (int32, the batch shape) is 0
where the matrix is positive definite, else the order of the first leading minor that is not
(a pivot <= 0 or NaN).  The factor of such a matrix is not meaningful; here its entries from the
failing column on are non-finite (NaN or inf), so that nothing downstream looks valid.
"""
from __future__ import annotations

import torch

# Batch sizes from which the vectorised routines beat LAPACK's per-matrix calls (CPU); below,
# inverse_cholesky_factor_t calls torch.linalg (the batch shape is known on the host, no sync).
MIN_BATCH = 512


def _batch_last(A: torch.Tensor) -> torch.Tensor:
    return A.movedim((-2, -1), (0, 1)).contiguous()


def _batch_first(A_t: torch.Tensor) -> torch.Tensor:
    return A_t.movedim((0, 1), (-2, -1))


def cholesky_t(S_t: torch.Tensor, out: torch.Tensor | None = None
               ) -> tuple[torch.Tensor, torch.Tensor]:
    """Lower Cholesky factor of S (n, n, *batch); only the lower triangle of S is read.
    Returns (L, info) with L (n, n, *batch) (written to ``out`` if given, a reusable buffer)
    and info (*batch) int32."""
    n = S_t.shape[0]
    L = torch.zeros_like(S_t) if out is None else out.zero_()
    info = torch.zeros(S_t.shape[2:], dtype=torch.int32, device=S_t.device)
    for j in range(n):
        v = S_t[j:, j]
        if j:
            v = v - (L[j:, :j] * L[j, :j]).sum(1)
        piv = v[0]
        # The first column j + 1 whose pivot fails (NaN fails too, as in LAPACK).
        info = torch.where((info == 0) & ~(piv > 0), j + 1, info)
        L[j:, j] = v * piv.rsqrt()
    return L, info


def tril_inverse_t(L_t: torch.Tensor, out: torch.Tensor | None = None) -> torch.Tensor:
    """L^-1 of lower-triangular L (n, n, *batch) by forward substitution, row by row:
    X[i, :i] = -L[i, i]^-1 L[i, :i] X[:i, :i], X[i, i] = L[i, i]^-1 (into ``out`` if given)."""
    n = L_t.shape[0]
    X = torch.zeros_like(L_t) if out is None else out.zero_()
    for i in range(n):
        di = L_t[i, i].reciprocal()
        X[i, i] = di
        if i:
            X[i, :i] = (L_t[i, :i, None] * X[:i, :i]).sum(0) * -di
    return X


def inverse_cholesky_factor_t(S_t: torch.Tensor, work: tuple | None = None
                              ) -> tuple[torch.Tensor, torch.Tensor]:
    """L^-1 (lower) with S = L L^T for S (n, n, m); (L^-1, info).  ``work``: two buffers
    shaped like S_t for L and L^-1 (reused between calls).  Below ``MIN_BATCH`` matrices
    LAPACK is called instead (fewer operations; its factor of a matrix that is not positive
    definite is made NaN, as here)."""
    if S_t[0, 0].numel() >= MIN_BATCH:
        L, info = cholesky_t(S_t, None if work is None else work[0])
        return tril_inverse_t(L, None if work is None else work[1]), info
    S = _batch_first(S_t)
    L, info = torch.linalg.cholesky_ex(S)
    L = torch.where((info != 0)[..., None, None], float("nan"), L)
    eye = torch.eye(S.shape[-1], dtype=S.dtype, device=S.device)
    return _batch_last(torch.linalg.solve_triangular(L, eye, upper=False)), info
