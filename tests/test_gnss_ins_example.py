"""The GNSS/INS smoother example (examples/gnss_ins_smoother.py), run small: its analytic truth,
the batched smoother against GTSAM on the same runs, and the consistency of its marginals."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest
import torch

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
F64 = torch.float64


@pytest.fixture(scope="module")
def example():
    sys.path.insert(0, os.path.join(ROOT, "examples"))
    try:
        import gnss_ins_smoother
    finally:
        sys.path.pop(0)
    return gnss_ins_smoother


@pytest.fixture(scope="module")
def study(example):
    pytest.importorskip("gtsam")
    pytest.importorskip("scipy")
    return example.compute(runs=8, duration=20.0, seed=0, gtsam_runs=2)


def test_truth_derivatives_match_finite_differences(example):
    """Velocity, acceleration and body rate of the closed-form truth against central
    differences of position, velocity and attitude; the nose points along the velocity."""
    t = torch.linspace(0.0, 120.0, 25, dtype=F64)
    h = 1e-5
    s, ahead, behind = example.vehicle(t), example.vehicle(t + h), example.vehicle(t - h)
    torch.testing.assert_close((ahead["position"] - behind["position"]) / (2 * h), s["velocity"],
                               rtol=0, atol=1e-7)
    torch.testing.assert_close((ahead["velocity"] - behind["velocity"]) / (2 * h), s["acceleration"],
                               rtol=0, atol=1e-7)
    W = s["rotation"].mT @ (ahead["rotation"] - behind["rotation"]) / (2 * h)  # R^T R_dot = omega^
    omega = torch.stack((W[..., 2, 1], W[..., 0, 2], W[..., 1, 0]), -1)
    torch.testing.assert_close(omega, s["rate"], rtol=0, atol=1e-8)
    assert s["rate"][:, 2].abs().max() > 0.05  # it turns
    nose = s["rotation"][..., 0]
    torch.testing.assert_close(nose, s["velocity"] / s["velocity"].norm(dim=-1, keepdim=True),
                               rtol=0, atol=1e-12)


def test_noise_free_imu_carries_the_truth(example):
    """The simulated IMU without noise, preintegrated at the true bias, predicts each keyframe
    from the one before to the sampling error of a smooth signal (midpoint samples: second
    order in dt)."""
    from torchsgal import SGal3
    from torchsgal.imu import preintegrate

    cfg = example.Config(duration=10.0)
    sim = example.simulate(cfg, runs=1, seed=3, noise=0.0)
    b = sim["bias"][0, 0]
    pre = preintegrate(sim["gyro"][0], sim["acc"][0], sim["dt"], gyro_bias=b[:3], acc_bias=b[3:])
    truth = sim["truth"]
    times = torch.arange(cfg.states, dtype=F64) / cfg.keyframe_rate
    start = SGal3.from_components(rotation=truth.rotation()[:-1], velocity=truth.velocity()[:-1],
                                  position=truth.position()[:-1], time=times[:-1])
    end = pre.predict(start, sim["g"])
    assert (end.position() - truth.position()[1:]).norm(dim=-1).max() < 1e-5
    assert (end.velocity() - truth.velocity()[1:]).norm(dim=-1).max() < 2e-5
    assert (end.rotation() - truth.rotation()[1:]).abs().max() < 1e-6
    assert (sim["bias"][0] == b).all()  # noise=0 holds the biases constant


def test_smoother_converges_and_beats_gtsam_on_noise_free_runs(study):
    """All runs converge.  On the noise-free versions of the compared runs (the same
    trajectory, biases and factors) the truth minimises the continuous-time problem, so each
    estimate's error is its preintegration's: torchsgal's (exact products of the held samples)
    is several times below GTSAM's first-order scheme's.  On the noisy runs the two RMSEs are
    dominated by the noise (decimetres) and differ by millimetres either way, which is why the
    comparison of accuracy is made where it can be decided."""
    assert study["converged"].all() and study["exact_converged"].all()
    assert study["sparse_difference"].max() < 1e-8  # run 0 alone (sparse Cholesky) = in the batch
    ours, gtsam = study["exact_rmse_ours"], study["exact_rmse_gtsam"]
    assert (ours <= gtsam).all(), (ours, gtsam)
    assert ours[0] < 0.25 * gtsam[0], (ours, gtsam)
    assert study["exact_ours"][:, 0].max() < 1e-3  # m, noise-free: the truth to a millimetre
    # noisy runs: both estimates are decimetres from the truth, the position within 1 m
    assert 0.1 < study["rmse_all"][0] < 1.0 and study["rmse_ours"][0] < 1.0


def test_trajectories_agree_within_the_discretisation_difference(study):
    """torchsgal's and GTSAM's estimates of the same noisy runs differ by about what their
    preintegrations' discretisation does to a trajectory: GTSAM's error on the noise-free runs
    (where torchsgal sits at the truth).  Noise moves the states and biases at which the
    discretisation acts, so the band is a factor of two; the difference stays far below the
    estimates' error against the truth."""
    between = study["between"]  # (G, 3) largest over the states: position, velocity, rotation
    discretisation = study["exact_gtsam"]
    assert (between <= 2 * discretisation).all(), (between, discretisation)
    assert (between > 0.25 * discretisation).all(), (between, discretisation)  # it is the cause
    assert between[:, 0].max() < 0.02 * study["rmse_gtsam"][0]
    # the per-window increments differ by GTSAM's O(dt) scheme: millimetres per 1 s window
    assert 1e-4 < study["window_difference"][:, 0].max() < 1e-2


def test_nees_of_the_smoothed_states(study, example):
    """The Laplace marginals are consistent with the errors.  The runs are samples of the
    model (priors drawn around the truth), so one state's NEES averaged over B runs is
    chi2(9 B) / B.  The average over the states of a run is a mean of such (correlated)
    variables, no more spread than one of them (convex order), so the 99.9 % interval of
    chi2(9 B) / B bounds it.  Here (mean 11.5 in [4.9, 14.8]) covariances 1.3 times too small
    or 2.4 times too large would fall outside."""
    nees = study["nees"]
    B = nees.shape[0]
    lo, hi = example.chi2_band(9 * B, mass=0.999)
    mean = float(nees.mean())
    assert lo / B < mean < hi / B, (mean, lo / B, hi / B)
    assert torch.isfinite(nees).all()


def test_the_script_writes_its_outputs(tmp_path):
    pytest.importorskip("matplotlib")
    pytest.importorskip("gtsam")
    out = subprocess.run(
        [sys.executable, "examples/gnss_ins_smoother.py", "--no-show", "--out", str(tmp_path),
         "--runs", "2", "--duration", "10", "--gtsam-runs", "1", "--repeats", "1", "--seed", "1"],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
        env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert out.returncode == 0, out.stderr[-3000:]
    assert (tmp_path / "gnss_ins.png").stat().st_size > 0
    text = (tmp_path / "gnss_ins.md").read_text()
    assert "2 Monte Carlo runs of 10 s" in text and "Converged: 2 of 2 runs" in text
    assert "| GTSAM, runs 0-0 |" in text
