"""DH tables (standard and modified/Craig) as the joints and links of a KinematicChain."""
from __future__ import annotations

import math
import numbers
from collections.abc import Sequence

import torch

from .state import CONTINUOUS, PRISMATIC, REVOLUTE, Joint


def _rot(axis: str, angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    m = torch.eye(4, dtype=torch.float64)
    i, j = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}[axis]
    m[i, i], m[i, j], m[j, i], m[j, j] = c, -s, s, c
    return m


def _trans(x: float, y: float, z: float) -> torch.Tensor:
    m = torch.eye(4, dtype=torch.float64)
    m[0, 3], m[1, 3], m[2, 3] = x, y, z
    return m


def _limits(values, name: str) -> list[float]:
    """Joint limits: real numbers, +-inf allowed (no limit), NaN refused."""
    if isinstance(values, torch.Tensor):
        values = values.detach().cpu().tolist()
    try:
        values = list(values)
    except TypeError:
        raise TypeError(f"{name} must be a sequence of numbers, got {type(values).__name__}") from None
    for i, v in enumerate(values):
        if isinstance(v, bool) or not isinstance(v, numbers.Real) or math.isnan(v):
            raise TypeError(f"{name}[{i}] must be a number (inf for no limit), got {v!r}")
    return [float(v) for v in values]


def dh_links(a, alpha, d, theta_offset, joint_types, convention: str = "standard",
             lower: Sequence[float] | None = None, upper: Sequence[float] | None = None):
    """(joints, links) of a DH table for :class:`KinematicChain` (see ``from_dh``): the joint
    i turns (or slides) about the z axis of its frame; the standard convention's Tx(a) Rx(alpha)
    after joint i becomes the offset of link ``frame_i`` and part of the next joint's origin."""
    from .gdh import _column_values, _joint_types_kind, _letters_hint, normalize_joint_type

    if convention not in ("standard", "modified"):
        raise ValueError(f"convention must be 'standard' or 'modified', got {convention!r}")
    cols = {key: _column_values(col, key) for key, col in
            (("a", a), ("alpha", alpha), ("d", d), ("theta_offset", theta_offset))}
    _joint_types_kind(joint_types)
    n = len(joint_types)
    lengths = {k: len(v) for k, v in cols.items()}
    if n < 1 or any(v != n for v in lengths.values()):
        raise ValueError(f"DH table columns must have one equal, non-zero length; got "
                         f"{lengths}, joint_types {n}{_letters_hint(joint_types)}")
    try:
        types = [normalize_joint_type(t, i) for i, t in enumerate(joint_types)]
    except ValueError as err:
        raise ValueError(f"{err}{_letters_hint(joint_types)}") from None
    lo = [-math.inf] * n if lower is None else _limits(lower, "lower")
    hi = [math.inf] * n if upper is None else _limits(upper, "upper")
    if len(lo) != n or len(hi) != n:
        raise ValueError(f"lower and upper must have {n} entries, got {len(lo)} and {len(hi)}")
    joints, links = [], {"frame_0": (-1, torch.eye(4, dtype=torch.float64))}
    tail = torch.eye(4, dtype=torch.float64)  # fixed factors since the last joint
    for i in range(n):
        th, di, ai, al = (cols[k][i] for k in ("theta_offset", "d", "a", "alpha"))
        rz, tz = _rot("z", th), _trans(0.0, 0.0, di)
        if convention == "standard":
            origin = tail @ rz @ tz
            after = _trans(ai, 0.0, 0.0) @ _rot("x", al)
        else:
            origin = tail @ _rot("x", al) @ _trans(ai, 0.0, 0.0) @ rz @ tz
            after = torch.eye(4, dtype=torch.float64)
        kind = REVOLUTE if types[i] == "revolute" else PRISMATIC
        if kind == REVOLUTE and not (math.isfinite(lo[i]) or math.isfinite(hi[i])):
            kind = CONTINUOUS
        joints.append(Joint(f"q{i + 1}", kind, (0.0, 0.0, 1.0), origin, lo[i], hi[i]))
        links[f"frame_{i + 1}"] = (i, after)
        tail = after
    return joints, links

