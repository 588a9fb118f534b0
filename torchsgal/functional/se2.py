"""SE(2) on plain tensors: (..., 3, 3) [[C, r], [0, 1]], tangent (..., 3) [rho (2), theta].

Barfoot, "Integral Forms", Section 4.5 and Table 1.  With J = [[0, -1], [1, 0]] (J^2 = -I)
and the scalar family c_m of ``numerics``:

    V(theta) = sum_n (theta J)^n/(n+1)! = c_1 I + theta c_2 J,    r = V rho,
    W(theta) = sum_n (theta J)^n/(n+2)! = c_2 I + theta c_3 J,
    Ad = [[C, -J r], [0, 1]],  ad(xi) = [[theta J, -J rho], [0, 0]],
    J_l = int_0^1 Ad(exp(a xi)) da = [[V, -J W rho], [0, 1]],
    V^-1 = (c_1 I - theta c_2 J) / (2 c_2)   (c_1^2 + theta^2 c_2^2 = 2 c_2).
"""
from __future__ import annotations

import sys

import torch

from . import blocks as B
from . import checks, numerics
from ._autograd import checked_backward_parts, make_exp_log, make_jacobians, make_products
from ._blocking import blocked

NAME = "SE2"
DOF = 3
MATRIX_DIM = 3
SIZES = [2, 1]
PHI = slice(2, 3)


def _split(xi: torch.Tensor):
    return xi[..., 0], xi[..., 1], xi[..., 2]


def _coeffs(t: torch.Tensor):
    return numerics.series_coefficients(t * t, 3)


def _mat(a, b):
    """a I + b J as (..., 2, 2)."""
    return torch.stack((a, -b, b, a), dim=-1).unflatten(-1, (2, 2))


def _apply(a, b, x, y):
    """(a I + b J) (x, y)."""
    return a * x - b * y, b * x + a * y


def _matrix(c, s, x, y) -> torch.Tensor:
    z, o = torch.zeros_like(c), torch.ones_like(c)
    return torch.stack((c, -s, x, s, c, y, z, z, o), dim=-1).unflatten(-1, (3, 3))


def components(M: torch.Tensor):
    """(C, r)."""
    checks.matrix(M, MATRIX_DIM, "M")
    return M[..., :2, :2], M[..., :2, 2]


def from_components(C, r) -> torch.Tensor:
    """C (..., 2, 2), r (..., 2), batches broadcast -> (..., 3, 3)."""
    C, r = checks.components(C=(C, (2, 2)), r=(r, (2,)))
    return _matrix(C[..., 0, 0], C[..., 1, 0], r[..., 0], r[..., 1])


def hat(xi: torch.Tensor) -> torch.Tensor:
    checks.vector(xi, DOF, "xi")
    x, y, t = _split(xi)
    z = torch.zeros_like(t)
    return torch.stack((z, -t, x, t, z, y, z, z, z), dim=-1).unflatten(-1, (3, 3))


def vee(X: torch.Tensor) -> torch.Tensor:
    checks.matrix(X, MATRIX_DIM, "X")
    return torch.stack((X[..., 0, 2], X[..., 1, 2], 0.5 * (X[..., 1, 0] - X[..., 0, 1])), dim=-1)


def exp_impl(xi: torch.Tensor) -> torch.Tensor:
    checks.vector(xi, DOF, "xi")
    x, y, t = _split(xi)
    c = _coeffs(t)
    rx, ry = _apply(c[1], t * c[2], x, y)
    return _matrix(c[0], t * c[1], rx, ry)


def log_impl(M: torch.Tensor) -> torch.Tensor:
    checks.matrix(M, MATRIX_DIM, "M")
    t = B.planar_angle(M)
    c = _coeffs(t)
    x, y = _apply(c[1] / (2 * c[2]), -t * c[2] / (2 * c[2]), M[..., 0, 2], M[..., 1, 2])
    return torch.stack((x, y, t), dim=-1)


@blocked(2)
def inverse(M: torch.Tensor) -> torch.Tensor:
    checks.matrix(M, MATRIX_DIM, "M")
    c, s = M[..., 0, 0], M[..., 1, 0]
    x, y = M[..., 0, 2], M[..., 1, 2]
    return _matrix(c, -s, -(c * x + s * y), -(-s * x + c * y))


def _block(A22, col, batch, like):
    """[[A22, col], [0, 1]] (..., 3, 3) from A22 (..., 2, 2) and col (..., 2)."""
    top = torch.cat((A22, col.unsqueeze(-1)), dim=-1)
    bottom = torch.zeros(*batch, 1, 3, dtype=like.dtype, device=like.device)
    bottom[..., 0, 2].fill_(1.0)  # fill_: an unbatched x[i, j] = 1.0 is a blocking copy on CUDA
    return torch.cat((top, bottom), dim=-2)


def _minus_J(x, y):
    """-J (x, y) = (y, -x)."""
    return torch.stack((y, -x), dim=-1)


@blocked(2)
def adjoint(M: torch.Tensor) -> torch.Tensor:
    """[[C, -J r], [0, 1]]."""
    checks.matrix(M, MATRIX_DIM, "M")
    return _block(M[..., :2, :2], _minus_J(M[..., 0, 2], M[..., 1, 2]), M.shape[:-2], M)


def ad(xi: torch.Tensor) -> torch.Tensor:
    """[[theta J, -J rho], [0, 0]]."""
    checks.vector(xi, DOF, "xi")
    x, y, t = _split(xi)
    z = torch.zeros_like(t)
    m = _minus_J(x, y)
    return torch.stack((z, -t, m[..., 0], t, z, m[..., 1], z, z, z), dim=-1).unflatten(-1, (3, 3))


def _jl_parts(xi: torch.Tensor):
    """c, (a, b) of V = a I + b J, and q = -J W rho (the top-right column of J_l)."""
    x, y, t = _split(xi)
    c = _coeffs(t)
    wx, wy = _apply(c[2], t * c[3], x, y)
    return c, c[1], t * c[2], _minus_J(wx, wy)


@blocked(1)
def jl_impl(xi: torch.Tensor) -> torch.Tensor:
    """[[V, -J W rho], [0, 1]]."""
    checks.vector(xi, DOF, "xi")
    _, a, b, q = _jl_parts(xi)
    return _block(_mat(a, b), q, xi.shape[:-1], xi)


@blocked(1)
def jl_inv_impl(xi: torch.Tensor) -> torch.Tensor:
    """[[V^-1, -V^-1 q], [0, 1]] with V^-1 = (a I - b J) / (2 c_2)."""
    checks.vector(xi, DOF, "xi")
    c, a, b, q = _jl_parts(xi)
    ai, bi = a / (2 * c[2]), -b / (2 * c[2])
    qx, qy = _apply(ai, bi, q[..., 0], q[..., 1])
    return _block(_mat(ai, bi), -torch.stack((qx, qy), dim=-1), xi.shape[:-1], xi)


def jr(xi: torch.Tensor) -> torch.Tensor:
    """J_r(xi) = J_l(-xi)."""
    checks.vector(xi, DOF, "xi")
    return jl(-xi)


def jr_inv(xi: torch.Tensor) -> torch.Tensor:
    """J_r(xi)^-1 = J_l(-xi)^-1."""
    checks.vector(xi, DOF, "xi")
    return jl_inv(-xi)


def _jl_tmv(xi: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """J_l^T w = (V^T w_rho, q . w_rho + w_theta)."""
    _, a, b, q = _jl_parts(xi)
    x, y = _apply(a, -b, w[..., 0], w[..., 1])
    return torch.stack((x, y, q[..., 0] * w[..., 0] + q[..., 1] * w[..., 1] + w[..., 2]), dim=-1)


def _jl_inv_tmv(xi: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """Solves J_l^T y = g: y_rho = V^-T g_rho, y_theta = g_theta - q . y_rho."""
    c, a, b, q = _jl_parts(xi)
    x, y = _apply(a / (2 * c[2]), b / (2 * c[2]), g[..., 0], g[..., 1])
    return torch.stack((x, y, g[..., 2] - q[..., 0] * x - q[..., 1] * y), dim=-1)


def _exp_pullback(M: torch.Tensor, G: torch.Tensor) -> torch.Tensor:
    """hat^T(M^T G)."""
    A = M.transpose(-1, -2) @ G
    return torch.stack((A[..., 0, 2], A[..., 1, 2], A[..., 1, 0] - A[..., 0, 1]), dim=-1)


def _log_pullback(M: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """M^-T vee^T(w) = M^-T hat(w_rho, w_theta / 2)."""
    half = torch.cat((w[..., :2], 0.5 * w[..., 2:]), dim=-1)
    return inverse(M).transpose(-1, -2) @ hat(half)


def act(M: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Points [p, 1] -> C p + r."""
    return B.act_homogeneous(M, p, "p", MATRIX_DIM, (1.0,), rows=2)


def act_jacobian(M: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """d act(M exp(xi^), p) / d xi at 0 (..., 2, DOF), the right perturbation."""
    return B.act_homogeneous_jacobian(M, p, "p", MATRIX_DIM, hat, DOF, (1.0,), rows=2)


def act_direction(M: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """Directions [d, 0] -> C d."""
    return B.act_homogeneous(M, d, "d", MATRIX_DIM, rows=2)


def random(batch_shape, dtype, device, generator=None) -> torch.Tensor:
    """A uniform rotation angle and a standard normal translation; batch_shape an int or a sequence."""
    batch_shape = checks.shape(batch_shape, "batch_shape")
    checks.dtype_arg(dtype)
    t = (torch.rand(tuple(batch_shape), dtype=dtype, device=device, generator=generator) * 2 - 1) * torch.pi
    r = torch.randn(*batch_shape, 2, dtype=dtype, device=device, generator=generator)
    return _matrix(torch.cos(t), torch.sin(t), r[..., 0], r[..., 1])


# The tensor code of the operators torchsgal::se2_inverse and se2_adjoint (ops.py); the group's
# inverse and adjoint run it directly (no operator: no C kernel would pay for these few entries).
inverse_impl, adjoint_impl = inverse, adjoint

exp, log = make_exp_log(sys.modules[__name__])
jl, jl_inv = make_jacobians(sys.modules[__name__])
compose = make_products(sys.modules[__name__], compose_min_batch=2048)[0]
jl_tmv, jl_inv_tmv, exp_pullback, log_pullback = checked_backward_parts(sys.modules[__name__])
