"""Sparse Cholesky factorisation of symmetric positive-definite systems with a fill-reducing
ordering, for the normal equations of factor graphs.

``SparseCholesky(rows, cols, size)`` takes the pattern of the lower triangle once (symbolic
analysis and ordering), then ``factor(values)`` and ``solve(rhs)`` as often as the values
change.  Backends, in the order ``"auto"`` tries them (measured on the normal equations of
sphere2500 by ``benchmarks/bench_posegraph.py``, see ``docs/guide/pose_graph_io.md``: cholmod
about twice as fast as cholespy and scipy, which are within the timing noise of each other
there; cholespy comes first of the two as it also runs on CUDA):

- ``"cholmod"``: CHOLMOD's supernodal Cholesky with AMD ordering (scikit-sparse); the
  symbolic analysis is kept and each ``factor`` is numeric only.
- ``"cholespy"``: cholespy (CHOLMOD on CPU, its own solver on CUDA); works on CUDA tensors,
  analyses the pattern again at each ``factor``.
- ``"scipy"``: SuperLU (``scipy.sparse.linalg.splu``) in symmetric mode with a minimum-degree
  ordering of A + A^T and no pivoting, so that its LU is the Cholesky's LDL^T.
- ``"dense"``: ``torch.linalg.cholesky_ex`` of the dense matrix (needs only torch; warns above
  ``DENSE_WARN_SIZE`` unknowns, where memory grows as size^2 and time as size^3).

A matrix that is not positive definite (indefinite, or singular: a squared pivot not above
``PIVOT_RTOL`` times the largest, where the backend exposes its pivots: all but cholespy,
which reports CHOLMOD's refusals, and from ``solve`` a result that is not finite for a finite
rhs) raises ``NotPositiveDefiniteError`` from ``factor``; the solver then holds no factor and
``solve`` raises until a ``factor`` succeeds.  ``factor`` raises ValueError for NaN or
infinite values; ``solve`` with a non-finite rhs is not a singular matrix: on every backend the
columns of rhs with NaN or infinite entries come back with non-finite entries (which ones
depends on the backend), the others as usual, and the factor is kept (the solvers test the
step for finiteness themselves).  The sparse backends compute in float64 on the CPU (one copy
to and from the host per call); the results come back with the values' dtype and device.
"""
from __future__ import annotations

import importlib.util
import warnings
from collections.abc import Callable
from typing import Protocol

import numpy as np
import torch

from ..functional import checks

BACKENDS = ("cholmod", "cholespy", "scipy", "dense")  # the order "auto" tries them in
DENSE_WARN_SIZE = 5000  # the dense backend warns above this many unknowns
PIVOT_RTOL = 1e-13  # a squared pivot at or below this times the largest one is singular
MARGINAL_CHUNK = 1024  # unit columns solved at once by marginal_blocks

_MODULES = {"cholmod": "sksparse", "cholespy": "cholespy", "scipy": "scipy", "dense": "torch"}


class _Backend(Protocol):
    device: torch.device

    def factor(self, values: torch.Tensor) -> None: ...

    def solve(self, rhs: torch.Tensor) -> torch.Tensor: ...


class NotPositiveDefiniteError(torch.linalg.LinAlgError):
    """``SparseCholesky.factor`` met a matrix that is not positive definite (indefinite or
    singular).  A subclass of ``torch.linalg.LinAlgError`` (a RuntimeError), so one handler
    catches it and the dense solvers' errors."""


def available_backends() -> tuple[str, ...]:
    """The backends whose library is installed, in the order ``"auto"`` tries them."""
    return tuple(b for b in BACKENDS if importlib.util.find_spec(_MODULES[b]) is not None)


class SparseCholesky:
    """Cholesky factorisation of a sparse symmetric positive-definite matrix A (size x size)
    given by its lower triangle.

    rows, cols  int64 (nnz,) pattern of the lower triangle (rows >= cols); duplicate entries
                are summed.  The symbolic analysis and the fill-reducing ordering run once here.
    size        the order of A.
    backend     "auto" (the first installed of ``BACKENDS``) or one of ``BACKENDS``.

    Attributes: ``backend`` (the library that runs it), ``size``, ``nnz`` (entries of the
    pattern given, duplicates included).  Raises ``NotPositiveDefiniteError`` from ``factor``
    for a matrix that is not positive definite.
    """

    def __init__(self, rows: torch.Tensor, cols: torch.Tensor, size: int, backend: str = "auto"):
        self.size = checks.integer(size, "size", minimum=1)
        rows = _index_vector(rows, "rows")
        cols = _index_vector(cols, "cols")
        if rows.shape != cols.shape:
            raise ValueError(f"rows and cols must have one shape, got {tuple(rows.shape)} "
                             f"and {tuple(cols.shape)}")
        rows, cols = rows.cpu(), cols.cpu()
        if rows.numel():
            lo = int(torch.minimum(rows.min(), cols.min()))
            hi = int(torch.maximum(rows.max(), cols.max()))
            if lo < 0 or hi >= self.size:
                raise ValueError(f"rows and cols must lie in [0, {self.size - 1}] (size={self.size}), "
                                 f"got entries from {lo} to {hi}")
            upper = int((rows < cols).sum())
            if upper:
                raise ValueError(f"rows and cols must give the lower triangle (rows >= cols), "
                                 f"got {upper} entries with rows < cols")
        self.nnz = rows.numel()
        self.backend = _choose(backend)
        # the entries in compressed-column order of the lower triangle, duplicates merged
        keys, self._inverse = torch.unique(cols * self.size + rows, sorted=True, return_inverse=True)
        self._merged = keys.numel()
        self._rows = (keys % self.size).numpy().astype(np.int64)
        self._cols = (keys // self.size).numpy().astype(np.int64)
        self._impl: _Backend = _IMPLEMENTATIONS[self.backend](self._rows, self._cols, self.size)
        self._dtype: torch.dtype | None = None
        self._device: torch.device | None = None

    def factor(self, values: torch.Tensor) -> None:
        """Factors A whose lower-triangle entries are ``values`` (nnz,) (float64 or float32,
        computed in float64), at the pattern given to the constructor.  Raises
        ``NotPositiveDefiniteError`` if A is not positive definite, ValueError for non-finite
        values."""
        checks.floating(values, "values")
        if values.shape != (self.nnz,):
            raise ValueError(f"values must have shape ({self.nnz},) (the pattern's nnz), "
                             f"got {tuple(values.shape)}")
        self._dtype = None  # no factor until this one succeeds
        merged = torch.zeros(self._merged, dtype=torch.float64, device=values.device)
        merged.index_add_(0, self._inverse.to(values.device), values.detach().to(torch.float64))
        if not bool(torch.isfinite(merged).all()):
            raise ValueError("values must be finite, got NaN or infinite entries")
        self._impl.factor(merged)
        self._dtype, self._device = values.dtype, values.device

    def solve(self, rhs: torch.Tensor) -> torch.Tensor:
        """A^-1 rhs for rhs (size,) or (size, k), with the factor of the last ``factor``; the
        result has the dtype and device of the values factored.  A column of rhs with NaN or
        infinite entries gives a column with non-finite entries (every backend alike)."""
        if self._dtype is None:
            raise RuntimeError("SparseCholesky.solve needs a successful factor(values) first")
        checks.floating(rhs, "rhs")
        if rhs.dim() not in (1, 2) or rhs.shape[0] != self.size:
            raise ValueError(f"rhs must have shape ({self.size},) or ({self.size}, k), "
                             f"got {tuple(rhs.shape)}")
        if rhs.device != self._device:
            raise ValueError(f"rhs is on {rhs.device} but the factored values are on {self._device}")
        x = self._impl.solve(rhs.detach().to(torch.float64).reshape(self.size, -1).contiguous())
        return x.reshape(rhs.shape).to(device=self._device, dtype=self._dtype)

    def marginal_blocks(self, starts: torch.Tensor, block: int) -> torch.Tensor:
        """Diagonal blocks of A^-1: (k, block, block), the rows and columns
        ``starts[i] : starts[i] + block``, from solves with the needed unit columns
        (``MARGINAL_CHUNK`` at a time), never the whole inverse."""
        block = checks.integer(block, "block", minimum=1)
        starts = _index_vector(starts, "starts")
        if starts.numel():
            lo, hi = int(starts.min()), int(starts.max())
            if lo < 0 or hi + block > self.size:
                raise ValueError(f"starts must lie in [0, {self.size - block}] (size={self.size}, "
                                 f"block={block}), got entries from {lo} to {hi}")
        if self._dtype is None:
            raise RuntimeError("SparseCholesky.marginal_blocks needs a successful factor(values) first")
        k = starts.numel()
        starts = starts.cpu()
        offsets = torch.arange(block)
        columns = (starts[:, None] + offsets).reshape(-1)  # (k * block,) unit columns e_c
        needed = starts.repeat_interleave(block)[:, None] + offsets  # (k * block, block) rows
        parts = []
        for c in range(0, columns.numel(), MARGINAL_CHUNK):
            chunk = columns[c:c + MARGINAL_CHUNK]
            unit = torch.zeros(self.size, chunk.numel(), dtype=torch.float64, device=self._impl.device)
            unit[chunk.to(unit.device), torch.arange(chunk.numel(), device=unit.device)] = 1.0
            x = self._impl.solve(unit)  # (size, chunk): the columns A^-1 e_c
            parts.append(x.T.gather(1, needed[c:c + MARGINAL_CHUNK].to(x.device)))
        if not k:
            return torch.zeros(0, block, block, dtype=self._dtype, device=self._device)
        # [i, b, a] = A^-1[s_i + a, s_i + b]
        out = torch.cat(parts, dim=0).reshape(k, block, block).transpose(-1, -2)
        return out.to(device=self._device, dtype=self._dtype)


# --------------------------------------------------------------------------- helpers
def _index_vector(x, name: str) -> torch.Tensor:
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    if x.dtype != torch.int64 or x.dim() != 1:
        raise TypeError(f"{name} must be an int64 tensor of shape (n,), "
                        f"got {x.dtype} of shape {tuple(x.shape)}")
    return x


def _choose(backend) -> str:
    if not isinstance(backend, str) or backend not in ("auto",) + BACKENDS:
        raise ValueError(f"backend must be 'auto' or one of {BACKENDS}, got {backend!r}")
    installed = available_backends()
    if backend == "auto":
        return installed[0]  # "dense" needs only torch
    if backend not in installed:
        raise ImportError(f"backend {backend!r} needs the package {_MODULES[backend]!r}, "
                          f"which is not installed; installed backends: {installed}")
    return backend


def _singular(pivots: np.ndarray) -> str | None:
    """Why the squared pivots (the diagonal of D in A = L D L^T) are not those of a positive
    definite matrix, or None."""
    if pivots.size == 0:
        return None
    bad = np.flatnonzero(~(pivots > PIVOT_RTOL * pivots.max()))
    if bad.size == 0:
        return None
    return (f"pivot {bad[0]} of the factor is {pivots[bad[0]]:.3g} (largest {pivots.max():.3g}, "
            f"{bad.size} at or below {PIVOT_RTOL:g} times it): the matrix is singular or indefinite")


class _Cholmod:
    device = torch.device("cpu")

    def __init__(self, rows, cols, size):
        import scipy.sparse as sp
        from sksparse import cholmod

        self._cholmod = cholmod
        indptr = np.zeros(size + 1, dtype=np.int64)
        np.cumsum(np.bincount(cols, minlength=size), out=indptr[1:])
        self._A = sp.csc_matrix((np.ones(rows.size), rows, indptr), shape=(size, size))
        self._factor = cholmod.analyze(self._A, mode="supernodal", ordering_method="amd")

    def factor(self, values: torch.Tensor) -> None:
        self._A.data[:] = values.cpu().numpy()
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", self._cholmod.CholmodWarning)
                self._factor.cholesky_inplace(self._A)
        except self._cholmod.CholmodNotPositiveDefiniteError as e:
            raise NotPositiveDefiniteError(f"cholmod: the matrix is not positive definite ({e})") from None
        # CHOLMOD refuses only pivots <= 0; the relative test catches singular matrices whose
        # zero pivots came out as rounding noise (D of L D L^T: the squared diagonal of L)
        reason = _singular(np.asarray(self._factor.D()))
        if reason:
            raise NotPositiveDefiniteError(f"cholmod: {reason}")

    def solve(self, rhs: torch.Tensor) -> torch.Tensor:
        return torch.from_numpy(np.asarray(self._factor(rhs.cpu().numpy())))


class _Cholespy:
    def __init__(self, rows, cols, size):
        import cholespy

        self._cholespy = cholespy
        self._size = size
        self._rows = torch.from_numpy(rows.astype(np.int32))
        self._cols = torch.from_numpy(cols.astype(np.int32))
        self._solver = None
        self.device = torch.device("cpu")

    def factor(self, values: torch.Tensor) -> None:
        self.device = values.device
        self._solver = None
        if values.numel() == 0:  # cholespy fails on it with a bare RuntimeError
            raise NotPositiveDefiniteError("cholespy: the pattern is empty: the matrix is zero, "
                                           "not positive definite")
        try:
            self._solver = self._cholespy.CholeskySolverD(
                self._size, self._rows.to(values.device), self._cols.to(values.device),
                values.contiguous(), self._cholespy.MatrixType.COO)
        except ValueError as e:
            raise NotPositiveDefiniteError(f"cholespy: {e}") from None

    def solve(self, rhs: torch.Tensor) -> torch.Tensor:
        rhs = rhs.to(self.device)
        x = torch.empty_like(rhs)
        step = 128 if self.device.type == "cuda" else rhs.shape[1]  # its CUDA limit per call
        for c in range(0, rhs.shape[1], max(step, 1)):
            part = torch.empty_like(rhs[:, c:c + step])
            self._solver.solve(rhs[:, c:c + step].contiguous(), part)
            x[:, c:c + step] = part
        # a non-finite result for a finite rhs column means a singular factor; a non-finite
        # rhs column gives a non-finite result, as on the other backends
        if bool((~torch.isfinite(x).all(0) & torch.isfinite(rhs).all(0)).any()):
            raise NotPositiveDefiniteError("cholespy: the solve gave non-finite values for a finite "
                                           "rhs: the matrix is singular")
        return x


class _Scipy:
    device = torch.device("cpu")

    def __init__(self, rows, cols, size):
        import scipy.sparse as sp
        from scipy.sparse.linalg import splu

        self._sp, self._splu = sp, splu
        off = rows != cols
        # the full symmetric pattern: each entry, then the mirror of the off-diagonal ones
        self._take = np.concatenate([np.arange(rows.size), np.flatnonzero(off)])
        self._r = np.concatenate([rows, cols[off]])
        self._c = np.concatenate([cols, rows[off]])
        self._size = size
        self._lu = None

    def factor(self, values: torch.Tensor) -> None:
        v = values.cpu().numpy()[self._take]
        A = self._sp.csc_matrix((v, (self._r, self._c)), shape=(self._size, self._size))
        self._lu = None
        try:
            lu = self._splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                            options={"SymmetricMode": True})
        except RuntimeError as e:  # "Factor is exactly singular"
            raise NotPositiveDefiniteError(f"scipy: {e}") from None
        if not (np.array_equal(lu.perm_r, lu.perm_c)):
            raise NotPositiveDefiniteError("scipy: SuperLU pivoted off the diagonal: the matrix is "
                                           "not positive definite")
        reason = _singular(lu.U.diagonal())
        if reason:
            raise NotPositiveDefiniteError(f"scipy: {reason}")
        self._lu = lu

    def solve(self, rhs: torch.Tensor) -> torch.Tensor:
        return torch.from_numpy(np.asarray(self._lu.solve(rhs.cpu().numpy()))).reshape(rhs.shape)


class _Dense:
    def __init__(self, rows, cols, size):
        if size > DENSE_WARN_SIZE:
            warnings.warn(f"SparseCholesky backend 'dense' on {size} unknowns stores the "
                          f"{size} x {size} matrix and factors it in O(size^3); install "
                          f"scikit-sparse, cholespy or scipy for a sparse factor", stacklevel=3)
        self._rows = torch.from_numpy(rows)
        self._cols = torch.from_numpy(cols)
        self._size = size
        self._L = None
        self.device = torch.device("cpu")

    def factor(self, values: torch.Tensor) -> None:
        self.device = values.device
        r, c = self._rows.to(values.device), self._cols.to(values.device)
        A = torch.zeros(self._size, self._size, dtype=torch.float64, device=values.device)
        A.index_put_((r, c), values)
        A.index_put_((c, r), values)  # the diagonal written twice with the same value
        self._L = None
        L, info = torch.linalg.cholesky_ex(A)
        if int(info):
            raise NotPositiveDefiniteError(f"dense: the leading minor of order {int(info)} is not "
                                           f"positive definite")
        reason = _singular((L.diagonal() ** 2).cpu().numpy())
        if reason:
            raise NotPositiveDefiniteError(f"dense: {reason}")
        self._L = L

    def solve(self, rhs: torch.Tensor) -> torch.Tensor:
        return torch.cholesky_solve(rhs.to(self.device), self._L)


_IMPLEMENTATIONS: dict[str, Callable[[np.ndarray, np.ndarray, int], _Backend]] = {
    "cholmod": _Cholmod, "cholespy": _Cholespy, "scipy": _Scipy, "dense": _Dense}
