"""SO(3) on plain tensors: rotation matrices (..., 3, 3), tangent phi (..., 3).

Equation numbers refer to kelly-giamou-uncertainty-sgal3.txt, (3.7)-(3.12).
"""
from __future__ import annotations

import sys

import torch

from . import blocks as B
from . import checks
from ._autograd import checked_backward_parts, make_exp_log, make_jacobians, make_products
from ._blocking import blocked, values_readable

NAME = "SO3"
DOF = 3
MATRIX_DIM = 3
SIZES = [3]
PHI = slice(0, 3)


def components(M: torch.Tensor):
    checks.matrix(M, MATRIX_DIM, "M")
    return (M,)


def from_components(C: torch.Tensor) -> torch.Tensor:
    checks.matrix(C, MATRIX_DIM, "C")
    return C


def hat(phi: torch.Tensor) -> torch.Tensor:
    checks.vector(phi, DOF, "xi")
    return B.skew(B.first(phi))


def vee(X: torch.Tensor) -> torch.Tensor:
    """Vector of the skew part of X."""
    checks.matrix(X, MATRIX_DIM, "X")
    return B.last(B.unskew(X))


def exp_impl(phi: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula (3.7)."""
    checks.vector(phi, DOF, "xi")
    p = B.first(phi)
    return B.rotation(B.coefficients(p, 2), p)


def log_impl(C: torch.Tensor) -> torch.Tensor:
    """(3.10)-(3.11), accurate near 0 and pi (see blocks.rotation_log)."""
    checks.matrix(C, MATRIX_DIM, "M")
    return B.last(B.rotation_log(C))


def inverse(C: torch.Tensor) -> torch.Tensor:
    """C^T (a view of C)."""
    checks.matrix(C, MATRIX_DIM, "C")
    return C.transpose(-1, -2)


def adjoint(C: torch.Tensor) -> torch.Tensor:
    """Ad(C) = C (C itself)."""
    checks.matrix(C, MATRIX_DIM, "C")
    return C


# The tensor code of the operators torchsgal::so3_inverse and so3_adjoint (ops.py), which return
# new tensors; the group's ``inverse`` and ``adjoint`` above are views and run no operator.
def inverse_impl(C: torch.Tensor) -> torch.Tensor:
    checks.matrix(C, MATRIX_DIM, "M")
    return C.transpose(-1, -2).clone(memory_format=torch.contiguous_format)


def adjoint_impl(C: torch.Tensor) -> torch.Tensor:
    checks.matrix(C, MATRIX_DIM, "M")
    return C.clone(memory_format=torch.contiguous_format)


def ad(phi: torch.Tensor) -> torch.Tensor:
    return hat(phi)


@blocked(1)
def jl_impl(phi: torch.Tensor) -> torch.Tensor:
    """D(phi) = Gamma_1(phi), (3.8) (with the corrected u^u^ coefficient)."""
    checks.vector(phi, DOF, "xi")
    p = B.first(phi)
    return B.gamma_mat(B.coefficients(p, 3), 1, p)


@blocked(1)
def jl_inv_impl(phi: torch.Tensor) -> torch.Tensor:
    """D^-1(phi), (3.12)."""
    checks.vector(phi, DOF, "xi")
    return B.jac_inv_mat(B.first(phi))


def _jl_tmv(phi: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """J_l(phi)^T w = Gamma_1(-phi) w."""
    phi, w = B.same_rank((phi, 1), (w, 1))
    p = B.first(phi)
    return B.last(B.gamma_vec(B.coefficients(p, 3), 1, -p, B.first(w)))


def _jl_inv_tmv(phi: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """J_l(phi)^-T w = D^-1(-phi) w."""
    phi, w = B.same_rank((phi, 1), (w, 1))
    return B.last(B.jac_inv_vec(-B.first(phi), B.first(w)))


def _exp_pullback(C: torch.Tensor, G: torch.Tensor) -> torch.Tensor:
    """hat^T(C^T G) (exp's backward)."""
    return B.last(B.rotation_pullback(C, G))


def _log_pullback(C: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """C^-T vee^T(w) = C (w/2)^ (log's backward)."""
    r = B.rotation_skew_rows(C, 0.5 * B.first(w))
    return torch.stack([x for row in r for x in row], dim=-1).unflatten(-1, (3, 3))


def jr(phi: torch.Tensor) -> torch.Tensor:
    """J_r(phi) = J_l(-phi)."""
    checks.vector(phi, DOF, "xi")
    return jl(-phi)


def jr_inv(phi: torch.Tensor) -> torch.Tensor:
    """J_r(phi)^-1 = J_l(-phi)^-1."""
    checks.vector(phi, DOF, "xi")
    return jl_inv(-phi)


def act(C: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Points (..., 3) -> C p."""
    return B.act_homogeneous(C, p, "p", MATRIX_DIM)


def act_jacobian(C: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """d act(C exp(xi^), p) / d xi at 0 (..., 3, DOF), the right perturbation."""
    return B.act_homogeneous_jacobian(C, p, "p", MATRIX_DIM, hat, DOF)


def act_direction(C: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    return B.act_homogeneous(C, d, "d", MATRIX_DIM)


QUATERNION_ORDERS = ("wxyz", "xyzw")


def _quaternion_order(order) -> None:
    if not isinstance(order, str) or order not in QUATERNION_ORDERS:
        raise ValueError(f"order must be 'wxyz' (scalar first: GTSAM, Eigen) or 'xyzw' (scalar "
                         f"last: scipy, pypose, ROS), got {order!r}")


def from_quaternion(q: torch.Tensor, order: str, name: str = "q") -> torch.Tensor:
    """Rotation matrices (..., 3, 3) of quaternions q (..., 4) with components in ``order``
    ("wxyz" or "xyzw"); q is normalised here, at any length the dtype holds, subnormal included
    (ValueError for a quaternion that is exactly zero or not finite, where its values can be
    read), and q and -q give the same rotation.  ``name``: what errors call q."""
    _quaternion_order(order)
    checks.vector(q, 4, name)
    if order == "xyzw":
        q = q.roll(1, -1)
    # Scaled by its largest |component| first (as hypot): the sum of squares of q itself
    # overflows above ~1e154 (float64) / 1e19 (float32) and underflows below their square
    # roots.  q / |q| does not depend on the scale, so the scale carries no gradient.
    scale = q.detach().abs().amax(dim=-1, keepdim=True)
    if q.numel() and values_readable(q):
        bad = torch.stack(((scale == 0).any(), (~torch.isfinite(q)).any())).tolist()
        if bad[0]:
            raise ValueError(f"{name} has a quaternion of zero length, which is no rotation")
        if bad[1]:
            raise ValueError(f"{name} has a quaternion that is not finite (inf or NaN components)")
    u = q / scale
    u = u / torch.linalg.vector_norm(u, dim=-1, keepdim=True)
    return B.quaternion_rotation(*B.first(u))


def to_quaternion(C: torch.Tensor, order: str) -> torch.Tensor:
    """Unit quaternions (..., 4) of rotation matrices C (..., 3, 3), components in ``order``
    ("wxyz" or "xyzw"), with the scalar part w >= 0 (of q and -q, the one with w >= 0; at
    w = 0 exactly, either).  Each is computed from its largest of |w|, |x|, |y|, |z| (selected
    with a gather: no branch, no division by a small number), so it is accurate for every
    rotation, near pi included."""
    _quaternion_order(order)
    checks.matrix(C, MATRIX_DIM, "C")
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = B.entries(C)
    # 4 w^2, 4 x^2, 4 y^2, 4 z^2 of the unit quaternion
    t = torch.stack((1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22,
                     1 - m00 - m11 + m22), dim=-1)
    positive = t > 0
    r = torch.where(positive, torch.sqrt(torch.where(positive, t, torch.ones_like(t))), 0.0)
    # candidate k: 2 |q_k| q / sign(q_k) in (w, x, y, z), divided by 2 * 2 |q_k| below
    rows = torch.stack((
        torch.stack((t[..., 0], m21 - m12, m02 - m20, m10 - m01), dim=-1),
        torch.stack((m21 - m12, t[..., 1], m10 + m01, m02 + m20), dim=-1),
        torch.stack((m02 - m20, m10 + m01, t[..., 2], m12 + m21), dim=-1),
        torch.stack((m10 - m01, m02 + m20, m12 + m21, t[..., 3]), dim=-1),
    ), dim=-2)  # (..., 4, 4)
    # the largest |q_k| is >= 1/2, so r >= 1 where selected; the floor only keeps the others finite
    candidates = rows / (2.0 * r.clamp_min(0.1)).unsqueeze(-1)
    k = r.argmax(dim=-1, keepdim=True)
    q = torch.gather(candidates, -2, k.unsqueeze(-1).expand(*k.shape, 4)).squeeze(-2)
    q = torch.where(q[..., :1] < 0, -q, q)
    return q.roll(-1, -1) if order == "xyzw" else q


def random(batch_shape, dtype, device, generator=None) -> torch.Tensor:
    """A uniform (Haar) rotation; batch_shape an int or a sequence."""
    batch_shape = checks.shape(batch_shape, "batch_shape")
    checks.dtype_arg(dtype)
    return B.random_rotation(batch_shape, dtype, device, generator)


exp, log = make_exp_log(sys.modules[__name__])
jl, jl_inv = make_jacobians(sys.modules[__name__])
# inverse and adjoint: the views above
compose = make_products(sys.modules[__name__], compose_min_batch=2048)[0]
jl_tmv, jl_inv_tmv, exp_pullback, log_pullback = checked_backward_parts(sys.modules[__name__])
