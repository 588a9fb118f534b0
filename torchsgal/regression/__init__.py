"""Regression of time-stamped noisy samples on the groups (Aubray and Nicol, "Polynomial
regression on Lie groups and application to SE(3)"): one-parameter-subgroup and polynomial
curves, Riemannian geodesics and polynomials of a left-invariant metric (Euler-Arnold), the
inertial worldline on SGal(3), the Frechet mean and variance, R^2, and the simulated maneuvers of Algorithm 2."""
from .fit import (
                  CurveFit,
                  fit_inertial_worldline,
                  fit_polynomial,
                  fit_riemannian_geodesic,
                  fit_riemannian_polynomial,
                  fit_subgroup,
)
from .models import euler_arnold_rhs, geodesic_flow, levi_civita, polynomial_flow, polynomial_rhs
from .simulate import Maneuver, simulate_maneuver
from .solvers import gauss_newton, lbfgs
from .statistics import FrechetMean, frechet_mean, log_distance, r_squared

__all__ = ["CurveFit", "fit_polynomial", "fit_subgroup", "fit_riemannian_geodesic",
           "fit_riemannian_polynomial", "fit_inertial_worldline", "euler_arnold_rhs",
           "geodesic_flow", "levi_civita", "polynomial_flow", "polynomial_rhs", "Maneuver",
           "simulate_maneuver", "gauss_newton", "lbfgs", "FrechetMean", "frechet_mean",
           "log_distance", "r_squared"]
