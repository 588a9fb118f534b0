"""Generalised Denavit-Hartenberg (GDH) chains on extended poses SE_2(3).

Mahony, Kelly and Weiss, "Galilean Symmetry in Robotics", Section 5 (equation numbers).  A
link is the extended pose (43)

    K_i = [[R_i, v_i, p_i], [0, 1, 0], [0, 0, 1]],   R_i = Rz(theta_i) Rx(alpha_i),
    p_i = (a cos theta, a sin theta, d),             v_i = dp_i/dt (44),

and its motion is dK_i/dt = K_i N - N K_i + K_i U_i with the link input
U_i = (0, acc_i, omega_i) (tangent order [rho, nu, phi]) of (46)-(47): omega_i (46) is the link's
relative angular velocity and acc_i (47) its relative acceleration (the paper's U(omega, a-dot),
written with both subscripts there; acc_i is not the DH length a_i, and omega_i is not the
paper's w_i = dd_i/dt, the prismatic joint rate).  The chain K = K_1 ... K_n (45) moves with
the input U = sum_i Ad(iK_n^-1) U_i (50).

Two departures from the paper, both checked against pytorch-kinematics in the tests:

* The velocity column of the product (45) is sum_i R_(0,i-1) v_i, each link's own coordinate
  velocity; it lacks the transport of the outer links by the inner joints' rotation.  The
  end-effector coordinate velocity is dp/dt = v + R U_rho, with U_rho the rho part of (50)
  (from K^-1 (dK/dt - [K, N]) = U).  ``GDHState.linear_velocity`` is this one.
* (47) prints -a_i qdot_i^2 for the first component; differentiating (44) gives -a_i q_i^2
  (q_i = dtheta_i/dt, the centripetal term).

Accelerations: with X_i = iK_n, W_i = Ad(X_i^-1) U_i, V_i = sum_(j>i) W_j, differentiating (50)
gives (the N terms reduce to a translation by -v(X_i^-1))

    dU/dt = sum_i Ad(X_i^-1) dU_i/dt + ad(W_i) (V_i + (-v(X_i^-1), 0, 0)),

and d2p/dt2 = R (U_nu + U_phi x U_rho + dU_rho/dt), domega/dt = R dU_phi/dt (base frame).  Only
the rho and phi parts of dU/dt are needed, so no joint jerk enters.

Only the public group API (SE23) is used.
"""
from __future__ import annotations

import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from ..functional import checks
from ..functional._blocking import values_readable
from ..functional.checks import SUPPORTED_DTYPES
from ..groups import SE23

REVOLUTE, PRISMATIC = "revolute", "prismatic"
_ALIASES = {"r": REVOLUTE, "revolute": REVOLUTE, "p": PRISMATIC, "prismatic": PRISMATIC}


def normalize_joint_type(t, index: int | None = None) -> str:
    """'revolute'/'R' or 'prismatic'/'P' (any case) -> REVOLUTE or PRISMATIC."""
    key = str(t).strip().lower()
    if key not in _ALIASES:
        where = "joint type" if index is None else f"joint_types[{index}]"
        raise ValueError(f"{where} must be 'revolute'/'R' or 'prismatic'/'P', got {t!r}")
    return _ALIASES[key]


@dataclass
class GDHState:
    """Forward kinematics of a GDH chain (``GDHChain.forward(q, qdot)``).

    ``...`` is the batch shape of q and qdot broadcast together; n the number of joints.
    Positions and velocities are in the base frame {0} unless stated otherwise.

    frames            SE23, batch (..., n): 0K_1 .. 0K_n, the prefix products of the link
                      matrices (43).  Frame i's rotation and position (``rotation()``,
                      ``position()``) are those of DH frame i in {0}; its velocity column is
                      the product's (45), not the velocity of frame i's origin (see below).
    end_effector      SE23, batch (...): 0K_n = ``frames[..., -1]``, the end-effector
                      extended pose (45).  ``end_effector.rotation()`` (..., 3, 3) and
                      ``end_effector.position()`` (..., 3) are the end-effector orientation
                      and position in {0}.
    chain_input       (..., 9) or None (no qdot): 0U_n of (50), tangent [rho, nu, phi] in the
                      end-effector frame.  phi is the end-effector angular velocity in its own
                      frame (51); rho = R^T (dp/dt - v) with (R, v) the rotation and velocity
                      column of ``end_effector``; nu is evaluated at zero joint
                      accelerations (use :meth:`GDHChain.acceleration` for accelerations).
    linear_velocity   (..., 3) or None (no qdot): dp/dt, the velocity of the end-effector
                      origin in {0}, dp/dt = v + R rho.
    angular_velocity  (..., 3) or None (no qdot): the end-effector angular velocity in {0}
                      (dR/dt = [w]x R).
    pose              property, (..., 4, 4): the end-effector SE(3) matrix [[R, p], [0, 1]].

    .. warning::
       ``end_effector.velocity()`` is **not** the end-effector velocity.  It is the velocity
       column of the product (45), sum_i R_(0,i-1) v_i, each link's own coordinate velocity,
       which lacks the transport of the outer links by the inner joints' rotation (the
       erratum in the module docstring); it differs from dp/dt whenever an inner revolute
       joint moves.  Use ``linear_velocity`` (and ``angular_velocity``); the same holds for
       ``frames.velocity()``.  Accelerations are not part of the state:
       ``GDHChain.acceleration(q, qdot, qddot)`` returns the end-effector (linear, angular)
       acceleration (..., 3) each in {0}, the time derivatives of ``linear_velocity`` and
       ``angular_velocity``.
    """

    frames: SE23  # 0K_1 .. 0K_n, batch (..., n)
    end_effector: SE23  # 0K_n (45); its velocity() is NOT dp/dt: use linear_velocity
    chain_input: torch.Tensor | None  # 0U_n (50), (..., 9), in the end-effector frame
    linear_velocity: torch.Tensor | None  # dp_n/dt (..., 3), base frame
    angular_velocity: torch.Tensor | None  # (..., 3), base frame

    @property
    def pose(self) -> torch.Tensor:
        """End-effector pose (..., 4, 4)."""
        M = self.end_effector.as_matrix()
        top = torch.cat((M[..., :3, :3], M[..., :3, 4:5]), dim=-1)
        bottom = torch.zeros_like(top[..., :1, :])
        bottom[..., 0, 3].fill_(1.0)  # not = 1.0: unbatched, a blocking copy on CUDA
        return torch.cat((top, bottom), dim=-2)


def _letters_hint(joint_types) -> str:
    """The hint added to a joint_types error when it is a string (read letter by letter)."""
    if not isinstance(joint_types, str):
        return ""
    return (f" (joint_types {joint_types!r} is read letter by letter, one 'R' or 'P' per joint, "
            f"e.g. 'RRP')")


def _columns_device(cols: dict) -> torch.device | None:
    """The device of the tensor columns of a DH table (None when no column is a tensor);
    ValueError naming the columns when they are on different devices."""
    devices = {k: v.device for k, v in cols.items() if isinstance(v, torch.Tensor)}
    if len(set(devices.values())) > 1:
        desc = ", ".join(f"{k} on {dev}" for k, dev in devices.items())
        raise ValueError(f"the DH table's tensor columns are on different devices ({desc}); "
                         f"move them to one device or pass device=")
    return next(iter(devices.values()), None)


_COLUMN = "a sequence of numbers or a 1-D tensor"


def _column_kind(value, name: str) -> None:
    """A DH table column must be a sequence (list, tuple, ...) or a 1-D tensor or array:
    TypeError naming the column, what is expected and what was given (metadata only)."""
    ndim = value.dim() if isinstance(value, torch.Tensor) else getattr(value, "ndim", None)
    if ndim is not None and not isinstance(value, Sequence):  # a tensor or a numpy array
        if ndim != 1:
            raise TypeError(f"{name} (a DH table column) must be {_COLUMN}, got a {ndim}-D "
                            f"{type(value).__name__} of shape {tuple(value.shape)}")
    elif isinstance(value, (str, bytes)) or not isinstance(value, Sequence):
        raise TypeError(f"{name} (a DH table column) must be {_COLUMN}, got "
                        f"{type(value).__name__} {value!r}")


def _has_bools(value) -> bool:
    """Whether a column holds booleans (a bool tensor or array, or bool entries)."""
    dt = getattr(value, "dtype", None)
    if dt is not None:
        return dt == torch.bool or getattr(dt, "kind", "") == "b"
    np = sys.modules.get("numpy")  # a numpy bool can only come from an imported numpy
    bools = (bool,) if np is None else (bool, np.bool_)
    return any(isinstance(v, bools) for v in value)


def _column_tensor(value, name: str, dtype: torch.dtype, device) -> torch.Tensor:
    """A column (checked by ``_column_kind``) as a new tensor (n,) of ``dtype`` on ``device``
    (a copy, never the caller's tensor; autograd history kept); TypeError naming the column
    where its entries are not real numbers (booleans included)."""
    message = f"{name} (a DH table column) must be {_COLUMN}: its entries must be real numbers"
    if _has_bools(value):
        raise TypeError(f"{message}, got booleans {value!r}")
    try:
        t = torch.as_tensor(value, dtype=dtype, device=device)
    except (TypeError, ValueError, RuntimeError):
        raise TypeError(f"{message}, got {value!r}") from None
    if t.dim() != 1:  # nested sequences
        raise TypeError(f"{name} (a DH table column) must be {_COLUMN}, got nested sequences of "
                        f"shape {tuple(t.shape)}")
    return t.clone()  # as_tensor may alias a tensor or numpy array of the caller


def _column_values(value, name: str) -> list[float]:
    """A DH column as a list of finite floats: the checks of ``_column_kind`` and
    ``_column_tensor`` (TypeError naming the column), ValueError naming it for a non-finite
    entry."""
    _column_kind(value, name)
    values = _column_tensor(value, name, torch.float64, "cpu").detach().tolist()
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"{name} (a DH table column) must be finite, got {values}")
    return values


def _joint_types_kind(joint_types) -> None:
    """TypeError unless joint_types is a string ('RRP') or a sequence of joint types."""
    if not isinstance(joint_types, (str, Sequence)):
        raise TypeError(f"joint_types must be a string such as 'RRP' or a sequence of "
                        f"'revolute'/'R' and 'prismatic'/'P', got {type(joint_types).__name__}")


def _cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return torch.linalg.cross(a, b, dim=-1)


def _matvec(M: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    return (M @ x.unsqueeze(-1)).squeeze(-1)


class GDHChain:
    """A serial chain from a standard DH table (a, alpha, d, theta offset, joint type).

    Joint variable q_i: theta_i = theta_offset_i + q_i (revolute) or d_i = d_offset_i + q_i
    (prismatic).  Standard DH only (as in the paper); for modified (Craig) DH, URDF and any
    joint axes use :class:`KinematicChain` (``KinematicChain.from_dh(..., convention="modified")``).
    Every method broadcasts over leading batch dimensions of q, qdot, qddot (..., n).

    ``dtype`` (float64 by default, or float32) and ``device`` are those of the DH table, and
    the joint tensors must match them (as everywhere in the library, nothing is cast): q of
    another dtype or device raises TypeError or ValueError naming q and the chain.  Build the
    chain in the dtype and on the device of your data (``ur5(dtype=torch.float32,
    device="cuda")``).

    The columns may be sequences of numbers or 1-D tensors (anything else, a scalar, a
    string, nested sequences or entries that are not real numbers, booleans included, raises
    TypeError naming the column).  With ``device=None`` the table goes where its tensor columns are (all of
    them on one device, else ValueError naming the columns), or to torch's default device
    when no column is a tensor; ``dtype`` is not taken from the columns (float64 unless given:
    tensor columns are converted; the chain keeps copies of the columns).  The table must be
    finite (ValueError naming the column; not checked on 'meta' or under torch.func
    transforms).
    ``joint_types`` is a sequence of "revolute"/"R" and "prismatic"/"P", or a string read
    letter by letter ("RRP").
    """

    def __init__(
        self,
        a: Sequence[float],
        alpha: Sequence[float],
        d: Sequence[float],
        theta_offset: Sequence[float],
        joint_types: Sequence[str],
        *,
        dtype: torch.dtype = torch.float64,
        device=None,
        name: str = "chain",
    ):
        cols = {"a": a, "alpha": alpha, "d": d, "theta_offset": theta_offset}
        for k, v in cols.items():
            _column_kind(v, k)
        _joint_types_kind(joint_types)
        lengths = {k: len(v) for k, v in cols.items()}
        lengths["joint_types"] = len(joint_types)
        n = lengths["a"]
        if n < 1 or any(v != n for v in lengths.values()):
            raise ValueError(f"DH table columns must have one equal, non-zero length; got "
                             f"{lengths}{_letters_hint(joint_types)}")
        dtype = checks.dtype_arg(torch.float64 if dtype is None else dtype)
        try:
            types = [normalize_joint_type(t, i) for i, t in enumerate(joint_types)]
        except ValueError as err:
            raise ValueError(f"{err}{_letters_hint(joint_types)}") from None
        if device is None:
            device = _columns_device(cols)
        self.name = name
        self.n_joints = n
        self.joint_types = tuple(types)
        self.a, self.alpha, self.d, self.theta_offset = (
            _column_tensor(v, k, dtype, device) for k, v in cols.items())
        table = dict(zip(cols, (self.a, self.alpha, self.d, self.theta_offset)))
        if all(values_readable(t) for t in table.values()):  # one host sync, at construction
            finite = torch.stack([torch.isfinite(t).all() for t in table.values()]).tolist()
            for (k, t), ok in zip(table.items(), finite):
                if not ok:
                    raise ValueError(f"{k} (a DH table column) must be finite, got "
                                     f"{t.tolist()} (as {dtype})")
        self._revolute = torch.tensor([t == REVOLUTE for t in types], device=self.a.device)

    @property
    def dtype(self) -> torch.dtype:
        """The dtype of the DH table, which q, qdot and qddot must have."""
        return self.a.dtype

    @property
    def device(self) -> torch.device:
        """The device of the DH table, where q, qdot and qddot must be."""
        return self.a.device

    def __repr__(self) -> str:
        kinds = "".join("R" if t == REVOLUTE else "P" for t in self.joint_types)
        return f"GDHChain({self.name!r}, {self.n_joints} joints {kinds}, dtype={self.a.dtype})"

    # ------------------------------------------------------------------ validation
    def _joint_tensor(self, x, name: str, like: torch.Tensor | None = None) -> torch.Tensor:
        if not isinstance(x, torch.Tensor):
            raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
        checks.dense(x, name)
        if x.dtype not in SUPPORTED_DTYPES:
            raise TypeError(f"{name} must have a floating dtype (torch.float32 or torch.float64), got {x.dtype}")
        if x.dim() < 1 or x.shape[-1] != self.n_joints:
            raise ValueError(
                f"{name} must have shape (..., {self.n_joints}) for the {self.n_joints} joints "
                f"of {self.name!r}, got {tuple(x.shape)}"
            )
        if like is None:
            self._check_like_chain(x, name)
        else:
            try:  # a device mismatch is ValueError, a dtype mismatch TypeError, as everywhere
                checks.same_device_dtype(q=like, **{name: x})
            except (TypeError, ValueError) as err:
                raise type(err)(f"{err} ({name} must match q: nothing is cast)") from None
            try:
                checks.broadcast_shapes(x.shape, like.shape)
            except RuntimeError:
                raise ValueError(
                    f"batch shapes do not broadcast: q {tuple(like.shape[:-1])}, "
                    f"{name} {tuple(x.shape[:-1])}"
                ) from None
        return x

    def _check_like_chain(self, q: torch.Tensor, name: str = "q") -> None:
        """q on the chain's device and in its dtype: the DH table is not cast to q's (metadata
        only).  A chain built on the meta device has no values to move: it only works with
        meta inputs."""
        if self.a.device != q.device and self.a.device.type == "meta":
            raise ValueError(f"{name} is on {q.device} but the chain {self.name!r} was built on "
                             f"{self.a.device}, where its DH table has no values; build the "
                             f"chain with device={str(q.device)!r}")
        try:
            checks.same_device_dtype(**{f"the chain {self.name!r}": self.a, name: q})
        except (TypeError, ValueError) as err:
            raise type(err)(f"{err} (a chain's dtype and device are set when it is built: "
                            f"GDHChain(..., dtype=, device=), ur5(dtype=, device=))") from None

    def _table(self):
        """The DH table (a, alpha, d, theta_offset, revolute mask); callers have checked that
        the joint tensors share its dtype and device (``_check_like_chain``)."""
        return self.a, self.alpha, self.d, self.theta_offset, self._revolute

    # --------------------------------------------------------------------- links
    def link_transforms(self, q: torch.Tensor, qdot: torch.Tensor | None = None) -> SE23:
        """The GDH matrices (43), an SE23 with batch (..., n)."""
        q = self._joint_tensor(q, "q")
        if qdot is None:
            qdot = torch.zeros_like(q)
        qdot = self._joint_tensor(qdot, "qdot", like=q)
        q, qdot = torch.broadcast_tensors(q, qdot)
        a, alpha, d, offset, rev = self._table()
        theta = offset + torch.where(rev, q, 0.0)
        dd = d + torch.where(rev, 0.0, q)
        qv = torch.where(rev, qdot, 0.0)  # q_i = dtheta_i/dt
        wv = torch.where(rev, 0.0, qdot)  # w_i = dd_i/dt, the prismatic joint rate (44)
        ct, st, ca, sa = torch.cos(theta), torch.sin(theta), torch.cos(alpha), torch.sin(alpha)
        zero, one = torch.zeros_like(ct), torch.ones_like(ct)
        R = torch.stack(
            (ct, -st * ca, st * sa, st, ct * ca, -ct * sa, zero, sa * one, ca * one), dim=-1
        ).unflatten(-1, (3, 3))
        p = torch.stack((a * ct, a * st, dd), dim=-1)
        v = torch.stack((-a * st * qv, a * ct * qv, wv), dim=-1)  # (44)
        return SE23.from_components(R, v, p)

    def link_inputs(self, q: torch.Tensor, qdot: torch.Tensor, qddot: torch.Tensor) -> torch.Tensor:
        """U_i = (0, acc_i, omega_i) (..., n, 9) from (46)-(47): acc_i (47) in the nu slot,
        omega_i (46) in the phi slot (first component of acc_i -a q^2, see module)."""
        q = self._joint_tensor(q, "q")
        qdot = self._joint_tensor(qdot, "qdot", like=q)
        qddot = self._joint_tensor(qddot, "qddot", like=q)
        q, qdot, qddot = torch.broadcast_tensors(q, qdot, qddot)
        a, alpha, _, _, rev = self._table()
        qv, qa = torch.where(rev, qdot, 0.0), torch.where(rev, qddot, 0.0)
        wa = torch.where(rev, 0.0, qddot)
        ca, sa = torch.cos(alpha), torch.sin(alpha)
        omega = torch.stack((torch.zeros_like(qv), qv * sa, qv * ca), dim=-1)  # (46)
        acc = torch.stack((-a * qv * qv, a * ca * qa + sa * wa, -a * sa * qa + ca * wa), dim=-1)
        return torch.cat((torch.zeros_like(acc), acc, omega), dim=-1)

    # ------------------------------------------------------------------- chain
    def _prefix(self, links: SE23) -> list[SE23]:
        """Prefix products 0K_1 .. 0K_n (45)."""
        prefix, acc = [], None
        for i in range(self.n_joints):
            acc = links[..., i] if acc is None else acc.compose(links[..., i])
            prefix.append(acc)
        return prefix

    @staticmethod
    def _base_inputs(prefix: list[SE23], U_links: torch.Tensor):
        """S_i = Ad(0K_i) U_i (base frame), as (rho, nu, phi) lists, Ad applied blockwise:
        phi' = C phi, rho' = C rho + r x phi', nu' = C nu + v x phi' (U_i has rho = 0)."""
        S = []
        for i, K in enumerate(prefix):
            C = K.rotation()
            phi = _matvec(C, U_links[..., i, 6:9])
            rho = _cross(K.position(), phi)
            nu = _matvec(C, U_links[..., i, 3:6]) + _cross(K.velocity(), phi)
            S.append((rho, nu, phi))
        return S

    @staticmethod
    def _to_end_effector(K: SE23, rho, nu, phi):
        """Ad(K^-1) (rho, nu, phi) = C^T (rho - r x phi, nu - v x phi, phi)."""
        Ct = K.rotation().transpose(-1, -2)
        return (_matvec(Ct, rho - _cross(K.position(), phi)),
                _matvec(Ct, nu - _cross(K.velocity(), phi)), _matvec(Ct, phi))

    def forward(self, q: torch.Tensor, qdot: torch.Tensor | None = None) -> GDHState:
        """Frames (45) and, with qdot, the end-effector velocities in the base frame: a
        :class:`GDHState` (its fields are documented there; the end-effector velocity is
        ``linear_velocity``, not ``end_effector.velocity()``).

        ``chain_input`` is 0U_n of (50) at zero joint accelerations (its rho and phi parts,
        which give the velocities, do not depend on them).
        """
        links = self.link_transforms(q, qdot)
        prefix = self._prefix(links)
        frames = SE23.stack(prefix, dim=-1)
        ee = prefix[-1]
        if qdot is None:
            return GDHState(frames, ee, None, None, None)
        q_b, qdot_b = torch.broadcast_tensors(q, qdot)
        U_links = self.link_inputs(q_b, qdot_b, torch.zeros_like(qdot_b))
        S = self._base_inputs(prefix, U_links)
        total = [sum(parts) for parts in zip(*S)]  # sum_i Ad(0K_i) U_i
        U = torch.cat(self._to_end_effector(ee, *total), dim=-1)  # (50)
        lin = ee.velocity() + total[0] - _cross(ee.position(), total[2])  # v + R U_rho
        return GDHState(frames, ee, U, lin, total[2])

    def acceleration(self, q: torch.Tensor, qdot: torch.Tensor, qddot: torch.Tensor):
        """End-effector (linear, angular) acceleration (..., 3) each, base frame (module doc).

        Computed in the base frame with ad(Ad_g a) Ad_g b = Ad_g ad(a) b:
        dU/dt = Ad(K^-1) sum_i [Ad(0K_i) dU_i/dt + ad(S_i)(sum_(j>i) S_j + (v_K - v_i, 0, 0))].
        """
        U_links = self.link_inputs(q, qdot, qddot)
        q, qdot, qddot = torch.broadcast_tensors(q, qdot, qddot)
        links = self.link_transforms(q, qdot)
        prefix = self._prefix(links)
        ee = prefix[-1]
        S = self._base_inputs(prefix, U_links)
        omega_rate = _omega_rate(self, qddot)
        D_rho = torch.zeros_like(S[0][0])
        D_phi = torch.zeros_like(D_rho)
        T_rho, T_phi = torch.zeros_like(D_rho), torch.zeros_like(D_rho)  # sum_{j > i} S_j
        for i in range(self.n_joints - 1, -1, -1):
            K = prefix[i]
            s_rho, _, s_phi = S[i]
            dphi = _matvec(K.rotation(), omega_rate[..., i, :])  # Ad(0K_i) (0, 0, domega_i/dt)
            y_rho = T_rho + ee.velocity() - K.velocity()
            D_rho = D_rho + _cross(K.position(), dphi) + _cross(s_phi, y_rho) + _cross(s_rho, T_phi)
            D_phi = D_phi + dphi + _cross(s_phi, T_phi)
            T_rho, T_phi = T_rho + s_rho, T_phi + s_phi
        total = [sum(parts) for parts in zip(*S)]
        U_rho, U_nu, U_phi = self._to_end_effector(ee, *total)
        dU_rho, _, dU_phi = self._to_end_effector(ee, D_rho, torch.zeros_like(D_rho), D_phi)
        R = ee.rotation()
        lin = _matvec(R, U_nu + _cross(U_phi, U_rho) + dU_rho)
        return lin, _matvec(R, dU_phi)


def _omega_rate(chain: GDHChain, qddot: torch.Tensor) -> torch.Tensor:
    """d/dt of (46): (0, qddot sin alpha, qddot cos alpha) for revolute joints."""
    _, alpha, _, _, rev = chain._table()
    qa = torch.where(rev, qddot, 0.0)
    return torch.stack((torch.zeros_like(qa), qa * torch.sin(alpha), qa * torch.cos(alpha)), dim=-1)
