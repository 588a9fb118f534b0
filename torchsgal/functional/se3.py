"""SE(3) on plain tensors: (..., 4, 4) [[C, r], [0, 1]], tangent (..., 6) [rho, phi].

Barfoot, "Integral Forms", Table 1: exp r = Gamma_1 rho, J_l = [[J, Q], [0, J]].
"""
from __future__ import annotations

import sys

import torch

from . import blocks as B
from . import checks
from ._autograd import make_exp_log

NAME = "SE3"
DOF = 6
MATRIX_DIM = 4
SIZES = [3, 3]
PHI = slice(3, 6)


def split(xi: torch.Tensor):
    return xi[..., 0:3], xi[..., 3:6]


def components(M: torch.Tensor):
    """(C, r)."""
    return M[..., :3, :3], M[..., :3, 3]


def from_components(C, r) -> torch.Tensor:
    top = torch.cat((C, r.unsqueeze(-1)), dim=-1)
    row = torch.cat((torch.zeros_like(r), torch.ones_like(r[..., :1])), dim=-1)
    return torch.cat((top, row.unsqueeze(-2)), dim=-2)


def hat(xi: torch.Tensor) -> torch.Tensor:
    checks.vector(xi, DOF, "xi")
    rho, phi = split(xi)
    top = torch.cat((B.skew(phi), rho.unsqueeze(-1)), dim=-1)
    return torch.cat((top, torch.zeros_like(top[..., :1, :])), dim=-2)


def vee(X: torch.Tensor) -> torch.Tensor:
    checks.matrix(X, MATRIX_DIM, "X")
    return torch.cat((X[..., :3, 3], B.unskew(X[..., :3, :3])), dim=-1)


def exp_impl(xi: torch.Tensor) -> torch.Tensor:
    checks.vector(xi, DOF, "xi")
    rho, phi = split(xi)
    c = B.coefficients(phi, 3)
    return from_components(B.rotation(c, phi), B.gamma_vec(c, 1, phi, rho))


def log_impl(M: torch.Tensor) -> torch.Tensor:
    checks.matrix(M, MATRIX_DIM, "M")
    C, r = components(M)
    phi = B.rotation_log(C)
    return torch.cat((B.jac_inv_vec(phi, r), phi), dim=-1)


def compose(A: torch.Tensor, Bm: torch.Tensor) -> torch.Tensor:
    return A @ Bm


def inverse(M: torch.Tensor) -> torch.Tensor:
    C, r = components(M)
    Ct = C.transpose(-1, -2)
    return from_components(Ct, -(Ct @ r.unsqueeze(-1)).squeeze(-1))


def adjoint(M: torch.Tensor) -> torch.Tensor:
    """[[C, r^ C], [0, C]]."""
    C, r = components(M)
    return B.block_matrix([[C, B.skew(r) @ C], [None, C]], SIZES, r)


def ad(xi: torch.Tensor) -> torch.Tensor:
    """[[phi^, rho^], [0, phi^]]."""
    checks.vector(xi, DOF, "xi")
    rho, phi = split(xi)
    P = B.skew(phi)
    return B.block_matrix([[P, B.skew(rho)], [None, P]], SIZES, xi)


def _jl_blocks(xi: torch.Tensor):
    rho, phi = split(xi)
    c = B.coefficients(phi, 5)
    J = B.gamma_mat(c, 1, phi)
    Q, _ = B.q_block(c, phi, rho, J)
    return J, Q


def jl(xi: torch.Tensor) -> torch.Tensor:
    checks.vector(xi, DOF, "xi")
    J, Q = _jl_blocks(xi)
    return B.block_matrix([[J, Q], [None, J]], SIZES, xi)


def jl_inv(xi: torch.Tensor) -> torch.Tensor:
    """[[J^-1, -J^-1 Q J^-1], [0, J^-1]]."""
    checks.vector(xi, DOF, "xi")
    _, Q = _jl_blocks(xi)
    Ji = B.jac_inv_mat(xi[..., PHI])
    return B.block_matrix([[Ji, -Ji @ Q @ Ji], [None, Ji]], SIZES, xi)


def jr(xi: torch.Tensor) -> torch.Tensor:
    return jl(-xi)


def jr_inv(xi: torch.Tensor) -> torch.Tensor:
    return jl_inv(-xi)


def act(M: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Points (..., 3) -> C p + r."""
    checks.vector(p, 3, "p")
    checks.binary(M, 2, p, 1, "g", "p")
    C, r = components(M)
    return (C @ p.unsqueeze(-1)).squeeze(-1) + r


def act_direction(M: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    checks.vector(d, 3, "d")
    checks.binary(M, 2, d, 1, "g", "d")
    return (M[..., :3, :3] @ d.unsqueeze(-1)).squeeze(-1)


def random(batch_shape, dtype, device, generator=None) -> torch.Tensor:
    C = B.random_rotation(batch_shape, dtype, device, generator)
    r = torch.randn(*batch_shape, 3, dtype=dtype, device=device, generator=generator)
    return from_components(C, r)


exp, log = make_exp_log(sys.modules[__name__])
