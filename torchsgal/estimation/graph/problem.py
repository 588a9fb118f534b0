"""The fixed layout of a ``FactorGraph`` for a batch of problems (``Problem``).

``Problem`` fixes the layout once: the variables' order and offsets in the stacked tangent
vector (variable-major, element-major: element n of variable v at ``offset_v + n dof_v``),
each factor block's data and noise with a problem axis, and the flat indices that scatter
every factor's Jacobian blocks ``J_a^T J_b`` into the (D x D) normal equations and ``J_a^T r``
into the gradient; ``select`` restricts it to a subset of the batch (the solvers' active set),
``retract`` moves the variables by a tangent step.  ``linearize`` evaluates it.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from ...groups import SE2, SE3, LieGroup
from ...uncertainty.covariance import check_covariance
from . import factors as _factors
from .factors import Factor
from .graph import FactorGraph
from .layout import EntryLayout, raw_layout
from .log_terms import se2_log_jacobians, se3_log_jacobians


@dataclass
class VariableInfo:
    name: str
    group: type[LieGroup] | None  # the group, or None for Euclidean
    size: int  # N
    dof: int
    offset: int


@dataclass
class Block:
    """One factor object, prepared: per slot (variable position, indices), its data with a
    problem axis or shared, its square-root information (or None), its scatter indices."""

    factor: Factor
    slots: list[tuple[int, torch.Tensor]]
    data: list  # tensors / group elements
    data_batched: list[bool]
    sqrt_info: torch.Tensor | None  # (m, m), (E, m, m) or (B, E, m, m)
    sqrt_info_batched: bool
    dofs: list[int]
    h_index: torch.Tensor  # (E * Dk * Dk,) into the flat (D * D) matrix ((Dk * Dk,) if reduced)
    g_index: torch.Tensor  # (E * Dk,) into the (D,) gradient ((Dk,) if reduced)
    size: int  # E
    uniform: list[int | None]  # per slot: the one index every factor reads, or None
    reduced: bool  # every slot uniform: the E factors' blocks are summed by one product
    log_form: str | None = None  # "prior" / "between": r = log(Z^-1 h(x)) (``_log_form``)
    measured_inv: torch.Tensor | None = None  # Z^-1 as a matrix leaf, for ``log_form``
    measured_inv_adjoint: torch.Tensor | None = None  # Ad(Z^-1), for SE(3) betweens


class Problem:
    """The fixed layout of a graph; ``select(rows)`` gives the same problem for a subset of
    the batch (the active set of the solvers).  ``attach=True`` keeps the factors' data and
    noise in the autograd graph (differentiable solves); by default they are detached."""

    def __init__(self, graph: FactorGraph, attach: bool = False):
        self.attach = attach
        if not graph.variables:
            raise ValueError("the graph has no variables")
        if not graph.factors:
            raise ValueError("the graph has no factors")
        first = next(iter(graph.variables.values()))
        leaf = first.as_matrix() if isinstance(first, LieGroup) else first
        self.dtype, self.device = leaf.dtype, leaf.device
        self.batched = graph.batch_size is not None
        self.B = graph.batch_size or 1
        self.variables: list[VariableInfo] = []
        offset = 0
        for name, v in graph.variables.items():
            group = type(v)._group if isinstance(v, LieGroup) else None
            info = VariableInfo(name, group, graph.size(name), graph.dof(name), offset)
            offset += info.size * info.dof
            self.variables.append(info)
        self.D = offset
        self.index = {v.name: k for k, v in enumerate(self.variables)}
        made: dict = {}  # what the blocks share, made once: tangent positions, noise checks
        self.blocks = [self._block(f, made) for f in graph.factors]
        self.h_index = torch.cat([b.h_index for b in self.blocks])  # (nnz,) flat into (D * D)
        self.block_entries = [b.h_index.numel() for b in self.blocks]  # each block's share
        self._layout: EntryLayout | None = None

    @property
    def layout(self) -> EntryLayout:
        """The raw layout (one column per entry, ``linearize``'s default), made when first asked."""
        if self._layout is None:
            self._layout = raw_layout(self.h_index, self.block_entries, self.D)
        return self._layout

    def _block(self, factor: Factor, made: dict) -> Block:
        E, B = factor.size, self.B
        slots, dofs, starts = [], [], []
        for name, idx in factor.slots:
            k = self.index[name]
            info = self.variables[k]
            idx = idx.to(self.device)
            slots.append((k, idx))
            dofs.append(info.dof)
            # (E, dof) positions of each slot's tangent in the stacked vector: element idx of
            # variable k starts at offset + idx dof
            first = made.get(("first", k))
            if first is None:
                first = made["first", k] = info.offset + torch.arange(info.dof, device=self.device)
            starts.append(idx[:, None] * info.dof + first)
        # a slot whose factors all read one element is passed as that element (batch (B, 1)),
        # broadcast against the data; when every slot is, the factors' J^T J sum by one product
        uniform = [_uniform(idx) if E else None for _, idx in slots]
        reduced = all(u is not None for u in uniform)
        pos = torch.cat(starts, dim=1)  # (E, Dk)
        if reduced:
            pos = pos[:1]
        h_index = (pos[:, :, None] * self.D + pos[:, None, :]).reshape(-1)
        data, batched = [], []
        for k, d in enumerate(factor.data):
            leaf = d.as_matrix() if isinstance(d, LieGroup) else d
            if leaf.device != self.device or leaf.dtype != self.dtype:
                raise ValueError(f"{factor!r} data[{k}]: expected {self.dtype} on {self.device}, "
                                 f"got {leaf.dtype} on {leaf.device}")
            nb = len(d.batch_shape) if isinstance(d, LieGroup) else None
            if nb is not None:
                per_problem = nb == 2
                shape_ok = (nb in (1, 2) and d.batch_shape[-1] in (E, 1)
                            and (nb == 1 or d.batch_shape[0] in (B, 1)))
            else:
                per_problem = self.batched and leaf.dim() >= 2 and tuple(leaf.shape[:2]) == (B, E)
                shape_ok = leaf.dim() >= 1 and leaf.shape[0] in (E, 1) or per_problem
            if not shape_ok:
                shape = tuple(d.batch_shape) if nb is not None else tuple(leaf.shape)
                raise ValueError(f"{factor!r} data[{k}]: expected a leading batch (E,) = ({E},) "
                                 f"or (B, E) = ({B}, {E}), got {shape}")
            if not self.attach:
                leaf = leaf.detach()
            d = type(d)._from_leaf(leaf) if isinstance(d, LieGroup) else leaf
            if per_problem:
                d = _expand_problem(d, B)
            data.append(d)
            batched.append(per_problem)
        L, L_batched = self._noise(factor, made)
        form = _log_form(factor, [self.variables[k].group for k, _ in slots], data)
        inv = adj = None
        if form is not None:
            inv = form[1]._f.inverse(data[0].as_matrix())  # Z^-1 once
            if form[0] == "between" and form[1] in ONE_PASS:
                adj = form[1]._f.adjoint(inv)  # Ad(Z^-1) once
        return Block(factor, slots, data, batched, L, L_batched, dofs, h_index, pos.reshape(-1),
                     E, uniform, reduced, None if form is None else form[0], inv, adj)

    def _noise(self, factor: Factor, made: dict) -> tuple[torch.Tensor | None, bool]:
        """The square-root information of a factor, its shape checked for the factor and its
        values once per tensor (a noise tensor several factors share is read once)."""
        W, L = factor.information, factor.sqrt_information
        if W is None and L is None:
            return None, False
        given = W if W is not None else L
        name = "information" if W is not None else "sqrt_information"
        m = factor.dim
        if not isinstance(given, torch.Tensor) or given.dim() not in (2, 3, 4) or (
                m is not None and given.shape[-2:] != (m, m)):
            raise ValueError(f"{factor!r} {name}: expected (m, m), (E, m, m) or (B, E, m, m) "
                             f"with m = {m}, got {getattr(given, 'shape', type(given).__name__)}")
        if given.dtype != self.dtype or given.device != self.device:
            raise ValueError(f"{factor!r} {name}: expected {self.dtype} on {self.device}, got "
                             f"{given.dtype} on {given.device}")
        if given.dim() == 3 and given.shape[0] not in (factor.size, 1):
            raise ValueError(f"{factor!r} {name}: leading size must be E = {factor.size}, got "
                             f"{given.shape[0]}")
        if given.dim() == 4 and tuple(given.shape[:2]) not in ((self.B, factor.size), (self.B, 1)):
            raise ValueError(f"{factor!r} {name}: leading sizes must be (B, E) = "
                             f"({self.B}, {factor.size}), got {tuple(given.shape[:2])}")
        key = ("noise", id(given), W is not None)  # ``made`` holds ``given``: its id stays its own
        if key not in made:
            if not torch.isfinite(given).all():
                raise ValueError(f"{factor!r} {name} has non-finite entries")
            if W is not None:
                # symmetric (the factorisation reads one triangle: an asymmetric W would be
                # solved as another matrix) and positive definite, as a covariance is checked
                check_covariance(W, W.shape[-1], f"{factor!r} information")
            made[key] = given
        sqrt = given if self.attach else given.detach()
        if W is not None:
            sqrt = torch.linalg.cholesky_ex(sqrt)[0].mT  # W = C C^T = L^T L
        return sqrt, sqrt.dim() == 4

    def select(self, rows: torch.Tensor) -> Problem:
        """The same problems restricted to the batch rows ``rows`` (int64)."""
        new = object.__new__(Problem)
        new.__dict__.update(self.__dict__)
        new.B = rows.numel()
        new.blocks = []
        for b in self.blocks:
            data = [_take(d, rows) if p else d for d, p in zip(b.data, b.data_batched)]
            L = b.sqrt_info
            if L is not None and b.sqrt_info_batched:
                L = L.index_select(0, rows)
            inv, adj = b.measured_inv, b.measured_inv_adjoint
            if b.log_form is not None and b.data_batched[0]:
                inv, adj = (None if t is None else t.index_select(0, rows) for t in (inv, adj))
            new.blocks.append(Block(b.factor, b.slots, data, b.data_batched, L,
                                    b.sqrt_info_batched, b.dofs, b.h_index, b.g_index, b.size,
                                    b.uniform, b.reduced, b.log_form, inv, adj))
        return new

    # ------------------------------------------------------------------ values
    def initial(self, graph: FactorGraph) -> list[torch.Tensor]:
        """The variables' values as tensors (B, N, n, n) or (B, N, k), in layout order."""
        out = []
        for info in self.variables:
            v = graph.variables[info.name]
            leaf = (v.as_matrix() if isinstance(v, LieGroup) else v).detach()
            nd = 4 if info.group is not None else 3
            if leaf.dim() < nd:
                leaf = leaf.unsqueeze(0)
            out.append(leaf.expand((self.B,) + leaf.shape[1:]).clone())
        return out

    def retract(self, x: list[torch.Tensor], delta: torch.Tensor) -> list[torch.Tensor]:
        """x exp(delta) for group variables, x + delta for Euclidean ones; delta (B, D)."""
        out = []
        for info, xv in zip(self.variables, x):
            d = delta[:, info.offset:info.offset + info.size * info.dof].reshape(
                xv.shape[0], info.size, info.dof)
            if info.group is None:
                out.append(xv + d)
            else:
                f = info.group._f
                out.append(f.compose(xv, f.exp(d)))  # the group product (its operator on large batches)
        return out

    def wrap(self, k: int, leaf: torch.Tensor):
        info = self.variables[k]
        return leaf if info.group is None else info.group._from_leaf(leaf)


# groups whose log, J_r^-1 and J_l^-1 come from one pass (``log_terms``)
ONE_PASS = {SE3: se3_log_jacobians, SE2: se2_log_jacobians}


def _uniform(idx: torch.Tensor) -> int | None:
    """The one index every entry of ``idx`` (E,), E > 0, holds, or None (one host read)."""
    low, high = torch.stack(idx.aminmax()).tolist()
    return low if low == high else None


def _log_form(factor: Factor, groups: list, data: list) -> tuple[str, type[LieGroup]] | None:
    """("prior" | "between", the group) for the built-in Prior / Between residuals (with their
    analytic Jacobians) on group variables of the measurement's group; None otherwise."""
    kinds: dict[tuple[object, object, int], str] = {
        (_factors._prior_residual, _factors._prior_jacobians, 1): "prior",
        (_factors._between_residual, _factors._between_jacobians, 2): "between"}
    kind = kinds.get((factor.residual, factor.jacobians, len(groups)))
    if kind is None or len(data) != 1 or not isinstance(data[0], LieGroup):
        return None
    group = type(data[0])._group
    return (kind, group) if all(g is group for g in groups) else None


def _expand_problem(d, B: int):
    """Data with a problem axis of size 1 expanded to B (a view; itself where it has B)."""
    if isinstance(d, LieGroup):
        m = d.as_matrix()
        return d if m.shape[0] == B else type(d)._from_leaf(m.expand((B,) + m.shape[1:]))
    return d if d.shape[0] == B else d.expand((B,) + d.shape[1:])


def _take(d, rows: torch.Tensor):
    if isinstance(d, LieGroup):
        return type(d)._from_leaf(d.as_matrix().index_select(0, rows))
    return d.index_select(0, rows)
