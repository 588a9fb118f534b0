"""The differentiation rules: exp and log as torch.autograd.Functions with closed-form backward.

For a group module ``mod`` (so2, so3, se2, se3, se23, sgal3, sim3):

* exp: xi -> M = exp(xi^).  Since d exp = M (J_r(xi) dxi)^ (right Jacobian, (3.22)),
      grad_xi = J_r(xi)^T hat^T(M^T grad_M),
  where hat^T is the Frobenius adjoint of hat.  Exact for every grad_M.

* log: M -> xi = log(M)^vee.  For perturbations tangent to the group, dM = M (dzeta)^,
      dxi = J_r(xi)^-1 vee(M^-1 dM),
  so grad_M = M^-T vee^T(J_r(xi)^-T grad_xi), with vee^T the Frobenius adjoint of vee (vee
  takes the skew part of the rotation block).  The gradient is therefore taken with respect
  to the group: a component of an incoming perturbation normal to the group is projected
  out, not differentiated through the closed form.

* Forward mode (``jvp``: torch.func.jacfwd, hessian, torch.autograd.forward_ad) uses the same
  Jacobians the other way round: d exp = M (J_r(xi) dxi)^ and dxi = J_r(xi)^-1 vee(M^-1 dM),
  the transpose of log's backward map, so jacfwd and jacrev agree.

* Inside two or more forward-mode transforms (jacfwd(jacfwd(f))), where torch 2.13 gets a
  Function's higher derivatives wrong (pytorch/pytorch#197867), exp and log are the closed
  forms under autograd too (jacfwd(jacrev), jacrev(jacfwd) and hessian keep the Functions).

* Under torch.compile, exp and log are the closed forms (``exp_impl``/``log_impl``) under
  autograd, not these Functions: torch 2.13 differentiates a compiled Function's backward
  with its saved tensors held constant (second derivatives came out silently wrong) and
  refuses one with a jvp.  The derivatives agree along the group; for log with respect to a
  matrix perturbed off the group, compiled code gives the closed form's derivative rather
  than the projection above.

Both use ``setup_context`` and ``generate_vmap_rule = True`` (torch.func.vmap, jacrev), and
their backward is itself differentiable (higher derivatives).  The forward and backward of
SGal(3), SO(3), SE(2), SE(3), SE_2(3) and Sim(3) run their registered operators (ops.py: C kernels on the CPU where
compiled, native.py); large CPU batches of the other groups run in blocks (_blocking).  Where
nothing records (no autograd recording, forward-mode tangent or torch.func transform, not
compiling: ``_blocking.unobserved``), exp, log, J_l, J_l^-1 and compose call their operators
without the Function around them: the same values, without its bookkeeping (~35 us a call,
benchmarks/bench_call_cost.py).
"""
from __future__ import annotations

import torch
from torch.autograd import forward_ad as _forward_ad

from .._compat import FastApply, forward_mode_depth
from . import checks, ops
from ._blocking import _is_wrapped, is_compiling, run_blocked, run_lifted, unobserved


def _nested_forward_mode(t: torch.Tensor) -> bool:
    """Whether ``t`` is inside two or more torch.func forward-mode transforms (jacfwd(jacfwd)),
    where torch 2.13 returns wrong higher derivatives through an autograd.Function
    (pytorch/pytorch#197867)."""
    return _is_wrapped(t) and forward_mode_depth() >= 2


def _compiled_inference(t: torch.Tensor) -> bool:
    """Whether torch.compile traces code that nothing differentiates (grad mode off) on CPU
    tensors: there compiled code calls the operators (their C kernels).  Elsewhere it fuses the
    closed forms (on CUDA: inductor's Triton kernels, which an opaque operator would prevent);
    with grad mode on, compiled code differentiates the closed forms: torch 2.13 compiles no
    double backward and no torch.func transform of a custom operator's autograd, and Dynamo
    cannot tell a torch.func wrapper (its ``requires_grad`` reads False while traced)."""
    return is_compiling() and not torch.is_grad_enabled() and t.device.type == "cpu"


def _differentiable_operator(operator, tensor_code, event_dims: tuple, name: str):
    """``operator`` as an autograd.Function whose derivatives, reverse and forward mode, are
    those of ``tensor_code`` (the same map as closed-form tensor operations)."""

    def lifted(*args):
        # unbatched arguments as a batch of one: functorch's jvp gives a Python number times a
        # 0-d float32 tensor a float64 tangent (run_lifted, _blocking.py)
        if all(a.dim() == k for a, k in zip(args, event_dims)):
            return tensor_code(*(a.unsqueeze(0) for a in args)).squeeze(0)
        return tensor_code(*args)

    class Function(FastApply, torch.autograd.Function):
        generate_vmap_rule = True

        @staticmethod
        def forward(*args):
            return operator(*args)

        @staticmethod
        def setup_context(ctx, inputs, output):
            ctx.save_for_backward(*inputs)
            ctx.save_for_forward(*inputs)

        @staticmethod
        def backward(ctx, grad):
            return torch.func.vjp(lifted, *ctx.saved_tensors)[1](grad)

        @staticmethod
        def jvp(ctx, *tangents):
            # make_dual refuses tensors whose elements share memory (an expanded incoming gradient)
            primals = tuple(p.clone(memory_format=torch.contiguous_format) for p in ctx.saved_tensors)
            tangents = tuple(torch.zeros_like(p) if t is None else t.clone(memory_format=torch.contiguous_format)
                             for p, t in zip(primals, tangents))
            return torch.func.jvp(lifted, primals, tangents)[1]

    Function.__name__ = Function.__qualname__ = name
    return Function


def make_exp_log(mod):
    # the group's registered operators (ops.py: the C kernels, or the closed forms), or None
    op = ops.register(mod) if mod.NAME in ops.GROUPS else None

    def _exp_backward(xi, M, grad_M):
        return mod._jl_tmv(-xi, mod._exp_pullback(M, grad_M))

    def _log_backward(M, xi, grad_xi):
        return mod._log_pullback(M, mod._jl_inv_tmv(-xi, grad_xi))

    def _forward(index, impl, args, event_dims):
        return run_blocked(impl, args, event_dims) if op is None else op[index](*args)

    # The backward maps as operators too, differentiable (higher derivatives, torch.func) through
    # their closed forms: a registered operator's own autograd is not a torch.func transform's in torch 2.13.
    backward_maps = None if op is None else (
        _differentiable_operator(op[2], _exp_backward, (1, 2, 2), f"{mod.NAME}ExpBackward"),
        _differentiable_operator(op[3], _log_backward, (2, 1, 1), f"{mod.NAME}LogBackward"))

    def _backward(index, impl, args, event_dims):
        if backward_maps is None:
            return run_blocked(impl, args, event_dims)
        if not torch.is_grad_enabled():  # nothing differentiates this backward: the operator
            return op[2 + index](*args)
        return backward_maps[index].apply(*args)

    def _matvec(A, x):
        return (A @ x.unsqueeze(-1)).squeeze(-1)

    def _exp_jvp(xi, M, dxi):  # (the jl and jl_inv of these jvps are lifted by run_blocked)
        # dM = M (J_r(xi) dxi)^, J_r(xi) = J_l(-xi)
        return M @ mod.hat(_matvec(mod.jl(-xi), dxi))

    def _log_jvp(M, xi, dM):
        # dxi = J_r(xi)^-1 vee(M^-1 dM), the transpose of the backward's map
        return _matvec(mod.jl_inv(-xi), mod.vee(mod.inverse(M) @ dM))

    class Exp(FastApply, torch.autograd.Function):
        generate_vmap_rule = True

        @staticmethod
        def forward(xi):
            return _forward(0, mod.exp_impl, (xi,), (1,))

        @staticmethod
        def setup_context(ctx, inputs, output):
            ctx.save_for_backward(inputs[0], output)

        @staticmethod
        def backward(ctx, grad_M):
            xi, M = ctx.saved_tensors
            # J_r(xi)^T hat^T(M^T grad_M), with J_r(xi)^T = J_l(-xi)^T
            return _backward(0, _exp_backward, (xi, M, grad_M), (1, 2, 2))

    class Log(FastApply, torch.autograd.Function):
        generate_vmap_rule = True

        @staticmethod
        def forward(M):
            return _forward(1, mod.log_impl, (M,), (2,))

        @staticmethod
        def setup_context(ctx, inputs, output):
            ctx.save_for_backward(inputs[0], output)

        @staticmethod
        def backward(ctx, grad_xi):
            M, xi = ctx.saved_tensors
            # M^-T vee^T(J_r(xi)^-T grad_xi)
            return _backward(1, _log_backward, (M, xi, grad_xi), (2, 1, 1))

    def _with_jvp(base, tangent_map):
        """``base`` with forward mode: jvp = tangent_map(*saved, tangent) (saved: input, output)."""
        class WithJvp(base):
            @staticmethod
            def setup_context(ctx, inputs, output):
                ctx.save_for_backward(inputs[0], output)
                ctx.save_for_forward(inputs[0], output)

            @staticmethod
            def jvp(ctx, tangent):
                return tangent_map(*ctx.saved_tensors, tangent)

        return WithJvp

    ExpWithJvp, LogWithJvp = _with_jvp(Exp, _exp_jvp), _with_jvp(Log, _log_jvp)

    for cls, name in ((Exp, "Exp"), (ExpWithJvp, "Exp"), (Log, "Log"), (LogWithJvp, "Log")):
        cls.__name__ = cls.__qualname__ = f"{mod.NAME}{name}"

    # Under torch.compile the closed forms are differentiated by autograd instead: torch 2.13
    # differentiates a compiled Function's backward with its saved tensors held constant, so
    # second derivatives through it came out silently wrong (tests/test_autograd.py shows it
    # on a ten-line Function), and Dynamo refuses a Function that defines jvp.  Compiled, the
    # Function was no faster than autograd through the closed form (bench_compile.py).
    def exp(xi: torch.Tensor) -> torch.Tensor:
        """Group exponential (..., dof) -> (..., n, n); backward through the closed-form J_r."""
        checks.vector(xi, mod.DOF, "xi")
        if op is not None and _compiled_inference(xi):
            return op[0](xi)
        if is_compiling() or _nested_forward_mode(xi):
            return run_lifted(mod.exp_impl, (xi,), (1,))
        if op is not None and unobserved((xi,)):  # nothing records: the operator, no Function around it
            return op[0](xi)
        return ExpWithJvp.apply(xi)

    def log(M: torch.Tensor) -> torch.Tensor:
        """Principal logarithm (..., n, n) -> (..., dof); backward through J_r^-1 (see module)."""
        checks.matrix(M, mod.MATRIX_DIM, "M")
        if op is not None and _compiled_inference(M):
            return op[1](M)
        if is_compiling() or _nested_forward_mode(M):
            return run_lifted(mod.log_impl, (M,), (2,))
        if op is not None and unobserved((M,)):
            return op[1](M)
        return LogWithJvp.apply(M)

    exp.__doc__ = f"{mod.NAME} exponential, custom autograd. " + (exp.__doc__ or "")
    log.__doc__ = f"{mod.NAME} logarithm, custom autograd. " + (log.__doc__ or "")
    return exp, log


def make_jacobians(mod):
    """``jl`` and ``jl_inv`` of a group module with registered operators (``ops.GROUPS``): the
    operators (their C kernels where they apply), differentiated, in reverse and forward mode,
    through the closed forms ``mod.jl_impl`` and ``mod.jl_inv_impl``.  Compiled code calls the
    operators for inference on CPU tensors and the closed forms otherwise, as exp and log do."""
    op = ops.register(mod)

    def make(index, impl, name, doc):
        function = _differentiable_operator(op[index], impl, (1,), f"{mod.NAME}{name.title()}")

        def jacobian(xi: torch.Tensor) -> torch.Tensor:
            checks.vector(xi, mod.DOF, "xi")
            if is_compiling():
                return op[index](xi) if _compiled_inference(xi) else impl(xi)
            if _nested_forward_mode(xi) or _forward_ad.unpack_dual(xi).tangent is not None:
                # jacfwd(jacfwd), or a dual tensor of torch.autograd.forward_ad, inside whose
                # level the Function's jvp (torch.func.jvp) cannot nest: the closed form
                return run_lifted(impl, (xi,), (1,))
            if unobserved((xi,)):  # nothing records: the operator, no Function around it
                return op[index](xi)
            return function.apply(xi)

        jacobian.__name__ = jacobian.__qualname__ = name
        jacobian.__module__ = mod.__name__
        jacobian.__doc__ = doc
        return jacobian

    d = mod.DOF
    return (make(4, mod.jl_impl, "jl", f"Left Jacobian (..., {d}) -> (..., {d}, {d}) "
                 "(SGal(3): (3.21)-(3.23))."),
            make(5, mod.jl_inv_impl, "jl_inv", f"Inverse of the left Jacobian (..., {d}) -> "
                 f"(..., {d}, {d}) (SGal(3): (3.23), block back-substitution)."))


# Batches below this many elements compose as tensor code (A @ B): there the operator's call
# (~55 us on one thread, benchmarks/bench_call_cost.py) costs more than torch's batched matmul
# (crossing over at 150-250 elements of 4 x 4 and 5 x 5; the 3 x 3 products of SO(3) and
# SE(2), cheaper in torch, pass their own, 2048: crossing over at 2,000-4,000 elements).
COMPOSE_MIN_BATCH = 256


def make_products(mod, compose_min_batch: int = COMPOSE_MIN_BATCH):
    """``compose`` (the group product A B of matrices), ``adjoint`` and ``inverse`` of a group
    module with registered operators (``ops.GROUPS``), running the operators (C kernels on the
    CPU) where they pay:

    * compose, for CPU batches of ``compose_min_batch`` elements or more (smaller ones, other
      devices and autocast regions run ``A @ B``), through an autograd.Function whose derivatives are the product
      rule's (backward G B^T and A^T G, jvp dA B + A dB, each a product again);
    * inverse and adjoint, where nothing differentiates them (no autograd recording in either
      mode, no torch.func transform: ``_blocking.unobserved``) and in compiled inference; where
      something does, their tensor code (``mod.inverse_impl``, ``mod.adjoint_impl``) runs and is
      differentiated, whose backward costs less than a second evaluation of it would."""
    op = ops.register(mod)
    n = mod.MATRIX_DIM

    class Compose(FastApply, torch.autograd.Function):
        generate_vmap_rule = True

        @staticmethod
        def forward(A, Bm):
            return op[6](A, Bm)

        @staticmethod
        def setup_context(ctx, inputs, output):
            ctx.save_for_backward(*inputs)
            ctx.save_for_forward(*inputs)

        @staticmethod
        def backward(ctx, grad):
            A, Bm = ctx.saved_tensors
            return compose(grad, Bm.mT), compose(A.mT, grad)

        @staticmethod
        def jvp(ctx, dA, dB):
            A, Bm = ctx.saved_tensors
            if dA is None and dB is None:
                return torch.zeros_like(A)
            if dB is None:
                return compose(dA, Bm)
            return compose(A, dB) if dA is None else compose(dA, Bm) + compose(A, dB)

    Compose.__name__ = Compose.__qualname__ = f"{mod.NAME}Compose"

    def compose(A: torch.Tensor, Bm: torch.Tensor) -> torch.Tensor:
        checks.matrix_pair(A, Bm, n, "A", "B")
        batch = A.shape[:-2] if A.shape[:-2] == Bm.shape[:-2] else checks.broadcast_shapes(
            A.shape[:-2], Bm.shape[:-2])
        # the kernel runs on the CPU only; under autocast the product is torch's (lower precision)
        if batch.numel() < compose_min_batch or A.device.type != "cpu" or torch.is_autocast_enabled("cpu"):
            return A @ Bm
        if is_compiling():
            return op[6](A, Bm) if _compiled_inference(A) else A @ Bm
        if _nested_forward_mode(A) or _nested_forward_mode(Bm):
            return A @ Bm
        if A.shape[:-2] != batch or Bm.shape[:-2] != batch:  # one batch shape for the kernel
            A, Bm = A.expand(*batch, n, n), Bm.expand(*batch, n, n)
        if unobserved((A, Bm)):  # nothing records: the operator, no Function around it
            return op[6](A, Bm)
        return Compose.apply(A, Bm)

    def unary(index, impl, name):
        def apply(M: torch.Tensor) -> torch.Tensor:
            checks.matrix(M, n, "M")
            if is_compiling():
                return op[index](M) if _compiled_inference(M) else impl(M)
            return op[index](M) if unobserved((M,)) else impl(M)

        apply.__name__ = apply.__qualname__ = name
        return apply

    adjoint = unary(7, mod.adjoint_impl, "adjoint")
    inverse = unary(8, mod.inverse_impl, "inverse")
    compose.__doc__ = (f"The {mod.NAME} product A B of (..., {n}, {n}) matrices (batch shapes "
                       f"broadcast); a registered operator for batches of {compose_min_batch} or more.")
    adjoint.__doc__ = "The adjoint matrix " + (mod.adjoint_impl.__doc__ or "").strip() + (
        "; a registered operator where nothing differentiates it.")
    inverse.__doc__ = (f"The {mod.NAME} inverse (..., {n}, {n}); a registered operator where nothing "
                       "differentiates it.")
    compose.__qualname__ = "compose"
    for f in (compose, adjoint, inverse):
        f.__module__ = mod.__name__
    return compose, adjoint, inverse


def checked_backward_parts(mod):
    """The public, checked ``jl_tmv``, ``jl_inv_tmv``, ``exp_pullback`` and ``log_pullback`` of
    ``mod``: the input checks, then the module's unchecked ``_jl_tmv`` etc., which the backward
    passes above call directly (no checks per backward call)."""
    n, dof = mod.MATRIX_DIM, mod.DOF

    def tangent_pair(xi, w, w_name):
        checks.vector(xi, dof, "xi")
        checks.vector(w, dof, w_name)
        checks.binary(xi, 1, w, 1, "xi", w_name)

    def jl_tmv(xi: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        tangent_pair(xi, w, "w")
        return mod._jl_tmv(xi, w)

    def jl_inv_tmv(xi: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
        tangent_pair(xi, g, "g")
        return mod._jl_inv_tmv(xi, g)

    def exp_pullback(M: torch.Tensor, G: torch.Tensor) -> torch.Tensor:
        checks.matrix_pair(M, G, n, "M", "G")
        return mod._exp_pullback(M, G)

    def log_pullback(M: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        checks.matrix(M, n, "M")
        checks.vector(w, dof, "w")
        checks.binary(M, 2, w, 1, "M", "w")
        return mod._log_pullback(M, w)

    out = (jl_tmv, jl_inv_tmv, exp_pullback, log_pullback)
    for f in out:
        f.__module__ = mod.__name__
        f.__doc__ = (getattr(mod, "_" + f.__name__).__doc__ or "").strip() + " Checks its input."
    return out
