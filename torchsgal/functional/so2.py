"""SO(2) on plain tensors: rotation matrices (..., 2, 2), tangent theta (..., 1).

Barfoot, "Integral Forms", Section 4.5 and Table 1: the group is abelian, so Ad = 1, ad = 0
and J_l = J_r = 1.
"""
from __future__ import annotations

import sys

import torch

from . import blocks as B
from . import checks
from ._autograd import checked_backward_parts, make_exp_log

NAME = "SO2"
DOF = 1
MATRIX_DIM = 2
SIZES = [1]
PHI = slice(0, 1)


def components(M: torch.Tensor):
    checks.matrix(M, MATRIX_DIM, "M")
    return (M,)


def from_components(C: torch.Tensor) -> torch.Tensor:
    checks.matrix(C, MATRIX_DIM, "C")
    return C


def _rot(c: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    return torch.stack((c, -s, s, c), dim=-1).unflatten(-1, (2, 2))


def hat(theta: torch.Tensor) -> torch.Tensor:
    """theta J with J = [[0, -1], [1, 0]]."""
    checks.vector(theta, DOF, "xi")
    t = theta[..., 0]
    return _rot(torch.zeros_like(t), t)


def vee(X: torch.Tensor) -> torch.Tensor:
    """The skew part of X: (X10 - X01) / 2."""
    checks.matrix(X, MATRIX_DIM, "X")
    return (0.5 * (X[..., 1, 0] - X[..., 0, 1])).unsqueeze(-1)


def exp_impl(theta: torch.Tensor) -> torch.Tensor:
    checks.vector(theta, DOF, "xi")
    t = theta[..., 0]
    return _rot(torch.cos(t), torch.sin(t))


def log_impl(C: torch.Tensor) -> torch.Tensor:
    """theta = atan2 of C's skew and symmetric parts, in [-pi, pi]: -pi at a half turn whose
    skew part is -0 or rounds below zero (exp(-pi)), as atan2 gives it."""
    checks.matrix(C, MATRIX_DIM, "M")
    return B.planar_angle(C).unsqueeze(-1)


def compose(A: torch.Tensor, Bm: torch.Tensor) -> torch.Tensor:
    checks.matrix_pair(A, Bm, MATRIX_DIM, "A", "B")
    return A @ Bm


def inverse(C: torch.Tensor) -> torch.Tensor:
    checks.matrix(C, MATRIX_DIM, "C")
    return C.transpose(-1, -2)


# SO(2) is abelian: Ad = J = 1 and ad = 0.  They are built from the input (x * 0 + 1) so that,
# as for the other groups, they are connected to its autograd graph (a zero gradient, not
# "does not require grad").


def adjoint(C: torch.Tensor) -> torch.Tensor:
    checks.matrix(C, MATRIX_DIM, "C")
    return C[..., :1, :1] * 0.0 + 1.0


def ad(theta: torch.Tensor) -> torch.Tensor:
    checks.vector(theta, DOF, "xi")
    return theta.unsqueeze(-1) * 0.0


def jl(theta: torch.Tensor) -> torch.Tensor:
    checks.vector(theta, DOF, "xi")
    return theta.unsqueeze(-1) * 0.0 + 1.0


jr = jl_inv = jr_inv = jl


def _jl_tmv(theta: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """J_l = 1: w, on the batch that theta and w broadcast to."""
    if theta.shape == w.shape:
        return w
    return w.expand(checks.broadcast_shapes(theta.shape, w.shape)).clone()


_jl_inv_tmv = _jl_tmv


def _exp_pullback(C: torch.Tensor, G: torch.Tensor) -> torch.Tensor:
    """hat^T(C^T G) = (C^T G)_10 - (C^T G)_01."""
    A = C.transpose(-1, -2) @ G
    return (A[..., 1, 0] - A[..., 0, 1]).unsqueeze(-1)


def _log_pullback(C: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """C^-T vee^T(w) = C hat(w / 2)."""
    return C @ hat(0.5 * w)


def act(C: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Points (..., 2) -> C p."""
    return B.act_homogeneous(C, p, "p", MATRIX_DIM, rows=2)


def act_jacobian(C: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """d act(C exp(xi^), p) / d xi at 0 (..., 2, DOF), the right perturbation."""
    return B.act_homogeneous_jacobian(C, p, "p", MATRIX_DIM, hat, DOF, rows=2)


def act_direction(C: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    return B.act_homogeneous(C, d, "d", MATRIX_DIM, rows=2)


def random(batch_shape, dtype, device, generator=None) -> torch.Tensor:
    """A uniform rotation angle in [-pi, pi); batch_shape an int or a sequence."""
    batch_shape = checks.shape(batch_shape, "batch_shape")
    checks.dtype_arg(dtype)
    t = (torch.rand(tuple(batch_shape), dtype=dtype, device=device, generator=generator) * 2 - 1) * torch.pi
    return _rot(torch.cos(t), torch.sin(t))


exp, log = make_exp_log(sys.modules[__name__])
jl_tmv, jl_inv_tmv, exp_pullback, log_pullback = checked_backward_parts(sys.modules[__name__])
