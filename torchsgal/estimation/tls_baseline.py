"""The SE_2(3) x R baseline of the total-least-squares problem (kelly-giamou Section 5(c)).

The baseline (``baseline_condition``) is defined in docs/guide/estimation.md: the direct
product of SE_2(3) and the clock, so that a clock error never moves a position.  Two readings
(``BASELINE_READINGS``): "invariant" forms the relative transforms M_n exactly in SGal(3) and reads
them in the product group, so a Galilean change of the global frame does not move the estimate;
"product" composes the observations in the product group, which drops v_g t terms and makes the
estimate depend on the velocity of the global frame.
"""
from __future__ import annotations

import torch

from ..groups import SE23, SGal3
from .tls_problem import TLSProblem, _ad_time_left, _ad_time_right_inverse


def split_clock(F: SGal3) -> tuple[SE23, torch.Tensor]:
    """(SE_2(3) part, clock) of SGal(3) elements: the baseline's view of an observation."""
    C, v, r, tau = F.rotation(), F.velocity(), F.position(), F.time()
    return SE23.from_components(C, v, r), tau


BASELINE_READINGS = ("invariant", "product")


def check_reading(reading: str) -> str:
    """``reading`` if it is one of ``BASELINE_READINGS``, else a ValueError naming it."""
    if not isinstance(reading, str) or reading not in BASELINE_READINGS:
        raise ValueError(f"reading must be one of {BASELINE_READINGS}, got {reading!r}")
    return reading


def baseline_observations(problem: TLSProblem, reading: str = "invariant"
                          ) -> tuple[SE23, torch.Tensor]:
    """(M'_n SE23 (B, N+1), clock difference t_a - t_b (B, N+1)): the observations as the
    baseline sees them.  "invariant": M_n = F~_gb_n^-1 F~_ga_n composed in SGal(3), then split;
    unchanged by a Galilean change of the global frame, F~ <- G F~.  "product": the split
    observations composed in SE_2(3), X~'_gb^-1 X~'_ga, which lacks SGal(3)'s v t terms and so
    depends on the velocities of the global frame."""
    if check_reading(reading) == "invariant":
        return split_clock(problem.M)
    Xa, ta = split_clock(problem.F_ga)
    Xb, tb = split_clock(problem.F_gb)
    return Xb.inverse() @ Xa, ta - tb


def baseline_start(F: SGal3, reading: str = "invariant") -> tuple[SE23, torch.Tensor]:
    """The baseline's (X', tau0) for a relative transform F = (C, v, r, tau) of SGal(3):
    "invariant": X' = (C, v, r - v tau), frame b's origin at frame a's time zero, which makes
    the noise-free M'_n equal to A'_n^-1 (docs/guide/estimation.md); "product": X' = (C, v, r).
    ``solve_baseline`` starts from it with F the first pair's F~_ga0^-1 F~_gb0."""
    C, v, r, tau = F.rotation(), F.velocity(), F.position(), F.time()
    if check_reading(reading) == "invariant":
        r = r - v * tau[..., None]
    return SE23.from_components(C, v, r), tau


def _drift(X: SE23, s: torch.Tensor) -> SE23:
    """A'_n = (C, v, r - s v): the SE_2(3) part of T^n F T^-n, an automorphism of SE_2(3)."""
    C, v, r = X.rotation(), X.velocity(), X.position()
    return SE23.from_components(C, v, r - s[..., None] * v)


def baseline_condition(problem: TLSProblem, reading: str = "invariant"):
    """The SE_2(3) x R estimator's condition function; x = (X' in SE_2(3), tau0 (B, 1),
    dtau (B, 1)); observation residuals per frame (eps' (9), clock error (1)).

    Spatial part (9): log(M'_n exp(eps'_a) A'_n exp(-eps'_b)) in SE_2(3), with M'_n from
    ``baseline_observations`` (``reading``) and A'_n = drift of X' by s = n dtau.
    Clock part (1): t~_a + iota_a + tau0 - t~_b - iota_b.
    As in ``sgal3_condition`` the spatial rows are returned multiplied by J_r(c).
    """
    n = problem.indices
    M, dclock = baseline_observations(problem, reading)  # (B, N+1)
    eye9 = torch.eye(9, dtype=M.dtype, device=M.device)

    def condition(x, e):
        X, tau0, dtau = x
        s = n * dtau  # (B, N+1)
        A = _drift(X.unsqueeze(-1), s)
        # The drift is an automorphism with differential P = I + s ad(e_10) restricted to
        # SE_2(3) (rho <- rho - s nu), so Ad(A^-1) = P Ad(X^-1) P^-1; d/d dtau: rho = -n C^T v.
        Ad_Xinv = X.inverse().adjoint()[:, None]
        Ad_Ainv = _ad_time_right_inverse(_ad_time_left(s, Ad_Xinv), s)
        P = _ad_time_left(s, eye9)
        Cv = (X.rotation().transpose(-1, -2) @ X.velocity()[..., None])[:, None, :, 0]  # (B, 1, 3)
        nCv = -n[:, None] * Cv  # (B, N+1, 3)
        dt_col = torch.cat([nCv, torch.zeros_like(nCv), torch.zeros_like(nCv)], -1)[..., None]
        if e is None:
            c9 = (M @ A).log()
            d_a, d_b = Ad_Ainv, -eye9.expand(c9.shape + (9,))
            ia = ib = 0.0
        else:
            ea, eb = e[..., :9], e[..., 10:19]
            ia, ib = e[..., 9], e[..., 19]
            Eb = SE23.exp(eb)
            c9 = (M @ SE23.exp(ea) @ A @ Eb.inverse()).log()
            left = Eb.adjoint()
            d_a = left @ Ad_Ainv @ SE23.jr(ea)
            d_b = -SE23.jl(eb)
            P, dt_col = left @ P, left @ dt_col
        ct = dclock + ia + tau0 - ib  # (B, N+1)
        c = torch.cat([c9, ct[..., None]], dim=-1)
        Ax = c.new_zeros(c.shape + (11,))  # (B, N+1, 10, 11): [X' (9), tau0, dtau]
        Ax[..., :9, :9] = P
        Ax[..., :9, 10:] = dt_col
        Ax[..., 9, 9] = 1.0
        Bm = c.new_zeros(c.shape + (20,))  # (B, N+1, 10, 20): [eps'_a, iota_a, eps'_b, iota_b]
        Bm[..., :9, :9] = d_a
        Bm[..., 9, 9] = 1.0
        Bm[..., :9, 10:19] = d_b
        Bm[..., 9, 19] = -1.0
        return c, Ax, Bm

    return condition


def baseline_covariance(problem: TLSProblem) -> tuple:
    """The baseline's observation covariance blocks (eps'_a, iota_a), (eps'_b, iota_b): each
    frame's SE_2(3) block and clock variance, their cross terms dropped (independent by
    construction of the product group)."""
    out = []
    for S in (problem.cov_a, problem.cov_b):
        S = S.clone()
        keep = S[..., 9, 9].clone()
        S[..., 9, :] = 0
        S[..., :, 9] = 0
        S[..., 9, 9] = keep
        out.append(S)
    return tuple(out)
