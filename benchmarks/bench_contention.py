#!/usr/bin/env python
"""Core and IMU operations beside a competing busy process: torch's thread policies compared.

Every case is timed under four conditions, all in one run:

(a) idle machine, one thread (``torch.set_num_threads(1)``): the reference of every ratio;
(b) idle machine, torch's default thread count (one per core);
(c) beside one busy process, torch's default thread count;
(d) beside the busy process, the library's policy: ``torchsgal.load.use_threads_for_load()``,
    called once after the busy process has started (as a program does where it starts).

The busy process is a ``multiprocessing`` process spinning in pure Python, started before the
busy conditions and stopped after them.  Cases (CPU, inputs built outside the timed calls):

* ``SGal3.exp(xi)``, ``g.log()`` (the C kernels where they apply), ``log(exp(xi)).sum()``
  forward and backward through the custom Functions, and ``SE3.exp(xi)`` (tensor code), at
  batch sizes ``--sizes``, float64 and float32;
* IMU: ``preintegrate`` of ``--windows`` windows x ``--samples`` samples with the covariance and
  bias Jacobian, as ``bench_imu.py`` (a), float64 and float32.

Timing: two untimed calls of each case first (the second, on one thread, sets how many
back-to-back calls make a sample of at least ``--min-sample`` seconds); then ``--blocks`` blocks,
each timing every case under every condition (``--samples-per`` samples, after an untimed
parallel operation that starts torch's thread team at the new count), the idle and busy halves
in alternating order from block to block, so that a slow drift of the machine hits every
condition alike.  A figure is the median over all samples of a case and condition; a ratio is
that median over the median of (a).  The share of the machine's CPU used by processes other
than this one is recorded for each half (the busy process included in (c) and (d)).

Usage::

    python benchmarks/bench_contention.py            # writes benchmarks/results/contention_cpu.*
    python benchmarks/bench_contention.py --quick    # 2 blocks, short samples, no files
"""
from __future__ import annotations

import argparse
import gc
import json
import math
import multiprocessing as mp
import statistics
import sys
import time
from pathlib import Path

import torch

_HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(_HERE))
sys.path.insert(1, str(_HERE.parent))  # benchmark the checkout this script lives in
from _timing import ForeignLoad, environment, loadavg  # noqa: E402

import torchsgal as ts  # noqa: E402
from torchsgal import load  # noqa: E402

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


def _spin(stop) -> None:
    """The competitor: a pure-Python busy loop until ``stop`` is set."""
    x = 0
    while not stop.is_set():
        for _ in range(100_000):
            x += 1


class BusyNeighbour:
    """A process spinning on one core for the duration of the block."""

    def __init__(self, settle_s: float = 0.5):
        self.settle_s = settle_s

    def __enter__(self):
        ctx = mp.get_context("fork" if "fork" in mp.get_all_start_methods() else "spawn")
        self._stop = ctx.Event()
        self._proc = ctx.Process(target=_spin, args=(self._stop,), daemon=True)
        self._proc.start()
        time.sleep(self.settle_s)  # let it reach the loop and the scheduler see it
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._proc.join(5.0)
        if self._proc.is_alive():
            self._proc.terminate()
            self._proc.join()
        return False


def core_cases(sizes, dtypes, gen) -> dict:
    """name -> zero-argument callable: SGal3 exp, log, backward and SE3 exp per size and dtype."""
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
            cases[f"SE3 exp (tensor code) {tag} {dt}"] = (lambda xs=xs: ts.SE3.exp(xs))
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


def run_half(cases, numbers, conditions, threads, args, times, shares) -> None:
    """Time every case under ``conditions`` (their thread counts in ``threads``); ``numbers``:
    the calls per sample of each case."""
    gc.collect()
    gc_was = gc.isenabled()
    gc.disable()
    try:
        with ForeignLoad() as foreign:
            for name, fn in cases.items():
                for c in conditions:
                    torch.set_num_threads(threads[c])
                    warm_threads()
                    times[(name, c)] += sample(fn, numbers[name], args.samples_per)
    finally:
        if gc_was:
            gc.enable()
    for c in conditions:
        shares[c].append(foreign.share)


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
    times = {(n, c): [] for n in cases for c in CONDITIONS}
    shares = {c: [] for c in CONDITIONS}
    chosen = []
    for block in range(args.blocks):
        idle_first = block % 2 == 0
        for half in ((0, 1) if idle_first else (1, 0)):
            if half == 0:
                order = ("a", "b") if block % 4 < 2 else ("b", "a")
                log(f"block {block + 1}/{args.blocks}: idle ({', '.join(order)}) ...")
                run_half(cases, numbers, order, {"a": 1, "b": default}, args, times, shares)
            else:
                with BusyNeighbour():
                    torch.set_num_threads(default)
                    policy = load.use_threads_for_load()
                    chosen.append(policy)
                    order = ("c", "d") if block % 4 < 2 else ("d", "c")
                    log(f"block {block + 1}/{args.blocks}: busy neighbour ({', '.join(order)}; "
                        f"use_threads_for_load() -> {policy}) ...")
                    run_half(cases, numbers, order, {"c": default, "d": policy}, args, times, shares)
    torch.set_num_threads(default)
    rows = {}
    for name in cases:
        med = {c: statistics.median(times[(name, c)]) for c in CONDITIONS}
        rows[name] = {
            "median_s": med,
            "ratio_to_a": {c: med[c] / med["a"] for c in CONDITIONS},
            "samples": {c: len(times[(name, c)]) for c in CONDITIONS},
        }
    return {
        "default_threads": default,
        "policy_threads": chosen,
        "foreign_cpu_share": {c: [None if s is None else round(s, 3) for s in v] for c, v in shares.items()},
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


def summary(res: dict) -> list[str]:
    worst = {c: max(r["ratio_to_a"][c] for r in res["cases"].values()) for c in ("c", "d")}
    over = {c: [n for n, r in res["cases"].items() if r["ratio_to_a"][c] > LIMIT] for c in ("c", "d")}
    shares = res["foreign_cpu_share"]
    mean = lambda v: statistics.mean(x for x in v if x is not None) if any(x is not None for x in v) else None  # noqa: E731
    share_text = ", ".join(f"({c}) {100 * mean(v):.0f}%" if mean(v) is not None else f"({c}) n/a"
                           for c, v in shares.items())
    lines = [f"- default threads {res['default_threads']}; use_threads_for_load() chose "
             f"{res['policy_threads']} beside the busy process",
             f"- CPU share of other processes during each condition (the busy process included in "
             f"(c), (d); one core of {mp.cpu_count()} is {100 / mp.cpu_count():.0f}%): {share_text}"]
    idle_share = mean(shares["a"] + shares["b"])
    if idle_share is not None and idle_share > BUSY:
        lines.append(f"- WARNING: other processes used {100 * idle_share:.0f}% of the CPU during the idle "
                     "conditions (a), (b): the machine was not idle, and every figure is inflated by that "
                     "load, the busy conditions more than the idle ones")
    for c in ("c", "d"):
        name = max(res["cases"], key=lambda n: res["cases"][n]["ratio_to_a"][c])
        lines.append(f"- ({c}) {CONDITIONS[c]}: worst ratio to (a) {worst[c]:.2f} ({name}); target <= {LIMIT}: "
                     + ("met" if not over[c] else f"NOT met for {len(over[c])} of {len(res['cases'])} cases"))
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    ap.add_argument("--sizes", default="1e3,1e5,1e6", help="batch sizes of the core cases")
    ap.add_argument("--dtypes", default="float64,float32")
    ap.add_argument("--windows", type=int, default=1000, help="IMU windows (0: no IMU case)")
    ap.add_argument("--samples", type=int, default=200, help="IMU samples per window")
    ap.add_argument("--blocks", type=int, default=4)
    ap.add_argument("--samples-per", type=int, default=2, help="samples per case, condition and block")
    ap.add_argument("--min-sample", type=float, default=0.05, help="seconds of back-to-back calls per sample")
    ap.add_argument("--out-dir", type=Path, default=_HERE / "results")
    ap.add_argument("--quick", action="store_true", help="2 blocks, 2 short samples, no result files")
    args = ap.parse_args(argv)
    args.sizes = [int(float(s)) for s in args.sizes.split(",")]
    if args.quick:
        args.blocks, args.samples_per, args.min_sample = 2, 2, 0.01
    t0 = time.perf_counter()
    env = environment("bench_contention.py", argv, native_kernels=ts.functional.native.enabled(),
                      competitor="one multiprocessing process spinning in pure Python")
    log(f"torch {env['torch']} | {env['cpu_model']} | {env['cpu_count']} CPUs | default threads "
        f"{env['torch_num_threads']} | load {env['loadavg_at_start']}")
    res = run(args)
    env["wall_s"] = round(time.perf_counter() - t0, 1)
    env["loadavg_at_end"] = loadavg()
    body = table(res)
    verdict = summary(res)
    print("\n" + "\n".join(body) + "\n\n" + "\n".join(verdict))
    log(f"wall {env['wall_s']} s")
    if not args.quick:
        md = [f"# Contention benchmark ({env['cpu_model']}, {env['cpu_count']} CPUs, {env['date']})", "",
              "| | |", "|---|---|"] + [f"| {k} | {v} |" for k, v in env.items()]
        md += ["", __doc__.split("Usage::")[0].split("\n", 2)[2].strip(), "",
               "Medians per call; ratios to (a); ** marks a ratio above the target "
               f"{LIMIT}.", ""] + body + ["", "## summary", ""] + verdict + [""]
        args.out_dir.mkdir(parents=True, exist_ok=True)
        out = {"env": env, "results": res}
        (args.out_dir / "contention_cpu.json").write_text(json.dumps(out, indent=2) + "\n")
        (args.out_dir / "contention_cpu.md").write_text("\n".join(md))
        log(f"wrote {args.out_dir / 'contention_cpu.json'} and {args.out_dir / 'contention_cpu.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
