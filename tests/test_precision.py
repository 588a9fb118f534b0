"""Float64 accuracy across the whole range of rotation angles against mpmath (50 digits).

The SGal(3) left Jacobian must hold 1e-12 relative error, block by block, from 1e-12 rad to
pi - 1e-6: the band 1e-5 .. 1e-3 is where cancellation in the printed closed forms costs
libraries up to 3 digits.  The error measure is per block of the tangent partition
(max |J - J_ref| / max |J_ref| over each non-zero block), stricter than a whole-matrix norm.
"""
from __future__ import annotations

import math

import mpmath
import numpy as np
import pytest
import reference as ref
import torch
from conftest import sample_tangent

import torchsgal as ts
from torchsgal.functional import numerics

ANGLES = [1e-12, 1e-8, 1e-6, 1e-5, 1e-4, 1e-3, 1e-2, 0.1, 0.5, 1.0, 2.0, 3.0, math.pi - 1e-6]
FUNCTIONS = ["jl", "jr", "jl_inv", "jr_inv", "exp"]


def _reference(G, fn, xi):
    name = G.__name__
    return {
        "jl": ref.jl_mp,
        "jr": ref.jr_mp,
        "jl_inv": ref.jl_inv_mp,
        "jr_inv": ref.jr_inv_mp,
        "exp": ref.exp_mp,
    }[fn](name, xi)


def _ours(G, fn, xi):
    t = torch.tensor(xi, dtype=torch.float64)
    return (G.exp(t).as_matrix() if fn == "exp" else getattr(G, fn)(t)).numpy()


@pytest.mark.parametrize("fn", FUNCTIONS)
@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=lambda g: g.__name__)
def test_relative_error_against_mpmath(G, fn):
    worst = 0.0
    for i, angle in enumerate(ANGLES):
        xi = sample_tangent(G, (), torch.float64, seed=100 + i, angles=[angle]).numpy()
        got, want = _ours(G, fn, xi), _reference(G, fn, xi)
        if fn == "exp":
            err = ref.rel_err(got, want)
        else:
            e = ref.blockwise_rel_err(got, want, G.__name__)
            err = e.rel
            assert e.zero_abs == 0.0, f"{fn} angle {angle:g}: non-zero entry in a zero block"
        worst = max(worst, err)
        assert err <= 1e-12, f"{G.__name__}.{fn} at angle {angle:g}: relative error {err:.3g}"
    print(f"{G.__name__}.{fn}: worst blockwise relative error {worst:.2e}")


@pytest.mark.parametrize("scale", [1e-3, 1.0, 30.0])
def test_sgal3_jl_with_large_and_small_translation(scale):
    """Relative accuracy must not depend on the size of rho, nu, iota."""
    for i, angle in enumerate([1e-7, 1e-4, 1e-3, 0.02, 2.5]):
        xi = sample_tangent(ts.SGal3, (), torch.float64, seed=200 + i, scale=scale, angles=[angle])
        e = ref.blockwise_rel_err(_ours(ts.SGal3, "jl", xi.numpy()), ref.jl_mp("SGal3", xi.numpy()), "SGal3")
        assert e.rel <= 1e-12, f"scale {scale}, angle {angle}: {e.rel:.3g}"


def test_paper_printed_D_has_the_known_typo():
    """CONVENTIONS.md: (3.8) prints (phi - sin phi)/phi^2 for the u^u^ coefficient of D; the
    series gives (phi - sin phi)/phi.  The reference tells the two apart, and ours is right."""
    phi = np.array([0.3, -0.2, 0.9])
    th = np.linalg.norm(phi)
    u = ref.skew(phi / th)
    printed = np.eye(3) + (1 - math.cos(th)) / th * u + (th - math.sin(th)) / th**2 * u @ u
    corrected = np.eye(3) + (1 - math.cos(th)) / th * u + (th - math.sin(th)) / th * u @ u
    want = ref.jl_mp("SO3", phi)
    assert ref.rel_err(corrected, want) < 1e-14
    assert ref.rel_err(printed, want) > 1e-6  # detectably wrong (4.6e-3 here)
    assert ref.rel_err(ts.SO3.jl(torch.tensor(phi)).numpy(), want) < 1e-14


@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=lambda g: g.__name__)
def test_log_relative_error_against_mpmath(G):
    """log of the correctly rounded exp (mpmath) returns xi to 1e-12 relative to |xi|, from
    1e-12 rad to pi - 1e-6 (the axis near pi comes from the symmetric part of C)."""
    worst = 0.0
    for i, angle in enumerate(ANGLES):
        xi = sample_tangent(G, (), torch.float64, seed=300 + i, angles=[angle]).numpy()
        M = ref.exp_mp(G.__name__, xi)
        got = G.from_matrix(torch.tensor(M)).log().numpy()
        err = ref.blockwise_rel_err(got, xi, G.__name__, kind="vector").rel
        worst = max(worst, err)
        assert err <= 1e-12, f"{G.__name__}.log at angle {angle:g}: relative error {err:.3g}"
    print(f"{G.__name__}.log: worst blockwise relative error {worst:.2e}")


# ------------------------------------------------------------------------------ Sim(3)
# Rotation angles x log-scales lambda (docs/guide/sim3_jacobian.md): the small-scale branch (lambda
# down to 0), both signs, |lambda| up to 5, and the joint small-angle & small-scale corner.
SIM3_LAMBDAS = [0.0, 1e-12, -1e-12, 1e-8, -1e-6, 1e-5, 1e-4, 1e-3, -1e-3, 0.5, -1.0, 2.0, -3.0, 5.0, -5.0]


def _sim3_xi(i, j, angle, lam, scale=1.0):
    xi = sample_tangent(ts.Sim3, (), torch.float64, seed=1000 + 31 * i + j, scale=scale, angles=[angle])
    xi[6] = lam
    return xi.numpy()


@pytest.mark.parametrize("fn", ["jl", "jl_inv"])
def test_sim3_jacobian_over_angles_and_scales(fn):
    """J_l and its inverse against the 50-digit series sum ad^n/(n+1)! (and its mpmath
    inverse), block by block, over the whole grid of angles and scales."""
    worst = (0.0, None, None)
    per_lambda = {}
    for i, angle in enumerate(ANGLES):
        for j, lam in enumerate(SIM3_LAMBDAS):
            xi = _sim3_xi(i, j, angle, lam)
            e = ref.blockwise_rel_err(_ours(ts.Sim3, fn, xi), _reference(ts.Sim3, fn, xi), "Sim3")
            assert e.zero_abs == 0.0, f"angle {angle:g}, lambda {lam:g}: non-zero entry in a zero block"
            assert e.rel <= 1e-12, f"Sim3.{fn} at angle {angle:g}, lambda {lam:g}: {e.rel:.3g}"
            worst = max(worst, (e.rel, angle, lam), key=lambda t: t[0])
            per_lambda[lam] = max(per_lambda.get(lam, 0.0), e.rel)
    print(f"\nSim3.{fn}: worst blockwise relative error {worst[0]:.2e} (angle {worst[1]:g}, lambda {worst[2]:g})")
    print("  worst over the angles, per lambda: "
          + ", ".join(f"{lam:g}: {err:.1e}" for lam, err in per_lambda.items()))


@pytest.mark.parametrize("fn", ["jr", "jr_inv"])
@pytest.mark.parametrize("scale", [1e-3, 30.0])
def test_sim3_jacobian_with_small_and_large_translation(fn, scale):
    """Relative accuracy does not depend on the size of rho (right Jacobians, a sub-grid)."""
    for i, angle in enumerate([1e-7, 1e-4, 1e-3, 0.9, 1.1, 2.5]):
        for j, lam in enumerate([1e-9, -1e-4, 0.7, -4.0]):
            xi = _sim3_xi(i, j, angle, lam, scale=scale)
            e = ref.blockwise_rel_err(_ours(ts.Sim3, fn, xi), _reference(ts.Sim3, fn, xi), "Sim3")
            assert e.rel <= 1e-12 and e.zero_abs == 0.0, f"angle {angle}, lambda {lam}: {e.rel:.3g}"


def test_sim3_exp_and_log_over_angles_and_scales():
    """exp against the 50-digit matrix series; log of that correctly rounded matrix back to
    xi.  The matrix stores exp(-lambda), which fixes lambda only to about eps/2 absolute, so
    lambda's error is taken relative to max(|lambda|, 1); rho and phi blockwise."""
    worst_exp = worst_log = 0.0
    for i, angle in enumerate(ANGLES):
        for j, lam in enumerate(SIM3_LAMBDAS):
            xi = _sim3_xi(i, j, angle, lam)
            M = ref.exp_mp("Sim3", xi)
            e_exp = ref.rel_err(_ours(ts.Sim3, "exp", xi), M)
            back = ts.Sim3.from_matrix(torch.tensor(M)).log().numpy()
            e_log = max(
                ref.blockwise_rel_err(back[:6], xi[:6], [3, 3], kind="vector").rel,
                abs(back[6] - xi[6]) / max(abs(xi[6]), 1.0),
            )
            assert e_exp <= 1e-12, f"exp at angle {angle:g}, lambda {lam:g}: {e_exp:.3g}"
            assert e_log <= 1e-12, f"log at angle {angle:g}, lambda {lam:g}: {e_log:.3g}"
            worst_exp, worst_log = max(worst_exp, e_exp), max(worst_log, e_log)
    print(f"Sim3.exp: worst relative error {worst_exp:.2e}; Sim3.log: {worst_log:.2e}")


def _moment_mp(x: float, j: int):
    """q_j(x) = sum_n x^n/(n+j+1)! summed in mpmath until the terms fall below 1e-45."""
    import mpmath

    x = mpmath.mpf(x)
    total, term, n = mpmath.mpf(0), 1 / mpmath.factorial(j + 1), 0
    while abs(term) > mpmath.mpf(10) ** -45 or n <= abs(x):
        total, n = total + term, n + 1
        term = term * x / (n + j + 1)
    return total


def test_sim3_scale_moments_against_mpmath():
    """q_j(x) (numerics.scale_moments, the orders Sim(3) uses) across both recursions and their
    switches at |x| = j + 1/2: every order to 1e-15 relative for |x| <= 6 (|lambda| <= 6), the
    leading orders to 1e-14 up to |x| = 40."""
    import mpmath

    from torchsgal.functional import numerics

    order = 2 * numerics.SIM3_SERIES_TERMS + 2
    xs = [0.0, 1e-12, -1e-6, 0.3, -0.49, 0.51, -1.2, 2.49, -2.51, 4.0, -5.0, 5.6, -5.6, 7.5, -9.0,
          -12.5, 20.0, -20.0, 40.0, -40.0]
    got = numerics.scale_moments(torch.tensor(xs, dtype=torch.float64), order)
    with mpmath.workdps(40):
        for i, x in enumerate(xs):
            for j in range(order + 1 if abs(x) <= 6 else 9):
                want = float(_moment_mp(x, j))
                err = abs(float(got[j][i]) - want) / abs(want)
                assert err <= (1e-15 if abs(x) <= 6 else 1e-14), f"q_{j}({x}): relative error {err:.3g}"


@pytest.mark.parametrize("lam", [1e-9, 0.5, -2.5, 5.0])
def test_sim3_gradients_across_scales(lam):
    """gradcheck of exp, log(exp) and J_l at a scale-branch switch (|lambda| = j + 1/2), near 0
    and at the ends of the range, at a small and a large angle."""
    f = ts.functional.sim3
    for angle in (1e-5, 2.0):
        xi = sample_tangent(ts.Sim3, (1,), torch.float64, seed=77, angles=[angle])
        xi[:, 6] = lam
        xi.requires_grad_(True)
        for fn in (f.exp, lambda x: f.log(f.exp(x)), f.jl):
            assert torch.autograd.gradcheck(fn, (xi,), eps=1e-6, atol=1e-6, rtol=1e-5)


def test_sim3_reference_oracle():
    """The Sim3 oracle of reference.py against hand-written layouts and Barfoot's (80):
    hat/vee, ad = [[phi^ + lambda I, rho^, -rho], [0, phi^, 0], [0, 0, 0]], scipy expm against
    the mpmath series, Ad(exp xi) = expm(ad xi), and the float64 against the mpmath J_l."""
    import scipy.linalg

    x = np.arange(1.0, 8.0)
    X = np.zeros((4, 4))
    X[:3, :3] = ref.skew(x[3:6])
    X[:3, 3] = x[:3]
    X[3, 3] = -x[6]
    np.testing.assert_array_equal(ref.hat("Sim3", x), X)
    np.testing.assert_array_equal(ref.vee("Sim3", ref.hat("Sim3", x)), x)
    for angle in (0.0, 1e-3, 1.0, 3.0):
        xi = ref.random_tangent("Sim3", 6, angle=angle)
        rho, phi, lam = xi[:3], xi[3:6], xi[6]
        want = np.zeros((7, 7))
        want[:3, :3] = ref.skew(phi) + lam * np.eye(3)
        want[:3, 3:6] = ref.skew(rho)
        want[:3, 6] = -rho
        want[3:6, 3:6] = ref.skew(phi)
        np.testing.assert_allclose(ref.ad("Sim3", xi), want, rtol=0, atol=1e-15)
        M = ref.expm_hat("Sim3", xi)
        assert ref.rel_err(M, ref.exp_mp("Sim3", xi, dps=30)) < 1e-13
        np.testing.assert_allclose(M[3], [0, 0, 0, np.exp(-lam)], rtol=1e-14, atol=1e-15)
        np.testing.assert_allclose(
            ref.Ad_from_matrix("Sim3", M), scipy.linalg.expm(ref.ad("Sim3", xi)), rtol=0, atol=1e-12
        )
        assert ref.rel_err(ref.jl_series("Sim3", xi), ref.jl_mp("Sim3", xi)) < 1e-13


@pytest.mark.parametrize("lam", [-50.0, 50.0])
def test_sim3_float32_at_large_scales(lam):
    """float32 J_l^-1 and log at |lambda| = 50 (e^(2|lambda|) overflows float32): against the
    float64 mpmath references, to float32 accuracy (the inverse of M is normalised by m0)."""
    for i, angle in enumerate([0.0, 1e-3, 0.5, 2.0, 3.1]):
        xi = _sim3_xi(i, 0, angle, lam)
        t = torch.tensor(xi, dtype=torch.float32)
        e = ref.rel_err(ts.Sim3.jl_inv(t).double().numpy(), ref.jl_inv_mp("Sim3", xi))
        assert e <= 1e-5, f"jl_inv float32 at angle {angle}, lambda {lam}: {e:.3g}"
        back = ts.Sim3.exp(t).log().double().numpy()
        assert np.isfinite(back).all()
        # 1e-5 relative to each block's own magnitude (|lambda| = 50 must not widen the rho and
        # phi tolerances): measured worst 2.5e-7 (rho), 4.8e-8 (phi), 0 (lambda)
        for name, b in (("rho", slice(0, 3)), ("phi", slice(3, 6)), ("lambda", slice(6, 7))):
            err = np.abs(back[b] - xi[b]).max()
            assert err <= 1e-5 * max(1.0, np.abs(xi[b]).max()), f"log float32 {name} at angle {angle}: {err:.3g}"


def test_jinv_coefficient_against_mpmath():
    """d(theta) = (1 - (theta/2) cot(theta/2)) / theta^2 on both branches: the Bernoulli series
    to 2e-15 relative below JINV_THRESHOLD, the closed form to 5e-14 above (its cancellation
    1/theta^2 - cot/(2 theta) costs ~50x at theta = 0.5)."""
    th = np.concatenate([np.linspace(1e-4, numerics.JINV_THRESHOLD, 400, endpoint=False),
                         np.linspace(numerics.JINV_THRESHOLD, 3.1, 400)])
    got = numerics.jinv_coefficient(torch.tensor(th * th, dtype=torch.float64)).numpy()
    with mpmath.workdps(40):
        want = np.array([float((1 - (mpmath.mpf(t) / 2) * mpmath.cot(mpmath.mpf(t) / 2)) / mpmath.mpf(t) ** 2)
                         for t in th])
    rel = np.abs(got - want) / np.abs(want)
    small = th < numerics.JINV_THRESHOLD
    assert rel[small].max() <= 2e-15, rel[small].max()
    assert rel[~small].max() <= 5e-14, rel[~small].max()


# Just below the series/closed-form switches (SERIES_THRESHOLD = SIM3_SERIES_THRESHOLD = 1): the
# end of each Taylor branch, where its truncation error is largest.  A tolerance of 1e-13 (the
# code holds ~1e-15 there) catches a series cut a few terms short, which 1e-12 did not.
NEAR_SWITCH = [0.9, 0.99, 0.999]


@pytest.mark.parametrize("fn", ["jl", "jl_inv", "exp"])
@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=lambda g: g.__name__)
def test_series_branch_end_against_mpmath(G, fn):
    """exp, J_l and J_l^-1 at the end of the Taylor branches, to 1e-13 relative."""
    for i, angle in enumerate(NEAR_SWITCH):
        xi = sample_tangent(G, (), torch.float64, seed=400 + i, angles=[angle]).numpy()
        t = torch.tensor(xi)
        got = (G.exp(t).as_matrix() if fn == "exp" else getattr(G, fn)(t)).numpy()
        want = getattr(ref, fn + "_mp")(G.__name__, xi)
        err = ref.rel_err(got, want) if fn == "exp" else ref.blockwise_rel_err(got, want, G.__name__).rel
        assert err <= 1e-13, f"{G.__name__}.{fn} at {angle}: {err:.3g}"


@pytest.mark.parametrize("fn", ["jl", "jl_inv"])
def test_sim3_series_branch_end(fn):
    """Sim(3): the (theta^2, moments) series at its upper end, over the scales."""
    for i, angle in enumerate(NEAR_SWITCH):
        for j, lam in enumerate([0.0, 1e-6, 2.0, -3.0, 5.0, -5.0]):
            xi = sample_tangent(ts.Sim3, (), torch.float64, seed=600 + 7 * i + j, angles=[angle])
            xi[6] = lam
            x = xi.numpy()
            e = ref.blockwise_rel_err(getattr(ts.Sim3, fn)(xi).numpy(), getattr(ref, fn + "_mp")("Sim3", x), "Sim3").rel
            assert e <= 1e-13, f"Sim3.{fn} at angle {angle}, lambda {lam}: {e:.3g}"


@pytest.mark.parametrize("G", [ts.SO3, ts.SE3, ts.SE23, ts.SGal3, ts.Sim3], ids=lambda g: g.__name__)
@pytest.mark.parametrize("axis", [0, 1, 2])
@pytest.mark.parametrize("angle", [2.0, math.pi - 1e-6, math.pi])
def test_log_about_coordinate_axes(G, axis, angle):
    """Rotations about e_x, e_y, e_z (two of the symmetric part's diagonal entries tie at 0):
    log is finite, has angle `angle`, and exp(log) reproduces the matrix."""
    xi = sample_tangent(G, (), torch.float64, seed=11, angles=[1.0])
    phi = torch.zeros(3, dtype=torch.float64)
    phi[axis] = angle
    xi[G._f.PHI] = phi
    M = G.exp(xi).as_matrix()
    back = G.from_matrix(M).log()
    assert torch.isfinite(back).all()
    assert abs(back[G._f.PHI].norm().item() - angle) <= 1e-12
    np.testing.assert_allclose(G.exp(back).as_matrix().numpy(), M.numpy(), rtol=0, atol=1e-12)


def _sim3_exp_quad(xi, dps=30):
    """Sim(3) exp from its integral definition M(phi, lambda) = int_0^1 e^(-(1-a) lambda)
    C(a phi) da, the three scalar integrals by mpmath quadrature (no series, no closed form
    of the code) -> float64 (4, 4)."""
    with mpmath.workdps(dps):
        x = [mpmath.mpf(float(v)) for v in xi]
        rho, lam = mpmath.matrix(x[0:3]), x[6]
        t = mpmath.sqrt(x[3] ** 2 + x[4] ** 2 + x[5] ** 2)
        P = mpmath.matrix([[0, -x[5], x[4]], [x[5], 0, -x[3]], [-x[4], x[3], 0]])
        w = lambda a: mpmath.exp(-(1 - a) * lam)  # noqa: E731
        m0 = mpmath.quad(w, [0, 1])
        s = mpmath.quad(lambda a: w(a) * mpmath.sin(a * t), [0, 1])
        c = mpmath.quad(lambda a: w(a) * mpmath.cos(a * t), [0, 1])
        I3 = mpmath.eye(3)
        C = I3 + (mpmath.sin(t) / t) * P + ((1 - mpmath.cos(t)) / t**2) * P * P
        r = (m0 * I3 + (s / t) * P + ((m0 - c) / t**2) * P * P) * rho
        out = np.zeros((4, 4))
        for i in range(3):
            out[i, :3] = [float(C[i, j]) for j in range(3)]
            out[i, 3] = float(r[i])
        out[3, 3] = float(mpmath.exp(-lam))
        return out


def _sim3_translation_mp(x):
    """The translation of Sim(3) exp, the same integral definition as _sim3_exp_quad but with
    its three scalar integrals in closed form, evaluated in mpmath at the working precision:
    m0 = (1 - e^-lambda) / lambda and c + i s = int_0^1 e^(-(1-a) lambda + i a t) da
    = (e^(it) - e^-lambda) / (lambda + i t).  x: 7 mpf -> mpmath (3, 1) matrix."""
    rho, lam = mpmath.matrix(x[0:3]), x[6]
    t = mpmath.sqrt(x[3] ** 2 + x[4] ** 2 + x[5] ** 2)
    P = mpmath.matrix([[0, -x[5], x[4]], [x[5], 0, -x[3]], [-x[4], x[3], 0]])
    m0 = (1 - mpmath.exp(-lam)) / lam
    z = (mpmath.expj(t) - mpmath.exp(-lam)) / mpmath.mpc(lam, t)
    return (m0 * mpmath.eye(3) + (z.imag / t) * P + ((m0 - z.real) / t**2) * P * P) * rho


def _sim3_translation_sum_grad_fd(xi, dps=50, h=1e-15):
    """d/dxi of the sum of the translation, central differences of _sim3_translation_mp at
    50 digits (truncation ~h^2, rounding ~1e-50/h: both far below float64) -> (translation
    as float64 (3,), gradient as float64 (7,))."""
    with mpmath.workdps(dps):
        x = [mpmath.mpf(float(v)) for v in xi]
        step = mpmath.mpf(h)
        grad = np.zeros(7)
        for k in range(7):
            up, dn = list(x), list(x)
            up[k] += step
            dn[k] -= step
            grad[k] = float(sum(_sim3_translation_mp(up) - _sim3_translation_mp(dn)) / (2 * step))
        return np.array([float(v) for v in _sim3_translation_mp(x)]), grad


@pytest.mark.parametrize("dtype, lam", [(torch.float32, -85.0), (torch.float64, -700.0), (torch.float64, -705.0)])
def test_sim3_exp_near_the_overflow_limit(dtype, lam):
    """At lambda near the dtype's exp limit the matrix (1/s = e^-lambda ~ 1e36 in float32,
    1e306 in float64) is finite and so must the translation be (it was NaN: an intermediate
    e^-lambda * lambda overflowed in the unused large-angle branch); exp against the quadrature
    of the integral definition, column by column, and the gradient of its translation against
    central differences of the same integrals (in closed form, at 50 digits), block by block."""
    eps = torch.finfo(dtype).eps
    for angle in [1e-3, 0.3, 2.0, 3.1]:  # both branches of sim3_coefficients
        xi = torch.tensor([0.1, 0.2, 0.3, 0.1, 0.2, 0.3, lam], dtype=torch.float64)
        xi[3:6] *= angle / xi[3:6].norm()
        want = _sim3_exp_quad(xi.numpy())
        r, want_grad = _sim3_translation_sum_grad_fd(xi.numpy())
        np.testing.assert_allclose(r, want[:3, 3], rtol=1e-14)  # the same integrals as the quadrature
        x = xi.to(dtype).requires_grad_()
        M = ts.functional.sim3.exp(x)
        err = np.abs(M.detach().double().numpy() - want).max(axis=0) / np.abs(want).max(axis=0)
        assert err.max() <= 50 * eps, f"angle {angle}, lambda {lam}: {err}"
        M[:3, 3].sum().backward()
        assert torch.isfinite(x.grad).all(), f"angle {angle}, lambda {lam}: {x.grad}"
        # Blockwise against the differences.  The rho and lambda blocks hold 2.6 eps of their
        # largest entry (measured).  The phi block is only ~0.25/|lambda| of the rho block here
        # (measured 2.4e-3 at lambda = -85, 4e-4 at -700), and its error stays below 1 eps of the
        # gradient's largest entry (measured 0.5 eps), which is up to 2.6 |lambda| eps of the phi
        # block's own largest entry (measured 164 eps at -85, 1821 eps at -705).
        g = x.grad.double().numpy()
        for name, b, allowed in (("rho", slice(0, 3), 50 * eps), ("phi", slice(3, 6), 50 * abs(lam) * eps),
                                 ("lambda", slice(6, 7), 50 * eps)):
            e = np.abs(g[b] - want_grad[b]).max() / np.abs(want_grad[b]).max()
            assert e <= allowed, f"d/d{name} at angle {angle}, lambda {lam}: {e:.3g} > {allowed:.3g}"


# --------------------------------------------------- Sim(3) at theta = 2 pi k, and extreme lambda
# At theta = 2 pi k with lambda = 0, M(phi, lambda) is singular (like Gamma_1): at the float value of
# 2 pi k the exact J_l^-1 is huge but finite.  M^-1 needs the real part of M's eigenvalue on the
# rotation plane; 1 - c theta^2 from the rounded c = m2/m0 cancelled to exactly 0 there (n2 = 0 * inf,
# NaN), and cos - e^-lambda cost eps/|lambda| nearby (2.4e-4 at lambda = 1e-12).  About a
# coordinate axis theta is exact, so the mpmath reference of the same float input is exact as well.


@pytest.mark.parametrize("k", [1, 2])
def test_sim3_inverse_jacobians_at_multiples_of_two_pi(k):
    """J_l^-1 and J_r^-1 at the float value of 2 pi k, lambda 0 and near 0, against mpmath (1e-13
    blockwise; ~2e-15 measured); J_l^-T g (the backward part) and the gradient of J_l^-1 finite."""
    f = ts.functional.sim3
    weights = torch.arange(49.0, dtype=torch.float64).reshape(7, 7)
    for axis in (0, 2):
        for lam in (0.0, 1e-12, -1e-4):
            xi = torch.tensor([0.7, -1.1, 0.4, 0.0, 0.0, 0.0, lam], dtype=torch.float64)
            xi[3 + axis] = 2 * math.pi * k
            for fn in ("jl_inv", "jr_inv"):
                want = getattr(ref, fn + "_mp")("Sim3", xi.numpy())
                e = ref.blockwise_rel_err(getattr(ts.Sim3, fn)(xi).numpy(), want, "Sim3").rel
                assert e <= 1e-13, f"Sim3.{fn} at 2 pi {k} about axis {axis}, lambda {lam}: {e:.3g}"
            assert torch.isfinite(f.jl_inv_tmv(xi, torch.arange(7.0, dtype=torch.float64))).all()
            x = xi.clone().requires_grad_()
            (f.jl_inv(x) * weights).sum().backward()
            assert torch.isfinite(x.grad).all(), f"gradient at 2 pi {k}, lambda {lam}: {x.grad}"


def test_sim3_inverse_jacobians_float32_near_two_pi():
    """float32 within 3 ulps of 2 pi, lambda 0 and 1e-12 (e^-1e-12 rounds to 1, so both are the
    singular case): J_l^-1 and J_r^-1 to 1e-5 blockwise against mpmath of the same input (they were
    NaN, or off by up to 0.2)."""
    two_pi = torch.tensor(2 * math.pi, dtype=torch.float32)
    for ulps in (-3, 0, 2):
        theta = two_pi
        for _ in range(abs(ulps)):
            theta = torch.nextafter(theta, torch.tensor(10.0 if ulps > 0 else 0.0))
        for lam in (0.0, 1e-12):
            xi = torch.tensor([0.7, -1.1, 0.4, 0.0, 0.0, 0.0, lam], dtype=torch.float32)
            xi[4] = theta
            for fn in ("jl_inv", "jr_inv"):
                want = getattr(ref, fn + "_mp")("Sim3", xi.double().numpy())
                e = ref.blockwise_rel_err(getattr(ts.Sim3, fn)(xi).double().numpy(), want, "Sim3").rel
                assert e <= 1e-5, f"float32 Sim3.{fn} at 2 pi {ulps:+d} ulps, lambda {lam}: {e:.3g}"


def _sim3_jl_expm_mp(xi, dps=30):
    """(J_l, J_l^-1) float64 (7, 7) with J_l = sum_n ad^n/(n+1)! the top-right block of
    expm([[ad, I], [0, 0]]) in mpmath: scaling and squaring, so |lambda| in the thousands costs no
    more than lambda = 1, and its e^(+-lambda) neither overflow nor underflow."""
    A = ref.ad("Sim3", np.asarray(xi, dtype=np.float64))
    with mpmath.workdps(dps):
        Z = mpmath.zeros(14, 14)
        for i in range(7):
            for j in range(7):
                Z[i, j] = mpmath.mpf(float(A[i, j]))
            Z[i, 7 + i] = 1
        E = mpmath.expm(Z)
        J = mpmath.matrix([[E[i, 7 + j] for j in range(7)] for i in range(7)])
        Ji = J**-1
        return (np.array([[float(J[i, j]) for j in range(7)] for i in range(7)]),
                np.array([[float(Ji[i, j]) for j in range(7)] for i in range(7)]))


@pytest.mark.parametrize("dtype, lam", [(torch.float64, -40.0), (torch.float64, -750.0),
                                        (torch.float64, -1e4), (torch.float32, -100.0)])
def test_sim3_jacobians_at_extreme_scales(dtype, lam):
    """For lambda -> -inf, s = e^lambda underflows and M ~ e^-lambda/|lambda| overflows (float64
    beyond 709, float32 88) while s M ~ 1/|lambda| is finite: J_l and J_l^-1 at lambda, J_r and
    J_r^-1 at -lambda (the same matrices) against the mpmath expm of ad; they were NaN.  The
    gradients of J_l^-1 at +-lambda (1/s overflowed in its backward at +lambda) and of J_r at
    -lambda are finite, and gradcheck in float64."""
    f = ts.functional.sim3
    tol = 1e-13 if dtype == torch.float64 else 1e-5
    for angle in (1e-3, 2.0):
        xi = torch.tensor([0.7, -1.1, 0.4, 0.3, 0.2, 0.5, lam], dtype=torch.float64)
        xi[3:6] *= angle / xi[3:6].norm()
        x = xi.to(dtype)
        J, J_inv = _sim3_jl_expm_mp(x.double().numpy())
        for fn, arg, want in [("jl", x, J), ("jl_inv", x, J_inv), ("jr", -x, J), ("jr_inv", -x, J_inv)]:
            got = getattr(ts.Sim3, fn)(arg).double().numpy()
            e = ref.blockwise_rel_err(got, want, "Sim3").rel
            assert e <= tol, f"{fn} at angle {angle}, lambda {float(arg[6]):g}: {e:.3g}"
        for fn, arg in [(f.jl_inv, x), (f.jl_inv, -x), (f.jr, -x), (f.jr_inv, x)]:
            a = arg.clone().requires_grad_()
            fn(a).sum().backward()
            assert torch.isfinite(a.grad).all(), f"gradient at angle {angle}, lambda {float(arg[6]):g}"
        if dtype == torch.float64:
            for fn, arg in [(f.jl_inv, x), (f.jr, -x)]:
                assert torch.autograd.gradcheck(fn, (arg[None].clone().requires_grad_(),), eps=1e-6,
                                                atol=1e-6, rtol=1e-5, fast_mode=True)
