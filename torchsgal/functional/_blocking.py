"""Cache blocking of large CPU batches.

A closed form here is a few dozen elementwise operations, each of which allocates a batch-sized
temporary.  On CPU a large temporary is a fresh ``mmap`` that the kernel fills page by page, and
past a few hundred thousand elements those page faults cost more than the arithmetic (of the
order of 0.3 ms per MB: at 1e6 elements, SGal3.exp would spend most of its time there).
``blocked`` runs such a function over blocks of ``BLOCK`` batch elements, whose temporaries the
allocator recycles from block to block instead of mapping fresh pages, and writes each block into
one output.

The blocked path is taken only where it cannot be observed: CPU tensors of the plain Tensor
type, a batch of at least ``MIN_BATCH`` elements, no autograd recording, no functorch transform
(vmap, grad, jacrev) and no torch.compile tracing.  Everywhere else the function runs as written,
so autograd, vmap and compile see exactly the unblocked graph.  Every operation is elementwise
over the batch, so blocked and unblocked results agree to the rounding of the vectorised math
kernels (tests/test_blocking.py).
"""
from __future__ import annotations

import functools
import math

import torch
from torch.autograd import forward_ad as _forward_ad

from .._compat import is_functorch_wrapped
from . import checks

# Batch elements per block.  Two of torch's parallel grains (32768 elements), so every kernel of
# a block still runs on two threads; 16384 lost that and was slower with 2 threads, 131072 gained
# nothing more (SGal3 exp and log at 1e6 elements, benchmarks/bench_core.py).
BLOCK = 65536
# Smallest batch that is blocked: at 1e5 elements fresh temporaries are still recycled by the
# allocator and blocking gained nothing.
MIN_BATCH = 2 * BLOCK

_is_wrapped = is_functorch_wrapped  # a torch.func wrapper
is_compiling = torch.compiler.is_compiling


def values_readable(t: torch.Tensor) -> bool:
    """Whether a value check may read ``t`` (one host sync): not on 'meta' (no data), not inside a
    torch.func transform (``bool`` of a batched tensor raises) and not while torch.compile
    traces.  The shape, dtype and device checks do not depend on it."""
    if t.device.type == "meta" or is_compiling():
        return False
    return not _is_wrapped(t)


def unobserved(args) -> bool:
    """True where a blocked or in-place evaluation of ``args`` cannot be observed: plain CPU
    tensors, no autograd recording (reverse or forward mode), no functorch transform, not
    compiling (the rule of this module, also used by the IMU's fast path, whose ``out=``
    kernels have no forward-mode derivative)."""
    if is_compiling():
        return False
    grad = torch.is_grad_enabled()
    for a in args:
        if type(a) is not torch.Tensor or not a.is_cpu or _is_wrapped(a):
            return False
        if grad and a.requires_grad:
            return False
    # Dual tensors of torch.autograd.forward_ad (0.6 us per argument outside a dual level).
    return all(_forward_ad.unpack_dual(a).tangent is None for a in args)


def run_lifted(fn, args, event_dims):
    """``fn(*args)``; inside a torch.func transform, unbatched arguments (each exactly its event
    dims) run as a batch of one.  functorch's jvp gives a Python number times a 0-d float32
    tensor a float64 tangent (pytorch/functorch#1073, still in torch 2.13), and the closed forms
    hold 0-d components when unbatched: float32 jacfwd and hessian raised in lerp or silently
    returned float64.  With a batch axis the components are 1-d and the tangents keep the
    dtype.  Same ``fn`` contract as ``run_blocked``.  Not while torch.compile traces (dynamo
    refuses the wrapper test)."""
    if (is_compiling()
            or not all(isinstance(a, torch.Tensor) and a.dim() == k
                       for a, k in zip(args, event_dims))
            or not any(_is_wrapped(a) for a in args)):
        return fn(*args)
    try:
        out = fn(*(a.unsqueeze(0) for a in args))
    except (ValueError, TypeError):
        return fn(*args)  # the same error, reported with the caller's shapes
    return out.squeeze(0)


def run_blocked(fn, args, event_dims):
    """``fn(*args)``, over blocks of the broadcast batch where that is safe (module docstring).

    ``event_dims[i]`` is the number of trailing non-batch dimensions of ``args[i]``; ``fn`` must
    act independently on every batch element and return one tensor (..., *event).  Inside
    torch.func transforms, unbatched calls go through ``run_lifted``.
    """
    if not unobserved(args) or any(a.dim() < k for a, k in zip(args, event_dims)):
        return run_lifted(fn, args, event_dims)
    try:
        batch = checks.broadcast_shapes(*(a.shape[: a.dim() - k] for a, k in zip(args, event_dims)))
    except RuntimeError:
        return fn(*args)  # raises the function's own error naming the arguments
    n = math.prod(batch)
    if n < MIN_BATCH:
        return fn(*args)
    flat = [a.expand(batch + a.shape[a.dim() - k:]).reshape((n,) + a.shape[a.dim() - k:])
            for a, k in zip(args, event_dims)]
    try:
        first = fn(*(f[:BLOCK] for f in flat))
    except (ValueError, TypeError):
        return fn(*args)  # the same error, reported with the caller's shapes
    out = first.new_empty((n,) + first.shape[1:])
    out[:BLOCK] = first
    for start in range(BLOCK, n, BLOCK):
        out[start: start + BLOCK] = fn(*(f[start: start + BLOCK] for f in flat))
    return out.reshape(batch + first.shape[1:])


def blocked(*event_dims: int):
    """Decorator form of ``run_blocked`` for ``fn(a_0, ..., a_k)`` with the given event dims."""

    def wrap(fn):
        @functools.wraps(fn)
        def inner(*args):
            return run_blocked(fn, args, event_dims)

        return inner

    return wrap
