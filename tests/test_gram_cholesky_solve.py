"""Cholesky solves of Gram matrices A = G diag(d) G^T (``dense_solve.gram_cholesky_solve``, the
operator ``torchsgal::gram_cholesky_solve`` and its C kernel in
torchsgal/estimation/_native_cholesky.h, which forms A per system in its vector lanes): against a
float64 LAPACK solve of the formed matrix, both dtypes, shared and per-system d, both loops of
the kernel; failures; the tensor code where the kernels are off or autograd records;
opcheck, gradcheck of the registered backward, vmap; bad arguments."""
from __future__ import annotations

import os

import pytest
import torch
from torch.library import opcheck

from torchsgal.estimation import dense_solve
from torchsgal.estimation.dense_solve import cholesky_solve, gram_cholesky_solve
from torchsgal.functional import native

_no_kernel = pytest.mark.skipif(not dense_solve.available()
                                and os.environ.get("TORCHSGAL_NO_SKIPS") != "1",
                                reason="the dense-solve C kernel was not compiled")


def needs_kernel(test):
    """Tests of the C kernel itself: left out of the run with the kernels off (.ci/run)."""
    return pytest.mark.kernels(_no_kernel(test))


def gram_inputs(batch, m, p, k, dtype, shared=False, seed=0):
    """G (batch, m, p) with singular values in [1, 10], d in [0.5, 1.5] (A's condition number
    at most ~300), R (batch, m, k); built in float64."""
    g = torch.Generator().manual_seed(seed)
    U, _ = torch.linalg.qr(torch.randn(*batch, m, m, dtype=torch.float64, generator=g))
    V, _ = torch.linalg.qr(torch.randn(*batch, p, p, dtype=torch.float64, generator=g))
    s = 1 + 9 * torch.rand(*batch, m, dtype=torch.float64, generator=g)
    G = U @ (s[..., :, None] * V[..., :m, :])
    d = 0.5 + torch.rand(*((1,) if shared else batch), p, dtype=torch.float64, generator=g)
    R = torch.randn(*batch, m, k, dtype=torch.float64, generator=g)
    return G.to(dtype), d.to(dtype), R.to(dtype)


def truth(G, d, R):
    """L, L^-1 R and A^-1 R of A = G diag(d) G^T, all in float64 by torch (LAPACK)."""
    G64, d64, R64 = G.double(), d.double(), R.double()
    L = torch.linalg.cholesky((G64 * d64[..., None, :]) @ G64.mT)
    X = torch.linalg.solve_triangular(L, R64, upper=False)
    return L, X, torch.linalg.solve_triangular(L.mT, X, upper=True)


def rel_error(x, ref):
    if not ref.numel():
        return 0.0
    return float((x.double() - ref).abs().amax() / ref.abs().amax())


def tolerance(dtype, m):
    # backward-stable formation, Cholesky and substitution at condition number ~300
    return 300 * m * torch.finfo(dtype).eps * 10


def call_kernel(G, d, R, back, d_stride):
    """The C function called directly (m > 64: its one-system-at-a-time loop)."""
    n, m, p, k = G.shape[0], G.shape[-2], G.shape[-1], R.shape[-1]
    G, d, R = G.contiguous(), d.contiguous(), R.contiguous()
    L, X, Y = G.new_empty(n, m, m), torch.empty_like(R), torch.empty_like(R)
    info = torch.empty(n, dtype=torch.int32)
    dense_solve._lib.gram_cholesky_solve(G.data_ptr(), d.data_ptr(), R.data_ptr(), L.data_ptr(),
                                         X.data_ptr(), Y.data_ptr() if back else 0, info.data_ptr(),
                                         n, m, p, k, d_stride, torch.get_num_threads(),
                                         G.dtype is torch.float64)
    return L, X, Y if back else None, info


# (batch, unknowns, columns of G, right-hand sides): one system, partial and full groups of
# lanes (4 to 16 systems), the Gauss-Helmert sizes (10 x 20 with 12 columns), more columns than
# one pass (16), and two mid-sized systems (fewer than dense_solve.MIN_BATCH: the tensor code)
CASES = [((1,), 1, 1, 1), ((3,), 6, 6, 2), ((8,), 10, 20, 12), ((4, 5), 10, 20, 12),
         ((13,), 9, 30, 20), ((2,), 16, 17, 1), ((9,), 40, 41, 3), ((3,), 5, 7, 0),
         ((2,), 20, 21, 2)]


@pytest.mark.parametrize("shared", [False, True])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("batch,m,p,k", CASES)
def test_matches_lapack_on_the_formed_matrix(batch, m, p, k, dtype, shared):
    G, d, R = gram_inputs(batch, m, p, k, dtype, shared, seed=m + p)
    L_ref, X_ref, Y_ref = truth(G, d, R)
    for back in (True, False):
        L, X, Y, info = gram_cholesky_solve(G, d, R, back)
        assert not info.any() and info.shape == G.shape[:-2] and info.dtype == torch.int32
        assert bool((L.triu(1) == 0).all())
        assert rel_error(L, L_ref) < tolerance(dtype, m)
        assert rel_error(X, X_ref) < tolerance(dtype, m)
        if back:
            assert rel_error(Y, Y_ref) < tolerance(dtype, m) * 300  # A^-1: the condition number
        else:
            assert Y is None


@needs_kernel
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_both_loops_of_the_kernel(dtype):
    """The lanes (m <= 64, what the operator runs) and the one-system loop (m = 65, called
    directly), with d per system and shared (stride 0)."""
    for m, p in ((10, 20), (65, 66)):
        G, d, R = gram_inputs((9,), m, p, 3, dtype, seed=m)
        L_ref, X_ref, Y_ref = truth(G, d, R)
        d1 = d[:1].contiguous()
        for dd, stride, ref in ((d, p, (L_ref, X_ref, Y_ref)), (d1, 0, truth(G, d1.expand(9, p), R))):
            L, X, Y, info = call_kernel(G, dd, R, True, stride)
            assert not info.any()
            for got, want, scale in ((L, ref[0], 1), (X, ref[1], 1), (Y, ref[2], 300)):
                assert rel_error(got, want) < tolerance(dtype, m) * scale, (m, stride)


@needs_kernel
def test_the_operator_runs_the_kernel_and_the_tensor_code_elsewhere():
    """Bitwise: the operator's results are the kernel's with the kernels on, and the tensor code's
    (the product formed, then torch's Cholesky) with them off or where autograd records."""
    G, d, R = gram_inputs((20,), 10, 20, 4, torch.float64, seed=3)
    got = gram_cholesky_solve(G, d, R, True)
    for a, b in zip(got, call_kernel(G, d, R, True, 20)):
        assert torch.equal(a, b)
    reference = dense_solve._gram_tensor(G, d, R, True)
    with native.disabled():
        off = gram_cholesky_solve(G, d, R, True)
    for a, b in zip(off, reference):
        assert torch.equal(a, b)
    recorded = gram_cholesky_solve(G.clone().requires_grad_(), d, R, True)
    composed = cholesky_solve((G * d[..., None, :]) @ G.mT, R, True)
    for a, b in zip(recorded, composed):
        assert torch.equal(a.detach(), b)
    assert recorded[1].grad_fn is not None


def test_a_failed_system_reports_its_pivot_and_leaves_the_others_alone():
    G, d, R = gram_inputs((9,), 10, 20, 3, torch.float64, seed=4)
    d = d.clone()
    d[3] = 0.0  # A = 0: the first pivot fails
    G = G.clone()
    G[5, 4] = float("nan")  # a non-finite row: pivot 5 fails
    L, X, Y, info = gram_cholesky_solve(G, d, R, True)
    _, _, _, info_ref = cholesky_solve((G * d[..., None, :]) @ G.mT, R, True)
    assert info.tolist() == info_ref.tolist() == [0, 0, 0, 1, 0, 5, 0, 0, 0]
    for t in (L, X, Y):
        assert t[[3, 5]].isnan().all() and not t[[0, 1, 2, 4, 6, 7, 8]].isnan().any()
    good = [0, 1, 2, 4, 6, 7, 8]
    L_ref, X_ref, _ = truth(G[good], d[good], R[good])
    assert rel_error(X[good], X_ref) < tolerance(torch.float64, 10)


def test_batch_shapes_broadcast_and_empty_batches():
    G, d, R = gram_inputs((2, 3), 4, 6, 2, torch.float64, seed=5)
    d1 = d[0, 0]  # (p,): one d for every system
    L, X, Y, _ = gram_cholesky_solve(G, d1, R[0], True)  # R (3, 4, 2) broadcast over the 2
    L_ref, X_ref, Y_ref = truth(G, d1.expand(2, 3, 6), R[0].expand(2, 3, 4, 2))
    assert L.shape == (2, 3, 4, 4) and X.shape == (2, 3, 4, 2)
    assert rel_error(Y, Y_ref) < tolerance(torch.float64, 4) * 300
    L0, X0, Y0, info0 = gram_cholesky_solve(G[:0], d1, R[:0], True)
    assert L0.shape == (0, 3, 4, 4) and X0.shape == (0, 3, 4, 2) and info0.shape == (0, 3)


def test_opcheck():
    G, d, R = gram_inputs((5,), 4, 6, 3, torch.float64, seed=6)
    for back in (True, False):
        opcheck(torch.ops.torchsgal.gram_cholesky_solve.default,
                (G.clone().requires_grad_(), d.clone().requires_grad_(), R.clone().requires_grad_(),
                 back))
        opcheck(torch.ops.torchsgal.gram_cholesky_solve.default,
                (G.mT.contiguous().mT, d, R.mT.contiguous().mT, back))


def test_registered_backward_is_torchs_gradient():
    """gradcheck of the operator's own backward (G, d, R), and the same gradients as autograd
    through the formed product and torch.linalg."""
    G, d, R = gram_inputs((3,), 4, 5, 2, torch.float64, seed=7)
    G, d, R = G.requires_grad_(), d.requires_grad_(), R.requires_grad_()

    def op(G, d, R):
        L, X, Y, _ = torch.ops.torchsgal.gram_cholesky_solve(G, d, R, True)
        return L, X, Y

    assert torch.autograd.gradcheck(op, (G, d, R))
    weights = [torch.randn(t.shape, dtype=torch.float64) for t in op(G, d, R)]
    got = torch.autograd.grad(sum((w * t).sum() for w, t in zip(weights, op(G, d, R))), (G, d, R))
    ref = torch.autograd.grad(sum((w * t).sum() for w, t in zip(weights, truth(G, d, R))), (G, d, R))
    for a, b in zip(got, ref):
        assert rel_error(a, b) < 1e-10


def test_vmap():
    G, d, R = gram_inputs((2, 3), 5, 7, 2, torch.float64, seed=8)

    def fn(G, d, R):
        return torch.ops.torchsgal.gram_cholesky_solve(G, d, R, True)

    mapped = torch.func.vmap(fn, in_dims=(0, 0, None))(G, d, R[0])
    for i in range(2):
        looped = fn(G[i], d[i], R[0])
        for a, b in zip(mapped, looped):
            assert torch.allclose(a[i].double(), b.double(), rtol=0, atol=1e-13) if a.is_floating_point() \
                else torch.equal(a[i], b)


def test_bad_arguments():
    G, d, R = gram_inputs((2,), 3, 4, 1, torch.float64)
    with pytest.raises(ValueError, match=r"d must have shape \(\.\.\., p\) with p = 4"):
        gram_cholesky_solve(G, d[..., :3], R)
    with pytest.raises(ValueError, match=r"R must have shape \(\.\.\., m, k\) with m = 3"):
        gram_cholesky_solve(G, d, R[:, :2])
    with pytest.raises(ValueError, match=r"G must have shape \(\.\.\., m, p\)"):
        gram_cholesky_solve(G[0, 0], d, R)
    with pytest.raises((TypeError, ValueError), match="float64"):
        gram_cholesky_solve(G, d.float(), R)
    with pytest.raises(TypeError, match="back"):
        gram_cholesky_solve(G, d, R, back=1)
    with pytest.raises(ValueError, match="batch shapes do not broadcast"):
        gram_cholesky_solve(G, d, torch.randn(3, 3, 1, dtype=torch.float64))
    with pytest.raises(ValueError, match="same batch shape"):
        torch.ops.torchsgal.gram_cholesky_solve(G, d[:1], R, False)


def test_inputs_are_not_modified():
    G, d, R = gram_inputs((9,), 10, 20, 2, torch.float64, seed=9)
    G0, d0, R0 = G.clone(), d.clone(), R.clone()
    gram_cholesky_solve(G, d, R, back=True)
    assert torch.equal(G, G0) and torch.equal(d, d0) and torch.equal(R, R0)
