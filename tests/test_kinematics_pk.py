"""pytorch_kinematics (pk) as an independent peer for the DH / GDH chain kinematics.

First the peer itself is validated: ``build_pk_chain`` against an explicit product of standard
DH matrices, and pk's geometric Jacobian against central finite differences of that FK.  Then
``torchsgal.kinematics.GDHChain`` is compared against the validated peer.
"""
import math

import pytest
import torch

pk = pytest.importorskip("pytorch_kinematics")

import torchsgal  # noqa: E402
from torchsgal.kinematics.pk_interop import (  # noqa: E402
    build_pk_chain,
    from_transform3d,
    to_transform3d,
)

DT = torch.float64
PI = math.pi

# name -> (a, alpha, d, theta_offset, joint_types)
ROBOTS = {
    # SCARA as in Fig. 4 of Mahony-Kelly-Weiss: R R P R; alpha_2 = pi flips z down so the
    # prismatic joint 3 moves the tool along -z of the base.
    "scara": (
        [0.4, 0.3, 0.0, 0.0],
        [0.0, PI, 0.0, 0.0],
        [0.5, 0.0, 0.0, 0.1],
        [0.0, 0.0, 0.0, 0.0],
        ("revolute", "revolute", "prismatic", "revolute"),
    ),
    # Universal Robots UR5, standard DH.
    "ur5": (
        [0.0, -0.425, -0.39225, 0.0, 0.0, 0.0],
        [PI / 2, 0.0, 0.0, PI / 2, -PI / 2, 0.0],
        [0.089159, 0.0, 0.0, 0.10915, 0.09465, 0.0823],
        [0.0] * 6,
        ("revolute",) * 6,
    ),
    # KUKA LBR iiwa 14 R820, standard DH.
    "iiwa7": (
        [0.0] * 7,
        [-PI / 2, PI / 2, PI / 2, -PI / 2, -PI / 2, PI / 2, 0.0],
        [0.36, 0.0, 0.42, 0.0, 0.4, 0.0, 0.126],
        [0.0] * 7,
        ("revolute",) * 7,
    ),
}
NAMES = list(ROBOTS)


# ----------------------------------------------------------------------------- reference
def dh_matrix(theta, d, a, alpha):
    """Classical DH link transform Rz(theta) Tz(d) Tx(a) Rx(alpha); all args (...,)."""
    c, s = torch.cos(theta), torch.sin(theta)
    ca, sa = torch.cos(alpha), torch.sin(alpha)
    zero, one = torch.zeros_like(c), torch.ones_like(c)
    rows = [
        [c, -s * ca, s * sa, a * c],
        [s, c * ca, -c * sa, a * s],
        [zero, sa, ca, d],
        [zero, zero, zero, one],
    ]
    return torch.stack([torch.stack(r, dim=-1) for r in rows], dim=-2)


def dh_fk(table, q, all_frames=False):
    """Product T_1 ... T_n for q (B, n); with all_frames the list [0T_1, ..., 0T_n]."""
    a, alpha, d, th0, types = table
    B = q.shape[0]
    T = torch.eye(4, dtype=q.dtype).expand(B, 4, 4)
    out = []
    for i, jt in enumerate(types):
        full = lambda v: torch.full((B,), float(v), dtype=q.dtype)  # noqa: E731
        theta = full(th0[i]) + (q[:, i] if jt == "revolute" else 0.0)
        di = full(d[i]) + (q[:, i] if jt == "prismatic" else 0.0)
        T = T @ dh_matrix(theta, di, full(a[i]), full(alpha[i]))
        out.append(T)
    return out if all_frames else T


def random_q(n, B=50, seed=0):
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(B, n, generator=g, dtype=DT) * 2 - 1) * PI


def vee(W):
    return torch.stack([W[..., 2, 1] - W[..., 1, 2], W[..., 0, 2] - W[..., 2, 0],
                        W[..., 1, 0] - W[..., 0, 1]], dim=-1) / 2


def fd(f, q, qd, h=1e-4):
    """d/dt f(q + t qd) at t = 0: fourth-order central difference (error ~ h^4)."""
    d1 = f(q + h * qd) - f(q - h * qd)
    d2 = f(q + 2 * h * qd) - f(q - 2 * h * qd)
    return (8 * d1 - d2) / (12 * h)


def fd_twist(fk, q, qd):
    """Base-frame (v, omega) of the FK pose along q + t qd, by central differences."""
    Tdot, T0 = fd(fk, q, qd), fk(q)
    return Tdot[:, :3, 3], vee(Tdot[:, :3, :3] @ T0[:, :3, :3].transpose(-1, -2))


def pk_fk(chain, q):
    return chain.forward_kinematics(q).get_matrix()


# ----------------------------------------------------------------------------- the peer
@pytest.mark.parametrize("name", NAMES)
def test_pk_chain_matches_dh_product(name):
    table = ROBOTS[name]
    chain = build_pk_chain(*table)
    assert chain.dtype == DT and chain.n_joints == len(table[4])
    q = random_q(len(table[4]), seed=1)
    got = pk_fk(chain, q)
    assert got.dtype == DT
    torch.testing.assert_close(got, dh_fk(table, q), atol=1e-12, rtol=0)
    # every intermediate DH frame i is pk's "frame_i"
    frames = chain.forward_kinematics(q, end_only=False)
    for i, Ti in enumerate(dh_fk(table, q, all_frames=True)):
        torch.testing.assert_close(frames[f"frame_{i + 1}"].get_matrix(), Ti, atol=1e-12, rtol=0)


def test_pk_chain_random_tables_with_offsets():
    """Random tables, mixed joint types and non-zero theta/d offsets on every joint."""
    g = torch.Generator().manual_seed(7)
    for trial in range(10):
        n = 1 + trial % 7
        a, alpha, d, th0 = (torch.randn(n, generator=g, dtype=DT) for _ in range(4))
        types = tuple("prismatic" if b else "revolute"
                      for b in (torch.rand(n, generator=g) < 0.4).tolist())
        table = (a, alpha, d, th0, types)
        chain = build_pk_chain(*table)
        q = torch.randn(20, n, generator=g, dtype=DT)
        torch.testing.assert_close(pk_fk(chain, q), dh_fk(table, q), atol=1e-12, rtol=0)
        # q = 0 is the DH table itself
        z = torch.zeros(1, n, dtype=DT)
        torch.testing.assert_close(pk_fk(chain, z), dh_fk(table, z), atol=1e-12, rtol=0)


def test_pk_chain_unbatched_and_errors():
    chain = build_pk_chain(*ROBOTS["scara"])
    q = random_q(4, B=1, seed=3)
    torch.testing.assert_close(pk_fk(chain, q[0]), dh_fk(ROBOTS["scara"], q), atol=1e-12, rtol=0)
    with pytest.raises(ValueError, match=r"joint_types\[0\] must be 'revolute'/'R' or 'prismatic'/'P', got 'spherical'"):
        build_pk_chain([0.0], [0.0], [0.0], [0.0], ["spherical"])
    with pytest.raises(ValueError, match=r"DH table lengths differ: a 2, alpha 1, d 1, theta_offset 1, joint_types 1"):
        build_pk_chain([0.0, 1.0], [0.0], [0.0], [0.0], ["revolute"])


@pytest.mark.parametrize("name", NAMES)
def test_pk_jacobian_is_base_frame_v_omega(name):
    """pk's jacobian(q) @ qd == [v; omega] of the end effector, both in the base frame."""
    table = ROBOTS[name]
    chain = build_pk_chain(*table)
    n = len(table[4])
    q, qd = random_q(n, seed=2), random_q(n, seed=3)
    J = chain.jacobian(q)
    assert J.shape == (q.shape[0], 6, n) and J.dtype == DT
    twist = (J @ qd.unsqueeze(-1)).squeeze(-1)
    v, w = fd_twist(lambda x: dh_fk(table, x), q, qd)
    # fourth-order difference, h = 1e-4: measured 7.1e-12 (40 seeds: 7.8e-12)
    torch.testing.assert_close(twist[:, :3], v, atol=1e-10, rtol=0)
    torch.testing.assert_close(twist[:, 3:], w, atol=1e-10, rtol=0)
    # the angular part is the spatial (base-frame) angular velocity, not the body one
    R = dh_fk(table, q)[:, :3, :3]
    w_body = (R.transpose(-1, -2) @ w.unsqueeze(-1)).squeeze(-1)
    if name != "scara":  # SCARA: every revolute axis is +-z of the base, so body = spatial z
        assert (twist[:, 3:] - w_body).abs().max() > 1e-3


@pytest.mark.parametrize("group", ["SE3", "SE23"])
def test_transform3d_round_trip(group):
    G = getattr(torchsgal, group)
    x = G.random((4, 3), dtype=DT, generator=torch.Generator().manual_seed(5))
    t = to_transform3d(x)
    assert isinstance(t, pk.Transform3d)
    m = t.get_matrix()
    assert m.shape == (12, 4, 4) and m.dtype == DT
    torch.testing.assert_close(m[:, :3, :3], x.rotation().reshape(12, 3, 3), atol=0, rtol=0)
    torch.testing.assert_close(m[:, :3, 3], x.position().reshape(12, 3), atol=0, rtol=0)
    torch.testing.assert_close(m[:, 3], torch.tensor([0.0, 0, 0, 1], dtype=DT).expand(12, 4))
    if group == "SE3":
        y = from_transform3d(t, batch_shape=(4, 3))
        assert isinstance(y, torchsgal.SE3)
    else:
        y = from_transform3d(t, velocity=x.velocity(), batch_shape=(4, 3))
        assert isinstance(y, torchsgal.SE23)
    assert y.batch_shape == x.batch_shape
    torch.testing.assert_close(y.as_matrix(), x.as_matrix(), atol=0, rtol=0)
    # flat batch without batch_shape, and back again through pk
    flat = from_transform3d(t)
    assert isinstance(flat, torchsgal.SE3) and flat.batch_shape == (12,)
    torch.testing.assert_close(to_transform3d(flat).get_matrix(), m, atol=0, rtol=0)
    # a single element
    single = to_transform3d(x[0, 0])
    assert single.get_matrix().shape == (1, 4, 4)


def test_from_transform3d_velocity_broadcast_and_tensor_input():
    chain = build_pk_chain(*ROBOTS["ur5"])
    q = random_q(6, B=8, seed=4)
    t = chain.forward_kinematics(q)
    v = torch.tensor([1.0, 2.0, 3.0], dtype=DT)
    y = from_transform3d(t, velocity=v)
    assert isinstance(y, torchsgal.SE23) and y.batch_shape == (8,)
    torch.testing.assert_close(y.velocity(), v.expand(8, 3))
    torch.testing.assert_close(y.position(), t.get_matrix()[:, :3, 3])
    z = from_transform3d(t.get_matrix())
    torch.testing.assert_close(z.as_matrix(), t.get_matrix())
    with pytest.raises(TypeError, match="x must be a torchsgal SE3 or SE23, got SO3"):
        to_transform3d(torchsgal.SO3.identity(dtype=DT))



def test_from_transform3d_and_build_pk_chain_check_their_arguments():
    gen = torch.Generator().manual_seed(6)
    x = torchsgal.SE3.random((6,), dtype=DT, generator=gen)
    t = to_transform3d(x)
    not_rigid = torch.randn(3, 4, 4, dtype=DT, generator=gen)
    assert isinstance(from_transform3d(not_rigid), torchsgal.SE3)  # taken as it is by default
    with pytest.raises(ValueError, match=r"t \(check=True\): matrix is not in SE3"):
        from_transform3d(not_rigid, check=True)
    with pytest.raises(ValueError, match=r"t \(check=True\): matrix is not in SE3"):
        from_transform3d(not_rigid, velocity=torch.zeros(3, dtype=DT), check=True)
    checked = from_transform3d(t, batch_shape=(2, 3), check=True)
    torch.testing.assert_close(checked.as_matrix(), x.as_matrix().reshape(2, 3, 4, 4), atol=0, rtol=0)
    with pytest.raises(ValueError, match=r"batch_shape \(4,\) does not fit the 6 poses of t"):
        from_transform3d(t, batch_shape=(4,))
    with pytest.raises(TypeError, match="batch_shape must be a tuple of ints"):
        from_transform3d(t, batch_shape="ab")
    assert from_transform3d(t, batch_shape=6).batch_shape == (6,)  # an int is a 1-D shape
    with pytest.raises(TypeError, match="t must have a floating dtype"):
        from_transform3d(x.as_matrix().int())
    with pytest.raises(ValueError, match=r"t must have shape \(\.\.\., 4, 4\), got \(6, 3, 3\)"):
        from_transform3d(x.rotation())
    with pytest.raises(TypeError, match="t must be a pytorch_kinematics Transform3d or"):
        from_transform3d(3)
    for dtype in (torch.int64, torch.float16):
        with pytest.raises(TypeError, match=f"dtype must be torch.float32 or torch.float64, got {dtype}"):
            build_pk_chain(*ROBOTS["scara"][:5], dtype=dtype)

# ----------------------------------------------------------------------------- GDHChain
def _kin():
    from torchsgal import kinematics  # an import failure fails these tests, never skips them

    return kinematics


def _check_against_pk(gdh, pkc, q, qd, tol=3e-14):
    # Both sides are float64 products of the same DH matrices: measured worst 2.7e-15 over the
    # inputs of the tests below (7.1e-15 over 40 other seeds).
    n = q.shape[-1]
    state = gdh.forward(q, qd)
    qf, qdf = q.reshape(-1, n), qd.reshape(-1, n)
    T = pk_fk(pkc, qf).reshape(*q.shape[:-1], 4, 4)
    twist = (pkc.jacobian(qf) @ qdf.unsqueeze(-1)).squeeze(-1).reshape(*q.shape[:-1], 6)
    torch.testing.assert_close(state.pose, T, atol=tol, rtol=0)
    torch.testing.assert_close(state.linear_velocity, twist[..., :3], atol=tol, rtol=0)
    torch.testing.assert_close(state.angular_velocity, twist[..., 3:], atol=tol, rtol=0)
    # the SE23 end effector carries the same pose
    ee = state.end_effector
    assert isinstance(ee, torchsgal.SE23) and ee.batch_shape == q.shape[:-1]
    torch.testing.assert_close(ee.rotation(), T[..., :3, :3], atol=tol, rtol=0)
    torch.testing.assert_close(ee.position(), T[..., :3, 3], atol=tol, rtol=0)
    # every GDH frame 0K_i against pk's frame_i.  The velocity column of the product (45) is
    # not dp_i/dt but sum_{j<=i} R_(0,j-1) (44)_j, each link's coordinate velocity rotated
    # into the base (no transport of outer links by inner rotations); rebuilt here from pk's
    # frame rotations and the DH table.
    frames = state.frames
    assert isinstance(frames, torchsgal.SE23) and frames.batch_shape == (*q.shape[:-1], n)
    allf = pkc.forward_kinematics(qf, end_only=False)
    a, th0 = gdh.a.to(DT), gdh.theta_offset.to(DT)
    R_prev = torch.eye(3, dtype=DT).expand(qf.shape[0], 3, 3)
    vsum = torch.zeros(qf.shape[0], 3, dtype=DT)
    for i, jt in enumerate(gdh.joint_types):
        rev = jt == "revolute"
        theta = th0[i] + (qf[:, i] if rev else 0.0)
        thdot = qdf[:, i] if rev else torch.zeros_like(qdf[:, i])
        ddot = torch.zeros_like(qdf[:, i]) if rev else qdf[:, i]
        pdot = torch.stack((-a[i] * torch.sin(theta) * thdot, a[i] * torch.cos(theta) * thdot,
                            ddot), dim=-1)
        vsum = vsum + (R_prev @ pdot.unsqueeze(-1)).squeeze(-1)
        Ti = allf[f"frame_{i + 1}"].get_matrix()
        R_prev = Ti[:, :3, :3]
        shp = q.shape[:-1]
        torch.testing.assert_close(frames.rotation()[..., i, :, :],
                                   Ti[:, :3, :3].reshape(*shp, 3, 3), atol=tol, rtol=0)
        torch.testing.assert_close(frames.position()[..., i, :], Ti[:, :3, 3].reshape(*shp, 3),
                                   atol=tol, rtol=0)
        torch.testing.assert_close(frames.velocity()[..., i, :], vsum.reshape(*shp, 3),
                                   atol=tol, rtol=0)
    torch.testing.assert_close(ee.velocity(), vsum.reshape(*q.shape[:-1], 3), atol=tol, rtol=0)
    return state


@pytest.mark.parametrize("name", NAMES)
def test_gdh_chain_matches_pk(name):
    kin = _kin()
    table = ROBOTS[name]
    gdh = kin.GDHChain(*table)
    assert gdh.n_joints == len(table[4]) and tuple(gdh.joint_types) == table[4]
    pkc = build_pk_chain(*table)
    n = gdh.n_joints
    _check_against_pk(gdh, pkc, random_q(n, seed=10), random_q(n, seed=11))
    # extra batch dimensions
    _check_against_pk(gdh, pkc, random_q(n, B=12, seed=12).reshape(3, 4, n),
                      random_q(n, B=12, seed=13).reshape(3, 4, n))


@pytest.mark.parametrize("factory", ["scara", "ur5", "iiwa7"])
def test_gdh_robot_factories_match_pk(factory):
    """Each factory robot against a pk chain built from the GDHChain's own DH table."""
    kin = _kin()
    gdh = getattr(kin, factory)()
    n = gdh.n_joints
    for attr in ("a", "alpha", "d", "theta_offset"):
        assert getattr(gdh, attr).shape == (n,)
    pkc = build_pk_chain(gdh.a, gdh.alpha, gdh.d, gdh.theta_offset, gdh.joint_types)
    _check_against_pk(gdh, pkc, random_q(n, seed=20), random_q(n, seed=21))


@pytest.mark.parametrize("factory", ["ur5", "iiwa7"])
def test_gdh_robot_factories_are_standard_dh(factory):
    kin = _kin()
    gdh = getattr(kin, factory)()
    a, alpha, d, th0, types = ROBOTS[factory]
    for attr, want in (("a", a), ("alpha", alpha), ("d", d)):
        torch.testing.assert_close(getattr(gdh, attr).to(DT), torch.tensor(want, dtype=DT),
                                   atol=1e-12, rtol=0)
    assert tuple(gdh.joint_types) == types


def test_gdh_random_tables_match_pk():
    kin = _kin()
    g = torch.Generator().manual_seed(30)
    for trial in range(6):
        n = 1 + trial
        a, alpha, d, th0 = ([float(v) for v in torch.randn(n, generator=g, dtype=DT)]
                            for _ in range(4))
        types = tuple("prismatic" if b else "revolute"
                      for b in (torch.rand(n, generator=g) < 0.4).tolist())
        gdh = kin.GDHChain(a, alpha, d, th0, types)
        pkc = build_pk_chain(a, alpha, d, th0, types)
        q = torch.randn(20, n, generator=g, dtype=DT)
        qd = torch.randn(20, n, generator=g, dtype=DT)
        _check_against_pk(gdh, pkc, q, qd)


@pytest.mark.parametrize("name", NAMES)
def test_gdh_acceleration_matches_pk_jacobian_derivative(name):
    """acceleration(q, qd, qdd) = J qdd + (dJ/dt) qd, dJ/dt by central differences of pk's J."""
    kin = _kin()
    table = ROBOTS[name]
    gdh = kin.GDHChain(*table)
    pkc = build_pk_chain(*table)
    n = gdh.n_joints
    q, qd, qdd = random_q(n, seed=40), random_q(n, seed=41), random_q(n, seed=42)
    Jdot = fd(pkc.jacobian, q, qd)
    acc = (pkc.jacobian(q) @ qdd.unsqueeze(-1) + Jdot @ qd.unsqueeze(-1)).squeeze(-1)
    lin, ang = gdh.acceleration(q, qd, qdd)
    # dJ/dt by a fourth-order difference: measured worst 1.7e-11 (40 seeds: 2.8e-11)
    torch.testing.assert_close(lin, acc[:, :3], atol=2e-10, rtol=0)
    torch.testing.assert_close(ang, acc[:, 3:], atol=2e-10, rtol=0)


def test_build_pk_chain_table_must_be_finite_and_joint_types_hint():
    scara = ROBOTS["scara"]
    for i, name in enumerate(("a", "alpha", "d", "theta_offset")):
        for bad in (math.nan, math.inf):
            table = list(scara)
            table[i] = [bad] + list(table[i][1:])
            with pytest.raises(ValueError, match=rf"{name} \(a DH table column\) must be finite"):
                build_pk_chain(*table)
    with pytest.raises(ValueError, match=r"d \(a DH table column\) must be finite"):
        build_pk_chain([0.0], [0.0], torch.tensor([math.nan], dtype=DT), [0.0], "R")
    hint = (r"joint_types 'revolute' is read letter by letter, one 'R' or 'P' per joint, "
            r"e\.g\. 'RRP'")
    with pytest.raises(ValueError, match=r"joint_types 8 \(" + hint):
        build_pk_chain([0.0], [0.0], [0.0], [0.0], "revolute")
    with pytest.raises(ValueError, match=r"joint_types\[1\] must be .* got 'e' \(" + hint):
        build_pk_chain(*([[0.0] * 8] * 4), "revolute")
