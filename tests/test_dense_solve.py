"""Batched Cholesky solves (torchsgal/estimation/dense_solve.py, the C kernel of
torchsgal/estimation/_native_cholesky.h): the kernel's two loops (several systems per pass, one
at a time) against torch's LAPACK Cholesky and triangular solves at the sizes and batches where
each runs, both dtypes; failures (the pivot reported, NaN in that system only); results that do
not depend on the batch around a system or on the threads; torch.library.opcheck, gradcheck,
vmap and torch.compile of the operators; bad arguments; and the engine's use of the combined
Jacobian form."""
from __future__ import annotations

import os

import pytest
import torch
from torch.library import opcheck

from torchsgal.estimation import dense_solve
from torchsgal.estimation.dense_solve import cholesky_solve, triangular_solve
from torchsgal.functional import native

_no_kernel = pytest.mark.skipif(not dense_solve.available()
                                and os.environ.get("TORCHSGAL_NO_SKIPS") != "1",
                                reason="the dense-solve C kernel was not compiled")


def needs_kernel(test):
    """Tests of the C kernel itself: left out of the run with the kernels off (.ci/run)."""
    return pytest.mark.kernels(_no_kernel(test))

# (systems, unknowns, right-hand sides): one and a few systems, full and partial groups of lanes
# (4 to 16 systems), the largest sizes of each loop, and more columns than one pass of the kernel
# takes (16)
CASES = [(1, 1, 1), (1, 6, 3), (3, 10, 12), (8, 16, 1), (13, 10, 20), (5, 17, 2), (9, 48, 1),
         (4, 64, 5), (2, 3, 0)]


def spd(n, m, dtype, seed=0, cond=1e3):
    """n symmetric positive definite (m, m) matrices with condition numbers up to ``cond``,
    built in float64."""
    g = torch.Generator().manual_seed(seed)
    Q, _ = torch.linalg.qr(torch.randn(n, m, m, dtype=torch.float64, generator=g))
    ev = torch.logspace(0, torch.log10(torch.tensor(cond)).item(), m, dtype=torch.float64)
    ev = ev * (1 + 0.1 * torch.rand(n, m, dtype=torch.float64, generator=g))
    A = Q @ torch.diag_embed(ev) @ Q.mT
    return ((A + A.mT) / 2).to(dtype)


def truth(A, R):
    """L, L^-1 R and A^-1 R in float64 by torch (LAPACK)."""
    A64, R64 = A.double(), R.double()
    L = torch.linalg.cholesky(A64)
    X = torch.linalg.solve_triangular(L, R64, upper=False)
    return L, X, torch.linalg.solve_triangular(L.mT, X, upper=True)


def rel_error(x, ref):
    scale = ref.abs().amax() if ref.numel() else torch.tensor(1.0, dtype=torch.float64)
    return float(((x.double() - ref).abs().amax() / scale) if ref.numel() else 0.0)


def tolerance(dtype, m):
    # backward-stable Cholesky and substitution at condition number 1e3
    return 1e3 * m * torch.finfo(dtype).eps * 10


def call_kernel(A, R, back, lanes):
    """The C loop called directly (lanes 1: several systems per pass; 0: one at a time)."""
    n, m, k = A.shape[0], A.shape[-1], R.shape[-1]
    A, R = A.contiguous(), R.contiguous()
    L, X, Y = torch.empty_like(A), torch.empty_like(R), torch.empty_like(R)
    info = torch.empty(n, dtype=torch.int32)
    dense_solve._lib.cholesky_solve(A.data_ptr(), R.data_ptr(), L.data_ptr(), X.data_ptr(),
                                    Y.data_ptr() if back else 0, info.data_ptr(), n, m, k, lanes,
                                    torch.get_num_threads(), A.dtype is torch.float64)
    return L, X, Y if back else None, info


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("n,m,k", CASES)
def test_cholesky_solve_matches_lapack(n, m, k, dtype):
    """The operator (the kernel where it runs, torch's LAPACK elsewhere) against a float64 LAPACK
    solve, with back substitution and without."""
    A, R = spd(n, m, dtype), torch.randn(n, m, k, dtype=torch.float64).to(dtype)
    L_ref, X_ref, Y_ref = truth(A, R)
    for back in (True, False):
        L, X, Y, info = cholesky_solve(A, R, back=back)
        assert info.dtype == torch.int32 and info.shape == (n,) and not info.any()
        assert L.dtype == X.dtype == dtype
        assert bool((L.triu(1) == 0).all())
        assert rel_error(L, L_ref) < tolerance(dtype, m)
        assert rel_error(X, X_ref) < tolerance(dtype, m)
        if back:
            assert rel_error(Y, Y_ref) < tolerance(dtype, m) * 1e3  # A^-1 R: cond(A) = 1e3
        else:
            assert Y is None


@needs_kernel
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("n,m,k", CASES)
def test_both_kernel_loops_match_lapack(n, m, k, dtype):
    A, R = spd(n, m, dtype, seed=1), torch.randn(n, m, k, dtype=torch.float64).to(dtype)
    L_ref, X_ref, Y_ref = truth(A, R)
    for lanes in (1, 0):
        L, X, Y, info = call_kernel(A, R, True, lanes)
        assert not info.any()
        assert bool((L.triu(1) == 0).all())
        for got, ref, scale in ((L, L_ref, 1), (X, X_ref, 1), (Y, Y_ref, 1e3)):
            assert rel_error(got, ref) < tolerance(dtype, m) * scale, (lanes, m)


@needs_kernel
@pytest.mark.parametrize("n,m", [(1, 6), (3, 16), (20, 10), (4, 48), (6, 64)])
def test_the_operator_runs_the_kernel_where_the_rule_says(n, m):
    """Bitwise: the operator's CPU results are the kernel's (lanes 1) where the size rule
    picks it (dense_solve.uses_kernel), and torch's otherwise."""
    A, R = spd(n, m, torch.float64, seed=2), torch.randn(n, m, 3, dtype=torch.float64)
    got = cholesky_solve(A, R, back=True)
    assert dense_solve.uses_kernel(A)
    for a, b in zip(got, call_kernel(A, R, True, 1)):
        assert torch.equal(a, b)
    with native.disabled():
        assert not dense_solve.uses_kernel(A)
        lapack = cholesky_solve(A, R, back=True)
    for a, b in zip(lapack, dense_solve._cholesky_solve_tensor(A, R, True)):
        assert torch.equal(a, b)


def test_size_rule():
    """Small systems always, mid-sized ones in batches of MIN_BATCH or more, large ones never."""
    def runs(n, m):
        return dense_solve.uses_kernel(torch.empty(n, m, m, dtype=torch.float64))
    if not dense_solve.available() or not native.enabled():
        assert not runs(100, 10)
        return
    assert runs(1, dense_solve.SMALL_SIZE) and runs(100, 10)
    assert not runs(dense_solve.MIN_BATCH - 1, dense_solve.SMALL_SIZE + 1)
    assert runs(dense_solve.MIN_BATCH, dense_solve.KERNEL_MAX_SIZE)
    assert not runs(100, dense_solve.KERNEL_MAX_SIZE + 1)
    assert not dense_solve.uses_kernel(torch.empty(100, 10, 10, dtype=torch.float16))


@pytest.mark.parametrize("kernel", [True, False])
@pytest.mark.parametrize("m", [5, 30])
@pytest.mark.parametrize("bad", ["negative", "nan", "inf", "singular"])
def test_a_failed_system_reports_its_pivot_and_leaves_the_others_alone(m, bad, kernel):
    if kernel:
        _failures(m, bad)
    else:
        with native.disabled():
            _failures(m, bad)


def _failures(m, bad):
    """info = the failing pivot's row + 1 as LAPACK reports it, NaN in that system's outputs,
    and every other system of the batch as if solved alone."""
    n = 11
    A, R = spd(n, m, torch.float64, seed=3), torch.randn(n, m, 2, dtype=torch.float64)
    row = 3
    if bad == "negative":
        A[4, row, row] = -1.0
    elif bad == "nan":
        A[4, row, row] = float("nan")
    elif bad == "inf":
        A[4, row, row] = float("inf")
    else:  # the rows and columns row and row + 1 equal: pivot row + 1 is zero
        A[4, row + 1, :], A[4, :, row + 1] = A[4, row, :], A[4, :, row]
        A[4, row + 1, row + 1] = A[4, row, row]
    L, X, Y, info = cholesky_solve(A, R, back=True)
    expected = {"negative": row + 1, "nan": row + 1, "inf": row + 1, "singular": row + 2}[bad]
    if bad in ("negative", "nan"):
        assert int(info[4]) == int(torch.linalg.cholesky_ex(A[4])[1]) == expected
    elif bad == "inf":  # LAPACK takes sqrt(inf) = inf as a pivot; the operators do not
        assert int(info[4]) == expected and int(torch.linalg.cholesky_ex(A[4])[1]) == 0
    else:  # rounding leaves a tiny pivot of either sign: not positive, or accepted
        assert int(info[4]) == expected or float(L[4, row + 1, row + 1]) < 1e-6 * float(L[4, row, row])
    if int(info[4]):
        assert bool(L[4].isnan().all() and X[4].isnan().all() and Y[4].isnan().all())
    others = [i for i in range(n) if i != 4]
    assert not info[others].any()
    clean = cholesky_solve(A[others], R[others], back=True)
    for a, b in zip(clean, (L, X, Y, info)):
        if native.enabled():  # the kernel: each system's own operations, whatever the batch
            assert torch.equal(a, b[others])
        else:  # LAPACK's batched solves may block a batch differently
            assert torch.allclose(a, b[others], rtol=1e-12, atol=0)


@needs_kernel
@pytest.mark.parametrize("m", [10, 40])
def test_results_do_not_depend_on_the_batch_or_the_threads(m):
    n = 6001 if m == 10 else 203  # enough work to split over two threads (MIN_PER_THREAD)
    A, R = spd(n, m, torch.float64, seed=4), torch.randn(n, m, 4, dtype=torch.float64)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = cholesky_solve(A, R, back=True)
        torch.set_num_threads(2)
        two = cholesky_solve(A, R, back=True)
    finally:
        torch.set_num_threads(before)
    for a, b in zip(one, two):
        assert torch.equal(a, b)
    part = cholesky_solve(A[5:13], R[5:13], back=True)
    for a, b in zip(part, one):
        assert torch.equal(a, b[5:13])


def test_only_the_lower_triangle_is_read():
    A, R = spd(9, 12, torch.float64, seed=5), torch.randn(9, 12, 3, dtype=torch.float64)
    garbage = A + torch.randn_like(A).triu(1) * 100
    for a, b in zip(cholesky_solve(A, R, True), cholesky_solve(garbage, R, True)):
        assert torch.equal(a, b)
    L = cholesky_solve(A, R)[0]
    for t in (False, True):
        assert torch.equal(triangular_solve(L, R, t), triangular_solve(L + L.mT.triu(1), R, t))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("n,m,k", [(1, 4, 1), (13, 10, 20), (9, 48, 2), (2, 70, 3)])
def test_triangular_solve_matches_lapack(n, m, k, dtype):
    A, R = spd(n, m, torch.float64, seed=6), torch.randn(n, m, k, dtype=torch.float64)
    L = torch.linalg.cholesky(A)
    for transpose in (False, True):
        ref = torch.linalg.solve_triangular(L.mT if transpose else L, R, upper=transpose)
        got = triangular_solve(L.to(dtype), R.to(dtype), transpose=transpose)
        assert got.dtype == dtype
        assert rel_error(got, ref) < tolerance(dtype, m) * 10


def test_batch_shapes_broadcast_and_empty_batches():
    A = spd(6, 5, torch.float64, seed=7).reshape(2, 3, 5, 5)
    R = torch.randn(3, 5, 2, dtype=torch.float64)
    L, X, Y, info = cholesky_solve(A, R, back=True)
    assert L.shape == (2, 3, 5, 5) and X.shape == Y.shape == (2, 3, 5, 2) and info.shape == (2, 3)
    assert torch.allclose(Y, torch.linalg.solve(A, R.expand(2, 3, 5, 2)), rtol=1e-12, atol=1e-14)
    assert triangular_solve(L, R).shape == (2, 3, 5, 2)
    L0, X0, Y0, info0 = cholesky_solve(A[:0], R.expand(2, 3, 5, 2)[:0], back=True)
    assert L0.shape == (0, 3, 5, 5) and X0.shape == (0, 3, 5, 2) and info0.shape == (0, 3)


def test_opcheck():
    """Contiguous and transposed (non-contiguous) inputs: the outputs are contiguous either way."""
    A, R = spd(5, 6, torch.float64, seed=8), torch.randn(5, 6, 3, dtype=torch.float64)
    Rt = torch.randn(5, 3, 6, dtype=torch.float64).mT
    for back in (True, False):
        for r in (R, Rt):
            opcheck(torch.ops.torchsgal.cholesky_solve.default,
                    (A.clone().requires_grad_(), r.clone().requires_grad_(), back))
        opcheck(torch.ops.torchsgal.cholesky_solve.default, (A.mT, Rt, back))
    L = torch.linalg.cholesky(A)
    for transpose in (True, False):
        opcheck(torch.ops.torchsgal.triangular_solve.default,
                (L.clone().requires_grad_(), R.clone().requires_grad_(), transpose))
        opcheck(torch.ops.torchsgal.triangular_solve.default, (L.mT.contiguous().mT, Rt, transpose))


def test_gradients_are_those_of_torchs_cholesky():
    """gradcheck of every output through the operators, and the same gradients as autograd
    through torch.linalg."""
    A0 = spd(3, 4, torch.float64, seed=9, cond=10.0)
    R = torch.randn(3, 4, 2, dtype=torch.float64, requires_grad=True)
    S = A0.clone().requires_grad_()

    def outputs(S, R):
        A = (S + S.mT) / 2  # the symmetric part: the operators read one triangle
        L, X, Y, _ = cholesky_solve(A, R, back=True)
        return L, X, Y, triangular_solve(L, R, transpose=True)

    assert torch.autograd.gradcheck(outputs, (S, R))
    assert torch.autograd.gradgradcheck(lambda S, R: outputs(S, R)[2], (S, R))
    w = [torch.randn_like(o) for o in outputs(S, R)]
    got = torch.autograd.grad(sum((o * c).sum() for o, c in zip(outputs(S, R), w)), (S, R))
    A = (S + S.mT) / 2
    L = torch.linalg.cholesky(A)
    X = torch.linalg.solve_triangular(L, R, upper=False)
    ref_out = (L, X, torch.linalg.solve_triangular(L.mT, X, upper=True),
               torch.linalg.solve_triangular(L.mT, R, upper=True))
    ref = torch.autograd.grad(sum((o * c).sum() for o, c in zip(ref_out, w)), (S, R))
    for a, b in zip(got, ref):
        assert torch.allclose(a, b, rtol=1e-10, atol=1e-12)


def test_forward_mode_and_torch_func_derivatives_are_torchs():
    """jvp, jacfwd, grad and jacfwd(jacfwd) through the operators equal those through
    torch.linalg (forward mode was zero and torch.func.grad raised through the bare operators)."""
    A = spd(3, 4, torch.float64, seed=12, cond=10.0)
    R = torch.randn(3, 4, 2, dtype=torch.float64)
    tA = torch.randn_like(A)
    tA, tR = tA + tA.mT, torch.randn_like(R)

    def ours(a, r):
        L, X, Y, _ = cholesky_solve(a, r, back=True)
        return L, X, Y, triangular_solve(L, r * r, transpose=True)

    def ref(a, r):
        L = torch.linalg.cholesky(a)
        X = torch.linalg.solve_triangular(L, r, upper=False)
        return (L, X, torch.linalg.solve_triangular(L.mT, X, upper=True),
                torch.linalg.solve_triangular(L.mT, r * r, upper=True))

    for a, b in zip(torch.func.jvp(ours, (A, R), (tA, tR))[1], torch.func.jvp(ref, (A, R), (tA, tR))[1]):
        assert float(b.abs().amax()) > 0
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)
    with torch.autograd.forward_ad.dual_level():
        dual = torch.autograd.forward_ad.make_dual(R, tR)
        tangent = torch.autograd.forward_ad.unpack_dual(ours(A, dual)[2]).tangent
    torch.testing.assert_close(tangent, torch.func.jvp(lambda r: ref(A, r)[2], (R,), (tR,))[1])
    def loss(f):
        return lambda a, r: sum((o * o).sum() for o in f(a, r)[1:])
    for a, b in zip(torch.func.grad(loss(ours), argnums=(0, 1))(A, R),
                    torch.func.grad(loss(ref), argnums=(0, 1))(A, R)):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)
    second = torch.func.jacfwd(torch.func.jacfwd(lambda r: loss(ours)(A, r)))(R)
    torch.testing.assert_close(second, torch.func.jacfwd(torch.func.jacfwd(lambda r: loss(ref)(A, r)))(R),
                               rtol=1e-9, atol=1e-11)


def test_inductor_compiles_them():
    """torch.compile with its default backend on transposed inputs (the fake outputs' strides are
    the operators')."""
    A = spd(4, 5, torch.float64, seed=13)
    Rt = torch.randn(4, 2, 5, dtype=torch.float64).mT

    def fn(A, R):
        L, X, Y, info = cholesky_solve(A, R, back=True)
        return Y + triangular_solve(L, X, transpose=True), info

    compiled = torch.compile(fn, fullgraph=True)(A.mT, Rt)
    eager = fn(A.mT, Rt)
    torch.testing.assert_close(compiled[0], eager[0], rtol=1e-13, atol=1e-14)
    assert torch.equal(compiled[1], eager[1])


def test_vmap_and_compile():
    A, R = spd(6, 7, torch.float64, seed=10).reshape(2, 3, 7, 7), torch.randn(3, 7, 2, dtype=torch.float64)

    def fn(A, R):
        L, X, Y, info = cholesky_solve(A, R, back=True)
        return Y + triangular_solve(L, X, transpose=True), info

    looped = [fn(A[i], R) for i in range(2)]
    mapped = torch.func.vmap(fn, in_dims=(0, None))(A, R)
    for i in range(2):
        assert torch.allclose(mapped[0][i], looped[i][0], rtol=0, atol=1e-13)
        assert torch.equal(mapped[1][i], looped[i][1])
    compiled = torch.compile(fn, fullgraph=True, backend="eager")(A, R)
    eager = fn(A, R)
    assert torch.equal(compiled[0], eager[0]) and torch.equal(compiled[1], eager[1])


def test_bad_arguments():
    A, R = spd(2, 3, torch.float64), torch.randn(2, 3, 1, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"A must have shape \(\.\.\., m, m\)"):
        cholesky_solve(A[..., :2], R)
    with pytest.raises(ValueError, match=r"R must have shape \(\.\.\., m, k\) with m = 3"):
        cholesky_solve(A, R[:, :2])
    with pytest.raises((TypeError, ValueError), match="float64"):
        cholesky_solve(A, R.float())
    with pytest.raises(TypeError, match="back"):
        cholesky_solve(A, R, back=1)
    with pytest.raises(TypeError, match="transpose"):
        triangular_solve(A, R, transpose="yes")
    with pytest.raises(TypeError, match="A"):
        cholesky_solve(A.long(), R)
    with pytest.raises(ValueError, match=r"batch shapes do not broadcast: A \(\d+,\), R \(3,\)"):
        cholesky_solve(A, torch.randn(3, A.shape[-1], 1, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"batch shapes do not broadcast: L \(\d+,\), R \(3,\)"):
        triangular_solve(A, torch.randn(3, A.shape[-1], 1, dtype=torch.float64))


def test_inputs_are_not_modified():
    A, R = spd(9, 10, torch.float64, seed=11), torch.randn(9, 10, 2, dtype=torch.float64)
    A0, R0 = A.clone(), R.clone()
    L, X, Y, _ = cholesky_solve(A, R, back=True)
    triangular_solve(L, R, transpose=True)
    assert torch.equal(A, A0) and torch.equal(R, R0)
