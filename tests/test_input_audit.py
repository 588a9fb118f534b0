"""Bad input and edge values found by an audit of the public API, one test per defect:
quaternions whose norm overflows or underflows, flags read by their truth value, the
tolerance of check_covariance, Sim(3) gradients at large scale log, sparse tensors, strings
and other types where numbers, dims, shapes or generators are expected, a non-finite regression
basis, the kernel switch shared between threads, and the attribution of host syncs to the
library's frames."""
from __future__ import annotations

import threading
import traceback
from pathlib import Path

import host_syncs
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

import torchsgal as ts
from torchsgal import regression
from torchsgal.estimation import study, tls
from torchsgal.functional import native, numerics, ops
from torchsgal.regression import models
from torchsgal.uncertainty import events, gaussian
from torchsgal.uncertainty.covariance import covariance_factor

F32, F64 = torch.float32, torch.float64


# ----------------------------------------------------------------- 1. quaternion norms
# Scales at which the sum of squares overflows (1e200, 1e30 in float32), underflows to a
# subnormal or to zero (1e-160, 1e-30 and 1e-40 in float32), and ordinary ones.
SCALES = {F64: [1e300, 1e200, 1e-160, 1e-300, 1.0], F32: [1e36, 1e30, 1e-30, 1e-40, 1.0]}


@pytest.mark.parametrize("order", ["wxyz", "xyzw"])
@pytest.mark.parametrize("dtype", [F32, F64])
def test_from_quaternion_scales_by_the_largest_component(order, dtype):
    gen = torch.Generator().manual_seed(1)
    base = torch.randn(6, 4, dtype=F64, generator=gen)
    base[0] = torch.tensor([0.0, 0.0, 0.0, 1.0])  # one non-zero component
    base[1] = torch.tensor([1.0, -1.0, 1.0, -1.0])  # ties for the largest
    xyzw = base.numpy() if order == "xyzw" else np.roll(base.numpy(), -1, axis=-1)
    ref = Rotation.from_quat(xyzw).as_matrix()
    for scale in SCALES[dtype]:
        q = (base * scale).to(dtype)
        assert torch.isfinite(q).all() and (q.abs().amax(-1) > 0).all()
        R = ts.SO3.from_quaternion(q, order=order).as_matrix()
        # float32: the subnormal scale 1e-40 keeps ~17 bits of each component
        tol = 1e-15 if dtype == F64 else (2e-5 if scale < 1e-38 else 1e-6)
        np.testing.assert_allclose(R.double().numpy(), ref, rtol=0, atol=4 * tol,
                                   err_msg=f"scale {scale}")
    # gradients: finite and exact at moderate norms (gradcheck), finite at extreme ones
    for scale in (0.3, 7.0):
        q = (base * scale).requires_grad_()
        assert torch.autograd.gradcheck(lambda q: ts.SO3.from_quaternion(q, order=order).as_matrix(),
                                        (q,))
    for scale in SCALES[dtype][:3]:  # not 1e-40 (float32): the derivative, ~1/|q|, overflows
        q = (base * scale).to(dtype).requires_grad_()
        ts.SO3.from_quaternion(q, order=order).as_matrix().sum().backward()
        assert torch.isfinite(q.grad).all(), f"scale {scale}"
    # only an exactly zero quaternion, or a non-finite one, is refused
    for bad, what in ((0.0, "zero"), (float("inf"), "finite"), (float("nan"), "finite")):
        q = base.clone().to(dtype)
        q[2] = 0.0
        q[2, 1] = bad
        with pytest.raises(ValueError, match=f"q .*{what}"):
            ts.SO3.from_quaternion(q, order=order)


# ------------------------------------------------------------------ 2. boolean flags
def _gaussian_sgal3():
    return gaussian.ConcentratedGaussian(ts.SGal3.identity(dtype=F64), 0.01 * torch.eye(10, dtype=F64))


def _tls_problem():
    gen = torch.Generator().manual_seed(0)
    Fa = ts.SGal3(ts.functional.sgal3.random((1, 3), F64, None, gen))
    Fb = ts.SGal3(ts.functional.sgal3.random((1, 3), F64, None, gen))
    S = study.paper_covariance()
    return tls.TLSProblem(Fa, Fb, S, S)


def _flow(fn, flag):
    x = torch.zeros(ts.SE3.dof, dtype=F64) if fn is regression.geodesic_flow else torch.zeros(1, ts.SE3.dof, dtype=F64)
    return fn(ts.SE3, x, torch.ones(2, dtype=F64), torch.ones(ts.SE3.dof, dtype=F64), 2, **{flag: "no"})


_EVENT = torch.tensor([0.1, 0.2, 0.3, 0.0], dtype=F64)
_EVENT_COV = 0.01 * torch.eye(4, dtype=F64)
_SMALL_STUDY = dict(trials=1, samples=2, variants=("iterated",), max_iterations=1)

# (flag, a call passing "no" for it and valid values elsewhere)
FLAGS = {
    "fuse_event-time_row": ("time_row", lambda: events.fuse_event(_gaussian_sgal3(), _EVENT, _EVENT_COV,
                                                                  time_row="no")),
    "fuse_event-validate": ("validate", lambda: events.fuse_event(_gaussian_sgal3(), _EVENT, _EVENT_COV,
                                                                  validate="no")),
    "check_covariance-definite": ("definite", lambda: gaussian.check_covariance(
        torch.eye(3, dtype=F64), 3, definite="no")),
    "solve_sgal3_lbfgs-batched": ("batched", lambda: tls.solve_sgal3_lbfgs(
        _tls_problem(), batched="no", reweightings=1, max_iterations=1)),
    "study.run-progress": ("progress", lambda: study.run(study.StudyConfig(**_SMALL_STUDY), progress="no")),
    "study.write_outputs-plot": ("plot", lambda: study.write_outputs({}, "unused", plot="no")),
    "geodesic_flow-sensitivity": ("sensitivity", lambda: _flow(regression.geodesic_flow, "sensitivity")),
    "polynomial_flow-sensitivity": ("sensitivity", lambda: _flow(regression.polynomial_flow, "sensitivity")),
    "PolynomialModel-fix_origin": ("fix_origin", lambda: models.PolynomialModel(
        ts.SE3, None, None, 1, None, fix_origin="no")),
    "RiemannianPolynomialModel-fix_origin": ("fix_origin", lambda: models.RiemannianPolynomialModel(
        ts.SE3, None, None, None, None, fix_origin="no")),
    "variables.unwrapped-single": ("single", lambda: ts.estimation.variables.unwrapped(print, "no")),
    "sim3_coefficients-derivatives": ("derivatives", lambda: numerics.sim3_coefficients(
        torch.ones(2, dtype=F64), torch.ones(2, dtype=F64), derivatives="no")),
    "sim3_coefficients-normalise": ("normalise", lambda: numerics.sim3_coefficients(
        torch.ones(2, dtype=F64), torch.ones(2, dtype=F64), normalise="no")),
    "ConcentratedGaussian-validate": ("validate", lambda: gaussian.ConcentratedGaussian(
        ts.SE3.identity(dtype=F64), torch.eye(6, dtype=F64), validate="no")),
    "ConcentratedGaussian-allow_singular": ("allow_singular", lambda: gaussian.ConcentratedGaussian(
        ts.SE3.identity(dtype=F64), torch.eye(6, dtype=F64), allow_singular="no")),
    "ConcentratedGaussian.compose-second_order": ("second_order", lambda: _gaussian_sgal3().compose(
        _gaussian_sgal3(), second_order="no")),
    "ConcentratedGaussian.act-validate": ("validate", lambda: _gaussian_sgal3().act(
        _EVENT, _EVENT_COV, validate="no")),
}


@pytest.mark.parametrize("case", list(FLAGS))
def test_boolean_flags_refuse_non_booleans(case):
    flag, call = FLAGS[case]
    with pytest.raises(TypeError, match=f"^{flag} must be True or False, got 'no'"):
        call()


# -------------------------------------------------------- 3. check_covariance's tol
def test_check_covariance_validates_its_tolerance():
    asymmetric = torch.tensor([[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], dtype=F64)
    eye = torch.eye(3, dtype=F64)
    for tol in (float("nan"), float("inf"), -1.0, -1e-300):
        for S in (asymmetric, eye):
            with pytest.raises(ValueError, match=r"^tol must be a finite number >= 0, got"):
                gaussian.check_covariance(S, 3, tol=tol)
    for tol in ("x", True, torch.tensor(1e-3), [1e-3]):
        with pytest.raises(TypeError, match=r"^tol must be a finite number >= 0, got"):
            gaussian.check_covariance(eye, 3, tol=tol)
    gaussian.check_covariance(eye, 3, tol=0)  # an int and zero are valid
    with pytest.raises(ValueError, match="not symmetric"):  # a valid tol still finds the asymmetry
        gaussian.check_covariance(asymmetric, 3, tol=1e-3)


# --------------------------------------------------------- 4. Sim(3) scale gradients
LAMBDAS = [float(v) for v in range(-40, 41, 2)] + [5.0, 7.0, 9.0, 11.0, 15.0, 21.0, 29.0, 30.5]


@pytest.mark.parametrize("fn", ["jl", "jr", "exp", "jl_inv"])
def test_sim3_gradients_at_large_scale_log_are_finite_and_correct(fn):
    weights = torch.linspace(0.5, 1.5, 49, dtype=F64).reshape(7, 7)  # a generic cotangent

    def f(x):
        out = getattr(ts.Sim3, fn)(x)
        M = out.as_matrix() if fn == "exp" else out
        return M * weights[: M.shape[-2], : M.shape[-1]].to(x.dtype)

    lam = torch.tensor(LAMBDAS, dtype=F64)
    x64 = torch.zeros(len(LAMBDAS), 7, dtype=F64)
    x64[:, 3:6] = torch.tensor([0.1, 0.5, -0.2], dtype=F64)  # a small and a large angle band
    x64[1::2, 3:6] *= 4.0
    x64[:, 6] = lam
    g64 = torch.autograd.grad(f(x64.requires_grad_()).sum(), x64)[0]
    x32 = x64.detach().float().requires_grad_()
    y32 = f(x32)
    g32 = torch.autograd.grad(y32.sum(), x32)[0]
    assert torch.isfinite(y32).all() and torch.isfinite(g64).all()
    bad = ~torch.isfinite(g32).all(-1)
    assert not bad.any(), f"float32 gradients not finite at lambda {lam[bad].tolist()}"
    # float32 against float64, relative to the largest entry of each row's gradient (worst
    # measured: 3.6e-7 for jl, jr and exp; 1.5e-5 for jl_inv, the inverse losing more)
    scale = g64.abs().amax(-1, keepdim=True)
    err = ((g32.double() - g64).abs() / scale).amax(-1)
    tol = 5e-5 if fn == "jl_inv" else 2e-6
    assert (err < tol).all(), f"worst {err.max():.2e} at lambda {lam[err.argmax()]:.1f}"
    # float64: exact derivatives (finite differences) across the range
    for k in range(0, len(LAMBDAS), 5):
        xk = x64.detach()[k:k + 1].clone().requires_grad_()
        assert torch.autograd.gradcheck(f, (xk,)), f"lambda {LAMBDAS[k]}"


# ------------------------------------------ 5. sparse tensors, strings for numbers
def _sparse(t):
    return t.to_sparse()


def _fit_samples():
    gen = torch.Generator().manual_seed(0)
    return ts.SE3.random(6, dtype=F64, generator=gen), torch.linspace(0.0, 1.0, 6, dtype=F64)


BAD_INPUTS = {
    "sparse-vector": ("xi", lambda: ts.SO3.exp(_sparse(torch.zeros(2, 3, dtype=F64)))),
    "sparse-matrix": ("M", lambda: ts.functional.so3.log(_sparse(torch.eye(3, dtype=F64)))),
    "sparse-quaternion": ("q", lambda: ts.SO3.from_quaternion(_sparse(torch.eye(4, dtype=F64)), order="wxyz")),
    "sparse-components": ("rotation", lambda: ts.SE3.from_components(
        _sparse(torch.eye(3, dtype=F64)), torch.zeros(3, dtype=F64))),
    "sparse-covariance": ("covariance", lambda: gaussian.check_covariance(_sparse(torch.eye(3, dtype=F64)), 3)),
    "sparse-covariance-factor": ("S", lambda: covariance_factor(_sparse(torch.eye(3, dtype=F64)), "S")),
    "sparse-times": ("times", lambda: regression.fit_polynomial(_fit_samples()[0], _sparse(_fit_samples()[1]))),
    "sparse-weights": ("weights", lambda: regression.fit_polynomial(
        *_fit_samples(), weights=_sparse(torch.ones(6, dtype=F64)))),
    "string-dtau0": ("dtau0", lambda: tls.solve_sgal3(_tls_problem(), dtau0="x")),
    "string-dtau0-lbfgs": ("dtau0", lambda: tls.solve_sgal3_lbfgs(_tls_problem(), dtau0="x")),
    "string-indices": ("indices", lambda: tls.TLSProblem(_tls_problem().F_ga, _tls_problem().F_gb,
                                                         study.paper_covariance(), study.paper_covariance(),
                                                         ["0", "1", "2"])),
    "string-weights": ("weights", lambda: regression.fit_polynomial(*_fit_samples(), weights="abc")),
    "string-weights-riemannian": ("weights", lambda: regression.fit_riemannian_polynomial(
        *_fit_samples(), weights="abc")),
    "string-weights-frechet": ("weights", lambda: regression.frechet_mean(_fit_samples()[0], weights="abc")),
    "sparse-gaussian": ("covariance", lambda: gaussian.ConcentratedGaussian(
        ts.SE3.identity(dtype=F64), _sparse(torch.eye(6, dtype=F64)))),
    "int-generator": ("generator", lambda: gaussian.ConcentratedGaussian(
        ts.SE3.identity(dtype=F64), torch.eye(6, dtype=F64)).sample((2,), generator=1)),
    "bool-dim-stack": ("dim", lambda: ts.SE3.stack([ts.SE3.identity(2), ts.SE3.identity(2)], dim=True)),
    "string-dim-cat": ("dim", lambda: ts.SE3.cat([ts.SE3.identity(2), ts.SE3.identity(2)], dim="0")),
    "bool-dim-unsqueeze": ("dim", lambda: ts.SE3.identity(2).unsqueeze(True)),
    "float-dim-squeeze": ("dim", lambda: ts.SE3.identity((2, 1)).squeeze(1.0)),
    "none-reshape": ("shape", lambda: ts.SE3.identity(2).reshape(None)),
    "bool-expand": ("shape", lambda: ts.SE3.identity(2).expand(True, 2)),
}


@pytest.mark.parametrize("case", list(BAD_INPUTS))
def test_sparse_tensors_and_strings_for_numbers_name_the_argument(case):
    name, call = BAD_INPUTS[case]
    with pytest.raises(TypeError, match=f"^{name} must be "):
        call()


# -------------------------------------------------- 6. the thread-local kernel switch
def test_native_disabled_is_local_to_its_thread(monkeypatch):
    monkeypatch.setitem(native._state, "on", True)  # as where the kernels are compiled
    inside, outside = threading.Event(), threading.Event()
    seen = {}
    x = torch.zeros(4, 10, dtype=F64)  # a call the kernels may take (plain CPU tensor, no autograd)

    def state():  # the switch, and the decision of the operators' dispatch for x
        return native.enabled(), ops._kernel("sgal3_exp", (x,), [x.shape[:-1]]) is not None

    def switched():
        with native.disabled():
            seen["inside"] = state()
            inside.set()
            outside.wait(10)  # the other thread looks while this one is inside the block
            with native.disabled():
                pass
            seen["after nested"] = state()
        seen["after"] = state()

    def other():
        inside.wait(10)
        seen["other thread"] = state()
        outside.set()

    threads = [threading.Thread(target=switched), threading.Thread(target=other)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(20)
    on, off = (True, True), (False, False)
    assert seen == {"inside": off, "other thread": on, "after nested": off, "after": on}
    # the main thread: its own state, unchanged by the others; a thread started inside the
    # block does not inherit it
    assert state() == on
    with native.disabled():
        child = {}
        t = threading.Thread(target=lambda: child.setdefault("state", state()))
        t.start()
        t.join(10)
        assert state() == off and child == {"state": on}
    assert state() == on


# ------------------------------------------------ 7. host syncs attributed to the library
def test_host_sync_caller_ignores_a_virtualenv_inside_a_checkout_named_torchsgal(monkeypatch):
    package = Path(ts.__file__).resolve().parent
    library = str(package / "functional" / "so3.py")
    # a checkout directory named torchsgal with its virtualenv inside (README Quickstart)
    venv_torch = "/home/user/torchsgal/.venv/lib/python3.11/site-packages/torch/_tensor.py"
    test_file = str(package.parent / "tests" / "test_estimation.py")
    stack = traceback.StackSummary.from_list([(test_file, 5, "test", ""), (library, 42, "log", ""),
                                              (venv_torch, 7, "__bool__", "")])
    monkeypatch.setattr(host_syncs.traceback, "extract_stack", lambda *a, **k: stack)
    assert host_syncs._caller() == f"{library}:42"
    stack = traceback.StackSummary.from_list([(test_file, 5, "test", ""), (venv_torch, 7, "__bool__", "")])
    assert host_syncs._caller() == "?"


@pytest.mark.parametrize("fn", ["jr", "jr_inv"])
def test_sim3_right_jacobians_check_xi_before_negating_it(fn):
    """A bool tensor: named, as for every group (torch's error on negating a bool before)."""
    with pytest.raises(TypeError, match="^xi must have a floating dtype"):
        getattr(ts.functional.sim3, fn)(torch.zeros(7, dtype=torch.bool))


def test_a_non_finite_regression_basis_is_refused():
    """fit_polynomial's basis is checked finite, as its weights and times (the SVD failed in
    torch, naming no argument)."""
    with pytest.raises(ValueError, match="^basis must be finite"):
        regression.fit_polynomial(*_fit_samples(), 1, basis=torch.full((6, 1), float("nan"), dtype=F64))


def test_unvalidated_non_positive_definite_covariance_names_the_covariance():
    """validate=False skips the checks at construction; a covariance that is not positive
    definite then fails with our message where it is factorised (sample, mahalanobis, log_prob),
    not with torch's internal linear-algebra error."""
    bad = -torch.eye(6, dtype=F64)
    d = gaussian.ConcentratedGaussian(ts.SE3.identity(dtype=F64), bad, validate=False)
    for use in (lambda: d.sample(3), lambda: d.mahalanobis(ts.SE3.identity(dtype=F64)),
                lambda: d.log_prob(ts.SE3.identity(dtype=F64))):
        with pytest.raises(ValueError, match=r"^covariance is not positive definite .*validate=False"):
            use()
