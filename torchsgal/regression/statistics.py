"""Frechet mean and variance and the coefficient of determination R^2, (50)-(51) of
Aubray and Nicol, for the left-invariant log distance d(a, b)^2 = r^T diag(w) r,
r = log(a^-1 b)."""
from __future__ import annotations

from dataclasses import dataclass

import torch

from ..functional import checks
from ..groups import LieGroup
from . import _checks
from .fit import _fit_polynomial, _options


def _group_pair(a, b, a_name: str, b_name: str) -> None:
    """a, b: elements of one group with one dtype and device and broadcastable batch shapes."""
    if not isinstance(a, LieGroup):
        raise TypeError(f"{a_name} must be a torchsgal group element (e.g. torchsgal.SE3), got "
                        f"{type(a).__name__}")
    if not isinstance(b, type(a)):
        raise TypeError(f"{b_name} must be a {type(a).__name__} like {a_name}, got {type(b).__name__}")
    checks.same_device_dtype(**{a_name: a.as_matrix(), b_name: b.as_matrix()})
    checks.broadcast_batch(**{a_name: a.batch_shape, b_name: b.batch_shape})


def _weights(weights, G, like: torch.Tensor, like_name: str) -> torch.Tensor:
    """Checked metric weights (values in one host sync, skipped where unreadable)."""
    w = _checks.metric_weights(weights, G, like, like_name)
    if weights is not None:
        _checks.read_values(_checks.weight_values(w))
    return w


def _squared_log_distance(a: LieGroup, b: LieGroup, w: torch.Tensor) -> torch.Tensor:
    r = a.between(b).log()
    return (w * r * r).sum(-1)


def log_distance(a: LieGroup, b: LieGroup, weights=None) -> torch.Tensor:
    """d(a, b) = |log(a^-1 b)|_w, batch broadcast (...).  Left-invariant; equal to the
    Riemannian distance of diag(w) near the diagonal to second order only (and exactly for a
    bi-invariant metric, e.g. SO(3) with equal weights).  Its gradient at a = b is zero (the
    subgradient convention of ``torch.linalg.norm``), not NaN.  weights (dof,) or (..., dof):
    positive and finite (a tensor of a's dtype and device, or numbers); their values are
    checked in one host sync, skipped on 'meta', under torch.func transforms and torch.compile."""
    _group_pair(a, b, "a", "b")
    w = _weights(weights, type(a), a.as_matrix(), "a")
    checks.broadcast_batch(a=a.batch_shape, b=b.batch_shape, weights=w.shape[:-1])
    sq = _squared_log_distance(a, b, w)
    # sqrt on a safe input: d sqrt(s)/ds is infinite at s = 0, and 0 * inf is NaN.
    positive = sq > 0
    safe = torch.where(positive, sq, torch.ones_like(sq))
    return torch.where(positive, safe.sqrt(), torch.zeros_like(sq))


@dataclass
class FrechetMean:
    mean: LieGroup  # (...)
    variance: torch.Tensor  # (...): Var_F = (1/N) min_y sum_j d(y, y_j)^2
    converged: torch.Tensor  # (...) bool


def frechet_mean(samples: LieGroup, weights=None, max_iterations: int = 50,
                 tolerance: float | None = None) -> FrechetMean:
    """Frechet mean argmin_y sum_j d(y, y_j)^2 of samples with batch (..., N), by the same
    Gauss-Newton as the curve fits (it is the degree-0 polynomial), and the Frechet variance
    of (50): Var_F = (1/N) min_y sum_j d(y, y_j)^2.  weights as in ``log_distance``."""
    _checks.group_samples(samples, "samples", 1)
    _options("gauss_newton", max_iterations, tolerance)
    w = _weights(weights, type(samples), samples.as_matrix(), "samples")
    checks.broadcast_batch(samples=samples.batch_shape[:-1], weights=w.shape[:-1])
    return _frechet_mean(samples, w, max_iterations, tolerance)


def _frechet_mean(samples: LieGroup, w: torch.Tensor, max_iterations, tolerance) -> FrechetMean:
    """frechet_mean with checked weights."""
    G, n = type(samples), samples.batch_shape[-1]
    batch = checks.broadcast_shapes(samples.batch_shape[:-1], w.shape[:-1])
    m = G.matrix_dim
    Y = samples.as_matrix().detach().expand(batch + (n, m, m))
    t = torch.arange(n, dtype=samples.dtype, device=samples.device).expand(batch + (n,))
    fit = _fit_polynomial(G, Y, t, torch.zeros(batch, dtype=Y.dtype, device=Y.device),
                          w.detach().expand(batch + (G.dof,)), 0, None, "gauss_newton",
                          max_iterations, tolerance)
    return FrechetMean(fit.origin, fit.cost / n, fit.converged)


def r_squared(samples: LieGroup, fitted: LieGroup, weights=None, mean: LieGroup | None = None
              ) -> torch.Tensor:
    """R^2 = 1 - sum_j d(gamma(t_j), y_j)^2 / min_y sum_j d(y, y_j)^2, (50); with the true
    samples in place of the noisy ones it is (51).  samples, fitted: batch (..., N);
    mean: the Frechet mean of samples (computed when not given), batch (...); weights (dof,)
    or (..., dof), per data set (each weighs all N samples of its data set), as in
    ``frechet_mean`` and the fits.

    Where the total variation min_y sum_j d(y, y_j)^2 is zero (all samples equal, e.g. N = 1)
    R^2 is undefined; as scikit-learn's ``r2_score(force_finite=True)`` it is then 1.0 if the
    fit is perfect (zero residual) and 0.0 otherwise, never NaN."""
    _checks.group_samples(samples, "samples", 1)
    if not isinstance(fitted, type(samples)):
        raise TypeError(f"fitted must be a {type(samples).__name__}, got {type(fitted).__name__}")
    if fitted.batch_shape[-1:] != samples.batch_shape[-1:]:
        raise ValueError(f"fitted must have one element per sample: batch (..., "
                         f"{samples.batch_shape[-1]}), got {tuple(fitted.batch_shape)}")
    _group_pair(samples, fitted, "samples", "fitted")
    if mean is not None:
        if not isinstance(mean, type(samples)):
            raise TypeError(f"mean must be a {type(samples).__name__}, got {type(mean).__name__}")
        checks.same_device_dtype(samples=samples.as_matrix(), mean=mean.as_matrix())
        checks.broadcast_batch(samples=samples.batch_shape[:-1], mean=mean.batch_shape)
    w = _weights(weights, type(samples), samples.as_matrix(), "samples")
    # weights (..., dof) are per data set (as in the fits): they weigh each of its N samples
    batches = {"samples": samples.batch_shape[:-1], "fitted": fitted.batch_shape[:-1],
               "weights": w.shape[:-1]}
    if mean is not None:
        batches["mean"] = mean.batch_shape
    checks.broadcast_batch(**batches)
    w_n = w.unsqueeze(-2)
    sse = _squared_log_distance(fitted, samples, w_n).sum(-1)
    if mean is None:
        mean = _frechet_mean(samples, w, 50, None).mean
    sst = _squared_log_distance(mean.unsqueeze(-1), samples, w_n).sum(-1)
    # No NaN where sst = 0: both branches on safe inputs, selected without a host sync.
    varies = sst > 0
    r2 = 1.0 - sse / torch.where(varies, sst, torch.ones_like(sst))
    degenerate = torch.where(sse == 0, torch.ones_like(sse), torch.zeros_like(sse))
    return torch.where(varies, r2, degenerate)
