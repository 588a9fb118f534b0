"""Robust losses rho(s) of the squared whitened residual norm s = |L r|^2 (Triggs et al.,
"Bundle adjustment: a modern synthesis", Section 6.8; Ceres' ``loss_function.h``).

A factor with loss rho contributes ``1/2 rho(s)`` to the cost (``rho(s) = s`` for the plain
loss, so the cost is ``1/2 |L r|^2``).  Each loss gives ``rho(s)``, ``rho'(s)`` and
``rho''(s)`` together (``evaluate``), with ``rho(0) = 0`` and ``rho'(0) = 1``: near zero every
loss is the plain one.

The solvers apply a loss with Ceres' ``Corrector``: the whitened residual r and Jacobian J
become ``r~ = sqrt(rho') / (1 - alpha) r`` and ``J~ = sqrt(rho') (I - alpha r r^T / s) J``,
``alpha = 1 - sqrt(1 + 2 s rho'' / rho')``, so that the Gauss-Newton model of r~ matches the
gradient and the curvature of ``1/2 rho(s)`` along r (Triggs' correction).  As in Ceres, the
correction is used only where ``rho'' > 0``; where ``rho'' <= 0`` (the outlier side of every
loss below) it is the plain IRLS weighting ``r~ = sqrt(rho') r``, ``J~ = sqrt(rho') J``, which
keeps the model quadratic and positive semi-definite.
"""
from __future__ import annotations

import torch

from ...functional import checks
from ...functional._blocking import values_readable
from ...functional.blocks import last_axis_dot

__all__ = ["RobustLoss", "TrivialLoss", "Huber", "Cauchy", "GemanMcClure", "Tukey", "correct"]


class RobustLoss:
    """Base class: a loss rho(s) of the squared whitened norm s >= 0 (Triggs/Ceres convention).

    Subclasses implement ``evaluate(s) -> (rho, rho', rho'')``, elementwise over any shape."""

    def evaluate(self, s: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(rho(s), rho'(s), rho''(s)), each of the shape of ``s``."""
        raise NotImplementedError

    def __call__(self, s: torch.Tensor) -> torch.Tensor:
        """rho(s) for s >= 0 (a negative s raises; ``evaluate``, which the solvers call on
        squared norms, does not check the values)."""
        checks.floating(s, "s")
        if values_readable(s) and bool((s < 0).any()):  # one read, where values can be read
            raise ValueError(f"s must be >= 0 (a squared whitened norm), got a minimum of {float(s.min()):g}")
        return self.evaluate(s)[0]

    def __repr__(self) -> str:
        scale = getattr(self, "scale", None)
        return f"{type(self).__name__}()" if scale is None else f"{type(self).__name__}({scale:g})"


class TrivialLoss(RobustLoss):
    """rho(s) = s: the plain least-squares cost."""

    def evaluate(self, s):
        checks.floating(s, "s")
        one = torch.ones_like(s)
        return s, one, torch.zeros_like(s)


def _scale(scale) -> float:
    """The loss's scale a: positive, and within [1e-75, 1e75], where a^2 and a^4 (which the
    losses and their derivatives use) are normal floating-point numbers."""
    a = checks.finite_number(scale, "scale", "> 0")
    if not 1e-75 <= a <= 1e75:
        raise ValueError(f"scale must be within [1e-75, 1e75] (in whitened units; its square and "
                         f"fourth power must be normal numbers), got {a:g}")
    return a


class Huber(RobustLoss):
    """Huber: rho(s) = s for s <= a^2, 2 a sqrt(s) - a^2 beyond (a = ``scale``, in whitened
    units: standard deviations)."""

    def __init__(self, scale: float = 1.0):
        self.scale = _scale(scale)

    def evaluate(self, s):
        checks.floating(s, "s")
        b = self.scale ** 2
        outer = s > b
        root = torch.where(outer, s, torch.ones_like(s)).sqrt()  # safe: sqrt only where s > b
        rho = torch.where(outer, 2.0 * self.scale * root - b, s)
        d1 = torch.where(outer, self.scale / root, torch.ones_like(s))
        d2 = torch.where(outer, -d1 / (2.0 * torch.where(outer, s, torch.ones_like(s))),
                         torch.zeros_like(s))
        return rho, d1, d2


class Cauchy(RobustLoss):
    """Cauchy (Lorentzian): rho(s) = a^2 log(1 + s / a^2)."""

    def __init__(self, scale: float = 1.0):
        self.scale = _scale(scale)

    def evaluate(self, s):
        checks.floating(s, "s")
        b = self.scale ** 2
        inv = 1.0 / (1.0 + s / b)
        return b * torch.log1p(s / b), inv, -inv * inv / b


class GemanMcClure(RobustLoss):
    """Geman-McClure: rho(s) = a^2 s / (a^2 + s) (GTSAM's ``GemanMcClure`` of scale a, whose
    error c^2 e^2 / (2 (c^2 + e^2)) is 1/2 rho(e^2))."""

    def __init__(self, scale: float = 1.0):
        self.scale = _scale(scale)

    def evaluate(self, s):
        checks.floating(s, "s")
        b = self.scale ** 2
        den = b + s
        return b * s / den, (b / den) ** 2, -2.0 * b * b / den ** 3


class Tukey(RobustLoss):
    """Tukey's biweight: rho(s) = a^2/3 (1 - (1 - s/a^2)^3) for s <= a^2, a^2/3 beyond (the
    residual's influence vanishes there: rho' = 0)."""

    def __init__(self, scale: float = 1.0):
        self.scale = _scale(scale)

    def evaluate(self, s):
        checks.floating(s, "s")
        b = self.scale ** 2
        inner = s <= b
        u = torch.where(inner, 1.0 - s / b, torch.zeros_like(s))
        rho = b / 3.0 * (1.0 - u ** 3)
        return rho, u * u, -2.0 * u / b


def correct(loss: RobustLoss | None, r: torch.Tensor, J: torch.Tensor | None
            ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
    """Ceres' Corrector on whitened residuals r (..., m) and Jacobians J (..., m, n) (or None):
    returns (r~, J~, rho(s)) with s = |r|^2 (see the module docstring); no loss: (r, J, s)."""
    if loss is not None and not isinstance(loss, RobustLoss):
        raise TypeError(f"loss must be a RobustLoss or None, got {type(loss).__name__}")
    checks.floating(r, "r")
    if r.dim() < 1:
        raise ValueError(f"r must have shape (..., m), got {tuple(r.shape)}")
    if J is not None:
        checks.floating(J, "J")
        if J.dim() < 2 or J.shape[-2] != r.shape[-1]:
            raise ValueError(f"J must have shape (..., {r.shape[-1]}, n) (r has shape "
                             f"{tuple(r.shape)}), got {tuple(J.shape)}")
        checks.binary(r, 1, J, 2, "r", "J")
    return corrected(loss, r, J)


def corrected(loss: RobustLoss | None, r: torch.Tensor, J: torch.Tensor | None
              ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
    """``correct`` without its argument checks, for residuals and Jacobians whose types and
    shapes are known (the engine's built-in factors)."""
    s = last_axis_dot(r, r)
    if loss is None:
        return r, J, s
    rho, d1, d2 = loss.evaluate(s)
    sqrt_d1 = d1.clamp_min(0.0).sqrt()
    curved = (s > 0) & (d2 > 0)
    safe_d1 = torch.where(curved, d1, torch.ones_like(d1))
    # alpha = 1 - sqrt(1 + 2 s rho''/rho'), clamped to the plain weighting where rho'' <= 0
    alpha = torch.where(curved, 1.0 - (1.0 + 2.0 * s * d2 / safe_d1).clamp_min(0.0).sqrt(),
                        torch.zeros_like(s))
    r_new = r * (sqrt_d1 / (1.0 - alpha))[..., None]
    if J is None:
        return r_new, None, rho
    safe_s = torch.where(curved, s, torch.ones_like(s))
    coef = (alpha / safe_s)[..., None, None]
    J_new = sqrt_d1[..., None, None] * (J - coef * r[..., :, None] * (r[..., None, :] @ J))
    return r_new, J_new, rho
