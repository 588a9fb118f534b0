"""torchsgal.imu against GTSAM's PreintegratedImuMeasurements and pypose's IMUPreintegrator
on the same IMU streams, and the conversions to their representations."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
import torch

from torchsgal import SGal3
from torchsgal.imu import gravity_vector, peers, preintegrate
from torchsgal.imu.trajectory import SinusoidalTrajectory

gtsam = pytest.importorskip("gtsam")
pp = pytest.importorskip("pypose")

F64 = torch.float64
G = 9.80665


def _constant_stream(dt, T=1.0):
    K = int(round(T / dt))
    w = torch.tensor([0.5, -0.8, 1.2], dtype=F64)
    a = torch.tensor([1.0, 2.0, -0.5], dtype=F64)
    return w.expand(1, K, 3), a.expand(1, K, 3), torch.full((1, K), dt, dtype=F64), w, a


def _expm(w, a, T):
    U = np.zeros((5, 5))
    U[:3, :3] = [[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]
    U[:3, 3] = a
    U[3, 4] = 1.0
    return scipy.linalg.expm(U * T)


def test_navstate_and_pypose_conversions_round_trip():
    X = SGal3.random((4,), dtype=F64, generator=torch.Generator().manual_seed(0))
    navs = peers.to_gtsam_navstate(X)
    assert isinstance(navs[0], gtsam.NavState)
    np.testing.assert_allclose(navs[2].attitude().matrix(), X[2].rotation().numpy(), rtol=0, atol=1e-15)
    np.testing.assert_allclose(np.asarray(navs[2].velocity()), X[2].velocity().numpy(), rtol=0, atol=1e-15)
    back = peers.from_gtsam_navstate(navs, X.time())
    assert torch.allclose(back.as_matrix(), X.as_matrix(), rtol=0, atol=1e-15)
    st = peers.to_pypose_state(X)
    assert torch.allclose(st["rot"].matrix()[:, 0], X.rotation(), rtol=0, atol=1e-12)
    assert torch.equal(st["pos"][:, 0], X.position()) and torch.equal(st["vel"][:, 0], X.velocity())



def test_peer_helpers_check_their_arguments():
    from torchsgal import SE3
    gyro, acc, dt, _, _ = _constant_stream(0.1)
    empty_g, empty_dt = gyro[:, :0], dt[:, :0]
    X = SGal3.identity((1,), dtype=F64)
    with pytest.raises(ValueError, match=r"gyro must have shape \(\.\.\., K, 3\) with at least one sample"):
        peers.gtsam_preintegrate(empty_g, empty_g, empty_dt, peers.gtsam_params())
    with pytest.raises(ValueError, match=r"gyro must have shape \(\.\.\., K, 3\) with at least one sample"):
        peers.pypose_predict(empty_g, empty_g, empty_dt, X)
    with pytest.raises(ValueError, match=r"dt must have shape \(\.\.\., K\) with K = 10"):
        peers.gtsam_preintegrate(gyro, acc, dt[:, :4], peers.gtsam_params())
    with pytest.raises(ValueError, match=r"gyro_bias must be a tensor of shape \(3,\) .* got \(2, 3\)"):
        peers.gtsam_preintegrate(gyro, acc, dt, peers.gtsam_params(), gyro_bias=torch.zeros(2, 3, dtype=F64))
    with pytest.raises(TypeError, match="frames must be SGal3, got SE3"):
        peers.to_gtsam_navstate(SE3.identity(dtype=F64))
    with pytest.raises(TypeError, match="frames must be SGal3, got SE3"):
        peers.to_pypose_state(SE3.identity(dtype=F64))
    with pytest.raises(TypeError, match="start must be SGal3, got SE3"):
        peers.pypose_predict(gyro, acc, dt, SE3.identity((1,), dtype=F64))

def test_constant_inputs_exact_for_us_first_order_for_peers():
    errs = {"ours": [], "gtsam": [], "pypose": []}
    params = peers.gtsam_params("z_up", G)
    for dt in (0.1, 0.05, 0.025):
        gyro, acc, h, w, a = _constant_stream(dt)
        ref = _expm(w.numpy(), a.numpy(), 1.0)
        delta = preintegrate(gyro, acc, h).delta
        errs["ours"].append(np.abs(delta.as_matrix()[0].numpy() - ref).max())
        # GTSAM's increment deltaXij() is (Delta R, Delta p, Delta v): the same quantities.
        nav = peers.gtsam_preintegrate(gyro, acc, h, params)[0].deltaXij()
        np.testing.assert_allclose(nav.attitude().matrix(), ref[:3, :3], rtol=0, atol=1e-12)  # rotation exact too
        errs["gtsam"].append(np.abs(np.asarray(nav.position()) - ref[:3, 4]).max())
        # pypose from the identity with zero gravity integrates the same increment.
        out = pp.module.IMUPreintegrator(gravity=0.0, prop_cov=False, reset=True).to(F64)(
            h.unsqueeze(-1), gyro, acc, init_state=peers.to_pypose_state(SGal3.identity((1,), dtype=F64)))
        errs["pypose"].append(np.abs(out["pos"][0, -1].numpy() - ref[:3, 4]).max())
    assert max(errs["ours"]) < 1e-12, errs
    for name in ("gtsam", "pypose"):
        e = errs[name]
        assert e[-1] > 1e-4, errs  # visible at dt = 0.025 s
        assert 1.6 < e[0] / e[1] < 2.5 and 1.6 < e[1] / e[2] < 2.5, (name, e)  # O(dt)


def _end_errors(pred: SGal3, truth: SGal3):
    rot = pred.between(truth).log()[..., 6:9].norm(dim=-1).max()
    vel = (pred.velocity() - truth.velocity()).norm(dim=-1).max()
    pos = (pred.position() - truth.position()).norm(dim=-1).max()
    return np.array([float(rot), float(vel), float(pos)])


@pytest.mark.parametrize("frame", ["z_up", "ned"])
def test_same_stream_sinusoid_accuracy(frame):
    traj = SinusoidalTrajectory()
    g = gravity_vector(frame, G, dtype=F64)
    t0 = torch.tensor([0.0, 1.3], dtype=F64)
    X0, X1 = traj.state(t0), traj.state(t0 + 1.0)
    params = peers.gtsam_params(frame, G)
    res = {}
    for h in (0.01, 0.005):
        gyro, acc, dt = traj.stream(t0, 1.0, h, g, sample="midpoint")
        res[h] = {
            "ours": _end_errors(preintegrate(gyro, acc, dt).predict(X0, g), X1),
            "gtsam": _end_errors(peers.gtsam_predict(peers.gtsam_preintegrate(gyro, acc, dt, params), X0), X1),
            "pypose": _end_errors(peers.pypose_predict(gyro, acc, dt, X0, frame, G), X1),
        }
    for name in ("gtsam", "pypose"):
        # the peers are right to first order (conventions and conversions agree) ...
        assert res[0.005][name][1:].max() < 2e-2 and 1.6 < res[0.01][name][2] / res[0.005][name][2] < 2.5
        # ... and at equal dt the exact increment is two orders of magnitude closer
        assert res[0.005]["ours"][1:].max() < 0.01 * res[0.005][name][1:].min(), res
    assert res[0.01]["ours"][2] / res[0.005]["ours"][2] > 3.5  # second order


def test_left_samples_all_first_order():
    # With samples latched at the start of each interval the sampling error dominates and every
    # method is first order (the exact increment has no advantage on such a stream).
    traj = SinusoidalTrajectory()
    g = gravity_vector("z_up", G, dtype=F64)
    t0 = torch.tensor([0.4], dtype=F64)
    X0, X1 = traj.state(t0), traj.state(t0 + 1.0)
    params = peers.gtsam_params("z_up", G)
    errs = {"ours": [], "gtsam": [], "pypose": []}
    for h in (0.01, 0.005):
        gyro, acc, dt = traj.stream(t0, 1.0, h, g, sample="left")
        errs["ours"].append(_end_errors(preintegrate(gyro, acc, dt).predict(X0, g), X1))
        errs["gtsam"].append(_end_errors(peers.gtsam_predict(peers.gtsam_preintegrate(gyro, acc, dt, params), X0), X1))
        errs["pypose"].append(_end_errors(peers.pypose_predict(gyro, acc, dt, X0, "z_up", G), X1))
    for name, (e1, e2) in errs.items():
        assert np.all((1.6 < e1 / e2) & (e1 / e2 < 2.5)), (name, e1, e2)


def test_covariance_agrees_with_gtsam_to_first_order():
    # GTSAM propagates a first-order discretisation (O(dt)); mapped to our right perturbation
    # its covariance approaches ours linearly in dt.
    traj = SinusoidalTrajectory()
    g = gravity_vector("z_up", G, dtype=F64)
    t0 = torch.tensor([0.3], dtype=F64)
    s_g, s_a = 2e-3, 3e-2
    diffs = []
    for h in (0.01, 0.005):
        gyro, acc, dt = traj.stream(t0, 1.0, h, g)
        ours = preintegrate(gyro, acc, dt, gyro_noise_density=s_g, acc_noise_density=s_a).covariance[0, :9, :9]
        pim = peers.gtsam_preintegrate(gyro, acc, dt, peers.gtsam_params("z_up", G, s_g, s_a))[0]
        theirs = peers.gtsam_covariance(pim)
        sd = ours.diagonal().sqrt()
        diffs.append(float(((theirs - ours).abs() / sd.unsqueeze(-1) / sd.unsqueeze(-2)).max()))
    assert diffs[1] < 2e-3, diffs
    assert 1.6 < diffs[0] / diffs[1] < 2.5, diffs
