"""Evaluation and linearisation of a ``FactorGraph`` for a batch of problems.

``Problem`` fixes the layout once: the variables' order and offsets in the stacked tangent
vector (variable-major, element-major: element n of variable v at ``offset_v + n dof_v``),
each factor block's data and noise with a problem axis, and the flat indices that scatter
every factor's Jacobian blocks ``J_a^T J_b`` into the (D x D) normal equations and ``J_a^T r``
into the gradient.  ``linearize`` evaluates all factors of a block together, whitens, applies
the robust loss (``robust.correct``) and assembles H = sum J~^T J~, g = sum J~^T r~ with one
``index_add_`` per block each, H in the layout of the linear system that solves it
(``layout.EntryLayout``: the dense matrix, or the stored triangle of the block and sparse
factorisations).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from ...groups import SE2, SE3, LieGroup
from . import factor_kernels
from . import factors as _factors
from .factors import Factor
from .graph import FactorGraph
from .layout import EntryLayout, raw_layout
from .log_terms import se2_log_jacobians, se3_inverse, se3_log_jacobians
from .robust import correct, corrected


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
        self.blocks = [self._block(f) for f in graph.factors]
        self.h_index = torch.cat([b.h_index for b in self.blocks])  # (nnz,) flat into (D * D)
        self.block_entries = [b.h_index.numel() for b in self.blocks]  # each block's share
        self.layout = raw_layout(self.h_index, self.block_entries, self.D)

    def _block(self, factor: Factor) -> Block:
        E, B = factor.size, self.B
        slots, dofs, starts = [], [], []
        for name, idx in factor.slots:
            k = self.index[name]
            info = self.variables[k]
            idx = idx.to(self.device)
            slots.append((k, idx))
            dofs.append(info.dof)
            # (E, dof) positions of each slot's tangent in the stacked vector
            starts.append(info.offset + idx[:, None] * info.dof
                          + torch.arange(info.dof, device=self.device))
        # a slot whose factors all read one element is passed as that element (batch (B, 1)),
        # broadcast against the data; when every slot is, the factors' J^T J sum by one product
        uniform = [int(idx[0]) if E and bool((idx == idx[0]).all()) else None
                   for _, idx in slots]
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
                shape_ok = (d.batch_shape[-1] in (E, 1)
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
        L, L_batched = self._noise(factor)
        form = _log_form(factor, [self.variables[k].group for k, _ in slots], data)
        inv = adj = None
        if form is not None:
            inv = form[1]._f.inverse(data[0].as_matrix())  # Z^-1 once
            if form[0] == "between" and form[1] in ONE_PASS:
                adj = form[1]._f.adjoint(inv)  # Ad(Z^-1) once
        return Block(factor, slots, data, batched, L, L_batched, dofs, h_index, pos.reshape(-1),
                     E, uniform, reduced, None if form is None else form[0], inv, adj)

    def _noise(self, factor: Factor) -> tuple[torch.Tensor | None, bool]:
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
        if not torch.isfinite(given).all():
            raise ValueError(f"{factor!r} {name} has non-finite entries")
        sqrt = given if self.attach else given.detach()
        if W is not None:
            C, info = torch.linalg.cholesky_ex(sqrt)
            if bool((info != 0).any()):
                raise ValueError(f"{factor!r} information must be symmetric positive definite")
            sqrt = C.mT  # W = C C^T = L^T L
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
                out.append(xv @ info.group._f.exp(d))  # the group product: the matrices' product
        return out

    def wrap(self, k: int, leaf: torch.Tensor):
        info = self.variables[k]
        return leaf if info.group is None else info.group._from_leaf(leaf)


# groups whose log, J_r^-1 and J_l^-1 come from one pass (``log_terms``)
ONE_PASS = {SE3: se3_log_jacobians, SE2: se2_log_jacobians}


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
    """Data with a problem axis of size 1 expanded to B (a view)."""
    if isinstance(d, LieGroup):
        m = d.as_matrix()
        return type(d)._from_leaf(m.expand((B,) + m.shape[1:]))
    return d.expand((B,) + d.shape[1:])


def _take(d, rows: torch.Tensor):
    if isinstance(d, LieGroup):
        return type(d)._from_leaf(d.as_matrix().index_select(0, rows))
    return d.index_select(0, rows)


@dataclass
class Assembly:
    """The normal equations being assembled: values (B, layout.size) and g (B, D)."""

    values: torch.Tensor
    g: torch.Tensor
    layout: EntryLayout


@dataclass
class Linearization:
    """values (B, size) of the normal equations' entries in an ``EntryLayout`` (``layout.dense``
    gives H (B, D, D)), g (B, D), cost (B,) = 1/2 sum rho(s), model_cost (B,)
    = 1/2 |r~|^2 (the linear model's error at zero)."""

    values: torch.Tensor
    g: torch.Tensor
    cost: torch.Tensor
    model_cost: torch.Tensor


def _right_basis(group: type[LieGroup], X: torch.Tensor) -> torch.Tensor:
    """X hat(e_j) for j < dof: (dof, *X.shape), as one matrix product (X rows against the
    basis matrices side by side)."""
    n, dof = X.shape[-1], group.dof
    hats = group._f.hat(torch.eye(dof, dtype=X.dtype, device=X.device))  # (dof, n, n)
    prod = X.reshape(-1, n) @ hats.permute(1, 0, 2).reshape(n, dof * n)  # (rows, dof * n)
    return prod.reshape(X.shape[:-1] + (dof, n)).movedim(-2, 0)


def _residual_and_jacobian(problem: Problem, block: Block, args: list, want_jacobian: bool):
    """r (B, E, m) and, if asked, J (B, E, m, Dk) with respect to the slots' perturbations."""
    f = block.factor
    elements = [problem.wrap(k, a) for (k, _), a in zip(block.slots, args)]
    if not want_jacobian:
        return f.residual(*elements, *block.data), None
    if f.jacobians is not None:
        r, Js = f.jacobians(*elements, *block.data)
        if isinstance(Js, torch.Tensor):  # the slots' Jacobians side by side already
            return r, Js.expand(r.shape + Js.shape[-1:])
        if len(Js) == 1:
            return r, Js[0]
        return r, torch.cat([J.expand(r.shape + J.shape[-1:]) for J in Js], dim=-1)
    # forward mode: tangent of slot k along basis direction j is X hat(e_j) (right perturbation)
    tangents, Dk, start = [], sum(block.dofs), 0
    for (k, _), a, dof in zip(block.slots, args, block.dofs):
        info = problem.variables[k]
        if len(args) == 1 and info.group is not None:  # one slot: the basis itself, no copy
            tangents.append(_right_basis(info.group, a))
            break
        t = a.new_zeros((Dk,) + a.shape)
        if info.group is None:
            t[start:start + dof] = torch.eye(dof, dtype=a.dtype, device=a.device).reshape(
                (dof,) + (1,) * (a.dim() - 1) + (dof,))
        else:
            t[start:start + dof] = _right_basis(info.group, a)
        tangents.append(t)
        start += dof

    def fn(*leaves):
        return f.residual(*[problem.wrap(k, a) for (k, _), a in zip(block.slots, leaves)],
                          *block.data)

    def column(*ts):
        return torch.func.jvp(fn, tuple(args), ts)

    out_dims: tuple = (None, 0)  # the residual once, its derivatives along the basis
    r_all, dr = torch.func.vmap(column, out_dims=out_dims)(*tangents)
    return r_all, dr.movedim(0, -1)


def _check_residual(block: Block, r, B: int) -> None:
    """The residual must be a floating tensor (..., dim) that broadcasts to (B, E, dim)."""
    f = block.factor
    if not isinstance(r, torch.Tensor) or not r.is_floating_point():
        raise TypeError(f"{f!r}: the residual must return a floating tensor, got "
                        f"{type(r).__name__ if not isinstance(r, torch.Tensor) else r.dtype}")
    if f.dim is not None and (r.dim() == 0 or r.shape[-1] != f.dim):
        raise ValueError(f"{f!r}: the residual has shape {tuple(r.shape)}, expected (..., {f.dim})")
    lead = tuple(r.shape[:-1])
    if len(lead) > 2 or any(n not in (1, m) for n, m in zip(lead[::-1], (block.size, B))):
        raise ValueError(f"{f!r}: the residual's shape {tuple(r.shape)} does not broadcast to "
                         f"(B, E, dim) = ({B}, {block.size}, {r.shape[-1]})")


def _args(block: Block, x: list[torch.Tensor]) -> list[torch.Tensor]:
    """The leaves each slot reads: (B, E, ...) gathered, or (B, 1, ...) for a uniform slot."""
    return [x[k].index_select(1, idx) if u is None else x[k].narrow(1, u, 1)
            for (k, idx), u in zip(block.slots, block.uniform)]


def _whiten(block: Block, r: torch.Tensor, J: torch.Tensor | None, B: int, built_in: bool = False
            ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
    """Checks r (unless ``built_in``: the fused priors and betweens, whose shapes are known),
    applies the square-root information and the robust loss: (r~ (B, E, m), J~ (B, E, m, Dk)
    or None, rho(s) (B, E))."""
    if not built_in:
        _check_residual(block, r, B)
    r = r.expand((B, block.size) + r.shape[-1:])
    if block.sqrt_info is not None:
        L = block.sqrt_info
        if L.dim() == 2:  # shared: one (m x m) product over all rows (no batched small products)
            r = r @ L.mT
            J = None if J is None else torch.einsum("ij,...jk->...ik", L, J)
        else:
            r = (L @ r.unsqueeze(-1)).squeeze(-1)
            J = None if J is None else L @ J
    return (corrected if built_in else correct)(block.factor.loss, r, J)


def _block_terms(problem: Problem, block: Block, x: list[torch.Tensor], want_jacobian: bool
                 ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
    """The block's corrected whitened residual r~ (B, E, m), Jacobian J~ (B, E, m, Dk) (None
    unless asked) and rho(s) (B, E)."""
    r, J = _residual_and_jacobian(problem, block, _args(block, x), want_jacobian)
    return _whiten(block, r, J, x[0].shape[0])


def _log_form_terms(problem: Problem, x: list[torch.Tensor], want_jacobian: bool,
                    normal: Assembly | None = None) -> dict[int, tuple]:
    """{block number: (r (B, E, dof), J (B, E, dof, Dk) or None)} for the blocks of built-in
    priors and betweens, r = log(E) with E = Z^-1 T (prior) or Z^-1 T_i^-1 T_j (between).
    The E of every such block of a group are stacked and go through one ``log`` and one
    ``J_r^-1``; the Jacobians are J_r^-1(r) (prior; between: J_j) and
    J_i = -J_r^-1(r) Ad(A^-1), A = T_i^-1 T_j, A^-1 = T_j^-1 T_i (the formulas of ``factors``),
    with each variable's inverses computed once and gathered; Z^-1 is the block's
    ``measured_inv`` (computed once per problem).  SE(3) and SE(2) blocks that nothing
    differentiates go through ``torchsgal::se3_factor_terms`` or ``se2_factor_terms`` instead
    (``factor_kernels``: one C pass per factor on the CPU), one call per block.  Otherwise, on
    SE(3) and SE(2), log, J_r^-1 and J_l^-1 come from one pass (``log_terms``) and
    J_i = -J_l^-1(r) Ad(Z^-1) (as J_r^-1(r) = J_l^-1(r) Ad(E) and E A^-1 = Z^-1), with Ad(Z^-1)
    computed once per problem.  With ``normal``, the kernels' blocks of factors without a robust
    loss are whitened and their blocks of H and g added in place into its values and g
    (``se3_factor_assemble``, ``se2_factor_assemble``); such a block gives (r~,)."""
    B = x[0].shape[0]
    stacks: dict[type[LieGroup], list] = {}
    inverses: dict[int, torch.Tensor] = {}  # variable -> its elements' inverses, once
    out: dict[int, tuple] = {}
    for n, block in enumerate(problem.blocks):
        if block.log_form is None:
            continue
        group = problem.variables[block.slots[0][0]].group
        Z_inv = block.measured_inv
        assert group is not None and Z_inv is not None  # set with log_form (``_log_form``)
        if group in (SE3, SE2) and factor_kernels.usable(Z_inv, *x):  # one call per block
            n_ = 4 if group is SE3 else 3
            shape = (B, block.size, n_, n_)
            Ts = [T.expand(shape) for T in _args(block, x)]
            Ti = None if block.log_form == "prior" else Ts[0]
            L = block.sqrt_info
            if normal and block.factor.loss is None and (L is None or factor_kernels.usable(L)):
                # whitened, its blocks of H and g added into ``normal`` (a noise that something
                # differentiates is applied below instead)
                if L is not None and L.dim() > 2:
                    L = L.expand(shape[:2] + L.shape[-2:])
                op = (torch.ops.torchsgal.se3_factor_assemble if group is SE3
                      else torch.ops.torchsgal.se2_factor_assemble)
                Dk = sum(block.dofs)
                slots = normal.layout.block_slots[n].reshape(-1, Dk * Dk).expand(block.size, -1)
                g_slots = block.g_index.reshape(-1, Dk).expand(block.size, -1)
                out[n] = (op(Z_inv.expand(shape), Ti, Ts[-1], L, slots, normal.values, g_slots,
                             normal.g),)
                continue
            op = (torch.ops.torchsgal.se3_factor_terms if group is SE3
                  else torch.ops.torchsgal.se2_factor_terms)
            r, J = op(Z_inv.expand(shape), Ti, Ts[-1], want_jacobian)
            out[n] = (r, J if want_jacobian else None)
            continue
        f = group._f
        if block.log_form == "prior":
            A, A_inv = _args(block, x)[0], None
        else:
            for v, _ in block.slots:  # T_i and T_j may be elements of two variables
                if v not in inverses:
                    inverses[v] = se3_inverse(x[v]) if group is SE3 else f.inverse(x[v])
            Ti, Tj = _args(block, x)
            Ti_inv = _args(block, [inverses.get(v, x[v]) for v in range(len(x))])[0]
            A = Ti_inv @ Tj  # the group product: the product of the matrices
            A_inv = None
            if want_jacobian and block.measured_inv_adjoint is None:  # A^-1 = T_j^-1 T_i
                A_inv = _args(block, [inverses.get(v, x[v]) for v in range(len(x))])[1] @ Ti
        err = Z_inv @ A
        stacks.setdefault(group, []).append((n, err.expand((B, block.size) + err.shape[-2:]), A_inv))
    for group, items in stacks.items():
        f = group._f
        sizes = [e.shape[1] for _, e, _ in items]
        errs = torch.cat([e for _, e, _ in items], dim=1) if len(items) > 1 else items[0][1]
        if group in ONE_PASS:
            r_all, jr_all, jl_all = ONE_PASS[group](errs, want_jacobian)
        else:
            r_all = f.log(errs)
            jr_all = f.jr_inv(r_all) if want_jacobian else None
            jl_all = None
        if jr_all is None:
            for (n, _, _), r in zip(items, r_all.split(sizes, dim=1)):
                out[n] = (r, None)
            continue
        jls = [None] * len(items) if jl_all is None else jl_all.split(sizes, dim=1)
        for (n, _, A_inv), r, jinv, jl in zip(items, r_all.split(sizes, dim=1),
                                              jr_all.split(sizes, dim=1), jls):
            block = problem.blocks[n]
            if block.log_form == "prior":
                out[n] = (r, jinv)
                continue
            if jl is not None and block.measured_inv_adjoint is not None and group is SE3:
                # [[a, u], [0, a]] [[R, T], [0, R]] = [[a R, a T + u R], [0, a R]]: the top rows'
                # product, the bottom rows from its left block
                top = torch.matmul(jl[..., :3, :], block.measured_inv_adjoint).neg_()
                Ji = torch.cat([top, torch.cat([torch.zeros_like(top[..., :3]), top[..., :3]],
                                               dim=-1)], dim=-2)
            elif jl is not None and block.measured_inv_adjoint is not None:
                Ji = torch.matmul(jl, block.measured_inv_adjoint).neg_()
            else:
                Ji = torch.matmul(jinv, f.adjoint(A_inv)).neg_()
            out[n] = (r, torch.cat([Ji, jinv], dim=-1))
    return out


def evaluate_cost(problem: Problem, x: list[torch.Tensor]) -> torch.Tensor:
    """The costs (B,) = 1/2 sum rho(|L r|^2) at x, without Jacobians."""
    B = x[0].shape[0]
    fused = _log_form_terms(problem, x, False)
    cost = x[0].new_zeros(B)
    for n, block in enumerate(problem.blocks):
        terms = (_whiten(block, fused[n][0], None, B, built_in=True) if n in fused
                 else _block_terms(problem, block, x, False))
        cost = cost + 0.5 * terms[2].sum(dim=-1)
    return cost


def linearize(problem: Problem, x: list[torch.Tensor], layout: EntryLayout | None = None
              ) -> Linearization:
    """The normal equations' entries (in ``layout``, by default the problem's raw layout),
    gradient, cost and model cost at x (``Linearization``)."""
    B, D = x[0].shape[0], problem.D
    layout = problem.layout if layout is None else layout
    cost, model = x[0].new_zeros(B), x[0].new_zeros(B)
    normal = Assembly(x[0].new_zeros(B, layout.size), x[0].new_zeros(B, D), layout)
    fused = _log_form_terms(problem, x, True, normal=normal)
    values, g = normal.values, normal.g  # with the blocks the kernels added
    for n, block in enumerate(problem.blocks):
        if n in fused and len(fused[n]) == 1:  # whitened, its blocks of H and g assembled
            half = 0.5 * (fused[n][0] ** 2).sum(dim=(-1, -2))
            cost, model = cost + half, model + half
            continue
        if n in fused:
            r, J = fused[n]
            r, J, rho = _whiten(block, r, J, B, built_in=True)
        else:
            r, J, rho = _block_terms(problem, block, x, True)
        assert J is not None  # asked for
        half = 0.5 * rho.sum(dim=-1)
        cost = cost + half
        J = J.expand((B, block.size) + J.shape[-2:])
        # 1/2 |r~|^2; without a loss rho(s) = s = |r~|^2 already (``robust.correct``)
        model = model + (half if block.factor.loss is None else 0.5 * (r * r).sum(dim=(-1, -2)))
        if block.reduced:  # sum over the factors: one (Dk x E m) (E m x Dk) product
            J = J.reshape(B, -1, J.shape[-1])
            r = r.reshape(B, -1)
        H, gb = J.mT @ J, (J * r.unsqueeze(-1)).sum(dim=-2)  # J^T J, J^T r
        values.index_add_(1, layout.block_slots[n], H.reshape(B, -1))
        g.index_add_(1, block.g_index, gb.reshape(B, -1))
    return Linearization(values, g, cost, model)
