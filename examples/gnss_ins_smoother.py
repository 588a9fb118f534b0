#!/usr/bin/env python
"""GNSS/INS batch smoothing of Monte Carlo runs with the factor-graph engine, checked against GTSAM.

A vehicle drives a closed-form trajectory (position a sum of sinusoids and a constant drift:
turns, speed changes, a gentle climb; heading and pitch along the velocity, a small roll).
Its derivatives give the analytic truth: velocity, acceleration, attitude R = Rz(psi) Ry(theta)
Rx(roll), the body rate (ZYX Euler rates) and the specific force f = R^T (a - g).  Each
Monte Carlo run adds, to a 200 Hz IMU:

* white noise (held over each sample: standard deviation s / sqrt(dt)),
* gyro and accelerometer biases drawn from their prior and walking at every sample,

and takes GNSS antenna positions (lever arm l) at the keyframe epochs with noise, except
during an outage.  Each sample is the signal at the middle of its interval (to second order
the interval's average, what an integrating IMU reports).

The smoother (states X_k in SE_2(3) at the keyframes, one bias [b_g, b_a] per keyframe):

* ``ImuFactor`` between consecutive states (torchsgal ``preintegrate``, linearised at zero
  bias, first-order bias correction), ``BiasRandomWalkFactor``, ``GnssPositionFactor``;
* a prior on the first state (its mean drawn around the truth from the prior covariance, so
  the runs are samples of the model) and on the first bias;
* solved for all runs at once: one graph with a leading batch of ``--runs`` problems,
  ``levenberg_marquardt``; Laplace marginals ``result.marginal_covariance``.

GTSAM solves the same graph (``PreintegratedImuMeasurements`` of the same samples,
``ImuFactor2``, ``BetweenFactorConstantBias``, ``GPSFactor2Arm``, ``PriorFactorNavState``,
``PriorFactorConstantBias``, ``LevenbergMarquardtOptimizer``) from the same initial values
for the first ``--gtsam-runs`` runs.  Initial values come from the GNSS fixes: positions
interpolated across the outage, velocity from their differences, heading along it.

Reports (``gnss_ins.md`` and ``gnss_ins.png`` in ``--out``, default examples/output/): RMSE
against the truth for both (same runs), the difference of the two estimates against the
difference of the two preintegrations (per window, and dead-reckoned across the outage), the NEES of the smoothed
states averaged over the runs with its chi-square band, and the times of the batched solve
and of the GTSAM runs.

Usage::

    python examples/gnss_ins_smoother.py --no-show
    python examples/gnss_ins_smoother.py --runs 64 --duration 90 --seed 1 --out /tmp/gnss_ins
"""
from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import torch

_HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(_HERE.parent))  # run against the checkout this script lives in

from _cli import int_at_least, output_folder, positive_float  # noqa: E402

from torchsgal import SE23, SO3, SGal3  # noqa: E402
from torchsgal.estimation import graph as fg  # noqa: E402
from torchsgal.imu import Preintegration, gravity_vector, predict, preintegrate  # noqa: E402
from torchsgal.imu.factors import BiasRandomWalkFactor, GnssPositionFactor, ImuFactor  # noqa: E402

F64 = torch.float64


# ------------------------------------------------------------------------------- model
@dataclass(frozen=True)
class Config:
    """The scenario.  Units: s, m, rad; densities per sqrt(Hz)."""

    duration: float = 60.0  # s
    imu_rate: float = 200.0  # Hz
    keyframe_rate: float = 1.0  # Hz: states and GNSS epochs
    outage: tuple = (0.4, 0.65)  # GNSS outage, fractions of the duration
    gyro_noise: float = 1e-3  # rad/s/sqrt(Hz)
    acc_noise: float = 1e-2  # m/s^2/sqrt(Hz)
    gyro_walk: float = 1e-5  # rad/s^2/sqrt(Hz)
    acc_walk: float = 1e-3  # m/s^3/sqrt(Hz)
    gyro_bias_sigma: float = 5e-3  # rad/s, initial bias prior
    acc_bias_sigma: float = 0.05  # m/s^2
    gnss_sigma: tuple = (0.5, 0.5, 1.0)  # m, east north up
    lever_arm: tuple = (0.5, 0.0, 1.2)  # m, antenna in the body frame
    prior_sigma: tuple = (1.0, 1.0, 1.0, 0.1, 0.1, 0.1, 0.01, 0.01, 0.05)  # [rho, nu, phi]

    def __post_init__(self):
        for name, ratio in (("duration", self.duration * self.keyframe_rate),
                            ("imu_rate", self.imu_rate / self.keyframe_rate)):
            if not (1 <= ratio <= 1e7 and abs(ratio - round(ratio)) < 1e-9):  # inf: no round()
                raise ValueError(f"{name} must be a positive whole multiple of the keyframe period or "
                                 f"rate ({self.keyframe_rate:g} Hz), at most 1e7 of them, got "
                                 f"{getattr(self, name)}")

    @property
    def samples_per_window(self) -> int:
        return int(round(self.imu_rate / self.keyframe_rate))

    @property
    def states(self) -> int:
        return int(round(self.duration * self.keyframe_rate)) + 1

    def gnss_epochs(self) -> torch.Tensor:
        """Indices of the states with a GNSS fix: all but those strictly inside the outage."""
        t = torch.arange(self.states, dtype=F64) / self.keyframe_rate
        a, b = self.outage[0] * self.duration, self.outage[1] * self.duration
        return torch.nonzero((t <= a) | (t >= b)).squeeze(-1)


def _rotation(angle: torch.Tensor, axis: int) -> torch.Tensor:
    """The rotation matrices (..., 3, 3) by ``angle`` (...) about body axis ``axis``."""
    phi = torch.zeros(angle.shape + (3,), dtype=angle.dtype)
    phi[..., axis] = angle
    return SO3.exp(phi).as_matrix()


# position p(t) = drift t + sum_k A_k sin(w_k t + c_k) per axis (closed form, derivatives exact)
_DRIFT = (8.0, 0.0, 0.02)
_WAVES = (  # (axis, amplitude [m], angular frequency [rad/s], phase [rad])
    (0, 30.0, 0.12, 0.0), (0, 4.0, 0.5, 1.0),
    (1, 60.0, 0.15, 0.0), (1, 12.0, 0.4, 0.3),
    (2, 3.0, 0.08, 0.5), (2, 0.4, 0.35, -0.2),
)
_ROLL = (0.03, 0.9, 0.3)  # amplitude [rad], angular frequency [rad/s], phase


def vehicle(t: torch.Tensor) -> dict:
    """The analytic truth at times t (...): position, velocity, acceleration (..., 3), attitude
    (..., 3, 3) and body rate (..., 3).  Attitude R = Rz(psi) Ry(theta) Rx(roll) (body x
    forward, z up) with the nose along the velocity: psi = atan2(v_y, v_x),
    theta = -atan2(v_z, v_h); body rate R^T R_dot = (roll_dot e_x + Rx^T theta_dot e_y +
    Rx^T Ry^T psi_dot e_z)^."""
    drift = torch.tensor(_DRIFT, dtype=t.dtype)
    p = drift * t[..., None]
    v = drift.expand_as(p).clone()
    a = torch.zeros_like(p)
    for axis, A, w, c in _WAVES:
        s, co = torch.sin(w * t + c), torch.cos(w * t + c)
        p[..., axis] += A * s
        v[..., axis] += A * w * co
        a[..., axis] -= A * w**2 * s
    vx, vy, vz = v.unbind(-1)
    ax, ay, az = a.unbind(-1)
    vh2 = vx**2 + vy**2
    vh = vh2.sqrt()
    psi = torch.atan2(vy, vx)
    psi_dot = (vx * ay - vy * ax) / vh2
    vh_dot = (vx * ax + vy * ay) / vh
    theta = -torch.atan2(vz, vh)
    theta_dot = -(vh * az - vz * vh_dot) / (vh2 + vz**2)
    A, w, c = _ROLL
    roll, roll_dot = A * torch.sin(w * t + c), A * w * torch.cos(w * t + c)
    Rx, Ry = _rotation(roll, 0), _rotation(theta, 1)
    ez = torch.zeros_like(p)
    ez[..., 2] = psi_dot
    ey = torch.zeros_like(p)
    ey[..., 1] = theta_dot
    omega = (Rx.mT @ (Ry.mT @ ez[..., None] + ey[..., None])).squeeze(-1)
    omega[..., 0] += roll_dot
    return dict(position=p, velocity=v, acceleration=a, rotation=_rotation(psi, 2) @ Ry @ Rx, rate=omega)


def truth_states(cfg: Config) -> SE23:
    """The true extended poses at the keyframes, (N,)."""
    s = vehicle(torch.arange(cfg.states, dtype=F64) / cfg.keyframe_rate)
    return SE23.from_components(s["rotation"], s["velocity"], s["position"])


def simulate(cfg: Config, runs: int, seed: int, noise: float = 1.0) -> dict:
    """Monte Carlo data of ``runs`` runs (module docstring): IMU samples (B, N-1, K, 3) per
    window, true biases (B, N, 6) at the keyframes, GNSS fixes (B, E, 3) at ``gnss`` (E,),
    the prior means (B, 1) and the initial values (B, N).

    ``noise`` scales every random term but the initial biases: IMU noise, bias walk, GNSS
    noise and the priors' offsets from the truth.  With ``noise=0`` (the same runs, the same
    biases, held constant) the truth minimises the continuous-time problem, so an estimate's
    distance from it is the error of its preintegration."""
    gen = torch.Generator().manual_seed(seed)
    N, K = cfg.states, cfg.samples_per_window
    S = (N - 1) * K
    dt = 1.0 / cfg.imu_rate
    g = gravity_vector("z_up", dtype=F64)
    s = vehicle((torch.arange(S, dtype=F64) + 0.5) * dt)  # midpoint samples
    rate = s["rate"]
    force = (s["rotation"].mT @ (s["acceleration"] - g)[..., None]).squeeze(-1)

    def randn(*shape):
        return torch.randn(*shape, generator=gen, dtype=F64)

    b0 = torch.cat((cfg.gyro_bias_sigma * randn(runs, 1, 3), cfg.acc_bias_sigma * randn(runs, 1, 3)), -1)
    walk = torch.tensor([cfg.gyro_walk] * 3 + [cfg.acc_walk] * 3, dtype=F64) * math.sqrt(dt)
    steps = torch.cat((torch.zeros(runs, 1, 6, dtype=F64), noise * walk * randn(runs, S - 1, 6)), 1)
    bias = b0 + steps.cumsum(1)  # (B, S, 6) bias of each sample
    gyro = rate + bias[..., :3] + noise * cfg.gyro_noise / math.sqrt(dt) * randn(runs, S, 3)
    acc = force + bias[..., 3:] + noise * cfg.acc_noise / math.sqrt(dt) * randn(runs, S, 3)

    truth = truth_states(cfg)
    lever = torch.tensor(cfg.lever_arm, dtype=F64)
    gnss = cfg.gnss_epochs()
    antenna = truth.position()[gnss] + truth.rotation()[gnss] @ lever
    gnss_sigma = torch.tensor(cfg.gnss_sigma, dtype=F64)
    fixes = antenna + noise * gnss_sigma * randn(runs, gnss.numel(), 3)
    prior_sigma = torch.tensor(cfg.prior_sigma, dtype=F64)
    prior = truth[:1].rplus(noise * prior_sigma * randn(runs, 1, 9))  # the prior's mean, (B, 1)
    bias_sigma = torch.tensor([cfg.gyro_bias_sigma] * 3 + [cfg.acc_bias_sigma] * 3, dtype=F64)
    bias_prior = b0 + noise * bias_sigma * randn(runs, 1, 6)  # the bias prior's mean, (B, 1, 6)
    return dict(cfg=cfg, g=g, truth=truth, gyro=gyro.unflatten(1, (N - 1, K)),
                acc=acc.unflatten(1, (N - 1, K)), dt=dt,
                bias=torch.cat((bias[:, ::K], bias[:, -1:]), 1), gnss=gnss, fixes=fixes,
                lever=lever, gnss_sigma=gnss_sigma, prior=prior, prior_sigma=prior_sigma,
                bias_prior=bias_prior, bias_sigma=bias_sigma, init=initial_values(cfg, gnss, fixes))


_PER_RUN = ("gyro", "acc", "bias", "fixes", "prior", "bias_prior", "init")


def first_runs(sim: dict, count: int) -> dict:
    """The data of the first ``count`` runs."""
    return {k: (v[:count] if k in _PER_RUN else v) for k, v in sim.items()}


def initial_values(cfg: Config, gnss: torch.Tensor, fixes: torch.Tensor) -> SE23:
    """States (B, N) from the GNSS fixes alone: positions interpolated linearly between fixes
    (across the outage), velocity from their central differences, level attitude with the
    heading along the velocity."""
    N = cfg.states
    n = torch.arange(N)
    after = torch.searchsorted(gnss, n).clamp(max=gnss.numel() - 1)  # first fix at or after n
    before = torch.where(gnss[after] == n, after, (after - 1).clamp(min=0))
    n0, n1 = gnss[before].to(F64), gnss[after].to(F64)
    w = torch.where(n1 > n0, (n - n0) / (n1 - n0).clamp(min=1), torch.zeros_like(n0))
    p = fixes[:, before] * (1 - w)[:, None] + fixes[:, after] * w[:, None]  # (B, N, 3)
    h = 1.0 / cfg.keyframe_rate
    v = torch.cat((p[:, 1:2] - p[:, :1], (p[:, 2:] - p[:, :-2]) / 2, p[:, -1:] - p[:, -2:-1]), 1) / h
    R = _rotation(torch.atan2(v[..., 1], v[..., 0]), 2)
    return SE23.from_components(R, v, p)


# --------------------------------------------------------------------------- torchsgal
def _bias_prior_residual(b: torch.Tensor, mean: torch.Tensor) -> torch.Tensor:
    return b - mean


def preintegrate_runs(sim: dict):
    """torchsgal's increments of every run's windows, batch (B, N-1), linearised at zero bias."""
    cfg = sim["cfg"]
    return preintegrate(sim["gyro"], sim["acc"], sim["dt"], gyro_noise_density=cfg.gyro_noise,
                        acc_noise_density=cfg.acc_noise)


def build_graph(sim: dict, pre) -> fg.FactorGraph:
    """The smoother of all runs: one graph with a batch of B problems."""
    cfg = sim["cfg"]
    B, N = sim["init"].batch_shape
    i = torch.arange(N - 1)
    graph = fg.FactorGraph()
    graph.add_variable("x", sim["init"])
    graph.add_variable("b", torch.zeros(B, N, 6, dtype=F64))
    graph.add(ImuFactor("x", i, i + 1, "b", i, pre, sim["g"], state_group=SE23))
    graph.add(BiasRandomWalkFactor("b", i, i + 1, pre.duration(), cfg.gyro_walk, cfg.acc_walk))
    graph.add(GnssPositionFactor("x", sim["gnss"], sim["fixes"],
                                 covariance=torch.diag(sim["gnss_sigma"] ** 2), lever_arm=sim["lever"]))
    graph.add(fg.Prior("x", 0, sim["prior"], information=torch.diag(sim["prior_sigma"] ** -2)))
    graph.add(fg.Factor(_bias_prior_residual, [("b", 0)], data=[sim["bias_prior"]], dim=6,
                        information=torch.diag(sim["bias_sigma"] ** -2)))
    return graph


RELATIVE_TOL = ABSOLUTE_TOL = 1e-9  # both solvers' error tolerances


def solve_torchsgal(sim: dict) -> dict:
    """Preintegrate, build and solve all runs; times of each stage [s]."""
    t0 = time.perf_counter()
    pre = preintegrate_runs(sim)
    t1 = time.perf_counter()
    graph = build_graph(sim, pre)
    result = fg.levenberg_marquardt(graph, max_iterations=50, relative_error_tol=RELATIVE_TOL,
                                    absolute_error_tol=ABSOLUTE_TOL)
    t2 = time.perf_counter()
    cov = result.marginal_covariance("x")  # (B, N, 9, 9), right perturbation [rho, nu, phi]
    t3 = time.perf_counter()
    return dict(pre=pre, result=result, x=result.values["x"], b=result.values["b"], cov=cov,
                time_preintegrate=t1 - t0, time_solve=t2 - t1, time_marginals=t3 - t2)


def solve_one_sparse(sim: dict) -> tuple[SE23, float]:
    """Run 0 alone with the engine's sparse Cholesky (a batch of one): its states (1, N) and the
    time of preintegration and solve [s]."""
    one = first_runs(sim, 1)
    t0 = time.perf_counter()
    graph = build_graph(one, preintegrate_runs(one))
    result = fg.levenberg_marquardt(graph, max_iterations=50, linear_solver="sparse",
                                    relative_error_tol=RELATIVE_TOL, absolute_error_tol=ABSOLUTE_TOL)
    return result.values["x"], time.perf_counter() - t0


# ------------------------------------------------------------------------------- GTSAM
def _navstates(X: SE23) -> list:
    import gtsam

    R, v, p = X.rotation().numpy(), X.velocity().numpy(), X.position().numpy()
    return [gtsam.NavState(gtsam.Rot3(R[k]), p[k], v[k]) for k in range(R.shape[0])]


def solve_gtsam(sim: dict, run: int) -> dict:
    """The same graph for one run with GTSAM; times of the preintegration and of the solve."""
    import gtsam
    import numpy as np

    from torchsgal.imu.gtsam_interop import gtsam_pim, to_gtsam_params

    cfg = sim["cfg"]
    N = cfg.states
    t0 = time.perf_counter()
    params = to_gtsam_params(sim["g"], cfg.gyro_noise, cfg.acc_noise)
    pims = [gtsam_pim(sim["gyro"][run, k], sim["acc"][run, k], sim["dt"], params) for k in range(N - 1)]
    t1 = time.perf_counter()
    X, Bk = (lambda k: gtsam.symbol("x", k)), (lambda k: gtsam.symbol("b", k))
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for k, nav in enumerate(_navstates(sim["init"][run])):
        values.insert(X(k), nav)
        values.insert(Bk(k), gtsam.imuBias.ConstantBias())
    walk = np.array([cfg.acc_walk] * 3 + [cfg.gyro_walk] * 3)  # ConstantBias: [b_a, b_g]
    for k, pim in enumerate(pims):
        graph.add(gtsam.ImuFactor2(X(k), X(k + 1), Bk(k), pim))
        graph.add(gtsam.BetweenFactorConstantBias(
            Bk(k), Bk(k + 1), gtsam.imuBias.ConstantBias(),
            gtsam.noiseModel.Diagonal.Sigmas(math.sqrt(pim.deltaTij()) * walk)))
    gnss_noise = gtsam.noiseModel.Diagonal.Sigmas(sim["gnss_sigma"].numpy())
    fixes, lever = sim["fixes"][run].numpy(), sim["lever"].numpy()
    for e, k in enumerate(sim["gnss"].tolist()):
        graph.add(gtsam.GPSFactor2Arm(X(k), fixes[e], lever, gnss_noise))
    sp = sim["prior_sigma"].numpy()  # NavState's tangent: [rotation, position, velocity]
    graph.add(gtsam.PriorFactorNavState(X(0), _navstates(sim["prior"][run])[0],
                                        gtsam.noiseModel.Diagonal.Sigmas(np.r_[sp[6:9], sp[0:6]])))
    bp, bs = sim["bias_prior"][run, 0].numpy(), sim["bias_sigma"].numpy()  # ConstantBias(b_a, b_g)
    graph.add(gtsam.PriorFactorConstantBias(Bk(0), gtsam.imuBias.ConstantBias(bp[3:], bp[:3]),
                                            gtsam.noiseModel.Diagonal.Sigmas(np.r_[bs[3:], bs[:3]])))
    lm = gtsam.LevenbergMarquardtParams()
    lm.setMaxIterations(50)
    lm.setRelativeErrorTol(RELATIVE_TOL)
    lm.setAbsoluteErrorTol(ABSOLUTE_TOL)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, lm)
    out = optimizer.optimize()
    t2 = time.perf_counter()
    navs = [out.atNavState(X(k)) for k in range(N)]
    t = lambda a: torch.tensor(np.stack(a), dtype=F64)  # noqa: E731
    x = SE23.from_components(t([s.attitude().matrix() for s in navs]), t([s.velocity() for s in navs]),
                             t([s.position() for s in navs]))
    return dict(x=x, pims=pims, iterations=optimizer.iterations(), time_preintegrate=t1 - t0,
                time_solve=t2 - t1)


# ----------------------------------------------------------------------------- metrics
def errors(x: SE23, y: SE23) -> torch.Tensor:
    """Position [m], velocity [m/s] and rotation [rad] differences (..., 3) of two states."""
    rot = SO3.from_matrix(x.rotation().mT @ y.rotation()).log().norm(dim=-1)
    return torch.stack(((x.position() - y.position()).norm(dim=-1),
                        (x.velocity() - y.velocity()).norm(dim=-1), rot), -1)


def rmse(x: SE23, truth: SE23) -> torch.Tensor:
    """Position, velocity, attitude RMSE (3,) over all states of all runs in x."""
    return errors(x, truth).pow(2).flatten(0, -2).mean(0).sqrt()


def nees(x: SE23, truth: SE23, cov: torch.Tensor) -> torch.Tensor:
    """e^T P^-1 e (B, N) with X_true = X exp(e) (right perturbation, as the marginals)."""
    e = truth.rminus(x)
    return (e.unsqueeze(-2) @ torch.linalg.solve(cov, e.unsqueeze(-1))).squeeze(-1).squeeze(-1)


def chi2_band(dof: int, mass: float = 0.95) -> tuple[float, float]:
    """Two-sided chi-square interval of ``dof`` degrees of freedom."""
    from scipy.stats import chi2

    return float(chi2.ppf((1 - mass) / 2, dof)), float(chi2.ppf((1 + mass) / 2, dof))


def dead_reckon(start: SGal3, deltas: SGal3, g: torch.Tensor) -> SGal3:
    """States (W + 1,) chained from ``start`` by the increments (W,) (no bias correction)."""
    out = [start]
    for w in range(deltas.batch_shape[0]):
        out.append(predict(out[-1], deltas[w], g))
    return SGal3.stack(out)


def _galilean(X: SE23, t: torch.Tensor) -> SGal3:
    return SGal3.from_components(rotation=X.rotation(), velocity=X.velocity(), position=X.position(), time=t)


def compare_preintegrations(sim: dict, pre, pims: list, run: int) -> dict:
    """The two preintegrations of one run: their largest per-window difference (3,), and the
    difference (3,) of two dead reckonings across the outage (from the true state at the last
    fix before it to the first fix after it), one with each preintegration."""
    from torchsgal.imu.gtsam_interop import from_gtsam_pim

    converted = [from_gtsam_pim(q) for q in pims]
    if not all(isinstance(c, Preintegration) for c in converted):
        raise TypeError("pims must be PreintegratedImuMeasurements (not combined)")
    theirs = SGal3.stack([c.delta for c in converted if isinstance(c, Preintegration)])
    ours = pre.delta[run]
    window = errors(SE23.from_components(ours.rotation(), ours.velocity(), ours.position()),
                    SE23.from_components(theirs.rotation(), theirs.velocity(), theirs.position()))
    gnss = sim["gnss"]
    gap = int(torch.argmax(gnss.diff()))
    a, b = int(gnss[gap]), int(gnss[gap + 1])
    cfg = sim["cfg"]
    start = _galilean(sim["truth"][a], torch.tensor(a / cfg.keyframe_rate, dtype=F64))
    X1, X2 = dead_reckon(start, ours[a:b], sim["g"]), dead_reckon(start, theirs[a:b], sim["g"])
    se = lambda X: SE23.from_components(X.rotation(), X.velocity(), X.position())  # noqa: E731
    return dict(window=window.amax(0), outage=errors(se(X1), se(X2)).amax(0), outage_epochs=(a, b))


def compute(runs: int = 32, duration: float = 60.0, seed: int = 0, gtsam_runs: int = 4,
            repeats: int = 1) -> dict:
    """The whole study (module docstring); ``repeats`` times the batched solve that often.

    The first ``gtsam_runs`` runs are also solved by GTSAM, and, with every random term but
    the biases switched off (``simulate(noise=0)``), by both: there the truth minimises the
    continuous-time problem and each estimate's error is its preintegration's."""
    cfg = Config(duration=duration)
    sim = simulate(cfg, runs, seed)
    ours = solve_torchsgal(sim)
    times = [ours["time_preintegrate"] + ours["time_solve"]]
    for _ in range(repeats - 1):
        again = solve_torchsgal(sim)
        times.append(again["time_preintegrate"] + again["time_solve"])
    sparse = [solve_one_sparse(sim) for _ in range(repeats + 1)]  # the first one warms up
    truth = sim["truth"]
    G = min(gtsam_runs, runs)
    theirs = [solve_gtsam(sim, r) for r in range(G)]
    n = nees(ours["x"], truth, ours["cov"])  # (B, N)
    report = ours["result"].report
    out = dict(sim=sim, ours=ours, gtsam=theirs, x_gtsam=None, nees=n, cfg=cfg,
               converged=(report.status == 0), iterations=report.iterations,
               rmse_all=rmse(ours["x"], truth), time_batch=statistics.median(times),
               time_sparse=statistics.median(t for _, t in sparse[1:]),
               sparse_difference=errors(sparse[0][0][0], ours["x"][0]).amax(0))
    if G:
        x_gt = SE23.stack([t["x"] for t in theirs])
        pre_cmp = [compare_preintegrations(sim, ours["pre"], theirs[r]["pims"], r) for r in range(G)]
        exact = first_runs(simulate(cfg, runs, seed, noise=0.0), G)
        ours_exact = solve_torchsgal(exact)
        x_gt_exact = SE23.stack([solve_gtsam(exact, r)["x"] for r in range(G)])
        out.update(
            x_gtsam=x_gt, rmse_ours=rmse(ours["x"][:G], truth), rmse_gtsam=rmse(x_gt, truth),
            between=errors(ours["x"][:G], x_gt).amax(-2),  # (G, 3) largest over the states
            window_difference=torch.stack([c["window"] for c in pre_cmp]),
            outage_difference=torch.stack([c["outage"] for c in pre_cmp]),
            exact_converged=(ours_exact["result"].report.status == 0),
            exact_rmse_ours=rmse(ours_exact["x"], truth), exact_rmse_gtsam=rmse(x_gt_exact, truth),
            exact_ours=errors(ours_exact["x"], truth).amax(-2),  # (G, 3)
            exact_gtsam=errors(x_gt_exact, truth).amax(-2),
            exact_between=errors(ours_exact["x"], x_gt_exact).amax(-2),
            gtsam_iterations=[t["iterations"] for t in theirs],
            time_gtsam=statistics.median(t["time_preintegrate"] + t["time_solve"] for t in theirs),
            time_gtsam_solve=statistics.median(t["time_solve"] for t in theirs))
    lo, hi = chi2_band(9 * runs)
    out["nees_band"] = (lo / runs, hi / runs)
    return out


# ----------------------------------------------------------------------------- outputs
def _row(name: str, values: torch.Tensor, digits: int = 3) -> str:
    return f"| {name} | " + " | ".join(f"{v:.{digits}g}" for v in values.tolist()) + " |"


def summary(out: dict) -> str:
    """The markdown summary."""
    cfg, sim = out["cfg"], out["sim"]
    B, N = out["nees"].shape
    a, b = cfg.outage[0] * cfg.duration, cfg.outage[1] * cfg.duration
    lines = [
        "# GNSS/INS smoother: torchsgal and GTSAM",
        "",
        f"{B} Monte Carlo runs of {cfg.duration:g} s, IMU {cfg.imu_rate:g} Hz, {N} states and "
        f"GNSS at {cfg.keyframe_rate:g} Hz ({sim['gnss'].numel()} fixes, outage {a:g}-{b:g} s), "
        f"float64.",
        "",
        f"Converged: {int(out['converged'].sum())} of {B} runs; iterations (median) "
        f"{int(out['iterations'].median())}"
        + (f"; GTSAM's on runs 0-{len(out['gtsam']) - 1}: {out['gtsam_iterations']}." if out["gtsam"] else "."),
        "",
        "| RMSE | position [m] | velocity [m/s] | attitude [rad] |",
        "|---|---|---|---|",
        _row(f"torchsgal, all {B} runs", out["rmse_all"], 4),
    ]
    G = len(out["gtsam"])
    if G:
        lines += [
            _row(f"torchsgal, runs 0-{G - 1}", out["rmse_ours"], 4),
            _row(f"GTSAM, runs 0-{G - 1}", out["rmse_gtsam"], 4),
            _row(f"noise-free runs 0-{G - 1}: torchsgal", out["exact_rmse_ours"]),
            _row(f"noise-free runs 0-{G - 1}: GTSAM", out["exact_rmse_gtsam"]),
            "",
            "| largest difference (over states, then runs) | position [m] | velocity [m/s] | attitude [rad] |",
            "|---|---|---|---|",
            _row("estimates, torchsgal - GTSAM", out["between"].amax(0)),
            _row("increments, torchsgal - GTSAM, per window", out["window_difference"].amax(0)),
            _row("increments dead-reckoned across the outage", out["outage_difference"].amax(0)),
            _row("noise-free runs: estimates, torchsgal - GTSAM", out["exact_between"].amax(0)),
            _row("noise-free runs: torchsgal - truth", out["exact_ours"].amax(0)),
            _row("noise-free runs: GTSAM - truth", out["exact_gtsam"].amax(0)),
        ]
    lo, hi = out["nees_band"]
    m = out["nees"].mean(0)
    inside = ((m >= lo) & (m <= hi)).float().mean()
    lines += [
        "",
        f"NEES (9 dof) of the smoothed states, averaged over the {B} runs: mean over the states "
        f"{float(m.mean()):.2f}, range {float(m.min()):.2f}-{float(m.max()):.2f}; 95 % chi-square band "
        f"for the average of {B} runs [{lo:.2f}, {hi:.2f}]; {100 * float(inside):.0f} % of the states inside.",
        "",
        f"Run 0 solved alone with the sparse Cholesky matches its batched solve to "
        f"{float(out['sparse_difference'].max()):.1g}.",
        "",
        "| time (median) | seconds |",
        "|---|---|",
        f"| torchsgal, all {B} runs in one batch (preintegration + solve) | {out['time_batch']:.3g} |",
        f"| torchsgal, per run | {out['time_batch'] / B:.3g} |",
        f"| torchsgal, run 0 alone, sparse Cholesky (preintegration + solve) | {out['time_sparse']:.3g} |",
    ]
    if G:
        lines += [
            f"| GTSAM, one run (preintegration + solve) | {out['time_gtsam']:.3g} |",
            f"| GTSAM, one run, solve only | {out['time_gtsam_solve']:.3g} |",
            f"| GTSAM per run / torchsgal per run (batch) | {out['time_gtsam'] / (out['time_batch'] / B):.3g} |",
            f"| GTSAM per run / torchsgal run alone (sparse) | {out['time_gtsam'] / out['time_sparse']:.3g} |",
        ]
    return "\n".join(lines) + "\n"


def plot(out: dict, path: Path, show: bool) -> None:
    """Run 0: truth, GNSS, both estimates (outage shaded); errors with 3-sigma bounds; NEES."""
    import matplotlib

    if not show:
        matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cfg, sim = out["cfg"], out["sim"]
    truth, x = sim["truth"], out["ours"]["x"][0]
    t = torch.arange(cfg.states, dtype=F64) / cfg.keyframe_rate
    outage = (cfg.outage[0] * cfg.duration, cfg.outage[1] * cfg.duration)
    fig, ax = plt.subplots(2, 2, figsize=(13, 9))
    a = ax[0, 0]
    a.plot(truth.position()[:, 0], truth.position()[:, 1], "k-", lw=1, label="truth")
    a.plot(sim["fixes"][0, :, 0], sim["fixes"][0, :, 1], ".", color="0.6", ms=4, label="GNSS")
    a.plot(x.position()[:, 0], x.position()[:, 1], "C0-", lw=1, label="torchsgal")
    if out["x_gtsam"] is not None:
        xg = out["x_gtsam"][0]
        a.plot(xg.position()[:, 0], xg.position()[:, 1], "C3--", lw=1, label="GTSAM")
    gap = (t > outage[0]) & (t < outage[1])
    a.plot(truth.position()[gap, 0], truth.position()[gap, 1], "-", color="orange", lw=4, alpha=0.3,
           label="outage")
    a.set(xlabel="east [m]", ylabel="north [m]", title="run 0, top view")
    a.axis("equal")
    a.legend()
    cov = out["ours"]["cov"][0]
    e = truth.rminus(x)  # right perturbation, as the marginals
    sigma = cov.diagonal(dim1=-2, dim2=-1).sqrt()
    for a, rows, name, unit in ((ax[0, 1], range(0, 3), "position error (body axes)", "m"),
                                (ax[1, 0], range(6, 9), "attitude error", "rad")):
        for c, r in enumerate(rows):
            a.plot(t, e[:, r], f"C{c}-", lw=1, label="xyz"[c])
            a.plot(t, 3 * sigma[:, r], f"C{c}:", lw=1)
            a.plot(t, -3 * sigma[:, r], f"C{c}:", lw=1)
        a.axvspan(*outage, color="orange", alpha=0.2)
        a.set(xlabel="t [s]", ylabel=unit, title=f"run 0, {name} and 3 sigma")
        a.legend()
    a = ax[1, 1]
    lo, hi = out["nees_band"]
    a.plot(t, out["nees"].mean(0), "C0-", label=f"NEES averaged over {out['nees'].shape[0]} runs")
    a.axhspan(lo, hi, color="C2", alpha=0.2, label="95 % chi-square band")
    a.axvspan(*outage, color="orange", alpha=0.2)
    a.set(xlabel="t [s]", title="NEES of the smoothed states (9 dof)")
    a.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    if show:
        plt.show()
    plt.close(fig)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runs", type=int_at_least(1), default=32, help="Monte Carlo runs, solved as one batch")
    parser.add_argument("--duration", type=positive_float, default=60.0, help="seconds")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--gtsam-runs", type=int_at_least(0), default=4, help="runs also solved by GTSAM")
    parser.add_argument("--repeats", type=int_at_least(1), default=3, help="timings of the batched solve")
    parser.add_argument("--out", type=Path, default=_HERE / "output",
                        help="output folder (default examples/output/)")
    parser.add_argument("--no-show", action="store_true")
    args = parser.parse_args(argv)
    try:
        Config(duration=args.duration)
    except ValueError as error:
        parser.error(f"argument --duration: {error}")
    output_folder(parser, args.out)
    out = compute(args.runs, args.duration, args.seed, args.gtsam_runs, args.repeats)
    text = summary(out)
    (args.out / "gnss_ins.md").write_text(text)
    print(text)
    plot(out, args.out / "gnss_ins.png", show=not args.no_show)


if __name__ == "__main__":
    main()
