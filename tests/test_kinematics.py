"""GDH chains: link matrices against the classical DH matrix, velocities against finite
differences, accelerations against forward-mode autodiff (torch.func.jvp), (51) against the
top-left block of (50), the paper's product velocity shown to differ, batching, bad input.
The comparison with pytorch-kinematics is in test_kinematics_pk.py."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import torchsgal as ts
from torchsgal.kinematics import GDHChain, iiwa7, scara, ur5

ROBOTS = [scara, ur5, iiwa7]
IDS = ["scara", "ur5", "iiwa7"]


def twisted_prismatic(dtype=torch.float64):
    """Not a catalogue robot: prismatic joints on twisted links and non-zero offsets, the terms
    that the three robots above leave out (a prismatic joint's acceleration on a twisted link,
    theta offsets, prismatic d offsets)."""
    return GDHChain([0.3, 0.2, 0.1, 0.25, 0.15], [0.7, -0.4, 1.1, 0.5, -0.9],
                    [0.2, 0.1, 0.3, -0.2, 0.05], [0.1, 0.2, 0.3, -0.4, 0.6], "RPRPP", dtype=dtype)


# the derivative tests run on all four
CHAINS, CHAIN_IDS = ROBOTS + [twisted_prismatic], IDS + ["twisted_prismatic"]


def _sample(chain, batch=(6,), seed=0):
    g = torch.Generator().manual_seed(seed)
    n = chain.n_joints
    return [torch.randn(*batch, n, dtype=torch.float64, generator=g) for _ in range(3)]


def _dh_matrix(a, alpha, d, theta):
    """Classical 4x4 standard DH matrix Rz(theta) Tz(d) Tx(a) Rx(alpha)."""
    ct, st, ca, sa = math.cos(theta), math.sin(theta), math.cos(alpha), math.sin(alpha)
    return np.array([[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st],
                     [0, sa, ca, d], [0, 0, 0, 1.0]])


@pytest.mark.parametrize("robot", CHAINS, ids=CHAIN_IDS)
def test_link_matrices_are_dh_plus_velocity(robot):
    """(43) with the fourth row and column deleted is the classical DH matrix; its fourth
    column is the derivative (44) of the position column."""
    chain = robot()
    q, qd, _ = _sample(chain, batch=())
    K = chain.link_transforms(q, qd).as_matrix().numpy()
    for i in range(chain.n_joints):
        rev = chain.joint_types[i] == "revolute"
        theta = chain.theta_offset[i].item() + (q[i].item() if rev else 0.0)
        d = chain.d[i].item() + (0.0 if rev else q[i].item())
        want = _dh_matrix(chain.a[i].item(), chain.alpha[i].item(), d, theta)
        got = K[i][np.ix_([0, 1, 2, 4], [0, 1, 2, 4])]
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-15)
        h = 1e-6
        dq = torch.zeros_like(q)
        dq[i] = h
        up = chain.link_transforms(q + dq * qd[i] / 1.0).as_matrix()[i, :3, 4]
        dn = chain.link_transforms(q - dq * qd[i] / 1.0).as_matrix()[i, :3, 4]
        # central difference, h = 1e-6: round-off ~ eps / h; measured 1.5e-10 (40 seeds: 1.3e-10)
        np.testing.assert_allclose(K[i][:3, 3], ((up - dn) / (2 * h)).numpy(), rtol=0, atol=2e-9)


def _fd_velocity(chain, q, qd, qdd, h=1e-6):
    def pose(t):
        return chain.forward(q + t * qd + 0.5 * t * t * qdd).pose
    P1, P0 = pose(h), pose(-h)
    lin = (P1[..., :3, 3] - P0[..., :3, 3]) / (2 * h)
    W = (P1[..., :3, :3] - P0[..., :3, :3]) / (2 * h) @ pose(0.0)[..., :3, :3].mT
    return lin, torch.stack((W[..., 2, 1], W[..., 0, 2], W[..., 1, 0]), dim=-1)


@pytest.mark.parametrize("robot", CHAINS, ids=CHAIN_IDS)
def test_velocity_against_finite_differences(robot):
    chain = robot()
    q, qd, qdd = _sample(chain)
    state = chain.forward(q, qd)
    lin_fd, ang_fd = _fd_velocity(chain, q, qd, qdd)
    # central difference, h = 1e-6: measured worst 3.5e-10 over the three robots
    # (40 seeds: 4.3e-10)
    np.testing.assert_allclose(state.linear_velocity.numpy(), lin_fd.numpy(), rtol=0, atol=4e-9)
    np.testing.assert_allclose(state.angular_velocity.numpy(), ang_fd.numpy(), rtol=0, atol=4e-9)


@pytest.mark.parametrize("robot", CHAINS, ids=CHAIN_IDS)
def test_product_velocity_column_is_not_the_end_effector_velocity(robot):
    """The departure from the paper: (45)'s velocity column is sum_i R_(0,i-1) v_i (each link's
    own coordinate velocity), which differs from dp/dt whenever an inner revolute joint moves."""
    chain = robot()
    q, qd, _ = _sample(chain)
    state = chain.forward(q, qd)
    links = chain.link_transforms(q, qd)
    expected = torch.zeros_like(state.linear_velocity)
    R = torch.eye(3, dtype=torch.float64).expand(*q.shape[:-1], 3, 3)
    for i in range(chain.n_joints):
        expected = expected + (R @ links[..., i].velocity().unsqueeze(-1)).squeeze(-1)
        R = R @ links[..., i].rotation()
    np.testing.assert_allclose(state.end_effector.velocity().numpy(), expected.numpy(), rtol=0, atol=1e-12)
    assert (state.end_effector.velocity() - state.linear_velocity).abs().max() > 1e-2


@pytest.mark.parametrize("robot", CHAINS, ids=CHAIN_IDS)
def test_acceleration_against_forward_mode_autodiff(robot):
    """d/dt of the velocity along q(t) with q' = qd, q'' = qdd: torch.func.jvp (exact)."""
    chain = robot()
    q, qd, qdd = _sample(chain, seed=1)

    def velocity(q_, qd_):
        s = chain.forward(q_, qd_)
        return s.linear_velocity, s.angular_velocity

    _, (lin_t, ang_t) = torch.func.jvp(velocity, (q, qd), (qd, qdd))
    lin, ang = chain.acceleration(q, qd, qdd)
    # round-off only: measured worst 1.8e-15 over the three robots (40 seeds: 7.1e-15), 2.5e-14
    # over 40 seeds of the twisted chain (its accelerations are larger)
    np.testing.assert_allclose(lin.numpy(), lin_t.numpy(), atol=1e-13, rtol=0)
    np.testing.assert_allclose(ang.numpy(), ang_t.numpy(), atol=1e-13, rtol=0)


@pytest.mark.parametrize("robot", CHAINS, ids=CHAIN_IDS)
def test_angular_velocity_sum_51_is_top_left_of_50(robot):
    """(51): the end-effector angular velocity (its frame) is sum_i q_i R_(n,i-1) e3."""
    chain = robot()
    q, qd, _ = _sample(chain, seed=2)
    state = chain.forward(q, qd)
    frames = state.frames.as_matrix()
    R_n = frames[..., -1, :3, :3]
    total = torch.zeros(*q.shape[:-1], 3, dtype=torch.float64)
    for i in range(chain.n_joints):
        if chain.joint_types[i] != "revolute":
            continue
        R_prev = torch.eye(3, dtype=torch.float64) if i == 0 else frames[..., i - 1, :3, :3]
        z_prev = R_prev[..., :, 2]
        total = total + qd[..., i : i + 1] * (R_n.mT @ z_prev.unsqueeze(-1)).squeeze(-1)
    np.testing.assert_allclose(state.chain_input[..., 6:9].numpy(), total.numpy(), rtol=0, atol=1e-12)


def test_prismatic_joint_moves_along_its_axis():
    chain = scara()
    q = torch.tensor([0.3, -0.7, 0.05, 1.1], dtype=torch.float64)
    qd = torch.tensor([0.0, 0.0, 0.25, 0.0], dtype=torch.float64)  # only the prismatic joint
    state = chain.forward(q, qd)
    z2 = state.frames[1].rotation()[:, 2]  # joint 3 slides along z of frame 2
    np.testing.assert_allclose(state.linear_velocity.numpy(), (0.25 * z2).numpy(), rtol=0, atol=1e-15)
    np.testing.assert_allclose(state.angular_velocity.numpy(), np.zeros(3), rtol=0, atol=1e-15)


def test_batch_shapes_broadcast():
    chain = ur5()
    q = torch.randn(2, 1, 6, dtype=torch.float64)
    qd = torch.randn(3, 6, dtype=torch.float64)
    state = chain.forward(q, qd)
    assert state.linear_velocity.shape == (2, 3, 3)
    assert state.frames.batch_shape == (2, 3, 6)
    assert state.pose.shape == (2, 3, 4, 4)
    one = chain.forward(q[1, 0], qd[2])
    np.testing.assert_allclose(state.linear_velocity[1, 2].numpy(), one.linear_velocity.numpy(), rtol=0, atol=1e-14)
    lin, ang = chain.acceleration(q, qd, torch.zeros(6, dtype=torch.float64))
    assert lin.shape == ang.shape == (2, 3, 3)


def test_bad_input():
    chain = iiwa7()
    with pytest.raises(ValueError, match=r"q must have shape \(\.\.\., 7\) for the 7 joints of 'iiwa7', got \(4, 6\)"):
        chain.forward(torch.zeros(4, 6, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"batch shapes do not broadcast: q \(4,\), qdot \(3,\)"):
        chain.forward(torch.zeros(4, 7, dtype=torch.float64), torch.zeros(3, 7, dtype=torch.float64))
    with pytest.raises(TypeError, match=r"q must have a floating dtype"):
        chain.forward(torch.zeros(7, dtype=torch.int64))
    with pytest.raises(TypeError, match=r"q must have a floating dtype .* got torch.bfloat16"):
        chain.forward(torch.zeros(7, dtype=torch.bfloat16))
    with pytest.raises(TypeError, match=r"qdot .* must match q"):
        chain.forward(torch.zeros(7, dtype=torch.float64), torch.zeros(7, dtype=torch.float32))
    with pytest.raises(ValueError, match=r"equal, non-zero length"):
        GDHChain([0.1, 0.2], [0.0], [0.0, 0.0], [0.0, 0.0], "RR")
    with pytest.raises(ValueError, match=r"joint_types\[1\] must be"):
        GDHChain([0.1, 0.2], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0], ["R", "spherical"])


def test_chain_dtype_and_device_are_checked():
    # An integer table would truncate the link lengths (a = [0.4, 0.3] -> [0, 0]).
    for dtype in (torch.int64, torch.int32, torch.float16):
        with pytest.raises(TypeError, match=f"dtype must be torch.float32 or torch.float64, got {dtype}"):
            GDHChain([0.4, 0.3], [0, 0], [0, 0], [0, 0], "RR", dtype=dtype)
    for robot in (ur5, scara, iiwa7):
        with pytest.raises(TypeError, match="dtype must be torch.float32 or torch.float64"):
            robot(dtype=torch.int32)
    chain = GDHChain([0.4, 0.3], [0, 0], [0, 0], [0, 0], "RR", dtype=None)
    assert torch.equal(chain.a, torch.tensor([0.4, 0.3], dtype=torch.float64))
    meta = ur5(device="meta")
    q = torch.zeros(6, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"q is on cpu but the chain 'ur5' was built on meta"):
        meta.forward(q)
    with pytest.raises(ValueError, match=r"q is on cpu but the chain 'ur5' was built on meta"):
        meta.acceleration(q, q, q)


def test_joint_dtype_and_device_must_match_the_chain():
    """q is not cast to the chain's dtype (nor the table to q's): a mismatch raises, as mixed
    dtypes do everywhere else (results must not come in q's dtype, ignoring the chain's)."""
    c64, c32 = ur5(), ur5(dtype=torch.float32)
    assert (c64.dtype, c32.dtype, c64.device) == (torch.float64, torch.float32, torch.device("cpu"))
    q64 = torch.zeros(2, 6, dtype=torch.float64)
    for chain, q in ((c64, q64.float()), (c32, q64)):
        for call in (lambda: chain.forward(q), lambda: chain.forward(q, q),
                     lambda: chain.link_transforms(q), lambda: chain.link_inputs(q, q, q),
                     lambda: chain.acceleration(q, q, q)):
            with pytest.raises(TypeError, match=f"q has dtype {q.dtype} but the chain 'ur5' has "
                                                f"dtype {chain.dtype}"):
                call()
    with pytest.raises(ValueError, match=r"q is on meta but the chain 'ur5' is on cpu; move them"):
        c64.forward(torch.zeros(6, dtype=torch.float64, device="meta"))
    assert c32.forward(q64.float()).pose.dtype == torch.float32


def test_float32_matches_float64():
    c64, c32 = iiwa7(), iiwa7(dtype=torch.float32)
    q, qd, qdd = _sample(c64)
    s64, s32 = c64.forward(q, qd), c32.forward(q.float(), qd.float())
    # measured: velocity 2.2e-7 (40 seeds: 5.2e-7), acceleration 9.3e-7 (40 seeds: 3.4e-6)
    np.testing.assert_allclose(s32.linear_velocity.numpy(), s64.linear_velocity.numpy(), rtol=0, atol=3e-6)
    a64, a32 = c64.acceleration(q, qd, qdd)[0], c32.acceleration(q.float(), qd.float(), qdd.float())[0]
    np.testing.assert_allclose(a32.numpy(), a64.numpy(), rtol=0, atol=1e-5)
    assert isinstance(s32.end_effector, ts.SE23)


def test_forward_compiles_in_one_graph():
    """GDHChain.forward traces under torch.compile(fullgraph=True) (no `@` between group
    objects, which dynamo cannot trace) and matches eager; its joint gradient too."""
    arm = iiwa7()
    q = torch.randn(4, 7, dtype=torch.float64, generator=torch.Generator().manual_seed(5), requires_grad=True)

    def f(q):
        return arm.forward(q).pose.square().sum()

    compiled = torch.compile(f, backend="eager", fullgraph=True)
    (g_eager,), (g_comp,) = torch.autograd.grad(f(q), q), torch.autograd.grad(compiled(q), q)
    assert torch.equal(compiled(q), f(q))
    np.testing.assert_allclose(g_comp.numpy(), g_eager.numpy(), rtol=1e-13, atol=1e-13)


def test_table_device_follows_its_tensor_columns():
    """With device=None the table goes where its tensor columns are, its list columns and
    joint-type mask included (left on the CPU, they would make forward fail with torch's
    'not on the expected device')."""
    a = torch.tensor([0.3, 0.2], dtype=torch.float64, device="meta")
    chain = GDHChain(a, [0.0, 0.0], [0.0, 0.0], [0.0, 0.0], "RR")
    assert chain.device == torch.device("meta")
    for t in (chain.a, chain.alpha, chain.d, chain.theta_offset, chain._revolute):
        assert t.device == torch.device("meta")
    q = torch.zeros(3, 2, dtype=torch.float64, device="meta")
    state = chain.forward(q, q)
    assert state.pose.shape == (3, 4, 4) and state.pose.device == torch.device("meta")
    assert chain.acceleration(q, q, q)[0].device == torch.device("meta")
    # the dtype is not taken from the columns: float64 unless given (unchanged rule)
    a32 = torch.tensor([0.3, 0.2], dtype=torch.float32)
    assert GDHChain(a32, [0.0, 0.0], [0.0, 0.0], [0.0, 0.0], "RR").dtype == torch.float64
    # an explicit device wins over the columns'
    moved = GDHChain(a32, [0.0, 0.0], [0.0, 0.0], [0.0, 0.0], "RR", device="meta")
    assert moved.a.device.type == moved._revolute.device.type == "meta"
    with pytest.raises(ValueError, match=r"tensor columns are on different devices \(a on meta, "
                                         r"d on cpu\)"):
        GDHChain(a, [0.0, 0.0], torch.zeros(2), [0.0, 0.0], "RR")


def test_table_must_be_finite():
    """A non-finite DH parameter raises ValueError (it would give NaN poses silently)."""
    good = [0.1, 0.2]
    for i, name in enumerate(("a", "alpha", "d", "theta_offset")):
        for bad in (math.nan, math.inf, -math.inf):
            cols = [good, good, good, good]
            cols[i] = [0.1, bad]
            with pytest.raises(ValueError, match=rf"{name} \(a DH table column\) must be finite"):
                GDHChain(*cols, "RP")
    # finite in float64, infinite once built in float32
    with pytest.raises(ValueError, match=r"a \(a DH table column\) must be finite, got \[inf\] "
                                         r"\(as torch.float32\)"):
        GDHChain([1e300], [0.0], [0.0], [0.0], "R", dtype=torch.float32)
    with pytest.raises(ValueError, match=r"alpha \(a DH table column\) must be finite"):
        GDHChain(good, torch.tensor([0.0, math.nan]), good, good, "RR")
    # no values to read on 'meta': not checked there
    GDHChain(torch.full((1,), math.nan, device="meta"), [0.0], [0.0], [0.0], "R")


def test_malformed_table_columns_raise_typeerror_naming_the_column():
    """A column that is not a sequence of numbers or a 1-D tensor raises TypeError naming the
    column; torch's or Python's message ("object of type 'float' has no len()", "len() of a 0-d
    tensor", "too many dimensions 'str'") would name no column."""
    expected = r"\(a DH table column\) must be a sequence of numbers or a 1-D tensor"
    with pytest.raises(TypeError, match=rf"^a {expected}, got float 0.3$"):
        GDHChain(0.3, 0.0, 0.1, 0.0, "R")
    with pytest.raises(TypeError, match=rf"^a {expected}, got a 0-D Tensor of shape \(\)$"):
        GDHChain(torch.tensor(0.3), [0.0], [0.0], [0.0], "R")
    with pytest.raises(TypeError, match=rf"^d {expected}, got a 2-D Tensor of shape \(1, 1\)$"):
        GDHChain([0.3], [0.0], torch.zeros(1, 1), [0.0], "R")
    with pytest.raises(TypeError, match=rf"^alpha {expected}, got str '0'$"):
        GDHChain([0.3], "0", [0.0], [0.0], "R")
    with pytest.raises(TypeError, match=rf"^a {expected}: its entries must be real numbers, "
                                        rf"got \['x'\]$"):
        GDHChain(["x"], [0.0], [0.0], [0.0], "R")
    with pytest.raises(TypeError, match=rf"^theta_offset {expected}: its entries must be real "
                                        rf"numbers, got \[None\]$"):
        GDHChain([0.3], [0.0], [0.0], [None], "R")
    with pytest.raises(TypeError, match=rf"^alpha {expected}, got nested sequences of shape "
                                        rf"\(2, 1\)$"):
        GDHChain([0.3, 0.2], [[0.0], [0.0]], [0.0, 0.0], [0.0, 0.0], "RR")
    with pytest.raises(TypeError, match=r"^joint_types must be a string such as 'RRP' or a "
                                        r"sequence .* got int$"):
        GDHChain([0.3], [0.0], [0.0], [0.0], 1)
    # tuples, ranges, numpy and 1-D tensors of any dtype are still columns
    chain = GDHChain((0.3,), np.array([0.0]), range(1), torch.zeros(1, dtype=torch.int64), "R")
    assert chain.d.dtype == torch.float64 and chain.n_joints == 1


def test_joint_tensor_mismatch_is_typeerror_for_dtype_valueerror_for_device():
    """qdot/qddot against q: a dtype mismatch is TypeError and a device mismatch ValueError, as
    for q against the chain (checks.same_device_dtype), not ValueError for both."""
    chain = ur5()
    q = torch.zeros(6, dtype=torch.float64)
    with pytest.raises(TypeError, match=r"qdot has dtype torch.float32 but q has dtype "
                                        r"torch.float64 \(qdot must match q"):
        chain.forward(q, q.float())
    with pytest.raises(TypeError, match=r"qddot has dtype torch.float32 but q has dtype"):
        chain.acceleration(q, q, q.float())
    with pytest.raises(ValueError, match=r"qdot is on meta but q is on cpu; move them to one "
                                         r"device \(qdot must match q"):
        chain.forward(q, q.to("meta"))
    with pytest.raises(ValueError, match=r"qddot is on meta but q is on cpu"):
        chain.link_inputs(q, q, q.to("meta"))


def test_joint_types_string_is_read_letter_by_letter():
    hint = (r"joint_types 'revolute' is read letter by letter, one 'R' or 'P' per joint, "
            r"e\.g\. 'RRP'")
    with pytest.raises(ValueError, match=r"'joint_types': 8\} \(" + hint):
        GDHChain([0.1], [0.0], [0.0], [0.0], "revolute")
    with pytest.raises(ValueError, match=r"joint_types\[1\] must be .* got 'e' \(" + hint):
        GDHChain(*([[0.1] * 8] * 4), "revolute")
    assert GDHChain([0.1], [0.0], [0.0], [0.0], ["revolute"]).joint_types == ("revolute",)
    with pytest.raises(ValueError, match=r"joint_types\[0\] must be") as info:
        GDHChain([0.1], [0.0], [0.0], [0.0], ["spherical"])
    assert "letter by letter" not in str(info.value)  # the hint is for strings only
