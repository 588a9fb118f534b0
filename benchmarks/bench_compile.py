"""The acceleration path of SGal(3) exp and exp+log (forward + backward): the registered
operators (C kernels, functional/ops.py) against the closed forms compiled by ``torch.compile``,
eager tensor code and the peers, in one run.

SGal3.exp written as tensor operations is ~170 small ops, and PyTorch's per-op overhead
dominates at small batches.  Two mechanisms remove it: the operator ``torchsgal::sgal3_exp``,
whose CPU implementation is one C loop, and ``torch.compile`` (inductor), which fuses the
closed form.  This script times, per batch size and dtype (medians, ns per element):

- exp: the operator in eager code (``SGal3.exp``), the same call compiled (inference: compiled
  code calls the operator), the closed form (``exp_impl``) eager and compiled,
  ``torch.linalg.matrix_exp`` of the hat matrix (eager, and compiled), pypose
  ``se3(x).Exp()`` (SE3, eager);
- ``xi * 2`` eager and compiled: torch.compile's own cost per call (guards and wrappers around
  one cheap operation), the floor under every compiled case at small batches;
- exp then log, forward + backward of the summed output: the custom autograd.Function (the
  operators and their closed-form backward maps) and plain autograd through the closed forms,
  eager, and plain autograd compiled (where autograd records, compiled code differentiates the
  closed forms; see functional/_autograd.py).

Compilation time is reported separately and excluded from the timings.

On CUDA the script opts in to the operators' compiled closed forms
(``native.use_compiled_cuda(True)``, functional/ops.py): "exp operator eager" there launches the
inductor kernels of the closed form, after a first call that compiles them (reported with the
other first calls).  ``--cases`` keeps the cases whose names contain one of its strings.

``--device cuda[:i]`` runs every case (inputs, compiled code, the pypose peer) on that GPU, with
the device synchronised around every timed sample; it also records each case's CUDA peak
memory (torch.cuda.max_memory_allocated over one call, minus what was allocated before) and
writes ``compile_cuda.{json,md}`` instead of ``compile_cpu.{json,md}``.

Usage::

    python benchmarks/bench_compile.py [--sizes 1000 100000 1000000] [--threads N]
    python benchmarks/bench_compile.py --device cuda --sizes 1000 100000 1000000
"""
from __future__ import annotations

import argparse
import contextlib
import datetime as _dt
import json
import os
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _timing import cpu_model, device_name, fmt_bytes, measure, resolve_device, synchronize  # noqa: E402

from torchsgal.functional import native  # noqa: E402
from torchsgal.functional import sgal3 as F  # noqa: E402

HERE = Path(__file__).resolve().parent


def fwd_bwd(exp, log):
    def step(xi):
        x = xi.detach().requires_grad_(True)
        out = log(exp(x)).sum()
        out.backward()
        return x.grad
    return step


def cuda_peak_bytes(fn, device) -> int:
    """Peak CUDA memory of one call of ``fn`` above what was allocated before it."""
    synchronize(device)
    torch.cuda.reset_peak_memory_stats(device)
    base = torch.cuda.memory_allocated(device)
    fn()
    synchronize(device)
    return torch.cuda.max_memory_allocated(device) - base


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("Usage::")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[1000, 100000, 1000000])
    ap.add_argument("--dtypes", nargs="+", default=["float32", "float64"])
    ap.add_argument("--threads", type=int, default=0)
    ap.add_argument("--target-s", type=float, default=0.5)
    ap.add_argument("--out", default=str(HERE / "results"),
                    help="folder for compile_<device>.{json,md} (default benchmarks/results)")
    ap.add_argument("--device", default="cpu", help="cpu or cuda[:i] (default cpu)")
    ap.add_argument("--cases", nargs="+", default=None,
                    help="run only the cases whose name contains one of these strings")
    args = ap.parse_args(argv)
    device = resolve_device(args.device)
    cuda = device.type == "cuda"
    if cuda:
        native.use_compiled_cuda(True)
    if args.threads:
        torch.set_num_threads(args.threads)
    try:
        import pypose as pp
    except ImportError as e:
        pp = None
        pp_missing = f"pypose not importable ({e}): its peer case is skipped"
        print(f"NOTE: {pp_missing}", file=sys.stderr)

    exp_c = torch.compile(F.exp)
    exp_impl_c = torch.compile(F.exp_impl)
    mexp_c = torch.compile(torch.linalg.matrix_exp)
    custom, plain = fwd_bwd(F.exp, F.log), fwd_bwd(F.exp_impl, F.log_impl)
    plain_c = torch.compile(plain)
    double_c = torch.compile(lambda x: x * 2)
    rows, compile_s = [], {}
    gen = torch.Generator().manual_seed(0)
    for dt_name in args.dtypes:
        dtype = getattr(torch, dt_name)
        for n in args.sizes:
            # generated on the CPU, so that the inputs are the same on every device
            xi = torch.randn(n, 10, generator=gen, dtype=torch.float64).to(dtype=dtype, device=device)
            X = F.hat(xi)
            cases = {"exp operator eager": lambda: F.exp(xi),
                     "exp operator compiled": lambda: exp_c(xi),
                     "exp closed form eager": lambda: F.exp_impl(xi),
                     "exp closed form compiled": lambda: exp_impl_c(xi),
                     "matrix_exp eager": lambda: torch.linalg.matrix_exp(X),
                     "matrix_exp compiled": lambda: mexp_c(X),
                     "exp+log fwd+bwd custom eager": lambda: custom(xi),
                     "exp+log fwd+bwd plain eager": lambda: plain(xi),
                     "exp+log fwd+bwd plain compiled": lambda: plain_c(xi),
                     # torch.compile's fixed cost per call (guards, wrappers) on one cheap operation
                     "xi * 2 eager": lambda: xi * 2,
                     "xi * 2 compiled": lambda: double_c(xi)}
            if pp is not None:
                x6 = torch.cat([xi[:, :3], xi[:, 6:9]], -1)
                lie = pp.se3(x6)
                cases["pypose SE3 Exp eager"] = lambda: lie.Exp()
            if args.cases:
                cases = {k: v for k, v in cases.items() if any(c in k for c in args.cases)}
            for name, fn in cases.items():
                # the first call, timed apart: compilation (torch.compile, and on CUDA the
                # operators' compiled closed forms), caches, allocator growth
                synchronize(device)
                t0 = time.perf_counter()
                with torch.no_grad() if "fwd+bwd" not in name else contextlib.nullcontext():
                    fn()
                synchronize(device)
                compile_s[f"{name} {dt_name} {n}"] = time.perf_counter() - t0
                with torch.no_grad() if "fwd+bwd" not in name else contextlib.nullcontext():
                    m = measure(fn, target_s=args.target_s, device=device)
                rows.append({"case": name, "dtype": dt_name, "n": n,
                             "ns_per_elem": 1e9 * m["median_s"] / n, "foreign_cpu": m["foreign_cpu"]})
                if cuda:
                    rows[-1]["cuda_peak_bytes"] = cuda_peak_bytes(fn, device)
                print(f"{dt_name} {n:>8} {name:34s} {rows[-1]['ns_per_elem']:10.1f} ns", file=sys.stderr)
    # Consistency: the operator on the device and the eager closed form on the CPU agree.
    xi = torch.randn(1000, 10, dtype=torch.float64, generator=gen)
    with torch.no_grad():
        agree = float((F.exp(xi.to(device)).cpu() - F.exp_impl(xi)).abs().max())

    def get(case, dt, n):
        for r in rows:
            if r["case"] == case and r["dtype"] == dt and r["n"] == n:
                return r["ns_per_elem"]
        return float("nan")

    ratio_rows = [("SGal3.exp (operator) vs matrix_exp eager (>= 10x)", "matrix_exp eager", "exp operator eager"),
                  ("SGal3.exp (operator) vs pypose SE3 Exp (>= 1x)", "pypose SE3 Exp eager", "exp operator eager"),
                  ("operator vs closed form compiled (the choice)", "exp closed form compiled",
                   "exp operator eager"),
                  ("compiled vs eager, the operator (>= 1x)", "exp operator eager", "exp operator compiled"),
                  ("compiled vs eager, xi * 2 (torch.compile's own cost per call)", "xi * 2 eager",
                   "xi * 2 compiled"),
                  ("operator vs closed form, eager", "exp closed form eager", "exp operator eager"),
                  ("SGal3.exp compiled vs matrix_exp compiled", "matrix_exp compiled", "exp operator compiled"),
                  ("custom vs plain autograd, eager", "exp+log fwd+bwd plain eager",
                   "exp+log fwd+bwd custom eager")]
    cols = [(dt, n) for dt in args.dtypes for n in args.sizes]
    where = f"{device_name(device)} ({device}), host {cpu_model()}" if cuda else cpu_model()
    md = [f"# SGal(3) under torch.compile ({where}, torch {torch.__version__}, "
          f"{torch.get_num_threads()} threads, {_dt.date.today()})", "",
          f"The operator on {device.type} and the eager closed form on the CPU agree to {agree:.1e} "
          "(float64).", "",
          *(["On CUDA the operator rows run the compiled closed forms (`native.use_compiled_cuda(True)`).",
             ""] if cuda else []),
          *([f"NOTE: {pp_missing}.", ""] if pp is None else []),
          "ns per element (medians):", "",
          "| case | " + " | ".join(f"{dt} {n:.0e}" for dt, n in cols) + " |",
          "|---|" + "---:|" * len(cols)]
    for case in dict.fromkeys(r["case"] for r in rows):
        md.append(f"| {case} | " + " | ".join(f"{get(case, dt, n):,.1f}" for dt, n in cols) + " |")
    md += ["", "Ratios (peer / ours):", "", "| ratio | " + " | ".join(f"{dt} {n:.0e}" for dt, n in cols)
           + " |", "|---|" + "---:|" * len(cols)]
    present = {r["case"] for r in rows}
    for label, peer, ours in ratio_rows:
        if peer not in present or ours not in present:  # not run (pypose not importable, --cases)
            continue
        md.append(f"| {label} | " + " | ".join(f"{get(peer, dt, n) / get(ours, dt, n):.1f}"
                                               for dt, n in cols) + " |")
    if cuda:
        md += ["", "CUDA peak memory of one call (max_memory_allocated minus the allocation before):", "",
               "| case | " + " | ".join(f"{dt} {n:.0e}" for dt, n in cols) + " |", "|---|" + "---:|" * len(cols)]
        peaks = {(r["case"], r["dtype"], r["n"]): r["cuda_peak_bytes"] for r in rows}
        for case in dict.fromkeys(r["case"] for r in rows):
            md.append(f"| {case} | " + " | ".join(fmt_bytes(peaks.get((case, dt, n))) for dt, n in cols) + " |")
    md += ["", "First calls over 0.5 s (compilation): " + ", ".join(
        f"{k}: {v:.1f} s" for k, v in compile_s.items() if v > 0.5), ""]
    payload = {"rows": rows, "compile_s": compile_s, "agree": agree, "threads": torch.get_num_threads(),
               "torch": torch.__version__}
    if cuda:
        payload.update(device=str(device), device_name=device_name(device), host_cpu=cpu_model(),
                       torch_cuda=torch.version.cuda)
    stem = f"compile_{device.type}"
    os.makedirs(args.out, exist_ok=True)
    Path(args.out, f"{stem}.md").write_text("\n".join(md))
    Path(args.out, f"{stem}.json").write_text(json.dumps(payload, indent=2))
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    sys.exit(main())
