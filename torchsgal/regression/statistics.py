"""Frechet mean and variance and the coefficient of determination R^2, (50)-(51) of
Aubray and Nicol, for the left-invariant log distance d(a, b)^2 = r^T diag(w) r,
r = log(a^-1 b)."""
from __future__ import annotations

from dataclasses import dataclass

import torch

from ..groups import LieGroup
from . import _checks
from .fit import fit_polynomial


def log_distance(a: LieGroup, b: LieGroup, weights=None) -> torch.Tensor:
    """d(a, b) = |log(a^-1 b)|_w, batch broadcast (...).  Left-invariant; equal to the
    Riemannian distance of diag(w) near the diagonal to second order only (and exactly for a
    bi-invariant metric, e.g. SO(3) with equal weights)."""
    r = a.between(b).log()
    w = _checks.metric_weights(weights, type(a), r)
    return (w * r * r).sum(-1).sqrt()


@dataclass
class FrechetMean:
    mean: LieGroup  # (...)
    variance: torch.Tensor  # (...): Var_F = (1/N) min_y sum_j d(y, y_j)^2
    converged: torch.Tensor  # (...) bool


def frechet_mean(samples: LieGroup, weights=None, max_iterations: int = 50,
                 tolerance: float | None = None) -> FrechetMean:
    """Frechet mean argmin_y sum_j d(y, y_j)^2 of samples with batch (..., N), by the same
    Gauss-Newton as the curve fits (it is the degree-0 polynomial), and the Frechet variance
    of (50): Var_F = (1/N) min_y sum_j d(y, y_j)^2."""
    _checks.group_samples(samples, "samples", 1)
    n = samples.batch_shape[-1]
    times = torch.arange(n, dtype=samples.dtype, device=samples.device)
    fit = fit_polynomial(samples, times, 0, weights=weights, max_iterations=max_iterations,
                         tolerance=tolerance)
    return FrechetMean(fit.origin, fit.cost / n, fit.converged)


def r_squared(samples: LieGroup, fitted: LieGroup, weights=None, mean: LieGroup | None = None
              ) -> torch.Tensor:
    """R^2 = 1 - sum_j d(gamma(t_j), y_j)^2 / min_y sum_j d(y, y_j)^2, (50); with the true
    samples in place of the noisy ones it is (51).  samples, fitted: batch (..., N);
    mean: the Frechet mean of samples (computed when not given)."""
    _checks.group_samples(samples, "samples", 1)
    if not isinstance(fitted, type(samples)):
        raise TypeError(f"fitted must be a {type(samples).__name__}, got {type(fitted).__name__}")
    if fitted.batch_shape[-1:] != samples.batch_shape[-1:]:
        raise ValueError(f"fitted must have one element per sample: batch (..., "
                         f"{samples.batch_shape[-1]}), got {tuple(fitted.batch_shape)}")
    sse = (log_distance(fitted, samples, weights) ** 2).sum(-1)
    if mean is None:
        mean = frechet_mean(samples, weights).mean
    sst = (log_distance(mean.unsqueeze(-1), samples, weights) ** 2).sum(-1)
    return 1.0 - sse / sst
