"""torchsgal.interop against the peers themselves: GTSAM's and pypose's own operations,
scipy's Rotation, and derivatives computed here by torch.func (never by the code under test)."""
from __future__ import annotations

import math
import subprocess
import sys
import warnings

import numpy as np
import pytest
import torch
from conftest import sample_tangent

import torchsgal as ts
from torchsgal.interop import euler
from torchsgal.interop import gtsam as tg
from torchsgal.interop import pypose as tp
from torchsgal.interop import quaternion as tq

gtsam = pytest.importorskip("gtsam")
pp = pytest.importorskip("pypose")
Rotation = pytest.importorskip("scipy.spatial.transform").Rotation

F64 = torch.float64
# identity, tiny, moderate, large and near-pi rotation angles
ANGLES = [0.0, 1e-9, 1e-5, 0.7, 2.5, math.pi - 1e-6]
# GTSAM's Pose2/Rot2 closed forms divide by theta (tests/test_gtsam_planar.py): away from 0
PLANAR_ANGLES = [0.5, 1.0, 2.5, math.pi - 1e-6, -2.0, -math.pi + 1e-6]
GTSAM_GROUPS = [ts.SO2, ts.SE2, ts.SO3, ts.SE3, ts.SE23, ts.SGal3, ts.Sim3]
PYPOSE_GROUPS = [ts.SO3, ts.SE3, ts.Sim3]


def _angles(G):
    return PLANAR_ANGLES if G.rotation_dim == 2 else ANGLES


def _xi(G, seed=0, angles=None, shape=None):
    angles = _angles(G) if angles is None else angles
    xi = sample_tangent(G, (len(angles),), F64, seed=seed, angles=angles)
    return xi if shape is None else xi.reshape(*shape, G.dof)


def _cls(G):
    return getattr(gtsam, tg.GTSAM_TYPE[G])


def _close(a, b, atol, what=""):
    a = a.detach().numpy() if isinstance(a, torch.Tensor) else np.asarray(a)
    b = b.detach().numpy() if isinstance(b, torch.Tensor) else np.asarray(b)
    np.testing.assert_allclose(a, b, rtol=0, atol=atol, err_msg=what)


def _matrix_ours(G, obj):
    """Our matrix of one GTSAM object, read with GTSAM's accessors (not the converter)."""
    if G is ts.SE23:
        M = np.eye(5)
        M[:3, :3] = obj.attitude().matrix()
        M[:3, 3] = obj.velocity()
        M[:3, 4] = obj.position()
        return M
    return np.asarray(obj.matrix())


def _random_gtsam(G, seed):
    """GTSAM objects built by GTSAM (Expmap of vectors in its own order)."""
    rng = np.random.default_rng(seed)
    out = []
    for angle in _angles(G):
        v = rng.standard_normal(G.dof)
        rot = slice(0, G.rotation_dim if G.rotation_dim == 3 else 1)
        if G.rotation_dim == 2:  # Pose2 (x, y, theta), Rot2 (theta)
            rot = slice(G.dof - 1, G.dof)
            v[rot] = angle
        else:
            u = rng.standard_normal(3)
            v[rot] = angle * u / np.linalg.norm(u)
        out.append(_cls(G).Expmap(v))
    return out


# ------------------------------------------------------------------------ GTSAM elements
@pytest.mark.parametrize("G", GTSAM_GROUPS, ids=lambda G: G.__name__)
def test_gtsam_round_trip_ours_peer_ours(G):
    g = G.exp(_xi(G, seed=1, shape=(2, 3)))
    objs = tg.to_gtsam(g)
    assert len(objs) == 2 and all(len(row) == 3 for row in objs)
    assert all(isinstance(o, _cls(G)) for row in objs for o in row)
    for i in range(2):
        for j in range(3):
            _close(_matrix_ours(G, objs[i][j]), g.as_matrix()[i, j], 1e-15, "to_gtsam")
    back = tg.from_gtsam(objs)
    assert type(back) is G and back.batch_shape == (2, 3) and back.dtype == F64
    _close(back.as_matrix(), g.as_matrix(), 1e-15)
    one = tg.to_gtsam(g[1, 2])  # unbatched: one object
    assert isinstance(one, _cls(G))
    assert tg.from_gtsam(one).batch_shape == ()
    g32 = g.float()
    back32 = tg.from_gtsam(tg.to_gtsam(g32), dtype=torch.float32)
    assert back32.dtype == torch.float32
    # Rot2.fromCosSin renormalises (c, s) in float64: one float32 ulp (6e-8) for SO2, SE2
    _close(back32.as_matrix(), g32.as_matrix(), 0.0 if G.rotation_dim == 3 else 1.2e-7)


@pytest.mark.parametrize("G", GTSAM_GROUPS, ids=lambda G: G.__name__)
def test_gtsam_round_trip_peer_ours_peer(G):
    objs = _random_gtsam(G, seed=2)
    g = tg.from_gtsam(objs, group=G)
    again = tg.to_gtsam(g)
    for a, b in zip(objs, again):
        _close(b.matrix(), a.matrix(), 1e-15)
        assert b.equals(a, 1e-14)


@pytest.mark.parametrize("G", GTSAM_GROUPS, ids=lambda G: G.__name__)
def test_gtsam_exp_log_compose_agree(G):
    """GTSAM's Expmap of the mapped tangent is our exp; its Logmap is our log; compose,
    between and inverse agree after conversion."""
    xi = _xi(G, seed=3)
    name = tg.GTSAM_TYPE[G]
    x_g = tg.tangent_to_gtsam(xi, name).numpy()
    peer = [_cls(G).Expmap(v) for v in x_g]
    ours = G.exp(xi)
    scale = max(1.0, float(ours.as_matrix().abs().max()))
    _close(tg.from_gtsam(peer).as_matrix(), ours.as_matrix(), 2e-15 * scale, "Expmap")
    logs = np.stack([_cls(G).Logmap(o) for o in peer])
    # GTSAM's Logmap is only O((pi - theta)^2) accurate near pi (tests/peers/gtsam_map.py)
    _close(tg.tangent_from_gtsam(logs, name), ours.log(), 1e-11 * scale, "Logmap")
    other = G.exp(_xi(G, seed=4))
    peer_other = tg.to_gtsam(other)
    _close(tg.from_gtsam([a.compose(b) for a, b in zip(peer, peer_other)]).as_matrix(),
           (ours @ other).as_matrix(), 1e-14 * scale**2, "compose")
    _close(tg.from_gtsam([a.between(b) for a, b in zip(peer, peer_other)]).as_matrix(),
           ours.between(other).as_matrix(), 1e-13 * scale**2, "between")
    _close(tg.from_gtsam([a.inverse() for a in peer]).as_matrix(), ours.inverse().as_matrix(),
           1e-14 * scale, "inverse")
    Ad = np.stack([o.AdjointMap() for o in peer]).reshape(-1, G.dof, G.dof)  # Rot2's is a 1-vector
    _close(tg.jacobian_from_gtsam(Ad, output=name, input=name), ours.adjoint(), 1e-13 * scale,
           "AdjointMap")


@pytest.mark.parametrize("G", [G for G in GTSAM_GROUPS if G is not ts.SE23], ids=lambda G: G.__name__)
def test_gtsam_retract_is_right_exp(G):
    """retract and localCoordinates are our rplus and rminus: GTSAM's chart is ours exactly."""
    name = tg.GTSAM_TYPE[G]
    g = G.exp(_xi(G, seed=5))
    d = 0.4 * _xi(G, seed=6)
    peer = tg.to_gtsam(g)
    moved = [o.retract(v) for o, v in zip(peer, tg.tangent_to_gtsam(d, name).numpy())]
    ours = g.rplus(d)
    scale = max(1.0, float(ours.as_matrix().abs().max()))
    _close(tg.from_gtsam(moved).as_matrix(), ours.as_matrix(), 1e-13 * scale)
    local = np.stack([o.localCoordinates(m) for o, m in zip(peer, tg.to_gtsam(ours))])
    _close(tg.tangent_from_gtsam(local, name), ours.rminus(g), 1e-11 * scale)


def test_gtsam_navstate_chart():
    """NavState.retract is the component-wise chart, not X exp(xi); navstate_local_to_tangent
    is the exact chart change, and its differential at 0 is the permutation (the charts agree
    to first order), while at second order they differ."""
    assert tg.navstate_retract_is_expmap() is False  # the wheel's default build
    g = ts.SE23.exp(_xi(ts.SE23, seed=7))
    v = 0.5 * torch.tensor(np.random.default_rng(8).standard_normal((len(ANGLES), 9)), dtype=F64)
    peer = tg.to_gtsam(g)
    moved = tg.from_gtsam([o.retract(x) for o, x in zip(peer, v.numpy())])
    _close(moved.as_matrix(), g.rplus(tg.navstate_local_to_tangent(v)).as_matrix(), 1e-13)
    xi = tg.navstate_local_to_tangent(v)
    local = np.stack([o.localCoordinates(m) for o, m in zip(peer, tg.to_gtsam(g.rplus(xi)))])
    _close(local, v, 1e-12)
    _close(tg.tangent_to_navstate_local(xi), v, 1e-14)
    # the retract of the permuted vector is not rplus: the charts differ at second order
    plain = g.rplus(tg.tangent_from_gtsam(v, "NavState"))
    assert float((plain.as_matrix() - moved.as_matrix()).abs().max()) > 1e-2
    # ... and agree to first order: d(chart change)/dv at 0 is the permutation M^T
    D = torch.func.jacfwd(tg.navstate_local_to_tangent)(torch.zeros(9, dtype=F64))
    _close(D, tg.tangent_map("NavState", F64).T, 0.0)
    # the second-order residual of the permutation shrinks as |v|^2
    for s in (1e-2, 1e-3):
        r = (tg.navstate_local_to_tangent(s * v) - tg.tangent_from_gtsam(s * v, "NavState")).abs().max()
        assert 1e-3 * s**2 < float(r) < 10 * s**2


@pytest.mark.parametrize("name", ["Pose3", "NavState"])
def test_gtsam_sampled_covariance_in_our_chart(name):
    """Samples v ~ N(0, sigma^2 S) in GTSAM's chart at X (``X.retract(v)`` by GTSAM), read back
    in ours (``rminus``): for Pose3 the charts are one, and the sample covariance in ours is the
    permuted one to rounding; for NavState they agree to first order only, and the two differ
    by O(sigma) relative, shrinking with sigma."""
    G = tg.TYPES[name][0]
    X = G.exp(_xi(G, seed=17, angles=[2.0])[0])
    peer = tg.to_gtsam(X)
    L = torch.linalg.cholesky(_spd(G.dof, 18))
    z = torch.tensor(np.random.default_rng(19).standard_normal((400, G.dof)), dtype=F64)
    rel = []
    for sigma in (1e-2, 1e-3):
        v = sigma * z @ L.T  # GTSAM-chart samples (its order)
        Y = tg.from_gtsam([peer.retract(x) for x in v.numpy()])
        d = Y.rminus(X.expand(len(Y)))
        expected = torch.cov(tg.tangent_from_gtsam(v, name).T)
        rel.append(float((torch.cov(d.T) - expected).abs().max() / expected.abs().max()))
    if name == "Pose3":
        assert max(rel) < 1e-12
    else:  # measured 0.12 sigma for this X and S (1.2e-3, 1.2e-4)
        for sigma, r in zip((1e-2, 1e-3), rel):
            assert 0.02 * sigma < r < sigma


def _expmap_h(cls, v):
    H = np.zeros((v.size, v.size), order="F")
    obj = cls.Expmap(v, H)
    return obj, H


@pytest.mark.parametrize("G", [ts.SO3, ts.SE3, ts.SE23, ts.SGal3, ts.SE2], ids=lambda G: G.__name__)
def test_gtsam_exp_log_jacobians_map_to_ours(G):
    """GTSAM's Expmap(H) and Logmap(H), mapped with jacobian_from_gtsam, are our jr and jr_inv."""
    name = tg.GTSAM_TYPE[G]
    angles = [0.0, 1e-3, 0.7, 2.5] if G.rotation_dim == 3 else [0.5, 1.0, 2.5, -2.0]
    xi = _xi(G, seed=9, angles=angles)
    for k, x in enumerate(xi):
        obj, H = _expmap_h(_cls(G), tg.tangent_to_gtsam(x, name).numpy())
        # Gal3's Expmap H loses to ~2.5e-10 around 1e-3 (tests/peers/gtsam_map.py)
        _close(tg.jacobian_from_gtsam(H, output=name, input=name), G.jr(x), 1e-9, f"Expmap H {k}")
        H2 = np.zeros_like(H, order="F")
        _cls(G).Logmap(obj, H2)
        _close(tg.jacobian_from_gtsam(H2, output=name, input=name), G.jr_inv(x), 1e-9, f"Logmap H {k}")
        back = tg.jacobian_to_gtsam(tg.jacobian_from_gtsam(H, output=name, input=name), output=name, input=name)
        _close(back, H, 0.0)


def _rminus_jacobian(f, g, h):
    """d log(f(g, h)^-1 f(g exp d1, h exp d2)) / d(d1, d2) at 0, by torch.func."""
    y0 = f(g, h)
    d0 = torch.zeros(g.dof, dtype=F64)
    J1 = torch.func.jacfwd(lambda d: f(g.rplus(d), h).rminus(y0))(d0)
    J2 = torch.func.jacfwd(lambda d: f(g, h.rplus(d)).rminus(y0))(d0)
    return J1, J2


def test_gtsam_between_and_action_jacobians_map_to_ours():
    g, h = ts.SE3.exp(_xi(ts.SE3, seed=10, angles=[2.5])[0]), ts.SE3.exp(_xi(ts.SE3, seed=11, angles=[3.1])[0])
    a, b = tg.to_gtsam(g), tg.to_gtsam(h)
    H1, H2 = np.zeros((6, 6), order="F"), np.zeros((6, 6), order="F")
    a.between(b, H1, H2)
    J1, J2 = _rminus_jacobian(lambda x, y: x.between(y), g, h)
    _close(tg.jacobian_from_gtsam(H1, output="Pose3", input="Pose3"), J1, 1e-13)
    _close(tg.jacobian_from_gtsam(H2, output="Pose3", input="Pose3"), J2, 1e-13)
    # point action: output a plain Point3, input the pose (right perturbation) or the point
    p = torch.tensor([0.3, -1.2, 2.0], dtype=F64)
    for G, obj, el in ((ts.SE3, a, g), (ts.Sim3, tg.to_gtsam(ts.Sim3.exp(_xi(ts.Sim3, 12, [2.0])[0])), None)):
        el = tg.from_gtsam(obj) if el is None else el
        Hs, Hp = np.zeros((3, G.dof), order="F"), np.zeros((3, 3), order="F")
        obj.transformFrom(p.numpy(), Hs, Hp)
        Js = torch.func.jacfwd(lambda d: el.rplus(d).act(p))(torch.zeros(G.dof, dtype=F64))
        Jp = torch.func.jacfwd(el.act)(p)
        _close(tg.jacobian_from_gtsam(Hs, output="Point3", input=tg.GTSAM_TYPE[G]), Js, 1e-13)
        _close(tg.jacobian_from_gtsam(Hs, output=None, input=tg.GTSAM_TYPE[G]), Js, 1e-13)
        _close(tg.jacobian_from_gtsam(Hp, output="Point3", input="Point3"), Jp, 1e-14)


def _spd(d, seed):
    A = np.random.default_rng(seed).standard_normal((d, d))
    return torch.tensor(A @ A.T / d + 0.1 * np.eye(d), dtype=F64)


@pytest.mark.parametrize("G", GTSAM_GROUPS, ids=lambda G: G.__name__)
def test_gtsam_marginals_map_to_ours(G):
    """A prior on x0 (covariance P0) and a between factor Z (covariance Q): GTSAM's marginal of
    x1 = x0 Z, mapped with covariance_from_gtsam, is our propagation Ad(Z^-1) P0 Ad(Z^-1)^T + Q.
    Full (not diagonal) covariances, so a wrong order fails; NavState's component-wise chart
    agrees with ours to first order, so its marginals map by the permutation too."""
    name = tg.GTSAM_TYPE[G]
    X0, Z = G.exp(_xi(G, seed=13, angles=[2.0])[0]), G.exp(_xi(G, seed=14, angles=[1.2])[0])
    P0, Q = _spd(G.dof, 15), _spd(G.dof, 16)
    noise = lambda P: gtsam.noiseModel.Gaussian.Covariance(tg.covariance_to_gtsam(P, name).numpy())  # noqa: E731
    graph = gtsam.NonlinearFactorGraph()
    graph.add(getattr(gtsam, f"PriorFactor{name}")(0, tg.to_gtsam(X0), noise(P0)))
    graph.add(getattr(gtsam, f"BetweenFactor{name}")(0, 1, tg.to_gtsam(Z), noise(Q)))
    values = gtsam.Values()
    values.insert(0, tg.to_gtsam(X0))
    values.insert(1, tg.to_gtsam(X0 @ Z))
    marginals = gtsam.Marginals(graph, values)
    A = Z.inverse().adjoint()
    expected = A @ P0 @ A.T + Q
    got = tg.covariance_from_gtsam(marginals.marginalCovariance(1), name)
    _close(got, expected, 1e-10 * float(expected.abs().max()))
    _close(tg.covariance_from_gtsam(marginals.marginalCovariance(0), name), P0, 1e-12)
    M = tg.tangent_map(name, F64)
    _close(tg.covariance_to_gtsam(P0, name), M @ P0 @ M.T, 0.0)


def test_gtsam_points_and_batched_tangent_maps():
    p = torch.randn(2, 4, 3, dtype=F64)
    pts = tg.points_to_gtsam(p)
    assert isinstance(pts[1][2], np.ndarray) and pts[1][2].shape == (3,)
    _close(tg.points_from_gtsam(pts), p, 0.0)
    q = torch.randn(5, 2, dtype=F64)
    _close(tg.points_from_gtsam(tg.points_to_gtsam(q)), q, 0.0)
    # batched maps equal the matrix M: xi' = M xi, P' = M P M^T, J' = M_out J M_in^T
    for name, (_, perm) in tg.TYPES.items():
        d = len(perm)
        M = tg.tangent_map(name, F64)
        assert torch.equal(M @ M.T, torch.eye(d, dtype=F64))
        xi = torch.randn(3, d, dtype=F64)
        _close(tg.tangent_to_gtsam(xi, name), xi @ M.T, 0.0)
        _close(tg.tangent_from_gtsam(tg.tangent_to_gtsam(xi, name), name), xi, 0.0)
        P = torch.randn(3, d, d, dtype=F64)
        _close(tg.covariance_from_gtsam(P, name), M.T @ P @ M, 0.0)
        J = torch.randn(3, 3, d, dtype=F64)
        _close(tg.jacobian_to_gtsam(J, output="Point3", input=name), J @ M.T, 0.0)


def test_gtsam_gal3_matches_the_tls_peer_order():
    from torchsgal.estimation import gtsam_peer
    assert tuple(gtsam_peer.PERM) == tg.TYPES["Gal3"][1]


# ------------------------------------------------------------------------------ pypose
def _pp_matrix_ours(G, x):
    """Our matrix of a pypose element: pypose's Sim3 matrix is s times ours."""
    M = x.matrix()
    return M / x.tensor()[..., 7, None, None] if G is ts.Sim3 else M


@pytest.mark.parametrize("array", [np.full(6, 1 + 2j), np.zeros(6, dtype=np.float16), np.array(["a"] * 6),
                                   np.zeros(6, dtype=np.int64), np.zeros(6, dtype=bool)], ids=lambda a: str(a.dtype))
def test_gtsam_arrays_of_other_kinds_are_refused(array):
    """GTSAM's vectors and matrices are float64 arrays (float32 accepted): complex numbers
    (whose imaginary part a cast drops), half precision, strings, integers and booleans are
    refused by name, as tensors of those dtypes are."""
    with pytest.raises(TypeError, match=f"^xi must be a float32 or float64 array or tensor, got a numpy array of dtype {array.dtype}"):
        tg.tangent_from_gtsam(array, "Pose3")
    for name, fn in (("P", tg.covariance_from_gtsam), ("J", lambda a, t: tg.jacobian_from_gtsam(a, output=t, input=t))):
        with pytest.raises(TypeError, match=f"^{name} must be a float32 or float64"):
            fn(np.zeros((6, 6), dtype=array.dtype) if array.dtype.kind != "U" else np.array([["a"] * 6] * 6), "Pose3")
    assert tg.tangent_from_gtsam(np.arange(6, dtype=np.float32), "Pose3").dtype == torch.float64
    # points too (a complex one would lose its imaginary part with only a warning), naming the point;
    # integer points are GTSAM's own (gtsam.Point3 of an integer array returns int64)
    good = np.array([1.0, 2.0, 3.0])
    if array.dtype.kind == "i":
        assert torch.equal(tg.points_from_gtsam([good, gtsam.Point3(np.array([1, 2, 3]))]),
                           torch.tensor([[1.0, 2.0, 3.0]] * 2, dtype=F64))
        return
    with pytest.raises(TypeError, match=f"^points must be float32, float64 or integer arrays, but "
                                        f"point 1 \\(row-major\\) has dtype {array.dtype}"):
        tg.points_from_gtsam([good, array[:3]])
    assert torch.equal(tg.points_from_gtsam([good, good.astype(np.float32)]),
                       torch.tensor([[1.0, 2.0, 3.0]] * 2, dtype=F64))


@pytest.mark.parametrize("G", PYPOSE_GROUPS, ids=lambda G: G.__name__)
def test_pypose_round_trips_and_exp(G):
    xi = _xi(G, seed=20, shape=(2, 3))
    g = G.exp(xi)
    x = tp.to_pypose(g)
    assert x.ltype == getattr(pp, f"{G.__name__}_type") and x.shape[:-1] == (2, 3)
    _close(_pp_matrix_ours(G, x), g.as_matrix(), 1e-14)
    _close(tp.from_pypose(x).as_matrix(), g.as_matrix(), 1e-14)
    # pypose's Exp of the same vector is our exp (the orders agree).  pypose's se3 Exp loses
    # about 2e-17 / theta in the translation at small angles (1.6e-9 at 1e-9, 1.4e-12 at 1e-5
    # against scipy's expm; ours stays within 2e-15 of expm, test_definitions): compared where
    # that is below 1e-13
    big = torch.tensor([a == 0 or a > 1e-3 for a in ANGLES]).reshape(2, 3)
    Exp = tp.tangent_to_pypose(xi[big], G).Exp()
    _close(_pp_matrix_ours(G, Exp), g.as_matrix()[big], 1e-14)
    _close(tp.tangent_from_pypose(tp.tangent_to_pypose(xi, G)), xi, 0.0)
    # peer -> ours -> peer: the same element (the quaternion up to sign)
    y = getattr(pp, f"randn_{G.__name__}")(4, dtype=F64)
    _close(tp.to_pypose(tp.from_pypose(y)).matrix(), y.matrix(), 1e-14)
    # compose and inverse agree
    h = G.exp(_xi(G, seed=21, shape=(2, 3)))
    _close(_pp_matrix_ours(G, x * tp.to_pypose(h)), (g @ h).as_matrix(), 1e-13)
    _close(_pp_matrix_ours(G, x.Inv()), g.inverse().as_matrix(), 1e-13)
    # float32 stays float32, within float32 rounding of the magnitudes
    x32 = tp.to_pypose(g.float())
    assert x32.dtype == torch.float32 and tp.from_pypose(x32).dtype == torch.float32
    scale = float(g.as_matrix().abs().max())
    _close(tp.from_pypose(x32).as_matrix().double(), g.as_matrix(), 1e-6 * scale)


def test_pypose_so3_jr_is_ours():
    # pypose's so3 Jr is the identity below its small-angle threshold (off by |phi|/2 there:
    # 4e-10 at 1e-9), so the angles here are those where it uses its closed form
    phi = _xi(ts.SO3, seed=22, angles=[0.0, 1e-3, 0.7, 2.5, math.pi - 1e-6])
    _close(tp.tangent_to_pypose(phi, ts.SO3).Jr(), ts.SO3.jr(phi), 1e-14)


@pytest.mark.parametrize("G", PYPOSE_GROUPS, ids=lambda G: G.__name__)
def test_pypose_left_perturbation_maps(G):
    """pypose's add_ (its optimisers' update) and autograd gradients use the left perturbation
    Exp(d) X; perturbation_map is d/dd_r of the left d reaching the same element (by torch.func),
    and the covariance and Jacobian maps follow from it."""
    g = G.exp(_xi(G, seed=23, angles=[2.9])[0])
    x = tp.to_pypose(g)
    d = 0.3 * _xi(G, seed=24, angles=[0.4])[0]
    moved = x.clone()
    moved.add_(d)  # pypose's own update
    _close(_pp_matrix_ours(G, moved), g.lplus(d).as_matrix(), 1e-13)
    # the right perturbation reaching exp(d_l) g is Ad(g^-1) d_l, exactly
    A = torch.func.jacfwd(lambda dl: g.lplus(dl).rminus(g))(torch.zeros(G.dof, dtype=F64))
    _close(torch.linalg.inv(A), tp.perturbation_map(g), 1e-12)
    _close(tp.perturbation_map(x), tp.perturbation_map(g), 1e-13)
    P = _spd(G.dof, 25)
    _close(tp.covariance_from_pypose(P, x), A @ P @ A.T, 1e-12)
    _close(tp.covariance_to_pypose(tp.covariance_from_pypose(P, g), g), P, 1e-11)
    # autograd through pypose gives left-perturbation gradients; mapped, they are ours
    p = torch.tensor([0.5, -0.2, 1.0], dtype=F64)
    xr = tp.to_pypose(g).detach().requires_grad_()
    (xr.Act(p) ** 2).sum().backward()
    grad_left = xr.grad[..., :G.dof].reshape(1, G.dof)
    ours = torch.func.jacfwd(lambda dr: (g.rplus(dr).act(p) ** 2).sum())(torch.zeros(G.dof, dtype=F64))
    _close(tp.jacobian_from_pypose(grad_left, output=None, input=x), ours.reshape(1, G.dof), 1e-12)
    _close(tp.jacobian_to_pypose(ours.reshape(1, G.dof), output=None, input=g), grad_left, 1e-12)
    # group-valued output: the inverse map, d(log) left -> right on both sides
    Jr_ours = torch.func.jacfwd(lambda dr: g.rplus(dr).inverse().rminus(g.inverse()))(torch.zeros(G.dof, dtype=F64))
    Jl_pp = torch.func.jacfwd(lambda dl: g.lplus(dl).inverse().lminus(g.inverse()))(torch.zeros(G.dof, dtype=F64))
    _close(tp.jacobian_from_pypose(Jl_pp, output=g.inverse(), input=g), Jr_ours, 1e-12)


def test_pypose_conversions_are_differentiable():
    xi = _xi(ts.SE3, seed=26, angles=[1.3])[0].requires_grad_()
    J = torch.autograd.functional.jacobian(lambda v: tp.from_pypose(tp.to_pypose(ts.SE3.exp(v))).log(), xi)
    _close(J, torch.eye(6, dtype=F64), 1e-12)


# --------------------------------------------------------------------------- quaternions
def test_quaternion_translation_against_scipy_gtsam_and_pypose():
    g = ts.SE3.exp(_xi(ts.SE3, seed=30))
    C, t = g.rotation().numpy(), g.position()
    q_xyzw, t_out = tq.as_quaternion_translation(g, order="xyzw")
    _close(t_out, t, 0.0)
    _close(Rotation.from_quat(q_xyzw.numpy()).as_matrix(), C, 1e-15)
    q_wxyz, _ = tq.as_quaternion_translation(g, order="wxyz")
    _close(q_wxyz.roll(-1, -1), q_xyzw, 0.0)
    for k, (w, x, y, z) in enumerate(q_wxyz.numpy()):
        _close(gtsam.Rot3.Quaternion(w, x, y, z).matrix(), C[k], 1e-15)
    # GTSAM's toQuaternion is (w, x, y, z) up to sign
    for k, o in enumerate(tg.to_gtsam(g)):
        ref = o.rotation().toQuaternion().coeffs()  # Eigen's storage: x, y, z, w
        ref = ref if ref[3] >= 0 else -ref
        _close(q_xyzw[k], ref, 1e-15)
    # 7-vectors: pypose's SE3 storage [t, x, y, z, w], by pypose's own mat2SE3 (q up to sign)
    pose = tq.as_pose7(g, order="xyzw")
    ref = pp.mat2SE3(g.as_matrix(), check=False).tensor().clone()
    ref[:, 3:] *= torch.where(ref[:, 6:] < 0, -1.0, 1.0).to(F64)
    _close(pose, ref, 1e-15)
    for order in ("xyzw", "wxyz"):
        v = tq.as_pose7(g, order=order)
        _close(tq.from_pose7(v, order=order).as_matrix(), g.as_matrix(), 1e-15)
        q, tt = tq.as_quaternion_translation(g, order=order)
        # -q and an unnormalised q give the same pose
        _close(tq.from_quaternion_translation(-3.0 * q, tt, order=order).as_matrix(), g.as_matrix(), 1e-15)
        w = q[..., 0] if order == "wxyz" else q[..., 3]
        assert bool((w >= 0).all())
    v32 = tq.as_pose7(g.float(), order="wxyz")
    assert v32.dtype == torch.float32
    scale = float(g.as_matrix().abs().max())
    _close(tq.from_pose7(v32, order="wxyz").as_matrix().double(), g.as_matrix(), 1e-6 * scale)
    # scipy reads the xyzw pose7 layout (TUM) the same way
    ref = Rotation.from_quat(pose[:, 3:].numpy()).as_matrix()
    _close(tq.from_pose7(pose, order="xyzw").rotation(), ref, 1e-15)


# ------------------------------------------------------------------------------- Euler
SEQUENCES = ["xyz", "xzy", "yxz", "yzx", "zxy", "zyx", "xyx", "xzx", "yxy", "yzy", "zxz", "zyz"]


@pytest.mark.parametrize("frame", ["intrinsic", "extrinsic"])
@pytest.mark.parametrize("seq", SEQUENCES)
def test_euler_against_scipy(seq, frame):
    s = seq.upper() if frame == "intrinsic" else seq
    R = ts.SO3.exp(_xi(ts.SO3, seed=40, angles=ANGLES * 4))
    angles = euler.as_euler(R, sequence=s, frame=frame)
    with warnings.catch_warnings():  # scipy warns of its gimbal lock (middle within 1e-7)
        warnings.simplefilter("ignore", UserWarning)
        ref = Rotation.from_matrix(R.as_matrix().numpy()).as_euler(s)
    # scipy declares gimbal lock within 1e-7 of the singular middle angle, we at 1e-12 (the
    # module docstring): between, the two split the rotation differently, so the angles are
    # compared where the middle one is away from its singular values; the rotation everywhere
    singular = (0.0, math.pi) if seq[0] == seq[2] else (math.pi / 2, -math.pi / 2)
    away = np.all([np.abs(ref[:, 1] - m) > 1e-6 for m in singular], axis=0)
    assert away.sum() >= len(ANGLES) * 2
    _close(angles[torch.from_numpy(away)], ref[away], 1e-12)
    _close(euler.from_euler(angles, sequence=s, frame=frame).as_matrix(), R.as_matrix(), 1e-14)
    a = torch.tensor(np.random.default_rng(41).uniform(-3, 3, (20, 3)), dtype=F64)
    ref_a = Rotation.from_euler(s, a.numpy()).as_matrix()
    _close(euler.from_euler(a, sequence=s, frame=frame).as_matrix(), ref_a, 1e-15)
    # gimbal lock: the third angle is 0, as scipy
    mids = (0.0, math.pi) if seq[0] == seq[2] else (math.pi / 2, -math.pi / 2)
    for m in mids:
        locked = torch.tensor([[0.3, m, 0.5], [-2.9, m, 2.0]], dtype=F64)
        Rl = euler.from_euler(locked, sequence=s, frame=frame)
        got = euler.as_euler(Rl, sequence=s, frame=frame)
        with pytest.warns(UserWarning, match="Gimbal"):
            ref = Rotation.from_matrix(Rl.as_matrix().numpy()).as_euler(s)
        _close(got, ref, 1e-9)
        assert bool((got[:, 2] == 0).all())
        _close(euler.from_euler(got, sequence=s, frame=frame).as_matrix(), Rl.as_matrix(), 1e-14)


def test_euler_against_gtsam_ypr_and_float32():
    a = np.random.default_rng(42).uniform(-1.5, 1.5, (10, 3))
    R = euler.from_euler(torch.tensor(a, dtype=F64), sequence="ZYX", frame="intrinsic")
    for k, (y, p, r) in enumerate(a):
        _close(gtsam.Rot3.Ypr(y, p, r).matrix(), R.as_matrix()[k], 1e-15)
        _close(gtsam.Rot3.RzRyRx(r, p, y).matrix(), R.as_matrix()[k], 1e-15)
    Rx = euler.from_euler(torch.tensor(a[:, ::-1].copy(), dtype=F64), sequence="xyz", frame="extrinsic")
    _close(Rx.as_matrix(), R.as_matrix(), 1e-15)
    ypr = euler.as_euler(R, sequence="ZYX", frame="intrinsic")
    for k, o in enumerate(tg.to_gtsam(R)):
        _close(o.ypr(), ypr[k], 1e-14)
        _close(o.rpy(), ypr[k].flip(-1), 1e-14)
    R32 = R.float()
    a32 = euler.as_euler(R32, sequence="ZYX", frame="intrinsic")
    assert a32.dtype == torch.float32
    _close(a32.double(), ypr, 1e-5)


def test_euler_gradients_match_finite_differences():
    a = torch.tensor([[0.3, -0.4, 1.1], [2.0, 0.2, -2.5]], dtype=F64, requires_grad=True)
    f = lambda x: euler.as_euler(euler.from_euler(x, sequence="zxz", frame="extrinsic"),  # noqa: E731
                                 sequence="yxz", frame="extrinsic")
    assert torch.autograd.gradcheck(f, (a,))
    # at gimbal lock the angles are not differentiable; the gradients stay finite
    for seq, mid in (("zyx", math.pi / 2), ("zxz", 0.0), ("zxz", math.pi)):
        M = euler.from_euler(torch.tensor([0.3, mid, 0.5], dtype=F64), sequence=seq, frame="extrinsic")
        M = M.as_matrix().clone().requires_grad_()
        euler.as_euler(ts.SO3.from_matrix(M), sequence=seq, frame="extrinsic").sum().backward()
        assert bool(M.grad.isfinite().all())


# --------------------------------------------------------------------------- bad input
def test_bad_input_errors():
    g = ts.SE3.identity(dtype=F64)
    with pytest.raises(ValueError, match=r"gtsam_type must be one of .*'Pose4'"):
        tg.tangent_to_gtsam(torch.zeros(6, dtype=F64), "Pose4")
    with pytest.raises(ValueError, match=r"xi must have shape \(\.\.\., 6\), got \(7,\)"):
        tg.tangent_to_gtsam(torch.zeros(7, dtype=F64), "Pose3")
    with pytest.raises(ValueError, match=r"P must have shape \(\.\.\., 9, 9\), got \(6, 6\)"):
        tg.covariance_from_gtsam(np.eye(6), gtsam.NavState)
    with pytest.raises(ValueError, match=r"J must have shape \(\.\.\., 3, 6\), got \(3, 7\)"):
        tg.jacobian_from_gtsam(np.zeros((3, 7)), output="Point3", input="Pose3")
    with pytest.raises(ValueError, match="output must be one of"):
        tg.jacobian_from_gtsam(np.zeros((3, 6)), output="Point4", input="Pose3")
    with pytest.raises(TypeError, match="g must be an element of one of"):
        tg.to_gtsam(torch.eye(4))
    with pytest.raises(TypeError, match=r"element 1 \(row-major\) is Rot3"):
        tg.from_gtsam([gtsam.Pose3(), gtsam.Rot3()])
    with pytest.raises(TypeError, match=r"objects\[0\] must be a gtsam Rot2, .*got Cal3_S2"):
        tg.from_gtsam([gtsam.Cal3_S2()])
    with pytest.raises(TypeError, match="objects are gtsam.Pose3, but group SO3 needs gtsam.Rot3"):
        tg.from_gtsam([gtsam.Pose3()], group=ts.SO3)
    with pytest.raises(ValueError, match="objects is empty: pass group="):
        tg.from_gtsam([])
    assert tg.from_gtsam([], group=ts.SE3).batch_shape == (0,)
    with pytest.raises(ValueError, match="objects must be rectangular"):
        tg.from_gtsam([[gtsam.Pose3()], []])
    with pytest.raises(TypeError, match="dtype must be torch.float32 or torch.float64"):
        tg.from_gtsam(gtsam.Pose3(), dtype=torch.int64)
    with pytest.raises(ValueError, match=r"p must have shape \(\.\.\., 3\) or \(\.\.\., 2\), got \(4,\)"):
        tg.points_to_gtsam(torch.zeros(4))
    with pytest.raises(ValueError, match="v must have shape"):
        tg.navstate_local_to_tangent(torch.zeros(6, dtype=F64))
    # pypose
    with pytest.raises(TypeError, match="g must be an element of SO3, SE3 or Sim3, got SE23"):
        tp.to_pypose(ts.SE23.identity())
    with pytest.raises(TypeError, match="x must be a pypose LieTensor of type SO3/SE3/Sim3, got Tensor"):
        tp.from_pypose(torch.zeros(7))
    with pytest.raises(TypeError, match="got one of type so3"):
        tp.from_pypose(pp.so3(torch.zeros(3)))
    with pytest.raises(TypeError, match="group must be SO3, SE3 or Sim3"):
        tp.tangent_to_pypose(torch.zeros(9), ts.SE23)
    with pytest.raises(ValueError, match=r"P must have shape \(\.\.\., 6, 6\), got \(7, 7\)"):
        tp.covariance_from_pypose(torch.eye(7, dtype=F64), g)
    with pytest.raises(ValueError, match=r"J must have shape \(\.\.\., m, 6\), got \(2, 7\)"):
        tp.jacobian_from_pypose(torch.zeros(2, 7, dtype=F64), output=None, input=g)
    # quaternions
    with pytest.raises(ValueError, match="order must be 'wxyz'"):
        tq.from_pose7(torch.zeros(7), order="wxzy")
    with pytest.raises(TypeError, match="order"):
        tq.as_pose7(g)  # the order is never guessed
    with pytest.raises(ValueError, match=r"pose must have shape \(\.\.\., 7\), got \(6,\)"):
        tq.from_pose7(torch.zeros(6), order="xyzw")
    with pytest.raises(ValueError, match=r"t must have shape \(\.\.\., 3\), got \(2,\)"):
        tq.from_quaternion_translation(torch.tensor([1.0, 0, 0, 0]), torch.zeros(2), order="wxyz")
    with pytest.raises(TypeError, match="g must be an SE3, got SO3"):
        tq.as_quaternion_translation(ts.SO3.identity(), order="wxyz")
    # Euler
    with pytest.raises(ValueError, match="sequence must be three of the letters x, y, z"):
        euler.from_euler(torch.zeros(3), sequence="abc", frame="intrinsic")
    with pytest.raises(ValueError, match="sequence must be three of the letters"):
        euler.from_euler(torch.zeros(3), sequence="ZyX", frame="intrinsic")
    with pytest.raises(ValueError, match="must not repeat an axis"):
        euler.from_euler(torch.zeros(3), sequence="zzx", frame="extrinsic")
    with pytest.raises(ValueError, match="write 'zyx' for extrinsic"):
        euler.from_euler(torch.zeros(3), sequence="ZYX", frame="extrinsic")
    with pytest.raises(ValueError, match="frame must be 'intrinsic' or 'extrinsic', got 'body'"):
        euler.as_euler(ts.SO3.identity(), sequence="zyx", frame="body")
    with pytest.raises(TypeError, match="frame"):
        euler.from_euler(torch.zeros(3), sequence="zyx")  # no default frame
    with pytest.raises(ValueError, match=r"angles must have shape \(\.\.\., 3\), got \(2,\)"):
        euler.from_euler(torch.zeros(2), sequence="zyx", frame="extrinsic")
    with pytest.raises(TypeError, match="rotation must be an SO3, got SE3"):
        euler.as_euler(g, sequence="zyx", frame="extrinsic")


def test_missing_peer_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "gtsam", None)  # import gtsam now raises ImportError
    monkeypatch.setitem(sys.modules, "pypose", None)
    with pytest.raises(ImportError, match=r"pip install 'torchsgal\[peers\]'"):
        tg.to_gtsam(ts.SE3.identity())
    with pytest.raises(ImportError, match=r"torchsgal.interop.pypose needs .*'pypose'"):
        tp.to_pypose(ts.SE3.identity())
    # what needs no peer still works, and the maps need none
    assert tg.tangent_map("Pose3").shape == (6, 6)
    assert euler.from_euler(torch.zeros(3), sequence="zyx", frame="extrinsic").batch_shape == ()


def test_import_does_not_import_the_peers():
    code = ("import sys, torchsgal, torchsgal.interop; "
            "print(sorted(m for m in ('gtsam', 'pypose') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_guide_examples_run():
    """The code blocks of docs/guide/interop.md, run in order in one namespace (each asserts
    what it shows)."""
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "docs" / "guide" / "interop.md").read_text()
    blocks = [b.split("```", 1)[0] for b in text.split("```python\n")[1:]]
    assert len(blocks) >= 6
    namespace: dict = {}
    torch.manual_seed(0)
    for i, code in enumerate(blocks):
        exec(compile(code, f"interop.md block {i}", "exec"), namespace)  # noqa: S102


def test_tensor_converters_are_device_generic():
    """The tensor-only converters on 'meta' (no data: an operation that mixes in a CPU constant
    or reads values raises there, as it would cost a copy or a sync on CUDA)."""
    meta = torch.device("meta")
    R = ts.SO3.identity((4, 2), dtype=torch.float32, device=meta)
    a = euler.as_euler(R, sequence="zxz", frame="extrinsic")
    assert a.shape == (4, 2, 3) and a.device == meta and a.dtype == torch.float32
    assert euler.from_euler(a, sequence="ZYX", frame="intrinsic").as_matrix().device == meta
    g = ts.SE3.identity(3, dtype=torch.float32, device=meta)
    v = tq.as_pose7(g, order="wxyz")
    assert v.shape == (3, 7) and v.device == meta
    assert tq.from_pose7(v, order="wxyz").as_matrix().device == meta
    xi = torch.empty(3, 9, device=meta)
    for out in (tg.tangent_to_gtsam(xi, "NavState"), tg.navstate_local_to_tangent(xi),
                tg.tangent_to_navstate_local(xi)):
        assert out.shape == (3, 9) and out.device == meta
    P = torch.empty(3, 10, 10, device=meta)
    assert tg.covariance_from_gtsam(P, "Gal3").device == meta
    J = torch.empty(3, 3, 10, device=meta)
    assert tg.jacobian_to_gtsam(J, output=None, input="Gal3").shape == (3, 3, 10)
    assert tp.covariance_from_pypose(torch.empty(3, 6, 6, device=meta), g).device == meta
    assert tg.tangent_map("Pose3", torch.float32, meta).device == meta


def test_pypose_jacobian_names_elements_of_other_batches():
    """output (3,) and input (2,): each broadcasts with J, not with each other (a raw torch error
    in the product before)."""
    with pytest.raises(ValueError, match=r"batch shapes do not broadcast: J \(\), output \(3,\), input \(2,\)"):
        tp.jacobian_from_pypose(torch.zeros(6, 6, dtype=F64), output=ts.SE3.random(3, dtype=F64),
                                input=ts.SE3.random(2, dtype=F64))
