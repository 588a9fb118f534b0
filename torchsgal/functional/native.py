"""The package's optional C kernels: their switches and constants.

``torchsgal.functional._native`` holds SGal(3) exp, log, their backward maps and Jacobians, and
the exp, log and Jacobians of SO(3), SE(2), SE(3), SE_2(3) and Sim(3): the CPU implementations of
the torch operators ``torchsgal::sgal3_*``, ``so3_*``, ``se2_*``, ``se3_*``, ``se23_*`` and
``sim3_*`` (``functional/ops.py``), and ``torchsgal::affine_rows`` (``functional/affine.py``: a
group element acting on many points, and that action's Jacobian);
``torchsgal.imu._native`` holds IMU preintegration, the CPU implementation of
``torchsgal::imu_preintegrate`` (``imu/_kernels.py``).

In eager CPU code a closed form written as tensor operations pays torch's per-operation
dispatch (~2 us) about 170 times for SGal(3) exp, whatever the batch size; at 1e3 elements that
overhead is most of the time.  The C kernels evaluate the same closed forms one element at a
time in one call: the same thresholds and series (passed from ``numerics`` at import by
``set_constants``, so ``numerics`` stays their only source), the same branches and, term by
term, the same arithmetic, so the two agree to rounding (tests/test_native.py compares them at
every angle band, both dtypes).  The tensor code remains the reference implementation, and the
operators run it wherever a kernel does not apply (other devices, kernels off or not built).
Batches of at least 16,384 elements are handed out in chunks to ``torch.get_num_threads()``
threads (a thread that loses its core to another process takes fewer; _native_common.h):
torch's own OpenMP threads where torch runs on OpenMP (``parallel_backend()`` of the module
says "openmp"; other threads would compete with their spin-wait after torch's last parallel
operation), else the kernels' own pool of POSIX threads (``TORCHSGAL_NATIVE_OPENMP=0`` in the
environment chooses it): helpers that sleep between calls, of which a call waits only for those
that took a chunk (a helper whose core another process holds takes none; docs/guide/threads.md
compares the two beside a busy process).

On CUDA the operators can run their closed forms compiled by ``torch.compile`` (inductor's
Triton kernels; ``functional/ops.py``): an opt-in, ``use_compiled_cuda(True)`` or
``TORCHSGAL_COMPILED_CUDA=1`` in the environment, as each operator's first call per dtype
compiles for seconds (docs/guide/acceleration.md has the measured trade-off).

The extensions are built by ``pip install`` where a C compiler is found and skipped otherwise
(``available()`` tells).  ``TORCHSGAL_NATIVE=0`` in the environment turns every kernel off in
the whole process, the compiled CUDA path too; the ``disabled()`` context manager turns them off
in the calling thread only, for the duration of its block (the operators then run the eager
tensor code there).
"""
from __future__ import annotations

import contextlib
import math
import os
import threading
from types import ModuleType

from . import numerics

try:
    from . import _native as _lib  # type: ignore[attr-defined]  # compiled: mypy reads no .so
except ImportError:  # not compiled: the tensor code runs everywhere
    _lib = None

ENV_VAR = "TORCHSGAL_NATIVE"
COMPILED_CUDA_ENV_VAR = "TORCHSGAL_COMPILED_CUDA"
# The process-wide setting (compiled, and not turned off by the environment) ...
_state = {"on": _lib is not None and os.environ.get(ENV_VAR, "1") != "0",
          # ... and the opt-in compiled closed forms that run the operators on CUDA
          "compiled": os.environ.get(COMPILED_CUDA_ENV_VAR) == "1",
          "env_off": os.environ.get(ENV_VAR, "1") == "0"}
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
                      [1.0 / math.factorial(m) for m in range(7)], list(numerics.JINV_SERIES),
                      numerics.SCALE_UPWARD_MARGIN, numerics.SCALE_EXTRA_ORDERS, numerics.SCALE_TAYLOR_TERMS,
                      numerics.SIM3_SERIES_THRESHOLD, numerics.SIM3_SERIES_TERMS, numerics.SIM3_NORMALISE,
                      [1.0 / math.factorial(j) for j in range(33)])


if _lib is not None:
    set_constants(_lib)


def available() -> bool:
    """Whether the C kernels were compiled for this installation."""
    return _lib is not None


def enabled() -> bool:
    """Whether eligible calls of the calling thread use the C kernels now (``available()``,
    not turned off by the environment, and not inside a ``disabled()`` block of this thread)."""
    return _state["on"] and not getattr(_thread, "off", False)


def compiled_enabled() -> bool:
    """Whether the operators of the calling thread run their compiled closed forms on the
    devices that have them (CUDA, ``functional/ops.py``): chosen (``use_compiled_cuda``), and
    not inside a ``disabled()`` block of this thread."""
    return _state["compiled"] and not _state["env_off"] and not getattr(_thread, "off", False)


def use_compiled_cuda(enabled: bool) -> None:
    """Process-wide: whether the SGal(3) operators run their closed forms compiled by
    ``torch.compile`` on CUDA float32 tensors (default False; ``TORCHSGAL_COMPILED_CUDA=1`` in
    the environment turns it on at import).  float64 stays on the eager closed forms.

    Compiled, an operator call on CUDA launches 14-49 Triton kernels instead of 126-549, and
    ``SGal3.exp`` is 2.1-2.4x faster per call from 1e3 to 1e6 float32 elements on an H200; each
    operator's first call per dtype compiles for seconds (up to ~46 s for exp+log with their
    backward; torch's on-disk caches shorten later processes).  It pays for long jobs.
    ``disabled()`` still turns it off per thread, and ``TORCHSGAL_NATIVE=0`` for the whole
    process."""
    from .checks import boolean

    _state["compiled"] = boolean(enabled, "enabled")


@contextlib.contextmanager
def disabled():
    """Run the eager tensor code everywhere inside the block (no C kernel, no compiled closed
    form), in the calling thread only (other
    threads keep their own choice; a thread started inside the block does not inherit it).
    Blocks nest: leaving one restores the state it found (tests and benchmarks compare the two
    paths)."""
    before = getattr(_thread, "off", False)
    _thread.off = True
    try:
        yield
    finally:
        _thread.off = before
