"""The batched kernel of :class:`KinematicChain`: joint frames and twists, batch last.

Tensors hold the batch in the last axis (rotations (3, 3, B), vectors (3, B)), so that the
per-joint work is a few matrix products with constants and elementwise operations on
contiguous rows.  Each joint is put in a canonical frame whose z axis is the joint axis: with
Q_i a constant rotation taking e_z to the axis a_i, Rot(a_i, q) = Q_i Rz(q) Q_i^T, and the
canonical frame R'_i = R_i Q_i obeys

    R'_i = R'_(i-1) C_i Rz(q_i),   C_i = Q_(i-1)^T R_o,i Q_i,
    p_i  = p_(i-1) + R'_(i-1) (Q_(i-1)^T p_o,i)   (+ q_i z_i for a prismatic joint),

where z_i = R'_i e_z is the joint axis in the base frame.  A link at offset F after joint j
is at R'_j (Q_j^T F).  The products are those of the extended-pose chain (45).
"""
from __future__ import annotations

import torch


def axis_frame(a: torch.Tensor) -> torch.Tensor:
    """A rotation Q (3, 3), float64, with Q e_z = a (a unit vector)."""
    a = a.to(torch.float64)
    if float(a[2]) < 0.0:
        # Q = F Q'(F a), F = diag(1, -1, -1) a half turn about x: F a has a_z >= 0, so the
        # 1 / (1 + c) below stays >= 1/2 (near a = -e_z it would cancel and lose accuracy).
        F = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))
        return F @ axis_frame(F @ a)
    z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    v = torch.linalg.cross(z, a)
    c = float(a[2])
    K = torch.tensor([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]],
                     dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + K + K @ K / (1.0 + c)


class Kernel:
    """Constants of a chain in one dtype and device, and the batched passes over it."""

    def __init__(self, origins: torch.Tensor, axes: torch.Tensor, revolute: list[bool],
                 parents: list[int], base: torch.Tensor, dtype: torch.dtype,
                 device: torch.device):
        n = origins.shape[0]
        self.n = n
        self.revolute = list(revolute)
        self.parents = list(parents)  # the joint each joint follows (-1: the base), < its index
        self.serial = self.parents == list(range(-1, n - 1))
        self.Q = torch.stack([axis_frame(axes[i]) for i in range(n)])  # float64, host
        eye = torch.eye(3, dtype=torch.float64)
        mats = []
        for i in range(n):
            Q_prev = self.Q[self.parents[i]] if self.parents[i] >= 0 else eye
            C = Q_prev.T @ origins[i, :3, :3] @ self.Q[i]
            t = Q_prev.T @ origins[i, :3, 3]
            # out[r] = M @ R'[r] for each row r of R' (3, B): M = [C | t]^T, (4, 3)
            mats.append(torch.cat((C, t[:, None]), dim=1).T.contiguous().to(dtype=dtype, device=device))
        self.mats = mats
        # A[k, i] = 1 where joint i is joint k or one of its ancestors (lower triangular)
        A = torch.zeros(n, n, dtype=torch.float64)
        for k in range(n):
            i = k
            while i >= 0:
                A[k, i] = 1.0
                i = self.parents[i]
        self.ancestors = A.to(dtype=dtype, device=device)
        self.ancestor_rows = [[i for i in range(n) if A[k, i] > 0] for k in range(n)]
        self.base_R = base[:3, :3].to(dtype=dtype, device=device)
        self.base_p = base[:3, 3].to(dtype=dtype, device=device)
        self.rev_mask = torch.tensor(revolute, dtype=dtype, device=device)[:, None, None]  # (n, 1, 1)
        self.pris_mask = 1.0 - self.rev_mask
        self.dtype, self.device = dtype, device

    def link_constant(self, joint: int, offset: torch.Tensor) -> torch.Tensor:
        """(4, 3) [G_R | G_p]^T of a link at ``offset`` (4, 4, float64) after ``joint``."""
        Qt = self.Q[joint].T if joint >= 0 else torch.eye(3, dtype=torch.float64)
        G = torch.cat((Qt @ offset[:3, :3], (Qt @ offset[:3, 3])[:, None]), dim=1)
        return G.T.contiguous().to(dtype=self.dtype, device=self.device)

    def frames(self, q: torch.Tensor):
        """Canonical rotations (n + 1, 3, 3, B) and positions (n + 1, 3, B) of the base (index
        0) and the joints, for q (n, B)."""
        B = q.shape[1]
        s, c = torch.sin(q), torch.cos(q)
        R = self.base_R[:, :, None].expand(3, 3, B)
        p = self.base_p[:, None].expand(3, B)
        Rs, ps = [R], [p]
        for i in range(self.n):
            R, p = Rs[self.parents[i] + 1], ps[self.parents[i] + 1]
            out = torch.matmul(self.mats[i], R)  # (3, 4, B): rows of R' C and R' t
            A, t = out[:, :3, :], out[:, 3, :]
            if self.revolute[i]:  # A Rz(q): columns (c A0 + s A1, c A1 - s A0, A2)
                a0, a1 = A[:, 0, :], A[:, 1, :]
                R = torch.stack((c[i] * a0 + s[i] * a1, c[i] * a1 - s[i] * a0, A[:, 2, :]), dim=1)
                p = p + t
            else:
                R = A
                p = p + t + q[i] * A[:, 2, :]
            Rs.append(R)
            ps.append(p)
        return torch.stack(Rs), torch.stack(ps)

    @staticmethod
    def links(Rs: torch.Tensor, ps: torch.Tensor, index: torch.Tensor, G: torch.Tensor):
        """Rotations (L, 3, 3, B) and positions (L, 3, B) of links at stack ``index`` (L,)
        with constants G (L, 4, 3)."""
        Rj, pj = Rs.index_select(0, index), ps.index_select(0, index)
        out = torch.matmul(G[:, None], Rj)  # (L, 3, 4, B)
        return out[:, :, :3, :], pj + out[:, :, 3, :]

    def ancestor_sum(self, x: torch.Tensor) -> torch.Tensor:
        """sum over each joint's ancestors and itself of x (n, ...): a prefix sum on a serial
        chain, a product with the ancestor matrix on a tree."""
        flat = x.reshape(x.shape[0], -1)
        out = flat.cumsum(0) if self.serial else self.ancestors @ flat
        return out.view(x.shape)

    def screws(self, Rs: torch.Tensor, ps: torch.Tensor):
        """Unit screws (S_lin, S_ang) (n, 3, B) of the joints in the base frame: (o x z, z)
        for revolute joints, (z, 0) for prismatic ones."""
        z = Rs[1:, :, 2, :]
        S_ang = z * self.rev_mask
        S_lin = cross1(ps[1:], S_ang) + z * self.pris_mask
        return S_lin, S_ang


def cross1(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Cross product along axis 1 of batch-last vectors (k, 3, B), componentwise."""
    a0, a1, a2 = a.unbind(1)
    b0, b1, b2 = b.unbind(1)
    return torch.stack((a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0), dim=1)


def to_batch_first(x: torch.Tensor, batch: torch.Size, trailing: int) -> torch.Tensor:
    """(L, *tail, B) -> (*batch, L, *tail) for ``trailing`` tail axes."""
    perm = (x.dim() - 1, 0) + tuple(range(1, 1 + trailing))
    return x.permute(perm).reshape(*batch, x.shape[0], *x.shape[1:-1])


__all__ = ["Kernel", "axis_frame", "cross1", "to_batch_first"]
