"""Process settings for long batched runs: thread counts for a shared machine, and the C
allocator's handling of large blocks.

torch's intra-op threads wait for each other at the end of every parallel operation: where
another busy process holds one of the cores, each such operation waits for the thread that lost
its core, and a multi-threaded run can take twice the time of a single-threaded one or more.
``threads_for_load`` picks a thread count from the cores that are idle now: every core on an
idle machine, one fewer for each core another process keeps busy, never fewer than one.  The
command line (``python -m torchsgal tls``) uses it unless ``--threads`` is given; a program
calls ``use_threads_for_load()`` once, where it starts, to the same end.  It samples the load
once, at the call: a load that starts later is not seen.  Against that, and against the collapse
itself, ``OMP_WAIT_POLICY=PASSIVE`` in the environment before torch is loaded makes the threads
that wait at the end of an operation sleep instead of spinning (docs/guide/threads.md: the
measurements behind this policy).

``keep_freed_memory`` is the other process setting a batched solve benefits from: on Linux with
glibc the allocator returns every freed block of 32 MB or more to the system, and the next block
of that size is paid again in page faults (docs/guide/estimation.md: a fifth of the TLS study's
time).  The command line calls it unless ``--release-memory`` is given.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import os
import platform
import time

import torch

from .functional import checks


def available_cores() -> int:
    """The CPUs this process may run on (its affinity mask where the platform has one)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def _cpu_times() -> tuple[float, float] | None:
    """(idle, total) jiffies summed over all CPUs from /proc/stat, or None where unavailable."""
    try:
        with open("/proc/stat", encoding="ascii") as f:
            fields = f.readline().split()
    except OSError:
        return None
    if not fields or fields[0] != "cpu" or len(fields) < 5:
        return None
    values = [float(v) for v in fields[1:]]
    idle = values[3] + (values[4] if len(values) > 4 else 0.0)  # idle + iowait
    return idle, sum(values[:8])  # user..steal (guest time is already counted in user)


def idle_cores(interval: float = 0.2) -> float | None:
    """The number of cores left idle by all processes over the next ``interval`` seconds (a
    float in [0, the machine's CPU count]), or None where the platform does not report it
    (no /proc/stat)."""
    checks.finite_number(interval, "interval", "> 0")
    first = _cpu_times()
    if first is None:
        return None
    time.sleep(interval)
    second = _cpu_times()
    if second is None or second[1] <= first[1]:
        return None
    share = (second[0] - first[0]) / (second[1] - first[1])
    return max(0.0, min(1.0, share)) * (os.cpu_count() or 1)


def threads_for_load(interval: float = 0.2) -> int:
    """A torch thread count for the current load: the idle cores (rounded to the nearest
    integer), at least 1 and at most the cores available to this process; where the load cannot
    be read, the cores available."""
    cores = available_cores()
    idle = idle_cores(interval)
    if idle is None:
        return cores
    return max(1, min(cores, int(idle + 0.5)))


def use_threads_for_load(interval: float = 0.2) -> int:
    """Set torch's intra-op thread count to ``threads_for_load(interval)`` and return it.

    torch's parallel operations and the C kernels of ``torchsgal.functional.native`` (which
    split large batches over ``torch.get_num_threads()``) then run on that many threads.  Call
    it once, where the program starts and before its own computations (the load of this process
    counts as busy), from the thread that runs them: ``torch.set_num_threads`` sets the calling
    thread's count and the one that threads starting their first torch operation later take.
    The load is sampled once, at the call (``interval`` seconds, > 0)."""
    threads = threads_for_load(interval)
    torch.set_num_threads(threads)
    return threads


# glibc's mallopt parameters (malloc.h) and the values ``keep_freed_memory`` sets: the mmap
# threshold (1 GiB; 32 MiB, the largest older glibc accepts on 64-bit, where it refuses more),
# then the trim threshold and the top pad
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD = -1, -2, -3
_MMAP_THRESHOLDS = (1 << 30, 32 << 20)
_KEEP = ((_M_TRIM_THRESHOLD, 2**31 - 1), (_M_TOP_PAD, 256 << 20))


def keep_freed_memory() -> int:
    """Where the C library is glibc (Linux), make this process keep the large blocks it frees
    for reuse instead of returning them to the system; returns the block size from which glibc
    still maps and unmaps blocks (1 GiB, or 32 MiB where glibc refuses larger), or 0 where
    nothing was changed (another C library, or glibc refusing the settings).

    By default glibc serves a block of 32 MiB or more by a fresh mapping and unmaps it when
    freed, so a loop over large batches (a batched solve's per-condition blocks are 30-65 MB at
    400 TLS trials) pays page faults for every block of every iteration.  This sets
    ``mallopt``'s M_MMAP_THRESHOLD to 1 GiB, M_TRIM_THRESHOLD to 2 GiB - 1 and M_TOP_PAD to
    256 MiB (what ``MALLOC_MMAP_THRESHOLD_`` etc. in the environment set at start-up): freed
    blocks stay in the heap and the next ones reuse them.  The price is memory: the process
    holds on to its peak heap instead of returning it.  A process setting, for a program where
    it starts; the library never calls it on its own."""
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return 0
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return 0
    for threshold in _MMAP_THRESHOLDS:
        if libc.mallopt(ctypes.c_int(_M_MMAP_THRESHOLD), ctypes.c_int(threshold)):
            break
    else:
        return 0
    for param, value in _KEEP:
        libc.mallopt(ctypes.c_int(param), ctypes.c_int(value))
    return threshold
