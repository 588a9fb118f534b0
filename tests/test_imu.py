"""Galilean IMU preintegration (torchsgal.imu): each result against something independent.

- increments against scipy's expm of the algebra element (constant inputs, any dt);
- the parallel scan against a sequential product;
- prediction against analytic motions and a scipy ODE solution of mahony (29);
- covariance against the sequential recursion of the brief on a subdivided stream, and
  against a Monte Carlo of noisy streams (NEES inside the chi-square 95% band);
- bias Jacobians against central finite differences of full re-integration.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.linalg
import scipy.stats
import torch
from scipy.integrate import solve_ivp

from torchsgal import SGal3
from torchsgal.imu import (
    Preintegration,
    earth_rate_vector,
    gravity_vector,
    increment_tangents,
    predict,
    predict_jacobians,
    preintegrate,
    suffix_products,
    window_product,
)
from torchsgal.imu.moments import noise_map
from torchsgal.imu.trajectory import SinusoidalTrajectory

F64 = torch.float64


def algebra(omega, a, kappa=1.0):
    """mahony (10)/(15)-(16): U(omega, a) + kappa N as a 5 x 5 numpy matrix."""
    w = np.asarray(omega, float)
    U = np.zeros((5, 5))
    U[:3, :3] = [[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]
    U[:3, 3] = a
    U[3, 4] = kappa
    return U


def random_stream(B, K, seed, dt_range=(0.002, 0.012), rate=1.0, acc=3.0, dtype=F64):
    g = torch.Generator().manual_seed(seed)
    gyro = rate * torch.randn(B, K, 3, generator=g, dtype=dtype)
    f = acc * torch.randn(B, K, 3, generator=g, dtype=dtype)
    dt = dt_range[0] + (dt_range[1] - dt_range[0]) * torch.rand(B, K, generator=g, dtype=dtype)
    return gyro, f, dt


# ------------------------------------------------------------------------- increments
@pytest.mark.parametrize("dt", [1e-3, 0.05, 0.5, 2.0])
def test_constant_inputs_match_expm_for_any_dt(dt):
    omegas = [[0.0, 0.0, 0.0], [1e-9, 0.0, 0.0], [0.3, -0.2, 0.5], [0.0, 0.0, 3.0], [2.0, 1.0, -1.5]]
    accs = [[0.1, 0.2, 9.8], [1.0, -2.0, 0.5], [0.0, 0.0, 0.0], [3.0, 0.0, -1.0], [-0.5, 0.7, 4.0]]
    K = 7
    gyro = torch.tensor(omegas, dtype=F64)[:, None, :].expand(-1, K, 3)
    acc = torch.tensor(accs, dtype=F64)[:, None, :].expand(-1, K, 3)
    h = torch.full((len(omegas), K), dt, dtype=F64)
    for cov in (False, True):
        delta = preintegrate(gyro, acc, h, covariance=cov, bias_jacobian=cov).delta.as_matrix().numpy()
        for i, (w, a) in enumerate(zip(omegas, accs)):
            ref = scipy.linalg.expm(algebra(w, a) * K * dt)
            scale = max(1.0, np.abs(ref).max())
            np.testing.assert_allclose(delta[i], ref, rtol=0, atol=1e-14 * scale)  # measured 1.6e-15


def test_constant_inputs_closed_form_and_varying_dt():
    # R = Exp(w T), v = Gamma_1(w T) a T, p = Gamma_2(w T) a T^2 (barfoot N(phi) = Gamma_2),
    # written with Rodrigues coefficients; the samples' dt vary, only their sum matters.
    w, a = np.array([0.4, -1.1, 0.7]), np.array([1.5, 0.3, -9.0])
    h = torch.tensor([0.01, 0.3, 0.002, 0.15, 0.07], dtype=F64)
    T = float(h.sum())
    K = h.numel()
    delta = preintegrate(torch.tensor(w).expand(K, 3), torch.tensor(a).expand(K, 3), h).delta
    th = np.linalg.norm(w * T)
    P = algebra(w * T, [0, 0, 0], 0.0)[:3, :3]
    c = [(1 - math.cos(th)) / th**2, (th - math.sin(th)) / th**3, (th**2 / 2 - 1 + math.cos(th)) / th**4]
    R = np.eye(3) + math.sin(th) / th * P + c[0] * P @ P
    G1 = np.eye(3) + c[0] * P + c[1] * P @ P
    G2 = 0.5 * np.eye(3) + c[1] * P + c[2] * P @ P
    np.testing.assert_allclose(delta.rotation().numpy(), R, rtol=0, atol=1e-12)
    np.testing.assert_allclose(delta.velocity().numpy(), G1 @ a * T, rtol=0, atol=1e-12)
    np.testing.assert_allclose(delta.position().numpy(), G2 @ a * T**2, rtol=0, atol=1e-12)
    assert abs(float(delta.time()) - T) < 1e-15


def test_float32_matches_float64():
    gyro, acc, dt = random_stream(4, 200, seed=3)
    dens = dict(gyro_noise_density=1e-3, acc_noise_density=1e-2, time_noise_density=1e-4)
    r64 = preintegrate(gyro, acc, dt, **dens)
    r32 = preintegrate(gyro.float(), acc.float(), dt.float(), **dens)
    ref = r64.delta.as_matrix()
    assert torch.allclose(r32.delta.as_matrix().double(), ref, rtol=0, atol=2e-5 * ref.abs().max())
    sd = r64.covariance.diagonal(dim1=-2, dim2=-1).sqrt()
    rel = (r32.covariance.double() - r64.covariance).abs() / sd.unsqueeze(-1) / sd.unsqueeze(-2)
    assert float(rel.max()) < 2e-6  # measured 1.8e-7
    J = r64.bias_jacobian
    assert torch.allclose(r32.bias_jacobian.double(), J, rtol=0, atol=1e-5 * J.abs().max())  # 1.1e-6


@pytest.mark.parametrize("K", [1, 2, 3, 8, 13, 64])
def test_scan_matches_sequential_product(K):
    g = torch.Generator().manual_seed(K)
    E = torch.linalg.matrix_exp(0.4 * torch.randn(3, K, 5, 5, generator=g, dtype=F64))
    seq, ref = torch.eye(5, dtype=F64).expand(3, 5, 5), []
    for k in reversed(range(K)):
        seq = E[:, k] @ seq
        ref.append(seq)
    ref = torch.stack(ref[::-1], dim=1)
    assert torch.allclose(suffix_products(E), ref, rtol=0, atol=1e-13 * ref.abs().max())
    assert torch.allclose(window_product(E), ref[:, 0], rtol=0, atol=1e-13 * ref.abs().max())


def test_tangents_are_mahony_inputs():
    # exp(xi_k) = expm((U(omega - b_g, f - b_a) + N) dt): the ordering conversion at the boundary.
    gyro, acc, dt = random_stream(1, 4, seed=5)
    bg, ba = torch.tensor([0.01, -0.02, 0.03], dtype=F64), torch.tensor([0.1, 0.0, -0.2], dtype=F64)
    xi = increment_tangents(gyro, acc, dt, bg, ba)
    for k in range(4):
        U = algebra((gyro[0, k] - bg).numpy(), (acc[0, k] - ba).numpy()) * float(dt[0, k])
        np.testing.assert_allclose(SGal3.exp(xi[0, k]).as_matrix().numpy(), scipy.linalg.expm(U), rtol=0, atol=1e-14)


def test_gradients_through_preintegration():
    gyro, acc, dt = random_stream(2, 5, seed=9)
    gyro.requires_grad_(True)
    acc.requires_grad_(True)
    fn = lambda g, a: preintegrate(g, a, dt, covariance=False, bias_jacobian=False).delta.as_matrix()
    assert torch.autograd.gradcheck(fn, (gyro, acc))


def test_noise_map_is_adjoint_columns():
    F = SGal3.random((4, 3), dtype=F64, generator=torch.Generator().manual_seed(2))
    ref = F.adjoint()[..., 3:10].movedim(-3, -1)  # nodes along the last axis
    assert torch.allclose(noise_map(F), ref, rtol=0, atol=1e-13)
    scale = torch.rand(4, 3, dtype=F64, generator=torch.Generator().manual_seed(3))
    assert torch.allclose(noise_map(F, scale), ref * scale[:, None, None, :], rtol=0, atol=1e-13)


# -------------------------------------------------------------------------- prediction
@pytest.mark.parametrize("frame", ["z_up", "ned"])
def test_predict_free_fall_and_rest(frame):
    g = gravity_vector(frame, 9.81, dtype=F64)
    gen = torch.Generator().manual_seed(0)
    X0 = SGal3.random((3,), dtype=F64, generator=gen)
    K, h = 20, 0.05
    T = K * h
    dt = torch.full((3, K), h, dtype=F64)
    # free fall: no specific force, the body spins freely
    gyro = torch.tensor([0.3, -0.1, 0.2], dtype=F64).expand(3, K, 3)
    X1 = predict(X0, preintegrate(gyro, torch.zeros(3, K, 3, dtype=F64), dt).delta, g)
    assert torch.allclose(X1.velocity(), X0.velocity() + g * T, rtol=0, atol=1e-12)
    assert torch.allclose(X1.position(), X0.position() + X0.velocity() * T + 0.5 * g * T**2, rtol=0, atol=1e-12)
    assert torch.allclose(X1.time(), X0.time() + T, rtol=0, atol=1e-14)
    # unaccelerated: the accelerometer reads -R^T g, no rotation: inertial motion p0 + v0 T
    f = -(X0.rotation().transpose(-1, -2) @ g)[:, None, :].expand(3, K, 3)
    X2 = predict(X0, preintegrate(torch.zeros(3, K, 3, dtype=F64), f, dt).delta, g)
    assert torch.allclose(X2.as_matrix()[..., :3, :4], X0.as_matrix()[..., :3, :4], rtol=0, atol=1e-12)
    assert torch.allclose(X2.position(), X0.position() + X0.velocity() * T, rtol=0, atol=1e-12)


def _ode_reference(X0, gyro, acc, dt, g, Omega):
    """scipy DOP853 on mahony (29) (sign of g_A e3 corrected; see docs/guide/imu.md) with Xdot = ...,
    sample by sample (inputs constant on each interval)."""
    W = algebra(Omega, [0, 0, 0], 0.0)[:3, :3]
    y = np.concatenate([X0.rotation().numpy().ravel(), X0.velocity().numpy(), X0.position().numpy(),
                        [float(X0.time())]])

    def rhs(_, y, w, f):
        R, v, p = y[:9].reshape(3, 3), y[9:12], y[12:15]
        dR = -W @ R + R @ algebra(w, [0, 0, 0], 0.0)[:3, :3]
        return np.concatenate([dR.ravel(), -np.cross(Omega, v) + g + R @ f, -np.cross(Omega, p) + v, [1.0]])

    for k in range(gyro.shape[0]):
        sol = solve_ivp(rhs, (0.0, float(dt[k])), y, method="DOP853", rtol=1e-12, atol=1e-13,
                        args=(gyro[k].numpy(), acc[k].numpy()))
        y = sol.y[:, -1]
    return y


def test_predict_with_earth_rotation_matches_ode():
    # An exaggerated Earth rate (0.2 rad/s) so that every term of (29) matters.
    g = gravity_vector("ned", 9.8, dtype=F64)
    Omega = torch.tensor([0.12, -0.05, -0.15], dtype=F64)
    gyro, acc, dt = random_stream(2, 12, seed=11, dt_range=(0.02, 0.1))
    X0 = SGal3.random((2,), dtype=F64, generator=torch.Generator().manual_seed(4))
    X1 = predict(X0, preintegrate(gyro, acc, dt).delta, g, Omega)
    for b in range(2):
        y = _ode_reference(X0[b], gyro[b], acc[b], dt[b], g.numpy(), Omega.numpy())
        got = np.concatenate([X1[b].rotation().numpy().ravel(), X1[b].velocity().numpy(),
                              X1[b].position().numpy(), [float(X1[b].time())]])
        np.testing.assert_allclose(got, y, rtol=0, atol=1e-13)  # measured 1.2e-14 (entries up to 7)


@pytest.mark.parametrize("frame", ["z_up", "ned"])
def test_point_fixed_on_rotating_earth_stays_fixed(frame):
    # A body fixed in the Earth frame at p: inertial velocity v = Omega x p, gyro R^T Omega,
    # specific force R^T (Omega x (Omega x p) - g).  (29) with the corrected sign keeps it there.
    g = gravity_vector(frame, 9.8, dtype=F64)
    Omega = earth_rate_vector(math.radians(48.0), frame, dtype=F64)
    R = SGal3.random((), dtype=F64, generator=torch.Generator().manual_seed(1)).rotation()
    p = torch.tensor([3e3, -2e3, 50.0], dtype=F64)
    v = torch.linalg.cross(Omega, p)
    X0 = SGal3.from_components(rotation=R, velocity=v, position=p, time=torch.tensor(7.0, dtype=F64))
    K, h = 100, 0.1
    gyro = (R.T @ Omega).expand(K, 3)
    acc = (R.T @ (torch.linalg.cross(Omega, v) - g)).expand(K, 3)
    X1 = predict(X0, preintegrate(gyro, acc, torch.full((K,), h, dtype=F64)).delta, g, Omega)
    assert torch.allclose(X1.rotation(), R, rtol=0, atol=1e-12)
    assert torch.allclose(X1.velocity(), v, rtol=0, atol=1e-9)
    assert torch.allclose(X1.position(), p, rtol=0, atol=1e-8)
    # the printed sign (- g_A e3 in (29b)/(31)) would make it fall at 2 g: 0.5 * 2 * 9.8 * 100 m
    assert abs(float(X1.time()) - 17.0) < 1e-12


def test_trajectory_imu_matches_finite_differences():
    traj = SinusoidalTrajectory()
    g = gravity_vector("z_up", dtype=F64)
    t = torch.tensor([0.3, 1.9], dtype=F64)
    gyro, acc = traj.imu(t, g)
    e = 1e-5
    Xm, X, Xp = traj.state(t - e), traj.state(t), traj.state(t + e)
    Rdot = (Xp.rotation() - Xm.rotation()) / (2 * e)
    W = X.rotation().transpose(-1, -2) @ Rdot
    omega = torch.stack((W[..., 2, 1], W[..., 0, 2], W[..., 1, 0]), dim=-1)
    assert torch.allclose(omega, gyro, rtol=0, atol=1e-8)
    a_world = (Xp.velocity() - Xm.velocity()) / (2 * e)
    assert torch.allclose((X.rotation() @ acc.unsqueeze(-1)).squeeze(-1) + g, a_world, rtol=0, atol=1e-7)
    assert torch.allclose((Xp.position() - Xm.position()) / (2 * e), X.velocity(), rtol=0, atol=1e-8)


def test_sinusoid_midpoint_samples_converge_at_second_order():
    traj = SinusoidalTrajectory()
    g = gravity_vector("z_up", dtype=F64)
    t0 = torch.tensor([0.0, 0.7, 2.3], dtype=F64)
    X0, X1 = traj.state(t0), traj.state(t0 + 1.0)
    errs = []
    for h in (0.02, 0.01, 0.005):
        gyro, acc, dt = traj.stream(t0, 1.0, h, g)
        Xp = preintegrate(gyro, acc, dt, covariance=False, bias_jacobian=False).predict(X0, g)
        errs.append(float((Xp.position() - X1.position()).norm(dim=-1).max()))
    assert errs[0] / errs[1] > 3.5 and errs[1] / errs[2] > 3.5, errs



def test_trajectory_checks_its_arguments():
    traj = SinusoidalTrajectory()
    g = gravity_vector("z_up", dtype=F64)
    t0 = torch.tensor(0.0, dtype=F64)
    for duration, dt in ((-1.0, -0.1), (1.0, -0.1), (1.0, 0.0), (1.0, math.nan), (math.inf, 0.1)):
        bad = "duration" if not 0 < duration < math.inf else "dt"
        with pytest.raises(ValueError, match=f"{bad} must be a finite number > 0"):
            traj.stream(t0, duration, dt, g)
    with pytest.raises(TypeError, match="t0 must be a torch.Tensor, got float"):
        traj.stream(0.0, 1.0, 0.1, g)
    with pytest.raises(TypeError, match="gravity has dtype torch.float64 but t0 has dtype torch.float32"):
        traj.stream(t0.float(), 1.0, 0.1, g)
    with pytest.raises(ValueError, match=r"gravity must have shape \(\.\.\., 3\), got \(2,\)"):
        traj.imu(t0, g[:2])
    with pytest.raises(TypeError, match="gravity has dtype torch.float32 but t has dtype torch.float64"):
        traj.imu(t0, g.float())  # not promoted silently
    with pytest.raises(ValueError, match=r"batch shapes do not broadcast: t \(3,\), gravity \(2,\)"):
        traj.imu(torch.zeros(3, dtype=F64), g.expand(2, 3))
    with pytest.raises(TypeError, match="t must have a floating dtype"):
        traj.state(torch.tensor(1))
    with pytest.raises(ValueError, match=r"rot_amplitude must be a 3-vector .* got shape \(2,\)"):
        SinusoidalTrajectory(rot_amplitude=(1.0, 2.0)).state(t0)
    gyro, acc, dt = traj.stream(t0, 1.0, 0.25, g)
    assert gyro.shape == acc.shape == (4, 3) and torch.equal(dt, torch.full((4,), 0.25, dtype=F64))

# -------------------------------------------------------------------------- covariance
def _sequential_covariance(gyro, acc, dt, s_g, s_a, s_t):
    """The brief's recursion, Sigma <- Ad(E^-1) Sigma Ad(E^-1)^T + J_r Q J_r^T (noise held
    constant over each sample), with the core's adjoint and J_r; s_g, s_a per axis (3,)."""
    xi = increment_tangents(gyro, acc, dt)
    B, K = xi.shape[:2]
    Sig = torch.zeros(B, 10, 10, dtype=F64)
    q = torch.cat((torch.as_tensor(s_a, dtype=F64).expand(3), torch.as_tensor(s_g, dtype=F64).expand(3),
                   torch.tensor([s_t], dtype=F64))) ** 2
    for k in range(K):
        A = SGal3.exp(xi[:, k]).inverse().adjoint()
        Bk = SGal3.jr(xi[:, k])[..., 3:10]
        Sig = A @ Sig @ A.transpose(-1, -2) + Bk @ torch.diag_embed(q * dt[:, k, None]) @ Bk.transpose(-1, -2)
    return Sig


def _subdivided(x, m, is_dt=False):
    return x.repeat_interleave(m, dim=1) / m if is_dt else x.repeat_interleave(m, dim=1)


@pytest.mark.parametrize("per_axis", [False, True])
def test_covariance_converges_to_the_sequential_recursion(per_axis):
    # Both discretise the same continuous-time integral.  The brief's recursion on a stream
    # subdivided m-fold (the same piecewise-constant inputs) converges to it as O((dt/m)^2):
    # Richardson over m = 8, 16 gives the limit.  Ours (Simpson) converges as O(dt^4): its error
    # drops about 16-fold when our own stream is subdivided 2-fold (measured 15.8 and 16.0; a
    # third-order error would drop 8-fold).  Isotropic densities (floats)
    # take the closed-form path, per-axis ones the general path.
    gyro, acc, dt = random_stream(1, 6, seed=21, dt_range=(0.01, 0.03), rate=2.0, acc=5.0)
    if per_axis:
        s_g, s_a = torch.tensor([2e-3, 1e-3, 4e-3], dtype=F64), torch.tensor([3e-2, 5e-2, 1e-2], dtype=F64)
    else:
        s_g, s_a = 2e-3, 3e-2
    refs = [_sequential_covariance(_subdivided(gyro, m), _subdivided(acc, m), _subdivided(dt, m, True), s_g, s_a, 1e-3)
            for m in (8, 16)]
    limit = (4 * refs[1] - refs[0]) / 3
    sd = limit.diagonal(dim1=-2, dim2=-1).sqrt()
    errs = []
    for m in (1, 2):
        cov = preintegrate(_subdivided(gyro, m), _subdivided(acc, m), _subdivided(dt, m, True), gyro_noise_density=s_g,
                           acc_noise_density=s_a, time_noise_density=1e-3).covariance
        errs.append(float(((cov - limit).abs() / sd.unsqueeze(-1) / sd.unsqueeze(-2)).max()))
    seq_err = float(((refs[1] - limit).abs() / sd.unsqueeze(-1) / sd.unsqueeze(-2)).max())
    assert errs[0] < seq_err, (errs, seq_err)  # ours at dt beats the recursion at dt / 16
    assert errs[1] < errs[0] / 12, errs  # fourth order


@pytest.mark.parametrize("per_axis", [False, True])
@pytest.mark.parametrize("K", [1, 2, 8])
def test_covariance_at_rest_is_the_continuous_integral(K, per_axis):
    """At rest with accelerometer noise only, the integral int_0^T Ad(F(s)) G Q_c G^T Ad(F(s))^T
    ds is, by hand (velocity error s_a W(s), position error its integral): nu block s_a^2 T,
    rho block s_a^2 T^3/3, cross s_a^2 T^2/2 (each times I), nothing else.  Noise held over
    each sample would give s_a^2 dt^3 (K^3/3 - K/12) for the rho block (the docstring's
    factor 1 / (1 - 1/(4 K^2)), 4/3 at K = 1): this pins down which model is computed."""
    dt, s_a = 0.1, 0.5
    z = torch.zeros(1, K, 3, dtype=F64)
    if per_axis:
        dens = dict(gyro_noise_density=torch.zeros(3, dtype=F64), acc_noise_density=torch.full((3,), s_a, dtype=F64))
    else:
        dens = dict(gyro_noise_density=0.0, acc_noise_density=s_a)
    cov = preintegrate(z, z, torch.full((1, K), dt, dtype=F64), **dens).covariance[0]
    T, q, eye = K * dt, s_a ** 2, torch.eye(3, dtype=F64)
    want = torch.zeros(10, 10, dtype=F64)
    want[:3, :3], want[3:6, 3:6] = q * T ** 3 / 3 * eye, q * T * eye
    want[:3, 3:6] = want[3:6, :3] = q * T ** 2 / 2 * eye
    torch.testing.assert_close(cov, want, rtol=0, atol=1e-15)
    held = q * dt ** 3 * (K ** 3 / 3 - K / 12)
    assert abs(float(cov[0, 0]) / held - 1 / (1 - 1 / (4 * K ** 2))) < 1e-12


def test_per_axis_covariance_gradient_at_a_zero_dt():
    """dt >= 0 allows a zero interval; the per-axis path took sqrt of the Simpson weights,
    whose derivative is infinite at 0 (NaN gradient with respect to dt).  The gradient equals
    the isotropic path's (the same densities on every axis)."""
    gyro, acc, dt = random_stream(1, 4, seed=24)
    dt = dt.clone()
    dt[0, 1] = 0.0
    grads = []
    for g, a in ((1e-3, 2e-2), (torch.full((3,), 1e-3, dtype=F64), torch.full((3,), 2e-2, dtype=F64))):
        d = dt.clone().requires_grad_(True)
        cov = preintegrate(gyro, acc, d, gyro_noise_density=g, acc_noise_density=a).covariance
        (grad,) = torch.autograd.grad((cov * torch.arange(100, dtype=F64).reshape(10, 10)).sum(), d)
        grads.append(grad)
    assert torch.isfinite(grads[1]).all(), grads[1]
    torch.testing.assert_close(grads[1], grads[0], rtol=1e-10, atol=1e-14)


def test_isotropic_and_per_axis_paths_agree():
    gyro, acc, dt = random_stream(3, 30, seed=22)
    iso = preintegrate(gyro, acc, dt, gyro_noise_density=1e-3, acc_noise_density=2e-2, time_noise_density=1e-4)
    axes = preintegrate(gyro, acc, dt, gyro_noise_density=torch.full((3,), 1e-3, dtype=F64),
                        acc_noise_density=torch.full((3,), 2e-2, dtype=F64), time_noise_density=1e-4)
    assert torch.allclose(iso.covariance, axes.covariance, rtol=0, atol=1e-14 * axes.covariance.abs().max())


@pytest.mark.parametrize("time_noise", [0.0, 2e-3])
def test_nees_monte_carlo_in_chi2_band(time_noise):
    # N noisy streams around one nominal stream; each sample's noise is held over its interval
    # (variance density^2 / dt) as a real IMU delivers it.
    N, K = 400, 100
    gyro, acc, dt = random_stream(1, K, seed=7, dt_range=(0.005, 0.015), rate=1.5, acc=4.0)
    s_g, s_a = 0.02, 0.2
    r = preintegrate(gyro, acc, dt, gyro_noise_density=s_g, acc_noise_density=s_a, time_noise_density=time_noise)
    gen = torch.Generator().manual_seed(123)
    root_dt = dt.sqrt().unsqueeze(-1)
    n_g = s_g / root_dt * torch.randn(N, K, 3, generator=gen, dtype=F64)
    n_a = s_a / root_dt * torch.randn(N, K, 3, generator=gen, dtype=F64)
    xi = increment_tangents(gyro - n_g, acc - n_a, dt.expand(N, K))
    n_t = time_noise * dt.sqrt() * torch.randn(N, K, generator=gen, dtype=F64)
    xi = torch.cat((xi[..., :9], xi[..., 9:] + n_t.unsqueeze(-1)), dim=-1)
    true = SGal3(window_product(SGal3.exp(xi).as_matrix()))
    eps = true.rminus(r.delta.expand(N))  # log(delta^-1 true): the right perturbation
    dims = 10 if time_noise > 0 else 9
    cov = r.covariance[0, :dims, :dims]
    nees = (eps[:, :dims] * torch.linalg.solve(cov, eps[:, :dims].T).T).sum(-1)
    lo, hi = scipy.stats.chi2.ppf([0.025, 0.975], N * dims) / N
    assert lo < float(nees.mean()) < hi, (float(nees.mean()), lo, hi)


# ------------------------------------------------------------------------------ biases
def test_bias_jacobian_matches_finite_differences():
    gyro, acc, dt = random_stream(3, 60, seed=31, dt_range=(0.004, 0.012), rate=1.5, acc=4.0)
    b0g = torch.tensor([0.02, -0.01, 0.03], dtype=F64)
    b0a = torch.tensor([0.1, -0.2, 0.05], dtype=F64)
    r = preintegrate(gyro, acc, dt, b0g, b0a)
    e = 1e-6
    cols = []
    for j in range(6):
        d = torch.zeros(6, dtype=F64)
        d[j] = e
        plus = preintegrate(gyro, acc, dt, b0g + d[:3], b0a + d[3:], covariance=False, bias_jacobian=False).delta
        minus = preintegrate(gyro, acc, dt, b0g - d[:3], b0a - d[3:], covariance=False, bias_jacobian=False).delta
        cols.append((plus.rminus(r.delta) - minus.rminus(r.delta)) / (2 * e))
    fd = torch.stack(cols, dim=-1)
    assert torch.allclose(r.bias_jacobian, fd, rtol=0, atol=1e-8 * fd.abs().max()), \
        float((r.bias_jacobian - fd).abs().max())


def test_bias_correction_is_first_order():
    gyro, acc, dt = random_stream(2, 100, seed=41)
    r = preintegrate(gyro, acc, dt)
    db_g, db_a = torch.tensor([0.02, -0.03, 0.01], dtype=F64), torch.tensor([0.2, 0.1, -0.3], dtype=F64)
    errs, raw = [], []
    for s in (1.0, 0.5, 0.25):
        exact = preintegrate(gyro, acc, dt, s * db_g, s * db_a, covariance=False, bias_jacobian=False).delta
        errs.append(float(r.corrected(s * db_g, s * db_a).rminus(exact).norm(dim=-1).max()))
        raw.append(float(r.delta.rminus(exact).norm(dim=-1).max()))
    assert errs[0] / errs[1] > 3.5 and errs[1] / errs[2] > 3.5, errs  # O(db^2)
    assert all(e < 0.05 * w for e, w in zip(errs, raw)), (errs, raw)


def test_a_number_dt_is_the_same_interval_for_every_sample():
    gyro, acc, _ = random_stream(3, 7, seed=4)
    kw = dict(gyro_noise_density=1e-3, acc_noise_density=1e-2, gyro_bias=0.01 * gyro[:, 0])
    by_number = preintegrate(gyro, acc, 0.004, **kw)
    by_tensor = preintegrate(gyro, acc, torch.full((3, 7), 0.004, dtype=F64), **kw)
    for name in ("covariance", "bias_jacobian"):
        assert torch.equal(getattr(by_number, name), getattr(by_tensor, name)), name
    assert torch.equal(by_number.delta.as_matrix(), by_tensor.delta.as_matrix())
    assert torch.equal(increment_tangents(gyro, acc, 0.004), increment_tangents(gyro, acc, torch.full((3, 7), 0.004, dtype=F64)))
    for bad in (float("inf"), float("nan"), -0.004):  # inf would give a NaN increment silently
        with pytest.raises(ValueError, match=rf"dt must be a finite number >= 0, got {bad}"):
            preintegrate(gyro, acc, bad, **kw)


# ------------------------------------------------------------------------------ errors
def test_bad_input_raises_with_names():
    gyro, acc, dt = random_stream(2, 5, seed=0)
    with pytest.raises(ValueError, match="acc must have the shape of gyro"):
        preintegrate(gyro, acc[:, :4], dt)
    with pytest.raises(ValueError, match=r"dt must have shape \(\.\.\., K\) with K = 5"):
        preintegrate(gyro, acc, dt[:, :3])
    with pytest.raises(ValueError, match=r"gyro must have shape \(\.\.\., 3\)"):
        preintegrate(gyro[..., :2], acc, dt)
    with pytest.raises(TypeError, match="dt must have a floating dtype"):
        preintegrate(gyro, acc, torch.ones(2, 5, dtype=torch.int64))
    with pytest.raises(TypeError, match=r"dt must be a number or a tensor \(\.\.\., K\), got bool"):
        preintegrate(gyro, acc, True)
    with pytest.raises(TypeError, match="acc has dtype torch.float32"):
        preintegrate(gyro, acc.float(), dt)
    with pytest.raises(ValueError, match=r"gyro_bias must have shape \(\.\.\., 3\)"):
        preintegrate(gyro, acc, dt, gyro_bias=torch.zeros(2, dtype=F64))
    with pytest.raises(ValueError, match=r"at least one sample \(K >= 1\)"):
        preintegrate(gyro[:, :0], acc[:, :0], dt[:, :0])
    with pytest.raises(ValueError, match="frame must be 'z_up' or 'ned'"):
        gravity_vector("enu")
    with pytest.raises(ValueError, match="bias_jacobian is None"):
        preintegrate(gyro, acc, dt, bias_jacobian=False).corrected(torch.zeros(3, dtype=F64))


def test_bad_dtypes_values_and_devices_raise_with_names():
    gyro, acc, dt = random_stream(2, 5, seed=1)
    neg = dt.clone()
    neg[1, 2] = -neg[1, 2]
    for kw in ({}, dict(gyro_noise_density=1e-3), dict(covariance=False, bias_jacobian=False)):
        with pytest.raises(ValueError, match="dt must be finite and >= 0 everywhere, got 1 negative"):
            preintegrate(gyro, acc, neg, **kw)
    # Zero intervals are legitimate: a zero-length sample changes nothing.
    zero = torch.cat([dt, torch.zeros(2, 1, dtype=F64)], 1)
    longer = preintegrate(torch.cat([gyro, gyro[:, :1]], 1), torch.cat([acc, acc[:, :1]], 1), zero,
                          gyro_noise_density=1e-3, acc_noise_density=1e-2)
    plain = preintegrate(gyro, acc, dt, gyro_noise_density=1e-3, acc_noise_density=1e-2)
    assert torch.allclose(longer.delta.as_matrix(), plain.delta.as_matrix(), rtol=0, atol=1e-14)
    assert torch.allclose(longer.covariance, plain.covariance, rtol=0, atol=1e-14)
    with pytest.raises(TypeError, match="gyro_bias must be None, a float or a tensor"):
        preintegrate(gyro, acc, dt, gyro_bias=[0.0, 0.0, 0.0])
    with pytest.raises(TypeError, match="dtype must be torch.float32 or torch.float64, got torch.int64"):
        gravity_vector(dtype=torch.int64)
    with pytest.raises(TypeError, match="dtype must be torch.float32 or torch.float64, got torch.float16"):
        earth_rate_vector(0.5, dtype=torch.float16)
    pre = preintegrate(gyro, acc, dt, gyro_noise_density=1e-3, acc_noise_density=1e-2)
    with pytest.raises(TypeError, match=r"gyro_bias has dtype torch.float32 but the preintegration"):
        pre.corrected(gyro_bias=torch.zeros(3))
    with pytest.raises(ValueError, match=r"acc_bias is on meta but the preintegration"):
        pre.corrected(acc_bias=torch.zeros(3, dtype=F64, device="meta"))
    start, g = SGal3.identity((2,), dtype=F64), gravity_vector(dtype=F64)
    eye = torch.eye(10, dtype=F64)
    with pytest.raises(TypeError, match="start_covariance has dtype torch.float32"):
        pre.predict_covariance(start, eye.float(), g)
    with pytest.raises(ValueError, match="start_covariance is on meta but delta is on cpu"):
        pre.predict_covariance(start, eye.to("meta"), g)
    with pytest.raises(ValueError, match=r"do not broadcast: prediction \(2,\), start_covariance \(5,\)"):
        pre.predict_covariance(start, eye.expand(5, 10, 10), g)
    with pytest.raises(TypeError, match="start has dtype torch.float32"):
        pre.predict(SGal3.identity((2,)), g)


def test_empty_and_non_floating_chains():
    gen = torch.Generator().manual_seed(4)
    E = torch.linalg.matrix_exp(0.3 * torch.randn(3, 4, 5, 5, dtype=F64, generator=gen))
    empty = E[:, :0]
    assert torch.equal(window_product(empty), torch.eye(5, dtype=F64).expand(3, 5, 5))
    assert suffix_products(empty).shape == (3, 0, 5, 5)
    for bad in (E.to(torch.int64), E.half()):
        for f in (window_product, suffix_products):
            with pytest.raises(TypeError, match="E must have a floating dtype"):
                f(bad)
    with pytest.raises(ValueError, match=r"E must have shape \(\.\.\., K, n, n\)"):
        window_product(E[0, 0])


@pytest.mark.parametrize("K", [1, 2, 3])
def test_splitting_samples_changes_nothing(K):
    # A sample split into two halves with the same inputs is the same piecewise-constant
    # stream: the increment is identical; covariance and bias Jacobian agree to Simpson's error.
    # Its largest term here: the gyro-noise part of the position block grows as s^4 over a
    # sample, which Simpson integrates 1/24 off on one interval; relative to the block that part
    # is ~ (s_g |f| dt / s_a)^2 ~ 1e-5, so the normalised difference stays below 5e-7.
    gyro, acc, dt = random_stream(2, K, seed=50 + K, dt_range=(0.002, 0.004))
    dens = dict(gyro_noise_density=1e-3, acc_noise_density=1e-2, time_noise_density=1e-4)
    one = preintegrate(gyro, acc, dt, **dens)
    two = preintegrate(gyro.repeat_interleave(2, 1), acc.repeat_interleave(2, 1), dt.repeat_interleave(2, 1) / 2, **dens)
    assert torch.allclose(one.delta.as_matrix(), two.delta.as_matrix(), rtol=0, atol=1e-14)
    sd = two.covariance.diagonal(dim1=-2, dim2=-1).sqrt()
    assert float(((one.covariance - two.covariance).abs() / sd.unsqueeze(-1) / sd.unsqueeze(-2)).max()) < 5e-7
    assert torch.allclose(one.bias_jacobian, two.bias_jacobian, rtol=0, atol=1e-10 * two.bias_jacobian.abs().max())


def test_predict_jacobians_match_finite_differences():
    gen = torch.Generator().manual_seed(3)
    gyro, acc, dt = random_stream(2, 20, seed=60, dt_range=(0.03, 0.06))
    delta = preintegrate(gyro, acc, dt, covariance=False, bias_jacobian=False).delta
    X0 = SGal3.random((2,), dtype=F64, generator=gen)
    g = gravity_vector("ned", 9.8, dtype=F64)
    Omega = torch.tensor([0.1, -0.2, 0.15], dtype=F64)  # exaggerated: every term matters
    J_start, J_delta = predict_jacobians(X0, delta, g, Omega)
    X1 = predict(X0, delta, g, Omega)
    e = 1e-6
    for J, perturb in ((J_start, lambda d: predict(X0.rplus(d), delta, g, Omega)),
                       (J_delta, lambda d: predict(X0, delta.rplus(d), g, Omega))):
        cols = []
        for k in range(10):
            d = torch.zeros(10, dtype=F64)
            d[k] = e
            cols.append((perturb(d).rminus(X1) - perturb(-d).rminus(X1)) / (2 * e))
        fd = torch.stack(cols, dim=-1)
        assert torch.allclose(J, fd, rtol=0, atol=1e-8 * fd.abs().max()), float((J - fd).abs().max())


def test_predicted_covariance_nees():
    N, K = 400, 50
    gen = torch.Generator().manual_seed(77)
    gyro, acc, dt = random_stream(1, K, seed=61, dt_range=(0.005, 0.015), rate=1.0, acc=3.0)
    s_g, s_a, s_t = 0.01, 0.1, 1e-3
    r = preintegrate(gyro, acc, dt, gyro_noise_density=s_g, acc_noise_density=s_a, time_noise_density=s_t)
    X0 = SGal3.random((1,), dtype=F64, generator=gen)
    g = gravity_vector("z_up", dtype=F64)
    Omega = torch.tensor([0.0, 0.05, 0.08], dtype=F64)
    L = 1e-2 * torch.randn(10, 10, dtype=F64, generator=gen)
    P0 = L @ L.T + 1e-6 * torch.eye(10, dtype=F64)
    P1 = r.predict_covariance(X0, P0, g, Omega)[0]
    # Monte Carlo: perturbed starts and noisy streams (noise held over each sample)
    eps0 = torch.randn(N, 10, generator=gen, dtype=F64) @ torch.linalg.cholesky(P0).T
    root = dt.sqrt().unsqueeze(-1)
    xi = increment_tangents(gyro - s_g / root * torch.randn(N, K, 3, generator=gen, dtype=F64),
                            acc - s_a / root * torch.randn(N, K, 3, generator=gen, dtype=F64), dt.expand(N, K))
    n_t = s_t * dt.sqrt() * torch.randn(N, K, generator=gen, dtype=F64)
    xi = torch.cat((xi[..., :9], xi[..., 9:] + n_t.unsqueeze(-1)), dim=-1)
    true_delta = SGal3(window_product(SGal3.exp(xi).as_matrix()))
    truth = predict(X0.expand(N).rplus(eps0), true_delta, g, Omega)
    eps1 = truth.rminus(r.predict(X0, g, Omega).expand(N))
    nees = (eps1 * torch.linalg.solve(P1, eps1.T).T).sum(-1)
    lo, hi = scipy.stats.chi2.ppf([0.025, 0.975], N * 10) / N
    assert lo < float(nees.mean()) < hi, (float(nees.mean()), lo, hi)


def test_preintegration_indexes_its_windows():
    """pre[index] indexes the batch axes of every field alike: each window equals the
    preintegration of that window alone, and the docstring's window-by-window dead reckoning
    equals the prediction over the whole stream at once (the increments and their noise
    integrals compose exactly)."""
    R, W, K = 2, 3, 20
    gyro, acc, dt = random_stream(R * W, K, seed=5)
    gyro, acc, dt = gyro.reshape(R, W, K, 3), acc.reshape(R, W, K, 3), dt.reshape(R, W, K)
    b_g = 0.01 * torch.randn(R, W, 3, dtype=F64, generator=torch.Generator().manual_seed(2))
    kw = dict(gyro_noise_density=0.01, acc_noise_density=0.1, time_noise_density=1e-3)
    pre = preintegrate(gyro, acc, dt, gyro_bias=b_g, **kw)
    assert pre.batch_shape == (R, W)
    for index, shape in ((1, (W,)), ((slice(None), 2), (R,)), ((..., 0), (R,)), (slice(0, 1), (1, W)),
                         (torch.tensor([False, True]), (1, W)), ((1, torch.tensor([2, 0])), (2,))):
        part = pre[index]
        assert part.batch_shape == shape
        assert part.covariance.shape == (*shape, 10, 10) and part.bias_jacobian.shape == (*shape, 10, 6)
        assert part.gyro_bias.shape == part.acc_bias.shape == (*shape, 3)
        at = lambda t, tail: t[(index if isinstance(index, tuple) else (index,))  # noqa: E731
                               + (slice(None),) * tail]
        alone = preintegrate(at(gyro, 2), at(acc, 2), at(dt, 1), gyro_bias=at(b_g, 1), **kw)
        for got, want in ((part.delta.as_matrix(), alone.delta.as_matrix()),
                          (part.covariance, alone.covariance), (part.bias_jacobian, alone.bias_jacobian),
                          (part.gyro_bias, alone.gyro_bias), (part.acc_bias, alone.acc_bias)):
            torch.testing.assert_close(got, want, rtol=0, atol=1e-13 * want.abs().max())
    assert preintegrate(gyro, acc, dt, covariance=False)[0, 1].covariance is None
    with pytest.raises(IndexError, match=r"does not fit the batch shape \(2, 3\)"):
        pre[0, 0, 0]
    built = Preintegration(pre.delta, None, None, pre.gyro_bias[0, 0], pre.acc_bias)
    torch.testing.assert_close(built[1, 0].gyro_bias, pre.gyro_bias[0, 0], rtol=0, atol=0)  # broadcast
    built.covariance = pre.covariance[0, :2]
    with pytest.raises(ValueError, match=r"covariance of shape \(2, 10, 10\) does not broadcast to "
                                         r"the batch shape \(2, 3\) of delta"):
        built[0]
    # dead reckoning window by window (the class docstring) = one window of all samples
    whole = preintegrate(gyro.reshape(R, W * K, 3), acc.reshape(R, W * K, 3), dt.reshape(R, W * K), **kw)
    g = gravity_vector(dtype=F64)
    X0 = SGal3.random((R,), dtype=F64, generator=torch.Generator().manual_seed(1))
    L = 1e-2 * torch.randn(R, 10, 10, dtype=F64, generator=torch.Generator().manual_seed(3))
    P0 = L @ L.mT + 1e-6 * torch.eye(10, dtype=F64)
    pre = preintegrate(gyro, acc, dt, **kw)
    X, P = X0, P0
    for w in range(W):
        X, P = pre[:, w].predict(X, g), pre[:, w].predict_covariance(X, P, g)
    torch.testing.assert_close(X.as_matrix(), whole.predict(X0, g).as_matrix(), rtol=0, atol=1e-12)
    P_whole = whole.predict_covariance(X0, P0, g)
    torch.testing.assert_close(P, P_whole, rtol=0, atol=1e-12 * P_whole.abs().max())


# ------------------------------------------------------------------ fast CPU path
def _plain(gyro, acc, dt, **kw):
    """preintegrate on the plain (autograd-capable) path: an input that requires grad keeps the
    in-place, blocked fast path out."""
    with torch.enable_grad():
        res = preintegrate(gyro.clone().requires_grad_(True), acc, dt, **kw)
    detach = lambda x: None if x is None else x.detach()  # noqa: E731
    return SGal3(res.delta.as_matrix().detach()), detach(res.covariance), detach(res.bias_jacobian)


def _assert_same(fast, plain, tol=1e-13):
    for a, b in zip((fast.delta.as_matrix(), fast.covariance, fast.bias_jacobian),
                    (plain[0].as_matrix(), plain[1], plain[2])):
        assert (a is None) == (b is None)
        if a is not None:
            assert a.shape == b.shape
            assert torch.allclose(a, b, rtol=0, atol=tol * b.abs().max()), float((a - b).abs().max())


@pytest.mark.parametrize("K", [1, 2, 7, 64])
@pytest.mark.parametrize("per_axis", [False, True])
@pytest.mark.parametrize("block_bytes", [None, 700])  # 700: blocks of a few windows, a ragged last one
@pytest.mark.parametrize("kernel", [True, False], ids=["C", "tensor"])  # C: the optional IMU kernel
def test_fast_path_matches_plain_path(K, per_axis, block_bytes, kernel, monkeypatch):
    import torchsgal.imu._fast_path as fast_path
    import torchsgal.imu.preintegration as P
    from torchsgal.functional import native

    if not kernel:
        monkeypatch.setattr(native, "_state", {"on": False})

    if block_bytes is not None:
        monkeypatch.setattr(fast_path, "_BLOCK_BYTES", block_bytes)
    gyro, acc, dt = random_stream(15, K, seed=70 + K)
    gyro, acc, dt = gyro.reshape(3, 5, K, 3), acc.reshape(3, 5, K, 3), dt[:5]  # dt broadcasts over 3
    g = torch.Generator().manual_seed(K)
    bg, ba = 0.01 * torch.randn(5, 3, generator=g, dtype=F64), 0.1 * torch.randn(3, 1, 3, generator=g, dtype=F64)
    dens = dict(gyro_noise_density=1e-3, acc_noise_density=2e-2, time_noise_density=1e-4)
    if per_axis:
        dens["acc_noise_density"] = torch.tensor([1e-2, 2e-2, 3e-2], dtype=F64)
    kw = dict(gyro_bias=bg, acc_bias=ba, **dens)
    flag_sets = [{}, dict(covariance=False, bias_jacobian=False), dict(covariance=False), dict(bias_jacobian=False)]
    with monkeypatch.context() as m, torch.no_grad():
        m.setattr(P, "_integrate", None)  # the fast path must not fall back to the plain one
        fast = [preintegrate(gyro, acc, dt, **kw, **flags) for flags in flag_sets]
    assert fast[0].delta.batch_shape == (3, 5)
    for res, flags in zip(fast, flag_sets):
        _assert_same(res, _plain(gyro, acc, dt, **kw, **flags))


def test_forward_ad_takes_the_plain_path():
    """Dual tensors of torch.autograd.forward_ad are observed: preintegrate runs the plain code
    (the fast path's out= kernels have no forward derivative) and its tangents equal the
    reverse-mode Jacobian times the direction, and central finite differences."""
    import torch.autograd.forward_ad as fwAD

    gyro, acc, dt = random_stream(2, 6, seed=81)
    v = torch.randn(gyro.shape, dtype=F64, generator=torch.Generator().manual_seed(82))
    dens = dict(gyro_noise_density=1e-3, acc_noise_density=1e-2)

    def outputs(g):
        r = preintegrate(g, acc, dt, **dens)
        return torch.cat([r.delta.as_matrix().flatten(), r.covariance.flatten(), r.bias_jacobian.flatten()])

    with fwAD.dual_level():
        tangent = fwAD.unpack_dual(outputs(fwAD.make_dual(gyro, v))).tangent
    J = torch.autograd.functional.jacobian(outputs, gyro)  # reverse mode, (370, 2, 6, 3)
    jv = (J.flatten(1) @ v.flatten())
    np.testing.assert_allclose(tangent.numpy(), jv.numpy(), rtol=1e-10, atol=1e-14 * float(jv.abs().max()))
    h = 1e-6  # central differences: rounding ~ eps |output| / h ~ 2e-10
    with torch.no_grad():
        fd = (outputs(gyro + h * v) - outputs(gyro - h * v)) / (2 * h)
    np.testing.assert_allclose(tangent.numpy(), fd.numpy(), rtol=1e-6, atol=1e-9)


def test_fast_path_blocks_large_float32_batches(monkeypatch):
    # Default block size: 520 x 256 float32 samples run as two blocks of 260 windows (the tensor
    # fast path: the optional C kernel, which needs no blocks, switched off).
    import torchsgal.imu._fast_path as fast_path
    from torchsgal.functional import native

    monkeypatch.setattr(native, "_state", {"on": False})

    gyro, acc, dt = random_stream(520, 256, seed=77, dtype=torch.float32)
    dens = dict(gyro_noise_density=1e-3, acc_noise_density=1e-2)
    blocks = []
    nodes = fast_path._nodes_fast
    monkeypatch.setattr(fast_path, "_nodes_fast", lambda *a: blocks.append(a[0].shape[0]) or nodes(*a))
    fast = preintegrate(gyro, acc, dt, **dens)
    assert blocks == [260, 260]
    plain = _plain(gyro, acc, dt, **dens)
    assert torch.allclose(fast.delta.as_matrix(), plain[0].as_matrix(), rtol=0, atol=1e-6)
    for a, b in ((fast.covariance, plain[1]), (fast.bias_jacobian, plain[2])):
        assert torch.allclose(a, b, rtol=0, atol=1e-5 * b.abs().max())


@pytest.mark.parametrize("K", [1, 2, 5, 8, 13])
def test_in_place_products_match_compose_packed(K):
    import torchsgal.imu._fast_path as fast_path
    import torchsgal.imu.products as products
    from torchsgal.functional import sgal3 as Fs

    M = SGal3.random((K, 4), dtype=F64, generator=torch.Generator().manual_seed(K)).as_matrix()
    E = Fs.pack(M)  # (16, K, 4)
    out = torch.empty_like(E)
    fast_path._compose_into(E, E.flip(1), out)
    assert torch.equal(out, Fs.compose_packed(E, E.flip(1)))  # same operations, same order
    fast_path._scan_into(E, out)
    assert torch.equal(out, products._suffix_products(E, Fs.compose_packed, 1, Fs.packed_identity(E)))
    assert torch.equal(fast_path._tree_product(E), products._window_product(E, Fs.compose_packed, 1))


def test_preintegration_module_keeps_the_names_of_its_parts():
    """``torchsgal.imu.preintegration`` gives the public names of products.py, moments.py and
    prediction.py as well: the same objects."""
    import torchsgal.imu.moments as moments
    import torchsgal.imu.prediction as prediction
    import torchsgal.imu.preintegration as P
    import torchsgal.imu.products as products

    homes = {products: ["window_product", "suffix_products"], moments: ["noise_map"],
             prediction: ["STANDARD_GRAVITY", "EARTH_RATE", "gravity_vector", "earth_rate_vector", "predict",
                          "predict_jacobians"]}
    for module, names in homes.items():
        for name in names:
            assert getattr(P, name) is getattr(module, name), name


def test_predict_compiles_in_one_graph():
    """predict traces under torch.compile(fullgraph=True) (no `@` between group objects, which
    dynamo cannot trace) and matches eager, with the Earth's rotation."""
    g = torch.Generator().manual_seed(91)
    start, delta = SGal3.random((3,), dtype=F64, generator=g), SGal3.random((3,), dtype=F64, generator=g)
    grav, rate = gravity_vector(dtype=F64), earth_rate_vector(0.7, dtype=F64)

    def f(a, b):
        return predict(a, b, grav, rate).as_matrix()

    compiled = torch.compile(f, backend="eager", fullgraph=True)
    assert torch.equal(compiled(start, delta), f(start, delta))


# ------------------------------------------------------------------ noise densities
@pytest.mark.parametrize("plain", [False, True], ids=["fast", "plain"])
def test_per_axis_density_batch_widens_the_windows(plain):
    """A per-axis density whose batch broadcasts with the stream's, but is wider, widens the
    result's batch like a bias (it is not folded into the node axis, which would give a wrong
    covariance and the batch of the stream); each window equals its own computation, on both paths."""
    gyro, acc, dt = random_stream(2, 5, seed=90)
    g = torch.Generator().manual_seed(91)
    s_g = 1e-3 * (1 + torch.rand(3, 2, 3, dtype=F64, generator=g))  # batch (3, 2) vs the stream's (2,)
    s_a = 1e-2 * (1 + torch.rand(3, 1, 3, dtype=F64, generator=g))
    kw = dict(gyro_noise_density=s_g, acc_noise_density=s_a, time_noise_density=1e-4)
    with torch.enable_grad():
        res = preintegrate(gyro.clone().requires_grad_(plain), acc, dt, **kw)
    assert res.batch_shape == (3, 2) and res.covariance.shape == (3, 2, 10, 10)
    assert res.bias_jacobian.shape == (3, 2, 10, 6) and res.gyro_bias.shape == (3, 2, 3)
    for i in range(3):
        for j in range(2):
            one = preintegrate(gyro[j], acc[j], dt[j], gyro_noise_density=s_g[i, j],
                               acc_noise_density=s_a[i, 0], time_noise_density=1e-4)
            for got, want in ((res.delta.as_matrix()[i, j], one.delta.as_matrix()),
                              (res.covariance[i, j], one.covariance),
                              (res.bias_jacobian[i, j], one.bias_jacobian)):
                torch.testing.assert_close(got.detach(), want, rtol=0, atol=1e-13 * want.abs().max())
    with pytest.raises(ValueError, match=r"do not broadcast: stream \(2,\), acc_noise_density \(3,\)"):
        preintegrate(gyro, acc, dt, acc_noise_density=torch.ones(3, 3, dtype=F64))


def test_empty_batches_with_every_density():
    """Empty batches return empty results, per-axis densities included (the general covariance
    must not reshape a tensor of 0 elements with a -1)."""
    gyro, acc, dt = random_stream(2, 5, seed=92)
    axes = torch.full((3,), 1e-3, dtype=F64)
    for kw, batch in ((dict(gyro_noise_density=axes), (0,)), (dict(gyro_noise_density=1e-3), (0,)),
                      (dict(acc_noise_density=axes.expand(4, 1, 3)), (4, 0))):
        res = preintegrate(gyro[:0], acc[:0], dt[:0], **kw)
        assert res.batch_shape == batch
        assert res.covariance.shape == (*batch, 10, 10) and res.bias_jacobian.shape == (*batch, 10, 6)


def test_noise_densities_are_checked_with_names():
    gyro, acc, dt = random_stream(2, 5, seed=93)
    ref = preintegrate(gyro, acc, dt, gyro_noise_density=1e-3, acc_noise_density=1e-2, time_noise_density=1e-4)
    # 0-d tensors of the stream's dtype and device are scalars; mixed with a per-axis one
    zero_d = preintegrate(gyro, acc, dt, gyro_noise_density=torch.tensor(1e-3, dtype=F64),
                          acc_noise_density=torch.tensor(1e-2, dtype=F64),
                          time_noise_density=torch.tensor(1e-4, dtype=F64))
    mixed = preintegrate(gyro, acc, dt, gyro_noise_density=torch.full((3,), 1e-3, dtype=F64),
                         acc_noise_density=torch.tensor(1e-2, dtype=F64), time_noise_density=1e-4)
    for res in (zero_d, mixed):
        torch.testing.assert_close(res.covariance, ref.covariance, rtol=0,
                                   atol=1e-14 * ref.covariance.abs().max())
    for name in ("gyro_noise_density", "acc_noise_density", "time_noise_density"):
        # a 0-d float32 tensor is refused as a per-axis one is, not cast silently to the float64 stream
        with pytest.raises(TypeError, match=f"{name} has dtype torch.float32 but gyro has dtype torch.float64"):
            preintegrate(gyro, acc, dt, **{name: torch.tensor(1e-3)})
        with pytest.raises(ValueError, match=f"{name} is on meta but gyro is on cpu"):
            preintegrate(gyro, acc, dt, **{name: torch.tensor(1e-3, dtype=F64, device="meta")})
        for bad in ("x", True, [1e-3, 1e-3, 1e-3]):
            with pytest.raises(TypeError, match=f"{name} must be a finite number >= 0 or a tensor"):
                preintegrate(gyro, acc, dt, **{name: bad})
        for bad in (-1e-3, math.nan, math.inf):
            with pytest.raises(ValueError, match=f"{name} must be a finite number >= 0, got"):
                preintegrate(gyro, acc, dt, **{name: bad})
        with pytest.raises(ValueError, match=f"{name} must be finite and >= 0 everywhere, got 1 negative"):
            preintegrate(gyro, acc, dt, **{name: torch.tensor(-1e-3, dtype=F64)})
    with pytest.raises(ValueError, match=r"gyro_noise_density must be finite and >= 0 everywhere, got 1 negative"):
        preintegrate(gyro, acc, dt, gyro_noise_density=torch.tensor([1e-3, -1e-3, 0.0], dtype=F64))
    with pytest.raises(ValueError, match=r"time_noise_density must be a float or a 0-d tensor, got shape \(3,\)"):
        preintegrate(gyro, acc, dt, time_noise_density=torch.ones(3, dtype=F64))
    with pytest.raises(ValueError, match=r"acc_noise_density must have shape \(\.\.\., 3\), got \(2,\)"):
        preintegrate(gyro, acc, dt, acc_noise_density=torch.ones(2, dtype=F64))


def test_vmap_over_any_one_argument():
    """Under torch.func.vmap any one argument may be the mapped one (the increment tangents and
    the prediction Jacobians must not be written in place into unbatched tensors): each result equals
    the batched call."""
    gen = torch.Generator().manual_seed(70)
    B, K, D = 3, 5, torch.float64
    gyro = 0.3 * torch.randn(K, 3, dtype=D, generator=gen)
    accs = torch.randn(B, K, 3, dtype=D, generator=gen)
    dts = 0.01 + 0.01 * torch.rand(B, K, dtype=D, generator=gen)
    f = lambda a, h: preintegrate(gyro, a, h, gyro_noise_density=1e-3, acc_noise_density=1e-2).covariance  # noqa: E731
    want = preintegrate(gyro.expand(B, K, 3), accs, dts, gyro_noise_density=1e-3,
                        acc_noise_density=1e-2).covariance
    torch.testing.assert_close(torch.func.vmap(f, in_dims=(0, None))(accs, dts[0]),
                               torch.stack([f(a, dts[0]) for a in accs]), rtol=0, atol=1e-18)
    torch.testing.assert_close(torch.func.vmap(f)(accs, dts), want, rtol=0, atol=1e-18)
    start = SGal3.random((B,), dtype=D, generator=gen)
    delta = SGal3.exp(0.3 * torch.randn(10, dtype=D, generator=gen))
    g = gravity_vector(dtype=D)
    J = lambda m: predict_jacobians(SGal3(m), delta, g)  # noqa: E731  only the start mapped
    for got, ref in zip(torch.func.vmap(J)(start.as_matrix()), predict_jacobians(start, delta, g)):
        torch.testing.assert_close(got, ref, rtol=0, atol=1e-15)
