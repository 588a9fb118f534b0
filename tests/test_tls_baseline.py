"""The SE_2(3) x R baseline of the TLS study in its two readings: "invariant" (relative
transforms composed in SGal(3), read in the product group) and "product" (observations
composed in the product group).  Frame invariance under a Galilean change of the global frame,
exact recovery, Jacobians against autograd, the structured solver against the generic one,
and argument checks."""
import pytest
import torch

import torchsgal as ts
from torchsgal.estimation import SolverStatus, gauss_helmert, metrics, study, tls
from torchsgal.estimation import variables as V

f64 = torch.float64
READINGS = ("invariant", "product")


def _time_shift(tau: torch.Tensor) -> ts.SGal3:
    """exp(tau e_10): the pure time translation by tau (B,)."""
    xi = torch.zeros(tau.shape + (10,), dtype=tau.dtype)
    xi[..., 9] = tau
    return ts.SGal3.exp(xi)


def _reexpressed(trials: study.TrialSet, G: ts.SGal3) -> study.TrialSet:
    """The same trials in another global frame g': F_g'x = G F_gx for the observations and the
    true frame a (the noise is a right perturbation, so it is carried along unchanged)."""
    P = trials.problem
    Gn = G.unsqueeze(-1)
    problem = tls.TLSProblem(Gn @ P.F_ga, Gn @ P.F_gb, P.cov_a, P.cov_b, indices=P.indices)
    return study.TrialSet(problem, trials.F_true, trials.dtau_true, G @ trials.F_ga0)


def _frames(trials: study.TrialSet) -> dict:
    """The study's global frame, a frame moving with frame a (G = F_ga0^-1: a at rest at the
    origin), and a frame moving at 20 m/s relative to it (rotated and shifted in space and
    time as well)."""
    B = trials.F_true.batch_shape[0]
    gen = torch.Generator().manual_seed(21)
    w = torch.randn(B, 3, generator=gen, dtype=f64)
    w = 20.0 * w / w.norm(dim=-1, keepdim=True)
    C = ts.SO3.random((B,), dtype=f64, generator=gen).as_matrix()
    boost = ts.SGal3.from_components(C, w, 50.0 * torch.randn(B, 3, generator=gen, dtype=f64),
                                     10.0 * torch.randn(B, generator=gen, dtype=f64))
    assert torch.allclose(boost.velocity().norm(dim=-1), torch.full((B,), 20.0, dtype=f64))
    return {"with a": _reexpressed(trials, trials.F_ga0.inverse()),
            "20 m/s": _reexpressed(trials, boost)}


def _anees(sol, trials, reading):
    ok = sol.report.status == SolverStatus.CONVERGED
    err = study.errors_baseline(sol, trials, reading)
    return float(metrics.nees(err[ok], sol.covariance[ok]).mean())


@pytest.mark.parametrize("variant", ["iterated", "paper"])
def test_invariant_reading_does_not_depend_on_the_global_frame(variant):
    """Re-expressing the same data in a frame moving with frame a, or at 20 m/s, leaves the
    invariant reading's estimate, covariance and ANEES unchanged to rounding, while the
    product reading's estimate moves by many standard deviations and its ANEES changes."""
    trials = study.simulate(study.StudyConfig(trials=16, samples=31, seed=3))
    frames = _frames(trials)
    # The paper variant's Gauss-Newton iterates are the same up to rounding (1e-10); the
    # iterated one stops where its Levenberg-Marquardt cost test meets the rounding of the
    # cost (relative_error_tol 1e-14 of a cost of ~3000: steps of ~1e-6 standard deviations),
    # so the two frames' estimates agree to that (measured 1.2e-6) and not to 1e-10.
    tight = {"step_tol": 1e-10, "corrections_tol": 1e-10}
    tol = 1e-10 if variant == "paper" else 1e-5
    ref = {r: tls.solve_baseline(trials.problem, variant=variant, reading=r, **tight)
           for r in READINGS}
    anees = {r: _anees(ref[r], trials, r) for r in READINGS}
    for r in READINGS:
        assert (ref[r].report.status == SolverStatus.CONVERGED).all()
    for name, moved in frames.items():
        inv = tls.solve_baseline(moved.problem, variant=variant, reading="invariant", **tight)
        assert torch.equal(inv.report.status, ref["invariant"].report.status), name
        sd = ref["invariant"].covariance.diagonal(dim1=-2, dim2=-1).sqrt()
        d = torch.cat([inv.x[0].rminus(ref["invariant"].x[0])] +
                      [a - b for a, b in zip(inv.x[1:], ref["invariant"].x[1:])], -1)
        # rounding of the composed relative transforms: measured 4e-13 to 1.3e-12 sd
        assert (d / sd).abs().max() < tol, name
        outer = sd[:, :, None] * sd[:, None, :]
        assert ((inv.covariance - ref["invariant"].covariance) / outer).abs().max() < tol, name
        assert _anees(inv, moved, "invariant") == pytest.approx(anees["invariant"], rel=tol)
        # The product reading changes with the frame (the test would fail if it did not).
        prod = tls.solve_baseline(moved.problem, variant=variant, reading="product")
        X_prod, _ = study.baseline_truth(trials.F_true, moved.F_ga0, "product")
        X_ref, _ = study.baseline_truth(trials.F_true, trials.F_ga0, "product")
        assert X_prod.rminus(X_ref).abs().max() > 1.0  # its target itself moves
        sd_prod = ref["product"].covariance.diagonal(dim1=-2, dim2=-1).sqrt()
        assert (prod.x[0].rminus(ref["product"].x[0]) / sd_prod[:, :9]).abs().max() > 3.0
        assert abs(_anees(prod, moved, "product") / anees["product"] - 1) > 0.2, name


@pytest.mark.parametrize("reading", READINGS)
@pytest.mark.parametrize("variant", ["iterated", "paper"])
def test_noise_free_observations_are_recovered_exactly(reading, variant):
    """Noise-free data give the baseline's truth exactly: for the invariant reading the
    SE_2(3) part of F_ab exp(-tau e_10) (frame b's origin at a-time zero), formed here by the
    group product; for the product reading (C, v, r + C_ga^T v_ga tau)."""
    trials = study.simulate(study.StudyConfig(trials=6, samples=21, noise_scale=0.0, seed=1))
    sol = tls.solve_baseline(trials.problem, variant=variant, reading=reading)
    assert sol.report.converged.all()
    F = trials.F_true
    tau = F.time()
    if reading == "invariant":
        X_true = tls.split_clock(F @ _time_shift(-tau))[0]
        assert torch.allclose(X_true.as_matrix(), study.baseline_truth(F)[0].as_matrix(),
                              rtol=0, atol=1e-12)
    else:
        C_ga, v_ga = trials.F_ga0.rotation(), trials.F_ga0.velocity()
        r = F.position() + (C_ga.transpose(-1, -2) @ v_ga[..., None])[..., 0] * tau[:, None]
        X_true = ts.SE23.from_components(F.rotation(), F.velocity(), r)
    assert X_true.rminus(sol.x[0]).abs().max() < 1e-9
    assert (tau - sol.x[1][:, 0]).abs().max() < 1e-10
    assert (trials.dtau_true - sol.x[2][:, 0]).abs().max() < 1e-10


def test_invariant_reading_solves_the_study_trials():
    """The study's own trials (101 samples, both variants): every trial converges, and the
    baseline is overconfident (clock noise times the relative velocity is not in its model)."""
    cfg = study.StudyConfig(trials=24, seed=5, readings="invariant")
    out = study.run(cfg, progress=False)
    assert set(out["results"]) == {"SGal(3)", study.BASELINE_NAMES["invariant"]}
    lo, hi = out["anees_band_95"]
    for variant in ("iterated", "paper"):
        res = out["results"][study.BASELINE_NAMES["invariant"]][variant]
        assert res["converged"] == 24 and res["status"] == {"CONVERGED": 24}
        assert res["ANEES"] > 3 * hi


def _per_condition_jacobian(f, e):
    """d f(e)_n / d e_n for f: (B, N, m) -> (B, N, k), by autograd."""
    J = torch.autograd.functional.jacobian(f, e)  # (B, N, k, B, N, m)
    B, N = e.shape[:2]
    return torch.stack([torch.stack([J[b, n, :, b, n, :] for n in range(N)]) for b in range(B)])


@pytest.mark.parametrize("reading", READINGS)
@pytest.mark.parametrize("at_zero", [True, False])
def test_condition_jacobians_match_autograd(reading, at_zero):
    """J_r(c)^-1 times the returned Jacobians of the spatial rows (and the clock rows as they
    are) equal autograd of the condition, at zero and non-zero residuals."""
    gen = torch.Generator().manual_seed(2)
    Fa = ts.SGal3(ts.functional.sgal3.random((3, 5), f64, None, gen))
    Fb = ts.SGal3(ts.functional.sgal3.random((3, 5), f64, None, gen))
    S = study.paper_covariance()
    cond = tls.baseline_condition(tls.TLSProblem(Fa, Fb, S, S), reading)
    x = (ts.SE23(ts.functional.se23.random((3,), f64, None, gen)),
         torch.randn(3, 1, generator=gen, dtype=f64), torch.randn(3, 1, generator=gen, dtype=f64))
    e = None if at_zero else 0.3 * torch.randn(3, 5, 20, generator=gen, dtype=f64)
    c, A, Bm = cond(x, e)
    jri = ts.SE23.jr_inv(c[..., :9])
    A = torch.cat([jri @ A[..., :9, :], A[..., 9:, :]], -2)
    Bm = torch.cat([jri @ Bm[..., :9, :], Bm[..., 9:, :]], -2)
    ee = torch.zeros(3, 5, 20, dtype=f64) if e is None else e
    JA = torch.func.jacrev(lambda d: cond(V.retract(x, d), e)[0].sum(0))(torch.zeros(3, 11, dtype=f64))
    assert (A - JA.permute(2, 0, 1, 3)).abs().max() < 1e-12  # round-off only
    JB = _per_condition_jacobian(lambda de: cond(x, ee + de)[0], torch.zeros_like(ee))
    assert (Bm - JB).abs().max() < 1e-12


def test_readings_compose_the_observations_differently():
    """The invariant reading's M'_n is the split of F~_gb^-1 F~_ga composed in SGal(3); the
    product reading's differs from it by the term of SGal(3)'s product that the product group
    drops (positions differ by metres in the study's data)."""
    P = study.simulate(study.StudyConfig(trials=2, samples=5, seed=8)).problem
    M_inv, dt_inv = tls.baseline_observations(P, "invariant")
    M_prod, dt_prod = tls.baseline_observations(P, "product")
    M = (P.F_gb.inverse() @ P.F_ga).as_matrix()
    assert torch.allclose(M_inv.as_matrix()[..., :3, :3], M[..., :3, :3], rtol=0, atol=1e-12)
    assert torch.allclose(M_inv.velocity(), M[..., :3, 3], rtol=0, atol=1e-12)
    assert torch.allclose(M_inv.position(), M[..., :3, 4], rtol=0, atol=1e-10)
    assert torch.allclose(dt_inv, M[..., 3, 4], rtol=0, atol=1e-12)
    assert torch.allclose(dt_prod, dt_inv, rtol=0, atol=1e-12)
    assert (M_prod.position() - M_inv.position()).norm(dim=-1).max() > 1.0


@pytest.mark.parametrize("reading", READINGS)
@pytest.mark.parametrize("variant", ["iterated", "paper"])
def test_engine_solver_matches_generic_gauss_helmert(reading, variant):
    """solve_baseline on the factor-graph engine gives the generic Gauss-Helmert solution of
    baseline_condition in each reading (paper variant to 1e-9 standard deviations, iterated to
    1e-6 with the engine stopping on its step test at 3e-7 standard deviations: see
    test_tls.py's test_engine_solvers_match_generic_gauss_helmert)."""
    P = study.simulate(study.StudyConfig(trials=5, samples=13, seed=10)).problem
    F0, dt = P.initial_guess(-1.0)
    X0, t0 = tls.baseline_start(F0, reading)
    x0 = (X0, t0[:, None], dt)
    ref = gauss_helmert(tls.baseline_condition(P, reading), x0, tls.baseline_covariance(P),
                        variant=variant, step_tol=1e-10, max_iterations=100)
    tight = (dict(step_tol=3e-7, corrections_tol=3e-7, relative_error_tol=0.0) if variant == "iterated"
             else dict(step_tol=1e-10, corrections_tol=1e-10))
    new = tls.solve_baseline(P, variant=variant, reading=reading, max_iterations=100, **tight)
    tol = 1e-9 if variant == "paper" else 1e-6
    sd = ref.covariance.diagonal(dim1=-2, dim2=-1).sqrt()
    d = torch.cat([new.x[0].rminus(ref.x[0])] + [a - b for a, b in zip(new.x[1:], ref.x[1:])], -1)
    assert (d / sd).abs().max() < tol
    outer = sd[:, :, None] * sd[:, None, :]
    assert ((new.covariance - ref.covariance) / outer).abs().max() < tol
    assert torch.equal(new.report.status, ref.report.status)


def test_bad_reading_is_refused_with_a_clear_error():
    P = study.simulate(study.StudyConfig(trials=2, samples=3, seed=0)).problem
    msg = r"reading must be one of \('invariant', 'product'\), got 'products'"
    with pytest.raises(ValueError, match=msg):
        tls.solve_baseline(P, reading="products")
    with pytest.raises(ValueError, match=msg):
        tls.baseline_condition(P, "products")
    with pytest.raises(ValueError, match=r"reading must be one of .*, got None"):
        tls.solve_baseline(P, reading=None)
    with pytest.raises(ValueError, match=msg):
        study.baseline_truth(study.simulate(study.StudyConfig(trials=1, samples=2)).F_true,
                             reading="products")
    with pytest.raises(TypeError, match="F_ga0 .* must be SGal3 for the product reading"):
        study.baseline_truth(study.simulate(study.StudyConfig(trials=1, samples=2)).F_true,
                             reading="product")
    with pytest.raises(ValueError, match=r"readings must be a non-empty tuple of .*, got \('x',\)"):
        study.StudyConfig(readings=("x",))
    with pytest.raises(ValueError, match=r"readings must be a non-empty tuple of .*, got \(\)"):
        study.StudyConfig(readings=())
    assert study.StudyConfig(readings="product").readings == ("product",)


def test_command_line_reports_both_readings(tmp_path, capsys):
    from torchsgal.__main__ import main
    assert main(["tls", "--trials", "3", "--samples", "11", "--out", str(tmp_path), "--quiet",
                 "--no-plot", "--variants", "paper"]) == 0
    table = (tmp_path / "tls_study.md").read_text()
    assert "| SE_2(3) x R invariant paper-style |" in table
    assert "| SE_2(3) x R product paper-style |" in table
    assert main(["tls", "--trials", "3", "--samples", "11", "--out", str(tmp_path), "--quiet",
                 "--no-plot", "--variants", "paper", "--readings", "product"]) == 0
    assert "SE_2(3) x R invariant" not in (tmp_path / "tls_study.md").read_text()
    with pytest.raises(SystemExit):
        main(["tls", "--readings", "both", "--out", str(tmp_path)])
    assert "argument --readings: invalid choice: 'both'" in capsys.readouterr().err
