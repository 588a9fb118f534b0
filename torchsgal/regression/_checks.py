"""Input validation for the regression package: every error names the argument.

Shape, dtype and device checks read metadata only.  The value checks (strictly increasing,
finite stamps; finite time origin; positive, finite weights) are collected by the entry of a
fit and read in one host sync (``read_values``), never inside the solver loop; as everywhere
in the library they are skipped where values cannot be read (on 'meta', inside a torch.func
transform, while torch.compile traces).
"""
from __future__ import annotations

import numbers

import torch

from ..functional import checks
from ..functional._blocking import values_readable
from ..functional.checks import SUPPORTED_DTYPES
from ..groups import LieGroup


def group_samples(samples, name: str = "samples", min_samples: int = 1) -> LieGroup:
    """A group element with batch shape (..., N), N >= min_samples."""
    if not isinstance(samples, LieGroup):
        raise TypeError(
            f"{name} must be a torchsgal group element (e.g. torchsgal.SE3) with batch shape "
            f"(..., N), got {type(samples).__name__}"
        )
    if len(samples.batch_shape) < 1:
        raise ValueError(f"{name} must have batch shape (..., N) with N samples, got an unbatched "
                         f"{type(samples).__name__}")
    n = samples.batch_shape[-1]
    if n < min_samples:
        raise ValueError(f"{name} must hold at least {min_samples} samples along its last batch "
                         f"dimension, got N = {n}")
    return samples


def sample_times(times, samples: LieGroup, name: str = "times") -> torch.Tensor:
    """Stamps (..., N) broadcasting with samples.batch_shape (metadata; their values are
    checked by ``time_values``)."""
    if not isinstance(times, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor of shape (..., N), got {type(times).__name__}")
    checks.dense(times, name)
    if times.dtype not in SUPPORTED_DTYPES:
        raise TypeError(f"{name} must have a floating dtype (torch.float32 or torch.float64), got {times.dtype}")
    if times.dtype != samples.dtype:
        raise TypeError(f"{name} has dtype {times.dtype} but samples have dtype {samples.dtype}")
    if times.device != samples.device:
        raise ValueError(f"{name} is on {times.device} but samples are on {samples.device}")
    n = samples.batch_shape[-1]
    if times.dim() < 1 or times.shape[-1] != n:
        raise ValueError(f"{name} must have shape (..., {n}) (one stamp per sample), got "
                         f"{tuple(times.shape)}")
    try:
        checks.broadcast_shapes(times.shape[:-1], samples.batch_shape[:-1])
    except RuntimeError:
        raise ValueError(f"batch shapes do not broadcast: {name} {tuple(times.shape[:-1])}, "
                         f"samples {tuple(samples.batch_shape[:-1])}") from None
    return times


def time_values(times: torch.Tensor, name: str = "times") -> list:
    """The value checks of the stamps, for ``read_values``: finite, then strictly increasing."""
    found = [(~torch.isfinite(times).all(), f"{name} must be finite")]
    if times.shape[-1] > 1:
        gaps = torch.diff(times, dim=-1)
        found += [((gaps == 0).any(), f"{name} must be strictly increasing along the last "
                                      f"dimension: duplicate time stamps found"),
                  ((gaps < 0).any(), f"{name} must be sorted (strictly increasing) along the last "
                                     f"dimension: found a decreasing pair")]
    return found


def time_origin(value, like: torch.Tensor, like_name: str = "samples", name: str = "time_origin"):
    """None (a per-data-set origin, chosen by the fit), a finite real number, or a floating
    tensor (...) of the samples' dtype and device (its finiteness is checked by
    ``read_values``).  Returns None or a tensor."""
    if value is None:
        return None
    if isinstance(value, torch.Tensor):
        checks.floating(value, name)
        checks.same_device_dtype(**{like_name: like, name: value})
        return value
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name} must be None, a finite number or a torch.Tensor, got {value!r}")
    value = checks.finite_number(value, name)
    return torch.tensor(value, dtype=like.dtype, device=like.device)


def metric_weights(weights, G, like: torch.Tensor, like_name: str = "samples",
                   name: str = "weights") -> torch.Tensor:
    """Weights per tangent component, shape (dof,) or (..., dof); default ones.  A tensor must
    have ``like``'s dtype and device; numbers and sequences are converted to them.  Metadata
    only: their values (positive, finite) are checked by ``weight_values``."""
    if weights is None:
        return torch.ones(G.dof, dtype=like.dtype, device=like.device)
    weights = checks.numbers_as_tensor(weights, name, like.dtype, like.device)
    checks.floating(weights, name)
    if weights.dim() < 1 or weights.shape[-1] != G.dof:
        raise ValueError(f"{name} must have shape (..., {G.dof}) for {G.__name__}, got "
                         f"{tuple(weights.shape)}")
    checks.same_device_dtype(**{like_name: like, name: weights})
    return weights


def weight_values(weights: torch.Tensor, name: str = "weights") -> list:
    """The value checks of metric weights, for ``read_values``."""
    return [(~torch.isfinite(weights).all(), f"{name} must be finite"),
            (~(weights > 0).all(), f"{name} must be positive")]


def finite_values(value, name: str) -> list:
    """``value`` (a tensor or None) must be finite, for ``read_values``."""
    if value is None:
        return []
    return [(~torch.isfinite(value).all(), f"{name} must be finite")]


def read_values(found: list) -> None:
    """Raises ValueError with the message of the first failed check of ``found``, a list of
    (0-d bool tensor, true where the check fails; message).  All are read in one host sync,
    and none where a value cannot be read (meta, a torch.func transform, torch.compile)."""
    if not found or not all(values_readable(bad) for bad, _ in found):
        return
    for failed, (_, message) in zip(torch.stack([bad for bad, _ in found]).tolist(), found):
        if failed:
            raise ValueError(message)


def degree(value, n_samples: int, name: str = "degree") -> int:
    """A polynomial degree >= 0 that the N samples can determine (N >= degree + 1)."""
    checks.integer(value, name, 0)
    if n_samples < value + 1:
        raise ValueError(
            f"too few samples for {name} {value}: a polynomial of degree {value} needs at least "
            f"{value + 1} samples, got N = {n_samples}"
        )
    return int(value)
