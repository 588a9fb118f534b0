"""Batched Cholesky solves of small dense systems as torch operators.

``cholesky_solve(A, R, back)`` factors every symmetric positive definite A = L L^T of a batch
and solves with it: X = L^-1 R, and with ``back`` also Y = L^-T X = A^-1 R.
``triangular_solve(L, R, transpose)`` solves with a factor already at hand: L^-1 R, or L^-T R.
``gram_cholesky_solve(G, d, R, back)`` is ``cholesky_solve`` of A = G diag(d) G^T, the matrix
formed per system inside the kernel (the covariance S = Bm Sigma Bm^T of a Gauss-Helmert
condition with a diagonal Sigma, without the (..., m, p) product G diag(d) and the batched
product of it with G^T in memory).
A failed factorisation (a pivot that is not positive: A not positive definite, or not finite)
reports info = the pivot's row + 1 (LAPACK's ``potrf`` convention; 0 when it succeeds) and
NaN in that matrix's L, X and Y, so a caller tests ``info`` once, without a host read.
Arguments are float32 or float64 tensors of one dtype and device (others: a TypeError).

The estimation engine solves many small systems at once: the normal equations of a batch of
small graphs (``graph.linear_system.DenseSystem``), and the covariance S = B Sigma B^T of every
condition of a Gauss-Helmert factor (``graph.gauss_helmert``).  torch's
``linalg.cholesky_ex`` and ``linalg.solve_triangular`` run LAPACK one matrix at a time on
one thread and copy every batch into column-major order and back; the C kernel of
``_native_cholesky.h`` factors and solves four float64 or eight float32 systems per pass, one
per vector lane (on CPUs with AVX2 twice as many where systems of up to eight unknowns have fewer
than four right-hand sides), with the batch split over ``torch.get_num_threads()`` threads
(``benchmarks/bench_factor_graph.py``, case 6, times it against torch.linalg).

One registration (``functional.registration``, through ``torch.library``) that autograd, ``torch.func`` and
``torch.compile`` all see:

* CPU, float32 or float64, systems of up to ``SMALL_SIZE`` unknowns, or up to
  ``KERNEL_MAX_SIZE`` in batches of at least ``MIN_BATCH``, kernels built and on
  (``functional.native.enabled()``): the C kernel (``uses_kernel``);
* otherwise (other devices, larger systems, kernels off): the tensor code below, torch's
  ``linalg.cholesky_ex`` and ``linalg.solve_triangular`` (the reference the tests compare the
  kernel with);
* derivatives: those of the tensor code, so gradients, forward derivatives and their
  derivatives are those of torch's own Cholesky and triangular solves, in closed form from the
  saved outputs (the backward: ``_cholesky_solve_vjp``, torch's Cholesky backward without a
  second factorisation; the forward derivative: ``_cholesky_jvp``), differentiable again;
  ``cholesky_solve`` and ``triangular_solve`` call the operators through an autograd.Function
  that carries them in reverse and forward mode and under ``torch.func`` transforms (where torch
  2.13 does not apply a custom operator's registered autograd), and the operators directly
  under ``torch.compile`` (their registered autograd); inside two or more forward-mode
  transforms they run the tensor code (torch 2.13 gives an autograd.Function's higher forward
  derivatives wrong, pytorch/pytorch#197867);
* vmap: the systems are independent, the vmapped axis joins the batch;
* fake tensors (torch.compile, meta): shapes only.
"""
from __future__ import annotations

import math

import torch

from .._compat import FastApply
from ..functional import checks, native
from ..functional._autograd import _nested_forward_mode
from ..functional._blocking import is_compiling, unobserved
from ..functional.registration import operator

try:
    from . import _native as _lib  # type: ignore[attr-defined]  # compiled: mypy reads no .so
except ImportError:  # not compiled: the tensor code runs everywhere
    _lib = None

if _lib is not None:
    native.set_constants(_lib)

# The kernel runs systems of up to SMALL_SIZE unknowns, and of up to KERNEL_MAX_SIZE where a batch
# holds at least MIN_BATCH of them (the C loop factors several systems at once, one per vector
# lane); LAPACK's blocked factorisation is faster for larger systems and for a few mid-sized ones.
SMALL_SIZE, KERNEL_MAX_SIZE, MIN_BATCH = 16, 64, 4

__all__ = ["cholesky_solve", "gram_cholesky_solve", "triangular_solve", "uses_kernel", "available"]


def available() -> bool:
    """Whether the C kernel of the dense solves was compiled for this installation."""
    return _lib is not None


def cholesky_solve(A: torch.Tensor, R: torch.Tensor, back: bool = False
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None, torch.Tensor]:
    """(L, X, Y, info) of a batch of symmetric positive definite A (..., m, m) and right-hand
    sides R (..., m, k), batch shapes broadcast: A = L L^T (L lower, its strict upper triangle
    zero), X = L^-1 R, Y = A^-1 R with ``back`` (else None), info (...,) int32 (0, or the row + 1
    of the first pivot that is not positive; that system's L, X and Y are NaN).  Only the lower
    triangle of A is read."""
    checks.boolean(back, "back")
    A, R = _broadcast(A, R, "A", "R")
    if is_compiling() or unobserved((A, R)):  # unobserved: the operator without the Function
        L, X, Y, info = torch.ops.torchsgal.cholesky_solve(A, R, back)
    elif _nested_forward_mode(A) or _nested_forward_mode(R):
        L, X, Y, info = _cholesky_solve_tensor(A, R, back)
    else:
        L, X, Y, info = _CholeskySolve.apply(A, R, back)
    return L, X, Y if back else None, info


def gram_cholesky_solve(G: torch.Tensor, d: torch.Tensor, R: torch.Tensor, back: bool = False
                        ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None, torch.Tensor]:
    """``cholesky_solve(G diag(d) G^T, R, back)`` for G (..., m, p), d (..., p) (positive where
    A is to be positive definite) and R (..., m, k), batch shapes broadcast.  Where nothing
    observes the call (no autograd recording, no torch.func transform, not compiling) it is one
    operator, ``torchsgal::gram_cholesky_solve``, whose CPU kernel forms each A in its vector
    lanes; otherwise the product is formed as tensors and ``cholesky_solve`` takes it (the same
    derivatives)."""
    checks.boolean(back, "back")
    _check_gram(G, d, R)
    if not unobserved((G, d, R)):
        return cholesky_solve((G * d[..., None, :]) @ G.mT, R, back)
    batch = checks.broadcast_shapes(G.shape[:-2], d.shape[:-1], R.shape[:-2])
    L, X, Y, info = torch.ops.torchsgal.gram_cholesky_solve(
        G.expand(batch + G.shape[-2:]), d.expand(batch + d.shape[-1:]), R.expand(batch + R.shape[-2:]),
        back)
    return L, X, Y if back else None, info


def _check_gram(G: torch.Tensor, d: torch.Tensor, R: torch.Tensor) -> None:
    for name, t in (("G", G), ("d", d), ("R", R)):
        checks.floating(t, name)
    checks.same_device_dtype(G=G, d=d, R=R)
    if G.dim() < 2:
        raise ValueError(f"G must have shape (..., m, p), got {tuple(G.shape)}")
    m, p = G.shape[-2:]
    if d.dim() < 1 or d.shape[-1] != p:
        raise ValueError(f"d must have shape (..., p) with p = {p} (G is {tuple(G.shape)}), got "
                         f"{tuple(d.shape)}")
    if R.dim() < 2 or R.shape[-2] != m:
        raise ValueError(f"R must have shape (..., m, k) with m = {m} (G is {tuple(G.shape)}), got "
                         f"{tuple(R.shape)}")
    checks.broadcast_batch(G=G.shape[:-2], d=d.shape[:-1], R=R.shape[:-2])


def triangular_solve(L: torch.Tensor, R: torch.Tensor, transpose: bool = False) -> torch.Tensor:
    """L^-1 R, or L^-T R with ``transpose``, for lower triangular L (..., m, m) with a nonzero
    diagonal and R (..., m, k), batch shapes broadcast (only the lower triangle of L is read)."""
    checks.boolean(transpose, "transpose")
    L, R = _broadcast(L, R, "L", "R")
    if is_compiling() or unobserved((L, R)):  # unobserved: the operator without the Function
        return torch.ops.torchsgal.triangular_solve(L, R, transpose)
    if _nested_forward_mode(L) or _nested_forward_mode(R):
        return _triangular_solve_tensor(L, R, transpose)
    return _TriangularSolve.apply(L, R, transpose)


def _broadcast(M: torch.Tensor, R: torch.Tensor, m_name: str, r_name: str
               ) -> tuple[torch.Tensor, torch.Tensor]:
    _check(M, R, m_name, r_name, same_batch=False)
    batch = checks.broadcast_batch(**{m_name: M.shape[:-2], r_name: R.shape[:-2]})
    return M.expand(batch + M.shape[-2:]), R.expand(batch + R.shape[-2:])


def _check(M, R, m_name: str, r_name: str, same_batch: bool = True) -> None:
    checks.floating(M, m_name)
    checks.floating(R, r_name)
    checks.same_device_dtype(**{m_name: M, r_name: R})
    if M.dim() < 2 or M.shape[-1] != M.shape[-2]:
        raise ValueError(f"{m_name} must have shape (..., m, m), got {tuple(M.shape)}")
    if R.dim() < 2 or R.shape[-2] != M.shape[-1]:
        raise ValueError(f"{r_name} must have shape (..., m, k) with m = {M.shape[-1]} "
                         f"({m_name} is {tuple(M.shape)}), got {tuple(R.shape)}")
    if same_batch and M.shape[:-2] != R.shape[:-2]:
        raise ValueError(f"{m_name} and {r_name} must have the same batch shape, got "
                         f"{tuple(M.shape[:-2])} and {tuple(R.shape[:-2])}")


# ---------------------------------------------------------------------------- tensor code
def _cholesky_solve_tensor(A, R, back: bool):
    L, info = torch.linalg.cholesky_ex(A)
    # LAPACK takes an infinite pivot (sqrt(inf) = inf) and fails, if at all, at a later row: the
    # first pivot that is not finite is the failure here, as in the kernel
    bad = ~torch.isfinite(L.diagonal(dim1=-2, dim2=-1))
    first = torch.where(bad.any(-1), bad.to(torch.int32).argmax(-1) + 1, 0).to(info.dtype)
    info = torch.where((first != 0) & ((info == 0) | (first < info)), first, info)
    L = torch.where((info == 0)[..., None, None], L, float("nan")).contiguous()  # row-major
    X = torch.linalg.solve_triangular(L, R, upper=False).contiguous()
    Y = (torch.linalg.solve_triangular(L.mT, X, upper=True).contiguous() if back
         else R.new_empty(R.shape[:-1] + (0,)))
    return L, X, Y, info.to(torch.int32)


def _triangular_solve_tensor(L, R, transpose: bool):
    return torch.linalg.solve_triangular(L.mT if transpose else L, R, upper=transpose).contiguous()


def uses_kernel(M: torch.Tensor) -> bool:
    """Whether the operators run the C kernel for systems M (..., m, m) on the CPU now: float32 or
    float64, the size rule above, kernels built and on in the calling thread."""
    return _kernel_for(M.shape[-1], math.prod(M.shape[:-2]), M)


def _kernel_for(m: int, systems: int, like: torch.Tensor) -> bool:
    """``uses_kernel`` for ``systems`` systems of m unknowns on ``like``'s device and dtype."""
    return (_lib is not None and native.enabled() and like.device.type == "cpu"
            and like.dtype in (torch.float32, torch.float64)
            and (m <= SMALL_SIZE or m <= KERNEL_MAX_SIZE and systems >= MIN_BATCH))


# ---------------------------------------------------------------------------- cholesky_solve
@operator("torchsgal::cholesky_solve",
          schema="(Tensor A, Tensor R, bool back) -> (Tensor, Tensor, Tensor, Tensor)")
def _cholesky_solve_op(A: torch.Tensor, R: torch.Tensor, back: bool):
    """(L, X, Y, info); Y (..., m, 0) without ``back`` (module docstring)."""
    _check(A, R, "A", "R")
    return _cholesky_solve_tensor(A, R, back)


@_cholesky_solve_op.register_kernel("cpu")
def _cholesky_solve_cpu(A, R, back):
    _check(A, R, "A", "R")
    if not uses_kernel(A):
        return _cholesky_solve_tensor(A, R, back)
    batch, m, k = A.shape[:-2], A.shape[-1], R.shape[-1]
    A, R = A.resolve_neg().contiguous(), R.resolve_neg().contiguous()
    L, X = torch.empty_like(A), torch.empty_like(R)
    Y = torch.empty_like(R) if back else R.new_empty(batch + (m, 0))
    info = torch.empty(batch, dtype=torch.int32)
    _lib.cholesky_solve(A.data_ptr(), R.data_ptr(), L.data_ptr(), X.data_ptr(),
                        Y.data_ptr() if back else 0, info.data_ptr(), info.numel(), m, k, True,
                        torch.get_num_threads(), A.dtype is torch.float64)
    return L, X, Y, info


@_cholesky_solve_op.register_fake
def _cholesky_solve_fake(A, R, back):
    _check(A, R, "A", "R")  # contiguous outputs, whatever the inputs' strides
    Y = R.new_empty(R.shape) if back else R.new_empty(R.shape[:-1] + (0,))
    return A.new_empty(A.shape), R.new_empty(R.shape), Y, A.new_empty(A.shape[:-2], dtype=torch.int32)


def _cholesky_solve_setup(ctx, inputs, output):
    ctx.mark_non_differentiable(output[3])
    ctx.save_for_backward(*output[:3])


def _cholesky_solve_backward(ctx, gL, gX, gY, _ginfo):
    return (*_cholesky_solve_vjp(*ctx.saved_tensors, gL, gX, gY), None)


_cholesky_solve_op.register_autograd(_cholesky_solve_backward, setup_context=_cholesky_solve_setup)


@_cholesky_solve_op.register_vmap
def _cholesky_solve_vmap(info, in_dims, A, R, back):
    A, R = _batched_front(info.batch_size, (A, R), in_dims[:2])
    return _cholesky_solve_op(A, R, back), (0, 0, 0, 0)


# ---------------------------------------------------------------------------- gram_cholesky_solve
def _gram_tensor(G, d, R, back: bool):
    return _cholesky_solve_tensor((G * d[..., None, :]) @ G.mT, R, back)


@operator("torchsgal::gram_cholesky_solve",
          schema="(Tensor G, Tensor d, Tensor R, bool back) -> (Tensor, Tensor, Tensor, Tensor)")
def _gram_cholesky_solve_op(G: torch.Tensor, d: torch.Tensor, R: torch.Tensor, back: bool):
    """(L, X, Y, info) of cholesky_solve(G diag(d) G^T, R, back); G (..., m, p), d (..., p) and
    R (..., m, k) of one batch shape; Y (..., m, 0) without ``back``."""
    _check_gram_same(G, d, R)
    return _gram_tensor(G, d, R, back)


def _check_gram_same(G, d, R) -> None:
    _check_gram(G, d, R)
    if not G.shape[:-2] == d.shape[:-1] == R.shape[:-2]:
        raise ValueError(f"G, d and R must have the same batch shape, got {tuple(G.shape[:-2])}, "
                         f"{tuple(d.shape[:-1])} and {tuple(R.shape[:-2])}")


@_gram_cholesky_solve_op.register_kernel("cpu")
def _gram_cholesky_solve_cpu(G, d, R, back):
    _check_gram_same(G, d, R)
    m, p, k = G.shape[-2], G.shape[-1], R.shape[-1]
    batch = G.shape[:-2]
    if not _kernel_for(m, math.prod(batch), G):
        return _gram_tensor(G, d, R, back)
    shared = d.dim() >= 1 and all(st == 0 for st in d.stride()[:-1])
    d_used = d[(0,) * (d.dim() - 1)][None] if shared and d.shape[:-1].numel() else d
    G, R = G.resolve_neg().contiguous(), R.resolve_neg().contiguous()
    d_used = d_used.resolve_neg().contiguous()
    L = G.new_empty(batch + (m, m))
    X = torch.empty_like(R)
    Y = torch.empty_like(R) if back else R.new_empty(batch + (m, 0))
    info = torch.empty(batch, dtype=torch.int32)
    _lib.gram_cholesky_solve(G.data_ptr(), d_used.data_ptr(), R.data_ptr(), L.data_ptr(),
                             X.data_ptr(), Y.data_ptr() if back else 0, info.data_ptr(),
                             info.numel(), m, p, k, 0 if shared else p, torch.get_num_threads(),
                             G.dtype is torch.float64)
    return L, X, Y, info


@_gram_cholesky_solve_op.register_fake
def _gram_cholesky_solve_fake(G, d, R, back):
    _check_gram_same(G, d, R)
    m = G.shape[-2]
    Y = R.new_empty(R.shape) if back else R.new_empty(R.shape[:-1] + (0,))
    return (G.new_empty(G.shape[:-2] + (m, m)), R.new_empty(R.shape), Y,
            G.new_empty(G.shape[:-2], dtype=torch.int32))


def _gram_setup(ctx, inputs, output):
    G, d, _, _ = inputs
    ctx.mark_non_differentiable(output[3])
    ctx.save_for_backward(G, d, *output[:3])


def _gram_backward(ctx, gL, gX, gY, _ginfo):
    """gA, gR of ``cholesky_solve``; then A = G D G^T with gA symmetric: gG = 2 gA G D,
    gd = diag(G^T gA G)."""
    G, d, L, X, Y = ctx.saved_tensors
    gA, gR = _cholesky_solve_vjp(L, X, Y, gL, gX, gY)
    gAG = gA @ G
    return 2.0 * gAG * d[..., None, :], (gAG * G).sum(-2), gR, None


_gram_cholesky_solve_op.register_autograd(_gram_backward, setup_context=_gram_setup)


@_gram_cholesky_solve_op.register_vmap
def _gram_cholesky_solve_vmap(info, in_dims, G, d, R, back):
    G, d, R = _batched_front(info.batch_size, (G, d, R), in_dims[:3], tails=(2, 1, 2))
    return _gram_cholesky_solve_op(G, d, R, back), (0, 0, 0, 0)


# ---------------------------------------------------------------------------- triangular_solve
@operator("torchsgal::triangular_solve",
          schema="(Tensor L, Tensor R, bool transpose) -> Tensor")
def _triangular_solve_op(L: torch.Tensor, R: torch.Tensor, transpose: bool) -> torch.Tensor:
    """L^-1 R or L^-T R (module docstring)."""
    _check(L, R, "L", "R")
    return _triangular_solve_tensor(L, R, transpose)


@_triangular_solve_op.register_kernel("cpu")
def _triangular_solve_cpu(L, R, transpose):
    _check(L, R, "L", "R")
    if not uses_kernel(L):
        return _triangular_solve_tensor(L, R, transpose)
    m, k = L.shape[-1], R.shape[-1]
    L, R = L.resolve_neg().contiguous(), R.resolve_neg().contiguous()
    X = torch.empty_like(R)
    _lib.triangular_solve(L.data_ptr(), R.data_ptr(), X.data_ptr(), math.prod(L.shape[:-2]), m, k,
                          transpose, True, torch.get_num_threads(), L.dtype is torch.float64)
    return X


@_triangular_solve_op.register_fake
def _triangular_solve_fake(L, R, transpose):
    _check(L, R, "L", "R")
    return R.new_empty(R.shape)  # contiguous, whatever the inputs' strides


def _triangular_solve_setup(ctx, inputs, output):
    ctx.transpose = inputs[2]
    ctx.save_for_backward(inputs[0], output)


def _triangular_solve_backward(ctx, gX):
    return (*_triangular_solve_vjp(*ctx.saved_tensors, gX, ctx.transpose), None)


_triangular_solve_op.register_autograd(_triangular_solve_backward,
                                       setup_context=_triangular_solve_setup)


@_triangular_solve_op.register_vmap
def _triangular_solve_vmap(info, in_dims, L, R, transpose):
    L, R = _batched_front(info.batch_size, (L, R), in_dims[:2])
    return _triangular_solve_op(L, R, transpose), 0


def _batched_front(size: int, args, in_dims, tails=None):
    """The arguments with the vmapped axis in front (unbatched ones expanded) and their batch
    shapes broadcast; ``tails``: each argument's number of non-batch axes (default 2)."""
    tails = tails or (2,) * len(args)
    moved = [a.unsqueeze(0).expand(size, *a.shape) if d is None else a.movedim(d, 0)
             for a, d in zip(args, in_dims)]
    batch = checks.broadcast_shapes(*(a.shape[:a.dim() - t] for a, t in zip(moved, tails)))
    return [a.expand(batch + a.shape[a.dim() - t:]) for a, t in zip(moved, tails)]


# ---------------------------------------------------------------------------- autograd.Functions
def _solve_lower(L, B, transpose: bool = False):
    return torch.linalg.solve_triangular(L.mT if transpose else L, B, upper=transpose)


def _solve_small(L, B, transpose: bool = False):
    """L^-1 B or L^-T B in a backward: ``triangular_solve`` (its kernel; differentiable, so
    second derivatives follow) for systems of up to SMALL_SIZE unknowns, torch's solves for
    larger ones, where the backward's m right-hand sides make LAPACK's blocked solves faster
    (``benchmarks/bench_factor_graph.py``, case 6)."""
    if L.shape[-1] <= SMALL_SIZE:
        return triangular_solve(L, B, transpose)
    return _solve_lower(L, B, transpose)


def _cholesky_solve_vjp(L, X, Y, gL, gX, gY):
    """(gA, gR) of (L, X, Y) = (chol(A), L^-1 R, L^-T X) from the outputs, the gradients of the
    tensor code (torch's Cholesky and triangular solves) without factoring A again:
    Y: u = L^-1 gY joins gX, gL -= Y u^T; X: gR = L^-T gX, gL -= gR X^T; L: torch's
    cholesky_backward, gA = L^-T sym(tril(L^T gL)) L^-1 (sym: half the diagonal, the strict lower
    triangle mirrored), symmetric (Murray 2016, arXiv:1602.07527).  None stands for zero."""
    gL = torch.zeros_like(L) if gL is None else gL
    gX = torch.zeros_like(X) if gX is None else gX
    if gY is not None and Y.shape[-1]:
        u = _solve_small(L, gY)
        gX = gX + u
        gL = gL - Y @ u.mT
    gR = _solve_small(L, gX, transpose=True)
    gL = gL - gR @ X.mT
    P = (L.mT @ gL).tril()
    P = 0.5 * (P + P.tril(-1).mT)
    gA = _solve_small(L, P, transpose=True)  # L^-T P, then (L^-T (L^-T P)^T)^T = . L^-1
    return _solve_small(L, gA.mT, transpose=True).mT, gR


def _triangular_solve_vjp(L, X, gX, transpose: bool):
    """(gL, gR) of X = L^-1 R (or L^-T R) from L and X, torch's solve_triangular backward:
    gR = L^-T gX (or L^-1 gX) and gL = -tril(gR X^T) (or -tril(X gR^T)).  None: zero."""
    if gX is None:
        return torch.zeros_like(L), torch.zeros_like(X)
    gR = _solve_small(L, gX, not transpose)
    return (-(X @ gR.mT if transpose else gR @ X.mT)).tril(), gR


def _cholesky_jvp(L, X, Y, dA, dR):
    """(dL, dX, dY) of L = chol(A), X = L^-1 R, Y = L^-T X: torch's forward derivative of the
    Cholesky factor, dL = L Phi(L^-1 dA L^-T) (Phi: the lower triangle, half the diagonal),
    then L dX = dR - dL X and L^T dY = dX - dL^T Y."""
    P = torch.linalg.solve_triangular(L.mT, _solve_lower(L, dA), upper=True, left=False)
    P = P.tril() - 0.5 * torch.diag_embed(P.diagonal(dim1=-2, dim2=-1))
    dL = L @ P
    dX = _solve_lower(L, dR - dL @ X)
    dY = _solve_lower(L, dX - dL.mT @ Y, transpose=True) if Y.shape[-1] else torch.zeros_like(Y)
    return dL, dX, dY


class _CholeskySolve(FastApply, torch.autograd.Function):
    """``torchsgal::cholesky_solve`` with the tensor code's derivatives (module docstring)."""

    generate_vmap_rule = True

    @staticmethod
    def forward(A, R, back):
        return torch.ops.torchsgal.cholesky_solve(A, R, back)

    @staticmethod
    def setup_context(ctx, inputs, output):
        A, R, back = inputs
        ctx.back = back
        ctx.mark_non_differentiable(output[3])
        ctx.save_for_backward(*output[:3])
        ctx.save_for_forward(*output[:3])

    @staticmethod
    def backward(ctx, gL, gX, gY, _ginfo):
        return (*_cholesky_solve_vjp(*ctx.saved_tensors, gL, gX, gY), None)

    @staticmethod
    def jvp(ctx, tA, tR, _tback):
        L, X, Y = ctx.saved_tensors
        tA = torch.zeros_like(L) if tA is None else tA
        tR = torch.zeros_like(X) if tR is None else tR
        return (*_cholesky_jvp(L, X, Y, tA, tR), None)


class _TriangularSolve(FastApply, torch.autograd.Function):
    """``torchsgal::triangular_solve`` with the tensor code's derivatives."""

    generate_vmap_rule = True

    @staticmethod
    def forward(L, R, transpose):
        return torch.ops.torchsgal.triangular_solve(L, R, transpose)

    @staticmethod
    def setup_context(ctx, inputs, output):
        L, R, transpose = inputs
        ctx.transpose = transpose
        ctx.save_for_backward(L, output)
        ctx.save_for_forward(L, output)

    @staticmethod
    def backward(ctx, gX):
        return (*_triangular_solve_vjp(*ctx.saved_tensors, gX, ctx.transpose), None)

    @staticmethod
    def jvp(ctx, tL, tR, _ttranspose):
        # L X = R (or L^T X = R), only L's lower triangle read: dX = L^-1 (dR - tril(dL) X)
        L, X = ctx.saved_tensors
        dR = torch.zeros_like(X) if tR is None else tR
        if tL is not None:
            dL = tL.tril()
            dR = dR - (dL.mT if ctx.transpose else dL) @ X
        return _solve_lower(L, dR, ctx.transpose)
