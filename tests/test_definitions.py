"""Every closed form against its definition: scipy expm/logm, the series, finite differences,
and the identities of the manif suite.  Runs over every group, batch shape and dtype."""
from __future__ import annotations

import math

import numpy as np
import pytest
import reference as ref
import scipy.linalg
import torch
from conftest import all_groups, assert_close, gname, np64, sample_group, sample_tangent

import torchsgal as ts
from torchsgal.functional import native


@all_groups
def test_exp_matches_expm(G, batch_shape, dtype):
    xi = sample_tangent(G, batch_shape, dtype)
    expected = ref.expm_hat(gname(G), np64(xi))
    assert_close(G.exp(xi).as_matrix(), expected, dtype)


@all_groups
def test_exp_impl_equals_exp(G, batch_shape, dtype):
    xi = sample_tangent(G, batch_shape, dtype)
    with native.disabled():  # the class runs the functional closed form, bit for bit
        assert torch.equal(G._f.exp_impl(xi), G.exp(xi).as_matrix())
    # (SGal3's C kernels evaluate it in another order: equal to rounding, tests/test_native.py)


@all_groups
def test_log_matches_logm(G, batch_shape, dtype):
    # logm of a rotation near pi is itself ill-conditioned: compare on angles below 3.
    ang = np.linspace(0.0, 3.0, int(np.prod(batch_shape)) if batch_shape else 1)
    xi = sample_tangent(G, batch_shape, torch.float64, angles=ang)
    M = ref.expm_hat(gname(G), np64(xi))
    got = G.from_matrix(torch.tensor(M, dtype=dtype)).log()
    assert_close(got, ref.logm_vee(gname(G), M), dtype, factor=10)


@all_groups
def test_log_exp_round_trip(G, batch_shape, dtype):
    """log(exp(xi)) = xi for rotation angles up to pi - 1e-6, float32 included: log takes the
    axis from the symmetric part of C near pi, and the angle from atan2, so float32 stays
    accurate there (measured worst relative error 4.7e-7 over angles pi - 1e-6 .. pi - 1e-3,
    40 seeds x 12 samples, every group; the tolerance is 2e-5)."""
    xi = sample_tangent(G, batch_shape, dtype, seed=1)
    back = G.exp(xi).log()
    scale = max(1.0, float(xi.abs().max()))
    assert_close(back, np64(xi), dtype, scale=scale)


@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=lambda g: g.__name__)
@pytest.mark.parametrize("delta", [1e-6, 1e-8, 1e-10])
def test_log_near_pi(G, delta):
    """Angle exactly pi - delta: the axis and angle survive (no division by sin alone)."""
    xi = sample_tangent(G, (4,), torch.float64, seed=2, angles=[math.pi - delta] * 4)
    back = G.exp(xi).log()
    assert_close(back, np64(xi), torch.float64)


@all_groups
def test_jl_matches_series(G, batch_shape, dtype):
    xi = sample_tangent(G, batch_shape, dtype)
    assert_close(G.jl(xi), ref.jl_series(gname(G), np64(xi)), dtype)
    assert_close(G.jr(xi), ref.jr_series(gname(G), np64(xi)), dtype)


@all_groups(dtypes=[torch.float64])
def test_jl_matches_finite_differences_of_exp(G, batch_shape, dtype):
    """J_l d = d/dh vee(logm(exp(xi + h d) exp(xi)^-1)) at h = 0, central differences."""
    xi = np64(sample_tangent(G, batch_shape, dtype)).reshape(-1, G.dof)
    J = np64(G.jl(torch.tensor(xi)))
    h = 1e-6
    for k in range(xi.shape[0]):
        E0inv = np.linalg.inv(ref.expm_hat(gname(G), xi[k]))
        fd = np.zeros((G.dof, G.dof))
        for j in range(G.dof):
            d = np.zeros(G.dof)
            d[j] = h
            up = ref.logm_vee(gname(G), ref.expm_hat(gname(G), xi[k] + d) @ E0inv)
            dn = ref.logm_vee(gname(G), ref.expm_hat(gname(G), xi[k] - d) @ E0inv)
            fd[:, j] = (up - dn) / (2 * h)
        np.testing.assert_allclose(J[k], fd, rtol=0, atol=1e-7 * max(1.0, np.abs(fd).max()))


@all_groups
def test_adjoint_of_exp_is_expm_of_ad(G, batch_shape, dtype):
    """Ad(exp xi) = expm(ad xi), (3.19); Ad from its definition vee(g hat(xi) g^-1)."""
    xi = sample_tangent(G, batch_shape, dtype)
    g = G.exp(xi)
    A = np64(G.ad(xi)).reshape(-1, G.dof, G.dof)
    expected = np.stack([scipy.linalg.expm(a) for a in A]).reshape(*batch_shape, G.dof, G.dof)
    assert_close(g.adjoint(), expected, dtype, factor=10)
    assert_close(g.adjoint(), ref.Ad_from_matrix(gname(G), np64(g.as_matrix())), dtype, factor=10)


@all_groups
def test_ad_matches_commutator(G, batch_shape, dtype):
    xi = sample_tangent(G, batch_shape, dtype)
    assert_close(G.ad(xi), ref.ad(gname(G), np64(xi)), dtype)


@all_groups
def test_hat_vee(G, batch_shape, dtype):
    xi = sample_tangent(G, batch_shape, dtype)
    assert_close(G.hat(xi), ref.hat(gname(G), np64(xi)), dtype)
    assert torch.equal(G.vee(G.hat(xi)), xi)


@all_groups
def test_jl_equals_adjoint_times_jr(G, batch_shape, dtype):
    xi = sample_tangent(G, batch_shape, dtype)
    lhs = G.jl(xi)
    rhs = G.exp(xi).adjoint() @ G.jr(xi)
    assert_close(lhs, np64(rhs), dtype, factor=10)


@all_groups
def test_jacobian_inverses(G, batch_shape, dtype):
    xi = sample_tangent(G, batch_shape, dtype)
    eye = np.broadcast_to(np.eye(G.dof), (*batch_shape, G.dof, G.dof))
    assert_close(G.jl(xi) @ G.jl_inv(xi), eye, dtype, factor=10)
    assert_close(G.jr_inv(xi) @ G.jr(xi), eye, dtype, factor=10)


@all_groups
def test_exp_of_adjoint_is_conjugation(G, batch_shape, dtype):
    """exp(Ad(g) xi) = g exp(xi) g^-1."""
    xi = sample_tangent(G, batch_shape, dtype)
    g = sample_group(G, batch_shape, dtype, seed=7)
    lhs = G.exp((g.adjoint() @ xi.unsqueeze(-1)).squeeze(-1))
    rhs = g @ G.exp(xi) @ g.inverse()
    assert_close(lhs.as_matrix(), np64(rhs.as_matrix()), dtype, factor=10)


@all_groups
def test_inverse_and_compose_match_matrices(G, batch_shape, dtype):
    g = sample_group(G, batch_shape, dtype, seed=3)
    h = sample_group(G, batch_shape, dtype, seed=4)
    assert_close(g.inverse().as_matrix(), np.linalg.inv(np64(g.as_matrix())), dtype, factor=10)
    assert_close((g @ h).as_matrix(), np64(g.as_matrix()) @ np64(h.as_matrix()), dtype)


@all_groups(dtypes=[torch.float64])
def test_jl_inv_matches_series_inverse(G, batch_shape, dtype):
    xi = sample_tangent(G, batch_shape, dtype)
    expected = np.linalg.inv(ref.jl_series(gname(G), np64(xi)))
    assert_close(G.jl_inv(xi), expected, dtype)
