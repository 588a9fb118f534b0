"""Factor types: a residual written once for one factor, evaluated for all factors of a type.

A factor type is a residual function ``residual(*variables, *data) -> (..., dim)`` over group
elements (and Euclidean tensors) that broadcasts over leading batch axes, as every group
operation does, with the variables it reads and its data.  The engine calls it once per
type on batches (B, E) (B problems, E factors) and differentiates it with respect to the
right perturbations ``x exp(d)`` of its group variables (additive for Euclidean ones) by
forward-mode autodiff (``torch.func.jvp`` under ``torch.func.vmap`` over the tangent basis),
unless the type provides ``jacobians`` (the built-in ``Prior`` and ``Between`` do).

Noise: ``information`` W or ``sqrt_information`` L (W = L^T L), (dim, dim) shared by the
factors of the object, (E, dim, dim) per factor or (B, E, dim, dim) per problem and factor.
The whitened residual is L r and the cost 1/2 rho(|L r|^2) (``robust``).
"""
from __future__ import annotations

from collections.abc import Callable, Sequence

import torch

from ...functional import checks
from ...groups import LieGroup
from .robust import RobustLoss

__all__ = ["Factor", "Prior", "Between", "PointObservation"]

Data = torch.Tensor | LieGroup


def _indices(index, name: str) -> torch.Tensor:
    """An int64 (E,) index tensor from an int, a sequence or a tensor."""
    if isinstance(index, bool):
        raise TypeError(f"{name} must be an integer index or an int64 tensor (E,), got a bool")
    if isinstance(index, int):
        return torch.tensor([index], dtype=torch.int64)
    if not isinstance(index, torch.Tensor):
        if index is None or isinstance(index, (str, bytes)):
            raise TypeError(f"{name} must be an integer index or an int64 tensor (E,), got {index!r}")
        try:
            index = torch.as_tensor(index)
        except (TypeError, ValueError, RuntimeError):
            raise TypeError(f"{name} must be an integer index or an int64 tensor (E,), "
                            f"got {index!r}") from None
    if index.dtype not in (torch.int64, torch.int32, torch.int16, torch.int8, torch.uint8):
        raise TypeError(f"{name} must be an integer tensor (E,), got dtype {index.dtype}")
    if index.dim() == 0:
        index = index[None]
    if index.dim() != 1:
        raise ValueError(f"{name} must have shape (E,), got {tuple(index.shape)}")
    return index.to(torch.int64)


def _noise(noise, name: str, dim: int | None) -> None:
    """A noise matrix: a float tensor (m, m), (E, m, m) or (B, E, m, m), m the residual's size
    ``dim`` where it is given (else checked when the graph is linearised; E and B against the
    graph when its layout is made)."""
    checks.floating(noise, name)
    if noise.dim() not in (2, 3, 4) or noise.shape[-2] != noise.shape[-1]:
        raise ValueError(f"{name} must have shape (m, m), (E, m, m) or (B, E, m, m), got "
                         f"{tuple(noise.shape)}")
    if dim is not None and noise.shape[-1] != dim:
        raise ValueError(f"{name} must be ({dim}, {dim}), (E, {dim}, {dim}) or (B, E, {dim}, {dim}) "
                         f"for a residual of size {dim}, got {tuple(noise.shape)}")


class Factor:
    """A set of E factors of one type.

    residual       ``f(*variables, *data) -> (..., dim)``: the residual of ONE factor written
                   on group elements / tensors; it must broadcast over leading batch axes
                   (the engine passes batches (B, E)).
    variables      ``[(name, index), ...]``: for each argument, the variable's name and the
                   (E,) int64 indices of the elements each factor reads (an int for E = 1).
    data           tensors or group elements with leading batch (E,) (shared by the problems)
                   or (B, E) (one per problem), passed after the variables.  In a batched
                   graph a tensor whose two leading sizes are (B, E) is read as per problem
                   (group elements are never ambiguous: their batch has one or two axes).
    dim            the residual's size; without it the residual must have the full shape
                   (B, E, dim), with it its leading axes may broadcast.
    information / sqrt_information: the noise (see the module docstring); neither: identity.
    loss           a ``RobustLoss`` or None (plain least squares).
    jacobians      optional ``g(*variables, *data) -> (r, [J_1, ...])``, J_k (..., dim, dof_k)
                   the derivative of r with respect to the right perturbation of variable k
                   (additive for Euclidean variables), or ``(r, J)`` with the J_k side by side
                   in one tensor (..., dim, dof_1 + dof_2 + ...); default: forward-mode
                   autodiff.

    A subclass may set ``variable_kinds``, one entry per variable argument: a group class (or a
    tuple of them) the variable must be, an int k for a Euclidean variable of size k, or None;
    ``FactorGraph.add`` checks the graph's variables against it and names a mismatch.
    """

    variable_kinds: tuple | None = None

    def __init__(self, residual: Callable, variables: Sequence[tuple[str, object]],
                 data: Sequence[Data] = (), dim: int | None = None,
                 information: torch.Tensor | None = None,
                 sqrt_information: torch.Tensor | None = None,
                 loss: RobustLoss | None = None, jacobians: Callable | None = None):
        if not callable(residual):
            raise TypeError(f"residual must be callable, got {type(residual).__name__}")
        if jacobians is not None and not callable(jacobians):
            raise TypeError(f"jacobians must be callable or None, got {type(jacobians).__name__}")
        self.residual = residual
        self.jacobians = jacobians
        if not isinstance(variables, (list, tuple)) or not variables:
            raise TypeError("variables must be a non-empty list of (name, index) pairs")
        slots = []
        for k, item in enumerate(variables):
            if not (isinstance(item, (list, tuple)) and len(item) == 2 and isinstance(item[0], str)):
                raise TypeError(f"variables[{k}] must be a (name, index) pair, got {item!r}")
            slots.append((item[0], _indices(item[1], f"variables[{k}] index")))
        sizes = {idx.shape[0] for _, idx in slots}
        if len(sizes - {1}) > 1:
            raise ValueError(f"the variables' index tensors must have one length E (or 1), got "
                             f"{[tuple(i.shape) for _, i in slots]}")
        self.size = max(sizes)
        self.slots = [(n, idx.expand(self.size)) for n, idx in slots]
        if not isinstance(data, (list, tuple)):
            raise TypeError(f"data must be a list or tuple of tensors / group elements, got "
                            f"{type(data).__name__}")
        for k, d in enumerate(data):
            if not isinstance(d, (torch.Tensor, LieGroup)):
                raise TypeError(f"data[{k}] must be a tensor or a group element, got {type(d).__name__}")
        self.data = tuple(data)
        self.dim = None if dim is None else checks.integer(dim, "dim", 1)
        if information is not None and sqrt_information is not None:
            raise ValueError("give information or sqrt_information, not both")
        for noise_name, noise in (("information", information), ("sqrt_information", sqrt_information)):
            if noise is not None:
                _noise(noise, noise_name, self.dim)
        self.information = information
        self.sqrt_information = sqrt_information
        if loss is not None and not isinstance(loss, RobustLoss):
            raise TypeError(f"loss must be a RobustLoss or None, got {type(loss).__name__}")
        self.loss = loss

    def __repr__(self) -> str:
        names = ", ".join(n for n, _ in self.slots)
        return f"{type(self).__name__}({names}; E={self.size}, dim={self.dim})"


def _between_residual(Ti, Tj, Z):
    """r = log(Z^-1 Ti^-1 Tj)."""
    return Z.inverse().compose(Ti.inverse()).compose(Tj).log()


def _between_jacobians(Ti, Tj, Z):
    """J_i = -J_r^-1(r) Ad(Tj^-1 Ti), J_j = J_r^-1(r) (right perturbations of Ti and Tj), with
    A = Ti^-1 Tj computed once: r = log(Z^-1 A), Ad(Tj^-1 Ti) = Ad(A^-1)."""
    A = Ti.inverse().compose(Tj)
    r = Z.inverse().compose(A).log()
    Jj = type(Ti).jr_inv(r)
    Ji = -Jj @ A.inverse().adjoint()
    return r, [Ji, Jj]


def _measured(measured) -> None:
    """A group element of batch (E,) or (B, E): the measurement of a ``Prior`` or ``Between``."""
    if not isinstance(measured, LieGroup):
        raise TypeError(f"measured must be a group element, got {type(measured).__name__}")
    if len(measured.batch_shape) not in (1, 2):
        raise ValueError(f"measured must be a group element of batch (E,) or (B, E), got batch "
                         f"{tuple(measured.batch_shape)}")


def _prior_residual(T, Z):
    """r = log(Z^-1 T)."""
    return Z.inverse().compose(T).log()


def _prior_jacobians(T, Z):
    r = _prior_residual(T, Z)
    return r, [type(T).jr_inv(r)]


class Prior(Factor):
    """Priors ``r = log(Z^-1 T_i)`` on elements ``index`` (E,) of the group variable ``variable``;
    ``measured`` a group element of batch (E,) or (B, E).  Jacobian J_r^-1(r) (analytic)."""

    def __init__(self, variable: str, index, measured: LieGroup, *,
                 information: torch.Tensor | None = None,
                 sqrt_information: torch.Tensor | None = None, loss: RobustLoss | None = None):
        _measured(measured)
        super().__init__(_prior_residual, [(variable, index)], data=[measured], dim=measured.dof,
                         information=information, sqrt_information=sqrt_information, loss=loss,
                         jacobians=_prior_jacobians)


class Between(Factor):
    """Relative measurements ``r = log(Z^-1 T_i^-1 T_j)`` between elements i and j (E,) of the
    group variable ``variable``; ``measured`` Z of batch (E,) or (B, E).  Analytic Jacobians
    J_i = -J_r^-1(r) Ad(T_j^-1 T_i), J_j = J_r^-1(r)."""

    def __init__(self, variable: str, i, j, measured: LieGroup, *,
                 information: torch.Tensor | None = None,
                 sqrt_information: torch.Tensor | None = None, loss: RobustLoss | None = None):
        _measured(measured)
        super().__init__(_between_residual, [(variable, i), (variable, j)], data=[measured],
                         dim=measured.dof, information=information,
                         sqrt_information=sqrt_information, loss=loss,
                         jacobians=_between_jacobians)


def _point_residual(T, p, z):
    """r = T p - z."""
    return T.act(p) - z


def _point_jacobians(T, p, z):
    """r = T p - z and [dr/dT (right perturbation), dr/dp] (``LieGroup.act_jacobians``)."""
    J_T, J_p = T.act_jacobians(p)
    return T.act(p) - z, [J_T, J_p]


class PointObservation(Factor):
    """A pose acting on a point vs a measured point: ``r = T_i p_j - z`` for the group variable
    ``pose`` (elements i) and the Euclidean variable ``point`` (elements j), ``measured`` z
    (E, point_dim) or (B, E, point_dim).  Analytic Jacobians (``LieGroup.act_jacobians``)."""

    def __init__(self, pose: str, i, point: str, j, measured: torch.Tensor, *,
                 information: torch.Tensor | None = None,
                 sqrt_information: torch.Tensor | None = None, loss: RobustLoss | None = None):
        measured = checks.floating(measured, "measured")
        if measured.dim() not in (2, 3):
            raise ValueError(f"measured must have shape (E, point_dim) or (B, E, point_dim), got "
                             f"{tuple(measured.shape)}")
        super().__init__(_point_residual, [(pose, i), (point, j)], data=[measured],
                         dim=measured.shape[-1], information=information,
                         sqrt_information=sqrt_information, loss=loss, jacobians=_point_jacobians)
