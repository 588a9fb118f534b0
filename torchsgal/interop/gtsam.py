"""Converters between torchsgal and GTSAM (``gtsam``, the ``peers`` extra; imported only when a
converter runs).

Groups and matrices (GTSAM's ``.matrix()`` is ours except for NavState):

| GTSAM | torchsgal | GTSAM tangent | ``xi_gtsam = xi_ours[perm]`` |
|---|---|---|---|
| ``Rot2`` | SO2 | ``[theta]`` | ``(0,)`` |
| ``Pose2`` | SE2 | ``[x, y, theta]`` | ``(0, 1, 2)`` |
| ``Rot3`` | SO3 | ``[omega]`` | ``(0, 1, 2)`` |
| ``Pose3`` | SE3 | ``[omega, v]`` | ``(3, 4, 5, 0, 1, 2)`` |
| ``NavState`` | SE23 | ``[omega, position, velocity]`` | ``(6, 7, 8, 0, 1, 2, 3, 4, 5)`` |
| ``Gal3`` | SGal3 | ``[omega, velocity, position, time]`` | ``(6, 7, 8, 3, 4, 5, 0, 1, 2, 9)`` |
| ``Similarity3`` | Sim3 | ``[omega, u, lambda]`` | ``(3, 4, 5, 0, 1, 2, 6)`` |
| ``Point2``, ``Point3`` | vectors | ``[x, y(, z)]`` | identity |

For each group, GTSAM's ``Expmap(xi_ours[perm])`` is our ``exp(xi_ours)`` and its ``Hat`` puts
the same entries in the same places (NavState's matrix has the velocity and position columns
swapped, ``[[R, p, v], ...]``; ours is ``[[C, v, r], ...]``).  GTSAM perturbs on the right as
torchsgal does: for every type but NavState, ``X.retract(v) = X * Expmap(v)`` and
``X.localCoordinates(Y) = Logmap(X.between(Y))``, so tangents, covariances and Jacobians map
exactly by the permutation: ``P_gtsam = M P M^T`` and ``J_gtsam = M_out J M_in^T`` with
``M = I[perm]``.

NavState's ``retract`` (unless GTSAM is built with ``GTSAM_NAVSTATE_EXPMAP``) is the
component-wise chart ``retract([phi, p, q]) = (R Exp(phi), t + R p, v + R q)`` and
``localCoordinates`` its inverse; our ``X exp([rho, nu, phi])`` is ``(R Exp(phi), t + R J_l(phi)
rho, v + R J_l(phi) nu)`` (J_l the left Jacobian of SO(3)).  The two charts differ at second
order (``p = J_l(phi) rho``) and agree to first order at the point: their differentials at zero
are both the permutation, so Jacobians (derivatives at zero perturbation) and covariances of
small perturbations (linearised at the point, as GTSAM's marginals are) map by the permutation.
The exact chart change is ``navstate_local_to_tangent`` / ``tangent_to_navstate_local``;
``navstate_retract_is_expmap()`` tells which chart the installed GTSAM uses.  (Rot3 and Pose3
retract by Expmap in GTSAM's default build, GTSAM_ROT3_EXPMAP and GTSAM_POSE3_EXPMAP.)
"""
from __future__ import annotations

from typing import Any

import numpy as np
import torch

from ..functional import checks
from ..groups import SE2, SE3, SE23, SO2, SO3, LieGroup, SGal3, Sim3
from ._common import (
    inverse_permutation,
    nest,
    nested_shape,
    permutation_matrix,
    permute_jacobian,
    permute_square,
    permute_vector,
    require,
)

# GTSAM type -> (torchsgal group or None for points, xi_gtsam = xi_ours[perm])
TYPES: dict[str, tuple[type[LieGroup] | None, tuple[int, ...]]] = {
    "Rot2": (SO2, (0,)),
    "Pose2": (SE2, (0, 1, 2)),
    "Rot3": (SO3, (0, 1, 2)),
    "Pose3": (SE3, (3, 4, 5, 0, 1, 2)),
    "NavState": (SE23, (6, 7, 8, 0, 1, 2, 3, 4, 5)),
    "Gal3": (SGal3, (6, 7, 8, 3, 4, 5, 0, 1, 2, 9)),
    "Similarity3": (Sim3, (3, 4, 5, 0, 1, 2, 6)),
    "Point2": (None, (0, 1)),
    "Point3": (None, (0, 1, 2)),
}
# a GTSAM type: its name ("Pose3") or the class (gtsam.Pose3)
GtsamType = str | type
# torchsgal group -> GTSAM type
GTSAM_TYPE: dict[type[LieGroup], str] = {g: name for name, (g, _) in TYPES.items() if g is not None}


def _gtsam():
    return require("gtsam", "torchsgal.interop.gtsam")


def _type_name(gtsam_type, name: str = "gtsam_type") -> str:
    """A GTSAM type given by name ("Pose3") or as the class (gtsam.Pose3)."""
    key = gtsam_type.__name__ if isinstance(gtsam_type, type) else gtsam_type
    if not isinstance(key, str) or key not in TYPES:
        raise ValueError(f"{name} must be one of {tuple(TYPES)} (a name or the gtsam class), "
                         f"got {gtsam_type!r}")
    return key


def _perm(gtsam_type, name: str = "gtsam_type") -> tuple[int, ...]:
    return TYPES[_type_name(gtsam_type, name)][1]


def _tensor(x, name: str) -> torch.Tensor:
    """A tensor, or a numpy array (GTSAM's vectors and matrices: float32 or float64) as float64;
    arrays of other kinds (integers, complex numbers, strings) are refused as tensors are."""
    if isinstance(x, np.ndarray):
        if x.dtype not in (np.float32, np.float64):
            raise TypeError(f"{name} must be a float32 or float64 array or tensor, got a numpy "
                            f"array of dtype {x.dtype}")
        x = torch.from_numpy(np.array(x, dtype=np.float64))
    return checks.floating(x, name)


# ------------------------------------------------------------------------------ tangents
def tangent_map(gtsam_type: GtsamType, dtype: torch.dtype | None = None,
                device: torch.device | str | None = None) -> torch.Tensor:
    """The permutation matrix M (d, d) with ``xi_gtsam = M xi_ours`` for the GTSAM type
    (a name such as "Pose3" or the class); ``M^-1 = M^T``."""
    return permutation_matrix(_perm(gtsam_type), dtype, device)


def tangent_to_gtsam(xi: torch.Tensor, gtsam_type: GtsamType) -> torch.Tensor:
    """Our tangent vectors (..., d) in GTSAM's order for ``gtsam_type``."""
    return permute_vector(_tensor(xi, "xi"), _perm(gtsam_type), "xi")


def tangent_from_gtsam(xi: torch.Tensor | np.ndarray, gtsam_type: GtsamType) -> torch.Tensor:
    """GTSAM's tangent vectors (..., d) (a tensor or a numpy array) in our order."""
    return permute_vector(_tensor(xi, "xi"), inverse_permutation(_perm(gtsam_type)), "xi")


def covariance_to_gtsam(P: torch.Tensor, gtsam_type: GtsamType) -> torch.Tensor:
    """Our covariances (..., d, d) on the right perturbation as GTSAM's: ``M P M^T``."""
    return permute_square(_tensor(P, "P"), _perm(gtsam_type), "P")


def covariance_from_gtsam(P: torch.Tensor | np.ndarray, gtsam_type: GtsamType) -> torch.Tensor:
    """GTSAM's covariances (..., d, d) (e.g. ``Marginals.marginalCovariance``, a tensor or a
    numpy array) in our order: ``M^T P M``."""
    return permute_square(_tensor(P, "P"), inverse_permutation(_perm(gtsam_type)), "P")


def _side(gtsam_type, name: str):
    return None if gtsam_type is None else _perm(gtsam_type, name)


def jacobian_to_gtsam(J: torch.Tensor, *, output: GtsamType | None, input: GtsamType | None) -> torch.Tensor:
    """Our Jacobian (..., m, n) of a map from ``input`` to ``output`` (GTSAM type names, or None
    for a plain vector side) in GTSAM's orders: ``M_out J M_in^-1``."""
    return permute_jacobian(_tensor(J, "J"), _side(output, "output"), _side(input, "input"), "J")


def jacobian_from_gtsam(J: torch.Tensor | np.ndarray, *, output: GtsamType | None,
                        input: GtsamType | None) -> torch.Tensor:
    """GTSAM's Jacobian (..., m, n) (the ``H`` arguments, a tensor or a numpy array) of a map
    from ``input`` to ``output`` (type names, or None for a plain vector side) in our orders:
    ``M_out^-1 J M_in``."""
    out = None if output is None else inverse_permutation(_perm(output, "output"))
    inp = None if input is None else inverse_permutation(_perm(input, "input"))
    return permute_jacobian(_tensor(J, "J"), out, inp, "J")


def navstate_local_to_tangent(v: torch.Tensor | np.ndarray) -> torch.Tensor:
    """The chart change of NavState: for GTSAM's component-wise ``v = [phi, p, q]`` (..., 9),
    our ``xi = [J_l(phi)^-1 p, J_l(phi)^-1 q, phi]`` with ``X.retract(v) = X exp(xi)``."""
    v = checks.vector(_tensor(v, "v"), 9, "v")
    phi, p, q = v[..., 0:3], v[..., 3:6], v[..., 6:9]
    Jinv = SO3.jl_inv(phi)
    rho = (Jinv @ p.unsqueeze(-1)).squeeze(-1)
    nu = (Jinv @ q.unsqueeze(-1)).squeeze(-1)
    return torch.cat((rho, nu, phi), dim=-1)


def tangent_to_navstate_local(xi: torch.Tensor) -> torch.Tensor:
    """The inverse of ``navstate_local_to_tangent``: ``[phi, J_l(phi) rho, J_l(phi) nu]``, GTSAM's
    ``X.localCoordinates(X exp(xi))`` for our xi (..., 9)."""
    xi = checks.vector(_tensor(xi, "xi"), 9, "xi")
    rho, nu, phi = xi[..., 0:3], xi[..., 3:6], xi[..., 6:9]
    J = SO3.jl(phi)
    p = (J @ rho.unsqueeze(-1)).squeeze(-1)
    q = (J @ nu.unsqueeze(-1)).squeeze(-1)
    return torch.cat((phi, p, q), dim=-1)


def navstate_retract_is_expmap() -> bool:
    """Whether the installed GTSAM's ``NavState.retract`` is ``X * Expmap(v)`` (built with
    GTSAM_NAVSTATE_EXPMAP: then NavState maps like the other types, by the permutation alone) or
    the component-wise chart of ``navstate_local_to_tangent`` (the default); read from one
    retract at the identity, where the two differ in the position."""
    gtsam = _gtsam()
    v = np.array([0.0, 0.0, 0.5, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0])  # phi about z, p along x
    moved = gtsam.NavState().retract(v)
    return bool(abs(float(np.asarray(moved.position())[0]) - 1.0) > 1e-3)


# ------------------------------------------------------------------------------ elements
def _with_data(x: torch.Tensor, name: str) -> torch.Tensor:
    """x, refused on the 'meta' device (shapes without values: nothing to convert)."""
    if x.device.type == "meta":
        raise ValueError(f"{name} is on the 'meta' device, which holds no values to convert; "
                         f"give it on cpu or cuda")
    return x


def _numpy_matrices(g: LieGroup) -> tuple[np.ndarray, tuple[int, ...]]:
    M = _with_data(g.as_matrix(), "g").detach().to("cpu", torch.float64)
    n = g.matrix_dim
    return M.reshape(-1, n, n).numpy(), tuple(g.batch_shape)


def _one_to_gtsam(gtsam, kind: str, M: np.ndarray):
    if kind == "Rot2":
        return gtsam.Rot2.fromCosSin(M[0, 0], M[1, 0])
    if kind == "Pose2":
        return gtsam.Pose2(gtsam.Rot2.fromCosSin(M[0, 0], M[1, 0]), M[:2, 2].copy())
    if kind == "Rot3":
        return gtsam.Rot3(M)
    if kind == "Pose3":
        return gtsam.Pose3(M)
    if kind == "NavState":  # ours [[C, v, r], ...]; NavState(R, position, velocity)
        return gtsam.NavState(gtsam.Rot3(M[:3, :3].copy()), M[:3, 4].copy(), M[:3, 3].copy())
    if kind == "Gal3":
        return gtsam.Gal3(M)
    return gtsam.Similarity3(M)


def to_gtsam(g: LieGroup) -> Any:
    """GTSAM objects of the elements of g (SO2, SE2, SO3, SE3, SE23, SGal3 or Sim3; any dtype,
    device and batch shape): one object for an unbatched g, else lists nested as the batch
    (as ``Tensor.tolist``).  One host copy, then one object per element (GTSAM has no batch)."""
    if not isinstance(g, LieGroup) or g._group not in GTSAM_TYPE:
        raise TypeError(f"g must be an element of one of {[c.__name__ for c in GTSAM_TYPE]}, "
                        f"got {type(g).__name__}")
    gtsam = _gtsam()
    kind = GTSAM_TYPE[g._group]
    if not hasattr(gtsam, kind):  # Gal3 came with GTSAM 4.3
        raise ImportError(f"the installed gtsam has no {kind} (GTSAM >= 4.3 has): upgrade it "
                          f"with pip install 'torchsgal[peers]'")
    mats, shape = _numpy_matrices(g)
    return nest([_one_to_gtsam(gtsam, kind, np.ascontiguousarray(m)) for m in mats], shape)


def _matrix_of(kind: str, obj) -> np.ndarray:
    if kind == "NavState":  # GTSAM's matrix is [[R, p, v], ...]; ours [[C, v, r], ...]
        M = np.eye(5)
        M[:3, :3] = obj.attitude().matrix()
        M[:3, 3] = np.asarray(obj.velocity()).reshape(3)
        M[:3, 4] = np.asarray(obj.position()).reshape(3)
        return M
    return np.asarray(obj.matrix(), dtype=np.float64)


def from_gtsam(objects, *, group: type[LieGroup] | None = None, dtype: torch.dtype = torch.float64,
               device: torch.device | str | None = None) -> LieGroup:
    """A batched element from a GTSAM object or (nested) lists of objects of one type (Rot2,
    Pose2, Rot3, Pose3, NavState, Gal3, Similarity3); the batch shape is the nesting's.
    ``group`` (optional) is the torchsgal group expected: needed for an empty list, and
    checked against the objects' type otherwise."""
    gtsam = _gtsam()
    dtype = checks.dtype_arg(dtype)
    classes = {name: getattr(gtsam, name) for name, (grp, _) in TYPES.items()
               if grp is not None and hasattr(gtsam, name)}
    if group is not None and group not in GTSAM_TYPE:
        raise TypeError(f"group must be None or one of {[c.__name__ for c in GTSAM_TYPE]}, got {group!r}")
    accepted = tuple(classes.values())
    flat, shape = nested_shape(objects, lambda o: isinstance(o, accepted), "objects",
                               "a gtsam " + ", ".join(classes))
    if not flat:
        if group is None:
            raise ValueError("objects is empty: pass group= to say which group to build")
        n = group.matrix_dim
        return group.from_matrix(torch.zeros(*shape, n, n, dtype=dtype, device=device))
    kind = next(k for k, c in classes.items() if isinstance(flat[0], c))
    if group is not None and GTSAM_TYPE[group] != kind:
        raise TypeError(f"objects are gtsam.{kind}, but group {group.__name__} needs "
                        f"gtsam.{GTSAM_TYPE[group]}")
    wanted = classes[kind]
    for i, obj in enumerate(flat):
        if type(obj) is not wanted and not isinstance(obj, wanted):
            raise TypeError(f"objects must all be gtsam.{kind} (as the first), but the element "
                            f"{i} (row-major) is {type(obj).__name__}")
    cls = next(grp for grp, name in GTSAM_TYPE.items() if name == kind)
    n = cls.matrix_dim
    mats = np.stack([_matrix_of(kind, o) for o in flat])
    return cls.from_matrix(torch.as_tensor(mats, dtype=dtype, device=device).reshape(*shape, n, n))


def points_to_gtsam(p: torch.Tensor) -> Any:
    """Points (..., 3) or (..., 2) as GTSAM's ``Point3``/``Point2`` (numpy vectors): one for an
    unbatched p, else lists nested as the batch."""
    checks.floating(p, "p")
    if p.dim() < 1 or p.shape[-1] not in (2, 3):
        raise ValueError(f"p must have shape (..., 3) or (..., 2), got {tuple(p.shape)}")
    flat = _with_data(p, "p").detach().to("cpu", torch.float64).reshape(-1, p.shape[-1]).numpy()
    return nest([row.copy() for row in flat], tuple(p.shape[:-1]))


def points_from_gtsam(points, *, dtype: torch.dtype = torch.float64,
                      device: torch.device | str | None = None) -> torch.Tensor:
    """A tensor (..., k) of GTSAM points (numpy vectors of length k = 2 or 3: float32 or
    float64, or integers, which ``gtsam.Point3`` of an integer array returns; complex, half,
    bool and other dtypes are refused), one or (nested) lists of them."""
    dtype = checks.dtype_arg(dtype)
    is_point = lambda o: isinstance(o, np.ndarray) and o.ndim == 1  # noqa: E731
    flat, shape = nested_shape(points, is_point, "points", "a point (1-D numpy array)")
    if not flat:
        raise ValueError("points is empty: there is no length to read")
    k = flat[0].shape[0]
    for i, p in enumerate(flat):
        if p.dtype not in (np.float32, np.float64) and p.dtype.kind not in "iu":
            raise TypeError(f"points must be float32, float64 or integer arrays, but point {i} "
                            f"(row-major) has dtype {p.dtype}")
        if p.shape != (k,) or k not in (2, 3):
            raise ValueError(f"points must all have length 2 or 3 and the same length, but point {i} "
                             f"(row-major) has shape {p.shape} and the first {(k,)}")
    return torch.as_tensor(np.stack(flat), dtype=dtype, device=device).reshape(*shape, k)
