"""SO(3) building blocks shared by every group (Barfoot, "Integral Forms", Sec. 3-4).

    Gamma_l(phi) = sum_n (phi^)^n / (n + l)! = c_l I + c_(l+1) phi^ + c_(l+2) phi phi^T

(c_m from ``numerics``).  Gamma_0 = C (Rodrigues, Kelly-Giamou (3.7)), Gamma_1 = D = J_SO3 (3.8),
Gamma_2 = E (3.9).  The Q-type blocks of the SE(3), SE_2(3) and SGal(3) Jacobians follow from
the derivative of Gamma_l(phi) x with respect to phi (``q_block``), which avoids the
cancellation of the closed forms printed in the papers.

Layout: inside the library a 3-vector is stored component-first, (3, *batch), so that every
operation is elementwise on contiguous (*batch) tensors (several times faster on CPU than
strided (..., 3) views); scalars are (*batch) and broadcast against it.  Matrices keep the
public layout (..., 3, 3).  ``first``/``last`` convert at the boundary.
"""
from __future__ import annotations

import math

import torch

from . import affine, checks, numerics
from ._blocking import _is_wrapped


# ------------------------------------------------------------------------- layout
def first(x: torch.Tensor) -> torch.Tensor:
    """(..., k) -> contiguous (k, ...): one copy, after which every read is contiguous."""
    return x.movedim(-1, 0).contiguous()


def same_rank(*pairs: tuple[torch.Tensor, int]) -> list[torch.Tensor]:
    """(tensor, event dims) pairs -> the tensors with leading unit dimensions added so that
    their batch parts have one rank: component-first code (``first``) puts the components in
    front, where broadcasting would otherwise align one argument's components with another's
    batch."""
    rank = max(t.dim() - k for t, k in pairs)
    return [t.reshape((1,) * (rank + k - t.dim()) + t.shape) if t.dim() - k < rank else t for t, k in pairs]


def last(*parts: torch.Tensor) -> torch.Tensor:
    """Component-first parts (k_i, ...) -> one contiguous (..., sum k_i) (pass a scalar s as
    s[None])."""
    return torch.stack([comp for p in parts for comp in p.unbind(0)], dim=-1)


def vec(*components: torch.Tensor) -> torch.Tensor:
    return torch.stack(components, dim=0)


def column(v: torch.Tensor) -> torch.Tensor:
    """(3, ...) -> (..., 3, 1)."""
    return v.movedim(0, -1).unsqueeze(-1)


# ------------------------------------------------------------------- vector algebra
def cross(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    u0, u1, u2 = u
    v0, v1, v2 = v
    return torch.stack((u1 * v2 - u2 * v1, u2 * v0 - u0 * v2, u0 * v1 - u1 * v0), dim=0)


def dot(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


def last_axis_dot(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """sum(u * v) over the last axis (...), as (u * v) times a vector of ones: torch's CPU sum
    over a short last axis (3-vectors, residuals of a few rows) costs several times that."""
    w = u * v
    return w @ w.new_ones(w.shape[-1])


def theta_squared(phi: torch.Tensor) -> torch.Tensor:
    return dot(phi, phi)


def skew(v: torch.Tensor) -> torch.Tensor:
    """v^ (..., 3, 3) from v (3, ...)."""
    x, y, z = v
    o = torch.zeros_like(x)
    return torch.stack((o, -z, y, z, o, -x, -y, x, o), dim=-1).unflatten(-1, (3, 3))


def skew_times(x: torch.Tensor, M: torch.Tensor) -> torch.Tensor:
    """x^ M for x (..., 3) in the *public* layout and M (..., 3, m): column-wise cross products,
    one kernel (several times faster on CPU than forming x^ and a batched 3x3 matmul)."""
    return torch.linalg.cross(x.unsqueeze(-1), M, dim=-2)


def unskew(m: torch.Tensor) -> torch.Tensor:
    """The vector (3, ...) of the skew part of m (..., 3, 3): vee((m - m^T)/2)."""
    return 0.5 * vec(m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1])


def outer(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """u v^T (..., 3, 3) from u, v (3, ...)."""
    return u.movedim(0, -1).unsqueeze(-1) * v.movedim(0, -1).unsqueeze(-2)


def eye(n: int, like: torch.Tensor) -> torch.Tensor:
    return torch.eye(n, dtype=like.dtype, device=like.device)


# ------------------------------------------------------------------ Gamma blocks
def coefficients(phi: torch.Tensor, order: int = numerics.MAX_ORDER) -> list[torch.Tensor]:
    """[c_0 .. c_order](theta), each (...)."""
    return numerics.series_coefficients(theta_squared(phi), order)


def gamma_vec(c: list[torch.Tensor], l: int, phi: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Gamma_l(phi) x (3, ...) without forming the matrix; Gamma_l(-phi) x = Gamma_l^T x."""
    px = cross(phi, x)
    base = x if l < 2 else x / math.factorial(l)
    return base + c[l + 1] * px + c[l + 2] * cross(phi, px)


def sym_skew_entries(d, a, b, phi: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Row-major entries of d I + a phi^ + b phi phi^T from scalars (...)."""
    x, y, z = phi
    ax, ay, az = a * x, a * y, a * z
    bx, by = b * x, b * y
    bxy, bxz, byz = bx * y, bx * z, by * z
    return (d + bx * x, bxy - az, bxz + ay, bxy + az, d + by * y, byz - ax, bxz - ay, byz + ax,
            d + b * z * z)


def sym_skew_matrix(d, a, b, phi: torch.Tensor) -> torch.Tensor:
    return torch.stack(sym_skew_entries(d, a, b, phi), dim=-1).unflatten(-1, (3, 3))


def gamma_entries(c: list[torch.Tensor], l: int, phi: torch.Tensor):
    """Entries of Gamma_l = c_l I + c_(l+1) phi^ + c_(l+2) phi phi^T (phi^ phi^ = phi phi^T -
    theta^2 I and c_l = 1/l! - theta^2 c_(l+2))."""
    return sym_skew_entries(c[l], c[l + 1], c[l + 2], phi)


def gamma_mat(c: list[torch.Tensor], l: int, phi: torch.Tensor) -> torch.Tensor:
    """Gamma_l(phi) (..., 3, 3)."""
    return sym_skew_matrix(c[l], c[l + 1], c[l + 2], phi)


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
    px = cross(phi, x)
    ppx = cross(phi, px)
    ea = numerics.series_derivative(c, l + 1)
    eb = numerics.series_derivative(c, l + 2)
    a, b = c[l + 1], c[l + 2]
    # d I + a' x^ terms as one sym-skew-shaped matrix, plus the rank-one outer products
    diag = (b * dot(phi, x))[..., None, None] * eye(3, phi)
    return (
        outer(ea * px + eb * ppx - 2.0 * b * x, phi)
        + b[..., None, None] * outer(phi, x)
        + diag
        - a[..., None, None] * skew(x)
    )


def gamma_vec_derivative_t(
    c: list[torch.Tensor], l: int, phi: torch.Tensor, x: torch.Tensor, w: torch.Tensor
) -> torch.Tensor:
    """(d/dphi [Gamma_l(phi) x])^T w (3, ...), the transpose of ``gamma_vec_derivative``."""
    px = cross(phi, x)
    ppx = cross(phi, px)
    ea = numerics.series_derivative(c, l + 1)
    eb = numerics.series_derivative(c, l + 2)
    b = c[l + 2]
    return (
        phi * (ea * dot(px, w) + eb * dot(ppx, w) - 2.0 * b * dot(x, w))
        + c[l + 1] * cross(x, w)
        + b * (dot(phi, x) * w + x * dot(phi, w))
    )


def q_block(c: list[torch.Tensor], phi: torch.Tensor, x: torch.Tensor, jac: torch.Tensor):
    """Q(x, phi) = int_0^1 (a Gamma_1(a phi) x)^ C(a phi) da, the off-diagonal block of the
    SE(3) left Jacobian (Barfoot Table 1; M(phi, nu) of (3.25)).

    From exp(J_l d) exp(xi) = exp(xi + d):  Q = d(Gamma_1 x)/dphi + (Gamma_1 x)^ Gamma_1.
    ``jac`` is Gamma_1(phi) (..., 3, 3).
    """
    return gamma_vec_derivative(c, 1, phi, x) + skew_times(gamma_vec(c, 1, phi, x).movedim(0, -1), jac)


def jac_inv_mat(phi: torch.Tensor) -> torch.Tensor:
    """D^-1(phi) = I - phi^/2 + d(theta) phi^ phi^, (3.12)."""
    theta2 = theta_squared(phi)
    d = numerics.jinv_coefficient(theta2)
    return sym_skew_matrix(1.0 - d * theta2, torch.full_like(d, -0.5), d, phi)


def jac_inv_vec(phi: torch.Tensor, x: torch.Tensor, d: torch.Tensor | None = None) -> torch.Tensor:
    """D^-1(phi) x (3, ...) without forming the matrix (``d``: jinv_coefficient(theta^2))."""
    if d is None:
        d = numerics.jinv_coefficient(theta_squared(phi))
    px = cross(phi, x)
    return x - 0.5 * px + d * cross(phi, px)


def rotation_log(C: torch.Tensor) -> torch.Tensor:
    """phi = log(C)^vee (3, ...) with the angle in [0, pi], accurate near 0 and near pi.

    theta = atan2(|s|, c) with s = vee(C - C^T)/2 = sin(theta) u and c = (tr C - 1)/2.  For
    c >= LOG_SYMMETRIC_COS, phi = (theta / sin theta) s  (3.11); below it the axis comes from
    the symmetric part (C + C^T)/2 - c I = (1 - c) u u^T (its largest column), with the sign
    of s, so that nothing divides by sin(theta) near pi.
    """
    c00, c01, c02, c10, c11, c12, c20, c21, c22 = entries(C)
    s = 0.5 * vec(c21 - c12, c02 - c20, c10 - c01)
    cos = 0.5 * (c00 + c11 + c22 - 1.0)
    ss = dot(s, s)
    one = torch.ones_like(ss)
    sel, flt = numerics.select, (lambda m: m.to(C.dtype))  # exact 0/1 masks (numerics.select)
    positive = flt(ss > 0)
    sin = positive * torch.sqrt(sel(positive, ss, one))
    theta = torch.atan2(sin, cos)

    # Near 0 / moderate angles: theta / sin theta, Taylor when sin is tiny.
    tiny = flt(sin < numerics.log_sin_taylor())
    t2 = theta * theta
    ratio = sel(tiny, 1.0 + t2 / 6.0 + 7.0 * t2 * t2 / 360.0, theta / sel(tiny, one, sin))

    # Near pi: axis from the symmetric part, its largest diagonal entry's column.
    d0, d1, d2 = c00 - cos, c11 - cos, c22 - cos
    s01, s02, s12 = 0.5 * (c01 + c10), 0.5 * (c02 + c20), 0.5 * (c12 + c21)
    pick0 = flt((d0 >= d1) & (d0 >= d2))
    pick1 = flt(d1 >= d2)
    col = sel(pick0, vec(d0, s01, s02), sel(pick1, vec(s01, d1, s12), vec(s02, s12, d2)))
    near_pi = flt(cos < numerics.log_symmetric_cos())
    sign = 1.0 - 2.0 * flt(dot(col, s) < 0)
    col_norm = torch.sqrt(sel(near_pi, dot(col, col), one))
    return nan_where_not_finite(sel(near_pi, (sign * theta / col_norm) * col, ratio * s), C)


def nan_where_not_finite(value: torch.Tensor, M: torch.Tensor) -> torch.Tensor:
    """``value`` ((...) or components first, (k, ...), as this module's closed forms hold them),
    NaN where an entry of the matrix M (..., r, c) is not finite: an infinite entry gives NaN,
    as a NaN one does (atan2 would read it as an angle of 0, a quarter or a half turn)."""
    return torch.where(torch.isfinite(M).all(-1).all(-1), value, torch.full_like(value, math.nan))


def planar_angle(M: torch.Tensor) -> torch.Tensor:
    """theta (...) of the rotation block M[..., :2, :2]: atan2 of its skew and symmetric parts,
    in [-pi, pi] (-pi at a half turn whose skew part is -0 or rounds below zero, as atan2 gives
    it); NaN where an entry of the block is not finite (SO(2) and SE(2) log)."""
    t = torch.atan2(0.5 * (M[..., 1, 0] - M[..., 0, 1]), 0.5 * (M[..., 0, 0] + M[..., 1, 1]))
    return nan_where_not_finite(t, M[..., :2, :2])


# ----------------------------------------------------------------------- assembly
def block_matrix(rows, sizes: list[int], batch_shape, like: torch.Tensor) -> torch.Tensor:
    """Assemble a (..., n, n) matrix from (..., h, w) blocks; ``None`` is a zero block.

    ``sizes`` are the block sizes of the partition; ``like`` gives dtype and device.  Uses
    torch.cat only (vmap-safe).
    """
    batch = tuple(batch_shape)
    out = []
    for i, row in enumerate(rows):
        parts = []
        for j, blk in enumerate(row):
            shape = batch + (sizes[i], sizes[j])
            parts.append(like.new_zeros(shape) if blk is None else blk.expand(shape))
        out.append(torch.cat(parts, dim=-1))
    return torch.cat(out, dim=-2)


def homogeneous(rot, cols, bottom) -> torch.Tensor:
    """A (..., n, n) group matrix in one stack: ``rot`` the 9 row-major rotation entries, ``cols``
    the extra columns (each (3, ...)), ``bottom`` the last rows (lists of scalars (...))."""
    entries = []
    for i in range(3):
        entries.extend(rot[3 * i: 3 * i + 3])
        entries.extend(col[i] for col in cols)
    for row in bottom:
        entries.extend(row)
    n = 3 + len(cols)
    return torch.stack(entries, dim=-1).unflatten(-1, (n, n))


def entries(C: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Row-major entries of (..., 3, 3), each a contiguous (...)."""
    return first(C.flatten(-2)).unbind(0)


def transpose_entries(C: torch.Tensor) -> tuple[torch.Tensor, ...]:
    return entries(C.transpose(-1, -2))


def matvec_entries(e, v: torch.Tensor) -> torch.Tensor:
    """Row-major 3x3 entries times v (3, ...) -> (3, ...)."""
    return vec(*(e[3 * i] * v[0] + e[3 * i + 1] * v[1] + e[3 * i + 2] * v[2] for i in range(3)))


def rows(C: torch.Tensor) -> list[torch.Tensor]:
    """The rows of (..., 3, 3) as component-first vectors."""
    E = first(C[..., :3, :3].flatten(-2))
    return [E[0:3], E[3:6], E[6:9]]


def rotation_pullback(C: torch.Tensor, G: torch.Tensor) -> torch.Tensor:
    """2 unskew(C^T G[:3, :3]) = sum_k G[k, :3] x C[k, :]: the rotation part of hat^T(M^T G)."""
    Cr, Gr = rows(C), rows(G[..., :3, :3])
    return cross(Gr[0], Cr[0]) + cross(Gr[1], Cr[1]) + cross(Gr[2], Cr[2])


def rotation_skew_rows(C: torch.Tensor, p: torch.Tensor) -> list[torch.Tensor]:
    """The rows of C p^ (C (..., 3, 3), p (3, ...)): row_i = C[i, :] x p."""
    return [cross(r, p) for r in rows(C)]


def _tail_offset(parts: list[torch.Tensor], tail: tuple) -> torch.Tensor | None:
    """sum_j tail[j] parts[j] over the nonzero constants of the homogeneous tail (None if all are
    zero): what the tail adds to every point's row, once per element."""
    offset = None
    for part, v in zip(parts, tail):
        if v != 0:
            term = part if v == 1 else part * v
            offset = term if offset is None else offset + term
    return offset


def act_homogeneous(M: torch.Tensor, x: torch.Tensor, name: str, n: int, tail: tuple = (), rows: int = 3):
    """The first ``rows`` entries of M [x, *tail] for M (..., n, n) and x (..., rows): points,
    events, velocities and directions in homogeneous coordinates (CONVENTIONS.md), with the
    input checks (the matrix is named ``g``, as in the group classes' ``g.act(p)``)."""
    checks.matrix(M, n, "g")
    checks.vector(x, rows, name)
    checks.binary(M, 2, x, 1, "g", name)
    if M.dim() >= 3 and x.dim() >= 2 and M.shape[-3] == 1 and x.shape[-2] != 1:
        # one element per batch row acting on N points (M (..., 1, n, n), x (..., N, k)): one
        # matrix product x M^T over the N rows, not N products of (rows x k) by (k x 1); the
        # tail's columns of M times its constants, once per element, added after
        k, E = x.shape[-1], M[..., 0, :rows, :]
        return affine.rows_times(x, E[..., :k].mT, _tail_offset([E[..., k + j] for j in range(len(tail))], tail))
    if tail:  # constants built on x's device without a host-to-device copy
        x = torch.cat([x] + [torch.full_like(x[..., :1], v) for v in tail], dim=-1)
    return (M[..., :rows, : x.shape[-1]] @ x.unsqueeze(-1)).squeeze(-1)


_GENERATORS: dict = {}


def generators(hat, dof: int, like: torch.Tensor) -> torch.Tensor:
    """hat(e_j) for j < dof, (dof, n, n), in ``like``'s dtype and on its device: a constant,
    cached per group (its ``hat``), dtype and device, as rebuilding it costs 20-25 us of small
    operations a call.  Built fresh where ``numerics.fresh_constants`` says so (a fake-tensor
    trace, torch.compile, a CUDA graph's capture), and only plain tensors are cached (not the
    inference tensors or torch.func wrappers of a first call), as ``numerics._series_constants``."""
    key = (hat, like.dtype, like.device)
    fresh = numerics.fresh_constants(like.device)
    basis = None if fresh else _GENERATORS.get(key)
    if basis is None:
        basis = hat(torch.eye(dof, dtype=like.dtype, device=like.device))
        if not fresh and type(basis) is torch.Tensor and not basis.is_inference() and not _is_wrapped(basis):
            _GENERATORS[key] = basis
    return basis


def act_homogeneous_jacobian(M: torch.Tensor, x: torch.Tensor, name: str, n: int, hat, dof: int,
                             tail: tuple = (), rows: int = 3, size: int | None = None) -> torch.Tensor:
    """J (..., rows, dof) of act_homogeneous(M exp(xi^), x) at xi = 0 (the right perturbation):
    column j is the first ``rows`` entries of M hat(e_j) [x, *tail] (``hat`` the group's, the
    basis from ``generators``).  The input checks are act_homogeneous's; x has ``size`` entries
    (by default ``rows``).

    Two contractions of the same sum, J[r, j] = sum_a,b M[r, a] hat(e_j)[a, b] x_b, chosen by
    which side has fewer elements: where one element acts on many points (M broadcast over x's
    batch), P_b = M[:rows] hat(e_j)[:, b] is formed once per element and the points contracted
    with it in one matrix product; where every point has its own element, G = hat(e_j) x (a
    product of x with the constant basis) is formed per point and J = M[:rows] G, with no per-point
    (k, rows * dof) intermediate."""
    checks.matrix(M, n, "g")
    checks.vector(x, rows if size is None else size, name)
    checks.binary(M, 2, x, 1, "g", name)
    per_point = M.dim() > 2 and M.shape[:-2].numel() > 1 and \
        M.shape[:-2].numel() >= x.shape[:-1].numel()
    broadcast = not per_point and M.dim() >= 3 and x.dim() >= 2 and M.shape[-3] == 1 and x.shape[-2] != 1
    points = x.shape[-1]
    if tail and not broadcast:
        x = torch.cat([x] + [torch.full_like(x[..., :1], v) for v in tail], dim=-1)
    k = points + len(tail)
    basis = generators(hat, dof, M)[:, :, :k]  # (dof, n, k)
    if per_point:
        # G[..., a, j] = sum_b hat(e_j)[a, b] x_b, as x (..., k) times the basis (k, n * dof)
        G = (x @ basis.permute(2, 1, 0).reshape(k, n * dof)).unflatten(-1, (n, dof))
        return M[..., :rows, :] @ G
    # P[..., b, r, j] = sum_a M[..., r, a] hat(e_j)[a, b], as (..., k, rows * dof); the rows of
    # every element stacked into one matrix product with the basis (a batch of small products
    # with a broadcast right factor costs some tens of times more)
    P = (M[..., :rows, :].reshape(-1, n) @ basis.permute(1, 2, 0).reshape(n, k * dof)).reshape(
        M.shape[:-2] + (rows, k * dof))
    P = P.unflatten(-1, (k, dof)).transpose(-3, -2).flatten(-2)
    if broadcast:
        # one element per batch row, N points: one product over the rows (``affine.rows_times``),
        # the tail's rows of P times its constants added once per element
        P = P[..., 0, :, :]
        offset = _tail_offset([P[..., points + j, :] for j in range(len(tail))], tail)
        J = affine.rows_times(x, P[..., :points, :], offset)
    else:
        J = (x.unsqueeze(-2) @ P).squeeze(-2)
    return J.unflatten(-1, (rows, dof))


def random_rotation(batch_shape, dtype, device, generator=None) -> torch.Tensor:
    """Uniformly distributed rotation matrices (normalised Gaussian quaternions)."""
    q = torch.randn(4, *batch_shape, dtype=dtype, device=device, generator=generator)
    return quaternion_rotation(*(q / torch.sqrt((q * q).sum(0))))


def quaternion_rotation(w, x, y, z) -> torch.Tensor:
    """The rotation matrix (..., 3, 3) of the unit quaternion w + x i + y j + z k (each (...))."""
    return torch.stack(
        (
            1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
            2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
            2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
        ),
        dim=-1,
    ).unflatten(-1, (3, 3))


# ------------------------------------------------------------- general phi^ polynomials
def poly_vec(m0, m1, m2, phi: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """(m0 I + m1 phi^ + m2 phi^ phi^) x (3, ...) for scalars (...) (Sim(3)'s M(phi, lambda))."""
    px = cross(phi, x)
    return m0 * x + m1 * px + m2 * cross(phi, px)


def poly_mat(m0, m1, m2, phi: torch.Tensor) -> torch.Tensor:
    """m0 I + m1 phi^ + m2 phi^ phi^ (..., 3, 3), written as (m0 - theta^2 m2) I + m1 phi^ + m2 phi phi^T."""
    return sym_skew_matrix(m0 - theta_squared(phi) * m2, m1, m2, phi)


def poly_vec_derivative(m1, m2, e1, e2, phi: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """d/dphi [(m1 phi^ + m2 phi^ phi^) x] (..., 3, 3) for scalar functions m_k(theta) with
    e_k = m_k'(theta)/theta (the same algebra as ``gamma_vec_derivative``)."""
    px = cross(phi, x)
    ppx = cross(phi, px)
    diag = (m2 * dot(phi, x))[..., None, None] * eye(3, phi)
    return (
        outer(e1 * px + e2 * ppx - 2.0 * m2 * x, phi)
        + m2[..., None, None] * outer(phi, x)
        + diag
        - m1[..., None, None] * skew(x)
    )


def poly_inverse(m0, m1, m2, theta2, m_re):
    """Coefficients (n0, n1, n2) of (m0 I + m1 phi^ + m2 phi^ phi^)^-1 = n0 I + n1 phi^ + n2 phi^ phi^.

    On the eigenvalues 0, +-i theta of phi^, with b = m1/m0, c = m2/m0 (normalised so that no
    square of m0 overflows) and mu = re + i b theta, re = m_re/m0 = 1 - c theta^2:
    n0 = 1/m0, n1 = -b/(m0 |mu|^2), n2 = (b^2 - c re)/(m0 |mu|^2) (no division by theta).
    ``m_re`` = m0 - theta^2 m2 is the caller's, free of that cancellation: near a singular M
    (Sim(3) at theta = 2 pi k, lambda = 0) re is the small difference, and 1 - c theta^2 from
    the rounded c can be exactly 0 there (n1, n2 = 0 * inf).
    """
    n0 = 1.0 / m0
    b, c = m1 * n0, m2 * n0
    re = m_re * n0
    scale = n0 / (re * re + b * b * theta2)
    return n0, -b * scale, (b * b - c * re) * scale


def poly_vec_derivative_t(m1, m2, e1, e2, phi: torch.Tensor, x: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """(d/dphi [(m1 phi^ + m2 phi^ phi^) x])^T w (3, ...), the transpose of ``poly_vec_derivative``."""
    px = cross(phi, x)
    ppx = cross(phi, px)
    return (
        phi * (e1 * dot(px, w) + e2 * dot(ppx, w) - 2.0 * m2 * dot(x, w))
        + m1 * cross(x, w)
        + m2 * (dot(phi, x) * w + x * dot(phi, w))
    )
