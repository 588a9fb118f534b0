"""Evaluation and linearisation of a ``FactorGraph`` for a batch of problems.

``Problem`` (``problem``) fixes the layout once: the variables' offsets in the stacked tangent
vector, each factor block's data and noise with a problem axis, and the flat indices of every
factor's blocks in the normal equations.  ``linearize`` evaluates all factors of a block
together, whitens, applies the robust loss (``robust.correct``) and assembles
H = sum J~^T J~, g = sum J~^T r~ per block (``normal_kernel.assemble``; the built-in SE(3) and
SE(2) priors and betweens by ``factor_kernels``), H in the layout of the linear system that
solves it (``layout.EntryLayout``: the dense matrix, or the stored triangle of the block and
sparse factorisations).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from ...groups import SE2, SE3, LieGroup
from . import factor_kernels
from .layout import EntryLayout
from .log_terms import se3_inverse
from .normal_kernel import assemble
from .problem import ONE_PASS, Block, Problem
from .robust import correct, corrected


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


def _residual_and_jacobian(problem: Problem, block: Block, args: list, want_jacobian: bool):
    """r (B, E, m) and, if asked, J (B, E, m, Dk) with respect to the slots' perturbations."""
    f = block.factor
    elements = [problem.wrap(k, a) for (k, _), a in zip(block.slots, args)]
    if not want_jacobian:
        return _own_dtype(problem, block, f.residual(*elements, *block.data)), None
    if f.jacobians is not None:
        r, Js = _checked_jacobians(problem, block, f.jacobians(*elements, *block.data))
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
            tangents.append(info.group._right_products(a))
            break
        t = a.new_zeros((Dk,) + a.shape)
        if info.group is None:
            t[start:start + dof] = torch.eye(dof, dtype=a.dtype, device=a.device).reshape(
                (dof,) + (1,) * (a.dim() - 1) + (dof,))
        else:
            t[start:start + dof] = info.group._right_products(a)
        tangents.append(t)
        start += dof

    def fn(*leaves):
        return f.residual(*[problem.wrap(k, a) for (k, _), a in zip(block.slots, leaves)],
                          *block.data)

    def column(*ts):
        return torch.func.jvp(fn, tuple(args), ts)

    out_dims: tuple = (None, 0)  # the residual once, its derivatives along the basis
    r_all, dr = torch.func.vmap(column, out_dims=out_dims)(*tangents)
    return _own_dtype(problem, block, r_all), dr.movedim(0, -1)


def _own_dtype(problem: Problem, block: Block, r):
    """``r`` if it is a tensor of the graph's dtype and device (other types are named by
    ``_check_residual``)."""
    if isinstance(r, torch.Tensor) and r.is_floating_point() and (
            r.dtype != problem.dtype or r.device != problem.device):
        raise TypeError(f"{block.factor!r}: the residual is {r.dtype} on {r.device}, the graph's "
                        f"variables {problem.dtype} on {problem.device}")
    return r


def _checked_jacobians(problem: Problem, block: Block, out) -> tuple:
    """(r, Js) of a factor's ``jacobians``: Js one tensor (..., dim, sum of the slots' dofs)
    or one (..., dim, dof_k) per slot, of the residual's dtype and device."""
    f = block.factor
    if not isinstance(out, (tuple, list)) or len(out) != 2:
        raise TypeError(f"{f!r}: jacobians must return (r, [J_1, ...]) or (r, J), got "
                        f"{type(out).__name__}")
    r, Js = out
    r = _own_dtype(problem, block, r)
    if not isinstance(r, torch.Tensor) or r.dim() == 0:
        return r, Js  # _check_residual names it
    parts = [Js] if isinstance(Js, torch.Tensor) else Js
    dofs = [sum(block.dofs)] if isinstance(Js, torch.Tensor) else list(block.dofs)
    if not isinstance(parts, (tuple, list)) or len(parts) != len(dofs):
        raise TypeError(f"{f!r}: jacobians must return one Jacobian per variable "
                        f"({len(block.dofs)}) or one tensor of them side by side, got "
                        f"{len(parts) if isinstance(parts, (tuple, list)) else type(parts).__name__}")
    for k, (J, dof) in enumerate(zip(parts, dofs)):
        if not isinstance(J, torch.Tensor) or J.dtype != r.dtype or J.device != r.device:
            raise TypeError(f"{f!r}: Jacobian {k} must be a tensor of the residual's dtype "
                            f"{r.dtype} on {r.device}, got "
                            f"{f'{J.dtype} on {J.device}' if isinstance(J, torch.Tensor) else type(J).__name__}")
        if J.dim() < 2 or J.shape[-2:] != (r.shape[-1], dof):
            raise ValueError(f"{f!r}: Jacobian {k} has shape {tuple(J.shape)}, expected "
                             f"(..., {r.shape[-1]}, {dof}) (the residual's size, the tangent size)")
    return r, Js


def _check_residual(block: Block, r, B: int) -> None:
    """The residual must be a floating tensor (..., dim) that broadcasts to (B, E, dim); without
    ``dim`` it must have all three axes, since a shorter one does not say which is its size."""
    f = block.factor
    if not isinstance(r, torch.Tensor) or not r.is_floating_point():
        raise TypeError(f"{f!r}: the residual must return a floating tensor, got "
                        f"{type(r).__name__ if not isinstance(r, torch.Tensor) else r.dtype}")
    if f.dim is not None and (r.dim() == 0 or r.shape[-1] != f.dim):
        raise ValueError(f"{f!r}: the residual has shape {tuple(r.shape)}, expected (..., {f.dim})")
    if f.dim is None and r.dim() != 3:
        raise ValueError(f"{f!r}: the residual has shape {tuple(r.shape)}; a factor without dim= "
                         f"must return (B, E, dim) (the engine passes (B, E) batches): give the "
                         f"factor its dim to let the residual broadcast")
    lead = tuple(r.shape[:-1])
    if len(lead) > 2 or any(n not in (1, m) for n, m in zip(lead[::-1], (block.size, B))):
        raise ValueError(f"{f!r}: the residual's shape {tuple(r.shape)} does not broadcast to "
                         f"(B, E, dim) = ({B}, {block.size}, {r.shape[-1]})")
    L, m = block.sqrt_info, r.shape[-1]
    if L is not None and tuple(L.shape[-2:]) != (m, m):  # a factor without dim: known only now
        name, noise = ("information", f.information) if f.information is not None else \
            ("sqrt_information", f.sqrt_information)
        given = tuple(noise.shape) if noise is not None else tuple(L.shape)
        raise ValueError(f"{f!r}: {name} must be ({m}, {m}), (E, {m}, {m}) or (B, E, {m}, {m}) for "
                         f"a residual of size {m}, got {given}")


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
    loss are whitened and their blocks of H and g added to its values and g
    (``se3_factor_assemble``, ``se2_factor_assemble``, which return the sums; ``normal`` then
    holds them); such a block gives (r~,)."""
    B = x[0].shape[0]
    stacks: dict[type[LieGroup], list] = {}
    inverses: dict[int, torch.Tensor] = {}  # variable -> its elements' inverses, once
    out: dict[int, tuple] = {}
    kernels: bool | None = None  # whether the kernels may read x (asked once)
    for n, block in enumerate(problem.blocks):
        if block.log_form is None:
            continue
        group = problem.variables[block.slots[0][0]].group
        Z_inv = block.measured_inv
        assert group is not None and Z_inv is not None  # set with log_form (``_log_form``)
        if kernels is None and group in (SE3, SE2):
            kernels = factor_kernels.usable(*x)
        if group in (SE3, SE2) and kernels and factor_kernels.usable(Z_inv):  # one call per block
            n_ = 4 if group is SE3 else 3
            shape = (B, block.size, n_, n_)
            Ts = [_shaped(T, shape) for T in _args(block, x)]
            Ti = None if block.log_form == "prior" else Ts[0]
            L = block.sqrt_info
            if normal and block.factor.loss is None and (L is None or factor_kernels.usable(L)):
                # whitened, its blocks of H and g added into ``normal`` (a noise that something
                # differentiates is applied below instead)
                if L is not None and L.dim() > 2:
                    L = L.expand(shape[:2] + L.shape[-2:])
                op = (torch.ops.torchsgal.se3_factor_assemble if group is SE3
                      else torch.ops.torchsgal.se2_factor_assemble)
                slots, g_slots = normal.layout.block_index(n, block.g_index, block.size,
                                                           sum(block.dofs))
                r, normal.values, normal.g = op(_shaped(Z_inv, shape), Ti, Ts[-1], L, slots,
                                                normal.values, g_slots, normal.g)
                out[n] = (r,)
                continue
            op = (torch.ops.torchsgal.se3_factor_terms if group is SE3
                  else torch.ops.torchsgal.se2_factor_terms)
            r, J = op(_shaped(Z_inv, shape), Ti, Ts[-1], want_jacobian)
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
    cost: torch.Tensor | None = None
    for n, block in enumerate(problem.blocks):
        terms = (_whiten(block, fused[n][0], None, B, built_in=True) if n in fused
                 else _block_terms(problem, block, x, False))
        cost = _plus(cost, 0.5 * terms[2].sum(dim=-1))
    assert cost is not None  # a graph has factors
    return cost


def linearize(problem: Problem, x: list[torch.Tensor], layout: EntryLayout | None = None
              ) -> Linearization:
    """The normal equations' entries (in ``layout``, by default the problem's raw layout),
    gradient, cost and model cost at x (``Linearization``)."""
    B, D = x[0].shape[0], problem.D
    layout = problem.layout if layout is None else layout
    # the sums over the blocks, from the first block's term (0 + t = t: no zeros to add to)
    cost: torch.Tensor | None = None
    model: torch.Tensor | None = None
    # the sums start as broadcast zeros (views: no buffer filled); every block's assembly
    # returns new tensors
    zero = x[0].new_zeros(())
    normal = Assembly(zero.expand(B, layout.size), zero.expand(B, D), layout)
    fused = _log_form_terms(problem, x, True, normal=normal)
    values, g = normal.values, normal.g  # with the blocks the kernels added
    for n, block in enumerate(problem.blocks):
        if n in fused and len(fused[n]) == 1:  # whitened, its blocks of H and g assembled
            half = 0.5 * (fused[n][0] ** 2).sum(dim=(-1, -2))
            cost, model = _plus(cost, half), _plus(model, half)
            continue
        if n in fused:
            r, J = fused[n]
            r, J, rho = _whiten(block, r, J, B, built_in=True)
        else:
            r, J, rho = _block_terms(problem, block, x, True)
        assert J is not None  # asked for
        half = 0.5 * rho.sum(dim=-1)
        cost = _plus(cost, half)
        J = J.expand((B, block.size) + J.shape[-2:])
        # 1/2 |r~|^2; without a loss rho(s) = s = |r~|^2 already (``robust.correct``)
        model = _plus(model, half if block.factor.loss is None else 0.5 * (r * r).sum(dim=(-1, -2)))
        slots, g_slots = layout.block_index(n, block.g_index, 1 if block.reduced else block.size,
                                            J.shape[-1])
        values, g = assemble(J, r, slots, values, g_slots, g, block.reduced)
    assert cost is not None and model is not None  # a graph has factors
    # cost and model are separate tensors (the solvers write a trial's into its own in place)
    return Linearization(values, g, cost, model.clone() if model is cost else model)


def _shaped(t: torch.Tensor, shape: tuple) -> torch.Tensor:
    """``t`` expanded to ``shape`` (itself where it has that shape already)."""
    return t if t.shape == shape else t.expand(shape)


def _plus(total: torch.Tensor | None, term: torch.Tensor) -> torch.Tensor:
    """total + term; term where there is no total yet."""
    return term if total is None else total + term
