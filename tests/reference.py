"""Independent reference implementation of the torchsgal groups, used as a test oracle.

Nothing here imports torchsgal. Everything is built from the definitions in
``shared/CONVENTIONS.md``:

* ``hat``/``vee`` from the matrix layouts,
* ``ad(xi)`` column by column from the commutator ``vee([hat(xi), hat(e_j)])``,
* ``Ad(M)`` column by column from the conjugation ``vee(M hat(e_j) M^-1)``,
* ``exp``/``log`` from ``scipy.linalg.expm``/``logm``,
* ``J_l(xi) = sum_n ad(xi)^n / (n+1)!`` and ``J_r(xi) = J_l(-xi)`` by their series,
  in float64 and in high precision (mpmath).

Groups: ``"SO2"``, ``"SE2"``, ``"SO3"``, ``"SE3"``, ``"SE23"``, ``"SGal3"``, ``"Sim3"``.  Tangent
orderings: SO3 ``phi``; SE3 ``[rho, phi]``; SE23 ``[rho, nu, phi]``; SGal3 ``[rho, nu, phi, iota]``;
Sim3 ``[rho, phi, lambda]`` with hat ``[[phi^, rho], [0, -lambda]]`` (Barfoot (78)), so the
matrix stores ``exp(-lambda)`` bottom-right.

The numpy functions accept a leading batch shape (``(..., dof)`` vectors and
``(..., n, n)`` matrices); the matrix functions loop over the batch.  The mpmath
functions accept a single vector or a batch as well and return float64 numpy arrays.
"""

from __future__ import annotations

from collections import namedtuple

import mpmath
import numpy as np
import scipy.linalg

__all__ = [
    "GROUPS",
    "DOF",
    "MATRIX_SIZE",
    "BLOCKS",
    "ROT_SLICE",
    "skew",
    "hat",
    "vee",
    "basis",
    "ad",
    "Ad_from_matrix",
    "expm_hat",
    "logm_vee",
    "inv",
    "jl_series",
    "jr_series",
    "random_tangent",
    "jl_mp",
    "jr_mp",
    "jl_inv_mp",
    "jr_inv_mp",
    "exp_mp",
    "rel_err",
    "BlockErr",
    "blockwise_rel_err",
]

# The groups that test_reference.py self-checks entry by hand (fixed bottom rows).  Sim3 is
# supported by every function here as well; its self-checks are in test_precision.py
# (test_sim3_reference_oracle).
GROUPS = ("SO2", "SE2", "SO3", "SE3", "SE23", "SGal3")
DOF = {"SO2": 1, "SE2": 3, "SO3": 3, "SE3": 6, "SE23": 9, "SGal3": 10, "Sim3": 7}
MATRIX_SIZE = {"SO2": 2, "SE2": 3, "SO3": 3, "SE3": 4, "SE23": 5, "SGal3": 5, "Sim3": 4}
# Partition of the tangent vector into blocks (rho / nu / phi / iota).
BLOCKS = {"SO2": [1], "SE2": [2, 1], "SO3": [3], "SE3": [3, 3], "SE23": [3, 3, 3], "SGal3": [3, 3, 3, 1],
          "Sim3": [3, 3, 1]}
# Where the rotation part phi sits in the tangent vector.
ROT_SLICE = {
    "SO2": slice(0, 1),
    "SE2": slice(2, 3),
    "SO3": slice(0, 3),
    "SE3": slice(3, 6),
    "SE23": slice(6, 9),
    "SGal3": slice(6, 9),
    "Sim3": slice(3, 6),
}


def _check_group(group):
    if group not in DOF:
        raise ValueError(f"group: expected one of {GROUPS}, got {group!r}")


def _check_vec(group, xi, name="xi"):
    _check_group(group)
    xi = np.asarray(xi, dtype=np.float64)
    if xi.ndim < 1 or xi.shape[-1] != DOF[group]:
        raise ValueError(
            f"{name}: expected shape (..., {DOF[group]}) for {group}, got {xi.shape}"
        )
    return xi


def _check_mat(group, M, name="M"):
    _check_group(group)
    M = np.asarray(M, dtype=np.float64)
    n = MATRIX_SIZE[group]
    if M.ndim < 2 or M.shape[-2:] != (n, n):
        raise ValueError(f"{name}: expected shape (..., {n}, {n}) for {group}, got {M.shape}")
    return M


# ----------------------------------------------------------------------------------------
# hat / vee
# ----------------------------------------------------------------------------------------


def skew(phi):
    """(..., 3) -> (..., 3, 3) with skew(a) b = a x b."""
    phi = np.asarray(phi, dtype=np.float64)
    S = np.zeros(phi.shape[:-1] + (3, 3))
    x, y, z = phi[..., 0], phi[..., 1], phi[..., 2]
    S[..., 0, 1] = -z
    S[..., 0, 2] = y
    S[..., 1, 0] = z
    S[..., 1, 2] = -x
    S[..., 2, 0] = -y
    S[..., 2, 1] = x
    return S


def _split(group, xi):
    """Return (rho, nu, phi, iota) slices of xi (None where the group has no such part)."""
    if group == "SO3":
        return None, None, xi[..., 0:3], None
    if group == "SE3":
        return xi[..., 0:3], None, xi[..., 3:6], None
    if group == "SE23":
        return xi[..., 0:3], xi[..., 3:6], xi[..., 6:9], None
    return xi[..., 0:3], xi[..., 3:6], xi[..., 6:9], xi[..., 9]


def hat(group, xi):
    """Tangent vector(s) (..., dof) -> algebra matrix (..., n, n)."""
    xi = _check_vec(group, xi)
    n = MATRIX_SIZE[group]
    X = np.zeros(xi.shape[:-1] + (n, n))
    if group in ("SO2", "SE2"):  # planar: theta J top-left, rho in the last column
        t = xi[..., -1]
        X[..., 0, 1], X[..., 1, 0] = -t, t
        if group == "SE2":
            X[..., 0:2, 2] = xi[..., 0:2]
        return X
    if group == "Sim3":
        X[..., 0:3, 0:3] = skew(xi[..., 3:6])
        X[..., 0:3, 3] = xi[..., 0:3]
        X[..., 3, 3] = -xi[..., 6]
        return X
    rho, nu, phi, iota = _split(group, xi)
    X[..., 0:3, 0:3] = skew(phi)
    if group == "SE3":
        X[..., 0:3, 3] = rho
    elif group in ("SE23", "SGal3"):
        X[..., 0:3, 3] = nu
        X[..., 0:3, 4] = rho
        if group == "SGal3":
            X[..., 3, 4] = iota
    return X


def vee(group, X):
    """Algebra matrix (..., n, n) -> tangent vector (..., dof). Reads only the
    defining entries (the rotation part from the antisymmetric part of the 3x3 block)."""
    X = _check_mat(group, X, "X")
    if group in ("SO2", "SE2"):
        t = 0.5 * (X[..., 1, 0] - X[..., 0, 1])[..., None]
        return t if group == "SO2" else np.concatenate([X[..., 0:2, 2], t], axis=-1)
    A = X[..., 0:3, 0:3]
    phi = 0.5 * np.stack(
        [A[..., 2, 1] - A[..., 1, 2], A[..., 0, 2] - A[..., 2, 0], A[..., 1, 0] - A[..., 0, 1]],
        axis=-1,
    )
    if group == "SO3":
        return phi
    if group == "SE3":
        return np.concatenate([X[..., 0:3, 3], phi], axis=-1)
    if group == "Sim3":
        return np.concatenate([X[..., 0:3, 3], phi, -X[..., 3, 3][..., None]], axis=-1)
    parts = [X[..., 0:3, 4], X[..., 0:3, 3], phi]
    if group == "SGal3":
        parts.append(X[..., 3, 4][..., None])
    return np.concatenate(parts, axis=-1)


def basis(group):
    """(dof, n, n): the algebra generators hat(e_j)."""
    _check_group(group)
    return hat(group, np.eye(DOF[group]))


# ----------------------------------------------------------------------------------------
# ad / Ad
# ----------------------------------------------------------------------------------------


def ad(group, xi):
    """(..., dof) -> (..., dof, dof); column j is vee([hat(xi), hat(e_j)])."""
    xi = _check_vec(group, xi)
    X = hat(group, xi)[..., None, :, :]  # (..., 1, n, n)
    E = basis(group)  # (dof, n, n)
    C = X @ E - E @ X  # (..., dof, n, n): commutator with each generator
    cols = vee(group, C)  # (..., dof(col j), dof(row))
    return np.swapaxes(cols, -1, -2)


def inv(M):
    return np.linalg.inv(np.asarray(M, dtype=np.float64))


def Ad_from_matrix(group, M):
    """(..., n, n) group matrix -> (..., dof, dof); column j is vee(M hat(e_j) M^-1)."""
    M = _check_mat(group, M)
    Mi = np.linalg.inv(M)[..., None, :, :]
    E = basis(group)
    cols = vee(group, M[..., None, :, :] @ E @ Mi)
    return np.swapaxes(cols, -1, -2)


# ----------------------------------------------------------------------------------------
# exp / log
# ----------------------------------------------------------------------------------------


def _map_batch(fn, arr, core_ndim, out_core_shape):
    batch = arr.shape[: arr.ndim - core_ndim]
    flat = arr.reshape((-1,) + arr.shape[arr.ndim - core_ndim :])
    out = np.empty((flat.shape[0],) + tuple(out_core_shape))
    for i in range(flat.shape[0]):
        out[i] = fn(flat[i])
    return out.reshape(batch + tuple(out_core_shape))


def expm_hat(group, xi):
    """Group matrix exp(hat(xi)) via scipy.linalg.expm. (..., dof) -> (..., n, n)."""
    xi = _check_vec(group, xi)
    n = MATRIX_SIZE[group]
    return _map_batch(lambda v: scipy.linalg.expm(hat(group, v)), xi, 1, (n, n))


def logm_vee(group, M):
    """vee(Re(logm(M))) via scipy.linalg.logm (principal log). (..., n, n) -> (..., dof)."""
    M = _check_mat(group, M)

    def one(m):
        L = scipy.linalg.logm(m)
        return vee(group, np.real(L))

    return _map_batch(one, M, 2, (DOF[group],))


# ----------------------------------------------------------------------------------------
# Jacobians, float64 series
# ----------------------------------------------------------------------------------------


def _series_f64(A, terms):
    """sum_{n>=0} A^n/(n+1)! in float64; stops when two consecutive terms are below
    1e-17 relative to the running sum, or after `terms` terms."""
    d = A.shape[0]
    S = np.eye(d)
    T = np.eye(d)
    small = 0
    for n in range(1, terms):
        T = (A @ T) / (n + 1)
        S = S + T
        tmax = np.max(np.abs(T))
        if tmax <= 1e-17 * np.max(np.abs(S)):
            small += 1
            if small >= 2:
                break
        else:
            small = 0
    return S


def jl_series(group, xi, terms=400):
    """Left Jacobian sum_n ad(xi)^n/(n+1)! in float64 (at most `terms` terms)."""
    xi = _check_vec(group, xi)
    d = DOF[group]
    return _map_batch(lambda v: _series_f64(ad(group, v), terms), xi, 1, (d, d))


def jr_series(group, xi, terms=400):
    """Right Jacobian J_r(xi) = J_l(-xi) = sum_n (-ad(xi))^n/(n+1)! in float64."""
    xi = _check_vec(group, xi)
    return jl_series(group, -xi, terms=terms)


# ----------------------------------------------------------------------------------------
# random tangents
# ----------------------------------------------------------------------------------------


def random_tangent(group, rng, angle=None, scale=1.0, size=None):
    """Random tangent vector(s) of `group`.

    The non-rotation components (rho, nu, iota) are scale * N(0, 1).  The rotation part
    phi is a uniformly random direction times `angle` (so ||phi|| == angle exactly up to
    rounding) if `angle` is given, else a uniformly random direction times an angle
    drawn uniformly from [0, pi).  `size` (int or tuple) adds a leading batch shape.
    `rng` is a numpy Generator (or an int seed).
    """
    _check_group(group)
    rng = np.random.default_rng(rng)
    shape = () if size is None else ((size,) if np.isscalar(size) else tuple(size))
    d = DOF[group]
    xi = scale * rng.standard_normal(shape + (d,))
    k = ROT_SLICE[group].stop - ROT_SLICE[group].start
    u = rng.standard_normal(shape + (k,))
    u /= np.linalg.norm(u, axis=-1, keepdims=True)  # a random sign when k == 1
    if angle is None:
        a = rng.uniform(0.0, np.pi, size=shape)[..., None]
    else:
        a = np.broadcast_to(np.asarray(angle, dtype=np.float64), shape)[..., None]
    xi[..., ROT_SLICE[group]] = a * u
    return xi


# ----------------------------------------------------------------------------------------
# High precision (mpmath)
# ----------------------------------------------------------------------------------------
#
# Matrices are lists of lists of mpf.  ad(xi) is sparse (at most a few non-zeros per
# row), so the series recursion T <- ad T / (n+1) only touches the non-zeros of ad.


def _mp_vec(xi):
    # mpf(float) is exact: every float64 is a dyadic rational.
    return [mpmath.mpf(float(v)) for v in xi]


def _mp_hat(group, x):
    """x: list of mpf (length dof) -> n x n list-of-lists of mpf."""
    z = mpmath.mpf(0)
    n = MATRIX_SIZE[group]
    X = [[z] * n for _ in range(n)]
    if group in ("SO2", "SE2"):
        X[0][1], X[1][0] = -x[-1], x[-1]
        if group == "SE2":
            X[0][2], X[1][2] = x[0], x[1]
        return X
    if group == "SO3":
        p = x[0:3]
    elif group == "Sim3":
        p = x[3:6]
        for i in range(3):
            X[i][3] = x[i]
        X[3][3] = -x[6]
    elif group == "SE3":
        p = x[3:6]
        for i in range(3):
            X[i][3] = x[i]
    else:
        p = x[6:9]
        for i in range(3):
            X[i][3] = x[3 + i]  # nu in column 4
            X[i][4] = x[i]  # rho in column 5
        if group == "SGal3":
            X[3][4] = x[9]
    X[0][1], X[0][2] = -p[2], p[1]
    X[1][0], X[1][2] = p[2], -p[0]
    X[2][0], X[2][1] = -p[1], p[0]
    return X


def _mp_vee(group, X):
    h = mpmath.mpf(0.5)
    if group in ("SO2", "SE2"):
        t = [h * (X[1][0] - X[0][1])]
        return t if group == "SO2" else [X[0][2], X[1][2]] + t
    phi = [h * (X[2][1] - X[1][2]), h * (X[0][2] - X[2][0]), h * (X[1][0] - X[0][1])]
    if group == "SO3":
        return phi
    if group == "SE3":
        return [X[0][3], X[1][3], X[2][3]] + phi
    if group == "Sim3":
        return [X[0][3], X[1][3], X[2][3]] + phi + [-X[3][3]]
    out = [X[0][4], X[1][4], X[2][4], X[0][3], X[1][3], X[2][3]] + phi
    if group == "SGal3":
        out.append(X[3][4])
    return out


def _mp_matmul(A, B):
    n, m, p = len(A), len(B), len(B[0])
    return [[mpmath.fsum(A[i][k] * B[k][j] for k in range(m)) for j in range(p)] for i in range(n)]


def _mp_ad(group, x):
    """High-precision ad(xi) from the commutator definition, column by column."""
    d = DOF[group]
    X = _mp_hat(group, x)
    cols = []
    one, zero = mpmath.mpf(1), mpmath.mpf(0)
    for j in range(d):
        e = [zero] * d
        e[j] = one
        E = _mp_hat(group, e)
        XE = _mp_matmul(X, E)
        EX = _mp_matmul(E, X)
        C = [[XE[i][k] - EX[i][k] for k in range(len(X))] for i in range(len(X))]
        cols.append(_mp_vee(group, C))
    return [[cols[j][i] for j in range(d)] for i in range(d)]


def _mp_series(A, tol_digits, max_terms, factorial_shift):
    """sum_{n>=0} A^n/(n + factorial_shift)! * (factorial_shift)! ... specifically:
    factorial_shift=1 -> sum A^n/(n+1)!  (Jacobian);  0 -> sum A^n/n!  (expm).

    Stops when two consecutive terms have max abs entry below 10^-tol_digits times the
    max abs entry of the running sum (a term that is exactly zero counts as small; the
    series of a nilpotent A terminates).  Raises if not converged in max_terms terms.
    """
    d = len(A)
    zero, one = mpmath.mpf(0), mpmath.mpf(1)
    sparse_rows = [[(k, a) for k, a in enumerate(row) if a != 0] for row in A]
    T = [[one if i == j else zero for j in range(d)] for i in range(d)]
    S = [row[:] for row in T]
    tol = mpmath.mpf(10) ** (-tol_digits)
    small = 0
    for n in range(1, max_terms + 1):
        div = n + factorial_shift
        T = [
            [mpmath.fsum(a * T[k][j] for k, a in sr) / div if sr else zero for j in range(d)]
            for sr in sparse_rows
        ]
        tmax = zero
        smax = zero
        for i in range(d):
            Ti, Si = T[i], S[i]
            for j in range(d):
                t = Ti[j]
                if t:
                    Si[j] += t
                    at = abs(t)
                    if at > tmax:
                        tmax = at
                as_ = abs(Si[j])
                if as_ > smax:
                    smax = as_
        if tmax <= tol * smax:
            small += 1
            if small >= 2 or tmax == 0:
                return S
        else:
            small = 0
    raise RuntimeError(
        f"mpmath series did not converge in {max_terms} terms "
        f"(last term {mpmath.nstr(tmax, 5)}, sum {mpmath.nstr(smax, 5)})"
    )


def _mp_to_np(M):
    return np.array([[float(v) for v in row] for row in M], dtype=np.float64)


def _mp_batch(fn, group, xi, out_shape):
    xi = _check_vec(group, xi)
    return _map_batch(fn, xi, 1, out_shape)


def _jl_mp_list(group, xi_row, dps, max_terms):
    with mpmath.workdps(dps):
        A = _mp_ad(group, _mp_vec(xi_row))
        return _mp_series(A, dps - 5, max_terms, 1)


def jl_mp(group, xi, dps=50, max_terms=400):
    """Left Jacobian sum_n ad(xi)^n/(n+1)! computed with mpmath at `dps` digits
    (input converted exactly), rounded to a float64 numpy array (..., dof, dof)."""
    d = DOF[group] if group in DOF else None
    return _mp_batch(
        lambda v: _mp_to_np(_jl_mp_list(group, v, dps, max_terms)), group, xi, (d, d)
    )


def jr_mp(group, xi, dps=50, max_terms=400):
    """Right Jacobian J_l(-xi) with mpmath (negation is exact)."""
    xi = _check_vec(group, xi)
    return jl_mp(group, -xi, dps=dps, max_terms=max_terms)


def jl_inv_mp(group, xi, dps=50, max_terms=400):
    """Inverse of the left Jacobian: mpmath matrix inverse of the high-precision J_l."""
    d = DOF[group] if group in DOF else None

    def one(v):
        with mpmath.workdps(dps):
            J = mpmath.matrix(_jl_mp_list(group, v, dps, max_terms))
            Ji = J ** -1
            return np.array(
                [[float(Ji[i, j]) for j in range(d)] for i in range(d)], dtype=np.float64
            )

    return _mp_batch(one, group, xi, (d, d))


def jr_inv_mp(group, xi, dps=50, max_terms=400):
    xi = _check_vec(group, xi)
    return jl_inv_mp(group, -xi, dps=dps, max_terms=max_terms)


def exp_mp(group, xi, dps=50, max_terms=400):
    """Group matrix sum_n hat(xi)^n/n! with mpmath at `dps` digits -> float64 (..., n, n)."""
    n = MATRIX_SIZE[group] if group in MATRIX_SIZE else None

    def one(v):
        with mpmath.workdps(dps):
            X = _mp_hat(group, _mp_vec(v))
            return _mp_to_np(_mp_series(X, dps - 5, max_terms, 0))

    return _mp_batch(one, group, xi, (n, n))


# ----------------------------------------------------------------------------------------
# Error measures
# ----------------------------------------------------------------------------------------

_TINY = np.finfo(np.float64).tiny


def rel_err(a, ref):
    """max|a - ref| / max|ref| (over all entries; the denominator is floored at the
    smallest normal float64, so an all-zero reference gives the absolute error)."""
    a = np.asarray(a, dtype=np.float64)
    ref = np.asarray(ref, dtype=np.float64)
    num = np.max(np.abs(a - ref)) if a.size else 0.0
    den = np.max(np.abs(ref)) if ref.size else 0.0
    return float(num / max(den, _TINY))


BlockErr = namedtuple("BlockErr", ["rel", "zero_abs", "worst_block"])
BlockErr.__doc__ = """Result of blockwise_rel_err.

rel: worst max|a_blk - ref_blk| / max|ref_blk| over the blocks whose reference is not
     identically zero (0.0 if there are none).
zero_abs: worst max|a_blk| over the blocks whose reference is identically zero
     (absolute error; 0.0 if there are none).
worst_block: (row_block, col_block) index of the block giving `rel` (col_block is None
     for vectors), or None.
"""


def blockwise_rel_err(a, ref, blocks, kind=None):
    """Block-by-block relative error over the tangent partition.

    `blocks` is a group name ("SO3", ...) or a list of block sizes (e.g. [3, 3, 3, 1]).
    `kind` is "matrix" (trailing (dof, dof); blocks are 3x3 / 3x1 / 1x3 / 1x1) or
    "vector" (trailing (dof,)); by default 1-D input is a vector, anything else a
    (batch of) matrix.  Leading batch dims: the worst over the batch, per element.
    Returns BlockErr(rel, zero_abs, worst_block).
    """
    sizes = BLOCKS[blocks] if isinstance(blocks, str) else list(blocks)
    a = np.asarray(a, dtype=np.float64)
    ref = np.asarray(ref, dtype=np.float64)
    if a.shape != ref.shape:
        a, ref = np.broadcast_arrays(a, ref)
    if kind is None:
        kind = "vector" if ref.ndim == 1 else "matrix"
    dof = sum(sizes)
    offs = np.concatenate([[0], np.cumsum(sizes)])
    sl = [slice(offs[i], offs[i + 1]) for i in range(len(sizes))]
    if kind == "vector":
        if ref.shape[-1] != dof:
            raise ValueError(f"ref: expected trailing dim {dof}, got {ref.shape}")
        ref = ref.reshape(-1, 1, dof)
        a = a.reshape(-1, 1, dof)
        pairs = [(None, j) for j in range(len(sizes))]
    elif kind == "matrix":
        if ref.shape[-2:] != (dof, dof):
            raise ValueError(f"ref: expected trailing dims ({dof}, {dof}), got {ref.shape}")
        ref = ref.reshape(-1, dof, dof)
        a = a.reshape(-1, dof, dof)
        pairs = [(i, j) for i in range(len(sizes)) for j in range(len(sizes))]
    else:
        raise ValueError(f"kind: expected 'matrix' or 'vector', got {kind!r}")
    worst_rel, worst_zero, worst_blk = 0.0, 0.0, None
    for i, j in pairs:
        rs = slice(0, 1) if i is None else sl[i]
        rb = ref[:, rs, sl[j]]
        ab = a[:, rs, sl[j]]
        err = np.max(np.abs(ab - rb), axis=(1, 2))
        mag = np.max(np.abs(rb), axis=(1, 2))
        nz = mag > 0
        if np.any(nz):
            r = float(np.max(err[nz] / np.maximum(mag[nz], _TINY)))
            if worst_blk is None or r > worst_rel:
                worst_rel = r
                worst_blk = (j, None) if i is None else (i, j)
        if np.any(~nz):
            worst_zero = max(worst_zero, float(np.max(err[~nz])))
    return BlockErr(worst_rel, worst_zero, worst_blk)
