"""Unknowns of a batched least-squares problem: a tuple of blocks, or one block alone.

A block is a group element (a ``LieGroup``) of batch shape (B,) (one variable per problem) or
(B, K) (K variables of that group per problem, e.g. the poses of a pose graph), or a
Euclidean tensor (B, k) or (B, K, k).  The solvers work on the tuple; unknowns given as one
block alone reach the user's functions (residual, Jacobian, condition, cost) and come back in
the solution alone, unwrapped (``is_single``, ``unwrapped``).

The tangent vector of the tuple is the concatenation of the blocks' tangents, in order; a
(B, K) block contributes K * dof coordinates ordered variable-major (variable 0's dof, then
variable 1's, ...), so a (B, K) block has the same tangent, covariance layout and solution as
the tuple of its K (B,) blocks.  Group blocks move by right perturbation,
``g.rplus(d) = g exp(d)`` (CONVENTIONS.md), each variable of a (B, K) block by its own
tangent; Euclidean blocks by addition.
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from typing import overload

import torch

from ..functional import checks
from ..functional.checks import SUPPORTED_DTYPES
from ..groups import LieGroup

Block = LieGroup | torch.Tensor
Values = tuple  # the blocks, in order
Unknowns = Block | Values  # one block alone, or a tuple of blocks (returned in the form given)


def is_single(x) -> bool:
    """True for unknowns given as one block alone (a group element or a tensor), not in a tuple."""
    return isinstance(x, (LieGroup, torch.Tensor))


def unwrapped(f, single: bool):
    """``f`` called with the one block itself instead of the 1-tuple when ``single`` (further
    arguments passed on)."""
    if not checks.boolean(single, "single") or f is None:
        return f
    return lambda x, *args: f(x[0], *args)


def as_values(x, name: str = "x") -> Values:
    """Normalises a single block or a sequence of blocks to a tuple."""
    if isinstance(x, (LieGroup, torch.Tensor)):
        return (x,)
    if isinstance(x, (str, bytes)) or not isinstance(x, Iterable):
        raise TypeError(f"{name} must be a group element, a tensor or a tuple of them, got "
                        f"{type(x).__name__}")
    return tuple(x)


def block_dims(x: Unknowns) -> list[int]:
    """The tangent size of each block: dof (group, batch (B,)), K dof (group, batch (B, K)),
    k or K k (tensor (B, k) or (B, K, k))."""
    x = as_values(x)
    return [b.dof * math.prod(b.batch_shape[1:]) if isinstance(b, LieGroup)
            else math.prod(b.shape[1:]) for b in x]


def tangent_dim(x: Unknowns) -> int:
    return sum(block_dims(x))


def batch_size(x: Unknowns) -> int:
    x = as_values(x)
    if not x:
        raise ValueError("x must hold at least one block, got none")
    return x[0].batch_shape[0] if isinstance(x[0], LieGroup) else x[0].shape[0]


def _block_name(name: str, i: int, single: bool) -> str:
    """``x0`` for unknowns given as one block alone, ``x0[i]`` for the blocks of a tuple."""
    return name if single else f"{name}[{i}]"


def check_values(x: Block | Sequence[Block], name: str = "x0") -> Values:
    """Checks that every block has the same batch size B (a group element of batch shape (B,)
    or (B, K), a tensor (B, k) or (B, K, k)), dtype and device; errors name ``name`` for a
    block given alone and ``name[i]`` for the blocks of a tuple."""
    single = is_single(x)
    x = as_values(x, name)
    if not x:
        raise ValueError(f"{name} must hold at least one block, got none")
    shapes, dtypes, devices = [], set(), set()
    for i, b in enumerate(x):
        bname = _block_name(name, i, single)
        if isinstance(b, LieGroup):
            shapes.append(tuple(b.batch_shape))
            if len(b.batch_shape) not in (1, 2):
                raise ValueError(f"{bname} ({type(b).__name__}) must have batch shape (B,) (one "
                                 f"variable per problem) or (B, K) (K variables per problem), "
                                 f"got {tuple(b.batch_shape)}")
        elif isinstance(b, torch.Tensor):
            if b.dim() not in (2, 3):
                raise ValueError(f"{bname} must be a tensor of shape (B, k) or (B, K, k) (K "
                                 f"variables per problem), got {tuple(b.shape)}")
            if b.dtype not in SUPPORTED_DTYPES:
                raise TypeError(f"{bname} must be floating point (torch.float32 or torch.float64), got {b.dtype}")
            shapes.append(tuple(b.shape[:-1]))
        else:
            raise TypeError(f"{bname} must be a LieGroup or a tensor, got {type(b).__name__}")
        dtypes.add(b.dtype)
        devices.add(b.device)
    if len({s[0] for s in shapes}) != 1:
        raise ValueError(f"the blocks of {name} must share the batch size B, got {shapes}")
    if len(dtypes) != 1 or len(devices) != 1:
        raise ValueError(f"the blocks of {name} must share dtype and device, got "
                         f"{sorted(map(str, dtypes))} on {sorted(map(str, devices))}")
    return x


def _same_blocks(x: Values, y: Values, x_name: str, y_name: str) -> None:
    """The same number of blocks, of the same kinds (metadata only: cheap in solver loops)."""
    if len(x) != len(y):
        raise ValueError(f"{x_name} and {y_name} must have the same number of blocks, got "
                         f"{len(x)} and {len(y)}")
    for i, (a, b) in enumerate(zip(x, y)):
        if isinstance(a, LieGroup) != isinstance(b, LieGroup) or \
                (isinstance(a, LieGroup) and type(a) is not type(b)):
            raise TypeError(f"{y_name}[{i}] must be of the kind of {x_name}[{i}] "
                            f"({type(a).__name__}), got {type(b).__name__}")


@overload
def retract(x: Values, delta: torch.Tensor) -> Values: ...
@overload
def retract(x: Block, delta: torch.Tensor) -> Block: ...
def retract(x: Unknowns, delta: torch.Tensor) -> Unknowns:
    """x boxplus delta: group blocks g exp(d), Euclidean blocks x + d; delta (B, dim).  Like
    every helper here, it takes one block alone or a tuple, and returns the same form."""
    single, x = is_single(x), as_values(x)
    dims = block_dims(x)
    if not isinstance(delta, torch.Tensor) or delta.dim() < 1 or delta.shape[-1] != sum(dims):
        got = tuple(delta.shape) if isinstance(delta, torch.Tensor) else type(delta).__name__
        raise ValueError(f"delta must have shape (B, {sum(dims)}) (the tangent dimension of x, "
                         f"blocks {dims}), got {got}")
    out: list[Block] = []
    i = 0
    for b, k in zip(x, dims):
        d = delta[..., i:i + k]
        if isinstance(b, LieGroup):
            if len(b.batch_shape) == 2:  # (B, K): variable-major, one tangent per variable
                d = d.unflatten(-1, (b.batch_shape[1], b.dof))
            out.append(b.rplus(d))
        else:
            out.append(b + (d.unflatten(-1, tuple(b.shape[1:])) if b.dim() == 3 else d))
        i += k
    return out[0] if single else tuple(out)


def local(x: Unknowns, y: Unknowns) -> torch.Tensor:
    """y boxminus x: the tangent d with retract(x, d) = y (group blocks log(x^-1 y))."""
    x, y = as_values(x), as_values(y)
    _same_blocks(x, y, "x", "y")
    parts = []
    for xb, yb in zip(x, y):
        if isinstance(xb, LieGroup):
            part = yb.rminus(xb)
            parts.append(part.flatten(-2) if len(xb.batch_shape) == 2 else part)
        else:
            parts.append((yb - xb).flatten(-2) if xb.dim() == 3 else yb - xb)
    return torch.cat(parts, dim=-1)


@overload
def select(mask: torch.Tensor, new: Values, old: Values) -> Values: ...
@overload
def select(mask: torch.Tensor, new: Block, old: Block) -> Block: ...
def select(mask: torch.Tensor, new: Unknowns, old: Unknowns) -> Unknowns:
    """Blockwise torch.where over the batch: new where mask (B,) else old."""
    single, new, old = is_single(new), as_values(new), as_values(old)
    _same_blocks(new, old, "new", "old")
    B = batch_size(new)
    if not isinstance(mask, torch.Tensor) or mask.dtype != torch.bool or mask.shape != (B,):
        got = (f"{mask.dtype} {tuple(mask.shape)}" if isinstance(mask, torch.Tensor)
               else type(mask).__name__)
        raise ValueError(f"mask must be a bool tensor of shape (B,) = ({B},), got {got}")
    out: list[Block] = []
    for a, b in zip(new, old):
        if isinstance(a, LieGroup):
            A = a.as_matrix()
            m = mask.reshape((B,) + (1,) * (A.dim() - 1))
            out.append(type(a).from_matrix(torch.where(m, A, b.as_matrix())))
        else:
            out.append(torch.where(mask.reshape((B,) + (1,) * (a.dim() - 1)), a, b))
    return out[0] if single else tuple(out)


@overload
def detach(x: Values) -> Values: ...
@overload
def detach(x: Block) -> Block: ...
def detach(x: Unknowns) -> Unknowns:
    if isinstance(x, (LieGroup, torch.Tensor)):  # is_single
        return x.detach()
    return tuple(b.detach() for b in x)


def finite(x: Unknowns) -> torch.Tensor:
    """(B,) True where every entry of every block is finite."""
    x = as_values(x)
    ok = None
    for b in x:
        t = (b.as_matrix() if isinstance(b, LieGroup) else b).flatten(1)
        f = torch.isfinite(t).all(dim=-1)
        ok = f if ok is None else ok & f
    if ok is None:
        raise ValueError("x must hold at least one block, got none")
    return ok
