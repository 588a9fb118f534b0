"""The total-least-squares problem of kelly-giamou Section 5: Jacobians, exactness,
consistency, robustness, the GTSAM peer and the command line."""
import json
import math

import pytest
import torch

import torchsgal as ts
from torchsgal.estimation import SolverStatus, gauss_helmert, study, tls
from torchsgal.estimation import variables as V

f64 = torch.float64


def _problem(B=3, N1=5, seed=0):
    gen = torch.Generator().manual_seed(seed)
    Fa = ts.SGal3(ts.functional.sgal3.random((B, N1), f64, None, gen))
    Fb = ts.SGal3(ts.functional.sgal3.random((B, N1), f64, None, gen))
    S = study.paper_covariance()
    return tls.TLSProblem(Fa, Fb, S, S), gen


def _per_condition_jacobian(f, e):
    """d f(e)_n / d e_n for f: (B, N, m) -> (B, N, k), by autograd."""
    J = torch.autograd.functional.jacobian(f, e)  # (B, N, k, B, N, m)
    B, N = e.shape[:2]
    return torch.stack([torch.stack([J[b, n, :, b, n, :] for n in range(N)]) for b in range(B)])


@pytest.mark.parametrize("estimator", ["sgal3", "baseline"])
@pytest.mark.parametrize("at_zero", [True, False])
def test_condition_jacobians_match_autograd(estimator, at_zero):
    """(5.19)-(5.22) and our derivation at non-zero residuals: J_r(c)^-1 times the returned
    Jacobians equals autograd of c = log(...) (the J_r(c) factor is dropped on purpose)."""
    P, gen = _problem()
    if estimator == "sgal3":
        cond = tls.sgal3_condition(P)
        x = (ts.SGal3(ts.functional.sgal3.random((3,), f64, None, gen)),
             torch.randn(3, 1, generator=gen, dtype=f64))
        G, rows = ts.SGal3, 10
    else:
        cond = tls.baseline_condition(P)
        x = (ts.SE23(ts.functional.se23.random((3,), f64, None, gen)),
             torch.randn(3, 1, generator=gen, dtype=f64), torch.randn(3, 1, generator=gen, dtype=f64))
        G, rows = ts.SE23, 9
    e = None if at_zero else 0.3 * torch.randn(3, 5, 20, generator=gen, dtype=f64)
    c, A, Bm = cond(x, e)
    jri = G.jr_inv(c[..., :rows])
    A = torch.cat([jri @ A[..., :rows, :], A[..., rows:, :]], -2)
    Bm = torch.cat([jri @ Bm[..., :rows, :], Bm[..., rows:, :]], -2)
    ee = torch.zeros(3, 5, 20, dtype=f64) if e is None else e
    JA = torch.func.jacrev(lambda d: cond(V.retract(x, d), e)[0].sum(0))(torch.zeros(3, 11, dtype=f64))
    # round-off only (entries up to ~10): measured 5e-15 to 9e-15 over the cases
    assert (A - JA.permute(2, 0, 1, 3)).abs().max() < 1e-12
    JB = _per_condition_jacobian(lambda de: cond(x, ee + de)[0], torch.zeros_like(ee))
    assert (Bm - JB).abs().max() < 1e-12


def test_printed_jacobian_5_21_at_zero_residual():
    """(5.21) as printed, J_r(eps)^-1 (n Ad(F_dtau^n F^-1) - n I) e_10, built from matrices."""
    P, gen = _problem(B=2, N1=4)
    cond = tls.sgal3_condition(P)
    F = ts.SGal3(ts.functional.sgal3.random((2,), f64, None, gen))
    dtau = torch.tensor([[0.7], [-1.3]], dtype=f64)
    c, A, _ = cond((F, dtau), None)
    for b in range(2):
        for n in range(4):
            xi = torch.zeros(10, dtype=f64)
            xi[9] = n * dtau[b, 0]
            T = ts.SGal3.exp(xi)
            col = n * ((T @ F[b].inverse()).adjoint() - torch.eye(10, dtype=f64))[:, 9]
            assert torch.allclose(A[b, n, :, 10], col, rtol=0, atol=1e-12)
            assert torch.allclose(A[b, n, :, :10], T.adjoint(), rtol=0, atol=1e-12)  # (5.22)


@pytest.mark.parametrize("variant", ["iterated", "paper"])
def test_noise_free_observations_are_recovered_exactly(variant):
    cfg = study.StudyConfig(trials=6, samples=21, noise_scale=0.0, seed=1)
    trials = study.simulate(cfg)
    sol = tls.solve_sgal3(trials.problem, variant=variant)
    assert sol.report.converged.all()
    assert trials.F_true.rminus(sol.x[0]).abs().max() < 1e-9
    assert (trials.dtau_true - sol.x[1][:, 0]).abs().max() < 1e-10
    base = tls.solve_baseline(trials.problem, variant=variant)
    X_true, tau_true = study.baseline_truth(trials.F_true, trials.F_ga0)
    assert base.report.converged.all()
    assert X_true.rminus(base.x[0]).abs().max() < 1e-9
    assert (tau_true - base.x[1][:, 0]).abs().max() < 1e-10
    assert (trials.dtau_true - base.x[2][:, 0]).abs().max() < 1e-10


def test_iterated_variant_is_the_errors_in_variables_optimum():
    """At the iterated Gauss-Helmert solution (x, e_a), the exact EIV cost with the true frames
    as nuisance variables is stationary in every variable."""
    cfg = study.StudyConfig(trials=4, samples=21, seed=2)
    trials = study.simulate(cfg)
    sol = tls.solve_sgal3(trials.problem, variant="iterated", step_tol=1e-10, max_iterations=60,
                          corrections_tol=1e-10)
    assert sol.report.converged.all()
    cost = tls.eiv_cost(trials.problem)
    d = torch.zeros(4, 11, dtype=f64, requires_grad=True)
    u = sol.aux[..., :10].clone().requires_grad_(True)
    gx, gu = torch.autograd.grad(cost(V.retract(sol.x, d), u).sum(), [d, u])
    # Gradients in whitened units: times the standard deviations of the variables.
    sd = sol.covariance.diagonal(dim1=-2, dim2=-1).sqrt()
    assert (gx * sd).abs().max() < 1e-6
    assert (gu * study.paper_covariance().diagonal().sqrt()).abs().max() < 1e-6
    # The paper variant stops elsewhere: within a fraction of a standard deviation.
    paper = tls.solve_sgal3(trials.problem, variant="paper")
    gap = paper.x[0].rminus(sol.x[0]) / sd[:, :10]
    assert 1e-6 < gap.abs().max() < 1.0


def test_small_monte_carlo_consistency():
    """Correctly specified model: the iterated SGal(3) estimator's ANEES lies in the 95% band;
    the SE_2(3) x R baseline is clearly overconfident.  (A 95% band: seed 0; seeds 0-7 of the
    chunk-independent simulation give 6 of 8 inside.)"""
    cfg = study.StudyConfig(trials=120, samples=31, seed=0, variants=("iterated",))
    out = study.run(cfg, progress=False)
    lo, hi = out["anees_band_95"]
    sg = out["results"]["SGal(3)"]["iterated"]
    assert lo <= sg["ANEES"] <= hi
    for reading in ("invariant", "product"):
        bl = out["results"][study.BASELINE_NAMES[reading]]["iterated"]
        assert sg["converged"] == bl["converged"] == 120
        assert bl["ANEES"] > 3 * hi


def test_bad_initialisation_converges_to_the_same_solution():
    """Rotation errors up to 90 degrees and dtau off by 50% (iterated variant, damped)."""
    cfg = study.StudyConfig(trials=12, samples=31, seed=4)
    trials = study.simulate(cfg)
    good = tls.solve_sgal3(trials.problem, variant="iterated")
    gen = torch.Generator().manual_seed(5)
    axis = torch.randn(12, 3, generator=gen, dtype=f64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    angle = torch.linspace(0.1, math.pi / 2, 12, dtype=f64)
    delta = torch.zeros(12, 10, dtype=f64)
    delta[:, 6:9] = axis * angle[:, None]
    F0 = trials.F_true.rplus(delta)
    dtau0 = (1.5 * trials.dtau_true)[:, None]
    bad = tls.solve_sgal3(trials.problem, x0=(F0, dtau0), variant="iterated", max_iterations=100)
    assert bad.report.converged.all()
    sd = good.covariance.diagonal(dim1=-2, dim2=-1).sqrt()
    assert (bad.x[0].rminus(good.x[0]) / sd[:, :10]).abs().max() < 1e-3


def test_non_finite_observation_spoils_only_its_trial():
    cfg = study.StudyConfig(trials=4, samples=11, seed=6)
    trials = study.simulate(cfg)
    M = trials.problem.F_ga.as_matrix().clone()
    M[1, 3, 0, 4] = float("inf")
    P = tls.TLSProblem(ts.SGal3(M), trials.problem.F_gb, trials.problem.cov_a, trials.problem.cov_b)
    sol = tls.solve_sgal3(P)
    assert sol.report.status.tolist() == [0, SolverStatus.NON_FINITE, 0, 0]
    ref = tls.solve_sgal3(trials.problem)
    ok = [0, 2, 3]
    # the other trials agree with the clean solve to the solver's stopping tolerance (step_tol,
    # in standard deviations of the estimate), not to rounding: the tensor code's vectorised
    # kernels round an element by its position in the batch, and the spoiled trial leaves the
    # working set after its first evaluation, moving the trials after it (measured 1.2e-7 sd;
    # through the position-independent C kernels 7e-15 sd)
    d = torch.cat([ref.x[0][ok].rminus(sol.x[0][ok]), ref.x[1][ok] - sol.x[1][ok]], -1)
    sd = ref.covariance[ok].diagonal(dim1=-2, dim2=-1).sqrt()
    assert (d / sd).abs().max() < tls.DEFAULT_OPTIONS["step_tol"]


@pytest.mark.parametrize("solver", ["sgal3", "baseline"])
@pytest.mark.parametrize("variant,samples", [("iterated", 11), ("paper", 11), ("paper", 101)])
def test_data_that_require_gradients_solve_as_detached_data(solver, variant, samples):
    """docs/guide/estimation.md: results come back detached whether or not the data or the
    covariances require gradients.  The structured solver's out= buffers must not raise 'functions
    with out=... arguments don't support automatic differentiation' (iterated, and the paper
    variant from 2,048 conditions: 21 trials of 101 samples)."""
    trials = study.simulate(study.StudyConfig(trials=21, samples=samples, seed=12)).problem
    solve = tls.solve_sgal3 if solver == "sgal3" else tls.solve_baseline
    ref = solve(trials, variant=variant)
    F_ga = ts.SGal3(trials.F_ga.as_matrix().clone().requires_grad_(True))
    cov_a = trials.cov_a.clone().requires_grad_(True)
    sol = solve(tls.TLSProblem(F_ga, trials.F_gb, cov_a, trials.cov_b), variant=variant)
    assert not sol.covariance.requires_grad and not sol.x[0].as_matrix().requires_grad
    assert torch.equal(sol.covariance, ref.covariance)
    assert torch.equal(sol.x[0].as_matrix(), ref.x[0].as_matrix())


def test_solver_options_are_checked_by_their_own_names():
    P, _ = _problem()
    with pytest.raises(TypeError, match=r"unknown solver option\(s\) \['straggler_fraction'\]"):
        tls.solve_sgal3(P, straggler_fraction=0.1)
    for bad in (-0.1, float("nan")):
        with pytest.raises(ValueError, match="step_tol must be a finite number >= 0"):
            tls.solve_baseline(P, step_tol=bad)
    for bad in (0, -1):
        with pytest.raises(ValueError, match="reweightings must be an integer >= 1"):
            tls.solve_sgal3_lbfgs(P, reweightings=bad)


def test_frames_at_rest_make_dtau_unobservable():
    """With no relative velocity, dtau does not enter the conditions: SINGULAR information."""
    cfg = study.StudyConfig(trials=3, samples=11, speed=0.0, noise_scale=0.0, seed=7)
    trials = study.simulate(cfg)
    sol = tls.solve_sgal3(trials.problem)
    assert (sol.report.status == SolverStatus.SINGULAR).all()


def test_bad_input_gets_clear_errors():
    P, _ = _problem()
    S = study.paper_covariance()
    with pytest.raises(ValueError, match="at least 2 observation pairs .* got 1"):
        tls.TLSProblem(P.F_ga[:, :1], P.F_gb[:, :1], S, S)
    with pytest.raises(ValueError, match="F_ga and F_gb must have the same batch shape"):
        tls.TLSProblem(P.F_ga, P.F_gb[:, :4], S, S)
    with pytest.raises(ValueError, match=r"F_ga must have batch shape \(B, N\+1\)"):
        tls.TLSProblem(P.F_ga[0], P.F_gb[0], S, S)
    with pytest.raises(TypeError, match="F_gb must be SGal3"):
        tls.TLSProblem(P.F_ga, ts.SE23.identity((3, 5), dtype=f64), S, S)
    with pytest.raises(ValueError, match="cov_b is not symmetric"):
        tls.TLSProblem(P.F_ga, P.F_gb, S, S + torch.triu(torch.ones(10, 10, dtype=f64), 1))
    with pytest.raises(ValueError, match="cov_a is not positive definite"):
        tls.TLSProblem(P.F_ga, P.F_gb, -S, S)
    with pytest.raises(ValueError, match=r"cov_a must have shape \(\.\.\., 10, 10\)"):
        tls.TLSProblem(P.F_ga, P.F_gb, torch.eye(9, dtype=f64), S)
    with pytest.raises(ValueError, match="cov_a must broadcast"):
        tls.TLSProblem(P.F_ga, P.F_gb, S.expand(7, 10, 10), S)
    with pytest.raises(ValueError, match=r"indices must have shape \(N\+1,\)"):
        tls.TLSProblem(P.F_ga, P.F_gb, S, S, indices=torch.arange(4))


def test_problem_and_unknowns_are_checked():
    P, _ = _problem(B=4)
    S = study.paper_covariance()
    with pytest.raises(TypeError, match="F_ga must be SGal3"):
        tls.TLSProblem(P.F_ga.as_matrix(), P.F_gb, S, S)
    with pytest.raises(TypeError, match="indices must be a tensor"):
        tls.TLSProblem(P.F_ga, P.F_gb, S, S, indices=range(5))
    with pytest.raises(ValueError, match="indices is on meta but F_ga is on cpu"):
        tls.TLSProblem(P.F_ga, P.F_gb, S, S, indices=torch.arange(5.0, device="meta"))
    with pytest.raises(TypeError, match="cov_a has dtype torch.float32"):
        tls.TLSProblem(P.F_ga, P.F_gb, S.float(), S)
    # A list of indices is taken as a tensor.
    listed = tls.TLSProblem(P.F_ga, P.F_gb, S, S, indices=[0, 1, 2, 3, 4])
    assert torch.equal(listed.indices, P.indices)
    # Non-finite sample indices (shared by every trial) are bad input, not 4 NON_FINITE trials;
    # bool or complex ones are not sample indices (cast, they would become 0/1, or lose their
    # imaginary part).
    for bad in (float("nan"), float("inf")):
        with pytest.raises(ValueError, match="indices must be finite"):
            tls.TLSProblem(P.F_ga, P.F_gb, S, S,
                           indices=torch.tensor([0.0, 1.0, bad, 3.0, 4.0], dtype=f64))
    with pytest.raises(ValueError, match="indices must be finite .*got 1 non-finite of 5, the first "
                                         "at position 3"):
        tls.TLSProblem(P.F_ga, P.F_gb, S, S, indices=[0, 1, 2, float("nan"), 4])
    with pytest.raises(TypeError, match=r"indices must be .* \(not bools\)"):  # not read as 1.0
        tls.TLSProblem(P.F_ga, P.F_gb, S, S, indices=[True] * 5)
    for bad in (torch.ones(5, dtype=torch.bool), torch.arange(5.0).to(torch.complex128)):
        with pytest.raises(TypeError, match=f"indices must be real numbers, got {bad.dtype}"):
            tls.TLSProblem(P.F_ga, P.F_gb, S, S, indices=bad)

    F0, dt = P.initial_guess(-1.0)
    X0, t0 = tls.split_clock(F0)
    with pytest.raises(ValueError, match=r"x0\[0\] must be SGal3 of batch shape \(B,\) = \(4,\)"):
        tls.solve_sgal3(P, x0=(X0, dt))
    with pytest.raises(TypeError, match=r"x0 must be a tuple \(F SGal3 \(B,\), dtau \(B, 1\)\)"):
        tls.solve_sgal3(P, x0=F0)
    with pytest.raises(ValueError, match=r"x0 must be a tuple .* got 3 block"):
        tls.solve_sgal3(P, x0=(F0, dt, dt))
    with pytest.raises(ValueError, match=r"x0\[1\] must be a tensor of shape \(B, 1\) = \(4, 1\)"):
        tls.solve_sgal3(P, x0=(F0, torch.cat([dt, dt], 1)))
    with pytest.raises(ValueError, match=r"x0\[0\] must be SE23"):
        tls.solve_baseline(P, x0=(F0, t0[:, None], dt))
    with pytest.raises(ValueError, match=r"x0 must be a tuple \(X' SE23 .* got 1 block"):
        tls.solve_baseline(P, x0=(X0,))
    with pytest.raises(TypeError, match="x0 has dtype torch.float32"):
        tls.solve_sgal3(P, x0=(ts.SGal3(F0.as_matrix().float()), dt.float()))
    with pytest.raises(ValueError, match=r"dtau0 must be a scalar or have shape \(B,\) = \(4,\)"):
        tls.solve_sgal3(P, dtau0=torch.ones(3, dtype=f64))
    with pytest.raises(ValueError, match=r"dtau0 must be a scalar or have shape \(B,\)"):
        tls.solve_baseline(P, dtau0=torch.ones(4, 1, dtype=f64))
    with pytest.raises(ValueError, match="lambda_initial must be a finite number > 0, got -1.0"):
        tls.solve_sgal3(P, lambda_initial=-1.0)
    with pytest.raises(ValueError, match="max_iterations must be an integer >= 0"):
        tls.solve_baseline(P, max_iterations=-1)
    with pytest.raises(ValueError, match="variant must be one of"):
        tls.solve_sgal3(tls.subset(P, slice(0, 0)), variant="exact")


@pytest.mark.parametrize("solver", ["sgal3", "baseline", "lbfgs"])
def test_empty_batch_gives_an_empty_solution(solver):
    P, _ = _problem(B=2)
    empty = tls.subset(P, slice(0, 0))
    assert empty.batch_size == 0
    solve = {"sgal3": tls.solve_sgal3, "baseline": tls.solve_baseline,
             "lbfgs": tls.solve_sgal3_lbfgs}[solver]
    sol = solve(empty)
    assert sol.covariance.shape == (0, 11, 11) and sol.covariance.dtype == f64
    assert sol.x[0].batch_shape == (0,) and all(b.shape == (0, 1) for b in sol.x[1:])
    assert len(sol.x) == (3 if solver == "baseline" else 2)
    for name in ("status", "iterations", "initial_cost", "cost", "step_norm", "gradient_norm"):
        assert getattr(sol.report, name).shape == (0,)
    assert sol.report.counts() == {}


def test_command_line_refuses_no_trials_and_float32(capsys):
    from torchsgal.__main__ import main
    for argv, message in ((["--trials", "0"], "--trials: must be at least 1, got 0"),
                          (["--chunk", "-3"], "--chunk: must be at least 1"),
                          (["--dtype", "float32"], "the TLS study needs float64"),
                          (["--samples", "1"], "--samples: must be at least 2, got 1"),
                          (["--samples", "-3"], "--samples: must be at least 2, got -3"),
                          (["--threads", "-2"], "--threads: must be at least 1, got -2"),
                          (["--speed", "nan"], "--speed: must be a finite number >= 0, got nan"),
                          (["--separation", "inf"], "--separation: must be a finite number >= 0"),
                          (["--clock-offset", "-1"], "--clock-offset: must be a finite number >= 0"),
                          (["--dtau-sigma", "x"], "--dtau-sigma: expected a finite number >= 0")):
        with pytest.raises(SystemExit) as exc:
            main(["tls", *argv, "--quiet", "--no-plot"])
        assert exc.value.code == 2
        assert message in capsys.readouterr().err


def test_study_config_and_run_check_their_arguments():
    with pytest.raises(ValueError, match="trials must be an integer >= 1, got 0"):
        study.StudyConfig(trials=0)
    with pytest.raises(ValueError, match="trials must be an integer >= 1, got -2"):
        study.StudyConfig(trials=-2)
    with pytest.raises(TypeError, match="trials must be an integer >= 1, got 2.5"):
        study.StudyConfig(trials=2.5)
    with pytest.raises(ValueError, match="samples must be an integer >= 2, got 1"):
        study.StudyConfig(samples=1)
    with pytest.raises(ValueError, match="max_iterations must be an integer >= 1, got 0"):
        study.StudyConfig(max_iterations=0)
    for name in ("noise_scale", "dtau_sigma", "speed", "separation", "clock_offset"):
        with pytest.raises(ValueError, match=f"{name} must be a finite number >= 0, got -0.5"):
            study.StudyConfig(**{name: -0.5})
        with pytest.raises(ValueError, match=f"{name} must be a finite number >= 0, got nan"):
            study.StudyConfig(**{name: float("nan")})
    with pytest.raises(ValueError, match="nominal_dtau must be a finite number, got inf"):
        study.StudyConfig(nominal_dtau=math.inf)
    for bad in ("int64", "bogus", torch.int64, torch.float16):
        with pytest.raises(ValueError, match="dtype must be 'float64' or 'float32'"):
            study.StudyConfig(dtype=bad)
    assert study.StudyConfig(dtype=torch.float64).dtype == "float64"
    assert study.StudyConfig(dtype=torch.float32).dtype == "float32"
    for bad in (("p",), (), ("paper", "exact"), 3):
        with pytest.raises(ValueError, match="variants must be a .*tuple of"):
            study.StudyConfig(variants=bad)
    assert study.StudyConfig(variants="paper").variants == ("paper",)
    assert study.StudyConfig().variants == ("iterated", "paper")
    with pytest.raises(TypeError, match="dtype must be torch.float32 or torch.float64, got torch.int64"):
        study.paper_covariance(torch.int64)
    cfg = study.StudyConfig(trials=3, samples=11)
    for chunk in (0, -1):  # chunk=0 would loop forever
        with pytest.raises(ValueError, match="chunk must be an integer >= 1"):
            study.run(cfg, chunk=chunk, progress=False)
    with pytest.raises(TypeError, match="chunk must be an integer >= 1, got 1.5"):
        study.run(cfg, chunk=1.5, progress=False)
    cfg.trials = 0  # changed after construction: checked again by run
    with pytest.raises(ValueError, match="trials must be an integer >= 1, got 0"):
        study.run(cfg, progress=False)
    with pytest.raises(ValueError, match="trials must be an integer >= 0, got -1"):
        study.simulate(study.StudyConfig(trials=3, samples=11), trials=-1)
    out = study.run(study.StudyConfig(trials=2, samples=11, variants="paper"), chunk=1,
                    progress=False)
    assert set(out["results"]["SGal(3)"]) == {"paper"}
    assert out["results"]["SGal(3)"]["paper"]["trials"] == 2


def test_gtsam_factor_graph_agrees():
    pytest.importorskip("gtsam")
    from torchsgal.estimation import gtsam_peer
    cfg = study.StudyConfig(trials=2, samples=31, seed=8)
    trials = study.simulate(cfg)
    P = trials.problem
    ours = tls.solve_sgal3(P, variant="iterated", step_tol=1e-9)
    F0, dt0 = P.initial_guess(cfg.nominal_dtau)
    for k in range(2):
        F, dtau, cov, _ = gtsam_peer.solve_trial(
            P.F_ga.as_matrix()[k].numpy(), P.F_gb.as_matrix()[k].numpy(), P.cov_a.numpy(),
            P.cov_b.numpy(), F0.as_matrix()[k].numpy(), float(dt0[k, 0]))
        sd = ours.covariance[k].diagonal().sqrt()
        # measured: 6e-8 and 2e-8 sd, covariances 1.6e-9 and 2e-10 (GTSAM's LM tolerances)
        assert (ts.SGal3(torch.tensor(F)).rminus(ours.x[0][k]) / sd[:10]).abs().max() < 1e-6
        assert abs(dtau - float(ours.x[1][k, 0])) / float(sd[10]) < 1e-6
        rel = (torch.tensor(cov) - ours.covariance[k]) / torch.outer(sd, sd)
        assert rel.abs().max() < 1e-8


def test_command_line_writes_the_study(tmp_path, monkeypatch):
    from torchsgal import load
    from torchsgal.__main__ import main
    kept = []
    monkeypatch.setattr(load, "keep_freed_memory", lambda: kept.append(True) or True)
    rc = main(["tls", "--trials", "6", "--samples", "11", "--out", str(tmp_path), "--quiet",
               "--no-plot", "--seed", "3"])
    assert rc == 0 and kept == [True]  # the process keeps freed blocks unless --release-memory
    out = json.loads((tmp_path / "tls_study.json").read_text())
    assert out["config"]["trials"] == 6
    assert out["chunk"] == study.DEFAULT_CHUNK  # recorded, and the same default as study.run
    assert set(out["results"]) == {"SGal(3)", "SE_2(3) x R invariant", "SE_2(3) x R product"}
    for est in out["results"].values():
        assert set(est) == {"iterated", "paper"}
        for r in est.values():
            assert r["converged"] == 6 and math.isfinite(r["ANEES"]) and r["ANEES"] > 0
    table = (tmp_path / "tls_study.md").read_text()
    assert "| SGal(3) paper-style |" in table and "paper: SGal(3)" in table


def test_command_line_warns_that_frames_at_rest_hide_dtau(tmp_path, capsys):
    from torchsgal.__main__ import main
    assert main(["tls", "--trials", "2", "--samples", "11", "--speed", "0", "--out", str(tmp_path),
                 "--quiet", "--no-plot", "--variants", "iterated", "--release-memory"]) == 0
    assert "dtau is not observable" in capsys.readouterr().err


def test_lbfgs_reaches_the_paper_variant_estimate():
    """torch.optim.LBFGS on the reduced condition cost with reweighted frozen weights has the
    paper variant's Gauss-Newton fixed point as its solution."""
    cfg = study.StudyConfig(trials=2, samples=31, seed=9)
    trials = study.simulate(cfg)
    gn = tls.solve_sgal3(trials.problem, variant="paper", step_tol=1e-9)
    lb = tls.solve_sgal3_lbfgs(trials.problem, step_tol=1e-7)
    assert lb.report.converged.all()
    sd = gn.covariance.diagonal(dim1=-2, dim2=-1).sqrt()
    d = torch.cat([lb.x[0].rminus(gn.x[0]), lb.x[1] - gn.x[1]], -1) / sd
    assert d.abs().max() < 1e-4


def _random_covariance(shape, gen, scale):
    A = torch.randn(*shape, 10, 10, generator=gen, dtype=f64)
    return scale * (A @ A.transpose(-1, -2) / 10 + 0.2 * torch.eye(10, dtype=f64))


@pytest.mark.parametrize("estimator", ["sgal3", "baseline"])
@pytest.mark.parametrize("variant", ["iterated", "paper"])
@pytest.mark.parametrize("covariance", ["paper", "per trial", "per sample"])
def test_engine_solvers_match_generic_gauss_helmert(estimator, variant, covariance):
    """The solvers on the factor-graph engine (graph.GaussHelmert, one condition per sample)
    give the generic Gauss-Helmert solution of sgal3_condition / baseline_condition: estimates,
    covariances, residual estimates and costs.  Measured: paper variant 1e-10 standard
    deviations; iterated 1.5e-7 with the engine stopping on its step test at 3e-7 standard
    deviations (``relative_error_tol=0``), about the agreement of the two solvers' fixed points
    when both run on.  Its default cost test would stop where the next step's predicted decrease
    is below 1e-14 of the cost: up to sqrt(2e-14 cost), ~3e-6 standard deviations here, from
    the fixed point, wherever rounding puts the last iterate."""
    cfg = study.StudyConfig(trials=5, samples=13, seed=10)
    trials = study.simulate(cfg)
    P = trials.problem
    gen = torch.Generator().manual_seed(11)
    if covariance != "paper":
        shape = (5, 1) if covariance == "per trial" else (5, 13)
        scale = study.paper_covariance().diagonal().sqrt()
        scale = scale[:, None] * scale[None, :]
        P = tls.TLSProblem(P.F_ga, P.F_gb, _random_covariance(shape, gen, scale),
                           _random_covariance(shape, gen, scale))
    if estimator == "sgal3":
        x0 = P.initial_guess(-1.0)
        cond, cov = tls.sgal3_condition(P), P.covariance
    else:
        F0, dt = P.initial_guess(-1.0)
        X0, t0 = tls.baseline_start(F0)  # the solver's start (invariant reading, the default)
        x0 = (X0, t0[:, None], dt)
        cond, cov = tls.baseline_condition(P), tls.baseline_covariance(P)
    ref = gauss_helmert(cond, x0, cov, variant=variant, step_tol=1e-10, max_iterations=100)
    solve = tls.solve_sgal3 if estimator == "sgal3" else tls.solve_baseline
    tight = (dict(step_tol=3e-7, corrections_tol=3e-7, relative_error_tol=0.0) if variant == "iterated"
             else dict(step_tol=1e-10, corrections_tol=1e-10))
    new = solve(P, variant=variant, max_iterations=100, **tight)
    assert new.report.converged.all() and ref.report.converged.all()
    tol = 1e-9 if variant == "paper" else 1e-6
    sd = ref.covariance.diagonal(dim1=-2, dim2=-1).sqrt()
    d = torch.cat([new.x[0].rminus(ref.x[0])] + [a - b for a, b in zip(new.x[1:], ref.x[1:])], -1)
    assert (d / sd).abs().max() < tol
    outer = sd[:, :, None] * sd[:, None, :]
    assert ((new.covariance - ref.covariance) / outer).abs().max() < tol
    torch.testing.assert_close(new.report.cost, ref.report.cost, rtol=tol, atol=0)
    if variant == "iterated":
        assert (new.aux - ref.aux).abs().max() < 1e-7
    else:
        assert new.aux is None


def _edge_problem():
    """4 trials: 0 and 3 ordinary, 1 with the frames at rest and no noise (dtau unobservable:
    SINGULAR), 2 with a NaN observation (NON_FINITE)."""
    P = study.simulate(study.StudyConfig(trials=4, samples=11, seed=6)).problem
    rest = study.simulate(study.StudyConfig(trials=4, samples=11, speed=0.0, noise_scale=0.0,
                                            seed=7)).problem
    Fa, Fb = P.F_ga.as_matrix().clone(), P.F_gb.as_matrix().clone()
    Fa[1], Fb[1] = rest.F_ga.as_matrix()[1], rest.F_gb.as_matrix()[1]
    Fa[2, 3, 0, 4] = float("nan")
    return tls.TLSProblem(ts.SGal3(Fa), ts.SGal3(Fb), P.cov_a, P.cov_b)


def test_lbfgs_solver_carries_singular_and_non_finite_trials():
    """A SINGULAR or NON_FINITE trial does not crash solve_sgal3_lbfgs (by a Cholesky of its NaN
    covariance): it gets the identity preconditioner and its status, and the other trials
    are what they are alone.  initial_cost is the cost at x0 (not the last round's)."""
    P = _edge_problem()
    sol = tls.solve_sgal3_lbfgs(P)
    assert sol.report.status.tolist() == [0, SolverStatus.SINGULAR, SolverStatus.NON_FINITE, 0]
    assert torch.isnan(sol.report.cost[2]) and torch.isnan(sol.report.initial_cost[2])
    for k in (0, 3):
        alone = tls.solve_sgal3_lbfgs(tls.subset(P, slice(k, k + 1)))
        sd = alone.covariance[0].diagonal().sqrt()
        d = torch.cat([alone.x[0].rminus(sol.x[0][k:k + 1]), alone.x[1] - sol.x[1][k:k + 1]], -1)
        assert (d[0] / sd).abs().max() < 1e-10  # rounding: the batch's factorisations
        assert alone.report.iterations[0] == sol.report.iterations[k]
    ok = [0, 3]
    x0 = P.initial_guess(-1.0)
    expected = tls.condition_cost(P, weights_at=x0)(x0)[ok]
    torch.testing.assert_close(sol.report.initial_cost[ok], expected, rtol=1e-12, atol=0)
    gh = tls.solve_sgal3(P, variant="paper")
    torch.testing.assert_close(sol.report.initial_cost[ok], gh.report.initial_cost[ok],
                               rtol=1e-10, atol=0)
    assert (sol.report.cost[ok] < 0.5 * sol.report.initial_cost[ok]).all()


def test_simulated_trials_do_not_depend_on_the_chunk():
    """Each chunk drew from one shared generator, so the table changed with --chunk (and the
    command line's default chunk differed from study.run's)."""
    cfg = study.StudyConfig(trials=5, samples=11, seed=4)
    whole = study.simulate(cfg)
    part = study.simulate(cfg, 3, start=2)
    assert torch.equal(whole.problem.F_ga.as_matrix()[2:], part.problem.F_ga.as_matrix())
    assert torch.equal(whole.problem.F_gb.as_matrix()[2:], part.problem.F_gb.as_matrix())
    assert torch.equal(whole.dtau_true[2:], part.dtau_true)
    # ... nor on the number of trials.
    assert torch.equal(study.simulate(study.StudyConfig(trials=2, samples=11, seed=4)
                                      ).problem.F_ga.as_matrix(), whole.problem.F_ga.as_matrix()[:2])
    a = study.run(cfg, chunk=2, progress=False)
    b = study.run(cfg, chunk=5, progress=False)
    assert (a["chunk"], b["chunk"]) == (2, 5)
    for name in ("SGal(3)", "SE_2(3) x R invariant", "SE_2(3) x R product"):
        for variant in ("iterated", "paper"):
            ra, rb = a["results"][name][variant], b["results"][name][variant]
            for key in ("position", "velocity", "interval", "ANEES", "MMD"):
                assert ra[key] == pytest.approx(rb[key], rel=1e-6), (name, variant, key)
    with pytest.raises(ValueError, match="start must be an integer >= 0, got -1"):
        study.simulate(cfg, 2, start=-1)
    # One default chunk for the library and the command line (test_command_line_writes_the_study).
    import inspect
    assert inspect.signature(study.run).parameters["chunk"].default == study.DEFAULT_CHUNK


def test_study_without_converged_trials_writes_strict_json(tmp_path):
    """NaN metrics (no converged trial) are written as null, not as NaN, which is not JSON."""
    cfg = study.StudyConfig(trials=2, samples=11, variants="paper", max_iterations=1)
    out = study.run(cfg, progress=False)
    assert out["results"]["SGal(3)"]["paper"]["converged"] == 0
    study.write_outputs(out, str(tmp_path), plot=False)

    def refuse(constant):
        raise ValueError(f"not JSON: {constant}")
    saved = json.loads((tmp_path / "tls_study.json").read_text(), parse_constant=refuse)
    assert saved["results"]["SGal(3)"]["paper"]["ANEES"] is None
    assert saved["chunk"] == study.DEFAULT_CHUNK


def _cli(*args, timeout=60):
    import os
    import subprocess
    import sys
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    return subprocess.run([sys.executable, "-m", "torchsgal", "tls", "--trials", "1",
                           "--samples", "2", "--quiet", "--no-plot", *args], cwd=root,
                          capture_output=True, text=True, timeout=timeout)


def test_command_line_checks_the_output_folder_before_running(tmp_path, capsys, monkeypatch):
    """A bad --out is refused before the study runs (it would fail after it with a traceback,
    losing the results)."""
    proc = _cli("--out", "/proc/nope")
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "argument --out: cannot write to '/proc/nope'" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert "trials of" not in proc.stderr  # refused before the study started
    from torchsgal.__main__ import main
    afile = tmp_path / "afile"
    afile.write_text("")
    monkeypatch.setattr(study, "run", lambda *a, **k: pytest.fail("the study ran"))
    with pytest.raises(SystemExit) as exc:
        main(["tls", "--quiet", "--no-plot", "--out", str(afile)])
    assert exc.value.code == 2
    assert f"argument --out: '{afile}' exists and is not a directory" in capsys.readouterr().err


def test_command_line_caps_the_threads_and_handles_ctrl_c(capsys, monkeypatch, tmp_path):
    """--threads 100000 is refused (it would crash torch, exit 139); Ctrl-C exits with 130, not
    a KeyboardInterrupt traceback."""
    from torchsgal.__main__ import _max_threads, main
    proc = _cli("--threads", "100000", "--out", str(tmp_path))
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert f"--threads: must be at most {_max_threads()}" in proc.stderr
    assert not list(tmp_path.iterdir())

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt
    monkeypatch.setattr(study, "run", interrupted)
    assert main(["tls", "--quiet", "--no-plot", "--out", str(tmp_path)]) == 130
    assert capsys.readouterr().err.strip().splitlines()[-1] == "interrupted"


@pytest.mark.parametrize("variant", ["iterated", "paper"])
def test_two_observation_pairs_suffice(variant):
    """The first pair fixes F_a0b0 (10 conditions), the second the interval through the drift
    r - dtau v: 2 pairs determine the 11 unknowns (3 must not be required)."""
    cfg = study.StudyConfig(trials=5, samples=2, noise_scale=0.0, seed=5)
    trials = study.simulate(cfg)
    sol = tls.solve_sgal3(trials.problem, variant=variant)
    assert sol.report.converged.all()
    assert trials.F_true.rminus(sol.x[0]).abs().max() < 1e-8
    assert (trials.dtau_true - sol.x[1][:, 0]).abs().max() < 1e-8
    base = tls.solve_baseline(trials.problem, variant=variant)
    assert base.report.converged.all()
    assert (trials.dtau_true - base.x[2][:, 0]).abs().max() < 1e-8
    # Without relative velocity the drift vanishes: dtau is unobservable, reported SINGULAR.
    rest = study.simulate(study.StudyConfig(trials=2, samples=2, speed=0.0, noise_scale=0.0,
                                            seed=5))
    assert (tls.solve_sgal3(rest.problem, variant=variant).report.status
            == SolverStatus.SINGULAR).all()


def test_subset_and_dtau0_name_bad_arguments():
    """subset takes a slice or an int64 index tensor (an int would drop the batch axis and the error
    would name F_ga); a bool is no number for dtau0 (True would be read as 1.0)."""
    P = study.simulate(study.StudyConfig(trials=3, samples=6, seed=0)).problem
    for index in (2, "a", torch.tensor([True, False, True]), torch.tensor([[0, 1]])):
        with pytest.raises(TypeError, match="index must be a slice or a 1-D int64 tensor of trials"):
            tls.subset(P, index)
    assert tls.subset(P, torch.tensor([0, 2])).batch_size == 2
    with pytest.raises(TypeError, match="dtau0 must be a torch.Tensor, a real number"):
        tls.solve_sgal3(P, dtau0=True)
    # A dtau0 tensor of another dtype is named as dtau0, not as x0[1] (an argument not given),
    # and initial_guess does not hand back an integer dtau.
    for solve in (tls.solve_sgal3, tls.solve_baseline):
        with pytest.raises(TypeError, match="dtau0 must have a floating dtype .* got torch.int64"):
            solve(P, dtau0=torch.tensor([-1, -1, -1]))
        with pytest.raises(TypeError, match="dtau0 has dtype torch.float32 but"):
            solve(P, dtau0=torch.tensor([-1.0, -1.0, -1.0]))
    with pytest.raises(TypeError, match="dtau must have a floating dtype .* got torch.int64"):
        P.initial_guess(torch.tensor(-1))
    assert P.initial_guess(-1)[1].dtype == torch.float64  # a Python number is converted
