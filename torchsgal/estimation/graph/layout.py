"""Where the linearisation stores the normal equations' entries: each linear system's own layout.

Every factor contributes the entries J_a^T J_b of its blocks at the flat positions
``Problem.h_index`` (r * D + c of H, both triangles, a position once per factor that touches
it).  An ``EntryLayout`` sends entry k to column ``slots[k]`` of the values (B, size) that
``linearize`` returns, summing the entries that share a column, so that each system receives H
in the form it factors: ``DenseSystem`` the matrix itself (column r * D + c), the block and
sparse systems their stored lower triangle, with the entries they do not store (the strict
upper triangle, which mirrors the lower one) summed into a spare column that nothing reads but
the finiteness tests.  The raw layout (one column per entry) is the default of ``linearize``.

``dense``, ``times`` and ``diagonal`` read H, H v and diag(H) from values of any layout,
through H's structural nonzeros (``EntryLayout.entries``).
"""
from __future__ import annotations

import torch

__all__ = ["EntryLayout", "raw_layout", "dense_layout", "dense", "times", "diagonal"]


class EntryLayout:
    """Entry k of ``h_index`` (nnz,) goes to column ``slots[k]`` of the values (B, size);
    ``spare`` is the column of the entries the system does not store (or None);
    ``square``: the values are H itself, flattened (size D * D, column r * D + c)."""

    def __init__(self, h_index: torch.Tensor, block_sizes: list[int], D: int, slots: torch.Tensor,
                 size: int, spare: int | None = None, square: bool = False):
        self.D, self.size, self.spare, self.square = D, size, spare, square
        self.h_index, self.slots = h_index, slots
        self.block_slots = slots.split(block_sizes)  # one index per factor block, in order
        self._entries: tuple[torch.Tensor, ...] | None = None
        self._block_index: dict[tuple[int, int], tuple[torch.Tensor, ...]] = {}

    def block_index(self, n: int, g_index: torch.Tensor, rows: int, Dk: int
                    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(slots (rows, Dk * Dk), g_slots (rows, Dk)): the columns of factor block n's entries
        and the positions ``g_index`` of its gradient, one row per factor (a block whose
        factors share one row expanded to ``rows``), as the assembly takes them; kept per
        block and ``rows`` (views of the fixed indices)."""
        kept = self._block_index.get((n, rows))
        if kept is None or kept[0] is not g_index:
            kept = (g_index, self.block_slots[n].reshape(-1, Dk * Dk).expand(rows, -1),
                    g_index.reshape(-1, Dk).expand(rows, -1))
            self._block_index[(n, rows)] = kept
        return kept[1], kept[2]

    def entries(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(rows, cols, columns): H[rows[k], cols[k]] is the sum of the values' ``columns[k]``
        over the k of each position (the raw layout has several columns per position, the
        others one); both triangles, a dropped entry (r, c) read from its mirror (c, r)."""
        if self._entries is None:
            D = self.D
            # the (position, column) pairs, sorted by position: keyed by the position's rank
            # among the distinct positions (below nnz: no overflow where r * D + c times the
            # number of columns would pass the int64 range)
            positions, rank = torch.unique(self.h_index, return_inverse=True)
            key = torch.unique(rank * self.size + self.slots)
            flat, column = positions[key // self.size], key % self.size
            if self.spare is not None:  # one column per position: the stored mirror's
                kept = (column != self.spare).nonzero().squeeze(-1)
                kept_flat, kept_column = flat[kept], column[kept]
                at = torch.searchsorted(kept_flat, (flat % D) * D + flat // D)
                at = at.clamp_max(kept_flat.numel() - 1)
                column = torch.where(column == self.spare, kept_column[at], column)
            self._entries = (flat // D, flat % D, column)
        return self._entries  # type: ignore[return-value]


def raw_layout(h_index: torch.Tensor, block_sizes: list[int], D: int) -> EntryLayout:
    """One column per entry: the factors' blocks side by side."""
    n = h_index.numel()
    return EntryLayout(h_index, block_sizes, D, torch.arange(n, device=h_index.device), n)


def dense_layout(h_index: torch.Tensor, block_sizes: list[int], D: int) -> EntryLayout:
    """H itself, flattened (B, D * D)."""
    return EntryLayout(h_index, block_sizes, D, h_index, D * D, square=True)


def dense(layout: EntryLayout, values: torch.Tensor) -> torch.Tensor:
    """H (B, D, D) from values in ``layout`` (differentiable)."""
    B, D = values.shape[0], layout.D
    if layout.square:
        return values.reshape(B, D, D)
    rows, cols, column = layout.entries()
    return values.new_zeros(B, D * D).index_add(1, rows * D + cols,
                                                values.index_select(1, column)).reshape(B, D, D)


def times(layout: EntryLayout, values: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """H v (B, D) from values in ``layout``."""
    if layout.square:
        return (dense(layout, values) @ v.unsqueeze(-1)).squeeze(-1)
    rows, cols, column = layout.entries()
    return v.new_zeros(v.shape).index_add(1, rows, values.index_select(1, column) * v[:, cols])


def diagonal(layout: EntryLayout, values: torch.Tensor) -> torch.Tensor:
    """diag(H) (B, D) from values in ``layout`` (no data-dependent shapes: no host sync)."""
    if layout.square:
        return dense(layout, values).diagonal(dim1=-2, dim2=-1)
    rows, cols, column = layout.entries()
    on = (rows == cols).to(values.dtype)
    return values.new_zeros(values.shape[0], layout.D).index_add(
        1, rows, values.index_select(1, column) * on)
