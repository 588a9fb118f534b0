"""Sim(3) on plain tensors: (..., 4, 4) [[C, r], [0, 1/s]], tangent (..., 7) [rho, phi, lambda].

Convention (Barfoot, "Integral Forms", Sec. 4.4, (78)-(80); the same as GTSAM's Similarity3):

    hat(xi) = [[phi^, rho], [0, -lambda]],   exp(hat(xi)) = [[C(phi), M(phi, lambda) rho], [0, 1/s]],

with scale s = exp(lambda) (the matrix stores 1/s = exp(-lambda)) and

    M(phi, lambda) = int_0^1 exp(-(1 - a) lambda) C(a phi) da = m0 I + m1 phi^ + m2 phi^ phi^   (90).

A point p acts as the homogeneous [p, 1]:  p -> s (C p + r)  (= (C p + r) / M[3, 3]).  A
direction [d, 0] is rotated only: d -> C d.

    Ad = [[s C, s r^ C, -s r], [0, C, 0], [0, 0, 1]],   ad(xi) = [[phi^ + lambda I, rho^, -rho],
                                                                   [0, phi^, 0], [0, 0, 0]]  (80),
    J_l = int_0^1 Ad(exp(a xi)) da = [[s M, s (d(M rho)/dphi + r^ Gamma_1), s dM/dlambda rho],
                                      [0, Gamma_1, 0], [0, 0, 1]]

(docs/guide/sim3_jacobian.md derives J_l from exp(J_l d) exp(xi) = exp(xi + d); the scalar
coefficients m_k, their theta- and lambda-derivatives come from ``numerics.sim3_coefficients``).
The Jacobians take them normalised, so that s M stays finite where s underflows and M overflows
(lambda -> -inf); the range of lambda each function covers is in ``torchsgal.Sim3``'s docstring.
"""
from __future__ import annotations

import sys

import torch

from . import blocks as B
from . import checks, numerics
from ._autograd import checked_backward_parts, make_exp_log, make_jacobians, make_products
from ._blocking import blocked

NAME = "Sim3"
DOF = 7
MATRIX_DIM = 4
SIZES = [3, 3, 1]
PHI = slice(3, 6)
SCALE = slice(6, 7)  # lambda, the log of the scale


def _split(xi: torch.Tensor):
    X = B.first(xi)
    return X[0:3], X[3:6], X[6]


def _components(M: torch.Tensor):
    return M[..., :3, :3], M[..., :3, 3], 1.0 / M[..., 3, 3]


def components(M: torch.Tensor):
    """(C, r, s) in the public layout; s = 1 / M[3, 3]."""
    checks.matrix(M, MATRIX_DIM, "M")
    return _components(M)


def _matrix(rot, r, inv_s) -> torch.Tensor:
    z = torch.zeros_like(inv_s)
    return B.homogeneous(rot, [r], [[z, z, z, inv_s]])


def from_components(C, r, s) -> torch.Tensor:
    """C (..., 3, 3), r (..., 3), scale s (...) (positive; not checked), batches broadcast
    -> (..., 4, 4)."""
    C, r, s = checks.components(C=(C, (3, 3)), r=(r, (3,)), s=(s, ()))
    return _matrix(B.entries(C), B.first(r), 1.0 / s)


def hat(xi: torch.Tensor) -> torch.Tensor:
    checks.vector(xi, DOF, "xi")
    rho, (x, y, z), lam = _split(xi)
    o = torch.zeros_like(x)
    return B.homogeneous((o, -z, y, z, o, -x, -y, x, o), [rho], [[o, o, o, -lam]])


def vee(X: torch.Tensor) -> torch.Tensor:
    checks.matrix(X, MATRIX_DIM, "X")
    return B.last(B.first(X[..., :3, 3]), B.unskew(X[..., :3, :3]), -X[..., 3, 3][None])


def _coefficients(phi: torch.Tensor, lam: torch.Tensor, derivatives: bool = True, normalise: bool = False):
    return numerics.sim3_coefficients(B.theta_squared(phi), lam, derivatives, normalise)


def exp_impl(xi: torch.Tensor) -> torch.Tensor:
    checks.vector(xi, DOF, "xi")
    rho, phi, lam = _split(xi)
    c = B.coefficients(phi, 2)
    m = _coefficients(phi, lam, derivatives=False)
    r = B.poly_vec(m["m0"], m["m1"], m["m2"], phi, rho)
    return _matrix(B.gamma_entries(c, 0, phi), r, torch.exp(-lam))


def _m_inverse(m: dict[str, torch.Tensor], phi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(n0, n1, n2): M(phi, lambda)^-1 = n0 I + n1 phi^ + n2 phi^ phi^."""
    return B.poly_inverse(m["m0"], m["m1"], m["m2"], B.theta_squared(phi), m["m_re"])


def _m_inverse_vec(m, phi, x):
    """M(phi, lambda)^-1 x."""
    return B.poly_vec(*_m_inverse(m, phi), phi, x)


def log_impl(M: torch.Tensor) -> torch.Tensor:
    checks.matrix(M, MATRIX_DIM, "M")
    phi = B.rotation_log(M[..., :3, :3])
    lam = -torch.log(M[..., 3, 3])
    rho = _m_inverse_vec(_coefficients(phi, lam, derivatives=False), phi, B.first(M[..., :3, 3]))
    return B.last(rho, phi, lam[None])


@blocked(2)
def inverse(M: torch.Tensor) -> torch.Tensor:
    """[[C^T, -s C^T r], [0, s]]."""
    checks.matrix(M, MATRIX_DIM, "M")
    Ct = B.transpose_entries(M[..., :3, :3])
    s = 1.0 / M[..., 3, 3]
    return _matrix(Ct, -s * B.matvec_entries(Ct, B.first(M[..., :3, 3])), s)


@blocked(2)
def adjoint(M: torch.Tensor) -> torch.Tensor:
    """[[s C, s r^ C, -s r], [0, C, 0], [0, 0, 1]]  (80)."""
    checks.matrix(M, MATRIX_DIM, "M")
    C, r, s = _components(M)
    sC = s[..., None, None] * C
    col = -(s[..., None] * r).unsqueeze(-1)
    one = torch.ones_like(s)[..., None, None]
    return B.block_matrix(
        [[sC, B.skew_times(r, sC), col], [None, C, None], [None, None, one]],
        SIZES, M.shape[:-2], M,
    )


def ad(xi: torch.Tensor) -> torch.Tensor:
    """[[phi^ + lambda I, rho^, -rho], [0, phi^, 0], [0, 0, 0]]."""
    checks.vector(xi, DOF, "xi")
    rho, phi, lam = _split(xi)
    P = B.skew(phi)
    A = P + lam[..., None, None] * B.eye(3, xi)
    return B.block_matrix(
        [[A, B.skew(rho), -B.column(rho)], [None, P, None], [None, None, None]],
        SIZES, xi.shape[:-1], xi,
    )


def _scale(lam, m, power: float = 1.0):
    """(s e^-shift)^power.  With the normalised coefficients m (e^shift times M's, from
    numerics.sim3_coefficients) s M = _scale M^ stays finite where s underflows and M overflows
    (lambda -> -inf).  power = -1 for 1/s: as exp, not 1/exp, whose gradient is 0 * inf where s
    overflows (lambda -> +inf)."""
    return torch.exp(power * (lam - m["shift"]))


def _jl_parts(xi: torch.Tensor):
    """(m, lambda, phi, Gamma_1, coupling, lam_col): J_l = [[s M, s coupling, s lam_col],
    [0, Gamma_1, 0], [0, 0, 1]] with coupling = d(M rho)/dphi + r^ Gamma_1, r = M rho, and
    lam_col = dM/dlambda rho (docs/guide/sim3_jacobian.md).  m, coupling and lam_col are normalised,
    so s is ``_scale(lambda, m)`` (the products are the same)."""
    rho, phi, lam = _split(xi)
    c = B.coefficients(phi, 3)
    m = _coefficients(phi, lam, normalise=True)
    G1 = B.gamma_mat(c, 1, phi)
    r = B.poly_vec(m["m0"], m["m1"], m["m2"], phi, rho)
    coupling = B.poly_vec_derivative(m["m1"], m["m2"], m["e1"], m["e2"], phi, rho) + B.skew_times(r.movedim(0, -1), G1)
    lam_col = B.poly_vec(m["p0"], m["p1"], m["p2"], phi, rho)
    return m, lam, phi, G1, coupling, lam_col


@blocked(1)
def jl_impl(xi: torch.Tensor) -> torch.Tensor:
    checks.vector(xi, DOF, "xi")
    m, lam, phi, G1, coupling, lam_col = _jl_parts(xi)
    s = _scale(lam, m)
    s2 = s[..., None, None]
    one = torch.ones_like(s)[..., None, None]
    Mmat = B.poly_mat(m["m0"], m["m1"], m["m2"], phi)
    return B.block_matrix(
        [[s2 * Mmat, s2 * coupling, s2 * B.column(lam_col)], [None, G1, None], [None, None, one]],
        SIZES, xi.shape[:-1], xi,
    )


@blocked(1)
def jl_inv_impl(xi: torch.Tensor) -> torch.Tensor:
    """[[M^-1 / s, -M^-1 coupling Gamma_1^-1, -M^-1 lam_col], [0, Gamma_1^-1, 0], [0, 0, 1]]."""
    checks.vector(xi, DOF, "xi")
    m, lam, phi, _, coupling, lam_col = _jl_parts(xi)
    inv_s = _scale(lam, m, -1.0)
    n0, n1, n2 = _m_inverse(m, phi)
    Minv = B.poly_mat(n0, n1, n2, phi)
    G1inv = B.jac_inv_mat(phi)
    one = torch.ones_like(inv_s)[..., None, None]
    return B.block_matrix(
        [
            [Minv * inv_s[..., None, None], -Minv @ coupling @ G1inv, -B.column(B.poly_vec(n0, n1, n2, phi, lam_col))],
            [None, G1inv, None],
            [None, None, one],
        ],
        SIZES, xi.shape[:-1], xi,
    )


@blocked(1)
def jr(xi: torch.Tensor) -> torch.Tensor:
    """J_r(xi) = J_l(-xi)."""
    checks.vector(xi, DOF, "xi")
    return jl(-xi)


@blocked(1)
def jr_inv(xi: torch.Tensor) -> torch.Tensor:
    """J_r(xi)^-1 = J_l(-xi)^-1."""
    checks.vector(xi, DOF, "xi")
    return jl_inv(-xi)


def _tmv_parts(xi: torch.Tensor):
    rho, phi, lam = _split(xi)
    c = B.coefficients(phi, 3)
    m = _coefficients(phi, lam, normalise=True)
    r = B.poly_vec(m["m0"], m["m1"], m["m2"], phi, rho)
    lam_col = B.poly_vec(m["p0"], m["p1"], m["p2"], phi, rho)
    return rho, phi, lam, c, m, r, lam_col


def _coupling_t(c, m, phi, rho, r, w):
    """coupling^T w = (d(M rho)/dphi)^T w + Gamma_1^T (w x r)."""
    return B.poly_vec_derivative_t(m["m1"], m["m2"], m["e1"], m["e2"], phi, rho, w) + B.gamma_vec(
        c, 1, -phi, B.cross(w, r)
    )


def _jl_tmv(xi: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """J_l(xi)^T w with vector operations only:
    (s M^T w_rho, s coupling^T w_rho + Gamma_1^T w_phi, s lam_col . w_rho + w_lambda)."""
    xi, w = B.same_rank((xi, 1), (w, 1))
    rho, phi, lam, c, m, r, lam_col = _tmv_parts(xi)
    s = _scale(lam, m)
    w_rho, w_phi, w_lam = _split(w)
    out_rho = s * B.poly_vec(m["m0"], m["m1"], m["m2"], -phi, w_rho)
    out_phi = s * _coupling_t(c, m, phi, rho, r, w_rho) + B.gamma_vec(c, 1, -phi, w_phi)
    return B.last(out_rho, out_phi, (s * B.dot(lam_col, w_rho) + w_lam)[None])


def _jl_inv_tmv(xi: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """J_l(xi)^-T g by substitution on the transposed blocks: with y = M^-T g_rho,
    (y / s, Gamma_1^-T (g_phi - coupling^T y), g_lambda - lam_col . y)."""
    xi, g = B.same_rank((xi, 1), (g, 1))
    rho, phi, lam, c, m, r, lam_col = _tmv_parts(xi)
    g_rho, g_phi, g_lam = _split(g)
    n = _m_inverse(m, phi)
    y = B.poly_vec(*n, -phi, g_rho)
    out_phi = B.jac_inv_vec(-phi, g_phi - _coupling_t(c, m, phi, rho, r, y))
    return B.last(y * _scale(lam, m, -1.0), out_phi, (g_lam - B.dot(lam_col, y))[None])


def _exp_pullback(M: torch.Tensor, G: torch.Tensor) -> torch.Tensor:
    """hat^T(M^T G) (exp's backward).  With A = M^T G: (A[:3, 3], 2 unskew(A[:3, :3]), -A[3, 3]),
    A[:3, :] = C^T G[:3, :] and A[3, 3] = r . G[:3, 3] + M[3, 3] G[3, 3]."""
    C = M[..., :3, :3]
    g = B.first(G[..., :3, 3])
    lam = -(B.dot(B.first(M[..., :3, 3]), g) + M[..., 3, 3] * G[..., 3, 3])
    return B.last(B.matvec_entries(B.transpose_entries(C), g), B.rotation_pullback(C, G), lam[None])


def _log_pullback(M: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """M^-T vee^T(w) = M^-T hat(w_rho, w_phi / 2, w_lambda); M^-T = [[C, 0], [b^T, s]] with
    b = -s C^T r, so the product is [[C h^, C w_rho], [(b x h)^T, b . w_rho - s w_lambda]], h = w_phi/2."""
    rho, phi, lam = _split(w)
    half = 0.5 * phi
    C = M[..., :3, :3]
    s = 1.0 / M[..., 3, 3]
    b = -s * B.matvec_entries(B.transpose_entries(C), B.first(M[..., :3, 3]))
    rot = [x for row in B.rotation_skew_rows(C, half) for x in row]
    bh = B.cross(b, half)
    return B.homogeneous(
        rot, [B.matvec_entries(B.entries(C), rho)], [[bh[0], bh[1], bh[2], B.dot(b, rho) - s * lam]]
    )


def act(M: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Points [p, 1] -> s (C p + r) = (C p + r) / M[3, 3]."""
    return B.act_homogeneous(M, p, "p", MATRIX_DIM, (1.0,)) / M[..., 3, 3].unsqueeze(-1)


def act_jacobian(M: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """d act(M exp(xi^), p) / d xi at 0 (..., 3, DOF), the right perturbation: [sC, -sC p^, sC p]
    for xi = [rho, phi, lambda].  By the quotient rule on y = u / w, u = (M [p, 1])[:3] and
    w = M[3, 3] (du and dw the first three rows and the fourth of d(M exp(xi^) [p, 1])), with
    M's translation r set to zero: the Jacobian does not depend on r, and the quotient rule on
    M itself would subtract terms of size s |r| that cancel (precision lost as |r| / |p|)."""
    checks.matrix(M, MATRIX_DIM, "g")
    M0 = torch.cat([M[..., :, :3], torch.cat([torch.zeros_like(M[..., :3, 3:]), M[..., 3:, 3:]],
                                             dim=-2)], dim=-1)
    J = B.act_homogeneous_jacobian(M0, p, "p", MATRIX_DIM, hat, DOF, (1.0,), rows=4, size=3)
    w = M[..., 3, 3, None, None]
    return (J[..., :3, :] - act(M0, p).unsqueeze(-1) * J[..., 3:, :]) / w


def act_direction(M: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """Directions [d, 0] -> C d (rotated, not scaled)."""
    return B.act_homogeneous(M, d, "d", MATRIX_DIM)


def random(batch_shape, dtype, device, generator=None) -> torch.Tensor:
    """Uniform rotation, standard normal translation, log-scale lambda standard normal;
    batch_shape an int or a sequence."""
    batch_shape = checks.shape(batch_shape, "batch_shape")
    checks.dtype_arg(dtype)
    C = B.random_rotation(batch_shape, dtype, device, generator)
    r = torch.randn(3, *batch_shape, dtype=dtype, device=device, generator=generator)
    lam = torch.randn(tuple(batch_shape), dtype=dtype, device=device, generator=generator)
    return _matrix(B.entries(C), r, torch.exp(-lam))


# The tensor code of the operators torchsgal::sim3_inverse and sim3_adjoint (ops.py).
inverse_impl, adjoint_impl = inverse, adjoint

exp, log = make_exp_log(sys.modules[__name__])
jl, jl_inv = make_jacobians(sys.modules[__name__])
compose, adjoint, inverse = make_products(sys.modules[__name__])
jl_tmv, jl_inv_tmv, exp_pullback, log_pullback = checked_backward_parts(sys.modules[__name__])
