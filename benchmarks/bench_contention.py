#!/usr/bin/env python
"""Core and IMU operations beside a competing busy process: torch's thread policies compared.

Every case is timed under four conditions, all in one run:

(a) idle machine, one thread (``torch.set_num_threads(1)``): the reference of every ratio;
(b) idle machine, torch's default thread count (one per core);
(c) beside one busy process, torch's default thread count;
(d) beside the busy process, the library's policy: ``torchsgal.load.use_threads_for_load()``,
    called once after the busy process has started (as a program does where it starts).

The busy process is a ``multiprocessing`` process spinning in pure Python: started with the run,
it spins from before each case's busy conditions until after them and sleeps during the idle
ones (stopped at the end).  Cases (CPU, inputs built outside the timed calls):

* ``SGal3.exp(xi)``, ``g.log()`` (the C kernels where they apply), ``log(exp(xi)).sum()``
  forward and backward through the custom Functions, and ``SE3.exp(xi)`` as tensor code (its
  kernel switched off: torch's own operations), at
  batch sizes ``--sizes``, float64 and float32;
* IMU: ``preintegrate`` of ``--windows`` windows x ``--samples`` samples with the covariance and
  bias Jacobian, as ``bench_imu.py`` (a), float64 and float32.

Timing: two untimed calls of each case first (the second, on one thread, sets how many
back-to-back calls make a sample of at least ``--min-sample`` seconds); then ``--blocks`` blocks.
A block first calls ``use_threads_for_load()`` with the busy process running (its count serves
(d) for the block), then times each case under the four conditions in turn (``--samples-per``
samples each, after an untimed parallel operation that starts torch's thread team at the new
count), idle pair and busy pair in alternating order from block to block, so that the load of
other processes, where there is any, hits the four conditions of a case alike.  A figure is the
median over all samples of a case and condition; a ratio is that median over the median of (a).
The share of the machine's CPU used by processes other than this one is recorded for each
condition (the busy process included in (c) and (d)).

Usage::

    python benchmarks/bench_contention.py            # writes benchmarks/results/contention_cpu.*
    python benchmarks/bench_contention.py --quick    # 2 blocks, short samples, no files
    python benchmarks/bench_contention.py --no-passive --sizes 1e5 --dtypes float64

A second run of the same cases follows in a child process started with ``OMP_WAIT_POLICY=PASSIVE``
(``--no-passive`` skips it), and a third with ``TORCHSGAL_NATIVE_OPENMP=0`` (the C kernels on
their own thread pool instead of torch's OpenMP threads; ``--no-pthreads`` skips it); their tables
are written after the first, their ratios against their own (a).
"""
from __future__ import annotations

import argparse
import gc
import json
import math
import multiprocessing as mp
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

_HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(_HERE))
sys.path.insert(1, str(_HERE.parent))  # benchmark the checkout this script lives in
from _timing import ForeignLoad, environment, loadavg  # noqa: E402

import torchsgal as ts  # noqa: E402
from torchsgal import load  # noqa: E402
from torchsgal.functional import native  # noqa: E402

CONDITIONS = {
    "a": "idle, 1 thread",
    "b": "idle, default threads",
    "c": "busy neighbour, default threads",
    "d": "busy neighbour, use_threads_for_load()",
}
LIMIT = 1.2  # the target: (c) or (d) at most this times (a)
TANGENT_SCALE = 0.5  # as bench_core.py
BUSY = 0.10  # warn where other processes used more than this share of the CPU in (a), (b)


def log(msg: str) -> None:
    print(msg, flush=True)


def _spin(running, stop) -> None:
    """The competitor: a pure-Python busy loop while ``running`` is set, until ``stop`` is."""
    x = 0
    while not stop.is_set():
        if not running.wait(0.05):
            continue
        for _ in range(100_000):  # a few milliseconds
            x += 1


class BusyNeighbour:
    """A process that spins on one core between ``resume()`` and ``pause()`` (paused, it sleeps),
    started on entering the block and stopped on leaving it."""

    def __init__(self, settle_s: float = 0.1):
        self.settle_s = settle_s

    def __enter__(self):
        ctx = mp.get_context("fork" if "fork" in mp.get_all_start_methods() else "spawn")
        self._running, self._stop = ctx.Event(), ctx.Event()
        self._proc = ctx.Process(target=_spin, args=(self._running, self._stop), daemon=True)
        self._proc.start()
        return self

    def resume(self) -> None:
        if not self._running.is_set():
            self._running.set()
            time.sleep(self.settle_s)  # let it reach the loop and the scheduler see it

    def pause(self) -> None:
        if self._running.is_set():
            self._running.clear()
            time.sleep(0.02)  # its current loop ends within milliseconds

    def __exit__(self, *exc):
        self._stop.set()
        self._running.set()
        self._proc.join(5.0)
        if self._proc.is_alive():
            self._proc.terminate()
            self._proc.join()
        return False


def _tensor_code(fn, *args):
    """fn with the kernels off in this thread: torch's own operations (SE(3)'s closed form)."""
    with native.disabled():
        return fn(*args)


def core_cases(sizes, dtypes, gen) -> dict:
    """name -> zero-argument callable: SGal3 exp, log, backward and SE3 exp (its closed form as
    tensor code, the kernels off) per size and dtype."""
    F = ts.functional.sgal3
    cases = {}
    for dtype in dtypes:
        dt = str(dtype).replace("torch.", "")
        for n in sizes:
            xi = (torch.randn(n, 10, generator=gen, dtype=torch.float64) * TANGENT_SCALE).to(dtype)
            xs = (torch.randn(n, 6, generator=gen, dtype=torch.float64) * TANGENT_SCALE).to(dtype)
            g = ts.SGal3.exp(xi)
            leaf = xi.clone().requires_grad_(True)

            def backward(leaf=leaf):
                leaf.grad = None
                F.log(F.exp(leaf)).sum().backward()

            tag = f"n=1e{round(math.log10(n))}" if n == 10 ** round(math.log10(n)) else f"n={n}"
            cases[f"SGal3 exp {tag} {dt}"] = (lambda xi=xi: ts.SGal3.exp(xi))
            cases[f"SGal3 log {tag} {dt}"] = (lambda g=g: g.log())
            cases[f"SGal3 log(exp) fwd+bwd {tag} {dt}"] = backward
            cases[f"SE3 exp (tensor code) {tag} {dt}"] = (lambda xs=xs: _tensor_code(ts.SE3.exp, xs))
    return cases


def imu_cases(windows, samples, dtypes) -> dict:
    """name -> callable: ``preintegrate`` with covariance and bias Jacobian, as bench_imu.py (a)."""
    from bench_imu import SIGMA_A, SIGMA_G, build

    from torchsgal.imu import preintegrate

    _, _, _, gyro64, acc64, h64 = build(windows, samples, 0.005)
    cases = {}
    for dtype in dtypes:
        gyro, acc, h = (x.to(dtype) for x in (gyro64, acc64, h64))

        def go(gyro=gyro, acc=acc, h=h):
            with torch.no_grad():
                return preintegrate(gyro, acc, h, gyro_noise_density=SIGMA_G, acc_noise_density=SIGMA_A)
        cases[f"IMU {windows}x{samples} +cov {str(dtype).replace('torch.', '')}"] = go
    return cases


def calls_per_sample(fn, min_sample_s: float) -> int:
    """Back-to-back calls that make a sample of at least ``min_sample_s`` seconds, from one call
    timed after an untimed first call (lazy initialisation, first use of the output memory)."""
    fn()
    t0 = time.perf_counter()
    fn()
    return max(1, math.ceil(min_sample_s / max(time.perf_counter() - t0, 1e-7)))


def warm_threads() -> None:
    """Start torch's thread team at the current count (one parallel operation), untimed."""
    torch.ones(1 << 20).add_(1.0)


def sample(fn, number: int, samples: int) -> list[float]:
    """``samples`` samples of seconds per call, each ``number`` back-to-back calls."""
    out = []
    for _ in range(samples):
        t0 = time.perf_counter()
        for _ in range(number):
            fn()
        out.append((time.perf_counter() - t0) / number)
    return out


def time_conditions(fn, number, conditions, threads, args, times, shares) -> None:
    """Samples of ``fn`` under each of ``conditions`` (thread counts ``threads``), appended to
    ``times[c]``; ``shares[c]`` accumulates (other processes' CPU share x seconds, seconds)."""
    for c in conditions:
        torch.set_num_threads(threads[c])
        warm_threads()
        t0 = time.perf_counter()
        with ForeignLoad() as foreign:
            times[c] += sample(fn, number, args.samples_per)
        seconds = time.perf_counter() - t0
        if foreign.share is not None:
            shares[c][0] += foreign.share * seconds
            shares[c][1] += seconds


def run(args) -> dict:
    gen = torch.Generator().manual_seed(0)
    dtypes = [getattr(torch, d.strip()) for d in args.dtypes.split(",")]
    cases = core_cases(args.sizes, dtypes, gen)
    if args.windows > 0:
        cases.update(imu_cases(args.windows, args.samples, dtypes))
    default = torch.get_num_threads()
    torch.set_num_threads(1)
    log(f"{len(cases)} cases: warm-up ...")
    numbers = {name: calls_per_sample(fn, args.min_sample) for name, fn in cases.items()}
    times = {name: {c: [] for c in CONDITIONS} for name in cases}
    shares = {c: [0.0, 0.0] for c in CONDITIONS}
    chosen = []
    gc.collect()
    gc_was = gc.isenabled()
    gc.disable()
    try:
        with BusyNeighbour() as neighbour:
            for block in range(args.blocks):
                idle_first = block % 2 == 0
                idle = ("a", "b") if block % 4 < 2 else ("b", "a")
                busy = ("c", "d") if block % 4 < 2 else ("d", "c")
                # the policy as a program applies it where it starts: once, with the neighbour running
                neighbour.resume()
                torch.set_num_threads(default)
                policy = load.use_threads_for_load()
                chosen.append(policy)
                log(f"block {block + 1}/{args.blocks}: use_threads_for_load() beside the busy process -> {policy}")
                for name, fn in cases.items():
                    for half in (("idle", "busy") if idle_first else ("busy", "idle")):
                        if half == "idle":
                            neighbour.pause()
                            time_conditions(fn, numbers[name], idle, {"a": 1, "b": default}, args,
                                            times[name], shares)
                        else:
                            neighbour.resume()
                            time_conditions(fn, numbers[name], busy, {"c": default, "d": policy}, args,
                                            times[name], shares)
                neighbour.pause()
    finally:
        if gc_was:
            gc.enable()
        torch.set_num_threads(default)
    rows = {}
    for name in cases:
        med = {c: statistics.median(times[name][c]) for c in CONDITIONS}
        rows[name] = {
            "median_s": med,
            "ratio_to_a": {c: med[c] / med["a"] for c in CONDITIONS},
            "samples": {c: len(times[name][c]) for c in CONDITIONS},
        }
    return {
        "default_threads": default,
        "policy_threads": chosen,
        "foreign_cpu_share": {c: (round(w / s, 3) if s > 0 else None) for c, (w, s) in shares.items()},
        "cases": rows,
    }


def fmt_time(s: float) -> str:
    if s >= 1e-1:
        return f"{s * 1e3:,.0f} ms"
    if s >= 1e-3:
        return f"{s * 1e3:,.2f} ms"
    return f"{s * 1e6:,.1f} µs"


def table(res: dict) -> list[str]:
    cond = " | ".join(f"({c}) {d}" for c, d in CONDITIONS.items())
    out = [f"| case | {cond} | (b)/(a) | (c)/(a) | (d)/(a) |", "|---" + "|---:" * 7 + "|"]
    for name, r in res["cases"].items():
        m, q = r["median_s"], r["ratio_to_a"]
        flag = lambda c: " **" if q[c] > LIMIT else ""  # noqa: E731
        out.append(f"| {name} | " + " | ".join(fmt_time(m[c]) for c in CONDITIONS)
                   + f" | {q['b']:.2f} | {q['c']:.2f}{flag('c')} | {q['d']:.2f}{flag('d')} |")
    return out


def ratio_table(res: dict, passive: dict | None) -> list[str]:
    """Ratios to (a) of both runs side by side (the table docs/guide/threads.md quotes), and what
    the passive wait costs or saves on the idle machine: (b)/(a) of the PASSIVE run over (b)/(a)
    of the first (ratios, not times, so that a load that changed between the runs cancels)."""
    head = "| case | (a) idle, 1 thread | (b)/(a) | (c)/(a) | (d)/(a) |"
    rule = "|---|---:|---:|---:|---:|"
    if passive is not None:
        head += " PASSIVE: (a) | (b)/(a) | (c)/(a) | (d)/(a) | idle: PASSIVE (b)/(a) over (b)/(a) |"
        rule += "---:|---:|---:|---:|---:|"
    out = [head, rule]
    for name, r in res["cases"].items():
        row = f"| {name} | {fmt_time(r['median_s']['a'])} | " + " | ".join(
            f"{r['ratio_to_a'][c]:.2f}" for c in "bcd") + " |"
        if passive is not None and name in passive["cases"]:
            q = passive["cases"][name]
            row += (f" {fmt_time(q['median_s']['a'])} | " + " | ".join(f"{q['ratio_to_a'][c]:.2f}" for c in "bcd")
                    + f" | {q['ratio_to_a']['b'] / r['ratio_to_a']['b']:.2f} |")
        out.append(row)
    return out


def summary(res: dict) -> list[str]:
    worst = {c: max(r["ratio_to_a"][c] for r in res["cases"].values()) for c in ("c", "d")}
    over = {c: [n for n, r in res["cases"].items() if r["ratio_to_a"][c] > LIMIT] for c in ("c", "d")}
    shares = res["foreign_cpu_share"]
    share_text = ", ".join(f"({c}) " + ("n/a" if v is None else f"{100 * v:.0f}%") for c, v in shares.items())
    lines = [f"- default threads {res['default_threads']}; use_threads_for_load() chose "
             f"{res['policy_threads']} beside the busy process",
             f"- CPU share of other processes during each condition (the busy process included in "
             f"(c), (d); one core of {mp.cpu_count()} is {100 / mp.cpu_count():.0f}%): {share_text}"]
    idle_share = max((v for v in (shares["a"], shares["b"]) if v is not None), default=None)
    if idle_share is not None and idle_share > BUSY:
        lines.append(f"- WARNING: other processes used {100 * idle_share:.0f}% of the CPU during the idle "
                     "conditions (a), (b): the machine was not idle, and every figure is inflated by that "
                     "load, the busy conditions more than the idle ones")
    for c in ("c", "d"):
        name = max(res["cases"], key=lambda n: res["cases"][n]["ratio_to_a"][c])
        lines.append(f"- ({c}) {CONDITIONS[c]}: worst ratio to (a) {worst[c]:.2f} ({name}); target <= {LIMIT}: "
                     + ("met" if not over[c] else f"NOT met for {len(over[c])} of {len(res['cases'])} cases"))
    return lines


def native_threads() -> str:
    """How the C kernels split a batch over threads: torch's OpenMP threads or their own pool."""
    lib = ts.functional.native._lib
    return "none (kernels not built)" if lib is None else lib.parallel_backend()


def child_run(argv: list[str], name: str, value: str) -> dict | None:
    """The same run in a child process started with the environment variable ``name`` set to
    ``value`` (read when torch or the kernels load, so only a new process can have it): its
    results, or None.  ``OMP_WAIT_POLICY=PASSIVE``: OpenMP threads sleep at once at the end of a
    parallel operation instead of spinning first; ``TORCHSGAL_NATIVE_OPENMP=0``: the C kernels
    split batches over their own pool of threads (``_native_common.h``) instead of torch's
    OpenMP threads."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "child.json"
        cmd = [sys.executable, str(Path(__file__).resolve()), *argv, "--no-passive", "--no-pthreads",
               "--child-out", str(path)]
        log(f"{name}={value}: the same cases in a child process ...")
        done = subprocess.run(cmd, env={**os.environ, name: value}, check=False)
        if done.returncode != 0 or not path.exists():
            log(f"the {name}={value} run failed (exit status {done.returncode})")
            return None
        return json.loads(path.read_text())


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    ap = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    ap.add_argument("--sizes", default="1e3,1e5,1e6", help="batch sizes of the core cases")
    ap.add_argument("--dtypes", default="float64,float32")
    ap.add_argument("--windows", type=int, default=1000, help="IMU windows (0: no IMU case)")
    ap.add_argument("--samples", type=int, default=200, help="IMU samples per window")
    ap.add_argument("--blocks", type=int, default=4)
    ap.add_argument("--samples-per", type=int, default=2, help="samples per case, condition and block")
    ap.add_argument("--min-sample", type=float, default=0.05, help="seconds of back-to-back calls per sample")
    ap.add_argument("--no-passive", action="store_true",
                    help="skip the second run, in a child process with OMP_WAIT_POLICY=PASSIVE")
    ap.add_argument("--no-pthreads", action="store_true",
                    help="skip the third run, in a child process with TORCHSGAL_NATIVE_OPENMP=0")
    ap.add_argument("--child-out", type=Path, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--out-dir", type=Path, default=_HERE / "results")
    ap.add_argument("--quick", action="store_true", help="2 blocks of 1 short sample, no result files")
    args = ap.parse_args(argv)
    args.sizes = [int(float(s)) for s in args.sizes.split(",")]
    if args.quick:
        args.blocks, args.samples_per, args.min_sample = 2, 1, 0.01
    t0 = time.perf_counter()
    env = environment("bench_contention.py", argv, native_kernels=ts.functional.native.enabled(),
                      omp_wait_policy=os.environ.get("OMP_WAIT_POLICY", "(not set)"),
                      kernel_threads=native_threads(),
                      competitor="one multiprocessing process spinning in pure Python")
    log(f"torch {env['torch']} | {env['cpu_model']} | {env['cpu_count']} CPUs | default threads "
        f"{env['torch_num_threads']} | OMP_WAIT_POLICY {env['omp_wait_policy']} | load {env['loadavg_at_start']}")
    res = run(args)
    body, verdict = table(res), summary(res)
    print("\n" + "\n".join(body) + "\n\n" + "\n".join(verdict), flush=True)
    if args.child_out is not None:
        args.child_out.write_text(json.dumps({"env": env, "results": res}) + "\n")
        return 0
    passive = None if args.no_passive else child_run(argv, "OMP_WAIT_POLICY", "PASSIVE")
    # the pool's run only where the kernels otherwise run on torch's OpenMP threads
    pool = (None if args.no_pthreads or native_threads() != "openmp"
            else child_run(argv, "TORCHSGAL_NATIVE_OPENMP", "0"))
    env["wall_s"] = round(time.perf_counter() - t0, 1)
    env["loadavg_at_end"] = loadavg()
    log(f"wall {env['wall_s']} s")
    if not args.quick:
        md = [f"# Contention benchmark ({env['cpu_model']}, {env['cpu_count']} CPUs, {env['date']})", "",
              "| | |", "|---|---|"] + [f"| {k} | {v} |" for k, v in env.items()]
        md += ["", __doc__.split("Usage::")[0].split("\n", 2)[2].strip(), "",
               f"Medians per call; ratios to (a); ** marks a ratio above the target {LIMIT}.", "",
               f"## OMP_WAIT_POLICY {env['omp_wait_policy']}", ""] + body + ["", "### summary", ""] + verdict + [""]
        out = {"env": env, "results": res}
        if passive is not None:
            md += ["## OMP_WAIT_POLICY=PASSIVE (the same cases, in a child process; ratios to its own (a))", ""]
            md += table(passive["results"]) + ["", "### summary", ""] + summary(passive["results"]) + [""]
            out["passive"] = passive
        if pool is not None:
            md += ["## The C kernels on their own thread pool (TORCHSGAL_NATIVE_OPENMP=0, the same cases, in "
                   "a child process; ratios to its own (a))", ""]
            md += table(pool["results"]) + ["", "### summary", ""] + summary(pool["results"]) + [""]
            out["pthreads"] = pool
        md += ["## ratios to (a), the first two runs", ""]
        md += ratio_table(res, None if passive is None else passive["results"])
        md += [""]
        args.out_dir.mkdir(parents=True, exist_ok=True)
        (args.out_dir / "contention_cpu.json").write_text(json.dumps(out, indent=2) + "\n")
        (args.out_dir / "contention_cpu.md").write_text("\n".join(md))
        log(f"wrote {args.out_dir / 'contention_cpu.json'} and {args.out_dir / 'contention_cpu.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
