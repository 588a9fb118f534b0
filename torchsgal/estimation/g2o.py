"""Read and write pose-graph files: g2o (``VERTEX_SE3:QUAT``, ``EDGE_SE3:QUAT``, ``VERTEX_SE2``,
``EDGE_SE2``), iSAM (``VERTEX3``, ``EDGE3``) and TORO (``VERTEX2``, ``EDGE2``), read as GTSAM's
``gtsam/slam/dataset.cpp`` reads them.

Each edge ``i j`` holds a measurement Z of the relative pose ``T_i^-1 T_j`` and the
information matrix of its residual.  Information comes back in torchsgal's tangent order
(SE3 ``[rho, phi]``, SE2 ``[rho, theta]``); the files order it thus:

- ``EDGE_SE3:QUAT i j x y z qx qy qz qw`` + 21 upper-triangular entries, row by row, in
  translation-first order: torchsgal's order as it is (GTSAM swaps the blocks into its
  rotation-first order).  Quaternions are normalised.
- ``EDGE3 i j x y z roll pitch yaw`` + 21 entries in rotation-first order (GTSAM reads them
  as given, in its own order): the blocks are swapped.  The rotation is
  ``Rz(yaw) Ry(pitch) Rx(roll)`` (GTSAM's ``Rot3::Ypr(yaw, pitch, roll)``).
- ``EDGE_SE2 i j x y theta`` + 6 upper-triangular entries (g2o order ``I_xx I_xy I_xt I_yy
  I_yt I_tt``).
- ``EDGE2 i j x y theta`` + TORO's 6 entries ``I_xx I_xy I_yy I_tt I_xt I_yt`` (GTSAM's
  ``NoiseFormatTORO``).

Vertices: ``VERTEX_SE3:QUAT id x y z qx qy qz qw``, ``VERTEX3 id x y z roll pitch yaw``,
``VERTEX_SE2``/``VERTEX2 id x y theta``.  Blank lines, ``#`` comments and g2o's ``FIX`` lines
are skipped; any other tag, a wrong count or a token that is not a number raises ValueError
with the line number and the token.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np
import torch

from ..groups import SE2, SE3, SO3

EDGE_TAGS = ("EDGE_SE3:QUAT", "EDGE3", "EDGE_SE2", "EDGE2")
VERTEX_TAG = {"EDGE_SE3:QUAT": "VERTEX_SE3:QUAT", "EDGE3": "VERTEX3", "EDGE_SE2": "VERTEX_SE2",
              "EDGE2": "VERTEX2"}
_VERTEX_SIZE = {"VERTEX_SE3:QUAT": 7, "VERTEX3": 6, "VERTEX_SE2": 3, "VERTEX2": 3}
_EDGE_SIZE = {"EDGE_SE3:QUAT": 7 + 21, "EDGE3": 6 + 21, "EDGE_SE2": 3 + 6, "EDGE2": 3 + 6}
_IS_3D = {"EDGE_SE3:QUAT": True, "EDGE3": True, "EDGE_SE2": False, "EDGE2": False,
          "VERTEX_SE3:QUAT": True, "VERTEX3": True, "VERTEX_SE2": False, "VERTEX2": False}
_SWAP_SE3 = [3, 4, 5, 0, 1, 2]  # [phi, rho] <-> [rho, phi]
_SKIPPED = ("FIX", "EQUIV")  # g2o's fixed vertices, TORO's vertex equivalences: GTSAM skips them too
_TORO = [(0, 0), (0, 1), (1, 1), (2, 2), (0, 2), (1, 2)]  # TORO's entry order (EDGE2)


@dataclass
class PoseGraph:
    """A pose graph as read from a file.

    group         ``SE3`` or ``SE2``.
    ids           int64 (N,): the vertex ids, sorted: those of the vertex lines and of the edges.
    poses         the vertices' poses, a ``group`` element of batch (N,) in the order of ``ids``,
                  or None if the file has no vertex lines.
    edges         int64 (E, 2): positions in ``ids`` of each edge's two vertices (i, j).
    measurements  ``group`` element of batch (E,): Z_ij, a measurement of T_i^-1 T_j.
    information   float64 (E, d, d), d = group.dof: the information of each residual, in
                  torchsgal's tangent order ([rho, phi] for SE3, [rho, theta] for SE2).
    edge_tag      the file's edge format (one of ``EDGE_TAGS``), which ``write_pose_graph``
                  writes by default.
    """

    group: type[SE3] | type[SE2]
    ids: torch.Tensor
    poses: SE3 | SE2 | None
    edges: torch.Tensor
    measurements: SE3 | SE2
    information: torch.Tensor
    edge_tag: str

    @property
    def edge_ids(self) -> torch.Tensor:
        """int64 (E, 2): the vertex ids of each edge (as written in the file)."""
        return self.ids[self.edges]


def _path(path) -> str | os.PathLike:
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path must be a str or an os.PathLike, got {type(path).__name__}")
    return path


def _pose_graph(graph) -> PoseGraph:
    if not isinstance(graph, PoseGraph):
        raise TypeError(f"graph must be a PoseGraph (read_pose_graph), got {type(graph).__name__}")
    return graph


def read_pose_graph(path: str | os.PathLike) -> PoseGraph:
    """Reads a g2o, iSAM or TORO pose-graph file (see the module docstring for the formats and
    the information order).  All edges must be of one dimension (3-D or 2-D) and one format;
    if the file has vertex lines, every vertex of an edge must have one."""
    path = _path(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"no pose-graph file at {os.fspath(path)!r}")
    vertices: dict[str, list] = {}
    edges: dict[str, list] = {}
    # Bytes that are not UTF-8 become U+FFFD: harmless in a comment, a token that is not a
    # number (an error naming the line) elsewhere.
    with open(path, encoding="utf-8", errors="replace") as f:
        for number, line in enumerate(f, start=1):
            tokens = line.split()
            if not tokens or tokens[0].startswith("#") or tokens[0] in _SKIPPED:
                continue
            tag = tokens[0]
            if tag in _VERTEX_SIZE:
                vertices.setdefault(tag, []).append(_numbers(tokens, 1, _VERTEX_SIZE[tag], path, number))
            elif tag in _EDGE_SIZE:
                edges.setdefault(tag, []).append(_numbers(tokens, 2, _EDGE_SIZE[tag], path, number))
            else:
                raise ValueError(f"{path}:{number}: unknown tag {tag!r}; expected one of "
                                 f"{tuple(_VERTEX_SIZE) + EDGE_TAGS} (or FIX, EQUIV, #comments)")
    if len(edges) != 1:
        found = tuple(edges) or "none"
        raise ValueError(f"{path}: a pose graph needs edges of exactly one format of {EDGE_TAGS}, "
                         f"found {found}")
    (edge_tag, rows), = edges.items()
    is_3d = _IS_3D[edge_tag]
    wrong = [t for t in vertices if _IS_3D[t] != is_3d]
    if wrong or len(vertices) > 1:
        raise ValueError(f"{path}: vertex lines {tuple(vertices)} do not match the edges {edge_tag!r} "
                         f"(one vertex format, of the edges' dimension)")
    pairs = torch.tensor([r[0] for r in rows], dtype=torch.int64)  # (E, 2) ids
    data = torch.tensor(np.array([r[1] for r in rows]), dtype=torch.float64)  # (E, k)
    vertex_ids = torch.zeros(0, dtype=torch.int64)
    vertex_data = None
    if vertices:
        (vertex_tag, vrows), = vertices.items()
        vertex_ids = torch.tensor([r[0][0] for r in vrows], dtype=torch.int64)
        vertex_data = torch.tensor(np.array([r[1] for r in vrows]), dtype=torch.float64)
        if torch.unique(vertex_ids).numel() != vertex_ids.numel():
            raise ValueError(f"{path}: a vertex id appears on more than one vertex line")
    ids = torch.unique(torch.cat([vertex_ids, pairs.reshape(-1)]))  # sorted
    poses = None
    if vertex_data is not None:
        present = torch.isin(ids, vertex_ids)
        if not bool(present.all()):
            first = int(ids[int(torch.argmin(present.to(torch.int8)))])
            raise ValueError(f"{path}: vertex {first} of an edge has no vertex line "
                             f"({int((~present).sum())} such vertices)")
        order = torch.argsort(vertex_ids)
        poses = _pose(vertex_tag, vertex_data[order])
    measurements, information = _edge(edge_tag, data)
    return PoseGraph(group=SE3 if is_3d else SE2, ids=ids, poses=poses,
                     edges=torch.searchsorted(ids, pairs), measurements=measurements,
                     information=information, edge_tag=edge_tag)


def write_pose_graph(path: str | os.PathLike, graph: PoseGraph, edge_tag: str | None = None) -> None:
    """Writes ``graph`` in the format of ``edge_tag`` (default ``graph.edge_tag``; one of
    ``EDGE_TAGS`` of the graph's dimension), with the matching vertex lines if it has poses;
    numbers with 17 significant digits, so that reading it back gives the same float64 values
    (rotations up to the rounding of their quaternion or angles)."""
    _pose_graph(graph)
    _path(path)
    edge_tag = graph.edge_tag if edge_tag is None else edge_tag
    if edge_tag not in EDGE_TAGS:
        raise ValueError(f"edge_tag must be one of {EDGE_TAGS}, got {edge_tag!r}")
    if _IS_3D[edge_tag] != (graph.group is SE3):
        raise ValueError(f"edge_tag {edge_tag!r} does not fit a graph of {graph.group.__name__}")
    _check_graph(graph)
    lines = []
    if graph.poses is not None:
        values = _pose_numbers(VERTEX_TAG[edge_tag], graph.poses)
        for vid, v in zip(graph.ids.tolist(), values.tolist()):
            lines.append(" ".join([VERTEX_TAG[edge_tag], str(vid)] + [_fmt(x) for x in v]))
    values = torch.cat([_pose_numbers(edge_tag, graph.measurements),
                        _information_numbers(edge_tag, graph.information)], dim=-1)
    for (i, j), v in zip(graph.edge_ids.tolist(), values.tolist()):
        lines.append(" ".join([edge_tag, str(i), str(j)] + [_fmt(x) for x in v]))
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")


def odometry_initial_guess(graph: PoseGraph) -> SE3 | SE2:
    """Initial poses (N,) in the order of ``graph.ids`` as GTSAM's ``load2D`` builds them for a
    file without vertices: in file order, an edge's first vertex not yet placed is put at the
    identity and its second at ``T_i Z_ij``; vertices no edge reaches stay at the identity.
    Sequential by nature (each pose depends on the one before), so it runs on the host once,
    in float64; the poses come back with the dtype and device of ``graph.measurements``."""
    _pose_graph(graph)
    _check_graph(graph)
    M = graph.measurements.as_matrix().detach().cpu().numpy()
    poses = np.tile(np.eye(M.shape[-1]), (graph.ids.numel(), 1, 1))
    placed = np.zeros(graph.ids.numel(), dtype=bool)
    for e, (i, j) in enumerate(graph.edges.tolist()):
        if not placed[i]:
            placed[i] = True
        if not placed[j]:
            poses[j] = poses[i] @ M[e]
            placed[j] = True
    Z = graph.measurements
    return graph.group.from_matrix(torch.from_numpy(poses)).to(dtype=Z.dtype, device=Z.device)


def _check_graph(graph: PoseGraph) -> None:
    """The fields' types and shapes agree (a PoseGraph made by hand), ValueError otherwise."""
    if graph.group not in (SE3, SE2):
        raise ValueError(f"graph.group must be SE3 or SE2, got {graph.group!r}")
    n, d = graph.ids.shape[0], graph.group.dof
    E = graph.edges.shape[0]
    problems = []
    if graph.ids.dtype != torch.int64 or graph.ids.dim() != 1:
        problems.append(f"ids must be int64 (N,), got {graph.ids.dtype} {tuple(graph.ids.shape)}")
    if graph.edges.dtype != torch.int64 or graph.edges.shape != (E, 2):
        problems.append(f"edges must be int64 (E, 2), got {graph.edges.dtype} {tuple(graph.edges.shape)}")
    elif E and (int(graph.edges.min()) < 0 or int(graph.edges.max()) >= n):
        problems.append(f"edges must hold positions in ids, in [0, {n - 1}]")
    if not isinstance(graph.measurements, graph.group) or graph.measurements.batch_shape != (E,):
        problems.append(f"measurements must be {graph.group.__name__} of batch ({E},), got "
                        f"{type(graph.measurements).__name__}")
    if graph.information.shape != (E, d, d):
        problems.append(f"information must have shape ({E}, {d}, {d}), got {tuple(graph.information.shape)}")
    elif not graph.information.is_floating_point():
        problems.append(f"information must be floating point, got {graph.information.dtype}")
    elif E:  # the formats store one triangle: an asymmetric matrix would come back as another
        W = graph.information.detach()
        asym = float((W - W.mT).abs().amax())
        if asym > 1e3 * torch.finfo(W.dtype).eps * float(W.abs().amax()):
            problems.append(f"information must be symmetric (the files hold its upper triangle), "
                            f"got max |W - W^T| = {asym:.3g}")
    if graph.poses is not None and (not isinstance(graph.poses, graph.group)
                                    or graph.poses.batch_shape != (n,)):
        problems.append(f"poses must be None or {graph.group.__name__} of batch ({n},)")
    if problems:
        raise ValueError("graph: " + "; ".join(problems))
    # what the readers refuse, refused before writing: ids >= 0 and distinct, finite numbers
    if n and int(graph.ids.min()) < 0:
        problems.append(f"ids must be >= 0 (g2o and TORO vertex ids), got {int(graph.ids.min())}")
    if graph.ids.unique().numel() != n:
        problems.append("ids must be distinct (one vertex line each)")
    for name, t in (("measurements", graph.measurements.as_matrix()), ("information", graph.information),
                    ("poses", None if graph.poses is None else graph.poses.as_matrix())):
        if t is not None and not bool(torch.isfinite(t).all()):
            problems.append(f"{name} must be finite")
    if problems:
        raise ValueError("graph: " + "; ".join(problems))


# --------------------------------------------------------------------------- parsing
def _numbers(tokens: list[str], n_ids: int, n_values: int, path, number: int):
    tag = tokens[0]
    expected = n_ids + n_values
    if len(tokens) - 1 != expected:
        raise ValueError(f"{path}:{number}: {tag} needs {expected} fields after the tag "
                         f"({n_ids} ids, {n_values} numbers), got {len(tokens) - 1}")
    ids = []
    for k, t in enumerate(tokens[1:1 + n_ids], start=1):
        if not (t.isascii() and t.isdigit()) or int(t) >= 2 ** 63:
            raise ValueError(f"{path}:{number}: {tag} field {k}, token {t!r}, is not a vertex id "
                             f"(an integer in [0, 2^63))")
        ids.append(int(t))
    try:
        values = np.array(tokens[1 + n_ids:], dtype=np.float64)
        ok = bool(np.isfinite(values).all())
    except ValueError:
        ok = False
    if not ok:  # find the token to name
        for k, t in enumerate(tokens[1 + n_ids:], start=1 + n_ids):
            try:
                v = float(t)
            except ValueError:
                v = math.nan
            if not math.isfinite(v):
                raise ValueError(f"{path}:{number}: {tag} field {k}, token {t!r}, is not a finite number")
    if tag.endswith(":QUAT") and not values[3:7].any():
        raise ValueError(f"{path}:{number}: {tag} fields {n_ids + 4}-{n_ids + 7}, the quaternion "
                         f"(qx qy qz qw), are all zero: no rotation")
    return ids, values


def _rpy_rotation(rpy: torch.Tensor) -> torch.Tensor:
    """Rz(yaw) Ry(pitch) Rx(roll) (..., 3, 3) of (..., 3) [roll, pitch, yaw] (GTSAM's Rot3::Ypr)."""
    cr, cp, cy = torch.cos(rpy).unbind(-1)
    sr, sp, sy = torch.sin(rpy).unbind(-1)
    return torch.stack([
        torch.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1),
        torch.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1),
        torch.stack([-sp, cp * sr, cp * cr], -1)], -2)


def _rotation_rpy(C: torch.Tensor) -> torch.Tensor:
    """[roll, pitch, yaw] (..., 3) with C = Rz(yaw) Ry(pitch) Rx(roll), pitch in [-pi/2, pi/2]."""
    roll = torch.atan2(C[..., 2, 1], C[..., 2, 2])
    pitch = torch.atan2(-C[..., 2, 0], torch.hypot(C[..., 2, 1], C[..., 2, 2]))
    yaw = torch.atan2(C[..., 1, 0], C[..., 0, 0])
    return torch.stack([roll, pitch, yaw], -1)


def _planar(x: torch.Tensor) -> SE2:
    c, s = torch.cos(x[:, 2]), torch.sin(x[:, 2])
    C = torch.stack([torch.stack([c, -s], -1), torch.stack([s, c], -1)], -2)
    return SE2.from_components(C, x[:, :2])


def _pose(tag: str, x: torch.Tensor) -> SE3 | SE2:
    """Poses (n,) of the numbers x (n, k) of vertex or edge lines of format ``tag``."""
    if tag in ("VERTEX_SE3:QUAT", "EDGE_SE3:QUAT"):
        C = SO3.from_quaternion(x[:, 3:7], order="xyzw").as_matrix()
        return SE3.from_components(C, x[:, :3])
    if tag in ("VERTEX3", "EDGE3"):
        return SE3.from_components(_rpy_rotation(x[:, 3:6]), x[:, :3])
    return _planar(x)


def _symmetric_upper(v: torch.Tensor, d: int) -> torch.Tensor:
    """(n, d, d) symmetric matrices of their upper triangles (n, d (d + 1) / 2), row by row."""
    r, c = torch.triu_indices(d, d)
    M = v.new_zeros(v.shape[0], d, d)
    M[:, r, c] = v
    M[:, c, r] = v
    return M


def _edge(tag: str, x: torch.Tensor):
    if tag == "EDGE_SE3:QUAT":
        return _pose(tag, x[:, :7]), _symmetric_upper(x[:, 7:], 6)  # translation first already
    if tag == "EDGE3":
        info = _symmetric_upper(x[:, 6:], 6)
        return _pose(tag, x[:, :6]), info[:, _SWAP_SE3][:, :, _SWAP_SE3]
    if tag == "EDGE_SE2":
        return _planar(x[:, :3]), _symmetric_upper(x[:, 3:], 3)
    M = x.new_zeros(x.shape[0], 3, 3)  # EDGE2: TORO's order
    for k, (r, c) in enumerate(_TORO):
        M[:, r, c] = x[:, 3 + k]
        M[:, c, r] = x[:, 3 + k]
    return _planar(x[:, :3]), M


# --------------------------------------------------------------------------- writing
def _fmt(x: float) -> str:
    return format(x, ".17g")


def _pose_numbers(tag: str, poses: SE3 | SE2) -> torch.Tensor:
    M = poses.as_matrix().detach().cpu().to(torch.float64)
    if tag in ("VERTEX_SE3:QUAT", "EDGE_SE3:QUAT"):
        q = SO3.from_matrix(M[:, :3, :3]).as_quaternion(order="xyzw")
        return torch.cat([M[:, :3, 3], q], -1)
    if tag in ("VERTEX3", "EDGE3"):
        return torch.cat([M[:, :3, 3], _rotation_rpy(M[:, :3, :3])], -1)
    theta = torch.atan2(M[:, 1, 0], M[:, 0, 0])
    return torch.stack([M[:, 0, 2], M[:, 1, 2], theta], -1)


def _information_numbers(tag: str, information: torch.Tensor) -> torch.Tensor:
    W = information.detach().cpu().to(torch.float64)
    if tag == "EDGE3":
        W = W[:, _SWAP_SE3][:, :, _SWAP_SE3]
    if tag == "EDGE2":
        return torch.stack([W[:, r, c] for r, c in _TORO], -1)
    d = W.shape[-1]
    r, c = torch.triu_indices(d, d)
    return W[:, r, c]
