"""SE_2(3), extended poses: (..., 5, 5) [[C, v, r], [0, 1, 0], [0, 0, 1]], tangent
(..., 9) [rho, nu, phi].  The isochronous subgroup of SGal(3) (iota = 0); Barfoot,
"Integral Forms", Table 1.
"""
from __future__ import annotations

import sys

import torch

from . import blocks as B
from . import checks
from ._autograd import make_exp_log

NAME = "SE23"
DOF = 9
MATRIX_DIM = 5
SIZES = [3, 3, 3]
PHI = slice(6, 9)


def split(xi: torch.Tensor):
    return xi[..., 0:3], xi[..., 3:6], xi[..., 6:9]


def components(M: torch.Tensor):
    """(C, v, r)."""
    return M[..., :3, :3], M[..., :3, 3], M[..., :3, 4]


def from_components(C, v, r) -> torch.Tensor:
    top = torch.cat((C, v.unsqueeze(-1), r.unsqueeze(-1)), dim=-1)
    z = torch.zeros_like(v)
    o = torch.ones_like(v[..., :1])
    row4 = torch.cat((z, o, torch.zeros_like(o)), dim=-1)
    row5 = torch.cat((z, torch.zeros_like(o), o), dim=-1)
    return torch.cat((top, row4.unsqueeze(-2), row5.unsqueeze(-2)), dim=-2)


def hat(xi: torch.Tensor) -> torch.Tensor:
    checks.vector(xi, DOF, "xi")
    rho, nu, phi = split(xi)
    top = torch.cat((B.skew(phi), nu.unsqueeze(-1), rho.unsqueeze(-1)), dim=-1)
    return torch.cat((top, torch.zeros_like(top[..., :2, :])), dim=-2)


def vee(X: torch.Tensor) -> torch.Tensor:
    checks.matrix(X, MATRIX_DIM, "X")
    return torch.cat((X[..., :3, 4], X[..., :3, 3], B.unskew(X[..., :3, :3])), dim=-1)


def exp_impl(xi: torch.Tensor) -> torch.Tensor:
    checks.vector(xi, DOF, "xi")
    rho, nu, phi = split(xi)
    c = B.coefficients(phi, 3)
    return from_components(
        B.rotation(c, phi), B.gamma_vec(c, 1, phi, nu), B.gamma_vec(c, 1, phi, rho)
    )


def log_impl(M: torch.Tensor) -> torch.Tensor:
    checks.matrix(M, MATRIX_DIM, "M")
    C, v, r = components(M)
    phi = B.rotation_log(C)
    return torch.cat((B.jac_inv_vec(phi, r), B.jac_inv_vec(phi, v), phi), dim=-1)


def compose(A: torch.Tensor, Bm: torch.Tensor) -> torch.Tensor:
    return A @ Bm


def inverse(M: torch.Tensor) -> torch.Tensor:
    C, v, r = components(M)
    Ct = C.transpose(-1, -2)
    mv = lambda x: -(Ct @ x.unsqueeze(-1)).squeeze(-1)  # noqa: E731
    return from_components(Ct, mv(v), mv(r))


def adjoint(M: torch.Tensor) -> torch.Tensor:
    """[[C, 0, r^ C], [0, C, v^ C], [0, 0, C]]."""
    C, v, r = components(M)
    return B.block_matrix(
        [[C, None, B.skew(r) @ C], [None, C, B.skew(v) @ C], [None, None, C]], SIZES, v
    )


def ad(xi: torch.Tensor) -> torch.Tensor:
    """[[phi^, 0, rho^], [0, phi^, nu^], [0, 0, phi^]]."""
    checks.vector(xi, DOF, "xi")
    rho, nu, phi = split(xi)
    P = B.skew(phi)
    return B.block_matrix(
        [[P, None, B.skew(rho)], [None, P, B.skew(nu)], [None, None, P]], SIZES, xi
    )


def _jl_blocks(xi: torch.Tensor):
    rho, nu, phi = split(xi)
    c = B.coefficients(phi, 5)
    J = B.gamma_mat(c, 1, phi)
    Q_rho, _ = B.q_block(c, phi, rho, J)
    Q_nu, _ = B.q_block(c, phi, nu, J)
    return J, Q_rho, Q_nu


def jl(xi: torch.Tensor) -> torch.Tensor:
    checks.vector(xi, DOF, "xi")
    J, Q_rho, Q_nu = _jl_blocks(xi)
    return B.block_matrix([[J, None, Q_rho], [None, J, Q_nu], [None, None, J]], SIZES, xi)


def jl_inv(xi: torch.Tensor) -> torch.Tensor:
    checks.vector(xi, DOF, "xi")
    _, Q_rho, Q_nu = _jl_blocks(xi)
    Ji = B.jac_inv_mat(xi[..., PHI])
    return B.block_matrix(
        [[Ji, None, -Ji @ Q_rho @ Ji], [None, Ji, -Ji @ Q_nu @ Ji], [None, None, Ji]], SIZES, xi
    )


def jr(xi: torch.Tensor) -> torch.Tensor:
    return jl(-xi)


def jr_inv(xi: torch.Tensor) -> torch.Tensor:
    return jl_inv(-xi)


def act(M: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Points (..., 3) -> C p + r."""
    checks.vector(p, 3, "p")
    checks.binary(M, 2, p, 1, "g", "p")
    C, _, r = components(M)
    return (C @ p.unsqueeze(-1)).squeeze(-1) + r


def act_velocity(M: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Velocities [u, 1, 0] -> C u + v."""
    checks.vector(u, 3, "u")
    checks.binary(M, 2, u, 1, "g", "u")
    C, v, _ = components(M)
    return (C @ u.unsqueeze(-1)).squeeze(-1) + v


def act_direction(M: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    checks.vector(d, 3, "d")
    checks.binary(M, 2, d, 1, "g", "d")
    return (M[..., :3, :3] @ d.unsqueeze(-1)).squeeze(-1)


def random(batch_shape, dtype, device, generator=None) -> torch.Tensor:
    C = B.random_rotation(batch_shape, dtype, device, generator)
    v, r = torch.randn(2, *batch_shape, 3, dtype=dtype, device=device, generator=generator)
    return from_components(C, v, r)


exp, log = make_exp_log(sys.modules[__name__])
