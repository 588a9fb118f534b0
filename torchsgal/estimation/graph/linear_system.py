"""The damped normal equations (H + lambda D) delta = -g of a linearised graph.

``DenseSystem``: a batch of small problems; H (B, D, D) assembled from the factors' blocks
(``linearize.dense``) and solved by a batched Cholesky (no host sync per problem): the operator
``torchsgal::damped_solve`` (``damped_solve``: damping, factor, solves and delta^T H delta in one
C pass) where its kernel runs (batches of small systems), LAPACK's ``cholesky_ex`` otherwise,
and its tensor code where autograd records.
``SparseSystem``: one large problem; the lower triangle of H's block pattern is analysed once by
``estimation.sparse.SparseCholesky`` (fill-reducing ordering) and refactored numerically at each
step.

Both answer the same questions: ``solve(values, g, lam, diagonal)`` -> (delta, solved),
``quadratic(values, delta)`` = delta^T H delta, ``singular(values)`` and ``marginal_blocks``
(diagonal blocks of H^-1 at the last ``set_solution``).  Rank deficiency: the Jacobi-scaled
H (unit diagonal) has a Cholesky pivot at or below ``RCOND`` (or no Cholesky), or a diagonal
entry at or below ``RCOND`` times the largest (a direction no factor sees); the scaled pivots
come from the Cholesky factor of H itself (chol(S H S) = S chol(H)).
"""
from __future__ import annotations

import threading
from collections import OrderedDict

import torch

from ..block_cholesky import Structure, analyse, block_cholesky_solve
from .damped_solve import _tensor_code as damped_tensor_code
from .damped_solve import damping, solve_damped
from .layout import EntryLayout, dense, dense_layout, times
from .problem import Problem

RCOND_FACTOR = 1e3  # RCOND = RCOND_FACTOR * eps of the dtype: the Jacobi-scaled pivots' test
# A diagonal entry at most eps times the largest is a direction no residual sees (its information
# is rounding noise, O(eps^2) of the largest); the test reads no units of its own below that
# (unknowns whose standard deviations are up to 1 / sqrt(eps) apart: 2,900 in float32, 6.7e7 in
# float64); RCOND_FACTOR * eps would flag well-posed float32 graphs whose standard deviations
# are 92 apart
DIAGONAL_RCOND_FACTOR = 1.0



def _finite_rows(x: torch.Tensor) -> torch.Tensor:
    """(B,) True where every entry of x (B, n) is finite: the largest |entry| is below inf (amax
    propagates NaN); a quicker reduction than ``isfinite(x).all(-1)``."""
    return x.abs().amax(dim=-1) < float("inf")


def _tiny_diagonal(H: torch.Tensor, rcond: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(the diagonal (B, D) of H, (B,) True where an entry is <= rcond times the largest or H
    has a non-finite entry).  A non-finite entry makes the sum of H's entries non-finite (inf,
    or NaN for inf - inf; so does a sum past the float range, entries no factorisation
    handles): one reduction instead of an elementwise finiteness test of every entry."""
    d = H.diagonal(dim1=-2, dim2=-1)
    tiny = (d <= rcond * d.amax(dim=-1, keepdim=True)).any(dim=-1) | ~torch.isfinite(
        H.sum(dim=(-1, -2)))
    return d, tiny


class DenseSystem:
    """Dense batched normal equations (module docstring)."""

    cost_first = False  # the solver linearises every trial point (one pass for the batch)

    def __init__(self, problem: Problem, workspace: tuple[torch.Tensor, ...] | None = None,
                 layout: EntryLayout | None = None, eye: torch.Tensor | None = None):
        self.problem = problem
        self.layout = layout if layout is not None else dense_layout(
            problem.h_index, problem.block_entries, problem.D)
        self.eye = eye if eye is not None else torch.eye(problem.D, dtype=problem.dtype,
                                                         device=problem.device)
        self.rcond = RCOND_FACTOR * torch.finfo(problem.dtype).eps
        self.diagonal_rcond = DIAGONAL_RCOND_FACTOR * torch.finfo(problem.dtype).eps
        self._H: torch.Tensor | None = None
        self._work = workspace

    def select(self, problem: Problem) -> DenseSystem:
        """The system of a subset of the problems (the solver's active set); it reuses this
        system's work buffers (the active set only shrinks) and its layout."""
        return DenseSystem(problem, self._work, self.layout, self.eye)

    def _workspace(self, B: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(H (B, D * D), L (B, D, D), info (B,) int32): the damped matrix and, for LAPACK, its
        Cholesky factor, allocated once per solve and reused by every step (fresh (B, D, D)
        temporaries cost more than their arithmetic at these sizes)."""
        D = self.problem.D
        if self._work is None or self._work[0].shape[0] < B:
            like = self.eye
            self._work = (like.new_empty(B, D * D), like.new_empty(B, D, D),
                          torch.empty(B, dtype=torch.int32, device=like.device))
        elif self._work[0].shape[0] > B:  # kept at this size: no slicing per step
            self._work = tuple(w[:B] for w in self._work)
        return self._work  # type: ignore[return-value]

    def solve(self, values: torch.Tensor, g: torch.Tensor, lam: torch.Tensor, diagonal: bool
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(delta (B, D), solved (B,) bool, delta^T H delta (B,)); lam (B,) (0: undamped);
        ``values`` (B, D * D) in ``layout``: H itself."""
        B, D = values.shape[0], self.problem.D
        if torch.is_grad_enabled() and (values.requires_grad or g.requires_grad):
            return damped_tensor_code(dense(self.layout, values), g, lam, diagonal)
        out = solve_damped(values.reshape(B, D, D), g, lam, diagonal)  # batches of small systems
        if out is not None:
            return out
        # LAPACK in the work buffers (larger systems, a few systems, kernels off)
        flat, L, info = self._workspace(B)
        Hd = flat.copy_(values).view(B, D, D)
        diag = Hd.diagonal(dim1=-2, dim2=-1)  # damped in place
        damp = damping(lam, diag if diagonal else None, D)
        diag.add_(damp)
        torch.linalg.cholesky_ex(Hd, out=(L, info))
        # an infinite pivot, which LAPACK takes, fails here as in the kernel
        info = info.masked_fill(~torch.isfinite(L.diagonal(dim1=-2, dim2=-1)).all(-1), 1)
        # L L^T delta = -g by two triangular solves (cholesky_solve would copy L)
        y = torch.linalg.solve_triangular(L, -g.unsqueeze(-1), upper=False)
        delta = torch.linalg.solve_triangular(L.mT, y, upper=True).squeeze(-1)
        solved = (info == 0) & _finite_rows(delta)
        delta = torch.where(solved.unsqueeze(-1), delta, 0.0)
        # delta^T H delta = delta^T (H + damping) delta - delta^T damping delta
        quad = (delta * (Hd @ delta.unsqueeze(-1)).squeeze(-1)).sum(-1) - (damp * delta * delta).sum(-1)
        return delta, solved, torch.where(solved, quad, 0.0)  # 0 H 0 = 0 where H is not finite

    def solve_information(self, rhs: torch.Tensor) -> torch.Tensor:
        """H^-1 rhs (B, D) with H at the solution (undamped), by a batched Cholesky (the
        implicit backward).  Raises where H is singular."""
        L, info = torch.linalg.cholesky_ex(self._solution())
        if bool((info != 0).any()):
            raise ValueError("the information at the solution is not positive definite: "
                             "no implicit gradient (add priors that fix the gauge)")
        return torch.cholesky_solve(rhs.unsqueeze(-1), L).squeeze(-1)

    def set_solution(self, values: torch.Tensor) -> None:
        """Keeps H at the solution for ``singular``, ``marginal_blocks``, ``dense_information``
        (and frees the work buffers of the steps)."""
        self._H = dense(self.layout, values)
        self._work = None

    def _solution(self) -> torch.Tensor:
        if self._H is None:
            raise RuntimeError("set_solution(values) first")
        return self._H

    def dense_information(self) -> torch.Tensor:
        """(B, D, D) H at the solution."""
        return self._solution()

    def singular(self) -> torch.Tensor:
        """(B,) True where H at the solution is numerically rank-deficient."""
        H = self._solution()
        d, tiny = _tiny_diagonal(H, self.diagonal_rcond)
        # the pivots of the Jacobi-scaled S H S (S = diag(H)^-1/2) without forming it:
        # chol(S H S) = S chol(H), so its pivots are L_ii^2 / H_ii (rows where ``tiny`` holds
        # are decided by ``tiny`` whatever their factorisation gives)
        L, info = torch.linalg.cholesky_ex(H)
        pivots = L.diagonal(dim1=-2, dim2=-1) ** 2 / torch.where(d > 0, d, 1.0)
        return tiny | (info != 0) | (pivots.amin(dim=-1) <= self.rcond)

    def marginal_blocks(self, starts: torch.Tensor, block: int) -> torch.Tensor:
        """(B, K, block, block) diagonal blocks of H^-1, from solves with the K * block unit
        columns they need (never the whole inverse); NaN where H is singular."""
        singular = self.singular()
        L, info = torch.linalg.cholesky_ex(torch.where(singular[:, None, None], self.eye,
                                                       self._solution()))
        B, K = L.shape[0], starts.numel()
        offsets = torch.arange(block, device=starts.device)
        pos = starts[:, None] + offsets  # (K, block)
        # the columns H^-1 e_c for c in pos, (B, D, K, block); out[b, k, i, j] = their entry
        # (s_k + i, column s_k + j), i.e. (H^-1)[s_k + i, s_k + j]
        cols = torch.cholesky_solve(self.eye[:, pos.reshape(-1)].expand(B, -1, -1), L)
        cols = cols.reshape(B, self.problem.D, K, block)
        k = torch.arange(K, device=starts.device)
        out = cols[:, pos[:, :, None], k[:, None, None], offsets]
        nan = (singular | (info != 0))[:, None, None, None]
        return torch.where(nan, torch.full_like(out, float("nan")), out)


def block_pattern(problem: Problem) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The block pattern of H: (sizes (N,), rows, cols) with one block per variable element (its
    tangent's size) and the block pairs that the factors' entries touch."""
    sizes, node_of = [], []
    first = 0
    for info in problem.variables:
        sizes += [info.dof] * info.size
        node_of.append(first + torch.arange(info.size * info.dof) // info.dof)
        first += info.size
    node = torch.cat(node_of)
    h = problem.h_index.cpu()
    return torch.tensor(sizes, dtype=torch.int64), node[h // problem.D], node[h % problem.D]


LAYOUT_CACHE = 32  # block layouts kept (the analysis and index maps of a graph's pattern)
_layouts: OrderedDict = OrderedDict()
_layouts_lock = threading.Lock()


def block_layout(problem: Problem, max_share: float | None = None
                 ) -> tuple[Structure, tuple[torch.Tensor, ...]] | None:
    """The analysis of H's block pattern and the index maps of ``BlockSparseSystem``: (each
    entry's position in the stored triangle, or the spare position P past it, the elimination
    order, the diagonal's positions).  Kept by the layout (variables' sizes and the entries'
    indices), so a graph built again with the same pattern reuses them.  With ``max_share``:
    None where the factorisation costs more than that share of the dense one
    (``block_cholesky.analyse``)."""
    h = problem.h_index.cpu()
    key = (problem.D, tuple((v.size, v.dof) for v in problem.variables), str(problem.device),
           h.numpy().tobytes(), max_share)
    with _layouts_lock:
        if key in _layouts:
            _layouts.move_to_end(key)
            return _layouts[key]
    st = analyse(*block_pattern(problem), max_share=max_share)
    if st is None:
        with _layouts_lock:
            _layouts[key] = None
        return None
    pos = st.scatter_index(h)
    maps = tuple(t.to(problem.device) for t in (pos, st.order, st.diagonal))
    with _layouts_lock:
        _layouts[key] = (st, maps)
        while len(_layouts) > LAYOUT_CACHE:
            _layouts.popitem(last=False)
    return st, maps


class BlockSparseSystem:
    """Block-sparse batched normal equations (``estimation.block_cholesky``): the pattern of H,
    one block per variable element, is analysed once (minimum-degree order, the fill of L) and
    every problem of the batch is factored and solved on it by one operator call per step.  The
    information at the solution is factored the same way for ``singular``, the implicit
    backward and the marginals; ``dense_information`` builds the dense matrix."""

    cost_first = False  # as DenseSystem: a batch linearises every trial point

    def __init__(self, problem: Problem, structure: Structure | None = None,
                 maps: tuple[torch.Tensor, ...] | None = None, layout: EntryLayout | None = None):
        self.problem = problem
        if structure is None or maps is None:
            analysed = block_layout(problem)
            assert analysed is not None  # no bound: always analysed
            structure, maps = analysed
        self.structure, self._maps = structure, maps
        self._unorder: torch.Tensor | None = None  # the elimination order's inverse (``_unordered``)
        self.layout = layout if layout is not None else EntryLayout(
            problem.h_index, problem.block_entries, problem.D, maps[0], structure.panels + 1,
            spare=structure.panels)
        self.rcond = RCOND_FACTOR * torch.finfo(problem.dtype).eps
        self.diagonal_rcond = DIAGONAL_RCOND_FACTOR * torch.finfo(problem.dtype).eps
        self._dense: DenseSystem | None = None  # built when a dense question is asked
        self._values: torch.Tensor | None = None

    def select(self, problem: Problem) -> BlockSparseSystem:
        """The system of a subset of the problems (one pattern: the analysis is shared)."""
        new = BlockSparseSystem(problem, self.structure, self._maps, self.layout)
        new._unorder = self._unorder
        return new

    def _panels(self, values: torch.Tensor) -> torch.Tensor:
        """H's stored triangle (B, P): the values (B, P + 1) in ``layout`` without their spare
        column (a view)."""
        return values[:, :self.structure.panels]

    def solve(self, values: torch.Tensor, g: torch.Tensor, lam: torch.Tensor, diagonal: bool
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """As ``DenseSystem.solve``, on the block-sparse factorisation."""
        if torch.is_grad_enabled() and (values.requires_grad or g.requires_grad):
            return damped_tensor_code(dense(self.layout, values), g, lam, diagonal)
        _, order, diag = self._maps
        damp = damping(lam, values.index_select(1, diag) if diagonal else None, diag.numel())
        v = self._panels(values).index_add(1, diag, damp)  # damped, in a new tensor
        _, X, Q, _ = block_cholesky_solve(v, g.index_select(1, order).neg_().unsqueeze(-1),
                                          self.structure)
        x = X.squeeze(-1)
        solved = _finite_rows(x)  # a failed factorisation's X is NaN (info != 0)
        x = torch.where(solved.unsqueeze(-1), x, 0.0)
        # delta^T H delta = delta^T (H + damping) delta - delta^T damping delta (elimination order)
        quad = torch.where(solved, Q.squeeze(-1), 0.0) - (damp * x * x).sum(-1)
        return x.index_select(1, self._unordered()), solved, quad

    def _unordered(self) -> torch.Tensor:
        """The inverse of the elimination order: x.index_select(1, it) puts x (B, D) in
        elimination order back in the layout's order."""
        if self._unorder is None:
            order = self._maps[1]
            self._unorder = torch.empty_like(order).index_copy_(
                0, order, torch.arange(order.numel(), device=order.device))
        return self._unorder

    def _dense_solution(self) -> DenseSystem:
        """The dense system at the solution, built when first asked (marginals, the implicit
        backward, the dense information)."""
        if self._values is None:
            raise RuntimeError("set_solution(values) first")
        if self._dense is None:
            self._dense = DenseSystem(self.problem)
            self._dense.set_solution(dense(self.layout, self._values).flatten(1))
        return self._dense

    def solve_information(self, rhs: torch.Tensor) -> torch.Tensor:
        """As ``DenseSystem.solve_information``, on the block-sparse factorisation (the dense
        system's where something differentiates ``rhs``: a second derivative)."""
        if self._values is None:
            raise RuntimeError("set_solution(values) first")
        if torch.is_grad_enabled() and rhs.requires_grad:
            return self._dense_solution().solve_information(rhs)
        order = self._maps[1]
        _, X, _, info = block_cholesky_solve(self._panels(self._values),
                                             rhs.index_select(1, order).unsqueeze(-1), self.structure)
        if bool((info != 0).any()):
            raise ValueError("the information at the solution is not positive definite: "
                             "no implicit gradient (add priors that fix the gauge)")
        return torch.empty_like(rhs).index_copy_(1, order, X.squeeze(-1))

    def set_solution(self, values: torch.Tensor) -> None:
        """Keeps H's entries at the solution for ``singular`` and the dense questions."""
        self._values = values
        self._dense = None

    def dense_information(self) -> torch.Tensor:
        """(B, D, D) H at the solution."""
        return self._dense_solution().dense_information()

    def singular(self) -> torch.Tensor:
        """(B,) True where H at the solution is numerically rank-deficient (``DenseSystem``'s
        test, on the block-sparse factor: the scaled pivots L_ii^2 / H_ii)."""
        if self._values is None:
            raise RuntimeError("set_solution(values) first")
        v = self._panels(self._values)
        d = v.index_select(1, self._maps[2])
        tiny = (d <= self.diagonal_rcond * d.amax(dim=-1, keepdim=True)).any(dim=-1) | ~torch.isfinite(
            self._values.sum(dim=-1))  # every entry of H, both triangles
        L, _, _, info = block_cholesky_solve(v, v.new_zeros(v.shape[0], self.problem.D, 0),
                                             self.structure)
        pivots = L.index_select(1, self._maps[2]) ** 2 / torch.where(d > 0, d, 1.0)
        return tiny | (info != 0) | (pivots.amin(dim=-1) <= self.rcond)

    def marginal_blocks(self, starts: torch.Tensor, block: int) -> torch.Tensor:
        """As ``DenseSystem.marginal_blocks``: solves with the K * block unit columns on the
        block-sparse factorisation at the solution (no dense matrix)."""
        if self._values is None:
            raise RuntimeError("set_solution(values) first")
        singular = self.singular()
        B, K, D = self._values.shape[0], starts.numel(), self.problem.D
        place = self._unordered()  # each unknown's position in elimination order
        offsets = torch.arange(block, device=starts.device)
        rows = place[starts[:, None] + offsets]  # (K, block): the unknowns in elimination order
        unit = self._values.new_zeros(D, K * block)
        unit[rows.reshape(-1), torch.arange(K * block, device=unit.device)] = 1.0
        _, X, _, _ = block_cholesky_solve(self._panels(self._values),
                                          unit.expand(B, D, K * block).contiguous(), self.structure)
        X = X.reshape(B, D, K, block)
        k = torch.arange(K, device=starts.device)
        out = X[:, rows[:, :, None], k[:, None, None], offsets]  # (H^-1)[s_k + i, s_k + j]
        return torch.where(singular[:, None, None, None], torch.full_like(out, float("nan")), out)


class SparseSystem:
    """Sparse normal equations of one problem (B = 1), through ``SparseCholesky``."""

    cost_first = True  # the solver evaluates a trial point's cost before linearising it

    def __init__(self, problem: Problem, backend: str = "auto"):
        from ..sparse import SparseCholesky

        if problem.B != 1:
            raise ValueError(f"the sparse linear solver takes one problem (B = 1), got B = "
                             f"{problem.B}: use linear_solver='dense' for batches")
        self.problem = problem
        D, h = problem.D, problem.h_index
        # the layout: H's lower triangle, each position once, and a spare column for the rest
        lower = torch.unique(h[((h // D) >= (h % D)).nonzero().squeeze(-1)])
        n = lower.numel()
        at = torch.searchsorted(lower, h).clamp_max(n - 1)
        slots = torch.where(lower[at] == h, at, torch.full_like(at, n))
        self.layout = EntryLayout(h, problem.block_entries, D, slots, n + 1, spare=n)
        rows, cols = lower // D, lower % D
        self.rows, self.stored = rows, n
        self.on_diagonal = (rows == cols).nonzero().squeeze(-1)
        diag = torch.arange(D, device=problem.device)
        self.factorization = SparseCholesky(torch.cat([rows, diag]), torch.cat([cols, diag]), D,
                                            backend)
        self.backend = self.factorization.backend
        self.rcond = RCOND_FACTOR * torch.finfo(problem.dtype).eps
        self.diagonal_rcond = DIAGONAL_RCOND_FACTOR * torch.finfo(problem.dtype).eps
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
            self.factorization.factor(torch.cat([v[:self.stored], damping]))
        except (NotPositiveDefiniteError, ValueError):
            return False
        return True

    def solve(self, values: torch.Tensor, g: torch.Tensor, lam: torch.Tensor, diagonal: bool
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """As ``DenseSystem.solve`` for B = 1, through the sparse factorisation."""
        v = values[0]
        D = self.problem.D
        ok = self._factor(v, damping(lam, self._diagonal(v)[None] if diagonal else None, D)[0])
        delta = self.factorization.solve(-g[0]) if ok else torch.zeros_like(g[0])
        ok = ok and bool(torch.isfinite(delta).all())
        if not ok:
            delta = torch.zeros_like(delta)
        quad = (delta * times(self.layout, values, delta[None])[0]).sum()
        return delta[None], torch.tensor([ok], device=v.device), quad[None]

    def set_solution(self, values: torch.Tensor) -> None:
        """Factors H at the solution (undamped) for ``singular`` and ``marginal_blocks``."""
        v = values[0]
        d = self._diagonal(v)
        tiny = bool((d <= self.diagonal_rcond * d.max()).any()) or not bool(torch.isfinite(v).all())
        ok = not tiny and self._factor(v, v.new_zeros(self.problem.D))
        self._values = values
        self._singular = torch.tensor([not ok], device=v.device)

    def _solution(self) -> tuple[torch.Tensor, torch.Tensor]:
        if self._values is None or self._singular is None:
            raise RuntimeError("set_solution(values) first")
        return self._values, self._singular

    def solve_information(self, rhs: torch.Tensor) -> torch.Tensor:
        """H^-1 rhs (1, D) with H at the solution, by its sparse factorisation (the implicit
        backward).  Raises where H is singular."""
        if bool(self._solution()[1][0]):
            raise ValueError("the information at the solution is not positive definite: "
                             "no implicit gradient (add priors that fix the gauge)")
        return self.factorization.solve(rhs[0])[None]

    def dense_information(self) -> torch.Tensor:
        """(1, D, D) H at the solution (dense: for small problems and checks)."""
        return dense(self.layout, self._solution()[0])

    def singular(self) -> torch.Tensor:
        """(1,) True where H at the solution is not positive definite (``SparseCholesky``)."""
        return self._solution()[1]

    def marginal_blocks(self, starts: torch.Tensor, block: int) -> torch.Tensor:
        """(1, K, block, block) diagonal blocks of H^-1 (``SparseCholesky.marginal_blocks``)."""
        if bool(self.singular()[0]):
            return torch.full((1, starts.numel(), block, block), float("nan"),
                              dtype=self.problem.dtype, device=self.problem.device)
        return self.factorization.marginal_blocks(starts, block)[None]


LinearSystem = DenseSystem | BlockSparseSystem | SparseSystem

