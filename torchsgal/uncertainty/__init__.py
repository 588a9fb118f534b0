"""Uncertainty on the groups: concentrated Gaussians, propagation, sampling and fusion."""
from .events import fuse_event, near_inertial_relative_frame
from .gaussian import ConcentratedGaussian, Gaussian, check_covariance

__all__ = ["ConcentratedGaussian", "Gaussian", "check_covariance", "fuse_event",
           "near_inertial_relative_frame"]
