"""``torchsgal::affine_rows`` (functional/affine.py): x @ W + c over a batch, the product behind
a group element acting on many points and that action's Jacobian.  The C kernel against the
tensor code (``baddbmm``) for every row length it has a loop for and one it has not; the
operator's registration (opcheck, vmap, derivatives); every group's ``act`` and
``act_jacobians`` on a broadcast batch with the kernels on and off."""
from __future__ import annotations

import os

import pytest
import torch
from conftest import GROUP_CLASSES
from torch.library import opcheck

from torchsgal.functional import affine, native

f64 = torch.float64
op = torch.ops.torchsgal.affine_rows


def needs_kernel(test):
    """Tests of the C kernel itself (torchsgal.functional._native): left out of the run with the
    kernels off (.ci/run), skipped where the extension was not built."""
    skip = pytest.mark.skipif(not native.available() and os.environ.get("TORCHSGAL_NO_SKIPS") != "1",
                              reason="torchsgal.functional._native not built")
    return pytest.mark.kernels(skip(test))


def _inputs(B, N, k, m, dtype, seed=0, with_c=True):
    gen = torch.Generator().manual_seed(seed)
    x = torch.randn(B, N, k, generator=gen, dtype=f64).to(dtype)
    W = torch.randn(B, k, m, generator=gen, dtype=f64).to(dtype)
    c = torch.randn(B, m, generator=gen, dtype=f64).to(dtype) if with_c else None
    return x, W, c


@pytest.fixture
def kernel_calls(monkeypatch):
    """The calls of the C kernel (its argument B) while the test runs."""
    calls: list = []
    if native._lib is not None:
        real = native._lib.affine_rows
        monkeypatch.setattr(native._lib, "affine_rows", lambda *a: calls.append(a[5]) or real(*a))
    return calls


@needs_kernel
@pytest.mark.parametrize("dtype", [torch.float32, f64], ids=str)
@pytest.mark.parametrize("m", [1, 2, 3, 4, 5, 6, 9, 18, 21, 27, 40, 64])
@pytest.mark.parametrize("k", [1, 3, 4, 7, 9, 12])
def test_the_kernel_is_the_batched_product(k, m, dtype, kernel_calls):
    """Every row length with a loop of its own (2, 3, 4, 6, 9, 18, 21, 27, 40) and others (1, 5,
    64), with and without c: the kernel's rows equal baddbmm's to a few units in the last place
    (the sums of k products are formed in another order)."""
    eps = torch.finfo(dtype).eps
    for with_c in (True, False):
        x, W, c = _inputs(5, 11, k, m, dtype, seed=k * 100 + m, with_c=with_c)
        got = op(x, W, c)
        want = torch.baddbmm(c.unsqueeze(1), x, W) if with_c else torch.bmm(x, W)
        scale = (x.abs() @ W.abs() + (c.abs().unsqueeze(1) if with_c else 0)).to(f64)
        assert ((got.to(f64) - want.to(f64)).abs() <= 4 * eps * scale).all()
    assert len(kernel_calls) == 2


@needs_kernel
@pytest.mark.parametrize("dtype", [torch.float32, f64], ids=str)
@pytest.mark.parametrize("k", [1, 3, 8, 9])
def test_each_entry_is_the_products_summed_in_order(k, dtype):
    """Rows of x (up to 8 entries: vectors of four; more: one entry at a time) and every row
    length: each entry is ((x_0 W_0 + x_1 W_1) + ...) + c, one rounding per operation, in that
    order: written out here with elementwise tensor operations, equal bit for bit."""
    for m in (2, 3, 4, 5, 6, 9, 18, 21, 27, 40):
        for with_c in (True, False):
            x, W, c = _inputs(3, 13, k, m, dtype, seed=7 * k + m, with_c=with_c)
            want = x[..., :1] * W[:, None, 0]
            for a in range(1, k):
                want = want + x[..., a:a + 1] * W[:, None, a]
            if with_c:
                want = want + c[:, None]
            assert torch.equal(op(x, W, c), want), (k, m, with_c)


@needs_kernel
def test_strided_inputs_are_read_as_their_values(kernel_calls):
    """A transposed W, a sliced x and a strided c: the values they show."""
    x, W, c = _inputs(3, 40, 4, 18, f64, seed=1)
    Wt = W.mT.contiguous().mT  # (B, k, m) with the k axis innermost
    xs = torch.randn(3, 40, 9, dtype=f64)[..., 2:6]
    cs = torch.randn(3, 36, dtype=f64)[:, ::2]
    got = op(xs, Wt, cs)
    torch.testing.assert_close(got, torch.baddbmm(cs.unsqueeze(1), xs, Wt), rtol=1e-14, atol=1e-14)
    assert len(kernel_calls) == 1


def test_bad_arguments_name_themselves():
    x, W, c = _inputs(2, 3, 4, 5, f64)
    with pytest.raises(ValueError, match=r"x must have shape \(Bx, N, k\) and W \(B, k, m\) with Bx a divisor of B"):
        op(x, W[:, :3], c)
    with pytest.raises(ValueError, match=r"divisor of B, got x \(2, 3, 4\) and W \(3, 4, 5\)"):
        op(x, torch.cat([W, W[:1]]), torch.cat([c, c[:1]]))
    with pytest.raises(ValueError, match=r"x must have shape"):
        op(x[0], W, c)
    with pytest.raises(ValueError, match=r"c must have shape \(2, 5\) \(B, m\), got \(2, 4\)"):
        op(x, W, c[:, :4])
    with pytest.raises((TypeError, ValueError), match="W"):
        op(x, W.float(), c)


def test_empty_batches_and_long_rows(kernel_calls):
    """No problems, no rows, and rows longer than the kernel forms: the operator's result is the
    product's, from the tensor code (the kernel is not called)."""
    for B, N, m in ((0, 4, 3), (3, 0, 3), (2, 5, 80)):
        x, W, c = _inputs(B, N, 3, m, f64)
        got = op(x, W, c)
        assert got.shape == (B, N, m)
        torch.testing.assert_close(got, torch.baddbmm(c.unsqueeze(1), x, W), rtol=1e-14, atol=1e-14)
    assert kernel_calls == []


@needs_kernel
def test_batches_split_over_threads_give_the_same_rows(kernel_calls):
    """A batch large enough for the kernel to hand it out over two threads: every row as the
    product's (each problem's rows are formed alone, so the split changes no bit)."""
    x, W, c = _inputs(4096, 100, 3, 18, f64, seed=3)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = op(x, W, c)
        torch.set_num_threads(2)
        two = op(x, W, c)
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(one, two)
    torch.testing.assert_close(two, torch.baddbmm(c.unsqueeze(1), x, W), rtol=1e-13, atol=1e-13)
    assert len(kernel_calls) == 2


def test_opcheck():
    """Values, fake implementation, autograd registration and vmap rule, with inputs that require
    grad (and without c)."""
    for dtype in (torch.float32, f64):
        for with_c in (True, False):
            x, W, c = _inputs(3, 6, 4, 18, dtype, with_c=with_c)
            opcheck(op.default, (x, W, c))
            grads = [t.clone().requires_grad_() if t is not None else None for t in (x, W, c)]
            opcheck(op.default, tuple(grads))


def test_gradients_are_the_products():
    """The registered backward (g W^T, x^T g, the sum of g over the rows) against gradcheck."""
    x, W, c = _inputs(2, 5, 3, 4, f64)
    args = tuple(t.requires_grad_() for t in (x, W, c))
    assert torch.autograd.gradcheck(lambda *a: op(*a), args)
    assert torch.autograd.gradcheck(lambda a, b: op(a, b, None), args[:2])


def test_vmap_is_a_loop_over_the_mapped_axis():
    """Any one argument mapped (c alone too, on another axis), without c, and a mapped axis of
    size 0."""
    x, W, c = _inputs(3, 7, 4, 9, f64)
    ulps = dict(rtol=1e-14, atol=1e-14)
    xs = torch.stack([x, 2 * x])
    got = torch.func.vmap(op, in_dims=(0, None, None))(xs, W, c)
    torch.testing.assert_close(got, torch.stack([op(x, W, c), op(2 * x, W, c)]), **ulps)
    got = torch.func.vmap(op, in_dims=(None, 1, None))(x, torch.stack([W, W.neg()], 1), c)
    torch.testing.assert_close(got, torch.stack([op(x, W, c), op(x, -W, c)]), **ulps)
    got = torch.func.vmap(op, in_dims=(None, None, 1))(x, W, torch.stack([c, 3 * c], 1))
    torch.testing.assert_close(got, torch.stack([op(x, W, c), op(x, W, 3 * c)]), **ulps)
    got = torch.func.vmap(lambda a: op(a, W, None))(xs)
    torch.testing.assert_close(got, torch.stack([op(x, W, None), op(2 * x, W, None)]), **ulps)
    assert torch.func.vmap(op, in_dims=(0, None, None))(xs[:0], W, c).shape == (0, 3, 7, 9)


# the products of ``act`` and ``act_jacobians`` the kernel forms (``affine.KERNEL_MAX_M``): the
# action's rows (every group, both dtypes; Sim(3)'s Jacobian acts once more, without the
# translation, for its quotient rule) and the Jacobian's rows (rows x dof) of at most 40 entries
# in float64 (every group's: SGal(3)'s 4 x 10) and 9 in float32 (SO(2)'s 2, SE(2)'s 6, SO(3)'s 9)
_KERNEL_PRODUCTS = {(name, dtype): n for name, d64, d32 in
                    (("SO2", 2, 2), ("SE2", 2, 2), ("SO3", 2, 2), ("SE3", 2, 1), ("SE23", 2, 1),
                     ("SGal3", 2, 1), ("Sim3", 3, 2))
                    for dtype, n in ((f64, d64), (torch.float32, d32))}


@needs_kernel
@pytest.mark.parametrize("dtype", [torch.float32, f64], ids=str)
@pytest.mark.parametrize("G", GROUP_CLASSES, ids=lambda g: g.__name__)
def test_every_group_acts_on_a_broadcast_batch_through_it(G, dtype, kernel_calls):
    """One element per batch row acting on 800 points (point_axes=1): ``act`` and
    ``act_jacobians`` with the kernels on (the operator runs where it pays) equal the same with
    them off (the tensor code) to a few units in the last place, and the kernel formed the
    products ``_KERNEL_PRODUCTS`` names."""
    gen = torch.Generator().manual_seed(7)
    g = G.random(6, dtype=dtype, generator=gen)
    x = torch.randn(6, 800, G.point_dim, dtype=dtype, generator=gen)
    on = (g.act(x, point_axes=1), *g.act_jacobians(x, point_axes=1))
    n_on = len(kernel_calls)
    with native.disabled():
        off = (g.act(x, point_axes=1), *g.act_jacobians(x, point_axes=1))
    for a, b in zip(on, off):
        torch.testing.assert_close(a, b, rtol=8 * torch.finfo(dtype).eps, atol=8 * torch.finfo(dtype).eps)
    assert n_on == _KERNEL_PRODUCTS[G.__name__, dtype], n_on
    assert len(kernel_calls) == n_on


def test_recorded_and_transformed_calls_have_the_products_derivatives():
    """Where autograd records or torch.func transforms, ``rows_times`` (through ``_RowsTimes``
    where the kernel runs) has the product's derivatives: gradients, jacrev, and jvp mapped over
    directions, against the same through ``baddbmm``."""
    x, W, c = _inputs(4, 300, 3, 18, f64)
    Wg = W.clone().requires_grad_()
    affine.rows_times(x, Wg, c).square().sum().backward()
    torch.testing.assert_close(Wg.grad, 2 * x.mT @ torch.baddbmm(c.unsqueeze(1), x, W), rtol=1e-13, atol=1e-12)
    xg = x.clone().requires_grad_()
    affine.rows_times(xg, W, c).square().sum().backward()
    torch.testing.assert_close(xg.grad, 2 * torch.baddbmm(c.unsqueeze(1), x, W) @ W.mT, rtol=1e-13, atol=1e-12)
    jac = torch.func.jacrev(lambda w: affine.rows_times(x[:1], w, c[:1]))(W[:1])
    assert jac.shape == (1, 300, 18, 1, 3, 18)
    torch.testing.assert_close(jac[0, :, :, 0], torch.einsum("na,jl->njal", x[0], torch.eye(18, dtype=f64)))
    dW = torch.randn(6, *W.shape, dtype=f64)
    dc = torch.randn(6, *c.shape, dtype=f64)
    dx = torch.randn(6, *x.shape, dtype=f64)
    for f, ref in ((lambda w, b: affine.rows_times(x, w, b), lambda w, b: torch.baddbmm(b.unsqueeze(1), x, w)),):
        r, t = torch.func.vmap(lambda u, v: torch.func.jvp(f, (W, c), (u, v)))(dW, dc)
        r0, t0 = torch.func.vmap(lambda u, v: torch.func.jvp(ref, (W, c), (u, v)))(dW, dc)
        torch.testing.assert_close(r, r0, rtol=1e-14, atol=1e-14)
        torch.testing.assert_close(t, t0, rtol=1e-14, atol=1e-14)
    t = torch.func.vmap(lambda u: torch.func.jvp(lambda a: affine.rows_times(a, W, c), (x,), (u,))[1])(dx)
    torch.testing.assert_close(t, dx @ W, rtol=1e-14, atol=1e-14)
    # second derivatives: hessian (jacfwd of jacrev) through the Function, jacfwd of jacfwd
    # through the tensor code
    small = (x[:1, :200], W[:1], c[:1])
    for second in (torch.func.hessian, lambda f: torch.func.jacfwd(torch.func.jacfwd(f))):
        h = second(lambda w: affine.rows_times(small[0], w, small[2]).square().sum())(small[1])
        want = 2 * torch.einsum("na,nb,jl->ajbl", small[0][0], small[0][0], torch.eye(18, dtype=f64))
        torch.testing.assert_close(h[0, :, :, 0], want, rtol=1e-12, atol=1e-10)


@needs_kernel
def test_derivatives_run_the_kernel(kernel_calls):
    """Reverse mode, and forward mode mapped over six directions of W and c (the engine's
    forward-mode Jacobian of a user's ``T.act(p) - q``), form their products by the kernel: one
    call for the value and one for all six tangents, x not copied six times."""
    x, W, c = _inputs(4, 400, 3, 3, f64)
    affine.rows_times(x, W.clone().requires_grad_(), c).sum().backward()
    assert kernel_calls == [4]
    kernel_calls.clear()
    dW, dc = torch.randn(6, *W.shape, dtype=f64), torch.randn(6, *c.shape, dtype=f64)
    torch.func.vmap(lambda u, v: torch.func.jvp(lambda w, b: affine.rows_times(x, w, b), (W, c), (u, v)))(dW, dc)
    assert kernel_calls == [4, 24]


@needs_kernel
@pytest.mark.parametrize("dtype", [torch.float32, f64], ids=str)
def test_one_x_for_several_W(dtype, kernel_calls):
    """x (Bx, N, k) with Bx a divisor of B: problem b reads x[b mod Bx], equal bit for bit to the
    kernel on x repeated; the gradient of x sums over the problems that share it."""
    x, W, c = _inputs(6, 50, 4, 9, dtype)
    got = op(x[:2], W, c)
    assert torch.equal(got, op(x[:2].repeat(3, 1, 1), W, c))
    assert kernel_calls == [6, 6]
    with native.disabled():
        torch.testing.assert_close(op(x[:2], W, c), got, rtol=0, atol=8 * torch.finfo(dtype).eps * 10)
    if dtype == f64:
        args = (x[:1, :5].clone().requires_grad_(), W[:3, :, :4].clone().requires_grad_(), c[:3, :4].clone().requires_grad_())
        assert torch.autograd.gradcheck(lambda *a: op(*a), args)
        opcheck(op.default, args)
