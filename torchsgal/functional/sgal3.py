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
from . import checks, numerics
from ._autograd import checked_backward_parts, make_exp_log, make_jacobians, make_products
from ._blocking import blocked

NAME = "SGal3"
DOF = 10
MATRIX_DIM = 5
SIZES = [3, 3, 3, 1]
PHI = slice(6, 9)


def _split(xi: torch.Tensor):
    """(..., 10) -> rho, nu, phi (3, ...) and iota (...)."""
    X = B.first(xi)
    return X[0:3], X[3:6], X[6:9], X[9]


def _components(M: torch.Tensor):
    return M[..., :3, :3], M[..., :3, 3], M[..., :3, 4], M[..., 3, 4]


def components(M: torch.Tensor):
    """(C, v, r, tau) of a group matrix in the public layout: C (..., 3, 3), v, r (..., 3) and
    tau (...), as ``SGal3.time()`` and Sim3's scale (``from_components`` takes the same)."""
    checks.matrix(M, MATRIX_DIM, "M")
    return _components(M)


def _matrix(rot, v, r, tau) -> torch.Tensor:
    z, o = torch.zeros_like(tau), torch.ones_like(tau)
    return B.homogeneous(rot, [v, r], [[z, z, z, o, tau], [z, z, z, z, o]])


def from_components(C, v, r, tau) -> torch.Tensor:
    """C (..., 3, 3), v, r (..., 3), tau (...), batches broadcast -> (..., 5, 5)."""
    C, v, r, tau = checks.components(C=(C, (3, 3)), v=(v, (3,)), r=(r, (3,)), tau=(tau, ()))
    return _matrix(B.entries(C), B.first(v), B.first(r), tau)


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


def exp_parts(nu: torch.Tensor, phi: torch.Tensor, iota: torch.Tensor, rho: torch.Tensor | None = None):
    """(3.6) on component-first parts nu, phi, rho (3, ...) and iota (...): the 9 entries of
    C = Gamma_0(phi), v = Gamma_1 nu and r = Gamma_1 rho + iota Gamma_2 nu (rho None: zero,
    its term skipped), sharing phi^ nu between Gamma_1 nu and Gamma_2 nu."""
    c = B.coefficients(phi, 4)
    pn = B.cross(phi, nu)
    ppn = B.cross(phi, pn)
    v = nu + c[2] * pn + c[3] * ppn  # Gamma_1 nu
    r = iota * (0.5 * nu + c[3] * pn + c[4] * ppn)  # iota Gamma_2 nu
    if rho is not None:
        r = B.gamma_vec(c, 1, phi, rho) + r
    return B.gamma_entries(c, 0, phi), v, r


def _exp_components(xi: torch.Tensor):
    """(3.6): C (9 entries), v, r and tau = iota of xi; vectors component-first."""
    rho, nu, phi, iota = _split(xi)
    return (*exp_parts(nu, phi, iota, rho), iota)


def exp_impl(xi: torch.Tensor) -> torch.Tensor:
    """(3.6), the group matrix (..., 5, 5)."""
    checks.vector(xi, DOF, "xi")
    return _matrix(*_exp_components(xi))


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


@blocked(2)
def inverse_impl(M: torch.Tensor) -> torch.Tensor:
    """[[C^T, -C^T v, -C^T (r - tau v)], [0, 1, -tau], [0, 0, 1]]."""
    checks.matrix(M, MATRIX_DIM, "M")
    Ct = B.transpose_entries(M[..., :3, :3])
    v, r, tau = B.first(M[..., :3, 3]), B.first(M[..., :3, 4]), M[..., 3, 4]
    return _matrix(Ct, -B.matvec_entries(Ct, v), -B.matvec_entries(Ct, r - tau * v), -tau)


@blocked(2)
def adjoint_impl(M: torch.Tensor) -> torch.Tensor:
    """(3.16)."""
    checks.matrix(M, MATRIX_DIM, "M")
    C, v, r, tau = _components(M)
    t = tau[..., None, None]
    return B.block_matrix(
        [
            [C, -t * C, B.skew_times(r - tau[..., None] * v, C), v.unsqueeze(-1)],
            [None, C, B.skew_times(v, C), None],
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
    g2n = B.gamma_vec(c, 2, phi, nu)
    r = B.gamma_vec(c, 1, phi, rho) + iota * g2n
    dr = B.gamma_vec_derivative(c, 1, phi, rho) + i3 * B.gamma_vec_derivative(c, 2, phi, nu)
    N = dr + B.skew_times(r.movedim(0, -1), D) - i3 * Mb
    Enu = B.column(g2n)
    return D, D - E, N, Enu, Mb, i3


@blocked(1)
def jl_impl(xi: torch.Tensor) -> torch.Tensor:
    """Left Jacobian (3.21)-(3.23), as tensor operations (the closed form ``jl`` runs where its
    operator's C kernel does not apply)."""
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


@blocked(1)
def jl_inv_impl(xi: torch.Tensor) -> torch.Tensor:
    """Inverse of (3.23) by block back-substitution (the Jacobian is block upper-triangular),
    as tensor operations."""
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


def _transpose_parts(xi: torch.Tensor):
    """Quantities shared by the transposed products of (3.23)."""
    rho, nu, phi, iota = _split(xi)
    c = B.coefficients(phi, 6)
    pr, pn = B.cross(phi, rho), B.cross(phi, nu)
    ppr, ppn = B.cross(phi, pr), B.cross(phi, pn)
    g1n = nu + c[2] * pn + c[3] * ppn  # Gamma_1 nu
    g2n = 0.5 * nu + c[3] * pn + c[4] * ppn  # Gamma_2 nu
    r = rho + c[2] * pr + c[3] * ppr + iota * g2n
    return rho, nu, phi, iota, c, pr, ppr, pn, ppn, g1n, g2n, r


def _coupling_t(parts, a, b):
    """(S, z) with N^T a + M^T b = S + D^T z (N, M of _jl_blocks), all vector operations.

    Sums gvdt(1, rho, a) + iota gvdt(2, nu, a) + gvdt(1, nu, b') with b' = b - iota a
    (B.gamma_vec_derivative_t written out to share its cross products), and
    z = a x r + b' x Gamma_1 nu.
    """
    rho, nu, phi, iota, c, pr, ppr, pn, ppn, g1n, g2n, r = parts
    e2, e3, e4 = (numerics.series_derivative(c, m) for m in (2, 3, 4))
    bp = b - iota * a
    u1 = iota * e3 * a + e2 * bp
    u2 = iota * e4 * a + e3 * bp
    u3 = iota * c[4] * a + c[3] * bp
    u4 = iota * c[3] * a + c[2] * bp
    scal = (e2 * B.dot(pr, a) + e3 * B.dot(ppr, a) - 2.0 * c[3] * B.dot(rho, a)
            + B.dot(pn, u1) + B.dot(ppn, u2) - 2.0 * B.dot(nu, u3))
    S = (phi * scal + c[2] * B.cross(rho, a) + B.cross(nu, u4)
         + c[3] * (B.dot(phi, rho) * a + rho * B.dot(phi, a))
         + B.dot(phi, nu) * u3 + nu * B.dot(phi, u3))
    return S, B.cross(a, r) + B.cross(bp, g1n)


def _jl_tmv(xi: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """J_l(xi)^T w with vector operations only (the transposed blocks of (3.23))."""
    xi, w = B.same_rank((xi, 1), (w, 1))
    parts = _transpose_parts(xi)
    phi, iota, c, g2n = parts[2], parts[3], parts[4], parts[10]
    w_rho, w_nu, w_phi, w_iota = _split(w)
    p = B.cross(phi, w_rho)
    pp = B.cross(phi, p)
    DT_w_rho = w_rho - c[2] * p + c[3] * pp
    ET_w_rho = 0.5 * w_rho - c[3] * p + c[4] * pp
    o_nu = B.gamma_vec(c, 1, -phi, w_nu) - iota * (DT_w_rho - ET_w_rho)
    S, z = _coupling_t(parts, w_rho, w_nu)
    o_phi = S + B.gamma_vec(c, 1, -phi, z + w_phi)
    o_iota = B.dot(g2n, w_rho) + w_iota
    return B.last(DT_w_rho, o_nu, o_phi, o_iota[None])


def _jl_inv_tmv(xi: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """J_l(xi)^-T g by forward substitution on the transposed blocks of (3.23)."""
    xi, g = B.same_rank((xi, 1), (g, 1))
    parts = _transpose_parts(xi)
    phi, iota, c, g2n = parts[2], parts[3], parts[4], parts[10]
    g_rho, g_nu, g_phi, g_iota = _split(g)
    d = numerics.jinv_coefficient(B.theta_squared(phi))
    y_rho = B.jac_inv_vec(-phi, g_rho, d)
    p = B.cross(phi, y_rho)
    LT_y_rho = 0.5 * y_rho - (c[2] - c[3]) * p + (c[3] - c[4]) * B.cross(phi, p)  # (D - E)^T
    y_nu = B.jac_inv_vec(-phi, g_nu + iota * LT_y_rho, d)
    S, z = _coupling_t(parts, y_rho, y_nu)
    y_phi = B.jac_inv_vec(-phi, g_phi - S, d) - z  # D^-T (g - S - D^T z)
    y_iota = g_iota - B.dot(g2n, y_rho)
    return B.last(y_rho, y_nu, y_phi, y_iota[None])


def _exp_pullback(M: torch.Tensor, G: torch.Tensor) -> torch.Tensor:
    """hat^T(M^T G), the tangent vector paired with a matrix cotangent G (exp's backward)."""
    M, G = B.same_rank((M, 2), (G, 2))
    Ct = B.transpose_entries(M[..., :3, :3])
    g5 = B.first(G[..., :3, 4])
    w_iota = B.dot(B.first(M[..., :3, 3]), g5) + G[..., 3, 4]
    return B.last(B.matvec_entries(Ct, g5), B.matvec_entries(Ct, B.first(G[..., :3, 3])),
                  B.rotation_pullback(M[..., :3, :3], G), w_iota[None])


def _log_pullback(M: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """M^-T vee^T(w) (log's backward): with M^-T = [[C, 0, 0], [a^T, 1, 0], [b^T, -tau, 1]],
    a = -C^T v, b = -C^T (r - tau v), and vee^T(w) = hat(w with phi halved)."""
    M, w = B.same_rank((M, 2), (w, 1))
    rho, nu, phi, iota = _split(w)
    half = 0.5 * phi
    C = M[..., :3, :3]
    Ce, Ct = B.entries(C), B.transpose_entries(C)
    v, r, tau = B.first(M[..., :3, 3]), B.first(M[..., :3, 4]), M[..., 3, 4]
    a = -B.matvec_entries(Ct, v)
    b = -B.matvec_entries(Ct, r - tau * v)
    rot = [x for row in B.rotation_skew_rows(C, half) for x in row]
    ah, bh = B.cross(a, half), B.cross(b, half)
    bottom = [[ah[0], ah[1], ah[2], B.dot(a, nu), B.dot(a, rho) + iota],
              [bh[0], bh[1], bh[2], B.dot(b, nu), B.dot(b, rho) - tau * iota]]
    return B.homogeneous(rot, [B.matvec_entries(Ce, nu), B.matvec_entries(Ce, rho)], bottom)


def jr(xi: torch.Tensor) -> torch.Tensor:
    """J_r(xi) = J_l(-xi)."""
    checks.vector(xi, DOF, "xi")
    return jl(-xi)


def jr_inv(xi: torch.Tensor) -> torch.Tensor:
    """J_r(xi)^-1 = J_l(-xi)^-1."""
    checks.vector(xi, DOF, "xi")
    return jl_inv(-xi)


def act(M: torch.Tensor, e: torch.Tensor) -> torch.Tensor:
    """Events [x, t, 1] -> (C x + v t + r, t + tau), (3.31)."""
    return B.act_homogeneous(M, e, "e", MATRIX_DIM, (1.0,), rows=4)


def act_jacobian(M: torch.Tensor, e: torch.Tensor) -> torch.Tensor:
    """d act(M exp(xi^), e) / d xi at 0 (..., 4, DOF), the right perturbation."""
    return B.act_homogeneous_jacobian(M, e, "e", MATRIX_DIM, hat, DOF, (1.0,), rows=4)


def act_velocity(M: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Inertial velocities [u, 1, 0] -> C u + v."""
    return B.act_homogeneous(M, u, "u", MATRIX_DIM, (1.0,))


def act_direction(M: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """Directions [d, 0, 0] -> C d."""
    return B.act_homogeneous(M, d, "d", MATRIX_DIM)


# ------------------------------------------------------------ packed layout for long chains
# P (16, ...) = [C row-major (9), v (3), r (3), tau], component-first.  A product in this
# layout is ~90 elementwise operations: 4-6x faster on CPU than a batched 5x5 matmul at
# large batches (the IMU scans), slower for a single small product.


def pack(M: torch.Tensor) -> torch.Tensor:
    """Group matrices (..., 5, 5) -> the packed layout (16, ...).  Sliced, not gathered with an
    index tensor (which would be copied from the host to the device on every call)."""
    checks.matrix(M, MATRIX_DIM, "M")
    parts = (M[..., :3, :3].flatten(-2), M[..., :3, 3], M[..., :3, 4], M[..., 3, 4:])
    return B.first(torch.cat(parts, dim=-1))


def exp_packed(xi: torch.Tensor) -> torch.Tensor:
    """exp (3.6) straight into the packed layout: (..., 10) -> (16, ...).  Not differentiated
    by a custom rule (plain autograd through the closed form)."""
    checks.vector(xi, DOF, "xi")
    C, v, r, iota = _exp_components(xi)
    return torch.stack((*C, *v.unbind(0), *r.unbind(0), iota), dim=0)


def _check_packed(P: torch.Tensor, name: str) -> None:
    checks.floating(P, name)
    if P.dim() < 1 or P.shape[0] != 16:
        raise ValueError(f"{name} must have shape (16, ...), got {tuple(P.shape)}")


def unpack(P: torch.Tensor) -> torch.Tensor:
    """The packed layout (16, ...) -> group matrices (..., 5, 5)."""
    _check_packed(P, "P")
    return _matrix(P[0:9].unbind(0), P[9:12], P[12:15], P[15])


def packed_identity(like: torch.Tensor) -> torch.Tensor:
    """The identity in the packed layout, (16,) + (1,) * (like.dim() - 1), dtype/device of ``like``
    (filled on the device: no host data copied)."""
    checks.floating(like, "like")
    e = like.new_zeros(16)
    e[0:9:4] = 1.0  # the diagonal of C, entries 0, 4, 8
    return e.reshape((16,) + (1,) * (like.dim() - 1))


def compose_packed(P1: torch.Tensor, P2: torch.Tensor) -> torch.Tensor:
    """Product in the packed layout: (C1 C2, C1 v2 + v1, C1 r2 + tau2 v1 + r1, tau1 + tau2)."""
    _check_packed(P1, "P1")
    _check_packed(P2, "P2")
    checks.same_device_dtype(P1=P1, P2=P2)
    checks.broadcast_batch(P1=P1.shape[1:], P2=P2.shape[1:])  # the batch follows the 16 rows
    a, b = P1.unbind(0), P2.unbind(0)
    C1, v1, r1, t1 = a[0:9], a[9:12], a[12:15], a[15]
    C2, v2, r2, t2 = b[0:9], b[9:12], b[12:15], b[15]

    def row_times(i, x0, x1, x2):  # row i of C1 times the vector (x0, x1, x2)
        return torch.addcmul(torch.addcmul(C1[3 * i] * x0, C1[3 * i + 1], x1), C1[3 * i + 2], x2)

    out = [row_times(i, C2[j], C2[3 + j], C2[6 + j]) for i in range(3) for j in range(3)]
    out += [row_times(i, *v2) + v1[i] for i in range(3)]
    out += [torch.addcmul(row_times(i, *r2) + r1[i], t2, v1[i]) for i in range(3)]
    out.append(t1 + t2)
    return torch.stack(out, dim=0)


def random(batch_shape, dtype, device, generator=None) -> torch.Tensor:
    """A uniform rotation, standard normal velocity, position and time; batch_shape an int or a
    sequence."""
    batch_shape = checks.shape(batch_shape, "batch_shape")
    checks.dtype_arg(dtype)
    C = B.random_rotation(batch_shape, dtype, device, generator)
    v, r = torch.randn(2, 3, *batch_shape, dtype=dtype, device=device, generator=generator)
    tau = torch.randn(batch_shape, dtype=dtype, device=device, generator=generator)
    return _matrix(B.entries(C), v, r, tau)


exp, log = make_exp_log(sys.modules[__name__])
jl, jl_inv = make_jacobians(sys.modules[__name__])
compose, adjoint, inverse = make_products(sys.modules[__name__])
jl_tmv, jl_inv_tmv, exp_pullback, log_pullback = checked_backward_parts(sys.modules[__name__])
