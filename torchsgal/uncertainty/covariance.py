"""Covariance matrices: the checks of a covariance argument and the factors that whiten by one.

``check_covariance`` raises unless a tensor is a symmetric positive (semi-)definite covariance,
reading all its measures in one host sync; ``covariance_factor`` runs the same check on a
definite covariance and returns the square root it factored on the way (the estimators' noise
models); ``_supported_factor`` gives a square root of a
covariance on its supported directions (exactly zero rows and columns are known directions)
and the whitening by it.
"""
from __future__ import annotations

import torch
from torch.autograd import forward_ad

from ..functional import checks
from ..functional._blocking import values_readable
from ..functional.checks import SUPPORTED_DTYPES


def _sym(S: torch.Tensor) -> torch.Tensor:
    return 0.5 * (S + S.transpose(-1, -2))


def _mv(M: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    return (M @ x.unsqueeze(-1)).squeeze(-1)


def check_covariance(S: torch.Tensor, dim: int, name: str = "covariance", tol: float | None = None,
                     definite: bool = True):
    """Raises unless S (..., dim, dim) is symmetric positive definite (``definite=False``:
    positive semi-definite, within ``tol`` of the largest entry).  Shape and dtype are always
    checked; the values (one host sync: all the measures are read together) only where they can
    be read: not on 'meta', under a torch.func transform or torch.compile.  An empty batch
    passes.  ``tol``: None (1e-5 float32, 1e-10 float64) or a finite real number >= 0;
    ``dim``: an integer >= 0 (bool refused)."""
    if not isinstance(dim, torch.SymInt):  # a traced size (torch.compile) is taken as it is
        dim = checks.integer(dim, "dim", 0)
    _covariance_shape(S, dim, name)
    checks.dense(S, name)
    checks.boolean(definite, "definite")
    if tol is not None:
        tol = checks.finite_number(tol, "tol", ">= 0")
    if S.numel() == 0 or not values_readable(S):
        return
    tol = _default_tol(S, tol)
    _raise_for_measures(_read(_covariance_measures(S, definite, tol)), S, name, definite, tol)


def covariance_factor(S: torch.Tensor, name: str = "covariance") -> tuple[bool, torch.Tensor]:
    """(diagonal, factor) of a covariance S (..., m, m), m >= 1, checked as ``check_covariance``
    (definite, default tolerance) in the same single read: ``diagonal`` says whether every
    matrix of S is diagonal and nothing differentiates S; ``factor`` is then the square-root
    diagonal (..., m), else the Cholesky factor (..., m, m) of S's symmetric part, whose
    derivatives in S's off-diagonal entries the square-root diagonal would miss.  Where values
    cannot be read (on 'meta', under torch.func or torch.compile): not diagonal, the factor
    unchecked."""
    if not isinstance(S, torch.Tensor):
        raise TypeError(f"{name} must be a tensor (..., m, m), got {type(S).__name__}")
    if S.dim() < 2 or S.shape[-1] != S.shape[-2] or S.shape[-1] < 1:
        raise ValueError(f"{name} must have shape (..., m, m) with m >= 1, got {tuple(S.shape)}")
    _covariance_shape(S, S.shape[-1], name)
    checks.dense(S, name)
    d = S.diagonal(dim1=-2, dim2=-1)
    if S.numel() == 0:  # an empty batch: nothing to check
        return True, d.sqrt()
    tol = _default_tol(S, None)
    measures, L = _covariance_measures(S, True, tol, factor=True)
    if not values_readable(S):
        return False, L
    off_diagonal = (S - torch.diag_embed(d)).abs().amax().reshape(1).to(S.dtype)
    *values, off = _read(measures, off_diagonal)
    _raise_for_measures(values, S, name, True, tol)
    differentiated = (torch.is_grad_enabled() and S.requires_grad) or \
        forward_ad.unpack_dual(S).tangent is not None
    return (True, d.sqrt()) if off == 0 and not differentiated else (False, L)


def _covariance_shape(S, dim: int, name: str) -> None:
    if not isinstance(S, torch.Tensor) or S.dtype not in SUPPORTED_DTYPES:
        raise TypeError(f"{name} must be a torch.Tensor of dtype torch.float32 or torch.float64, got "
                        f"{getattr(S, 'dtype', type(S).__name__)}")
    if S.dim() < 2 or S.shape[-2:] != (dim, dim):
        raise ValueError(f"{name} must have shape (..., {dim}, {dim}), got {tuple(S.shape)}")


def _default_tol(S: torch.Tensor, tol: float | None) -> float:
    return (1e-5 if S.dtype == torch.float32 else 1e-10) if tol is None else tol


def _covariance_measures(S: torch.Tensor, definite: bool, tol: float, factor: bool = False):
    """The measures that check_covariance reads, as one tensor (3,) of S's dtype, not read here
    (no host sync): all entries finite (1 or 0), the largest relative asymmetry, and how many of
    the batch fail the (semi-)definiteness test.  Semi-definite within ``tol``: the smallest
    eigenvalue of S / max|S| is > -tol, tested as a Cholesky factorisation of S / max|S| + tol I
    (not with an eigensolver, which checks its own convergence: a host sync of its own on CUDA).
    S non-empty.  ``factor`` (definite only): also the Cholesky factor of S's symmetric part that
    the test computes, as (measures, factor)."""
    finite = torch.isfinite(S)
    S0 = torch.where(finite, S, torch.zeros((), dtype=S.dtype, device=S.device))
    scale = S0.abs().amax(dim=(-1, -2)).clamp_min(torch.finfo(S.dtype).tiny)
    asym = ((S0 - S0.transpose(-1, -2)).abs().amax(dim=(-1, -2)) / scale).max()
    sym = _sym(S0)
    if not definite:
        eye = torch.eye(S.shape[-1], dtype=S.dtype, device=S.device)
        sym = sym / scale[..., None, None] + tol * eye
    L, info = torch.linalg.cholesky_ex(sym)
    measures = torch.stack((finite.all().to(S.dtype), asym, (info != 0).sum().to(S.dtype)))
    return (measures, L) if factor else measures


def _raise_for_measures(values, S: torch.Tensor, name: str, definite: bool, tol: float) -> None:
    """Raises ValueError naming ``name`` if the measures of ``_covariance_measures`` (Python
    floats, already read) say that S is not a covariance."""
    finite, asym, bad = values
    if not finite:
        raise ValueError(f"{name} has non-finite entries")
    if asym > tol:
        raise ValueError(f"{name} is not symmetric (max relative asymmetry {asym:.3g})")
    if bad and definite:
        raise ValueError(f"{name} is not positive definite ({int(bad)} of the batch)")
    if bad:  # only on the way to the error: the smallest relative eigenvalue for the message
        scale = S.abs().amax(dim=(-1, -2)).clamp_min(torch.finfo(S.dtype).tiny)
        low = (torch.linalg.eigvalsh(_sym(S))[..., 0] / scale).min()
        raise ValueError(f"{name} is not positive semi-definite (min relative eigenvalue "
                         f"{float(low):.3g})")


def _read(*tensors: torch.Tensor) -> list[float]:
    """The values of the given tensors (flattened, in order) as Python floats, in one host sync."""
    dtype = next((t.dtype for t in tensors if t.is_floating_point()), torch.float32)
    return torch.cat([t.detach().reshape(-1).to(dtype) for t in tensors]).tolist()


def _known_directions(S: torch.Tensor) -> torch.Tensor:
    """(..., dof) bool: the rows (and columns) of S that are exactly zero."""
    zero = S == 0
    return zero.all(-1) & zero.all(-2)


def _with_known_directions(S: torch.Tensor) -> torch.Tensor:
    """S with a 1 on the diagonal of its zero rows and columns: definite where S is definite on
    the other directions, and equal to S where it has none."""
    return S + torch.diag_embed(_known_directions(S).to(S.dtype))


def _supported_factor(S: torch.Tensor, allow_singular: bool):
    """(M, keep, whiten): M (..., dof, dof) with M M^T = S, keep (..., dof) the supported
    directions, and whiten(xi) -> (z, log pseudo-determinant of S) with |z| the norm of xi's
    supported part in the metric S^+.  Known (zero) directions: a Cholesky factor of
    _with_known_directions(S) (S itself where none is zero).  ``allow_singular``: the support
    is spanned by the eigenvectors U of S whose eigenvalues exceed the tolerance, and S is
    factored there as the Cholesky factor of U^T S U on it (the identity elsewhere), U held as
    a constant: the derivatives are those of S's restriction to its support, finite also where
    eigenvalues repeat (an isotropic covariance), where eigh's are not."""
    if not allow_singular:
        keep = ~_known_directions(S)
        L, info = torch.linalg.cholesky_ex(_sym(_with_known_directions(S)))
        if values_readable(S) and bool((info != 0).any()):
            raise ValueError("covariance is not positive definite on its supported directions (it was not "
                             "validated: validate=False); use allow_singular=True for a semi-definite one")

        def whiten(xi):
            z = torch.linalg.solve_triangular(L, (xi * keep).unsqueeze(-1), upper=False).squeeze(-1)
            return z, 2.0 * torch.log(torch.diagonal(L, dim1=-2, dim2=-1)).sum(-1)
        return L * keep.unsqueeze(-1), keep, whiten
    sym = _sym(S)
    lam, U = torch.linalg.eigh(sym.detach())
    scale = S.detach().abs().amax(dim=(-1, -2), keepdim=True).squeeze(-1)
    keep = lam > _default_tol(S, None) * scale
    both = keep.unsqueeze(-1) & keep.unsqueeze(-2)
    # U^T S U on the support (diag(lam) but for rounding, and differentiable in S), the identity
    # on the rest: eigh sorts the dropped (smallest) eigenvalues first, so L = blockdiag(I, L_kept)
    restricted = torch.where(both, U.mT @ sym @ U, torch.zeros_like(sym)) + \
        torch.diag_embed((~keep).to(S.dtype))
    L = torch.linalg.cholesky_ex(restricted)[0]

    def whiten_eigen(xi):
        z = torch.linalg.solve_triangular(L, (_mv(U.mT, xi) * keep).unsqueeze(-1), upper=False).squeeze(-1)
        return z, 2.0 * torch.log(torch.diagonal(L, dim1=-2, dim2=-1)).sum(-1)
    return U @ (L * keep.unsqueeze(-2)), keep, whiten_eigen
