"""Sim3 against GTSAM 4.3's Similarity3.

Convention mapping (checked below, not assumed):
- matrices: GTSAM's ``Similarity3.matrix()`` is [[R, t], [0, 1/s]], exactly our 4x4 (Barfoot's
  (78) with s = exp(lambda)); ``Similarity3(M)`` builds from it;
- tangent: GTSAM's is [w, u, lambda] (rotation first) with Hat [[w^, u], [0, -lambda]], ours
  [rho, phi, lambda] with the same hat, so ``xi_gtsam = xi_ours[P]``, P = [3, 4, 5, 0, 1, 2, 6];
  a matrix on tangents maps as ``A_gtsam = A_ours[P][:, P]`` (AdjointMap);
- action: ``transformFrom(p) = s (R p + t)``, our ``act``; its H1 is the derivative with respect
  to a right perturbation g exp(d) in GTSAM's ordering, its H2 is s R;
- ``localCoordinates(h)`` of g is our ``h.rminus(g)`` = log(g^-1 h).

Not mapped: GTSAM's Python wrapper exposes no derivatives of Similarity3's Expmap/Logmap (the
C++ Expmap/Logmap take no OptionalJacobian for Similarity3 in the wrapper), so J_r and J_r^-1
are checked against the series (test_definitions, test_precision) but not against GTSAM.

GTSAM's closed forms cancel in a small-scale band: for lambda ~ 1e-5 its Expmap/Logmap lose
~5 digits (1e-11 absolute at angle ~pi).  Those points are compared with the 50-digit series,
where torchsgal stays at rounding level (test_small_scale_band_against_mpmath).
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import reference as ref
import torch

import torchsgal as ts

gtsam = pytest.importorskip("gtsam")

P = [3, 4, 5, 0, 1, 2, 6]
ANGLES = [0.0, 1e-9, 1e-4, 0.5, 2.0, math.pi - 1e-4]
# lambda away from GTSAM's cancellation band (see the module docstring)
LAMBDAS = [0.0, 1e-9, 0.7, -2.0, 5.0]


def _xi(angle, lam, seed):
    xi = ref.random_tangent("Sim3", seed, angle=angle)
    xi[6] = lam
    return xi


def _t(x):
    return torch.tensor(x, dtype=torch.float64)


@pytest.mark.parametrize("lam", LAMBDAS)
@pytest.mark.parametrize("angle", ANGLES)
def test_sim3_against_similarity3(angle, lam):
    xi = _xi(angle, lam, seed=int(angle * 1e3 + lam * 1e2) % 101)
    S = gtsam.Similarity3.Expmap(xi[P])
    g = ts.Sim3.exp(_t(xi))
    M = g.as_matrix().numpy()
    scale = max(1.0, np.abs(M).max())
    np.testing.assert_allclose(M, S.matrix(), rtol=0, atol=1e-14 * scale)
    np.testing.assert_allclose(g.log().numpy()[P], gtsam.Similarity3.Logmap(S), rtol=0, atol=1e-13)
    Ad = g.adjoint().numpy()
    np.testing.assert_allclose(Ad[np.ix_(P, P)], S.AdjointMap(), rtol=0, atol=1e-14 * max(1.0, np.abs(Ad).max()))
    np.testing.assert_allclose(float(g.scale()), S.scale(), rtol=1e-15)

    Q = gtsam.Similarity3.Expmap(_xi(0.8, -0.3, 5)[P])
    h = ts.Sim3.from_matrix(_t(Q.matrix()), check=True)
    np.testing.assert_allclose((g @ h).as_matrix().numpy(), S.compose(Q).matrix(), rtol=0, atol=1e-14 * scale)
    np.testing.assert_allclose(g.inverse().as_matrix().numpy(), S.inverse().matrix(), rtol=1e-14, atol=1e-14 * scale)
    np.testing.assert_allclose(g.between(h).as_matrix().numpy(), S.between(Q).matrix(), rtol=1e-13, atol=1e-13 * scale)
    np.testing.assert_allclose(h.rminus(g).numpy()[P], S.localCoordinates(Q), rtol=0, atol=1e-12)

    # action on points and its derivatives
    p = np.array([0.3, -1.0, 2.0])
    H1 = np.zeros((3, 7), order="F")
    H2 = np.zeros((3, 3), order="F")
    y = S.transformFrom(p, H1, H2)
    np.testing.assert_allclose(g.act(_t(p)).numpy(), y, rtol=1e-14, atol=1e-14 * scale)
    D = torch.func.jacrev(lambda d: g.rplus(d).act(_t(p)))(torch.zeros(7, dtype=torch.float64)).numpy()
    np.testing.assert_allclose(D[:, P], H1, rtol=1e-13, atol=1e-13 * scale)
    np.testing.assert_allclose((g.scale()[..., None, None] * g.rotation()).numpy(), H2, rtol=0, atol=1e-15 * np.abs(H2).max())


def test_hat_conventions_agree():
    xi = _xi(1.3, 0.4, 7)
    np.testing.assert_array_equal(ts.Sim3.hat(_t(xi)).numpy(), gtsam.Similarity3.Hat(xi[P]))
    np.testing.assert_array_equal(ts.Sim3.vee(_t(gtsam.Similarity3.Hat(xi[P]))).numpy(), xi)


@pytest.mark.parametrize("angle", [0.5, 2.0, math.pi - 1e-4])
def test_small_scale_band_against_mpmath(angle):
    """lambda = 1e-5: GTSAM's Expmap/Logmap cancel; ours stay at rounding level.  Both against
    the 50-digit series (exp) and its exact logarithm (xi itself)."""
    xi = _xi(angle, 1e-5, 11)
    M_ref = ref.exp_mp("Sim3", xi)
    ours_exp = np.abs(ts.Sim3.exp(_t(xi)).as_matrix().numpy() - M_ref).max()
    gtsam_exp = np.abs(gtsam.Similarity3.Expmap(xi[P]).matrix() - M_ref).max()
    ours_log = np.abs(ts.Sim3.from_matrix(_t(M_ref)).log().numpy() - xi).max()
    gtsam_log = np.abs(gtsam.Similarity3.Logmap(gtsam.Similarity3(M_ref))[np.argsort(P)] - xi).max()
    assert ours_exp <= 1e-15 * np.abs(M_ref).max() and ours_log <= 1e-15 * np.abs(xi).max()
    print(f"angle {angle:g}, lambda 1e-5: exp error ours {ours_exp:.1e}, GTSAM {gtsam_exp:.1e}; "
          f"log error ours {ours_log:.1e}, GTSAM {gtsam_log:.1e}")
    assert gtsam_exp > 10 * ours_exp and gtsam_log > 10 * ours_log  # the band is real
