"""``estimation.block_cholesky``: the symbolic analysis (order, fill, cache), the operator's C
kernel against the definitions (L L^T = A, A X = R) and against its tensor code (torch.linalg),
failures, opcheck, and the engine's block-sparse linear solver against the dense one."""
from __future__ import annotations

import pytest
import torch
from torch.library import opcheck

from torchsgal.estimation import block_cholesky as bc
from torchsgal.functional import native

f64 = torch.float64


def pattern_matrix(sizes, pairs, B=3, seed=0, dtype=f64):
    """A batch of SPD matrices (B, D, D) with the block pattern ``pairs`` (J^T J of random
    factors on each pair, plus a diagonal)."""
    gen = torch.Generator().manual_seed(seed)
    starts = [0]
    for s in sizes:
        starts.append(starts[-1] + s)
    D = starts[-1]
    A = torch.zeros(B, D, D, dtype=f64)
    for a, b in pairs:
        idx = list(range(starts[a], starts[a + 1])) + list(range(starts[b], starts[b + 1]))
        J = torch.randn(B, len(idx) + 1, len(idx), generator=gen, dtype=f64)
        A[:, torch.tensor(idx)[:, None], torch.tensor(idx)] += J.mT @ J
    A += torch.eye(D, dtype=f64)
    return A.to(dtype), starts


def stored(structure, A):
    """The values (B, P) of A (system order) in the structure's layout (its scatter index of
    every entry)."""
    D = A.shape[-1]
    flat = torch.arange(D * D)
    pos = structure.scatter_index(flat)
    keep = pos < structure.panels
    values = A.new_zeros(A.shape[0], structure.panels)
    values[:, pos[keep]] = A.reshape(A.shape[0], -1)[:, flat[keep]]
    return values


def dense_factor(structure, L):
    """L (B, P) as a dense lower-triangular (B, D, D) matrix in elimination order."""
    rows, cols = bc._unpack_dense(structure.packed)
    D = structure.size
    return L.new_zeros(L.shape[0], D * D).index_copy_(1, rows * D + cols, L).view(-1, D, D)


def analysed(sizes, pairs):
    rows = torch.tensor([a for a, _ in pairs], dtype=torch.int64)
    cols = torch.tensor([b for _, b in pairs], dtype=torch.int64)
    return bc.analyse(torch.tensor(sizes, dtype=torch.int64), rows, cols)


CHAIN = ([6] * 8, [(i, i + 1) for i in range(7)])
POSE_GRAPH = ([6] * 8, [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (5, 6), (6, 7), (0, 4), (2, 6),
                        (1, 7), (0, 0)])
MIXED = ([3, 10, 1, 6, 15, 2], [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (5, 0), (1, 4), (2, 2)])
ONE = ([4], [(0, 0)])


@pytest.mark.kernels
@pytest.mark.parametrize("case", [CHAIN, POSE_GRAPH, MIXED, ONE], ids=["chain", "pose graph", "mixed", "one"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_kernel_solves_and_factors_by_the_definition(case, dtype):
    sizes, pairs = case
    st = analysed(sizes, pairs)
    A, _ = pattern_matrix(sizes, pairs, B=11, seed=len(pairs), dtype=dtype)  # lanes and a tail
    Ap = A[:, st.order][:, :, st.order]  # elimination order
    R = torch.randn(11, st.size, 3, dtype=dtype, generator=torch.Generator().manual_seed(1))
    L, X, Q, info = bc.block_cholesky_solve(stored(st, A), R, st)
    assert (info == 0).all()
    Ld = dense_factor(st, L)
    tol = dict(rtol=0, atol=2e-12 if dtype == f64 else 2e-4)
    torch.testing.assert_close(Ld @ Ld.mT, Ap, **tol)  # L L^T = A
    assert torch.equal(Ld, Ld.tril())
    scale = float(Ap.abs().amax())
    torch.testing.assert_close(Ap @ X / scale, R / scale, **tol)  # A X = R
    with native.disabled():  # the tensor code: torch.linalg on the dense matrix
        L0, X0, Q0, info0 = bc.block_cholesky_solve(stored(st, A), R, st)
    assert torch.equal(info0, info)
    torch.testing.assert_close(L, L0, rtol=0, atol=50 * torch.finfo(dtype).eps * scale ** 0.5)
    torch.testing.assert_close(X, X0, rtol=1e-9 if dtype == f64 else 1e-3, atol=0)
    torch.testing.assert_close(Q, (X * (Ap @ X)).sum(-2), rtol=1e-10 if dtype == f64 else 1e-4, atol=0)
    torch.testing.assert_close(Q0, Q, rtol=1e-10 if dtype == f64 else 1e-4, atol=0)


def test_minimum_degree_leaves_a_chain_without_fill_and_costs_less_than_dense():
    st = analysed(*CHAIN)
    # a chain's factor has the pattern of its lower triangle: 8 diagonal and 7 off-diagonal blocks
    assert st.panels == 8 * 36 + 7 * 36
    loop = analysed(*POSE_GRAPH)
    assert loop.flops < loop.dense_flops / 2, (loop.flops, loop.dense_flops)
    assert analysed(*CHAIN) is st  # the analysis is cached by the pattern
    assert sorted(st.order.tolist()) == list(range(48))


@pytest.mark.kernels
def test_a_failed_factorisation_reports_its_pivot_as_the_tensor_code_does():
    sizes, pairs = POSE_GRAPH
    st = analysed(sizes, pairs)
    A, _ = pattern_matrix(sizes, pairs, B=3, seed=4)
    A = A.clone()
    A[1, st.order[20], st.order[20]] = -1.0  # not positive definite
    A[2, st.order[7], st.order[7]] = float("inf")
    R = torch.ones(3, st.size, 1, dtype=f64)
    L, X, Q, info = bc.block_cholesky_solve(stored(st, A), R, st)
    with native.disabled():
        L0, X0, Q0, info0 = bc.block_cholesky_solve(stored(st, A), R, st)
    assert info.tolist() == info0.tolist() and info[0] == 0 and info[1] > 0 and info[2] == 8
    assert torch.isnan(L[1:]).all() and torch.isnan(X[1:]).all() and torch.isnan(Q[1:]).all()
    assert torch.isfinite(L[0]).all() and torch.isfinite(X[0]).all()


@pytest.mark.kernels
def test_bits_do_not_depend_on_threads():
    sizes, pairs = MIXED
    st = analysed(sizes, pairs)
    A, _ = pattern_matrix(sizes, pairs, B=300, seed=2)
    v = stored(st, A)
    R = torch.randn(300, st.size, 2, dtype=f64)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = bc.block_cholesky_solve(v, R, st)
        torch.set_num_threads(2)
        two = bc.block_cholesky_solve(v, R, st)
    finally:
        torch.set_num_threads(threads)
    assert all(torch.equal(a, b) for a, b in zip(one, two))
    assert torch.equal(bc.block_cholesky_solve(v[5:6], R[5:6], st)[1], one[1][5:6])
    assert torch.equal(bc.block_cholesky_solve(v[5:6], R[5:6], st)[2], one[2][5:6])


@pytest.mark.parametrize("kernels", [pytest.param(True, marks=pytest.mark.kernels), False],
                         ids=["kernel", "tensor code"])
def test_opcheck(kernels):
    assert not kernels or bc.uses_kernel(torch.zeros(1, dtype=f64))
    sizes, pairs = MIXED
    st = analysed(sizes, pairs)
    A, _ = pattern_matrix(sizes, pairs, B=2, seed=3)
    v = stored(st, A)
    R = torch.randn(2, st.size, 2, dtype=f64)
    ctx = native.disabled() if not kernels else torch.no_grad()
    with ctx:
        opcheck(torch.ops.torchsgal.block_cholesky_solve.default, (v, R, st.packed),
                test_utils=("test_schema", "test_faketensor"))


def test_bad_input_names_the_argument():
    st = analysed(*CHAIN)
    v = torch.zeros(2, st.panels, dtype=f64)
    with pytest.raises(ValueError, match=r"rhs must have shape \(2, 48, k\)"):
        bc.block_cholesky_solve(v, torch.zeros(2, 47, 1, dtype=f64), st)
    with pytest.raises(ValueError, match="values must have shape"):
        bc.block_cholesky_solve(v[:, 1:], torch.zeros(2, 48, 1, dtype=f64), st)
    with pytest.raises(TypeError, match="structure must be a Structure"):
        bc.block_cholesky_solve(v, torch.zeros(2, 48, 1, dtype=f64), st.packed)
    with pytest.raises(TypeError, match="rows must be an int64"):
        bc.analyse(torch.tensor([6]), torch.tensor([0.0]), torch.tensor([0]))
    with pytest.raises(ValueError, match=r"\[0, 2\)"):
        bc.analyse(torch.tensor([6, 6]), torch.tensor([0]), torch.tensor([2]))
    with pytest.raises(ValueError, match="sizes must be positive"):
        bc.analyse(torch.tensor([6, 0]), torch.tensor([0]), torch.tensor([1]))


# ----------------------------------------------------------------- the engine's linear solver
def _engine_case(B=6, seed=3, prior=True, measured=None):
    """Pose graphs of ``tests/test_factor_graph.py`` (``measured``: replaces the Between
    measurements' matrices)."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from test_factor_graph import _graph, pose_graphs

    _, Z, Z0, x0 = pose_graphs(B=B, seed=seed)
    if measured is not None:
        Z = type(Z)(measured(Z.as_matrix()))
    return _graph(Z, Z0, x0, prior=prior)


@pytest.mark.kernels
def test_engine_picks_the_block_solver_where_the_pattern_pays_and_it_matches_dense():
    from torchsgal.estimation.graph import linear_system as ls

    graph = _engine_case()
    auto = fg_solve("levenberg_marquardt", graph, "auto")
    assert isinstance(auto.system, ls.BlockSparseSystem)
    for solver in ("levenberg_marquardt", "gauss_newton", "dogleg"):
        a, b = fg_solve(solver, graph, "block"), fg_solve(solver, graph, "dense")
        assert isinstance(b.system, ls.DenseSystem)
        assert a.report.iterations.tolist() == b.report.iterations.tolist(), solver
        assert a.report.status.tolist() == b.report.status.tolist(), solver
        torch.testing.assert_close(a.report.cost, b.report.cost, rtol=1e-10, atol=0)
        torch.testing.assert_close(a.values["x"].as_matrix(), b.values["x"].as_matrix(), rtol=0,
                                   atol=1e-9)
    dense = fg_solve("levenberg_marquardt", graph, "dense")
    torch.testing.assert_close(auto.marginal_covariance("x", [2, 5]),
                               dense.marginal_covariance("x", [2, 5]), rtol=1e-8, atol=0)
    # one block per problem (no sparsity to use): the dense path
    import torchsgal as ts
    from torchsgal.estimation import graph as fg

    one = fg.FactorGraph()
    one.add_variable("x", ts.SE3.identity((4, 1), dtype=f64))
    one.add(fg.Prior("x", 0, ts.SE3.exp(torch.randn(4, 1, 6, dtype=f64))))
    assert isinstance(fg.levenberg_marquardt(one).system, ls.DenseSystem)


def fg_solve(name, graph, linear_solver, **kw):
    from torchsgal.estimation import graph as fg

    return getattr(fg, name)(graph, linear_solver=linear_solver, **kw)


def _implicit_solve(solver, seed):
    """LM with ``backward_mode="implicit"`` on two pose graphs whose Between measurements'
    matrices are a leaf that requires grad: (result, leaf)."""
    leaves = []

    def keep(M):
        leaves.append(M.detach().clone().requires_grad_())
        return leaves[0]

    result = fg_solve("levenberg_marquardt", _engine_case(B=2, seed=seed, measured=keep), solver,
                      backward_mode="implicit")
    return result, leaves[0]


@pytest.mark.kernels
def test_block_solver_reports_rank_deficiency_and_differentiates_as_dense():
    from torchsgal.estimation import SolverStatus

    free = fg_solve("levenberg_marquardt", _engine_case(B=2, prior=False), "block")
    assert (free.report.status == SolverStatus.CONVERGED_RANK_DEFICIENT).all()
    assert torch.isnan(free.marginal_covariance("x", 0)).all()
    grads = []
    for solver in ("block", "dense"):
        out, leaf = _implicit_solve(solver, seed=3)
        grads.append(torch.autograd.grad(out.values["x"].as_matrix().sum(), leaf)[0])
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-7, atol=1e-9)
    assert float(grads[0].abs().max()) > 0


@pytest.mark.kernels
def test_second_derivatives_through_the_implicit_solve_match_dense():
    """create_graph through the implicit backward: the block system hands a differentiated
    right-hand side to the dense solve, so second derivatives are the dense system's."""
    out = []
    for solver in ("block", "dense"):
        res, leaf = _implicit_solve(solver, seed=5)
        (g,) = torch.autograd.grad(res.values["x"].as_matrix()[..., :3, 3].square().sum(), leaf,
                                   create_graph=True)
        (gg,) = torch.autograd.grad(g.square().sum(), leaf)
        out.append((g.detach(), gg))
    torch.testing.assert_close(out[0][0], out[1][0], rtol=1e-7, atol=1e-9)
    torch.testing.assert_close(out[0][1], out[1][1], rtol=1e-6, atol=1e-8)
    assert float(out[0][1].abs().max()) > 0


@pytest.mark.kernels
def test_q_reads_the_lower_triangle_only_as_the_factorisation():
    """Values whose diagonal blocks hold only their lower triangle (the upper zeroed): the
    kernel's x^T A x is that of the symmetric matrix, as the tensor code's."""
    sizes, pairs = MIXED
    st = analysed(sizes, pairs)
    A, _ = pattern_matrix(sizes, pairs, B=9, seed=21)
    v = stored(st, A)
    node = st._node_of
    upper = (node[:, None] == node[None, :]) & torch.ones_like(A[0], dtype=torch.bool).triu(1)
    lower = stored(st, A.masked_fill(upper, 0.0))  # the diagonal blocks' upper triangles zero
    R = torch.randn(9, st.size, 2, dtype=f64)
    _, X, Q, _ = bc.block_cholesky_solve(lower, R, st)
    with native.disabled():
        _, X0, Q0, _ = bc.block_cholesky_solve(lower, R, st)
    Ap = A[:, st.order][:, :, st.order]
    torch.testing.assert_close(Q, (X * (Ap @ X)).sum(-2), rtol=1e-10, atol=0)
    torch.testing.assert_close(Q, Q0, rtol=1e-10, atol=0)
    torch.testing.assert_close(Q, bc.block_cholesky_solve(v, R, st)[2], rtol=1e-10, atol=0)


def test_a_malformed_structure_is_refused():
    st = analysed(*CHAIN)
    v = torch.eye(6, dtype=f64).flatten().repeat(1, st.panels // 36)
    R = torch.ones(1, st.size, 1, dtype=f64)
    short = st.packed.clone()
    short[0] = 100000  # blocks claimed with no arrays behind them
    with pytest.raises(ValueError, match="consistent block pattern"):
        torch.ops.torchsgal.block_cholesky_solve(v, R, short)
    if bc.uses_kernel(v):
        tampered = st.packed.clone()
        tampered[-1] = 10 ** 9  # a row map entry past its panel
        with pytest.raises(ValueError, match="consistent block pattern"):
            torch.ops.torchsgal.block_cholesky_solve(v, R, tampered)


def test_a_pattern_that_fills_in_is_not_analysed_for_auto():
    """``max_share``: a dense pattern is refused at once, and one whose elimination passes the
    bound is refused (None, cached); without the bound it is analysed."""
    n = 30
    dense_pairs = [(i, j) for i in range(n) for j in range(i, n)]
    assert analysed([3] * n, dense_pairs) is not None
    rows = torch.tensor([a for a, _ in dense_pairs])
    cols = torch.tensor([b for _, b in dense_pairs])
    assert bc.analyse(torch.full((n,), 3), rows, cols, max_share=0.5) is None
    # a ring with chords every 3 blocks: sparse enough to try, too much fill for 1% of dense
    ring = [(i, (i + 1) % n) for i in range(n)] + [(i, (i + n // 2) % n) for i in range(0, n, 3)]
    rows = torch.tensor([a for a, _ in ring])
    cols = torch.tensor([b for _, b in ring])
    assert bc.analyse(torch.full((n,), 3), rows, cols, max_share=0.01) is None
    full = bc.analyse(torch.full((n,), 3), rows, cols)
    assert full is not None and full.flops > 0.01 * full.dense_flops
    assert bc.analyse(torch.full((n,), 3), rows, cols, max_share=0.9) is not None


@pytest.mark.kernels
def test_the_block_system_builds_no_dense_matrix_to_solve_or_for_marginals():
    from torchsgal.estimation.graph import linear_system as ls

    result = fg_solve("levenberg_marquardt", _engine_case(B=3), "auto")
    assert isinstance(result.system, ls.BlockSparseSystem) and result.system._dense is None
    cov = result.marginal_covariance("x", torch.tensor([4, 0, 4]))  # on the block factorisation
    assert result.system._dense is None
    P = torch.linalg.inv(result.information)  # the dense information, built when asked
    assert result.system._dense is not None
    expected = torch.stack([P[:, 6 * n:6 * n + 6, 6 * n:6 * n + 6] for n in (4, 0, 4)], dim=1)
    torch.testing.assert_close(cov, expected, rtol=1e-9, atol=1e-12 * float(expected.abs().max()))


def test_vmap_joins_the_mapped_axis_to_the_batch():
    sizes, pairs = MIXED
    st = analysed(sizes, pairs)
    A, _ = pattern_matrix(sizes, pairs, B=6, seed=22)
    v = stored(st, A).reshape(2, 3, -1)
    R = torch.randn(2, 3, st.size, 2, dtype=f64)
    got = torch.vmap(lambda a, r: bc.block_cholesky_solve(a, r, st))(v, R)
    want = bc.block_cholesky_solve(v.reshape(6, -1), R.reshape(6, st.size, 2), st)
    for a, b in zip(got, want):
        assert torch.equal(a.reshape(b.shape), b)
    with pytest.raises(ValueError, match="cannot be vmapped"):
        torch.vmap(lambda p: torch.ops.torchsgal.block_cholesky_solve(v[0], R[0], p))(
            st.packed.expand(2, -1))
