"""Pose-graph optimisation on CPU: GTSAM's Levenberg-Marquardt and Gauss-Newton (C++ optimisers
through the Python bindings), the torchsgal factor-graph engine (``torchsgal.estimation.graph``),
Theseus (when it imports), and ``SparseCholesky``'s backends on the problems' normal equations.

Problems (``../shared/data``): sphere2500 (SE3, iSAM ``EDGE3``, no vertices: the chained
odometry is the initial guess, as GTSAM's ``load2D`` builds it), pose3example-grid (SE3, g2o,
the file's vertices) and w100 (SE2, TORO, the file's vertices); each with a tight prior on its
first pose (at its initial value, sigma 1e-3 on every tangent component).

For every solver: the final cost 1/2 chi-square evaluated by GTSAM's ``graph.error`` on the
solution (one objective for all), the iterations, and the wall time (median of ``--repeats``
runs, 5x as many for the problems under ``--dense-limit`` unknowns, each from the same initial
guess; GTSAM's graph is built outside the clock, the engine's graph inside it; Theseus runs
once, with a fixed damping).  The torchsgal engine runs with its default
``linear_solver="auto"`` (``SparseCholesky`` for one problem of more than 1000 unknowns, the
block-sparse factorisation of ``estimation.block_cholesky`` for the smaller ones); an
engine without a sparse solver is run only up to ``--dense-limit`` unknowns.  Its targets:
GTSAM LM's final cost (1e-6 relative) in at most 2x GTSAM LM's time.

The ``SparseCholesky`` rows time factor + solve of each backend on the Gauss-Newton normal
equations at the initial guess (assembled by the engine's linearisation), and the engine's own
block-sparse factorisation (``estimation.block_cholesky``, what ``linear_solver="auto"`` uses for
a problem of up to 1000 unknowns whose pattern pays) on the same equations.

Usage: python benchmarks/bench_posegraph.py [--repeats 3] [--problems NAME ...] [--merge]
[--out benchmarks/results/posegraph_cpu]
Writes <out>.json and <out>.md; with --merge the problems not run keep their entries from the
existing <out>.json (marked as such).

With ``--device cuda`` (or cpu): the engine on that device and on the host CPU in the same run
(LM and GN, its own final cost, iterations, status, median wall time with the device
synchronised around each call), GTSAM and Theseus rows where they import (a note where they do
not), no SparseCholesky rows; an untimed warm-up solve of the small problems on each device
first; no timed run starts after ``--time-budget`` seconds.  Writes
``benchmarks/results/posegraph_<device type>.{json,md}`` by default, never the CPU files.
"""
from __future__ import annotations

import argparse
import inspect
import json
import os
import platform
import statistics
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

import torchsgal as ts
from torchsgal.estimation import SolverStatus
from torchsgal.estimation.g2o import PoseGraph, odometry_initial_guess, read_pose_graph
from torchsgal.estimation.sparse import SparseCholesky, available_backends

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _timing import cpu_model, kernels_note, resolve_device, synchronize  # noqa: E402

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
PROBLEMS = ("sphere2500.txt", "pose3example-grid.txt", "w100.graph")
PRIOR_SIGMA = 1e-3
THESEUS_DAMPING = 1e-3  # fixed: Theseus's adaptive damping does not run with its CHOLMOD solver


def median_time(fn, repeats: int):
    """(median seconds, last result) over ``repeats`` calls."""
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


# --------------------------------------------------------------------------- GTSAM
def gtsam_problem(graph: PoseGraph, initial):
    import gtsam

    planar = graph.group is ts.SE2
    fg = gtsam.NonlinearFactorGraph()
    swap = [0, 1, 2] if planar else [3, 4, 5, 0, 1, 2]  # torchsgal -> GTSAM tangent order
    Z = graph.measurements.as_matrix().numpy()
    W = graph.information.numpy()[:, swap][:, :, swap]
    ids = graph.ids.tolist()
    for (i, j), z, w in zip(graph.edges.tolist(), Z, W):
        noise = gtsam.noiseModel.Gaussian.Information(w)
        if planar:
            fg.add(gtsam.BetweenFactorPose2(ids[i], ids[j], pose2(z), noise))
        else:
            fg.add(gtsam.BetweenFactorPose3(ids[i], ids[j], gtsam.Pose3(z), noise))
    values = gtsam_values(graph, initial)
    dof = 3 if planar else 6
    prior = gtsam.noiseModel.Isotropic.Sigma(dof, PRIOR_SIGMA)
    first = values.atPose2(ids[0]) if planar else values.atPose3(ids[0])
    fg.add((gtsam.PriorFactorPose2 if planar else gtsam.PriorFactorPose3)(ids[0], first, prior))
    return fg, values


def pose2(m: np.ndarray):
    import gtsam

    return gtsam.Pose2(m[0, 2], m[1, 2], np.arctan2(m[1, 0], m[0, 0]))


def gtsam_values(graph: PoseGraph, poses):
    import gtsam

    values = gtsam.Values()
    make = pose2 if graph.group is ts.SE2 else gtsam.Pose3
    for k, m in zip(graph.ids.tolist(), poses.as_matrix().detach().cpu().double().numpy()):
        values.insert(k, make(m))
    return values


def run_gtsam(fg, values, method: str, repeats: int) -> dict:
    import gtsam

    def solve():
        if method == "LM":
            opt = gtsam.LevenbergMarquardtOptimizer(fg, values, gtsam.LevenbergMarquardtParams())
        else:
            opt = gtsam.GaussNewtonOptimizer(fg, values, gtsam.GaussNewtonParams())
        result = opt.optimize()
        return result, opt.iterations()

    t, (result, iterations) = median_time(solve, repeats)
    return dict(solver=f"GTSAM {method}", cost=fg.error(result), iterations=iterations, time_s=t)


# --------------------------------------------------------------------------- torchsgal engine
def engine_graph(graph: PoseGraph, initial, device: torch.device | None = None):
    """The engine's graph of ``graph`` from ``initial``, with every tensor on ``device``
    (default: where ``initial`` is)."""
    from torchsgal.estimation import graph as fg

    device = initial.device if device is None else device
    G = graph.group

    def on(x):
        return G(x.as_matrix().to(device)) if isinstance(x, ts.LieGroup) else x.to(device)

    g = fg.FactorGraph()
    g.add_variable("x", on(initial))
    i, j = graph.edges[:, 0], graph.edges[:, 1]
    g.add(fg.Between("x", on(i), on(j), on(graph.measurements), information=on(graph.information)))
    dof = graph.group.dof
    W0 = torch.eye(dof, dtype=torch.float64, device=device) / PRIOR_SIGMA**2
    g.add(fg.Prior("x", torch.tensor([0], device=device), on(initial[0:1]), information=W0))
    return g


def run_engine(graph: PoseGraph, initial, gtsam_fg, method: str, repeats: int) -> dict:
    from torchsgal.estimation import graph as fg

    solver = fg.levenberg_marquardt if method == "LM" else fg.gauss_newton

    def solve():
        return solver(engine_graph(graph, initial), max_iterations=100)

    t, result = median_time(solve, repeats)
    poses = result.values["x"]
    return dict(solver=f"torchsgal {method}", cost=gtsam_fg.error(gtsam_values(graph, poses)),
                engine_cost=float(result.report.cost[0]),
                iterations=int(result.report.iterations[0]), time_s=t,
                status=int(result.report.status[0]))


def engine_skip_reason(D: int, dense_limit: int) -> str | None:
    try:
        from torchsgal.estimation import graph as fg
    except ImportError as e:
        return f"torchsgal.estimation.graph does not import ({e})"
    params = inspect.signature(fg.levenberg_marquardt).parameters
    sparse = any(p in params for p in ("linear_solver", "sparse"))
    if D > dense_limit and not sparse:
        return (f"the engine assembles dense normal equations ({D} x {D}, "
                f"{D * D * 8 / 2**30:.1f} GiB per matrix, O(D^3) per step); run above "
                f"--dense-limit={dense_limit} once it takes a sparse solver")
    return None


# --------------------------------------------------------------------------- Theseus
def theseus_status() -> tuple[object | None, str]:
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            import theseus as th
        return th, f"theseus {th.__version__}"
    except Exception as e:  # any import failure is reported, not raised
        return None, f"theseus does not import: {type(e).__name__}: {e}"


def run_theseus(th, graph: PoseGraph, initial, gtsam_fg, repeats: int, max_iterations: int) -> dict:
    """Theseus LM with its CHOLMOD sparse solver; SE3 tangent [v, w] as torchsgal's."""
    if graph.group is not ts.SE3:
        raise NotImplementedError("the Theseus run covers SE3 graphs")
    W = graph.information
    if not torch.equal(W, torch.diag_embed(torch.diagonal(W, dim1=-2, dim2=-1))):
        raise NotImplementedError("the Theseus run takes diagonal information")
    sqrt_diag = torch.diagonal(W, dim1=-2, dim2=-1).sqrt()
    M0 = initial.as_matrix()[:, :3, :]  # Theseus stores (3, 4)
    Z = graph.measurements.as_matrix()[:, :3, :]

    def build():
        poses = [th.SE3(tensor=M0[k:k + 1].clone(), name=f"x{k}") for k in range(M0.shape[0])]
        objective = th.Objective(dtype=torch.float64)
        for e, (i, j) in enumerate(graph.edges.tolist()):
            w = th.DiagonalCostWeight(th.Variable(sqrt_diag[e:e + 1]))
            objective.add(th.Between(poses[i], poses[j], th.SE3(tensor=Z[e:e + 1]), w,
                                     name=f"e{e}"))
        w0 = th.ScaleCostWeight(torch.tensor([[1.0 / PRIOR_SIGMA]], dtype=torch.float64))
        objective.add(th.Difference(poses[0], th.SE3(tensor=M0[0:1].clone()), w0, name="prior"))
        return objective, poses

    def solve():
        objective, poses = build()
        optimizer = th.LevenbergMarquardt(objective, linear_solver_cls=th.CholmodSparseSolver,
                                          max_iterations=max_iterations, step_size=1.0,
                                          abs_err_tolerance=1e-5, rel_err_tolerance=1e-5)
        layer = th.TheseusLayer(optimizer)
        with torch.no_grad():
            _, info = layer.forward({}, optimizer_kwargs={"damping": THESEUS_DAMPING,
                                                          "track_best_solution": True})
        return poses, info

    t, (poses, info) = median_time(solve, repeats)
    M = torch.cat([p.tensor for p in poses]).detach()
    bottom = torch.tensor([0, 0, 0, 1], dtype=M.dtype).expand(M.shape[0], 1, 4)
    solution = ts.SE3.from_matrix(torch.cat([M, bottom], dim=1))
    return dict(solver="Theseus LM (CHOLMOD)", cost=gtsam_fg.error(gtsam_values(graph, solution)),
                iterations=_theseus_iterations(info, max_iterations),
                time_s=t)


def _theseus_iterations(info, max_iterations: int) -> str:
    done = int(info.converged_iter.max()) if info.converged_iter is not None else -1
    return str(done) if done >= 0 else f"{max_iterations} (not converged)"


# --------------------------------------------------------------------------- sparse solver
def normal_equations(graph: PoseGraph, initial):
    """The Gauss-Newton normal equations at ``initial``, from the engine's linearisation:
    lower-triangle pattern (rows, cols), entries (duplicates not merged), gradient."""
    from torchsgal.estimation.graph.linearize import Problem, linearize

    problem = Problem(engine_graph(graph, initial))
    lin = linearize(problem, problem.initial(engine_graph(graph, initial)))
    rows, cols = problem.h_index // problem.D, problem.h_index % problem.D
    lower = rows >= cols
    return rows[lower], cols[lower], lin.values[0][lower], lin.g[0], problem.D


def run_block(graph: PoseGraph, initial, repeats: int) -> dict:
    """The engine's block-sparse factorisation (``estimation.block_cholesky``) on the same
    normal equations: the analysis (minimum-degree order, fill, index maps; once per pattern)
    and factor + solve, timed as the backends."""
    from torchsgal.estimation import block_cholesky
    from torchsgal.estimation.block_cholesky import block_cholesky_solve
    from torchsgal.estimation.graph import linear_system
    from torchsgal.estimation.graph.linearize import Problem, linearize

    problem = Problem(engine_graph(graph, initial))
    lin = linearize(problem, problem.initial(engine_graph(graph, initial)))
    linear_system._layouts.clear()  # the analysis is timed afresh (both caches emptied)
    block_cholesky._cache.clear()
    t0 = time.perf_counter()
    system = linear_system.BlockSparseSystem(problem)
    analyse = time.perf_counter() - t0
    st, order = system.structure, system.structure.order
    rhs = -lin.g[:, order].unsqueeze(-1)
    stored = linearize(problem, problem.initial(engine_graph(graph, initial)), system.layout).values

    def factor_solve():
        return block_cholesky_solve(system._panels(stored), rhs, st)[1]

    t, x = median_time(factor_solve, repeats)
    delta = torch.empty_like(lin.g).index_copy_(1, order, x[..., 0])[0]
    rows, cols = problem.h_index // problem.D, problem.h_index % problem.D
    Ax = torch.zeros(problem.D, dtype=torch.float64).index_add_(0, rows, lin.values[0] * delta[cols])
    rel = float((Ax + lin.g[0]).norm() / lin.g[0].norm())
    return dict(backend="block (engine)", size=problem.D, nnz=int(rows.numel()), analyse_s=analyse,
                factor_solve_s=t, relative_residual=rel, flops=st.flops, dense_flops=st.dense_flops)


def run_sparse(graph: PoseGraph, initial, repeats: int) -> list[dict]:
    rows, cols, values, g, D = normal_equations(graph, initial)
    out = [run_block(graph, initial, repeats)]
    for backend in available_backends():
        if backend == "dense" and D > 5000:
            out.append(dict(backend=backend, size=D, skipped=f"{D} unknowns: dense O(D^3)"))
            continue
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            S = SparseCholesky(rows, cols, D, backend=backend)
        analyse = time.perf_counter() - t0

        def factor_solve(S=S):
            S.factor(values)
            return S.solve(-g)

        t, x = median_time(factor_solve, repeats)
        # residual of the solve against the pattern's matrix product
        Ax = torch.zeros(D, dtype=torch.float64).index_add_(0, rows, values * x[cols])
        off = rows != cols
        Ax.index_add_(0, cols[off], values[off] * x[rows[off]])
        rel = float((Ax + g).norm() / g.norm())
        out.append(dict(backend=backend, size=D, nnz=int(rows.numel()), analyse_s=analyse,
                        factor_solve_s=t, relative_residual=rel))
    return out


# --------------------------------------------------------------------------- --device mode
def gtsam_status() -> tuple[bool, str]:
    try:
        import gtsam
        return True, f"gtsam {getattr(gtsam, '__version__', '')}".strip()
    except Exception as e:  # any import failure is reported, not raised
        return False, f"gtsam not importable: {type(e).__name__}: {e}"


def timed_runs(fn, repeats: int, device: torch.device, deadline: float, warmup: bool):
    """(median seconds, runs, last result) of up to ``repeats`` calls of ``fn``, the device
    synchronised before starting and before stopping each clock; no further call once
    ``deadline`` (perf_counter) has passed, one at least.  ``warmup``: one untimed call first."""
    if warmup:
        fn()
    times, out = [], None
    for _ in range(repeats):
        synchronize(device)
        t0 = time.perf_counter()
        out = fn()
        synchronize(device)
        times.append(time.perf_counter() - t0)
        if time.perf_counter() > deadline:
            break
    return statistics.median(times), len(times), out


def run_engine_on(graph: PoseGraph, initial, method: str, device: torch.device, repeats: int,
                  deadline: float, warmup: bool, gtsam_fg=None) -> dict:
    """The engine (linear_solver "auto") on ``device``: its own final cost 1/2 chi-square (and
    GTSAM's ``graph.error`` of its solution where GTSAM imports)."""
    from torchsgal.estimation import graph as fg

    solver = fg.levenberg_marquardt if method == "LM" else fg.gauss_newton

    def solve():
        return solver(engine_graph(graph, initial, device), max_iterations=100)

    t, runs, result = timed_runs(solve, repeats, device, deadline, warmup)
    poses = result.values["x"]
    row = dict(solver=f"torchsgal {method}", device=str(device), time_s=t, runs=runs,
               engine_cost=float(result.report.cost[0]), iterations=int(result.report.iterations[0]),
               status=SolverStatus(int(result.report.status[0])).name, results_device=str(poses.device),
               linear_solver=type(result.system).__name__ + (
                   f" ({result.system.backend})" if hasattr(result.system, "backend") else " (batched Cholesky)"))
    row["cost"] = gtsam_fg.error(gtsam_values(graph, poses)) if gtsam_fg is not None else row["engine_cost"]
    return row


def warm_up(device: torch.device, graphs: list[PoseGraph]) -> float:
    """One untimed LM and GN solve of each small graph on ``device`` with the dense and with the
    sparse linear solver (CUDA context, library handles, kernel loading); returns seconds."""
    from torchsgal.estimation import graph as fg

    t0 = time.perf_counter()
    for graph in graphs:
        initial = graph.poses if graph.poses is not None else odometry_initial_guess(graph)
        for solver in (fg.levenberg_marquardt, fg.gauss_newton):
            for linear_solver in ("dense", "sparse"):
                solver(engine_graph(graph, initial, device), max_iterations=3, linear_solver=linear_solver)
    synchronize(device)
    return time.perf_counter() - t0


def main_device(args, device: torch.device) -> dict:
    """The engine on ``device`` and on the host CPU in one run (--device); GTSAM and Theseus
    rows where they import, a note where they do not."""
    cpu = torch.device("cpu")
    start = time.perf_counter()
    deadline = start + args.time_budget
    has_gtsam, gtsam_note = gtsam_status()
    th, theseus_note = theseus_status()
    small = [read_pose_graph(DATA / n) for n in ("pose3example-grid.txt", "w100.graph")]
    warm = {str(d): warm_up(d, small) for d in dict.fromkeys([device, cpu])}
    results = dict(device=str(device), device_name=device_name(device), cpu=cpu_model(),
                   python=sys.version.split()[0], torch=torch.__version__, cuda=torch.version.cuda,
                   threads=torch.get_num_threads(), repeats=args.repeats, time_budget_s=args.time_budget,
                   prior_sigma=PRIOR_SIGMA, gtsam=gtsam_note, theseus=theseus_note,
                   sparse_backends=list(available_backends()), warm_up_s=warm, kernels=kernels_note(),
                   environment={k: os.environ.get(k) for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS")},
                   command=" ".join(["python benchmarks/bench_posegraph.py", *sys.argv[1:]]), problems={})
    for name in args.problems:
        graph = read_pose_graph(DATA / name)
        initial = graph.poses if graph.poses is not None else odometry_initial_guess(graph)
        gtsam_fg = values = None
        if has_gtsam:
            gtsam_fg, values = gtsam_problem(graph, initial)
        D = graph.ids.numel() * graph.group.dof
        small_problem = D <= args.dense_limit
        repeats = 5 * args.repeats if small_problem else args.repeats
        entry = dict(group=graph.group.__name__, vertices=graph.ids.numel(), edges=graph.edges.shape[0],
                     unknowns=D, repeats=repeats, solvers=[])
        if gtsam_fg is not None:
            entry["initial_cost_gtsam"] = gtsam_fg.error(values)
        for method in ("LM", "GN"):
            for d in dict.fromkeys([device, cpu]):
                if time.perf_counter() > deadline:
                    row = dict(solver=f"torchsgal {method}", device=str(d),
                               skipped=f"time budget of {args.time_budget} s spent")
                else:
                    row = run_engine_on(graph, initial, method, d, repeats, deadline, small_problem, gtsam_fg)
                entry["solvers"].append(row)
                print(name, row, flush=True)
        if has_gtsam:
            for method in ("LM", "GN"):
                row = dict(run_gtsam(gtsam_fg, values, method, repeats), device="cpu")
                entry["solvers"].append(row)
                print(name, row, flush=True)
        else:
            entry["solvers"].append(dict(solver="GTSAM LM and GN", device="cpu", skipped=gtsam_note))
        if th is None or not has_gtsam:
            entry["solvers"].append(dict(solver="Theseus LM (CHOLMOD)", device="cpu", skipped=(
                theseus_note if th is None else "needs GTSAM's graph.error for its cost")))
        elif time.perf_counter() > deadline:
            entry["solvers"].append(dict(solver="Theseus LM (CHOLMOD)", device="cpu",
                                         skipped=f"time budget of {args.time_budget} s spent"))
        else:
            try:
                row = run_theseus(th, graph, initial, gtsam_fg, 1, args.theseus_max_iterations)
                entry["solvers"].append(dict(row, device="cpu", runs=1))
            except Exception as e:  # reported in the results, not raised
                entry["solvers"].append(dict(solver="Theseus LM (CHOLMOD)", device="cpu",
                                             skipped=f"{type(e).__name__}: {e}"))
        print(name, entry["solvers"][-1], flush=True)
        for row in entry["solvers"]:
            if "time_s" in row and row["solver"].startswith("torchsgal"):
                peer = next((r for r in entry["solvers"] if r["solver"] == row["solver"]
                             and r.get("device") == "cpu" and "time_s" in r), None)
                if peer is not None:
                    row["time_vs_engine_cpu"] = row["time_s"] / peer["time_s"]
                    row["cost_vs_engine_cpu"] = (row["cost"] - peer["cost"]) / peer["cost"]
        results["problems"][name] = entry
    results["total_s"] = time.perf_counter() - start
    out = Path(args.out or Path(__file__).parent / "results" / f"posegraph_{device.type}")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(results, indent=2) + "\n")
    out.with_suffix(".md").write_text(markdown_device(results))
    print(markdown_device(results))
    return results


def device_name(device: torch.device) -> str:
    return torch.cuda.get_device_name(device) if device.type == "cuda" else cpu_model()


def markdown_device(results: dict) -> str:
    lines = [f"# Pose-graph optimisation: the engine on {results['device']} ({results['device_name']}) "
             "and on the host CPU", "",
             f"`{results['command']}`; torch {results['torch']} (CUDA {results['cuda']}), host CPU "
             f"{results['cpu']}, {results['threads']} threads, "
             f"{results.get('kernels', 'C kernels not recorded')}; median of up to {results['repeats']} "
             f"runs (5x that, after an untimed run, for the problems of at most --dense-limit "
             f"unknowns), the device synchronised before and after each; time budget "
             f"{results['time_budget_s']} s (a row with fewer runs than asked, or not run, when it "
             f"was spent); total {results['total_s']:.1f} s. The engine's linear solver is \"auto\" "
             f"(sparse backends installed: {', '.join(results['sparse_backends'])}); its results "
             f"stay on the device it ran on. {results['gtsam']}; {results['theseus']}; "
             f"environment {results['environment']}.", ""]
    for name, e in results["problems"].items():
        lines += [f"## {name}: {e['group']}, {e['vertices']} poses, {e['edges']} edges, "
                  f"{e['unknowns']} unknowns", "",
                  "| solver | device | linear solver | final cost | iterations | status | runs | time (s) "
                  "| x engine on CPU |", "|---|---|---|---|---|---|---|---|---|"]
        for s in e["solvers"]:
            if "skipped" in s:
                lines.append(f"| {s['solver']} | {s['device']} | not run: {s['skipped']} | | | | | | |")
                continue
            ratio = f"{s['time_vs_engine_cpu']:.2f}" if "time_vs_engine_cpu" in s else ""
            lines.append(f"| {s['solver']} | {s['device']} | {s.get('linear_solver', '')} | "
                         f"{s['cost']:.10g} | {s['iterations']} | {s.get('status', '')} | "
                         f"{s.get('runs', e['repeats'])} | {s['time_s']:.4g} | {ratio} |")
        lines.append("")
    return "\n".join(lines)


# --------------------------------------------------------------------------- main
def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--problems", nargs="+", default=list(PROBLEMS), choices=PROBLEMS)
    parser.add_argument("--dense-limit", type=int, default=2000)
    parser.add_argument("--theseus-max-iterations", type=int, default=30)
    parser.add_argument("--out", default=None,
                        help="output path without suffix (default benchmarks/results/posegraph_cpu, "
                             "with --device: posegraph_<device type>)")
    parser.add_argument("--device", default=None,
                        help="run the engine on this device (cpu or cuda[:i]) and on the host CPU, "
                             "GTSAM and Theseus where they import (no SparseCholesky rows)")
    parser.add_argument("--time-budget", type=float, default=100.0,
                        help="with --device: seconds after which no further timed run starts")
    parser.add_argument("--merge", action="store_true",
                        help="keep the entries of the problems not run from the existing result "
                             "file at --out (marked as such)")
    args = parser.parse_args(argv)
    torch.set_default_dtype(torch.float64)
    if not DATA.is_dir():
        raise SystemExit(f"data folder not found: {DATA}")
    if args.device is not None:
        device = resolve_device(args.device)
        if device.type != "cpu" and args.out and Path(args.out).name.endswith("_cpu"):
            raise SystemExit(f"--out {args.out}: a {device.type} run does not write the CPU result files")
        if args.merge:
            raise SystemExit("--merge is for the CPU benchmark (without --device)")
        return main_device(args, device)
    args.out = args.out or str(Path(__file__).parent / "results" / "posegraph_cpu")
    th, theseus_note = theseus_status()
    results = dict(machine=platform.processor() or platform.machine(), python=sys.version.split()[0],
                   torch=torch.__version__, threads=torch.get_num_threads(), repeats=args.repeats,
                   prior_sigma=PRIOR_SIGMA, theseus=theseus_note,
                   environment={k: os.environ.get(k) for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS")},
                   command=" ".join(["python benchmarks/bench_posegraph.py", *(argv or sys.argv[1:])]),
                   problems={})
    for name in args.problems:
        graph = read_pose_graph(DATA / name)
        initial = graph.poses if graph.poses is not None else odometry_initial_guess(graph)
        gtsam_fg, values = gtsam_problem(graph, initial)
        D = graph.ids.numel() * graph.group.dof
        entry = dict(group=graph.group.__name__, vertices=graph.ids.numel(),
                     edges=graph.edges.shape[0], unknowns=D, initial_cost=gtsam_fg.error(values),
                     solvers=[])
        repeats = args.repeats if D > args.dense_limit else 5 * args.repeats  # small: noisier
        entry["repeats"] = repeats
        for method in ("LM", "GN"):
            entry["solvers"].append(run_gtsam(gtsam_fg, values, method, repeats))
            print(name, entry["solvers"][-1], flush=True)
        reason = engine_skip_reason(D, args.dense_limit)
        for method in ("LM", "GN"):
            if reason:
                entry["solvers"].append(dict(solver=f"torchsgal {method}", skipped=reason))
            else:
                entry["solvers"].append(run_engine(graph, initial, gtsam_fg, method, repeats))
            print(name, entry["solvers"][-1], flush=True)
        if th is None:
            entry["solvers"].append(dict(solver="Theseus LM (CHOLMOD)", skipped=theseus_note))
        else:
            try:
                entry["solvers"].append(run_theseus(th, graph, initial, gtsam_fg, 1,
                                                    args.theseus_max_iterations))
            except Exception as e:  # reported in the results, not raised
                entry["solvers"].append(dict(solver="Theseus LM (CHOLMOD)",
                                             skipped=f"{type(e).__name__}: {e}"))
        print(name, entry["solvers"][-1], flush=True)
        try:
            entry["sparse"] = run_sparse(graph, initial, repeats)
        except Exception as e:  # the engine's linearisation is needed for the real matrices
            entry["sparse"] = [dict(skipped=f"{type(e).__name__}: {e}")]
        for s in entry["sparse"]:
            print(name, s, flush=True)
        lm = entry["solvers"][0]
        for s in entry["solvers"]:
            if "cost" in s:
                s["cost_vs_gtsam_lm"] = (s["cost"] - lm["cost"]) / lm["cost"]
                s["time_vs_gtsam_lm"] = s["time_s"] / lm["time_s"]
        results["problems"][name] = entry
    out = Path(args.out)
    if args.merge and out.with_suffix(".json").exists():
        earlier = json.loads(out.with_suffix(".json").read_text())
        merged = {}
        for name, entry in earlier.get("problems", {}).items():
            if name in results["problems"]:
                merged[name] = results["problems"][name]
            else:
                merged[name] = dict(entry, kept=entry.get("kept") or dict(
                    torch=earlier.get("torch"), repeats=earlier.get("repeats"),
                    threads=earlier.get("threads")))
        merged.update({n: e for n, e in results["problems"].items() if n not in merged})
        results["problems"] = merged
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(results, indent=2) + "\n")
    out.with_suffix(".md").write_text(markdown(results))
    return results


def markdown(results: dict) -> str:
    lines = ["# Pose-graph optimisation (CPU)", "",
             f"`{results.get('command', 'python benchmarks/bench_posegraph.py')}`; torch "
             f"{results['torch']}, {results['threads']} threads; median of {results['repeats']} "
             f"runs (5x that for the small problems); cost = 1/2 chi-square by GTSAM's `graph.error` "
             f"on each solution; prior sigma {results['prior_sigma']} on the first pose; "
             f"{results['theseus']}; environment {results['environment']}.", ""]
    for name, e in results["problems"].items():
        kept = e.get("kept")
        note = ([f"Not re-run with the other problems (`--merge`): measured by an earlier run of "
                 f"this script (torch {kept['torch']}, {kept['threads']} threads, --repeats "
                 f"{kept['repeats']}).", ""] if kept else [])
        lines += [f"## {name}: {e['group']}, {e['vertices']} poses, {e['edges']} edges, "
                  f"{e['unknowns']} unknowns (initial cost {e['initial_cost']:.6g})", "", *note,
                  "| solver | final cost | rel. to GTSAM LM | iterations | time (s) | x GTSAM LM |",
                  "|---|---|---|---|---|---|"]
        for s in e["solvers"]:
            if "skipped" in s:
                lines.append(f"| {s['solver']} | not run: {s['skipped']} | | | | |")
            else:
                lines.append(f"| {s['solver']} | {s['cost']:.10g} | {s['cost_vs_gtsam_lm']:+.2e} | "
                             f"{s['iterations']} | {s['time_s']:.4g} | {s['time_vs_gtsam_lm']:.2f} |")
        lines += ["", "| SparseCholesky backend (and the engine's block factorisation) | unknowns | "
                      "analyse (s) | factor + solve (s) | relative residual |", "|---|---|---|---|---|"]
        for s in e["sparse"]:
            if "skipped" in s:
                lines.append(f"| {s.get('backend', '-')} | {s.get('size', '')} | not run: "
                             f"{s['skipped']} | | |")
            else:
                lines.append(f"| {s['backend']} | {s['size']} | {s['analyse_s']:.4f} | "
                             f"{s['factor_solve_s']:.4f} | {s['relative_residual']:.1e} |")
        lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
