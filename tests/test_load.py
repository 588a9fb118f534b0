"""torchsgal.load: the thread count chosen from the idle cores (the command line's default and
``use_threads_for_load``)."""
from __future__ import annotations

import threading

import pytest
import torch

from torchsgal import load


def _fake_stat(monkeypatch, samples, cpus):
    """/proc/stat read as ``samples`` (idle, total) in turn, on a machine of ``cpus`` CPUs."""
    it = iter(samples)
    monkeypatch.setattr(load, "_cpu_times", lambda: next(it))
    monkeypatch.setattr(load.os, "cpu_count", lambda: cpus)
    monkeypatch.setattr(load.time, "sleep", lambda s: None)


@pytest.mark.parametrize(("idle_share", "cores", "want"), [
    (1.0, 2, 2),     # idle machine: every core
    (0.5, 2, 1),     # one busy process on two cores: one thread
    (0.02, 2, 1),    # both cores busy: still one thread
    (0.74, 4, 3),    # one of four cores busy
    (1.0, 1, 1),     # affinity allows one core only
])
def test_threads_follow_the_idle_cores(monkeypatch, idle_share, cores, want):
    cpus = max(cores, 2) if cores > 1 else 4
    _fake_stat(monkeypatch, [(0.0, 0.0), (100.0 * idle_share, 100.0)], cpus)
    monkeypatch.setattr(load, "available_cores", lambda: cores)
    assert load.threads_for_load() == want


def test_without_proc_stat_all_available_cores(monkeypatch):
    _fake_stat(monkeypatch, [None], 8)
    monkeypatch.setattr(load, "available_cores", lambda: 3)
    assert load.threads_for_load() == 3


def test_idle_cores_reads_this_machine():
    idle = load.idle_cores(0.05)
    if idle is not None:  # Linux: /proc/stat
        assert 0.0 <= idle <= (load.os.cpu_count() or 1)
    assert 1 <= load.threads_for_load(0.05) <= load.available_cores()


@pytest.mark.parametrize(("bad", "error"), [(0, ValueError), (-1.0, ValueError), (float("nan"), ValueError),
                                            (float("inf"), ValueError), ("0.2", TypeError), (True, TypeError)])
def test_interval_is_checked(bad, error):
    with pytest.raises(error, match="interval must be a finite number > 0"):
        load.idle_cores(bad)


@pytest.fixture
def restore_threads():
    """torch's thread count as the test found it, restored afterwards."""
    before = torch.get_num_threads()
    yield before
    torch.set_num_threads(before)


@pytest.mark.parametrize("chosen", [1, 3])
def test_use_threads_for_load_sets_torch_threads(monkeypatch, restore_threads, chosen):
    """The count of threads_for_load becomes torch's (which the C kernels split over), returned."""
    calls = []
    monkeypatch.setattr(load, "threads_for_load", lambda interval=0.2: calls.append(interval) or chosen)
    assert load.use_threads_for_load(0.05) == chosen
    assert calls == [0.05]
    assert torch.get_num_threads() == chosen


def test_use_threads_for_load_one_thread_beside_a_busy_core(monkeypatch, restore_threads):
    """Two cores, one kept busy by another process: one torch thread (from /proc/stat's counts)."""
    torch.set_num_threads(2)
    _fake_stat(monkeypatch, [(0.0, 0.0), (50.0, 100.0)], 2)
    monkeypatch.setattr(load, "available_cores", lambda: 2)
    assert load.use_threads_for_load() == 1
    assert torch.get_num_threads() == 1


def test_use_threads_for_load_reaches_threads_started_later(monkeypatch, restore_threads):
    """A thread whose first torch operation comes after the call takes the count too."""
    monkeypatch.setattr(load, "threads_for_load", lambda interval=0.2: 1)
    torch.set_num_threads(2)
    load.use_threads_for_load()
    seen = []
    worker = threading.Thread(target=lambda: seen.append(torch.get_num_threads()))
    worker.start()
    worker.join()
    assert seen == [1]


@pytest.mark.parametrize(("bad", "error"), [(0, ValueError), (float("nan"), ValueError), ("0.2", TypeError)])
def test_use_threads_for_load_checks_interval_first(restore_threads, bad, error):
    """A bad interval raises before torch's thread count is touched."""
    with pytest.raises(error, match="interval must be a finite number > 0"):
        load.use_threads_for_load(bad)
    assert torch.get_num_threads() == restore_threads


def test_keep_freed_memory_sets_the_allocator_where_it_is_glibc(monkeypatch):
    calls = []

    def libc(accepts):
        class FakeLibc:
            def mallopt(self, param, value):
                calls.append((param.value, value.value))
                return int(accepts(param.value, value.value))
        return lambda name: FakeLibc()

    monkeypatch.setattr(load.platform, "system", lambda: "Linux")
    monkeypatch.setattr(load.platform, "libc_ver", lambda: ("glibc", "2.36"))
    monkeypatch.setattr(load.ctypes, "CDLL", libc(lambda p, v: True))
    assert load.keep_freed_memory() == 1 << 30
    # M_MMAP_THRESHOLD, M_TRIM_THRESHOLD, M_TOP_PAD (malloc.h) to 1 GiB, 2 GiB - 1, 256 MiB
    assert calls == [(-3, 1 << 30), (-1, 2**31 - 1), (-2, 256 << 20)]
    calls.clear()  # a glibc that refuses an mmap threshold above 32 MiB (HEAP_MAX_SIZE / 2)
    monkeypatch.setattr(load.ctypes, "CDLL", libc(lambda p, v: p != -3 or v <= 32 << 20))
    assert load.keep_freed_memory() == 32 << 20
    assert calls == [(-3, 1 << 30), (-3, 32 << 20), (-1, 2**31 - 1), (-2, 256 << 20)]
    calls.clear()  # one that refuses both: nothing else is set
    monkeypatch.setattr(load.ctypes, "CDLL", libc(lambda p, v: False))
    assert load.keep_freed_memory() == 0 and calls == [(-3, 1 << 30), (-3, 32 << 20)]

    def no_libc(name):
        raise OSError("no C library")
    monkeypatch.setattr(load.ctypes, "CDLL", no_libc)
    assert load.keep_freed_memory() == 0
    calls.clear()
    monkeypatch.setattr(load.ctypes, "CDLL", libc(lambda p, v: True))
    monkeypatch.setattr(load.platform, "libc_ver", lambda: ("musl", ""))
    assert load.keep_freed_memory() == 0 and calls == []


def test_keep_freed_memory_in_this_process_keeps_large_blocks_in_the_heap():
    """64 MiB blocks: glibc's defaults map and unmap each (16,384 first-touch faults of 4 kB
    pages per block); kept, they come from the heap once it has grown to hold them.  The heap
    places a block at a new address again while the process's small allocations settle above it
    (with four warm-up blocks, one or two blocks' faults in a process started from Python, none
    with ten), so ten blocks warm it up and the kept run is bounded by one block's faults and by
    a factor 4."""
    import subprocess
    import sys
    code = """
import resource, torch
from torchsgal import load
threshold = load.keep_freed_memory() if {keep} else 0
for _ in range(10):  # warm-up: the heap grows to hold the blocks
    x = torch.empty(8 << 20, dtype=torch.float64); x.fill_(1.0); del x
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(5):
    x = torch.empty(8 << 20, dtype=torch.float64); x.fill_(1.0); del x
print(threshold, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""
    out = {}
    for keep in (False, True):
        threshold, faults = subprocess.run([sys.executable, "-c", code.format(keep=keep)],
                                           capture_output=True, text=True, check=True).stdout.split()
        out[keep] = (int(threshold), int(faults))
    import platform
    glibc = platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"
    if not glibc:  # nothing changed: the same allocator both times
        assert out[True][0] == 0, out
        return
    assert out[False][1] >= 5 * 10_000, out
    if out[True][0] > 64 << 20:
        assert out[True][1] <= 16_384 + 1_000 and 4 * out[True][1] < out[False][1], out
    else:  # a glibc that keeps blocks up to 32 MiB only: 64 MiB blocks are still mapped
        assert out[True][0] == 32 << 20 and out[True][1] >= 5 * 10_000, out


def test_load_is_an_attribute_of_the_package():
    """``import torchsgal`` then ``torchsgal.load.use_threads_for_load()``, as the threads guide
    writes it, in a fresh interpreter (the package must import the module itself)."""
    import subprocess
    import sys

    code = "import torchsgal; print(torchsgal.load.threads_for_load.__name__)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "threads_for_load"


@pytest.mark.parametrize("seed", [str(2**64), str(-(2**63) - 1), "99999999999999999999999"])
def test_command_line_demo_refuses_a_seed_torch_cannot_take(capsys, seed):
    """``python -m torchsgal demo --seed S``: torch.manual_seed takes 64-bit seeds only
    ([-2^63, 2^64 - 1]); one outside is a usage error (exit status 2), not a traceback."""
    from torchsgal.__main__ import main
    with pytest.raises(SystemExit) as info:
        main(["demo", "--seed", seed])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert "argument --seed: must be between" in err and seed in err


@pytest.mark.parametrize("seed", [2**64 - 1, -(2**63)])
def test_command_line_demo_takes_the_extreme_seeds(capsys, seed):
    from torchsgal.__main__ import main
    with torch.random.fork_rng():  # the demo seeds torch's global generator
        assert main(["demo", "--seed", str(seed)]) == 0
    assert "d loss / d xi finite: True" in capsys.readouterr().out
