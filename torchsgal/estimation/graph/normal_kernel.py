"""The normal equations of any block of factors, assembled by a torch operator.

``torch.ops.torchsgal.normal_assemble(J, r, slots, values, g_slots, g, summed)`` ->
(values + sum H, g + sum g): J (B, E, m, Dk) the whitened Jacobians of a block's E factors in
B problems and r (B, E, m) their whitened residuals; each factor's H = J^T J (Dk, Dk) is added
to its problem's ``values`` (B, size) at ``slots[e]`` (Dk * Dk,) and J^T r to ``g`` (B, D) at
``g_slots[e]`` (Dk,), or with ``summed`` (every factor on the same variables: ``Block.reduced``)
the sums over the factors at ``slots[0]`` and ``g_slots[0]`` (slots (1, Dk * Dk), g_slots
(1, Dk)).  The results are new tensors; the inputs are left as they are.

The engine's linearisation assembles every block of at most ``MAX_DK`` columns that is not a
built-in SE(3)/SE(2) prior or between (those have ``factor_kernels``) this way: user factors,
point observations, robust blocks; wider blocks (e.g. a between of SGal(3), 20 columns) take
the tensor code.  The tensor code forms H with a batched matrix product and adds it with
``index_add``: every (Dk, Dk) block is written and read back, and for a summed block torch's CPU
product of one (Dk, E m) by (E m, Dk) pair per problem costs a few microseconds each.  The C
kernel of ``estimation/_native_normal.h`` reads J and r once through their strides (an expanded
noise, a moved tangent axis: no copy), accumulates each block in a local square of fixed size
and adds it at its slots, the problems split over ``torch.get_num_threads()`` threads.  It takes
CPU float32/float64 blocks of 1 to ``MAX_DK`` columns where nothing observes the call
(``factor_kernels.usable``); elsewhere the tensor code runs (the reference the tests compare the
kernel with), and autograd, forward mode and ``torch.func`` see only the tensor code
(``assemble``).  Under vmap the mapped axis joins the problems' axis.  Slots out of range
raise: a ``ValueError`` from the kernel, torch's ``index_add`` error from the tensor code.
"""
from __future__ import annotations

import torch

from ...functional import checks, native
from ...functional.registration import operator
from .. import dense_solve
from .factor_kernels import check_index_maps, usable

__all__ = ["normal_assemble", "assemble", "MAX_DK"]

MAX_DK = 12  # NORMAL_MAX_DK of _native_normal.h


def _check(J, r, slots, values, g_slots, g, summed: bool) -> None:
    if not isinstance(J, torch.Tensor) or J.dim() != 4:
        raise ValueError(f"J must have shape (B, E, m, Dk), got "
                         f"{tuple(J.shape) if isinstance(J, torch.Tensor) else type(J).__name__}")
    B, E, m, Dk = J.shape
    if not isinstance(r, torch.Tensor) or tuple(r.shape) != (B, E, m):
        raise ValueError(f"r must have shape {(B, E, m)}, got "
                         f"{tuple(r.shape) if isinstance(r, torch.Tensor) else type(r).__name__}")
    checks.boolean(summed, "summed")
    checks.same_device_dtype(J=J, r=r, values=values, g=g)
    check_index_maps(slots, g_slots, values, g, B, 1 if summed else E, Dk, J.device)


def _tensor_code(J, r, slots, values, g_slots, g, summed: bool):
    """H = J^T J and J^T r by batched products, added with ``index_add`` (differentiable)."""
    if summed:  # one (Dk x E m) (E m x Dk) product per problem
        J, r = J.flatten(1, 2).unsqueeze(1), r.flatten(1, 2).unsqueeze(1)
    H = J.mT @ J
    gb = (J.mT @ r.unsqueeze(-1)).squeeze(-1)
    return (values.index_add(1, slots.reshape(-1), H.flatten(1)),
            g.index_add(1, g_slots.reshape(-1), gb.flatten(1)))


_SCHEMA = ("(Tensor J, Tensor r, Tensor slots, Tensor values, Tensor g_slots, Tensor g, "
           "bool summed) -> (Tensor, Tensor)")


@operator("torchsgal::normal_assemble", schema=_SCHEMA)
def normal_assemble(J: torch.Tensor, r: torch.Tensor, slots: torch.Tensor, values: torch.Tensor,
                    g_slots: torch.Tensor, g: torch.Tensor, summed: bool
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """(values + sum J^T J, g + sum J^T r) at the factors' slots (module docstring)."""
    _check(J, r, slots, values, g_slots, g, summed)
    return _tensor_code(J, r, slots, values, g_slots, g, summed)


def _kernel(J, r, slots, values, g_slots, g, summed: bool):
    _check(J, r, slots, values, g_slots, g, summed)
    lib = dense_solve._lib
    B, E, m, Dk = J.shape
    if (lib is None or not native.enabled() or J.dtype not in (torch.float32, torch.float64)
            or not 1 <= Dk <= MAX_DK):
        return _tensor_code(J, r, slots, values, g_slots, g, summed)
    J, r = J.resolve_neg().resolve_conj(), r.resolve_neg().resolve_conj()
    slots, g_slots = slots.contiguous(), g_slots.contiguous()
    values = values.resolve_neg().resolve_conj().clone(memory_format=torch.contiguous_format)
    g = g.resolve_neg().resolve_conj().clone(memory_format=torch.contiguous_format)
    dims = torch.tensor([E, m, Dk, values.shape[1], g.shape[1], int(summed), *J.stride(),
                         *r.stride()], dtype=torch.int64)
    cost = E * m * Dk * Dk // 400 + 1  # in units of one SGal(3) exp (~400 flops)
    lib.normal_assemble(J.data_ptr(), r.data_ptr(), values.data_ptr(), g.data_ptr(),
                        slots.data_ptr(), g_slots.data_ptr(), dims.data_ptr(), B, cost,
                        torch.get_num_threads(), J.dtype is torch.float64)
    return values, g


normal_assemble.register_kernel("cpu")(_kernel)


@normal_assemble.register_fake
def _fake(J, r, slots, values, g_slots, g, summed):
    _check(J, r, slots, values, g_slots, g, summed)
    return (torch.empty_like(values, memory_format=torch.contiguous_format),
            torch.empty_like(g, memory_format=torch.contiguous_format))


@normal_assemble.register_vmap
def _vmap(info, in_dims, J, r, slots, values, g_slots, g, summed):
    """The vmapped axis joins the problems' axis (an unmapped argument expanded); the index maps
    are shared."""
    if in_dims[2] is not None or in_dims[4] is not None:
        raise ValueError("slots and g_slots are shared by the problems: they cannot be vmapped")
    V = info.batch_size
    J, r, values, g = (t.unsqueeze(0).expand(V, *t.shape) if d is None else t.movedim(d, 0)
                       for t, d in zip((J, r, values, g), (in_dims[0], in_dims[1], in_dims[3],
                                                           in_dims[5])))
    out = normal_assemble(J.flatten(0, 1), r.flatten(0, 1), slots, values.flatten(0, 1), g_slots,
                          g.flatten(0, 1), summed)
    return tuple(t.unflatten(0, (V, -1)) for t in out), (0, 0)


def assemble(J: torch.Tensor, r: torch.Tensor, slots: torch.Tensor, values: torch.Tensor,
             g_slots: torch.Tensor, g: torch.Tensor, summed: bool
             ) -> tuple[torch.Tensor, torch.Tensor]:
    """The engine's call: the operator where its kernel runs (``usable``, 1 to ``MAX_DK``
    columns), else the tensor code, which autograd and ``torch.func`` differentiate."""
    if 1 <= J.shape[-1] <= MAX_DK and usable(J, r, values, g):
        return torch.ops.torchsgal.normal_assemble(J, r, slots, values, g_slots, g, summed)
    return _tensor_code(J, r, slots, values, g_slots, g, summed)
