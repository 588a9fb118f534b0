"""Regression of time-stamped group samples: polynomial (one-parameter subgroup) curves,
Riemannian geodesics and polynomials of a left-invariant metric, and the inertial worldline
on SGal(3).

Equation numbers refer to Aubray and Nicol, "Polynomial regression on Lie groups and
application to SE(3)" (aubray-nicol-polynomial-regression-se3.txt).  Every fit minimises
(32) with d(gamma, y)^2 = r^T diag(w) r, r = log(gamma^-1 y) (see ``models.py``), over a
batch of independent data sets (leading batch dimensions); the samples are not
differentiated through (fits run under ``torch.no_grad``).

The fits are local methods: Gauss-Newton (or LBFGS) from a starting point (p, v of
consecutive samples).  Where a solution ends costlier than the constant curve at the Frechet
mean (R^2 < 0; high noise), that data set is solved again from the constant curve
(``_restart``).  The time origin t0 defaults to the mean of each data set's stamps.
"""
from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import torch

from ..functional import checks
from ..groups import LieGroup, SGal3
from . import _checks
from .models import PolynomialModel, RiemannianPolynomialModel, _polynomial_flow
from .solvers import SolverState, gauss_newton, lbfgs

METHODS = ("gauss_newton", "lbfgs")
# A Riemannian fit is reported not converged where its curve, integrated again with twice the
# steps, moves at some sample by more than this fraction of the curve's extent (see
# ``_integration_ok``).
INTEGRATION_TOLERANCE = 1e-3


@dataclass
class CurveFit:
    """A fitted curve on ``group`` for a batch of data sets.

    origin: gamma(time_origin) (batch (...)); coefficients: the algebra coefficients v_k
    (..., K, dof) of the polynomial model, or the initial body coordinates
    (v_1, ..., v_K)(t0) (..., K, dof) of a Riemannian polynomial (v_1 = X0 for a geodesic);
    time_origin: t0 (...), given or chosen (the mean of each data set's stamps);
    cost: sum_i d(gamma(t_i), y_i)^2 (...); converged: (...) bool.
    Call ``fit(times)`` for gamma at times (..., M)."""

    group: type[LieGroup]
    model: str
    origin: LieGroup
    coefficients: torch.Tensor
    time_origin: torch.Tensor
    cost: torch.Tensor
    converged: torch.Tensor
    iterations: int
    method: str
    _model: PolynomialModel | RiemannianPolynomialModel
    _x: torch.Tensor

    def __call__(self, times: torch.Tensor) -> LieGroup:
        """gamma at times (..., M), the leading dimensions broadcasting with the fit's batch.

        A tensor ``times`` is checked as the fit functions check theirs, never cast: it must
        have the fit's floating dtype (TypeError for an integer or bool dtype or the other
        float) and be on its device (ValueError).  Python numbers in a list or tuple (nested
        for a batch) are converted to the fit's dtype and device."""
        if isinstance(times, torch.Tensor):
            checks.floating(times, "times")
            checks.same_device_dtype(**{"the fit": self.time_origin, "times": times})
        elif isinstance(times, (list, tuple)) or (isinstance(times, numbers.Real)
                                                  and not isinstance(times, bool)):
            if checks.holds_bool(times):  # torch would read True as 1.0
                raise TypeError(f"times must be a torch.Tensor or a (nested) list of numbers of "
                                f"shape (..., M), not bools, got {times!r}")
            try:
                times = torch.tensor(times, dtype=self.origin.dtype, device=self.origin.device)
            except (TypeError, ValueError, RuntimeError):
                raise TypeError(f"times must be a torch.Tensor or a (nested) list of numbers of "
                                f"shape (..., M), got {times!r}") from None
        else:
            raise TypeError(f"times must be a torch.Tensor or a (nested) list of numbers of shape "
                            f"(..., M), got {type(times).__name__}")
        if times.dim() < 1:
            raise ValueError(f"times must have shape (..., M), got {tuple(times.shape)}")
        try:
            checks.broadcast_shapes(times.shape[:-1], self.time_origin.shape)
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
    """Checks a fit's data (the value checks in one host sync) and expands it to the batch.
    time_origin None: the mean of each data set's stamps."""
    _checks.group_samples(samples, "samples", min_samples)
    G = type(samples)
    Ym = samples.as_matrix()
    _checks.sample_times(times, samples)
    batch = checks.broadcast_shapes(samples.batch_shape[:-1], times.shape[:-1])
    n = samples.batch_shape[-1]
    w = _checks.metric_weights(weights, G, Ym)
    try:
        batch = checks.broadcast_shapes(batch, w.shape[:-1])
    except RuntimeError:
        raise ValueError(f"batch shapes do not broadcast: weights {tuple(w.shape[:-1])}, "
                         f"samples/times {tuple(batch)}") from None
    t0 = _checks.time_origin(time_origin, Ym)
    if t0 is not None:
        try:
            batch = checks.broadcast_shapes(batch, t0.shape)
        except RuntimeError:
            raise ValueError(f"time_origin must broadcast with the batch {tuple(batch)}, got shape "
                             f"{tuple(t0.shape)}") from None
    _checks.read_values(_checks.time_values(times) + _checks.finite_values(t0, "time_origin")
                        + _checks.weight_values(w))
    m = G.matrix_dim
    Y = Ym.detach().expand(batch + (n, m, m))
    t = times.detach().expand(batch + (n,))
    t0 = t.mean(-1) if t0 is None else t0.detach().expand(batch)
    w = w.detach().expand(batch + (G.dof,))
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


def _solve(model, origin, x, method, max_iterations, tolerance) -> SolverState:
    """The solver's state; a non-finite cost is never reported converged."""
    _options(method, max_iterations, tolerance)
    if tolerance is None:  # relative step length; float32 resolves ~1e-6 at best
        tolerance = 1e-10 if x.dtype == torch.float64 else 1e-5
    if max_iterations is None:
        max_iterations = 50 if method == "gauss_newton" else 500
    if method == "gauss_newton":
        state = gauss_newton(model, origin, x, max_iterations, tolerance)
    else:
        state = lbfgs(model, origin, x, max_iterations, tolerance)
    state.converged = state.converged & torch.isfinite(state.cost)
    return state


def _basis(basis, G, like):
    if basis is None:
        return None
    if not isinstance(basis, torch.Tensor) or basis.dtype not in checks.SUPPORTED_DTYPES:
        raise TypeError("basis must be a float32 or float64 torch.Tensor of shape (dof, m)")
    if basis.dim() != 2 or basis.shape[0] != G.dof or not 1 <= basis.shape[1] <= G.dof:
        raise ValueError(f"basis must have shape ({G.dof}, m) with 1 <= m <= {G.dof}, got "
                         f"{tuple(basis.shape)}")
    checks.same_device_dtype(samples=like, basis=basis)
    _checks.read_values(_checks.finite_values(basis, "basis"))
    return basis


def _constant_curve(G, Y, t, t0, w) -> torch.Tensor:
    """The origin of the fits' second start: the Frechet mean of each data set (Gauss-Newton
    of degree 0 from its middle sample, to a relative step of 1e-6 in float64, which puts its
    cost within about 1e-12 of the optimum), as group matrices."""
    tolerance = 1e-6 if Y.dtype == torch.float64 else None
    return _fit_polynomial(G, Y, t, t0, w, 0, None, "gauss_newton", 50, tolerance).origin.as_matrix()


def _rows(t: torch.Tensor, idx: torch.Tensor, batch_dims: int) -> torch.Tensor:
    """The data sets ``idx`` (int64 indices into the flattened leading ``batch_dims``
    dimensions) of ``t``, stacked: (len(idx),) + t.shape[batch_dims:].  Integer indexing,
    which does not copy the rest of an expanded ``t``; an unbatched t is data set 0."""
    if batch_dims == 0:
        return t.unsqueeze(0).index_select(0, idx)
    return t[torch.unravel_index(idx, t.shape[:batch_dims])]


def _restart(make_model, model, state: SolverState, origin, x, method, max_iterations,
             tolerance) -> SolverState:
    """Where the solution costs more than the start (origin, x), the constant curve at the
    (approximate) Frechet mean, whose cost is about the total variation of R^2 (a local
    minimum worse than the constant curve: R^2 < 0), solves those data sets again from it
    and keeps that solution where it is cheaper (or finite where the first was not).  One
    host sync to find them (``nonzero``); the second solve runs on those data sets only.
    ``make_model(idx)``: the model of the data sets ``idx``, int64 indices into the
    flattened batch (``_rows``); they are merged back with ``index_copy``."""
    r = model.residuals(origin, x)
    constant = (r * r).sum(-1)
    worse = ~(state.cost <= constant * (1 + 1e-9))  # a non-finite cost too
    idx = worse.reshape(-1).nonzero()[:, 0]  # the one host sync
    if idx.numel() == 0:
        return state
    nb = worse.dim()
    again = _solve(make_model(idx), _rows(origin, idx, nb), _rows(x, idx, nb), method,
                   max_iterations, tolerance)
    cost = _rows(state.cost, idx, nb)
    keep = (again.cost < cost) | (~torch.isfinite(cost) & torch.isfinite(again.cost))
    out = []
    for full, part in ((state.origin, again.origin), (state.coefficients, again.coefficients),
                       (state.cost, again.cost), (state.converged, again.converged)):
        flat = full.reshape((-1,) + full.shape[nb:])
        merged = torch.where(keep.reshape(keep.shape + (1,) * (part.dim() - 1)), part, flat[idx])
        out.append(flat.index_copy(0, idx, merged).reshape(full.shape))
    merged_origin, merged_coefficients, merged_cost, merged_converged = out
    return SolverState(merged_origin, merged_coefficients, merged_cost, merged_converged,
                       state.iterations + again.iterations)


def _fit_polynomial(G, Y, t, t0, w, degree, B, method, max_iterations, tolerance,
                    constant=None) -> CurveFit:
    """fit_polynomial on checked, expanded data.  Degree 0 starts from the middle sample.
    Degree >= 1 starts from p, v of consecutive samples (``_initial_subgroup``), then
    ``_restart``s from the constant curve at ``constant`` (default ``_constant_curve``)
    the data sets whose solution costs more than that curve."""
    with torch.no_grad():
        tau = t - t0.unsqueeze(-1)
        model = PolynomialModel(G, Y, tau, degree, w.sqrt(), B)
        x = torch.zeros(Y.shape[:-3] + (degree * model.generator_dim,), dtype=Y.dtype, device=Y.device)
        if degree == 0:
            state = _solve(model, Y[..., Y.shape[-3] // 2, :, :], x, method, max_iterations, tolerance)
        else:
            p, v = _initial_subgroup(G, Y, t, t0)
            m = model.generator_dim
            x[..., :m] = v if B is None else v @ torch.linalg.pinv(B).transpose(-1, -2)
            state = _solve(model, p, x, method, max_iterations, tolerance)
            if constant is None:
                constant = _constant_curve(G, Y, t, t0, w)
            sqrt_w, nb = w.sqrt(), t0.dim()
            state = _restart(lambda k: PolynomialModel(G, _rows(Y, k, nb), _rows(tau, k, nb),
                                                       degree, _rows(sqrt_w, k, nb), B),
                             model, state, constant, torch.zeros_like(x), method,
                             max_iterations, tolerance)
    return CurveFit(G, "polynomial", G.from_matrix(state.origin), model.coefficients(state.coefficients),
                    t0, state.cost, state.converged, state.iterations, method, model, state.coefficients)


def _integration_ok(G, model, V0, w):
    """Whether ``steps`` resolve the Riemannian curves of initial coordinates V0 (..., K, dof)
    from t0: integrated with 2 steps, each moves by at most INTEGRATION_TOLERANCE times its
    extent (max_i |log Phi(tau_i)|_w) at every sample, plus a rounding floor; False where
    either is not finite."""
    tau, steps = model.tau, model.steps
    coarse, _ = _polynomial_flow(G, V0, tau, w, steps, False)
    fine, _ = _polynomial_flow(G, V0, tau, w, 2 * steps, False)
    norm = lambda r: (w.unsqueeze(-2) * r * r).sum(-1).sqrt().amax(-1)  # noqa: E731
    error = norm(G.from_matrix(coarse).between(G.from_matrix(fine)).log())
    extent = norm(G.from_matrix(fine).log())
    floor = 64 * torch.finfo(extent.dtype).eps * (1 + extent)
    return error <= INTEGRATION_TOLERANCE * extent + floor


def fit_polynomial(samples: LieGroup, times: torch.Tensor, degree: int = 1, *, weights=None,
                   time_origin=None, basis: torch.Tensor | None = None,
                   method: str = "gauss_newton", max_iterations: int | None = None,
                   tolerance: float | None = None) -> CurveFit:
    """Fits gamma(t) = p exp(sum_{k=1..degree} (t - t0)^k B v_k) to samples y_i at times t_i.

    samples: a group element (SE3, SE23, SGal3, ...) with batch shape (..., N); times: (..., N),
    strictly increasing and finite; weights: positive, finite metric weights per tangent
    component (dof,) or (..., dof) (a tensor of the samples' dtype and device, or numbers);
    time_origin t0, where gamma(t0) = p: None (default) for the mean of each data set's stamps,
    a finite number, or a tensor (...) of the samples' dtype and device.  Degrees 0 and 1 fit
    the same curve for any t0 (only p changes); for degree >= 2 the model itself depends on t0
    (exp of a polynomial in t - t0: a shift of t0 is not a reparametrisation when the v_k do
    not commute), so the fitted curve and cost do too.  basis B (dof, m), of the samples' dtype
    and device: restricts the generators (default identity).  degree 1 is the one-parameter
    subgroup (geodesic of the Cartan-Schouten connections), degree 0 the Frechet mean of the
    log distance.  method: "gauss_newton" (batched Levenberg-Marquardt with closed-form
    Jacobians; max_iterations default 50) or "lbfgs" (``torch.optim.LBFGS`` on the tangent
    perturbation; default 500 per round).  tolerance: relative step length for convergence
    (default 1e-10 in float64, 1e-5 in float32).  max_iterations and tolerance: None for the
    defaults; 0 iterations return the start (the constant curve below where it costs less).

    A local method: degree >= 1 starts from p and v of consecutive samples; the data sets whose
    solution costs more than the constant curve at their Frechet mean (a local minimum with
    R^2 < 0, at high noise) are solved again from that curve (with zero coefficients), so that
    with Gauss-Newton the cost never exceeds the constant curve's (times 1 + 1e-9).  Better
    minima than both starts can exist at high noise.  ``converged`` is False where the solver
    did not converge or the cost is not finite."""
    _checks.group_samples(samples, "samples")
    _checks.degree(degree, samples.batch_shape[-1])
    _options(method, max_iterations, tolerance)
    G, Y, t, t0, w = _prepare(samples, times, weights, time_origin, max(1, degree + 1))
    B = _basis(basis, G, Y)
    return _fit_polynomial(G, Y, t, t0, w, degree, B, method, max_iterations, tolerance)


def fit_subgroup(samples: LieGroup, times: torch.Tensor, **kwargs) -> CurveFit:
    """The one-parameter-subgroup model gamma(t) = p exp((t - t0) v): ``fit_polynomial``
    with degree 1."""
    return fit_polynomial(samples, times, 1, **kwargs)


def fit_riemannian_polynomial(samples: LieGroup, times: torch.Tensor, degree: int = 1, *,
                              weights=None, time_origin=None, steps: int = 16,
                              method: str = "gauss_newton", max_iterations: int | None = None,
                              tolerance: float | None = None) -> CurveFit:
    """Fits a Riemannian polynomial (28) of the left-invariant metric diag(weights) (20)-(21):
    gamma(t) = p Phi(t - t0), Phi' = Phi v_1, with (v_1, ..., v_K) solving the forward
    equations (30)/(33) of the Levi-Civita connection (29) from V0 at t0; degree 1 is the
    geodesic, whose v_1 solves the Euler-Arnold equation (24).  Shooting on (p, V0) as in
    Algorithm 3, but by Gauss-Newton (or LBFGS) instead of gradient descent.  Started from
    ``fit_polynomial`` of the same degree (v_k(0) ~ k! times its coefficients).
    ``coefficients`` is V0 (..., K, dof).  samples, times, weights, time_origin (default None:
    the mean of each data set's stamps), method, max_iterations, tolerance: as in
    ``fit_polynomial``, and as there the data sets whose solution costs more than the constant
    curve at their Frechet mean (V0 = 0) are solved again from it.

    Each sample's curve is integrated from t0 on its own grid of ``steps`` fixed steps
    (h = (t_i - t0) / steps), so the accuracy falls with |t_i - t0|: keep t0 inside the stamps
    (the default) and raise ``steps`` for long spans or fast curves.  ``converged`` is False
    where the solver did not converge, where the cost is not finite, and where ``steps`` do
    not resolve the fitted curve: where the curve integrated with 2 steps differs from it at
    some sample by more than 1e-3 (``INTEGRATION_TOLERANCE``) times its extent
    max_i d(gamma(t0), gamma(t_i)) (log distance of the metric), and where the same test fails
    for the polynomial start, whose motion is the data's (else a fit stuck at the constant
    curve, which any step count integrates exactly, would pass).  The check integrates both
    curves with ``steps`` and 2 ``steps`` without sensitivities: about 10% of a fit."""
    checks.integer(steps, "steps", 1)
    _checks.group_samples(samples, "samples")
    _checks.degree(degree, samples.batch_shape[-1])
    _options(method, max_iterations, tolerance)
    if degree < 1:
        raise ValueError(f"degree must be >= 1 for a Riemannian polynomial, got {degree}")
    G, Y, t, t0, w = _prepare(samples, times, weights, time_origin, degree + 1)
    with torch.no_grad():
        constant = _constant_curve(G, Y, t, t0, w)
        start = _fit_polynomial(G, Y, t, t0, w, degree, None, "gauss_newton", 20, None, constant)
        factorials = torch.tensor([math.factorial(k) for k in range(1, degree + 1)],
                                  dtype=Y.dtype, device=Y.device)
        tau, sqrt_w = t - t0.unsqueeze(-1), w.sqrt()
        model = RiemannianPolynomialModel(G, Y, tau, sqrt_w, w, degree, steps)
        x = (start.coefficients * factorials[:, None]).flatten(-2)
        state = _solve(model, start.origin.as_matrix(), x, method, max_iterations, tolerance)
        nb = t0.dim()
        state = _restart(lambda k: RiemannianPolynomialModel(
            G, *(_rows(v, k, nb) for v in (Y, tau, sqrt_w, w)), degree, steps),  # type: ignore[call-arg]  # mypy: 4 rows
            model, state, constant, torch.zeros_like(x), method, max_iterations, tolerance)
        V0 = model.initial(state.coefficients)
        # The fitted curve and the polynomial start, whose motion is the data's, must both be
        # resolved (the start too: else a fit that cannot leave the constant curve, where the
        # integration is trivially exact, would pass).
        resolved = _integration_ok(G, model, torch.stack([V0, model.initial(x)]), w).all(0)
        converged = state.converged & resolved
    return CurveFit(G, "riemannian_polynomial", G.from_matrix(state.origin), V0, t0, state.cost,
                    converged, state.iterations, method, model, state.coefficients)


def fit_riemannian_geodesic(samples: LieGroup, times: torch.Tensor, *, weights=None,
                            time_origin=None, steps: int = 16, method: str = "gauss_newton",
                            max_iterations: int | None = None, tolerance: float | None = None) -> CurveFit:
    """Fits a Riemannian geodesic of the left-invariant metric diag(weights): gamma(t) =
    p Phi(t - t0), Phi' = Phi X, X solving the Euler-Arnold equation (24) from X(t0) = X0
    (``fit_riemannian_polynomial`` with degree 1, whose notes on time_origin, steps and
    ``converged`` apply; ``coefficients[..., 0, :]`` is X0)."""
    return fit_riemannian_polynomial(samples, times, 1, weights=weights, time_origin=time_origin,
                                     steps=steps, method=method, max_iterations=max_iterations,
                                     tolerance=tolerance)


def fit_inertial_worldline(samples: SGal3, times: torch.Tensor, *, weights=None, time_origin=None,
                           method: str = "gauss_newton", max_iterations: int | None = None,
                           tolerance: float | None = None) -> CurveFit:
    """The worldline of an inertial observer on SGal(3): gamma(t) = p exp((t - t0) [0, 0, 0, iota])
    (a pure time translation in the body frame: constant rotation and velocity, position
    r + v s, clock tau + s, s = iota (t - t0)).  Fits p and the clock rate iota to noisy frames
    y_i (SGal3, batch (..., N)) stamped t_i; t0 as in ``fit_polynomial`` (default: the mean
    stamp).  ``coefficients[..., 0, 9]`` is iota."""
    if not isinstance(samples, SGal3):
        raise TypeError(f"samples must be a torchsgal.SGal3 with batch shape (..., N), got "
                        f"{type(samples).__name__}")
    basis = torch.zeros(10, 1, dtype=samples.dtype, device=samples.device)
    basis[9, 0] = 1.0
    return fit_polynomial(samples, times, 1, weights=weights, time_origin=time_origin, basis=basis,
                          method=method, max_iterations=max_iterations, tolerance=tolerance)
