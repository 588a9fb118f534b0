"""Uncertainty on the groups: concentrated Gaussians, propagation, sampling and fusion."""
from .gaussian import ConcentratedGaussian, Gaussian, check_covariance

__all__ = ["ConcentratedGaussian", "Gaussian", "check_covariance"]
