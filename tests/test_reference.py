"""Self-tests of the test oracle tests/reference.py against independent definitions."""

import time

import numpy as np
import pytest
import scipy.linalg

try:  # tests/ as a package
    from . import reference as R
except ImportError:  # tests/ on sys.path (pytest rootdir-less "prepend" import)
    import reference as R

GROUPS = R.GROUPS


def _rng(seed=0):
    return np.random.default_rng(seed)


# ---------------------------------------------------------------------------- hat / vee


def _hand_hat(group, x):
    """hat written out entry by entry from CONVENTIONS.md (1-based comments)."""
    if group in ("SO2", "SE2"):  # theta J, rho in column 3
        X = np.zeros((R.MATRIX_SIZE[group],) * 2)
        X[0, 1], X[1, 0] = -x[-1], x[-1]
        if group == "SE2":
            X[:2, 2] = x[:2]
        return X
    if group == "SO3":
        p = x
    elif group == "SE3":
        p = x[3:6]
    else:
        p = x[6:9]
    S = np.array([[0, -p[2], p[1]], [p[2], 0, -p[0]], [-p[1], p[0], 0]], dtype=float)
    n = R.MATRIX_SIZE[group]
    X = np.zeros((n, n))
    X[:3, :3] = S
    if group == "SE3":
        X[:3, 3] = x[0:3]  # rho in column 4
    elif group in ("SE23", "SGal3"):
        X[:3, 3] = x[3:6]  # nu in column 4
        X[:3, 4] = x[0:3]  # rho in column 5
        if group == "SGal3":
            X[3, 4] = x[9]  # iota at row 4, column 5
    return X


@pytest.mark.parametrize("group", GROUPS)
def test_hat_layout_and_roundtrip(group):
    d = R.DOF[group]
    x = np.arange(1.0, d + 1.0)
    np.testing.assert_array_equal(R.hat(group, x), _hand_hat(group, x))
    xs = _rng().standard_normal((4, 2, d))
    X = R.hat(group, xs)
    assert X.shape == (4, 2) + (R.MATRIX_SIZE[group],) * 2
    np.testing.assert_array_equal(R.vee(group, X), xs)
    # skew(a) b == a x b
    a, b = _rng(1).standard_normal((2, 3))
    np.testing.assert_allclose(R.skew(a) @ b, np.cross(a, b), rtol=0, atol=1e-15)


def test_bad_input_raises():
    with pytest.raises(ValueError, match="xi"):
        R.hat("SE3", np.zeros(5))
    with pytest.raises(ValueError, match="group"):
        R.hat("SE4", np.zeros(6))


# ----------------------------------------------------------------------------- ad / Ad


@pytest.mark.parametrize("group", GROUPS)
def test_ad_is_commutator(group):
    rng = _rng(2)
    d = R.DOF[group]
    xi, eta, zeta = rng.standard_normal((3, d))
    X, E = R.hat(group, xi), R.hat(group, eta)
    np.testing.assert_allclose(R.ad(group, xi) @ eta, R.vee(group, X @ E - E @ X), rtol=0, atol=1e-13)
    # antisymmetry and the Jacobi identity of the bracket [a, b] = ad(a) b
    A = lambda v: R.ad(group, v)
    np.testing.assert_allclose(A(xi) @ eta, -A(eta) @ xi, rtol=0, atol=1e-13)
    jac = A(xi) @ A(eta) @ zeta + A(eta) @ A(zeta) @ xi + A(zeta) @ A(xi) @ eta
    np.testing.assert_allclose(jac, 0, rtol=0, atol=1e-12)
    # batched == looped
    xs = rng.standard_normal((3, d))
    np.testing.assert_array_equal(R.ad(group, xs)[1], R.ad(group, xs[1]))


def test_ad_se3_closed_form():
    xi = _rng(3).standard_normal(6)
    rho, phi = xi[:3], xi[3:]
    expected = np.block([[R.skew(phi), R.skew(rho)], [np.zeros((3, 3)), R.skew(phi)]])
    np.testing.assert_allclose(R.ad("SE3", xi), expected, rtol=0, atol=1e-15)


@pytest.mark.parametrize("group", GROUPS)
def test_Ad_of_exp_is_expm_of_ad(group):
    xi = R.random_tangent(group, _rng(4), angle=2.0)
    Ad = R.Ad_from_matrix(group, R.expm_hat(group, xi))
    np.testing.assert_allclose(Ad, scipy.linalg.expm(R.ad(group, xi)), rtol=0, atol=1e-12)
    # Ad(M) eta == vee(M hat(eta) M^-1) for a random eta
    M = R.expm_hat(group, xi)
    eta = _rng(5).standard_normal(R.DOF[group])
    np.testing.assert_allclose(
        Ad @ eta, R.vee(group, M @ R.hat(group, eta) @ np.linalg.inv(M)), rtol=0, atol=1e-12
    )


# ---------------------------------------------------------------------------- exp / log


@pytest.mark.parametrize("group", GROUPS)
@pytest.mark.parametrize("angle", [0.0, 1e-3, 1.0, 3.0])
def test_expm_hat_vs_exp_mp(group, angle):
    xi = R.random_tangent(group, _rng(6), angle=angle)
    M = R.expm_hat(group, xi)
    Mmp = R.exp_mp(group, xi, dps=30)
    assert R.rel_err(M, Mmp) < 1e-13
    k = 2 if group in ("SO2", "SE2") else 3
    C = Mmp[:k, :k]
    np.testing.assert_allclose(C.T @ C, np.eye(k), rtol=0, atol=1e-14)
    assert abs(np.linalg.det(C) - 1) < 1e-14
    n = R.MATRIX_SIZE[group]
    if n > k:
        np.testing.assert_array_equal(Mmp[n - 1], np.eye(n)[n - 1])
    if group == "SE23":
        np.testing.assert_array_equal(Mmp[3], [0, 0, 0, 1, 0])
    if group == "SGal3":  # row 4 is [0, 0, 0, 1, tau] with tau = iota
        np.testing.assert_allclose(Mmp[3], [0, 0, 0, 1, xi[9]], rtol=0, atol=1e-15)


@pytest.mark.parametrize("group", GROUPS)
def test_logm_vee_inverts_expm_hat(group):
    xs = np.stack([R.random_tangent(group, _rng(7 + k), angle=a) for k, a in enumerate([0.3, 2.0, 3.0])])
    np.testing.assert_allclose(R.logm_vee(group, R.expm_hat(group, xs)), xs, rtol=0, atol=1e-10)


# ----------------------------------------------------------------------------- Jacobians


def _fd_left(group, xi, h=1e-5):
    """Column j: (log(exp(xi + h e_j) exp(xi)^-1) - log(exp(xi - h e_j) exp(xi)^-1)) / 2h."""
    d = R.DOF[group]
    Mi = np.linalg.inv(R.expm_hat(group, xi))
    J = np.empty((d, d))
    for j in range(d):
        e = np.zeros(d)
        e[j] = h
        p = R.logm_vee(group, R.expm_hat(group, xi + e) @ Mi)
        m = R.logm_vee(group, R.expm_hat(group, xi - e) @ Mi)
        J[:, j] = (p - m) / (2 * h)
    return J


def _fd_right(group, xi, h=1e-5):
    d = R.DOF[group]
    Mi = np.linalg.inv(R.expm_hat(group, xi))
    J = np.empty((d, d))
    for j in range(d):
        e = np.zeros(d)
        e[j] = h
        p = R.logm_vee(group, Mi @ R.expm_hat(group, xi + e))
        m = R.logm_vee(group, Mi @ R.expm_hat(group, xi - e))
        J[:, j] = (p - m) / (2 * h)
    return J


@pytest.mark.parametrize("group", GROUPS)
@pytest.mark.parametrize("angle", [0.5, 2.5])
def test_jacobian_series_vs_finite_differences(group, angle):
    xi = R.random_tangent(group, _rng(8), angle=angle)
    assert R.rel_err(R.jl_series(group, xi), _fd_left(group, xi)) < 1e-8
    assert R.rel_err(R.jr_series(group, xi), _fd_right(group, xi)) < 1e-8


@pytest.mark.parametrize("group", GROUPS)
def test_jl_is_Ad_jr(group):
    xi = R.random_tangent(group, _rng(9), angle=2.8, size=2)
    Ad = R.Ad_from_matrix(group, R.expm_hat(group, xi))
    np.testing.assert_allclose(
        R.jl_series(group, xi), Ad @ R.jr_series(group, xi), rtol=0, atol=1e-12
    )


def test_so3_jl_closed_form():
    phi = R.random_tangent("SO3", _rng(10), angle=2.0)
    t = np.linalg.norm(phi)
    S = R.skew(phi)
    Jl = np.eye(3) + (1 - np.cos(t)) / t**2 * S + (t - np.sin(t)) / t**3 * S @ S
    assert R.rel_err(R.jl_mp("SO3", phi), Jl) < 1e-14
    assert R.rel_err(R.jl_series("SO3", phi), Jl) < 1e-14


@pytest.mark.parametrize("group", GROUPS)
@pytest.mark.parametrize("angle", [1e-3, 1.0, 3.0])
def test_jl_series_vs_jl_mp(group, angle):
    xi = R.random_tangent(group, _rng(11), angle=angle)
    J = R.jl_mp(group, xi)
    Jf = R.jl_series(group, xi)
    assert R.rel_err(Jf, J) < 1e-14
    be = R.blockwise_rel_err(Jf, J, group)
    assert be.rel < 1e-13 and be.zero_abs == 0.0
    # right Jacobian too (against finite differences of exp on the right), and the dps is
    # honoured (30 and 60 digits agree to float64)
    assert R.rel_err(R.jr_mp(group, xi), _fd_right(group, xi)) < 1e-8
    assert R.rel_err(R.jl_mp(group, xi, dps=30), R.jl_mp(group, xi, dps=60)) < 1e-16


@pytest.mark.parametrize("group", GROUPS)
def test_jl_inv_mp(group):
    xi = R.random_tangent(group, _rng(12), angle=3.0)
    Ji = R.jl_inv_mp(group, xi)
    np.testing.assert_allclose(Ji @ R.jl_mp(group, xi), np.eye(R.DOF[group]), rtol=0, atol=1e-13)
    assert R.rel_err(Ji, np.linalg.inv(R.jl_series(group, xi))) < 1e-12
    # the right one inverts the float64 right series (itself checked against finite differences)
    np.testing.assert_allclose(R.jr_inv_mp(group, xi) @ R.jr_series(group, xi), np.eye(R.DOF[group]), rtol=0, atol=1e-13)


def test_jl_mp_near_pi_and_nilpotent():
    xi = R.random_tangent("SGal3", _rng(13), angle=np.pi - 1e-6)
    t0 = time.perf_counter()
    J = R.jl_mp("SGal3", xi)
    assert time.perf_counter() - t0 < 1.0
    assert R.rel_err(R.jl_series("SGal3", xi), J) < 1e-14
    # phi = 0: ad is nilpotent, the series terminates exactly
    xi0 = xi.copy()
    xi0[6:9] = 0
    A = R.ad("SGal3", xi0)
    closed = sum(np.linalg.matrix_power(A, k) / np.prod(np.arange(1, k + 2)) for k in range(10))
    assert R.rel_err(R.jl_mp("SGal3", xi0), closed) < 1e-15


def test_jl_mp_nonconvergence_guard():
    with pytest.raises(RuntimeError, match="converge"):
        R.jl_mp("SO3", np.array([0.0, 0.0, 3.0]), max_terms=5)


# -------------------------------------------------------------------------------- helpers


@pytest.mark.parametrize("group", GROUPS)
def test_random_tangent(group):
    xs = R.random_tangent(group, _rng(14), angle=1.234, scale=5.0, size=(7,))
    assert xs.shape == (7, R.DOF[group])
    np.testing.assert_allclose(np.linalg.norm(xs[:, R.ROT_SLICE[group]], axis=-1), 1.234, rtol=1e-15)
    free = R.random_tangent(group, _rng(15), size=50)
    ang = np.linalg.norm(free[:, R.ROT_SLICE[group]], axis=-1)
    assert np.all(ang < np.pi) and np.ptp(ang) > 0.5


def test_error_measures_detect_small_block_errors():
    xi = R.random_tangent("SGal3", _rng(16), angle=1e-3, scale=1e-4)
    J = R.jl_series("SGal3", xi)
    assert R.blockwise_rel_err(J, J, "SGal3") == (0.0, 0.0, (0, 0))
    bad = J.copy()
    bad[0:3, 6:9] *= 1 + 1e-6  # a small block, relative error 1e-6
    assert R.rel_err(bad, J) < 1e-9  # invisible against the whole matrix
    be = R.blockwise_rel_err(bad, J, [3, 3, 3, 1])
    assert be.rel == pytest.approx(1e-6, rel=1e-3) and be.worst_block == (0, 2)
    assert be.zero_abs == 0.0
    bad2 = J.copy()
    bad2[9, 0] = 1e-3  # the iota row of J_l is identically zero in the reference
    be2 = R.blockwise_rel_err(bad2, J, "SGal3")
    assert be2.zero_abs == 1e-3 and be2.rel == 0.0
    # vectors and batches
    v = xi.copy()
    v[9] *= 1 + 1e-5
    assert R.blockwise_rel_err(v, xi, "SGal3").rel == pytest.approx(1e-5, rel=1e-6)
    assert R.blockwise_rel_err(np.stack([J, bad]), np.stack([J, J]), "SGal3").rel == be.rel
