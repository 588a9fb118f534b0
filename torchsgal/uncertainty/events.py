"""Fusion of a measured event with an uncertain timestamp into a concentrated Gaussian on
SGal(3) (Mahony, Kelly and Weiss, Section 6, (52)-(69)).

Prior F_k = F_hat exp(eta), eta ~ N(0, Q) (52).  Measurement: the event y_tau = (y, tau) (55)
with covariance Sigma = diag(Sigma_p, Sigma_t) (53)-(54), of the state F_i at the (unknown)
measurement time.  The relative frame kF_i = F_k^-1 F_i is near-inertial by default (58): the
identity but for the time offset tau - t_hat_k; a preintegrated estimate may be passed instead.

    d       = I4^T F_hat^-1 y_tau                                (60), (63)
    N_mu    = I4^T F_hat^-1 I4 - e4 e4^T,  N_eta = e4 e10^T,   S = N_mu Sigma N_mu^T + N_eta Q N_eta^T
    d_tilde = d - I4^T kF_i y0                                   (67)
    C eps   = I4^T eps^ kF_i y0                                  (68), sign: see below
    eps     = (Q^-1 + C^T S^-1 C)^-1 C^T S^-1 d_tilde,   F* = F_hat exp(eps)
    Q*      = J_r(eps) (Q^-1 + C^T S^-1 C)^-1 J_r(eps)^T         (the reset, end of 6.4)

Departures, checked by the tests (brute-force posterior) and examples/timestamp_fusion.py:

* The paper substitutes E ~ I - eps^ although E = exp(eps^) (65); linearising exp gives
  E ~ I + eps^, hence C eps = +I4^T eps^ kF_i y0 (the printed sign moves the estimate away
  from the measurement).
* The time row carries no information: kF_i is built from tau itself, so d_t - (E kF_i y0)_t
  = -eps_iota identically, and its noise is exactly -eta_iota (with (58)'s sign corrected:
  tau - t_hat = (t_i - t_k) + mu_t + eta_iota), not noise independent of the prior.  The paper
  adds it as N_eta Q N_eta^T, which counts the prior's time information twice (the time NEES
  doubles).  By default only the three position rows are fused; their noise already holds the
  timestamp jitter along the velocity (-C^T v Sigma_t).  ``time_row=True`` gives the printed
  model.
* The reset is written J_r P J_r^T from exp(eps + d) ~ exp(eps) exp(J_r d).

``iterations > 1`` re-linearises exp (Gauss-Newton on eps with the exact Jacobian).
"""
from __future__ import annotations

from typing import cast

import torch

from ..functional import blocks, checks, sgal3
from ..functional._blocking import values_readable
from ..groups import SGal3
from .covariance import _covariance_measures, _default_tol, _mv, _raise_for_measures, _read, _sym
from .gaussian import KNOWN_DIRECTIONS_HINT, ConcentratedGaussian


def near_inertial_relative_frame(tau: torch.Tensor, t_hat: torch.Tensor) -> SGal3:
    """(58): kF_i = identity but for the time offset tau - t_hat (batch: tau's and t_hat's
    broadcast; t_hat may be a number)."""
    checks.floating(tau, "tau")
    if isinstance(t_hat, torch.Tensor):
        checks.floating(t_hat, "t_hat")
        checks.same_device_dtype(tau=tau, t_hat=t_hat)
        checks.broadcast_batch(tau=tau.shape, t_hat=t_hat.shape)
    else:  # a number: no copy of it to the device
        t_hat = checks.finite_number(t_hat, "t_hat")
    dt = tau - t_hat
    eye = torch.eye(3, dtype=dt.dtype, device=dt.device).expand(*dt.shape, 3, 3)
    z = torch.zeros(*dt.shape, 3, dtype=dt.dtype, device=dt.device)
    return SGal3.from_components(eye, z, z, dt)


def _event_columns(x: torch.Tensor) -> torch.Tensor:
    """The 4 x 10 matrix of eps -> I4^T eps^ x for a homogeneous 5-vector x (..., 5)."""
    hats = blocks.generators(sgal3.hat, 10, x)  # (10, 5, 5)
    return torch.einsum("jab,...b->...aj", hats, x)[..., :4, :]


def fuse_event(prior: ConcentratedGaussian, event: torch.Tensor, event_covariance: torch.Tensor,
               relative_frame: SGal3 | None = None, iterations: int = 1,
               time_row: bool = False, validate: bool = True) -> ConcentratedGaussian:
    """Posterior concentrated Gaussian (right perturbation) after fusing the event
    (..., 4) = (y, tau) with covariance (..., 4, 4) into ``prior`` on SGal3.  ``time_row``:
    also fuse the (uninformative) time row as the paper prints it (see the module doc).

    The prior's covariance must be positive definite: it is inverted.  The singular ones that
    the constructor accepts (rows and columns of exact zeros, directions known exactly, as in an
    IMU increment's covariance with time_noise_density=0) raise ValueError ('the prior's
    covariance is singular'); give those directions a small variance first (``covariance +
    s2 * torch.diag_embed(known)``, ``known`` the zero rows) or integrate with a
    time_noise_density > 0.

    ``event_covariance`` must be symmetric positive semi-definite with a positive definite
    position block (an exact timestamp, variance 0, is allowed; an exact position is not: its
    noise would be singular).  The position noise it implies in the prior mean's frame,
    [I, -v] Sigma [I, -v]^T (v: the mean's velocity), must be positive definite too: a
    position error exactly correlated with the timestamp along v cancels and raises
    ValueError ('... is singular').  ``validate`` checks this as the ConcentratedGaussian
    constructor checks its covariance (skipped on 'meta', under torch.func transforms and
    torch.compile).

    One host sync, at the end: it reads the validation's measures and whether a matrix that
    was inverted (the prior's covariance, the measurement noise, a Gauss-Newton system) was
    singular, and raises ValueError for the first of these that fails (the validation's in the
    order above).  The computation runs before, unchecked (``torch.linalg.*_ex``), whatever
    ``iterations``; with ``validate=False`` the read stays (a singular matrix still raises)."""
    checks.integer(iterations, "iterations", 1)
    checks.boolean(time_row, "time_row")
    checks.boolean(validate, "validate")
    if not isinstance(prior, ConcentratedGaussian):
        raise TypeError(f"prior must be a ConcentratedGaussian on SGal3, got {type(prior).__name__}")
    if not isinstance(prior.mean, SGal3):
        raise TypeError(f"fuse_event needs a prior on SGal3, got {prior.group.__name__}")
    checks.floating(event, "event")
    if event.dim() < 1 or event.shape[-1] != 4:
        raise ValueError(f"event must have shape (..., 4) = (y, tau), got {tuple(event.shape)}")
    checks.matrix(event_covariance, 4, "event_covariance")
    tensors = {"prior": prior.covariance, "event": event, "event_covariance": event_covariance}
    batches = {"prior": prior.batch_shape, "event": event.shape[:-1],
               "event_covariance": event_covariance.shape[:-2]}
    if relative_frame is not None:
        if not isinstance(relative_frame, SGal3):
            raise TypeError(f"relative_frame must be an SGal3 (kF_i = F_k^-1 F_i), got "
                            f"{type(relative_frame).__name__}")
        tensors["relative_frame"] = relative_frame.as_matrix()
        batches["relative_frame"] = relative_frame.batch_shape
    checks.same_device_dtype(**tensors)
    checks.broadcast_batch(**batches)
    # the data checks: measured now, read with the status of the linear algebra at the end
    readable = (event_covariance.numel() > 0 and values_readable(prior.mean.as_matrix())
                and all(values_readable(t) for t in tensors.values()))
    tol = _default_tol(event_covariance, None)
    checked = []
    if validate and readable:
        checked = [(event_covariance, "event_covariance", False),
                   (event_covariance[..., :3, :3],
                    "the position block event_covariance[..., :3, :3]", True)]
    measures = [_covariance_measures(S, definite, tol) for S, _, definite in checked]
    prior = prior.to_side("right")
    F_hat, Q = cast(SGal3, prior.mean), prior.covariance  # an SGal3 mean, checked above
    if relative_frame is None:
        relative_frame = near_inertial_relative_frame(event[..., 3], F_hat.time())
    # d = I4^T F_hat^-1 y_tau (60)
    d = F_hat.inverse().act(event)
    # noise mapping (after (62)): N_mu = I4^T F_hat^-1 I4 - e4 e4^T, N_eta = e4 e10^T
    N_mu = F_hat.inverse().as_matrix()[..., :4, :4].clone()
    N_mu[..., 3, 3] = N_mu[..., 3, 3] - 1.0
    S = N_mu @ event_covariance @ N_mu.transpose(-1, -2)
    rows = 4 if time_row else 3
    if time_row:
        # + Q_99 e4 e4^T, out of place: Q's batch may be larger than S's
        S = S + torch.nn.functional.pad(Q[..., 9:, 9:], (3, 0, 3, 0))
    S_inv, s_status = torch.linalg.inv_ex(_sym(S[..., :rows, :rows]))
    Q_inv, q_status = torch.linalg.inv_ex(_sym(Q))
    singular = [(q_status != 0).any(), (s_status != 0).any()]
    h_status = torch.zeros((), dtype=torch.bool, device=Q.device)
    y0 = torch.zeros(*event.shape[:-1], 5, dtype=event.dtype, device=event.device)
    y0[..., 4].fill_(1.0)  # not = 1.0: unbatched, a blocking copy on CUDA
    x = (relative_frame.as_matrix() @ y0.unsqueeze(-1)).squeeze(-1)  # kF_i y0
    eps = torch.zeros(*event.shape[:-1], 10, dtype=event.dtype, device=event.device)
    for _ in range(iterations):
        Ex = (SGal3.exp(eps).as_matrix() @ x.unsqueeze(-1)).squeeze(-1)
        r = (d - Ex[..., :4])[..., :rows]  # residual at the current eps
        # d/d(delta) I4^T exp(eps + delta) x = C(exp(eps) x) J_l(eps)
        C = (_event_columns(Ex) @ SGal3.jl(eps))[..., :rows, :]
        H = Q_inv + C.transpose(-1, -2) @ S_inv @ C
        g = _mv(C.transpose(-1, -2) @ S_inv, r) - _mv(Q_inv, eps)
        delta, status = torch.linalg.solve_ex(H, g)
        h_status = h_status | (status != 0).any()
        eps = eps + delta
    Ex = (SGal3.exp(eps).as_matrix() @ x.unsqueeze(-1)).squeeze(-1)
    C = (_event_columns(Ex) @ SGal3.jl(eps))[..., :rows, :]
    P, status = torch.linalg.inv_ex(Q_inv + C.transpose(-1, -2) @ S_inv @ C)
    singular.append(h_status | (status != 0).any())
    if readable:  # the one host sync
        values = _read(*measures, *singular)
        for k, (S_k, name, definite) in enumerate(checked):
            _raise_for_measures(values[3 * k: 3 * k + 3], S_k, name, definite, tol)
        for flag, what in zip(values[3 * len(checked):], (
                "the prior's covariance is singular" + KNOWN_DIRECTIONS_HINT,
                "the measurement noise N_mu event_covariance N_mu^T is singular",
                "the information matrix Q^-1 + C^T S^-1 C is singular")):
            if flag:
                raise ValueError(f"fuse_event: {what}")
    J = SGal3.jr(eps)
    return ConcentratedGaussian(F_hat.rplus(eps), _sym(J @ P @ J.transpose(-1, -2)), "right",
                                validate=False)
