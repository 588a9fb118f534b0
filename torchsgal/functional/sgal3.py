"""SGal(3), the special Galilean group, on plain tensors.

Matrices (..., 5, 5) [[C, v, r], [0, 1, tau], [0, 0, 1]]; tangent (..., 10) [rho, nu, phi, iota].
Equation numbers refer to Kelly and Giamou, "Uncertainty in space, time, and motion on the
special Galilean group" (kelly-giamou-uncertainty-sgal3.txt).  Internally vectors are
component-first (see blocks).
"""
from __future__ import annotations

import sys

import torch

from . import blocks as B
from . import checks
from . import numerics
from ._autograd import make_exp_log

NAME = "SGal3"
DOF = 10
MATRIX_DIM = 5
SIZES = [3, 3, 3, 1]
PHI = slice(6, 9)


def _split(xi: torch.Tensor):
    """(..., 10) -> rho, nu, phi (3, ...) and iota (...)."""
    X = B.first(xi)
    return X[0:3], X[3:6], X[6:9], X[9]


def components(M: torch.Tensor):
    """(C, v, r, tau) of a group matrix in the public layout; tau has shape (..., 1)."""
    return M[..., :3, :3], M[..., :3, 3], M[..., :3, 4], M[..., 3, 4:5]


def _matrix(rot, v, r, tau) -> torch.Tensor:
    z, o = torch.zeros_like(tau), torch.ones_like(tau)
    return B.homogeneous(rot, [v, r], [[z, z, z, o, tau], [z, z, z, z, o]])


def from_components(C, v, r, tau) -> torch.Tensor:
    """C (..., 3, 3), v, r (..., 3), tau (..., 1) -> (..., 5, 5)."""
    return _matrix(B.entries(C), B.first(v), B.first(r), tau[..., 0])


def hat(xi: torch.Tensor) -> torch.Tensor:
    """(3.4): [[phi^, nu, rho], [0, 0, iota], [0, 0, 0]]."""
    checks.vector(xi, DOF, "xi")
    rho, nu, (x, y, z), iota = _split(xi)
    o = torch.zeros_like(iota)
    rot = (o, -z, y, z, o, -x, -y, x, o)
    return B.homogeneous(rot, [nu, rho], [[o, o, o, o, iota], [o, o, o, o, o]])


def vee(X: torch.Tensor) -> torch.Tensor:
    """Inverse of ``hat``; the rotation part is the skew part of the top-left block."""
    checks.matrix(X, MATRIX_DIM, "X")
    return B.last(B.first(X[..., :3, 4]), B.first(X[..., :3, 3]), B.unskew(X[..., :3, :3]), X[..., 3, 4][None])


def exp_impl(xi: torch.Tensor) -> torch.Tensor:
    """(3.6): C = Gamma_0(phi), v = Gamma_1 nu, r = Gamma_1 rho + iota Gamma_2 nu, tau = iota."""
    checks.vector(xi, DOF, "xi")
    rho, nu, phi, iota = _split(xi)
    c = B.coefficients(phi, 4)
    v = B.gamma_vec(c, 1, phi, nu)
    r = B.gamma_vec(c, 1, phi, rho) + iota * B.gamma_vec(c, 2, phi, nu)
    return _matrix(B.gamma_entries(c, 0, phi), v, r, iota)


def log_impl(M: torch.Tensor) -> torch.Tensor:
    """(3.13): phi = log(C), nu = D^-1 v, rho = D^-1 (r - tau E nu), iota = tau."""
    checks.matrix(M, MATRIX_DIM, "M")
    v, r, tau = B.first(M[..., :3, 3]), B.first(M[..., :3, 4]), M[..., 3, 4]
    phi = B.rotation_log(M[..., :3, :3])
    d = numerics.jinv_coefficient(B.theta_squared(phi))
    nu = B.jac_inv_vec(phi, v, d)
    c = B.coefficients(phi, 4)
    rho = B.jac_inv_vec(phi, r - tau * B.gamma_vec(c, 2, phi, nu), d)
    return B.last(rho, nu, phi, tau[None])


def compose(A: torch.Tensor, Bm: torch.Tensor) -> torch.Tensor:
    return A @ Bm


def inverse(M: torch.Tensor) -> torch.Tensor:
    """[[C^T, -C^T v, -C^T (r - tau v)], [0, 1, -tau], [0, 0, 1]]."""
    Ct = B.transpose_entries(M[..., :3, :3])
    v, r, tau = B.first(M[..., :3, 3]), B.first(M[..., :3, 4]), M[..., 3, 4]
    return _matrix(Ct, -B.matvec_entries(Ct, v), -B.matvec_entries(Ct, r - tau * v), -tau)


def adjoint(M: torch.Tensor) -> torch.Tensor:
    """(3.16)."""
    C, v, r, tau = components(M)
    t = tau.unsqueeze(-1)
    return B.block_matrix(
        [
            [C, -t * C, B.skew(B.first(r - tau * v)) @ C, v.unsqueeze(-1)],
            [None, C, B.skew(B.first(v)) @ C, None],
            [None, None, C, None],
            [None, None, None, torch.ones_like(t)],
        ],
        SIZES,
        M.shape[:-2],
        M,
    )


def ad(xi: torch.Tensor) -> torch.Tensor:
    """(3.18)."""
    checks.vector(xi, DOF, "xi")
    rho, nu, phi, iota = _split(xi)
    P = B.skew(phi)
    return B.block_matrix(
        [
            [P, -iota[..., None, None] * B.eye(3, xi), B.skew(rho), B.column(nu)],
            [None, P, B.skew(nu), None],
            [None, None, P, None],
            [None, None, None, None],
        ],
        SIZES,
        xi.shape[:-1],
        xi,
    )


def _jl_blocks(xi: torch.Tensor):
    """Blocks of (3.23): D, L = D - E (3.24), N (3.26), E nu, M (3.25).

    M = d(D nu)/dphi + (D nu)^ D and N = dr/dphi + r^ D - iota M follow from
    exp(J_l d) exp(xi) = exp(xi + d) with r = D rho + iota E nu; they equal the series of
    (3.25)-(3.28) (checked in the tests) without their cancellation at small angles.
    """
    rho, nu, phi, iota = _split(xi)
    c = B.coefficients(phi, 6)
    D = B.gamma_mat(c, 1, phi)
    E = B.gamma_mat(c, 2, phi)
    Mb = B.q_block(c, phi, nu, D)
    i3 = iota[..., None, None]
    r = B.gamma_vec(c, 1, phi, rho) + iota * B.gamma_vec(c, 2, phi, nu)
    dr = B.gamma_vec_derivative(c, 1, phi, rho) + i3 * B.gamma_vec_derivative(c, 2, phi, nu)
    N = dr + B.skew(r) @ D - i3 * Mb
    Enu = B.column(B.gamma_vec(c, 2, phi, nu))
    return D, D - E, N, Enu, Mb, i3


def jl(xi: torch.Tensor) -> torch.Tensor:
    """Left Jacobian (3.21)-(3.23)."""
    checks.vector(xi, DOF, "xi")
    D, L, N, Enu, Mb, i3 = _jl_blocks(xi)
    return B.block_matrix(
        [
            [D, -i3 * L, N, Enu],
            [None, D, Mb, None],
            [None, None, D, None],
            [None, None, None, torch.ones_like(i3)],
        ],
        SIZES,
        xi.shape[:-1],
        xi,
    )


def jl_inv(xi: torch.Tensor) -> torch.Tensor:
    """Inverse of (3.23) by block back-substitution (the Jacobian is block upper-triangular)."""
    checks.vector(xi, DOF, "xi")
    D, L, N, Enu, Mb, i3 = _jl_blocks(xi)
    Di = B.jac_inv_mat(_split(xi)[2])
    P = Di @ Mb @ Di
    Y = -Di @ (i3 * (L @ P) + N @ Di)
    return B.block_matrix(
        [
            [Di, i3 * (Di @ L @ Di), Y, -(Di @ Enu)],
            [None, Di, -P, None],
            [None, None, Di, None],
            [None, None, None, torch.ones_like(i3)],
        ],
        SIZES,
        xi.shape[:-1],
        xi,
    )


def _coupling_t(c, phi, rho, nu, iota, a, b):
    """N^T a + M^T b, with N = dr/dphi + r^ D - iota M (see _jl_blocks)."""
    r = B.gamma_vec(c, 1, phi, rho) + iota * B.gamma_vec(c, 2, phi, nu)
    return (
        B.gamma_vec_derivative_t(c, 1, phi, rho, a)
        + iota * B.gamma_vec_derivative_t(c, 2, phi, nu, a)
        + B.gamma_vec(c, 1, -phi, B.cross(a, r))
        + B.q_block_t(c, phi, nu, b - iota * a)
    )


def jl_tmv(xi: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """J_l(xi)^T w with vector operations only (the transposed blocks of (3.23))."""
    rho, nu, phi, iota = _split(xi)
    w_rho, w_nu, w_phi, w_iota = _split(w)
    c = B.coefficients(phi, 6)
    DT_w_rho = B.gamma_vec(c, 1, -phi, w_rho)
    LT_w_rho = DT_w_rho - B.gamma_vec(c, 2, -phi, w_rho)
    o_nu = B.gamma_vec(c, 1, -phi, w_nu) - iota * LT_w_rho
    o_phi = _coupling_t(c, phi, rho, nu, iota, w_rho, w_nu) + B.gamma_vec(c, 1, -phi, w_phi)
    o_iota = B.dot(B.gamma_vec(c, 2, phi, nu), w_rho) + w_iota
    return B.last(DT_w_rho, o_nu, o_phi, o_iota[None])


def jl_inv_tmv(xi: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """J_l(xi)^-T g by forward substitution on the transposed blocks of (3.23)."""
    rho, nu, phi, iota = _split(xi)
    g_rho, g_nu, g_phi, g_iota = _split(g)
    c = B.coefficients(phi, 6)
    d = numerics.jinv_coefficient(B.theta_squared(phi))
    y_rho = B.jac_inv_vec(-phi, g_rho, d)
    LT_y_rho = B.gamma_vec(c, 1, -phi, y_rho) - B.gamma_vec(c, 2, -phi, y_rho)
    y_nu = B.jac_inv_vec(-phi, g_nu + iota * LT_y_rho, d)
    y_phi = B.jac_inv_vec(-phi, g_phi - _coupling_t(c, phi, rho, nu, iota, y_rho, y_nu), d)
    y_iota = g_iota - B.dot(B.gamma_vec(c, 2, phi, nu), y_rho)
    return B.last(y_rho, y_nu, y_phi, y_iota[None])


def jr(xi: torch.Tensor) -> torch.Tensor:
    """J_r(xi) = J_l(-xi)."""
    return jl(-xi)


def jr_inv(xi: torch.Tensor) -> torch.Tensor:
    return jl_inv(-xi)


def act(M: torch.Tensor, e: torch.Tensor) -> torch.Tensor:
    """Events (..., 4) = (x, t) -> (C x + v t + r, t + tau), (3.31)."""
    checks.vector(e, 4, "e")
    checks.binary(M, 2, e, 1, "g", "e")
    return (M[..., :4, :] @ torch.cat((e, torch.ones_like(e[..., :1])), -1).unsqueeze(-1)).squeeze(-1)


def act_velocity(M: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Inertial velocities [u, 1, 0] -> C u + v."""
    checks.vector(u, 3, "u")
    checks.binary(M, 2, u, 1, "g", "u")
    return (M[..., :3, :4] @ torch.cat((u, torch.ones_like(u[..., :1])), -1).unsqueeze(-1)).squeeze(-1)


def act_direction(M: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """Directions [d, 0, 0] -> C d."""
    checks.vector(d, 3, "d")
    checks.binary(M, 2, d, 1, "g", "d")
    return (M[..., :3, :3] @ d.unsqueeze(-1)).squeeze(-1)


def random(batch_shape, dtype, device, generator=None) -> torch.Tensor:
    C = B.random_rotation(batch_shape, dtype, device, generator)
    v, r = torch.randn(2, 3, *batch_shape, dtype=dtype, device=device, generator=generator)
    tau = torch.randn(batch_shape, dtype=dtype, device=device, generator=generator)
    return _matrix(B.entries(C), v, r, tau)


exp, log = make_exp_log(sys.modules[__name__])
