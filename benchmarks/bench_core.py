#!/usr/bin/env python
"""Core-operation benchmark: torchsgal against its peers, all in the same run.

What is timed (ns per batch element, median over samples; see ``_timing.measure``):

* torchsgal, for SO2 / SE2 / SO3 / SE3 / SE23 / SGal3 / Sim3: ``G.exp(xi)``, ``g.log()``, ``g @ h``,
  ``g.inverse()``, ``g.act(p)`` (points (...,3), (...,2) for SO2/SE2; events (...,4) for SGal3),
  ``g.act_jacobians(p)`` (both Jacobians of the action, one element per point), ``g.adjoint()``,
  ``G.jl(xi)``, and the functional layer ``ts.functional.<g>.exp(xi)`` (-> matrix) / ``.log(M)``;
  for the groups with C kernels (``functional.ops.GROUPS``: all but SO2) exp, log, compose,
  inverse and adjoint again with the kernels off (rows "[tensor code]").
* peers on the same group, batch, dtype and device:
  - ``torch.linalg.matrix_exp(G.hat(xi))`` (hat matrix built outside the timed region);
  - pypose ``pp.so3(x).Exp()``, ``pp.SO3(q).Log()``, ``pp.se3(x).Exp()``, ``pp.SE3(T).Log()``,
    ``pp.sim3(x).Exp()``, ``pp.Sim3(T).Log()``
    (LieTensors built outside the timed region; pypose's se3 is [translation, rotation],
    its SE3 is [t, quaternion xyzw], its sim3 [translation, rotation, log-scale]; inputs are
    i.i.d. so the ordering does not change the work done);
  - GTSAM ``Rot2/Pose2/Rot3/Pose3/NavState/Gal3/Similarity3.Expmap`` and ``.Logmap`` called in a Python loop over
    ``--gtsam-n`` numpy rows (float64 only; the per-element figure includes the Python
    loop and the pybind11 call overhead, which is what a Python user of GTSAM pays);
* autograd for ``xi -> log(exp(xi)) -> sum -> backward``: the custom ``autograd.Function``
  (``functional.<g>.exp`` / ``.log``) against plain autograd through the same closed form
  (``exp_impl`` / ``log_impl``), forward+backward time and memory held for backward.

Memory measure (CPU): the bytes of all tensors that autograd keeps alive between forward
and backward, i.e. everything passed through ``torch.autograd.graph.saved_tensors_hooks``
plus tensors stored as attributes on custom-Function ``ctx`` objects found by walking the
graph, de-duplicated by storage, and excluding the input ``xi`` itself.  This is the
part of peak memory that differs between the two implementations (transient temporaries
are not included; torch's CPU allocator has no peak counter).  On CUDA the true peak,
``torch.cuda.max_memory_allocated()`` minus the allocation before the step, is reported
as well.

Usage::

    python benchmarks/bench_core.py                 # full run: sizes 1e3,1e5,1e6, fp32+fp64
    python benchmarks/bench_core.py --quick         # smoke run, small sizes, few repeats
    python benchmarks/bench_core.py --device cuda --sizes 1e3,1e6 --dtypes float32
"""
from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
import traceback
from pathlib import Path

import torch

_HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(_HERE))
sys.path.insert(1, str(_HERE.parent))  # benchmark the checkout this script lives in
from _timing import (  # noqa: E402
    cpu_model,
    environment,
    fmt_bytes,
    fmt_ns,
    loadavg,
    measure,
    mem_available_bytes,
    synchronize,
    wait_for_idle,
)

GROUPS = ("SO2", "SE2", "SO3", "SE3", "SE23", "SGal3", "Sim3")
FUNCTIONAL = {"SO2": "so2", "SE2": "se2", "SO3": "so3", "SE3": "se3", "SE23": "se23", "SGal3": "sgal3",
              "Sim3": "sim3"}
DOF = {"SO2": 1, "SE2": 3, "SO3": 3, "SE3": 6, "SE23": 9, "SGal3": 10, "Sim3": 7}
MDIM = {"SO2": 2, "SE2": 3, "SO3": 3, "SE3": 4, "SE23": 5, "SGal3": 5, "Sim3": 4}
POINT_DIM = {"SO2": 2, "SE2": 2, "SO3": 3, "SE3": 3, "SE23": 3, "SGal3": 4, "Sim3": 3}
PYPOSE_GROUPS = ("SO3", "SE3", "Sim3")  # groups pypose has
OPS = ("exp", "log", "compose", "inverse", "act", "act_jacobians", "adjoint", "jl", "F.exp", "F.log")
# Ops that run as C kernels where torchsgal.functional.native has them (SGal3, SE3 and SE23 on
# the CPU), timed again with the kernels off: rows "<op> [tensor code]".
NATIVE_OPS = ("exp", "log", "compose", "inverse", "adjoint")
TENSOR_CODE = " [tensor code]"


def has_native(ts, group, device) -> bool:
    native = ts.functional.native
    return (torch.device(device).type == "cpu" and native.available() and native.enabled()
            and group in ts.functional.ops.GROUPS)
GTSAM_CLASS = {"SO2": "Rot2", "SE2": "Pose2", "SO3": "Rot3", "SE3": "Pose3", "SE23": "NavState",
               "SGal3": "Gal3", "Sim3": "Similarity3"}
TANGENT_SCALE = 0.5  # xi ~ N(0, 0.5^2) per component: rotation angles mostly in (0, 2)

# Targets of the project (ratio = peer time / torchsgal time unless said otherwise).
TARGET_MATRIX_EXP = 10.0
TARGET_PYPOSE = 1.0
TARGET_AUTOGRAD = 2.0
BUSY = 0.10  # flag a measurement when other processes used more than this share of the CPU


# --------------------------------------------------------------------------------------
# bookkeeping
# --------------------------------------------------------------------------------------
class Results:
    def __init__(self):
        self.records: list[dict] = []

    def add(self, **rec):
        self.records.append(rec)
        return rec

    def get(self, **key):
        for r in self.records:
            if all(r.get(k) == v for k, v in key.items()):
                return r
        return None

    def ns(self, **key):
        r = self.get(**key)
        return None if r is None else r.get("ns_per_elem")


def log(msg: str = "") -> None:
    print(msg, flush=True)


def time_case(res: Results, args, fn, *, n_elem: int, **key) -> dict:
    try:
        m = measure(fn, device=args.device, target_s=args.target, min_repeats=args.min_repeats,
                    min_sample_s=args.min_sample)
    except Exception as e:  # record and go on: one broken op must not kill the run
        r = res.add(**key, size=n_elem, status="error", error=f"{type(e).__name__}: {e}")
        log(f"  {key.get('group', ''):6s} {key.get('op', ''):8s} {key.get('impl', ''):22s} "
            f"n={n_elem:<8d} ERROR {r['error'][:120]}")
        if args.verbose:
            traceback.print_exc()
        return r
    ns = m["median_s"] / n_elem * 1e9
    r = res.add(**key, size=n_elem, status="ok", ns_per_elem=ns, **m)
    busy = m.get("foreign_cpu")
    log(f"  {key.get('group', ''):6s} {key.get('op', ''):8s} {key.get('impl', ''):22s} "
        f"n={n_elem:<8d} {ns:10.2f} ns/elem  ({m['repeats']}x{m['number']})"
        + (f"  [other processes used {busy:.0%} of the CPU]" if busy is not None and busy > BUSY else ""))
    return r


def skip_case(res: Results, reason: str, *, n_elem: int, **key) -> None:
    res.add(**key, size=n_elem, status="skipped", reason=reason)
    log(f"  {key.get('group', ''):6s} {key.get('op', ''):8s} {key.get('impl', ''):22s} "
        f"n={n_elem:<8d} skipped: {reason}")


HEAVY_LIMIT = 100_000  # default: slow peer / autograd cases above this size only for SGal3


def heavy_skip_reason(args, group: str, n: int) -> str | None:
    """The default run keeps to ~10 min on 2 cores by timing the slow cases (matrix_exp peer,
    autograd fwd+bwd) at n > 1e5 only for SGal3, the group the targets are about."""
    if args.full or group == "SGal3" or n <= HEAVY_LIMIT:
        return None
    return f"n > {HEAVY_LIMIT:g} timed for SGal3 only (run with --full for all groups)"


def randn(shape, dtype, device, gen, scale=1.0):
    # Generated on the CPU so that inputs are identical across devices.
    return (torch.randn(shape, generator=gen, dtype=torch.float64) * scale).to(dtype=dtype, device=device)


# --------------------------------------------------------------------------------------
# memory held for backward
# --------------------------------------------------------------------------------------
def _collect_ctx_tensors(root, exclude: set, storages: dict) -> None:
    """Tensors stored as attributes of custom-Function ctx objects in the graph."""
    seen, stack = set(), [root]
    while stack:
        node = stack.pop()
        if node is None or id(node) in seen:
            continue
        seen.add(id(node))
        attrs = getattr(node, "__dict__", None) or {}
        for v in attrs.values():
            vals = v if isinstance(v, (list, tuple)) else (v,)
            for t in vals:
                if isinstance(t, torch.Tensor):
                    _add_storage(t, exclude, storages)
        stack.extend(f for f, _ in getattr(node, "next_functions", ()))


def _add_storage(t: torch.Tensor, exclude: set, storages: dict) -> None:
    try:
        s = t.untyped_storage()
    except Exception:
        return
    key = (str(t.device), s.data_ptr())
    if key in exclude or s.nbytes() == 0:
        return
    storages[key] = max(storages.get(key, 0), s.nbytes())


def saved_bytes(forward, inp: torch.Tensor) -> int:
    exclude = {(str(inp.device), inp.untyped_storage().data_ptr())}
    storages: dict = {}

    def pack(t):
        _add_storage(t, exclude, storages)
        return t

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        out = forward()
    if out.grad_fn is not None:
        _collect_ctx_tensors(out.grad_fn, exclude, storages)
    total = sum(storages.values())
    del out
    return total


# --------------------------------------------------------------------------------------
# sections
# --------------------------------------------------------------------------------------
def bench_torchsgal(res, args, ts, group, n, dtype, device, gen):
    G = getattr(ts, group)
    Fm = getattr(ts.functional, FUNCTIONAL[group])
    dof = DOF[group]
    key = dict(section="torchsgal", group=group, impl="torchsgal", dtype=str(dtype).split(".")[-1])
    xi = randn((n, dof), dtype, device, gen, TANGENT_SCALE)
    xi2 = randn((n, dof), dtype, device, gen, TANGENT_SCALE)
    g = G.exp(xi)
    h = G.exp(xi2)
    p = randn((n, POINT_DIM[group]), dtype, device, gen)
    M = Fm.exp(xi)
    fns = {
        "exp": lambda: G.exp(xi),
        "log": lambda: g.log(),
        "compose": lambda: g @ h,
        "inverse": lambda: g.inverse(),
        "act": lambda: g.act(p),
        "act_jacobians": lambda: g.act_jacobians(p),
        "adjoint": lambda: g.adjoint(),
        "jl": lambda: G.jl(xi),
        "F.exp": lambda: Fm.exp(xi),
        "F.log": lambda: Fm.log(M),
    }
    for op in OPS:
        time_case(res, args, fns[op], n_elem=n, op=op, **key)
    if has_native(ts, group, device):  # the same calls on the tensor code, for comparison
        with ts.functional.native.disabled():
            for op in NATIVE_OPS:
                time_case(res, args, fns[op], n_elem=n, op=op + TENSOR_CODE, **key)


def bench_matrix_exp(res, args, ts, group, n, dtype, device, gen):
    key = dict(section="peer", group=group, op="exp", impl="torch.linalg.matrix_exp",
               dtype=str(dtype).split(".")[-1])
    k = MDIM[group]
    itemsize = torch.finfo(dtype).bits // 8
    est = n * k * k * itemsize * 16  # input + Pade/Taylor temporaries, generous
    avail = mem_available_bytes() if torch.device(device).type == "cpu" else None
    if avail is not None and est > 0.5 * avail:
        return skip_case(res, f"needs ~{fmt_bytes(est)}, only {fmt_bytes(avail)} available", n_elem=n, **key)
    if n > args.matrix_exp_max:
        return skip_case(res, f"n > --matrix-exp-max={args.matrix_exp_max:g}", n_elem=n, **key)
    reason = heavy_skip_reason(args, group, n)
    if reason:
        return skip_case(res, reason, n_elem=n, **key)
    G = getattr(ts, group)
    xi = randn((n, DOF[group]), dtype, device, gen, TANGENT_SCALE)
    A = G.hat(xi).contiguous()
    del xi
    time_case(res, args, lambda: torch.linalg.matrix_exp(A), n_elem=n, **key)


def bench_pypose(res, args, pp, n, dtype, device, gen):
    dt = str(dtype).split(".")[-1]
    x6 = randn((n, 6), dtype, device, gen, TANGENT_SCALE)
    x3 = x6[:, 3:].contiguous()
    so3 = pp.so3(x3)
    q = so3.Exp()
    se3 = pp.se3(x6)
    T = se3.Exp()
    sim3 = pp.sim3(randn((n, 7), dtype, device, gen, TANGENT_SCALE))
    S = sim3.Exp()
    cases = [
        ("SO3", "exp", lambda: so3.Exp()),
        ("SO3", "log", lambda: q.Log()),
        ("SE3", "exp", lambda: se3.Exp()),
        ("SE3", "log", lambda: T.Log()),
        ("Sim3", "exp", lambda: sim3.Exp()),
        ("Sim3", "log", lambda: S.Log()),
    ]
    for group, op, fn in cases:
        if group in args.groups:
            time_case(res, args, fn, n_elem=n, section="peer", group=group, op=op, impl="pypose", dtype=dt)


def bench_gtsam(res, args, gtsam, gen):
    import numpy as np

    n = args.gtsam_n
    for group in args.groups:
        cls = getattr(gtsam, GTSAM_CLASS[group], None)
        key = dict(section="gtsam", group=group, impl=f"gtsam.{GTSAM_CLASS[group]} (Python loop)",
                   dtype="float64")
        if cls is None:
            for op in ("exp", "log"):
                skip_case(res, f"gtsam has no {GTSAM_CLASS[group]}", n_elem=n, op=op, **key)
            continue
        xs = (torch.randn((n, DOF[group]), generator=gen, dtype=torch.float64) * TANGENT_SCALE).numpy()
        rows = [np.ascontiguousarray(r) for r in xs]
        elems = [cls.Expmap(r) for r in rows]
        expmap, logmap = cls.Expmap, cls.Logmap

        def run_exp():
            for r in rows:
                expmap(r)

        def run_log():
            for e in elems:
                logmap(e)

        time_case(res, args, run_exp, n_elem=n, op="exp", **key)
        time_case(res, args, run_log, n_elem=n, op="log", **key)


def bench_autograd(res, args, ts, pp, group, n, dtype, device, gen, bytes_per_elem):
    dt = str(dtype).split(".")[-1]
    Fm = getattr(ts.functional, FUNCTIONAL[group])
    xi0 = randn((n, DOF[group]), dtype, device, gen, TANGENT_SCALE)
    impls = {
        "custom Function": lambda x: Fm.log(Fm.exp(x)),
        "plain autograd": lambda x: Fm.log_impl(Fm.exp_impl(x)),
    }
    if has_native(ts, group, device):
        impls["custom Function" + TENSOR_CODE] = lambda x: Fm.log(Fm.exp(x))
    if pp is not None and group in PYPOSE_GROUPS:
        lie = {"SO3": pp.so3, "SE3": pp.se3, "Sim3": pp.sim3}[group]
        impls["pypose"] = lambda x: lie(x).Exp().Log().tensor()
    grads = {}
    for impl, f in impls.items():
        key = dict(section="autograd", group=group, op="log(exp(xi)) fwd+bwd", impl=impl, dtype=dt)
        avail = mem_available_bytes() if torch.device(device).type == "cpu" else None
        est = bytes_per_elem.get((group, impl, dt))
        if avail is not None and est is not None and 3 * est * n > 0.5 * avail:
            skip_case(res, f"would hold ~{fmt_bytes(est * n)} for backward; {fmt_bytes(avail)} free",
                      n_elem=n, **key)
            continue
        xi = xi0.clone().requires_grad_(True)

        def step(xi=xi, f=f, off=impl.endswith(TENSOR_CODE)):  # noqa: B008 (binds this case's values)
            xi.grad = None
            with ts.functional.native.disabled() if off else contextlib.nullcontext():
                f(xi).sum().backward()  # forward and backward

        try:
            with ts.functional.native.disabled() if impl.endswith(TENSOR_CODE) else contextlib.nullcontext():
                sb = saved_bytes(lambda: f(xi), xi)
            bytes_per_elem[(group, impl, dt)] = sb / n
            if n == min(args.sizes):  # gradient agreement check, once per group/dtype
                step()
                grads[impl] = xi.grad.detach().clone()
        except Exception as e:
            res.add(**key, size=n, status="error", error=f"{type(e).__name__}: {e}")
            log(f"  {group:6s} autograd {impl:22s} n={n:<8d} ERROR {type(e).__name__}: {str(e)[:120]}")
            if args.verbose:
                traceback.print_exc()
            continue
        peak = None
        if torch.device(device).type == "cuda":
            synchronize(device)
            torch.cuda.reset_peak_memory_stats(device)
            base = torch.cuda.memory_allocated(device)
            step()
            synchronize(device)
            peak = torch.cuda.max_memory_allocated(device) - base
        r = time_case(res, args, step, n_elem=n, **key)
        r["saved_bytes"] = sb
        r["cuda_peak_bytes"] = peak
        log(f"{'':48s} saved for backward: {fmt_bytes(sb)} ({sb / n:.0f} B/elem)"
            + ("" if peak is None else f", CUDA peak {fmt_bytes(peak)}"))
    if "custom Function" in grads and "plain autograd" in grads:
        d = (grads["custom Function"] - grads["plain autograd"]).abs().max().item()
        r = res.get(section="autograd", group=group, impl="custom Function", dtype=dt, size=n)
        if r is not None:
            r["grad_maxabs_diff_vs_plain"] = d


# --------------------------------------------------------------------------------------
# report
# --------------------------------------------------------------------------------------
def ratio(peer, ours):
    if peer is None or ours is None or ours <= 0:
        return None
    return peer / ours





def fmt_ratio(x, target=None):
    if x is None:
        return "–"
    s = f"{x:.1f}x" if x >= 10 else f"{x:.2f}x"
    if target is not None:
        s += " ✓" if x >= target else " ✗"
    return s


def busy_mark(r) -> str:
    b = r.get("foreign_cpu")
    return " †" if b is not None and b > BUSY else ""


def cell(res, **key):
    r = res.get(**key)
    if r is None:
        return "–"
    if r["status"] == "ok":
        return fmt_ns(r["ns_per_elem"]) + busy_mark(r)
    if r["status"] == "skipped":
        return "skipped¹"
    return "error"


def compute_ratios(res, args):
    """Rows of {name, dtype, size, ratio, target, meaning, busy}; ratio = peer / torchsgal."""
    rows = []
    mx_impl = "torch.linalg.matrix_exp"
    for dt in args.dtype_names:
        for n in args.sizes:
            def add(name, peer_key, ours_key, target, field="ns_per_elem", meaning="speed-up"):
                p = res.get(dtype=dt, size=n, **peer_key)
                o = res.get(dtype=dt, size=n, **ours_key)
                pv = p.get(field) if p and p.get("status") == "ok" else None
                ov = o.get(field) if o and o.get("status") == "ok" else None
                busy = any(r is not None and r.get("status") == "ok" and bool(busy_mark(r))
                           for r in (p, o)) and field == "ns_per_elem"
                rows.append(dict(name=name, dtype=dt, size=n, ratio=ratio(pv, ov), target=target,
                                 meaning=meaning, busy=busy))

            if "SGal3" in args.groups:
                mx = dict(section="peer", group="SGal3", op="exp", impl=mx_impl)
                add("SGal3.exp vs matrix_exp(hat)", mx,
                    dict(section="torchsgal", group="SGal3", op="exp"), TARGET_MATRIX_EXP)
                add("functional.sgal3.exp vs matrix_exp(hat)", mx,
                    dict(section="torchsgal", group="SGal3", op="F.exp"), TARGET_MATRIX_EXP)
                add("SGal3.exp [tensor code] vs matrix_exp(hat)", mx,
                    dict(section="torchsgal", group="SGal3", op="exp" + TENSOR_CODE), None)
                add("SGal3.exp vs pypose SE3 Exp (per element)",
                    dict(section="peer", group="SE3", op="exp", impl="pypose"),
                    dict(section="torchsgal", group="SGal3", op="exp"), TARGET_PYPOSE)
            for g in args.groups:
                if g in PYPOSE_GROUPS:
                    for op in ("exp", "log"):
                        add(f"{g}.{op} vs pypose {g} {op.capitalize()}",
                            dict(section="peer", group=g, op=op, impl="pypose"),
                            dict(section="torchsgal", group=g, op=op), TARGET_PYPOSE)
                if g != "SGal3":
                    add(f"{g}.exp vs matrix_exp(hat)", dict(section="peer", group=g, op="exp", impl=mx_impl),
                        dict(section="torchsgal", group=g, op="exp"), None)
            for g in args.groups:
                plain = dict(section="autograd", group=g, impl="plain autograd")
                custom = dict(section="autograd", group=g, impl="custom Function")
                add(f"{g} custom Function vs plain autograd, exp+log fwd+bwd (time)", plain, custom,
                    TARGET_AUTOGRAD if g == "SGal3" else None)
                add(f"{g} custom Function [tensor code] vs plain autograd, exp+log fwd+bwd (time)", plain,
                    dict(section="autograd", group=g, impl="custom Function" + TENSOR_CODE), None)
                add(f"{g} custom Function vs plain autograd, exp+log (memory held for bwd)", plain, custom,
                    1.0 if g == "SGal3" else None, field="saved_bytes", meaning="plain/custom bytes")
    return rows


def write_markdown(path: Path, res: Results, ratios, env, args) -> None:
    L = []
    L.append(f"# torchsgal core benchmark ({env['device_name']}, {env['date']})\n")
    L.append("| | |\n|---|---|")
    for k in ("torch", "device", "device_name", "cpu_model", "torch_num_threads", "python", "platform",
              "torchsgal", "native_kernels", "pypose", "gtsam", "command", "wall_s",
              "loadavg_at_start", "loadavg_at_end", "warning"):
        if k == "warning" and k not in env:
            continue
        L.append(f"| {k} | {env.get(k)} |")
    L.append("")
    L.append("All figures are **ns per batch element** (median over samples; one untimed warm-up; "
             f"adaptive repeats targeting ~{args.target} s per case, at least {args.min_repeats} samples). "
             "Lower is better.\n")

    sizes = args.sizes
    head = "| group | op | " + " | ".join(f"n={fmt_n(n)}" for n in sizes) + " |"
    sep = "|---|---|" + "---:|" * len(sizes)
    for dt in args.dtype_names:
        L.append(f"## torchsgal, {dt}\n")
        L.append(head)
        L.append(sep)
        for g in args.groups:
            for op in OPS + tuple(o + TENSOR_CODE for o in NATIVE_OPS):
                if not any(res.get(section="torchsgal", group=g, op=op, dtype=dt, size=n) for n in sizes):
                    continue
                L.append(f"| {g} | {op} | " + " | ".join(
                    cell(res, section="torchsgal", group=g, op=op, dtype=dt, size=n) for n in sizes) + " |")
        L.append("")
        L.append(f"## Peers, {dt}\n")
        L.append("| group | op | impl | " + " | ".join(f"n={fmt_n(n)}" for n in sizes) + " |")
        L.append("|---|---|---|" + "---:|" * len(sizes))
        for r_g in args.groups:
            for impl, ops in (("torch.linalg.matrix_exp", ("exp",)), ("pypose", ("exp", "log"))):
                for op in ops:
                    if not any(res.get(section="peer", group=r_g, op=op, impl=impl, dtype=dt, size=n)
                               for n in sizes):
                        continue
                    L.append(f"| {r_g} | {op} | {impl} | " + " | ".join(
                        cell(res, section="peer", group=r_g, op=op, impl=impl, dtype=dt, size=n)
                        for n in sizes) + " |")
        L.append("")
        L.append(f"## Autograd: xi -> log(exp(xi)) -> sum -> backward, {dt}\n")
        L.append("Time is forward+backward ns per element; memory is the bytes autograd holds for "
                 "backward (saved tensors + custom-Function ctx tensors, de-duplicated by storage, "
                 "excluding xi)" + ("; CUDA peak is max_memory_allocated during the step" if
                                    args.device.startswith("cuda") else "") + ".\n")
        L.append("| group | impl | " + " | ".join(f"n={fmt_n(n)} time | mem" for n in sizes) + " |")
        L.append("|---|---|" + "---:|---:|" * len(sizes))
        for g in args.groups:
            for impl in ("custom Function", "custom Function" + TENSOR_CODE, "plain autograd", "pypose"):
                rs = [res.get(section="autograd", group=g, impl=impl, dtype=dt, size=n) for n in sizes]
                if not any(rs):
                    continue
                cells = []
                for r in rs:
                    if r is None:
                        cells += ["–", "–"]
                    elif r["status"] != "ok":
                        cells += ["skipped¹" if r["status"] == "skipped" else "error", "–"]
                    else:
                        mem = fmt_bytes(r.get("saved_bytes"))
                        if r.get("cuda_peak_bytes") is not None:
                            mem += f" (peak {fmt_bytes(r['cuda_peak_bytes'])})"
                        cells += [fmt_ns(r["ns_per_elem"]) + busy_mark(r), mem]
                L.append(f"| {g} | {impl} | " + " | ".join(cells) + " |")
        L.append("")
        diffs = [(g, r["size"], r["grad_maxabs_diff_vs_plain"]) for g in args.groups
                 if (r := res.get(section="autograd", group=g, impl="custom Function", dtype=dt,
                                  size=min(sizes))) and "grad_maxabs_diff_vs_plain" in r]
        if diffs:
            L.append("Gradient check, max |grad(custom) - grad(plain)|: "
                     + ", ".join(f"{g} {d:.2g}" for g, _, d in diffs) + f" (n={min(sizes)}).\n")

    gt = [r for r in res.records if r["section"] == "gtsam"]
    if gt:
        L.append(f"## GTSAM (float64, Python loop over n={args.gtsam_n} calls, ns per call)\n")
        L.append("| group | class | exp | log |\n|---|---|---:|---:|")
        for g in args.groups:
            L.append(f"| {g} | gtsam.{GTSAM_CLASS[g]} | "
                     f"{cell(res, section='gtsam', group=g, op='exp')} | "
                     f"{cell(res, section='gtsam', group=g, op='log')} |")
        L.append("")
        L.append("GTSAM is a per-element C++ call; the figure includes the Python loop and pybind11 "
                 "overhead. For comparison, torchsgal float64, batched, per element: "
                 + ", ".join(f"{g}.exp "
                             + fmt_ns(res.ns(section='torchsgal', group=g, op='exp', dtype='float64',
                                             size=min(args.sizes)))
                             for g in args.groups) + f" ns (n={min(args.sizes)}).\n")

    L.append("## Ratios against the project's targets\n")
    L.append("Ratio = peer time / torchsgal time (>1 means torchsgal is faster); for memory "
             "plain-autograd bytes / custom-Function bytes. ✓/✗ against the target where one is set.\n")
    L.append("| comparison | target | " + " | ".join(
        f"{dt} n={fmt_n(n)}" for dt in args.dtype_names for n in sizes) + " |")
    L.append("|---|---|" + "---:|" * (len(sizes) * len(args.dtype_names)))
    names = list(dict.fromkeys(r["name"] for r in ratios))
    for name in names:
        rs = {(r["dtype"], r["size"]): r for r in ratios if r["name"] == name}
        if all(r["ratio"] is None for r in rs.values()):
            continue  # e.g. the tensor-code rows where no C kernels are compiled
        tgt = next(iter(rs.values()))["target"]
        tgt_s = "–" if tgt is None else (f">= {tgt:g}x" if "memory" not in name else "> 1x")
        L.append(f"| {name} | {tgt_s} | " + " | ".join(
            fmt_ratio(rs[(dt, n)]["ratio"], rs[(dt, n)]["target"])
            + (" †" if rs[(dt, n)]["busy"] and rs[(dt, n)]["ratio"] is not None else "")
            for dt in args.dtype_names for n in sizes) + " |")
    L.append("")
    busy = [r for r in res.records if r["status"] == "ok" and busy_mark(r)]
    L.append(f"† other processes used more than {BUSY:.0%} of the machine's CPU during this "
             f"measurement ({len(busy)} of {sum(r['status'] == 'ok' for r in res.records)} cases; "
             "read from /proc/stat minus this process): treat it as an upper bound.\n")
    skipped = [r for r in res.records if r["status"] == "skipped"]
    errors = [r for r in res.records if r["status"] == "error"]
    if skipped:
        L.append("¹ Skipped cases:\n")
        by_reason: dict = {}
        for r in skipped:
            by_reason.setdefault(r["reason"], []).append(
                f"{r['group']} {r['op']} [{r['impl']}] {r['dtype']} n={fmt_n(r['size'])}")
        for reason, cases in by_reason.items():
            L.append(f"- {reason}: " + "; ".join(cases))
        L.append("")
    if errors:
        L.append("Errors:\n")
        for r in errors:
            L.append(f"- {r['group']} {r['op']} [{r['impl']}] {r['dtype']} n={r['size']}: `{r['error'][:200]}`")
        L.append("")
    L.append("Notes: inputs are created outside the timed region (xi ~ N(0, 0.5²) per component; "
             "group elements via G.exp; points/events ~ N(0, 1)); the matrix_exp peer receives "
             "the precomputed hat matrix; pypose LieTensors are constructed outside the timed "
             "region; torch threads are left at the default; CUDA timings are synchronised.")
    path.write_text("\n".join(L) + "\n")


def print_ratios(ratios):
    log("\n=== ratios (peer / torchsgal; >1 = torchsgal faster) ===")
    for r in ratios:
        if r["ratio"] is None:
            continue
        verdict = "OK" if r["target"] is not None and r["ratio"] >= r["target"] else "MISSED"
        tgt = "" if r["target"] is None else f"  [target >= {r['target']:g}x: {verdict}]"
        busy = "  (measured while other processes were busy)" if r["busy"] else ""
        log(f"  {r['name']:75s} {r['dtype']:8s} n={r['size']:<8d} {fmt_ratio(r['ratio'])}{tgt}{busy}")


# --------------------------------------------------------------------------------------
def fmt_n(n: int) -> str:
    """1000 -> 1e3, 100000 -> 1e5, 20000 -> 2e4, 1234 -> 1234."""
    m, e = f"{n:.0e}".split("e")
    return f"{m}e{int(e)}" if float(f"{m}e{e}") == n else str(n)


def parse_sizes(s: str) -> list[int]:
    return [int(float(x)) for x in s.split(",") if x.strip()]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", type=parse_sizes, default=None, help="comma list, e.g. 1e3,1e5,1e6")
    ap.add_argument("--dtypes", default="float32,float64", help="comma list (default float32,float64)")
    ap.add_argument("--device", default="cpu", help="cpu or cuda[:i] (default cpu)")
    ap.add_argument("--groups", default=",".join(GROUPS), help="comma list (default all seven)")
    ap.add_argument("--quick", action="store_true", help="smoke run: small sizes, few repeats")
    ap.add_argument("--full", action="store_true",
                    help="also time matrix_exp and autograd at n > 1e5 for SO3/SE3/SE23 (slow)")
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent / "results"),
                    help="output directory (default benchmarks/results)")
    ap.add_argument("--tag", default=None, help="file stem (default core_<device>[_quick], the canonical result file; "
                         "give another stem for a partial run such as --groups SGal3)")
    ap.add_argument("--target", type=float, default=None, help="seconds per measurement (default 0.4)")
    ap.add_argument("--min-repeats", type=int, default=3)
    ap.add_argument("--gtsam-n", type=int, default=None, help="calls in the GTSAM loop (default 10000)")
    ap.add_argument("--matrix-exp-max", type=float, default=1e6, help="largest batch for the matrix_exp peer")
    ap.add_argument("--autograd-max", type=float, default=1e6, help="largest batch for the autograd section")
    ap.add_argument("--skip", default="", help="comma list of sections to skip: "
                    "torchsgal,matrix_exp,pypose,gtsam,autograd")
    ap.add_argument("--wait-idle", type=float, default=0.0, metavar="SECONDS",
                    help="before starting, wait up to SECONDS for the 1-min load average to drop "
                         "below 0.5 (other processes distort multi-threaded timings)")
    ap.add_argument("--threads", type=int, default=None,
                    help="torch.set_num_threads(N) (default: leave torch's default alone); "
                         "1 is less sensitive to other processes on a small machine")
    ap.add_argument("--verbose", action="store_true")
    args = ap.parse_args(argv)

    if args.sizes is None:
        args.sizes = [1000, 10000] if args.quick else [1000, 100000, 1000000]
    if args.target is None:
        args.target = 0.05 if args.quick else 0.4
    args.min_sample = 0.005 if args.quick else 0.02
    if args.gtsam_n is None:
        args.gtsam_n = 500 if args.quick else 10000
    args.groups = [g for g in args.groups.split(",") if g]
    args.dtype_names = [d.strip() for d in args.dtypes.split(",") if d.strip()]
    dtypes = [getattr(torch, d) for d in args.dtype_names]
    skip = set(s for s in args.skip.split(",") if s)
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        sys.exit("CUDA requested but torch.cuda.is_available() is False")

    wait_for_idle(args.wait_idle)
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    t_start = time.time()
    env = environment(
        "bench_core.py", argv,
        device=str(device),
        device_name=torch.cuda.get_device_name(device) if device.type == "cuda" else cpu_model(),
        memory_measure="bytes held for backward: saved_tensors_hooks + custom-Function ctx tensor "
                       "attributes, de-duplicated by storage, excluding the input"
                       + ("; plus torch.cuda.max_memory_allocated peak" if device.type == "cuda" else ""),
        timing=f"median of >= {args.min_repeats} samples, adaptive repeats targeting {args.target} s, "
               "one untimed warm-up, gc disabled while timing",
    )
    load_start = env["loadavg_at_start"]

    try:
        import torchsgal as ts

        _ = (ts.SO3, ts.functional)  # fail early if the package is not there yet
    except Exception as e:
        ts = None
        env["torchsgal"] = f"not importable ({type(e).__name__}: {e})"
        log(f"WARNING: torchsgal not importable ({e}); running peer sections only")
    try:
        import pypose as pp

        env["pypose"] = pp.__version__
    except Exception as e:
        pp = None
        env["pypose"] = f"not importable ({e})"
    try:
        import gtsam

        env["gtsam"] = getattr(gtsam, "__version__", "installed")
    except Exception as e:
        gtsam = None
        env["gtsam"] = f"not importable ({e})"

    if ts is not None:
        nat = ts.functional.native
        env["native_kernels"] = ("enabled" if nat.enabled() else "compiled, switched off" if nat.available()
                                 else "not compiled")
    log(f"torch {env['torch']} | {env['device_name']} | threads {env['torch_num_threads']} | "
        f"sizes {args.sizes} | dtypes {args.dtype_names} | target {args.target}s/case")

    res = Results()
    gen = torch.Generator().manual_seed(0)
    bytes_per_elem: dict = {}
    for dtype in dtypes:
        for n in args.sizes:
            log(f"\n--- {str(dtype).split('.')[-1]}, n={n} ---")
            for group in args.groups:
                if ts is not None and "torchsgal" not in skip:
                    try:
                        bench_torchsgal(res, args, ts, group, n, dtype, device, gen)
                    except Exception as e:
                        log(f"  {group} torchsgal setup failed: {type(e).__name__}: {e}")
                        if args.verbose:
                            traceback.print_exc()
                if ts is not None and "matrix_exp" not in skip:
                    try:
                        bench_matrix_exp(res, args, ts, group, n, dtype, device, gen)
                    except Exception as e:
                        log(f"  {group} matrix_exp setup failed: {type(e).__name__}: {e}")
            if pp is not None and "pypose" not in skip:
                bench_pypose(res, args, pp, n, dtype, device, gen)
            if ts is not None and "autograd" not in skip:
                for group in args.groups:
                    key = dict(section="autograd", group=group, op="log(exp(xi)) fwd+bwd",
                               dtype=str(dtype).split(".")[-1])
                    reason = (f"n > --autograd-max={args.autograd_max:g}" if n > args.autograd_max
                              else heavy_skip_reason(args, group, n))
                    if reason:
                        impls = ("custom Function", "plain autograd") + (
                            ("pypose",) if pp is not None and group in PYPOSE_GROUPS else ())
                        for impl in impls:
                            skip_case(res, reason, n_elem=n, impl=impl, **key)
                        continue
                    bench_autograd(res, args, ts, pp, group, n, dtype, device, gen, bytes_per_elem)
    if gtsam is not None and "gtsam" not in skip:
        log(f"\n--- GTSAM, float64, Python loop of {args.gtsam_n} calls ---")
        bench_gtsam(res, args, gtsam, gen)

    env["wall_s"] = round(time.time() - t_start, 1)
    env["loadavg_at_end"] = loadavg()
    if load_start is not None and load_start[0] > 0.5:
        env["warning"] = (f"1-min load average was {load_start[0]:.2f} at start: other processes were "
                          "using the CPU, so timings (especially multi-threaded ones) may be inflated")
        log("WARNING: " + env["warning"])
    ratios = compute_ratios(res, args)
    print_ratios(ratios)

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    stem = args.tag or f"core_{device.type}" + ("_quick" if args.quick else "")
    payload = {"env": env, "args": {k: v for k, v in vars(args).items()}, "records": res.records,
               "ratios": ratios}
    (out / f"{stem}.json").write_text(json.dumps(payload, indent=1, default=str) + "\n")
    write_markdown(out / f"{stem}.md", res, ratios, env, args)
    log(f"\nwrote {out / (stem + '.json')} and {out / (stem + '.md')}  (wall {env['wall_s']} s)")


if __name__ == "__main__":
    main()
