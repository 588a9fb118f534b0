"""The linear systems' layouts of the normal equations (``graph.layout``): every system's
values give the same H, H v and diag(H) as the raw layout, where H is assembled by the
definition (each factor's entries added at their positions)."""
from __future__ import annotations

import pytest
import torch
from test_factor_graph import _graph, pose_graphs

import torchsgal as ts
from torchsgal.estimation import graph as fg
from torchsgal.estimation.graph import linear_system
from torchsgal.estimation.graph.layout import EntryLayout, dense, diagonal, times
from torchsgal.estimation.graph.linearize import Problem, linearize

f64 = torch.float64


def _problems():
    """A batch of SE(3) pose graphs (built-in factors, the assemble kernel where it runs) and
    a batch with a user factor on a Euclidean variable and a robust loss (the tensor path)."""
    _, Z, Z0, x0 = pose_graphs(B=3, seed=31)
    yield "pose graphs", _graph(Z, Z0, x0)
    gen = torch.Generator().manual_seed(32)
    graph = fg.FactorGraph()
    graph.add_variable("T", ts.SE3.exp(0.3 * torch.randn(3, 2, 6, generator=gen, dtype=f64)))
    graph.add_variable("p", torch.randn(3, 4, 3, generator=gen, dtype=f64))
    graph.add(fg.Prior("T", 0, ts.SE3.identity((3, 1), dtype=f64)))
    graph.add(fg.Between("T", torch.tensor([0]), torch.tensor([1]),
                         ts.SE3.exp(0.2 * torch.randn(3, 1, 6, generator=gen, dtype=f64)),
                         loss=fg.Huber(0.5)))
    graph.add(fg.PointObservation("T", torch.tensor([0, 1, 1, 0]), "p", torch.arange(4),
                                  torch.randn(3, 4, 3, generator=gen, dtype=f64)))
    graph.add(fg.Factor(lambda p: p.square().sum(-1, keepdim=True), [("p", torch.arange(4))], [],
                        dim=1))
    yield "points", graph


@pytest.mark.parametrize("kind", ["DenseSystem", "BlockSparseSystem", "SparseSystem"])
@pytest.mark.parametrize("case", ["pose graphs", "points"])
def test_every_layout_holds_the_same_normal_equations(case, kind):
    graph = dict(_problems())[case]
    problem = Problem(graph)
    x = problem.initial(graph)
    B, D = problem.B, problem.D
    raw = linearize(problem, x)
    # H by the definition: the raw entries added at their flat positions
    H = raw.values.new_zeros(B, D * D).index_add_(1, problem.h_index, raw.values).reshape(B, D, D)
    torch.testing.assert_close(H, H.mT, rtol=0, atol=0)  # a symmetric pattern and values
    torch.testing.assert_close(dense(problem.layout, raw.values), H, rtol=0, atol=0)
    rows = range(B) if kind == "SparseSystem" else [slice(None)]  # the sparse system: B = 1
    for row in rows:
        sub = problem.select(torch.arange(B)[row].reshape(-1))
        system = getattr(linear_system, kind)(sub)
        lin = linearize(sub, sub.initial(graph) if kind != "SparseSystem" else
                        [v[row].reshape(1, *v.shape[1:]) for v in x], system.layout)
        Hs = H[row].reshape(-1, D, D)
        assert lin.values.shape == (Hs.shape[0], system.layout.size)
        torch.testing.assert_close(dense(system.layout, lin.values), Hs, rtol=1e-13, atol=1e-12)
        v = torch.randn(Hs.shape[0], D, dtype=f64, generator=torch.Generator().manual_seed(33))
        torch.testing.assert_close(times(system.layout, lin.values, v),
                                   (Hs @ v.unsqueeze(-1)).squeeze(-1), rtol=1e-12, atol=1e-11)
        torch.testing.assert_close(diagonal(system.layout, lin.values),
                                   Hs.diagonal(dim1=-2, dim2=-1), rtol=1e-13, atol=1e-12)
        torch.testing.assert_close(lin.g, raw.g[row].reshape(-1, D), rtol=1e-13, atol=1e-12)


@pytest.mark.parametrize("B", [1, 2])
def test_a_block_solve_leaves_the_stored_equations_unchanged(B):
    """The damped step of the block system works on a copy of the stored triangle, also where
    one problem's values are a contiguous slice (B = 1, or one problem left running)."""
    _, Z, Z0, x0 = pose_graphs(B=B, seed=34)
    problem = Problem(_graph(Z, Z0, x0))
    system = linear_system.BlockSparseSystem(problem)
    lin = linearize(problem, problem.initial(_graph(Z, Z0, x0)), system.layout)
    kept = lin.values.clone()
    for diagonal_damping in (False, True):
        system.solve(lin.values, lin.g, torch.full((B,), 10.0, dtype=f64), diagonal_damping)
        assert torch.equal(lin.values, kept)


def test_rejected_trials_leave_the_information_undamped():
    """One problem whose trials are rejected until it stops: each system reports the undamped
    information J^T J = 1 at the solution, after the same iterations."""
    results = {}
    for solver in ("dense", "block"):
        graph = fg.FactorGraph()
        graph.add_variable("p", torch.tensor([[[0.5]]], dtype=f64))
        graph.add(fg.Factor(lambda p: p + torch.sign(p), [("p", torch.tensor([0]))], [], dim=1))
        results[solver] = fg.levenberg_marquardt(graph, linear_solver=solver)
    for r in results.values():
        torch.testing.assert_close(r.information.flatten(), torch.ones(1, dtype=f64), rtol=0, atol=1e-12)
        torch.testing.assert_close(r.marginal_covariance("p").flatten(), torch.ones(1, dtype=f64),
                                   rtol=0, atol=1e-12)
    assert results["dense"].report.iterations.tolist() == results["block"].report.iterations.tolist()


@pytest.mark.parametrize("group", [ts.SE3, ts.SE2])
def test_an_empty_block_of_built_in_factors_adds_nothing(group):
    """A Prior and a Between with no factors beside non-empty ones: the same solution as
    without them, with every linear solver."""
    gen = torch.Generator().manual_seed(35)
    dof = 6 if group is ts.SE3 else 3
    x = group.exp(0.3 * torch.randn(2, 3, dof, generator=gen, dtype=f64))
    Z = group.exp(0.1 * torch.randn(2, 2, dof, generator=gen, dtype=f64))
    none = torch.zeros(0, dtype=torch.int64)
    costs = []
    for empty in (False, True):
        for solver in ("dense", "block"):
            graph = fg.FactorGraph()
            graph.add_variable("x", x)
            graph.add(fg.Prior("x", 0, group.identity((2, 1), dtype=f64)))
            graph.add(fg.Between("x", torch.tensor([0, 1]), torch.tensor([1, 2]), Z))
            if empty:
                graph.add(fg.Between("x", none, none, group.identity((2, 0), dtype=f64)))
                graph.add(fg.Prior("x", none, group.identity((2, 0), dtype=f64)))
            r = fg.levenberg_marquardt(graph, linear_solver=solver)
            assert r.report.status.tolist() == [0, 0]
            costs.append(r.values["x"].as_matrix())
    for c in costs[1:]:
        torch.testing.assert_close(c, costs[0], rtol=0, atol=1e-12)


def test_entries_of_a_layout_past_the_int64_range_of_a_flat_key():
    """Positions r * D + c of a large H and many columns (position * columns would pass 2^63):
    ``entries`` keeps the pairs exact and H v reads them."""
    D, size = 3_000_000, 1_100_000
    r = torch.tensor([D - 3, D - 3, D - 2, D - 2])
    c = torch.tensor([D - 3, D - 2, D - 3, D - 2])
    h = r * D + c
    assert int(h.max()) * size > 2 ** 63
    slots = torch.tensor([size - 2, size - 3, size - 3, size - 4])
    layout = EntryLayout(h, [4], D, slots, size)
    rows, cols, columns = layout.entries()
    assert rows.tolist() == r.tolist() and cols.tolist() == c.tolist()
    assert columns.tolist() == slots.tolist()
    values = torch.zeros(1, size, dtype=f64)
    values[0, slots] = torch.tensor([2.0, 1.0, 1.0, 3.0], dtype=f64)
    v = torch.zeros(1, D, dtype=f64)
    v[0, D - 3], v[0, D - 2] = 1.0, 1.0
    Hv = times(layout, values, v)
    # slots size - 3 is shared by (r, c) and (c, r), summed once per position
    assert Hv[0, D - 3].item() == 3.0 and Hv[0, D - 2].item() == 4.0
    assert int((Hv != 0).sum()) == 2
