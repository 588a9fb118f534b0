"""Input validation for the regression package: every error names the argument.

Shape, dtype and device checks read metadata only.  The time checks (strictly increasing
stamps) read values once, at the entry of a fit, never inside the solver loop.
"""
from __future__ import annotations

import torch

from ..functional import checks
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
    """Stamps (..., N) broadcasting with samples.batch_shape, strictly increasing along the last
    dimension (reads values: one host sync at the entry of a fit)."""
    if not isinstance(times, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor of shape (..., N), got {type(times).__name__}")
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
        torch.broadcast_shapes(times.shape[:-1], samples.batch_shape[:-1])
    except RuntimeError:
        raise ValueError(f"batch shapes do not broadcast: {name} {tuple(times.shape[:-1])}, "
                         f"samples {tuple(samples.batch_shape[:-1])}") from None
    if n > 1:
        gaps = torch.diff(times, dim=-1)
        if not bool(torch.isfinite(times).all()):
            raise ValueError(f"{name} must be finite")
        if bool((gaps == 0).any()):
            raise ValueError(f"{name} must be strictly increasing along the last dimension: "
                             f"duplicate time stamps found")
        if bool((gaps < 0).any()):
            raise ValueError(f"{name} must be sorted (strictly increasing) along the last "
                             f"dimension: found a decreasing pair")
    return times


def metric_weights(weights, G, like: torch.Tensor, name: str = "weights") -> torch.Tensor:
    """Positive weights per tangent component, shape (dof,) or (..., dof); default ones."""
    if weights is None:
        return torch.ones(G.dof, dtype=like.dtype, device=like.device)
    if not isinstance(weights, torch.Tensor):
        weights = torch.as_tensor(weights, dtype=like.dtype, device=like.device)
    if weights.dtype not in SUPPORTED_DTYPES:
        raise TypeError(f"{name} must have a floating dtype (torch.float32 or torch.float64), got {weights.dtype}")
    if weights.dim() < 1 or weights.shape[-1] != G.dof:
        raise ValueError(f"{name} must have shape (..., {G.dof}) for {G.__name__}, got "
                         f"{tuple(weights.shape)}")
    if weights.device != like.device:
        raise ValueError(f"{name} is on {weights.device} but samples are on {like.device}")
    if not bool((weights > 0).all()):
        raise ValueError(f"{name} must be positive")
    return weights.to(like.dtype)


def degree(value, n_samples: int, name: str = "degree") -> int:
    """A polynomial degree >= 0 that the N samples can determine (N >= degree + 1)."""
    checks.integer(value, name, 0)
    if n_samples < value + 1:
        raise ValueError(
            f"too few samples for {name} {value}: a polynomial of degree {value} needs at least "
            f"{value + 1} samples, got N = {n_samples}"
        )
    return int(value)
