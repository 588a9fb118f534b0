"""SparseCholesky (torchsgal.estimation.sparse) against dense torch.linalg.solve / inv on random
symmetric positive-definite block-sparse systems, for every backend.  A backend whose library is
not installed is skipped; CI installs them all, and there a skip fails the run
(TORCHSGAL_NO_SKIPS=1, tests/conftest.py)."""
import pytest
import torch

from torchsgal.estimation.sparse import BACKENDS, NotPositiveDefiniteError, SparseCholesky, available_backends


def block_system(n_blocks=12, block=3, n_edges=20, seed=0, duplicates=False):
    """A = sum_e J_e^T J_e + I over random edges (i, j) of blocks, J_e = [B_i B_j]: SPD with the
    sparsity of a pose graph's normal equations.  Returns the dense A and its lower-triangle
    pattern (rows, cols, values); with ``duplicates`` every entry is split in two entries."""
    g = torch.Generator().manual_seed(seed)
    n = n_blocks * block
    A = torch.eye(n, dtype=torch.float64)
    for _ in range(n_edges):
        i, j = torch.randperm(n_blocks, generator=g)[:2].tolist()
        J = torch.zeros(block, n, dtype=torch.float64)
        J[:, i * block:(i + 1) * block] = torch.randn(block, block, generator=g, dtype=torch.float64)
        J[:, j * block:(j + 1) * block] = torch.randn(block, block, generator=g, dtype=torch.float64)
        A += J.T @ J
    rows, cols = torch.tril_indices(n, n)
    keep = A[rows, cols] != 0
    rows, cols = rows[keep], cols[keep]
    values = A[rows, cols]
    if duplicates:
        share = torch.rand(values.shape, generator=g, dtype=torch.float64)
        perm = torch.randperm(2 * values.numel(), generator=g)
        rows, cols = torch.cat([rows, rows])[perm], torch.cat([cols, cols])[perm]
        values = torch.cat([values * share, values * (1 - share)])[perm]
    return A, rows, cols, values


INSTALLED = available_backends()
BACKEND_PARAMS = [pytest.param(b, marks=pytest.mark.skipif(b not in INSTALLED, reason=f"{b}'s library is not installed"))
                  for b in BACKENDS]


def test_all_backends_installed():
    missing = [b for b in BACKENDS if b not in INSTALLED]
    if missing:
        pytest.skip(f"not installed: {missing} (pip install 'torchsgal[sparse]'; CHOLMOD needs libsuitesparse-dev)")
    assert INSTALLED == BACKENDS


@pytest.mark.parametrize("backend", BACKEND_PARAMS)
@pytest.mark.parametrize("duplicates", [False, True])
def test_solve_matches_dense(backend, duplicates):
    A, rows, cols, values = block_system(duplicates=duplicates)
    n = A.shape[0]
    S = SparseCholesky(rows, cols, n, backend=backend)
    assert S.backend == backend
    kept = values.clone()
    S.factor(values)
    assert torch.equal(values, kept)  # not mutated
    g = torch.Generator().manual_seed(1)
    b = torch.randn(n, generator=g, dtype=torch.float64)
    B = torch.randn(n, 5, generator=g, dtype=torch.float64)
    x, X = S.solve(b), S.solve(B)
    assert x.shape == (n,) and X.shape == (n, 5) and x.dtype == torch.float64
    torch.testing.assert_close(x, torch.linalg.solve(A, b), rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(X, torch.linalg.solve(A, B), rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("backend", BACKEND_PARAMS)
def test_refactor_new_values(backend):
    A, rows, cols, values = block_system(seed=3)
    S = SparseCholesky(rows, cols, A.shape[0], backend=backend)
    b = torch.ones(A.shape[0], dtype=torch.float64)
    for scale in (1.0, 2.5):  # the same pattern, other values (one symbolic analysis)
        A2 = A + (scale - 1) * torch.diag(torch.diagonal(A))
        S.factor(A2[rows, cols])
        torch.testing.assert_close(S.solve(b), torch.linalg.solve(A2, b), rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("backend", BACKEND_PARAMS)
def test_marginal_blocks_match_dense_inverse(backend, monkeypatch):
    import torchsgal.estimation.sparse as sparse

    monkeypatch.setattr(sparse, "MARGINAL_CHUNK", 7)  # several chunks, one not a block multiple
    block = 3
    A, rows, cols, values = block_system(block=block, seed=5)
    S = SparseCholesky(rows, cols, A.shape[0], backend=backend)
    S.factor(values)
    starts = torch.tensor([0, 9, 3, 33, 14], dtype=torch.int64)  # 14: not on a block boundary
    M = S.marginal_blocks(starts, block)
    inv = torch.linalg.inv(A)
    expected = torch.stack([inv[s:s + block, s:s + block] for s in starts.tolist()])
    assert M.shape == (5, block, block)
    torch.testing.assert_close(M, expected, rtol=1e-10, atol=1e-12)
    assert S.marginal_blocks(torch.zeros(0, dtype=torch.int64), block).shape == (0, block, block)


@pytest.mark.parametrize("backend", BACKEND_PARAMS)
def test_float32_values_give_float32_results(backend):
    A, rows, cols, values = block_system(seed=2)
    S = SparseCholesky(rows, cols, A.shape[0], backend=backend)
    S.factor(values.float())
    b = torch.ones(A.shape[0])
    x = S.solve(b)
    assert x.dtype == torch.float32
    torch.testing.assert_close(x.double(), torch.linalg.solve(A, b.double()), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("backend", BACKEND_PARAMS)
def test_singular_and_indefinite_raise(backend):
    # a graph Laplacian of blocks with no prior: positive semi-definite, rank n - block
    block, n_blocks = 2, 5
    n = block * n_blocks
    L = torch.zeros(n, n, dtype=torch.float64)
    for i in range(n_blocks - 1):
        D = torch.zeros(block, n, dtype=torch.float64)
        D[:, i * block:(i + 1) * block] = torch.eye(block)
        D[:, (i + 1) * block:(i + 2) * block] = -torch.eye(block)
        L += D.T @ D
    rows, cols = torch.tril_indices(n, n)
    keep = L[rows, cols] != 0
    rows, cols = rows[keep], cols[keep]
    S = SparseCholesky(rows, cols, n, backend=backend)
    with pytest.raises(NotPositiveDefiniteError):
        S.factor(L[rows, cols])
    with pytest.raises(RuntimeError, match="successful factor"):
        S.solve(torch.ones(n, dtype=torch.float64))
    indefinite = L + torch.eye(n, dtype=torch.float64)
    indefinite[3, 3] = -1.0
    with pytest.raises(NotPositiveDefiniteError):
        S.factor(indefinite[rows, cols])
    assert issubclass(NotPositiveDefiniteError, torch.linalg.LinAlgError)
    # the solver recovers with a positive-definite matrix of the same pattern
    good = L + torch.eye(n, dtype=torch.float64)
    S.factor(good[rows, cols])
    b = torch.arange(n, dtype=torch.float64)
    torch.testing.assert_close(S.solve(b), torch.linalg.solve(good, b), rtol=1e-10, atol=1e-12)


def test_auto_picks_first_installed():
    A, rows, cols, values = block_system()
    assert SparseCholesky(rows, cols, A.shape[0]).backend == available_backends()[0]


def test_bad_input_errors():
    A, rows, cols, values = block_system()
    n = A.shape[0]
    with pytest.raises(ValueError, match="backend must be 'auto' or one of"):
        SparseCholesky(rows, cols, n, backend="umfpack")
    with pytest.raises(TypeError, match="rows must be an int64 tensor"):
        SparseCholesky(rows.int(), cols, n)
    with pytest.raises(ValueError, match="lower triangle"):
        SparseCholesky(cols, rows, n)
    with pytest.raises(ValueError, match=r"must lie in \[0, 3\]"):
        SparseCholesky(rows, cols, 4)
    with pytest.raises(ValueError, match="rows and cols must have one shape"):
        SparseCholesky(rows, cols[:-1], n)
    with pytest.raises(ValueError, match="size must be an integer >= 1"):
        SparseCholesky(rows, cols, 0)
    S = SparseCholesky(rows, cols, n)
    with pytest.raises(ValueError, match=rf"values must have shape \({rows.numel()},\)"):
        S.factor(values[:-1])
    with pytest.raises(TypeError, match="values must have a floating dtype"):
        S.factor(values.long())
    bad = values.clone()
    bad[0] = float("nan")
    with pytest.raises(ValueError, match="values must be finite"):
        S.factor(bad)
    S.factor(values)
    with pytest.raises(ValueError, match=rf"rhs must have shape \({n},\)"):
        S.solve(torch.ones(n + 1, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"starts must lie in"):
        S.marginal_blocks(torch.tensor([n - 2]), 3)
    with pytest.raises(ValueError, match="block must be an integer >= 1"):
        S.marginal_blocks(torch.tensor([0]), 0)


@pytest.mark.parametrize("backend", BACKEND_PARAMS)
@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_rhs_gives_non_finite_column_on_every_backend(backend, bad):
    # a non-finite right-hand side is not a singular matrix (no NotPositiveDefiniteError,
    # cholespy's included): every backend returns the non-finite column as such,
    # the finite columns solved, and keeps its factor
    A, rows, cols, values = block_system()
    n = A.shape[0]
    S = SparseCholesky(rows, cols, n, backend=backend)
    S.factor(values)
    rhs = torch.stack([torch.arange(n, dtype=torch.float64), torch.ones(n, dtype=torch.float64)], 1)
    rhs[4, 1] = bad
    x = S.solve(rhs)
    assert x.shape == (n, 2)
    torch.testing.assert_close(x[:, 0], torch.linalg.solve(A, rhs[:, 0]), rtol=1e-10, atol=1e-12)
    assert not bool(torch.isfinite(x[:, 1]).all())
    assert not bool(torch.isfinite(S.solve(rhs[:, 1])).all())  # a vector rhs alike
    b = torch.ones(n, dtype=torch.float64)
    torch.testing.assert_close(S.solve(b), torch.linalg.solve(A, b), rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("backend", BACKEND_PARAMS)
def test_empty_pattern_is_not_positive_definite(backend):
    # no entries at all: A is the zero matrix, singular, on every backend the module's own error
    empty = torch.zeros(0, dtype=torch.int64)
    S = SparseCholesky(empty, empty, 3, backend=backend)
    with pytest.raises(NotPositiveDefiniteError):
        S.factor(torch.zeros(0, dtype=torch.float64))
    with pytest.raises(RuntimeError, match="successful factor"):
        S.solve(torch.ones(3, dtype=torch.float64))
