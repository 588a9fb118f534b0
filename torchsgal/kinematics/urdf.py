"""Kinematic chains from URDF robot descriptions and from pytorch-kinematics chains.

URDF files are parsed with ``yourdfpy`` (an optional dependency: ``pip install yourdfpy``);
meshes are never loaded, so ``package://`` mesh URIs need not resolve.  Joint origins are read
in float64 (``xyz``, and ``rpy`` as R = Rz(yaw) Ry(pitch) Rx(roll), the URDF convention).

A chain runs from ``root_link`` to ``end_link`` (or to several end links: the branches of a
tree) through the tree; fixed joints are folded into
the next actuated joint's origin (or into the offset of the links after the last one).  The
links of the chain are those on the path and the links attached to them by fixed joints only
(a gripper's TCP frame, a flange).  When ``root_link`` is not an ancestor of ``end_link`` it
must hang from the path by fixed joints only; its inverse transform becomes the base.
"""
from __future__ import annotations

import io
import math
import os
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from pathlib import Path

import torch

from .chain import KinematicChain
from .state import CONTINUOUS, PRISMATIC, REVOLUTE, Joint

_KINDS = {"revolute": REVOLUTE, "continuous": CONTINUOUS, "prismatic": PRISMATIC}


def _import_yourdfpy():
    try:
        import yourdfpy
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError("reading URDF needs the optional package `yourdfpy` "
                          "(pip install yourdfpy, or the `robots` extra)") from exc
    return yourdfpy


def _read_source(source) -> tuple[bytes, str]:
    """(the URDF bytes, a description for messages) from a path or an XML string."""
    if isinstance(source, Path) or (isinstance(source, str) and not source.lstrip().startswith("<")):
        path = Path(source)
        if not path.is_file():
            raise FileNotFoundError(f"source: no URDF file at {str(path)!r} (give a path to a "
                                    f"file or the URDF XML text itself)")
        return path.read_bytes(), str(path)
    if isinstance(source, str):
        return source.encode("utf-8"), "the URDF string"
    raise TypeError(f"source must be a path (str or pathlib.Path) or a URDF XML string, got "
                    f"{type(source).__name__}")


def parse_urdf(source):
    """The ``yourdfpy.URDF`` model of ``source`` (a path or URDF XML text), meshes not loaded.

    Raises ValueError for text that is not well-formed XML, not a ``<robot>``, or whose joints
    name links that do not exist, or that have no parent/child; for duplicate link or joint
    names, a link that is the child of two joints, joints that form a cycle (a URDF is a
    tree), and a ``<limit>`` with a negative or NaN ``effort`` or ``velocity``, or (revolute
    and prismatic joints) a NaN bound or ``lower`` > ``upper``.
    """
    yourdfpy = _import_yourdfpy()
    text, where = _read_source(source)
    try:
        root = ET.fromstring(text)
    except ET.ParseError as err:
        raise ValueError(f"{where} is not well-formed XML: {err}") from None
    if root.tag != "robot":
        raise ValueError(f"{where} is not a URDF: its root element is <{root.tag}>, expected "
                         f"<robot>")
    for j in root.findall("joint"):
        name = j.get("name")
        if name is None:
            raise ValueError(f"{where}: a <joint> has no name attribute")
        for tag in ("parent", "child"):
            el = j.find(tag)
            if el is None or el.get("link") is None:
                raise ValueError(f"{where}: joint {name!r} has no <{tag} link=...>")
    _check_structure(root, where)
    try:
        model = yourdfpy.URDF.load(io.BytesIO(text), build_scene_graph=False, load_meshes=False,
                                   build_collision_scene_graph=False,
                                   load_collision_meshes=False)
    except Exception as err:  # yourdfpy raises its own error types and KeyError/ValueError
        raise ValueError(f"{where} could not be read as URDF: {type(err).__name__}: {err}") from None
    links = {lk.name for lk in model.robot.links}
    for j in model.robot.joints:
        for role, lk in (("parent", j.parent), ("child", j.child)):
            if lk not in links:
                raise ValueError(f"{where}: joint {j.name!r} names {role} link {lk!r}, which is "
                                 f"not a <link> of the robot")
        _check_limit(j, where)
    return model


def _duplicates(names: list[str]) -> list[str]:
    seen: set[str] = set()
    dup: set[str] = set()
    for k in names:
        (dup if k in seen else seen).add(k)
    return sorted(dup)


def _link_of(joint: ET.Element, tag: str) -> str:
    el = joint.find(tag)
    return "" if el is None else str(el.get("link"))


def _check_structure(root: ET.Element, where: str) -> None:
    """ValueError for duplicate link or joint names, a link with two parent joints or a cycle
    of joints."""
    for tag in ("link", "joint"):
        dup = _duplicates([str(el.get("name")) for el in root.findall(tag) if el.get("name") is not None])
        if dup:
            raise ValueError(f"{where}: {tag} names must be unique, got several <{tag}> named "
                             f"{dup}")
    parent_of: dict[str, tuple[str, str]] = {}  # child link -> (joint, parent link)
    for j in root.findall("joint"):  # parse_urdf checked that each has them
        name, parent, child = str(j.get("name")), _link_of(j, "parent"), _link_of(j, "child")
        if child in parent_of:
            raise ValueError(f"{where}: link {child!r} is the child of two joints, "
                             f"{parent_of[child][0]!r} and {name!r}: a URDF must be a tree, each "
                             f"link the child of at most one joint")
        parent_of[child] = (name, parent)
    done: set[str] = set()
    for start in parent_of:  # each link has at most one parent: follow them up
        path: list[tuple[str, str, str]] = []
        on_path: dict[str, int] = {}
        k = start
        while k in parent_of and k not in done:
            if k in on_path:
                cycle = path[on_path[k]:][::-1]
                desc = ", ".join(f"{jn!r} ({p!r} -> {c!r})" for jn, p, c in cycle)
                raise ValueError(f"{where}: the joints {desc} form a cycle through the links "
                                 f"{[c for _, _, c in cycle]}: a URDF must be a tree")
            on_path[k] = len(path)
            jn, p = parent_of[k]
            path.append((jn, p, k))
            k = p
        done.update(on_path)


def _check_limit(j, where: str) -> None:
    """ValueError naming the joint and the attribute of a bad ``<limit>``."""
    lim = j.limit
    if lim is None:
        return
    for attr in ("effort", "velocity"):
        v = getattr(lim, attr, None)
        if v is not None and not float(v) >= 0:
            raise ValueError(f"{where}: joint {j.name!r} has <limit {attr}=\"{v}\">: {attr} must "
                             f"be >= 0")
    if j.type not in ("revolute", "prismatic"):  # the spec ignores lower/upper elsewhere
        return
    for attr in ("lower", "upper"):
        v = getattr(lim, attr, None)
        if v is not None and math.isnan(float(v)):
            raise ValueError(f"{where}: joint {j.name!r} has <limit {attr}=\"{v}\">: {attr} must "
                             f"be a number")
    if lim.lower is not None and lim.upper is not None and float(lim.lower) > float(lim.upper):
        raise ValueError(f"{where}: joint {j.name!r} has <limit lower=\"{lim.lower}\" "
                         f"upper=\"{lim.upper}\">: lower must be <= upper")


def _origin(joint) -> torch.Tensor:
    m = joint.origin
    return torch.eye(4, dtype=torch.float64) if m is None else torch.as_tensor(m, dtype=torch.float64)


def from_urdf(
    source,
    end_link: str | Sequence[str] | None = None,
    root_link: str | None = None,
    *,
    base=None,
    tool=None,
    dtype: torch.dtype = torch.float64,
    device=None,
) -> KinematicChain:
    """A :class:`KinematicChain` from a URDF file path or URDF XML text.

    Args:
        source: a path to a .urdf file, or the URDF text.
        end_link: the chain's end link (default: the only leaf of the tree; ValueError listing
            the leaves when there are several), or several links, the ends of a tree's
            branches (a hand's fingertips): the chain then holds the joints of every branch
            (``chain.parents`` gives each joint's predecessor), ``chain.end_links`` lists the
            ends and the first is ``chain.end_link``.
        root_link: the chain's base link (default: the root of the tree).
        base, tool: transforms before the root link and after the end link (None, SE3 or
            (4, 4)).
        dtype, device: of the chain.

    Revolute, continuous, prismatic and fixed joints are supported, about any axis;
    floating and planar joints and mimic joints on the chain raise ValueError.  Joint limits
    (``lower``, ``upper``, velocity) are read; continuous joints have none.  A file that is not
    a tree (a link with two parent joints, a cycle of joints anywhere in it) or has duplicate
    names or bad limits raises ValueError naming them (:func:`parse_urdf`).
    """
    model = parse_urdf(source)
    robot = model.robot
    by_child = {j.child: j for j in robot.joints}
    children: dict[str, list] = {}
    for j in robot.joints:
        children.setdefault(j.parent, []).append(j)
    link_names = [lk.name for lk in robot.links]
    roots = [k for k in link_names if k not in by_child]
    if len(roots) != 1:
        raise ValueError(f"the URDF must be one tree with one root link, got roots {roots}")
    leaves = [k for k in link_names if k not in children]
    if end_link is None:
        if len(leaves) != 1:
            raise ValueError(f"end_link must be given: the robot {robot.name!r} has several leaf "
                             f"links {leaves}")
        end_link = leaves[0]
    if not isinstance(end_link, (str, list, tuple)):
        raise TypeError(f"end_link must be a link name, a list of them or None, got {end_link!r}")
    ends = [end_link] if isinstance(end_link, str) else list(end_link)
    if not ends:
        raise ValueError("end_link must name at least one link")
    for arg, k in [("end_link", e) for e in ends] + [("root_link", root_link)]:
        if k is not None and (not isinstance(k, str) or (k not in by_child and k not in roots)):
            raise ValueError(f"{arg} {k!r} is not a link of the robot {robot.name!r}; its links "
                             f"are {link_names}")
    root_link = roots[0] if root_link is None else root_link

    def ancestors(k):  # the joints from the tree root down to k
        path = []
        while k in by_child:
            path.append(by_child[k])
            k = by_child[k].parent
        return path[::-1]

    root_path = ancestors(root_link)
    paths, anchors = [], set()
    for e in ends:
        end_path = ancestors(e)
        common = 0
        while (common < min(len(end_path), len(root_path))
               and end_path[common] is root_path[common]):
            common += 1
        up = root_path[common:]  # from the common ancestor down to root_link: must be fixed
        moving = [j.name for j in up if j.type != "fixed"]
        if moving:
            raise ValueError(f"root_link {root_link!r} is not an ancestor of end_link {e!r} and "
                             f"hangs from it by the moving joints {moving}; choose a root_link "
                             f"on the path or attached to it by fixed joints")
        anchors.add(common)
        paths.append(end_path[common:])
    if len(anchors) != 1:
        raise ValueError(f"the end links {ends} must share one ancestor with root_link "
                         f"{root_link!r}")
    to_root = torch.eye(4, dtype=torch.float64)
    for j in root_path[anchors.pop():]:
        to_root = to_root @ _origin(j)
    inv_root = torch.linalg.inv(to_root)

    joints: list[Joint] = []
    parents: list[int] = []
    # link -> (the last actuated joint before it, -1 for none; offset from that joint's frame)
    links: dict[str, tuple[int, torch.Tensor]] = {root_link: (-1, torch.eye(4, dtype=torch.float64))}
    for path in paths:
        if path and path[0].parent not in links:
            links[path[0].parent] = (-1, inv_root.clone())  # the common ancestor
        for j in path:
            if j.child in links:  # shared with an earlier branch
                continue
            idx, off = links[j.parent]
            if j.type == "fixed":
                links[j.child] = (idx, off @ _origin(j))
                continue
            joints.append(_joint(j, off @ _origin(j)))
            parents.append(idx)
            links[j.child] = (len(joints) - 1, torch.eye(4, dtype=torch.float64))
    if not joints:
        raise ValueError(f"no actuated joint between {root_link!r} and {ends}")
    # Links hanging from the chain by fixed joints only (flanges, TCP frames).
    stack = list(links)
    while stack:
        k = stack.pop()
        for j in children.get(k, []):
            if j.type == "fixed" and j.child not in links:
                idx, off = links[k]
                links[j.child] = (idx, off @ _origin(j))
                stack.append(j.child)
    return KinematicChain(joints, links, ends[0], base=base, tool=tool, dtype=dtype,
                          device=device, name=robot.name, root_link=root_link, parents=parents,
                          end_links=ends)


def _joint(j, origin: torch.Tensor) -> Joint:
    """The Joint of an actuated URDF joint ``j`` with the given origin."""
    if j.type not in _KINDS:
        raise ValueError(f"joint {j.name!r} on the chain has type {j.type!r}; supported: "
                         f"revolute, continuous, prismatic, fixed")
    if j.mimic is not None:
        raise ValueError(f"joint {j.name!r} on the chain mimics {j.mimic.joint!r}: mimic "
                         f"joints are not supported")
    raw = [1.0, 0.0, 0.0] if j.axis is None else [float(x) for x in j.axis]
    norm = math.sqrt(sum(x * x for x in raw))
    if len(raw) != 3 or not (norm > 0 and math.isfinite(norm)):
        raise ValueError(f"joint {j.name!r} has axis {raw}: it must be a non-zero 3-vector")
    axis = (raw[0] / norm, raw[1] / norm, raw[2] / norm)
    lim = j.limit
    kind = _KINDS[j.type]
    lower = -math.inf if kind == CONTINUOUS or lim is None or lim.lower is None else float(lim.lower)
    upper = math.inf if kind == CONTINUOUS or lim is None or lim.upper is None else float(lim.upper)
    vel = math.inf if lim is None or lim.velocity is None else float(lim.velocity)
    return Joint(j.name, kind, axis, origin, lower, upper, vel)


def from_pk(serial_chain, *, base=None, tool=None, dtype: torch.dtype | None = None,
            device=None) -> KinematicChain:
    """A :class:`KinematicChain` from a ``pytorch_kinematics.SerialChain``.

    Each pk frame moves by ``link.offset @ joint.offset @ M(axis, q)`` relative to its parent;
    the offsets are taken in the pk chain's precision (pk's URDF parser reads angles in
    float32).  dtype and device default to the pk chain's.
    """
    frames = getattr(serial_chain, "_serial_frames", None)
    if frames is None:
        raise TypeError(f"serial_chain must be a pytorch_kinematics.SerialChain, got "
                        f"{type(serial_chain).__name__}")
    lows, highs = serial_chain.get_joint_limits() if hasattr(serial_chain, "get_joint_limits") \
        else (None, None)
    joints: list[Joint] = []
    links: dict[str, tuple[int, torch.Tensor]] = {}
    acc = torch.eye(4, dtype=torch.float64)
    links[frames[0].name] = (-1, acc.clone())
    for f in frames[1:]:
        lo = f.link.offset.get_matrix()[0] if f.link.offset is not None else None
        jo = f.joint.offset.get_matrix()[0] if f.joint.offset is not None else None
        for m in (lo, jo):
            if m is not None:
                acc = acc @ m.detach().to("cpu", torch.float64)
        if f.joint.joint_type == "fixed":
            links[f.name] = (len(joints) - 1, acc.clone())
            continue
        if f.joint.joint_type not in ("revolute", "prismatic"):
            raise ValueError(f"pk joint {f.joint.name!r} has type {f.joint.joint_type!r}")
        ax = [float(x) for x in f.joint.axis.detach().cpu().double()]
        axis = (ax[0], ax[1], ax[2])
        kind = REVOLUTE if f.joint.joint_type == "revolute" else PRISMATIC
        k = len(joints)
        lower = float(lows[k]) if lows is not None else -math.inf
        upper = float(highs[k]) if highs is not None else math.inf
        joints.append(Joint(f.joint.name, kind, axis, acc, lower, upper))
        acc = torch.eye(4, dtype=torch.float64)
        links[f.name] = (len(joints) - 1, acc.clone())
    return KinematicChain(joints, links, frames[-1].name, base=base, tool=tool,
                          dtype=serial_chain.dtype if dtype is None else dtype,
                          device=serial_chain.device if device is None else device,
                          name="pk", root_link=frames[0].name)


# ------------------------------------------------------------------- robot data
def example_robot_data_dir() -> Path:
    """The ``robots`` folder of the installed ``example-robot-data`` package (or of the
    directory named by ``EXAMPLE_ROBOT_DATA_MODEL_DIR``).  FileNotFoundError if neither."""
    env = os.environ.get("EXAMPLE_ROBOT_DATA_MODEL_DIR")
    candidates = [Path(env)] if env else []
    try:
        from importlib import metadata

        dist = metadata.distribution("example-robot-data")
        candidates.append(Path(str(dist.locate_file("cmeel.prefix/share/example-robot-data/robots"))))
    except Exception:  # not installed: the error below says what to install
        pass
    for c in candidates:
        if c.is_dir():
            return c
    raise FileNotFoundError("the URDF files of real robots come from the package "
                            "`example-robot-data` (pip install example-robot-data); it is not "
                            "installed (or set EXAMPLE_ROBOT_DATA_MODEL_DIR to its robots folder)")
