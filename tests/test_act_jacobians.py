"""``g.act_jacobians(x)``: the Jacobians of the action with respect to the right perturbation
of g and to x, against their written-out forms, central differences and GTSAM's
``transformFrom`` / ``rotate`` / ``act`` Jacobians."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from conftest import GROUP_CLASSES, all_groups, assert_close, sample_group

import torchsgal as ts

F64 = torch.float64


def _skew(p: torch.Tensor) -> torch.Tensor:
    z = torch.zeros_like(p[..., 0])
    return torch.stack([z, -p[..., 2], p[..., 1], p[..., 2], z, -p[..., 0],
                        -p[..., 1], p[..., 0], z], -1).unflatten(-1, (3, 3))


def _written_out(g, x):
    """(J_g, J_x) of each group's action written out: the perturbed matrix M (I + xi^) acting
    on x, term by term."""
    G = type(g)._group
    M = g.as_matrix().expand(x.shape[:-1] + g.as_matrix().shape[-2:])
    C = M[..., :G.rotation_dim, :G.rotation_dim]
    Cx = lambda v: (C @ v.unsqueeze(-1)).squeeze(-1)  # noqa: E731
    if G in (ts.SO2, ts.SE2):
        Jp = Cx(torch.stack([-x[..., 1], x[..., 0]], -1)).unsqueeze(-1)  # C [[0, -1], [1, 0]] p
        return (Jp if G is ts.SO2 else torch.cat([C, Jp], -1)), C
    if G is ts.SO3:
        return -C @ _skew(x), C
    if G is ts.SE3:
        return torch.cat([C, -C @ _skew(x)], -1), C
    if G is ts.SE23:  # [rho, nu, phi]: the velocity does not move a point
        return torch.cat([C, torch.zeros_like(C), -C @ _skew(x)], -1), C
    if G is ts.Sim3:  # s (C p + r); lambda scales M's last column [r, 1/s] by (1 - lambda):
        # d/drho = s C, d/dphi = -s C p^, d/dlambda = s C p
        s = 1.0 / M[..., 3, 3, None, None]
        return torch.cat([s * C, -s * C @ _skew(x), s * Cx(x).unsqueeze(-1)], -1), s * C
    # SGal3, events (x, t): [rho, nu, phi, iota] -> (C rho, C t nu, -C x^ phi, v iota; iota)
    p, t = x[..., :3], x[..., 3:]
    v = M[..., :3, 3:4]
    top = torch.cat([C, C * t.unsqueeze(-1), -C @ _skew(p), v], -1)
    bottom = torch.zeros_like(top[..., :1, :])
    bottom[..., 0, 9] = 1.0
    J_x = torch.cat([torch.cat([C, v], -1), torch.cat([torch.zeros_like(v.mT), torch.ones_like(v[..., :1, :])], -1)], -2)
    return torch.cat([top, bottom], -2), J_x


@all_groups
def test_act_jacobians_are_the_written_out_derivatives(G, batch_shape, dtype):
    g = sample_group(G, batch_shape, dtype, seed=5)
    gen = torch.Generator().manual_seed(6)
    x = torch.randn(batch_shape + (G.point_dim,), generator=gen, dtype=F64).to(dtype)
    J_g, J_x = g.act_jacobians(x)
    want_g, want_x = _written_out(g, x)
    assert J_g.shape == batch_shape + (want_g.shape[-2], G.dof) and J_g.dtype == dtype
    assert_close(J_g, want_g, dtype, msg="J_g")
    assert_close(J_x, want_x, dtype, msg="J_x")


@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=lambda G: G.__name__)
def test_act_jacobians_match_central_differences(G):
    g = sample_group(G, (4,), F64, seed=8)
    gen = torch.Generator().manual_seed(9)
    x = 2.0 * torch.randn(4, G.point_dim, generator=gen, dtype=F64)
    J_g, J_x = g.act_jacobians(x)
    h = 1e-6
    for j in range(G.dof):
        e = torch.zeros(G.dof, dtype=F64)
        e[j] = h
        fd = ((g @ G.exp(e)).act(x) - (g @ G.exp(-e)).act(x)) / (2 * h)
        torch.testing.assert_close(J_g[..., j], fd, rtol=1e-7, atol=1e-7)
    for i in range(G.point_dim):
        e = torch.zeros(G.point_dim, dtype=F64)
        e[i] = h
        torch.testing.assert_close(J_x[..., i], (g.act(x + e) - g.act(x - e)) / (2 * h), rtol=1e-7, atol=1e-7)


def test_act_jacobians_broadcast_as_act_and_own_their_storage():
    """One element per batch row acting on N points (point_axes=1), and an unbatched element on
    a batch of points; J_x and the adjoint are copies (writing to them leaves the element alone,
    in every group: SO(3)'s J_x and adjoint are its whole matrix); where one element acts on many
    points, J_x is its copy expanded over them (an in-place write is refused by torch, and a
    clone of it is writable).  The batched
    contraction of the points sums in another order than one point at a time: equal to a few
    units in the last place (rtol 4 eps)."""
    gen = torch.Generator().manual_seed(5)
    g = ts.SE3.exp(torch.randn(2, 6, dtype=F64, generator=gen))
    P = torch.randn(2, 7, 3, dtype=F64, generator=gen)
    ulps = dict(rtol=4 * torch.finfo(F64).eps, atol=1e-15)
    J_g, J_x = g.act_jacobians(P, point_axes=1)
    assert J_g.shape == (2, 7, 3, 6) and J_x.shape == (2, 7, 3, 3)
    want = torch.stack([g[k].act_jacobians(P[k])[0] for k in range(2)])
    torch.testing.assert_close(J_g, want, **ulps)
    for G in (ts.Sim3, ts.SE3):  # points' last batch axis as long as Sim3's tangent (7)
        one = G.exp(torch.randn(G.dof, dtype=F64, generator=gen))
        J_g1, J_x1 = one.act_jacobians(P)
        assert J_g1.shape == (2, 7, 3, G.dof) and J_x1.shape == (2, 7, 3, 3)
        each = torch.stack([torch.stack([one.act_jacobians(P[i, k])[0] for k in range(7)]) for i in range(2)])
        torch.testing.assert_close(J_g1, each, **ulps)
    before = one.as_matrix().clone()
    assert J_x1.stride()[:2] == (0, 0)  # one block in memory for the 14 points
    with pytest.raises(RuntimeError, match="single memory location"):
        J_x1.mul_(2)
    J_x1.clone().mul_(2)
    J_x1.zero_()  # a fill writes the one block
    assert torch.equal(one.as_matrix(), before)
    for G in GROUP_CLASSES:  # SO(3) and SO(2): J_x is the whole matrix, and still a copy
        g = G.random(4, dtype=F64, generator=gen)
        before = g.as_matrix().clone()
        g.act_jacobians(torch.randn(4, G.point_dim, dtype=F64, generator=gen))[1].zero_()
        assert torch.equal(g.as_matrix(), before), G.__name__
        g.adjoint().zero_()  # so is the adjoint (SO(3)'s is the rotation matrix)
        assert torch.equal(g.as_matrix(), before), G.__name__


@pytest.mark.parametrize("G", GROUP_CLASSES, ids=lambda g: g.__name__)
def test_act_jacobians_under_vmap_and_compile_equal_eager(G):
    """The basis hat(e_j) (``blocks.generators``, cached per group, dtype and device) under
    torch.func.vmap over elements and points and under torch.compile (fullgraph): the eager
    values, float32 and float64."""
    gen = torch.Generator().manual_seed(8)
    for dtype in (torch.float32, F64):
        g = G.exp(torch.randn(3, 1, G.dof, dtype=F64, generator=gen).to(dtype))
        x = torch.randn(3, 5, G.point_dim, dtype=F64, generator=gen).to(dtype)
        want = g.act_jacobians(x)[0]
        assert want.dtype == dtype
        mapped = torch.vmap(lambda M, p: G.from_matrix(M).act_jacobians(p)[0])(g.as_matrix(), x)
        torch.testing.assert_close(mapped, want, rtol=0, atol=0)
        if G in (ts.SE3, ts.SGal3):  # compiling costs seconds a group
            compiled = torch.compile(lambda M, p: G.from_matrix(M).act_jacobians(p)[0], fullgraph=True)
            torch.testing.assert_close(compiled(g.as_matrix(), x), want)


def test_generator_cache_keeps_only_plain_tensors(monkeypatch):
    """Created first under inference mode or a fake-tensor trace, the basis is not cached (it
    would poison later calls: inference tensors cannot be saved for backward, fake ones cannot
    mix with real ones); a plain call caches it, and a fake-tensor trace with the cache filled
    runs and leaves it as it was."""
    from torch._subclasses.fake_tensor import FakeTensorMode

    from torchsgal.functional import blocks

    monkeypatch.setattr(blocks, "_GENERATORS", {})
    with torch.inference_mode():
        ts.SO2.random(4, dtype=F64).act_jacobians(torch.randn(4, 2, dtype=F64))
    with FakeTensorMode():
        ts.SE3.random(4, dtype=F64).act_jacobians(torch.randn(4, 3, dtype=F64))
    assert blocks._GENERATORS == {}
    g = ts.SO2.exp(torch.randn(4, 1, dtype=F64)).as_matrix().requires_grad_(True)
    x = torch.randn(4, 2, dtype=F64)
    assert torch.autograd.gradcheck(lambda M: ts.SO2.from_matrix(M).act_jacobians(x)[0], (g,))
    for G in GROUP_CLASSES:
        G.random(2, dtype=torch.float32).act_jacobians(torch.randn(2, G.point_dim))
    assert len(blocks._GENERATORS) == len(GROUP_CLASSES) + 1  # SO2 in both dtypes
    assert all(type(t) is torch.Tensor and not t.is_inference() for t in blocks._GENERATORS.values())
    for (hat, dtype, device), t in blocks._GENERATORS.items():
        dof = t.shape[0]
        assert t.dtype == dtype and t.device == device
        assert torch.equal(t, hat(torch.eye(dof, dtype=dtype)))
    cached = dict(blocks._GENERATORS)
    with FakeTensorMode():
        for G in GROUP_CLASSES:
            J = G.random(3).act_jacobians(torch.randn(3, G.point_dim))[0]
            assert J.shape[-1] == G.dof
    assert blocks._GENERATORS == cached


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=str)
def test_sim3_act_jacobian_keeps_its_precision_far_from_the_origin_and_at_extreme_scales(dtype):
    """Sim(3)'s J_g = [sC, -sC p^, sC p] does not depend on the translation: with |r| = 1e8
    and points of unit size, and with lambda = +-80 and +-700 (float64), every entry is exact to
    a few eps relative to the Jacobian's size (the quotient rule on M itself cancelled terms of
    size s |r|: relative errors up to 1 in float32)."""
    gen = torch.Generator().manual_seed(3)
    C = ts.SO3.exp(torch.randn(50, 3, dtype=F64, generator=gen)).as_matrix()
    r = 1e8 * torch.randn(50, 3, dtype=F64, generator=gen)
    lam = torch.zeros(50, dtype=F64)
    if dtype is F64:
        lam[:4] = torch.tensor([-80.0, 80.0, -700.0, 700.0], dtype=F64)
    M = ts.Sim3.from_components(C, r, torch.exp(lam)).as_matrix().to(dtype)
    p = torch.randn(50, 3, dtype=dtype, generator=gen)
    J = ts.Sim3(M).act_jacobians(p)[0].double()
    sC = M.double()[:, :3, :3] / M.double()[:, 3, 3, None, None]
    want = torch.cat([sC, -sC @ _skew(p.double()), sC @ p.double()[..., None]], -1)
    err = (J - want).abs().amax((-1, -2)) / want.abs().amax((-1, -2))
    assert err.max() < 8 * torch.finfo(dtype).eps, err.max()


@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=lambda G: G.__name__)
def test_act_jacobians_raise_as_act_does(G):
    """Bad points raise act's own error (the argument's name, its batch shape without the
    tangent axis the Jacobians add)."""
    g = G.identity((3,), dtype=F64)
    for bad in (torch.zeros(3, G.point_dim + 1, dtype=F64), torch.zeros(4, G.point_dim, dtype=F64),
                torch.zeros(3, G.point_dim, dtype=torch.float32)):
        with pytest.raises((ValueError, TypeError)) as want:
            g.act(bad)
        with pytest.raises(type(want.value)) as got:
            g.act_jacobians(bad)
        assert str(got.value) == str(want.value)
    with pytest.raises(ValueError, match="point_axes"):
        g.act_jacobians(torch.zeros(3, G.point_dim, dtype=F64), point_axes=2)


# ------------------------------------------------------------------------ GTSAM
gtsam = pytest.importorskip("gtsam")
from torchsgal.interop import gtsam as interop  # noqa: E402

# where our tangent coordinate k sits in GTSAM's: xi_gtsam = xi_ours[perm]
PEERS = {ts.SO2: "Rot2", ts.SE2: "Pose2", ts.SO3: "Rot3", ts.SE3: "Pose3", ts.Sim3: "Similarity3",
         ts.SGal3: "Gal3"}


def _gtsam_act(G, obj, x):
    """(y, H_self, H_x) from GTSAM, H in GTSAM's tangent and point orders."""
    rows = 4 if G is ts.SGal3 else x.size
    Hs = np.zeros((rows, G.dof), order="F")
    Hx = np.zeros((rows, rows), order="F")
    if G is ts.SGal3:  # gtsam.Event is (t, location): its tangent [t, x]
        out = obj.act(gtsam.Event(float(x[3]), x[:3]), Hs, Hx)
        return np.concatenate([out.location(), [out.time()]]), Hs, Hx
    method = "rotate" if G in (ts.SO2, ts.SO3) else "transformFrom"
    return np.asarray(getattr(obj, method)(x, Hs, Hx)), Hs, Hx


@pytest.mark.parametrize("angle", [0.0, 1e-6, 0.7, 2.5, math.pi - 1e-4])
@pytest.mark.parametrize("G", list(PEERS), ids=lambda G: G.__name__)
def test_act_jacobians_match_gtsam(G, angle):
    xi = torch.tensor(np.random.default_rng(3).standard_normal(G.dof), dtype=F64)
    phi = G._f.PHI
    axis = xi[phi] / xi[phi].norm()
    xi[phi] = axis * angle
    g = G.exp(xi)
    x = torch.tensor(np.random.default_rng(4).standard_normal(G.point_dim), dtype=F64)
    J_g, J_x = g.act_jacobians(x)
    y, Hs, Hx = _gtsam_act(G, interop.to_gtsam(g), x.numpy())
    perm = list(interop.TYPES[PEERS[G]][1])
    want_g = np.empty_like(Hs)
    want_g[:, perm] = Hs  # our column perm[k] is GTSAM's column k
    if G is ts.SGal3:  # GTSAM's event rows and columns [t, x] -> ours [x, t]
        order = [1, 2, 3, 0]
        want_g, Hx = want_g[order], Hx[np.ix_(order, order)]
    np.testing.assert_allclose(g.act(x).numpy(), y, rtol=0, atol=1e-12)
    np.testing.assert_allclose(J_g.numpy(), want_g, rtol=0, atol=1e-10)
    np.testing.assert_allclose(J_x.numpy(), Hx, rtol=0, atol=1e-12)
