"""SGal(3), the special Galilean group, on plain tensors.

Matrices (..., 5, 5) [[C, v, r], [0, 1, tau], [0, 0, 1]]; tangent (..., 10) [rho, nu, phi, iota].
Equation numbers refer to Kelly and Giamou, "Uncertainty in space, time, and motion on the
special Galilean group" (kelly-giamou-uncertainty-sgal3.txt).
"""
from __future__ import annotations

import sys

import torch

from . import blocks as B
from . import checks
from ._autograd import make_exp_log

NAME = "SGal3"
DOF = 10
MATRIX_DIM = 5
SIZES = [3, 3, 3, 1]
PHI = slice(6, 9)


def split(xi: torch.Tensor):
    return xi[..., 0:3], xi[..., 3:6], xi[..., 6:9], xi[..., 9:10]


def components(M: torch.Tensor):
    """(C, v, r, tau) of a group matrix; tau has shape (..., 1)."""
    return M[..., :3, :3], M[..., :3, 3], M[..., :3, 4], M[..., 3, 4:5]


def from_components(C, v, r, tau) -> torch.Tensor:
    top = torch.cat((C, v.unsqueeze(-1), r.unsqueeze(-1)), dim=-1)
    zeros = torch.zeros_like(v)
    ones = torch.ones_like(tau)
    row4 = torch.cat((zeros, ones, tau), dim=-1)
    row5 = torch.cat((zeros, torch.zeros_like(tau), ones), dim=-1)
    return torch.cat((top, row4.unsqueeze(-2), row5.unsqueeze(-2)), dim=-2)


def hat(xi: torch.Tensor) -> torch.Tensor:
    """(3.4): [[phi^, nu, rho], [0, 0, iota], [0, 0, 0]]."""
    checks.vector(xi, DOF, "xi")
    rho, nu, phi, iota = split(xi)
    top = torch.cat((B.skew(phi), nu.unsqueeze(-1), rho.unsqueeze(-1)), dim=-1)
    z = torch.zeros_like(nu)
    row4 = torch.cat((z, torch.zeros_like(iota), iota), dim=-1)
    row5 = torch.zeros_like(row4)
    return torch.cat((top, row4.unsqueeze(-2), row5.unsqueeze(-2)), dim=-2)


def vee(X: torch.Tensor) -> torch.Tensor:
    """Inverse of ``hat``; the rotation part is the skew part of the top-left block."""
    checks.matrix(X, MATRIX_DIM, "X")
    return torch.cat((X[..., :3, 4], X[..., :3, 3], B.unskew(X[..., :3, :3]), X[..., 3, 4:5]), -1)


def exp_impl(xi: torch.Tensor) -> torch.Tensor:
    """(3.6): C = Gamma_0(phi), v = Gamma_1 nu, r = Gamma_1 rho + iota Gamma_2 nu, tau = iota."""
    checks.vector(xi, DOF, "xi")
    rho, nu, phi, iota = split(xi)
    c = B.coefficients(phi, 4)
    v = B.gamma_vec(c, 1, phi, nu)
    r = B.gamma_vec(c, 1, phi, rho) + iota * B.gamma_vec(c, 2, phi, nu)
    return from_components(B.rotation(c, phi), v, r, iota)


def log_impl(M: torch.Tensor) -> torch.Tensor:
    """(3.13): phi = log(C), nu = D^-1 v, rho = D^-1 (r - tau E nu), iota = tau."""
    checks.matrix(M, MATRIX_DIM, "M")
    C, v, r, tau = components(M)
    phi = B.rotation_log(C)
    nu = B.jac_inv_vec(phi, v)
    c = B.coefficients(phi, 4)
    rho = B.jac_inv_vec(phi, r - tau * B.gamma_vec(c, 2, phi, nu))
    return torch.cat((rho, nu, phi, tau), dim=-1)


def compose(A: torch.Tensor, Bm: torch.Tensor) -> torch.Tensor:
    return A @ Bm


def inverse(M: torch.Tensor) -> torch.Tensor:
    """[[C^T, -C^T v, -C^T (r - tau v)], [0, 1, -tau], [0, 0, 1]]."""
    C, v, r, tau = components(M)
    Ct = C.transpose(-1, -2)
    return from_components(
        Ct, -(Ct @ v.unsqueeze(-1)).squeeze(-1), -(Ct @ (r - tau * v).unsqueeze(-1)).squeeze(-1), -tau
    )


def adjoint(M: torch.Tensor) -> torch.Tensor:
    """(3.16)."""
    C, v, r, tau = components(M)
    t = tau.unsqueeze(-1)
    return B.block_matrix(
        [
            [C, -t * C, B.skew(r - tau * v) @ C, v.unsqueeze(-1)],
            [None, C, B.skew(v) @ C, None],
            [None, None, C, None],
            [None, None, None, torch.ones_like(tau).unsqueeze(-1)],
        ],
        SIZES,
        v,
    )


def ad(xi: torch.Tensor) -> torch.Tensor:
    """(3.18)."""
    checks.vector(xi, DOF, "xi")
    rho, nu, phi, iota = split(xi)
    P = B.skew(phi)
    return B.block_matrix(
        [
            [P, -iota.unsqueeze(-1) * B.eye(3, xi), B.skew(rho), nu.unsqueeze(-1)],
            [None, P, B.skew(nu), None],
            [None, None, P, None],
            [None, None, None, None],
        ],
        SIZES,
        xi,
    )


def _jl_blocks(xi: torch.Tensor):
    """Blocks of (3.23): D, L = D - E (3.24), N (3.26), E nu, M (3.25).

    M = d(D nu)/dphi + (D nu)^ D and N = dr/dphi + r^ D - iota M follow from
    exp(J_l d) exp(xi) = exp(xi + d) with r = D rho + iota E nu; they equal the series of
    (3.25)-(3.28) (checked in the tests) without their cancellation at small angles.
    """
    rho, nu, phi, iota = split(xi)
    c = B.coefficients(phi, 6)
    D = B.gamma_mat(c, 1, phi)
    E = B.gamma_mat(c, 2, phi)
    Mb, _ = B.q_block(c, phi, nu, D)
    i3 = iota.unsqueeze(-1)
    r = B.gamma_vec(c, 1, phi, rho) + iota * B.gamma_vec(c, 2, phi, nu)
    dr = B.gamma_vec_derivative(c, 1, phi, rho) + i3 * B.gamma_vec_derivative(c, 2, phi, nu)
    N = dr + B.skew(r) @ D - i3 * Mb
    Enu = B.gamma_vec(c, 2, phi, nu)
    return D, D - E, N, Enu, Mb, i3


def jl(xi: torch.Tensor) -> torch.Tensor:
    """Left Jacobian (3.21)-(3.23)."""
    checks.vector(xi, DOF, "xi")
    D, L, N, Enu, Mb, i3 = _jl_blocks(xi)
    return B.block_matrix(
        [
            [D, -i3 * L, N, Enu.unsqueeze(-1)],
            [None, D, Mb, None],
            [None, None, D, None],
            [None, None, None, torch.ones_like(i3)],
        ],
        SIZES,
        xi,
    )


def jl_inv(xi: torch.Tensor) -> torch.Tensor:
    """Inverse of (3.23) by block back-substitution (the Jacobian is block upper-triangular)."""
    checks.vector(xi, DOF, "xi")
    D, L, N, Enu, Mb, i3 = _jl_blocks(xi)
    Di = B.jac_inv_mat(xi[..., PHI])
    P = Di @ Mb @ Di
    Y = -Di @ (i3 * (L @ P) + N @ Di)
    return B.block_matrix(
        [
            [Di, i3 * (Di @ L @ Di), Y, -(Di @ Enu.unsqueeze(-1))],
            [None, Di, -P, None],
            [None, None, Di, None],
            [None, None, None, torch.ones_like(i3)],
        ],
        SIZES,
        xi,
    )


def jr(xi: torch.Tensor) -> torch.Tensor:
    """J_r(xi) = J_l(-xi)."""
    return jl(-xi)


def jr_inv(xi: torch.Tensor) -> torch.Tensor:
    return jl_inv(-xi)


def act(M: torch.Tensor, e: torch.Tensor) -> torch.Tensor:
    """Events (..., 4) = (x, t) -> (C x + v t + r, t + tau), (3.31)."""
    checks.vector(e, 4, "e")
    checks.binary(M, 2, e, 1, "g", "e")
    C, v, r, tau = components(M)
    x, t = e[..., :3], e[..., 3:4]
    return torch.cat(((C @ x.unsqueeze(-1)).squeeze(-1) + v * t + r, t + tau), dim=-1)


def act_velocity(M: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Inertial velocities [u, 1, 0] -> C u + v."""
    checks.vector(u, 3, "u")
    checks.binary(M, 2, u, 1, "g", "u")
    C, v, _, _ = components(M)
    return (C @ u.unsqueeze(-1)).squeeze(-1) + v


def act_direction(M: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """Directions [d, 0, 0] -> C d."""
    checks.vector(d, 3, "d")
    checks.binary(M, 2, d, 1, "g", "d")
    return (M[..., :3, :3] @ d.unsqueeze(-1)).squeeze(-1)


def random(batch_shape, dtype, device, generator=None) -> torch.Tensor:
    C = B.random_rotation(batch_shape, dtype, device, generator)
    v, r = torch.randn(2, *batch_shape, 3, dtype=dtype, device=device, generator=generator)
    tau = torch.randn(*batch_shape, 1, dtype=dtype, device=device, generator=generator)
    return from_components(C, v, r, tau)


exp, log = make_exp_log(sys.modules[__name__])
