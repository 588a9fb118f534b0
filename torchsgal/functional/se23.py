"""SE_2(3), extended poses: (..., 5, 5) [[C, v, r], [0, 1, 0], [0, 0, 1]], tangent
(..., 9) [rho, nu, phi].  The isochronous subgroup of SGal(3) (iota = 0); Barfoot,
"Integral Forms", Table 1.  Internally vectors are component-first (see blocks).
"""
from __future__ import annotations

import sys

import torch

from . import blocks as B
from . import checks, numerics
from ._autograd import checked_backward_parts, make_exp_log, make_jacobians, make_products
from ._blocking import blocked

NAME = "SE23"
DOF = 9
MATRIX_DIM = 5
SIZES = [3, 3, 3]
PHI = slice(6, 9)


def _split(xi: torch.Tensor):
    X = B.first(xi)
    return X[0:3], X[3:6], X[6:9]


def _components(M: torch.Tensor):
    return M[..., :3, :3], M[..., :3, 3], M[..., :3, 4]


def components(M: torch.Tensor):
    """(C, v, r) in the public layout."""
    checks.matrix(M, MATRIX_DIM, "M")
    return _components(M)


def _matrix(rot, v, r) -> torch.Tensor:
    z = torch.zeros_like(v[0])
    o = torch.ones_like(z)
    return B.homogeneous(rot, [v, r], [[z, z, z, o, z], [z, z, z, z, o]])


def from_components(C, v, r) -> torch.Tensor:
    """C (..., 3, 3), v, r (..., 3), batches broadcast -> (..., 5, 5)."""
    C, v, r = checks.components(C=(C, (3, 3)), v=(v, (3,)), r=(r, (3,)))
    return _matrix(B.entries(C), B.first(v), B.first(r))


def hat(xi: torch.Tensor) -> torch.Tensor:
    checks.vector(xi, DOF, "xi")
    rho, nu, (x, y, z) = _split(xi)
    o = torch.zeros_like(x)
    rot = (o, -z, y, z, o, -x, -y, x, o)
    return B.homogeneous(rot, [nu, rho], [[o] * 5, [o] * 5])


def vee(X: torch.Tensor) -> torch.Tensor:
    checks.matrix(X, MATRIX_DIM, "X")
    return B.last(B.first(X[..., :3, 4]), B.first(X[..., :3, 3]), B.unskew(X[..., :3, :3]))


def exp_impl(xi: torch.Tensor) -> torch.Tensor:
    checks.vector(xi, DOF, "xi")
    rho, nu, phi = _split(xi)
    c = B.coefficients(phi, 3)
    return _matrix(B.gamma_entries(c, 0, phi), B.gamma_vec(c, 1, phi, nu), B.gamma_vec(c, 1, phi, rho))


def log_impl(M: torch.Tensor) -> torch.Tensor:
    checks.matrix(M, MATRIX_DIM, "M")
    phi = B.rotation_log(M[..., :3, :3])
    d = numerics.jinv_coefficient(B.theta_squared(phi))
    rho = B.jac_inv_vec(phi, B.first(M[..., :3, 4]), d)
    nu = B.jac_inv_vec(phi, B.first(M[..., :3, 3]), d)
    return B.last(rho, nu, phi)


@blocked(2)
def inverse_impl(M: torch.Tensor) -> torch.Tensor:
    checks.matrix(M, MATRIX_DIM, "M")
    Ct = B.transpose_entries(M[..., :3, :3])
    v, r = B.first(M[..., :3, 3]), B.first(M[..., :3, 4])
    return _matrix(Ct, -B.matvec_entries(Ct, v), -B.matvec_entries(Ct, r))


@blocked(2)
def adjoint_impl(M: torch.Tensor) -> torch.Tensor:
    """[[C, 0, r^ C], [0, C, v^ C], [0, 0, C]]."""
    checks.matrix(M, MATRIX_DIM, "M")
    C, v, r = _components(M)
    return B.block_matrix(
        [[C, None, B.skew_times(r, C)], [None, C, B.skew_times(v, C)], [None, None, C]],
        SIZES, M.shape[:-2], M,
    )


def ad(xi: torch.Tensor) -> torch.Tensor:
    """[[phi^, 0, rho^], [0, phi^, nu^], [0, 0, phi^]]."""
    checks.vector(xi, DOF, "xi")
    rho, nu, phi = _split(xi)
    P = B.skew(phi)
    return B.block_matrix(
        [[P, None, B.skew(rho)], [None, P, B.skew(nu)], [None, None, P]], SIZES, xi.shape[:-1], xi
    )


def _jl_blocks(xi: torch.Tensor):
    rho, nu, phi = _split(xi)
    c = B.coefficients(phi, 5)
    J = B.gamma_mat(c, 1, phi)
    return J, B.q_block(c, phi, rho, J), B.q_block(c, phi, nu, J)


@blocked(1)
def jl_impl(xi: torch.Tensor) -> torch.Tensor:
    checks.vector(xi, DOF, "xi")
    J, Q_rho, Q_nu = _jl_blocks(xi)
    return B.block_matrix(
        [[J, None, Q_rho], [None, J, Q_nu], [None, None, J]], SIZES, xi.shape[:-1], xi
    )


@blocked(1)
def jl_inv_impl(xi: torch.Tensor) -> torch.Tensor:
    checks.vector(xi, DOF, "xi")
    _, Q_rho, Q_nu = _jl_blocks(xi)
    Ji = B.jac_inv_mat(_split(xi)[2])
    return B.block_matrix(
        [[Ji, None, -Ji @ Q_rho @ Ji], [None, Ji, -Ji @ Q_nu @ Ji], [None, None, Ji]],
        SIZES, xi.shape[:-1], xi,
    )


def _jl_tmv(xi: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """J_l(xi)^T w with vector operations only: Q^T a = gvdt(1, x, a) + J^T (a x Gamma_1 x)."""
    xi, w = B.same_rank((xi, 1), (w, 1))
    rho, nu, phi = _split(xi)
    w_rho, w_nu, w_phi = _split(w)
    c = B.coefficients(phi, 5)
    S = B.gamma_vec_derivative_t(c, 1, phi, rho, w_rho) + B.gamma_vec_derivative_t(c, 1, phi, nu, w_nu)
    z = B.cross(w_rho, B.gamma_vec(c, 1, phi, rho)) + B.cross(w_nu, B.gamma_vec(c, 1, phi, nu))
    o_phi = S + B.gamma_vec(c, 1, -phi, z + w_phi)
    return B.last(B.gamma_vec(c, 1, -phi, w_rho), B.gamma_vec(c, 1, -phi, w_nu), o_phi)


def _jl_inv_tmv(xi: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """J_l(xi)^-T g by forward substitution on the transposed blocks."""
    xi, g = B.same_rank((xi, 1), (g, 1))
    rho, nu, phi = _split(xi)
    g_rho, g_nu, g_phi = _split(g)
    c = B.coefficients(phi, 5)
    d = numerics.jinv_coefficient(B.theta_squared(phi))
    y_rho = B.jac_inv_vec(-phi, g_rho, d)
    y_nu = B.jac_inv_vec(-phi, g_nu, d)
    S = B.gamma_vec_derivative_t(c, 1, phi, rho, y_rho) + B.gamma_vec_derivative_t(c, 1, phi, nu, y_nu)
    z = B.cross(y_rho, B.gamma_vec(c, 1, phi, rho)) + B.cross(y_nu, B.gamma_vec(c, 1, phi, nu))
    return B.last(y_rho, y_nu, B.jac_inv_vec(-phi, g_phi - S, d) - z)


def _exp_pullback(M: torch.Tensor, G: torch.Tensor) -> torch.Tensor:
    """hat^T(M^T G) (exp's backward)."""
    Ct = B.transpose_entries(M[..., :3, :3])
    return B.last(B.matvec_entries(Ct, B.first(G[..., :3, 4])),
                  B.matvec_entries(Ct, B.first(G[..., :3, 3])),
                  B.rotation_pullback(M[..., :3, :3], G))


def _log_pullback(M: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """M^-T vee^T(w) (log's backward); M^-T = [[C, 0, 0], [a^T, 1, 0], [b^T, 0, 1]] with
    a = -C^T v, b = -C^T r."""
    rho, nu, phi = _split(w)
    half = 0.5 * phi
    C = M[..., :3, :3]
    Ce, Ct = B.entries(C), B.transpose_entries(C)
    a = -B.matvec_entries(Ct, B.first(M[..., :3, 3]))
    b = -B.matvec_entries(Ct, B.first(M[..., :3, 4]))
    rot = [x for row in B.rotation_skew_rows(C, half) for x in row]
    ah, bh = B.cross(a, half), B.cross(b, half)
    bottom = [[ah[0], ah[1], ah[2], B.dot(a, nu), B.dot(a, rho)],
              [bh[0], bh[1], bh[2], B.dot(b, nu), B.dot(b, rho)]]
    return B.homogeneous(rot, [B.matvec_entries(Ce, nu), B.matvec_entries(Ce, rho)], bottom)


def jr(xi: torch.Tensor) -> torch.Tensor:
    """J_r(xi) = J_l(-xi)."""
    checks.vector(xi, DOF, "xi")
    return jl(-xi)


def jr_inv(xi: torch.Tensor) -> torch.Tensor:
    """J_r(xi)^-1 = J_l(-xi)^-1."""
    checks.vector(xi, DOF, "xi")
    return jl_inv(-xi)


def act(M: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Points [p, 0, 1] -> C p + r."""
    return B.act_homogeneous(M, p, "p", MATRIX_DIM, (0.0, 1.0))


def act_jacobian(M: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """d act(M exp(xi^), p) / d xi at 0 (..., 3, DOF), the right perturbation."""
    return B.act_homogeneous_jacobian(M, p, "p", MATRIX_DIM, hat, DOF, (0.0, 1.0))


def act_velocity(M: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Velocities [u, 1, 0] -> C u + v."""
    return B.act_homogeneous(M, u, "u", MATRIX_DIM, (1.0,))


def act_direction(M: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """Directions [d, 0, 0] -> C d."""
    return B.act_homogeneous(M, d, "d", MATRIX_DIM)


def random(batch_shape, dtype, device, generator=None) -> torch.Tensor:
    """A uniform rotation, standard normal velocity and position; batch_shape an int or a sequence."""
    batch_shape = checks.shape(batch_shape, "batch_shape")
    checks.dtype_arg(dtype)
    C = B.random_rotation(batch_shape, dtype, device, generator)
    v, r = torch.randn(2, 3, *batch_shape, dtype=dtype, device=device, generator=generator)
    return _matrix(B.entries(C), v, r)


exp, log = make_exp_log(sys.modules[__name__])
jl, jl_inv = make_jacobians(sys.modules[__name__])
compose, adjoint, inverse = make_products(sys.modules[__name__])
jl_tmv, jl_inv_tmv, exp_pullback, log_pullback = checked_backward_parts(sys.modules[__name__])
