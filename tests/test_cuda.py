"""The library on a CUDA device against the same code on the CPU (whose results the rest of the
suite checks against their definitions and the peers), and CUDA's own host-sync detector on the
hot paths.

Collected only where ``torch.cuda.is_available()`` (see conftest.py): CI has no GPU, so these
tests run on a GPU machine (``python -m pytest tests/test_cuda.py``); docs/benchmarks.md (On
CUDA) names the machine and torch they last passed on.  ``TORCHSGAL_CUDA_TEST_DEVICE=cpu`` runs
this file against the CPU itself, to work on the harness without a GPU (the parity checks are
then trivial and the sync detector is off).
"""
from __future__ import annotations

import contextlib
import os

import pytest
import torch
from conftest import GROUP_CLASSES, assert_close, sample_tangent

import torchsgal as ts
from torchsgal import imu
from torchsgal import kinematics as kin
from torchsgal import regression as reg
from torchsgal.estimation import study, tls
from torchsgal.uncertainty import ConcentratedGaussian, fuse_event

DEVICE = torch.device(os.environ.get("TORCHSGAL_CUDA_TEST_DEVICE", "cuda"))
CPU = torch.device("cpu")
if DEVICE.type == "cuda" and not torch.cuda.is_available():
    raise RuntimeError("tests/test_cuda.py needs a CUDA device and torch.cuda.is_available() is False "
                       "(TORCHSGAL_CUDA_TEST_DEVICE=cpu runs its harness on the CPU)")
IDS = [G.__name__ for G in GROUP_CLASSES]
DTYPES = [torch.float64, torch.float32]
DIDS = ["float64", "float32"]
# Every angle band of conftest.ANGLES (12 cycled angles) plus random tangents of all sizes.
N_BANDED, N_RANDOM = 48, 4096


def _same(actual, expected, dtype, what, factor=1.0):
    """``actual`` computed on DEVICE equals ``expected`` computed on the CPU, within the suite's
    float tolerance (conftest.tol; relative to magnitude)."""
    if isinstance(actual, ts.LieGroup):
        actual, expected = actual.as_matrix(), expected.as_matrix()
    assert actual.device.type == DEVICE.type, f"{what}: result on {actual.device}, not {DEVICE}"
    assert actual.dtype == dtype, f"{what}: dtype {actual.dtype}, expected {dtype}"
    assert_close(actual, expected, dtype, factor=factor, msg=what)


@contextlib.contextmanager
def _no_sync():
    """CUDA raises on any synchronising call (value reads, nonzero, blocking copies)."""
    if DEVICE.type != "cuda":
        yield
        return
    old = torch.cuda.get_sync_debug_mode()
    torch.cuda.set_sync_debug_mode("error")
    try:
        yield
    finally:
        torch.cuda.set_sync_debug_mode(old)


def _tangents(G, dtype):
    banded = sample_tangent(G, (N_BANDED,), dtype, seed=3)
    rand = torch.randn(N_RANDOM, G.dof, dtype=dtype, generator=torch.Generator().manual_seed(4))
    return torch.cat([banded, rand])


def test_device_is_what_this_file_tests():
    x = torch.ones(2, device=DEVICE)
    assert x.device.type == DEVICE.type
    if DEVICE.type == "cuda":
        assert torch.cuda.is_available()


@pytest.mark.parametrize("dtype", DTYPES, ids=DIDS)
@pytest.mark.parametrize("G", GROUP_CLASSES, ids=IDS)
def test_group_operations_match_cpu(G, dtype):
    xi = _tangents(G, dtype)
    other = _tangents(G, dtype).flip(0)
    alpha = torch.linspace(-0.5, 1.5, xi.shape[0], dtype=dtype)
    points = 3 * torch.randn(xi.shape[0], 4, dtype=dtype, generator=torch.Generator().manual_seed(2))
    results = {}
    for dev in (CPU, DEVICE):
        x, y, a = xi.to(dev), other.to(dev), alpha.to(dev)
        g, h = G.exp(x), G.exp(y)
        p, d = points[..., :G.point_dim].to(dev), points[..., :G.rotation_dim].to(dev)
        ops = {
            "exp": g, "log": g.log(), "compose": g @ h, "inverse": g.inverse(),
            "adjoint": g.adjoint(), "act": g.act(p), "act_direction": g.act_direction(d),
            "rplus": g.rplus(y), "rminus": g.rminus(h), "lplus": g.lplus(y), "lminus": g.lminus(h),
            "between": g.between(h), "interpolate": g.interpolate(h, a),
            "interpolate(number)": g.interpolate(h, 0.3), "hat": G.hat(x), "vee": G.vee(G.hat(x)),
            "ad": G.ad(x), "jl": G.jl(x), "jr": G.jr(x), "jl_inv": G.jl_inv(x), "jr_inv": G.jr_inv(x),
            "from_matrix(check=True)": G.from_matrix(g.as_matrix(), check=True),
        }
        if hasattr(g, "act_velocity"):
            ops["act_velocity"] = g.act_velocity(points[..., :3].to(dev))
        results[dev] = ops
    for name, expected in results[CPU].items():
        _same(results[DEVICE][name], expected, dtype, f"{G.__name__}.{name} ({dtype})")


@pytest.mark.parametrize("G", GROUP_CLASSES, ids=IDS)
def test_constructors_on_device(G):
    for dtype in DTYPES:
        e = G.identity((3, 2), dtype=dtype, device=DEVICE)
        assert e.device.type == DEVICE.type and e.dtype == dtype and e.batch_shape == (3, 2)
        gen = torch.Generator(device=DEVICE).manual_seed(0)
        r = G.random((1000,), dtype=dtype, device=DEVICE, generator=gen)
        assert r.device.type == DEVICE.type and r.dtype == dtype
        assert_close(G.from_matrix(r.as_matrix(), check=True).as_matrix(), r.as_matrix(), dtype)
        again = G.random((1000,), dtype=dtype, device=DEVICE,
                         generator=torch.Generator(device=DEVICE).manual_seed(0))
        assert torch.equal(again.as_matrix(), r.as_matrix())
    with pytest.raises(ValueError, match="not in"):
        bad = G.identity((2,), dtype=torch.float64, device=DEVICE).as_matrix().clone()
        bad[..., 0, 0] = 2.0
        G.from_matrix(bad, check=True)


@pytest.mark.parametrize("dtype", DTYPES, ids=DIDS)
@pytest.mark.parametrize("G", GROUP_CLASSES, ids=IDS)
def test_custom_autograd_matches_cpu(G, dtype):
    """Reverse mode (the closed-form backward of exp and log) and forward mode."""
    xi = _tangents(G, dtype)
    w = torch.randn(xi.shape[0], G.dof, dtype=dtype, generator=torch.Generator().manual_seed(5))
    W = torch.randn(xi.shape[0], G.matrix_dim, G.matrix_dim, dtype=dtype,
                    generator=torch.Generator().manual_seed(6))
    out = {}
    for dev in (CPU, DEVICE):
        x = xi.to(dev).requires_grad_()
        (g_exp,) = torch.autograd.grad((G.exp(x).as_matrix() * W.to(dev)).sum(), x)
        m = G.exp(xi.to(dev)).as_matrix().requires_grad_()
        (g_log,) = torch.autograd.grad((G.from_matrix(m).log() * w.to(dev)).sum(), m)
        _, tangent = torch.func.jvp(lambda v: G.exp(v).log(), (xi.to(dev),), (w.to(dev),))
        out[dev] = {"exp backward": g_exp, "log backward": g_log, "exp/log jvp": tangent}
    for name, expected in out[CPU].items():
        # Gradients near pi carry log's conditioning (1/sin): a few times the value tolerance.
        _same(out[DEVICE][name], expected, dtype, f"{G.__name__} {name} ({dtype})", factor=10.0)


@pytest.mark.parametrize("G", GROUP_CLASSES, ids=IDS)
def test_gradcheck_on_device(G):
    xi = sample_tangent(G, (6,), torch.float64, seed=7).to(DEVICE).requires_grad_()
    assert torch.autograd.gradcheck(lambda x: G.exp(x).as_matrix(), (xi,))
    # log of a group-valued function of xi built independently of exp (matrix_exp)
    log_of = lambda v: G.from_matrix(torch.linalg.matrix_exp(G.hat(v))).log()  # noqa: E731
    assert torch.autograd.gradcheck(log_of, (xi,))


@pytest.mark.parametrize("G", GROUP_CLASSES, ids=IDS)
def test_vmap_and_jacrev_match_cpu(G):
    xi = sample_tangent(G, (12,), torch.float64, seed=8)
    f = lambda v: G.exp(v).log()  # noqa: E731
    jac = {dev: torch.func.vmap(torch.func.jacrev(f))(xi.to(dev)) for dev in (CPU, DEVICE)}
    _same(jac[DEVICE], jac[CPU], torch.float64, f"{G.__name__} vmap(jacrev)", factor=10.0)
    # The identity: d log(exp(v)) / dv = I away from the cut locus (angles here are < pi).
    eye = torch.eye(G.dof, dtype=torch.float64).expand_as(jac[CPU])
    assert_close(jac[DEVICE], eye, torch.float64, factor=1e4, msg="jacobian of log(exp(v))")


def test_compile_on_device_matches_eager():
    """One compiled function through exp, log and their backward (inductor's device kernels)."""
    G = ts.SGal3

    def f(x):
        return G.exp(x).compose(G.exp(x.flip(0))).log().square().sum()  # not @ (README)

    def value_and_grad(fn, xi):
        x = xi.clone().requires_grad_()
        val = fn(x)
        (grad,) = torch.autograd.grad(val, x)
        return val, grad

    compiled = torch.compile(f, fullgraph=True)
    for dtype in DTYPES:
        xi = _tangents(G, dtype).to(DEVICE)
        eager_val, eager_grad = value_and_grad(f, xi)
        val, grad = value_and_grad(compiled, xi)
        assert val.device.type == DEVICE.type
        assert_close(val, eager_val, dtype, factor=10.0, msg=f"compiled value ({dtype})")
        assert_close(grad, eager_grad, dtype, factor=10.0, msg=f"compiled grad ({dtype})")


# ------------------------------------------------- the SGal(3) operators' compiled closed forms
OPS = ("sgal3_exp", "sgal3_log", "sgal3_exp_vjp", "sgal3_log_vjp", "sgal3_jl", "sgal3_jl_inv")


@pytest.fixture
def compiled_cuda():
    """The opt-in compiled closed forms (native.use_compiled_cuda) for one test."""
    native = ts.functional.native
    before = native._state["compiled"]
    native.use_compiled_cuda(True)
    yield
    native.use_compiled_cuda(before)


def _op_arguments(name, batch, dtype):
    """The operator's arguments, every angle band included (conftest.sample_tangent)."""
    n = 1
    for b in batch:
        n *= b
    xi = sample_tangent(ts.SGal3, (n,), torch.float64, seed=11).reshape(*batch, 10)
    g = torch.Generator().manual_seed(12)
    M = ts.functional.sgal3.exp_impl(xi)
    G = torch.randn(*batch, 5, 5, generator=g, dtype=torch.float64)
    w = torch.randn(*batch, 10, generator=g, dtype=torch.float64)
    args = {"sgal3_exp": (xi,), "sgal3_log": (M,), "sgal3_exp_vjp": (xi, M, G),
            "sgal3_log_vjp": (M, xi, w), "sgal3_jl": (xi,), "sgal3_jl_inv": (xi,)}[name]
    return tuple(a.to(dtype) for a in args)


def _cuda_kernels(fn):
    """Names of the device kernels one call of ``fn`` launches (torch.profiler)."""
    activity = torch.profiler.ProfilerActivity
    with torch.profiler.profile(activities=[activity.CPU, activity.CUDA]) as prof:
        fn()
        torch.cuda.synchronize()
    return [e.name for e in prof.events() if e.device_type == torch.autograd.DeviceType.CUDA]


@pytest.mark.parametrize("dtype", DTYPES, ids=DIDS)
@pytest.mark.parametrize("name", OPS)
def test_operators_on_device_match_cpu(name, dtype, compiled_cuda):
    """Each operator on DEVICE (on CUDA with the opt-in: float32 through the closed form
    compiled into Triton kernels, float64 through the eager closed form) equals the eager closed
    form on the CPU, at every angle band, for batches of every size (1 and 0 included) and
    shape, and for arguments whose batches broadcast ((1,) against (3, 1); the one-argument
    operators take the (1,) batch).  Compiled code reorders and fuses the arithmetic, hence the
    factor 10 of test_compile_on_device_matches_eager."""
    from torchsgal.functional import ops

    op = getattr(torch.ops.torchsgal, name).default
    for batch in [(N_BANDED,), (4, 3), (1,), (), (0,), (N_RANDOM,)]:
        args = _op_arguments(name, batch, dtype)
        with ts.functional.native.disabled():
            expected = op(*args)
        _same(op(*(a.to(DEVICE) for a in args)), expected, dtype, f"{name} {tuple(batch)}", factor=10.0)
    args = _op_arguments(name, (3,), dtype)
    broadcast = tuple(a[:1] if k == 0 else a.unsqueeze(1) for k, a in enumerate(args))
    with ts.functional.native.disabled():
        expected = op(*broadcast)
    _same(op(*(a.to(DEVICE) for a in broadcast)), expected, dtype, f"{name} broadcast", factor=10.0)
    if DEVICE.type == "cuda" and dtype in ops.COMPILED_DTYPES:  # the compiled path ran
        compiled = ops._COMPILED.get(name)
        assert compiled is not None and compiled is not ops._FAILED, compiled


@pytest.mark.parametrize("name", OPS)
def test_operators_on_cuda_run_fused_kernels(name, compiled_cuda):
    """On CUDA a compiled operator call launches Triton kernels, at least 4x fewer than the
    eager closed form (measured on an H200: 14-49 against 126-549); ``native.disabled()``
    brings the eager closed form back."""
    if DEVICE.type != "cuda":
        pytest.skip("CUDA kernels are profiled on a CUDA device only (TORCHSGAL_CUDA_TEST_DEVICE=cpu)")
    op = getattr(torch.ops.torchsgal, name).default
    args = tuple(a.to(DEVICE) for a in _op_arguments(name, (1000,), torch.float32))
    op(*args)  # compiles
    fused = _cuda_kernels(lambda: op(*args))
    with ts.functional.native.disabled():
        eager = _cuda_kernels(lambda: op(*args))
    assert any("triton" in k for k in fused), fused
    assert 4 * len(fused) < len(eager), (len(fused), len(eager))


@pytest.mark.parametrize("dtype", DTYPES, ids=DIDS)
@pytest.mark.parametrize("name", OPS)
def test_opcheck_on_device(name, dtype, compiled_cuda):
    args = tuple(a.to(DEVICE).requires_grad_(dtype is torch.float64) for a in _op_arguments(name, (3,), dtype))
    torch.library.opcheck(getattr(torch.ops.torchsgal, name).default, args)


# ---------------------------------------------------------------------- no host syncs on CUDA
@pytest.mark.parametrize("dtype", DTYPES, ids=DIDS)
@pytest.mark.parametrize("G", GROUP_CLASSES, ids=IDS)
def test_group_hot_paths_make_no_host_sync(G, dtype):
    """torch.cuda's sync debug mode raises on a value read, a data-dependent shape or a
    blocking copy: the group operations and the exp/log backward make none.  The first call
    (outside the detector) fills the per-device constants cache (functional.numerics)."""
    xi = _tangents(G, dtype).to(DEVICE)
    points = torch.ones(xi.shape[0], G.point_dim, dtype=dtype, device=DEVICE)

    def run():
        outs = []
        for x, p in ((xi, points), (xi[0], points[0])):  # batched and unbatched
            g, h = G.exp(x), G.exp(x.flip(0))
            outs += [g.log(), (g @ h).as_matrix(), g.inverse().as_matrix(), g.adjoint(),
                     g.act(p), G.jl(x), G.jr(x), G.jl_inv(x), G.jr_inv(x),
                     g.interpolate(h, 0.3).as_matrix(), g.rminus(h), G.hat(x), G.ad(x)]
            leaf = x.clone().requires_grad_()
            outs.append(torch.autograd.grad(G.exp(leaf).log().square().sum(), leaf)[0])
        return outs

    run()
    with _no_sync():
        run()


def test_application_hot_paths_make_no_host_sync():
    windows, samples = 8, 50
    g = torch.Generator().manual_seed(9)
    gyro = torch.randn(windows, samples, 3, generator=g).to(DEVICE)
    acc = torch.randn(windows, samples, 3, generator=g).to(DEVICE)
    dt = torch.full((windows, samples), 0.005, device=DEVICE)
    chain = kin.ur5(dtype=torch.float32, device=DEVICE)
    q = torch.randn(windows, chain.n_joints, generator=g).to(DEVICE)
    cov = 1e-2 * torch.eye(10, device=DEVICE).expand(windows, 10, 10)
    d = ConcentratedGaussian(ts.SGal3.random((windows,), device=DEVICE), cov, validate=False)

    def run():
        pre = imu.preintegrate(gyro, acc, dt, gyro_noise_density=1e-3, acc_noise_density=1e-2)
        start = ts.SGal3.identity((windows,), device=DEVICE)
        pre.predict(start, imu.gravity_vector(device=DEVICE), imu.earth_rate_vector(0.8, device=DEVICE))
        pre.predict_covariance(start, cov, imu.gravity_vector(device=DEVICE))
        chain.forward(q, q).pose
        chain.forward(q[0], q[0]).pose
        chain.acceleration(q, q, q)
        d.compose(d)
        d.inverse()
        d.to_side("left")
        reg.geodesic_flow(ts.SGal3, d.mean.log(), torch.linspace(0, 1, 6, device=DEVICE),
                          torch.ones(10, device=DEVICE))

    run()
    with _no_sync():
        run()


# ------------------------------------------------------------------ applications against the CPU
@pytest.mark.parametrize("per_axis", [False, True], ids=["isotropic", "per_axis"])
def test_imu_preintegration_matches_cpu(per_axis):
    """The CPU takes a fast path for large streams; the device the plain one: same numbers."""
    windows, samples = 16, 200
    g = torch.Generator().manual_seed(10)
    gyro = torch.randn(windows, samples, 3, generator=g, dtype=torch.float64)
    acc = torch.randn(windows, samples, 3, generator=g, dtype=torch.float64) + 9.8
    dt = torch.full((windows, samples), 0.005, dtype=torch.float64)
    bias = 0.01 * torch.randn(windows, 3, generator=g, dtype=torch.float64)
    density = torch.tensor([1e-3, 2e-3, 3e-3], dtype=torch.float64) if per_axis else 1e-3
    out = {}
    for dev in (CPU, DEVICE):
        pre = imu.preintegrate(gyro.to(dev), acc.to(dev), dt.to(dev), gyro_bias=bias.to(dev),
                               gyro_noise_density=density.to(dev) if per_axis else density,
                               acc_noise_density=1e-2, time_noise_density=1e-4)
        out[dev] = {"delta": pre.delta, "covariance": pre.covariance, "bias_jacobian": pre.bias_jacobian}
    for name, expected in out[CPU].items():
        _same(out[DEVICE][name], expected, torch.float64, f"imu {name}")


@pytest.mark.parametrize("G", GROUP_CLASSES, ids=IDS)
def test_gaussians_match_cpu(G):
    dtype, n = torch.float64, 64
    gen = torch.Generator().manual_seed(11)
    A = 0.1 * torch.randn(n, G.dof, G.dof, generator=gen, dtype=dtype)
    cov = A @ A.mT + 1e-3 * torch.eye(G.dof, dtype=dtype)
    mean = G.exp(sample_tangent(G, (n,), dtype, seed=12))
    out = {}
    for dev in (CPU, DEVICE):
        d = ConcentratedGaussian(mean.to(dev), cov.to(dev))
        e = ConcentratedGaussian(mean.to(dev).inverse(), cov.to(dev).flip(0))
        probe = mean.to(dev).rplus(0.1 * torch.ones(n, G.dof, dtype=dtype, device=dev))
        out[dev] = {
            "compose": d.compose(e).covariance, "compose(second_order)": d.compose(e, second_order=True).covariance,
            "inverse": d.inverse().covariance, "to_side": d.to_side("left").covariance,
            "between": d.between(e).covariance, "log_prob": d.log_prob(probe),
            "mahalanobis": d.mahalanobis(probe), "fuse": d.fuse(e).covariance, "fused mean": d.fuse(e).mean,
        }
    for name, expected in out[CPU].items():
        _same(out[DEVICE][name], expected, dtype, f"{G.__name__} Gaussian {name}", factor=10.0)
    s = ConcentratedGaussian(mean.to(DEVICE), cov.to(DEVICE)).sample(
        (100,), generator=torch.Generator(device=DEVICE).manual_seed(0))
    assert s.device.type == DEVICE.type and s.batch_shape == (100, n)


def test_fuse_event_matches_cpu():
    dtype, n = torch.float64, 32
    gen = torch.Generator().manual_seed(13)
    mean = ts.SGal3.exp(0.3 * torch.randn(n, 10, generator=gen, dtype=dtype))
    cov = 1e-2 * torch.eye(10, dtype=dtype).expand(n, 10, 10)
    event = torch.randn(n, 4, generator=gen, dtype=dtype)
    ecov = 1e-3 * torch.eye(4, dtype=dtype).expand(n, 4, 4)
    post = {dev: fuse_event(ConcentratedGaussian(mean.to(dev), cov.to(dev)), event.to(dev), ecov.to(dev))
            for dev in (CPU, DEVICE)}
    _same(post[DEVICE].mean, post[CPU].mean, dtype, "fuse_event mean", factor=10.0)
    _same(post[DEVICE].covariance, post[CPU].covariance, dtype, "fuse_event covariance", factor=10.0)


@pytest.mark.parametrize("robot", [kin.ur5, kin.iiwa7, kin.scara], ids=["ur5", "iiwa7", "scara"])
def test_gdh_chain_matches_cpu(robot):
    dtype = torch.float64
    out = {}
    for dev in (CPU, DEVICE):
        chain = robot(dtype=dtype, device=dev)
        q, dq, ddq = (torch.randn(256, chain.n_joints, generator=torch.Generator().manual_seed(k),
                                  dtype=dtype).to(dev) for k in range(3))
        state = chain.forward(q, dq)
        out[dev] = {"pose": state.pose, "linear_velocity": state.linear_velocity,
                    "angular_velocity": state.angular_velocity,
                    **dict(zip(("acceleration[0]", "acceleration[1]"), chain.acceleration(q, dq, ddq)))}
    for name, expected in out[CPU].items():
        _same(out[DEVICE][name], expected, dtype, f"{robot.__name__} {name}")


@pytest.mark.parametrize("G", [ts.SE3, ts.SGal3], ids=["SE3", "SGal3"])
def test_regression_fits_match_cpu(G):
    """The fits run the library's solvers, whose stop tests read values (a few syncs a
    solve, by design): the same fit on either device.  Iterative: the two devices' rounding
    can end the iterations at different steps, so the results agree to the solver's
    tolerance (1e3 x the value tolerance, 1e-7), not to rounding."""
    dtype = torch.float64
    gen = torch.Generator().manual_seed(15)
    p = G.exp(0.8 * torch.randn(3, G.dof, generator=gen, dtype=dtype))
    v = torch.randn(3, 2, G.dof, generator=gen, dtype=dtype)
    t = torch.linspace(-0.9, 1.1, 12, dtype=dtype)
    noise = 0.01 * torch.randn(3, 12, G.dof, generator=gen, dtype=dtype)
    Y = (p.unsqueeze(-1) @ G.exp(torch.stack([t, t * t], -1) @ v)).rplus(noise)
    fits = {}
    for dev in (CPU, DEVICE):
        Yd, td = Y.to(dev), t.to(dev)
        fits[dev] = {"polynomial": reg.fit_polynomial(Yd, td, 2),
                     "riemannian": reg.fit_riemannian_geodesic(Yd, td, steps=8)}
    for name, fit in fits[CPU].items():
        other = fits[DEVICE][name]
        assert bool(other.converged.all()) == bool(fit.converged.all()), name
        _same(other.origin, fit.origin, dtype, f"{G.__name__} {name} origin", factor=1e3)
        _same(other.coefficients, fit.coefficients, dtype, f"{G.__name__} {name} coefficients", factor=1e3)


def test_tls_solvers_match_cpu():
    """The structured Gauss-Helmert solvers on the device (iterative: agreement to the solver's
    tolerance, as for the regression fits)."""
    trials = study.simulate(study.StudyConfig(trials=16, samples=21, seed=16))
    P = trials.problem
    Pd = tls.TLSProblem(P.F_ga.to(DEVICE), P.F_gb.to(DEVICE), P.cov_a.to(DEVICE), P.cov_b.to(DEVICE),
                        indices=P.indices.to(DEVICE))
    for name, solve in [("sgal3", tls.solve_sgal3), ("baseline", tls.solve_baseline)]:
        cpu, dev = solve(P), solve(Pd)
        assert torch.equal(dev.report.status.cpu(), cpu.report.status), name
        for k, (a, b) in enumerate(zip(dev.x, cpu.x)):
            a = a.as_matrix() if isinstance(a, ts.LieGroup) else a
            b = b.as_matrix() if isinstance(b, ts.LieGroup) else b
            assert_close(a, b, torch.float64, factor=1e3, msg=f"{name} x[{k}]")
        assert_close(dev.covariance, cpu.covariance, torch.float64, factor=1e3, msg=f"{name} covariance")
