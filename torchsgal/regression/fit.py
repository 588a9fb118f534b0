"""Regression of time-stamped group samples: polynomial (one-parameter subgroup) curves,
Riemannian geodesics and polynomials of a left-invariant metric, and the inertial worldline
on SGal(3).

Equation numbers refer to Aubray and Nicol, "Polynomial regression on Lie groups and
application to SE(3)" (aubray-nicol-polynomial-regression-se3.txt).  Every fit minimises
(32) with d(gamma, y)^2 = r^T diag(w) r, r = log(gamma^-1 y) (see ``models.py``), over a
batch of independent data sets (leading batch dimensions); the samples are not
differentiated through (fits run under ``torch.no_grad``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..functional import checks
from ..functional.checks import SUPPORTED_DTYPES
from ..groups import LieGroup, SGal3
from . import _checks
from .models import PolynomialModel, RiemannianPolynomialModel
from .solvers import gauss_newton, lbfgs

METHODS = ("gauss_newton", "lbfgs")


@dataclass
class CurveFit:
    """A fitted curve on ``group`` for a batch of data sets.

    origin: gamma(time_origin) (batch (...)); coefficients: the algebra coefficients v_k
    (..., K, dof) of the polynomial model, or the initial body coordinates
    (v_1, ..., v_K)(t0) (..., K, dof) of a Riemannian polynomial (v_1 = X0 for a geodesic);
    cost: sum_i d(gamma(t_i), y_i)^2 (...); converged: (...) bool.
    Call ``fit(times)`` for gamma at times (..., M)."""

    group: type
    model: str
    origin: LieGroup
    coefficients: torch.Tensor
    time_origin: torch.Tensor
    cost: torch.Tensor
    converged: torch.Tensor
    iterations: int
    method: str
    _model: object
    _x: torch.Tensor

    def __call__(self, times: torch.Tensor) -> LieGroup:
        """gamma at times (..., M), the leading dimensions broadcasting with the fit's batch."""
        if isinstance(times, torch.Tensor) and times.device != self.origin.device:
            raise ValueError(f"times is on {times.device} but the fit is on "
                             f"{self.origin.device}; move them to one device")
        times = torch.as_tensor(times, dtype=self.origin.dtype, device=self.origin.device)
        if times.dim() < 1:
            raise ValueError(f"times must have shape (..., M), got {tuple(times.shape)}")
        try:
            torch.broadcast_shapes(times.shape[:-1], self.time_origin.shape)
        except RuntimeError:
            raise ValueError(f"times must have shape (..., M) with (...) broadcasting with the "
                             f"fit's batch shape {tuple(self.time_origin.shape)}, got "
                             f"{tuple(times.shape)}") from None
        tau = times - self.time_origin.unsqueeze(-1)
        with torch.no_grad():
            return self.group.from_matrix(self._model.curve(self.origin.as_matrix(), self._x, tau))

    def residuals(self) -> torch.Tensor:
        """Unweighted r_i = log(gamma(t_i)^-1 y_i) at the fitted parameters, (..., N, dof)."""
        with torch.no_grad():
            r = self._model.residuals(self.origin.as_matrix(), self._x)
        r = r.reshape(r.shape[:-1] + (-1, self.group.dof))
        return r / self._model.sqrt_w.unsqueeze(-2)


def _prepare(samples, times, weights, time_origin, min_samples):
    _checks.group_samples(samples, "samples", min_samples)
    G = type(samples)
    _checks.sample_times(times, samples)
    batch = torch.broadcast_shapes(samples.batch_shape[:-1], times.shape[:-1])
    n = samples.batch_shape[-1]
    w = _checks.metric_weights(weights, G, samples.as_matrix())
    try:
        batch = torch.broadcast_shapes(batch, w.shape[:-1])
    except RuntimeError:
        raise ValueError(f"batch shapes do not broadcast: weights {tuple(w.shape[:-1])}, "
                         f"samples/times {tuple(batch)}") from None
    t0 = torch.as_tensor(time_origin, dtype=samples.dtype, device=samples.device)
    try:
        batch = torch.broadcast_shapes(batch, t0.shape)
    except RuntimeError:
        raise ValueError(f"time_origin must broadcast with the batch {tuple(batch)}, got shape "
                         f"{tuple(t0.shape)}") from None
    m = G.matrix_dim
    Y = samples.as_matrix().detach().expand(batch + (n, m, m))
    t = times.detach().expand(batch + (n,))
    t0 = t0.expand(batch)
    w = w.expand(batch + (G.dof,))
    return G, Y, t, t0, w


def _initial_subgroup(G, Y, t, t0):
    """p, v from consecutive samples: v = mean_i log(y_i^-1 y_(i+1)) / (t_(i+1) - t_i),
    p = y_0 exp(-(t_0 - t0) v) (robust to a total rotation beyond pi)."""
    Yg = G.from_matrix(Y)
    if Y.shape[-3] < 2:
        return Y[..., 0, :, :], torch.zeros(Y.shape[:-3] + (G.dof,), dtype=Y.dtype, device=Y.device)
    steps = Yg[..., :-1].between(Yg[..., 1:]).log() / torch.diff(t, dim=-1).unsqueeze(-1)
    v = steps.mean(dim=-2)
    p = Y[..., 0, :, :] @ G.exp(-(t[..., 0] - t0).unsqueeze(-1) * v).as_matrix()
    return p, v


def _options(method, max_iterations, tolerance) -> None:
    """Validates the solver options at the entry of a fit, before any work."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if max_iterations is not None:
        checks.integer(max_iterations, "max_iterations", 0)
    if tolerance is not None:
        checks.finite_number(tolerance, "tolerance", ">= 0")


def _solve(model, origin, x, method, max_iterations, tolerance):
    _options(method, max_iterations, tolerance)
    if tolerance is None:  # relative step length; float32 resolves ~1e-6 at best
        tolerance = 1e-10 if x.dtype == torch.float64 else 1e-5
    if max_iterations is None:
        max_iterations = 50 if method == "gauss_newton" else 500
    if method == "gauss_newton":
        return gauss_newton(model, origin, x, max_iterations, tolerance)
    return lbfgs(model, origin, x, max_iterations, tolerance)


def _basis(basis, G, like):
    if basis is None:
        return None
    if not isinstance(basis, torch.Tensor) or basis.dtype not in SUPPORTED_DTYPES:
        raise TypeError("basis must be a float32 or float64 torch.Tensor of shape (dof, m)")
    if basis.dim() != 2 or basis.shape[0] != G.dof or not 1 <= basis.shape[1] <= G.dof:
        raise ValueError(f"basis must have shape ({G.dof}, m) with 1 <= m <= {G.dof}, got "
                         f"{tuple(basis.shape)}")
    return basis.to(dtype=like.dtype, device=like.device)


def fit_polynomial(samples: LieGroup, times: torch.Tensor, degree: int = 1, *, weights=None,
                   time_origin=0.0, basis: torch.Tensor | None = None,
                   method: str = "gauss_newton", max_iterations: int | None = None,
                   tolerance: float | None = None) -> CurveFit:
    """Fits gamma(t) = p exp(sum_{k=1..degree} (t - t0)^k B v_k) to samples y_i at times t_i.

    samples: a group element (SE3, SE23, SGal3, ...) with batch shape (..., N); times: (..., N),
    strictly increasing; weights: metric weights per tangent component (dof,) or (..., dof);
    time_origin t0: where gamma(t0) = p; basis B (dof, m): restricts the generators (default
    identity).  degree 1 is the one-parameter subgroup (geodesic of the Cartan-Schouten
    connections), degree 0 the Frechet mean of the log distance.  method: "gauss_newton"
    (batched Levenberg-Marquardt with closed-form Jacobians; max_iterations default 50) or
    "lbfgs" (``torch.optim.LBFGS`` on the tangent perturbation; default 500 per round).
    tolerance: relative step length for convergence (default 1e-10 in float64, 1e-5 in
    float32).  max_iterations and tolerance: None for the defaults; 0 iterations return the
    starting point."""
    _checks.group_samples(samples, "samples")
    _checks.degree(degree, samples.batch_shape[-1])
    _options(method, max_iterations, tolerance)
    G, Y, t, t0, w = _prepare(samples, times, weights, time_origin, max(1, degree + 1))
    B = _basis(basis, G, Y)
    with torch.no_grad():
        model = PolynomialModel(G, Y, t - t0.unsqueeze(-1), degree, w.sqrt(), B)
        p, v = _initial_subgroup(G, Y, t, t0)
        m = model.generator_dim
        x = torch.zeros(Y.shape[:-3] + (degree * m,), dtype=Y.dtype, device=Y.device)
        if degree >= 1:
            x[..., :m] = v if B is None else v @ torch.linalg.pinv(B).transpose(-1, -2)
        state = _solve(model, p, x, method, max_iterations, tolerance)
    return CurveFit(G, "polynomial", G.from_matrix(state.origin), model.coefficients(state.coefficients), t0,
                    state.cost, state.converged, state.iterations, method, model, state.coefficients)


def fit_subgroup(samples: LieGroup, times: torch.Tensor, **kwargs) -> CurveFit:
    """The one-parameter-subgroup model gamma(t) = p exp((t - t0) v): ``fit_polynomial``
    with degree 1."""
    return fit_polynomial(samples, times, 1, **kwargs)


def fit_riemannian_polynomial(samples: LieGroup, times: torch.Tensor, degree: int = 1, *,
                              weights=None, time_origin=0.0, steps: int = 16,
                              method: str = "gauss_newton", max_iterations: int | None = None,
                              tolerance: float | None = None) -> CurveFit:
    """Fits a Riemannian polynomial (28) of the left-invariant metric diag(weights) (20)-(21):
    gamma(t) = p Phi(t - t0), Phi' = Phi v_1, with (v_1, ..., v_K) solving the forward
    equations (30)/(33) of the Levi-Civita connection (29) from V0 at t0; degree 1 is the
    geodesic, whose v_1 solves the Euler-Arnold equation (24).  Shooting on (p, V0) as in
    Algorithm 3, but by Gauss-Newton (or LBFGS) instead of gradient descent; each sample's
    curve is integrated with ``steps`` steps.  Started from ``fit_polynomial`` of the same
    degree (v_k(0) ~ k! times its coefficients).  ``coefficients`` is V0 (..., K, dof)."""
    checks.integer(steps, "steps", 1)
    _checks.group_samples(samples, "samples")
    _checks.degree(degree, samples.batch_shape[-1])
    _options(method, max_iterations, tolerance)
    if degree < 1:
        raise ValueError(f"degree must be >= 1 for a Riemannian polynomial, got {degree}")
    G, Y, t, t0, w = _prepare(samples, times, weights, time_origin, degree + 1)
    with torch.no_grad():
        start = fit_polynomial(G.from_matrix(Y), t, degree, weights=w, time_origin=t0, max_iterations=20)
        factorials = torch.tensor([math.factorial(k) for k in range(1, degree + 1)],
                                  dtype=Y.dtype, device=Y.device)
        model = RiemannianPolynomialModel(G, Y, t - t0.unsqueeze(-1), w.sqrt(), w, degree, steps)
        x = (start.coefficients * factorials[:, None]).flatten(-2)
        state = _solve(model, start.origin.as_matrix(), x, method, max_iterations, tolerance)
    return CurveFit(G, "riemannian_polynomial", G.from_matrix(state.origin), model.initial(state.coefficients),
                    t0, state.cost, state.converged, state.iterations, method, model,
                    state.coefficients)


def fit_riemannian_geodesic(samples: LieGroup, times: torch.Tensor, *, weights=None,
                            time_origin=0.0, steps: int = 16, method: str = "gauss_newton",
                            max_iterations: int | None = None, tolerance: float | None = None) -> CurveFit:
    """Fits a Riemannian geodesic of the left-invariant metric diag(weights): gamma(t) =
    p Phi(t - t0), Phi' = Phi X, X solving the Euler-Arnold equation (24) from X(t0) = X0
    (``fit_riemannian_polynomial`` with degree 1; ``coefficients[..., 0, :]`` is X0)."""
    return fit_riemannian_polynomial(samples, times, 1, weights=weights, time_origin=time_origin,
                                     steps=steps, method=method, max_iterations=max_iterations,
                                     tolerance=tolerance)


def fit_inertial_worldline(samples: SGal3, times: torch.Tensor, *, weights=None, time_origin=0.0,
                           method: str = "gauss_newton", max_iterations: int | None = None,
                           tolerance: float | None = None) -> CurveFit:
    """The worldline of an inertial observer on SGal(3): gamma(t) = p exp((t - t0) [0, 0, 0, iota])
    (a pure time translation in the body frame: constant rotation and velocity, position
    r + v s, clock tau + s, s = iota (t - t0)).  Fits p and the clock rate iota to noisy frames
    y_i (SGal3, batch (..., N)) stamped t_i.  ``coefficients[..., 0, 9]`` is iota."""
    if not isinstance(samples, SGal3):
        raise TypeError(f"samples must be a torchsgal.SGal3 with batch shape (..., N), got "
                        f"{type(samples).__name__}")
    basis = torch.zeros(10, 1, dtype=samples.dtype, device=samples.device)
    basis[9, 0] = 1.0
    return fit_polynomial(samples, times, 1, weights=weights, time_origin=time_origin, basis=basis,
                          method=method, max_iterations=max_iterations, tolerance=tolerance)
