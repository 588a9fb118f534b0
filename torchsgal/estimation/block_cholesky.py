"""Batched Cholesky solves of block-sparse systems that share one pattern.

A factor graph's normal equations are block-sparse: one block row and column per variable
element (its tangent's size), a nonzero block where a factor joins two elements.  Every problem
of a batched graph has the same pattern, so one symbolic analysis serves the whole batch:

* ``analyse(sizes, rows, cols)``: a minimum-degree elimination order of the blocks (ties to the
  lowest index), the pattern of the factor L (each block column holds the blocks still joined to
  it when it is eliminated: its fill), and the index maps of the numeric factorisation.  Kept in
  a small cache keyed by the pattern, so a graph solved again (each step of a solver, each call
  of a solver on the same graph) is analysed once.
* L is stored as one dense panel per block column: the diagonal block and, below it, the blocks
  of the rows that column reaches (sorted by elimination), row-major; the systems' values are
  (B, P) in that layout (``Structure.scatter_index`` places the entries of H there).
* ``torchsgal::block_cholesky_solve(values, rhs, structure)`` -> (L, X, Q, info): the factor's
  panels (B, P), X = A^-1 rhs (B, D, k) with rhs and X in elimination order
  (``Structure.order``), Q (B, k) the quadratic forms x^T A x of X's columns (a solver's model
  decrease), and info (B,) int32: 0, or the (elimination-order) row + 1 of the first pivot that
  is not positive, as LAPACK's potrf, with that system's L, X and Q NaN.  On the CPU with the
  kernels built and on: the C kernel of ``_native_block_cholesky.h``, left-looking by block
  column (each column gathers the updates of the columns that reach it, then factors its
  diagonal block and solves the blocks below), eight systems per pass, the batch split over
  ``torch.get_num_threads()`` threads.  Elsewhere (other
  devices, kernels off): the tensor code below, the dense factorisation of the same matrix
  (torch.linalg), the reference the tests compare the kernel with.  No autograd formula: the
  engine calls it where nothing differentiates (the dense path serves differentiable solves).
  Under vmap the mapped axis joins the systems' batch (the structure is not mapped); a fake
  implementation gives torch.compile the shapes.

Cost: a minimum-degree order leaves a chain or a tree without fill, and a pose graph's loops
with a few fill blocks, so the factorisation costs a small fraction of the dense one
(``Structure.flops`` and ``dense_flops`` give both; ``analyse(..., max_share=)`` refuses a
pattern that would cost more than a share of the dense one without finishing its analysis).
``benchmarks/bench_posegraph.py`` times it against ``SparseCholesky``'s backends.
"""
from __future__ import annotations

import heapq
import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import torch

from ..functional import checks, native
from ..functional.registration import operator

try:
    from . import _native as _lib  # type: ignore[attr-defined]  # compiled: mypy reads no .so
except ImportError:  # not compiled: the tensor code runs everywhere
    _lib = None

__all__ = ["Structure", "analyse", "block_cholesky_solve", "uses_kernel"]

CACHE_SIZE = 32  # analyses kept, least recently used dropped first
_cache: OrderedDict = OrderedDict()
_cache_lock = threading.Lock()


@dataclass(frozen=True)
class Structure:
    """The symbolic analysis of one block pattern (``analyse``).

    size           D, the number of unknowns.
    order          (D,) int64: scalar e of the elimination order is scalar ``order[e]`` of the
                   system (permute a right-hand side by ``rhs[..., order, :]``).
    panels         P, the number of stored values of L per system.
    packed         int64 tensor handed to the operator: the header and index arrays below.
    scatter_index  callable (flat indices r * D + c of entries of A) -> positions in the
                   (P + 1,) values (P: an entry of the strict upper triangle, dropped).
    diagonal       (D,) int64: positions of the diagonal entries, in elimination order.
    flops          multiply-adds of the factorisation; ``dense_flops`` those of a dense one.
    """

    size: int
    order: torch.Tensor
    panels: int
    packed: torch.Tensor
    diagonal: torch.Tensor
    flops: int
    dense_flops: int
    _node_of: torch.Tensor  # (D,) the block of each scalar (system order)
    _start: torch.Tensor  # (nodes,) its first scalar (system order)
    _pair_keys: torch.Tensor  # sorted keys node_r * nodes + node_c of the stored blocks
    _pair_base: torch.Tensor  # per key: position of the block's (0, 0) entry
    _pair_stride: torch.Tensor  # per key: the panel's row stride (its column block's size)

    def scatter_index(self, flat: torch.Tensor) -> torch.Tensor:
        """Positions in the values (P + 1,) of the entries ``flat`` = r * D + c of A: the lower
        triangle in elimination order (and the diagonal blocks whole); P for the others."""
        D, n = self.size, self._start.numel()
        r, c = flat // D, flat % D
        nr, nc = self._node_of[r], self._node_of[c]
        keys = nr * n + nc
        at = torch.searchsorted(self._pair_keys, keys).clamp_max(self._pair_keys.numel() - 1)
        found = self._pair_keys[at] == keys
        pos = (self._pair_base[at] + (r - self._start[nr]) * self._pair_stride[at]
               + (c - self._start[nc]))
        return torch.where(found, pos, torch.full_like(pos, self.panels))


def _minimum_degree(adjacency: list[set], size: list[int], max_flops: float | None
                    ) -> tuple[list[int], list[list[int]], int] | None:
    """Elimination order by minimum degree (exact degrees of the elimination graph, ties to the
    lowest block), each eliminated block's neighbours at that moment (L's column pattern) and the
    factorisation's multiply-adds (column k with s unknowns and R below: s^3/6 + s^2 R/2 for
    its own block and rows, s (R^2 + sum of its blocks' s_t^2)/2 for its updates of the later
    columns); None once they pass ``max_flops``."""
    n = len(adjacency)
    adj = [set(a) for a in adjacency]
    heap = [(len(a), v) for v, a in enumerate(adj)]
    heapq.heapify(heap)
    done = [False] * n
    order, columns = [], []
    flops = 0.0
    while heap:
        d, v = heapq.heappop(heap)
        if done[v] or d != len(adj[v]):
            continue  # an outdated entry
        done[v] = True
        nbrs = adj[v]
        order.append(v)
        columns.append(list(nbrs))
        s, below = size[v], [size[u] for u in nbrs]
        R = sum(below)
        flops += s ** 3 / 6 + s * s * R / 2 + s * (R * R + sum(b * b for b in below)) / 2
        if max_flops is not None and flops > max_flops:
            return None
        for u in nbrs:  # the neighbours become a clique
            a = adj[u]
            a.discard(v)
            a |= nbrs
            a.discard(u)
            heapq.heappush(heap, (len(a), u))
        adj[v] = set()
    return order, columns, int(flops)


def analyse(sizes: torch.Tensor, rows: torch.Tensor, cols: torch.Tensor,
            max_share: float | None = None) -> Structure | None:
    """The symbolic analysis (module docstring) of the symmetric block pattern with block sizes
    ``sizes`` (N,) and nonzero blocks (rows[i], cols[i]) (int64 block indices; either triangle,
    duplicates allowed; the diagonal blocks are always stored).  Cached by the pattern.

    With ``max_share``, None where the factorisation would cost more than that share of the
    dense one's multiply-adds: at once where more than half the block pairs are nonzero (such
    a pattern fills in), else as soon as the elimination passes the bound (a pattern with much
    fill is not analysed to its end)."""
    for name, t in (("sizes", sizes), ("rows", rows), ("cols", cols)):
        if not isinstance(t, torch.Tensor) or t.dtype != torch.int64 or t.dim() != 1:
            raise TypeError(f"{name} must be an int64 tensor of shape (n,), got "
                            f"{getattr(t, 'dtype', type(t).__name__)} of shape "
                            f"{tuple(getattr(t, 'shape', ()))}")
    n = sizes.numel()
    if rows.shape != cols.shape:
        raise ValueError(f"rows and cols must have one shape, got {tuple(rows.shape)} and "
                         f"{tuple(cols.shape)}")
    if n == 0 or bool((sizes < 1).any()):
        raise ValueError(f"sizes must be positive (at least one block), got {sizes.tolist()}")
    if rows.numel() and (int(torch.minimum(rows, cols).min()) < 0
                         or int(torch.maximum(rows, cols).max()) >= n):
        raise ValueError(f"block indices must lie in [0, {n})")
    if max_share is not None:
        checks.finite_number(max_share, "max_share", "> 0")
    keys = torch.unique(torch.minimum(rows, cols) * n + torch.maximum(rows, cols)).cpu()
    key = (tuple(sizes.tolist()), keys.numpy().tobytes(), max_share)
    with _cache_lock:
        if key in _cache:
            _cache.move_to_end(key)
            return _cache[key]
    D = int(sizes.sum())
    if max_share is not None and 2 * keys.numel() > n * (n + 1) // 2:
        structure = None
    else:
        structure = _analyse(sizes.cpu(), keys, n,
                             None if max_share is None else max_share * D ** 3 / 6)
    with _cache_lock:
        _cache[key] = structure
        while len(_cache) > CACHE_SIZE:
            _cache.popitem(last=False)
    return structure


def _ranges(starts, lengths) -> np.ndarray:
    """The concatenated ranges [starts[i], starts[i] + lengths[i]) (int64)."""
    starts, lengths = np.asarray(starts, dtype=np.int64), np.asarray(lengths, dtype=np.int64)
    total = int(lengths.sum())
    if total == 0:
        return np.zeros(0, dtype=np.int64)
    first = np.cumsum(lengths) - lengths
    return np.arange(total, dtype=np.int64) + np.repeat(starts - first, lengths)


def _analyse(sizes: torch.Tensor, keys: torch.Tensor, n: int, max_flops: float | None
             ) -> Structure | None:
    size = [int(s) for s in sizes.tolist()]
    adjacency: list[set] = [set() for _ in range(n)]
    for k in keys.tolist():
        a, b = divmod(k, n)
        if a != b:
            adjacency[a].add(b)
            adjacency[b].add(a)
    elimination = _minimum_degree(adjacency, size, max_flops)
    if elimination is None:
        return None
    order, columns, flops = elimination
    pos = [0] * n
    for t, v in enumerate(order):
        pos[v] = t
    sizes_elim = [size[v] for v in order]
    elim_off = np.concatenate([[0], np.cumsum(sizes_elim)[:-1]]).astype(np.int64).tolist()
    D = sum(size)
    start = np.concatenate([[0], np.cumsum(size)[:-1]]).astype(np.int64)  # per block, system order
    # panel t: rows of block order[t], then of its column's blocks in elimination order
    panel_nodes = [[order[t]] + sorted(columns[t], key=pos.__getitem__) for t in range(n)]
    panel_rows: list[int] = []
    panel_off: list[int] = []
    row_base: list[int] = []
    row_of: list[dict] = []  # per panel: block -> its first row
    node_rows: list[int] = []  # per (panel, block): the block's first unknown (elimination order)
    node_len: list[int] = []
    off = rbase = 0
    for t in range(n):
        s, r, offsets = sizes_elim[t], 0, {}
        for u in panel_nodes[t]:
            offsets[u] = r
            node_rows.append(elim_off[pos[u]])
            node_len.append(size[u])
            r += size[u]
        row_of.append(offsets)
        panel_rows.append(r)
        panel_off.append(off)
        row_base.append(rbase)
        off += r * s
        rbase += r
    P = off
    row_index = _ranges(node_rows, node_len)  # each panel row's unknown
    # updates: column t gathers L_{i k} L_{t k}^T from every earlier column k that reaches t
    updates: list[list[int]] = [[] for _ in range(n)]
    for k in range(n):
        for u in panel_nodes[k][1:]:
            updates[pos[u]].append(k)
    upd_ptr: list[int] = [0]  # per column: its updates' range
    upd_k: list[int] = []  # per update: the source column
    upd_start: list[int] = []  # its first row in the source panel
    upd_map: list[int] = []  # the offset of its row map
    map_starts: list[int] = []  # the row map, as ranges of panel t's rows
    map_lens: list[int] = []
    mapped = 0
    for t in range(n):
        target = row_of[t]
        for k in updates[t]:
            first = row_of[k][order[t]]  # block t's first row in panel k
            upd_k.append(k)
            upd_start.append(first)
            upd_map.append(mapped)
            for u in panel_nodes[k]:
                if pos[u] >= t:  # rows from block t on, into panel t
                    map_starts.append(target[u])
                    map_lens.append(size[u])
            mapped += panel_rows[k] - first
        upd_ptr.append(len(upd_k))
    maps = _ranges(map_starts, map_lens)
    header = [n, D, P, len(upd_k), int(maps.size), rbase, flops]
    packed = torch.from_numpy(np.concatenate([
        np.asarray(header + sizes_elim + elim_off + panel_off + panel_rows + row_base, dtype=np.int64),
        row_index, np.asarray(upd_ptr + upd_k + upd_start + upd_map, dtype=np.int64), maps]))
    # the stored blocks: (row block, column block) -> position of (0, 0) and row stride
    pair_keys, pair_base, pair_stride = [], [], []
    for t in range(n):
        v, s = order[t], sizes_elim[t]
        for u in panel_nodes[t]:
            pair_keys.append(u * n + v)
            pair_base.append(panel_off[t] + row_of[t][u] * s)
            pair_stride.append(s)
    # the diagonal's positions: entry c of block t at panel_off[t] + c (s + 1)
    sizes_np = np.asarray(sizes_elim, dtype=np.int64)
    c = _ranges(np.zeros(n, dtype=np.int64), sizes_np)
    diagonal = np.repeat(np.asarray(panel_off, dtype=np.int64), sizes_np) + c * (np.repeat(sizes_np, sizes_np) + 1)
    sort = np.argsort(np.asarray(pair_keys, dtype=np.int64), kind="stable")
    scalar_order = _ranges(start[np.asarray(order, dtype=np.int64)], sizes_np)
    node_of = np.repeat(np.arange(n, dtype=np.int64), np.asarray(size, dtype=np.int64))

    def as_long(xs) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(np.asarray(xs, dtype=np.int64)))

    return Structure(D, as_long(scalar_order), P, packed, as_long(diagonal), flops, D ** 3 // 6,
                     as_long(node_of), as_long(start),
                     as_long(np.asarray(pair_keys, dtype=np.int64)[sort]),
                     as_long(np.asarray(pair_base, dtype=np.int64)[sort]),
                     as_long(np.asarray(pair_stride, dtype=np.int64)[sort]))


def uses_kernel(values: torch.Tensor) -> bool:
    """Whether the operator runs the C kernel for these values now: CPU float32/float64, kernels
    built and on in the calling thread."""
    return (_lib is not None and native.enabled() and values.device.type == "cpu"
            and values.dtype in (torch.float32, torch.float64))


def block_cholesky_solve(values: torch.Tensor, rhs: torch.Tensor, structure: Structure
                         ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """(L (B, P), X (B, D, k), Q (B, k), info (B,)) for the systems whose stored values (B, P) are
    ``values`` (the lower triangle in ``structure``'s layout) and right-hand sides ``rhs``
    (B, D, k) in elimination order (module docstring)."""
    if not isinstance(structure, Structure):
        raise TypeError(f"structure must be a Structure (analyse), got {type(structure).__name__}")
    packed = structure.packed if structure.packed.device == values.device else \
        structure.packed.to(values.device)
    return torch.ops.torchsgal.block_cholesky_solve(values, rhs, packed)


HEADER = 7  # n, D, P, U, M, Rt, flops


def _check(values, rhs, packed, read: bool = True) -> tuple[int, int, int, int]:
    """Types and shapes; with ``read``, also against the sizes in the structure's header (not
    for fake tensors, whose values are unknown)."""
    checks.floating(values, "values")
    checks.floating(rhs, "rhs")
    checks.same_device_dtype(values=values, rhs=rhs)
    if packed.dtype != torch.int64 or packed.dim() != 1 or packed.numel() < HEADER:
        raise ValueError("structure must be the packed int64 tensor of a Structure (analyse)")
    if values.dim() != 2 or rhs.dim() != 3:
        raise ValueError(f"values must be (B, P) and rhs (B, D, k), got {tuple(values.shape)} "
                         f"and {tuple(rhs.shape)}")
    if not read:
        return rhs.shape[1], values.shape[1], rhs.shape[2], 0
    n, D, P, U, M, Rt, flops = packed[:HEADER].tolist()
    if packed.numel() != HEADER + 5 * n + Rt + (n + 1) + 3 * U + M:
        raise ValueError("structure is not a consistent block pattern (block_cholesky.analyse "
                         "makes one)")
    if values.shape[1] != P:
        raise ValueError(f"values must have shape (B, {P}), got {tuple(values.shape)}")
    if rhs.dim() != 3 or rhs.shape[0] != values.shape[0] or rhs.shape[1] != D:
        raise ValueError(f"rhs must have shape ({values.shape[0]}, {D}, k), got {tuple(rhs.shape)}")
    return D, P, rhs.shape[2], flops


def _unpack_dense(packed: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(rows, cols) (P,) of each stored value in the dense elimination-order matrix."""
    h = [int(v) for v in packed[:HEADER].tolist()]
    n, P, rtot = h[0], h[2], h[5]
    base = HEADER
    sizes = packed[base:base + n]
    elim_off = packed[base + n:base + 2 * n]
    panel_rows = packed[base + 3 * n:base + 4 * n]
    row_index = packed[base + 5 * n:base + 5 * n + rtot]
    # per stored value: its panel t, row r within the panel and column c
    counts = panel_rows * sizes
    t = torch.repeat_interleave(torch.arange(n, device=packed.device), counts)
    first = torch.cumsum(counts, 0) - counts
    local = torch.arange(P, device=packed.device) - first[t]
    r, c = local // sizes[t], local % sizes[t]
    row_base = torch.cumsum(panel_rows, 0) - panel_rows
    return row_index[row_base[t] + r], elim_off[t] + c


@operator("torchsgal::block_cholesky_solve",
          schema="(Tensor values, Tensor rhs, Tensor structure) -> (Tensor, Tensor, Tensor, Tensor)")
def _block_cholesky_solve_op(values: torch.Tensor, rhs: torch.Tensor, structure: torch.Tensor
                             ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """(L, X, Q, info) (module docstring): the tensor code."""
    D, P, _, _ = _check(values, rhs, structure)
    return _tensor_code(values, rhs, structure, D, P)


def _tensor_code(values, rhs, structure, D: int, P: int):
    B = values.shape[0]
    rows, cols = _unpack_dense(structure)
    A = values.new_zeros(B, D * D).index_copy_(1, rows * D + cols, values).view(B, D, D)
    L, info = torch.linalg.cholesky_ex(A)  # reads the lower triangle
    bad = ~torch.isfinite(L.diagonal(dim1=-2, dim2=-1))
    first = torch.where(bad.any(-1), bad.to(torch.int32).argmax(-1) + 1, 0).to(info.dtype)
    info = torch.where((first != 0) & ((info == 0) | (first < info)), first, info)
    ok = (info == 0)[:, None, None]
    X = torch.where(ok, torch.cholesky_solve(rhs, torch.where(ok, L, torch.eye(
        D, dtype=L.dtype, device=L.device))), float("nan"))
    Lp = L.reshape(B, D * D).index_select(1, rows * D + cols)
    full = A.tril() + A.tril(-1).mT
    Q = (X * (full @ X)).sum(dim=-2)
    return (torch.where(ok[:, 0], Lp, float("nan")).contiguous(), X.contiguous(), Q,
            info.to(torch.int32))


@_block_cholesky_solve_op.register_kernel("cpu")
def _block_cholesky_solve_cpu(values, rhs, structure):
    D, P, k, flops = _check(values, rhs, structure)
    if not uses_kernel(values):
        return _tensor_code(values, rhs, structure, D, P)
    B = values.shape[0]
    values, rhs = values.resolve_neg().contiguous(), rhs.resolve_neg().contiguous()
    structure = structure.contiguous()
    L, X, Q = torch.empty_like(values), torch.empty_like(rhs), values.new_empty(B, k)
    info = torch.empty(B, dtype=torch.int32)
    cost = (flops + 3 * P * k) // 400 + 1  # one system's work in SGal(3) exps (~400 flops)
    _lib.block_cholesky_solve(values.data_ptr(), rhs.data_ptr(), structure.data_ptr(), L.data_ptr(),
                              X.data_ptr(), Q.data_ptr(), info.data_ptr(), B, k, cost,
                              torch.get_num_threads(), values.dtype is torch.float64,
                              structure.numel())
    return L, X, Q, info


@_block_cholesky_solve_op.register_fake
def _block_cholesky_solve_fake(values, rhs, structure):
    _check(values, rhs, structure, read=False)
    return (values.new_empty(values.shape), rhs.new_empty(rhs.shape),
            values.new_empty(values.shape[0], rhs.shape[2]),
            values.new_empty(values.shape[:1], dtype=torch.int32))


@_block_cholesky_solve_op.register_vmap
def _block_cholesky_solve_vmap(info, in_dims, values, rhs, structure):
    """The vmapped axis joins the systems' batch (one pattern for all)."""
    if in_dims[2] is not None:
        raise ValueError("block_cholesky_solve: the structure cannot be vmapped (one pattern)")
    V = info.batch_size
    moved = [t.unsqueeze(0).expand(V, *t.shape) if d is None else t.movedim(d, 0)
             for t, d in zip((values, rhs), in_dims[:2])]
    values, rhs = moved[0], moved[1]
    B = values.shape[1]
    L, X, Q, status = _block_cholesky_solve_op(values.reshape(V * B, -1),
                                               rhs.reshape((V * B,) + rhs.shape[2:]), structure)
    return ((L.reshape(V, B, -1), X.reshape((V, B) + X.shape[1:]), Q.reshape(V, B, -1),
             status.reshape(V, B)), (0, 0, 0, 0))
