"""The residuals and Jacobians of the built-in SE(3) and SE(2) priors and betweens as torch
operators.

``torch.ops.torchsgal.se3_factor_terms(Zinv, Ti, Tj, jacobians)`` -> (r (..., 6), J), and
``se2_factor_terms`` the same with (..., 3, 3) matrices and r (..., 3): for priors (``Ti``
None) E = Z^-1 T_j and J = J_r^-1(r) (..., dof, dof); for betweens E = Z^-1 T_i^-1 T_j and
J = [J_i | J_j] (..., dof, 2 dof) with J_j = J_r^-1(r) and J_i = -J_l^-1(r) Ad(Z^-1) (the
formulas of ``factors``; ``linearize._log_form_terms`` derives them); r = log(E); J is
(..., dof, 0) without ``jacobians``.  All arguments of one batch shape, dtype and device.

``se3_factor_normal(Zinv, Ti, Tj, L)`` and ``se2_factor_normal`` go one step further, for
factors without a robust loss: the whitened residual r~ = L r and the factor's blocks of the
normal equations, H = J~^T J~ and g = J~^T r~ with J~ = L J (L shared (dof, dof), per factor
(..., dof, dof), or None), so that whitening and the products of small matrices are part of the
same C pass.  ``se3_factor_assemble`` and ``se2_factor_assemble``, which the engine's
linearisation calls, add those blocks to each problem's normal equations, in the layout of the
linear system (``layout.EntryLayout``: each factor's entries of H at its ``slots``, of g at its
``g_slots``), so that no (B, E, Dk, Dk) intermediate is written and read back; they return the
sums as new tensors (torch's dispatcher gives an operator that writes its arguments in place
a further Python step per call, about as costly as the rest of the call).  Under vmap the mapped axis
of any of these operators joins the factors' batch.

The engine's linearisation of a pose graph otherwise runs some thirty tensor operations (and,
on SE(3), three operator calls) per block of factors: the inverses, two products, the log,
both inverse Jacobians, Ad(Z^-1) and the products that assemble J, a fixed cost per step that
dominates small problems.  On the CPU the C kernel of ``estimation/_native_factors.h``
evaluates a factor in one pass (SE(3) on the closed forms of ``functional/_native_sgal3.h``, the
kernels of ``torchsgal::se3_log`` and ``se3_jl_inv``; SE(2) on the formulas and series of
``log_terms.se2_log_jacobians``), the batch split over ``torch.get_num_threads()`` threads;
elsewhere, or with the kernels off, the tensor code below (the reference the tests compare the
kernel with).  No autograd formula is registered: the engine calls the operators only where
nothing records a derivative (``usable``), and its differentiable solves take the tensor path
of ``_log_form_terms``.
"""
from __future__ import annotations

import torch

from ...functional import checks, native, se2, se3
from ...functional._blocking import unobserved
from ...functional.registration import operator
from .. import dense_solve
from .log_terms import _SERIES, SERIES_THRESHOLD, se2_log_jacobians, se3_inverse, se3_log_jacobians

__all__ = ["se3_factor_terms", "se2_factor_terms", "se3_factor_normal", "se2_factor_normal",
           "se3_factor_assemble", "se2_factor_assemble", "usable"]


def usable(*tensors: torch.Tensor) -> bool:
    """Whether the engine may call the operators' C kernels for these: plain CPU float32/float64
    tensors that nothing observes (no autograd recording in reverse or forward mode, no
    torch.func transform, not compiling: ``functional._blocking.unobserved``), kernels built and
    on in the calling thread."""
    if dense_solve._lib is None or not native.enabled():
        return False
    if any(t.dtype not in (torch.float32, torch.float64) for t in tensors):
        return False
    return unobserved(tensors)


def _check(Zinv, Ti, Tj, n: int = 4) -> None:
    for name, t in (("Zinv", Zinv), ("Ti", Ti), ("Tj", Tj)):
        if t is not None:
            checks.matrix(t, n, name)
    given = {k: v for k, v in (("Zinv", Zinv), ("Ti", Ti), ("Tj", Tj)) if v is not None}
    checks.same_device_dtype(**given)
    shapes = [v.shape for v in given.values()]
    if any(shape != shapes[0] for shape in shapes[1:]):
        raise ValueError(f"Zinv, Ti and Tj must have one shape (..., {n}, {n}), got "
                         f"{ {k: tuple(v.shape) for k, v in given.items()} }")


def _log_form_code(inverse, log_jacobians, adjoint, dof: int):
    """The operator's tensor code for one group: r = log(Z^-1 T_i^-1 T_j) and [J_i | J_j]
    (J_j = J_r^-1(r), J_i = -J_l^-1(r) Ad(Z^-1))."""

    def code(Zinv, Ti, Tj, jacobians: bool):
        E = Zinv @ (Tj if Ti is None else inverse(Ti) @ Tj)
        r, jr, jl = log_jacobians(E, jacobians)
        if not jacobians:
            return r, r.new_empty(r.shape[:-1] + (dof, 0))
        assert jr is not None and jl is not None
        if Ti is None:
            return r, jr
        return r, torch.cat([-(jl @ adjoint(Zinv)), jr], dim=-1)

    return code


_tensor_code = _log_form_code(se3_inverse, se3_log_jacobians, se3.adjoint, 6)


@operator("torchsgal::se3_factor_terms",
          schema="(Tensor Zinv, Tensor? Ti, Tensor Tj, bool jacobians) -> (Tensor, Tensor)")
def se3_factor_terms(Zinv: torch.Tensor, Ti: torch.Tensor | None, Tj: torch.Tensor,
                     jacobians: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """(r, J) of SE(3) priors (``Ti`` None) or betweens (module docstring)."""
    _check(Zinv, Ti, Tj)
    return _tensor_code(Zinv, Ti, Tj, jacobians)


def _run(name: str, n: int, tensor_code, Zinv, Ti, Tj, jacobians: bool, *extra: torch.Tensor):
    """The operator ``name``'s CPU kernel (matrices (..., n, n), tangent dimension
    ``n * (n - 1) // 2``) where it runs, else ``tensor_code``; ``extra`` pointers follow J."""
    _check(Zinv, Ti, Tj, n)
    lib = dense_solve._lib
    if lib is None or not native.enabled() or Tj.dtype not in (torch.float32, torch.float64):
        return tensor_code(Zinv, Ti, Tj, jacobians)
    dof, batch = n * (n - 1) // 2, Tj.shape[:-2]
    Zinv, Tj = Zinv.resolve_neg().contiguous(), Tj.resolve_neg().contiguous()
    Ti = None if Ti is None else Ti.resolve_neg().contiguous()
    r = Tj.new_empty(batch + (dof,))
    J = Tj.new_empty(batch + (dof, (dof if Ti is None else 2 * dof) if jacobians else 0))
    getattr(lib, name)(Zinv.data_ptr(), 0 if Ti is None else Ti.data_ptr(), Tj.data_ptr(),
                       r.data_ptr(), J.data_ptr() if jacobians else 0, *(e.data_ptr() for e in extra),
                       r.numel() // dof, torch.get_num_threads(), Tj.dtype is torch.float64)
    return r, J


def _fake(n: int):
    def fake(Zinv, Ti, Tj, jacobians):
        _check(Zinv, Ti, Tj, n)
        dof = n * (n - 1) // 2
        width = (dof if Ti is None else 2 * dof) if jacobians else 0
        return Tj.new_empty(Tj.shape[:-2] + (dof,)), Tj.new_empty(Tj.shape[:-2] + (dof, width))
    return fake


se3_factor_terms.register_kernel("cpu")(
    lambda Zinv, Ti, Tj, jacobians: _run("se3_factor_terms", 4, _tensor_code, Zinv, Ti, Tj, jacobians))
se3_factor_terms.register_fake(_fake(4))


# ---------------------------------------------------------------------------- SE(2)
# the squared series threshold, then the series of d in theta^2 (``log_terms``), for the kernel
_SE2_SERIES = torch.tensor([SERIES_THRESHOLD ** 2] + [d for d, _ in _SERIES], dtype=torch.float64)


_se2_tensor_code = _log_form_code(se2.inverse, se2_log_jacobians, se2.adjoint, 3)


@operator("torchsgal::se2_factor_terms",
          schema="(Tensor Zinv, Tensor? Ti, Tensor Tj, bool jacobians) -> (Tensor, Tensor)")
def se2_factor_terms(Zinv: torch.Tensor, Ti: torch.Tensor | None, Tj: torch.Tensor,
                     jacobians: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """(r, J) of SE(2) priors (``Ti`` None) or betweens (module docstring)."""
    _check(Zinv, Ti, Tj, 3)
    return _se2_tensor_code(Zinv, Ti, Tj, jacobians)


se2_factor_terms.register_kernel("cpu")(
    lambda Zinv, Ti, Tj, jacobians: _run("se2_factor_terms", 3, _se2_tensor_code, Zinv, Ti, Tj,
                                         jacobians, _SE2_SERIES))
se2_factor_terms.register_fake(_fake(3))


# ---------------------------------------------------------------------------- normal blocks
def _normal_code(terms):
    """The tensor code of ``<group>_factor_normal``: the terms, whitened, and their products."""

    def code(Zinv, Ti, Tj, L):
        r, J = terms(Zinv, Ti, Tj, True)
        if L is not None:
            r = (L @ r.unsqueeze(-1)).squeeze(-1)
            J = L @ J
        return r, J.mT @ J, (J.mT @ r.unsqueeze(-1)).squeeze(-1)

    return code


def _check_noise(L, Tj, dof: int) -> None:
    if L is None:
        return
    checks.same_device_dtype(L=L, Tj=Tj)
    if L.shape not in ((dof, dof), Tj.shape[:-2] + (dof, dof)):
        raise ValueError(f"L must have shape ({dof}, {dof}) or {tuple(Tj.shape[:-2]) + (dof, dof)}, "
                         f"got {tuple(L.shape)}")


def _run_normal(name: str, n: int, code, Zinv, Ti, Tj, L, *extra: torch.Tensor):
    """The operator ``name``'s CPU kernel where it runs, else ``code``."""
    _check(Zinv, Ti, Tj, n)
    dof = n * (n - 1) // 2
    _check_noise(L, Tj, dof)
    lib = dense_solve._lib
    if lib is None or not native.enabled() or Tj.dtype not in (torch.float32, torch.float64):
        return code(Zinv, Ti, Tj, L)
    batch, Dk = Tj.shape[:-2], dof if Ti is None else 2 * dof
    Zinv, Tj = Zinv.resolve_neg().contiguous(), Tj.resolve_neg().contiguous()
    Ti = None if Ti is None else Ti.resolve_neg().contiguous()
    L = None if L is None else L.resolve_neg().contiguous()
    r, H, g = Tj.new_empty(batch + (dof,)), Tj.new_empty(batch + (Dk, Dk)), Tj.new_empty(batch + (Dk,))
    getattr(lib, name)(Zinv.data_ptr(), 0 if Ti is None else Ti.data_ptr(), Tj.data_ptr(),
                       0 if L is None else L.data_ptr(), r.data_ptr(), H.data_ptr(), g.data_ptr(),
                       *(e.data_ptr() for e in extra), r.numel() // dof,
                       L is not None and L.dim() == 2, torch.get_num_threads(),
                       Tj.dtype is torch.float64)
    return r, H, g


def _normal_fake(n: int):
    def fake(Zinv, Ti, Tj, L):
        _check(Zinv, Ti, Tj, n)
        dof = n * (n - 1) // 2
        _check_noise(L, Tj, dof)
        Dk = dof if Ti is None else 2 * dof
        batch = Tj.shape[:-2]
        return Tj.new_empty(batch + (dof,)), Tj.new_empty(batch + (Dk, Dk)), Tj.new_empty(batch + (Dk,))
    return fake


_se3_normal_code = _normal_code(_tensor_code)
_se2_normal_code = _normal_code(_se2_tensor_code)


@operator("torchsgal::se3_factor_normal",
          schema="(Tensor Zinv, Tensor? Ti, Tensor Tj, Tensor? L) -> (Tensor, Tensor, Tensor)")
def se3_factor_normal(Zinv: torch.Tensor, Ti: torch.Tensor | None, Tj: torch.Tensor,
                      L: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(r~ = L r (..., 6), H = J~^T J~ (..., Dk, Dk), g = J~^T r~ (..., Dk)) of SE(3) priors
    (``Ti`` None, Dk = 6) or betweens (Dk = 12), J~ = L J, with (r, J) those of
    ``se3_factor_terms`` and L (6, 6) for all factors, (..., 6, 6) per factor, or None (the
    identity): the factors' whitened residuals and their blocks of the normal equations in one
    pass (the per-factor form of ``se3_factor_assemble``, which the engine calls)."""
    _check(Zinv, Ti, Tj)
    _check_noise(L, Tj, 6)
    return _se3_normal_code(Zinv, Ti, Tj, L)


se3_factor_normal.register_kernel("cpu")(
    lambda Zinv, Ti, Tj, L: _run_normal("se3_factor_normal", 4, _se3_normal_code, Zinv, Ti, Tj, L))
se3_factor_normal.register_fake(_normal_fake(4))


@operator("torchsgal::se2_factor_normal",
          schema="(Tensor Zinv, Tensor? Ti, Tensor Tj, Tensor? L) -> (Tensor, Tensor, Tensor)")
def se2_factor_normal(Zinv: torch.Tensor, Ti: torch.Tensor | None, Tj: torch.Tensor,
                      L: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """As ``se3_factor_normal`` for SE(2) (matrices (..., 3, 3), r (..., 3), Dk 3 or 6)."""
    _check(Zinv, Ti, Tj, 3)
    _check_noise(L, Tj, 3)
    return _se2_normal_code(Zinv, Ti, Tj, L)


se2_factor_normal.register_kernel("cpu")(
    lambda Zinv, Ti, Tj, L: _run_normal("se2_factor_normal", 3, _se2_normal_code, Zinv, Ti, Tj, L,
                                        _SE2_SERIES))
se2_factor_normal.register_fake(_normal_fake(3))


def _matrices_in_front(V: int, tensors, in_dims):
    """The operators' matrices with the vmapped axis in front (unmapped ones expanded) and
    their batch shapes broadcast; and that batch."""
    moved = [None if t is None else (t.unsqueeze(0).expand(V, *t.shape) if d is None
                                      else t.movedim(d, 0)) for t, d in zip(tensors, in_dims)]
    batch = checks.broadcast_shapes(*(t.shape[:-2] for t in moved if t is not None))
    return [None if t is None else t.expand(batch + t.shape[-2:]) for t in moved], batch


def _noise_in_front(V: int, L, in_dim, batch, dof: int):
    """The noise of a vmapped call: a shared (dof, dof) L stays shared unless vmapped; else
    (V, ..., dof, dof), its batch aligned to the right, expanded to the matrices' ``batch``."""
    if L is None or (in_dim is None and L.dim() == 2):
        return L
    L = L.unsqueeze(0).expand(V, *L.shape) if in_dim is None else L.movedim(in_dim, 0)
    if L.dim() < len(batch) + 2:
        L = L.reshape((V,) + (1,) * (len(batch) + 2 - L.dim()) + L.shape[1:])
    return L.expand(batch + (dof, dof))


def _normal_vmap(op, dof: int):
    """The vmapped axis joins the factors' batch; a shared L stays shared unless vmapped."""

    def rule(info, in_dims, Zinv, Ti, Tj, L):
        V = info.batch_size
        (Zinv, Ti, Tj), batch = _matrices_in_front(V, (Zinv, Ti, Tj), in_dims[:3])
        return op(Zinv, Ti, Tj, _noise_in_front(V, L, in_dims[3], batch, dof)), (0, 0, 0)

    return rule


se3_factor_normal.register_vmap(_normal_vmap(se3_factor_normal, 6))
se2_factor_normal.register_vmap(_normal_vmap(se2_factor_normal, 3))


def _terms_vmap(op):
    """The vmapped axis joins the factors' batch."""

    def rule(info, in_dims, Zinv, Ti, Tj, jacobians):
        (Zinv, Ti, Tj), _ = _matrices_in_front(info.batch_size, (Zinv, Ti, Tj), in_dims[:3])
        return op(Zinv, Ti, Tj, jacobians), (0, 0)

    return rule


se3_factor_terms.register_vmap(_terms_vmap(se3_factor_terms))
se2_factor_terms.register_vmap(_terms_vmap(se2_factor_terms))


# ---------------------------------------------------------------------------- assembled
def _assemble_code(normal):
    """The tensor code of ``<group>_factor_assemble``: the normal blocks, added at the slots."""

    def code(Zinv, Ti, Tj, L, slots, values, g_slots, g):
        r, H, gb = normal(Zinv, Ti, Tj, L)
        return (r, values.index_add(1, slots.reshape(-1), H.flatten(1)),
                g.index_add(1, g_slots.reshape(-1), gb.flatten(1)))

    return code


def _check_assemble(Zinv, Ti, Tj, L, slots, values, g_slots, g, n: int) -> None:
    _check(Zinv, Ti, Tj, n)
    dof = n * (n - 1) // 2
    _check_noise(L, Tj, dof)
    Dk = dof if Ti is None else 2 * dof
    if Tj.dim() != 4:
        raise ValueError(f"Tj must have shape (B, E, {n}, {n}), got {tuple(Tj.shape)}")
    B, E = Tj.shape[:2]
    checks.same_device_dtype(values=values, g=g, Tj=Tj)
    check_index_maps(slots, g_slots, values, g, B, E, Dk, Tj.device)


def check_index_maps(slots, g_slots, values, g, B: int, rows: int, Dk: int, device) -> None:
    """The assemble operators' index maps, slots (rows, Dk * Dk) and g_slots (rows, Dk) int64
    on ``device``, and the sums they add into, values (B, size) and g (B, D)."""
    for name, t, shape in (("slots", slots, (rows, Dk * Dk)), ("g_slots", g_slots, (rows, Dk))):
        if t.dtype != torch.int64 or t.device != device or tuple(t.shape) != shape:
            raise ValueError(f"{name} must be int64 of shape {shape} on {device}, got "
                             f"{t.dtype} of shape {tuple(t.shape)} on {t.device}")
    for name, t in (("values", values), ("g", g)):
        if t.dim() != 2 or t.shape[0] != B:
            raise ValueError(f"{name} must have shape ({B}, n), got {tuple(t.shape)}")


def _run_assemble(name: str, n: int, code, Zinv, Ti, Tj, L, slots, values, g_slots, g,
                  *extra: torch.Tensor):
    """The operator ``name``'s CPU kernel where it runs, else ``code``."""
    _check_assemble(Zinv, Ti, Tj, L, slots, values, g_slots, g, n)
    lib = dense_solve._lib
    if lib is None or not native.enabled() or Tj.dtype not in (torch.float32, torch.float64):
        return code(Zinv, Ti, Tj, L, slots, values, g_slots, g)
    dof, (B, E) = n * (n - 1) // 2, Tj.shape[:2]
    Zinv, Tj = Zinv.resolve_neg().contiguous(), Tj.resolve_neg().contiguous()
    Ti = None if Ti is None else Ti.resolve_neg().contiguous()
    L = None if L is None else L.resolve_neg().contiguous()
    slots, g_slots = slots.contiguous(), g_slots.contiguous()
    values = values.resolve_neg().resolve_conj().clone(memory_format=torch.contiguous_format)
    g = g.resolve_neg().resolve_conj().clone(memory_format=torch.contiguous_format)
    r = Tj.new_empty(B, E, dof)
    getattr(lib, name)(Zinv.data_ptr(), 0 if Ti is None else Ti.data_ptr(), Tj.data_ptr(),
                       0 if L is None else L.data_ptr(), r.data_ptr(), values.data_ptr(),
                       g.data_ptr(), slots.data_ptr(), g_slots.data_ptr(),
                       *(e.data_ptr() for e in extra), B, E, values.shape[1], g.shape[1],
                       L is not None and L.dim() == 2, torch.get_num_threads(),
                       Tj.dtype is torch.float64)
    return r, values, g


def _assemble_fake(n: int):
    def fake(Zinv, Ti, Tj, L, slots, values, g_slots, g):
        _check_assemble(Zinv, Ti, Tj, L, slots, values, g_slots, g, n)
        return (Tj.new_empty(Tj.shape[:2] + (n * (n - 1) // 2,)),
                torch.empty_like(values, memory_format=torch.contiguous_format),
                torch.empty_like(g, memory_format=torch.contiguous_format))
    return fake


_se3_assemble_code = _assemble_code(_se3_normal_code)
_se2_assemble_code = _assemble_code(_se2_normal_code)
_ASSEMBLE_SCHEMA = ("(Tensor Zinv, Tensor? Ti, Tensor Tj, Tensor? L, Tensor slots, Tensor values, "
                    "Tensor g_slots, Tensor g) -> (Tensor, Tensor, Tensor)")


@operator("torchsgal::se3_factor_assemble",
          schema=_ASSEMBLE_SCHEMA)
def se3_factor_assemble(Zinv: torch.Tensor, Ti: torch.Tensor | None, Tj: torch.Tensor,
                        L: torch.Tensor | None, slots: torch.Tensor, values: torch.Tensor,
                        g_slots: torch.Tensor, g: torch.Tensor
                        ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(r~ (B, E, 6) of ``se3_factor_normal``, values + H, g + g) for the factors (B, E, 4, 4)
    of B problems: each factor e's H (Dk, Dk) added to its problem's ``values`` (B, size) at
    ``slots[e]`` (Dk * Dk,) and its g (Dk,) to ``g`` (B, D) at ``g_slots[e]``, in new tensors
    (the inputs are left as they are): the blocks go straight into a linear system's layout
    (``layout.EntryLayout``), with no (B, E, Dk, Dk) intermediate.  A functional operator: a
    mutating one costs torch's dispatcher about twice the time per call."""
    _check_assemble(Zinv, Ti, Tj, L, slots, values, g_slots, g, 4)
    return _se3_assemble_code(Zinv, Ti, Tj, L, slots, values, g_slots, g)


se3_factor_assemble.register_kernel("cpu")(
    lambda *a: _run_assemble("se3_factor_assemble", 4, _se3_assemble_code, *a))
se3_factor_assemble.register_fake(_assemble_fake(4))


@operator("torchsgal::se2_factor_assemble",
          schema=_ASSEMBLE_SCHEMA)
def se2_factor_assemble(Zinv: torch.Tensor, Ti: torch.Tensor | None, Tj: torch.Tensor,
                        L: torch.Tensor | None, slots: torch.Tensor, values: torch.Tensor,
                        g_slots: torch.Tensor, g: torch.Tensor
                        ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """As ``se3_factor_assemble`` for SE(2) (matrices (B, E, 3, 3), r~ (B, E, 3))."""
    _check_assemble(Zinv, Ti, Tj, L, slots, values, g_slots, g, 3)
    return _se2_assemble_code(Zinv, Ti, Tj, L, slots, values, g_slots, g)


se2_factor_assemble.register_kernel("cpu")(
    lambda *a: _run_assemble("se2_factor_assemble", 3, _se2_assemble_code, *a, _SE2_SERIES))
se2_factor_assemble.register_fake(_assemble_fake(3))


def _assemble_vmap(op, dof: int):
    """The vmapped axis joins the problems' axis of the matrices and of ``values`` and ``g``
    (an unmapped one expanded); the index maps are shared."""

    def rule(info, in_dims, Zinv, Ti, Tj, L, slots, values, g_slots, g):
        if in_dims[4] is not None or in_dims[6] is not None:
            raise ValueError("slots and g_slots are shared by the problems: they cannot be vmapped")
        V = info.batch_size
        (Zinv, Ti, Tj), batch = _matrices_in_front(V, (Zinv, Ti, Tj), in_dims[:3])
        L = _noise_in_front(V, L, in_dims[3], batch, dof)
        L = L if L is None or L.dim() == 2 else L.flatten(0, 1)
        values, g = (t.unsqueeze(0).expand(V, *t.shape) if d is None else t.movedim(d, 0)
                     for t, d in ((values, in_dims[5]), (g, in_dims[7])))
        out = op(*(None if t is None else t.flatten(0, 1) for t in (Zinv, Ti, Tj)), L, slots,
                 values.flatten(0, 1), g_slots, g.flatten(0, 1))
        return tuple(t.unflatten(0, (V, -1)) for t in out), (0, 0, 0)

    return rule


se3_factor_assemble.register_vmap(_assemble_vmap(se3_factor_assemble, 6))
se2_factor_assemble.register_vmap(_assemble_vmap(se2_factor_assemble, 3))
