"""Shared helpers of the converters: lazy peer imports and tangent-order maps.

A tangent map is a permutation ``perm`` with ``xi_peer = xi_ours[..., perm]``: as a matrix
``M = I[perm]``, so covariances map as ``P' = M P M^T`` and Jacobians as ``J' = M_out J M_in^-1``
(``M^-1 = M^T``).  Gathering the entries is exact and batched.
"""
from __future__ import annotations

import importlib
from collections.abc import Sequence
from types import ModuleType

import torch

from ..functional import checks


def require(module: str, user: str) -> ModuleType:
    """Imports the peer ``module`` (only when a converter runs), or raises ImportError naming
    the extra that installs it."""
    try:
        return importlib.import_module(module)
    except ImportError as err:
        raise ImportError(f"{user} needs the optional dependency {module!r}: install it with "
                          f"pip install 'torchsgal[peers]' (or pip install {module})") from err


def permutation_matrix(perm: Sequence[int], dtype: torch.dtype | None = None,
                       device: torch.device | str | None = None) -> torch.Tensor:
    """``M = I[perm]`` (d, d): ``M @ xi = xi[perm]``."""
    dtype = checks.dtype_arg(dtype or torch.get_default_dtype())
    eye = torch.eye(len(perm), dtype=dtype, device=device)
    return eye[list(perm)]


def inverse_permutation(perm: Sequence[int]) -> tuple[int, ...]:
    """``inv`` with ``x[perm][inv] = x``."""
    inv = [0] * len(perm)
    for i, p in enumerate(perm):
        inv[p] = i
    return tuple(inv)


def _index(perm: Sequence[int], like: torch.Tensor) -> torch.Tensor:
    return torch.tensor(list(perm), dtype=torch.long, device=like.device)


def permute_vector(x: torch.Tensor, perm: Sequence[int], name: str) -> torch.Tensor:
    """``x[..., perm]`` for x (..., d), d = len(perm)."""
    checks.vector(x, len(perm), name)
    return x.index_select(-1, _index(perm, x))


def permute_square(A: torch.Tensor, perm: Sequence[int], name: str) -> torch.Tensor:
    """``A[..., perm, :][..., :, perm]`` for A (..., d, d): ``M A M^T``."""
    checks.matrix(A, len(perm), name)
    idx = _index(perm, A)
    return A.index_select(-2, idx).index_select(-1, idx)


def permute_jacobian(J: torch.Tensor, out_perm: Sequence[int] | None, in_perm: Sequence[int] | None,
                     name: str) -> torch.Tensor:
    """``M_out J M_in^T`` for J (..., m, n): rows permuted by ``out_perm``, columns by
    ``in_perm`` (None: a Euclidean side, left as it is)."""
    checks.floating(J, name)
    m = J.shape[-2] if J.dim() >= 2 else None
    n = J.shape[-1] if J.dim() >= 2 else None
    rows = "m" if out_perm is None else str(len(out_perm))
    cols = "n" if in_perm is None else str(len(in_perm))
    if (J.dim() < 2 or (out_perm is not None and m != len(out_perm))
            or (in_perm is not None and n != len(in_perm))):
        raise ValueError(f"{name} must have shape (..., {rows}, {cols}), got {tuple(J.shape)}")
    if out_perm is not None:
        J = J.index_select(-2, _index(out_perm, J))
    if in_perm is not None:
        J = J.index_select(-1, _index(in_perm, J))
    return J


def nested_shape(objects, is_leaf, name: str, what: str) -> tuple[list, tuple[int, ...]]:
    """A leaf or (nested) lists/tuples of leaves of one rectangular shape: the leaves in
    row-major order and that shape (() for one leaf); ``what`` names the leaves accepted."""
    if is_leaf(objects):
        return [objects], ()
    if not isinstance(objects, (list, tuple)):
        raise TypeError(f"{name} must be {what} or a (nested) list of them, "
                        f"got {type(objects).__name__}")
    if not objects:
        return [], (0,)
    if all(is_leaf(o) for o in objects):  # one level: the common case, no recursion
        return list(objects), (len(objects),)
    parts = [nested_shape(o, is_leaf, f"{name}[{i}]", what) for i, o in enumerate(objects)]
    inner = parts[0][1]
    for i, (_, s) in enumerate(parts):
        if s != inner:
            raise ValueError(f"{name} must be rectangular: {name}[0] has shape {inner}, "
                             f"{name}[{i}] has shape {s}")
    return [leaf for leaves, _ in parts for leaf in leaves], (len(objects),) + inner


def nest(flat: list, shape: tuple[int, ...]):
    """The inverse of ``nested_shape``: one item for shape (), else nested lists."""
    if not shape:
        return flat[0]
    if len(shape) == 1:
        return list(flat)
    step = len(flat) // shape[0] if shape[0] else 0
    return [nest(flat[i * step:(i + 1) * step], shape[1:]) for i in range(shape[0])]
