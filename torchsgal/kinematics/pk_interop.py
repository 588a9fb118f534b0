"""Interoperability with ``pytorch_kinematics`` (pk), used as an independent peer for testing.

``pytorch_kinematics`` is an optional dependency: it is imported inside the functions below,
never at module import time.  Install it with ``pip install pytorch-kinematics``.

How pk models a serial chain (pytorch_kinematics 0.10, ``frame.py`` / ``chain.py``)
-----------------------------------------------------------------------------------
A chain is a tree of ``Frame`` objects; each frame carries a ``Joint`` (type ``"fixed"``,
``"revolute"`` or ``"prismatic"``, a unit ``axis`` expressed in the joint frame and an
``offset`` Transform3d, the fixed "joint origin") and a ``Link`` (with its own ``offset``).
Forward kinematics composes, frame by frame from the root,

    T_world[f] = T_world[parent(f)] @ link.offset @ joint.offset @ M(axis, q)

with ``M`` a rotation by ``q`` about ``axis`` (revolute), a translation ``q * axis``
(prismatic) or the identity (fixed).  pk has no separate "joint zero offset": a DH offset
``theta_offset_i`` (or ``d_offset_i``) has to be folded into the fixed transform that precedes
the joint motion.  ``SerialChain`` resets the root frame's joint and link offset, so the root
is the base frame ``{0}``.

The chain built by :func:`build_pk_chain` for a standard-DH table is

    frame_0 (root, base)
      -> joint_1   (revolute about z: offset Rz(theta_offset_1); prismatic along z: offset Tz(d_1))
      -> frame_1   (fixed: Tz(d_1) Tx(a_1) Rx(alpha_1) if revolute, Rz(theta_1) Tx(a_1) Rx(alpha_1)
                    if prismatic)
      -> joint_2 -> frame_2 -> ... -> joint_n -> frame_n   (end effector)

so that the world pose of ``frame_i`` is the product T_1 ... T_i of classical DH matrices
T_i = Rz(theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i) with theta_i = theta_offset_i + q_i (revolute)
or d_i = d_offset_i + q_i (prismatic).  ``Rz`` and ``Tz`` commute, which is why the
prismatic link can take ``Rz(theta_i)`` after the translation.  The intermediate ``joint_i``
frames sit on the joint axis of DH frame ``{i-1}``, which is what pk's geometric Jacobian
uses (axis ``R_joint e_z`` and origin of the joint frame).

pk Jacobian convention: ``SerialChain.jacobian(q)`` is ``(B, 6, n)`` with rows ``[v; omega]``,
both expressed in the base frame, ``v`` being the velocity of the end-effector origin
(columns ``z_{i-1} x (p_n - p_{i-1}); z_{i-1}`` for revolute and ``z_{i-1}; 0`` for prismatic).
"""
from __future__ import annotations

import math
import numbers
from collections.abc import Iterable, Sequence

import torch

from ..functional import checks
from .gdh import _column_values, _joint_types_kind, _letters_hint, normalize_joint_type


def _import_pk():
    try:
        import pytorch_kinematics as pk  # noqa: F401
        from pytorch_kinematics import frame as pk_frame
        from pytorch_kinematics import transforms as pk_tf
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError(
            "torchsgal.kinematics.pk_interop needs the optional package `pytorch-kinematics` "
            "(pip install pytorch-kinematics)"
        ) from exc
    return pk, pk_frame, pk_tf


def _rz(theta: float, dtype, device) -> torch.Tensor:
    c, s = math.cos(theta), math.sin(theta)
    return torch.tensor(
        [[c, -s, 0.0, 0.0], [s, c, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]],
        dtype=dtype, device=device,
    )


def _rx(alpha: float, dtype, device) -> torch.Tensor:
    c, s = math.cos(alpha), math.sin(alpha)
    return torch.tensor(
        [[1.0, 0.0, 0.0, 0.0], [0.0, c, -s, 0.0], [0.0, s, c, 0.0], [0.0, 0.0, 0.0, 1.0]],
        dtype=dtype, device=device,
    )


def _trans(x: float, y: float, z: float, dtype, device) -> torch.Tensor:
    m = torch.eye(4, dtype=dtype, device=device)
    m[0, 3], m[1, 3], m[2, 3] = x, y, z
    return m


def build_pk_chain(
    a: Sequence[float],
    alpha: Sequence[float],
    d: Sequence[float],
    theta_offset: Sequence[float],
    joint_types: Sequence[str],
    dtype: torch.dtype = torch.float64,
    device: str | torch.device = "cpu",
):
    """A ``pytorch_kinematics.SerialChain`` equivalent to a standard-DH table.

    Args:
        a, alpha, d, theta_offset: sequences of real numbers (or 1-D tensors) of length n,
            checked as :class:`GDHChain`'s columns (TypeError naming the column for a string,
            booleans, a scalar or nested sequences), finite (ValueError naming the column).
            For a prismatic joint ``d`` is the offset ``d_offset_i``; for a revolute one
            ``theta_offset`` is.
        joint_types: n entries, each ``"revolute"`` or ``"prismatic"`` (``"R"``/``"P"`` too);
            a string is read letter by letter (``"RRPR"``).
        dtype, device: of the chain (torch.float64, the default, or torch.float32; built
            directly in that precision: the URDF loader is not used since it parses angles in
            float32).

    Returns:
        ``SerialChain`` whose ``forward_kinematics(q)`` (q of shape (B, n) or (n,)) is the
        pose of DH frame ``{n}`` (pk frame ``"frame_<n>"``) in the base frame ``{0}``
        (``"frame_0"``), i.e. the product of the classical DH matrices with
        theta_i = theta_offset_i + q_i (revolute) or d_i = d_offset_i + q_i (prismatic).
        ``forward_kinematics(q, end_only=False)`` also gives ``"frame_i"`` for every i and the
        on-axis joint frames ``"joint_i"``.  Joint names are ``"q1" .. "qn"``.
    """
    checks.dtype_arg(dtype)
    pk, pk_frame, pk_tf = _import_pk()
    a_, al_, d_, th_ = (_column_values(v, n) for v, n in
                        ((a, "a"), (alpha, "alpha"), (d, "d"), (theta_offset, "theta_offset")))
    _joint_types_kind(joint_types)
    n = len(joint_types)
    if not (len(a_) == len(al_) == len(d_) == len(th_) == n):
        raise ValueError(
            f"DH table lengths differ: a {len(a_)}, alpha {len(al_)}, d {len(d_)}, "
            f"theta_offset {len(th_)}, joint_types {n}{_letters_hint(joint_types)}"
        )
    try:
        types = [normalize_joint_type(t, i) for i, t in enumerate(joint_types)]
    except ValueError as err:
        raise ValueError(f"{err}{_letters_hint(joint_types)}") from None
    if n == 0:
        raise ValueError("a chain needs at least one joint")

    def T(m: torch.Tensor):
        return pk_tf.Transform3d(matrix=m.unsqueeze(0), dtype=dtype, device=device)

    def fixed_joint(name: str):
        return pk_frame.Joint(name, joint_type="fixed", dtype=dtype, device=device)

    z_axis = torch.tensor([0.0, 0.0, 1.0], dtype=dtype, device=device)
    root = pk_frame.Frame("frame_0", link=pk_frame.Link("link_0"), joint=fixed_joint("fixed_0"))
    parent = root
    for i in range(n):
        k = i + 1
        if types[i] == "revolute":
            joint_offset = _rz(th_[i], dtype, device)
            fixed = _trans(0.0, 0.0, d_[i], dtype, device) @ _trans(a_[i], 0.0, 0.0, dtype, device)
        else:
            joint_offset = _trans(0.0, 0.0, d_[i], dtype, device)
            fixed = _rz(th_[i], dtype, device) @ _trans(a_[i], 0.0, 0.0, dtype, device)
        fixed = fixed @ _rx(al_[i], dtype, device)
        jframe = pk_frame.Frame(
            f"joint_{k}",
            link=pk_frame.Link(f"joint_link_{k}"),
            joint=pk_frame.Joint(f"q{k}", offset=T(joint_offset), joint_type=types[i],
                                 axis=z_axis, dtype=dtype, device=device),
        )
        lframe = pk_frame.Frame(
            f"frame_{k}",
            link=pk_frame.Link(f"link_{k}"),
            joint=pk_frame.Joint(f"fixed_{k}", offset=T(fixed), joint_type="fixed",
                                 dtype=dtype, device=device),
        )
        # Frame.__init__ only creates the children list when none is given.
        jframe.children = [lframe]
        lframe.children = []
        parent.children = [jframe]
        parent = lframe
    root_chain = pk.Chain(root, dtype=dtype, device=device)
    return pk.SerialChain(root_chain, f"frame_{n}", dtype=dtype, device=device)


def to_transform3d(x):
    """A torchsgal ``SE3`` or ``SE23`` element as a ``pytorch_kinematics.Transform3d``.

    The Transform3d holds the pose ``[[C, r], [0, 1]]`` (for SE23 the rows/columns 0, 1, 2, 4
    of the 5x5 matrix: the velocity is dropped).  pk transforms are flat batches, so the batch
    shape of ``x`` is flattened (row-major): the result has ``get_matrix()`` of shape
    (N, 4, 4) with N = prod(x.batch_shape) (N = 1 for an unbatched element).  Pass
    ``batch_shape=x.batch_shape`` to :func:`from_transform3d` to restore it.
    """
    _, _, pk_tf = _import_pk()
    from ..groups import SE3, SE23

    if isinstance(x, SE3):
        m = x.as_matrix()
    elif isinstance(x, SE23):
        C, r = x.rotation(), x.position()
        m = torch.zeros(*C.shape[:-2], 4, 4, dtype=C.dtype, device=C.device)
        m[..., :3, :3] = C
        m[..., :3, 3] = r
        m[..., 3, 3].fill_(1.0)  # not = 1.0: unbatched, a blocking copy on CUDA
    else:
        raise TypeError(f"x must be a torchsgal SE3 or SE23, got {type(x).__name__}")
    m = m.reshape(-1, 4, 4)
    return pk_tf.Transform3d(matrix=m, dtype=m.dtype, device=m.device)


def _batch_shape(batch_shape) -> tuple[int, ...]:
    """``batch_shape`` of :func:`from_transform3d`: an int or a sequence of ints >= 0 (bools,
    floats and strings refused, naming ``batch_shape[i]``)."""
    if isinstance(batch_shape, numbers.Integral) and not isinstance(batch_shape, bool):
        batch_shape = (batch_shape,)
    if isinstance(batch_shape, (str, bytes, bool)) or not isinstance(batch_shape, Iterable):
        raise TypeError(f"batch_shape must be a tuple of ints (or an int), got {batch_shape!r}")
    return tuple(checks.integer(n, f"batch_shape[{i}]", 0)
                 for i, n in enumerate(batch_shape))


def from_transform3d(t, velocity: torch.Tensor | None = None, batch_shape=None,
                     check: bool = False, tol: float | None = None):
    """A ``pytorch_kinematics.Transform3d`` (or a (..., 4, 4) pose tensor) as torchsgal.

    Returns ``SE3`` of batch (N,) where N = len(t), or, when ``velocity`` (..., 3) is given,
    the ``SE23`` element with that velocity (broadcast against the batch of ``t``).  With
    ``batch_shape`` (a tuple of ints >= 0, or an int; a float, bool or string is a TypeError
    naming ``batch_shape[i]``) the batch is reshaped to it (inverse of the
    flattening in :func:`to_transform3d`; applied before the velocity is broadcast).

    The rotation block and the translation column are taken as they are: a matrix that is not
    a rigid transform (a non-orthonormal rotation, a scaled or sheared Transform3d) gives an
    element outside the group, unless ``check=True``, which raises ValueError for such
    matrices (``SE3.from_matrix(check=True, tol=tol)``: one host sync).
    """
    from ..groups import SE3, SE23

    if torch.is_tensor(t):
        m = t
    elif hasattr(t, "get_matrix"):
        _import_pk()
        m = t.get_matrix()
    else:
        raise TypeError(f"t must be a pytorch_kinematics Transform3d or a (..., 4, 4) tensor, "
                        f"got {type(t).__name__}")
    checks.matrix(m, 4, "t")
    checks.boolean(check, "check")
    if batch_shape is not None:
        shape = _batch_shape(batch_shape)
        if math.prod(shape) != math.prod(m.shape[:-2]):
            raise ValueError(f"batch_shape {shape} does not fit the {math.prod(m.shape[:-2])} "
                             f"poses of t (batch {tuple(m.shape[:-2])})")
        m = m.reshape(*shape, 4, 4)
    if check:
        try:
            SE3.from_matrix(m, check=True, tol=tol)
        except ValueError as exc:
            raise ValueError(f"t (check=True): {exc}") from None
    C, r = m[..., :3, :3], m[..., :3, 3]
    if velocity is None:
        return SE3.from_components(C, r)
    return SE23.from_components(C, velocity, r)


__all__ = ["build_pk_chain", "to_transform3d", "from_transform3d"]
