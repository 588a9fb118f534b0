"""Rows times a small matrix, plus a row, over a batch: ``torchsgal::affine_rows``.

``torch.ops.torchsgal.affine_rows(x, W, c)`` -> x @ W + c[:, None, :] for x (Bx, N, k), W (B, k, m)
and c (B, m) or None, Bx a divisor of B (problem b reads x[b mod Bx]): B matrices W with few
rows, each applied to N rows of x.  It is what a group element acting on many points costs
(``blocks.act_homogeneous``: W the transposed rotation block, c the translation column) and the
Jacobian of that action (``blocks.act_homogeneous_jacobian``: W the element times the
generators, (k, rows * dof)); one x read by several W is forward mode's tangents of an action
(the directions' W over the same points).

torch's CPU ``baddbmm`` hands each of the B products to BLAS, whose fixed cost per product
dominates for k of 3 or 4; the C kernel (``_native_affine.h``) forms each output row in place,
its length a compile-time constant, as vectors of four entries.  On one thread, 256 products of
100 x 3 rows: rows of 3 entries (the action) 0.034 ms against 0.17 ms, of 18 (SE(3)'s Jacobian)
0.076 ms against 0.34 ms, of 40 0.24 ms against 0.47 ms in float64; in float32 (whose BLAS
products are twice as fast) 18 entries 0.072 ms against 0.115 ms, and on two threads, where BLAS
splits the products and the kernel splits only batches of at least some hundred microseconds of
work (``_native_common.h``), float32 rows of 18 take 0.072 ms against 0.062 ms, while float64
rows of 27 (SE_2(3)'s) take 0.12 ms against 0.18 ms.  Hence ``rows_times``, the groups' call,
takes the operator for rows of up to ``KERNEL_MAX_M[dtype]`` entries (every action and, in
float64, every group's Jacobian) on CPU float32/float64 tensors where the kernels are on in the
calling thread (``native.enabled``) and the output has at least ``MIN_KERNEL_ENTRIES`` entries
(below, the operator's fixed cost exceeds the product's): called directly where nothing
observes the call (``_blocking.unobserved``), through ``_RowsTimes`` (the product's derivatives
in both modes, the operator's vmap rule) where autograd records or a torch.func transform maps
it.  Compiled code and nested forward-mode transforms take the tensor code (``baddbmm``), the
reference the tests compare the kernel with.  The operator has a fake implementation, a vmap
rule and its derivatives (the product's), and ``tests/test_affine_rows.py`` runs
``torch.library.opcheck`` on it.
"""
from __future__ import annotations

import torch

from .._compat import FastApply, forward_mode_depth
from . import checks, native
from ._blocking import is_compiling, unobserved
from .registration import operator

__all__ = ["affine_rows", "rows_times"]

MIN_KERNEL_ENTRIES = 4096  # B * N * m below which the tensor code runs (the call's own cost)
# the longest rows ``rows_times`` forms by the kernel, per dtype (module docstring)
KERNEL_MAX_M = {torch.float32: 9, torch.float64: 40}
MAX_M = 64  # AF_MAX_M of _native_affine.h: the longest row the kernel forms


def _check(x: torch.Tensor, W: torch.Tensor, c: torch.Tensor | None) -> None:
    for name, t in (("x", x), ("W", W)) + ((("c", c),) if c is not None else ()):
        if not isinstance(t, torch.Tensor):
            raise TypeError(f"affine_rows: {name} must be a tensor, got {type(t).__name__}")
    if (x.dim() != 3 or W.dim() != 3 or x.shape[2] != W.shape[1]
            or not (x.shape[0] == W.shape[0] or x.shape[0] >= 1 and W.shape[0] % x.shape[0] == 0)):
        raise ValueError(f"affine_rows: x must have shape (Bx, N, k) and W (B, k, m) with Bx a "
                         f"divisor of B, got x {tuple(x.shape)} and W {tuple(W.shape)}")
    if c is not None and tuple(c.shape) != (W.shape[0], W.shape[2]):
        raise ValueError(f"affine_rows: c must have shape {(W.shape[0], W.shape[2])} (B, m), got "
                         f"{tuple(c.shape)}")
    given = {"x": x, "W": W} if c is None else {"x": x, "W": W, "c": c}
    checks.same_device_dtype(**given)


def _tensor_code(x: torch.Tensor, W: torch.Tensor, c: torch.Tensor | None) -> torch.Tensor:
    if x.shape[0] != W.shape[0]:
        x = x.repeat(W.shape[0] // x.shape[0], 1, 1)
    return torch.bmm(x, W) if c is None else torch.baddbmm(c.unsqueeze(-2), x, W)


def _sum_repeats(grad_x: torch.Tensor, Bx: int) -> torch.Tensor:
    """The gradient (B, N, k) of x @ W summed over the problems that share each x (Bx, N, k)."""
    return grad_x if grad_x.shape[0] == Bx else grad_x.unflatten(0, (-1, Bx)).sum(0)


@operator("torchsgal::affine_rows", schema="(Tensor x, Tensor W, Tensor? c) -> Tensor")
def affine_rows(x: torch.Tensor, W: torch.Tensor, c: torch.Tensor | None) -> torch.Tensor:
    """x @ W + c[:, None, :] (module docstring); x (Bx, N, k) with Bx a divisor of B: problem b
    reads x[b mod Bx]."""
    _check(x, W, c)
    return _tensor_code(x, W, c)


def _kernel(x: torch.Tensor, W: torch.Tensor, c: torch.Tensor | None) -> torch.Tensor:
    _check(x, W, c)
    lib = native._lib
    Bx, N, k = x.shape
    B, m = W.shape[0], W.shape[2]
    if (lib is None or not native.enabled() or x.dtype not in (torch.float32, torch.float64)
            or k == 0 or not 1 <= m <= MAX_M or B * N == 0):
        return _tensor_code(x, W, c)
    x, W = (t.resolve_neg().resolve_conj().contiguous() for t in (x, W))
    if c is not None:
        c = c.resolve_neg().resolve_conj().contiguous()
    out = torch.empty(B, N, m, dtype=x.dtype)
    dims = torch.tensor([N, k, m, Bx], dtype=torch.int64)
    lib.affine_rows(x.data_ptr(), W.data_ptr(), 0 if c is None else c.data_ptr(), out.data_ptr(),
                    dims.data_ptr(), B, torch.get_num_threads(), x.dtype is torch.float64)
    return out


affine_rows.register_kernel("cpu")(_kernel)


@affine_rows.register_fake
def _fake(x, W, c):
    _check(x, W, c)
    return x.new_empty(W.shape[0], x.shape[1], W.shape[2])


def _setup_context(ctx, inputs, output):
    x, W, c = inputs
    ctx.save_for_backward(x, W)
    ctx.has_c = c is not None


def _backward(ctx, grad):
    x, W = ctx.saved_tensors
    grad_x = _sum_repeats(grad @ W.mT, x.shape[0]) if ctx.needs_input_grad[0] else None
    grad_W = _tensor_code(x.mT, grad, None) if ctx.needs_input_grad[1] else None
    grad_c = grad.sum(-2) if ctx.has_c and ctx.needs_input_grad[2] else None
    return grad_x, grad_W, grad_c


affine_rows.register_autograd(_backward, setup_context=_setup_context)


@affine_rows.register_vmap
def _vmap(info, in_dims, x, W, c):
    """The vmapped axis joins the batch axis in front (V B problems, laid out as V unmapped
    outputs: forward mode keeps mapped tangents in that layout without a copy).  An unmapped x
    is read by every mapped W, not copied (the operator's x batch dividing B); an unmapped W or
    c is repeated V times."""
    V = info.batch_size
    dx, dW, dc = in_dims
    if dW is None:
        B, W = W.shape[0], W.repeat(V, 1, 1)
    else:
        W = W.movedim(dW, 0)
        B, W = W.shape[1], W.flatten(0, 1)
    if c is not None:
        c = c.repeat(V, 1) if dc is None else c.movedim(dc, 0).flatten(0, 1)
    if dx is not None:
        x = x.movedim(dx, 0)  # (V, Bx, N, k): problem v B + b reads x[v, b mod Bx]
        x = (x if x.shape[1] == B else x.repeat(1, B // x.shape[1], 1, 1)).flatten(0, 1)
    return affine_rows(x, W, c).unflatten(0, (V, B)), 0


class _Constant:
    """An argument of ``_RowsTimes`` that nothing observes, passed as a non-tensor (with the
    shape the operator takes it in): it gets no tangent, no gradient and no vmapped axis (torch
    would give a tensor argument without a tangent a tangent of zeros, mapped over every
    direction).  It holds the caller's own tensor: inside a forward-mode transform, every
    operation's output (a reshape too) is that transform's wrapper."""

    __slots__ = ("tensor", "shape")

    def __init__(self, tensor: torch.Tensor, shape: tuple) -> None:
        self.tensor, self.shape = tensor, shape


def _value(a):
    return a.tensor.reshape(a.shape) if isinstance(a, _Constant) else a


class _RowsTimes(FastApply, torch.autograd.Function):
    """``affine_rows`` where something differentiates it or a torch.func transform maps it:
    reverse mode grad W^T, x^T grad and grad's rows summed (tensor operations, themselves
    differentiable), forward mode dx W + x dW + dc (the operator again), vmap through the
    operator's rule.  Arguments that nothing observes come as ``_Constant``."""

    generate_vmap_rule = True

    @staticmethod
    def forward(x, W, c):
        return affine_rows(_value(x), _value(W), _value(c))

    @staticmethod
    def setup_context(ctx, inputs, output):
        x, W, c = inputs
        ctx.constant = [isinstance(a, _Constant) for a in (x, W)]
        ctx.has_c = c is not None
        ctx.held = [_value(a) for a in (x, W) if isinstance(a, _Constant)]
        tracked = [a for a in (x, W) if not isinstance(a, _Constant)]
        ctx.save_for_backward(*tracked)
        ctx.save_for_forward(*tracked)

    @staticmethod
    def _operands(ctx):
        held, tracked = iter(ctx.held), iter(ctx.saved_tensors)
        return [next(held) if constant else next(tracked) for constant in ctx.constant]

    @staticmethod
    def backward(ctx, grad):
        x, W = _RowsTimes._operands(ctx)
        return (_sum_repeats(grad @ W.mT, x.shape[0]) if ctx.needs_input_grad[0] else None,
                _tensor_code(x.mT, grad, None) if ctx.needs_input_grad[1] else None,
                grad.sum(-2) if ctx.has_c and ctx.needs_input_grad[2] else None)

    @staticmethod
    def jvp(ctx, dx, dW, dc):
        x, W = _RowsTimes._operands(ctx)
        out = None
        if dW is not None:
            out = affine_rows(x, dW, dc)
        elif dc is not None:
            out = dc.unsqueeze(-2).expand(W.shape[0], x.shape[1], W.shape[2]).clone()
        if dx is not None:
            term = affine_rows(dx, W, None)
            out = term if out is None else out + term
        if out is None:
            return x.new_zeros(W.shape[0], x.shape[1], W.shape[2])
        return out


def rows_times(x: torch.Tensor, W: torch.Tensor, c: torch.Tensor | None = None) -> torch.Tensor:
    """x @ W (+ c[..., None, :]) for x (..., N, k), W (..., k, m) and c (..., m): the operator
    where its kernel runs and pays (one batch shape, CPU float32/float64, rows of at most
    ``KERNEL_MAX_M[dtype]`` entries, at least ``MIN_KERNEL_ENTRIES`` output entries, kernels
    on): called directly where nothing observes the call, through ``_RowsTimes`` where autograd
    records or a torch.func transform maps it; else (compiling, nested forward-mode transforms,
    other devices and sizes) the same product as tensor operations, which autograd and
    ``torch.func`` differentiate."""
    batch = x.shape[:-2]
    if (native._lib is not None and x.is_cpu and x.dtype in KERNEL_MAX_M
            and W.shape[:-2] == batch and (c is None or c.shape[:-1] == batch)
            and W.dtype == x.dtype and (c is None or c.dtype == x.dtype)
            and x.shape[-1] >= 1 and 1 <= W.shape[-1] <= KERNEL_MAX_M[x.dtype]
            and x.shape[:-1].numel() * W.shape[-1] >= MIN_KERNEL_ENTRIES
            and native.enabled() and not is_compiling()):
        args = (x, W) if c is None else (x, W, c)
        direct = unobserved(args)
        if direct or (forward_mode_depth() < 2 and all(type(a) is torch.Tensor for a in args)):
            B = batch.numel()
            shapes = ((B, *x.shape[-2:]), (B, *W.shape[-2:]), (B, W.shape[-1]))
            if direct:
                out = torch.ops.torchsgal.affine_rows(
                    *(None if a is None else a.reshape(shape) for a, shape in zip((x, W, c), shapes)))
            else:
                out = _RowsTimes.apply(*(
                    None if a is None else _Constant(a, shape) if unobserved((a,)) else a.reshape(shape)
                    for a, shape in zip((x, W, c), shapes)))
            return out.reshape(x.shape[:-1] + W.shape[-1:])
    if c is None:
        return x @ W
    if x.dim() == 3 and W.dim() == 3 and x.shape[0] == W.shape[0]:
        return torch.baddbmm(c.unsqueeze(-2), x, W)
    return x @ W + c.unsqueeze(-2)
