"""Mapping between torchsgal's conventions and GTSAM 4.3's (python wrapper).

Numpy in and out; the orders and the element conversions are the package's own
(``torchsgal.interop.gtsam``), imported here so that every test using this map tests them too.
Our conventions are those of ``CONVENTIONS.md``. Every fact below was checked numerically
(``self_check()`` below re-checks them against ``scipy.linalg.expm`` of an independent numpy
hat in this file and against central finite differences; run ``python tests/peers/gtsam_map.py``
or call ``self_check()``).

Group correspondence and matrices
---------------------------------
- SO(3)   <-> ``gtsam.Rot3``:     ``Rot3(C)``; ``.matrix()`` is our C.
- SE(3)   <-> ``gtsam.Pose3``:    ``Pose3(M4)``; ``.matrix()`` is our 4x4.
- SE_2(3) <-> ``gtsam.NavState``: ``NavState(Rot3(C), r, v)`` (argument order: rotation,
  *position*, velocity). ``.position()`` is our r and ``.velocity()`` is our v, both in the
  nav (world) frame (``.bodyVelocity()`` is C^T v). ``.matrix()`` exists but its last two
  columns are swapped relative to ours: ``[[C, r, v], [0, 1, 0], [0, 0, 1]]``. Swapping
  rows and columns 3 and 4 (conjugation by a permutation) is a group isomorphism.
- SGal(3) <-> ``gtsam.Gal3``:     ``Gal3(M5)``; ``.matrix()`` is exactly our 5x5
  ``[[C, v, r], [0, 1, tau], [0, 0, 1]]``. ``Gal3(Rot3, r, v, t)`` also works
  (argument order: rotation, position, velocity, time).

Tangent orderings (GTSAM puts rotation first everywhere)
--------------------------------------------------------
- Rot3:     ``[phi]``                          (identity map)
- Pose3:    ``[phi, rho]``                     ours ``[rho, phi]``
- NavState: ``[phi, rho, nu]`` (rho position)  ours ``[rho, nu, phi]``
- Gal3:     ``[phi, nu, rho, iota]``           ours ``[rho, nu, phi, iota]``
  (Gal3.Hat puts xi[3:6] in the velocity column 3 and xi[6:9] in the position column 4.)
With ``P = PERM[group]``: ``xi_gtsam = xi_ours[P]`` and a matrix acting on tangents maps
as ``A_gtsam = A_ours[np.ix_(P, P)]`` (``T = I[P]``, ``A_gtsam = T A_ours T^T``).
For all four groups ``Expmap(xi_gtsam).matrix()`` (NavState: after the column swap) equals
``expm(hat_ours(xi_ours))`` to ~1e-15, and ``Logmap`` is its principal inverse.

Derivatives (right / local convention, same as ours)
----------------------------------------------------
- ``G.Expmap(xi, H)`` fills H (pass ``np.zeros((d, d))``; C or Fortran order both work)
  with the right Jacobian J_r(xi): ``Expmap(xi + d) ~ Expmap(xi) * Expmap(H d)``.
- ``G.Logmap(g, H)`` fills H with J_r(log g)^{-1}: ``Logmap(g * Expmap(d)) ~ log g + H d``.
- Accuracy of GTSAM itself (vs a 40-digit mpmath series): Expmap, AdjointMap, rotation log
  ~1e-15; Logmap translational parts and Logmap H are only O((pi - theta)^2) accurate
  near pi (~1e-9 at pi - 1e-4); Gal3's Expmap H has up to ~2.5e-10 error for angles
  around 1e-3 (cancellation, needs nu and iota non-zero).
- Rot3 and Pose3 also have static ``ExpmapDerivative(xi)`` (= J_r(xi)) and
  ``LogmapDerivative(xi)`` (= J_r(xi)^{-1}; Pose3 also accepts a Pose3). NavState and Gal3
  do not: use the optional H arguments.
- ``g.AdjointMap()`` is Ad(g) in GTSAM's ordering: ``Ad(g) xi = vee(g hat(xi) g^-1)``.
- ``g.compose(h)`` = g h, ``g.inverse()``, ``g.between(h)`` = g^-1 h (matrix products).
"""

import numpy as np
import torch

import torchsgal as ts
from torchsgal.interop import gtsam as interop

GROUPS = ("SO3", "SE3", "SE23", "SGal3")
GTSAM_CLASS = {"SO3": "Rot3", "SE3": "Pose3", "SE23": "NavState", "SGal3": "Gal3"}
DOF = {"SO3": 3, "SE3": 6, "SE23": 9, "SGal3": 10}
MATRIX_DIM = {"SO3": 3, "SE3": 4, "SE23": 5, "SGal3": 5}
_GROUP_CLASS = {"SO3": ts.SO3, "SE3": ts.SE3, "SE23": ts.SE23, "SGal3": ts.SGal3}

# xi_gtsam = xi_ours[PERM[g]], the package's table (interop.TYPES):
# SE3 ours [rho, phi] -> gtsam [phi, rho]; SE23 ours [rho, nu, phi] -> gtsam [phi, rho, nu];
# SGal3 ours [rho, nu, phi, iota] -> gtsam [phi, nu, rho, iota]
PERM = {g: np.array(interop.TYPES[GTSAM_CLASS[g]][1]) for g in GROUPS}
# where phi sits in our tangent
PHI_SLICE = {"SO3": slice(0, 3), "SE3": slice(3, 6), "SE23": slice(6, 9), "SGal3": slice(6, 9)}
# xi_ours = xi_gtsam[INV_PERM[g]]
INV_PERM = {k: np.argsort(p) for k, p in PERM.items()}


def _check_group(group):
    if group not in PERM:
        raise ValueError(f"group: expected one of {GROUPS}, got {group!r}")


def gtsam_class(group):
    import gtsam

    _check_group(group)
    return getattr(gtsam, GTSAM_CLASS[group])


def tangent_map(group):
    """T with xi_gtsam = T @ xi_ours (a permutation matrix, so T^-1 = T^T)."""
    _check_group(group)
    return np.eye(DOF[group])[PERM[group]]


def tangent_to_gtsam(group, xi):
    _check_group(group)
    return np.asarray(xi, dtype=np.float64)[..., PERM[group]]


def tangent_from_gtsam(group, xi):
    _check_group(group)
    return np.asarray(xi, dtype=np.float64).reshape(-1)[INV_PERM[group]]


def operator_to_gtsam(group, A):
    """A (dof x dof) acting on our tangents -> same operator on GTSAM's tangents."""
    _check_group(group)
    name = GTSAM_CLASS[group]
    A = torch.as_tensor(np.asarray(A, dtype=np.float64))
    return interop.jacobian_to_gtsam(A, output=name, input=name).numpy()


def operator_from_gtsam(group, A):
    """A (dof x dof) acting on GTSAM's tangents -> same operator on our tangents."""
    _check_group(group)
    name = GTSAM_CLASS[group]
    return interop.jacobian_from_gtsam(np.asarray(A, dtype=np.float64), output=name, input=name).numpy()


def to_gtsam(group, M):
    """Our matrix (numpy, n x n) -> gtsam object (the package's converter)."""
    _check_group(group)
    M = np.asarray(M, dtype=np.float64)
    n = MATRIX_DIM[group]
    if M.shape != (n, n):
        raise ValueError(f"M: expected shape ({n}, {n}) for {group}, got {M.shape}")
    return interop.to_gtsam(_GROUP_CLASS[group].from_matrix(torch.from_numpy(M.copy())))


def from_gtsam(group, obj):
    """gtsam object -> our matrix (numpy, n x n) (the package's converter)."""
    _check_group(group)
    return interop.from_gtsam(obj, group=_GROUP_CLASS[group]).as_matrix().numpy()


def expmap(group, xi_ours):
    """GTSAM Expmap of our tangent; returns (gtsam object, J_r in our ordering)."""
    d = DOF[group]
    H = np.zeros((d, d), order="F")
    g = gtsam_class(group).Expmap(tangent_to_gtsam(group, xi_ours), H)
    return g, operator_from_gtsam(group, H)


def logmap(group, obj):
    """GTSAM Logmap; returns (our tangent, J_r(log g)^-1 in our ordering)."""
    d = DOF[group]
    H = np.zeros((d, d), order="F")
    xi = gtsam_class(group).Logmap(obj, H)
    return tangent_from_gtsam(group, xi), operator_from_gtsam(group, H)


def adjoint(group, obj):
    """GTSAM AdjointMap in our ordering."""
    return operator_from_gtsam(group, obj.AdjointMap())


# ---------------------------------------------------------------------------
# Our conventions in plain numpy, used only to verify the mapping above.


def _skew(w):
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def hat(group, xi):
    """Our hat (CONVENTIONS.md) in numpy."""
    _check_group(group)
    xi = np.asarray(xi, dtype=np.float64)
    n = MATRIX_DIM[group]
    X = np.zeros((n, n))
    if group == "SO3":
        X[:] = _skew(xi)
    elif group == "SE3":
        X[:3, :3] = _skew(xi[3:6])
        X[:3, 3] = xi[0:3]
    else:
        X[:3, :3] = _skew(xi[6:9])
        X[:3, 3] = xi[3:6]
        X[:3, 4] = xi[0:3]
        if group == "SGal3":
            X[3, 4] = xi[9]
    return X


def vee(group, X):
    _check_group(group)
    X = np.asarray(X, dtype=np.float64)
    phi = np.array([X[2, 1], X[0, 2], X[1, 0]])
    if group == "SO3":
        return phi
    if group == "SE3":
        return np.concatenate([X[:3, 3], phi])
    xi = np.concatenate([X[:3, 4], X[:3, 3], phi])
    if group == "SGal3":
        xi = np.concatenate([xi, [X[3, 4]]])
    return xi


def ad(group, xi):
    """ad(xi) eta = vee([hat xi, hat eta]), built column by column."""
    d = DOF[group]
    X = hat(group, xi)
    A = np.zeros((d, d))
    for j in range(d):
        E = hat(group, np.eye(d)[j])
        A[:, j] = vee(group, X @ E - E @ X)
    return A


def jr_series(group, xi, terms=80):
    """J_r(xi) = sum_n (-ad xi)^n / (n+1)!"""
    d = DOF[group]
    A = -ad(group, xi)
    J = np.zeros((d, d))
    term = np.eye(d)
    for n in range(terms):
        J += term
        term = term @ A / (n + 2)
    return J


def self_check(seed=0, verbose=False):
    """Re-verify every fact in the docstring; raises AssertionError on failure."""
    import gtsam  # noqa: F401  (fail early without the peer)
    from scipy.linalg import expm

    rng = np.random.default_rng(seed)
    worst = {}
    for group in GROUPS:
        cls = gtsam_class(group)
        d = DOF[group]
        for angle in (1e-9, 1e-5, 1e-3, 1.0, 2.5, np.pi - 1e-4):
            xi = rng.normal(size=d)
            u = rng.normal(size=3)
            u /= np.linalg.norm(u)
            xi[PHI_SLICE[group]] = angle * u
            errs = {}
            M = expm(hat(group, xi))
            g, Jr = expmap(group, xi)
            errs["exp"] = np.abs(from_gtsam(group, g) - M).max()
            errs["roundtrip"] = np.abs(from_gtsam(group, to_gtsam(group, M)) - M).max()
            if group == "SE23":  # NavState.matrix() has the last two columns swapped
                S = np.eye(5)[[0, 1, 2, 4, 3]]
                errs["navmatrix"] = np.abs(np.array(g.matrix()) - S @ M @ S.T).max()
                errs["navvel"] = np.abs(np.asarray(g.velocity()).ravel() - M[:3, 3]).max()
                errs["navpos"] = np.abs(np.asarray(g.position()).ravel() - M[:3, 4]).max()
            xlog, Jr_inv = logmap(group, g)
            errs["log"] = np.abs(xlog - xi).max()
            errs["hat"] = np.abs(cls.Hat(tangent_to_gtsam(group, xi)) - (
                S @ hat(group, xi) @ S.T if group == "SE23" else hat(group, xi))).max()
            Jref = jr_series(group, xi)
            errs["jr"] = np.abs(Jr - Jref).max()
            errs["jr_inv"] = np.abs(Jr_inv - np.linalg.inv(Jref)).max() / max(1.0, np.abs(Jr_inv).max())
            # right-perturbation definition by central differences
            eps = 1e-6
            Jfd = np.zeros((d, d))
            for j in range(d):
                e = eps * np.eye(d)[j]
                Mp, Mm = expm(hat(group, xi + e)), expm(hat(group, xi - e))
                Jfd[:, j] = vee(group, np.linalg.solve(M, Mp - Mm)) / (2 * eps)
            errs["jr_fd"] = np.abs(Jr - Jfd).max() * 1e-3  # fd error ~1e-9
            # adjoint: Ad(g) eta = vee(M hat(eta) M^-1)
            Ad = adjoint(group, g)
            Minv = np.linalg.inv(M)
            Adref = np.stack([vee(group, M @ hat(group, np.eye(d)[j]) @ Minv) for j in range(d)], 1)
            errs["Ad"] = np.abs(Ad - Adref).max() / max(1.0, np.abs(Adref).max())
            # compose / between / inverse
            h = cls.Expmap(tangent_to_gtsam(group, rng.normal(size=d)))
            Mh = from_gtsam(group, h)
            errs["compose"] = np.abs(from_gtsam(group, g.compose(h)) - M @ Mh).max()
            errs["between"] = np.abs(from_gtsam(group, g.between(h)) - Minv @ Mh).max()
            errs["inverse"] = np.abs(from_gtsam(group, g.inverse()) - Minv).max()
            if hasattr(cls, "ExpmapDerivative"):
                xg = tangent_to_gtsam(group, xi)
                errs["ExpmapDerivative"] = np.abs(operator_from_gtsam(group, cls.ExpmapDerivative(xg)) - Jref).max()
                errs["LogmapDerivative"] = np.abs(
                    operator_from_gtsam(group, cls.LogmapDerivative(xg)) - np.linalg.inv(Jref)).max()
            for k, v in errs.items():
                worst[(group, k)] = max(worst.get((group, k), 0.0), v)
    if verbose:
        for k, v in sorted(worst.items()):
            print(k, f"{v:.2e}")
    # A wrong ordering/layout gives O(1) errors; GTSAM's own Logmap and its derivative
    # are only accurate to ~1e-9 at pi - 1e-4 (see tests/test_gtsam.py), hence 1e-8.
    bad = {k: v for k, v in worst.items() if not v < 1e-8}
    assert not bad, f"gtsam mapping check failed: {bad}"
    return worst


if __name__ == "__main__":
    self_check(verbose=True)
    print("ok")
