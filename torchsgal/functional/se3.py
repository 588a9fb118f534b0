"""SE(3) on plain tensors: (..., 4, 4) [[C, r], [0, 1]], tangent (..., 6) [rho, phi].

Barfoot, "Integral Forms", Table 1: exp r = Gamma_1 rho, J_l = [[J, Q], [0, J]].
Internally vectors are component-first (see blocks).
"""
from __future__ import annotations

import sys

import torch

from . import blocks as B
from . import checks, numerics
from ._autograd import checked_backward_parts, make_exp_log, make_jacobians, make_products
from ._blocking import blocked

NAME = "SE3"
DOF = 6
MATRIX_DIM = 4
SIZES = [3, 3]
PHI = slice(3, 6)


def _split(xi: torch.Tensor):
    X = B.first(xi)
    return X[0:3], X[3:6]


def _components(M: torch.Tensor):
    return M[..., :3, :3], M[..., :3, 3]


def components(M: torch.Tensor):
    """(C, r) in the public layout."""
    checks.matrix(M, MATRIX_DIM, "M")
    return _components(M)


def _matrix(rot, r) -> torch.Tensor:
    z = torch.zeros_like(r[0])
    return B.homogeneous(rot, [r], [[z, z, z, torch.ones_like(z)]])


def from_components(C, r) -> torch.Tensor:
    """C (..., 3, 3), r (..., 3), batches broadcast -> (..., 4, 4)."""
    C, r = checks.components(C=(C, (3, 3)), r=(r, (3,)))
    return _matrix(B.entries(C), B.first(r))


def hat(xi: torch.Tensor) -> torch.Tensor:
    checks.vector(xi, DOF, "xi")
    rho, (x, y, z) = _split(xi)
    o = torch.zeros_like(x)
    return B.homogeneous((o, -z, y, z, o, -x, -y, x, o), [rho], [[o] * 4])


def vee(X: torch.Tensor) -> torch.Tensor:
    checks.matrix(X, MATRIX_DIM, "X")
    return B.last(B.first(X[..., :3, 3]), B.unskew(X[..., :3, :3]))


def exp_impl(xi: torch.Tensor) -> torch.Tensor:
    checks.vector(xi, DOF, "xi")
    rho, phi = _split(xi)
    c = B.coefficients(phi, 3)
    return _matrix(B.gamma_entries(c, 0, phi), B.gamma_vec(c, 1, phi, rho))


def log_impl(M: torch.Tensor) -> torch.Tensor:
    checks.matrix(M, MATRIX_DIM, "M")
    phi = B.rotation_log(M[..., :3, :3])
    return B.last(B.jac_inv_vec(phi, B.first(M[..., :3, 3])), phi)


@blocked(2)
def inverse_impl(M: torch.Tensor) -> torch.Tensor:
    checks.matrix(M, MATRIX_DIM, "M")
    Ct = B.transpose_entries(M[..., :3, :3])
    return _matrix(Ct, -B.matvec_entries(Ct, B.first(M[..., :3, 3])))


@blocked(2)
def adjoint_impl(M: torch.Tensor) -> torch.Tensor:
    """[[C, r^ C], [0, C]]."""
    checks.matrix(M, MATRIX_DIM, "M")
    C, r = _components(M)
    return B.block_matrix([[C, B.skew_times(r, C)], [None, C]], SIZES, M.shape[:-2], M)


def ad(xi: torch.Tensor) -> torch.Tensor:
    """[[phi^, rho^], [0, phi^]]."""
    checks.vector(xi, DOF, "xi")
    rho, phi = _split(xi)
    P = B.skew(phi)
    return B.block_matrix([[P, B.skew(rho)], [None, P]], SIZES, xi.shape[:-1], xi)


def _jl_blocks(xi: torch.Tensor):
    rho, phi = _split(xi)
    c = B.coefficients(phi, 5)
    J = B.gamma_mat(c, 1, phi)
    return J, B.q_block(c, phi, rho, J)


@blocked(1)
def jl_impl(xi: torch.Tensor) -> torch.Tensor:
    checks.vector(xi, DOF, "xi")
    J, Q = _jl_blocks(xi)
    return B.block_matrix([[J, Q], [None, J]], SIZES, xi.shape[:-1], xi)


@blocked(1)
def jl_inv_impl(xi: torch.Tensor) -> torch.Tensor:
    """[[J^-1, -J^-1 Q J^-1], [0, J^-1]]."""
    checks.vector(xi, DOF, "xi")
    _, Q = _jl_blocks(xi)
    Ji = B.jac_inv_mat(_split(xi)[1])
    return B.block_matrix([[Ji, -Ji @ Q @ Ji], [None, Ji]], SIZES, xi.shape[:-1], xi)


def _jl_tmv(xi: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """J_l(xi)^T w with vector operations only: (J^T w_rho, Q^T w_rho + J^T w_phi)."""
    xi, w = B.same_rank((xi, 1), (w, 1))
    rho, phi = _split(xi)
    w_rho, w_phi = _split(w)
    c = B.coefficients(phi, 5)
    z = B.cross(w_rho, B.gamma_vec(c, 1, phi, rho))
    o_phi = B.gamma_vec_derivative_t(c, 1, phi, rho, w_rho) + B.gamma_vec(c, 1, -phi, z + w_phi)
    return B.last(B.gamma_vec(c, 1, -phi, w_rho), o_phi)


def _jl_inv_tmv(xi: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """J_l(xi)^-T g by forward substitution on the transposed blocks."""
    xi, g = B.same_rank((xi, 1), (g, 1))
    rho, phi = _split(xi)
    g_rho, g_phi = _split(g)
    c = B.coefficients(phi, 5)
    d = numerics.jinv_coefficient(B.theta_squared(phi))
    y_rho = B.jac_inv_vec(-phi, g_rho, d)
    S = B.gamma_vec_derivative_t(c, 1, phi, rho, y_rho)
    z = B.cross(y_rho, B.gamma_vec(c, 1, phi, rho))
    return B.last(y_rho, B.jac_inv_vec(-phi, g_phi - S, d) - z)


def _exp_pullback(M: torch.Tensor, G: torch.Tensor) -> torch.Tensor:
    """hat^T(M^T G) (exp's backward)."""
    Ct = B.transpose_entries(M[..., :3, :3])
    return B.last(B.matvec_entries(Ct, B.first(G[..., :3, 3])), B.rotation_pullback(M[..., :3, :3], G))


def _log_pullback(M: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """M^-T vee^T(w) (log's backward); M^-T = [[C, 0], [b^T, 1]] with b = -C^T r."""
    rho, phi = _split(w)
    half = 0.5 * phi
    C = M[..., :3, :3]
    b = -B.matvec_entries(B.transpose_entries(C), B.first(M[..., :3, 3]))
    rot = [x for row in B.rotation_skew_rows(C, half) for x in row]
    bh = B.cross(b, half)
    return B.homogeneous(rot, [B.matvec_entries(B.entries(C), rho)], [[bh[0], bh[1], bh[2], B.dot(b, rho)]])


def jr(xi: torch.Tensor) -> torch.Tensor:
    """J_r(xi) = J_l(-xi)."""
    checks.vector(xi, DOF, "xi")
    return jl(-xi)


def jr_inv(xi: torch.Tensor) -> torch.Tensor:
    """J_r(xi)^-1 = J_l(-xi)^-1."""
    checks.vector(xi, DOF, "xi")
    return jl_inv(-xi)


def act(M: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Points [p, 1] -> C p + r."""
    return B.act_homogeneous(M, p, "p", MATRIX_DIM, (1.0,))


def act_jacobian(M: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """d act(M exp(xi^), p) / d xi at 0 (..., 3, DOF), the right perturbation."""
    return B.act_homogeneous_jacobian(M, p, "p", MATRIX_DIM, hat, DOF, (1.0,))


def act_direction(M: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """Directions [d, 0] -> C d."""
    return B.act_homogeneous(M, d, "d", MATRIX_DIM)


def random(batch_shape, dtype, device, generator=None) -> torch.Tensor:
    """A uniform rotation and a standard normal translation; batch_shape an int or a sequence."""
    batch_shape = checks.shape(batch_shape, "batch_shape")
    checks.dtype_arg(dtype)
    C = B.random_rotation(batch_shape, dtype, device, generator)
    r = torch.randn(3, *batch_shape, dtype=dtype, device=device, generator=generator)
    return _matrix(B.entries(C), r)


exp, log = make_exp_log(sys.modules[__name__])
jl, jl_inv = make_jacobians(sys.modules[__name__])
compose, adjoint, inverse = make_products(sys.modules[__name__])
jl_tmv, jl_inv_tmv, exp_pullback, log_pullback = checked_backward_parts(sys.modules[__name__])
