"""The C kernels of SGal(3) exp, log and their backward maps (torchsgal/functional/native.py)
against the tensor closed forms they transcribe, at every angle band and in both dtypes, and the
rule that decides where they run; the same for the SGal(3) TLS linearisation kernel against its
tensor code (the IMU preintegration kernel: tests/test_imu_kernels.py).  The tensor code is itself checked against scipy, mpmath and
GTSAM elsewhere; the rest of the suite runs through the kernels wherever they are eligible."""
from __future__ import annotations

import contextlib
import math
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from torchsgal import SGal3
from torchsgal.functional import native
from torchsgal.functional import sgal3 as F

# ``kernels``: tests of the C kernels themselves, left out of the run with the kernels switched off
# (TORCHSGAL_NATIVE=0, the second test run of .ci/run).
pytestmark = [pytest.mark.kernels,
              pytest.mark.skipif(not native.available() and os.environ.get("TORCHSGAL_NO_SKIPS") != "1",
                                 reason="the C kernels were not compiled for this installation")]

KERNELS = native.kernels("SGal3")
# Both branches of every series and threshold: numerics.SERIES_THRESHOLD = 1, JINV_THRESHOLD =
# 0.5, LOG_SIN_TAYLOR = 1e-4 and the symmetric-part log below cos = 0 (theta > pi/2).
ANGLES = [0.0, 1e-12, 1e-9, 1e-8, 1e-6, 1e-5, 1e-4, 1.0001e-4, 1e-3, 0.3, 0.5, 0.5 + 1e-9, 0.7,
          1.0 - 1e-9, 1.0, 1.0 + 1e-9, 1.5, math.pi / 2, 2.0, 3.0, math.pi - 1e-3, math.pi - 1e-6,
          math.pi - 1e-9]
# Largest deviation allowed between kernel and tensor code, relative to the largest entry of the
# compared quantity: rounding of a differently ordered but identical sequence of operations.
# Measured worst over the samples below: 6.4e-16 (float64), 4.9e-7 (float32) for exp and log;
# 2.3e-16 / 3.1e-7 for the backward maps.
REL_TOL = {torch.float64: 4e-15, torch.float32: 3e-6}


def tangents(dtype, seed=0, copies=4):
    rng = np.random.default_rng(seed)
    ang = np.repeat(ANGLES, copies)
    xi = rng.standard_normal((ang.size, 10))
    axis = rng.standard_normal((ang.size, 3))
    xi[:, 6:9] = axis / np.linalg.norm(axis, axis=-1, keepdims=True) * ang[:, None]
    return torch.tensor(xi, dtype=dtype)


def assert_rowwise_close(actual, expected, dtype):
    """Per batch element, the largest deviation relative to that element's largest entry."""
    a, e = actual.flatten(1).double(), expected.flatten(1).double()
    scale = e.abs().amax(dim=1).clamp_min(1.0)
    err = ((a - e).abs().amax(dim=1) / scale).max().item()
    assert torch.isfinite(actual).all()
    assert err <= REL_TOL[dtype], f"kernel vs tensor code: {err:.3g} > {REL_TOL[dtype]:.1g}"


def test_the_kernels_are_built_where_the_suite_requires_every_dependency():
    # .ci/run sets TORCHSGAL_NO_SKIPS=1 on a machine with a C compiler: pip must have built them.
    if os.environ.get("TORCHSGAL_NO_SKIPS") == "1":
        assert native.available(), "pip install did not build torchsgal.functional._native"
    assert native.enabled() == (native.available() and os.environ.get(native.ENV_VAR, "1") != "0")


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["float64", "float32"])
def test_exp_and_log_match_the_tensor_code_at_every_angle(dtype):
    xi = tangents(dtype)
    M = KERNELS.exp(xi)
    with native.disabled():
        M_ref = F.exp(xi)
    assert_rowwise_close(M, M_ref, dtype)
    # log of the same matrices: the rotation log's near-0, closed-form and near-pi branches.
    assert_rowwise_close(KERNELS.log(M_ref), F.log_impl(M_ref), dtype)
    assert torch.equal(M[:, 3:, :], M_ref[:, 3:, :])  # the bottom rows exactly


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["float64", "float32"])
def test_backward_maps_match_the_tensor_code_at_every_angle(dtype):
    xi = tangents(dtype, seed=1)
    gen = torch.Generator().manual_seed(2)
    M = F.exp_impl(xi)
    G = torch.randn(M.shape, generator=gen, dtype=dtype)
    g = torch.randn(xi.shape, generator=gen, dtype=dtype)
    assert_rowwise_close(KERNELS.exp_vjp(xi, M, G), F._jl_tmv(-xi, F._exp_pullback(M, G)), dtype)
    assert_rowwise_close(KERNELS.log_vjp(M, xi, g), F._log_pullback(M, F._jl_inv_tmv(-xi, g)), dtype)


def test_log_at_exactly_pi_and_the_identity():
    # cos = -1 exactly (the symmetric-part branch with s = 0) and C = I (sin = 0, the Taylor ratio).
    M = torch.eye(5, dtype=torch.float64).repeat(4, 1, 1)
    M[1, :3, :3] = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))
    M[2, :3, :3] = torch.diag(torch.tensor([-1.0, 1.0, -1.0], dtype=torch.float64))
    M[3, :3, :3] = torch.diag(torch.tensor([-1.0, -1.0, 1.0], dtype=torch.float64))
    M[:, :3, 3:] = torch.randn(4, 3, 2, dtype=torch.float64)
    M[:, 3, 4] = torch.tensor([0.5, -1.0, 2.0, 0.0], dtype=torch.float64)
    assert torch.equal(KERNELS.log(M)[:, 6:9], F.log_impl(M)[:, 6:9])
    assert_rowwise_close(KERNELS.log(M), F.log_impl(M), torch.float64)


def test_non_finite_input_gives_the_same_non_finite_output():
    xi = tangents(torch.float64)[:6].clone()
    xi[0, 0], xi[1, 7], xi[2, 9], xi[3, 6] = math.nan, math.inf, -math.inf, math.nan
    with native.disabled():
        ref = F.exp(xi)
    out = F.exp(xi)
    assert torch.equal(torch.isnan(out), torch.isnan(ref))
    finite = torch.isfinite(ref)
    assert torch.equal(finite, torch.isfinite(out))
    assert torch.allclose(out[finite], ref[finite], rtol=0, atol=1e-14)


@pytest.mark.parametrize("shape", [(), (5,), (2, 3, 1), (0,), (3, 0, 2)])
def test_batch_shapes_and_layouts(shape):
    xi = tangents(torch.float64)[: math.prod(shape)].reshape(*shape, 10)
    with native.disabled():
        ref = F.exp(xi)
    assert KERNELS.exp(xi).shape == ref.shape == (*shape, 5, 5)
    assert torch.allclose(KERNELS.exp(xi), ref, rtol=0, atol=1e-14)
    assert KERNELS.log(ref).shape == (*shape, 10)


def test_strided_negated_and_expanded_inputs_are_read_by_value():
    base = tangents(torch.float64)[:12]
    with native.disabled():
        ref = F.exp(base)
    strided = base.t().contiguous().t()  # column-major
    assert not strided.is_contiguous()
    neg_view = torch._neg_view(-base)  # lazily negated memory
    assert neg_view.is_neg()
    for x in (strided, neg_view):
        assert torch.allclose(KERNELS.exp(x), ref, rtol=0, atol=1e-14)
    one = base[:1].expand(7, 10)  # stride 0
    assert torch.allclose(KERNELS.exp(one), ref[:1].expand(7, 5, 5), rtol=0, atol=1e-14)
    # An output written from another tensor's layout would be wrong in the transposed places.
    M_t = ref.transpose(-1, -2).contiguous().transpose(-1, -2)
    assert torch.allclose(KERNELS.log(M_t), KERNELS.log(ref), rtol=0, atol=0)


def test_threads_split_the_batch_without_changing_a_bit():
    xi = tangents(torch.float64, copies=1500)  # 34,500 elements: split over 2 threads
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = KERNELS.exp(xi), KERNELS.log(F.exp_impl(xi))
        torch.set_num_threads(2)
        two = KERNELS.exp(xi), KERNELS.log(F.exp_impl(xi))
    finally:
        torch.set_num_threads(before)
    assert all(torch.equal(a, b) for a, b in zip(one, two))


_SPLIT_EXP = """
import hashlib, torch
from torchsgal.functional import native
torch.set_num_threads(2)
xi = torch.randn(40000, 10, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
out = native.kernels("SGal3").exp(xi)
print(native._lib.parallel_backend(), hashlib.sha256(out.numpy().tobytes()).hexdigest())
"""


def test_large_batches_run_on_torchs_openmp_threads_or_on_pthreads_alike():
    # Where torch runs on OpenMP its threads take the split batches (they would otherwise
    # spin-wait beside fresh pthreads); TORCHSGAL_NATIVE_OPENMP=0 keeps pthreads.  Same bits.
    import hashlib
    expected = ("none" if sys.platform == "win32" else "openmp"
                if "ATen parallel backend: OpenMP" in torch.__config__.parallel_info() else "pthreads")
    assert native._lib.parallel_backend() == expected
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        xi = torch.randn(40000, 10, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
        here = hashlib.sha256(KERNELS.exp(xi).numpy().tobytes()).hexdigest()
    finally:
        torch.set_num_threads(before)
    env = dict(os.environ, TORCHSGAL_NATIVE_OPENMP="0")
    backend, digest = subprocess.run([sys.executable, "-c", _SPLIT_EXP], env=env, capture_output=True,
                                     text=True, check=True).stdout.split()
    assert backend == ("none" if sys.platform == "win32" else "pthreads")
    assert digest == here


class _Recorder:
    """Stands in for the compiled module and records which kernels were called."""

    def __init__(self, lib):
        self.lib, self.calls = lib, []

    def __getattr__(self, name):
        fn = getattr(self.lib, name)

        def record(*args):
            self.calls.append(name)
            return fn(*args)

        return record


@pytest.fixture
def recorder(monkeypatch):
    rec = _Recorder(native._lib)
    monkeypatch.setattr(native, "_lib", rec)
    return rec


def test_eager_cpu_calls_use_the_kernels(recorder):
    xi = tangents(torch.float64)[:8]
    g = SGal3.exp(xi)
    g.log()
    g.rplus(xi)
    assert recorder.calls == ["sgal3_exp", "sgal3_log", "sgal3_exp"]
    x = xi.clone().requires_grad_()
    F.log(F.exp(x)).sum().backward()
    assert recorder.calls[3:] == ["sgal3_exp", "sgal3_log", "sgal3_log_vjp", "sgal3_exp_vjp"]


def test_observed_calls_run_the_tensor_code(recorder):
    xi = tangents(torch.float64)[:8]
    x = xi.clone().requires_grad_()
    # a backward that is itself recorded (create_graph) runs the tensor code ...
    (grad,) = torch.autograd.grad(F.exp(x).sum(), x, create_graph=True)
    assert recorder.calls == ["sgal3_exp"]  # the forward only
    # ... whose own backward reaches exp's output again, unrecorded: the kernel
    grad.sum().backward()
    assert recorder.calls == ["sgal3_exp", "sgal3_exp_vjp"]
    recorder.calls.clear()
    torch.func.vmap(F.exp)(xi)  # batched tensors: the tensor code
    assert recorder.calls == []
    # torch.func.jacrev and forward AD give a Function's forward the plain primal tensors (the
    # kernel runs, as under ordinary autograd); the vmapped backward and the jvp are tensor code.
    torch.func.jacrev(F.log)(F.exp_impl(xi[0]))
    with torch.autograd.forward_ad.dual_level():
        F.exp(torch.autograd.forward_ad.make_dual(xi, torch.ones_like(xi)))
    assert recorder.calls == ["sgal3_log", "sgal3_exp"]
    recorder.calls.clear()
    with native.disabled():
        F.exp(xi)
    torch.compile(F.exp, backend="eager", fullgraph=True)(xi)
    assert recorder.calls == []
    # differing batch shapes in a backward (not produced by autograd itself): the tensor code
    assert KERNELS.exp_vjp(xi, F.exp_impl(xi), torch.ones(5, 5, dtype=torch.float64)) is None
    assert KERNELS.exp_vjp(xi, F.exp_impl(xi), torch.ones(8, 5, 5, dtype=torch.float32)) is None


def test_gradcheck_through_the_kernels():
    xi = tangents(torch.float64, copies=1)[::3].clone().requires_grad_()
    assert torch.autograd.gradcheck(F.exp, (xi,))
    # log's backward projects onto the group (see _autograd.py): check it along the group.
    d = torch.randn(xi.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    x0 = xi.detach()

    def log_along(t):
        return F.log(F.exp_impl(x0) @ F.exp_impl(t * d))

    t = torch.zeros(xi.shape[:-1], dtype=torch.float64)[..., None].requires_grad_()
    assert torch.autograd.gradcheck(log_along, (t,))


def test_environment_variable_turns_the_kernels_off():
    code = "from torchsgal.functional import native; print(native.enabled())"
    env = dict(os.environ, TORCHSGAL_NATIVE="0")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


# ------------------------------------------------------------- TLS linearisation kernel
def tls_problem(trials, samples, covariance, seed):
    from torchsgal.estimation import study, tls
    P = study.simulate(study.StudyConfig(trials=trials, samples=samples, seed=seed)).problem
    if covariance == "paper":  # diagonal, shared
        return P
    gen = torch.Generator().manual_seed(seed)
    shape = (trials, 1) if covariance == "per trial" else (trials, samples)
    scale = study.paper_covariance().diagonal().sqrt()
    scale = scale[:, None] * scale[None, :]

    def cov():
        A = torch.randn(*shape, 10, 10, generator=gen, dtype=torch.float64)
        return scale * (A @ A.mT / 10 + 0.2 * torch.eye(10, dtype=torch.float64))
    indices = torch.arange(samples, dtype=torch.float64) * 1.5 - 3.0  # not 0..N
    return tls.TLSProblem(P.F_ga, P.F_gb, cov(), cov(), indices)


def tls_linearisations(P, iterated, e, x):
    from torchsgal.estimation import tls
    out = []
    for on in (True, False):
        with contextlib.nullcontext() if on else native.disabled():
            linearise, post_step = tls._structured(P, iterated, chunk=3)
            lin = linearise(x, e)
            delta = torch.linspace(-1e-3, 1e-3, 11, dtype=torch.float64).expand(lin.g.shape)
            out.append((lin, post_step(x, e, lin, delta)))
    return out


@pytest.mark.parametrize("covariance", ["paper", "per trial", "per sample"])
@pytest.mark.parametrize("iterated, e_scale", [(True, 0.05), (True, 1.0), (False, 0.0)],
                         ids=["iterated", "iterated-large-e", "paper"])
def test_tls_kernel_matches_the_tensor_code(covariance, iterated, e_scale, recorder):
    # e_scale 1: rotation angles of eps_a, eps_b up to ~3 rad, past the series threshold of J_r
    P = tls_problem(7, 9, covariance, seed=3)
    gen = torch.Generator().manual_seed(4)
    x = P.initial_guess(-1.0)
    e = e_scale * torch.randn(7, 9, 20, generator=gen, dtype=torch.float64)
    if e_scale > 0.5:
        angles = torch.cat([e[..., 6:9], e[..., 16:19]], -1).unflatten(-1, (2, 3)).norm(dim=-1)
        assert angles.min() < 0.5 and angles.max() > 2.0
    (lin_c, step_c), (lin_t, step_t) = tls_linearisations(P, iterated, e, x)
    # 3 chunks, each linearised and updated in C; nothing in C with the kernels off
    assert recorder.calls.count("tls_sgal3") == recorder.calls.count("tls_sgal3_step") == 3
    # The whitened Jacobians W: rounding of the same operations (measured 4e-16).  (The paper
    # variant with shared covariances has no W in the tensor code: its S is a quadratic in s.)
    quadratic = len(lin_t.extra.parts[0]) == 3
    assert quadratic == (not iterated and covariance != "per sample")
    diagonal = covariance == "paper"
    for (R_c, W_c), (R_t, *extra) in zip(lin_c.extra.parts, lin_t.extra.parts):
        # the kernel's R and W are packed (only the entries that can be non-zero, lanes last)
        assert R_c.shape[1:] == (3, 75, 4) and W_c.shape[1:] == (3, 116 if diagonal else 188, 4)
        R_c, W_c = native.kernels("tls").unpack(R_c, W_c, 9, diagonal, diagonal)
        assert R_c.shape == R_t.shape
        # the rows, relative to each trial's largest entry: measured 7e-15
        err = ((R_c - R_t).abs().amax((-2, -1)) / R_t.abs().amax((-2, -1))).max()
        assert err < 5e-14, float(err)
        if not quadratic:
            err = ((W_c - extra[0]).abs().amax((-2, -1)) / extra[0].abs().amax((-2, -1))).max()
            assert err < 4e-15, float(err)
    # The rows [L^-1, n L^-1 a, L^-1 w] and the normal equations amplify that rounding by the
    # condition of S = W W^T (up to ~5e6 here): measured 4e-13 on L^-1 (LAPACK's factor of the
    # same S differs from either by as much), 1e-13 on H, g, cost and the next e.
    for name in ("H", "g", "cost"):
        a, b = getattr(lin_c, name), getattr(lin_t, name)
        assert ((a - b).abs().max() / b.abs().max()) < 1e-11, name
    assert ((step_c - step_t).abs().max() / step_t.abs().max()) < 1e-11


def test_tls_kernel_marks_non_finite_conditions_and_runs_only_where_it_may(recorder):
    from torchsgal.estimation import tls
    P = tls_problem(4, 6, "paper", seed=5)
    x = P.initial_guess(-1.0)
    e = torch.zeros(4, 6, 20, dtype=torch.float64)
    e[2, 3, 5] = math.nan  # one condition of trial 2: its Cholesky fails
    (lin_c, _), (lin_t, _) = tls_linearisations(P, True, e, x)
    for lin in (lin_c, lin_t):
        assert torch.isfinite(lin.cost).tolist() == [True, True, False, True]
    recorder.calls.clear()
    tls.solve_sgal3(P, variant="iterated")
    assert "tls_sgal3" in recorder.calls
    recorder.calls.clear()
    tls.solve_baseline(P, variant="iterated")  # SE_2(3) x R: tensor code
    P32 = tls.TLSProblem(P.F_ga.to(torch.float32), P.F_gb.to(torch.float32),
                         P.cov_a.float(), P.cov_b.float())
    tls.solve_sgal3(P32, variant="iterated")  # float32: tensor code
    assert "tls_sgal3" not in recorder.calls


@pytest.mark.parametrize("variant", ["iterated", "paper"])
def test_tls_kernel_skips_the_trials_that_stopped_with_the_same_solution(variant, monkeypatch):
    # solver.iterate passes the running trials to a linearisation that takes them; the kernel
    # skips the others (their results are dropped).  Same solution, bit for bit, as without.
    from torchsgal.estimation import solver, study, tls
    P = study.simulate(study.StudyConfig(trials=24, seed=8)).problem
    masks = []
    linearise = native._TlsKernels.linearise

    def spy(*args):
        masks.append(args[-1])
        return linearise(*args)
    monkeypatch.setattr(native._TlsKernels, "linearise", staticmethod(spy))
    skipping = tls.solve_sgal3(P, variant=variant, straggler_fraction=0.0)
    # the first linearisation has no mask; later ones skip the trials that converged earlier
    assert masks[0] is None and all(m is not None for m in masks[1:])
    assert any(not bool(m.all()) for m in masks[1:])
    iterations = skipping.report.iterations
    assert bool((iterations < iterations.max()).any())  # some trials stop before others
    monkeypatch.setattr(solver, "ACTIVE_SET", "no such attribute")  # every trial, every time
    masks.clear()
    full = tls.solve_sgal3(P, variant=variant, straggler_fraction=0.0)
    assert all(m is None for m in masks)
    for a, b in zip(skipping.x, full.x):
        a, b = (t.as_matrix() if hasattr(t, "as_matrix") else t for t in (a, b))
        assert torch.equal(a, b)
    assert torch.equal(skipping.covariance, full.covariance)
    assert torch.equal(skipping.report.status, full.report.status)
    assert torch.equal(skipping.report.iterations, full.report.iterations)


def test_tls_kernel_state_through_rejected_steps_matches_generic_gauss_helmert(monkeypatch):
    # From a bad start (rotations off by up to 2.5 rad, dtau by a factor 2) and little damping,
    # Levenberg-Marquardt rejects steps far from the solution: the kernel's packed state is then
    # kept for the running trials that rejected (only; _ChunkState.select).  The generic
    # Gauss-Helmert layer (no packed state) is the reference, iteration by iteration: a wrong
    # kept state changes the next residual estimates and steps.
    from torchsgal.estimation import gauss_helmert, study, tls
    cfg = study.StudyConfig(trials=12, samples=31, seed=4)
    trials = study.simulate(cfg)
    P = trials.problem
    gen = torch.Generator().manual_seed(5)
    axis = torch.nn.functional.normalize(torch.randn(12, 3, generator=gen, dtype=torch.float64), dim=-1)
    delta = torch.zeros(12, 10, dtype=torch.float64)
    delta[:, 6:9] = axis * torch.linspace(0.1, 2.5, 12, dtype=torch.float64)[:, None]
    x0 = (trials.F_true.rplus(delta), (2.0 * trials.dtau_true)[:, None])
    kept = []
    select = tls._ChunkState.select

    def spy(self, mask, other):
        kept.append(int((~mask & self.active).sum()) if self.active is not None else 0)
        return select(self, mask, other)
    monkeypatch.setattr(tls._ChunkState, "select", spy)
    for k in (3, 5, 8, 12, 20, 100):
        kept.clear()
        c = tls.solve_sgal3(P, x0=x0, variant="iterated", max_iterations=k, damping=1e-10,
                            straggler_fraction=0.0)
        ref = gauss_helmert(tls.sgal3_condition(P), x0, P.covariance, variant="iterated",
                            max_iterations=k, damping=1e-10)
        assert torch.equal(c.report.iterations, ref.report.iterations), k
        assert torch.equal(c.report.status, ref.report.status), k
        sd = ref.covariance.diagonal(dim1=-2, dim2=-1).sqrt()
        assert (c.x[0].rminus(ref.x[0]) / sd[:, :10]).abs().max() < 1e-9, k
        assert ((c.x[1] - ref.x[1]) / sd[:, 10:]).abs().max() < 1e-9, k
    assert bool(c.report.converged.all()) and sum(kept) > 0  # rejected steps, state kept
