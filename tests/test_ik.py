"""Batched inverse kinematics on the Panda (7 joints, redundant) and the UR5 (6 joints).

Targets are poses of random configurations within the joint limits (reachable by
construction).  Every reported success is checked by Pinocchio's forward kinematics of the
returned joints, independently of the chain that solved it, and against the joint limits.
"""
import math

import numpy as np
import pytest
import torch

import torchsgal
from torchsgal.estimation import SolverStatus
from torchsgal.kinematics import inverse_kinematics, load_robot, robot_urdf

pin = pytest.importorskip("pinocchio")

F64 = torch.float64


def _targets(chain, n, seed):
    g = torch.Generator().manual_seed(seed)
    q = chain.random_configuration((n,), generator=g)
    return chain.pose(q), g


def _pinocchio_errors(robot, end, chain, q, target):
    """Position and rotation errors of q by Pinocchio's FK (an independent peer)."""
    model = pin.buildModelFromUrdf(str(robot_urdf(robot)))
    data = model.createData()
    fid = model.getFrameId(end)
    idx = [model.joints[model.getJointId(n)].idx_q for n in chain.joint_names]
    e_pos, e_rot = [], []
    for b in range(q.shape[0]):
        qp = pin.neutral(model)
        qp[idx] = q[b].numpy()
        pin.framesForwardKinematics(model, data, qp)
        M = data.oMf[fid]
        Mt = target.as_matrix()[b].numpy()
        e_pos.append(np.linalg.norm(M.translation - Mt[:3, 3]))
        e_rot.append(np.linalg.norm(pin.log3(Mt[:3, :3].T @ M.rotation)))
    return np.array(e_pos), np.array(e_rot)


def test_panda_pose_targets():
    """A few hundred reachable targets: most are solved, every success is real (Pinocchio),
    every solution is within the limits, and the redundant arm's SINGULAR information does
    not turn reached targets into failures."""
    chain = load_robot("panda")
    target, g = _targets(chain, 200, 0)
    res = inverse_kinematics(chain, target, num_seeds=8, generator=g,
                             position_tol=1e-4, rotation_tol=1e-3)
    assert res.q.shape == (200, 7) and res.success.shape == (200,)
    assert res.success_rate >= 0.85, res.success_rate
    assert bool(chain.within_limits(res.q).all())
    e_pos, e_rot = _pinocchio_errors("panda", "panda_hand_tcp", chain, res.q, target)
    ok = res.success.numpy()
    assert (e_pos[ok] <= 1e-4).all() and (e_rot[ok] <= 1e-3).all()
    np.testing.assert_allclose(res.position_error.numpy(), e_pos, rtol=0, atol=1e-12)
    np.testing.assert_allclose(res.rotation_error.numpy(), e_rot, rtol=0, atol=1e-9)
    assert ((e_pos[~ok] > 1e-4) | (e_rot[~ok] > 1e-3)).all()  # failures are real too
    # 7 joints for a 6-dof pose: the information is rank-deficient at every solution
    singular = (res.solver_status == SolverStatus.SINGULAR).numpy()
    assert (singular & ok).sum() >= 0.5 * ok.sum()
    assert np.median(e_pos[ok]) < 1e-8  # converged, not stopped at the tolerance


def test_tolerance_decides_success():
    chain = load_robot("panda")
    target, g = _targets(chain, 40, 1)
    few = inverse_kinematics(chain, target, num_seeds=4, generator=g, max_iterations=3,
                             position_tol=0.05, rotation_tol=0.1)
    expected = (few.position_error <= 0.05) & (few.rotation_error <= 0.1)
    assert torch.equal(few.success, expected) and 0 < expected.sum() < 40  # a mix
    g.manual_seed(5)
    tight = inverse_kinematics(chain, target, num_seeds=4, generator=g, max_iterations=3,
                               position_tol=1e-12, rotation_tol=1e-12)
    assert not tight.success.any()


def test_position_only_and_orientation_only():
    chain = load_robot("panda")
    target, g = _targets(chain, 100, 2)
    res = inverse_kinematics(chain, target.position(), orientation=False, num_seeds=4, generator=g)
    assert res.success_rate >= 0.95
    e_pos, _ = _pinocchio_errors("panda", "panda_hand_tcp", chain, res.q, target)
    assert (e_pos[res.success.numpy()] <= 1e-4).all()
    assert torch.equal(res.rotation_error, torch.zeros_like(res.rotation_error))
    rot = inverse_kinematics(chain, target, position=False, num_seeds=4, generator=g)
    assert rot.success_rate >= 0.95
    _, e_rot = _pinocchio_errors("panda", "panda_hand_tcp", chain, rot.q, target)
    assert (e_rot[rot.success.numpy()] <= 1e-3).all()


def test_ur5_seeds_and_unreachable_targets():
    chain = load_robot("ur5")
    target, g = _targets(chain, 50, 3)
    # one seed near the answer, no centering stage (a few targets are near a wrist
    # singularity or a limit)
    q_true = chain.random_configuration((50,), generator=torch.Generator().manual_seed(3))
    res = inverse_kinematics(chain, target, q0=q_true + 0.05, centering=0.0)
    assert res.success_rate >= 0.95
    e_pos, e_rot = _pinocchio_errors("ur5", "tool0", chain, res.q, target)
    ok = res.success.numpy()
    assert (e_pos[ok] <= 1e-4).all() and (e_rot[ok] <= 1e-3).all()
    # a target 5 m away: no success, finite errors, joints within the limits
    far = torchsgal.SE3.from_components(torch.eye(3, dtype=F64).expand(3, 3, 3),
                                        torch.tensor([[5.0, 0.0, 0.0]] * 3, dtype=F64))
    bad = inverse_kinematics(chain, far, num_seeds=2, generator=g, max_iterations=20)
    assert not bad.success.any()
    assert torch.isfinite(bad.position_error).all() and (bad.position_error > 3.5).all()
    assert chain.within_limits(bad.q).all()


def test_without_limits_and_q0_shapes():
    chain = load_robot("panda")
    target, g = _targets(chain, 10, 4)
    q0 = chain.random_configuration((3,), generator=g)
    res = inverse_kinematics(chain, target, q0=q0, respect_limits=False)  # (S, n) shared seeds
    assert res.seed.max() <= 2 and res.success_rate >= 0.8
    one = inverse_kinematics(chain, target[0], q0=q0[0])  # one target, one seed
    assert one.q.shape == (1, 7)


def test_bad_input():
    chain = load_robot("panda")
    target, _ = _targets(chain, 2, 5)
    with pytest.raises(TypeError, match="position must be True or False"):
        inverse_kinematics(chain, target, position=1)
    with pytest.raises(TypeError, match="respect_limits must be True or False"):
        inverse_kinematics(chain, target, respect_limits="no")
    with pytest.raises(ValueError, match="both False"):
        inverse_kinematics(chain, target, position=False, orientation=False)
    with pytest.raises(ValueError, match="orientation=False"):
        inverse_kinematics(chain, target.position())
    with pytest.raises(ValueError, match="centering must be a finite number >= 0"):
        inverse_kinematics(chain, target, centering=-1.0)
    with pytest.raises(ValueError, match="position_tol must be a finite number > 0"):
        inverse_kinematics(chain, target, position_tol=0.0)
    with pytest.raises(ValueError, match=r"q0 must be"):
        inverse_kinematics(chain, target, q0=torch.zeros(4, 5, 7, dtype=F64))
    with pytest.raises(ValueError, match=r"q0 must have shape \(\.\.\., 7\)"):
        inverse_kinematics(chain, target, q0=torch.zeros(6, dtype=F64))
    with pytest.raises(ValueError, match="unknown link"):
        inverse_kinematics(chain, target, link="hand")
    with pytest.raises(TypeError, match="target"):
        inverse_kinematics(chain, target.position().float(), orientation=False)
    with pytest.raises(TypeError, match="chain must be a KinematicChain"):
        inverse_kinematics("panda", target)
    assert math.isfinite(chain.upper[0].item())
