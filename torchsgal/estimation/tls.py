"""The total-least-squares problem of kelly-giamou Section 5, batched.

Two inertial frames a and b are observed at N + 1 sample indices n = 0..N.  The unknowns are
the initial relative transform F = F_a0b0 in SGal(3) and the sampling interval dtau.  Inertial
motion, (5.2)-(5.4): F_{a_n a_0} = F_{b_n b_0} = T^n with T = F_dtau the pure time translation,
so that

    F_gb_n = F_ga_n A_n,   A_n = T^n F T^-n.                                          (5.4)

With the paper's (5.2), sample n + 1 later than sample n means dtau < 0 (the origin of a_0 is
at a_1-time dtau); ``simulate`` uses dtau = -1 s for 1 s sampling.

Observations F~ with right-perturbation noise, (5.5): F = F~ exp(eps), eps ~ N(0, Sigma).
Our condition function, one per n (the paper's (5.12) up to the side its exp(eps_b) is on):

    c_n(x, eps_a, eps_b) = log(M_n exp(eps_a) A_n exp(-eps_b)),   M_n = F~_gb_n^-1 F~_ga_n.

Its Jacobians (derived in docs/guide/estimation.md, checked against autograd in the tests), with
E = exp(c), right perturbations F <- F exp(d), dtau <- dtau + d:

    dc/deps_a = J_r(c)^-1 Ad(exp(eps_b)) Ad(A_n^-1) J_r(eps_a)
    dc/deps_b = -J_r(c)^-1 J_l(eps_b)
    dc/dF     = J_r(c)^-1 Ad(exp(eps_b)) Ad(T^n)                                    (5.22)
    dc/ddtau  = J_r(c)^-1 Ad(exp(eps_b)) n (Ad(T^n F^-1) - I) e_10                 (5.21)

At eps = 0 these are (5.19)-(5.22) with the paper's sign of eps.

The SE_2(3) x R baseline (``baseline_condition``) is defined in docs/guide/estimation.md: the direct
product of SE_2(3) and the clock, so that a clock error never moves a position.  Two readings
(``BASELINE_READINGS``): "invariant" forms the relative transforms M_n exactly in SGal(3) and reads
them in the product group, so a Galilean change of the global frame does not move the estimate;
"product" composes the observations in the product group, which drops v_g t terms and makes the
estimate depend on the velocity of the global frame.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from ..functional import checks, native
from ..groups import SE23, LieGroup, SGal3
from . import _small_linalg
from . import variables as V
from .gauss_helmert import _CovarianceBlocks, check_covariance, gauss_helmert, variant_options
from .solver import ACTIVE_SET, Linearisation, Solution, SolverReport, SolverStatus, iterate

E10 = 9  # index of iota, the time component of the SGal(3) tangent


def _check_frames(F_ga, F_gb, group=SGal3):
    for name, F in (("F_ga", F_ga), ("F_gb", F_gb)):
        if not isinstance(F, group):
            raise TypeError(f"{name} must be {group.__name__} of batch shape (B, N+1), got "
                            f"{type(F).__name__}")
        if len(F.batch_shape) != 2:
            raise ValueError(f"{name} must have batch shape (B, N+1), got {tuple(F.batch_shape)}")


def _check_observations(F_ga, F_gb, cov_a, cov_b, indices, group=SGal3):
    _check_frames(F_ga, F_gb, group)
    if F_ga.batch_shape != F_gb.batch_shape:
        raise ValueError(f"F_ga and F_gb must have the same batch shape, got "
                         f"{tuple(F_ga.batch_shape)} and {tuple(F_gb.batch_shape)}")
    Bn, N1 = F_ga.batch_shape
    if N1 < 2:
        # One pair gives 10 conditions for 11 unknowns: dtau enters A_n only as r - n dtau v,
        # confounded with r.  Two pairs at distinct indices n, m separate it through the drift
        # (m - n) dtau v (observable when the relative velocity v is not zero; repeated
        # indices or v = 0 leave it unobservable, reported SINGULAR by the solvers).
        raise ValueError(f"need at least 2 observation pairs (11 unknowns, 10 conditions per "
                         f"pair; dtau is seen through the drift between two distinct sample "
                         f"indices), got {N1}")
    for name, S in (("cov_a", cov_a), ("cov_b", cov_b)):
        check_covariance(S, 10, name)
        checks.same_device_dtype(F_ga=F_ga.as_matrix(), **{name: S})
        if S.dim() > 4 or any(s not in (1, t) for s, t in zip(S.shape[:-2][::-1], (N1, Bn))):
            raise ValueError(f"{name} must broadcast to (B, N+1, 10, 10) = ({Bn}, {N1}, 10, 10), "
                             f"got {tuple(S.shape)}")
    if indices.device != F_ga.device:
        raise ValueError(f"indices is on {indices.device} but F_ga is on {F_ga.device}; move "
                         f"them to one device")
    if indices.shape != (N1,):
        raise ValueError(f"indices must have shape (N+1,) = ({N1},), got {tuple(indices.shape)}")
    return Bn, N1


@dataclass
class TLSProblem:
    """Paired observations of frames a and b: F_ga, F_gb SGal3 of batch shape (B, N+1);
    covariances of their right-perturbation noise (B or 1, N+1 or 1, 10, 10); sample indices
    n (N+1,) (default 0..N)."""

    F_ga: SGal3
    F_gb: SGal3
    cov_a: torch.Tensor
    cov_b: torch.Tensor
    indices: torch.Tensor | None = None

    def __post_init__(self):
        _check_frames(self.F_ga, self.F_gb)
        checks.same_device_dtype(F_ga=self.F_ga.as_matrix(), F_gb=self.F_gb.as_matrix())
        if self.indices is None:
            self.indices = torch.arange(self.F_ga.batch_shape[-1], dtype=self.F_ga.dtype,
                                        device=self.F_ga.device)
        elif isinstance(self.indices, (list, tuple)):
            self.indices = checks.numbers_as_tensor(self.indices, "indices", self.F_ga.dtype,
                                                    self.F_ga.device)
        elif not isinstance(self.indices, torch.Tensor):
            raise TypeError(f"indices must be a tensor (N+1,) (or a list), got "
                            f"{type(self.indices).__name__}")
        elif self.indices.device != self.F_ga.device:
            raise ValueError(f"indices is on {self.indices.device} but F_ga is on "
                             f"{self.F_ga.device}; move them to one device")
        self.indices = self.indices.to(self.F_ga.dtype)
        _check_observations(self.F_ga, self.F_gb, self.cov_a, self.cov_b, self.indices)
        self.M = self.F_gb.inverse() @ self.F_ga  # (B, N+1)
        self.covariance = (self.cov_a, self.cov_b)  # block-diagonal over (eps_a, eps_b)

    @property
    def batch_size(self) -> int:
        return self.F_ga.batch_shape[0]

    def initial_guess(self, dtau: torch.Tensor | float, name: str = "dtau") -> tuple:
        """F from the first pair (F~_ga0^-1 F~_gb0) and the given dtau (B,) or scalar."""
        if isinstance(dtau, torch.Tensor) and dtau.device != self.F_ga.device:
            raise ValueError(f"{name} is on {dtau.device} but the problem is on "
                             f"{self.F_ga.device}; move them to one device")
        F0 = self.F_ga[:, 0].inverse() @ self.F_gb[:, 0]
        dt = checks.numbers_as_tensor(dtau, name, self.F_ga.dtype, self.F_ga.device)
        if dt.dim() > 1 or (dt.dim() == 1 and dt.shape[0] != self.batch_size):
            raise ValueError(f"{name} must be a scalar or have shape (B,) = ({self.batch_size},), "
                             f"got {tuple(dt.shape)}")
        return F0, dt.expand(self.batch_size).reshape(-1, 1).clone()


def _ad_time_left(s: torch.Tensor, M: torch.Tensor) -> torch.Tensor:
    """Ad(T^s) M = (I + s ad(e_10)) M: the rho rows minus s times the nu rows (ad(e_10)^2 = 0)."""
    shape = torch.broadcast_shapes(s.shape + (1, 1), M.shape)
    out = M.expand(shape).clone()
    out[..., 0:3, :] -= s[..., None, None] * M[..., 3:6, :]
    return out


def _ad_time_right_inverse(M: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """M Ad(T^-s) = M (I - s ad(e_10)): the nu columns plus s times the rho columns."""
    shape = torch.broadcast_shapes(s.shape + (1, 1), M.shape)
    out = M.expand(shape).clone()
    out[..., :, 3:6] += s[..., None, None] * M[..., :, 0:3]
    return out


def _drift_sgal3(F: SGal3, s: torch.Tensor) -> SGal3:
    """A_n = T^n F T^-n = (C, v, r - s v, tau) for s = n dtau."""
    v = F.velocity()
    return SGal3.from_components(F.rotation(), v, F.position() - s[..., None] * v, F.time())


def sgal3_condition(problem: TLSProblem):
    """The condition function (x, e) -> (c, A, Bm) of the SGal(3) estimator; x = (F, dtau).

    Returns the linearisation multiplied on the left by J_r(c): the Gauss-Helmert solution is
    unchanged by an invertible factor per condition, J_r(c) c = c, and the factor removes the
    J_r(c)^-1 of every Jacobian.  So A = [Ad(exp(eps_b)) Ad(T^n), Ad(exp(eps_b)) n (Ad(T^n F^-1)
    - I) e_10] and Bm = [Ad(exp(eps_b)) Ad(A_n^-1) J_r(eps_a), -J_l(eps_b)], with
    Ad(A_n^-1) = Ad(T^n) Ad(F^-1) Ad(T^-n) and Ad(T^n) = I + n dtau ad(e_10).
    """
    n = problem.indices
    M = problem.M
    eye = torch.eye(10, dtype=M.dtype, device=M.device)
    e10 = eye[E10]

    def condition(x, e):
        F, dtau = x
        s = n * dtau  # (B, N+1)
        Ad_Finv = F.inverse().adjoint()[:, None]  # (B, 1, 10, 10)
        A = _drift_sgal3(F.unsqueeze(-1), s)
        Ad_Ainv = _ad_time_right_inverse(_ad_time_left(s, Ad_Finv), s)
        d_F = _ad_time_left(s, eye)
        d_t = n[:, None, None] * (_ad_time_left(s, Ad_Finv[..., E10:E10 + 1]) - e10[:, None])
        if e is None:
            c = (M @ A).log()
            d_a, d_b = Ad_Ainv, -eye.expand(c.shape + (10,))
        else:
            ea, eb = e[..., :10], e[..., 10:]
            Eb = SGal3.exp(eb)
            c = (M @ SGal3.exp(ea) @ A @ Eb.inverse()).log()
            left = Eb.adjoint()
            d_a = left @ Ad_Ainv @ SGal3.jr(ea)
            d_b = -SGal3.jl(eb)
            # left Ad(T^n) = left (I + s ad(e_10)): elementwise instead of a product.
            d_F = _ad_time_right_inverse(left, -s)
            d_t = (left * d_t.transpose(-1, -2)).sum(-1, keepdim=True)
        Ax = c.new_empty(c.shape + (11,))  # (B, N+1, 10, 11)
        Ax[..., :10] = d_F
        Ax[..., 10:] = d_t
        Bm = c.new_empty(c.shape + (20,))  # (B, N+1, 10, 20)
        Bm[..., :10] = d_a
        Bm[..., 10:] = d_b
        return c, Ax, Bm

    return condition


# ------------------------------------------------------------------------ SE_2(3) x R baseline
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


def _whiten(G: torch.Tensor, factor: torch.Tensor, diagonal: bool) -> torch.Tensor:
    """G R for the covariance factor R (a square-root diagonal or a Cholesky factor)."""
    return G * factor[..., None, :] if diagonal else G @ factor


def _shared_over_samples(S: torch.Tensor) -> torch.Tensor | None:
    """A covariance (B or 1, N+1 or 1, d, d) that is the same for every sample, as
    (B or 1, d, d); None when it varies with the sample."""
    if S.dim() >= 3 and S.shape[-3] != 1:
        return None
    return S.reshape((-1,) + S.shape[-2:])


class _ChunkState:
    """Per-condition solver state kept in chunks of trials (``slices``), so that no tensor
    spans the whole batch: large temporaries cost page faults on every allocation.  ``active``:
    the trials this state was computed for (None: all); the others' rows are stale, and they
    are never used again (solver.iterate: a problem that stopped running does not restart)."""

    def __init__(self, slices, parts, active=None):
        self.slices, self.parts, self.active = slices, parts, active

    def select(self, mask, other):
        """This state where ``mask``, else ``other``, written into this state's buffers (only
        for the trials it was computed for: the rest are not used)."""
        keep = ~mask if self.active is None else ~mask & self.active
        for sl, new, old in zip(self.slices, self.parts, other.parts):
            if new[0].device.type == "cpu":  # copy the kept rows only (no sync on the CPU)
                idx = keep[sl].nonzero()[:, 0]
                if idx.numel():
                    for a, b in zip(new, old):
                        a.index_copy_(0, idx, b.index_select(0, idx))
                continue
            for a, b in zip(new, old):
                torch.where(keep[sl].reshape((-1,) + (1,) * (a.dim() - 1)), b, a, out=a)
        return self


class _Model:
    """What the structured solver needs of an estimator: the group of its spatial part and
    its compositions M_n, the spatial covariance blocks, and (baseline) the clock row."""

    def __init__(self, problem: TLSProblem, baseline: bool, reading: str = "invariant"):
        self.baseline = baseline
        self.group: type[LieGroup]
        if baseline:
            self.group, self.d = SE23, 9
            self.M, self.dclock = baseline_observations(problem, reading)
            ca, cb = baseline_covariance(problem)
            self.var = (ca[..., 9, 9], cb[..., 9, 9])  # clock variances (B or 1, N+1 or 1)
            self.cov = (ca[..., :9, :9], cb[..., :9, :9])
        else:
            self.group, self.d, self.M, self.cov = SGal3, 10, problem.M, problem.covariance

    def unknowns(self, x):
        """(spatial element X, tau0 (K, 1) or None, dtau (K, 1))."""
        return (x[0], x[1], x[2]) if self.baseline else (x[0], None, x[1])

    def drift(self, X, s):
        return _drift(X, s) if self.baseline else _drift_sgal3(X, s)

    def dtau_direction(self, X, Ad_Xinv):
        """a with dA'/ddtau = n a: Ad(F^-1) e_10 - e_10 (SGal(3)); [-C^T v, 0, 0] (SE_2(3))."""
        if self.baseline:
            Ctv = (X.rotation().transpose(-1, -2) @ X.velocity()[..., None])[..., 0]
            return torch.cat([-Ctv, torch.zeros_like(Ctv), torch.zeros_like(Ctv)], -1)
        a = Ad_Xinv[..., E10].clone()
        a[..., E10] -= 1.0
        return a


def _structured(problem: TLSProblem, iterated: bool, baseline: bool = False,
                chunk: int | None = None, reading: str = "invariant"):
    """(linearise, post_step) for ``solver.iterate``: the Gauss-Helmert reduction of
    ``sgal3_condition`` (or of ``baseline_condition`` in its ``reading``) with its normal
    equations summed in closed form; the same solution, up to rounding.

    The (spatial) conditions are multiplied by K = Ad(T^-n) Ad(exp(eb))^-1 J_r(c) instead of
    J_r(c) (the solution does not change, see ``gauss_helmert``).  With J_l(x) = Ad(exp(x))
    J_r(x) and Ad(A_n^-1) = Ad(T^n) Ad(F^-1) Ad(T^-n):

        c' = Ad(T^-n) log(exp(-eb) M_n exp(ea) A_n)     (= K c, a conjugation)
        A' = [I, n a]                                   (a: ``_Model.dtau_direction``)
        Bm' = [Ga, Gb] = [Ad(F^-1) Ad(T^-n) J_r(ea), -Ad(T^-n) J_r(eb)].

    With S = Bm' Sigma Bm'^T = L L^T and Li = L^-1, the whitened rows of condition n are
    [Li, n Li a, Li w] (w = c' - Bm' e); one product per trial of their stack gives
    H = J^T J, g = J^T r and |r|^2 (5.24).  Li comes from ``_small_linalg`` (vectorised over
    the conditions).  At e = 0 (the paper variant) with covariances shared by the samples,
    Ad(T^-n) = I + s N (s = n dtau, N: rho <- nu) makes S a quadratic in s with per-trial
    coefficients.  The baseline's clock rows (scalar, independent) are appended as they are.
    The trials are processed ``chunk`` at a time (default: about 8000 conditions on the CPU,
    the whole batch elsewhere) with reused buffers: on the CPU, fresh temporaries that span the
    whole batch cost more in page faults than in arithmetic.  The
    per-condition state of a linearisation lives in one of two buffer sets, used in turn, so
    it stays valid until the next-but-one call (``solver.iterate`` keeps the current and the
    new linearisation only, and ``_ChunkState.select`` writes into the newer one).  For SGal(3)
    in float64 on the CPU, unobserved, the optional C kernel (``native.kernels("tls")``,
    functional/_native_tls.h) computes a chunk's rows, W (packed) and normal equations instead."""
    model = _Model(problem, baseline, reading)
    G_, d, M = model.group, model.d, model.M
    n = problem.indices
    Bn, N1 = M.batch_shape
    if chunk is None:  # chunks on the CPU only: elsewhere each would be more kernel launches
        cpu = M.as_matrix().device.type == "cpu"
        chunk = max(1, (KERNEL_CHUNK if _kernel_applies(problem, baseline) else 8192) // N1) if cpu else Bn
    slices = [slice(i, min(i + chunk, Bn)) for i in range(0, Bn, chunk)]
    cov = _CovarianceBlocks(model.cov)
    (fa, fb), (da, db) = cov.factors, cov.diagonal
    shared = [_shared_over_samples(S) for S in model.cov]
    quadratic = not iterated and shared[0] is not None and shared[1] is not None
    minus_eye = -torch.eye(d, dtype=M.dtype, device=M.device)
    nc = d + 3 if baseline else d + 2  # columns: [X, (tau0), dtau, rhs]
    eb0 = 10  # eps_b starts at 10 in both layouts (the baseline's clock errors at 9 and 19)
    work = {}
    calls = [0]  # linearisations so far: the state buffer set is calls % 2
    kernel = None if baseline else native.kernels("tls")  # None: not compiled

    def buffer(name, *shape, state=None):
        """A buffer reused between chunks and calls (one per name and shape), or for what
        the linearisation keeps, one per chunk ``state`` and buffer set."""
        key = (name, None if state is None else (state, calls[0] % 2)) + shape
        if key not in work:
            work[key] = torch.empty(shape, dtype=M.dtype, device=M.device)
        return work[key]

    def per_trial(f, nd, sl):
        """The chunk's rows of a tensor whose leading dimension (of ``nd``) is the trial."""
        return f[sl] if f.dim() == nd and f.shape[0] > 1 else f

    def rows(Li_t, a, w, K, R):
        """[Li, (0), n Li a, Li w] of every condition into R[:, :(N+1) d] (K, rows, nc)."""
        m = K * N1
        rhs_t = torch.stack([a.T[:, :, None].expand(d, K, N1).reshape(d, -1),
                             w.reshape(-1, d).T], 1)  # (d, 2, K (N+1))
        prod = torch.mul(Li_t[:, :, None], rhs_t, out=buffer("prod", d, d, 2, m))
        u_t = prod.sum(1)
        u_t[:, 0] *= n.repeat(K)
        Rs = R[:, :N1 * d].unflatten(1, (N1, d))  # a view: (K, N+1, d, nc)
        Rs[..., :d] = Li_t.permute(2, 0, 1).unflatten(0, (K, N1))
        Rs[..., nc - 2:] = u_t.permute(2, 0, 1).unflatten(0, (K, N1))
        if baseline:
            Rs[..., d] = 0.0

    def clock_rows(tau0, sl, R):
        """The baseline's clock conditions c = t~_a + iota_a + tau0 - t~_b - iota_b, linear in
        e (w = c - Bm e = t~_a - t~_b + tau0), whitened by their standard deviation: rows
        [0, 1, 0, w] / sd into R[:, (N+1) d:] (K, N+1, nc)."""
        va, vb = (per_trial(v, 2, sl) for v in model.var)
        ct = model.dclock[sl] + tau0
        sd = (va + vb).sqrt().expand(ct.shape)
        Rc = R[:, N1 * d:]
        Rc.zero_()
        Rc[..., d] = sd.reciprocal()
        Rc[..., nc - 1] = ct / sd

    def part(x, e, sl, active):
        X, tau0, dtau = model.unknowns(tuple(b[sl] for b in x))
        Mk = M[sl]
        K = Mk.batch_shape[0]
        m = K * N1
        s = n * dtau  # (K, N+1)
        Ad_Xinv = X.inverse().adjoint()  # (K, d, d)
        a = model.dtau_direction(X, Ad_Xinv)  # (K, d)
        if kernel is not None:  # the optional C kernel: the same rows, packed (native.py)
            shape_R, shape_W = kernel.shapes(K, N1, da, db)
            R = buffer("R packed", *shape_R, state=sl.start)
            W = buffer("W packed", *shape_W, state=sl.start)
            factors = ((per_trial(fa, 3 if da else 4, sl), da), (per_trial(fb, 3 if db else 4, sl), db))
            done = kernel.linearise(Mk.as_matrix(), X.as_matrix(), Ad_Xinv, a, s, n, e, factors, R, W,
                                    None if active is None else active[sl])
            if done is not None:
                G, info = done
                bad = (info != 0).any(-1)
                G[:, -1, -1] = torch.where(bad, float("nan"), G[:, -1, -1])
                return G, (R, W)
        A = model.drift(X.unsqueeze(-1), s)
        if e is None:
            c = (Mk @ A).log()
        else:
            ea, eb = e[..., :d], e[..., eb0:eb0 + d]
            E = G_.exp(torch.stack([ea, -eb]))
            c = (E[1] @ Mk @ E[0] @ A).log()
        c = c.clone()
        c[..., 0:3] += s[..., None] * c[..., 3:6]  # Ad(T^-n) c
        if quadratic:
            # S = Ad(X^-1) P Sa P^T Ad(X^-1)^T + P Sb P^T with P = I + s N:
            # S0 + s S1 + s^2 S2, where V = Ad(X^-1) N holds Ad(X^-1)[:, 0:3] in columns 3:6.
            Sa, Sb = (per_trial(S, 3, sl) for S in shared)
            V = torch.zeros_like(Ad_Xinv)
            V[..., 3:6] = Ad_Xinv[..., 0:3]
            Z = V @ Sa @ Ad_Xinv.transpose(-1, -2)
            NSb = Z.new_zeros(Z.shape)
            NSb[..., 0:3, :] = Sb[..., 3:6, :]
            S0 = Ad_Xinv @ Sa @ Ad_Xinv.transpose(-1, -2) + Sb
            S1 = Z + Z.transpose(-1, -2) + NSb + NSb.transpose(-1, -2)
            S2 = V @ Sa @ V.transpose(-1, -2)
            S2[..., 0:3, 0:3] += Sb[..., 3:6, 3:6]
            coef = torch.stack([S0, S1, S2], -1).permute(1, 2, 0, 3).reshape(d, d, K, 1, 3)
            S_t = torch.addcmul(coef[..., 1], s, coef[..., 2], out=buffer("S2", d, d, K, N1))
            S_t = torch.addcmul(coef[..., 0], s, S_t, out=buffer("S_t", d, d, K, N1))
            S_t = S_t.reshape(d, d, m)
        else:
            Bm = buffer("Bm", K, N1, d, 2 * d)
            Ga, Gb = Bm[..., :d], Bm[..., d:]
            if e is None:
                Ga.copy_(_ad_time_right_inverse(Ad_Xinv[:, None], s))
                Gb.copy_(_ad_time_left(-s, minus_eye))
            else:
                Jr = G_.jr(torch.stack([ea, eb]))  # (2, K, N+1, d, d), a fresh tensor
                Jr[..., 0:3, :] += s[..., None, None] * Jr[..., 3:6, :]  # Ad(T^-n) J_r
                Ga.copy_(Ad_Xinv[:, None] @ Jr[0])
                torch.neg(Jr[1], out=Gb)
            if e is not None:
                c -= (Bm @ torch.cat([ea, eb], -1)[..., None])[..., 0]
            W = buffer("W", K, N1, d, 2 * d, state=sl.start)
            if cov.all_diagonal:
                torch.mul(Bm, per_trial(cov.sqrt_diag, 3, sl)[..., None, :], out=W)
            else:
                torch.cat([_whiten(Ga, per_trial(fa, 3 if da else 4, sl), da),
                           _whiten(Gb, per_trial(fb, 3 if db else 4, sl), db)], -1, out=W)
            S = torch.bmm(W.reshape(m, d, 2 * d), W.reshape(m, d, 2 * d).transpose(-1, -2),
                          out=buffer("S", m, d, d))
            S_t = buffer("S_t", d, d, m)
            S_t.copy_(S.permute(1, 2, 0))
        Li_t, info = _small_linalg.inverse_cholesky_factor_t(
            S_t, (buffer("L", d, d, m), buffer("Li", d, d, m)))
        R = buffer("R", K, N1 * (d + 1) if baseline else N1 * d, nc, state=sl.start)
        rows(Li_t, a, c, K, R)
        if baseline:
            clock_rows(tau0, sl, R)
        G = R.transpose(-1, -2) @ R
        # A non-positive-definite S gives a non-finite factor; mark its trial explicitly.
        bad = (info != 0).reshape(K, N1).any(-1)
        G[:, -1, -1] = torch.where(bad, float("nan"), G[:, -1, -1])
        return G, (R, Ad_Xinv, s) if quadratic else (R, W)

    def linearise(x, e, active=None):
        e = e if iterated else None
        calls[0] += 1
        Gs, parts = [], []
        for sl in slices:
            G, p = part(x, None if e is None else e[sl], sl, active)
            Gs.append(G)
            parts.append(p)
        G = torch.cat(Gs)
        return Linearisation(None, None, extra=_ChunkState(slices, parts, active), H=G[:, :-1, :-1],
                             g=G[:, :-1, -1], cost=0.5 * G[:, -1, -1])

    def post_step(x, e, lin, delta, active=None):
        # e = -Sigma Bm'^T S^-1 (w + A' delta) = -Sigma Bm'^T Li^T (Li w + Li A' delta).
        out, e_all = [], None  # e_all: the kernel's updates, written in place (no cat)
        d1 = torch.cat([delta, torch.ones_like(delta[:, :1])], -1)[..., None]
        for sl, (R, *extra) in zip(lin.extra.slices, lin.extra.parts):
            K = R.shape[0]
            if R.dim() == 4:  # packed by the C kernel: the same update in C, or unpacked
                factors = ((per_trial(fa, 3 if da else 4, sl), da), (per_trial(fb, 3 if db else 4, sl), db))
                if e_all is None:
                    e_all = torch.empty(Bn, N1, 2 * d, dtype=M.dtype)
                e_new = kernel.step(R, extra[0], delta[sl], factors, N1,
                                    None if active is None else active[sl], out=e_all[sl])
                if e_new is not None:
                    out.append(e_new)
                    continue
                R, *extra = kernel.unpack(R, extra[0], N1, da, db)
            z = R @ d1[sl]  # (K, rows, 1)
            y = (R[:, :N1 * d, :d].reshape(K, N1, d, d) * z[:, :N1 * d].reshape(K, N1, d, 1)
                 ).sum(-2)  # Li^T z
            if len(extra) == 2:  # the quadratic form's parts (Ad_Xinv, s)
                # Ga^T y = P^T Ad(X^-1)^T y, Gb^T y = -P^T y, P^T: nu <- nu + s rho.
                Ad_Xinv, s = extra
                u = torch.stack([y @ Ad_Xinv, -y])  # (2, K, N+1, d)
                u[..., 3:6] += s[..., None] * u[..., 0:3]
                ea, eb = (u[i] @ per_trial(S, 3, sl) for i, S in enumerate(shared))
            else:
                W, = extra
                Wy = (y[..., None, :] @ W)[..., 0, :]  # (K, N+1, 2 d): W^T y, no (K, N+1, d, 2 d) temporary
                ea, eb = Wy[..., :d], Wy[..., d:]
                ra, rb = per_trial(fa, 3 if da else 4, sl), per_trial(fb, 3 if db else 4, sl)
                ea = ea * ra if da else (ra @ ea[..., None])[..., 0]
                eb = eb * rb if db else (rb @ eb[..., None])[..., 0]
            if baseline:
                # Clock rows: y_t = z_t / sd, Bm^T y_t = (y_t, -y_t) on (iota_a, iota_b).
                va, vb = (per_trial(v, 2, sl) for v in model.var)
                yt = z[:, N1 * d:, 0] * R[:, N1 * d:, d]
                ea = torch.cat([ea, (va * yt)[..., None]], -1)
                eb = torch.cat([eb, (-vb * yt)[..., None]], -1)
            out.append(-torch.cat([ea, eb], -1))
        if e_all is not None and all(o.data_ptr() == e_all[sl].data_ptr() for o, sl in zip(out, lin.extra.slices)):
            return e_all
        return torch.cat(out)

    # The C kernel skips the trials that are not running (solver.iterate drops their results).
    setattr(linearise, ACTIVE_SET, kernel is not None)
    return linearise, post_step


# Below this many conditions the paper variant takes the generic path: the structured one
# saves arithmetic but costs a few more (overhead-bound) operations (a rule on shapes only).
# Where the C kernel of the SGal(3) linearisation runs, the structured path is the faster one at
# every size (one trial of 101 conditions: 13.5 ms against 22 ms generic) and is taken.
STRUCTURED_MIN_CONDITIONS = 2048


# Conditions per chunk where the C kernel runs: it has no temporaries, and its per-condition
# state (about 1.5 kB) for 65,536 conditions is 100 MB per buffer set.
KERNEL_CHUNK = 65536


def _kernel_applies(problem: TLSProblem, baseline: bool) -> bool:
    kernel = None if baseline else native.kernels("tls")
    return kernel is not None and kernel.applies(problem.M.as_matrix(), *problem.covariance)


def _gauss_helmert_tls(problem: TLSProblem, x0, variant: str, e0=None,
                       baseline: bool = False, reading: str = "invariant", **options) -> Solution:
    """``gauss_helmert`` with ``sgal3_condition`` (or ``baseline_condition`` in its ``reading``
    and ``baseline_covariance``), through ``_structured`` unless the batch is small (paper)."""
    if (variant == "paper" and problem.M.batch_shape.numel() < STRUCTURED_MIN_CONDITIONS
            and not _kernel_applies(problem, baseline)):
        if baseline:
            return gauss_helmert(baseline_condition(problem, reading), x0,
                                 baseline_covariance(problem), variant=variant, e0=e0, **options)
        return gauss_helmert(sgal3_condition(problem), x0, problem.covariance, variant=variant,
                             e0=e0, **options)
    iterated = variant_options(variant, options)
    linearise, post_step = _structured(problem, iterated, baseline, reading=reading)
    return iterate(linearise, V.check_values(x0), e0, post_step, **options)


# ------------------------------------------------------------------------------------ solvers
def subset(problem: TLSProblem, index) -> TLSProblem:
    """The trials ``index`` (a slice or index tensor) of a problem."""
    def pick(S):
        return S[index] if S.dim() == 4 and S.shape[0] > 1 else S
    return TLSProblem(problem.F_ga[index], problem.F_gb[index], pick(problem.cov_a),
                      pick(problem.cov_b), indices=problem.indices)


def _check_unknowns(problem: TLSProblem, x0, baseline: bool, name: str = "x0") -> tuple:
    """x0 of ``solve_sgal3`` (F SGal3 (B,), dtau (B, 1)) or of ``solve_baseline``
    (X' SE23 (B,), tau0 (B, 1), dtau (B, 1)), on the problem's dtype and device."""
    layout: tuple[type[LieGroup] | int, ...]  # a group block of that class, or a tensor (B, k)
    if baseline:
        layout, expected = (SE23, 1, 1), "(X' SE23 (B,), tau0 (B, 1), dtau (B, 1))"
    else:
        layout, expected = (SGal3, 1), "(F SGal3 (B,), dtau (B, 1))"
    if not isinstance(x0, (tuple, list)):
        raise TypeError(f"{name} must be a tuple {expected}, got {type(x0).__name__}")
    if len(x0) != len(layout):
        raise ValueError(f"{name} must be a tuple {expected}, got {len(x0)} block(s)")
    x0 = V.check_values(x0, name)
    Bn = problem.batch_size
    for i, (b, kind) in enumerate(zip(x0, layout)):
        if isinstance(kind, type) and issubclass(kind, LieGroup):  # a group block, else (B, kind)
            if not isinstance(b, kind) or tuple(b.batch_shape) != (Bn,):
                got = (f"{type(b).__name__} of batch shape {tuple(b.batch_shape)}"
                       if isinstance(b, LieGroup) else f"a tensor of shape {tuple(b.shape)}")
                raise ValueError(f"{name}[{i}] must be {kind.__name__} of batch shape (B,) = "
                                 f"({Bn},) ({name} = {expected}), got {got}")
        elif not isinstance(b, torch.Tensor) or tuple(b.shape) != (Bn, kind):
            got = (f"a tensor of shape {tuple(b.shape)}" if isinstance(b, torch.Tensor)
                   else type(b).__name__)
            raise ValueError(f"{name}[{i}] must be a tensor of shape (B, 1) = ({Bn}, 1) "
                             f"({name} = {expected}), got {got}")
    ref = x0[0].as_matrix()
    checks.same_device_dtype(problem=problem.F_ga.as_matrix(), **{name: ref})
    return x0


def _empty_solution(problem: TLSProblem, x0: tuple) -> Solution:
    """The solution of a problem without trials (B = 0): x0 itself, empty report."""
    like = problem.F_ga.as_matrix()
    empty = like.new_zeros(0)
    status = torch.zeros(0, dtype=torch.int64, device=like.device)
    report = SolverReport(status=status, iterations=status.clone(), initial_cost=empty,
                          cost=empty.clone(), step_norm=empty.clone(),
                          gradient_norm=empty.clone())
    return Solution(x=x0, covariance=like.new_zeros(0, 11, 11), report=report,
                    aux=like.new_zeros(0, problem.F_ga.batch_shape[1], 20))


def _in_rounds(solve, problem, x0, options) -> Solution:
    """Gauss-Helmert with the stragglers compacted: once at most ``straggler_fraction``
    (default 5%) of the trials are still running, they are solved again on their own, from
    where they stopped, so the whole batch does not iterate for its slowest members."""
    if "stop_below_fraction" in options:
        raise TypeError("stop_below_fraction is set by the TLS solvers; give straggler_fraction "
                        "(the running fraction below which the stragglers are solved on their own)")
    fraction = checks.finite_number(options.pop("straggler_fraction", 0.05), "straggler_fraction",
                                    "in [0, 1]")
    if problem.batch_size == 0:
        return _empty_solution(problem, x0)
    max_it = options.pop("max_iterations", 50)
    # The solvers are not differentiable (solver.iterate): data that require gradients would
    # only make the structured solver's out= buffers refuse them.
    with torch.no_grad():
        return _rounds(solve, problem, x0, options, max_it, fraction)


def _rounds(solve, problem, x0, options, max_it, fraction) -> Solution:
    sol = solve(problem, x0, None, max_iterations=max_it, stop_below_fraction=fraction, **options)
    first = int(sol.report.iterations.max())
    pending = sol.report.status == SolverStatus.MAX_ITERATIONS
    if max_it <= first or not bool(pending.any()):
        return sol
    idx = pending.nonzero()[:, 0]
    sub = subset(problem, idx)
    x_sub = tuple(b[idx] for b in sol.x)
    rest = solve(sub, x_sub, None if sol.aux is None else sol.aux[idx],
                 max_iterations=max_it - first, **options)
    x = []
    for full, part in zip(sol.x, rest.x):
        if isinstance(full, torch.Tensor):
            x.append(full.index_copy(0, idx, part))
        else:
            x.append(type(full).from_matrix(full.as_matrix().index_copy(0, idx, part.as_matrix())))
    report = sol.report
    fields = {}
    for name in ("status", "initial_cost", "cost", "step_norm", "gradient_norm"):
        t = getattr(report, name)
        fields[name] = t if name == "initial_cost" else t.index_copy(0, idx, getattr(rest.report, name))
    fields["iterations"] = report.iterations.index_add(0, idx, rest.report.iterations)
    return Solution(x=tuple(x), covariance=sol.covariance.index_copy(0, idx, rest.covariance),
                    report=SolverReport(**fields),
                    aux=rest.aux if sol.aux is None else sol.aux.index_copy(0, idx, rest.aux))


def solve_sgal3(problem: TLSProblem, x0=None, dtau0=-1.0, variant: str = "iterated",
                **options) -> Solution:
    """Estimates (F_a0b0, dtau) on SGal(3); covariance (B, 11, 11) over [dxi (10), ddtau].
    x0: (F SGal3 (B,), dtau (B, 1)); by default F from the first pair and ``dtau0`` (a scalar
    or (B,)).  options: see ``gauss_helmert`` and ``solver.iterate``; ``straggler_fraction``
    (0.05): the running fraction below which the stragglers are finished in a batch of their
    own.  A problem without trials (B = 0) gives an empty solution.

    Use float64.  The information of this problem is badly scaled: its diagonal spans about
    six decades (smallest entries 7e-7 to 3e-6 of the largest), below the SINGULAR test's
    threshold in float32 (1e3 eps = 1.2e-4 relative; its Jacobi-scaled reciprocal condition,
    3e-4 to 3e-3, passes), so float32 problems are reported SINGULAR (with NaN covariances)
    even where the estimate is fine."""
    variant_options(variant, {})
    x0 = problem.initial_guess(dtau0, "dtau0") if x0 is None else x0
    x0 = _check_unknowns(problem, x0, baseline=False)
    return _in_rounds(lambda p, x, e0, **kw: _gauss_helmert_tls(p, x, variant, e0, **kw),
                      problem, x0, options)


def solve_baseline(problem: TLSProblem, x0=None, dtau0=-1.0, variant: str = "iterated",
                   reading: str = "invariant", **options) -> Solution:
    """Estimates (X' in SE_2(3), tau0, dtau) on SE_2(3) x R; covariance (B, 11, 11) over
    [dxi' (9), dtau0, ddtau].  ``reading`` (``BASELINE_READINGS``): "invariant" (default) reads
    the relative transforms F~_gb^-1 F~_ga, composed in SGal(3), in the product group, and is
    unchanged by a Galilean change of the global frame; "product" composes the observations in
    the product group, and depends on the global frame's velocity (``baseline_observations``).
    x0: (X' SE23 (B,), tau0 (B, 1), dtau (B, 1)); by default ``baseline_start`` of the first
    pair and ``dtau0``.  Options, B = 0 and float32 (which may be reported SINGULAR for the
    reason given there): as ``solve_sgal3``."""
    variant_options(variant, {})
    check_reading(reading)
    if x0 is None:
        F0, dt = problem.initial_guess(dtau0, "dtau0")
        X0, t0 = baseline_start(F0, reading)
        x0 = (X0, t0[:, None], dt)
    x0 = _check_unknowns(problem, x0, baseline=True)
    return _in_rounds(lambda p, x, e0, **kw: _gauss_helmert_tls(
        p, x, variant, e0, baseline=True, reading=reading, **kw), problem, x0, options)


def eiv_cost(problem: TLSProblem):
    """The exact errors-in-variables cost of the SGal(3) model with the true frames a as
    nuisance variables F_ga_n = F~_ga_n exp(u_n):

        1/2 sum_n u_n^T Sigma_a^-1 u_n + 1/2 sum_n eps_b^T Sigma_b^-1 eps_b,
        eps_b = log(F~_gb_n^-1 F_ga_n A_n)  (F_gb_n = F_ga_n A_n exactly).

    Returns cost(x, u) -> (B,) with u (B, N+1, 10); the Gauss-Helmert iterated variant and
    the GTSAM factor graph minimise the same function."""
    n = problem.indices
    La = torch.linalg.cholesky(problem.cov_a)
    Lb = torch.linalg.cholesky(problem.cov_b)
    Fb_inv = problem.F_gb.inverse()

    def cost(x, u):
        F, dtau = x
        A = _drift_sgal3(F.unsqueeze(-1), n * dtau)
        eb = (Fb_inv @ problem.F_ga @ SGal3.exp(u) @ A).log()
        wa = torch.linalg.solve_triangular(La, u[..., None], upper=False)[..., 0]
        wb = torch.linalg.solve_triangular(Lb, eb[..., None], upper=False)[..., 0]
        return 0.5 * (wa.square().sum((-1, -2)) + wb.square().sum((-1, -2)))

    return cost


def condition_cost(problem: TLSProblem, weights_at=None):
    """The reduced cost of the Gauss-Helmert linearisation at zero observation residual,
    1/2 sum_n c_n^T S_n^-1 c_n with c_n = log(M_n A_n) and S_n = Ad(A_n^-1) Sigma_a Ad(A_n^-1)^T
    + Sigma_b ((5.23)-(5.24)).  With ``weights_at`` (unknowns x_ref) the weights S_n are frozen
    at x_ref: the paper variant's Gauss-Newton fixed point is the minimum of that cost with
    x_ref = the minimiser.  Without, S_n moves with x (a different, biased estimator)."""
    cond = sgal3_condition(problem)
    Sa, Sb = problem.cov_a, problem.cov_b

    def factor(x):
        c, _, Bm = cond(x, None)
        Ga = Bm[..., :10]
        # NaN where S is not positive definite (non-finite observations): the cost is NaN
        # there, which lbfgs reports NON_FINITE, instead of an exception for the batch.
        L, info = torch.linalg.cholesky_ex(Ga @ Sa @ Ga.transpose(-1, -2) + Sb)
        return torch.where((info == 0)[..., None, None], L, float("nan")), c

    frozen = None
    if weights_at is not None:
        # The condition's linearisation is returned multiplied by K = J_r(c), so the true
        # effective covariance is K^-1 S' K^-T and the frozen weight is K^T S'^-1 K.
        with torch.no_grad():
            L, c_ref = factor(V.detach(weights_at))
            frozen = (L, SGal3.jr(c_ref))

    def cost(x, _extra=None):
        if frozen is None:
            L, c = factor(x)  # K c = c: the factor K drops out of c^T S^-1 c
        else:
            L, K = frozen
            c, _, _ = cond(x, None)
            c = (K @ c[..., None])[..., 0]
        w = torch.linalg.solve_triangular(L, c[..., None], upper=False)[..., 0]
        return 0.5 * w.square().sum((-1, -2))

    return cost


def _put(x: tuple, idx: torch.Tensor, part: tuple) -> tuple:
    """x with the trials ``idx`` replaced by ``part`` (blockwise index_copy)."""
    out = []
    for full, p in zip(x, part):
        if isinstance(full, torch.Tensor):
            out.append(full.index_copy(0, idx, p))
        else:
            out.append(type(full).from_matrix(full.as_matrix().index_copy(0, idx, p.as_matrix())))
    return tuple(out)


def solve_sgal3_lbfgs(problem: TLSProblem, x0=None, dtau0=-1.0, batched: bool = False,
                      reweightings: int = 60, step_tol: float = 1e-4, **options) -> Solution:
    """The paper variant's estimate by a first-order method: ``torch.optim.LBFGS`` on the
    reduced condition cost 1/2 sum c^T S^-1 c with the weights S frozen, re-evaluated between
    LBFGS runs (at most ``reweightings`` times per trial, until its estimate moves by less
    than ``step_tol`` standard deviations), by autograd through the group operations.

    The tangent perturbation is preconditioned by the Cholesky factor of the Gauss-Newton
    covariance at the current weights (delta = L z; the identity where that covariance is
    not available, a SINGULAR or NON_FINITE trial, which then gets one LBFGS run).
    torch.optim.LBFGS has one line search and one stopping test, so by default the problems
    are solved one at a time (a Python loop over the batch; each trial's result is the one it
    gets alone); ``batched=True`` sums the trials still reweighting into one LBFGS problem
    instead, which couples them.  The covariance is the inverse Gauss-Newton information at
    the solution.  Report: status from the last LBFGS run, MAX_ITERATIONS for a converged
    trial still moving after ``reweightings`` rounds, and SINGULAR / NON_FINITE from the
    information at the solution (NON_FINITE wins); initial_cost is the cost at x0 (weights
    frozen at x0), cost and gradient_norm those of the last run, iterations the LBFGS
    iterations summed over the rounds, step_norm the last move in standard deviations (NaN
    where there is no covariance to measure it).  Not differentiable."""
    from .lbfgs import lbfgs
    batched = checks.boolean(batched, "batched")
    step_tol = checks.finite_number(step_tol, "step_tol", ">= 0")
    reweightings = checks.integer(reweightings, "reweightings", 1)
    x = problem.initial_guess(dtau0, "dtau0") if x0 is None else x0
    x = V.detach(_check_unknowns(problem, x, baseline=False))
    if problem.batch_size == 0:
        return _empty_solution(problem, x)
    cond = sgal3_condition(problem)
    options.setdefault("max_iterations", 200)

    def run(prob, x_start, scale):
        return lbfgs(condition_cost(prob, weights_at=x_start), x_start, scale=scale, **options)

    Bn = problem.batch_size
    like = problem.F_ga.as_matrix()
    nan = like.new_full((Bn,), float("nan"))
    iterations = torch.zeros(Bn, dtype=torch.int64, device=like.device)
    status = torch.full((Bn,), int(SolverStatus.MAX_ITERATIONS), dtype=torch.int64,
                        device=like.device)
    initial_cost, cost, gradient_norm, moved = nan.clone(), nan.clone(), nan.clone(), nan.clone()
    eye = torch.eye(11, dtype=like.dtype, device=like.device)
    active = torch.ones(Bn, dtype=torch.bool, device=like.device)
    for round_ in range(reweightings):
        idx = active.nonzero()[:, 0]
        if idx.numel() == 0:
            break
        sub = problem if idx.numel() == Bn else subset(problem, idx)
        xs = tuple(b[idx] for b in x)
        info = gauss_helmert(sgal3_condition(sub), xs, sub.covariance, variant="paper",
                             max_iterations=0)
        L, bad = torch.linalg.cholesky_ex(info.covariance)
        good = (bad == 0) & torch.isfinite(L).flatten(1).all(-1)
        scale = torch.where(good[:, None, None], L, eye)
        if batched:
            x_new, _, report = run(sub, xs, scale)
        else:
            parts = [run(subset(sub, slice(k, k + 1)), tuple(b[k:k + 1] for b in xs),
                         scale[k:k + 1]) for k in range(sub.batch_size)]
            x_new = tuple(type(parts[0][0][i]).stack([p[0][i] for p in parts]).reshape(-1)
                          if hasattr(parts[0][0][i], "as_matrix")
                          else torch.cat([p[0][i] for p in parts]) for i in range(len(x)))
            report = SolverReport(**{f: torch.cat([getattr(p[2], f) for p in parts])
                                     for f in ("status", "iterations", "initial_cost", "cost",
                                               "step_norm", "gradient_norm")})
        # The move in standard deviations of the covariance at the round's start: |L^-1 d|.
        d = torch.cat([x_new[0].rminus(xs[0]), x_new[1] - xs[1]], -1)
        w = torch.linalg.solve_triangular(scale, d[..., None], upper=False)[..., 0]
        step = torch.where(good, w.norm(dim=-1), float("nan"))
        x = _put(x, idx, x_new)
        iterations = iterations.index_add(0, idx, report.iterations)
        status = status.index_copy(0, idx, report.status)
        cost = cost.index_copy(0, idx, report.cost)
        gradient_norm = gradient_norm.index_copy(0, idx, report.gradient_norm)
        moved = moved.index_copy(0, idx, step)
        if round_ == 0:
            initial_cost = report.initial_cost  # every trial runs in the first round
        done = (step <= step_tol) | ~good | (report.status == SolverStatus.NON_FINITE)
        active = active.index_copy(0, idx, ~done)
    # Still moving after the last round: not settled.
    status = torch.where(active & (status == SolverStatus.CONVERGED),
                         SolverStatus.MAX_ITERATIONS, status)
    at = gauss_helmert(cond, x, problem.covariance, variant="paper", max_iterations=0)
    singular = at.report.status == SolverStatus.SINGULAR
    status = torch.where(singular & (status != SolverStatus.NON_FINITE), SolverStatus.SINGULAR,
                         status)
    status = torch.where(at.report.status == SolverStatus.NON_FINITE, SolverStatus.NON_FINITE,
                         status).to(torch.int64)
    non_finite = status == SolverStatus.NON_FINITE
    report = SolverReport(status=status, iterations=iterations,
                          initial_cost=torch.where(non_finite, float("nan"), initial_cost),
                          cost=torch.where(non_finite, float("nan"), cost),
                          step_norm=torch.where(non_finite, float("nan"), moved),
                          gradient_norm=torch.where(non_finite, float("nan"), gradient_norm))
    return Solution(x=x, covariance=at.covariance, report=report)
