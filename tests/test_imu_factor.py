"""IMU, bias random-walk and GNSS factors (torchsgal.imu.factors) for the factor-graph engine:
residual definitions against ``predict``, Jacobians against torch.func.jacfwd and central
finite differences, noise against GTSAM's factors, and a small GNSS/IMU smoothing problem
solved by the engine and by GTSAM."""
from __future__ import annotations

import numpy as np
import pytest
import torch

import torchsgal as ts
from torchsgal import SE3, SE23, SGal3
from torchsgal.estimation import graph as fg
from torchsgal.estimation.graph.linearize import Problem, evaluate_cost, linearize
from torchsgal.imu import earth_rate_vector, gravity_vector, predict, preintegrate
from torchsgal.imu.factors import (
    BiasRandomWalkFactor,
    GnssPositionFactor,
    ImuFactor,
    implied_increment,
    imu_jacobians,
    imu_residual,
)
from torchsgal.imu.preintegration import Preintegration
from torchsgal.imu.trajectory import SinusoidalTrajectory

D64 = torch.float64


def _windows(E=4, K=40, seed=0, bias=True):
    """E windows of K samples (dt 5 ms) of random IMU data, preintegrated with noise and (if
    ``bias``) a non-zero linearisation bias."""
    gen = torch.Generator().manual_seed(seed)
    gyro = 0.5 * torch.randn(E, K, 3, generator=gen, dtype=D64)
    acc = 3.0 * torch.randn(E, K, 3, generator=gen, dtype=D64) + torch.tensor([0, 0, 9.8], dtype=D64)
    b = 0.02 * torch.randn(E, 6, generator=gen, dtype=D64) if bias else torch.zeros(E, 6, dtype=D64)
    return preintegrate(gyro, acc, 0.005, gyro_bias=b[:, :3], acc_bias=b[:, 3:],
                        gyro_noise_density=1e-3, acc_noise_density=1e-2)


def _states(E, seed, group=SGal3):
    gen = torch.Generator().manual_seed(seed)
    xi = torch.randn(E, group.dof, generator=gen, dtype=D64)
    return group.exp(xi)


# ------------------------------------------------------------------------- definitions
def test_implied_increment_inverts_predict():
    g = gravity_vector("ned", 9.81, dtype=D64)
    w = earth_rate_vector(0.7, "ned", dtype=D64) * 1e3  # exaggerated: every term matters
    start, delta = _states(5, 1), _windows(5).delta
    end = predict(start, delta, g, w)
    D = implied_increment(start, end, g, w)
    torch.testing.assert_close(D.as_matrix(), delta.as_matrix(), rtol=0, atol=1e-12)
    torch.testing.assert_close(predict(start, D, g, w).as_matrix(), end.as_matrix(), rtol=0,
                               atol=1e-12)


@pytest.mark.parametrize("group", [SGal3, SE23])
def test_residual_is_the_increment_noise(group):
    """X_j = predict(X_i, Delta(b_i) exp(eps)) gives r = eps: the residual's noise is the
    preintegrated covariance itself."""
    pre = _windows(4)
    g = gravity_vector("z_up", dtype=D64)
    w = earth_rate_vector(0.3, dtype=D64) * 100.0
    gen = torch.Generator().manual_seed(3)
    b_i = torch.cat((pre.gyro_bias, pre.acc_bias), -1) + 0.01 * torch.randn(4, 6, generator=gen, dtype=D64)
    eps = 0.05 * torch.randn(4, 10, generator=gen, dtype=D64)
    if group is SE23:
        eps[:, 9] = 0.0  # known times: no time error
    start = _states(4, 5)
    if group is SE23:  # an SE23 state is the Galilean frame at time 0
        start = SGal3.from_components(start.rotation(), start.velocity(), start.position(),
                                      torch.zeros(4, dtype=D64))
    corrected = pre.corrected(b_i[:, :3], b_i[:, 3:])
    end = predict(start, corrected.rplus(eps), g, w)
    b_lin = torch.cat((pre.gyro_bias, pre.acc_bias), -1)
    if group is SE23:
        start, end = (SE23.from_components(x.rotation(), x.velocity(), x.position()) for x in (start, end))
    r = imu_residual(start, end, b_i, pre.delta, pre.bias_jacobian, b_lin, g.expand(4, 3),
                     w.expand(4, 3))
    torch.testing.assert_close(r, eps[:, :group.dof], rtol=0, atol=1e-12)


# -------------------------------------------------------------------------- Jacobians
def _check_jacobians(f, sizes, analytic=None):
    """jacfwd of f(*perturbations) at zero against central differences (h = 1e-5, float64),
    and the analytic Jacobians (a list, one per perturbation) if given, to 1e-7."""
    zeros = [torch.zeros(n, dtype=D64) for n in sizes]
    J_fwd = torch.func.jacfwd(f, argnums=tuple(range(len(sizes))))(*zeros)
    h = 1e-5
    for k, n in enumerate(sizes):
        cols = []
        for c in range(n):
            e = torch.zeros(n, dtype=D64)
            e[c] = h
            plus = [z + e if m == k else z for m, z in enumerate(zeros)]
            minus = [z - e if m == k else z for m, z in enumerate(zeros)]
            cols.append((f(*plus) - f(*minus)) / (2 * h))
        J_fd = torch.stack(cols, dim=-1)
        assert J_fd.abs().max() > 1e-3  # the perturbation moves the residual
        torch.testing.assert_close(J_fwd[k], J_fd, rtol=0, atol=1e-7)
        if analytic is not None:
            torch.testing.assert_close(analytic[k], J_fd, rtol=0, atol=1e-7)


@pytest.mark.parametrize("group", [SGal3, SE23])
def test_imu_jacobians(group):
    pre = _windows(1, seed=2)[0]
    g = gravity_vector("z_up", dtype=D64)
    w = earth_rate_vector(0.5, dtype=D64) * 100.0
    X_i = _states(1, 7, group)[0]
    X_j = X_i.compose(group.exp(0.3 * torch.ones(group.dof, dtype=D64)))  # r far from zero
    b = torch.tensor([0.01, -0.02, 0.03, 0.1, -0.2, 0.05], dtype=D64)
    b_lin = torch.cat((pre.gyro_bias, pre.acc_bias))

    def f(d_i, d_j, db):
        return imu_residual(X_i.rplus(d_i), X_j.rplus(d_j), b + db, pre.delta, pre.bias_jacobian,
                            b_lin, g, w)
    assert f(*[torch.zeros(n, dtype=D64) for n in (group.dof, group.dof, 6)]).norm() > 0.1
    r, Js = imu_jacobians(X_i, X_j, b, pre.delta, pre.bias_jacobian, b_lin, g, w)
    torch.testing.assert_close(r, f(*[torch.zeros(n, dtype=D64) for n in (group.dof, group.dof, 6)]),
                               rtol=0, atol=1e-14)
    _check_jacobians(f, [group.dof, group.dof, 6], Js)


@pytest.mark.parametrize("group", [SE3, SE23, SGal3])
def test_gnss_jacobians(group):
    X = _states(1, 11, group)[0]
    lever = torch.tensor([0.3, -0.2, 0.5], dtype=D64)
    z = torch.tensor([1.0, 2.0, -0.5], dtype=D64)
    factor = GnssPositionFactor("x", 0, z[None], covariance=torch.eye(3, dtype=D64), lever_arm=lever)
    r, (J,) = factor.jacobians(X, z, lever)
    torch.testing.assert_close(r, factor.residual(X, z, lever), rtol=0, atol=0)
    torch.testing.assert_close(r, X.position() + X.rotation() @ lever - z, rtol=0, atol=1e-14)
    _check_jacobians(lambda d: factor.residual(X.rplus(d), z, lever), [group.dof], [J])


def test_random_walk_jacobians():
    f = BiasRandomWalkFactor("b", 0, 1, torch.tensor([0.5], dtype=D64), 1e-4, 1e-3)
    b_i, b_j = torch.randn(2, 6, dtype=D64, generator=torch.Generator().manual_seed(0))
    r, Js = f.jacobians(b_i, b_j)
    _check_jacobians(lambda d_i, d_j: f.residual(b_i + d_i, b_j + d_j), [6, 6], Js)


@pytest.mark.parametrize("group", [SGal3, SE23])
@pytest.mark.parametrize("analytic", [True, False])
def test_engine_gradient_matches_cost_differences(group, analytic):
    """The engine's linearisation of a batch of 2 graphs of IMU factors (analytic or
    forward-mode Jacobians): its gradient J^T W r equals central differences of its cost
    along right perturbations, and its normal equations do not depend on the mode."""
    pre = _windows(3, seed=4)
    g = gravity_vector("z_up", dtype=D64)
    X = _states(8, 9, group).reshape(2, 4)
    b = 0.01 * torch.randn(2, 4, 6, dtype=D64, generator=torch.Generator().manual_seed(1))
    graphs = []
    for mode in (analytic, not analytic):
        graph = fg.FactorGraph()
        graph.add_variable("x", X)
        graph.add_variable("b", b)
        graph.add(ImuFactor("x", [0, 1, 2], [1, 2, 3], "b", [0, 1, 2], pre, g,
                            state_group=group, time_sigma=1e-2 if group is SGal3 else None,
                            analytic_jacobians=mode))
        graphs.append(graph)
    problem, other = Problem(graphs[0]), Problem(graphs[1])
    x0 = problem.initial(graphs[0])
    lin, lin_other = linearize(problem, x0), linearize(other, x0)
    torch.testing.assert_close(lin.values, lin_other.values, rtol=1e-9, atol=1e-6)
    grad = lin.g[1]
    # the costs are ~1e8 here (random states): with h = 1e-6 the rounding, cost eps / h, is
    # ~0.05; h = 1e-4 keeps rounding and truncation (h^2 f''') near 1e-4 absolute (1e-8 relative)
    h, fd = 1e-4, []
    for c in range(problem.D):
        e = torch.zeros(1, problem.D, dtype=D64)
        e[0, c] = h
        e = torch.cat((torch.zeros_like(e), e))  # the second problem
        fd.append((evaluate_cost(problem, problem.retract(x0, e))
                   - evaluate_cost(problem, problem.retract(x0, -e)))[1] / (2 * h))
    fd = torch.stack(fd)
    assert fd.abs().max() > 1.0
    torch.testing.assert_close(grad, fd, rtol=1e-6, atol=1e-4)


# ------------------------------------------------------------------ noise against GTSAM
def test_random_walk_cost_matches_gtsam():
    gtsam = pytest.importorskip("gtsam")
    dt, s_g, s_a = 0.37, 2e-4, 3e-3
    b_i, b_j = 0.01 * torch.randn(2, 6, dtype=D64, generator=torch.Generator().manual_seed(2))
    f = BiasRandomWalkFactor("b", 0, 1, torch.tensor([dt], dtype=D64), s_g, s_a)
    r = f.residual(b_i, b_j)
    ours = 0.5 * (f.sqrt_information[0] @ r).square().sum()
    bias = lambda b: gtsam.imuBias.ConstantBias(b[3:].numpy(), b[:3].numpy())  # noqa: E731
    model = gtsam.noiseModel.Diagonal.Sigmas(np.sqrt(dt) * np.array([s_a] * 3 + [s_g] * 3))
    factor = gtsam.BetweenFactorConstantBias(1, 2, gtsam.imuBias.ConstantBias(), model)
    values = gtsam.Values()
    values.insert(1, bias(b_i))
    values.insert(2, bias(b_j))
    assert ours.item() == pytest.approx(factor.error(values), rel=1e-12)


def test_gnss_cost_matches_gtsam():
    gtsam = pytest.importorskip("gtsam")
    from torchsgal.imu.peers import to_gtsam_navstate

    X = _states(1, 13)
    lever = torch.tensor([0.4, 0.1, -0.3], dtype=D64)
    z = X.position() + 0.1 * torch.tensor([[1.0, -2.0, 0.5]], dtype=D64)
    A = torch.tensor([[2.0, 0.3, 0.0], [0.3, 1.0, 0.2], [0.0, 0.2, 0.5]], dtype=D64)
    cov = 1e-2 * A @ A.T
    f = GnssPositionFactor("x", 0, z, covariance=cov, lever_arm=lever)
    r = f.residual(X, z, lever[None])
    ours = 0.5 * (f.sqrt_information @ r[0]).square().sum()
    factor = gtsam.GPSFactor2Arm(0, z[0].numpy(), lever.numpy(), gtsam.noiseModel.Gaussian.Covariance(cov.numpy()))
    values = gtsam.Values()
    values.insert(0, to_gtsam_navstate(X)[0])
    assert ours.item() == pytest.approx(factor.error(values), rel=1e-10)


# ---------------------------------------------------------------------------- errors
def test_bad_input_raises():
    pre = _windows(2)
    g = gravity_vector(dtype=D64)
    with pytest.raises(ValueError, match="time_sigma"):
        ImuFactor("x", [0, 1], [1, 2], "b", [0, 1], pre, g)  # exact clock, SGal3 states
    with pytest.raises(ValueError, match="time_sigma applies"):
        ImuFactor("x", [0, 1], [1, 2], "b", [0, 1], pre, g, state_group=SE23, time_sigma=1e-6)
    with pytest.raises(ValueError, match="state_group"):
        ImuFactor("x", [0, 1], [1, 2], "b", [0, 1], pre, g, state_group=SE3)
    with pytest.raises(ValueError, match="time_sigma"):
        ImuFactor("x", [0, 1], [1, 2], "b", [0, 1], pre, g, time_sigma=-1.0)
    for sigma in (1e200, 1e-200):  # sigma^2 overflowed (a bare OverflowError) or underflowed
        with pytest.raises(ValueError, match=r"time_sigma must lie in \[6.72e-139, 2.98e\+138\] s"):
            ImuFactor("x", [0, 1], [1, 2], "b", [0, 1], pre, g, time_sigma=sigma)
    with pytest.raises(ValueError, match="bias_jacobian"):
        ImuFactor("x", 0, 1, "b", 0, Preintegration(pre.delta, pre.covariance, None,
                                                     pre.gyro_bias, pre.acc_bias), g,
                  state_group=SE23)
    with pytest.raises(TypeError, match="preintegration"):
        ImuFactor("x", 0, 1, "b", 0, pre.delta, g, state_group=SE23)
    with pytest.raises(ValueError, match="gravity"):
        ImuFactor("x", [0, 1], [1, 2], "b", [0, 1], pre, g[:2], state_group=SE23)
    noisy = preintegrate(torch.zeros(2, 3, 3, dtype=D64), torch.zeros(2, 3, 3, dtype=D64), 0.01,
                         gyro_noise_density=1e-3, acc_noise_density=1e-2, time_noise_density=1e-4)
    assert ImuFactor("x", [0, 1], [1, 2], "b", [0, 1], noisy, g).dim == 10  # regular covariance
    z = torch.zeros(1, 3, dtype=D64)
    with pytest.raises(ValueError, match="exactly one"):
        GnssPositionFactor("x", 0, z)
    with pytest.raises(ValueError, match="positive definite"):
        GnssPositionFactor("x", 0, z, covariance=torch.zeros(3, 3, dtype=D64))
    with pytest.raises(ValueError, match="lever_arm"):
        GnssPositionFactor("x", 0, z, covariance=torch.eye(3, dtype=D64), lever_arm=torch.zeros(2, dtype=D64))
    with pytest.raises(ValueError, match="duration"):
        BiasRandomWalkFactor("b", 0, 1, torch.tensor([0.0], dtype=D64), 1e-4, 1e-3)
    with pytest.raises(ValueError, match="acc_random_walk"):
        BiasRandomWalkFactor("b", 0, 1, torch.tensor([0.5], dtype=D64), 1e-4, -1e-3)


# ------------------------------------------------------------------- a smoothing problem
def _smoothing_problem(N=6, window=0.5, rate=200):
    """A sinusoidal trajectory sampled at ``rate`` Hz (midpoint samples) with constant biases,
    N states ``window`` s apart, GNSS (lever arm) on states 0, 2, 3, 5, priors on state 0 and
    bias 0 centred on the truth: the truth minimises the continuous-time problem."""
    traj = SinusoidalTrajectory()
    g = gravity_vector("z_up", dtype=D64)
    b_true = torch.tensor([0.01, -0.02, 0.015, 0.05, -0.03, 0.08], dtype=D64)
    gyro, acc, dt = traj.stream(torch.arange(N - 1, dtype=D64) * window, window, 1 / rate, g)
    truth = traj.state(torch.arange(N, dtype=D64) * window)
    gnss = torch.tensor([0, 2, 3, 5])
    lever = torch.tensor([0.3, -0.1, 0.5], dtype=D64)
    z = truth[gnss].position() + truth[gnss].rotation() @ lever
    gen = torch.Generator().manual_seed(0)
    tangent = torch.cat((0.1 * torch.randn(N, 9, generator=gen, dtype=D64), torch.zeros(N, 1, dtype=D64)), -1)
    return dict(g=g, b_true=b_true, gyro=gyro + b_true[:3], acc=acc + b_true[3:], dt=dt,
                truth=truth, gnss=gnss, lever=lever, z=z, init=truth.rplus(tangent),
                s_noise=(1e-3, 1e-2), s_walk=(1e-4, 1e-3), s_gnss=0.02,
                s_prior=torch.tensor([0.01] * 6 + [0.001] * 3 + [1e-6], dtype=D64),  # rho nu phi iota
                s_bias=torch.tensor([0.05] * 3 + [0.2] * 3, dtype=D64))


def _se23(X: SGal3) -> SE23:
    return SE23.from_components(X.rotation(), X.velocity(), X.position())


def _solve_torchsgal(p, pre, init=None, group=SGal3):
    """The problem for the engine; ``init`` of batch (N,) or (B, N) (B problems)."""
    init = p["init"] if init is None else init
    N = init.batch_shape[-1]
    i = torch.arange(N - 1)
    graph = fg.FactorGraph()
    graph.add_variable("x", init if group is SGal3 else _se23(init))
    graph.add_variable("b", torch.zeros(init.batch_shape + (6,), dtype=D64))
    graph.add(ImuFactor("x", i, i + 1, "b", i, pre, p["g"], state_group=group,
                        time_sigma=1e-6 if group is SGal3 else None))
    graph.add(BiasRandomWalkFactor("b", i, i + 1, pre.duration(), *p["s_walk"]))
    graph.add(GnssPositionFactor("x", p["gnss"], p["z"], covariance=p["s_gnss"] ** 2 * torch.eye(3, dtype=D64),
                                 lever_arm=p["lever"]))
    prior = p["truth"][:1] if group is SGal3 else _se23(p["truth"][:1])
    graph.add(fg.Prior("x", 0, prior, information=torch.diag(p["s_prior"][:group.dof] ** -2)))
    graph.add(fg.Factor(lambda b, m: b - m, [("b", 0)], data=[p["b_true"][None]], dim=6,
                        information=torch.diag(p["s_bias"] ** -2)))
    result = fg.levenberg_marquardt(graph, relative_error_tol=1e-10, absolute_error_tol=1e-12)
    assert (result.report.status == 0).all()
    return result.values["x"], result.values["b"]


def test_batched_problems_and_state_groups():
    """Two problems in one batch (per-problem preintegrations (B, E) and initial values) solve
    as each alone; SE23 states with known times reach the SGal3 states' estimate."""
    p = _smoothing_problem()
    s_g, s_a = p["s_noise"]
    b = p["b_true"]
    pres = [preintegrate(p["gyro"], p["acc"], p["dt"], gyro_bias=lin[:3], acc_bias=lin[3:],
                         gyro_noise_density=s_g, acc_noise_density=s_a)
            for lin in (torch.zeros(6, dtype=D64), b)]  # two linearisation biases
    both = Preintegration(SGal3.stack([q.delta for q in pres]),
                          torch.stack([q.covariance for q in pres]),
                          torch.stack([q.bias_jacobian for q in pres]),
                          torch.stack([q.gyro_bias for q in pres]),
                          torch.stack([q.acc_bias for q in pres]))  # batch (2, E)
    inits = SGal3.stack([p["init"], p["truth"]])  # (2, N)
    x_both, b_both = _solve_torchsgal(p, both, inits)
    for k in range(2):
        x_k, b_k = _solve_torchsgal(p, pres[k], inits[k])
        torch.testing.assert_close(x_both[k].as_matrix(), x_k.as_matrix(), rtol=0, atol=1e-9)
        torch.testing.assert_close(b_both[k], b_k, rtol=0, atol=1e-9)
    assert (_errors(x_both[0], x_both[1]) > 1e-6).any()  # the two problems differ
    x_se23, b_se23 = _solve_torchsgal(p, pres[0], group=SE23)
    x_sgal = x_both[0]
    torch.testing.assert_close(x_se23.as_matrix(), _se23(x_sgal).as_matrix(), rtol=0, atol=1e-8)
    torch.testing.assert_close(b_se23, b_both[0], rtol=0, atol=1e-8)


def _solve_gtsam(p, pims):
    import gtsam

    from torchsgal.imu.peers import from_gtsam_navstate, to_gtsam_navstate

    N = p["init"].batch_shape[0]
    X, Bk = (lambda k: gtsam.symbol("x", k)), (lambda k: gtsam.symbol("b", k))
    bias = lambda b: gtsam.imuBias.ConstantBias(b[3:].numpy(), b[:3].numpy())  # noqa: E731
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for k, nav in enumerate(to_gtsam_navstate(p["init"])):
        values.insert(X(k), nav)
        values.insert(Bk(k), gtsam.imuBias.ConstantBias())
    s_g, s_a = p["s_walk"]
    for k, pim in enumerate(pims):
        graph.add(gtsam.ImuFactor2(X(k), X(k + 1), Bk(k), pim))
        sigmas = np.sqrt(pim.deltaTij()) * np.array([s_a] * 3 + [s_g] * 3)
        graph.add(gtsam.BetweenFactorConstantBias(Bk(k), Bk(k + 1), gtsam.imuBias.ConstantBias(),
                                                  gtsam.noiseModel.Diagonal.Sigmas(sigmas)))
    for n, k in enumerate(p["gnss"].tolist()):
        graph.add(gtsam.GPSFactor2Arm(X(k), p["z"][n].numpy(), p["lever"].numpy(),
                                      gtsam.noiseModel.Isotropic.Sigma(3, p["s_gnss"])))
    sp = p["s_prior"].numpy()  # NavState's tangent: [rotation, position, velocity]
    graph.add(gtsam.PriorFactorNavState(X(0), to_gtsam_navstate(p["truth"][:1])[0],
                                        gtsam.noiseModel.Diagonal.Sigmas(np.r_[sp[6:9], sp[0:6]])))
    sb = p["s_bias"].numpy()
    graph.add(gtsam.PriorFactorConstantBias(Bk(0), bias(p["b_true"]),
                                            gtsam.noiseModel.Diagonal.Sigmas(np.r_[sb[3:], sb[:3]])))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-10)
    params.setAbsoluteErrorTol(1e-12)
    out = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    return from_gtsam_navstate([out.atNavState(X(k)) for k in range(N)], p["truth"].time())


def _errors(x, y):
    """Largest position, velocity and rotation differences between two trajectories."""
    return torch.stack(((x.position() - y.position()).norm(dim=-1).max(),
                        (x.velocity() - y.velocity()).norm(dim=-1).max(),
                        ts.SO3.from_matrix(x.rotation().mT @ y.rotation()).log().norm(dim=-1).max()))


def test_smoothing_against_gtsam():
    """Same samples, same factors and noise: the engine with torchsgal's preintegration and
    GTSAM (ImuFactor2, BetweenFactor<ConstantBias>, GPSFactor2Arm, priors, LM).

    1. The preintegrated increments differ by GTSAM's O(dt) discretisation (docs/guide/imu.md);
       the two estimates differ by less than that, and torchsgal's is closer to the truth.
    2. Given GTSAM's own increments and covariances (both linearised at one bias), the engine's
       IMU factor reaches GTSAM's estimate: the residuals define the same problem."""
    pytest.importorskip("gtsam")
    from torchsgal.imu.gtsam_interop import from_gtsam_pim, gtsam_pim, to_gtsam_params

    p = _smoothing_problem()
    s_g, s_a = p["s_noise"]
    params = to_gtsam_params(p["g"], s_g, s_a)
    K = p["gyro"].shape[0]
    pre = preintegrate(p["gyro"], p["acc"], p["dt"], gyro_noise_density=s_g, acc_noise_density=s_a)
    pims = [gtsam_pim(p["gyro"][k], p["acc"][k], p["dt"][k], params) for k in range(K)]
    discretisation = _errors(pre.delta, SGal3.stack([from_gtsam_pim(q).delta for q in pims]))
    x_ts, b_ts = _solve_torchsgal(p, pre)
    x_gt = _solve_gtsam(p, pims)
    between = _errors(x_ts, x_gt)
    err_ts, err_gt = _errors(x_ts, p["truth"]), _errors(x_gt, p["truth"])
    assert (between[:2] < discretisation[:2]).all(), (between, discretisation)
    assert (err_ts <= err_gt).all(), (err_ts, err_gt)
    assert err_ts[0] < 5e-5 and (b_ts - p["b_true"]).abs().max() < 1e-3, (err_ts, b_ts)

    # 2. GTSAM's increments in the engine's factor, both linearised at the true bias
    b = p["b_true"]
    pims_b = [gtsam_pim(p["gyro"][k], p["acc"][k], p["dt"][k], params, gyro_bias=b[:3], acc_bias=b[3:])
              for k in range(K)]
    ours_b = preintegrate(p["gyro"], p["acc"], p["dt"], gyro_bias=b[:3], acc_bias=b[3:],
                          gyro_noise_density=s_g, acc_noise_density=s_a)
    theirs = [from_gtsam_pim(q) for q in pims_b]
    pre_gt = Preintegration(SGal3.stack([q.delta for q in theirs]),
                            torch.stack([q.covariance for q in theirs]), ours_b.bias_jacobian,
                            ours_b.gyro_bias, ours_b.acc_bias)
    same = _errors(_solve_torchsgal(p, pre_gt)[0], _solve_gtsam(p, pims_b))
    rows = [("increments, torchsgal - GTSAM (per window)", discretisation),
            ("estimates, torchsgal - GTSAM", between), ("torchsgal - truth", err_ts),
            ("GTSAM - truth", err_gt), ("GTSAM's increments in both, estimates apart", same)]
    print("\n| | position [m] | velocity [m/s] | rotation [rad] |\n|---|---|---|---|")
    for name, e in rows:
        print(f"| {name} | " + " | ".join(f"{v:.2g}" for v in e.tolist()) + " |")
    assert (same < 1e-5).all(), same


def test_guide_example_runs():
    """The example of docs/guide/imu_factors.md runs (its asserts check what it states)."""
    import re
    from pathlib import Path

    guide = Path(__file__).resolve().parents[1] / "docs" / "guide" / "imu_factors.md"
    blocks = re.findall(r"```python\n(.*?)```", guide.read_text(), flags=re.S)
    assert len(blocks) == 1
    namespace: dict = {}
    exec(compile(blocks[0], str(guide), "exec"), namespace)
    assert namespace["cov"].shape == (1, 10, 10)
    assert torch.isfinite(namespace["cov"]).all()


def test_gnss_factor_with_batched_measurements_and_the_default_lever_arm():
    """Measurements (B, E, 3) with the default lever arm (one zero vector for every factor and
    problem; it was (B, 1, 3), which the engine read as E = 1 and failed to broadcast) solve as
    with an explicit zero lever arm; measurements and lever arms of another E are named, as is
    an asymmetric covariance (Cholesky read its lower triangle only)."""
    gen = torch.Generator().manual_seed(3)
    B, N = 3, 4
    truth = SE3.exp(torch.randn(N, 6, dtype=D64, generator=gen))
    k = torch.tensor([0, 2, 3])
    z = truth[k].position() + 0.01 * torch.randn(B, 3, 3, dtype=D64, generator=gen)
    C = 0.02 ** 2 * torch.eye(3, dtype=D64)

    def solve(**lever):
        graph = fg.FactorGraph()
        graph.add_variable("x", truth.rplus(0.01 * torch.randn(B, N, 6, dtype=D64, generator=gen)))
        graph.add(GnssPositionFactor("x", k, z, covariance=C, **lever))
        graph.add(fg.Prior("x", torch.arange(N), truth, information=torch.eye(6, dtype=D64)))
        return fg.levenberg_marquardt(graph)

    default, explicit = solve(), solve(lever_arm=torch.zeros(3, dtype=D64))
    assert default.report.converged.all()
    torch.testing.assert_close(default.values["x"].as_matrix(), explicit.values["x"].as_matrix(),
                               rtol=0, atol=1e-9)
    with pytest.raises(ValueError, match=r"measured must have shape \(E, 3\) or \(B, E, 3\) with E = 3"):
        GnssPositionFactor("x", k, z[:, :2], covariance=C)
    with pytest.raises(ValueError, match=r"lever_arm must have shape \(3,\) or \(E, 3\) = \(3, 3\), got \(2, 3\)"):
        GnssPositionFactor("x", k, z, covariance=C, lever_arm=torch.zeros(2, 3, dtype=D64))
    bad = torch.tensor([[1.0, 5.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], dtype=D64)
    with pytest.raises(ValueError, match=r"covariance is not symmetric \(max relative asymmetry 1\)"):
        GnssPositionFactor("x", k, z, covariance=bad)


def test_random_walk_factor_checks_its_sizes_and_ranges():
    """duration of another E is named at construction (it was reported at the solve as
    sqrt_information's leading size); densities beyond the dtype (a raw torch overflow) and so
    small that the information overflows (NaN costs at the solve) are refused."""
    with pytest.raises(ValueError, match=r"duration must have shape \(E,\) or \(B, E\) with E = 3"):
        BiasRandomWalkFactor("b", [0, 1, 2], [1, 2, 3], torch.ones(5, dtype=D64), 1e-3, 1e-3)
    with pytest.raises(ValueError, match="gyro_random_walk must be representable in torch.float32"):
        BiasRandomWalkFactor("b", [0, 1, 2], [1, 2, 3], torch.ones(3), 1e39, 1.0)
    with pytest.raises(ValueError, match=r"information 1 / \(s\^2 duration\) overflows"):
        BiasRandomWalkFactor("b", [0, 1, 2], [1, 2, 3], torch.ones(3, dtype=D64), 1e-160, 1.0)
    assert BiasRandomWalkFactor("b", [0, 1, 2], [1, 2, 3], torch.ones(3, dtype=D64), 1e-3, 1e-2).size == 3


def test_factors_name_variables_of_the_wrong_kind():
    """An IMU factor on states of another group, a bias variable of another size and a GNSS
    factor on a Euclidean variable are refused when added (the IMU case failed at the solve
    with "the residual has shape (1, 3, 9), expected (..., 10)")."""
    pre = _windows(2)
    g = gravity_vector(dtype=D64)
    graph = fg.FactorGraph()
    graph.add_variable("x", SE23.identity(3, dtype=D64))
    graph.add_variable("b", torch.zeros(3, 6, dtype=D64))
    graph.add_variable("b4", torch.zeros(3, 4, dtype=D64))
    with pytest.raises(TypeError, match="variable 'x' must be SGal3, got SE23"):
        graph.add(ImuFactor("x", [0, 1], [1, 2], "b", [0, 1], pre, g, time_sigma=1e-6))
    with pytest.raises(TypeError, match="variable 'b4' must be a Euclidean variable of size 6, got size 4"):
        graph.add(ImuFactor("x", [0, 1], [1, 2], "b4", [0, 1], pre, g, state_group=SE23))
    with pytest.raises(TypeError, match="variable 'x' must be a Euclidean variable of size 6, got SE23"):
        graph.add(BiasRandomWalkFactor("x", [0, 1], [1, 2], torch.ones(2, dtype=D64), 1e-3, 1e-3))
    with pytest.raises(TypeError, match="variable 'b' must be SE3 or SE23 or SGal3, got a Euclidean tensor"):
        graph.add(GnssPositionFactor("b", [0], torch.zeros(1, 3, dtype=D64), covariance=torch.eye(3, dtype=D64)))
    graph.add(ImuFactor("x", [0, 1], [1, 2], "b", [0, 1], pre, g, state_group=SE23))
    assert len(graph.factors) == 1
