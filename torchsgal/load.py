"""Thread counts for a shared machine.

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
"""
from __future__ import annotations

import os
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
