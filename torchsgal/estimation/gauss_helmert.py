"""Errors-in-variables (Gauss-Helmert) least squares, batched.

Unknowns x and observation residuals e (B, N, m) with e_n ~ N(0, Sigma_n) are tied by condition
functions c_n(x, e_n) = 0 (B, N, k).  Minimise 1/2 sum_n e_n^T Sigma_n^-1 e_n subject to the
conditions.  Linearising at (x, e0):

    c + A delta + Bm (e - e0) = 0,   A = dc/dx (B, N, k, d),  Bm = dc/de (B, N, k, m).

Eliminating e with Lagrange multipliers gives the reduced problem in delta with the misclosure
w = c - Bm e0 and the effective covariance S = Bm Sigma Bm^T (kelly-giamou (5.23)):

    (sum A^T S^-1 A) delta = -sum A^T S^-1 w                                       (5.24)
    e = -Sigma Bm^T S^-1 (w + A delta).

``variant="paper"`` re-linearises at e0 = 0 on every iteration, as (5.18) does; ``"iterated"``
re-linearises at the current estimate of e (the classical Gauss-Helmert iteration), which needs
the condition Jacobians at non-zero residuals and converges to the constrained optimum.
The whitened reduced residual L^-1 w (S = L L^T) drives the shared Levenberg-Marquardt loop of
``solver.iterate``; its cost 1/2 w^T S^-1 w is the linearised errors-in-variables cost.
"""
from __future__ import annotations

from collections.abc import Callable

import torch

from ..functional import checks
from ..uncertainty.covariance import covariance_factor
from . import variables as V
from .solver import Linearisation, Solution, _as_given, iterate

VARIANTS = ("iterated", "paper")


class _CovarianceBlocks:
    """Block-diagonal observation covariance: B Sigma B^T = sum_i (B_i R_i)(B_i R_i)^T with
    R_i the Cholesky factor of block i, or its square-root diagonal when the block is diagonal
    (checked once, at entry)."""

    def __init__(self, covariance):
        blocks = covariance if isinstance(covariance, (tuple, list)) else (covariance,)
        if not blocks:
            raise ValueError("observation_covariance must hold at least one block, got none")
        self.sizes, self.factors, self.diagonal = [], [], []
        self.blocks, self.names = blocks, []
        for i, S in enumerate(blocks):
            name = "observation_covariance" + (f"[{i}]" if len(blocks) > 1 else "")
            self.names.append(name)
            if not isinstance(S, torch.Tensor) or S.dim() < 2:
                raise ValueError(f"{name} must be a tensor (..., m, m), got "
                                 f"{tuple(getattr(S, 'shape', ()))}")
            diagonal, factor = covariance_factor(S, name)
            self.sizes.append(S.shape[-1])
            self.diagonal.append(diagonal)
            self.factors.append(factor)
        # All blocks diagonal: one square-root diagonal for the whole of e.
        self.all_diagonal = all(self.diagonal)
        if self.all_diagonal:
            shapes = [f.shape[:-1] for f in self.factors]
            batch = checks.broadcast_shapes(*shapes)
            self.sqrt_diag = torch.cat([f.expand(batch + f.shape[-1:]) for f in self.factors], -1)

    @property
    def dim(self) -> int:
        return sum(self.sizes)

    def _split(self, Bm):
        out, i = [], 0
        for k in self.sizes:
            out.append(Bm[..., i:i + k])
            i += k
        return out

    def whiten(self, Bm):
        """[B_i R_i] per block (one block when every block is diagonal)."""
        if self.all_diagonal:
            return [Bm * self.sqrt_diag[..., None, :]]
        return [Bi * R[..., None, :] if diag else Bi @ R
                for Bi, R, diag in zip(self._split(Bm), self.factors, self.diagonal)]

    def effective(self, Bw):
        """S = sum_i (B_i R_i)(B_i R_i)^T."""
        S = None
        for W in Bw:
            term = W @ W.transpose(-1, -2)
            S = term if S is None else S + term
        return S

    def apply_transposed(self, Bw, y):
        """Sigma B^T y = concat_i R_i (B_i R_i)^T y; y (..., k)."""
        if self.all_diagonal:
            return (Bw[0] * y[..., :, None]).sum(-2) * self.sqrt_diag
        parts = []
        for W, R, diag in zip(Bw, self.factors, self.diagonal):
            u = (W.transpose(-1, -2) @ y[..., None])[..., 0]
            parts.append(u * R if diag else (R @ u[..., None])[..., 0])
        return torch.cat(parts, dim=-1)


def variant_options(variant: str, options: dict) -> bool:
    """Checks ``variant`` and sets its default solver options; True for "iterated"."""
    if variant not in VARIANTS:
        raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
    if variant == "iterated":
        # Its linearised cost is re-evaluated at each new residual estimate, so it can rise a
        # little even for a vanishing step: steps shorter than 0.1 standard deviations are
        # always accepted, and it stops on the step size only (it converges linearly).
        options.setdefault("accept_tol", 1e-6)
        options.setdefault("always_accept_below", 0.1)
        options.setdefault("cost_tol", 0.0)
    else:
        # The paper's scheme is plain Gauss-Newton: its fixed point (the gradient of the
        # condition cost with the weights S held fixed) is not a minimum of that cost once S
        # moves with x, so Levenberg-Marquardt's cost test stalls it there (DIVERGED at the
        # fixed point).  An explicit ``damping`` is kept.
        options.setdefault("damping", None)
    return variant == "iterated"


def gauss_helmert(
    condition: Callable,
    x0,
    observation_covariance,
    *,
    variant: str = "iterated",
    e0: torch.Tensor | None = None,
    **options,
) -> Solution:
    """Solves a batch of errors-in-variables problems.

    condition: (x, e) -> (c (B, N, k), A (B, N, k, d), Bm (B, N, k, m)); e is (B, N, m), or
        None for e = 0 (the condition may take a cheaper path then).  Any invertible factor
        per condition may multiply c's linearisation (A, Bm and the linear part of c) without
        changing the solution.
    x0: the unknowns, as in ``gauss_newton``: a group element (B,) or (B, K), a tensor (B, k)
        or (B, K, k), or a tuple of them; ``condition`` receives x, and ``Solution.x`` comes
        back, in the same form (a block given alone arrives alone).  d, the size of A's last
        axis, is the sum of the blocks' tangent sizes (K dof for a (B, K) group block,
        variable-major).
    observation_covariance: (B or 1, N or 1, m, m) symmetric positive definite, or a tuple of
        such blocks along the diagonal (sizes adding up to m); diagonal blocks are detected and
        handled elementwise.
    variant: "iterated" (default) or "paper" (see the module docstring).
    options: see ``solver.iterate``.  The iterated variant accepts steps whose linearised cost
        rises by at most ``accept_tol`` (default 1e-6, relative) or whose step is below
        ``always_accept_below`` (0.1) standard deviations, since that cost is re-evaluated at
        the new residual estimate, and by default stops on the step size only (``cost_tol=0``);
        it is Levenberg-Marquardt damped (``damping`` 1e-4).  The paper variant takes plain
        Gauss-Newton steps by default (``damping=None``): Levenberg-Marquardt's cost test
        stalls it at its fixed point, which does not minimise the cost it evaluates.
    e0: the start of the residual estimate e (B, N, m) (default zero); for the iterated variant
        the condition is called once more, at e = None, to check e0's N before its first use.
    Returns a ``Solution`` whose ``aux`` holds the estimated observation residuals e.  Not
    differentiable: the solution carries no autograd graph.
    """
    iterated = variant_options(variant, options)
    single = V.is_single(x0)
    condition = V.unwrapped(condition, single)
    x0 = V.check_values(x0)
    cov = _CovarianceBlocks(observation_covariance)
    ref = x0[0].as_matrix() if hasattr(x0[0], "as_matrix") else x0[0]
    Bn, d = V.batch_size(x0), V.tangent_dim(x0)
    for i, S in enumerate(cov.blocks):
        checks.same_device_dtype(x0=ref, **{cov.names[i]: S})
    if e0 is not None:
        checks.floating(e0, "e0")
        checks.same_device_dtype(x0=ref, e0=e0)
        if e0.dim() != 3 or e0.shape[0] != Bn or e0.shape[-1] != cov.dim:
            raise ValueError(f"e0 must have shape (B, N, m) = ({Bn}, N, {cov.dim}), got "
                             f"{tuple(e0.shape)}")
    checked = [False]

    def check_condition(c, A, Bm, e):
        """The condition's outputs against x0 and the covariance, once (metadata only)."""
        for name, t in (("c", c), ("A", A), ("Bm", Bm)):
            if not isinstance(t, torch.Tensor):
                raise TypeError(f"condition must return tensors (c, A, Bm), got {name} of type "
                                f"{type(t).__name__}")
        if c.dim() != 3 or c.shape[0] != Bn:
            raise ValueError(f"condition must return c of shape (B, N, k) with B = {Bn}, got "
                             f"{tuple(c.shape)}")
        N, k = c.shape[1:]
        if tuple(A.shape) != (Bn, N, k, d):
            raise ValueError(f"condition must return A of shape (B, N, k, d) = "
                             f"{(Bn, N, k, d)}, got {tuple(A.shape)}")
        if tuple(Bm.shape) != (Bn, N, k, cov.dim):
            raise ValueError(f"condition returned Bm of shape {tuple(Bm.shape)}, expected "
                             f"(B, N, k, m) = {(Bn, N, k, cov.dim)}: the observation covariance "
                             f"has size {cov.dim}")
        checks.same_device_dtype(x0=ref, c=c, A=A, Bm=Bm)
        for i, S in enumerate(cov.blocks):
            checks.broadcast_batch(conditions=c.shape[:2], **{cov.names[i]: S.shape[:-2]})
        if e is not None and e.shape[1] != N:
            raise ValueError(f"e0 must have shape (B, N, m) = {(Bn, N, cov.dim)}, got "
                             f"{tuple(e.shape)}")
        checked[0] = True

    def linearise(x, e):
        c, A, Bm = condition(x, e if iterated else None)
        if not checked[0]:
            check_condition(c, A, Bm, e)
        w = c - (Bm @ e[..., None])[..., 0] if (iterated and e is not None) else c
        Bw = cov.whiten(Bm)
        L, _ = torch.linalg.cholesky_ex(cov.effective(Bw))
        rw = torch.linalg.solve_triangular(L, w[..., None], upper=False)[..., 0]
        Aw = torch.linalg.solve_triangular(L, A, upper=False)
        Bn, N, k = c.shape
        return Linearisation(rw.reshape(Bn, N * k), Aw.reshape(Bn, N * k, A.shape[-1]),
                             extra=(L, Bw))

    def post_step(x, e, lin, delta):
        L, Bw = lin.extra
        Bn = delta.shape[0]
        N, k = L.shape[1], L.shape[-1]
        z = (lin.r + (lin.J @ delta[..., None])[..., 0]).reshape(Bn, N, k)
        y = torch.linalg.solve_triangular(L.transpose(-1, -2), z[..., None], upper=True)[..., 0]
        return -cov.apply_transposed(Bw, y)

    if e0 is not None and iterated:
        # N is known only from the condition: read it at e = 0 (the cheap path, without e0) so
        # that an e0 of another N is named here, not failed on inside the condition
        with torch.no_grad():
            c0, A0, B0 = condition(V.detach(x0), None)
            check_condition(c0, A0, B0, e0)

    # The observation residual estimate starts at e0; None is zero (the condition's cheap path).
    return _as_given(iterate(linearise, x0, e0, post_step, **options), single)
