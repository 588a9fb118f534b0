"""Serial kinematic chains with arbitrary joint axes: pose, velocity, acceleration, Jacobians.

A chain is a base transform, then for each actuated joint i a fixed origin O_i (the product of
the URDF joint origins and fixed joints since the previous actuated joint) followed by the
joint motion M_i(q_i) (a rotation by q_i about the unit axis a_i, or a translation q_i a_i);
a link's frame is a fixed offset after the last actuated joint before it.  This is the link
structure of the GDH chain (Mahony, Kelly and Weiss, Section 5, (43)-(45)) with DH's
Rz Tz Tx Rx factors replaced by a general fixed transform, so that the closed forms of
(48)-(50) carry over: the chain's velocity is the sum of the joints' inputs transported by
the adjoint of their frames, and its derivative adds the brackets of those inputs.

In the base frame (spatial twists, tangent order [linear, angular] as SE(3)'s [rho, phi]),
with z_i the world joint axis and o_i the world joint origin, joint i contributes the unit
screw S_i = (o_i x z_i, z_i) (revolute) or (z_i, 0) (prismatic).  Then

    V_k   = sum_(i <= k) S_i qd_i                       (spatial velocity after joint k, (50))
    dV_k  = sum_(i <= k) S_i qdd_i + ad(V_i) S_i qd_i    (its derivative; dS_i/dt = ad(V_i) S_i)

with ad((v, w)) (n, s) = (w x n + v x s, w x s).  A point p fixed to link k moves with
dp/dt = N_k + W_k x p and d2p/dt2 = dN_k + dW_k x p + W_k x dp/dt, for V_k = (N_k, W_k).
The body twist is Ad(T^-1) V_k and the body acceleration Ad(T^-1) dV_k.  All of these are
cumulative sums over the joint axis: only the pose needs a loop over the joints (the product
(45)), none over the batch.
"""
from __future__ import annotations

import dataclasses
import math
import numbers
from collections.abc import Mapping, Sequence

import torch

from ..functional import checks
from ..functional.checks import SUPPORTED_DTYPES
from ..groups import SE3
from ._core import Kernel, to_batch_first
from ._core import cross1 as _cross1
from .state import CONTINUOUS, JOINT_KINDS, PRISMATIC, REVOLUTE, ChainState, Joint, _transform

FRAMES = ("base", "body", "spatial")


class KinematicChain:
    """A serial chain of revolute, continuous and prismatic joints about arbitrary axes.

    Build it from a robot description with :func:`torchsgal.kinematics.from_urdf`,
    :meth:`from_dh` (standard or modified DH), :meth:`from_gdh` or
    :func:`torchsgal.kinematics.from_pk`; the constructor takes the joints and links directly.

    Args:
        joints: the actuated joints, root to end (:class:`Joint`).
        links: {link name: (joint index, (4, 4) offset)}: the link frame is the offset after
            the frame of joint ``index`` (``-1``: after the base, before any joint).
        end_link: the link whose kinematics ``forward`` and ``jacobian`` return by default.
        base: the base transform (None, SE3 or (4, 4)) applied before the chain: poses are in
            the frame the base maps into.
        tool: a transform applied after the end link (the tool centre point).
        dtype, device: of the chain's constants; q, qdot, qddot must match them (nothing is
            cast).  Change them with :meth:`to`.
        name: a label for messages.
        root_link: the name of the base link.
        parents: for a tree, the index of the joint each joint follows (-1: the base), each
            smaller than its own index; None for a serial chain (joint i follows i - 1).
        end_links: a tree's branch ends (``forward(q, links=chain.end_links)``); ``end_link``
            is the default link of ``forward`` and ``jacobian``.

    Joint limits are ``lower`` and ``upper`` ((n,) tensors, -inf / inf where there are none;
    a limit that is not a real number, or NaN, or a negative ``velocity``, raises naming it).
    Joint axes are normalised (a zero or non-finite axis is a ValueError naming
    ``joints[i].axis``); joint origins, base, tool and link offsets are checked as rigid
    transforms and copied, so later changes to the caller's tensors do not reach the chain.
    """

    def __init__(
        self,
        joints: Sequence[Joint],
        links: Mapping[str, tuple[int, torch.Tensor]],
        end_link: str,
        *,
        base=None,
        tool=None,
        dtype: torch.dtype = torch.float64,
        device=None,
        name: str = "chain",
        root_link: str = "base",
        parents: Sequence[int] | None = None,
        end_links: Sequence[str] | None = None,
    ):
        dtype = checks.dtype_arg(dtype)
        joints = list(joints)
        if not joints:
            raise ValueError(f"a chain needs at least one actuated joint, got none ({name!r})")
        for i, j in enumerate(joints):
            if not isinstance(j, Joint):
                raise TypeError(f"joints[{i}] must be a Joint, got {type(j).__name__}")
            if j.kind not in JOINT_KINDS:
                raise ValueError(f"joints[{i}] ({j.name!r}) kind must be one of {JOINT_KINDS}, "
                                 f"got {j.kind!r}")
            lower = _limit(j.lower, f"joints[{i}].lower ({j.name!r})", "-inf for no limit")
            upper = _limit(j.upper, f"joints[{i}].upper ({j.name!r})", "inf for no limit")
            velocity = _limit(j.velocity, f"joints[{i}].velocity ({j.name!r})", "inf for no limit")
            if not lower <= upper:
                raise ValueError(f"joint {j.name!r}: lower limit {lower} exceeds upper {upper}")
            if velocity < 0:
                raise ValueError(f"joints[{i}].velocity ({j.name!r}) must be >= 0 (inf for no "
                                 f"limit), got {velocity}")
            # own copies: a unit axis and a checked origin the caller cannot change later
            joints[i] = dataclasses.replace(
                j, axis=_unit_axis(j.axis, f"joints[{i}].axis ({j.name!r})"),
                origin=_transform(j.origin, f"joints[{i}].origin ({j.name!r})"),
                lower=lower, upper=upper, velocity=velocity)
        names = [j.name for j in joints]
        if len(set(names)) != len(names):
            raise ValueError(f"joint names must be unique, got {names}")
        if end_link not in links:
            raise ValueError(f"end_link {end_link!r} is not a link of the chain; links: "
                             f"{sorted(links)}")
        self.name = name
        self.joints = tuple(joints)
        self.joint_names = tuple(names)
        self.n_joints = len(joints)
        self.root_link = root_link
        self.end_link = end_link
        self.end_links = tuple(end_links) if end_links is not None else (end_link,)
        for k in self.end_links:
            if k not in links:
                raise ValueError(f"end_links: {k!r} is not a link of the chain")
        n = len(joints)
        self.parents = tuple(range(-1, n - 1)) if parents is None else tuple(
            checks.integer(x, f"parents[{i}]", -1) for i, x in enumerate(parents))
        if len(self.parents) != n or any(x >= i for i, x in enumerate(self.parents)):
            raise ValueError(f"parents must give, for each of the {n} joints, an earlier joint's "
                             f"index or -1 (the base), got {list(self.parents)}")
        self._base64 = _transform(base, "base")
        self._tool64 = _transform(tool, "tool")
        self._links64 = {}
        for k, (idx, off) in links.items():
            idx = checks.integer(idx, f"links[{k!r}] joint index", -1)
            if idx >= self.n_joints:
                raise ValueError(f"links[{k!r}] joint index must be in [-1, {self.n_joints - 1}], "
                                 f"got {idx}")
            self._links64[k] = (idx, _transform(off, f"links[{k!r}] offset"))
        self.link_names = tuple(self._links64)
        self._build(dtype, torch.device("cpu") if device is None else torch.device(device))

    # ----------------------------------------------------------------- constants
    def _build(self, dtype: torch.dtype, device: torch.device) -> None:
        """The chain's constants in ``dtype`` on ``device``."""
        f64 = torch.float64
        origins = torch.stack([j.origin.to("cpu", f64) for j in self.joints])
        axes = torch.tensor([j.axis for j in self.joints], dtype=f64)
        self._kernel = Kernel(origins, axes, [j.kind != PRISMATIC for j in self.joints],
                              list(self.parents), self._base64, dtype, device)
        self._lower = torch.tensor([j.lower for j in self.joints], dtype=dtype, device=device)
        self._upper = torch.tensor([j.upper for j in self.joints], dtype=dtype, device=device)
        self._dtype, self._device = dtype, device
        self._link_cache: dict = {}

    def _link_constants(self, link_names: Sequence[str]) -> tuple[torch.Tensor, torch.Tensor]:
        """(stack indices (L,) of the links' last joints (0: the base), constants (L, 4, 3))."""
        key = tuple(link_names)
        if key not in self._link_cache:
            idx, consts = [], []
            for k in link_names:
                j, off = self._links64[k]
                if k == self.end_link:
                    off = off @ self._tool64
                idx.append(j + 1)
                consts.append(self._kernel.link_constant(j, off))
            self._link_cache[key] = (torch.tensor(idx, device=self._device), torch.stack(consts))
        return self._link_cache[key]

    @property
    def dtype(self) -> torch.dtype:
        """The dtype of the chain, which q, qdot and qddot must have."""
        return self._dtype

    @property
    def device(self) -> torch.device:
        """The device of the chain, where q, qdot and qddot must be."""
        return self._device

    @property
    def lower(self) -> torch.Tensor:
        """(n,) lower joint limits (-inf where a joint has none)."""
        return self._lower

    @property
    def upper(self) -> torch.Tensor:
        """(n,) upper joint limits (inf where a joint has none)."""
        return self._upper

    @property
    def base(self) -> SE3:
        """The base transform (a copy)."""
        return SE3.from_matrix(self._base64.to(self._device, self._dtype, copy=True))

    @property
    def tool(self) -> SE3:
        """The tool transform after the end link (a copy)."""
        return SE3.from_matrix(self._tool64.to(self._device, self._dtype, copy=True))

    def to(self, dtype: torch.dtype | None = None, device=None) -> KinematicChain:
        """A copy of the chain in ``dtype`` and on ``device`` (unchanged where None)."""
        new = object.__new__(KinematicChain)
        new.__dict__.update(self.__dict__)
        new._build(checks.dtype_arg(dtype) if dtype is not None else self._dtype,
                   torch.device(device) if device is not None else self._device)
        return new

    def __repr__(self) -> str:
        kinds = "".join({REVOLUTE: "R", CONTINUOUS: "C", PRISMATIC: "P"}[j.kind] for j in self.joints)
        return (f"KinematicChain({self.name!r}, {self.root_link!r} -> {self.end_link!r}, "
                f"{self.n_joints} joints {kinds}, dtype={self._dtype})")

    def within_limits(self, q: torch.Tensor, tol: float = 0.0) -> torch.Tensor:
        """(...,) bool: every joint of q within [lower - tol, upper + tol]."""
        q = self._joint_tensor(q, "q")
        tol = checks.finite_number(tol, "tol", ">= 0")
        return ((q >= self._lower - tol) & (q <= self._upper + tol)).all(dim=-1)

    def random_configuration(self, batch_shape=(), generator: torch.Generator | None = None,
                             unbounded_range: float = math.pi) -> torch.Tensor:
        """(*batch_shape, n) joint positions, uniform within the limits.

        A joint with both limits is sampled in [lower, upper]; with one limit, in an interval
        of width 2 * unbounded_range from it: [lower, lower + 2 r] or [upper - 2 r, upper];
        with none, in [-r, r] (r = ``unbounded_range``, default pi)."""
        shape = checks.shape(batch_shape, "batch_shape")
        span = checks.finite_number(unbounded_range, "unbounded_range", "> 0")
        if generator is not None and not isinstance(generator, torch.Generator):
            raise TypeError(f"generator must be None or a torch.Generator, got {type(generator).__name__}")
        has_lo, has_hi = torch.isfinite(self._lower), torch.isfinite(self._upper)
        lo = torch.where(has_lo, self._lower, torch.where(has_hi, self._upper - 2 * span, -span))
        hi = torch.where(has_hi, self._upper, torch.where(has_lo, self._lower + 2 * span, span))
        u = torch.rand(*shape, self.n_joints, generator=generator, dtype=self._dtype,
                       device=generator.device if generator is not None else self._device)
        return lo + (hi - lo) * u.to(self._device)

    # ---------------------------------------------------------------- validation
    def _joint_tensor(self, x, name: str, like: torch.Tensor | None = None) -> torch.Tensor:
        if not isinstance(x, torch.Tensor):
            raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
        checks.dense(x, name)
        if x.dtype not in SUPPORTED_DTYPES:
            raise TypeError(f"{name} must have a floating dtype (torch.float32 or "
                            f"torch.float64), got {x.dtype}")
        if x.dim() < 1 or x.shape[-1] != self.n_joints:
            raise ValueError(f"{name} must have shape (..., {self.n_joints}) for the "
                             f"{self.n_joints} joints of {self.name!r} {list(self.joint_names)}, "
                             f"got {tuple(x.shape)}")
        try:
            checks.same_device_dtype(**{f"the chain {self.name!r}": self._lower, name: x})
        except (TypeError, ValueError) as err:
            raise type(err)(f"{err} (a chain's dtype and device are set when it is built; "
                            f"use chain.to(dtype=..., device=...))") from None
        if like is not None:
            checks.broadcast_batch(q=like.shape[:-1], **{name: x.shape[:-1]})
        return x

    def _link_names(self, links, all_links: bool) -> tuple[list[str], bool]:
        """The requested links and whether a link axis is kept."""
        all_links = checks.boolean(all_links, "all_links")
        if all_links:
            if links is not None:
                raise ValueError("give either links or all_links=True, not both")
            return list(self.link_names), True
        if links is None:
            return [self.end_link], False
        if isinstance(links, str):
            names, keep = [links], False
        else:
            try:
                names, keep = list(links), True
            except TypeError:
                raise TypeError(f"links must be a link name, a list of them or None, "
                                f"got {links!r}") from None
        if not names:
            raise ValueError("links must name at least one link")
        for k in names:
            if not isinstance(k, str) or k not in self._links64:
                raise ValueError(f"unknown link {k!r} of the chain {self.name!r}; its links are "
                                 f"{list(self.link_names)}")
        return names, keep

    # -------------------------------------------------------------- the core
    def forward(
        self,
        q: torch.Tensor,
        qdot: torch.Tensor | None = None,
        qddot: torch.Tensor | None = None,
        *,
        links: str | Sequence[str] | None = None,
        all_links: bool = False,
    ) -> ChainState:
        """Pose and, with qdot (and qddot), velocity (and acceleration) of links (module doc).

        q, qdot, qddot: (..., n) joint positions, velocities, accelerations (broadcast
        together); qddot needs qdot.  ``links``: a link name (fields of batch (...)) or a
        sequence of names (batch (..., L)); default the end link (with the tool transform).
        ``all_links=True``: every link of the chain, in ``link_names`` order.
        Returns a :class:`ChainState`.  Differentiable in q, qdot, qddot.
        """
        names, keep = self._link_names(links, all_links)
        q, qdot, qddot = self._inputs(q, qdot, qddot)
        batch, k = q.shape[:-1], self._kernel
        index, G = self._link_constants(names)
        Rs, ps = k.frames(self._flat(q))
        R, p = k.links(Rs, ps, index, G)  # (L, 3, 3, B), (L, 3, B)
        state = ChainState(SE3.from_components(to_batch_first(R, batch, 2),
                                               to_batch_first(p, batch, 1)))
        if qdot is not None:
            S_lin, S_ang = k.screws(Rs, ps)
            qd = self._flat(qdot)[:, None, :]
            nu, om = S_lin * qd, S_ang * qd
            N, W = k.ancestor_sum(nu), k.ancestor_sum(om)  # V_k = sum_(i <= k) S_i qd_i  (50)
            last = self._is_last(names)
            Nk, Wk = _at(N, index, last), _at(W, index, last)
            v = Nk + _cross1(Wk, p)
            state.linear_velocity = to_batch_first(v, batch, 1)
            state.angular_velocity = to_batch_first(Wk, batch, 1)
            if qddot is not None:
                qdd = self._flat(qddot)[:, None, :]
                # dV_k = sum_(i <= k) S_i qdd_i + ad(V_i)(S_i qd_i)
                dN = k.ancestor_sum(S_lin * qdd + _cross1(W, nu) + _cross1(N, om))
                dW = k.ancestor_sum(S_ang * qdd + _cross1(W, om))
                dNk, dWk = _at(dN, index, last), _at(dW, index, last)
                a = dNk + _cross1(dWk, p) + _cross1(Wk, v)
                state.linear_acceleration = to_batch_first(a, batch, 1)
                state.angular_acceleration = to_batch_first(dWk, batch, 1)
        return state if keep else _squeeze_link(state)

    def _is_last(self, names: Sequence[str]) -> bool:
        """One link, after the last joint (host-side, from the chain's tables)."""
        return len(names) == 1 and self._links64[names[0]][0] == self.n_joints - 1

    def _flat(self, x: torch.Tensor) -> torch.Tensor:
        """(..., n) -> (n, B), batch last."""
        return x.reshape(-1, self.n_joints).transpose(0, 1).contiguous()

    def pose(self, q: torch.Tensor, link: str | None = None) -> SE3:
        """The pose (SE3, batch (...)) of ``link`` (default the end link, with the tool)."""
        return self.forward(q, links=link).pose

    def _inputs(self, q, qdot, qddot):
        q = self._joint_tensor(q, "q")
        if qdot is not None:
            qdot = self._joint_tensor(qdot, "qdot", like=q)
        if qddot is not None:
            if qdot is None:
                raise ValueError("qddot needs qdot: the acceleration depends on the velocity")
            qddot = self._joint_tensor(qddot, "qddot", like=q)
        shape = checks.broadcast_shapes(*(x.shape for x in (q, qdot, qddot) if x is not None))
        return tuple(None if x is None else x.expand(shape) for x in (q, qdot, qddot))

    # -------------------------------------------------------------- Jacobians
    def _one_link(self, link: str | None) -> str:
        if link is None:
            return self.end_link
        if not isinstance(link, str) or link not in self._links64:
            raise ValueError(f"unknown link {link!r} of the chain {self.name!r}; its links are "
                             f"{list(self.link_names)}")
        return link

    def _jacobian_parts(self, q: torch.Tensor, link: str, qdot: torch.Tensor | None):
        """Pose (R, p), the base-frame Jacobian at the link origin (..., 6, n) and, with qdot,
        its time derivative and the link's (dp/dt, w)."""
        batch, k = q.shape[:-1], self._kernel
        index, G = self._link_constants([link])
        Rs, ps = k.frames(self._flat(q))
        R, p = k.links(Rs, ps, index, G)
        R, p = R[0], p[0]  # (3, 3, B), (3, B)
        S_lin, S_ang = k.screws(Rs, ps)
        j = self._links64[link][0]  # the last joint before the link (-1: the base)
        if not (k.serial and j == self.n_joints - 1):  # only the link's ancestors move it
            mask = k.ancestors[j] if j >= 0 else torch.zeros_like(k.ancestors[0])
            S_lin, S_ang = S_lin * mask[:, None, None], S_ang * mask[:, None, None]
        lin = S_lin + _cross1(S_ang, p[None])  # z_i x (p - o_i), or z_i
        R_b, p_b = to_batch_first(R[None], batch, 2)[..., 0, :, :], to_batch_first(p[None], batch, 1)[..., 0, :]
        J = _columns(torch.cat((lin, S_ang), dim=1), batch)
        if qdot is None:
            return R_b, p_b, J, None, None, None
        qd = self._flat(qdot)[:, None, :]
        nu, om = S_lin * qd, S_ang * qd
        N, W = k.ancestor_sum(nu), k.ancestor_sum(om)
        w = om.sum(0)  # the link's angular velocity: the sum over its (unmasked) ancestors
        v = nu.sum(0) + _cross1(w[None], p[None])[0]
        dS_lin = _cross1(W, S_lin) + _cross1(N, S_ang)  # dS_i/dt = ad(V_i) S_i
        dS_ang = _cross1(W, S_ang)
        dlin = dS_lin + _cross1(dS_ang, p[None]) + _cross1(S_ang, v[None])
        dJ = _columns(torch.cat((dlin, dS_ang), dim=1), batch)
        return (R_b, p_b, J, dJ, to_batch_first(v[None], batch, 1)[..., 0, :],
                to_batch_first(w[None], batch, 1)[..., 0, :])

    def _frame(self, frame: str) -> str:
        if frame not in FRAMES:
            raise ValueError(f"frame must be one of {FRAMES}, got {frame!r}")
        return frame

    def jacobian(self, q: torch.Tensor, *, link: str | None = None, frame: str = "base") -> torch.Tensor:
        """The geometric Jacobian (..., 6, n) of ``link`` (default the end link with the
        tool), rows [linear; angular]:

        * ``frame="base"``: (dp/dt, w) of the link origin in the base frame (pytorch-kinematics'
          ``jacobian``, Pinocchio's LOCAL_WORLD_ALIGNED);
        * ``"body"``: the body twist (R^T dp/dt, R^T w) (Pinocchio's LOCAL): the right
          perturbation, T(q + dq) ~ T(q) exp(J dq);
        * ``"spatial"``: the spatial twist (dp/dt - w x p, w) (Pinocchio's WORLD).
        """
        frame = self._frame(frame)
        link = self._one_link(link)
        q = self._joint_tensor(q, "q")
        R, p, J, _, _, _ = self._jacobian_parts(q, link, None)
        return _reframe(J, R, p, frame)

    def jacobian_derivative(self, q: torch.Tensor, qdot: torch.Tensor, *, link: str | None = None,
                            frame: str = "base") -> torch.Tensor:
        """dJ/dt (..., 6, n) along qdot, J as in :meth:`jacobian` for the same ``frame``:
        the link's acceleration is J qddot + dJ/dt qdot in that frame (classical acceleration
        for ``"base"``, the body twist's derivative for ``"body"``).  qdot (..., n) is
        required (TypeError naming it otherwise)."""
        frame = self._frame(frame)
        link = self._one_link(link)
        if not isinstance(qdot, torch.Tensor):
            raise TypeError(f"qdot must be a torch.Tensor (..., {self.n_joints}) of joint "
                            f"velocities: dJ/dt is taken along it, got {type(qdot).__name__}")
        q, qdot, _ = self._inputs(q, qdot, None)
        R, p, J, dJ, v, w = self._jacobian_parts(q, link, qdot)
        if frame == "base":
            return dJ
        if frame == "spatial":  # d/dt (J_lin + p x J_ang) = dJ_lin + v x J_ang + p x dJ_ang
            lin = dJ[..., :3, :] + _cross0(v[..., :, None], J[..., 3:, :]) \
                + _cross0(p[..., :, None], dJ[..., 3:, :])
            return torch.cat((lin, dJ[..., 3:, :]), dim=-2)
        # body: d/dt (R^T J) = R^T (dJ - [w]x J), blockwise
        Rt = R.transpose(-1, -2)
        A = dJ - torch.cat((_cross0(w[..., :, None], J[..., :3, :]),
                            _cross0(w[..., :, None], J[..., 3:, :])), dim=-2)
        return torch.cat((Rt @ A[..., :3, :], Rt @ A[..., 3:, :]), dim=-2)

    def pose_and_jacobian(self, q: torch.Tensor, *, link: str | None = None,
                          frame: str = "base") -> tuple[SE3, torch.Tensor]:
        """The pose and the Jacobian (as :meth:`jacobian`) from one pass over the chain."""
        frame = self._frame(frame)
        link = self._one_link(link)
        q = self._joint_tensor(q, "q")
        R, p, J, _, _, _ = self._jacobian_parts(q, link, None)
        return SE3.from_components(R, p), _reframe(J, R, p, frame)

    # ------------------------------------------------------------ DH tables
    @classmethod
    def from_dh(
        cls,
        a: Sequence[float] | torch.Tensor,
        alpha: Sequence[float] | torch.Tensor,
        d: Sequence[float] | torch.Tensor,
        theta_offset: Sequence[float] | torch.Tensor,
        joint_types: Sequence[str] | str,
        *,
        convention: str = "standard",
        base=None,
        tool=None,
        lower: Sequence[float] | None = None,
        upper: Sequence[float] | None = None,
        dtype: torch.dtype = torch.float64,
        device=None,
        name: str = "dh",
    ) -> KinematicChain:
        """A chain from a DH table, standard (Rz(theta) Tz(d) Tx(a) Rx(alpha) per link, as the
        mahony paper's (43) and :class:`GDHChain`) or ``convention="modified"`` (Craig:
        Rx(alpha_(i-1)) Tx(a_(i-1)) Rz(theta_i) Tz(d_i), the row i holding alpha_(i-1),
        a_(i-1)).  theta_i = theta_offset_i + q_i (revolute) or d_i + q_i (prismatic).

        Joints are ``q1 .. qn``; links ``frame_0`` (the base) .. ``frame_n`` (DH frame n, the
        end link).  ``lower``/``upper``: optional joint limits (n values each).
        """
        from .dh import dh_links

        joints, links = dh_links(a, alpha, d, theta_offset, joint_types, convention, lower, upper)
        return cls(joints, links, f"frame_{len(joints)}", base=base, tool=tool, dtype=dtype,
                   device=device, name=name, root_link="frame_0")

    @classmethod
    def from_gdh(cls, chain, *, base=None, tool=None) -> KinematicChain:
        """The :class:`GDHChain` (standard DH) as a KinematicChain, same dtype and device."""
        from .gdh import GDHChain

        if not isinstance(chain, GDHChain):
            raise TypeError(f"chain must be a GDHChain, got {type(chain).__name__}")
        return cls.from_dh(chain.a, chain.alpha, chain.d, chain.theta_offset, chain.joint_types,
                           base=base, tool=tool, dtype=chain.dtype, device=chain.device,
                           name=chain.name)


def _unit_axis(axis, name: str) -> tuple[float, float, float]:
    """A joint axis: 3 finite real numbers, not all zero, normalised (as ``from_urdf`` does);
    ValueError (TypeError for a wrong type) naming ``name`` otherwise."""
    if isinstance(axis, torch.Tensor):
        axis = axis.detach().cpu().tolist() if axis.dim() == 1 else axis
    try:
        raw = list(axis)
    except TypeError:
        raise TypeError(f"{name} must be 3 real numbers, got {axis!r}") from None
    if len(raw) != 3 or any(isinstance(x, bool) or not isinstance(x, numbers.Real) for x in raw):
        raise TypeError(f"{name} must be 3 real numbers, got {axis!r}")
    vals = [float(x) for x in raw]
    norm = math.hypot(*vals)  # no overflow or underflow of the squares
    if not (math.isfinite(norm) and norm > 0):
        raise ValueError(f"{name} must be a finite, non-zero 3-vector, got {tuple(vals)}")
    return (vals[0] / norm, vals[1] / norm, vals[2] / norm)


def _limit(value, name: str, hint: str) -> float:
    """A joint limit: a real number, +-inf allowed, NaN refused (TypeError / ValueError naming
    ``name``); a 0-d tensor is read as its value."""
    if isinstance(value, torch.Tensor) and value.dim() == 0 and value.dtype != torch.bool:
        value = value.item()
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name} must be a real number ({hint}), got {value!r}")
    value = float(value)
    if math.isnan(value):
        raise ValueError(f"{name} must be a real number ({hint}), got nan")
    return value


def _reframe(J: torch.Tensor, R: torch.Tensor, p: torch.Tensor, frame: str) -> torch.Tensor:
    """A base-frame Jacobian (rows dp/dt, w) in ``frame``."""
    if frame == "base":
        return J
    if frame == "spatial":
        lin = J[..., :3, :] + _cross0(p[..., :, None], J[..., 3:, :])  # dp/dt - w x p
        return torch.cat((lin, J[..., 3:, :]), dim=-2)
    Rt = R.transpose(-1, -2)
    return torch.cat((Rt @ J[..., :3, :], Rt @ J[..., 3:, :]), dim=-2)


def _at(x: torch.Tensor, index: torch.Tensor, last: bool) -> torch.Tensor:
    """Cumulative sums (n, 3, B) at stack indices (0: the base, where they are zero);
    ``last``: the one index is n (the end link after the last joint)."""
    if last:
        return x[-1:]
    x = torch.cat((torch.zeros_like(x[:1]), x), dim=0)
    return x.index_select(0, index)


def _columns(x: torch.Tensor, batch: torch.Size) -> torch.Tensor:
    """(n, 6, B) Jacobian columns -> (*batch, 6, n)."""
    return x.permute(2, 1, 0).reshape(*batch, 6, x.shape[0])


def _cross0(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return torch.linalg.cross(a, b, dim=-2)


def _squeeze_link(state: ChainState) -> ChainState:
    """The one-link state without its link axis."""
    def sq(x):
        return None if x is None else x.squeeze(-2)
    return ChainState(state.pose.squeeze(-1), sq(state.linear_velocity),
                      sq(state.angular_velocity), sq(state.linear_acceleration),
                      sq(state.angular_acceleration))
