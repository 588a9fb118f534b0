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

The SE_2(3) x R baseline is in ``tls_baseline``, the solvers on the factor-graph engine in
``tls_solvers``; ``tls`` gathers the public names.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from ..functional import checks
from ..functional._blocking import values_readable
from ..groups import SE23, LieGroup, SGal3
from ..uncertainty.covariance import check_covariance
from . import variables as V
from .solver import Solution, SolverReport

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
        given = self.indices is not None  # the default 0..N needs no value check
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
        if self.indices.dtype == torch.bool or self.indices.is_complex():
            raise TypeError(f"indices must be real numbers, got {self.indices.dtype}")
        # Integers are finite: only given floating-point indices are read (one host read).
        read = given and self.indices.is_floating_point() and values_readable(self.indices)
        self.indices = self.indices.to(self.F_ga.dtype)
        if read and not bool(torch.isfinite(self.indices).all()):
            bad = ~torch.isfinite(self.indices)
            raise ValueError(f"indices must be finite (the sample indices n, shared by every "
                             f"trial), got {int(bad.sum())} non-finite of {bad.numel()}, the first "
                             f"at position {int(bad.int().argmax())}")
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
        checks.floating(dt, name)  # a tensor given is not converted: the problem's dtype
        checks.same_device_dtype(F_ga=self.F_ga.as_matrix(), **{name: dt})
        if dt.dim() > 1 or (dt.dim() == 1 and dt.shape[0] != self.batch_size):
            raise ValueError(f"{name} must be a scalar or have shape (B,) = ({self.batch_size},), "
                             f"got {tuple(dt.shape)}")
        return F0, dt.expand(self.batch_size).reshape(-1, 1).clone()


def _ad_time_left(s: torch.Tensor, M: torch.Tensor) -> torch.Tensor:
    """Ad(T^s) M = (I + s ad(e_10)) M: the rho rows minus s times the nu rows (ad(e_10)^2 = 0)."""
    shape = checks.broadcast_shapes(s.shape + (1, 1), M.shape)
    out = M.expand(shape).clone()
    out[..., 0:3, :] -= s[..., None, None] * M[..., 3:6, :]
    return out


def _ad_time_right_inverse(M: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """M Ad(T^-s) = M (I - s ad(e_10)): the nu columns plus s times the rho columns."""
    shape = checks.broadcast_shapes(s.shape + (1, 1), M.shape)
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



def subset(problem: TLSProblem, index) -> TLSProblem:
    """The trials ``index`` (a slice, or an int64 index tensor (K,)) of a problem."""
    if not isinstance(index, slice) and not (
            isinstance(index, torch.Tensor) and index.dim() == 1 and index.dtype == torch.int64):
        got = (f"a tensor of {index.dtype} and shape {tuple(index.shape)}" if isinstance(index, torch.Tensor)
               else repr(index))
        raise TypeError(f"index must be a slice or a 1-D int64 tensor of trials, got {got}")

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
