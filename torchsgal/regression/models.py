"""Curve models on a group G, their residuals and Jacobians.

Residual convention (right / body frame, CONVENTIONS.md): sample Y_i = gamma(t_i) exp(r_i),
    r_i = log(gamma(t_i)^-1 Y_i),
weighted as sqrt(w) * r_i so that the cost sum_i r_i^T diag(w) r_i is the squared
left-invariant "log distance" of the metric with weights w (Aubray-Nicol (21), (32)).
The cost is invariant under left translation of samples and curve together.

Polynomial model (one-parameter subgroup for degree 1, geodesics of the Cartan-Schouten
connections [Aubray-Nicol ref. 28]):
    gamma(t) = p exp(s(t)),   s(t) = sum_{k=1..K} (t - t0)^k B x_k,
B a fixed basis (dof, m) of the allowed generators (identity by default).  Jacobians, with
E = exp(s) and J_l^-1(r) the inverse left Jacobian of the residual:
    dr/dp   = -J_l^-1(r) Ad(E^-1)                 (p <- p exp(dp))
    dr/dx_k = -(t - t0)^k J_l^-1(r) J_r(s) B      (x_k <- x_k + dx_k)
(derived here; the tests check them against autograd).

Riemannian polynomial model (geodesic for degree 1): gamma(t) = p Phi(t - t0), Phi the
curve of ``polynomial_flow`` (forward equations (30)/(33) of the Levi-Civita connection of
diag(w), Euler-Arnold (24) for degree 1), with Jacobians from its exact discrete sensitivity.
"""
from __future__ import annotations

import torch

from ..functional import checks
from ..groups import LieGroup


def _group_class(G) -> None:
    if not (isinstance(G, type) and issubclass(G, LieGroup)):
        raise TypeError(f"G must be a torchsgal group class (e.g. torchsgal.SE3), got {G!r}")


def _check_flow_args(G, first, first_name: str, first_tail: int, tau, weights, steps) -> None:
    """Metadata checks of the public flows (no host sync): ``first`` (..., [K,] dof), tau
    (..., M), weights (..., dof), one dtype and device, broadcastable batches, steps >= 1."""
    checks.floating(tau, "tau")
    checks.vector(weights, G.dof, "weights")
    checks.same_device_dtype(**{first_name: first, "tau": tau, "weights": weights})
    if tau.dim() < 1:
        raise ValueError(f"tau must have shape (..., M), got {tuple(tau.shape)}")
    checks.broadcast_batch(**{first_name: first.shape[: first.dim() - first_tail],
                              "tau": tau.shape[:-1], "weights": weights.shape[:-1]})
    checks.integer(steps, "steps", 1)


def _coordinates(G, V, name: str) -> None:
    """V (..., K, dof), K >= 1."""
    checks.floating(V, name)
    if V.dim() < 2 or V.shape[-1] != G.dof or V.shape[-2] < 1:
        raise ValueError(f"{name} must have shape (..., K, {G.dof}) with K >= 1 for "
                         f"{G.__name__}, got {tuple(V.shape)}")


def _weighted(r: torch.Tensor, sqrt_w: torch.Tensor) -> torch.Tensor:
    return r * sqrt_w.unsqueeze(-2)


class PolynomialModel:
    """gamma(t) = p exp(sum_k (t - t0)^k B x_k); x is (..., K*m)."""

    def __init__(self, G, samples: torch.Tensor, tau: torch.Tensor, degree: int,
                 sqrt_w: torch.Tensor, basis: torch.Tensor | None = None, fix_origin: bool = False):
        self.G = G
        self.samples = samples  # (..., N, n, n)
        self.tau = tau  # (..., N)
        self.degree = degree
        self.sqrt_w = sqrt_w  # (..., dof)
        self.basis = basis  # (dof, m) or None
        self.fix_origin = checks.boolean(fix_origin, "fix_origin")

    @property
    def generator_dim(self) -> int:
        return self.G.dof if self.basis is None else self.basis.shape[-1]

    def coefficients(self, x: torch.Tensor) -> torch.Tensor:
        """x (..., K*m) -> algebra coefficients v_k (..., K, dof)."""
        m = self.generator_dim
        xk = x.reshape(x.shape[:-1] + (self.degree, m))
        return xk if self.basis is None else xk @ self.basis.transpose(-1, -2)

    def algebra_curve(self, x: torch.Tensor, tau: torch.Tensor) -> torch.Tensor:
        """s(t) (..., M, dof) at offsets tau (..., M)."""
        if self.degree == 0:
            return torch.zeros(tau.shape + (self.G.dof,), dtype=tau.dtype, device=tau.device)
        v = self.coefficients(x)  # (..., K, dof)
        powers = torch.stack([tau ** (k + 1) for k in range(self.degree)], dim=-1)  # (..., M, K)
        return powers @ v

    def curve(self, origin: torch.Tensor, x: torch.Tensor, tau: torch.Tensor) -> torch.Tensor:
        """gamma at offsets tau (..., M): group matrices (..., M, n, n)."""
        s = self.algebra_curve(x, tau)
        return origin.unsqueeze(-3) @ self.G.exp(s).as_matrix()

    def raw_residuals(self, origin, x):
        s = self.algebra_curve(x, self.tau)
        if self.degree == 0:  # a constant curve: exp(0) = I
            gamma = self.G.from_matrix(origin.unsqueeze(-3))
        else:
            gamma = self.G.from_matrix(origin.unsqueeze(-3) @ self.G.exp(s).as_matrix())
        return gamma.between(self.G.from_matrix(self.samples)).log(), s

    def residuals(self, origin: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        r, _ = self.raw_residuals(origin, x)
        return _weighted(r, self.sqrt_w).flatten(-2)

    def linearize(self, origin: torch.Tensor, x: torch.Tensor):
        G = self.G
        r, s = self.raw_residuals(origin, x)
        jl_inv = G.jl_inv(r)  # (..., N, dof, dof)
        blocks = []
        if not self.fix_origin:  # Ad(exp(-0)) = I for degree 0
            blocks.append(-jl_inv if self.degree == 0 else -jl_inv @ G.exp(-s).adjoint())
        if self.degree > 0:
            jv = -jl_inv @ G.jr(s)
            if self.basis is not None:
                jv = jv @ self.basis
            for k in range(1, self.degree + 1):
                blocks.append((self.tau ** k)[..., None, None] * jv)
        J = torch.cat(blocks, dim=-1) * self.sqrt_w[..., None, :, None]
        J = J.flatten(-3, -2)  # (..., N*dof, P)
        return _weighted(r, self.sqrt_w).flatten(-2), J


def euler_arnold_rhs(G, X: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """dX/dt = W^-1 ad(X)^T W X, the Euler-Arnold (Euler-Poincare) equation (24) of the
    left-invariant metric <a, b> = a^T diag(w) b, for the body velocity X = gamma^-1 dgamma/dt.
    The transpose in (24) is the metric one: W^-1 ad(X)^T W.  Sign: for SO(3) this is
    Euler's I dw/dt = (I w) x w.  X (..., dof), weights (..., dof): positive (not checked,
    that would read values; a zero weight divides by zero)."""
    _group_class(G)
    checks.vector(X, G.dof, "X")
    checks.vector(weights, G.dof, "weights")
    checks.binary(X, 1, weights, 1, "X", "weights")
    return (G.ad(X).transpose(-1, -2) @ (weights * X).unsqueeze(-1)).squeeze(-1) / weights


# Commutator-free Lie-group method of order 4 (Blanes and Moan) for gamma' = gamma X(t):
# gamma_(n+1) = gamma_n exp(h (a1 X1 + a2 X2)) exp(h (a2 X1 + a1 X2)), X1, X2 at the Gauss
# points t_n + c_i h.
_SQ3 = 3.0 ** 0.5
_GAUSS = (0.5 - _SQ3 / 6, 0.5 + _SQ3 / 6)
_A1, _A2 = 0.25 + _SQ3 / 6, 0.25 - _SQ3 / 6


def _hermite(c: float):
    """Cubic Hermite weights (X_n, h F_n, X_(n+1), h F_(n+1)) at fraction c of the step."""
    return (2 * c**3 - 3 * c**2 + 1, c**3 - 2 * c**2 + c, -2 * c**3 + 3 * c**2, c**3 - c**2)


def levi_civita(G, X: torch.Tensor, Y: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """The Levi-Civita connection of the left-invariant metric diag(w) on left-invariant
    fields, (29) in vector form: nabla_X Y = 1/2 ([X, Y] - ad*_X Y - ad*_Y X), with the metric
    adjoint ad*_X = W^-1 ad(X)^T W.  Along a curve with body velocity X, a field with body
    components Y(t) has covariant derivative dY/dt + nabla_X Y.  X, Y, weights (..., dof),
    broadcast; weights positive (not checked: a zero weight divides by zero)."""
    _group_class(G)
    for name, v in (("X", X), ("Y", Y), ("weights", weights)):
        checks.vector(v, G.dof, name)
    checks.same_device_dtype(X=X, Y=Y, weights=weights)
    checks.broadcast_batch(X=X.shape[:-1], Y=Y.shape[:-1], weights=weights.shape[:-1])
    return _levi_civita(G, X, Y, weights)


def _levi_civita(G, X, Y, weights):
    adj = lambda A, B: (G.ad(A).transpose(-1, -2) @ (weights * B).unsqueeze(-1)).squeeze(-1)  # noqa: E731
    bracket = (G.ad(X) @ Y.unsqueeze(-1)).squeeze(-1)
    return 0.5 * (bracket - (adj(X, Y) + adj(Y, X)) / weights)


def _levi_civita_jacobians(G, X, Y, weights, structure):
    """d(nabla_X Y)/dX and d(nabla_X Y)/dY (..., dof, dof)."""
    dof = X.shape[-1]
    Cm = structure.permute(1, 2, 0).reshape(dof, dof * dof)
    M = lambda mu: (mu @ Cm).unflatten(-1, (dof, dof))  # noqa: E731  M(mu) d = ad(d)^T mu
    wl, wr = weights.unsqueeze(-1), weights.unsqueeze(-2)
    adX, adY = G.ad(X), G.ad(Y)
    dY = 0.5 * (adX - (adX.transpose(-1, -2) * wr + M(weights * X)) / wl)
    dX = 0.5 * (-adY - (M(weights * Y) + adY.transpose(-1, -2) * wr) / wl)
    return dX, dY


def polynomial_rhs(G, V: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """The forward equations (30)/(33) of a Riemannian polynomial of degree K in body
    coordinates, V = (v_1, ..., v_K) (..., K, dof), v_1 the body velocity and
    v_(i+1) = nabla_(gamma') v_i:  dv_i/dt = v_(i+1) - nabla_(v_1) v_i, v_(K+1) = 0.
    K = 1 is the Euler-Arnold equation (24).  weights (..., dof), positive (not checked)."""
    _group_class(G)
    _coordinates(G, V, "V")
    checks.vector(weights, G.dof, "weights")
    checks.binary(V, 2, weights, 1, "V", "weights")
    return _polynomial_rhs(G, V, weights)


def _polynomial_rhs(G, V, weights):
    w = weights.unsqueeze(-2)
    nab = _levi_civita(G, V[..., :1, :].expand(V.shape), V, w)
    return torch.cat([V[..., 1:, :], torch.zeros_like(V[..., :1, :])], dim=-2) - nab


def _polynomial_rhs_jacobian(G, V, weights, structure):
    """d polynomial_rhs / dV, (..., K dof, K dof) in the flattened order of V."""
    K, dof = V.shape[-2], V.shape[-1]
    dX, dY = _levi_civita_jacobians(G, V[..., :1, :].expand(V.shape), V, weights.unsqueeze(-2),
                                    structure)  # (..., K, dof, dof)
    eye = torch.eye(dof, dtype=V.dtype, device=V.device).expand(V.shape[:-2] + (dof, dof))
    zero = torch.zeros_like(eye)
    rows = []
    for i in range(K):
        blocks = [zero] * K
        blocks[0] = -dX[..., i, :, :]
        blocks[i] = blocks[i] - dY[..., i, :, :]
        if i + 1 < K:
            blocks[i + 1] = eye
        rows.append(torch.cat(blocks, dim=-1))
    return torch.cat(rows, dim=-2)


def geodesic_flow(G, velocity: torch.Tensor, tau: torch.Tensor, weights: torch.Tensor,
                  steps: int = 16, sensitivity: bool = False):
    """Riemannian geodesic from the identity with initial body velocity ``velocity``
    (..., dof), evaluated at offsets ``tau`` (..., M); weights (..., dof).

    Returns Phi (..., M, n, n), X(tau) (..., M, dof) and, with ``sensitivity=True``, eta
    (..., M, dof, dof) such that Phi(X0 + d) = Phi(X0) exp(eta d) to first order.
    ``polynomial_flow`` with degree 1 (the Euler-Arnold equation (24)); its notes on the
    step size and the weights apply."""
    _group_class(G)
    checks.vector(velocity, G.dof, "velocity")
    _check_flow_args(G, velocity, "velocity", 1, tau, weights, steps)
    checks.boolean(sensitivity, "sensitivity")
    out = _polynomial_flow(G, velocity.unsqueeze(-2), tau, weights, steps, sensitivity)
    return (out[0], out[1][..., 0, :]) + tuple(out[2:])


def polynomial_flow(G, initial: torch.Tensor, tau: torch.Tensor, weights: torch.Tensor,
                    steps: int = 16, sensitivity: bool = False):
    """Riemannian polynomial (28) of degree K of the left-invariant metric diag(w) from the
    identity, initial body coordinates ``initial`` = (v_1, ..., v_K)(0) (..., K, dof),
    evaluated at offsets ``tau`` (..., M).

    Returns Phi (..., M, n, n), V(tau) (..., M, K, dof) and, with ``sensitivity=True``, eta
    (..., M, dof, K dof) such that Phi(V0 + d) = Phi(V0) exp(eta d) to first order.

    Each offset is integrated on its own grid of ``steps`` equal steps (h = tau / steps), all
    in one batch: ``polynomial_rhs`` by classical RK4, and the reconstruction (25)
    gamma' = gamma v_1 by the fourth-order commutator-free method above, v_1 at the Gauss
    points from the cubic Hermite interpolant of the RK4 step.  ((26), gamma = exp(int X),
    holds only when the X(t) commute; it is not used.)  The sensitivity is the exact
    derivative of this discrete map (tangent-linear RK4 for S = dV/dV0 and
    eta_(n+1) = Ad(e^-b) (Ad(e^-a) eta_n + J_r(a) da) + J_r(b) db).

    The steps are fixed, not adaptive: the step h = tau / steps must resolve the dynamics
    (h |V| well below 1).  Beyond that (a large velocity or offset for the number of steps)
    the result is inaccurate and can overflow to inf or NaN without an error; raise
    ``steps``.  The weights (..., dof) must be positive (not checked, that would read values:
    a zero weight divides by zero)."""
    _group_class(G)
    _coordinates(G, initial, "initial")
    _check_flow_args(G, initial, "initial", 2, tau, weights, steps)
    checks.boolean(sensitivity, "sensitivity")
    return _polynomial_flow(G, initial, tau, weights, steps, sensitivity)


def _polynomial_flow(G, initial, tau, weights, steps, sensitivity):
    K, dof = initial.shape[-2], G.dof
    V, w = initial.unsqueeze(-3), weights.unsqueeze(-2)
    batch = checks.broadcast_shapes(V.shape[:-2], tau.shape, w.shape[:-1])
    tau = tau.expand(batch)
    V = V.expand(batch + (K, dof))
    h = (tau / steps)[..., None, None]
    n = G.matrix_dim
    Phi = torch.eye(n, dtype=V.dtype, device=V.device).expand(batch + (n, n))
    f = lambda Z: _polynomial_rhs(G, Z, w)  # noqa: E731
    if sensitivity:
        C = G.ad(torch.eye(dof, dtype=V.dtype, device=V.device))
        Df = lambda Z: _polynomial_rhs_jacobian(G, Z, w, C)  # noqa: E731
        S = torch.eye(K * dof, dtype=V.dtype, device=V.device).expand(batch + (K * dof, K * dof))
        eta = torch.zeros(batch + (dof, K * dof), dtype=V.dtype, device=V.device)
        hm = h[..., 0, :, None]
    weights_g = [_hermite(c) for c in _GAUSS]
    F = f(V)
    if sensitivity:
        dF = Df(V) @ S
    for _ in range(steps):
        k1 = F
        k2 = f(V + 0.5 * h * k1)
        k3 = f(V + 0.5 * h * k2)
        V4 = V + h * k3
        k4 = f(V4)
        V_new = V + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        F_new = f(V_new)
        Xg = [(c0 * V + c1 * h * F + c2 * V_new + c3 * h * F_new)[..., 0, :]
              for c0, c1, c2, c3 in weights_g]
        a = h[..., 0, :] * (_A1 * Xg[0] + _A2 * Xg[1])
        b = h[..., 0, :] * (_A2 * Xg[0] + _A1 * Xg[1])
        Ea, Eb = G.exp(a), G.exp(b)
        Phi = Phi @ Ea.as_matrix() @ Eb.as_matrix()
        if sensitivity:
            K1 = dF
            K2 = Df(V + 0.5 * h * k1) @ (S + 0.5 * hm * K1)
            K3 = Df(V + 0.5 * h * k2) @ (S + 0.5 * hm * K2)
            K4 = Df(V4) @ (S + hm * K3)
            S_new = S + hm / 6 * (K1 + 2 * K2 + 2 * K3 + K4)
            dF_new = Df(V_new) @ S_new
            Sg = [(c0 * S + c1 * hm * dF + c2 * S_new + c3 * hm * dF_new)[..., :dof, :]
                  for c0, c1, c2, c3 in weights_g]
            da = hm * (_A1 * Sg[0] + _A2 * Sg[1])
            db = hm * (_A2 * Sg[0] + _A1 * Sg[1])
            eta = Eb.inverse().adjoint() @ (Ea.inverse().adjoint() @ eta + G.jr(a) @ da) \
                + G.jr(b) @ db
            S, dF = S_new, dF_new
        V, F = V_new, F_new
    if sensitivity:
        return Phi, V, eta
    return Phi, V


class RiemannianPolynomialModel:
    """gamma(t) = p Phi(t - t0; V0), Phi the Riemannian polynomial of degree K of the
    left-invariant metric diag(w) from the identity with initial body coordinates
    V0 = (v_1, ..., v_K)(0) (x = V0 flattened, (..., K dof)); K = 1 is the geodesic.

    dr/dp = -J_l^-1(r) Ad(Phi^-1), dr/dV0 = -J_l^-1(r) eta (Phi -> Phi exp(eta d)), eta the
    exact sensitivity of the discrete flow (``polynomial_flow``)."""

    def __init__(self, G, samples, tau, sqrt_w, weights, degree=1, steps=16, fix_origin=False):
        self.G = G
        self.samples = samples
        self.tau = tau
        self.sqrt_w = sqrt_w
        self.weights = weights
        self.degree = degree
        self.steps = steps
        self.fix_origin = checks.boolean(fix_origin, "fix_origin")

    def initial(self, x):
        return x.unflatten(-1, (self.degree, self.G.dof))

    def curve(self, origin, x, tau):
        Phi, _ = _polynomial_flow(self.G, self.initial(x), tau, self.weights, self.steps, False)
        return origin.unsqueeze(-3) @ Phi

    def residuals(self, origin, x):
        G = self.G
        gamma = self.curve(origin, x, self.tau)
        r = G.from_matrix(gamma).between(G.from_matrix(self.samples)).log()
        return _weighted(r, self.sqrt_w).flatten(-2)

    def linearize(self, origin, x):
        G = self.G
        Phi, _, eta = _polynomial_flow(G, self.initial(x), self.tau, self.weights, self.steps,
                                       sensitivity=True)
        r = G.from_matrix(origin.unsqueeze(-3) @ Phi).between(G.from_matrix(self.samples)).log()
        jl_inv = G.jl_inv(r)
        blocks = []
        if not self.fix_origin:
            blocks.append(-jl_inv @ G.from_matrix(Phi).inverse().adjoint())
        blocks.append(-jl_inv @ eta)
        J = torch.cat(blocks, dim=-1) * self.sqrt_w[..., None, :, None]
        return _weighted(r, self.sqrt_w).flatten(-2), J.flatten(-3, -2)


RiemannianGeodesicModel = RiemannianPolynomialModel  # degree 1
