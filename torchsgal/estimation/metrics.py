"""Accuracy and consistency metrics of kelly-giamou (5.28)-(5.32)."""
from __future__ import annotations

import math

import torch

from ..functional import checks
from ..functional._blocking import values_readable

Z975 = 1.959963984540054  # standard normal 97.5% quantile



def chi2_quantile(p_z: float, dof: float) -> float:
    """Wilson-Hilferty approximation of the chi-square quantile for the normal quantile p_z;
    relative error below 1e-4 for dof >= 100 (checked against scipy in the tests).  ``p_z`` a
    number in [-40, 40], ``dof`` a finite number > 0; never below 0 (where the approximation
    falls below, at small dof and very negative p_z, it gives 0)."""
    checks.finite_number(p_z, "p_z", "in [-40, 40]")
    checks.finite_number(dof, "dof", "> 0")
    a = 2.0 / (9.0 * dof)
    return dof * max(0.0, 1.0 - a + p_z * math.sqrt(a)) ** 3


def anees_band(trials: int, dof: int) -> tuple[float, float]:
    """95% band of the ANEES of a consistent estimator: chi2_{trials dof} quantiles / trials;
    ``trials`` and ``dof`` integers >= 1."""
    k = checks.integer(trials, "trials", 1) * checks.integer(dof, "dof", 1)
    return chi2_quantile(-Z975, k) / trials, chi2_quantile(Z975, k) / trials


def expected_mmd(dof: int) -> float:
    """E[sqrt(chi2_dof)] = sqrt(2) Gamma((dof + 1)/2) / Gamma(dof/2) (3.24 for dof 11);
    ``dof`` a finite number > 0."""
    checks.finite_number(dof, "dof", "> 0")
    if dof > 3e3:  # sqrt(k) (1 - 1/(4k) + 1/(32 k^2)): within 2e-12 there, where the difference of
        # the lgammas loses more (1e-11 at 1e4, 1e-5 at 1e10) and then overflows
        return math.sqrt(dof) * (1.0 - 0.25 / dof + 1.0 / (32.0 * dof * dof))
    return math.sqrt(2.0) * math.exp(math.lgamma((dof + 1) / 2) - math.lgamma(dof / 2))


def nees(error: torch.Tensor, covariance: torch.Tensor) -> torch.Tensor:
    """(5.31): e^T P^-1 e per trial; error (K, d), covariance (K, d, d) (any broadcasting
    batch; one dtype and device).  NaN for a trial whose covariance is not positive definite
    (a solver reports those as SINGULAR, with a NaN covariance)."""
    checks.floating(error, "error")
    if error.dim() < 1:
        raise ValueError(f"error must have shape (..., d), got {tuple(error.shape)}")
    checks.matrix(covariance, error.shape[-1], "covariance")
    checks.binary(error, 1, covariance, 2, "error", "covariance")
    if covariance.numel() and values_readable(covariance):  # Cholesky reads one triangle only
        gap = (covariance - covariance.mT).abs()
        gap, size = (torch.where(torch.isfinite(gap), gap, 0).amax(),
                     torch.where(torch.isfinite(covariance), covariance.abs(), 0).amax())
        if bool(gap > 1e3 * torch.finfo(covariance.dtype).eps * size):
            raise ValueError(f"covariance is not symmetric: max |P - P^T| = {float(gap):.3g}")
    L, info = torch.linalg.cholesky_ex(covariance)
    y = torch.linalg.solve_triangular(L, error[..., None], upper=False)[..., 0]
    out = y.square().sum(-1)
    return torch.where(info == 0, out, torch.full_like(out, float("nan")))


def rmse(error: torch.Tensor) -> torch.Tensor:
    """(5.29) over the trials (dim 0) of error blocks (K, k): sqrt(mean |e_k|^2).  NaN for an
    empty batch (K = 0: no trial, no estimate of the error), as torch's mean of nothing."""
    checks.floating(error, "error")
    if error.dim() != 2:
        raise ValueError(f"error must have shape (K, k), got {tuple(error.shape)}")
    return error.square().sum(-1).mean().sqrt()
