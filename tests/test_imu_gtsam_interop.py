"""torchsgal.imu against GTSAM's preintegration through torchsgal.imu.gtsam_interop: parameter
conversions, increments and covariances (combined with the bias random walk) on the same
samples, and the IMU-to-body extrinsic.

GTSAM integrates with a first-order scheme (R_{k+1} = R_k Exp(w dt), v_{k+1} = v_k + R_k a dt,
p_{k+1} = p_k + v_k dt + R_k a dt^2 / 2), torchsgal exactly: their difference is GTSAM's
discretisation error.  The tests check GTSAM against that scheme written here (to rounding) and
the difference to torchsgal against its order: halving dt halves it (increment, covariance
correlations and cross terms), and at dt = 5 ms over 1 s it is below the bounds stated.
"""
from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
import torch

from torchsgal import SE3
from torchsgal.imu import gravity_vector, preintegrate
from torchsgal.imu import gtsam_interop as gi
from torchsgal.imu.streaming import StreamingPreintegration

gtsam = pytest.importorskip("gtsam")

F64 = torch.float64
W = torch.tensor([0.4, -0.3, 0.6], dtype=F64)
A = torch.tensor([1.0, 0.5, 9.8], dtype=F64)
NOISE = dict(gyro_noise_density=0.01, acc_noise_density=0.1)
WALK = dict(gyro_bias_random_walk=1e-3, acc_bias_random_walk=1e-2)


def constant(dt, T=1.0):
    K = int(round(T / dt))
    return W.expand(K, 3), A.expand(K, 3)


def first_order_scheme(gyro, acc, dt):
    """GTSAM's discretisation, written out (numpy)."""
    R, v, p = np.eye(3), np.zeros(3), np.zeros(3)
    for w, a in zip(gyro.numpy(), acc.numpy()):
        p = p + v * dt + 0.5 * R @ a * dt**2
        v = v + R @ a * dt
        th = w * dt
        R = R @ scipy.linalg.expm(np.array([[0, -th[2], th[1]], [th[2], 0, -th[0]], [-th[1], th[0], 0]]))
    return R, v, p


def correlation_error(X, P):
    sd = P.diagonal().sqrt()
    sd = torch.where(sd > 0, sd, torch.ones_like(sd))
    return (X - P) / sd[:, None] / sd[None, :]


def test_params_round_trip():
    body = SE3.exp(torch.tensor([0.1, -0.2, 0.05, 0.3, -0.1, 0.2], dtype=F64))
    dens = dict(gyro_noise_density=torch.tensor([1e-3, 2e-3, 3e-3], dtype=F64), acc_noise_density=0.02)
    p = gi.to_gtsam_params(gravity_vector("ned", dtype=F64), body_P_sensor=body, **dens)
    assert type(p) is gtsam.PreintegrationParams
    m = gi.from_gtsam_params(p)
    assert torch.allclose(m["gravity"], torch.tensor([0, 0, 9.80665], dtype=F64), rtol=0, atol=1e-15)
    assert torch.allclose(m["gyro_noise_density"], dens["gyro_noise_density"], rtol=1e-15, atol=0)
    assert torch.allclose(m["acc_noise_density"], torch.full((3,), 0.02, dtype=F64), rtol=1e-15, atol=0)
    assert torch.allclose(m["body_P_sensor"].as_matrix(), body.as_matrix(), rtol=0, atol=1e-15)
    assert not m["integration_covariance"].any() and "gyro_bias_random_walk" not in m
    c = gi.to_gtsam_params(gravity_vector(dtype=F64), **NOISE, **WALK)
    assert type(c) is gtsam.PreintegrationCombinedParams
    m = gi.from_gtsam_params(c)
    assert torch.allclose(m["acc_bias_random_walk"], torch.full((3,), 1e-2, dtype=F64), rtol=1e-15, atol=0)
    assert m["body_P_sensor"] is None
    s = gi.streaming_from_gtsam_params(c)
    gyro, acc = constant(0.01)
    s.integrate(gyro, acc, 0.01)
    ref = StreamingPreintegration(dtype=F64, **NOISE, **WALK)
    ref.integrate(gyro, acc, 0.01)
    assert torch.allclose(s.combined_covariance(), ref.combined_covariance(), rtol=1e-13, atol=0)
    correlated = gtsam.PreintegrationParams.MakeSharedU(9.8)
    correlated.setGyroscopeCovariance(np.array([[1.0, 0.1, 0], [0.1, 1.0, 0], [0, 0, 1.0]]))
    with pytest.raises(ValueError, match="gyroscope covariance must be diagonal"):
        gi.from_gtsam_params(correlated)
    with pytest.raises(ValueError, match="give both gyro_bias_random_walk and acc_bias_random_walk"):
        gi.to_gtsam_params(gravity_vector(dtype=F64), gyro_bias_random_walk=1e-3)
    with pytest.raises(TypeError, match="params must be gtsam.PreintegrationParams"):
        gi.from_gtsam_params("params")


def test_gtsam_follows_the_first_order_scheme_and_converges_to_the_exact_increment():
    params = gi.to_gtsam_params(gravity_vector(dtype=F64), **NOISE)
    errors = []
    for dt in (0.02, 0.01, 0.005):
        gyro, acc = constant(dt)
        pim = gi.gtsam_pim(gyro, acc, dt, params)
        R, v, p = first_order_scheme(gyro, acc, dt)
        assert np.abs(pim.deltaRij().matrix() - R).max() < 1e-12
        assert np.abs(np.asarray(pim.deltaVij()) - v).max() < 1e-12
        assert np.abs(np.asarray(pim.deltaPij()) - p).max() < 1e-12
        ours = preintegrate(gyro, acc, dt, covariance=False, bias_jacobian=False).delta.as_matrix()
        errors.append(float((gi.from_gtsam_pim(pim).delta.as_matrix() - ours).abs().max()))
    assert 1.8 < errors[0] / errors[1] < 2.2 and 1.8 < errors[1] / errors[2] < 2.2
    assert errors[2] < 0.011  # v: |w x a| dt T / 2 ~ 0.01 m/s at 5 ms over 1 s


def test_combined_covariance_against_gtsam():
    """Navigation block, cross terms (GTSAM's sign: those of -db) and the bias block."""
    params = gi.to_gtsam_params(gravity_vector(dtype=F64), **NOISE, **WALK)
    nav, cross = [], []
    for dt in (0.02, 0.01, 0.005):
        gyro, acc = constant(dt)
        pim = gi.gtsam_pim(gyro, acc, dt, params)
        assert isinstance(pim, gtsam.PreintegratedCombinedMeasurements)
        pre, full = gi.from_gtsam_pim(pim)
        s = StreamingPreintegration(dtype=F64, **NOISE, **WALK)
        s.integrate(gyro, acc, dt)
        P = s.combined_covariance()
        err = correlation_error(full, P)
        nav.append(float(err[:10, :10].abs().max()))
        cross.append(float(err[:10, 10:].abs().max()))
        assert torch.allclose(full[10:, 10:], P[10:, 10:], rtol=1e-12, atol=0)  # R T, both exact
        assert torch.equal(pre.covariance, full[:10, :10])
        # the inverse conversion gives GTSAM's matrix back
        back = gi.to_gtsam_covariance(full, pre.delta)
        assert np.abs(back - np.asarray(pim.preintMeasCov())).max() < 1e-12 * np.abs(back).max()
    for errs in (nav, cross):
        assert 1.8 < errs[0] / errs[1] < 2.2 and 1.8 < errs[1] / errs[2] < 2.2
    assert nav[2] < 3e-3 and cross[2] < 2e-4  # correlations, 5 ms over 1 s
    # the plain measurements: the navigation block alone, the same numbers
    plain = gi.gtsam_pim(*constant(0.005), 0.005, gi.to_gtsam_params(gravity_vector(dtype=F64), **NOISE))
    pre = gi.from_gtsam_pim(plain)
    assert pre.bias_jacobian is None and pre.covariance.shape == (10, 10) and not pre.covariance[9].any()
    assert np.abs(gi.to_gtsam_covariance(pre.covariance, pre.delta) - np.asarray(plain.preintMeasCov())).max() \
        < 1e-12 * np.abs(np.asarray(plain.preintMeasCov())).max()


def test_sensor_to_body_matches_gtsams_body_P_sensor():
    """GTSAM with body_P_sensor on sensor samples = GTSAM without it on sensor_to_body's samples
    (GTSAM keeps the centripetal term only: no angular acceleration), to rounding."""
    body = SE3.exp(torch.tensor([0.2, -0.1, 0.3, 0.4, -0.2, 0.7], dtype=F64))
    g = torch.Generator().manual_seed(0)
    gyro = torch.randn(50, 3, generator=g, dtype=F64)
    acc = torch.randn(50, 3, generator=g, dtype=F64) + torch.tensor([0, 0, 9.8], dtype=F64)
    with_pose = gi.gtsam_pim(gyro, acc, 0.01,
                             gi.to_gtsam_params(gravity_vector(dtype=F64), body_P_sensor=body, **NOISE))
    w, f = gi.sensor_to_body(gyro, acc, body)
    plain = gi.gtsam_pim(w, f, 0.01, gi.to_gtsam_params(gravity_vector(dtype=F64), **NOISE))
    a, b = gi.from_gtsam_pim(with_pose), gi.from_gtsam_pim(plain)
    assert (a.delta.as_matrix() - b.delta.as_matrix()).abs().max() < 1e-12
    # Covariance: GTSAM also carries gyro noise into the specific force through the lever arm
    # (d(w x (w x r))/dw), which converted samples with body-frame densities do not: with the
    # sensor at the body's origin (a rotation only, isotropic densities) they are the same.
    turned = SE3.exp(torch.tensor([0, 0, 0, 0.4, -0.2, 0.7], dtype=F64))
    with_pose = gi.gtsam_pim(gyro, acc, 0.01,
                             gi.to_gtsam_params(gravity_vector(dtype=F64), body_P_sensor=turned, **NOISE))
    w, f = gi.sensor_to_body(gyro, acc, turned)
    plain = gi.gtsam_pim(w, f, 0.01, gi.to_gtsam_params(gravity_vector(dtype=F64), **NOISE))
    a, b = gi.from_gtsam_pim(with_pose), gi.from_gtsam_pim(plain)
    assert (a.delta.as_matrix() - b.delta.as_matrix()).abs().max() < 1e-12
    assert ((a.covariance - b.covariance).abs().max() / b.covariance.abs().max()) < 1e-12


def test_sensor_to_body_euler_and_centripetal_terms():
    """A rigid body with omega_b(t) = w0 + alpha t and specific force f_b at its origin; the
    sensor at r, rotated by R_bs, measures R_bs^T (f_b + alpha x r + omega x (omega x r))."""
    R_bs = SE3.exp(torch.tensor([0, 0, 0, 0.3, 0.5, -0.2], dtype=F64)).rotation()
    r = torch.tensor([0.3, -0.2, 0.1], dtype=F64)
    body = SE3.from_components(rotation=R_bs, position=r)
    Rb = body.rotation()
    t = torch.arange(20, dtype=F64) * 0.01
    alpha = torch.tensor([0.5, -1.0, 2.0], dtype=F64)
    omega_b = torch.tensor([0.2, 0.1, -0.3], dtype=F64) + t[:, None] * alpha
    f_b = torch.tensor([0.1, 0.2, 9.8], dtype=F64).expand(20, 3)
    lever = torch.linalg.cross(alpha.expand(20, 3), r.expand(20, 3)) + torch.linalg.cross(
        omega_b, torch.linalg.cross(omega_b, r.expand(20, 3)))
    gyro_s = omega_b @ Rb  # R_bs^T omega_b, row-wise
    acc_s = (f_b + lever) @ Rb
    w, f = gi.sensor_to_body(gyro_s, acc_s, body, dt=0.01)  # alpha from the rate: exact for linear omega
    assert (w - omega_b).abs().max() < 1e-14 and (f - f_b).abs().max() < 1e-12
    w, f = gi.sensor_to_body(gyro_s, acc_s, body, angular_acceleration=alpha.expand(20, 3))
    assert (f - f_b).abs().max() < 1e-12
    _, f = gi.sensor_to_body(gyro_s, acc_s, body)  # no Euler term: off by alpha x r
    assert torch.allclose(f - f_b, torch.linalg.cross(alpha, r).expand(20, 3), rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="needs K >= 2 samples"):
        gi.sensor_to_body(gyro_s[:1], acc_s[:1], body, dt=0.01)
    with pytest.raises(TypeError, match="body_P_sensor must be an SE3"):
        gi.sensor_to_body(gyro_s, acc_s, "pose")


def gtsam_bias_jacobian_fd(pim, eps=1e-6):
    """d[theta, p, v] / d[b_a, b_g] of GTSAM's bias-corrected prediction (first order in GTSAM,
    so central differences are exact up to rounding), from the identity with no gravity."""
    from torchsgal import SO3
    cols = []
    for i in range(6):
        vals = []
        for sign in (1.0, -1.0):
            b = np.zeros(6)
            b[i] = sign * eps
            nav = pim.predict(gtsam.NavState(), gtsam.imuBias.ConstantBias(b[:3], b[3:]))
            theta = SO3.from_matrix(torch.tensor(nav.attitude().matrix(), dtype=F64)).log().numpy()
            vals.append(np.concatenate((theta, np.asarray(nav.position()), np.asarray(nav.velocity()))))
        cols.append((vals[0] - vals[1]) / (2 * eps))
    return np.stack(cols, axis=1)


def test_bias_jacobian_against_gtsam():
    """torchsgal's bias Jacobian in GTSAM's chart and bias order against GTSAM's own (through its
    bias-corrected prediction): the difference is GTSAM's discretisation, halved with dt."""
    params = gi.to_gtsam_params(torch.zeros(3, dtype=F64), **NOISE)
    errors = []
    for dt in (0.02, 0.01, 0.005):
        gyro, acc = constant(dt)
        ref = gtsam_bias_jacobian_fd(gi.gtsam_pim(gyro, acc, dt, params))
        pre = preintegrate(gyro, acc, dt)
        ours = gi.to_gtsam_bias_jacobian(pre.bias_jacobian, pre.delta)
        assert ours.shape == (9, 6)
        errors.append(np.abs(ours - ref).max() / np.abs(ref).max())
    assert 1.8 < errors[0] / errors[1] < 2.2 and 1.8 < errors[1] / errors[2] < 2.2
    assert errors[2] < 6e-3  # 0.95 dt per second of window, first order
    with pytest.raises(ValueError, match=r"bias_jacobian must have shape \(10, 6\)"):
        gi.to_gtsam_bias_jacobian(torch.zeros(9, 6, dtype=F64), pre.delta)
