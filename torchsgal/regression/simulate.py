"""The simulated data of Aubray and Nicol, Algorithm 2 (one maneuver per data set)."""
from __future__ import annotations

from dataclasses import dataclass

import torch

from ..functional import checks
from ..groups import LieGroup


@dataclass
class Maneuver:
    times: torch.Tensor  # (..., N): i / N, i = 1..N
    real: LieGroup  # (..., N): start exp(t_i zeta)
    measured: LieGroup  # (..., N): start exp(t_i zeta + n_i), n_i ~ N(0, sigma^2 I) in the algebra


def simulate_maneuver(G, velocity: torch.Tensor, n_samples: int, noise_std: float, *,
                      start: LieGroup | None = None, generator: torch.Generator | None = None
                      ) -> Maneuver:
    """Algorithm 2: a maneuver with constant algebra velocity zeta = ``velocity`` (..., dof),
    sampled at t_i = i / N, i = 1..N; the measurement adds Gaussian noise of standard deviation
    ``noise_std`` to every algebra component before the exponential (line 6).  ``start``
    (default identity) multiplies on the left, as x_0 does in lines 5 and 7."""
    if not (isinstance(G, type) and issubclass(G, LieGroup) and G is not LieGroup):
        raise TypeError(f"G must be a group class (ts.SE3, ts.SGal3, ...), got {G!r}")
    checks.vector(velocity, G.dof, "velocity")
    n_samples = checks.integer(n_samples, "n_samples", 1)
    noise_std = checks.finite_number(noise_std, "noise_std", ">= 0")
    if generator is not None and not isinstance(generator, torch.Generator):
        raise TypeError(f"generator must be a torch.Generator or None, got {type(generator).__name__}")
    if start is not None:
        if not isinstance(start, G):
            raise TypeError(f"start must be a {G.__name__}, got {type(start).__name__}")
        checks.same_device_dtype(velocity=velocity, start=start.as_matrix())
        checks.broadcast_batch(velocity=velocity.shape[:-1], start=start.batch_shape)
    dtype, device = velocity.dtype, velocity.device
    t = torch.arange(1, n_samples + 1, dtype=dtype, device=device) / n_samples
    t = t.expand(velocity.shape[:-1] + (n_samples,))
    s = t.unsqueeze(-1) * velocity.unsqueeze(-2)
    noise = torch.randn(s.shape, dtype=dtype, device=device, generator=generator) * noise_std
    real, measured = G.exp(s), G.exp(s + noise)
    if start is not None:
        real, measured = start.unsqueeze(-1) @ real, start.unsqueeze(-1) @ measured
    return Maneuver(t, real, measured)
