"""The factor-graph engine (``torchsgal.estimation.graph``) on a CUDA device against the same
code on the CPU (whose results ``test_factor_graph.py`` and ``test_factor_graph_gtsam.py``
check against finite differences, the closed form and GTSAM), and the host reads of its solve
loop on the device.

Collected only where ``torch.cuda.is_available()`` (see conftest.py), like ``test_cuda.py``,
whose harness it shares (``DEVICE`` from ``TORCHSGAL_CUDA_TEST_DEVICE``, default "cuda";
``TORCHSGAL_CUDA_TEST_DEVICE=cpu`` runs it against the CPU itself, where the parity checks are
trivial and CUDA's sync detector is off).

float64 runs take the same steps on both devices: the iteration counts and statuses must be
equal, the costs and solutions equal within the suite's tolerance (conftest.tol, relative to
magnitude: the devices' kernels round differently, by a few ulps per operation).
"""
from __future__ import annotations

import torch
from conftest import tol
from host_syncs import HostSyncs, solve_loop_reads
from test_cuda import CPU, DEVICE, _no_sync, _same
from test_factor_graph import EDGES_I, EDGES_J, SIGMA, pose_graphs, rigid_fit_problem

import torchsgal as ts
from torchsgal.estimation import SolverStatus
from torchsgal.estimation import graph as fg
from torchsgal.estimation.graph.linear_system import DenseSystem, SparseSystem
from torchsgal.estimation.graph.linearize import Problem, evaluate_cost, linearize
from torchsgal.estimation.sparse import available_backends

f64 = torch.float64


def _on(x, device, dtype=f64):
    """A group element or tensor moved to ``device`` and cast to ``dtype`` (a new copy)."""
    if isinstance(x, ts.LieGroup):
        return type(x)(x.as_matrix().to(device=device, dtype=dtype))
    return x.to(device=device, dtype=dtype) if x.is_floating_point() else x.to(device)


def _pose_graph(Z, Z0, x0, device, dtype=f64, loss=None):
    """``test_factor_graph._graph`` with every tensor (indices, noise) on ``device``."""
    W = _on(torch.diag(SIGMA ** -2), device, dtype)
    graph = fg.FactorGraph()
    graph.add_variable("x", _on(x0, device, dtype))
    graph.add(fg.Prior("x", 0, _on(Z0, device, dtype), information=W))
    graph.add(fg.Between("x", EDGES_I.to(device), EDGES_J.to(device), _on(Z, device, dtype),
                         information=W), loss=loss)
    return graph


def _rigid_fit_graph(p, q, device, loss=None):
    """``test_factor_graph.rigid_fit_graph`` (a user factor: forward-mode Jacobians) on ``device``."""
    B, K = p.shape[:2]
    graph = fg.FactorGraph()
    graph.add_variable("T", ts.SE3.identity((B, 1), dtype=f64, device=device))
    graph.add(fg.Factor(lambda T, a, b: T.act(a) - b,
                        [("T", torch.zeros(K, dtype=torch.int64, device=device))],
                        [_on(p, device), _on(q, device)], dim=3), loss=loss)
    return graph


def _same_solve(dev, cpu, name, dtype=f64):
    """Two ``GraphResult``s of one graph, on DEVICE and on the CPU: equal statuses and
    iterations, costs and solutions within tolerance, everything on DEVICE."""
    r, c = dev.report, cpu.report
    for what in ("status", "iterations", "cost", "initial_cost"):
        assert getattr(r, what).device.type == DEVICE.type, f"report.{what} on {getattr(r, what).device}"
    assert r.status.tolist() == c.status.tolist(), (r.counts(), c.counts())
    assert r.iterations.tolist() == c.iterations.tolist()
    _same(r.initial_cost, c.initial_cost, dtype, "initial cost")
    _same(r.cost, c.cost, dtype, "final cost")
    _same(dev.values[name], cpu.values[name], dtype, f"solution {name}")


def test_batched_pose_graphs_match_cpu():
    """64 SE(3) pose graphs (8 poses, 10 edges, a prior), batched Levenberg-Marquardt."""
    _, Z, Z0, x0 = pose_graphs(B=64, seed=0)
    dev = fg.levenberg_marquardt(_pose_graph(Z, Z0, x0, DEVICE))
    cpu = fg.levenberg_marquardt(_pose_graph(Z, Z0, x0, CPU))
    assert (cpu.report.status == SolverStatus.CONVERGED).all(), cpu.report.counts()
    if DEVICE.type == "cuda":  # the block-sparse Cholesky kernel is the CPU's: "auto" takes dense
        assert isinstance(dev.system, DenseSystem)
    _same_solve(dev, cpu, "x")
    _same(dev.marginal_covariance("x", [1, 6]), cpu.marginal_covariance("x", [1, 6]), f64,
          "marginal covariances")


def test_batched_pose_graphs_with_huber_loss_match_cpu():
    """The same with a Huber loss on the Between factors, from far initial poses (residuals
    beyond the Huber threshold, so that the reweighting acts)."""
    _, Z, Z0, x0 = pose_graphs(B=64, seed=2, init_noise=1.0)
    dev = fg.levenberg_marquardt(_pose_graph(Z, Z0, x0, DEVICE, loss=fg.Huber(1.0)))
    cpu = fg.levenberg_marquardt(_pose_graph(Z, Z0, x0, CPU, loss=fg.Huber(1.0)))
    plain = fg.levenberg_marquardt(_pose_graph(Z, Z0, x0, CPU))
    assert not torch.equal(cpu.report.cost, plain.report.cost), "the loss changed nothing"
    _same_solve(dev, cpu, "x")


def test_float32_pose_graphs_on_device_reach_the_float64_optimum():
    """float32 on DEVICE: every problem converges, and the float64 cost at its float32 solution
    (and the float32 cost it reports) is the float64 optimum's within float32 tolerance
    (conftest.tol, relative).  The cost, stationary at the optimum, is compared rather than the
    poses or the iteration counts: float32 poses sit up to cond(H) x eps from the optimum
    (2e-4 on translations of up to 6 on the CPU itself), and a step whose cost change is near
    the 1e-5 relative stopping rule is judged on float32 costs that round differently on each
    device."""
    _, Z, Z0, x0 = pose_graphs(B=64, seed=0)
    ref = fg.levenberg_marquardt(_pose_graph(Z, Z0, x0, CPU))
    dev = fg.levenberg_marquardt(_pose_graph(Z, Z0, x0, DEVICE, torch.float32))
    assert (dev.report.status == SolverStatus.CONVERGED).all(), dev.report.counts()
    x = dev.values["x"]
    assert x.device.type == DEVICE.type and x.dtype == torch.float32
    at_solution = fg.levenberg_marquardt(_pose_graph(Z, Z0, _on(x, CPU), CPU), max_iterations=0)
    for cost in (at_solution.report.cost, dev.report.cost.cpu().double()):
        rel = ((cost - ref.report.cost).abs() / ref.report.cost).max()
        assert float(rel) <= tol(torch.float32), float(rel)


def test_user_factor_with_cauchy_loss_matches_cpu():
    """The rigid fit (a user factor, forward-mode Jacobians) with outliers and a Cauchy loss."""
    _, p, q = rigid_fit_problem(B=64, K=60, seed=6, noise=0.005, outliers=15)
    dev = fg.levenberg_marquardt(_rigid_fit_graph(p, q, DEVICE, loss=fg.Cauchy(0.02)))
    cpu = fg.levenberg_marquardt(_rigid_fit_graph(p, q, CPU, loss=fg.Cauchy(0.02)))
    assert (cpu.report.status == SolverStatus.CONVERGED).all(), cpu.report.counts()
    _same_solve(dev, cpu, "T")


def _chain_with_loops(N=300, seed=21):
    """One SE(3) pose graph of N poses (6N unknowns, above levenberg_marquardt.SPARSE_ABOVE):
    odometry edges i -> i+1 and loop closures i -> i+25 every 5 poses, a prior on pose 0."""
    gen = torch.Generator().manual_seed(seed)
    scale = torch.tensor([1.0, 0.2, 0.2, 0.05, 0.05, 0.2], dtype=f64)  # forward, turning
    steps = ts.SE3.exp(torch.randn(N - 1, 6, generator=gen, dtype=f64) * scale)
    mats = [torch.eye(4, dtype=f64)]
    for m in steps.as_matrix():
        mats.append(mats[-1] @ m)
    truth = ts.SE3(torch.stack(mats))
    loops = torch.arange(0, N - 25, 5)
    i = torch.cat([torch.arange(N - 1), loops])
    j = torch.cat([torch.arange(1, N), loops + 25])
    noise = ts.SE3.exp(torch.randn(i.numel(), 6, generator=gen, dtype=f64) * SIGMA)
    Z = truth[i].inverse() @ truth[j] @ noise
    x0 = truth @ ts.SE3.exp(0.05 * torch.randn(N, 6, generator=gen, dtype=f64))
    return truth, i, j, Z, x0


def _large_graph(device):
    truth, i, j, Z, x0 = _chain_with_loops()
    W = _on(torch.diag(SIGMA ** -2), device)
    graph = fg.FactorGraph()
    graph.add_variable("x", _on(x0, device))
    graph.add(fg.Prior("x", torch.tensor([0], device=device), _on(truth[0:1], device), information=W))
    graph.add(fg.Between("x", i.to(device), j.to(device), _on(Z, device), information=W))
    return graph


def test_one_large_problem_auto_takes_the_sparse_solver_and_matches_cpu():
    """1800 unknowns, one problem: "auto" takes ``SparseCholesky`` with its first installed
    backend (``estimation.sparse``: cholmod, cholespy, scipy, dense; where only scipy is
    installed, SuperLU on the host, one copy to and from the host per factor/solve), on DEVICE
    as on the CPU; the answer equals the CPU's with that backend and the CPU's dense solve."""
    backend = available_backends()[0]
    dev = fg.levenberg_marquardt(_large_graph(DEVICE))
    assert isinstance(dev.system, SparseSystem) and dev.system.backend == backend, (
        type(dev.system).__name__, getattr(dev.system, "backend", None))
    cpu = fg.levenberg_marquardt(_large_graph(CPU), linear_solver=backend)
    assert (cpu.report.status == SolverStatus.CONVERGED).all(), cpu.report.counts()
    _same_solve(dev, cpu, "x")
    dense = fg.levenberg_marquardt(_large_graph(CPU), linear_solver="dense")
    assert dense.report.iterations.tolist() == dev.report.iterations.tolist()
    _same(dev.values["x"], dense.values["x"], f64, "sparse on DEVICE vs dense on CPU")


def test_implicit_gradient_matches_cpu():
    """d(sum of weighted solution matrices)/d(tangent perturbations of the Between
    measurements) by implicit differentiation at the converged batched solve."""
    _, Z, Z0, x0 = pose_graphs(B=16, seed=3)
    weights = torch.randn(16, 8, 4, 4, generator=torch.Generator().manual_seed(1), dtype=f64)
    grads = []
    for device in (DEVICE, CPU):
        xi = torch.zeros(16, 10, 6, dtype=f64, device=device, requires_grad=True)
        graph = fg.FactorGraph()
        W = _on(torch.diag(SIGMA ** -2), device)
        graph.add_variable("x", _on(x0, device))
        graph.add(fg.Prior("x", 0, _on(Z0, device), information=W))
        graph.add(fg.Between("x", EDGES_I.to(device), EDGES_J.to(device),
                             _on(Z, device) @ ts.SE3.exp(xi), information=W))
        out = fg.levenberg_marquardt(graph, backward_mode="implicit")
        assert (out.report.status == SolverStatus.CONVERGED).all(), out.report.counts()
        loss = (out.values["x"].as_matrix() * weights.to(device)).sum()
        grads.append(torch.autograd.grad(loss, xi)[0])
    g_dev, g_cpu = grads
    assert float(g_cpu.abs().max()) > 1e-3  # a gradient that is there
    _same(g_dev, g_cpu, f64, "implicit gradient")


def test_hot_path_reads_nothing_from_the_device():
    """One Levenberg-Marquardt round's work on DEVICE (linearise, damped dense solve, retract,
    trial cost) under CUDA's sync detector and the suite's recorder: no value read, no linalg
    error check, no host copy."""
    _, Z, Z0, x0 = pose_graphs(B=16, seed=11)
    graph = _pose_graph(Z, Z0, x0, DEVICE)
    problem = Problem(graph)
    x = problem.initial(graph)
    system = DenseSystem(problem)
    lam = torch.full((16,), 1e-5, dtype=f64, device=DEVICE)

    def one_round():
        lin = linearize(problem, x, system.layout)
        delta, solved, _ = system.solve(lin.values, lin.g, lam, False)
        return lin, solved, evaluate_cost(problem, problem.retract(x, delta))

    one_round()  # first call (kernel loading, library handles, work buffers) outside the detectors
    with HostSyncs() as syncs, _no_sync():
        lin, solved, cost = one_round()
    assert not syncs.events, syncs.events
    assert solved.all() and (cost < lin.cost).all()  # the round did its work (read afterwards)


def test_solve_loop_reads_once_per_round_on_device():
    """The whole solve on DEVICE: the only host reads are the loop's, one per round (how many
    problems still run) and the active set's indices when it shrinks (the engine's documented
    reads; test_factor_graph.test_host_syncs_are_one_per_round_outside_the_setup on the CPU)."""
    _, Z, Z0, x0 = pose_graphs(B=16, seed=11)
    graph = _pose_graph(Z, Z0, x0, DEVICE)
    result, in_hot, loop = solve_loop_reads(lambda: fg.levenberg_marquardt(graph))
    assert not in_hot, in_hot
    rounds = int(result.report.iterations.max()) + 2
    assert 0 < len(loop) <= 2 * rounds, loop
    _same(result.report.cost, fg.levenberg_marquardt(_pose_graph(Z, Z0, x0, CPU)).report.cost, f64,
          "final cost")


# --------------------------------------------------------- the engine's operators on the device
def _operator_cases():
    """Each of the engine's registered operators with CPU arguments (the builders of its CPU
    tests) and the opcheck utilities its CPU test runs."""
    from test_block_cholesky import MIXED, analysed, pattern_matrix, stored
    from test_dense_solve import spd
    from test_factor_kernels import _assemble_case, _pair, _pair2
    from test_gram_cholesky_solve import gram_inputs
    from test_normal_kernel import case

    ops = torch.ops.torchsgal
    cases = []
    for summed in (False, True):
        J, r, slots, values, g_slots, g = case(B=2, E=3, m=2, Dk=4, summed=summed)
        cases.append((f"normal_assemble summed={summed}", ops.normal_assemble,
                      (J, r, slots, values, g_slots, g, summed), None))
    gen = torch.Generator().manual_seed(5)
    for group, pair, d in (("se3", _pair, 6), ("se2", _pair2, 3)):
        Zinv, Ti, Tj = pair(0.5, n=4, seed=7)
        L = torch.randn(d, d, generator=gen, dtype=f64).tril() + 3 * torch.eye(d, dtype=f64)
        cases += [(f"{group}_factor_terms between", getattr(ops, f"{group}_factor_terms"), (Zinv, Ti, Tj, True), None),
                  (f"{group}_factor_terms prior", getattr(ops, f"{group}_factor_terms"), (Zinv, None, Tj, False), None),
                  (f"{group}_factor_normal", getattr(ops, f"{group}_factor_normal"), (Zinv, Ti, Tj, L), None)]
        _, Zb, Tib, Tjb, vals, gvec, gen2 = _assemble_case(group.upper(), B=2, E=3)
        slots = torch.randint(0, vals.shape[1], (3, 4 * d * d), generator=gen2)
        g_slots = torch.randint(0, gvec.shape[1], (3, 2 * d), generator=gen2)
        cases.append((f"{group}_factor_assemble", getattr(ops, f"{group}_factor_assemble"),
                      (Zb, Tib, Tjb, L, slots, vals, g_slots, gvec), None))
    A, R = spd(5, 6, f64, seed=8), torch.randn(5, 6, 3, dtype=f64, generator=gen)
    cases += [(f"cholesky_solve back={back}", ops.cholesky_solve, (A, R, back), None) for back in (True, False)]
    G, d, Rg = gram_inputs((5,), 4, 6, 3, f64, seed=6)
    cases += [(f"gram_cholesky_solve back={back}", ops.gram_cholesky_solve, (G, d, Rg, back), None)
              for back in (True, False)]
    Lc = torch.linalg.cholesky(A)
    cases += [(f"triangular_solve transpose={t}", ops.triangular_solve, (Lc, R, t), None) for t in (True, False)]
    st = analysed(*MIXED)
    Ab, _ = pattern_matrix(*MIXED, B=2, seed=3)
    cases.append(("block_cholesky_solve", ops.block_cholesky_solve,
                  (stored(st, Ab), torch.randn(2, st.size, 2, dtype=f64, generator=gen), st.packed),
                  ("test_schema", "test_faketensor")))
    return cases


def test_engine_operators_on_device_match_cpu_and_pass_opcheck():
    """Every registered operator of the engine (the factor terms, normal blocks and assembly of
    SE(3)/SE(2), the normal equations of any block, the dense, Gram and block-sparse Cholesky solves)
    on DEVICE: the same outputs as on the CPU, new tensors on DEVICE, and torch.library.opcheck
    with device arguments (float64 and float32)."""
    from torch.library import opcheck

    for name, op, args, utils in _operator_cases():
        for dtype in (f64, torch.float32):
            cpu_args = tuple(a.to(dtype) if isinstance(a, torch.Tensor) and a.is_floating_point() else a
                             for a in args)
            dev_args = tuple(a.to(DEVICE) if isinstance(a, torch.Tensor) else a for a in cpu_args)
            expected = op(*cpu_args)
            got = op(*dev_args)
            for k, (x, y) in enumerate(zip(got, expected)):
                if y.is_floating_point():
                    _same(x, y, dtype, f"{name} {dtype} output {k}")
                else:  # a solve's failure flags
                    assert x.device.type == DEVICE.type and torch.equal(x.cpu(), y), (name, k, x, y)
            for a, b in zip(dev_args, cpu_args):  # no argument written
                if isinstance(a, torch.Tensor):
                    assert torch.equal(a.cpu(), b), f"{name}: an argument was written"
            opcheck(op.default, dev_args, **({} if utils is None else {"test_utils": utils}))
