"""Optional C kernels: SGal(3) exp, log and their backward maps and the SGal(3) TLS linearisation,
on CPU (``_native.c``); and the switches and constants of every C kernel of the package (the IMU
preintegration kernel, ``torchsgal.imu._native``, is registered as a torch operator in
``torchsgal.imu._kernels`` and follows ``enabled()`` too).

In eager CPU code a closed form written as tensor operations pays torch's per-operation
dispatch (~2 us) about 170 times for SGal(3) exp, whatever the batch size; at 1e3 elements that
overhead is most of the time.  The C kernels evaluate the same closed forms one element at a
time in one call: the same thresholds and series (passed from ``numerics`` at import, which
stays their only source), the same branches and, term by term, the same arithmetic, so the two
agree to rounding (tests/test_native.py compares them at every angle band, both dtypes).  The
tensor code remains the reference implementation and the differentiable one.

They are used by ``functional.sgal3.exp``/``log`` (and so ``SGal3.exp``, ``g.log()``, ``rplus``
...) and by those functions' custom backward, only where the call cannot be observed
(``unobserved``: plain CPU tensors, nothing recording autograd, no torch.func transform, not
compiling) and every argument has the same batch shape; everywhere else, and on other devices,
the tensor code runs.  Batches of at least 16,384 elements are split over
``torch.get_num_threads()`` threads: torch's own OpenMP threads where torch runs on OpenMP
(``parallel_backend()`` of the module says "openmp"; fresh threads would compete with their
spin-wait after torch's last parallel operation), else POSIX threads
(``TORCHSGAL_NATIVE_OPENMP=0`` in the environment forces them).

``kernels("tls")`` linearises the SGal(3) total-least-squares
conditions and updates their residuals (``torchsgal.estimation.tls._structured``, float64,
docs/guide/estimation.md), four conditions at a time, keeping its per-condition state packed.

The extensions are built by ``pip install`` where a C compiler is found and skipped otherwise
(``available()`` tells).  ``TORCHSGAL_NATIVE=0`` in the environment turns every kernel off in
the whole process; the ``disabled()`` context manager turns them off in the calling thread
only, for the duration of its block (the tensor code then runs there).
"""
from __future__ import annotations

import contextlib
import math
import os
import threading
from types import ModuleType

import torch

from . import numerics
from ._blocking import is_compiling, unobserved

try:
    from . import _native as _lib  # type: ignore[attr-defined]  # compiled: mypy reads no .so
except ImportError:  # not compiled: the tensor code runs everywhere
    _lib = None

ENV_VAR = "TORCHSGAL_NATIVE"
# The process-wide setting (compiled, and not turned off by the environment) ...
_state = {"on": _lib is not None and os.environ.get(ENV_VAR, "1") != "0"}
# ... and the switch of ``disabled()``, per thread: a block in one thread leaves the kernel
# choice of the others alone.
_thread = threading.local()


def set_constants(lib: ModuleType) -> None:
    """Give a compiled kernel module (``functional._native``, ``imu._native``: each holds its own
    copy, _native_common.h) the thresholds and series of ``numerics``, their only source."""
    def taylor(m):  # the series of c_m used by numerics.series_coefficients
        return [(-1.0) ** k / math.factorial(2 * k + m) for k in range(numerics.TAYLOR_TERMS)]

    lib.set_constants(numerics.SERIES_THRESHOLD, numerics.JINV_THRESHOLD,
                      numerics.LOG_SYMMETRIC_COS, numerics.LOG_SIN_TAYLOR,
                      taylor(3), taylor(4), taylor(5), taylor(6),
                      [1.0 / math.factorial(m) for m in range(7)], list(numerics.JINV_SERIES))


if _lib is not None:
    set_constants(_lib)


def available() -> bool:
    """Whether the C kernels were compiled for this installation."""
    return _lib is not None


def enabled() -> bool:
    """Whether eligible calls of the calling thread use the C kernels now (``available()``,
    not turned off by the environment, and not inside a ``disabled()`` block of this thread)."""
    return _state["on"] and not getattr(_thread, "off", False)


@contextlib.contextmanager
def disabled():
    """Run the tensor code everywhere inside the block, in the calling thread only (other
    threads keep their own choice; a thread started inside the block does not inherit it).
    Blocks nest: leaving one restores the state it found (tests and benchmarks compare the two
    paths)."""
    before = getattr(_thread, "off", False)
    _thread.off = True
    try:
        yield
    finally:
        _thread.off = before


def _eligible(args) -> bool:
    if not _state["on"] or is_compiling():  # compiled graphs run the tensor code
        return False
    dtype = args[0].dtype
    return (not getattr(_thread, "off", False) and all(a.dtype is dtype for a in args)
            and unobserved(args))


def _data(t: torch.Tensor) -> torch.Tensor:
    """A contiguous tensor whose memory holds t's values (no lazy negation)."""
    return t.resolve_neg().contiguous()


def _run(fn, inputs, batch, event):
    """fn over the batch: contiguous inputs, a fresh output (*batch, *event) of their dtype."""
    ins = [_data(t) for t in inputs]
    dtype = ins[0].dtype
    out = torch.empty(batch + event, dtype=dtype)
    fn(*(t.data_ptr() for t in ins), out.data_ptr(), math.prod(batch), torch.get_num_threads(),
       dtype is torch.float64)
    return out


class _SGal3Kernels:
    """exp, log and their backward maps for the custom autograd Functions of sgal3 (each returns
    None where the C kernels may not run: the caller then runs the tensor code)."""

    @staticmethod
    def exp(xi: torch.Tensor):
        if not _eligible((xi,)):
            return None
        return _run(_lib.sgal3_exp, (xi,), xi.shape[:-1], (5, 5))

    @staticmethod
    def log(M: torch.Tensor):
        if not _eligible((M,)):
            return None
        return _run(_lib.sgal3_log, (M,), M.shape[:-2], (10,))

    @staticmethod
    def exp_vjp(xi: torch.Tensor, M: torch.Tensor, G: torch.Tensor):
        """J_r(xi)^T hat^T(M^T G), exp's backward (same batch shapes only)."""
        if not (xi.shape[:-1] == M.shape[:-2] == G.shape[:-2] and _eligible((xi, M, G))):
            return None
        return _run(_lib.sgal3_exp_vjp, (xi, M, G), xi.shape[:-1], (10,))

    @staticmethod
    def log_vjp(M: torch.Tensor, xi: torch.Tensor, g: torch.Tensor):
        """M^-T vee^T(J_r(xi)^-T g), log's backward (same batch shapes only)."""
        if not (xi.shape[:-1] == M.shape[:-2] == g.shape[:-1] and _eligible((M, xi, g))):
            return None
        return _run(_lib.sgal3_log_vjp, (M, xi, g), M.shape[:-2], (5, 5))


class _TlsKernels:
    """The structured linearisation of the SGal(3) TLS conditions
    (torchsgal.estimation.tls._structured), float64 only (``_native_tls.h``).

    What the residual update needs is kept packed, in the kernel's layout: R (K, NB, 75, LANES)
    and W (K, NB, NW, LANES) for NB = ceil(N1 / LANES) blocks of LANES conditions (``shapes``;
    ``unpack`` restores the dense rows and whitened Jacobians of the tensor code)."""

    LANES = 4  # NL of _native_tls.h
    _LO = (0, 0, 0, 3, 3, 3, 6, 6, 6, 9)  # TLS_LO, TLS_HI: W's row i can be non-zero in [LO, HI)
    _HI = (10, 10, 10, 9, 9, 9, 9, 9, 9, 10)

    @staticmethod
    def applies(*tensors) -> bool:
        """Whether a linearisation of these (float64) tensors would run in C now."""
        return tensors[0].dtype is torch.float64 and _eligible(tensors)

    @staticmethod
    def _w_entries(diagonal_a: bool, diagonal_b: bool) -> list:
        """(i, column of W) of the packed W's entries, in order (tls_w_layout)."""
        return [(i, 10 * h + j) for h, diag in enumerate((diagonal_a, diagonal_b)) for i in range(10)
                for j in range(_TlsKernels._LO[i] if diag else 0, _TlsKernels._HI[i])]

    @staticmethod
    def shapes(K: int, N1: int, diagonal_a: bool, diagonal_b: bool) -> tuple:
        """The shapes of the packed R and W of K trials of N1 conditions."""
        NB, L = -(-N1 // _TlsKernels.LANES), _TlsKernels.LANES
        return (K, NB, 75, L), (K, NB, len(_TlsKernels._w_entries(diagonal_a, diagonal_b)), L)

    @staticmethod
    def unpack(R, W, N1: int, diagonal_a: bool, diagonal_b: bool) -> tuple:
        """The dense rows [Li, n Li a, Li w] (K, N1 10, 12) and W (K, N1, 10, 20) of packed ones."""
        K = R.shape[0]
        lanes = lambda P: P.transpose(-1, -2).reshape(K, -1, P.shape[-2])[:, :N1]  # (K, N1, entries)
        Rl, Wl = lanes(R), lanes(W)
        i, j = torch.tril_indices(10, 10)
        Rd = R.new_zeros(K, N1, 10, 12)
        Rd[..., i, j] = Rl[..., :55]
        Rd[..., 10] = Rl[..., 55:65]
        Rd[..., 11] = Rl[..., 65:75]
        i, j = torch.tensor(_TlsKernels._w_entries(diagonal_a, diagonal_b)).T
        Wd = W.new_zeros(K, N1, 10, 20)
        Wd[..., i, j] = Wl
        return Rd.reshape(K, N1 * 10, 12), Wd

    @staticmethod
    def linearise(M, X, Ad_Xinv, a, s, n, e, factors, R, W, active=None):
        """Fill the packed R and W (``shapes``) and return (G (K, 12, 12), info (K, N1)); None
        where the kernel may not run.  M (K, N1, 5, 5), X (K, 5, 5), Ad_Xinv (K, 10, 10), a (K, 10),
        s (K, N1), n (N1,), e (K, N1, 20) or None (the paper variant), factors ((fa, diagonal_a),
        (fb, diagonal_b)): square-root diagonals (..., 10) or lower Cholesky factors
        (..., 10, 10) broadcasting to (K, N1).  active (K,) bool or None (all): the trials to
        linearise; the others get G = 0 and info = 0, and their R and W are left as they are."""
        K, N1 = s.shape
        args = [M, X, Ad_Xinv, a, s, n] + ([] if e is None else [e]) + [f for f, _ in factors]
        if not (args[0].dtype is torch.float64 and _eligible(args)
                and _TlsKernels._buffers(R, W, K, N1, factors)):
            return None
        fs = _TlsKernels._factors(factors, K, N1)
        if fs is None:
            return None
        ins = [_data(t) for t in (M, X, Ad_Xinv, a, s, n)]
        e = None if e is None else _data(e)
        active = _TlsKernels._active(active, K)
        G = torch.empty(K, 12, 12, dtype=torch.float64)
        info = torch.empty(K, N1, dtype=torch.int32)
        _lib.tls_sgal3(*(t.data_ptr() for t in ins), 0 if e is None else e.data_ptr(),
                       fs[0].data_ptr(), fs[1].data_ptr(), R.data_ptr(), W.data_ptr(),
                       G.data_ptr(), info.data_ptr(), 0 if active is None else active.data_ptr(),
                       fs[0].stride(0), fs[0].stride(1),
                       fs[1].stride(0), fs[1].stride(1), int(factors[0][1]), int(factors[1][1]),
                       K, N1, torch.get_num_threads())
        return G, info

    @staticmethod
    def step(R, W, dx, factors, N1: int, active=None, out=None):
        """post_step's residual update e (K, N1, 20) = -Sigma Bm'^T Li^T (R [dx, 1]) from the
        packed R and W of ``linearise`` and dx (K, 11); None where the kernel may not run.
        active (K,) bool or None (all): the trials to update; the others get e = 0.  out: a
        contiguous float64 (K, N1, 20) to write e into (else a new tensor)."""
        K = R.shape[0]
        args = [R, W, dx] + [f for f, _ in factors]
        if not (R.dtype is torch.float64 and _eligible(args) and _TlsKernels._buffers(R, W, K, N1, factors)
                and dx.shape == (K, 11)):
            return None
        fs = _TlsKernels._factors(factors, K, N1)
        if fs is None:
            return None
        dx = _data(dx)
        active = _TlsKernels._active(active, K)
        e = out if out is not None and out.shape == (K, N1, 20) and out.dtype is torch.float64 \
            and out.is_contiguous() and out.device.type == "cpu" else torch.empty(K, N1, 20, dtype=torch.float64)
        _lib.tls_sgal3_step(R.data_ptr(), W.data_ptr(), dx.data_ptr(), fs[0].data_ptr(),
                            fs[1].data_ptr(), e.data_ptr(), 0 if active is None else active.data_ptr(),
                            fs[0].stride(0), fs[0].stride(1),
                            fs[1].stride(0), fs[1].stride(1), int(factors[0][1]), int(factors[1][1]),
                            K, N1, torch.get_num_threads())
        return e

    @staticmethod
    def _active(active, K):
        """The trial mask as contiguous bytes (K,), or None (all trials)."""
        if active is None:
            return None
        if active.shape != (K,) or active.dtype is not torch.bool:
            raise ValueError(f"active: expected a bool tensor of shape ({K},), got {active.dtype} "
                             f"{tuple(active.shape)}")
        return active.contiguous().view(torch.uint8)

    @staticmethod
    def _buffers(R, W, K, N1, factors) -> bool:
        shapes = _TlsKernels.shapes(K, N1, bool(factors[0][1]), bool(factors[1][1]))
        return (R.is_contiguous() and W.is_contiguous() and not R.is_neg() and not W.is_neg()
                and R.dtype is W.dtype is torch.float64 and (R.shape, W.shape) == shapes
                and R.data_ptr() % 16 == 0 and W.data_ptr() % 16 == 0)  # streaming stores

    @staticmethod
    def _factors(factors, K, N1):
        """The covariance factors expanded to (K, N1, 10[, 10]) (stride-0 views where they are
        shared), their last dimensions contiguous; None for a shape the kernel does not take."""
        fs = []
        for f, diagonal in factors:
            tail = (10,) if diagonal else (10, 10)
            if f.shape[-len(tail):] != tail or f.dim() > len(tail) + 2:
                return None
            f = f.resolve_neg()
            if f.stride()[-len(tail):] != torch.empty(tail).stride():
                f = f.contiguous()
            try:
                fs.append(f.expand(K, N1, *tail))
            except RuntimeError:
                return None
        return fs


def kernels(name: str):
    """The C kernels of ``name`` ("SGal3", "tls"), or None (not compiled, or no kernels; the IMU
    kernel is the operator ``torch.ops.torchsgal.imu_preintegrate``, torchsgal.imu._kernels)."""
    if _lib is None:
        return None
    return {"SGal3": _SGal3Kernels, "tls": _TlsKernels}.get(name)
