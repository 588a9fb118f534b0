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
from torchsgal.estimation.graph.layout import dense, diagonal, times
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
