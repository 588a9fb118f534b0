"""Converters between torchsgal and pypose (the ``peers`` extra; imported only when a converter
runs).  Batched tensor operations on both sides, differentiable, no host copy.

| torchsgal | pypose LieTensor (storage) | pypose algebra | tangent map |
|---|---|---|---|
| SO3 | ``SO3``: ``[qx, qy, qz, qw]`` | ``so3``: ``[phi]`` | identity |
| SE3 | ``SE3``: ``[t, qx, qy, qz, qw]`` | ``se3``: ``[tau, phi]`` | identity |
| Sim3 | ``Sim3``: ``[t, qx, qy, qz, qw, s]`` | ``sim3``: ``[tau, phi, sigma]`` | identity |

pypose's Sim3 matrix is ``[[s R, t], [0, 1]]``; ours is ``[[C, r], [0, 1/s]]``, the same
projective map (p -> s C p + s r), so ``t = s r`` and ``pp.sim3(xi).Exp().matrix()`` is s times
our ``Sim3.exp(xi)``'s matrix.  ``Exp`` of the same tangent vector gives the same element for
all three (pypose's se3 ``Exp`` loses about 2e-17/theta in the translation at small angles),
and pypose's ``so3.Jr`` is our ``SO3.jr`` (except at tiny angles, where pypose's is the identity).

Perturbation side: pypose perturbs on the LEFT.  Its optimisers update ``X <- Exp(d) X``
(``LieTensor.add_``) and autograd's gradient of a LieTensor is the derivative with respect to
that d.  With ``Exp(d_l) X = X Exp(Ad(X^-1) d_l)``, pypose's ``d_l = Ad(X) d_r`` for our right
perturbation ``d_r``: covariances map as ``P_ours = Ad(X)^-1 P_pp Ad(X)^-T`` and Jacobians as
``J_ours = Ad(Y)^-1 J_pp Ad(X)`` (Y the output element, X the input one).
"""
from __future__ import annotations

import torch

from ..functional import checks
from ..functional import so3 as _so3
from ..functional._blocking import values_readable
from ..groups import SE3, SO3, LieGroup, Sim3
from ._common import require

GROUPS = (SO3, SE3, Sim3)


def _pp():
    return require("pypose", "torchsgal.interop.pypose")


def _group_arg(g, name: str) -> LieGroup:
    if not isinstance(g, LieGroup) or g._group not in GROUPS:
        raise TypeError(f"{name} must be an element of SO3, SE3 or Sim3, got {type(g).__name__}")
    return g


def _lie_tensor(x, name: str, kinds: tuple[str, ...]):
    """x: a pypose LieTensor whose ltype is one of ``kinds`` ("SO3", "so3", ...); its kind."""
    pp = _pp()
    if not isinstance(x, pp.LieTensor):
        raise TypeError(f"{name} must be a pypose LieTensor of type {'/'.join(kinds)}, "
                        f"got {type(x).__name__}")
    for kind in kinds:
        if x.ltype == getattr(pp, f"{kind}_type"):
            return kind
    raise TypeError(f"{name} must be a pypose LieTensor of type {'/'.join(kinds)}, got one of "
                    f"type {type(x.ltype).__name__.removesuffix('Type')}")


def to_pypose(g: LieGroup):
    """A pypose LieTensor (SO3, SE3 or Sim3, batch shape g's) of our SO3, SE3 or Sim3 elements."""
    pp = _pp()
    _group_arg(g, "g")
    q = _so3.to_quaternion(g.rotation(), "xyzw")
    if isinstance(g, SO3):
        return pp.SO3(q)
    if isinstance(g, SE3):
        return pp.SE3(torch.cat((g.position(), q), dim=-1))
    assert isinstance(g, Sim3)  # _group_arg: SO3, SE3 or Sim3
    s = g.scale().unsqueeze(-1)
    return pp.Sim3(torch.cat((s * g.position(), q, s), dim=-1))


def from_pypose(x) -> LieGroup:
    """Our SO3, SE3 or Sim3 of a pypose LieTensor of type SO3, SE3 or Sim3 (quaternions are
    normalised; differentiable).  A Sim3 scale must be finite and > 0 (ValueError naming x;
    checked, with one host sync, where the values can be read: not on 'meta', inside a
    torch.func transform or while torch.compile traces)."""
    return _from_pypose(x, "x")


def _from_pypose(x, name: str) -> LieGroup:
    """``from_pypose``, its errors naming the argument ``name``."""
    kind = _lie_tensor(x, name, ("SO3", "SE3", "Sim3"))
    data = x.tensor()
    if kind == "SO3":
        return SO3.from_matrix(_so3.from_quaternion(data, "xyzw", name))
    C = _so3.from_quaternion(data[..., 3:7], "xyzw", name)
    if kind == "SE3":
        return SE3.from_components(rotation=C, position=data[..., 0:3])
    s = data[..., 7]
    if s.numel() and values_readable(s):
        bad = ~(torch.isfinite(s) & (s > 0))
        if bad.any():  # the host sync
            first = s.detach().reshape(-1)[bad.reshape(-1).int().argmax()].item()
            raise ValueError(f"{name} must be a pypose Sim3 with finite scales > 0 (its last "
                             f"component), got a scale of {first}")
    return Sim3.from_components(rotation=C, position=data[..., 0:3] / s.unsqueeze(-1), scale=s)


def tangent_to_pypose(xi: torch.Tensor, group: type[LieGroup]):
    """Our tangent vectors of ``group`` (SO3, SE3 or Sim3) as a pypose so3/se3/sim3 LieTensor
    (the same numbers: the orders agree)."""
    pp = _pp()
    if group not in GROUPS:
        raise TypeError(f"group must be SO3, SE3 or Sim3, got {group!r}")
    checks.vector(xi, group.dof, "xi")
    return {SO3: pp.so3, SE3: pp.se3, Sim3: pp.sim3}[group](xi)


def tangent_from_pypose(x) -> torch.Tensor:
    """Our tangent vectors of a pypose so3/se3/sim3 LieTensor (its numbers, as a plain tensor)."""
    _lie_tensor(x, "x", ("so3", "se3", "sim3"))
    return x.tensor()


def _element(at, name: str) -> LieGroup:
    """Our element, or a pypose LieTensor converted."""
    if isinstance(at, LieGroup):
        return _group_arg(at, name)
    return _from_pypose(at, name)


def perturbation_map(at) -> torch.Tensor:
    """M = Ad(at) (..., d, d) with ``d_pypose = M d_ours`` (pypose's left perturbation of the
    element ``at``, ours or a LieTensor, from our right one)."""
    return _element(at, "at").adjoint()


def _inverse_adjoint(at, name: str) -> torch.Tensor:
    return _element(at, name).inverse().adjoint()


def covariance_from_pypose(P: torch.Tensor, at) -> torch.Tensor:
    """A covariance (..., d, d) of pypose's left perturbation of ``at`` on our right one:
    ``Ad(at)^-1 P Ad(at)^-T``."""
    A = _inverse_adjoint(at, "at")
    checks.matrix(P, A.shape[-1], "P")
    checks.binary(P, 2, A, 2, "P", "at")
    return A @ P @ A.transpose(-1, -2)


def covariance_to_pypose(P: torch.Tensor, at) -> torch.Tensor:
    """A covariance (..., d, d) of our right perturbation of ``at`` on pypose's left one:
    ``Ad(at) P Ad(at)^T``."""
    A = perturbation_map(at)
    checks.matrix(P, A.shape[-1], "P")
    checks.binary(P, 2, A, 2, "P", "at")
    return A @ P @ A.transpose(-1, -2)


def _jacobian(J: torch.Tensor, left, right) -> torch.Tensor:
    """``left @ J @ right`` (either None: identity), with J's shape checked."""
    checks.floating(J, "J")
    m = "m" if left is None else left.shape[-1]
    n = "n" if right is None else right.shape[-2]
    if J.dim() < 2 or (left is not None and J.shape[-2] != m) or (right is not None and J.shape[-1] != n):
        raise ValueError(f"J must have shape (..., {m}, {n}), got {tuple(J.shape)}")
    for side, A in (("output", left), ("input", right)):
        if A is not None:  # dtype, device and batch of J against each element's
            checks.binary(J, 2, A, 2, "J", side)
    if left is not None and right is not None:  # and the two elements' batches together
        checks.broadcast_batch(J=J.shape[:-2], output=left.shape[:-2], input=right.shape[:-2])
    if left is not None:
        J = left @ J
    if right is not None:
        J = J @ right
    return J


def jacobian_from_pypose(J: torch.Tensor, *, output, input) -> torch.Tensor:
    """pypose's Jacobian (..., m, n) (left perturbations) of a map from the element ``input`` to
    the element ``output`` (ours or LieTensors; None for a plain vector side) on our right
    perturbations: ``Ad(output)^-1 J Ad(input)``."""
    left = None if output is None else _inverse_adjoint(output, "output")
    right = None if input is None else _element(input, "input").adjoint()
    return _jacobian(J, left, right)


def jacobian_to_pypose(J: torch.Tensor, *, output, input) -> torch.Tensor:
    """Our Jacobian (..., m, n) (right perturbations) of a map from ``input`` to ``output``
    (elements, or None for a plain vector side) on pypose's left ones:
    ``Ad(output) J Ad(input)^-1``."""
    left = None if output is None else _element(output, "output").adjoint()
    right = None if input is None else _inverse_adjoint(input, "input")
    return _jacobian(J, left, right)
