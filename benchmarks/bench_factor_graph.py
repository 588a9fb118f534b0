"""Factor-graph engine (``torchsgal.estimation.graph``) on CPU against its peers, in one run.

1. A batch of 64 small SE(3) pose graphs (8 poses, 10 relative-pose edges, a prior; the
   seeded generator of ``tests/test_factor_graph.py``): the engine's batched Levenberg-
   Marquardt against a Python loop over GTSAM's ``LevenbergMarquardtOptimizer`` on the same
   graphs (GTSAM's graphs built outside the clock, the engine's inside it).  Reported: median
   wall times of ``--repeats`` solves each, their ratio, the largest relative difference of the
   final costs and how many problems took GTSAM's iteration count.
2. A user factor, the rigid fit of 256 problems of 100 point pairs (forward-mode Jacobians,
   and analytic ones from ``T.act_jacobians``), against the closed form (SVD, Kabsch): medians
   and ratio, and the largest deviation.
   The same from far initial poses (most problems stop after 5-7 iterations, a few run to
   100), then for larger batches (64, 256, 1024 graphs).
3. Where the engine's time goes: cProfile of one pose-graph solve, cumulative seconds of the
   linearisation (residuals, Jacobians, assembly; of which the prior and between residuals and
   Jacobians, and within them the operator ``torchsgal::se3_factor_assemble``), the linear solves
   and the rest.
4. Native batching against ``torch.func.vmap`` over factors for the Between residual and its
   analytic Jacobians (64 x 10 factors): medians and ratio.  Then the assembly of a block's
   normal equations, ``torchsgal::normal_assemble`` (C kernel) against its tensor code, on
   256 x 100 factors of 3 x 6: per factor, with the tangent axis last, and summed.
5. Differentiable solves of the 64 pose graphs of 1. (measurements Z exp(xi), xi requiring
   grad): the plain solve, the forward and backward of ``backward_mode="implicit"`` and of
   ``"unroll"``, the implicit mode with nothing requiring grad, in alternation; medians, the
   ratio backward / forward, and the largest difference of the implicit and unrolled gradients.
6. The batched Cholesky solves of ``estimation.dense_solve`` (the C kernel where its size rule
   picks it) against ``torch.linalg.cholesky_ex`` and ``solve_triangular`` on the same systems:
   medians, ratio and the largest relative difference; then forward and backward of both.
7. Cases 1 and 2 again with the process keeping its freed memory
   (``torchsgal.load.keep_freed_memory()``; last, as it cannot be undone).

Usage: python benchmarks/bench_factor_graph.py [--repeats 7] [--out benchmarks/results/factor_graph_cpu]

With ``--device cuda`` (or cpu): cases 1 and 5 and the batch scaling with the engine on that
device and on the host CPU in the same run (alternated, the device synchronised around each
call), the GTSAM loop where it imports; the device's results against the CPU's (costs,
iterations, statuses, gradients); no timed round starts after ``--time-budget`` seconds.
Writes ``benchmarks/results/factor_graph_<device type>.{json,md}`` by default, never the CPU
files.
"""
from __future__ import annotations

import argparse
import cProfile
import json
import os
import pstats
import statistics
import sys
import time

import numpy as np
import torch

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.join(ROOT, "tests"))

from _timing import cpu_model, eager_call_us, kernels_note, resolve_device, synchronize  # noqa: E402
from test_factor_graph import (  # noqa: E402
    EDGES_I,
    EDGES_J,
    SIGMA,
    _graph,
    _gtsam_graph,
    _gtsam_values,
    _kabsch,
    pose_graphs,
    rigid_fit_graph,
    rigid_fit_problem,
)

import torchsgal as ts  # noqa: E402
from torchsgal.estimation import graph as fg  # noqa: E402
from torchsgal.estimation.graph import factors as F  # noqa: E402


def median_time(fn, repeats: int) -> tuple[float, object]:
    out = fn()  # warm-up, not timed
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def bench_pose_graphs(repeats: int, seed: int = 0, init_noise: float = 0.3) -> dict:
    import gtsam

    _, Z, Z0, x0 = pose_graphs(seed=seed, init_noise=init_noise)
    B = Z.batch_shape[0]
    graphs = [_gtsam_graph(Z, Z0, b) for b in range(B)]
    values = [_gtsam_values(x0, b) for b in range(B)]
    params = gtsam.LevenbergMarquardtParams()

    def gtsam_loop():
        out = []
        for g, v in zip(graphs, values):
            opt = gtsam.LevenbergMarquardtOptimizer(g, v, params)
            r = opt.optimize()
            out.append((g.error(r), opt.iterations()))
        return out

    def engine():
        return fg.levenberg_marquardt(_graph(Z, Z0, x0))

    # alternate the two so that machine load affects both alike
    t_engine, t_gtsam = [], []
    result, peer = engine(), gtsam_loop()
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = engine()
        t_engine.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        peer = gtsam_loop()
        t_gtsam.append(time.perf_counter() - t0)
    costs = torch.tensor([c for c, _ in peer], dtype=torch.float64)
    its = [i for _, i in peer]
    rel = float(((result.report.cost - costs).abs() / costs).max())
    same = sum(a == b for a, b in zip(result.report.iterations.tolist(), its))
    te, tg = statistics.median(t_engine), statistics.median(t_gtsam)
    return dict(problems=B, poses=8, edges=10, init_noise=init_noise, engine_s=te, gtsam_loop_s=tg,
                speedup_vs_gtsam=tg / te,
                paired_ratio_median=statistics.median(g / e for g, e in zip(t_gtsam, t_engine)),
                max_rel_cost_diff=rel, iterations_equal=same,
                engine_iterations=np.bincount(result.report.iterations.numpy()).tolist(),
                gtsam_iterations=np.bincount(np.array(its)).tolist(),
                statuses=result.report.counts())


def bench_batch_scaling(repeats: int, sizes=(64, 256, 1024)) -> list[dict]:
    """The engine's batched LM against the GTSAM loop as the batch grows (the loop's time per
    problem from the first 64 problems of each batch, paired in time with the engine)."""
    import gtsam

    rows = []
    for B in sizes:
        _, Z, Z0, x0 = pose_graphs(B=B, seed=1)
        graphs = [_gtsam_graph(Z, Z0, b) for b in range(64)]
        values = [_gtsam_values(x0, b) for b in range(64)]

        def loop():
            for g, v in zip(graphs, values):
                gtsam.LevenbergMarquardtOptimizer(g, v, gtsam.LevenbergMarquardtParams()).optimize()

        t_engine, _ = median_time(lambda: fg.levenberg_marquardt(_graph(Z, Z0, x0)), max(1, repeats // 2))
        t_loop, _ = median_time(loop, max(1, repeats // 2))
        per_problem = t_loop / 64
        rows.append(dict(problems=B, engine_s=t_engine, gtsam_loop_s_estimated=per_problem * B,
                         speedup_vs_gtsam=per_problem * B / t_engine))
    return rows


def _point_jacobians(T, a, b):
    """r = C a + t - b and its Jacobian in T's right perturbation, [C, -C a^] (act_jacobians)."""
    J_T, _ = T.act_jacobians(a)
    return T.act(a) - b, [J_T]


def bench_rigid_fit(repeats: int) -> dict:
    """LM (relative_error_tol 1e-10, as the test) with forward-mode and with analytic Jacobians."""
    _, p, q = rigid_fit_problem()
    graph = rigid_fit_graph(p, q)
    B, K = p.shape[:2]
    analytic = fg.FactorGraph()
    analytic.add_variable("T", ts.SE3.identity((B, 1), dtype=torch.float64))
    analytic.add(fg.Factor(lambda T, a, b: T.act(a) - b, [("T", torch.zeros(K, dtype=torch.int64))],
                           [p, q], dim=3, jacobians=_point_jacobians))
    tol = dict(relative_error_tol=1e-10, absolute_error_tol=0.0)
    t_engine, result = median_time(lambda: fg.levenberg_marquardt(graph, **tol), repeats)
    t_analytic, res_a = median_time(lambda: fg.levenberg_marquardt(analytic, **tol), repeats)
    t_closed, closed = median_time(lambda: _kabsch(p, q), repeats)
    dev = float((result.values["T"][:, 0].as_matrix() - closed.as_matrix()).abs().max())
    dev_a = float((res_a.values["T"][:, 0].as_matrix() - closed.as_matrix()).abs().max())
    return dict(problems=B, points=K, engine_s=t_engine, engine_analytic_s=t_analytic,
                closed_form_s=t_closed, ratio_engine_over_closed_form=t_engine / t_closed,
                ratio_analytic_over_closed_form=t_analytic / t_closed, max_abs_deviation=dev,
                max_abs_deviation_analytic=dev_a, iterations_max=int(result.report.iterations.max()))


def profile_pose_graphs() -> dict:
    _, Z, Z0, x0 = pose_graphs()
    graph = _graph(Z, Z0, x0)
    fg.levenberg_marquardt(graph)
    prof = cProfile.Profile()
    prof.enable()
    fg.levenberg_marquardt(graph)
    prof.disable()
    stats = pstats.Stats(prof).stats
    total = sum(v[2] for v in stats.values())  # tottime sum = wall of the profiled call

    def cum(fname, func):
        return sum(v[3] for (f, _, fn), v in stats.items() if f.endswith(fname) and fn == func)

    parts = dict(linearize=cum("linearize.py", "linearize"),
                 prior_between_log_terms=cum("linearize.py", "_log_form_terms"),
                 se3_factor_assemble_kernel=cum("factor_kernels.py", "_run_assemble"),
                 linear_solve=cum("linear_system.py", "solve"),
                 retract=cum("graph/problem.py", "retract"),
                 final_rank_test=cum("linear_system.py", "set_solution") + cum("linear_system.py", "singular"),
                 problem_setup=cum("graph/problem.py", "__init__"))
    parts["total_profiled"] = total
    return parts


def bench_vmap_vs_native(repeats: int) -> dict:
    gen = torch.Generator().manual_seed(0)
    G, B, E = ts.SE3, 64, 10
    Ti, Tj, Z = (G.exp(torch.randn(B, E, 6, generator=gen, dtype=torch.float64)) for _ in range(3))

    def native():
        return F._between_jacobians(Ti, Tj, Z)

    per_factor = torch.func.vmap(torch.func.vmap(F._between_jacobians))

    def vmapped():
        return per_factor(Ti, Tj, Z)

    t_native, a = median_time(native, repeats)
    t_vmap, b = median_time(vmapped, repeats)
    agree = max(float((x - y).abs().max()) for x, y in zip([a[0], *a[1]], [b[0], *b[1]]))
    return dict(factors=B * E, native_s=t_native, vmap_s=t_vmap, vmap_over_native=t_vmap / t_native,
                max_abs_difference=agree)


def bench_assembly(repeats: int) -> list[dict]:
    """``torchsgal::normal_assemble`` (C kernel) against its tensor code (batched ``J.mT @ J``,
    ``J.mT @ r`` and ``index_add``, as with the kernels off) on 256 problems x 100 factors of
    3 x 6 (the rigid fit's point factors): per-factor blocks (each at its own slots), the same
    with the tangent axis moved last (forward mode's layout), and summed blocks."""
    from torchsgal.estimation.graph import normal_kernel
    from torchsgal.functional import native

    gen = torch.Generator().manual_seed(0)
    B, E, m, Dk = 256, 100, 3, 6
    J = torch.randn(B, E, m, Dk, generator=gen, dtype=torch.float64)
    r = torch.randn(B, E, m, generator=gen, dtype=torch.float64)
    rows = []
    for name, Jl, summed in (("per factor", J, False),
                             ("per factor, tangent axis last", J.movedim(-1, 0).contiguous().movedim(0, -1), False),
                             ("summed", J, True)):
        n = 1 if summed else E
        slots = torch.arange(n * Dk * Dk).reshape(n, Dk * Dk)
        g_slots = torch.arange(n * Dk).reshape(n, Dk)
        values = torch.zeros(B, n * Dk * Dk, dtype=torch.float64)
        g = torch.zeros(B, n * Dk, dtype=torch.float64)
        args = (Jl, r, slots, values, g_slots, g, summed)
        t_kernel, a = median_time(lambda: torch.ops.torchsgal.normal_assemble(*args), repeats)
        with native.disabled():
            t_tensor, b = median_time(lambda: normal_kernel.normal_assemble(*args), repeats)
        diff = max(float(((x - y).abs() / y.abs().max()).max()) for x, y in zip(a, b))
        rows.append(dict(block=name, problems=B, factors=E, rows=m, columns=Dk,
                         kernel_s=t_kernel, tensor_s=t_tensor, tensor_over_kernel=t_tensor / t_kernel,
                         max_rel_difference=diff))
    return rows


def bench_dense_solves(repeats: int) -> list[dict]:
    """The engine's batched Cholesky solves (``estimation.dense_solve``: the C kernel where its
    size rule picks it) against torch's ``linalg.cholesky_ex`` and two ``solve_triangular``
    (LAPACK, one matrix at a time) on the same systems: the pose graphs' normal equations (48
    unknowns), the TLS conditions' covariances (10 x 10 with 12 right-hand sides), small
    blocks."""
    from torchsgal.estimation import dense_solve

    rows = []
    for n, m, k in ((64, 48, 1), (1024, 48, 1), (40400, 10, 12), (4096, 6, 1), (1, 16, 1)):
        gen = torch.Generator().manual_seed(0)
        G = torch.randn(n, m, m, dtype=torch.float64, generator=gen)
        A = G @ G.mT + m * torch.eye(m, dtype=torch.float64)
        R = torch.randn(n, m, k, dtype=torch.float64, generator=gen)

        def lapack():
            L, info = torch.linalg.cholesky_ex(A)
            X = torch.linalg.solve_triangular(L, R, upper=False)
            return L, X, torch.linalg.solve_triangular(L.mT, X, upper=True), info

        t_op, a = median_time(lambda: dense_solve.cholesky_solve(A, R, back=True), repeats)
        t_lapack, b = median_time(lapack, repeats)
        dev = max(float((x - y).abs().max() / y.abs().max()) for x, y in zip(a[:3], b[:3]))
        # forward and backward of sum(Y^2) + sum(X) with respect to A (its symmetric part) and R
        Ag, Rg = A.clone().requires_grad_(), R.clone().requires_grad_()

        def grads(solve):
            def run():
                A_sym = (Ag + Ag.mT) / 2
                _, X, Y, _ = solve(A_sym)
                return torch.autograd.grad((Y * Y).sum() + X.sum(), (Ag, Rg))
            return run

        t_op_grad, ga = median_time(grads(lambda S: dense_solve.cholesky_solve(S, Rg, back=True)), repeats)
        t_lapack_grad, gb = median_time(grads(lambda S: _lapack_solve(S, Rg)), repeats)
        dev_grad = max(float((x - y).abs().max() / y.abs().max()) for x, y in zip(ga, gb))
        rows.append(dict(systems=n, unknowns=m, rhs=k, kernel=dense_solve.uses_kernel(A),
                         operator_s=t_op, lapack_s=t_lapack, lapack_over_operator=t_lapack / t_op,
                         max_rel_difference=dev, operator_grad_s=t_op_grad, lapack_grad_s=t_lapack_grad,
                         lapack_over_operator_grad=t_lapack_grad / t_op_grad,
                         max_rel_difference_grad=dev_grad))
    return rows


def _lapack_solve(A, R):
    L = torch.linalg.cholesky(A)
    X = torch.linalg.solve_triangular(L, R, upper=False)
    return L, X, torch.linalg.solve_triangular(L.mT, X, upper=True), None


def bench_kept_memory(repeats: int) -> dict:
    """Cases 1 and 2 again after ``torchsgal.load.keep_freed_memory()`` (glibc keeps the blocks a
    process frees for its next allocations instead of returning them, so a fresh temporary of
    some hundred kB or more costs no page faults).  It is a setting of the process, made once
    and not undone, so this case runs last."""
    from torchsgal.load import keep_freed_memory

    keep_freed_memory()
    return dict(pose_graphs=bench_pose_graphs(repeats), rigid_fit=bench_rigid_fit(repeats))


def bench_differentiable(repeats: int) -> dict:
    _, Z, Z0, x0 = pose_graphs()
    xi = torch.zeros(Z.batch_shape + (6,), dtype=torch.float64, requires_grad=True)
    weights = torch.randn(x0.batch_shape + (4, 4), generator=torch.Generator().manual_seed(1),
                          dtype=torch.float64)

    def solve(mode, theta):
        return fg.levenberg_marquardt(_graph(Z @ ts.SE3.exp(theta), Z0, x0), backward_mode=mode)

    times: dict[str, list[float]] = {k: [] for k in (
        "plain_s", "implicit_nothing_to_differentiate_s", "implicit_forward_s",
        "implicit_backward_s", "unroll_forward_s", "unroll_backward_s")}
    grads = {}
    for k in range(repeats + 1):  # the first round warms up, untimed
        t0 = time.perf_counter()
        solve("none", xi.detach())
        t1 = time.perf_counter()
        solve("implicit", xi.detach())
        t2 = time.perf_counter()
        stamps = [t0, t1, t2]
        for mode in ("implicit", "unroll"):
            t3 = time.perf_counter()
            out = solve(mode, xi)
            loss = (out.values["x"].as_matrix() * weights).sum()
            t4 = time.perf_counter()
            (grads[mode],) = torch.autograd.grad(loss, xi)
            t5 = time.perf_counter()
            stamps += [t3, t4, t5]
        if k:
            times["plain_s"].append(t1 - t0)
            times["implicit_nothing_to_differentiate_s"].append(t2 - t1)
            times["implicit_forward_s"].append(stamps[4] - stamps[3])
            times["implicit_backward_s"].append(stamps[5] - stamps[4])
            times["unroll_forward_s"].append(stamps[7] - stamps[6])
            times["unroll_backward_s"].append(stamps[8] - stamps[7])
    med = {k: statistics.median(v) for k, v in times.items()}
    scale = float(grads["unroll"].abs().max())
    return dict(problems=Z.batch_shape[0], poses=8, edges=10, **med,
                implicit_backward_over_forward=med["implicit_backward_s"] / med["implicit_forward_s"],
                implicit_backward_over_plain=med["implicit_backward_s"] / med["plain_s"],
                implicit_forward_over_plain=med["implicit_forward_s"] / med["plain_s"],
                unroll_backward_over_forward=med["unroll_backward_s"] / med["unroll_forward_s"],
                max_rel_gradient_difference=float((grads["implicit"] - grads["unroll"]).abs().max())
                / scale)


# --------------------------------------------------------------------------- --device mode
def _on(x, device):
    return ts.SE3(x.as_matrix().to(device)) if isinstance(x, ts.LieGroup) else x.to(device)


def _device_graph(Z, Z0, x0, device):
    """``test_factor_graph._graph`` with its indices and noise on ``device`` (Z, Z0, x0 there)."""
    W = torch.diag(SIGMA ** -2).to(device)
    graph = fg.FactorGraph()
    graph.add_variable("x", x0)
    graph.add(fg.Prior("x", 0, Z0, information=W))
    graph.add(fg.Between("x", EDGES_I.to(device), EDGES_J.to(device), Z, information=W))
    return graph


def _timed(cases: dict, repeats: int, device, deadline: float) -> tuple[dict, dict]:
    """Median seconds of each case (name -> zero-arg callable), called in alternation after one
    untimed round, the device synchronised before starting and before stopping each clock; no
    new round once ``deadline`` (perf_counter) has passed (one round at least).  Returns
    (medians, last results)."""
    out = {k: f() for k, f in cases.items()}  # warm-up, not timed
    times: dict[str, list[float]] = {k: [] for k in cases}
    for _ in range(repeats):
        for k, f in cases.items():
            synchronize(device)
            t0 = time.perf_counter()
            out[k] = f()
            synchronize(device)
            times[k].append(time.perf_counter() - t0)
        if time.perf_counter() > deadline:
            break
    return {k: dict(median_s=statistics.median(v), runs=len(v)) for k, v in times.items()}, out


def _gtsam_importable() -> tuple[bool, str]:
    try:
        import gtsam  # noqa: F401
        return True, "gtsam imports"
    except Exception as e:  # any import failure is reported, not raised
        return False, f"gtsam not importable: {type(e).__name__}: {e}"


def device_pose_graphs(device, repeats: int, deadline: float, B=64, seed=0, init_noise=0.3,
                       with_gtsam=False) -> dict:
    """The batched LM on ``device`` and on the CPU (inputs on each device before the clock, the
    graph built inside it), and the GTSAM loop where it imports."""
    _, Z, Z0, x0 = pose_graphs(B=B, seed=seed, init_noise=init_noise)
    cpu = torch.device("cpu")
    inputs = {d: (_on(Z, d), _on(Z0, d), _on(x0, d)) for d in (device, cpu)}
    cases = {"device": lambda: fg.levenberg_marquardt(_device_graph(*inputs[device], device)),
             "cpu": lambda: fg.levenberg_marquardt(_device_graph(*inputs[cpu], cpu))}
    if with_gtsam:
        import gtsam

        graphs = [_gtsam_graph(Z, Z0, b) for b in range(B)]
        values = [_gtsam_values(x0, b) for b in range(B)]
        cases["gtsam_loop"] = lambda: [gtsam.LevenbergMarquardtOptimizer(
            g, v, gtsam.LevenbergMarquardtParams()).optimize() for g, v in zip(graphs, values)]
    times, out = _timed(cases, repeats, device, deadline)
    dev, ref = out["device"].report, out["cpu"].report
    x_dev, x_cpu = out["device"].values["x"].as_matrix(), out["cpu"].values["x"].as_matrix()
    row = dict(problems=B, init_noise=init_noise, device_s=times["device"]["median_s"],
               cpu_s=times["cpu"]["median_s"], runs=times["device"]["runs"],
               cpu_over_device=times["cpu"]["median_s"] / times["device"]["median_s"],
               results_device=str(x_dev.device),
               max_rel_cost_diff_vs_cpu=float(((dev.cost.cpu() - ref.cost).abs() / ref.cost).max()),
               max_abs_solution_diff_vs_cpu=float((x_dev.cpu() - x_cpu).abs().max()),
               iterations_equal_to_cpu=int((dev.iterations.cpu() == ref.iterations).sum()),
               statuses_device=dev.counts(), statuses_cpu=ref.counts(),
               iterations_max=int(ref.iterations.max()))
    if "gtsam_loop" in times:
        row["gtsam_loop_s"] = times["gtsam_loop"]["median_s"]
    return row


def device_differentiable(device, repeats: int, deadline: float) -> dict:
    """The implicit forward and backward of 64 pose graphs on ``device`` and on the CPU."""
    _, Z, Z0, x0 = pose_graphs()
    cpu = torch.device("cpu")
    weights = torch.randn(x0.batch_shape + (4, 4), generator=torch.Generator().manual_seed(1),
                          dtype=torch.float64)

    def case(d):
        Zd, Z0d, x0d, w = _on(Z, d), _on(Z0, d), _on(x0, d), weights.to(d)

        def run():
            xi = torch.zeros(Z.batch_shape + (6,), dtype=torch.float64, device=d, requires_grad=True)
            out = fg.levenberg_marquardt(_device_graph(Zd @ ts.SE3.exp(xi), Z0d, x0d, d),
                                         backward_mode="implicit")
            loss = (out.values["x"].as_matrix() * w).sum()
            return torch.autograd.grad(loss, xi)[0]
        return run

    times, out = _timed({"device": case(device), "cpu": case(cpu)}, repeats, device, deadline)
    scale = float(out["cpu"].abs().max())
    return dict(problems=64, device_s=times["device"]["median_s"], cpu_s=times["cpu"]["median_s"],
                runs=times["device"]["runs"],
                cpu_over_device=times["cpu"]["median_s"] / times["device"]["median_s"],
                max_rel_gradient_diff_vs_cpu=float((out["device"].cpu() - out["cpu"]).abs().max()) / scale)


def main_device(args) -> None:
    device = resolve_device(args.device)
    out_path = args.out or os.path.join(HERE, "results", f"factor_graph_{device.type}")
    if device.type != "cpu" and os.path.basename(out_path).endswith("_cpu"):
        raise SystemExit(f"--out {out_path}: a {device.type} run does not write the CPU result files")
    torch.set_num_threads(args.threads)
    start = time.perf_counter()
    deadline = start + args.time_budget
    has_gtsam, gtsam_note = _gtsam_importable()
    o = dict(device=str(device), device_name=(torch.cuda.get_device_name(device) if device.type == "cuda"
                                              else cpu_model()),
             cpu=cpu_model(), torch=torch.__version__, cuda=torch.version.cuda,
             threads=torch.get_num_threads(), repeats=args.repeats, time_budget_s=args.time_budget,
             gtsam=gtsam_note, kernels=kernels_note(),
             command=" ".join(["python benchmarks/bench_factor_graph.py", *sys.argv[1:]]))
    o["pose_graphs"] = device_pose_graphs(device, args.repeats, deadline, with_gtsam=has_gtsam)
    print(o["pose_graphs"], flush=True)
    o["pose_graphs_far"] = device_pose_graphs(device, max(1, args.repeats // 2), deadline, seed=2,
                                              init_noise=1.0, with_gtsam=has_gtsam)
    print(o["pose_graphs_far"], flush=True)
    o["differentiable"] = (device_differentiable(device, args.repeats, deadline)
                           if time.perf_counter() < deadline else dict(skipped="time budget spent"))
    print(o["differentiable"], flush=True)
    o["batch_scaling"] = []
    for B in args.batches:
        if time.perf_counter() > deadline:
            o["batch_scaling"].append(dict(problems=B, skipped="time budget spent"))
        else:
            o["batch_scaling"].append(device_pose_graphs(device, max(1, args.repeats // 2), deadline,
                                                         B=B, seed=1))
        print(o["batch_scaling"][-1], flush=True)
    o["total_s"] = time.perf_counter() - start
    os.makedirs(os.path.dirname(out_path) or ".", exist_ok=True)
    with open(out_path + ".json", "w") as f:
        json.dump(o, f, indent=2)
    with open(out_path + ".md", "w") as f:
        f.write(_markdown_device(o))
    print(_markdown_device(o))


def _markdown_device(o: dict) -> str:
    def row(name, r):
        if "skipped" in r:
            return f"| {name} | not run: {r['skipped']} | | | | | | |"
        gt = f"{r['gtsam_loop_s']:.4f}" if "gtsam_loop_s" in r else "not importable"
        return (f"| {name} | {r['device_s']:.4f} | {r['cpu_s']:.4f} | {r['cpu_over_device']:.2f} | {gt} | "
                f"{r['iterations_equal_to_cpu']} of {r['problems']} | {r['max_rel_cost_diff_vs_cpu']:.1e} | "
                f"{r['runs']} |")

    d = o["differentiable"]
    lines = [
        f"# Factor-graph engine on {o['device']} ({o['device_name']}) and on the host CPU", "",
        f"`{o['command']}`; torch {o['torch']} (CUDA {o['cuda']}); host CPU {o['cpu']}, {o['threads']} "
        f"thread(s), {o.get('kernels', 'C kernels not recorded')}; medians of up to --repeats "
        f"{o['repeats']} alternated runs after an untimed one, the "
        f"device synchronised before and after each; time budget {o['time_budget_s']} s (fewer runs, or "
        f"rows not run, once spent); total {o['total_s']:.1f} s; {o['gtsam']}.", "",
        "SE(3) pose graphs (8 poses, 10 edges, a prior; the generator of tests/test_factor_graph.py), "
        "batched Levenberg-Marquardt, the graph built inside the clock from inputs already on each device; "
        "results stay on the device.", "",
        "| problems | device s | CPU s | CPU / device | GTSAM loop s | iterations equal to CPU | "
        "max rel. cost diff. | runs |", "|---|---|---|---|---|---|---|---|",
        row(f"{o['pose_graphs']['problems']} (tangent noise 0.3)", o["pose_graphs"]),
        row(f"{o['pose_graphs_far']['problems']} (tangent noise 1.0)", o["pose_graphs_far"]),
        *[row(f"{r['problems']} (batch scaling)", r) for r in o["batch_scaling"]], "",
        f"Statuses (64 graphs): device {o['pose_graphs']['statuses_device']}, CPU "
        f"{o['pose_graphs']['statuses_cpu']}; largest solution difference "
        f"{o['pose_graphs']['max_abs_solution_diff_vs_cpu']:.1e}.", "",
    ]
    if "skipped" in d:
        lines += [f"Implicit forward and backward: not run: {d['skipped']}.", ""]
    else:
        lines += [f"Implicit forward and backward, {d['problems']} pose graphs: device {d['device_s']:.4f} s, "
                  f"CPU {d['cpu_s']:.4f} s (CPU / device {d['cpu_over_device']:.2f}); largest gradient "
                  f"difference relative to its largest entry {d['max_rel_gradient_diff_vs_cpu']:.1e}.", ""]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--out", default=None,
                    help="output path without suffix (default benchmarks/results/factor_graph_cpu, "
                         "with --device: factor_graph_<device type>)")
    ap.add_argument("--device", default=None,
                    help="the pose-graph batches and the implicit gradient on this device (cpu or "
                         "cuda[:i]) and on the host CPU, the GTSAM loop where it imports")
    ap.add_argument("--time-budget", type=float, default=45.0,
                    help="with --device: seconds after which no further timed round starts")
    ap.add_argument("--threads", type=int, default=1, help="with --device: torch CPU threads")
    ap.add_argument("--batches", type=int, nargs="+", default=[256, 1024, 4096, 16384],
                    help="with --device: batch sizes of the scaling rows")
    ap.add_argument("--only-differentiable", action="store_true",
                    help="run case 5 alone and print it (no result files)")
    args = ap.parse_args()
    if args.device is not None:
        main_device(args)
        return
    args.out = args.out or os.path.join(HERE, "results", "factor_graph_cpu")
    if args.only_differentiable:
        torch.set_num_threads(1)
        print(json.dumps(bench_differentiable(args.repeats), indent=2))
        return
    torch.set_num_threads(1)
    out = dict(cpu=cpu_model(), torch=torch.__version__, threads=torch.get_num_threads(),
               repeats=args.repeats, eager_call_us=eager_call_us())
    out["pose_graphs"] = bench_pose_graphs(args.repeats)
    out["pose_graphs_far"] = bench_pose_graphs(max(1, args.repeats // 2), seed=2, init_noise=1.0)
    out["batch_scaling"] = bench_batch_scaling(args.repeats)
    out["rigid_fit"] = bench_rigid_fit(args.repeats)
    out["profile_pose_graphs_s"] = profile_pose_graphs()
    out["between_native_vs_vmap"] = bench_vmap_vs_native(args.repeats)
    out["assembly"] = bench_assembly(args.repeats)
    out["differentiable"] = bench_differentiable(args.repeats)
    out["dense_solves"] = bench_dense_solves(args.repeats)
    out["kept_memory"] = bench_kept_memory(args.repeats)  # last: it changes the process
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out + ".json", "w") as f:
        json.dump(out, f, indent=2)
    with open(args.out + ".md", "w") as f:
        f.write(_markdown(out))
    print(_markdown(out))


def _markdown(o: dict) -> str:
    pg, rf, pr, vm = o["pose_graphs"], o["rigid_fit"], o["profile_pose_graphs_s"], o["between_native_vs_vmap"]
    lines = [
        "# Factor-graph engine, CPU",
        "",
        f"CPU: {o['cpu']}; torch {o['torch']}, {o['threads']} thread; medians of {o['repeats']} "
        "repeats (`python benchmarks/bench_factor_graph.py`); an eager `x * 2` on 1,000 float64 "
        f"elements takes {o['eager_call_us']:.1f} us on one thread (the per-call cost, which the engine's small "
        "batches pay most: some hundreds of eager operations per iteration).",
        "",
        f"## {pg['problems']} SE(3) pose graphs ({pg['poses']} poses, {pg['edges']} edges, a prior)",
        "",
        "| solver | median s | ratio |",
        "|---|---|---|",
        f"| torchsgal LM (batched) | {pg['engine_s']:.4f} | 1 |",
        f"| GTSAM LM, Python loop | {pg['gtsam_loop_s']:.4f} | {pg['speedup_vs_gtsam']:.2f} |",
        "",
        f"Paired ratio GTSAM / engine (median over repeats): {pg['paired_ratio_median']:.2f}. "
        f"Largest relative cost difference: {pg['max_rel_cost_diff']:.1e}; iteration counts equal "
        f"to GTSAM's in {pg['iterations_equal']} of {pg['problems']} problems "
        f"(histograms, index = iterations: engine {pg['engine_iterations']}, "
        f"GTSAM {pg['gtsam_iterations']}); statuses {pg['statuses']}.",
        "",
        "Where the engine's time goes (cProfile of one solve, cumulative seconds):",
        "",
        "| part | s |",
        "|---|---|",
        *[f"| {k} | {v:.4f} |" for k, v in pr.items()],
        "",
        f"From far initial poses (tangent noise {o['pose_graphs_far']['init_noise']}, "
        f"{o['pose_graphs_far']['gtsam_iterations'].__len__() - 1} iterations at most; most "
        "problems stop early and leave the working set): engine "
        f"{o['pose_graphs_far']['engine_s']:.4f} s, GTSAM loop {o['pose_graphs_far']['gtsam_loop_s']:.4f} s "
        f"(GTSAM / engine {o['pose_graphs_far']['speedup_vs_gtsam']:.2f}); iteration counts equal in "
        f"{o['pose_graphs_far']['iterations_equal']} of {o['pose_graphs_far']['problems']}, largest "
        f"relative cost difference {o['pose_graphs_far']['max_rel_cost_diff']:.1e}.",
        "",
        "Batch scaling (GTSAM loop time = B x its median time per problem on 64 of them):",
        "",
        "| problems | engine s | GTSAM loop s | GTSAM / engine |",
        "|---|---|---|---|",
        *[f"| {r['problems']} | {r['engine_s']:.4f} | {r['gtsam_loop_s_estimated']:.4f} | "
          f"{r['speedup_vs_gtsam']:.2f} |" for r in o["batch_scaling"]],
        "",
        f"## Rigid fit, {rf['problems']} problems x {rf['points']} points (user factor, forward mode)",
        "",
        "| solver | median s | ratio |",
        "|---|---|---|",
        f"| closed form (SVD) | {rf['closed_form_s']:.4f} | 1 |",
        f"| torchsgal LM, forward-mode Jacobians | {rf['engine_s']:.4f} | "
        f"{rf['ratio_engine_over_closed_form']:.1f} |",
        f"| torchsgal LM, analytic Jacobians | {rf['engine_analytic_s']:.4f} | "
        f"{rf['ratio_analytic_over_closed_form']:.1f} |",
        "",
        f"Largest deviation of the matrices from the closed form: {rf['max_abs_deviation']:.1e} "
        f"(analytic: {rf['max_abs_deviation_analytic']:.1e}; up to {rf['iterations_max']} "
        "iterations, relative_error_tol 1e-10).",
        "",
        f"## Between residual and Jacobians, {vm['factors']} factors",
        "",
        f"Native batching {vm['native_s'] * 1e3:.2f} ms, torch.func.vmap over factors "
        f"{vm['vmap_s'] * 1e3:.2f} ms (vmap / native {vm['vmap_over_native']:.2f}); "
        f"largest difference {vm['max_abs_difference']:.1e}.",
        "",
        "## Assembly of a block's normal equations",
        "",
        "`torch.ops.torchsgal.normal_assemble` (C kernel: J^T J and J^T r of every factor added "
        "at its slots) against its tensor code (batched products and `index_add`, as with the "
        "kernels off), on the same J and r:",
        "",
        "| block | problems x factors | J per factor | kernel ms | tensor code ms | "
        "tensor / kernel | largest relative difference |",
        "|---|---|---|---|---|---|---|",
        *[f"| {r['block']} | {r['problems']} x {r['factors']} | {r['rows']} x {r['columns']} | "
          f"{r['kernel_s'] * 1e3:.3f} | {r['tensor_s'] * 1e3:.3f} | {r['tensor_over_kernel']:.2f} | "
          f"{r['max_rel_difference']:.1e} |" for r in o.get("assembly", [])],
        "",
        *_markdown_differentiable(o["differentiable"]),
        "",
        "## Batched Cholesky solves (factor, L^-1 R and A^-1 R)",
        "",
        "`estimation.dense_solve.cholesky_solve` against `torch.linalg.cholesky_ex` and two "
        "`solve_triangular` on the same symmetric positive definite systems:",
        "",
        "| systems | unknowns | right-hand sides | C kernel | operator ms | torch.linalg ms | "
        "torch.linalg / operator | largest relative difference |",
        "|---|---|---|---|---|---|---|---|",
        *[f"| {r['systems']} | {r['unknowns']} | {r['rhs']} | {'yes' if r['kernel'] else 'no'} | "
          f"{r['operator_s'] * 1e3:.3f} | {r['lapack_s'] * 1e3:.3f} | "
          f"{r['lapack_over_operator']:.2f} | {r['max_rel_difference']:.1e} |"
          for r in o.get("dense_solves", [])],
        "",
        "Forward and backward (the gradient of sum(Y^2) + sum(X) with respect to A and R; the "
        "operators' backward is the closed form of `dense_solve._cholesky_solve_vjp` from the "
        "saved factor) against autograd through `torch.linalg.cholesky` and `solve_triangular`:",
        "",
        "| systems | unknowns | right-hand sides | operator ms | torch.linalg ms | "
        "torch.linalg / operator | largest relative difference |",
        "|---|---|---|---|---|---|---|",
        *[f"| {r['systems']} | {r['unknowns']} | {r['rhs']} | {r['operator_grad_s'] * 1e3:.3f} | "
          f"{r['lapack_grad_s'] * 1e3:.3f} | {r['lapack_over_operator_grad']:.2f} | "
          f"{r['max_rel_difference_grad']:.1e} |"
          for r in o.get("dense_solves", []) if "operator_grad_s" in r],
        *_markdown_kept(o.get("kept_memory")),
    ]
    return "\n".join(lines)


def _markdown_kept(k: dict | None) -> list[str]:
    if not k:
        return []
    pg, rf = k["pose_graphs"], k["rigid_fit"]
    return [
        "",
        "## With `torchsgal.load.keep_freed_memory()`",
        "",
        "The process keeps the blocks it frees for its next allocations (glibc's `mallopt`), so "
        "fresh temporaries cost no page faults; cases 1 and 2 again, in the same run:",
        "",
        "| case | engine s | peer s | peer / engine |",
        "|---|---|---|---|",
        f"| {pg['problems']} pose graphs, LM | {pg['engine_s']:.4f} | GTSAM loop {pg['gtsam_loop_s']:.4f} | "
        f"{pg['speedup_vs_gtsam']:.2f} |",
        f"| rigid fit, forward mode | {rf['engine_s']:.4f} | closed form {rf['closed_form_s']:.4f} | "
        f"{1 / rf['ratio_engine_over_closed_form']:.3f} |",
        f"| rigid fit, analytic Jacobians | {rf['engine_analytic_s']:.4f} | closed form "
        f"{rf['closed_form_s']:.4f} | {1 / rf['ratio_analytic_over_closed_form']:.3f} |",
    ]


def _markdown_differentiable(d: dict) -> list[str]:
    return [
        f"## Differentiable solves, {d['problems']} pose graphs ({d['poses']} poses, "
        f"{d['edges']} edges, a prior)",
        "",
        "Gradient of a weighted sum of the solution's matrices with respect to tangent "
        "perturbations of all Between measurements (LM, GTSAM's defaults).",
        "",
        "| step | median s | / plain solve |",
        "|---|---|---|",
        *[f"| {name} | {d[k]:.4f} | {d[k] / d['plain_s']:.2f} |" for name, k in (
            ("plain solve (`backward_mode=\"none\"`)", "plain_s"),
            ("`\"implicit\"`, nothing requires grad", "implicit_nothing_to_differentiate_s"),
            ("`\"implicit\"` forward", "implicit_forward_s"),
            ("`\"implicit\"` backward", "implicit_backward_s"),
            ("`\"unroll\"` forward", "unroll_forward_s"),
            ("`\"unroll\"` backward", "unroll_backward_s"))],
        "",
        f"Implicit backward / forward: {d['implicit_backward_over_forward']:.2f} (unrolled: "
        f"{d['unroll_backward_over_forward']:.2f}). Largest difference of the implicit and "
        f"unrolled gradients, relative to the largest entry: "
        f"{d['max_rel_gradient_difference']:.1e} (the Gauss-Newton information stands for the "
        "Hessian in the implicit gradient: the relative difference is of the order of the "
        "measurement residuals, here 0.02-0.05 in tangent units).",
        "",
    ]


if __name__ == "__main__":
    main()
