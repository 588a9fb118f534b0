"""Concentrated Gaussians on the groups (Kelly and Giamou, Section 4, (4.1)-(4.11)).

F = mean exp(xi^) (right perturbation, the default) or F = exp(xi^) mean (left), with
xi ~ N(0, Sigma).  Propagation is first order through the adjoint unless stated; the
second-order compounding follows Barfoot and Furgale ("Associating uncertainty with
three-dimensional poses", 2014) written for any group through ad:

    exp(a) exp(b) = exp(a + b + ad(a) b / 2 + (ad(a)^2 b + ad(b)^2 a) / 12 + ...)
    Cov ~ Sa + Sb + B / 4 + (Aa Sb + Sb Aa^T + Ab Sa + Sa Ab^T) / 12,
    A_S = E[ad(x)^2] = sum_ij S_ij ad(e_i) ad(e_j),   B = E[ad(a) Sb ad(a)^T].

Only the public group API is used.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..functional import blocks, checks
from ..functional._blocking import values_readable
from ..groups import LieGroup
from .covariance import _mv, _read, _supported_factor, _sym, _with_known_directions, check_covariance

SIDES = ("right", "left")


@dataclass
class Gaussian:
    """A Gaussian on R^n: mean (..., n), covariance (..., n, n)."""

    mean: torch.Tensor
    covariance: torch.Tensor


# fuse's default step tolerances (largest step entry): float32 steps bottom out near its
# epsilon (1.2e-7) times the residuals, so 1e-12 would always run every iteration.
FUSE_TOL = 1e-12
FUSE_TOL_FLOAT32 = 1e-6


def _group_names(method: str | None = None) -> list[str]:
    """The group classes (those with ``method``), for error messages."""
    from .. import ALL_GROUPS  # the package is imported by the time a Gaussian is made
    return [G.__name__ for G in ALL_GROUPS if method is None or hasattr(G, method)]


class ConcentratedGaussian:
    """A concentrated Gaussian on a group: ``mean`` (a group element, any batch shape),
    ``covariance`` (..., dof, dof) of the tangent perturbation, ``side`` 'right' (F = mean
    exp(xi)) or 'left' (F = exp(xi) mean).

    ``validate`` checks that the covariance is symmetric positive definite (one host sync: its
    measures are read together; skipped on 'meta', under torch.func transforms and
    torch.compile).  Host syncs elsewhere: ``sample``, ``mahalanobis`` and ``log_prob`` factorise
    the covariance with ``torch.linalg.cholesky``, whose positive-definiteness check reads a
    value on CUDA (one sync per call; a covariance that is not positive definite raises there);
    ``fuse`` and ``fuse_event`` read their status once at the end (see their docstrings);
    propagation (``to_side``, ``inverse``, ``compose``, ``between``, the actions without
    ``validate``) reads nothing.

    Singular covariances.  A positive semi-definite covariance is accepted where its rows and
    columns that are exactly zero mark directions known exactly (the rank-9 covariance of an
    IMU increment with exact timestamps has a zero time row and column) and the rest is
    positive definite; with ``allow_singular=True`` any positive semi-definite covariance is
    (its support: the eigenvectors whose eigenvalues exceed the tolerance of
    ``check_covariance`` times the largest entry).  The distribution then lives on the
    supported subspace of the tangent, of dimension r = :meth:`rank`: ``sample`` draws
    perturbations in it (exact zeros along known directions), ``mahalanobis`` is the norm of
    the perturbation's projection onto it, whitened (its square, a NEES, is chi-square with r
    degrees of freedom), and ``log_prob`` is the density of that projection on the r-dimensional
    subspace: the formula below with r for dof and the product of the supported eigenvalues
    (the pseudo-determinant) for det Sigma.  For known directions it is the limit of the
    full-rank log_prob plus (dof - r) log(2 pi s^2) / 2 as their variance s^2 goes to 0.
    Known directions are those of the Gaussian's own side; ``to_side`` mixes them (log_prob of
    a left Gaussian goes through the right side), so propagate and evaluate such Gaussians with
    ``allow_singular=True``, which the results of ``to_side``, ``inverse``, ``compose`` and
    ``between`` inherit."""

    def __init__(self, mean: LieGroup, covariance: torch.Tensor, side: str = "right",
                 validate: bool = True, allow_singular: bool = False):
        if not isinstance(mean, LieGroup):
            raise TypeError(f"mean must be a group element ({', '.join(_group_names())}), "
                            f"got {type(mean).__name__}")
        if side not in SIDES:
            raise ValueError(f"side must be 'right' or 'left', got {side!r}")
        dof = mean.dof
        if not isinstance(covariance, torch.Tensor):
            raise TypeError(f"covariance must be a torch.Tensor, got {type(covariance).__name__}")
        if covariance.dim() < 2 or covariance.shape[-2:] != (dof, dof):
            raise ValueError(
                f"covariance must have shape (..., {dof}, {dof}) for {type(mean).__name__}, "
                f"got {tuple(covariance.shape)}"
            )
        checks.dense(covariance, "covariance")
        if covariance.dtype != mean.dtype or covariance.device != mean.device:
            # a dtype mismatch is a TypeError, a device mismatch a ValueError (as checks.same_device_dtype)
            error = ValueError if covariance.device != mean.device else TypeError
            raise error(
                f"covariance ({covariance.dtype}, {covariance.device}) must match the mean "
                f"({mean.dtype}, {mean.device})"
            )
        try:
            checks.broadcast_shapes(mean.batch_shape, covariance.shape[:-2])
        except RuntimeError:
            raise ValueError(
                f"batch shapes do not broadcast: mean {tuple(mean.batch_shape)}, "
                f"covariance {tuple(covariance.shape[:-2])}"
            ) from None
        validate = checks.boolean(validate, "validate")
        self.allow_singular = checks.boolean(allow_singular, "allow_singular")
        if validate and self.allow_singular:
            check_covariance(covariance, dof, definite=False)
        elif validate:
            try:  # definite on the directions that are not known exactly
                check_covariance(_with_known_directions(covariance), dof)
            except ValueError as error:
                if "not positive definite" not in str(error):
                    raise
                raise ValueError(f"{error}: a singular covariance is accepted where its null "
                                 f"directions are rows and columns of exact zeros (directions "
                                 f"known exactly), or with allow_singular=True") from None
        self.mean = mean
        self.covariance = covariance
        self.side = side

    @property
    def group(self) -> type[LieGroup]:
        return type(self.mean)

    @property
    def dof(self) -> int:
        return self.mean.dof

    def __repr__(self) -> str:
        return (f"ConcentratedGaussian({self.group.__name__}, side={self.side}, "
                f"batch_shape={tuple(self.mean.batch_shape)})")

    # --------------------------------------------------------------- the perturbation
    def _apply(self, xi: torch.Tensor) -> LieGroup:
        return self.mean.rplus(xi) if self.side == "right" else self.mean.lplus(xi)

    @property
    def batch_shape(self) -> torch.Size:
        """The broadcast batch shape of the mean and the covariance."""
        return checks.broadcast_shapes(self.mean.batch_shape, self.covariance.shape[:-2])

    @property
    def _group(self) -> type[LieGroup]:
        """The built-in group class of the mean (that of a user subclass's base)."""
        return self.mean._group

    def _check_element(self, g, name: str = "g") -> LieGroup:
        """g: an element of this Gaussian's group (any subclass of its built-in class), its
        dtype and device, broadcasting batch."""
        if not isinstance(g, self._group):
            raise TypeError(f"{name} must be a {self._group.__name__} (the group of this Gaussian), "
                            f"got {type(g).__name__}")
        checks.same_device_dtype(mean=self.mean.as_matrix(), **{name: g.as_matrix()})
        checks.broadcast_batch(gaussian=self.batch_shape, **{name: g.batch_shape})
        return g

    def perturbation(self, g: LieGroup) -> torch.Tensor:
        """xi with g = mean exp(xi) (right) or exp(xi) mean (left), (4.5)."""
        self._check_element(g)
        return g.rminus(self.mean) if self.side == "right" else g.lminus(self.mean)

    def sample(self, sample_shape=(), generator=None) -> LieGroup:
        """Reparameterised samples, batch ``sample_shape + batch_shape``; gradients flow to the
        mean and the covariance (through its Cholesky factor)."""
        sample_shape = checks.shape(sample_shape, "sample_shape")
        if generator is not None and not isinstance(generator, torch.Generator):
            raise TypeError(f"generator must be None or a torch.Generator, got {type(generator).__name__}")
        L = _supported_factor(self.covariance, self.allow_singular)[0]
        batch = self.batch_shape
        eps = torch.randn(*sample_shape, *batch, self.dof, dtype=L.dtype, device=L.device,
                          generator=generator)
        return self._apply(_mv(L, eps))

    def mahalanobis(self, g: LieGroup) -> torch.Tensor:
        """sqrt(xi^T Sigma^-1 xi) with xi the perturbation of g."""
        xi = self.perturbation(g)
        z = _supported_factor(self.covariance, self.allow_singular)[2](xi)[0]
        # dim as a non-negative index: the vector_norm decomposition of torch 2.9 to 2.12 (meta
        # and fake tensors, inductor) keeps a reduced dimension of size 1 (SO2) named as -1
        # (pytorch/pytorch#182181, fixed in 2.13; tests/test_devices.py).
        return torch.linalg.vector_norm(z, dim=z.dim() - 1)

    def log_prob(self, g: LieGroup) -> torch.Tensor:
        """Log density with respect to the left-invariant Haar measure, normalised to be the
        Lebesgue measure dxi of the tangent coordinates at the identity: about any element M,
        F = M exp(xi) gives dF = |det J_r(xi)| dxi (F^-1 dF = J_r(xi) dxi), (4.3)-(4.11):

            log_prob = -xi^T Sigma^-1 xi / 2 - log((2 pi)^dof det Sigma) / 2 - log |det J_r(xi)|

        with xi and Sigma the right perturbation and its covariance.  A left Gaussian is
        evaluated as the same distribution on the right side (``to_side``, exact), so the value
        does not depend on the side.  All the groups here but Sim3 are unimodular: the left- and
        right-invariant Haar measures agree (and |det J_l| = |det J_r|).  Sim3 is not: its
        right-invariant measure (|det J_l(xi)| dxi about F = exp(xi) M) is |det Ad(F)| = s^3
        times this one, so a density against it is this log_prob - 3 log s(F).  One host sync on
        CUDA: the Cholesky factorisation's positive-definiteness check."""
        self._check_element(g)
        r = self._right()
        xi = g.rminus(r.mean)
        _, keep, whiten = _supported_factor(r.covariance, self.allow_singular)
        z, log_det_sigma = whiten(xi)
        log_det_j = torch.linalg.slogdet(self.group.jr(xi))[1]
        dof = keep.sum(-1).to(z.dtype)  # the rank (the dof where the covariance is definite)
        return (-0.5 * (z * z).sum(-1) - 0.5 * (dof * math.log(2 * math.pi) + log_det_sigma)
                - log_det_j)

    def rank(self) -> torch.Tensor:
        """(...) int64: the dimension r of the supported subspace (``dof`` for a definite
        covariance; the degrees of freedom of ``mahalanobis(g) ** 2``)."""
        return _supported_factor(self.covariance, self.allow_singular)[1].sum(-1)

    # ------------------------------------------------------------------ conversions
    def to_side(self, side: str) -> ConcentratedGaussian:
        """The same distribution with the other perturbation side, exactly: mean exp(xi) =
        exp(Ad(mean) xi) mean, a linear map of the Gaussian perturbation (Ad(mean) Sigma
        Ad(mean)^T to the left, Ad(mean^-1) Sigma Ad(mean^-1)^T to the right)."""
        if side not in SIDES:
            raise ValueError(f"side must be 'right' or 'left', got {side!r}")
        if side == self.side:
            return self
        # Ad(mean)^-1 = Ad(mean^-1): closed form, no matrix inversion (nor its host sync on CUDA)
        A = self.mean.adjoint() if self.side == "right" else self.mean.inverse().adjoint()
        return ConcentratedGaussian(self.mean, _sym(A @ self.covariance @ A.transpose(-1, -2)),
                                    side, validate=False, allow_singular=self.allow_singular)

    # ------------------------------------------------------------------ propagation
    def _right(self) -> ConcentratedGaussian:
        return self.to_side("right")

    def inverse(self) -> ConcentratedGaussian:
        """F^-1 = mean^-1 exp(-Ad(mean) xi): Sigma' = Ad(mean) Sigma Ad(mean)^T (right side)."""
        r = self._right()
        Ad = r.mean.adjoint()
        out = ConcentratedGaussian(r.mean.inverse(), _sym(Ad @ r.covariance @ Ad.transpose(-1, -2)),
                                   "right", validate=False, allow_singular=self.allow_singular)
        return out.to_side(self.side)

    def compose(self, other: ConcentratedGaussian, cross_covariance: torch.Tensor | None = None,
                second_order: bool = False) -> ConcentratedGaussian:
        """F1 F2.  Right perturbations: F1 F2 exp(a) exp(b) with a = Ad(mean2^-1) xi1, b = xi2.
        ``cross_covariance`` is E[xi1 xi2^T] of the right perturbations (first order only);
        ``second_order`` adds the Barfoot-Furgale fourth-order terms (independent operands)."""
        second_order = checks.boolean(second_order, "second_order")
        self._same_group(other)
        self._check_cross(other, cross_covariance)
        r1, r2 = self._right(), other._right()
        A = r2.mean.inverse().adjoint()
        Sa = A @ r1.covariance @ A.transpose(-1, -2)
        Sb = r2.covariance
        S = Sa + Sb
        if cross_covariance is not None:
            if second_order:
                raise ValueError("second_order compounding assumes independent operands")
            C = A @ cross_covariance
            S = S + C + C.transpose(-1, -2)
        if second_order:
            S = S + self._fourth_order(Sa, Sb)
        out = ConcentratedGaussian(r1.mean.compose(r2.mean), _sym(S), "right", validate=False,
                                   allow_singular=self.allow_singular or other.allow_singular)
        return out.to_side(self.side)

    def between(self, other: ConcentratedGaussian, cross_covariance: torch.Tensor | None = None
                ) -> ConcentratedGaussian:
        """F1^-1 F2 = B exp(-Ad(B^-1) xi1 + xi2), B = mean1^-1 mean2 (first order, right side)."""
        self._same_group(other)
        self._check_cross(other, cross_covariance)
        r1, r2 = self._right(), other._right()
        Bm = r1.mean.between(r2.mean)
        A = -Bm.inverse().adjoint()
        S = A @ r1.covariance @ A.transpose(-1, -2) + r2.covariance
        if cross_covariance is not None:
            C = A @ cross_covariance
            S = S + C + C.transpose(-1, -2)
        return ConcentratedGaussian(Bm, _sym(S), "right", validate=False,
                                    allow_singular=self.allow_singular or other.allow_singular
                                    ).to_side(self.side)

    def _fourth_order(self, Sa: torch.Tensor, Sb: torch.Tensor) -> torch.Tensor:
        basis = torch.eye(self.dof, dtype=Sa.dtype, device=Sa.device)
        ads = self.group.ad(basis)  # (dof, dof, dof): ad(e_i)
        A_a = torch.einsum("...ij,iab,jbc->...ac", Sa, ads, ads)
        A_b = torch.einsum("...ij,iab,jbc->...ac", Sb, ads, ads)
        Bt = torch.einsum("...ij,iab,...bc,jdc->...ad", Sa, ads, Sb, ads)
        T = A_a @ Sb + A_b @ Sa
        return 0.25 * Bt + (T + T.transpose(-1, -2)) / 12.0

    def _same_group(self, other):
        """other: a ConcentratedGaussian on the same group, dtype and device, broadcasting batch."""
        if not isinstance(other, ConcentratedGaussian) or other._group is not self._group:
            got = (f"a ConcentratedGaussian on {other._group.__name__}"
                   if isinstance(other, ConcentratedGaussian) else type(other).__name__)
            raise TypeError(f"other must be a ConcentratedGaussian on {self._group.__name__}, got {got}")
        checks.same_device_dtype(self=self.covariance, other=other.covariance)
        checks.broadcast_batch(self=self.batch_shape, other=other.batch_shape)

    def _check_cross(self, other, cross_covariance):
        """E[xi1 xi2^T] (..., dof, dof): not symmetric, so shape, dtype, device and batch only."""
        if cross_covariance is None:
            return
        checks.matrix(cross_covariance, self.dof, "cross_covariance")
        checks.same_device_dtype(self=self.covariance, cross_covariance=cross_covariance)
        checks.broadcast_batch(self=self.batch_shape, other=other.batch_shape,
                               cross_covariance=cross_covariance.shape[:-2])

    # ------------------------------------------------------------------ actions
    def _act(self, fn_name: str, x: torch.Tensor, x_cov: torch.Tensor | None, x_name: str,
             validate: bool) -> Gaussian:
        """y = F x in homogeneous coordinates x_h (x in its first k slots), first order:
        right perturbation z ~ M (I + xi^) x_h, so dz/dxi_j = (M hat(e_j) x_h) and dz/dx =
        M[:, :k].  Points are z[:k] / z[n-1] (projective: Sim3's last row is [0, 1/s]; for the
        other groups z[n-1] = 1 and the division changes nothing), so
        dy = (dz[:k] - y dz[n-1]) / z[n-1].  Velocities and directions are z[:k]."""
        validate = checks.boolean(validate, "validate")
        if not hasattr(self.group, fn_name):
            raise TypeError(f"{fn_name} is not available for a Gaussian on {self.group.__name__}: "
                            f"only {', '.join(_group_names(fn_name))} have {fn_name}")
        r = self._right()
        y = getattr(r.mean, fn_name)(x)  # validates x
        M = r.mean.as_matrix()
        n, k = M.shape[-1], x.shape[-1]
        if x_cov is not None:
            cov_name = f"{x_name}_covariance"
            checks.matrix(x_cov, k, cov_name)
            checks.same_device_dtype(**{x_name: x, cov_name: x_cov})
            checks.broadcast_batch(gaussian=self.batch_shape, **{x_name: x.shape[:-1],
                                                                  cov_name: x_cov.shape[:-2]})
            if validate:  # a zero covariance (an exact point) is allowed: semi-definite
                check_covariance(x_cov, k, cov_name, definite=False)
        # x_h = [x, pad]: points [p, (0,) 1], events [x, t, 1], velocities [u, 1, 0], directions [d, 0, ...]
        pads = {"act": [0.0] * (n - k - 1) + [1.0] if n > k else [],
                "act_velocity": [1.0] + [0.0] * (n - k - 1), "act_direction": [0.0] * (n - k)}[fn_name]
        xh = torch.cat([x] + [torch.full_like(x[..., :1], v) for v in pads], dim=-1)
        hats = blocks.generators(self.group._f.hat, self.dof, x)  # (dof, n, n)
        Y = torch.einsum("jab,...b->...ja", hats, xh)
        Hfull = torch.einsum("...ab,...jb->...aj", M, Y)  # (..., n, dof)
        H, Jx = Hfull[..., :k, :], M[..., :k, :k]
        if fn_name == "act" and n > k:
            z_last = (M[..., n - 1, :] * xh).sum(-1)[..., None, None]
            yk = y[..., :, None]
            H = (H - yk * Hfull[..., n - 1:n, :]) / z_last
            Jx = (Jx - yk * M[..., n - 1:n, :k]) / z_last
        S = H @ r.covariance @ H.transpose(-1, -2)
        if x_cov is not None:
            S = S + Jx @ x_cov @ Jx.transpose(-1, -2)
        return Gaussian(y, _sym(S))

    def act(self, x: torch.Tensor, x_covariance: torch.Tensor | None = None,
            validate: bool = True) -> Gaussian:
        """Points (..., point_dim) (events (..., 4) for SGal3) through F, as a Gaussian on R^n.
        ``x_covariance`` (..., k, k): the point's own covariance, independent of F; with
        ``validate`` it is checked symmetric positive semi-definite (one host sync, as the
        constructor's check; skipped on 'meta', under torch.func transforms and torch.compile)."""
        return self._act("act", x, x_covariance, "x", validate)

    def act_velocity(self, u: torch.Tensor, u_covariance: torch.Tensor | None = None,
                     validate: bool = True) -> Gaussian:
        """Velocities (..., 3) through F (SE23 and SGal3, the groups with a velocity; TypeError
        for the others); ``u_covariance`` as ``x_covariance`` of ``act``."""
        return self._act("act_velocity", u, u_covariance, "u", validate)

    def act_direction(self, d: torch.Tensor, d_covariance: torch.Tensor | None = None,
                      validate: bool = True) -> Gaussian:
        """Directions through F; ``d_covariance`` as ``x_covariance`` of ``act``."""
        return self._act("act_direction", d, d_covariance, "d", validate)

    # --------------------------------------------------------------------- fusion
    def fuse(self, other: ConcentratedGaussian, iterations: int = 10,
             tol: float | None = None) -> ConcentratedGaussian:
        """Fusion of two concentrated Gaussians on the same group by Gauss-Newton on the group
        (right side): the mean minimises r_1^T Sigma_1^-1 r_1 + r_2^T Sigma_2^-1 r_2, r_k =
        log(mean_k^-1 F), i.e. it maximises the product of the two tangent-space Gaussians.

        This is the standard practice (Barfoot and Furgale's pose fusion; the mahony paper,
        Section 6), not the exact maximiser of p1(F) p2(F) for the densities of ``log_prob``:
        those also hold the volume factor 1/|det J_r(r_k)|, and the maximiser of log_prob1 +
        log_prob2 differs from this mean by a small fraction of the fused standard deviation
        (5e-4 to 7e-3 against about 0.13 in the tests' cases).

        Residuals r_k linearised at F_op exp(d): r_k + J_r^-1(r_k) d.  The posterior covariance
        is re-expressed about the final estimate (the Jacobian reset of the mahony paper,
        Section 6.4): Sigma = (sum J_k^T Sigma_k^-1 J_k)^-1 at F_op.

        Only two operands are fused.  Chaining, d1.fuse(d2).fuse(d3), re-linearises the first
        fusion's Gaussian about the second estimate: an approximation of the joint fusion of the
        three (in a probe with tangent residual entries of about 0.3, the means differed by up
        to about 1e-2 on SGal3, the covariances by about 1% relative).  The joint fusion is the
        least-squares problem of the stacked whitened residuals L_k^-1 r_k (Sigma_k = L_k L_k^T),
        which ``torchsgal.estimation.gauss_newton`` solves.

        ``iterations``: an integer >= 1, the most Gauss-Newton steps; ``tol``: a finite number
        >= 0, the largest step entry at which they stop early (0: they never do; None: 1e-12 in
        float64, 1e-6 in float32, about 8 of its epsilons, where the steps bottom out).

        Both covariances must be positive definite: they are inverted.  The singular ones that
        the constructor accepts (rows and columns of exact zeros, directions known exactly, as
        in an IMU increment's covariance with time_noise_density=0) raise ValueError ('...
        covariance is singular'); give those directions a small variance first (``covariance +
        s2 * torch.diag_embed(known)``, ``known`` the zero rows) or integrate with a
        time_noise_density > 0.

        Host syncs: with ``tol`` > 0, one per iteration (the step test, which also reads whether
        a matrix so far was singular); then one at the end, which raises ValueError if a
        covariance or the final information matrix is singular.  With ``tol=0`` only the one at
        the end.  None where values cannot be read ('meta', torch.func transforms,
        torch.compile), where all the iterations run.
        """
        self._same_group(other)
        iterations = checks.integer(iterations, "iterations", 1)
        if tol is None:
            tol = FUSE_TOL_FLOAT32 if self.covariance.dtype == torch.float32 else FUSE_TOL
        tol = checks.finite_number(tol, "tol", ">= 0")
        parts = [self._right(), other._right()]
        # the *_ex variants do not check (no host sync); their status is read at the end
        inverted = [torch.linalg.inv_ex(p.covariance) for p in parts]
        infos = [W for W, _ in inverted]
        failed = [(status != 0).any() for _, status in inverted]
        step_failed = torch.zeros((), dtype=torch.bool, device=self.covariance.device)
        # every input feeds the flags read at the end (under vmap any of them may be batched)
        readable = all(values_readable(t) for t in (self.covariance, other.covariance,
                                                     self.mean.as_matrix(), other.mean.as_matrix()))
        F = parts[0].mean
        for _ in range(iterations):
            H: torch.Tensor | int = 0  # a tensor once the (two) parts are added
            g: torch.Tensor | int = 0
            for p, W in zip(parts, infos):
                r = F.rminus(p.mean)
                J = self.group.jr_inv(r)
                JtW = J.transpose(-1, -2) @ W
                H = H + JtW @ J
                g = g + _mv(JtW, r)
            step, status = torch.linalg.solve_ex(H, -g)
            step_failed = step_failed | (status != 0).any()
            F = F.rplus(step)
            # An empty batch has nothing to do; where the step cannot be read ('meta', torch.func
            # transforms, torch.compile) all the iterations run.
            if step.numel() == 0:
                break
            if tol > 0 and readable and values_readable(step):
                # one host sync per iteration: the step and the status so far
                big, *bad = _read(step.abs().max(), *failed, step_failed)
                _raise_fuse(bad)
                if big < tol:
                    break
        H = 0
        for p, W in zip(parts, infos):
            J = self.group.jr_inv(F.rminus(p.mean))
            H = H + J.transpose(-1, -2) @ W @ J
        P, status = torch.linalg.inv_ex(H)
        if readable and P.numel() > 0:
            _raise_fuse(_read(*failed, step_failed | (status != 0).any()))
        return ConcentratedGaussian(F, _sym(P), "right", validate=False).to_side(self.side)


# fuse and fuse_event invert covariances: what to do with directions known exactly
KNOWN_DIRECTIONS_HINT = ("; fusion inverts it, so it must be positive definite: give directions "
                         "known exactly (rows and columns of zeros) a small variance first, "
                         "e.g. covariance + s2 * torch.diag_embed(known), or integrate an IMU "
                         "increment with time_noise_density > 0")


def _raise_fuse(bad) -> None:
    """The status flags of fuse (Python floats, read): self's, other's covariance, then a
    Gauss-Newton system (a step's or the final information matrix)."""
    for flag, what in zip(bad, ("self.covariance is singular" + KNOWN_DIRECTIONS_HINT,
                                "other.covariance is singular" + KNOWN_DIRECTIONS_HINT,
                                "the fused information matrix (sum_k J_k^T Sigma_k^-1 J_k) is "
                                "singular")):
        if flag:
            raise ValueError(f"fuse: {what}")
