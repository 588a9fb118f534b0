"""``FactorGraph``: named variables (group elements or Euclidean vectors, N elements each,
optionally for a batch of B independent problems) and factors (``factors.Factor``)."""
from __future__ import annotations

import copy

import torch

from ...functional import checks
from ...groups import LieGroup
from .factors import Between, Factor, PointObservation, Prior
from .gauss_helmert import GaussHelmert
from .robust import RobustLoss

__all__ = ["FactorGraph"]


class FactorGraph:
    """A nonlinear least-squares problem, or a batch of B independent ones of one structure.

    ``add_variable(name, value)``: a group element of batch (N,) or (B, N), or a tensor (N, k)
    or (B, N, k) (Euclidean, additive updates).  All batched variables share B; an unbatched
    variable is shared as the initial value of every problem.
    ``add(factor, loss=None)``: a ``Factor`` (``Prior``, ``Between``, ``PointObservation`` or
    a user ``Factor``); ``loss`` overrides the factor's robust loss.

    The graph holds references to the tensors given (it never modifies them); the solvers
    return new values.
    """

    def __init__(self) -> None:
        self.variables: dict[str, LieGroup | torch.Tensor] = {}
        self.factors: list[Factor] = []
        self._batch: int | None = None

    # ------------------------------------------------------------------ building
    def add_variable(self, name: str, value: LieGroup | torch.Tensor) -> None:
        """Adds the variable ``name`` with its initial value (see the class docstring)."""
        if not isinstance(name, str) or not name:
            raise TypeError(f"name must be a non-empty str, got {name!r}")
        if name in self.variables:
            raise ValueError(f"variable {name!r} is already in the graph")
        if isinstance(value, LieGroup):
            nd = len(value.batch_shape)
            if nd not in (1, 2):
                raise ValueError(f"variable {name!r}: a group element of batch (N,) or (B, N), "
                                 f"got batch {tuple(value.batch_shape)}")
            batch = value.batch_shape[0] if nd == 2 else None
            if value.batch_shape.numel() == 0:
                raise ValueError(f"variable {name!r}: a group element of batch (N,) or (B, N) with "
                                 f"B, N >= 1, got batch {tuple(value.batch_shape)}")
        elif isinstance(value, torch.Tensor):
            checks.floating(value, name)
            if value.dim() not in (2, 3):
                raise ValueError(f"variable {name!r}: a tensor (N, k) or (B, N, k), got shape "
                                 f"{tuple(value.shape)}")
            batch = value.shape[0] if value.dim() == 3 else None
            if value.numel() == 0:
                raise ValueError(f"variable {name!r}: a tensor (N, k) or (B, N, k) with B, N, k >= 1, "
                                 f"got shape {tuple(value.shape)}")
        else:
            raise TypeError(f"variable {name!r}: expected a group element or a tensor, got "
                            f"{type(value).__name__}")
        if batch is not None:
            if self._batch is not None and batch != self._batch:
                raise ValueError(f"variable {name!r}: batch of {batch} problems, but the graph's "
                                 f"other variables have {self._batch}")
            self._batch = batch
        first = next(iter(self.variables.values()), None)
        if first is not None:
            checks.same_device_dtype(**{"first variable": _leaf(first), name: _leaf(value)})
        self.variables[name] = value

    def add(self, factor: Factor, loss: RobustLoss | None = None) -> None:
        """Adds a ``Factor`` (its variables must already be in the graph, its data and noise of
        their dtype and device; a ``Prior`` or ``Between`` measured in its variable's group); ``loss`` (a
        ``RobustLoss``) replaces the factor's own."""
        if not isinstance(factor, Factor):
            raise TypeError(f"factor must be a Factor, got {type(factor).__name__}")
        if loss is not None:
            if not isinstance(loss, RobustLoss):
                raise TypeError(f"loss must be a RobustLoss or None, got {type(loss).__name__}")
            source, factor = factor, copy.copy(factor)  # the caller's factor keeps its own loss
            factor.loss = loss
            if isinstance(factor, GaussHelmert) and isinstance(source, GaussHelmert):
                factor.source = source  # gauss_helmert's corrections reach the caller's factor too
        for name, idx in factor.slots:
            if name not in self.variables:
                raise KeyError(f"factor {factor!r} reads variable {name!r}, which is not in the "
                               f"graph (add_variable first)")
            n = self.size(name)
            if idx.numel() and (int(idx.min()) < 0 or int(idx.max()) >= n):
                raise IndexError(f"factor {factor!r}: indices of {name!r} must be in [0, {n}), "
                                 f"got [{int(idx.min())}, {int(idx.max())}]")
        if isinstance(factor, (Prior, Between)):  # measured Z must be of the variable's group
            name = factor.slots[0][0]
            variable, measured = self.variables[name], factor.data[0]
            if not isinstance(variable, LieGroup) or variable._group is not measured._group:
                kind = type(variable).__name__ if isinstance(variable, LieGroup) else "a Euclidean tensor"
                raise TypeError(f"factor {factor!r}: measured is a {type(measured).__name__} but the "
                                f"variable {name!r} is {kind}")
        if isinstance(factor, PointObservation):  # a group pose acting on Euclidean points
            (pose, _), (point, _) = factor.slots
            T, p, z = self.variables[pose], self.variables[point], factor.data[0]
            if not isinstance(T, LieGroup):
                raise TypeError(f"factor {factor!r}: pose {pose!r} must be a group variable, got "
                                f"a Euclidean tensor")
            if isinstance(p, LieGroup):
                raise TypeError(f"factor {factor!r}: point {point!r} must be a Euclidean variable, "
                                f"got a {type(p).__name__}")
            if p.shape[-1] != T.point_dim or z.shape[-1] != T.point_dim:
                raise ValueError(f"factor {factor!r}: {type(T).__name__} acts on points of size "
                                 f"{T.point_dim}; point {point!r} has size {p.shape[-1]} and "
                                 f"measured {z.shape[-1]}")
        _check_kinds(self, factor)
        first = _leaf(next(iter(self.variables.values())))
        for k, d in enumerate(factor.data):
            checks.same_device_dtype(**{"the graph's first variable": first,
                                        f"factor {factor!r} data[{k}]": _leaf(d)})
        for noise_name in ("information", "sqrt_information"):
            noise = getattr(factor, noise_name, None)
            if isinstance(noise, torch.Tensor):
                checks.same_device_dtype(**{"the graph's first variable": first,
                                            f"factor {factor!r} {noise_name}": noise})
        self.factors.append(factor)

    # ------------------------------------------------------------------ queries
    @property
    def batch_size(self) -> int | None:
        """B, or None for one unbatched problem."""
        return self._batch

    def size(self, name: str) -> int:
        """N, the number of elements of the variable ``name``."""
        v = self._variable(name)
        return v.batch_shape[-1] if isinstance(v, LieGroup) else v.shape[-2]

    def dof(self, name: str) -> int:
        """The tangent size of one element of the variable ``name``."""
        v = self._variable(name)
        return v.dof if isinstance(v, LieGroup) else v.shape[-1]

    def _variable(self, name: str) -> LieGroup | torch.Tensor:
        if name not in self.variables:
            raise KeyError(f"no variable {name!r} in the graph; its variables are "
                           f"{list(self.variables)}")
        return self.variables[name]

    def __repr__(self) -> str:
        vs = ", ".join(f"{n}: {type(v).__name__ if isinstance(v, LieGroup) else 'R^' + str(v.shape[-1])}"
                       f" x {self.size(n)}" for n, v in self.variables.items())
        return (f"FactorGraph(B={self._batch}, variables [{vs}], "
                f"{sum(f.size for f in self.factors)} factors in {len(self.factors)} blocks)")


def _leaf(value) -> torch.Tensor:
    return value.as_matrix() if isinstance(value, LieGroup) else value


def _check_kinds(graph: FactorGraph, factor: Factor) -> None:
    """The variables a factor reads against its ``variable_kinds`` (group classes, Euclidean
    sizes or None per argument)."""
    if factor.variable_kinds is None:
        return
    for (name, _), kind in zip(factor.slots, factor.variable_kinds):
        value = graph.variables[name]
        if kind is None:
            continue
        if isinstance(kind, int):
            if isinstance(value, LieGroup) or value.shape[-1] != kind:
                got = type(value).__name__ if isinstance(value, LieGroup) else f"size {value.shape[-1]}"
                raise TypeError(f"factor {factor!r}: variable {name!r} must be a Euclidean variable of "
                                f"size {kind}, got {got}")
            continue
        classes = kind if isinstance(kind, tuple) else (kind,)
        if not isinstance(value, classes):
            got = type(value).__name__ if isinstance(value, LieGroup) else "a Euclidean tensor"
            raise TypeError(f"factor {factor!r}: variable {name!r} must be "
                            f"{' or '.join(c.__name__ for c in classes)}, got {got}")
