"""SO(3) building blocks shared by every group (Barfoot, "Integral Forms", Sec. 3-4).

    Gamma_l(phi) = sum_n (phi^)^n / (n + l)! = I/l! + c_(l+1) phi^ + c_(l+2) phi^ phi^

Gamma_0 = C (Rodrigues, (3.7)), Gamma_1 = D = J_SO3 (3.8), Gamma_2 = E = N (3.9).  The
Q-type blocks of the SE(3), SE_2(3) and SGal(3) Jacobians follow from the derivative of
Gamma_l(phi) x with respect to phi (see ``q_block``), which avoids the cancellation-prone
closed forms printed in the papers.
"""
from __future__ import annotations

import math

import torch

from . import numerics


def skew(v: torch.Tensor) -> torch.Tensor:
    """v^ (..., 3, 3) from v (..., 3)."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack((o, -z, y, z, o, -x, -y, x, o), dim=-1).unflatten(-1, (3, 3))


def unskew(m: torch.Tensor) -> torch.Tensor:
    """The vector of the skew part of m (..., 3, 3): vee((m - m^T)/2)."""
    return 0.5 * torch.stack(
        (m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]),
        dim=-1,
    )


def skew_transpose(m: torch.Tensor) -> torch.Tensor:
    """Adjoint of ``skew`` for the Frobenius product: <m, v^> = <skew_transpose(m), v>."""
    return 2.0 * unskew(m)


def dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a * b).sum(-1, keepdim=True)


def theta_squared(phi: torch.Tensor) -> torch.Tensor:
    return (phi * phi).sum(-1)


def coefficients(phi: torch.Tensor, order: int = numerics.MAX_ORDER) -> list[torch.Tensor]:
    """[c_0 .. c_order](theta), each (..., 1) for broadcasting against vectors."""
    return [c.unsqueeze(-1) for c in numerics.series_coefficients(theta_squared(phi), order)]


def gamma_vec(c: list[torch.Tensor], l: int, phi: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Gamma_l(phi) x without forming the matrix."""
    px = torch.linalg.cross(phi, x, dim=-1)
    ppx = torch.linalg.cross(phi, px, dim=-1)
    return x / math.factorial(l) + c[l + 1] * px + c[l + 2] * ppx


def gamma_mat(c: list[torch.Tensor], l: int, phi: torch.Tensor) -> torch.Tensor:
    """Gamma_l(phi) as a (..., 3, 3) matrix; uses phi^ phi^ = phi phi^T - theta^2 I."""
    theta2 = theta_squared(phi)[..., None, None]
    a = c[l + 1][..., None]
    b = c[l + 2][..., None]
    eye = torch.eye(3, dtype=phi.dtype, device=phi.device)
    outer = phi.unsqueeze(-1) * phi.unsqueeze(-2)
    return (1.0 / math.factorial(l) - b * theta2) * eye + a * skew(phi) + b * outer


def rotation(c: list[torch.Tensor], phi: torch.Tensor) -> torch.Tensor:
    """C(phi) = Gamma_0(phi), Rodrigues' formula (3.7)."""
    return gamma_mat(c, 0, phi)


def gamma_vec_derivative(
    c: list[torch.Tensor], l: int, phi: torch.Tensor, x: torch.Tensor
) -> torch.Tensor:
    """d/dphi [Gamma_l(phi) x], a (..., 3, 3) matrix (needs c up to l + 4).

    With a = c_(l+1), b = c_(l+2) and e_m = c_m'/theta:
      d(a phi^x)/dphi = e_(l+1) (phi^x) phi^T - a x^
      d(b phi^phi^x)/dphi = e_(l+2) (phi^phi^x) phi^T + b ((phi.x) I + phi x^T - 2 x phi^T)
    """
    px = torch.linalg.cross(phi, x, dim=-1)
    ppx = torch.linalg.cross(phi, px, dim=-1)
    ea = numerics.series_derivative(c, l + 1)
    eb = numerics.series_derivative(c, l + 2)
    a = c[l + 1][..., None]
    b = c[l + 2][..., None]
    eye = torch.eye(3, dtype=phi.dtype, device=phi.device)
    outer = lambda u, w: u.unsqueeze(-1) * w.unsqueeze(-2)  # noqa: E731
    return (
        outer(ea * px + eb * ppx, phi)
        - a * skew(x)
        + b * (dot(phi, x)[..., None] * eye + outer(phi, x) - 2.0 * outer(x, phi))
    )


def q_block(c: list[torch.Tensor], phi: torch.Tensor, x: torch.Tensor, jac: torch.Tensor):
    """Q(x, phi) = int_0^1 (a Gamma_1(a phi) x)^ C(a phi) da, the off-diagonal block of the
    SE(3) left Jacobian (Barfoot Table 1; M(phi, nu) of (3.25)).

    From exp(J_l d) exp(xi) = exp(xi + d):  Q = d(Gamma_1 x)/dphi + (Gamma_1 x)^ Gamma_1.
    ``jac`` is Gamma_1(phi).  Returns (Q, Gamma_1 x).
    """
    g1x = gamma_vec(c, 1, phi, x)
    return gamma_vec_derivative(c, 1, phi, x) + skew(g1x) @ jac, g1x


def jac_inv_mat(phi: torch.Tensor) -> torch.Tensor:
    """D^-1(phi) = I - phi^/2 + d(theta) phi^ phi^, (3.12)."""
    theta2 = theta_squared(phi)[..., None, None]
    d = numerics.jinv_coefficient(theta_squared(phi))[..., None, None]
    eye = torch.eye(3, dtype=phi.dtype, device=phi.device)
    outer = phi.unsqueeze(-1) * phi.unsqueeze(-2)
    return (1.0 - d * theta2) * eye - 0.5 * skew(phi) + d * outer


def jac_inv_vec(phi: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """D^-1(phi) x without forming the matrix."""
    d = numerics.jinv_coefficient(theta_squared(phi)).unsqueeze(-1)
    px = torch.linalg.cross(phi, x, dim=-1)
    return x - 0.5 * px + d * torch.linalg.cross(phi, px, dim=-1)


def rotation_log(C: torch.Tensor) -> torch.Tensor:
    """phi = log(C)^vee with the angle in [0, pi], accurate near 0 and near pi.

    theta = atan2(|s|, c) with s = vee(C - C^T)/2 = sin(theta) u and c = (tr C - 1)/2.  For
    c >= LOG_SYMMETRIC_COS, phi = (theta / sin theta) s  (3.11); below it the axis comes from
    the symmetric part (C + C^T)/2 - c I = (1 - c) u u^T (its largest column), with the sign
    of s, so that nothing divides by sin(theta) near pi.
    """
    s = unskew(C)
    cos = 0.5 * (C[..., 0, 0] + C[..., 1, 1] + C[..., 2, 2] - 1.0)
    sin = torch.linalg.vector_norm(s, dim=-1)
    theta = torch.atan2(sin, cos)

    # Near 0 / moderate angles: theta / sin theta, Taylor when sin is tiny.
    tiny = sin < numerics.LOG_SIN_TAYLOR
    sin_safe = torch.where(tiny, torch.ones_like(sin), sin)
    t2 = theta * theta
    ratio = torch.where(tiny, 1.0 + t2 / 6.0 + 7.0 * t2 * t2 / 360.0, theta / sin_safe)
    phi_small = ratio.unsqueeze(-1) * s

    # Near pi: axis from the symmetric part.
    sym = 0.5 * (C + C.transpose(-1, -2)) - cos[..., None, None] * torch.eye(
        3, dtype=C.dtype, device=C.device
    )
    d0, d1, d2 = sym[..., 0, 0], sym[..., 1, 1], sym[..., 2, 2]
    col = torch.where(
        ((d0 >= d1) & (d0 >= d2)).unsqueeze(-1),
        sym[..., :, 0],
        torch.where((d1 >= d2).unsqueeze(-1), sym[..., :, 1], sym[..., :, 2]),
    )
    sign = torch.where(dot(col, s) < 0, -1.0, 1.0).to(C.dtype)
    near_pi = cos < numerics.LOG_SYMMETRIC_COS
    col_norm = torch.linalg.vector_norm(col, dim=-1, keepdim=True)
    col_norm = torch.where(near_pi.unsqueeze(-1), col_norm, torch.ones_like(col_norm))
    phi_pi = (sign * theta.unsqueeze(-1)) * col / col_norm
    return torch.where(near_pi.unsqueeze(-1), phi_pi, phi_small)


def block_matrix(rows, sizes: list[int], like: torch.Tensor) -> torch.Tensor:
    """Assemble a (..., n, n) matrix from blocks; ``None`` is a zero block.

    ``sizes`` are the block sizes of the partition; ``like`` is any (..., k) tensor whose
    batch shape, dtype and device the result takes.  Uses torch.cat only (vmap-safe).
    """
    batch = like.shape[:-1]
    out = []
    for i, row in enumerate(rows):
        parts = []
        for j, blk in enumerate(row):
            shape = batch + (sizes[i], sizes[j])
            parts.append(like.new_zeros(shape) if blk is None else blk.expand(shape))
        out.append(torch.cat(parts, dim=-1))
    return torch.cat(out, dim=-2)


def eye(n: int, like: torch.Tensor) -> torch.Tensor:
    return torch.eye(n, dtype=like.dtype, device=like.device)


def random_rotation(batch_shape, dtype, device, generator=None) -> torch.Tensor:
    """Uniformly distributed rotation matrices (normalised Gaussian quaternions)."""
    q = torch.randn(*batch_shape, 4, dtype=dtype, device=device, generator=generator)
    q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        (
            1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
            2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
            2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
        ),
        dim=-1,
    ).unflatten(-1, (3, 3))
