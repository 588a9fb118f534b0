"""Inputs of the kinematics API: joint axes, one-sided limits, copies of the caller's tensors,
IK targets and seeds, pk interop arguments.  Expected values come from Rodrigues' formula
written here, the limits themselves and values taken before the caller's tensors change."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchsgal import SE3
from torchsgal.kinematics import GDHChain, KinematicChain, inverse_kinematics
from torchsgal.kinematics.pk_interop import from_transform3d
from torchsgal.kinematics.state import Joint

F64 = torch.float64


def _eye():
    return torch.eye(4, dtype=F64)


def _one_joint(axis, kind="revolute", lower=-math.inf, upper=math.inf, origin=None,
               base=None, offset=None, tool=None):
    j = Joint("j", kind, axis, _eye() if origin is None else origin, lower, upper)
    return KinematicChain([j], {"l": (0, _eye() if offset is None else offset)}, "l",
                          base=base, tool=tool)


def _unit(axis):
    k = np.asarray(axis, dtype=float)
    k = k / np.abs(k).max()  # first: the squares of tiny or huge entries under/overflow
    return k / np.linalg.norm(k)


def _rodrigues(axis, angle):
    k = _unit(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


# ------------------------------------------------------------------ 1. joint axes
@pytest.mark.parametrize("axis", [(1.0, 0.0, 1.0), (0.0, 3.0, 0.0), (1e-200, 2e-200, -1e-200),
                                  (1e200, 0.0, 1e200)])
def test_non_unit_axis_is_normalised(axis):
    q = torch.tensor([0.7, -2.1], dtype=F64)[:, None]
    R = _one_joint(axis).pose(q).rotation()
    for b in range(2):
        np.testing.assert_allclose(R[b].numpy(), _rodrigues(axis, float(q[b, 0])),
                                   rtol=0, atol=1e-14)
    p = _one_joint(axis, "prismatic").pose(q).position()
    unit = _unit(axis)
    np.testing.assert_allclose(p.numpy(), q.numpy() * unit, rtol=0, atol=1e-14)


@pytest.mark.parametrize("axis", [(1e-3, 0.0, -1.0), (0.0, 1e-5, -1.0), (3e-7, 0.0, -1.0),
                                  (1e-9, -1e-9, -1.0), (0.0, 0.0, -1.0), (-0.6, 0.0, -0.8)])
def test_axis_close_to_minus_z_is_exact(axis):
    """An axis near -z keeps its accuracy (a canonical frame dividing by 1 + a_z, which cancels,
    or replacing axes within ~1e-6 of -z by -z, would be 3e-7 off Rodrigues' formula at a 1e-5 tilt)."""
    q = torch.tensor([0.7, -2.1, math.pi], dtype=F64)[:, None]
    R = _one_joint(axis).pose(q).rotation()
    for b in range(3):
        np.testing.assert_allclose(R[b].numpy(), _rodrigues(axis, float(q[b, 0])),
                                   rtol=0, atol=1e-14)
    p = _one_joint(axis, "prismatic").pose(q).position()
    np.testing.assert_allclose(p.numpy(), q.numpy() * _unit(axis), rtol=0, atol=1e-14)


@pytest.mark.parametrize("axis", [(0.0, 0.0, 0.0), (math.nan, 0.0, 1.0), (math.inf, 0.0, 0.0),
                                  (0.0, -math.inf, 1.0)])
def test_zero_or_non_finite_axis_raises(axis):
    with pytest.raises(ValueError, match=r"joints\[0\]\.axis .* finite, non-zero 3-vector"):
        _one_joint(axis)


@pytest.mark.parametrize("axis", [(True, 0, 0), (0.0, 1.0), "xyz", 3.0])
def test_malformed_axis_raises_typeerror(axis):
    with pytest.raises(TypeError, match=r"joints\[0\]\.axis .* must be 3 real numbers"):
        _one_joint(axis)


def test_joint_origin_is_checked():
    bad = _eye()
    bad[1, 3] = math.nan
    with pytest.raises(ValueError, match=r"joints\[0\]\.origin .* must be finite"):
        _one_joint((0.0, 0.0, 1.0), origin=bad)
    scaled = 2 * _eye()
    scaled[3, 3] = 1.0
    with pytest.raises(ValueError, match=r"joints\[0\]\.origin .* rigid transform"):
        _one_joint((0.0, 0.0, 1.0), origin=scaled)


# ------------------------------------------------------------ 2. one-sided limits
def test_random_configuration_with_one_sided_limits():
    joints = [Joint("a", "prismatic", (0.0, 0.0, 1.0), _eye(), 4.0, math.inf),
              Joint("b", "revolute", (0.0, 0.0, 1.0), _eye(), -math.inf, -5.0),
              Joint("c", "revolute", (0.0, 0.0, 1.0), _eye(), -0.5, 0.25),
              Joint("d", "continuous", (0.0, 0.0, 1.0), _eye())]
    chain = KinematicChain(joints, {"l": (3, _eye())}, "l")
    g = torch.Generator().manual_seed(0)
    q = chain.random_configuration(4000, generator=g)
    assert bool(chain.within_limits(q).all())
    tp = 2 * math.pi
    lo = torch.tensor([4.0, -5.0 - tp, -0.5, -math.pi], dtype=F64)
    hi = torch.tensor([4.0 + tp, -5.0, 0.25, math.pi], dtype=F64)
    assert bool(((q >= lo) & (q <= hi)).all())
    # the samples fill each interval (4000 uniform samples: gaps at the ends are < 1%)
    width = hi - lo
    assert bool(((q.min(0).values - lo) < 0.01 * width).all())
    assert bool(((hi - q.max(0).values) < 0.01 * width).all())
    q1 = chain.random_configuration(500, generator=g, unbounded_range=1.0)
    assert bool(((q1[:, 0] >= 4.0) & (q1[:, 0] <= 6.0)).all())
    assert bool(((q1[:, 1] >= -7.0) & (q1[:, 1] <= -5.0)).all())
    assert bool(((q1[:, 3] >= -1.0) & (q1[:, 3] <= 1.0)).all())


# ----------------------------------------------------- 3. copies of user tensors
def test_chain_keeps_copies_of_the_callers_tensors():
    base, origin, offset, tool = _eye(), _eye(), _eye(), _eye()
    base[0, 3], origin[1, 3], offset[2, 3], tool[0, 3] = 0.5, 0.25, 0.125, 1.0
    chain = _one_joint((0.0, 0.0, 1.0), base=base, origin=origin, offset=offset, tool=tool)
    q = torch.tensor([[0.0]], dtype=F64)
    expected = torch.tensor([[1.5, 0.25, 0.125]], dtype=F64)  # sum of the translations
    torch.testing.assert_close(chain.pose(q).position(), expected, rtol=0, atol=1e-15)
    for m in (base, origin, offset, tool):
        m[:3, 3] = math.nan
    torch.testing.assert_close(chain.pose(q).position(), expected, rtol=0, atol=1e-15)
    torch.testing.assert_close(chain.to(torch.float32).pose(q.float()).position(),
                               expected.float(), rtol=0, atol=1e-7)
    torch.testing.assert_close(chain.base.position(), torch.tensor([0.5, 0.0, 0.0], dtype=F64),
                               rtol=0, atol=0)
    chain.base.as_matrix()[0, 3] = 9.0  # a copy: the chain does not change
    torch.testing.assert_close(chain.pose(q).position(), expected, rtol=0, atol=1e-15)


def test_gdh_chain_keeps_copies_of_its_columns():
    a = torch.tensor([0.5, 0.25], dtype=F64)
    d = np.array([0.125, 0.0])
    chain = GDHChain(a, [0.0, 0.0], d, [0.0, 0.0], "RR")
    q = torch.zeros(2, dtype=F64)
    a[0], d[0] = math.nan, math.nan
    expected = torch.tensor([0.75, 0.0, 0.125], dtype=F64)
    torch.testing.assert_close(chain.forward(q).end_effector.position(), expected,
                               rtol=0, atol=1e-15)
    assert chain.a.tolist() == [0.5, 0.25]


def test_dh_column_of_booleans_raises():
    with pytest.raises(TypeError, match=r"a \(a DH table column\) .* booleans"):
        GDHChain([True, False], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0], "RR")
    with pytest.raises(TypeError, match=r"d \(a DH table column\) .* booleans"):
        GDHChain([0.0, 0.0], [0.0, 0.0], torch.tensor([True, False]), [0.0, 0.0], "RR")


# --------------------------------------------------------------- 4, 5. inverse kinematics
def _planar():
    return KinematicChain.from_dh([1.0], [0.0], [0.0], [0.0], "R")


def test_ik_target_must_be_rigid():
    chain = _planar()
    T = chain.pose(torch.tensor([[0.3], [2.0]], dtype=F64)).as_matrix()
    scaled = T.clone()
    scaled[0, :3, :3] *= 1.1
    row = T.clone()
    row[1, 3, 0] = 0.5
    nan = T.clone()
    nan[0, 0, 3] = math.nan
    for bad in (scaled, row, nan, scaled[0]):
        with pytest.raises(ValueError, match=r"target must be rigid transforms"):
            inverse_kinematics(chain, bad)
    with pytest.raises(ValueError, match=r"target must be rigid transforms"):
        inverse_kinematics(chain, SE3.from_matrix(scaled))
    with pytest.raises(ValueError, match=r"target must be a \(4, 4\) or \(B, 4, 4\) tensor .* "
                                         r"got shape \(2, 2, 4, 4\)"):
        inverse_kinematics(chain, T.expand(2, 2, 4, 4))
    res = inverse_kinematics(chain, T[1], num_seeds=2, generator=torch.Generator().manual_seed(0))
    assert res.q.shape == (1, 1) and bool(res.success.all())


def test_ik_q0_reading_when_seeds_equal_targets():
    """q0 (2, n) with B = 2 targets: one seed per target by default; num_seeds=2 reads it as
    two shared seeds.  max_iterations=0 keeps each seed as it is, so the answer shows the
    reading: per target, the seeds are swapped; shared, each target finds its own angle."""
    chain = _planar()
    angles = torch.tensor([[0.3], [2.0]], dtype=F64)
    T = chain.pose(angles)
    q0 = angles.flip(0)
    kw = dict(q0=q0, max_iterations=0, centering=0.0)
    for ns in (None, 1):
        per_target = inverse_kinematics(chain, T, num_seeds=ns, **kw)
        assert per_target.q.tolist() == q0.tolist() and not per_target.success.any()
    shared = inverse_kinematics(chain, T, num_seeds=2, **kw)
    assert shared.q.tolist() == angles.tolist() and shared.seed.tolist() == [1, 0]
    with pytest.raises(ValueError, match=r"num_seeds \(3\) conflicts with q0 of shape \(2, 1\)"):
        inverse_kinematics(chain, T, num_seeds=3, **kw)
    with pytest.raises(ValueError, match=r"num_seeds \(2\) conflicts with q0 of shape \(1,\)"):
        inverse_kinematics(chain, T, q0=q0[0], num_seeds=2)


def test_ik_non_finite_position_target_or_seed_raises():
    """Position targets and q0 are checked finite, as pose targets are (as rigid transforms):
    unchecked, a NaN/inf target or seed would run the solver and return NaN errors and joints."""
    chain = _planar()
    good = torch.tensor([[0.6, 0.8, 0.0], [0.0, 1.0, 0.0]], dtype=F64)
    for bad_value in (math.nan, math.inf, -math.inf):
        bad = good.clone()
        bad[1, 0] = bad_value
        with pytest.raises(ValueError, match=r"^target must be finite"):
            inverse_kinematics(chain, bad, orientation=False)
        with pytest.raises(ValueError, match=r"^q0 must be finite"):
            inverse_kinematics(chain, good, orientation=False,
                               q0=torch.tensor([[0.1], [bad_value]], dtype=F64))
    res = inverse_kinematics(chain, good, orientation=False, q0=torch.tensor([[0.1], [1.0]], dtype=F64))
    assert bool(res.success.all())
    torch.testing.assert_close(res.q, torch.tensor([[math.atan2(0.8, 0.6)], [math.pi / 2]],
                                                   dtype=F64), rtol=0, atol=1e-6)


def test_ik_respects_one_sided_limits():
    """Only joints with both limits were bounded: a one-sided limit was ignored.  A prismatic
    joint along z reaches p = q; targets beyond its one limit are not solved and stay within
    it, targets inside are solved as without limits."""
    tgt = torch.tensor([[0.0, 0.0, 0.2], [0.0, 0.0, 2.0], [0.0, 0.0, -3.0]], dtype=F64)
    for lower, upper, solved in ((0.5, math.inf, [False, True, False]),
                                 (-math.inf, 1.0, [True, False, True])):
        chain = KinematicChain.from_dh([0.0], [0.0], [0.0], [0.0], "P", lower=[lower], upper=[upper])
        res = inverse_kinematics(chain, tgt, orientation=False,
                                 generator=torch.Generator().manual_seed(0))
        assert chain.within_limits(res.q).all()
        assert res.success.tolist() == solved
        q_ref = tgt[:, 2].clamp(lower, upper)  # the nearest reachable point
        assert (res.q[:, 0] - q_ref).abs().max() < 1e-4
        torch.testing.assert_close(res.position_error, (tgt[:, 2] - res.q[:, 0]).abs())
        free = inverse_kinematics(chain, tgt, orientation=False, respect_limits=False,
                                  generator=torch.Generator().manual_seed(0))
        assert free.success.all()
        inside = torch.tensor(solved)
        torch.testing.assert_close(res.q[inside], free.q[inside], rtol=0, atol=1e-8)
        at_limit = torch.tensor([lower if math.isfinite(lower) else upper], dtype=F64)
        res = inverse_kinematics(chain, tgt, orientation=False, q0=at_limit)  # a seed on the limit
        assert res.success.tolist() == solved and chain.within_limits(res.q).all()
    # a revolute arm whose one-sided limits are far from the solution: the free solver's answer
    chain = KinematicChain.from_dh([0.5, 0.4], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0], "RR",
                                   lower=[-10.0, -math.inf], upper=[math.inf, 10.0])
    q_true = torch.tensor([[0.4, 0.9], [-1.0, -0.5]], dtype=F64)
    kw = dict(orientation=False, q0=(q_true + 0.1)[:, None, :])
    res = inverse_kinematics(chain, chain.pose(q_true).position(), **kw)
    free = inverse_kinematics(chain, chain.pose(q_true).position(), respect_limits=False, **kw)
    assert res.success.all() and free.success.all()
    torch.testing.assert_close(res.q, free.q, rtol=0, atol=1e-8)


def test_ik_holds_a_joint_with_equal_limits():
    """lower == upper was treated as no limit: the joint moved away from its value."""
    chain = KinematicChain.from_dh([0.5, 0.5], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0], "RR",
                                   lower=[0.2, -1.0], upper=[0.2, 1.0])
    g = torch.Generator().manual_seed(0)
    reachable = chain.pose(torch.tensor([[0.2, 0.7]], dtype=F64))
    res = inverse_kinematics(chain, reachable, generator=g)
    assert res.success.all() and res.q[0, 0].item() == 0.2
    # reachable only with q1 = -0.3: not solved, and the joint stays at 0.2
    tgt = torch.tensor([[math.cos(-0.3), math.sin(-0.3), 0.0]], dtype=F64)
    for dtype in (F64, torch.float32):
        c = chain.to(dtype=dtype)
        res = inverse_kinematics(c, tgt.to(dtype), orientation=False, generator=g)
        assert not res.success.any() and c.within_limits(res.q).all()
        assert res.q[0, 0].item() == torch.tensor(0.2, dtype=dtype).item()
        p = c.pose(res.q).position()
        torch.testing.assert_close(res.position_error, (p - tgt.to(dtype)).norm(dim=-1))
        assert res.position_error.item() > 0.1


# ------------------------------------------------------ jacobian_derivative, DH, Joint
def test_jacobian_derivative_needs_qdot():
    """jacobian_derivative(q, None) returned None (base) or a TypeError from inside."""
    chain = KinematicChain.from_dh([0.5, 0.4], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0], "RR")
    q = torch.zeros(2, dtype=F64)
    for frame in ("base", "body", "spatial"):
        with pytest.raises(TypeError, match=r"^qdot must be a torch.Tensor \(\.\.\., 2\) .* got "
                                            r"NoneType$"):
            chain.jacobian_derivative(q, None, frame=frame)
    assert chain.jacobian_derivative(q, torch.ones(2, dtype=F64)).shape == (6, 2)


def test_from_dh_names_a_bad_column_or_joint_types():
    """from_dh gave "object of type 'int' has no len()" and "'float' object is not iterable"."""
    with pytest.raises(TypeError, match=r"^joint_types must be a string such as 'RRP' or a "
                                        r"sequence .* got int$"):
        KinematicChain.from_dh([0.5], [0.0], [0.0], [0.0], 5)
    expected = r"\(a DH table column\) must be a sequence of numbers or a 1-D tensor"
    with pytest.raises(TypeError, match=rf"^a {expected}, got a 0-D Tensor of shape \(\)$"):
        KinematicChain.from_dh(torch.tensor(0.0), [0.0], [0.0], [0.0], "R")
    with pytest.raises(TypeError, match=rf"^theta_offset {expected}, got float 0.5$"):
        KinematicChain.from_dh([0.0], [0.0], [0.0], 0.5, "R")
    with pytest.raises(ValueError, match=r"^d \(a DH table column\) must be finite"):
        KinematicChain.from_dh([0.0], [0.0], [math.nan], [0.0], "R")
    with pytest.raises(ValueError, match=r"^joint_types\[1\] must be .* got 'X' \(joint_types"):
        KinematicChain.from_dh([0.0, 0.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0], "RX")
    chain = KinematicChain.from_dh(torch.tensor([0.5]), np.array([0.0]), (0.0,), [0.0], ["R"])
    assert chain.n_joints == 1


@pytest.mark.parametrize("field, value, error, message", [
    ("lower", "x", TypeError, r"^joints\[0\]\.lower \('j'\) must be a real number \(-inf for no "
                              r"limit\), got 'x'$"),
    ("upper", None, TypeError, r"^joints\[0\]\.upper \('j'\) must be a real number"),
    ("lower", True, TypeError, r"^joints\[0\]\.lower \('j'\) must be a real number"),
    ("upper", math.nan, ValueError, r"^joints\[0\]\.upper \('j'\) must be a real number .* got nan"),
    ("velocity", -1.0, ValueError, r"^joints\[0\]\.velocity \('j'\) must be >= 0"),
    ("velocity", math.nan, ValueError, r"^joints\[0\]\.velocity \('j'\) must be a real number"),
])
def test_joint_limits_are_checked(field, value, error, message):
    """Joint(..., lower="x") gave Python's comparison error, naming no argument."""
    j = Joint("j", "revolute", (0.0, 0.0, 1.0), _eye(), **{field: value})
    with pytest.raises(error, match=message):
        KinematicChain([j], {"l": (0, _eye())}, "l")


def test_joint_limits_accept_numbers_and_0d_tensors():
    j = Joint("j", "revolute", (0.0, 0.0, 1.0), _eye(), torch.tensor(-1.0), 2, np.float32(3.0))
    chain = KinematicChain([j], {"l": (0, _eye())}, "l")
    assert chain.lower.tolist() == [-1.0] and chain.upper.tolist() == [2.0]
    assert chain.joints[0].velocity == 3.0


# -------------------------------------------------------------- URDF structure
_LIMIT = '<axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="1" velocity="1"/>'


def _urdf(joints, links=("base", "a", "b", "c")):
    body = "".join(f'<link name="{k}"/>' for k in links)
    for name, parent, child, *extra in joints:
        body += (f'<joint name="{name}" type="revolute"><parent link="{parent}"/>'
                 f'<child link="{child}"/><origin xyz="0 0 0.1"/>'
                 f'{extra[0] if extra else _LIMIT}</joint>')
    return f'<robot name="r">{body}</robot>'


def test_urdf_cycle_raises():
    """A cycle of joints made from_urdf loop forever (or pass unnoticed off the chain)."""
    from torchsgal.kinematics import from_urdf

    pytest.importorskip("yourdfpy")
    cyc = _urdf([("j1", "base", "a"), ("j2", "b", "c"), ("j3", "c", "b")])
    message = r"the joints .*'j[23]'.*'j[23]'.* form a cycle through the links \['[bc]', '[bc]'\]"
    for kw in (dict(end_link="c"), dict(end_link="a", root_link="b"), dict(end_link="a")):
        with pytest.raises(ValueError, match=message):
            from_urdf(cyc, **kw)
    loop = _urdf([("j1", "base", "a"), ("j2", "b", "b")], links=("base", "a", "b"))
    with pytest.raises(ValueError, match=r"the joints 'j2' \('b' -> 'b'\) form a cycle"):
        from_urdf(loop, end_link="a")


def test_urdf_link_with_two_parents_and_duplicate_names_raise():
    """A link that was the child of two joints kept only the last joint (a wrong chain)."""
    from torchsgal.kinematics import from_urdf

    pytest.importorskip("yourdfpy")
    two = _urdf([("j1", "base", "a"), ("j2", "base", "b"), ("j3", "a", "c"), ("j4", "b", "c")])
    with pytest.raises(ValueError, match=r"link 'c' is the child of two joints, 'j3' and 'j4'"):
        from_urdf(two)
    dup_link = _urdf([("j1", "base", "a")], links=("base", "a", "a"))
    with pytest.raises(ValueError, match=r"link names must be unique, got several <link> named \['a'\]"):
        from_urdf(dup_link, end_link="a")
    dup_joint = _urdf([("j1", "base", "a"), ("j1", "a", "b")], links=("base", "a", "b"))
    with pytest.raises(ValueError, match=r"joint names must be unique, got several <joint> named \['j1'\]"):
        from_urdf(dup_joint)


@pytest.mark.parametrize("limit, message", [
    ('lower="1" upper="-1" effort="1" velocity="1"', r'<limit lower="1.0" upper="-1.0">: lower must be <= upper'),
    ('lower="nan" upper="1" effort="1" velocity="1"', r'<limit lower="nan">: lower must be a number'),
    ('lower="-1" upper="1" effort="1" velocity="-5"', r'<limit velocity="-5.0">: velocity must be >= 0'),
    ('lower="-1" upper="1" effort="1" velocity="nan"', r'<limit velocity="nan">: velocity must be >= 0'),
    ('lower="-1" upper="1" effort="-2" velocity="1"', r'<limit effort="-2.0">: effort must be >= 0'),
    ('lower="-1" upper="1" effort="nan" velocity="1"', r'<limit effort="nan">: effort must be >= 0'),
])
def test_urdf_bad_limits_raise(limit, message):
    from torchsgal.kinematics import from_urdf

    pytest.importorskip("yourdfpy")
    bad = _urdf([("j1", "base", "a", f'<axis xyz="0 0 1"/><limit {limit}/>'), ("j2", "a", "b")],
                links=("base", "a", "b"))
    with pytest.raises(ValueError, match=r"joint 'j1' has " + message):
        from_urdf(bad)


def test_urdf_equal_limits_and_zero_velocity_are_allowed():
    from torchsgal.kinematics import from_urdf

    pytest.importorskip("yourdfpy")
    ok = _urdf([("j1", "base", "a", '<axis xyz="0 0 1"/><limit lower="0.3" upper="0.3" '
                                    'effort="0" velocity="0"/>'), ("j2", "a", "b")],
               links=("base", "a", "b"))
    chain = from_urdf(ok)
    assert chain.lower.tolist() == [0.3, -1.0] and chain.upper.tolist() == [0.3, 1.0]
    assert chain.joints[0].velocity == 0.0


# ------------------------------------------------------------------ 6, 7. pk interop
@pytest.mark.parametrize("shape, error, message", [
    ((2.7, 2), TypeError, r"batch_shape\[0\] must be an integer >= 0, got 2.7"),
    ((2, True), TypeError, r"batch_shape\[1\] must be an integer >= 0, got True"),
    ((2, "2"), TypeError, r"batch_shape\[1\] must be an integer >= 0, got '2'"),
    ("22", TypeError, r"batch_shape must be a tuple of ints \(or an int\), got '22'"),
    (True, TypeError, r"batch_shape must be a tuple of ints \(or an int\), got True"),
    (4.0, TypeError, r"batch_shape must be a tuple of ints \(or an int\), got 4.0"),
    ((-2, -2), ValueError, r"batch_shape\[0\] must be an integer >= 0, got -2"),
])
def test_from_transform3d_batch_shape_entries(shape, error, message):
    M = _eye().expand(4, 4, 4)
    with pytest.raises(error, match=message):
        from_transform3d(M, batch_shape=shape)


def test_from_transform3d_batch_shape_accepts_integers():
    M = _eye().expand(4, 4, 4)
    assert from_transform3d(M, batch_shape=(np.int64(2), 2)).batch_shape == (2, 2)
    assert from_transform3d(M, batch_shape=torch.Size([1, 4])).batch_shape == (1, 4)


@pytest.mark.parametrize("column, message", [
    ("12", r"a \(a DH table column\) must be a sequence of numbers or a 1-D tensor, got str"),
    ([True, False], r"a \(a DH table column\) .* booleans"),
    (torch.tensor([True, False]), r"a \(a DH table column\) .* booleans"),
    (torch.zeros(2, 1, dtype=F64), r"a \(a DH table column\) .* got a 2-D Tensor"),
    (0.5, r"a \(a DH table column\) must be a sequence of numbers or a 1-D tensor, got float"),
])
def test_build_pk_chain_checks_columns_as_gdh(column, message):
    pytest.importorskip("pytorch_kinematics")
    from torchsgal.kinematics.pk_interop import build_pk_chain

    with pytest.raises(TypeError, match=message):
        build_pk_chain(column, [0.0, 0.0], [0.0, 0.0], [0.0, 0.0], "RR")
    with pytest.raises(TypeError, match=message):  # the same error as GDHChain's
        GDHChain(column, [0.0, 0.0], [0.0, 0.0], [0.0, 0.0], "RR")


def test_sparse_joint_tensors_are_refused_by_name():
    """A sparse q, qdot or q0 is refused by name (unchecked, it would fail inside torch:
    expand/reshape/where not implemented for sparse tensors)."""
    chain = KinematicChain.from_dh([0.5, 0.25], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0], "RR")
    gdh = GDHChain([0.5, 0.25], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0], "RR")
    q = torch.zeros(1, 2, dtype=F64)
    sparse = q.to_sparse()
    calls = {
        "q": [lambda: chain.forward(sparse), lambda: chain.jacobian(sparse),
              lambda: chain.within_limits(sparse), lambda: gdh.forward(sparse),
              lambda: gdh.link_transforms(sparse)],
        "qdot": [lambda: chain.forward(q, sparse), lambda: chain.jacobian_derivative(q, sparse),
                 lambda: gdh.forward(q, sparse)],
        "q0": [lambda: inverse_kinematics(chain, torch.tensor([[0.75, 0.0, 0.0]], dtype=F64),
                                          orientation=False, q0=sparse)],
    }
    for name, fns in calls.items():
        for fn in fns:
            with pytest.raises(TypeError, match=rf"^{name} must be a dense \(strided\) torch.Tensor"):
                fn()
    torch.testing.assert_close(chain.pose(q).position(),
                               torch.tensor([[0.75, 0.0, 0.0]], dtype=F64), rtol=0, atol=1e-15)
