"""The vectorised small-matrix Cholesky and triangular inverse of
torchsgal.estimation._small_linalg against torch.linalg (LAPACK)."""
import pytest
import torch

from torchsgal.estimation import _small_linalg as sl


def _spd(batch, n, dtype, seed=0):
    gen = torch.Generator().manual_seed(seed)
    A = torch.randn(*batch, n, n + 3, generator=gen, dtype=torch.float64)
    S = A @ A.transpose(-1, -2) / n + 0.1 * torch.eye(n, dtype=torch.float64)
    return S.to(dtype)


def _tol(dtype):
    # relative to the factor's scale: measured 3.6e-16 (Cholesky) and 8.7e-16 (inverses) in
    # float64, 2.6e-7 in float32
    return 1e-14 if dtype == torch.float64 else 2e-5


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("batch", [(), (5,), (2, 3), (700,)])
@pytest.mark.parametrize("n", [1, 3, 10])
def test_cholesky_and_inverses_match_lapack(dtype, batch, n):
    S = _spd(batch, n, dtype)
    S_t = S.movedim((-2, -1), (0, 1)).contiguous()
    L_t, info = sl.cholesky_t(S_t)
    L_ref = torch.linalg.cholesky(S.double())
    L = L_t.movedim((0, 1), (-2, -1))
    assert info.shape == batch and info.dtype == torch.int32 and (info == 0).all()
    scale = L_ref.abs().amax()
    assert ((L.double() - L_ref).abs().max() / scale) < _tol(dtype)
    assert (torch.triu(L, 1) == 0).all()
    Li = sl.tril_inverse_t(L_t).movedim((0, 1), (-2, -1))
    Li_ref = torch.linalg.inv(L_ref)
    assert ((Li.double() - Li_ref).abs().max() / Li_ref.abs().amax()) < 10 * _tol(dtype)
    # Both paths of inverse_cholesky_factor_t (LAPACK below MIN_BATCH, vectorised above).
    Lit, _ = sl.inverse_cholesky_factor_t(S_t)
    assert ((Lit.movedim((0, 1), (-2, -1)).double() - Li_ref).abs().max()
            / Li_ref.abs().amax()) < 10 * _tol(dtype)


@pytest.mark.parametrize("m", [4, 700])
def test_not_positive_definite_reports_the_failing_minor(m):
    """info as torch.linalg.cholesky_ex: the order of the first non-positive-definite leading
    minor, 0 elsewhere; the factor of a failing matrix is not finite (from that column on)."""
    S = _spd((m,), 6, torch.float64)
    S[1, 3, 3] = -1.0  # minor of order 4 fails
    S[2, 0, 0] = 0.0  # order 1
    S[3, 5, 5] = float("nan")  # order 6
    _, info_ref = torch.linalg.cholesky_ex(S)
    S_t = S.movedim((-2, -1), (0, 1)).contiguous()
    L_t, info = sl.cholesky_t(S_t)
    assert info.tolist() == info_ref.tolist()
    assert info[:4].tolist() == [0, 4, 1, 6]
    L = L_t.movedim((0, 1), (-2, -1))
    assert torch.isfinite(L[0]).all() and torch.isfinite(L[4:]).all()
    for b, col in ((1, 3), (2, 0), (3, 5)):
        assert not torch.isfinite(L[b, col:, col]).all()
    Li, info2 = sl.inverse_cholesky_factor_t(S_t)
    assert info2.tolist() == info_ref.tolist()
    Li = Li.movedim((0, 1), (-2, -1))
    assert torch.isfinite(Li[0]).all()
    assert not torch.isfinite(Li[1:4]).flatten(1).all(-1).any()
