"""Small, honest timing helpers shared by the benchmark scripts.

Rules followed by :func:`measure`:

* the first call (warm-up) is never part of the statistics; it is timed only to
  calibrate how many calls go into one sample;
* a sample is ``number`` back-to-back calls (``number`` chosen so a sample lasts at
  least ``min_sample_s``, which keeps tiny batches out of timer resolution);
* samples are taken until ``target_s`` seconds of sampling have elapsed, with at least
  ``min_repeats`` (and at most ``max_repeats``) samples;
* the reported figure is the median over samples of (sample time / number);
* on CUDA the device is synchronised before starting and before stopping the clock;
* Python's garbage collector is disabled while the clock runs (as ``timeit`` does).

Inputs must be created by the caller outside the timed callable.
"""
from __future__ import annotations

import gc
import math
import os
import statistics
import time
from collections.abc import Callable

import torch


def synchronize(device: torch.device | str | None) -> None:
    if device is not None and torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def _timed(fn: Callable[[], object], number: int, device) -> float:
    synchronize(device)
    t0 = time.perf_counter()
    for _ in range(number):
        fn()
    synchronize(device)
    return time.perf_counter() - t0


def measure(
    fn: Callable[[], object],
    *,
    device: torch.device | str | None = None,
    target_s: float = 0.5,
    min_repeats: int = 3,
    max_repeats: int = 200,
    min_sample_s: float = 0.02,
    warmup: int = 1,
) -> dict:
    """Time ``fn()``; returns seconds per call (median, min, max) and the sampling plan."""
    gc.collect()
    # Warm-up call(s): excluded from the statistics.
    t_call = 0.0
    for _ in range(max(1, warmup)):
        t_call = _timed(fn, 1, device)
    # Calibration (also excluded): the warm-up is a poor estimate (lazy init, a context
    # switch), so re-time one call unless that is expensive, then a short burst if tiny.
    if t_call < 0.2:
        t_call = min(t_call, _timed(fn, 1, device))
    if t_call < min_sample_s:
        n_cal = max(1, min(1000, int(min_sample_s / max(t_call, 1e-7) / 4)))
        t_call = _timed(fn, n_cal, device) / n_cal
    number = max(1, math.ceil(min_sample_s / max(t_call, 1e-9)))

    # Samples: at least min_repeats, then more until target_s of sampling has elapsed.
    times = []
    gc_was_enabled = gc.isenabled()
    gc.disable()
    try:
        with ForeignLoad() as load:
            t_begin = time.perf_counter()
            while len(times) < min_repeats or (
                time.perf_counter() - t_begin < target_s and len(times) < max_repeats
            ):
                times.append(_timed(fn, number, device) / number)
    finally:
        if gc_was_enabled:
            gc.enable()
    repeats = len(times)
    return {
        "median_s": statistics.median(times),
        "min_s": min(times),
        "max_s": max(times),
        "repeats": repeats,
        "number": number,
        "total_s": sum(times) * number,
        "foreign_cpu": load.share,
    }


def fmt_ns(ns: float | None) -> str:
    if ns is None or (isinstance(ns, float) and math.isnan(ns)):
        return "–"
    if ns >= 1e5:
        return f"{ns / 1e3:,.0f} µs"
    if ns >= 100:
        return f"{ns:,.0f}"
    if ns >= 10:
        return f"{ns:.1f}"
    return f"{ns:.2f}"


def fmt_bytes(b: float | None) -> str:
    if b is None:
        return "–"
    for unit, scale in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if b >= scale:
            return f"{b / scale:.1f} {unit}"
    return f"{b:.0f} B"


def _cpu_ticks() -> tuple[int, int] | None:
    """(busy ticks of the whole machine, ticks used by this process), from /proc."""
    try:
        with open("/proc/stat") as f:
            v = [int(x) for x in f.readline().split()[1:]]
        busy = sum(v) - v[3] - (v[4] if len(v) > 4 else 0)  # minus idle and iowait
        with open("/proc/self/stat") as f:
            st = f.read().rsplit(")", 1)[1].split()
        return busy, int(st[11]) + int(st[12])  # utime + stime
    except (OSError, ValueError, IndexError):
        return None


class ForeignLoad:
    """Share of the machine's CPU used by *other* processes while the block ran (0..1).

    A value well above 0 means someone else was computing during the measurement, which on
    a small machine inflates timings (multi-threaded torch kernels wait for descheduled
    threads).  Resolution is the kernel tick (10 ms), so short blocks read as noisy."""

    def __enter__(self):
        self._t0, self._c0 = time.perf_counter(), _cpu_ticks()
        self.share = None
        return self

    def __exit__(self, *exc):
        c1 = _cpu_ticks()
        dt = time.perf_counter() - self._t0
        if self._c0 is None or c1 is None or dt <= 0:
            return False
        hz = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
        ncpu = os.cpu_count() or 1
        other = (c1[0] - self._c0[0]) - (c1[1] - self._c0[1])
        self.share = max(0.0, min(1.0, other / hz / (dt * ncpu)))
        return False


def mem_available_bytes() -> int | None:
    """MemAvailable from /proc/meminfo (Linux), or None."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.lower().startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    import platform

    return platform.processor() or "unknown"


def eager_call_us() -> float:
    """Microseconds of one eager ``x * 2`` on 1,000 float64 elements, one thread (median of 20
    samples of 1,000 calls): the machine's per-call cost, which sets the ratios of batched
    solves to one-problem-at-a-time solves and to peers called in a Python loop."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        x = torch.ones(1000, dtype=torch.float64)
        for _ in range(1000):
            x * 2
        samples = []
        for _ in range(20):
            t0 = time.perf_counter()
            for _ in range(1000):
                x * 2
            samples.append((time.perf_counter() - t0) / 1000)
        return 1e6 * statistics.median(samples)
    finally:
        torch.set_num_threads(threads)


def resolve_device(name: str) -> torch.device:
    """The ``--device`` of a benchmark script: "cpu" or "cuda[:i]"; exits with a clear message
    when it is malformed, of another type, or CUDA is asked for and not available."""
    import sys

    try:
        device = torch.device(name)
    except (RuntimeError, ValueError) as e:
        sys.exit(f"--device must be 'cpu' or 'cuda[:i]', got {name!r} ({e})")
    if device.type not in ("cpu", "cuda"):
        sys.exit(f"--device must be 'cpu' or 'cuda[:i]', got {name!r}")
    if device.type == "cuda":
        if not torch.cuda.is_available():
            sys.exit(f"--device {name}: CUDA requested but torch.cuda.is_available() is False "
                     f"(torch {torch.__version__}, built for CUDA {torch.version.cuda})")
        if device.index is not None and device.index >= torch.cuda.device_count():
            sys.exit(f"--device {name}: only {torch.cuda.device_count()} CUDA device(s) visible")
    return device


def device_name(device: torch.device) -> str:
    """torch.cuda.get_device_name for a CUDA device, else the CPU model."""
    return torch.cuda.get_device_name(device) if device.type == "cuda" else cpu_model()


def dist_version(name: str) -> str | None:
    """Installed version of a distribution, or None."""
    try:
        from importlib.metadata import version

        return version(name)
    except Exception:
        return None


def loadavg() -> tuple[float, float, float] | None:
    return os.getloadavg() if hasattr(os, "getloadavg") else None


def wait_for_idle(seconds: float, threshold: float = 0.5, poll_s: float = 2.0) -> None:
    """Wait up to ``seconds`` for the 1-minute load average to drop below ``threshold``."""
    if seconds <= 0 or loadavg() is None:
        return
    t0 = time.time()
    while os.getloadavg()[0] > threshold and time.time() - t0 < seconds:
        time.sleep(poll_s)


def environment(benchmark: str, argv: list[str] | None = None, **extra) -> dict:
    """The header every results file starts with: what ran, where, with which versions, and
    the load average at the start; ``extra`` entries are appended."""
    import datetime as _dt
    import platform
    import sys
    from pathlib import Path

    try:
        import torchsgal

        where = str(getattr(torchsgal, "__version__", "?"))
    except Exception as e:  # the peer sections of a benchmark can still run
        where = f"not importable ({type(e).__name__}: {e})"
    env = {
        "benchmark": benchmark,
        "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "torch": torch.__version__,
        "torchsgal": where,
        "cpu_model": cpu_model(),
        "cpu_count": os.cpu_count(),
        "torch_num_threads": torch.get_num_threads(),
        "torch_num_interop_threads": torch.get_num_interop_threads(),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "command": " ".join([Path(sys.argv[0]).name] + (sys.argv[1:] if argv is None else list(argv))),
        "loadavg_at_start": loadavg(),
    }
    env.update(extra)
    return env


def interleaved(cases: dict, *, target_s: float, min_rounds: int, max_rounds: int, warmup: int = 2,
                device: torch.device | str | None = None):
    """Round-robin timing of ``cases`` (name -> zero-arg callable): every round calls each case
    once, in an order rotated by one per round, so that slow drifts of the machine hit all cases
    alike.  Untimed warm-up calls first; GC off while timing.  On CUDA (``device``) the device is
    synchronised before starting and before stopping the clock of every call, as in ``measure``
    (a case that runs on the CPU, e.g. a C++ peer, then only pays a no-op synchronise).

    Returns (per-case dict of median/min/max seconds and rounds, per-round times, foreign share)."""
    names = list(cases)
    cuda = device is not None and torch.device(device).type == "cuda"
    for name in names:
        for _ in range(warmup):
            cases[name]()
    if cuda:
        torch.cuda.synchronize(device)
    times = {k: [] for k in names}
    gc.collect()
    gc_was = gc.isenabled()
    gc.disable()
    try:
        with ForeignLoad() as load:
            t_begin = time.perf_counter()
            r = 0
            while r < min_rounds or (time.perf_counter() - t_begin < target_s and r < max_rounds):
                for name in names[r % len(names):] + names[: r % len(names)]:
                    if cuda:
                        torch.cuda.synchronize(device)
                    t0 = time.perf_counter()
                    cases[name]()
                    if cuda:
                        torch.cuda.synchronize(device)
                    times[name].append(time.perf_counter() - t0)
                r += 1
    finally:
        if gc_was:
            gc.enable()
    stats = {k: {"median_s": statistics.median(v), "min_s": min(v), "max_s": max(v), "rounds": len(v)}
             for k, v in times.items()}
    return stats, times, load.share


def paired_ratio(times: dict, slow: str, fast: str) -> float:
    """Median over rounds of time(slow) / time(fast)."""
    return statistics.median(a / b for a, b in zip(times[slow], times[fast]))


def kernels_note() -> str:
    """Whether the engine's optional C kernels run on this machine's CPU (the host-CPU rows of a
    device run): they are compiled at install and missing where no compiler was there."""
    from torchsgal.estimation import dense_solve
    from torchsgal.functional import native
    if dense_solve.available() and native.enabled():
        return "the engine's C kernels built and on"
    return "the engine's C kernels not built or off (the host CPU runs the tensor code)"
