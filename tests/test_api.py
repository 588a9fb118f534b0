"""The class API: constructors, accessors, actions, plus/minus, interpolation, batching, and
clear errors on bad input.  Expected values come from plain matrix algebra on the
homogeneous matrices (numpy), independent of the code under test."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
import torch
from conftest import all_groups, assert_close, np64, sample_group, sample_tangent

import torchsgal as ts

IDS = lambda g: g.__name__  # noqa: E731


def test_dimensions():
    assert [(G.dof, G.matrix_dim) for G in ts.ALL_GROUPS] == [(1, 2), (3, 3), (3, 3), (6, 4), (9, 5), (10, 5), (7, 4)]


def test_worked_event_example():
    """kelly-all-about-sgal3.txt, 'A Simple Transform Example': (1, 1, 0, 2) -> (3, 2, 0, 1)."""
    F = torch.tensor(
        [[0, -1, 0, 2, 0], [1, 0, 0, 0, 1], [0, 0, 1, 0, 0], [0, 0, 0, 1, -1], [0, 0, 0, 0, 1]],
        dtype=torch.float64,
    )
    g = ts.SGal3.from_matrix(F, check=True)
    out = g.act(torch.tensor([1.0, 1.0, 0.0, 2.0], dtype=torch.float64))
    assert out.tolist() == [3.0, 2.0, 0.0, 1.0]
    # the same element from its components: rotation pi/2 about z, boost 2 in x, y + 1, t - 1
    C = torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]], dtype=torch.float64)
    h = ts.SGal3.from_components(
        C, torch.tensor([2.0, 0, 0], dtype=torch.float64), torch.tensor([0.0, 1, 0], dtype=torch.float64),
        torch.tensor(-1.0, dtype=torch.float64),
    )
    assert torch.equal(h.as_matrix(), F)


def _homogeneous(G, x, kind):
    """Homogeneous coordinates per CONVENTIONS.md."""
    n = G.matrix_dim
    out = np.zeros(x.shape[:-1] + (n,))
    if kind == "point":
        out[..., : x.shape[-1]] = x
        if n > G.point_dim:
            out[..., n - 1] = 1.0  # point [x, (0,) 1], event [x, t, 1]; none for SO2/SO3
    elif kind == "velocity":
        out[..., :3] = x
        out[..., 3] = 1.0  # [v, 1, 0]
    else:
        out[..., : x.shape[-1]] = x  # direction [d, 0, ...]
    return out


@all_groups
def test_actions_match_homogeneous_products(G, batch_shape, dtype):
    g = sample_group(G, batch_shape, dtype, seed=11)
    M = np64(g.as_matrix())
    dim, k = G.point_dim, G.rotation_dim
    gen = torch.Generator().manual_seed(31)
    p = torch.randn(*batch_shape, dim, dtype=dtype, generator=gen)
    hom = np.einsum("...ij,...j->...i", M, _homogeneous(G, np64(p), "point"))
    if G.matrix_dim > dim:  # back from homogeneous coordinates (Sim3's last entry is 1/s)
        hom = hom / hom[..., -1:]
    assert_close(g.act(p), hom[..., :dim], dtype)
    d = torch.randn(*batch_shape, k, dtype=dtype, generator=gen)
    want = np.einsum("...ij,...j->...i", M, _homogeneous(G, np64(d), "direction"))[..., :k]
    assert_close(g.act_direction(d), want, dtype)
    if hasattr(g, "act_velocity"):
        want = np.einsum("...ij,...j->...i", M, _homogeneous(G, np64(d), "velocity"))
        assert_close(g.act_velocity(d), want[..., :3], dtype)
        np.testing.assert_allclose(want[..., 3], 1.0)  # stays a velocity


@all_groups
def test_plus_minus_between(G, batch_shape, dtype):
    g = sample_group(G, batch_shape, dtype, seed=12)
    h = sample_group(G, batch_shape, dtype, seed=13)
    d = 0.3 * sample_tangent(G, batch_shape, dtype, seed=14)
    Mg, Mh, Ed = np64(g.as_matrix()), np64(h.as_matrix()), np64(G.exp(d).as_matrix())
    assert_close(g.rplus(d).as_matrix(), Mg @ Ed, dtype)
    assert_close(g.lplus(d).as_matrix(), Ed @ Mg, dtype)
    assert_close(g.between(h).as_matrix(), np.linalg.inv(Mg) @ Mh, dtype, factor=10)
    assert_close(g.rplus(d).rminus(g), np64(d), dtype, factor=10)
    assert_close(g.lplus(d).lminus(g), np64(d), dtype, factor=10)


@all_groups(dtypes=[torch.float64])
def test_interpolate_is_the_geodesic(G, batch_shape, dtype):
    g = sample_group(G, batch_shape, dtype, seed=15)
    h = sample_group(G, batch_shape, dtype, seed=16)
    assert_close(g.interpolate(h, 0.0).as_matrix(), np64(g.as_matrix()), dtype)
    # g exp(log(g^-1 h)) = h: measured worst 9.2e-16 relative (Sim3) on these samples
    assert_close(g.interpolate(h, 1.0).as_matrix(), np64(h.as_matrix()), dtype, factor=1e-3)
    # alpha as a batched tensor: g expm(alpha logm(g^-1 h)) from scipy (measured worst 7.2e-15)
    alpha = torch.rand(batch_shape, dtype=dtype, generator=torch.Generator().manual_seed(32))
    got = np64(g.interpolate(h, alpha).as_matrix()).reshape(-1, G.matrix_dim, G.matrix_dim)
    Mg = np64(g.as_matrix()).reshape(-1, G.matrix_dim, G.matrix_dim)
    Mh = np64(h.as_matrix()).reshape(-1, G.matrix_dim, G.matrix_dim)
    a = np64(alpha).reshape(-1)
    for k in range(Mg.shape[0]):
        rel = np.real(scipy.linalg.logm(np.linalg.inv(Mg[k]) @ Mh[k]))
        np.testing.assert_allclose(got[k], Mg[k] @ scipy.linalg.expm(a[k] * rel), rtol=0, atol=1e-12)


@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=IDS)
def test_batch_broadcasting_indexing_reshaping(G):
    g = G.random((5,), dtype=torch.float64)
    h = G.random((2, 1), dtype=torch.float64)
    gh = g @ h
    assert gh.batch_shape == (2, 5)
    np.testing.assert_allclose(
        np64(gh.as_matrix()[1, 3]), np64(g.as_matrix()[3]) @ np64(h.as_matrix()[1, 0]), rtol=0, atol=1e-14
    )
    assert gh[1].batch_shape == (5,)
    assert gh[:, 2:4].batch_shape == (2, 2)
    assert gh.reshape(10).batch_shape == (10,)
    assert gh.reshape(-1, 5).batch_shape == (2, 5)
    assert g.unsqueeze(0).batch_shape == (1, 5)
    assert len(g) == 5
    assert G.stack([g, g], dim=0).batch_shape == (2, 5)
    assert G.stack([g, g], dim=-1).batch_shape == (5, 2)
    both = G.cat([g, g[:2]])
    assert both.batch_shape == (7,) and torch.equal(both.as_matrix()[5:], g.as_matrix()[:2])
    assert G.cat([gh, gh], dim=-1).batch_shape == (2, 10)
    assert g.unsqueeze(-1).batch_shape == (5, 1)
    assert g.to(torch.float32).dtype == torch.float32
    assert g.float().dtype == torch.float32 and g.float().double().dtype == torch.float64
    assert g.cpu().device.type == "cpu"
    assert g.detach().as_matrix().requires_grad is False
    col = g.unsqueeze(0).unsqueeze(-1)  # (1, 5, 1)
    assert col.squeeze().batch_shape == (5,) and col.squeeze(-1).batch_shape == (1, 5)
    assert col.squeeze(1).batch_shape == (1, 5, 1)  # size 5: unchanged, as torch.squeeze
    assert G.identity().unsqueeze(0).squeeze().batch_shape == ()
    assert torch.equal(gh.flatten().as_matrix(), gh.as_matrix().reshape(10, G.matrix_dim, G.matrix_dim))
    assert G.identity().flatten().batch_shape == (1,)
    assert [x.batch_shape for x in h] == [(1,), (1,)]  # iteration over the first batch axis
    i = G.identity((3,), dtype=torch.float32)
    assert i.batch_shape == (3,) and i.dtype == torch.float32
    assert torch.equal(i.as_matrix()[0], torch.eye(G.matrix_dim))
    # random elements are members of the group
    G.from_matrix(G.random((100,), dtype=torch.float64).as_matrix(), check=True)
    assert "batch_shape=(5,)" in repr(g)
    assert "with matrix" not in repr(g)  # more than REPR_ELEMENTS elements: metadata only
    one = G.exp(torch.full((G.dof,), 0.25, dtype=torch.float64))
    assert repr(one).endswith(" with matrix\n" + repr(one.as_matrix()))  # a few show their matrices
    assert "with matrix" not in repr(G.identity(device="meta"))  # no values to show


def test_components_round_trip():
    g = ts.SGal3.random((4,), dtype=torch.float64)
    h = ts.SGal3.from_components(g.rotation(), g.velocity(), g.position(), g.time())
    assert torch.equal(g.as_matrix(), h.as_matrix())
    e = ts.SE23.random((4,), dtype=torch.float64)
    assert torch.equal(
        ts.SE23.from_components(e.rotation(), e.velocity(), e.position()).as_matrix(), e.as_matrix()
    )
    p = ts.SE3.random((4,), dtype=torch.float64)
    assert torch.equal(ts.SE3.from_components(p.rotation(), p.position()).as_matrix(), p.as_matrix())
    for G in (ts.SO3, ts.SO2):
        r = G.random((4,), dtype=torch.float64)
        assert torch.equal(G.from_components(rotation=r.rotation()).as_matrix(), r.as_matrix())
        with pytest.raises(ValueError, match=rf"rotation must have shape \(\.\.\., {G.matrix_dim}, {G.matrix_dim}\)"):
            G.from_components(torch.eye(G.matrix_dim + 1, dtype=torch.float64))
    # components broadcast: one rotation, a batch of positions
    q = ts.SE3.from_components(torch.eye(3), torch.zeros(7, 3))
    assert q.batch_shape == (7,)
    # Sim3 stores 1/s: the round trip through the scale is exact up to one rounding
    m = ts.Sim3.random((4,), dtype=torch.float64)
    back = ts.Sim3.from_components(m.rotation(), m.position(), m.scale()).as_matrix()
    np.testing.assert_allclose(np64(back), np64(m.as_matrix()), rtol=2e-16, atol=0)
    np.testing.assert_allclose(np64(m.scale()), 1.0 / np64(m.as_matrix()[:, 3, 3]), rtol=0)
    p = torch.randn(4, 3, dtype=torch.float64)
    want = np64(m.scale())[:, None] * np.einsum("bij,bj->bi", np64(m.rotation()), np64(p)) \
        + np64(m.scale())[:, None] * np64(m.position())
    np.testing.assert_allclose(np64(m.act(p)), want, rtol=1e-14, atol=1e-14)


def test_sim3_scale_must_be_positive():
    M = ts.Sim3.random((3,), dtype=torch.float64).as_matrix().clone()
    M[1, 3, 3] = -0.5
    with pytest.raises(ValueError, match=r"not in Sim3: M\[3, 3\] = 1/s must be positive, got -0.5"):
        ts.Sim3.from_matrix(M, check=True)
    with pytest.raises(TypeError, match=r"scale must have a floating dtype"):
        ts.Sim3.from_components(torch.eye(3), torch.zeros(3), torch.ones((), dtype=torch.int64))
    with pytest.raises(ValueError, match=r"batch shapes do not broadcast: rotation \(\), position \(3,\), scale \(4,\)"):
        ts.Sim3.from_components(torch.eye(3), torch.zeros(3, 3), torch.ones(4))
    # one unbatched element: a 0-dim scale (the expand of an empty shape must not crash)
    D = torch.float64
    one = ts.Sim3.from_components(torch.eye(3, dtype=D), torch.zeros(3, dtype=D), torch.tensor(2.0, dtype=D))
    assert one.batch_shape == () and one.scale().item() == 2.0
    assert torch.equal(one.as_matrix(), torch.diag(torch.tensor([1.0, 1.0, 1.0, 0.5], dtype=D)))


# ------------------------------------------------------------------------------ bad input
@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=IDS)
def test_wrong_trailing_dimension(G):
    with pytest.raises(ValueError, match=rf"xi must have shape \(\.\.\., {G.dof}\), got \(4, {G.dof + 1}\)"):
        G.exp(torch.zeros(4, G.dof + 1))
    with pytest.raises(ValueError, match=r"matrix must have shape"):
        G.from_matrix(torch.zeros(2, G.matrix_dim + 1, G.matrix_dim + 1))
    with pytest.raises(ValueError, match=r"must have shape"):
        G.jl(torch.zeros(G.dof - 1))
    g = G.random((2,))
    with pytest.raises(ValueError, match=rf"must have shape \(\.\.\., {G.point_dim}\), got \(2, 7\)"):
        g.act(torch.zeros(2, 7))


@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=IDS)
def test_batch_shapes_that_do_not_broadcast(G):
    g, h = G.random((3,)), G.random((4,))
    with pytest.raises(ValueError, match=r"batch shapes do not broadcast: self \(3,\), other \(4,\)"):
        g @ h
    with pytest.raises(ValueError, match=r"batch shapes do not broadcast"):
        g.act(torch.zeros(5, G.point_dim))


@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=IDS)
def test_functional_layer_checks_its_matrices(G):
    """The functional compose, inverse and adjoint name their argument like the classes do."""
    f, n = G._f, G.matrix_dim
    A, B = G.random((3,)).as_matrix(), G.random((4,)).as_matrix()
    with pytest.raises(ValueError, match=r"batch shapes do not broadcast: A \(3,\), B \(4,\)"):
        f.compose(A, B)
    with pytest.raises(ValueError, match=rf"B must have shape \(\.\.\., {n}, {n}\), got \(3, {n}, {n + 1}\)"):
        f.compose(A, torch.zeros(3, n, n + 1))
    with pytest.raises(TypeError, match=r"B has dtype torch.float64 but A has dtype torch.float32"):
        f.compose(A, A.double())
    for fn in (f.inverse, f.adjoint):
        with pytest.raises(ValueError, match=rf"must have shape \(\.\.\., {n}, {n}\), got \(2, {n + 1}, {n}\)"):
            fn(torch.zeros(2, n + 1, n))
        with pytest.raises(TypeError, match=r"floating dtype"):
            fn(torch.zeros(n, n, dtype=torch.int64))


@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=IDS)
def test_integer_and_mixed_dtypes(G):
    with pytest.raises(TypeError, match=r"xi must have a floating dtype .* got torch.int64"):
        G.exp(torch.zeros(G.dof, dtype=torch.int64))
    with pytest.raises(TypeError, match=r"floating dtype"):
        G.from_matrix(torch.eye(G.matrix_dim, dtype=torch.int32))
    # Half precision is refused, not computed with float32/float64 thresholds.
    for half in (torch.float16, torch.bfloat16):
        with pytest.raises(TypeError, match=rf"xi must have a floating dtype .* got {half}; convert"):
            G.exp(torch.zeros(G.dof, dtype=half))
        with pytest.raises(TypeError, match=rf"matrix must have a floating dtype .* got {half}"):
            G.from_matrix(torch.eye(G.matrix_dim, dtype=half))
        with pytest.raises(TypeError, match=rf"got {half}"):
            G._f.log(torch.eye(G.matrix_dim, dtype=half))
        for make in (G.identity, G.random):
            with pytest.raises(TypeError, match=rf"dtype must be torch.float32 or torch.float64, got {half}"):
                make((2,), dtype=half)
    with pytest.raises(TypeError, match=r"dtype torch.float32 but self has dtype torch.float64"):
        G.random((), dtype=torch.float64) @ G.random((), dtype=torch.float32)
    with pytest.raises(TypeError, match=r"must be a torch.Tensor"):
        G.exp([0.0] * G.dof)
    for fn in (G.jl, G.jr, G.jl_inv, G.jr_inv):  # jr negated a list before checking it
        with pytest.raises(TypeError, match=r"xi must be a torch.Tensor, got list"):
            fn([0.0] * G.dof)
    with pytest.raises(TypeError, match=r"other must be a"):
        G.random(()).between(ts.SO3.random(()) if G is not ts.SO3 else ts.SE3.random(()))
    g, h = G.random((3,), dtype=torch.float64), G.random((3,), dtype=torch.float64)
    with pytest.raises(ValueError, match=r"batch shapes do not broadcast: batch \(3,\), alpha \(2,\)"):
        g.interpolate(h, torch.rand(2, dtype=torch.float64))
    with pytest.raises(TypeError, match=r"alpha has dtype torch.float32 but self has dtype torch.float64"):
        g.interpolate(h, torch.rand(3))
    with pytest.raises(TypeError, match=r"alpha must have a floating dtype"):
        g.interpolate(h, torch.ones(3, dtype=torch.int64))
    with pytest.raises(TypeError, match=r"alpha must be a number or a torch.Tensor, got list"):
        g.interpolate(h, [0.5, 0.5, 0.5])
    assert g.interpolate(h, torch.rand(4, 1, dtype=torch.float64)).batch_shape == (4, 3)


@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=IDS)
def test_plus_names_delta(G):
    """rplus/lplus check delta against self before exp, naming both the right way round."""
    g = G.random((4,), dtype=torch.float64)
    for fn in (g.rplus, g.lplus):
        with pytest.raises(TypeError, match=r"delta has dtype torch.float32 but self has dtype torch.float64"):
            fn(torch.zeros(4, G.dof))
        with pytest.raises(ValueError, match=r"batch shapes do not broadcast: self \(4,\), delta \(3,\)"):
            fn(torch.zeros(3, G.dof, dtype=torch.float64))
        with pytest.raises(ValueError, match=rf"delta must have shape \(\.\.\., {G.dof}\), got \(4, {G.dof + 1}\)"):
            fn(torch.zeros(4, G.dof + 1, dtype=torch.float64))
        with pytest.raises(ValueError, match=r"delta is on meta but self is on cpu"):
            fn(torch.zeros(4, G.dof, dtype=torch.float64, device="meta"))


@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=IDS)
def test_batch_shape_arguments(G):
    """identity and random take an int or a sequence of sizes >= 0; expand names both shapes."""
    assert G.identity(3).batch_shape == (3,) and G.random(3).batch_shape == (3,)
    assert G.identity((0,)).batch_shape == (0,)
    for make in (G.identity, G.random):
        with pytest.raises(ValueError, match=r"batch_shape must have sizes >= 0, got \(-1,\)"):
            make((-1,))
        with pytest.raises(TypeError, match=r"batch_shape must be an int or a sequence of ints"):
            make(2.5)
        with pytest.raises(TypeError, match=r"batch_shape must be an int or a sequence of ints"):
            make((2, None))
    with pytest.raises(TypeError, match=r"generator must be None or a torch.Generator, got int"):
        G.random(generator=5)
    # a numpy integer is an int, alone as in a tuple; the functional layer takes the same shapes
    assert G.identity(np.int64(2)).batch_shape == (2,) == G.random(np.int64(2)).batch_shape
    f = G._f
    assert f.random(3, torch.float64, "cpu").shape == (3, G.matrix_dim, G.matrix_dim)
    with pytest.raises(TypeError, match=r"batch_shape must be an int or a sequence of ints"):
        f.random(2.5, torch.float64, "cpu")
    g = G.random((4,), dtype=torch.float64)
    assert g.expand(2, 4).batch_shape == (2, 4) and g[:1].expand(3).batch_shape == (3,)
    with pytest.raises(ValueError, match=r"cannot expand the batch shape \(4,\) .* to \(3,\)"):
        g.expand(3)
    with pytest.raises(ValueError, match=r"cannot expand the batch shape \(4,\) .* to \(\)"):
        g.expand(())


@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=IDS)
def test_mixed_devices(G):
    """Tensors on different devices are refused before any kernel runs (meta stands in for a
    second device where no GPU is available)."""
    g = G.random((2,))
    other = G(torch.empty(2, G.matrix_dim, G.matrix_dim, device="meta"))
    with pytest.raises(ValueError, match=r"other is on meta but self is on cpu"):
        g @ other
    with pytest.raises(ValueError, match=r"is on meta but g is on cpu"):
        g.act_direction(torch.zeros(2, G.rotation_dim, device="meta"))


@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=IDS)
def test_from_matrix_check(G):
    M = G.random((3,), dtype=torch.float64).as_matrix().clone()
    G.from_matrix(M, check=True)
    bad = M.clone()
    bad[1, 0, 0] += 1e-3  # not orthonormal
    with pytest.raises(ValueError, match=rf"not in {G.__name__}.*C\^T C - I"):
        G.from_matrix(bad, check=True)
    refl = M.clone()
    refl[0, 0, :] = -refl[0, 0, :]  # flip a row of C: orthogonal, det -1
    with pytest.raises(ValueError, match=r"det C - 1"):
        G.from_matrix(refl, check=True)
    if G.matrix_dim > G.rotation_dim:
        row = M.clone()
        row[2, -1, 0] = 0.5  # the fixed bottom row
        with pytest.raises(ValueError, match=r"fixed rows"):
            G.from_matrix(row, check=True)
    else:  # SO2, SO3 have no fixed rows: the message does not speak of them
        with pytest.raises(ValueError) as err:
            G.from_matrix(bad, check=True)
        assert "fixed rows" not in str(err.value)
    nan = M.clone()
    nan[0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match=r"non-finite"):
        G.from_matrix(nan, check=True)
    G.from_matrix(bad, check=False)  # unchecked wrapping is allowed
    # tol: None or a finite number > 0 (nan and inf would accept anything, -1 reject all: each raises)
    for tol in (float("nan"), float("inf"), -1, 0):
        with pytest.raises(ValueError, match=r"tol must be a finite number > 0, got"):
            G.from_matrix(bad, check=True, tol=tol)
    with pytest.raises(TypeError, match=r"tol must be a finite number > 0, got '1e-9'"):
        G.from_matrix(M, check=True, tol="1e-9")
    G.from_matrix(bad, check=True, tol=1e-2)  # a looser valid tol accepts it
    # values are checked only where they can be read (as in the uncertainty module): not on
    # 'meta' and not under a torch.func transform; shapes always are
    meta = G.from_matrix(torch.empty(2, G.matrix_dim, G.matrix_dim, device="meta"), check=True)
    assert meta.device.type == "meta" and meta.batch_shape == (2,)
    out = torch.func.vmap(lambda m: G.from_matrix(m, check=True).as_matrix())(M)
    assert torch.equal(out, M)
    with pytest.raises(ValueError, match=r"matrix must have shape"):
        G.from_matrix(torch.empty(2, 1, 1, device="meta"), check=True)


@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=IDS)
def test_no_nan_for_finite_input(G):
    """Exact identity, exact pi rotations and huge angles: finite results everywhere."""
    xi = torch.zeros(6, G.dof, dtype=torch.float64)
    phi = G._f.PHI
    k = phi.stop - phi.start
    xi[1, phi] = torch.tensor([np.pi, 0, 0][:k], dtype=torch.float64)
    xi[2, phi] = torch.tensor([0, 0, -np.pi][-k:], dtype=torch.float64)
    xi[3, phi] = torch.tensor([1e3, -2e3, 5e2][:k], dtype=torch.float64)
    xi[4, phi] = torch.tensor([1e-300, 0, 0][:k], dtype=torch.float64)
    xi[5] = 1e6
    # a log-scale component (Sim3's lambda) is stored as exp(-lambda): keep it representable
    xi[5, getattr(G, "log_scale_slice", slice(0, 0))] = 700.0
    for fn in ("jl", "jr", "jl_inv", "jr_inv", "ad"):
        assert torch.isfinite(getattr(G, fn)(xi[[0, 1, 2, 4]])).all(), fn
    g = G.exp(xi)
    assert torch.isfinite(g.as_matrix()).all()
    assert torch.isfinite(g.log()).all()
    assert torch.isfinite(g.adjoint()).all()
    # rotation by exactly pi: log returns angle pi about the right axis (either sign)
    phi_back = g.log()[1:3, phi]
    np.testing.assert_allclose(np64(phi_back.abs()), np64(xi[1:3, phi].abs()), rtol=0, atol=1e-12)


@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=IDS)
def test_stack_cat_unsqueeze_errors(G):
    g = G.random((5,), dtype=torch.float64)
    with pytest.raises(IndexError, match="dim must be in \\[-2, 1\\]"):
        G.stack([g, g], dim=2)  # would otherwise stack inside the matrix axes
    with pytest.raises(IndexError, match="dim must be in \\[-1, 0\\]"):
        G.cat([g, g], dim=1)
    with pytest.raises(IndexError, match="dim must be in"):
        g.unsqueeze(2)
    with pytest.raises(IndexError, match="dim must be in"):
        g.squeeze(1)
    with pytest.raises(IndexError, match=r"does not fit the batch shape \(5,\) .*: too many indices for 1 batch axis$"):
        g[0, 0]  # would otherwise index a matrix row
    with pytest.raises(IndexError, match=r"too many indices for 0 batch axes$"):
        G.identity()[0]
    with pytest.raises(ValueError, match=r"cannot reshape the batch shape \(5,\) .* to \(2, 2\)"):
        g.reshape(2, 2)
    with pytest.raises(ValueError, match="needs at least one element"):
        G.stack([])
    with pytest.raises(ValueError, match="use stack"):
        G.cat([G.identity(), G.identity()])
    other = next(H for H in ts.ALL_GROUPS if H is not G)
    with pytest.raises(TypeError, match=f"elements\\[1\\] must be a {G.__name__}"):
        G.stack([g, other.random((5,), dtype=torch.float64)])
    # one dtype and device, as compose (no silent promotion to float64)
    for op in (G.stack, G.cat):
        with pytest.raises(TypeError, match=r"elements\[1\] has dtype torch.float32 but elements\[0\] has dtype torch.float64"):
            op([g, g.float()])
        with pytest.raises(ValueError, match=r"elements\[2\] is on meta but elements\[0\] is on cpu"):
            op([g, g, g.to("meta")])
    with pytest.raises(ValueError, match=r"stack needs elements of equal batch shape: elements\[0\] has \(5,\), elements\[1\] has \(2,\)"):
        G.stack([g, g[:2]])
    with pytest.raises(ValueError, match=r"cat needs elements whose batch shapes differ only along dim 0: elements\[0\] has \(5,\), elements\[1\] has \(1, 5\)"):
        G.cat([g, g.unsqueeze(0)])
    with pytest.raises(ValueError, match=r"differ only along dim -1: elements\[0\] has \(1, 5\), elements\[1\] has \(2, 5\)"):
        G.cat([g.unsqueeze(0), G.random((2, 5), dtype=torch.float64)], dim=-1)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["f32", "f64"])
def test_sgal3_packed_layout(dtype):
    from torchsgal.functional import sgal3 as F

    g = torch.Generator().manual_seed(3)
    A = ts.SGal3.random((2, 3), dtype=dtype, generator=g).as_matrix()
    Bm = ts.SGal3.random((2, 3), dtype=dtype, generator=g).as_matrix()
    P, Q = F.pack(A), F.pack(Bm)
    assert P.shape == (16, 2, 3) and torch.equal(F.unpack(P), A)
    eps = torch.finfo(dtype).eps
    AB = np64(A) @ np64(Bm)  # the product in float64
    np.testing.assert_allclose(np64(F.unpack(F.compose_packed(P, Q))), AB, rtol=0, atol=50 * eps * np.abs(AB).max())
    I = F.packed_identity(P)
    assert I.shape == (16, 1, 1) and torch.equal(F.unpack(F.compose_packed(I.expand_as(P), P)), A)
    xi = torch.randn(4, 10, dtype=dtype, generator=g)
    E = np64(F.unpack(F.exp_packed(xi)))
    for k in range(4):  # against the matrix exponential of the hat matrix
        ref = scipy.linalg.expm(np64(F.hat(xi[k].double())))
        np.testing.assert_allclose(E[k], ref, rtol=0, atol=100 * eps * np.abs(ref).max())
    with pytest.raises(ValueError, match=r"P must have shape \(16, \.\.\.\)"):
        F.unpack(torch.zeros(15, 2, dtype=dtype))
    with pytest.raises(ValueError, match=r"P2 must have shape \(16, \.\.\.\)"):
        F.compose_packed(P, torch.zeros(15, 2, 3, dtype=dtype))
    with pytest.raises(ValueError, match="M must have shape"):
        F.pack(torch.zeros(2, 4, 4, dtype=dtype))


def test_series_constant_cache_keeps_only_plain_tensors(monkeypatch):
    """The series constants are cached per dtype/device, but not when first created under
    inference mode or a fake-tensor trace (those tensors would poison later calls)."""
    from torch._subclasses.fake_tensor import FakeTensorMode

    from torchsgal.functional import native, numerics

    monkeypatch.setattr(numerics, "_CONSTANTS", {})
    monkeypatch.setitem(native._state, "on", False)  # the tensor code (C kernels need no cache)
    with torch.inference_mode():
        ts.SGal3.exp(torch.randn(3, 10, dtype=torch.float64))
    with FakeTensorMode():
        ts.SGal3.exp(torch.randn(3, 10, dtype=torch.float32))
    assert numerics._CONSTANTS == {}
    x = torch.randn(4, 10, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda v: ts.SGal3.exp(v).as_matrix(), (x,))
    assert numerics._CONSTANTS and all(type(t) is torch.Tensor and not t.is_inference()
                                       for consts in numerics._CONSTANTS.values() for t in consts)
    # with the cache filled, a fake-tensor trace still runs (it must not get the cached real
    # tensors and fail on mixing them with fake ones), and leaves the cache as it was
    for G in ts.ALL_GROUPS:
        G.jl(torch.randn(3, G.dof, dtype=torch.float32))
    cached = dict(numerics._CONSTANTS)
    with FakeTensorMode():
        for G in ts.ALL_GROUPS:
            xi = torch.randn(3, G.dof, dtype=torch.float32)
            assert G.exp(xi).log().shape == (3, G.dof) and G.jl_inv(xi).shape == (3, G.dof, G.dof)
    assert numerics._CONSTANTS == cached


def test_the_abstract_base_class_says_so():
    """LieGroup has no group: its constructors name the classes to use instead of failing on a
    missing attribute, as does a subclass that names no group."""
    from torchsgal.groups.base import LieGroup

    class NoGroup(LieGroup):
        pass

    for cls in (LieGroup, NoGroup):
        for make in (cls.random, cls.identity, lambda: cls.exp(torch.zeros(3)), lambda: cls(torch.eye(4)),
                     lambda: cls.from_matrix(torch.eye(4)), lambda: cls.hat(torch.zeros(3))):
            with pytest.raises(TypeError, match=r"LieGroup is the abstract base class: use SO2, SE2"):
                make()


@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=IDS)
def test_indexing_gives_views_and_names_a_negative_step(G):
    g = G.random((4,), dtype=torch.float64)
    assert g[1:3].as_matrix().data_ptr() == g.as_matrix()[1].data_ptr()  # a view, as documented
    with pytest.raises(IndexError, match=r"does not fit the batch shape \(4,\) of this .*step must be greater"):
        g[::-1]


@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=IDS)
def test_indexing_refuses_float_lists_and_arrays_and_names_the_index(G):
    """torch truncates a list, tuple or numpy array of floats to integers (t[[0.7]] is t[[0]]):
    the batch index refuses them, as it refuses a float index tensor, and names the index for a
    string too; integer and bool lists and arrays index as the matrices do."""
    g = G.random((4,), dtype=torch.float64)
    M = g.as_matrix()
    for bad, got in (([0.7], "0.7"), ([1, 2.5], "2.5"), ([[0], [1.0]], "1.0"),
                     (np.array([0.5]), "dtype float64"), (np.array([1 + 0j]), "dtype complex128"),
                     ([np.float32(1.0)], "np.float32")):
        with pytest.raises(IndexError, match=rf"does not fit the batch shape \(4,\) of this {G.__name__}: "
                                             rf"index lists, tuples and arrays must hold integers or bools, got {got}"):
            g[bad]
    with pytest.raises(IndexError, match="must hold integers or bools"):
        g[None, [0.5]]
    # a tuple inside the index is a sequence index too (torch would truncate (0.7, 1.9) to [0, 1])
    g2 = G.random((4, 3), dtype=torch.float64)
    for bad in ((slice(None), (0.7, 1.9)), ((0.7,),), ([(0.5,)],), (np.array([1]), [(0.5,)])):
        with pytest.raises(IndexError, match="must hold integers or bools, got 0"):
            g2[bad]
    torch.testing.assert_close(g2[:, (0, 2)].as_matrix(), g2.as_matrix()[:, [0, 2]], rtol=0, atol=0)
    with pytest.raises(TypeError, match=rf"index \('a',\) does not fit the batch shape \(4,\) of this {G.__name__}"):
        g["a"]
    picks = [[0, 2], np.array([3, 1]), [True, False, True, False], np.array([False, True, True, False])]
    for ok, rows in zip(picks, ([0, 2], [3, 1], [0, 2], [1, 2])):
        assert torch.equal(g[ok].as_matrix(), torch.stack([M[i] for i in rows]))


def test_stack_cat_squeeze_name_what_is_wrong():
    """LieGroup.stack/cat (no group of its own) refuse elements of different groups by name
    (unchecked, they would fail on their matrix sizes: "equal batch shape: () and ()", or torch's
    RuntimeError); a non-iterable ``elements`` is named; squeeze(dim) of an unbatched element
    says it has no batch axis (not a dim "in [0, -1]")."""
    from torchsgal.groups.base import LieGroup

    with pytest.raises(TypeError, match="LieGroup is the abstract base class"):
        LieGroup.stack([ts.SO3.identity(), ts.SE3.identity()])
    with pytest.raises(TypeError, match="LieGroup is the abstract base class"):
        LieGroup.cat([ts.SO3.identity((2,)), ts.SE3.identity((2,))])
    for op, bad in ((ts.SE3.stack, None), (ts.SE3.cat, 5)):
        with pytest.raises(TypeError, match=rf"elements must be a sequence of elements \(a list or tuple\), "
                                            rf"got {type(bad).__name__}"):
            op(bad)
    for dim in (0, -1):
        with pytest.raises(IndexError, match=rf"dim must index a batch axis, but an unbatched element has none, got {dim}"):
            ts.SE3.identity().squeeze(dim)
