"""Conveniences of the group classes: ``shape``, ``requires_grad_``, acting on sets of points
(``point_axes``) and composition inside torch.compile(fullgraph=True)."""
from __future__ import annotations

import itertools

import pytest
import torch

import torchsgal as ts

F64 = torch.float64
BATCHES = [(), (3,), (2, 3)]


def _random(G, batch, seed=0, dtype=F64):
    return G.random(batch, dtype=dtype, generator=torch.Generator().manual_seed(seed))


def _velocity_groups():
    return [G for G in ts.ALL_GROUPS if hasattr(G, "act_velocity")]


# ------------------------------------------------------------------------------- shape
@pytest.mark.parametrize("G", ts.ALL_GROUPS)
@pytest.mark.parametrize("batch", BATCHES)
def test_shape_is_the_batch_shape(G, batch):
    g = _random(G, batch)
    assert g.shape == torch.Size(batch) == g.batch_shape
    assert g.as_matrix().shape == torch.Size(batch) + (G.matrix_dim, G.matrix_dim)
    assert g[None].shape == (1, *batch)


# ---------------------------------------------------------------------- requires_grad_
@pytest.mark.parametrize("G", ts.ALL_GROUPS)
@pytest.mark.parametrize("batch", BATCHES)
def test_requires_grad_sets_it_on_the_matrix_and_returns_self(G, batch):
    g = _random(G, batch)
    assert not g.requires_grad
    out = g.requires_grad_()
    assert out is g and g.requires_grad and g.as_matrix().requires_grad and g.as_matrix().is_leaf
    # the gradient is the Euclidean one of the matrix entries: d/dM sum(M) = ones
    g.as_matrix().sum().backward()
    assert torch.equal(g.as_matrix().grad, torch.ones_like(g.as_matrix()))
    assert g.requires_grad_(False) is g and not g.requires_grad


@pytest.mark.parametrize("G", ts.ALL_GROUPS)
def test_requires_grad_refuses_a_bad_flag_and_a_non_leaf(G):
    g = _random(G, (2,))
    with pytest.raises(TypeError, match="requires_grad must be True or False, got 1"):
        g.requires_grad_(1)
    h = G.exp(torch.zeros(2, G.dof, dtype=F64, requires_grad=True))  # a result, not a leaf
    with pytest.raises(RuntimeError, match="requires_grad flags of leaf variables"):
        h.requires_grad_(False)


# ------------------------------------------------------------------ acting on points
def _act_methods(G):
    """(method name, size of the vectors it takes) for each action of G."""
    methods = [("act", G.point_dim), ("act_direction", G.rotation_dim)]
    if hasattr(G, "act_velocity"):
        methods.append(("act_velocity", 3))
    return methods


def _one_by_one(g, x, method, k):
    """The reference: every element acts on every point of its set, one pair at a time, with
    the unbatched API (point_axes=0)."""
    batch = torch.broadcast_shapes(g.shape, x.shape[: x.dim() - 1 - k])
    sets = x.shape[x.dim() - 1 - k: -1]
    gg = g.expand(batch)
    xx = x.expand(*batch, *sets, x.shape[-1])
    out = torch.empty_like(xx)
    for b in itertools.product(*map(range, batch)):
        for n in itertools.product(*map(range, sets)):
            out[b + n] = getattr(gg[b] if b else gg, method)(xx[b + n])
    return out


@pytest.mark.parametrize("G", ts.ALL_GROUPS)
@pytest.mark.parametrize("batch, x_outer, sets", [
    ((3,), (3,), (5,)),        # one set per element: g (B,), x (B, N, d)
    ((3,), (), (5,)),          # one set for all elements: x (N, d)
    ((), (), (4,)),            # an unbatched element
    ((2, 3), (3,), (4,)),      # the outer axes broadcast, as torch's
    ((3,), (3,), (2, 4)),      # two point axes (an image of points)
])
def test_point_axes_maps_every_point_of_each_set(G, batch, x_outer, sets):
    g = _random(G, batch)
    k = len(sets)
    for method, d in _act_methods(G):
        x = torch.randn(*x_outer, *sets, d, dtype=F64, generator=torch.Generator().manual_seed(1))
        got = getattr(g, method)(x, point_axes=k)
        want = _one_by_one(g, x, method, k)
        assert got.shape == torch.broadcast_shapes(batch, x_outer) + (*sets, d)
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)
        # the same as inserting the axes by hand
        torch.testing.assert_close(got, getattr(g.reshape(*batch, *(1,) * k), method)(x), rtol=0, atol=0)
        assert x.shape == (*x_outer, *sets, d)  # the input is not changed


@pytest.mark.parametrize("G", ts.ALL_GROUPS)
def test_point_axes_zero_keeps_torch_broadcasting(G):
    """The default: g (B,) with x (B, B, d) maps x[i, j] by g[j] (right-aligned batches)."""
    B = 3
    g = _random(G, (B,))
    x = torch.randn(B, B, G.point_dim, dtype=F64, generator=torch.Generator().manual_seed(2))
    got = g.act(x)
    for i in range(B):
        for j in range(B):
            torch.testing.assert_close(got[i, j], g[j].act(x[i, j]), rtol=1e-12, atol=1e-12)
    # with one point axis, x[i, j] is mapped by g[i] instead
    torch.testing.assert_close(g.act(x, point_axes=1)[2, 0], g[2].act(x[2, 0]), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("G", ts.ALL_GROUPS)
@pytest.mark.parametrize("batch", [(3,), (2, 3)], ids=["one batch axis", "two batch axes"])
def test_point_axes_maps_every_point_by_its_element(G, batch):
    """point_axes=1 (one element per batch entry acting on 5 points: one matrix product over the
    points, the homogeneous tail's constants added once per element), with one and with two
    batch axes, against each point mapped alone; the points and the element are not written."""
    g = _random(G, batch)
    x = torch.randn(*batch, 5, G.point_dim, dtype=F64, generator=torch.Generator().manual_seed(6))
    x_before, m_before = x.clone(), g.as_matrix().clone()
    got = g.act(x, point_axes=1)
    assert got.shape == x.shape
    flat_g, flat_x, flat_got = g.reshape(-1), x.reshape(-1, 5, G.point_dim), got.reshape(-1, 5, G.point_dim)
    for b in range(flat_x.shape[0]):
        for k in range(5):
            torch.testing.assert_close(flat_got[b, k], flat_g[b].act(flat_x[b, k]), rtol=1e-12, atol=1e-12)
    assert torch.equal(x, x_before) and torch.equal(g.as_matrix(), m_before)


@pytest.mark.parametrize("G", ts.ALL_GROUPS)
def test_point_axes_gradients(G):
    """Gradients with respect to the element and the points through point_axes=1 agree with
    the unsqueezed element's (finite differences: torch.autograd.gradcheck)."""
    xi = torch.randn(2, G.dof, dtype=F64, generator=torch.Generator().manual_seed(3)) * 0.3
    x = torch.randn(2, 4, G.point_dim, dtype=F64, generator=torch.Generator().manual_seed(4))
    xi.requires_grad_(True)
    x.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b: G.exp(a).act(b, point_axes=1), (xi, x))


@pytest.mark.parametrize("G", ts.ALL_GROUPS)
def test_point_axes_errors_name_the_argument(G):
    g = _random(G, (3,))
    d = G.point_dim
    for bad in (-1, 1.5, True, "1"):
        with pytest.raises((TypeError, ValueError), match=rf"point_axes must be an integer >= 0, got {bad!r}"):
            g.act(torch.zeros(3, 4, d, dtype=F64), point_axes=bad)
    with pytest.raises(ValueError,
                       match=rf"(p|e) must have shape \(\.\.\., N, N, {d}\) with point_axes=2, got \({d},\)"):
        g.act(torch.zeros(d, dtype=F64), point_axes=2)
    with pytest.raises(ValueError, match=r"batch shape \(3,\) of this \w+ does not broadcast with the axes \(4,\) of "
                                         r"\w \(4, 5, \d\) before its 1 point axis \(point_axes=1\)"):
        g.act(torch.zeros(4, 5, d, dtype=F64), point_axes=1)
    with pytest.raises(ValueError, match=rf"must have shape \(\.\.\., {d}\), got \(3, 5, {d + 1}\)"):
        g.act(torch.zeros(3, 5, d + 1, dtype=F64), point_axes=1)
    with pytest.raises(TypeError, match="must be a torch.Tensor, got list"):
        g.act([[0.0] * d], point_axes=1)
    with pytest.raises(TypeError, match=r"(p|e) has dtype torch.float32 but g has dtype torch.float64"):
        g.act(torch.zeros(3, 5, d), point_axes=1)


# ------------------------------------------------------------- composition when compiled
@pytest.mark.parametrize("G", ts.ALL_GROUPS)
def test_compose_and_point_axes_trace_with_fullgraph(G):
    """``g.compose(h)`` (and the rest of the group API used here) compiles without graph breaks."""
    g, h = _random(G, (3,), seed=5), _random(G, (3,), seed=6)
    x = torch.randn(4, G.point_dim, dtype=F64)

    def f(a, b, p):
        c = a.compose(b.inverse())
        return c.log(), c.act(p, point_axes=1), c.shape[0]

    torch._dynamo.reset()
    got = torch.compile(f, fullgraph=True, backend="eager")(g, h, x)
    want = f(g, h, x)
    torch.testing.assert_close(got[:2], want[:2], rtol=0, atol=0)
    assert got[2] == want[2] == 3


@pytest.mark.parametrize("G", [ts.SO3, ts.SE3])
def test_matmul_compiles_with_graph_breaks_only(G):
    """``g @ h`` inside torch.compile: correct without fullgraph (dynamo breaks the graph at
    ``@``); with fullgraph=True dynamo refuses it (torch 2.13: its object protocol has no
    ``nb_matrix_multiply`` for classes that are not tensors, so ``__matmul__`` is never inlined) and
    ``compose`` is the spelling to use (LieGroup.compose's docstring).  If this starts to compile,
    torch traces ``@``: update that docstring and docs/guide/training.md."""
    g, h = _random(G, (2,), seed=7), _random(G, (2,), seed=8)

    def f(a, b):
        return (a @ b).log()

    torch._dynamo.reset()
    torch.testing.assert_close(torch.compile(f, backend="eager")(g, h), g.compose(h).log(), rtol=0, atol=0)
    torch._dynamo.reset()
    with pytest.raises(torch._dynamo.exc.Unsupported, match="matmul"):
        torch.compile(f, fullgraph=True, backend="eager")(g, h)
