"""The factor-graph engine's fast paths against the plain evaluation they replace.

1. ``act`` for one element per batch row acting on N points (matrix batch (..., 1), points
   (..., N, k)): one matrix product over the N rows.  Compared with the per-point product of
   the element expanded to (..., N) (the general path), for every group, values and
   forward-mode derivatives.
2. The engine's fused built-in priors and betweens (the E = Z^-1 h(x) of every such block of a
   group through one log and one J_r^-1): normal equations, gradient and cost equal to those of
   the same factors evaluated one block at a time (user factors with the same residual and
   Jacobian functions, which the engine does not fuse), with noise, robust losses, per-problem
   measurements, several groups in one graph and the solvers' active set (``Problem.select``).
"""
import pytest
import torch

import torchsgal as ts
from torchsgal.estimation import graph as fg
from torchsgal.estimation.graph import factors as F
from torchsgal.estimation.graph.layout import dense
from torchsgal.estimation.graph.linearize import Problem, evaluate_cost, linearize

f64 = torch.float64


def _elements(G, shape, gen, scale=0.7):
    return G.exp(scale * torch.randn(*shape, G.dof, generator=gen, dtype=f64))


def _expanded(g, n):
    """g of batch (..., 1) as an element of batch (..., n) (a copy: the general act path)."""
    M = g.as_matrix()
    return type(g)._new(M.expand(M.shape[:-3] + (n,) + M.shape[-2:]).contiguous())


@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=lambda G: G.__name__)
def test_act_of_one_element_on_many_points_matches_the_per_point_product(G):
    gen = torch.Generator().manual_seed(3)
    B, N = 5, 7
    g = _elements(G, (B, 1), gen)
    p = torch.randn(B, N, G.point_dim, generator=gen, dtype=f64)
    d = torch.randn(B, N, G.rotation_dim, generator=gen, dtype=f64)
    ref = _expanded(g, N)
    torch.testing.assert_close(g.act(p), ref.act(p), rtol=1e-13, atol=1e-13)
    torch.testing.assert_close(g.act_direction(d), ref.act_direction(d), rtol=1e-13, atol=1e-13)
    # point_axes=1: elements (B,) on points (B, N, k), the same product
    torch.testing.assert_close(g[:, 0].act(p, point_axes=1), ref.act(p), rtol=1e-13, atol=1e-13)
    # a point batch (N, k) against elements (1,): both paths agree as well
    torch.testing.assert_close(g[0].act(p[0]), ref[0].act(p[0]), rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("G", [ts.SE3, ts.SGal3, ts.Sim3, ts.SE2], ids=lambda G: G.__name__)
def test_act_fast_path_forward_mode_derivatives_match_the_per_point_product(G):
    """jvp of g.act(p) along right perturbations of g, under vmap over a tangent basis (the
    engine's forward mode), against the same for the expanded element."""
    gen = torch.Generator().manual_seed(4)
    B, N = 4, 6
    g = _elements(G, (B, 1), gen)
    p = torch.randn(B, N, G.point_dim, generator=gen, dtype=f64)
    M = g.as_matrix()
    hats = G.hat(torch.eye(G.dof, dtype=f64))  # (dof, n, n)
    basis = M.unsqueeze(0) @ hats[:, None, None]  # (dof, B, 1, n, n): M hat(e_j)

    def derivative(leaf, tangents):
        def fn(m):
            return G._new(m).act(p)

        return torch.func.vmap(lambda t: torch.func.jvp(fn, (leaf,), (t,))[1])(tangents)

    fast = derivative(M, basis)
    expanded = derivative(M.expand(B, N, *M.shape[-2:]), basis.expand(G.dof, B, N, *M.shape[-2:]))
    torch.testing.assert_close(fast, expanded, rtol=1e-12, atol=1e-12)
    # and against central finite differences of g exp(t e_j) p
    eps = 1e-6
    for j in range(G.dof):
        e = torch.zeros(G.dof, dtype=f64)
        e[j] = eps
        fd = (g.rplus(e.expand(B, 1, G.dof)).act(p) - g.rplus(-e.expand(B, 1, G.dof)).act(p)) / (2 * eps)
        torch.testing.assert_close(fast[j], fd, rtol=1e-7, atol=1e-7)


def _graph(fused: bool, gen):
    """Three groups (SE3 poses x and z, SO3 rotations y, SE2 poses w), priors and betweens with
    shared and per-factor noise, robust losses, per-problem and shared measurements, a uniform
    slot, a between of two variables."""
    B = 4
    x = _elements(ts.SE3, (B, 6), gen)
    y = _elements(ts.SO3, (B, 5), gen)
    graph = fg.FactorGraph()
    graph.add_variable("x", x)
    graph.add_variable("y", y)
    graph.add_variable("z", _elements(ts.SE3, (B, 3), gen))
    iz, jz = torch.tensor([4, 1]), torch.tensor([0, 2])  # x_i to z_j: two variables of a group
    Zxz = _elements(ts.SE3, (B, 2), gen)
    i, j = torch.tensor([0, 1, 2, 3, 4, 0]), torch.tensor([1, 2, 3, 4, 5, 3])
    Zx = _elements(ts.SE3, (B, 6), gen)
    L = torch.randn(6, 6, 6, generator=gen, dtype=f64) * 0.1 + 2 * torch.eye(6, dtype=f64)
    W = torch.diag(torch.tensor([4.0, 4, 4, 9, 9, 9], dtype=f64))
    Zy = _elements(ts.SO3, (3,), gen)  # shared by the problems
    iy, jy = torch.tensor([0, 1, 2]), torch.tensor([1, 2, 4])
    graph.add_variable("w", _elements(ts.SE2, (B, 4), gen))
    iw, jw = torch.tensor([0, 1, 2, 3]), torch.tensor([1, 2, 3, 0])
    Zw, Zw0 = _elements(ts.SE2, (B, 4), gen), _elements(ts.SE2, (1,), gen)
    Lw = torch.tensor([[3.0, 0.5, 0.1], [0.0, 2.0, 0.3], [0.0, 0.0, 4.0]], dtype=f64)
    if fused:
        graph.add(fg.Prior("w", 2, Zw0), loss=fg.Huber(0.4))
        graph.add(fg.Between("w", iw, jw, Zw, sqrt_information=Lw))
        graph.add(fg.Prior("x", 0, Zx[:, :1], information=W))
        graph.add(fg.Between("x", i, j, Zx, sqrt_information=L), loss=fg.Huber(0.5))
        graph.add(fg.Between("x", 5, torch.tensor([1, 2]), Zx[:, :2]))  # a uniform slot
        graph.add(fg.Prior("y", torch.tensor([0, 3]), _elements(ts.SO3, (B, 2), gen)))
        graph.add(fg.Between("y", iy, jy, Zy), loss=fg.Cauchy(0.3))
        graph.add(fg.Factor(F._between_residual, [("x", iz), ("z", jz)], [Zxz], dim=6,
                            jacobians=F._between_jacobians))
    else:  # the same residuals, not recognised as built-ins: evaluated one block at a time
        def between(*a):
            return F._between_jacobians(*a)

        def prior(*a):
            return F._prior_jacobians(*a)

        graph.add(fg.Factor(F._prior_residual, [("w", 2)], [Zw0], dim=3, jacobians=prior),
                  loss=fg.Huber(0.4))
        graph.add(fg.Factor(F._between_residual, [("w", iw), ("w", jw)], [Zw], dim=3,
                            sqrt_information=Lw, jacobians=between))

        graph.add(fg.Factor(F._prior_residual, [("x", 0)], [Zx[:, :1]], dim=6, information=W,
                            jacobians=prior))
        graph.add(fg.Factor(F._between_residual, [("x", i), ("x", j)], [Zx], dim=6,
                            sqrt_information=L, jacobians=between), loss=fg.Huber(0.5))
        graph.add(fg.Factor(F._between_residual, [("x", 5), ("x", torch.tensor([1, 2]))],
                            [Zx[:, :2]], dim=6, jacobians=between))
        graph.add(fg.Factor(F._prior_residual, [("y", torch.tensor([0, 3]))],
                            [_elements(ts.SO3, (B, 2), gen)], dim=3, jacobians=prior))
        graph.add(fg.Factor(F._between_residual, [("y", iy), ("y", jy)], [Zy], dim=3,
                            jacobians=between), loss=fg.Cauchy(0.3))
        def between_side_by_side(*a):  # the one-tensor form of ``jacobians``
            r, (Ji, Jj) = F._between_jacobians(*a)
            return r, torch.cat([Ji, Jj], dim=-1)

        graph.add(fg.Factor(F._between_residual, [("x", iz), ("z", jz)], [Zxz], dim=6,
                            jacobians=between_side_by_side))
    return graph


def test_fused_priors_and_betweens_match_the_blockwise_evaluation():
    graphs = [_graph(fused, torch.Generator().manual_seed(5)) for fused in (True, False)]
    problems = [Problem(g) for g in graphs]
    assert [b.log_form for b in problems[0].blocks] == ["prior", "between", "prior", "between",
                                                       "between", "prior", "between", "between"]
    assert all(b.log_form is None for b in problems[1].blocks)
    rows = torch.tensor([3, 1])
    results = []
    for graph, p in zip(graphs, problems):
        x = p.initial(graph)
        # a point away from the initial values, so that every residual is non-zero
        x = p.retract(x, 0.3 * torch.randn(p.B, p.D, generator=torch.Generator().manual_seed(6),
                                           dtype=f64))
        lin = linearize(p, x)
        sub = p.select(rows)
        lin_sub = linearize(sub, [v.index_select(0, rows) for v in x])
        results.append((dense(p.layout, lin.values), lin.g, lin.cost, lin.model_cost, evaluate_cost(p, x),
                        dense(sub.layout, lin_sub.values), lin_sub.g, lin_sub.cost))
    for a, b in zip(*results):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    H, cost, H_sub = results[0][0], results[0][2], results[0][5]
    assert bool((cost > 0).all()) and float(H.abs().amax()) > 0
    torch.testing.assert_close(H_sub, H.index_select(0, rows), rtol=1e-12, atol=1e-12)


def test_fused_solve_matches_the_blockwise_solve():
    results = [fg.levenberg_marquardt(_graph(fused, torch.Generator().manual_seed(7)))
               for fused in (True, False)]
    a, b = results
    assert torch.equal(a.report.iterations, b.report.iterations)
    assert torch.equal(a.report.status, b.report.status)
    torch.testing.assert_close(a.report.cost, b.report.cost, rtol=1e-10, atol=1e-12)
    for name in ("x", "y", "z", "w"):
        torch.testing.assert_close(a.values[name].as_matrix(), b.values[name].as_matrix(),
                                   rtol=1e-9, atol=1e-9)


def test_fused_evaluation_reads_nothing_on_the_host():
    """No host read inside the fused prior / between evaluation and the helpers it shares with
    the blockwise path (the solvers' one read per round is elsewhere)."""
    import importlib
    import inspect

    from host_syncs import HostSyncs

    lz = importlib.import_module("torchsgal.estimation.graph.linearize")

    def lines(fn):
        src, start = inspect.getsourcelines(fn)
        return range(start, start + len(src))

    graph = _graph(True, torch.Generator().manual_seed(8))
    problem = Problem(graph)
    x = problem.initial(graph)
    with HostSyncs() as syncs:
        linearize(problem, x)
        evaluate_cost(problem, x)
    hot = [lines(f) for f in (lz._log_form_terms, lz._whiten, lz._args, lz.linearize,
                              lz.evaluate_cost)]
    seen = [(why, where) for why, where in syncs.events
            if where.rsplit(":", 1)[0] == lz.__file__
            and any(int(where.rsplit(":", 1)[1]) in r for r in hot)]
    assert not seen, seen
