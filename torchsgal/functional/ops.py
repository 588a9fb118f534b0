"""The exp, log, their backward maps, the left Jacobian and its inverse, the product, the
inverse and the adjoint of SGal(3), of its subgroups SO(3), SE(3) and SE_2(3), of SE(2) and of
Sim(3) as registered torch operators.

``torchsgal::sgal3_exp``, ``sgal3_log``, ``sgal3_exp_vjp``, ``sgal3_log_vjp``, ``sgal3_jl``,
``sgal3_jl_inv``, ``sgal3_compose``, ``sgal3_inverse`` and ``sgal3_adjoint``
(defined through ``torch.library``, ``registration.py``), and the same nine of ``so3_``,
``se2_``, ``se3_``, ``se23_`` and ``sim3_``, are the one mechanism that eager code, autograd,
``torch.func`` and ``torch.compile`` all see:

* the implementation runs the C kernel (``native.py``) on CPU float32/float64 tensors of one
  batch shape, where the kernels are compiled and not switched off for the calling thread (every
  SGal(3) operator; exp, log, jl, jl_inv, compose, inverse and adjoint of the other groups (the
  inverse and adjoint of SO(3) and SE(2) excepted: their closed forms are a few entries), whose
  backward maps run their closed forms); on CUDA, for SGal(3), where chosen (``native.use_compiled_cuda(True)``) and
  Triton is installed, the closed
  form compiled by ``torch.compile`` (inductor's Triton kernels), one compilation per operator
  and dtype, over the flattened batch with a dynamic size (float32: float64 stays eager); the
  eager closed-form tensor code everywhere else (other devices, broadcast batches on the CPU,
  kernels off): the same choice whatever the context
  (autograd recording, vmap, grad, compile);
* a fake implementation (shapes only) lets ``torch.compile`` and ``torch.export`` trace them;
* ``register_autograd`` differentiates exp and log through their closed-form Jacobians
  (``_autograd.py``: grad_xi = J_r(xi)^T hat^T(M^T G), grad_M = M^-T vee^T(J_r(xi)^-T g)), each
  backward being the next operator; the backward operators' own derivatives (second order),
  and those of the Jacobians, the product, the inverse and the adjoint, are those of their
  tensor code;
* ``register_vmap`` maps every vmapped axis into the batch the kernels already loop over.

``tests/test_ops.py`` and ``tests/test_native_subgroups.py`` run ``torch.library.opcheck`` on
them.  The closed forms (``sgal3.exp_impl`` ...) stay the reference implementation.

Why C kernels on the CPU and compiled closed forms (opt-in) on CUDA: on the CPU the C kernel is
1.4-5.2x faster than the closed form compiled by inductor, which is itself faster than eager
tensor code; on CUDA a compiled closed form launches 14-49 kernels where the eager one launches
126-549 (SGal3.exp 2.1-2.4x faster per call in float32 on an H200), but the first call of
each operator and dtype pays its compilation (seconds to ~46 s; torch's caches shorten later
processes).  Figures:
``benchmarks/bench_compile.py``, docs/guide/acceleration.md.
"""
from __future__ import annotations

import importlib.util
import math
import warnings
from collections.abc import Callable, Sequence

import torch

from . import checks, native
from ._blocking import run_blocked
from .registration import operator

Tensor = torch.Tensor
_FLOATS = (torch.float32, torch.float64)
# the groups whose exp, log and J_l are operators, with C kernels (every group but SO(2))
GROUPS = ("SGal3", "SE3", "SE23", "SO3", "SE2", "Sim3")
# the groups whose operators may run compiled closed forms (``_compiles``; measured on CUDA for these)
COMPILED_GROUPS = ("SGal3",)
# devices whose operators run their closed forms through torch.compile, and what that needs
COMPILED_DEVICE_TYPES = ("cuda",)
# float64 stays on the eager closed forms: compiled for CUDA, sgal3_log_vjp was 1.6e-3 off the
# CPU in float64 on an H200 (tests/test_cuda.py), unexplained so far
COMPILED_DTYPES = (torch.float32,)
_COMPILER_NEEDS = {"cuda": "triton"}
COMPILE_BACKEND = "inductor"  # torch.compile's backend for them


def _kernel(name: str, args: Sequence[Tensor], batch: Sequence[torch.Size]) -> Callable | None:
    """The C kernel ``name`` if it runs for ``args`` (whose batch shapes are ``batch``), else None."""
    lib = native._lib
    if lib is None or not native.enabled():
        return None
    dtype = args[0].dtype
    if dtype not in _FLOATS:
        return None
    for a, b in zip(args, batch):
        if a.dtype is not dtype or not a.is_cpu or b != batch[0]:
            return None
    return getattr(lib, name, None)  # an operator without a kernel runs its closed form


def _run_kernel(fn: Callable, args: Sequence[Tensor], batch: torch.Size, event: tuple) -> Tensor:
    """fn over the batch: contiguous inputs, a fresh (*batch, *event) output of their dtype."""
    ins = [a if a.is_contiguous() and not a.is_neg() and not a.is_conj()
           else a.resolve_neg().resolve_conj().contiguous() for a in args]
    dtype = ins[0].dtype
    out = torch.empty(tuple(batch) + event, dtype=dtype)
    fn(*[t.data_ptr() for t in ins], out.data_ptr(), math.prod(batch), torch.get_num_threads(),
       dtype is torch.float64)
    return out


_COMPILED: dict = {}
_FOUND: dict = {}


def _compiles(args: Sequence[Tensor]) -> bool:
    """Whether ``args`` run through the compiled closed form: all of one dtype of
    ``COMPILED_DTYPES`` on one device of ``COMPILED_DEVICE_TYPES`` whose compiler backend is
    installed, path chosen and not off."""
    device, dtype = args[0].device, args[0].dtype
    if device.type not in COMPILED_DEVICE_TYPES or dtype not in COMPILED_DTYPES:
        return False
    if any(a.dtype is not dtype or a.device != device for a in args) or not native.compiled_enabled():
        return False
    need = _COMPILER_NEEDS.get(device.type)
    if need is not None and need not in _FOUND:
        _FOUND[need] = importlib.util.find_spec(need) is not None
    return need is None or _FOUND[need]


def _run_compiled(key: str, flat_code, args: Sequence[Tensor], event_dims: Sequence[int]) -> Tensor:
    """The operator's closed form compiled (once per operator; torch.compile adds a graph per
    dtype, device and inference mode), called on the arguments flattened to one dimension each
    (``flat_code`` views them back): with the batch as the only dynamic size, every batch shape
    and size reuses the graph, and no batch size is equated with an event size (torch.compile's
    duck sizing); a batch of one runs as two rows (the graph assumes a batch of at least two,
    as torch specialises sizes 0 and 1 of the batch it derives).  The inputs are passed
    detached, never as views (torch.compile guards on an input's view base).  Each operator has
    its own ``flat_code`` function: torch.compile keeps its graphs per code object.  Where
    compiling fails (a backend error, the recompilation limit), the operator warns once and runs
    its eager closed form from then on."""
    batch = _batch_shape(args, event_dims)
    flat = [a.expand(*batch, *a.shape[a.dim() - k:]).reshape(-1).detach() for a, k in zip(args, event_dims)]
    fn = _COMPILED.get(key)
    if fn is None:
        fn = _COMPILED[key] = torch.compile(flat_code, dynamic=True, fullgraph=True, backend=COMPILE_BACKEND)
    count = math.prod(batch)
    if count == 0 or fn is _FAILED:
        out = flat_code(*flat)
    else:
        try:
            with torch.no_grad():  # the operator's inputs never record (it sits below autograd)
                out = fn(*(torch.cat((f, f)) for f in flat) if count == 1 else flat)[:count]
        except Exception as e:  # noqa: BLE001  (any compiler failure: the eager code is exact)
            _COMPILED[key] = _FAILED
            warnings.warn(f"torchsgal::{key}: compiling its closed form failed ({type(e).__name__}: {e}); "
                          "it runs the eager closed form from now on", RuntimeWarning, stacklevel=2)
            out = flat_code(*flat)
    return out.reshape(*batch, *out.shape[1:])


_FAILED = object()  # marks an operator whose compilation failed


def _batch_shape(args: Sequence[Tensor], event_dims: Sequence[int]) -> torch.Size:
    return checks.broadcast_shapes(*(a.shape[: a.dim() - k] for a, k in zip(args, event_dims)))


def _vmap_rule(op, event_dims: Sequence[int]):
    """vmap of an operator that acts on every batch element alone: the vmapped axis of each
    argument moved to the front (unbatched arguments expanded), batch shapes broadcast, one call."""

    def rule(info, in_dims, *args):
        size = info.batch_size
        moved = []
        for a, d in zip(args, in_dims):
            moved.append(a.unsqueeze(0).expand(size, *a.shape) if d is None else a.movedim(d, 0))
        batch = _batch_shape(moved, event_dims)
        moved = [a.expand(*batch, *a.shape[a.dim() - k:]) for a, k in zip(moved, event_dims)]
        return op(*moved), 0

    return rule


_REGISTERED: dict = {}


def register(mod) -> tuple:
    """Define the operators of the group module ``mod`` (``functional.sgal3``, ``se3``, ``se23``)
    once and return them as (exp, log, exp_vjp, log_vjp, jl, jl_inv, compose, adjoint, inverse)."""
    if mod.NAME not in _REGISTERED:
        _REGISTERED[mod.NAME] = _define(mod)
    return _REGISTERED[mod.NAME]


def _define(mod) -> tuple:
    name, n, dof = mod.NAME.lower(), mod.MATRIX_DIM, mod.DOF
    prefix = f"torchsgal::{name}_"
    compiled_group = mod.NAME in COMPILED_GROUPS

    def exp_vjp_tensor(xi: Tensor, M: Tensor, G: Tensor) -> Tensor:
        return mod._jl_tmv(-xi, mod._exp_pullback(M, G))  # J_r(xi)^T hat^T(M^T G)

    def log_vjp_tensor(M: Tensor, xi: Tensor, g: Tensor) -> Tensor:
        return mod._log_pullback(M, mod._jl_inv_tmv(-xi, g))  # M^-T vee^T(J_r(xi)^-T g)

    def compose_tensor(A: Tensor, Bm: Tensor) -> Tensor:
        return A @ Bm

    names = {"exp": ("xi",), "log": ("M",), "exp_vjp": ("xi", "M", "G"), "log_vjp": ("M", "xi", "g"),
             "jl": ("xi",), "jl_inv": ("xi",), "compose": ("A", "B"), "adjoint": ("M",), "inverse": ("M",)}

    # the closed forms on arguments flattened to one dimension (_run_compiled): one function each
    def exp_flat(xi: Tensor) -> Tensor:
        return mod.exp_impl(xi.view(-1, dof))

    def log_flat(M: Tensor) -> Tensor:
        return mod.log_impl(M.view(-1, n, n))

    def exp_vjp_flat(xi: Tensor, M: Tensor, G: Tensor) -> Tensor:
        return exp_vjp_tensor(xi.view(-1, dof), M.view(-1, n, n), G.view(-1, n, n))

    def log_vjp_flat(M: Tensor, xi: Tensor, g: Tensor) -> Tensor:
        return log_vjp_tensor(M.view(-1, n, n), xi.view(-1, dof), g.view(-1, dof))

    def jl_flat(xi: Tensor) -> Tensor:
        return mod.jl_impl(xi.view(-1, dof))

    def jl_inv_flat(xi: Tensor) -> Tensor:
        return mod.jl_inv_impl(xi.view(-1, dof))

    def compose_flat(A: Tensor, Bm: Tensor) -> Tensor:
        return A.view(-1, n, n) @ Bm.view(-1, n, n)

    def adjoint_flat(M: Tensor) -> Tensor:
        return mod.adjoint_impl(M.view(-1, n, n))

    def inverse_flat(M: Tensor) -> Tensor:
        return mod.inverse_impl(M.view(-1, n, n))

    flat_codes = {"exp": exp_flat, "log": log_flat, "exp_vjp": exp_vjp_flat, "log_vjp": log_vjp_flat,
                  "jl": jl_flat, "jl_inv": jl_inv_flat, "compose": compose_flat, "adjoint": adjoint_flat,
                  "inverse": inverse_flat}

    kernel_names = {kernel: f"{name}_{kernel}" for kernel in names}

    def run(kernel: str, tensor_code, args, event_dims, event):
        # the operators are public: shapes checked before a C loop reads the memory
        batch = []
        for a, k, arg_name in zip(args, event_dims, names[kernel]):
            if k == 1:
                checks.vector(a, dof, arg_name)
            else:
                checks.matrix(a, n, arg_name)
            batch.append(a.shape[: a.dim() - k])
        if len(args) > 1:
            if kernel == "compose":  # A @ B promotes no dtype: name the mismatch
                checks.same_device_dtype(**dict(zip(names[kernel], args)))
            if any(b != batch[0] for b in batch[1:]):
                checks.broadcast_batch(**dict(zip(names[kernel], batch)))
        fn = _kernel(kernel_names[kernel], args, batch)
        if fn is None:
            if compiled_group and _compiles(args):
                return _run_compiled(kernel_names[kernel], flat_codes[kernel], args, event_dims)
            return run_blocked(tensor_code, tuple(args), tuple(event_dims))
        return _run_kernel(fn, args, batch[0], event)

    @operator(prefix + "exp")
    def exp(xi: Tensor) -> Tensor:
        return run("exp", mod.exp_impl, (xi,), (1,), (n, n))

    @operator(prefix + "log")
    def log(M: Tensor) -> Tensor:
        return run("log", mod.log_impl, (M,), (2,), (dof,))

    @operator(prefix + "exp_vjp")
    def exp_vjp(xi: Tensor, M: Tensor, G: Tensor) -> Tensor:
        return run("exp_vjp", exp_vjp_tensor, (xi, M, G), (1, 2, 2), (dof,))

    @operator(prefix + "log_vjp")
    def log_vjp(M: Tensor, xi: Tensor, g: Tensor) -> Tensor:
        return run("log_vjp", log_vjp_tensor, (M, xi, g), (2, 1, 1), (n, n))

    @operator(prefix + "jl")
    def jl(xi: Tensor) -> Tensor:
        return run("jl", mod.jl_impl, (xi,), (1,), (dof, dof))

    @operator(prefix + "jl_inv")
    def jl_inv(xi: Tensor) -> Tensor:
        return run("jl_inv", mod.jl_inv_impl, (xi,), (1,), (dof, dof))

    @operator(prefix + "compose")
    def compose(A: Tensor, Bm: Tensor) -> Tensor:
        return run("compose", compose_tensor, (A, Bm), (2, 2), (n, n))

    @operator(prefix + "adjoint")
    def adjoint(M: Tensor) -> Tensor:
        return run("adjoint", mod.adjoint_impl, (M,), (2,), (dof, dof))

    @operator(prefix + "inverse")
    def inverse(M: Tensor) -> Tensor:
        return run("inverse", mod.inverse_impl, (M,), (2,), (n, n))

    def fake(event_dims, event):
        def impl(*args):
            return args[0].new_empty(tuple(_batch_shape(args, event_dims)) + event)
        return impl

    exp.register_fake(fake((1,), (n, n)))
    log.register_fake(fake((2,), (dof,)))
    exp_vjp.register_fake(fake((1, 2, 2), (dof,)))
    log_vjp.register_fake(fake((2, 1, 1), (n, n)))
    jl.register_fake(fake((1,), (dof, dof)))
    jl_inv.register_fake(fake((1,), (dof, dof)))
    compose.register_fake(fake((2, 2), (n, n)))
    adjoint.register_fake(fake((2,), (dof, dof)))
    inverse.register_fake(fake((2,), (n, n)))

    def save_all(ctx, inputs, output):
        ctx.save_for_backward(*inputs, output)

    def exp_backward(ctx, grad_M):
        xi, M = ctx.saved_tensors
        return exp_vjp(xi, M, grad_M)

    def log_backward(ctx, grad_xi):
        M, xi = ctx.saved_tensors
        return log_vjp(M, xi, grad_xi)

    def tensor_code_backward(tensor_code):
        def backward(ctx, grad):  # second order: the closed-form backward differentiated
            saved = ctx.saved_tensors[:-1]
            with torch.enable_grad():
                _, pullback = torch.func.vjp(tensor_code, *saved)
            return pullback(grad)
        return backward

    exp.register_autograd(exp_backward, setup_context=save_all)
    log.register_autograd(log_backward, setup_context=save_all)
    exp_vjp.register_autograd(tensor_code_backward(exp_vjp_tensor), setup_context=save_all)
    log_vjp.register_autograd(tensor_code_backward(log_vjp_tensor), setup_context=save_all)
    jl.register_autograd(tensor_code_backward(mod.jl_impl), setup_context=save_all)
    jl_inv.register_autograd(tensor_code_backward(mod.jl_inv_impl), setup_context=save_all)
    compose.register_autograd(tensor_code_backward(compose_tensor), setup_context=save_all)
    adjoint.register_autograd(tensor_code_backward(mod.adjoint_impl), setup_context=save_all)
    inverse.register_autograd(tensor_code_backward(mod.inverse_impl), setup_context=save_all)

    for op, event_dims in ((exp, (1,)), (log, (2,)), (exp_vjp, (1, 2, 2)), (log_vjp, (2, 1, 1)),
                           (jl, (1,)), (jl_inv, (1,)), (compose, (2, 2)), (adjoint, (2,)), (inverse, (2,))):
        op.register_vmap(_vmap_rule(op, event_dims))
    return exp, log, exp_vjp, log_vjp, jl, jl_inv, compose, adjoint, inverse
