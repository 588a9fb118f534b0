"""KinematicChain from URDF, DH tables and pytorch-kinematics, against Pinocchio, pk, autograd.

Pinocchio (``pin``) reads the same URDF files of example-robot-data independently; its
Jacobians and velocities are compared in its three reference frames (LOCAL_WORLD_ALIGNED =
the chain's "base", LOCAL = "body", WORLD = "spatial"), rows [linear, angular] as ours.
Continuous joints are (cos q, sin q) in Pinocchio's configuration vector.
"""
import math
from pathlib import Path

import numpy as np
import pytest
import torch

import torchsgal
from torchsgal.kinematics import GDHChain, KinematicChain, from_pk, from_urdf, iiwa7, load_robot, robot_urdf, scara, ur5

pin = pytest.importorskip("pinocchio")
pk = pytest.importorskip("pytorch_kinematics")

F64 = torch.float64
TOL = 1e-12
# (robot, end link): revolute arms, a prismatic finger, continuous joints, a 7-dof xArm
CASES = [("panda", "panda_hand_tcp"), ("panda", "panda_leftfinger"), ("ur5", "tool0"),
         ("kinova", "j2s6s200_end_effector"), ("xarm7", "link_eef")]


class PinRobot:
    """Pinocchio's model of a URDF and the map from the chain's joints to its q and v."""

    def __init__(self, chain: KinematicChain, path: Path):
        self.model = pin.buildModelFromUrdf(str(path))
        self.data = self.model.createData()
        self.joints = [self.model.joints[self.model.getJointId(n)] for n in chain.joint_names]
        self.continuous = [j.kind == "continuous" for j in chain.joints]

    def q(self, q):
        out = pin.neutral(self.model)
        for jm, cont, x in zip(self.joints, self.continuous, q):
            if cont:
                out[jm.idx_q:jm.idx_q + 2] = (math.cos(x), math.sin(x))
            else:
                out[jm.idx_q] = x
        return out

    def v(self, v):
        out = np.zeros(self.model.nv)
        for jm, x in zip(self.joints, v):
            out[jm.idx_v] = x
        return out

    def cols(self):
        return [jm.idx_v for jm in self.joints]


def _random(chain, n, seed):
    g = torch.Generator().manual_seed(seed)
    q = chain.random_configuration((n,), generator=g)
    qd = torch.randn(n, chain.n_joints, generator=g, dtype=F64)
    qdd = torch.randn(n, chain.n_joints, generator=g, dtype=F64)
    return q, qd, qdd


@pytest.mark.parametrize("robot,end", CASES)
def test_against_pinocchio(robot, end):
    chain = load_robot(robot, end)
    ref = PinRobot(chain, robot_urdf(robot))
    fid = ref.model.getFrameId(end)
    q, qd, qdd = _random(chain, 6, 0)
    st = chain.forward(q, qd, qdd)
    J = {f: chain.jacobian(q, frame=f) for f in ("base", "body", "spatial")}
    dJ = {f: chain.jacobian_derivative(q, qd, frame=f) for f in ("base", "body", "spatial")}
    frames = {"base": pin.LOCAL_WORLD_ALIGNED, "body": pin.LOCAL, "spatial": pin.WORLD}
    m, d = ref.model, ref.data
    for b in range(q.shape[0]):
        qp, vp, ap = ref.q(q[b].tolist()), ref.v(qd[b].tolist()), ref.v(qdd[b].tolist())
        pin.forwardKinematics(m, d, qp, vp, ap)
        pin.updateFramePlacements(m, d)
        M = d.oMf[fid]
        np.testing.assert_allclose(st.pose.rotation()[b].numpy(), M.rotation, atol=TOL, rtol=0)
        np.testing.assert_allclose(st.pose.position()[b].numpy(), M.translation, atol=TOL, rtol=0)
        lwa = pin.getFrameVelocity(m, d, fid, pin.LOCAL_WORLD_ALIGNED)
        np.testing.assert_allclose(st.linear_velocity[b].numpy(), lwa.linear, atol=TOL, rtol=0)
        np.testing.assert_allclose(st.angular_velocity[b].numpy(), lwa.angular, atol=TOL, rtol=0)
        np.testing.assert_allclose(st.body_velocity[b].numpy(),
                                   pin.getFrameVelocity(m, d, fid, pin.LOCAL).vector, atol=TOL, rtol=0)
        np.testing.assert_allclose(st.spatial_velocity[b].numpy(),
                                   pin.getFrameVelocity(m, d, fid, pin.WORLD).vector, atol=TOL, rtol=0)
        acc = pin.getFrameClassicalAcceleration(m, d, fid, pin.LOCAL_WORLD_ALIGNED)
        np.testing.assert_allclose(st.linear_acceleration[b].numpy(), acc.linear, atol=TOL, rtol=0)
        np.testing.assert_allclose(st.angular_acceleration[b].numpy(), acc.angular, atol=TOL, rtol=0)
        np.testing.assert_allclose(st.body_acceleration[b].numpy(),
                                   pin.getFrameAcceleration(m, d, fid, pin.LOCAL).vector,
                                   atol=TOL, rtol=0)
        pin.computeJointJacobians(m, d, qp)
        pin.computeJointJacobiansTimeVariation(m, d, qp, vp)
        for f, pf in frames.items():
            Jp = pin.computeFrameJacobian(m, d, qp, fid, pf)[:, ref.cols()]
            np.testing.assert_allclose(J[f][b].numpy(), Jp, atol=TOL, rtol=0, err_msg=f)
            dJp = pin.getFrameJacobianTimeVariation(m, d, fid, pf)[:, ref.cols()]
            np.testing.assert_allclose(dJ[f][b].numpy(), dJp, atol=TOL, rtol=0, err_msg=f)


def test_all_links_against_pinocchio():
    chain = load_robot("panda")
    ref = PinRobot(chain, robot_urdf("panda"))
    q, qd, qdd = _random(chain, 3, 1)
    st = chain.forward(q, qd, qdd, all_links=True)
    assert st.pose.batch_shape == (3, len(chain.link_names))
    for b in range(3):
        pin.forwardKinematics(ref.model, ref.data, ref.q(q[b].tolist()), ref.v(qd[b].tolist()),
                              ref.v(qdd[b].tolist()))
        pin.updateFramePlacements(ref.model, ref.data)
        for k, name in enumerate(chain.link_names):
            fid = ref.model.getFrameId(name)
            M = ref.data.oMf[fid]
            np.testing.assert_allclose(st.pose.as_matrix()[b, k].numpy(), M.homogeneous,
                                       atol=TOL, rtol=0, err_msg=name)
            acc = pin.getFrameClassicalAcceleration(ref.model, ref.data, fid,
                                                    pin.LOCAL_WORLD_ALIGNED)
            np.testing.assert_allclose(st.linear_acceleration[b, k].numpy(), acc.linear,
                                       atol=TOL, rtol=0, err_msg=name)
            vel = pin.getFrameVelocity(ref.model, ref.data, fid, pin.LOCAL_WORLD_ALIGNED)
            np.testing.assert_allclose(st.linear_velocity[b, k].numpy(), vel.linear,
                                       atol=TOL, rtol=0, err_msg=name)
    # a subset in the order asked, and a link's Jacobian has zero columns after it
    sub = chain.forward(q, qd, links=["panda_link3", "panda_link0"])
    torch.testing.assert_close(sub.pose.as_matrix(), st.pose.as_matrix()[:, [3, 0]], rtol=0, atol=0)
    J3 = chain.jacobian(q, link="panda_link3")
    assert torch.equal(J3[..., 3:], torch.zeros_like(J3[..., 3:]))


def test_accelerations_against_jvp():
    """d/dt of (dp/dt, w) along (qdot, qddot) by forward-mode autograd, and dJ/dt."""
    chain = load_robot("panda", "panda_leftfinger")  # 7 revolute + 1 prismatic joint
    q, qd, qdd = _random(chain, 5, 2)

    def vel(q_, qd_):
        s = chain.forward(q_, qd_)
        return torch.cat((s.linear_velocity, s.angular_velocity), dim=-1)

    ref = torch.func.jvp(vel, (q, qd), (qd, qdd))[1]
    st = chain.forward(q, qd, qdd)
    torch.testing.assert_close(st.linear_acceleration, ref[:, :3], rtol=0, atol=TOL)
    torch.testing.assert_close(st.angular_acceleration, ref[:, 3:], rtol=0, atol=TOL)

    def body(q_, qd_):
        return chain.forward(q_, qd_).body_velocity

    torch.testing.assert_close(st.body_acceleration, torch.func.jvp(body, (q, qd), (qd, qdd))[1],
                               rtol=0, atol=TOL)
    for f in ("base", "body", "spatial"):
        ref_dJ = torch.func.jvp(lambda x: chain.jacobian(x, frame=f), (q,), (qd,))[1]
        torch.testing.assert_close(chain.jacobian_derivative(q, qd, frame=f), ref_dJ,
                                   rtol=0, atol=TOL)
        # acceleration = J qddot + dJ/dt qdot
        acc = chain.jacobian(q, frame=f) @ qdd[..., None] + \
            chain.jacobian_derivative(q, qd, frame=f) @ qd[..., None]
        if f == "base":
            want = torch.cat((st.linear_acceleration, st.angular_acceleration), -1)
        elif f == "body":
            want = st.body_acceleration
        else:
            continue
        torch.testing.assert_close(acc[..., 0], want, rtol=0, atol=TOL)


def test_jacobian_against_finite_differences_and_gradcheck():
    chain = load_robot("ur5")
    q = _random(chain, 1, 3)[0][0]
    J = chain.jacobian(q, frame="body")
    eps = 1e-6
    T0 = chain.pose(q)
    cols = []
    for i in range(chain.n_joints):
        dq = torch.zeros_like(q)
        dq[i] = eps
        cols.append((chain.pose(q + dq).rminus(T0) - chain.pose(q - dq).rminus(T0)) / (2 * eps))
    torch.testing.assert_close(J, torch.stack(cols, -1), rtol=0, atol=1e-8)
    qg = q.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: chain.forward(x, x * 0.5).linear_velocity, (qg,))


def test_against_pytorch_kinematics():
    """pk parses URDF angles in float32 (its rpy tensor), so its poses differ from the exact
    float64 ones by float32 rounding of pi/2 (~4e-8): compared at 1e-6.  The chain built from
    the pk chain itself (same constants) agrees with pk to 1e-12."""
    text = robot_urdf("panda").read_text()
    pkc = pk.build_serial_chain_from_urdf(text, "panda_hand_tcp").to(dtype=F64)
    chain = load_robot("panda")
    q, qd, _ = _random(chain, 8, 4)
    T_pk = pkc.forward_kinematics(q).get_matrix()
    J_pk = pkc.jacobian(q)
    torch.testing.assert_close(chain.pose(q).as_matrix(), T_pk, rtol=0, atol=1e-6)
    torch.testing.assert_close(chain.jacobian(q), J_pk, rtol=0, atol=1e-6)
    same = from_pk(pkc)
    assert same.joint_names == chain.joint_names
    torch.testing.assert_close(same.pose(q).as_matrix(), T_pk, rtol=0, atol=TOL)
    torch.testing.assert_close(same.jacobian(q), J_pk, rtol=0, atol=TOL)
    st = same.forward(q, qd)
    v_pk = (J_pk @ qd[..., None])[..., 0]
    torch.testing.assert_close(torch.cat((st.linear_velocity, st.angular_velocity), -1), v_pk,
                               rtol=0, atol=TOL)
    torch.testing.assert_close(same.lower, chain.lower, rtol=0, atol=1e-6)


# ------------------------------------------------------------------------- DH
PANDA_MDH = dict(  # Franka's published modified (Craig) DH table; flange d = 0.107
    a=[0.0, 0.0, 0.0, 0.0825, -0.0825, 0.0, 0.088],
    alpha=[0.0, -math.pi / 2, math.pi / 2, math.pi / 2, -math.pi / 2, math.pi / 2, math.pi / 2],
    d=[0.333, 0.0, 0.316, 0.0, 0.384, 0.0, 0.0], theta_offset=[0.0] * 7, joint_types="R" * 7)


def test_modified_dh_agrees_with_urdf():
    tool = torch.eye(4, dtype=F64)
    tool[2, 3] = 0.107
    dh = KinematicChain.from_dh(**PANDA_MDH, convention="modified", tool=tool)
    urdf = load_robot("panda", "panda_link8")
    q, qd, qdd = _random(urdf, 10, 5)
    a, b = dh.forward(q, qd, qdd), urdf.forward(q, qd, qdd)
    torch.testing.assert_close(a.pose.as_matrix(), b.pose.as_matrix(), rtol=0, atol=TOL)
    for f in ("linear_velocity", "angular_velocity", "linear_acceleration", "angular_acceleration"):
        torch.testing.assert_close(getattr(a, f), getattr(b, f), rtol=0, atol=TOL, msg=f)
    torch.testing.assert_close(dh.jacobian(q, frame="body"), urdf.jacobian(q, frame="body"),
                               rtol=0, atol=TOL)


def test_standard_dh_agrees_with_urdf():
    """The UR5's published standard DH table (``ur5()``) against its URDF from the frame
    ``base`` (base_link turned by pi) to ``tool0``.  The URDF writes pi as 3.14159265359 and
    pi/2 as 1.57079632679 (errors ~2e-12 rad), hence 1e-10 rather than 1e-12."""
    dh = KinematicChain.from_gdh(ur5())
    urdf = load_robot("ur5", root_link="base")
    q, qd, qdd = _random(urdf, 10, 10)
    a, b = dh.forward(q, qd, qdd), urdf.forward(q, qd, qdd)
    torch.testing.assert_close(a.pose.as_matrix(), b.pose.as_matrix(), rtol=0, atol=1e-10)
    for f in ("linear_velocity", "angular_velocity", "linear_acceleration", "angular_acceleration"):
        torch.testing.assert_close(getattr(a, f), getattr(b, f), rtol=0, atol=1e-10, msg=f)
    torch.testing.assert_close(dh.jacobian(q), urdf.jacobian(q), rtol=0, atol=1e-10)


def _dh_product(q, a, alpha, d, theta, types):
    """Standard DH: prod_i Rz(theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i), written out."""
    T = torch.eye(4, dtype=F64)
    for i in range(len(a)):
        th = theta[i] + (q[i] if types[i] == "R" else 0.0)
        di = d[i] + (q[i] if types[i] == "P" else 0.0)
        ct, st, ca, sa = math.cos(th), math.sin(th), math.cos(alpha[i]), math.sin(alpha[i])
        T = T @ torch.tensor([[ct, -st * ca, st * sa, a[i] * ct], [st, ct * ca, -ct * sa, a[i] * st],
                              [0, sa, ca, d[i] * 0 + di], [0, 0, 0, 1]], dtype=F64)
    return T


@pytest.mark.parametrize("factory", [scara, ur5, iiwa7])
def test_standard_dh_agrees_with_gdh_and_the_dh_product(factory):
    gdh = factory()
    chain = KinematicChain.from_gdh(gdh)
    q, qd, qdd = _random(chain, 6, 6)
    q = q + 0.3  # no limits: random_configuration spans [-pi, pi]
    st, g = chain.forward(q, qd, qdd), gdh.forward(q, qd)
    torch.testing.assert_close(st.pose.as_matrix(), g.pose, rtol=0, atol=TOL)
    torch.testing.assert_close(st.linear_velocity, g.linear_velocity, rtol=0, atol=TOL)
    torch.testing.assert_close(st.angular_velocity, g.angular_velocity, rtol=0, atol=TOL)
    lin, ang = gdh.acceleration(q, qd, qdd)
    torch.testing.assert_close(st.linear_acceleration, lin, rtol=0, atol=1e-11)
    torch.testing.assert_close(st.angular_acceleration, ang, rtol=0, atol=1e-11)
    types = "".join("R" if t == "revolute" else "P" for t in gdh.joint_types)
    cols = [c.tolist() for c in (gdh.a, gdh.alpha, gdh.d, gdh.theta_offset)]
    for b in range(2):
        ref = _dh_product(q[b].tolist(), *cols, types)
        torch.testing.assert_close(st.pose.as_matrix()[b], ref, rtol=0, atol=TOL)
    # every DH frame: frame_i is the product of the first i link matrices
    allf = chain.forward(q[:1], all_links=True)
    assert chain.link_names[0] == "frame_0"
    torch.testing.assert_close(allf.pose.as_matrix()[0, 2], _dh_product(
        q[0].tolist()[:2], *(c[:2] for c in cols), types[:2]), rtol=0, atol=TOL)


# ------------------------------------------------------------------- options
def test_float32_and_limits_and_root_link():
    chain = load_robot("panda")
    c32 = chain.to(dtype=torch.float32)
    q, qd, qdd = _random(chain, 4, 7)
    a, b = chain.forward(q, qd, qdd), c32.forward(q.float(), qd.float(), qdd.float())
    assert b.pose.dtype == torch.float32
    torch.testing.assert_close(b.linear_acceleration.double(), a.linear_acceleration, rtol=0, atol=1e-4)
    torch.testing.assert_close(b.pose.as_matrix().double(), a.pose.as_matrix(), rtol=0, atol=1e-5)
    # limits as in the URDF; continuous joints have none
    torch.testing.assert_close(chain.lower[3], torch.tensor(-3.0718, dtype=F64))
    torch.testing.assert_close(chain.upper[5], torch.tensor(3.7525, dtype=F64))
    kin = load_robot("kinova")
    assert kin.joints[0].kind == "continuous" and math.isinf(kin.lower[0].item())
    assert chain.within_limits(q).all() and not chain.within_limits(q + 10).any()
    # a root link hanging from the chain by fixed joints: UR's "base" (base_link turned by pi)
    ur = load_robot("ur5")
    ur_b = load_robot("ur5", root_link="base")
    qq = _random(ur, 3, 8)[0]
    ref = PinRobot(ur, robot_urdf("ur5"))
    pin.framesForwardKinematics(ref.model, ref.data, ref.q(qq[0].tolist()))
    rel = ref.data.oMf[ref.model.getFrameId("base")].inverse() * \
        ref.data.oMf[ref.model.getFrameId("tool0")]
    np.testing.assert_allclose(ur_b.pose(qq[0]).as_matrix().numpy(), rel.homogeneous, rtol=0, atol=TOL)
    # base and tool transforms
    base = torchsgal.SE3.exp(torch.tensor([0.1, 0.2, 0.3, 0.4, -0.2, 0.1], dtype=F64))
    tool = torchsgal.SE3.exp(torch.tensor([0.0, 0.0, 0.05, 0.0, 0.3, 0.0], dtype=F64))
    moved = load_robot("ur5", base=base, tool=tool)
    torch.testing.assert_close(moved.pose(qq).as_matrix(),
                               base.compose(ur.pose(qq)).compose(tool).as_matrix(), rtol=0, atol=TOL)


def test_urdf_string_and_custom_axes():
    """A hand-made URDF with a tilted revolute axis, a prismatic joint and fixed joints,
    against Pinocchio."""
    text = """<robot name="toy">
      <link name="a"/><link name="b"/><link name="c"/><link name="d"/><link name="e"/>
      <joint name="j1" type="revolute"><parent link="a"/><child link="b"/>
        <origin xyz="0.1 0 0.2" rpy="0.3 -0.2 0.5"/><axis xyz="1 1 0"/>
        <limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
      <joint name="f" type="fixed"><parent link="b"/><child link="c"/>
        <origin xyz="0 0.3 0" rpy="0 0.4 0"/></joint>
      <joint name="j2" type="prismatic"><parent link="c"/><child link="d"/>
        <origin xyz="0 0 0.1"/><axis xyz="0 0.6 0.8"/>
        <limit lower="0" upper="0.5" effort="1" velocity="1"/></joint>
      <joint name="j3" type="continuous"><parent link="d"/><child link="e"/>
        <origin xyz="0.2 0 0" rpy="1.0 0 0"/><axis xyz="0 0 -1"/></joint>
    </robot>"""
    chain = from_urdf(text)
    assert chain.end_link == "e" and [j.kind for j in chain.joints] == [
        "revolute", "prismatic", "continuous"]
    model = pin.buildModelFromXML(text)
    data = model.createData()
    q, qd, qdd = _random(chain, 3, 9)
    st = chain.forward(q, qd, qdd)
    fid = model.getFrameId("e")
    for b in range(3):
        qp = np.array([q[b, 0], q[b, 1], math.cos(q[b, 2]), math.sin(q[b, 2])])
        pin.forwardKinematics(model, data, qp, qd[b].numpy(), qdd[b].numpy())
        pin.updateFramePlacements(model, data)
        np.testing.assert_allclose(st.pose.as_matrix()[b].numpy(), data.oMf[fid].homogeneous, rtol=0, atol=TOL)
        acc = pin.getFrameClassicalAcceleration(model, data, fid, pin.LOCAL_WORLD_ALIGNED)
        np.testing.assert_allclose(st.linear_acceleration[b].numpy(), acc.linear, rtol=0, atol=TOL)
        np.testing.assert_allclose(st.angular_acceleration[b].numpy(), acc.angular, rtol=0, atol=TOL)


# ---------------------------------------------------------------- bad input
def test_bad_input():
    chain = load_robot("panda")
    q = torch.zeros(7, dtype=F64)
    with pytest.raises(ValueError, match=r"unknown link 'nope'.*panda_link0"):
        chain.forward(q, links="nope")
    with pytest.raises(ValueError, match="unknown link"):
        chain.jacobian(q, link="nope")
    with pytest.raises(ValueError, match=r"end_link 'nope' is not a link"):
        load_robot("panda", "nope")
    with pytest.raises(ValueError, match=r"q must have shape \(\.\.\., 7\).*got \(6,\)"):
        chain.forward(torch.zeros(6, dtype=F64))
    with pytest.raises(ValueError, match=r"qdot must have shape"):
        chain.forward(q, torch.zeros(8, dtype=F64))
    with pytest.raises(TypeError, match="dtype"):
        chain.forward(q.float())
    with pytest.raises(TypeError, match="all_links must be True or False"):
        chain.forward(q, all_links="yes")
    with pytest.raises(ValueError, match="qddot needs qdot"):
        chain.forward(q, None, q)
    with pytest.raises(ValueError, match="frame must be one of"):
        chain.jacobian(q, frame="world")
    with pytest.raises(ValueError, match="batch shapes do not broadcast"):
        chain.forward(torch.zeros(2, 7, dtype=F64), torch.zeros(3, 7, dtype=F64))
    with pytest.raises(ValueError, match="not well-formed XML"):
        from_urdf("<robot name='x'><link name='a'></robot>")
    with pytest.raises(ValueError, match="root element is <html>"):
        from_urdf("<html/>")
    with pytest.raises(ValueError, match=r"joint 'j' names child link 'zz'"):
        from_urdf("<robot name='x'><link name='a'/><joint name='j' type='revolute'>"
                  "<parent link='a'/><child link='zz'/><axis xyz='0 0 1'/></joint></robot>")
    with pytest.raises(ValueError, match=r"joint 'j' has no <child"):
        from_urdf("<robot name='x'><link name='a'/><joint name='j' type='revolute'>"
                  "<parent link='a'/></joint></robot>")
    with pytest.raises(ValueError, match="floating"):
        from_urdf("<robot name='x'><link name='a'/><link name='b'/><joint name='j' "
                  "type='floating'><parent link='a'/><child link='b'/></joint></robot>")
    with pytest.raises(FileNotFoundError, match="no URDF file"):
        from_urdf("/nonexistent/robot.urdf")
    with pytest.raises(ValueError, match="several leaf links"):
        from_urdf(robot_urdf("panda"))
    with pytest.raises(ValueError, match="convention must be"):
        KinematicChain.from_dh(**PANDA_MDH, convention="craig")
    with pytest.raises(ValueError, match="equal, non-zero length"):
        KinematicChain.from_dh([0.0], [0.0], [0.0, 1.0], [0.0], "R")
    with pytest.raises(ValueError, match="rigid transform"):
        load_robot("ur5", tool=torch.ones(4, 4, dtype=F64))
    assert isinstance(GDHChain, type)


def test_load_robot_refuses_empty_and_non_string_names():
    """Only end_link None takes the default tool frame; "" (or [], 0) is refused as any bad end
    link (through ``end_link or default`` it would fall back to the default).  A robot name
    that is not a str is a TypeError naming it (not "unhashable type")."""
    with pytest.raises(ValueError, match=r"^end_link '' is not a link of the robot 'panda'; its links are .*'panda_link0'"):
        load_robot("panda", end_link="")
    with pytest.raises(ValueError, match="^end_link must name at least one link$"):
        load_robot("panda", end_link=[])
    with pytest.raises(TypeError, match="^end_link must be a link name"):
        load_robot("panda", end_link=0)
    for call in (robot_urdf, load_robot):
        with pytest.raises(TypeError, match=r"^name must be a robot name \(a str\).*'panda'.*got list \['panda'\]$"):
            call(["panda"])
    assert load_robot("panda", end_link=None).end_link == "panda_hand_tcp"  # the default


def test_tree_branches_against_pinocchio():
    """The Allegro hand: four fingers as the branches of one tree (16 joints), every fingertip's
    pose, velocity, acceleration and Jacobians against Pinocchio."""
    hand = load_robot("allegro")
    assert hand.n_joints == 16 and len(hand.end_links) == 4
    assert hand.parents[:5] == (-1, 0, 1, 2, -1)  # finger 2 starts again at the palm
    ref = PinRobot(hand, robot_urdf("allegro"))
    q, qd, qdd = _random(hand, 3, 11)
    st = hand.forward(q, qd, qdd, links=hand.end_links)
    m, d = ref.model, ref.data
    for b in range(3):
        qp, vp = ref.q(q[b].tolist()), ref.v(qd[b].tolist())
        pin.forwardKinematics(m, d, qp, vp, ref.v(qdd[b].tolist()))
        pin.updateFramePlacements(m, d)
        pin.computeJointJacobians(m, d, qp)
        pin.computeJointJacobiansTimeVariation(m, d, qp, vp)
        for k, tip in enumerate(hand.end_links):
            fid = m.getFrameId(tip)
            np.testing.assert_allclose(st.pose.as_matrix()[b, k].numpy(), d.oMf[fid].homogeneous,
                                       rtol=0, atol=TOL, err_msg=tip)
            vel = pin.getFrameVelocity(m, d, fid, pin.LOCAL_WORLD_ALIGNED)
            np.testing.assert_allclose(st.linear_velocity[b, k].numpy(), vel.linear, rtol=0, atol=TOL)
            np.testing.assert_allclose(st.angular_velocity[b, k].numpy(), vel.angular, rtol=0, atol=TOL)
            acc = pin.getFrameClassicalAcceleration(m, d, fid, pin.LOCAL_WORLD_ALIGNED)
            np.testing.assert_allclose(st.linear_acceleration[b, k].numpy(), acc.linear, rtol=0, atol=TOL)
            np.testing.assert_allclose(st.angular_acceleration[b, k].numpy(), acc.angular, rtol=0, atol=TOL)
            for f, pf in (("base", pin.LOCAL_WORLD_ALIGNED), ("body", pin.LOCAL)):
                J = hand.jacobian(q[b], link=tip, frame=f)
                np.testing.assert_allclose(J.numpy(), pin.getFrameJacobian(m, d, fid, pf)[:, ref.cols()],
                                           rtol=0, atol=TOL, err_msg=f"{tip} {f}")
                dJ = hand.jacobian_derivative(q[b], qd[b], link=tip, frame=f)
                np.testing.assert_allclose(
                    dJ.numpy(), pin.getFrameJacobianTimeVariation(m, d, fid, pf)[:, ref.cols()],
                    rtol=0, atol=TOL, err_msg=f"{tip} {f}")
    # a chain to one fingertip alone gives that finger's kinematics
    one = load_robot("allegro", "link_7.0_tip")
    assert one.n_joints == 4
    torch.testing.assert_close(one.pose(q[:, 4:8]).as_matrix(), st.pose.as_matrix()[:, 1],
                               rtol=0, atol=TOL)
    with pytest.raises(ValueError, match="parents must give"):
        KinematicChain(list(one.joints), {"x": (0, torch.eye(4, dtype=F64))}, "x",
                       parents=[-1, 0, 2, 1])
