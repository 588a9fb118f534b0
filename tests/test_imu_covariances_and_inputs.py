"""torchsgal.imu's streaming covariance, input checks and copies (and fusion of its rank-9 covariance):

- the streaming covariance and result() equal preintegrate's with a bias random walk (the walk
  only in combined_covariance), under chunkings, batched;
- sensor_to_body: a tensor dt checked (finite, > 0), angular_acceleration checked and broadcast,
  against the formula written out here; body_P_sensor's batch checked against the samples';
- increment_tangents checks a tensor dt as preintegrate does; gravity_vector refuses a negative
  magnitude; SinusoidalTrajectory names a parameter that is not a 3-vector of numbers;
- results do not follow in-place updates of the caller's biases or chains (K = 1 products);
- fuse / fuse_event refuse a covariance with known directions with a message saying what to do;
- a number dt is filled on the device when the held samples are flushed (no torch.tensor);
- a non-tensor gyro beside a number dt is named (not dt); sensor_to_body refuses samples without
  a sample axis; trajectory tensor parameters must broadcast with the times; the peers'
  gtsam_params, pypose_predict and from_gtsam_navstate check their arguments before calling out.
"""
from __future__ import annotations

import functools

import pytest
import torch

from torchsgal import SE3, SGal3
from torchsgal.imu import gravity_vector, increment_tangents, preintegrate, suffix_products, window_product
from torchsgal.imu.gtsam_interop import sensor_to_body
from torchsgal.imu.streaming import StreamingPreintegration
from torchsgal.imu.trajectory import SinusoidalTrajectory
from torchsgal.uncertainty import ConcentratedGaussian, fuse_event

F64 = torch.float64
DENS = dict(gyro_noise_density=2e-2, acc_noise_density=3e-1)


def samples(batch, K, seed):
    g = torch.Generator().manual_seed(seed)
    gyro = 2.0 * torch.randn(*batch, K, 3, generator=g, dtype=F64)
    acc = 3.0 * torch.randn(*batch, K, 3, generator=g, dtype=F64)
    dt = 0.002 + 0.01 * torch.rand(*batch, K, generator=g, dtype=F64)
    bg = 0.05 * torch.randn(*batch, 3, generator=g, dtype=F64)
    ba = 0.2 * torch.randn(*batch, 3, generator=g, dtype=F64)
    return gyro, acc, dt, bg, ba


@pytest.mark.parametrize("buffer_size", [1, 5, 256])
@pytest.mark.parametrize("time_noise", [0.0, 1e-3])
def test_streaming_covariance_is_preintegrates_with_random_walk(buffer_size, time_noise):
    gyro, acc, dt, bg, ba = samples((3,), 23, seed=4)
    pre = preintegrate(gyro, acc, dt, bg, ba, time_noise_density=time_noise, **DENS)
    s = StreamingPreintegration((3,), gyro_bias=bg, acc_bias=ba, gyro_bias_random_walk=0.05,
                                acc_bias_random_walk=0.05, time_noise_density=time_noise,
                                buffer_size=buffer_size, dtype=F64, **DENS)
    i = 0
    for n in (1, 4, 1, 1, 9, 7):  # one-sample calls and chunks
        if n == 1:
            s.integrate(gyro[:, i], acc[:, i], dt[:, i])
        else:
            s.integrate(gyro[:, i:i + n], acc[:, i:i + n], dt[:, i:i + n])
        i += n
    scale = pre.covariance.abs().max()
    assert (s.covariance - pre.covariance).abs().max() < 1e-14 * scale
    assert (s.result().covariance - pre.covariance).abs().max() < 1e-14 * scale
    # the combined block carries the walk (its cross terms), the plain one does not
    assert (s.combined_covariance()[..., :10, :10] - pre.covariance).abs().max() > 1e-4 * scale


def lever_arm_formula(gyro, acc, T: SE3, alpha):
    R, r = T.rotation(), T.position()
    w = gyro @ R.mT
    f = acc @ R.mT - torch.linalg.cross(w, torch.linalg.cross(w, r.expand_as(w)))
    return w, f - torch.linalg.cross(alpha, r.expand_as(f))


def test_sensor_to_body_checks_a_tensor_dt():
    gyro, acc, dt, _, _ = samples((2,), 5, seed=1)
    T = SE3.exp(torch.tensor([0.1, -0.2, 0.3, 0.2, 0.1, -0.4], dtype=F64))
    for bad in (torch.zeros(2, 5, dtype=F64), -dt, dt.new_tensor(float("nan")), dt.new_tensor(float("inf"))):
        with pytest.raises(ValueError, match=r"dt must be finite and > 0"):
            sensor_to_body(gyro, acc, T, bad)
    # a valid tensor dt equal to a number dt gives the same result
    w1, f1 = sensor_to_body(gyro, acc, T, 0.01)
    w2, f2 = sensor_to_body(gyro, acc, T, torch.full((5,), 0.01, dtype=F64))
    assert torch.equal(w1, w2) and torch.equal(f1, f2)


def test_sensor_to_body_checks_angular_acceleration():
    gyro, acc, _, _, _ = samples((2,), 5, seed=2)
    T = SE3.exp(torch.tensor([0.1, -0.2, 0.3, 0.2, 0.1, -0.4], dtype=F64))
    alpha = torch.randn(5, 3, dtype=F64)
    with pytest.raises(TypeError, match=r"angular_acceleration has dtype torch.float32"):
        sensor_to_body(gyro, acc, T, angular_acceleration=alpha.float())
    with pytest.raises(ValueError, match=r"angular_acceleration must have shape \(\.\.\., 3\)"):
        sensor_to_body(gyro, acc, T, angular_acceleration=torch.zeros(5, 4, dtype=F64))
    with pytest.raises(ValueError, match=r"angular_acceleration"):
        sensor_to_body(gyro, acc, T, angular_acceleration=torch.zeros(3, 5, 3, dtype=F64))
    with pytest.raises(ValueError, match=r"angular_acceleration must broadcast to the samples' shape"):
        sensor_to_body(gyro, acc, T, angular_acceleration=torch.zeros(4, 2, 5, 3, dtype=F64))
    w, f = sensor_to_body(gyro, acc, T, angular_acceleration=alpha)  # broadcast over the batch
    w_ref, f_ref = lever_arm_formula(gyro, acc, T, alpha.expand(2, 5, 3))
    assert (w - w_ref).abs().max() < 1e-13 and (f - f_ref).abs().max() < 1e-13


def test_sensor_to_body_checks_the_pose_batch():
    """A pose batch that does not broadcast with the windows' gave torch's RuntimeError."""
    gyro, acc, _, _, _ = samples((4,), 10, seed=3)
    T = SE3.exp(0.1 * torch.randn(3, 6, dtype=F64, generator=torch.Generator().manual_seed(0)))
    for dt in (None, 0.01):
        with pytest.raises(ValueError, match=r"body_P_sensor's batch shape \(3,\) must broadcast "
                                             r"with .* gyro and acc of shape \(4, 10, 3\)"):
            sensor_to_body(gyro, acc, T, dt)
    w, f = sensor_to_body(gyro, acc, T[:1])  # (1,) broadcasts
    w_ref, f_ref = lever_arm_formula(gyro, acc, T[0], torch.zeros_like(acc))
    assert (w - w_ref).abs().max() < 1e-13 and (f - f_ref).abs().max() < 1e-13


def test_increment_tangents_checks_dt_as_preintegrate():
    """increment_tangents refuses a negative or non-finite tensor dt as preintegrate does, and as
    it refuses such a number."""
    gyro, acc, dt, _, _ = samples((2,), 5, seed=4)
    for bad in (-dt, torch.full_like(dt, float("nan")), torch.full_like(dt, float("inf"))):
        for f in (increment_tangents, preintegrate):
            with pytest.raises(ValueError, match=r"^dt must be finite and >= 0 everywhere"):
                f(gyro, acc, bad)
    with pytest.raises(ValueError, match=r"^dt must be a finite number >= 0, got -0.01"):
        increment_tangents(gyro, acc, -0.01)
    assert increment_tangents(gyro, acc, torch.zeros_like(dt))[..., 3:].abs().max() == 0


def test_gravity_magnitude_must_not_be_negative():
    """gravity_vector("ned", -9.8) flipped gravity to point up."""
    for frame in ("ned", "z_up"):
        with pytest.raises(ValueError, match=r"^magnitude must be a finite number >= 0, got -9.8$"):
            gravity_vector(frame, -9.8)
    assert gravity_vector("z_up", 0.0, dtype=F64).abs().max() == 0


def test_trajectory_parameters_are_named():
    """A string parameter gave torch's "new(): invalid data type 'str'"."""
    t = torch.zeros(2, dtype=F64)
    for bad in ("abc", (1.0, "x", 2.0), None):
        with pytest.raises(TypeError, match=r"^rot_amplitude must be a 3-vector of real numbers"):
            SinusoidalTrajectory(rot_amplitude=bad).state(t)
    with pytest.raises(ValueError, match=r"^pos_phase must be finite, got \(nan, 0.0, 0.0\)"):
        SinusoidalTrajectory(pos_phase=(float("nan"), 0.0, 0.0)).state(t)
    ref = SinusoidalTrajectory().state(t).as_matrix()
    as_tensor = SinusoidalTrajectory(rot_amplitude=torch.tensor([0.3, 0.4, 0.8], dtype=F64)).state(t)
    assert torch.equal(as_tensor.as_matrix(), ref)


def test_preintegration_does_not_follow_in_place_bias_updates():
    gyro, acc, dt, bg, ba = samples((2,), 6, seed=3)
    pre = preintegrate(gyro, acc, dt, bg, ba, **DENS)
    start = SGal3.exp(0.1 * torch.ones(10, dtype=F64))
    g = gravity_vector(dtype=F64)
    new_g, new_a = bg + 0.01, ba - 0.02
    want_c, want_p = pre.corrected(new_g, new_a).as_matrix(), pre.predict(start, g, None, new_g, new_a).as_matrix()
    bg0, ba0 = bg.clone(), ba.clone()
    bg.add_(0.3)  # an estimator updating its bias in place
    ba.mul_(2.0)
    assert torch.equal(pre.gyro_bias, bg0) and torch.equal(pre.acc_bias, ba0)
    assert torch.equal(pre.corrected(new_g, new_a).as_matrix(), want_c)
    assert torch.equal(pre.predict(start, g, None, new_g, new_a).as_matrix(), want_p)


@pytest.mark.parametrize("K", [0, 1, 2, 3])
def test_chain_products_are_new_tensors(K):
    E = torch.randn(2, K, 4, 4, dtype=F64)
    S, W = suffix_products(E), window_product(E)
    eye = torch.eye(4, dtype=F64).expand(2, 4, 4)
    ref_S = [functools.reduce(torch.matmul, [E[:, j] for j in range(k, K)], eye) for k in range(K)]
    ref_W = functools.reduce(torch.matmul, [E[:, j] for j in range(K)], eye)
    assert S.shape == E.shape and (W - ref_W).abs().max() < 1e-12
    for k in range(K):
        assert (S[:, k] - ref_S[k]).abs().max() < 1e-12
    before_S, before_W = S.clone(), W.clone()
    E.add_(1.0)  # the caller updates its chain in place
    assert torch.equal(S, before_S) and torch.equal(W, before_W)


def test_fusion_refuses_known_directions_with_advice():
    gyro, acc, dt, bg, ba = samples((), 8, seed=5)
    pre = preintegrate(gyro, acc, dt, bg, ba, **DENS)  # rank 9: exact time
    assert not pre.covariance[9].any()
    a = ConcentratedGaussian(pre.delta, pre.covariance)  # the constructor takes it
    step = torch.tensor([1e-3, 0, 0, 0, 2e-3, 0, 0, 1e-3, 0, 0], dtype=F64)
    b = ConcentratedGaussian(pre.delta.rplus(step), pre.covariance)
    with pytest.raises(ValueError, match=r"fuse: self.covariance is singular.*small variance"):
        a.fuse(b)
    event = torch.tensor([0.1, 0.2, 0.3, float(pre.delta.time())], dtype=F64)
    with pytest.raises(ValueError, match=r"fuse_event: the prior's covariance is singular.*small variance"):
        fuse_event(a, event, 1e-2 * torch.eye(4, dtype=F64))
    # the advice: a small variance on the known directions
    known = (pre.covariance == 0).all(-1)
    cov = pre.covariance + 1e-12 * torch.diag_embed(known.to(F64))
    fused = ConcentratedGaussian(pre.delta, cov).fuse(ConcentratedGaussian(b.mean, cov))
    assert torch.isfinite(fused.covariance).all()
    assert abs(float(fused.mean.time() - pre.delta.time())) < 1e-12  # both know the same time


def test_number_dt_is_filled_on_the_device(monkeypatch):
    gyro, acc, _, bg, ba = samples((2,), 9, seed=6)
    s = StreamingPreintegration((2,), gyro_bias=bg, acc_bias=ba, buffer_size=64, dtype=F64, **DENS)
    s.integrate(gyro[:, :3], acc[:, :3], 0.01)
    s.integrate(gyro[:, 3], acc[:, 3], 0.01)
    s.integrate(gyro[:, 4:], acc[:, 4:], 0.02)

    def no_copy(*args, **kwargs):
        raise AssertionError("torch.tensor (a host-to-device copy on CUDA) in a flush")
    with monkeypatch.context() as m:
        m.setattr(torch, "tensor", no_copy)
        cov, delta = s.covariance, s.delta.as_matrix()
    dt = torch.tensor([0.01] * 4 + [0.02] * 5, dtype=F64)
    pre = preintegrate(gyro, acc, dt, bg, ba, **DENS)
    assert (delta - pre.delta.as_matrix()).abs().max() < 1e-12
    assert (cov - pre.covariance).abs().max() < 1e-12 * pre.covariance.abs().max()


def test_a_non_tensor_gyro_is_named_beside_a_number_dt():
    """preintegrate(gyro as a list, acc, 0.01) names gyro, not the valid dt (as in "dt must be a
    number or a tensor (..., K), got float")."""
    gyro, acc, _, _, _ = samples((), 4, seed=1)
    for f in (preintegrate, increment_tangents):
        for bad, kind in ((gyro.tolist(), "list"), (gyro.numpy(), "ndarray")):
            with pytest.raises(TypeError, match=rf"^gyro must be a torch.Tensor, got {kind}$"):
                f(bad, acc, 0.01)
    # a number dt beside a tensor gyro means one interval for every sample
    ref = torch.tensor([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.01], dtype=F64)
    assert torch.equal(increment_tangents(torch.zeros(4, 3, dtype=F64), torch.zeros(4, 3, dtype=F64),
                                          0.01), ref.expand(4, 10))


def test_sensor_to_body_refuses_samples_without_a_sample_axis():
    """gyro, acc (3,) (no K axis) are refused: read as one sample, they would come back as
    (1, 3), another shape than the samples'."""
    gyro, acc, _, _, _ = samples((), 4, seed=2)
    T = SE3.exp(0.1 * torch.randn(6, dtype=F64, generator=torch.Generator().manual_seed(1)))
    for kw in ({}, {"angular_acceleration": torch.zeros(3, dtype=F64)}):
        with pytest.raises(ValueError, match=r"^gyro must have shape \(\.\.\., K, 3\) .* got \(3,\)$"):
            sensor_to_body(gyro[0], acc[0], T, **kw)
    w, f = sensor_to_body(gyro[:1], acc[:1], T)  # one sample with its axis: (1, 3)
    w_ref, f_ref = lever_arm_formula(gyro[:1], acc[:1], T, torch.zeros(1, 3, dtype=F64))
    assert w.shape == f.shape == (1, 3)
    assert (w - w_ref).abs().max() < 1e-13 and (f - f_ref).abs().max() < 1e-13


def test_trajectory_tensor_parameters_must_broadcast_with_the_times():
    """A tensor parameter whose batch does not broadcast with t is named (unchecked, torch's
    "The size of tensor a (4) must match ..." would name no parameter)."""
    t = torch.zeros(3, dtype=F64)
    traj = SinusoidalTrajectory(pos_amplitude=torch.ones(4, 3, dtype=F64))
    with pytest.raises(ValueError, match=r"^batch shapes do not broadcast: t \(3,\), .*pos_amplitude \(4,\)"):
        traj.state(t)
    with pytest.raises(ValueError, match=r"^batch shapes do not broadcast: t \(3,\), .*pos_amplitude \(4,\)"):
        traj.imu(t, gravity_vector(dtype=F64))
    # a parameter batch (4, 1) broadcasts with t (3,): (4, 3) states, each row its own amplitude
    amp = torch.arange(1.0, 5.0, dtype=F64)[:, None, None] * torch.ones(4, 1, 3, dtype=F64)
    t = torch.tensor([0.1, 0.2, 0.3], dtype=F64)
    p = SinusoidalTrajectory(pos_amplitude=amp).state(t).position()
    ref = SinusoidalTrajectory(pos_amplitude=(1.0, 1.0, 1.0)).state(t).position()
    assert p.shape == (4, 3, 3)
    assert (p - torch.arange(1.0, 5.0, dtype=F64)[:, None, None] * ref).abs().max() < 1e-14


def test_gtsam_params_refuse_negative_or_non_finite_densities():
    """peers.gtsam_params checks the densities and the gravity magnitude before GTSAM is imported
    (unchecked, a density of -1e-3 would be squared into a valid covariance, a NaN magnitude taken)."""
    from torchsgal.imu import peers
    for name, bad in (("gyro_noise_density", -1e-3), ("acc_noise_density", float("nan")),
                      ("integration_sigma", -1.0), ("magnitude", float("nan")), ("magnitude", -9.8)):
        with pytest.raises(ValueError, match=rf"^{name} must be a finite number >= 0, got"):
            peers.gtsam_params(**{name: bad})
    with pytest.raises(TypeError, match=r"^gyro_noise_density must be a finite number >= 0, got True"):
        peers.gtsam_params(gyro_noise_density=True)


def test_pypose_predict_and_navstates_check_dtypes_first():
    """pypose_predict names a float32 start beside float64 samples (pypose would fail on it:
    "expected scalar type Float but found Double"); from_gtsam_navstate names an integer or a
    list time (not "rotation", nor an AttributeError)."""
    from torchsgal.imu import peers
    gyro, acc, dt, _, _ = samples((1,), 5, seed=5)
    start = SGal3.identity((1,), dtype=torch.float32)
    with pytest.raises(TypeError, match=r"^start has dtype torch.float32 but gyro has dtype torch.float64"):
        peers.pypose_predict(gyro, acc, dt, start)
    with pytest.raises(TypeError, match=r"^acc has dtype torch.float32 but gyro has dtype torch.float64"):
        peers.pypose_predict(gyro, acc.float(), dt, SGal3.identity((1,), dtype=F64))
    with pytest.raises(TypeError, match=r"^time must have a floating dtype"):
        peers.from_gtsam_navstate([], torch.zeros(0, dtype=torch.int64))
    with pytest.raises(TypeError, match=r"^time must be a torch.Tensor, got list"):
        peers.from_gtsam_navstate([], [])
