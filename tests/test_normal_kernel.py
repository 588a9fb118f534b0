"""torchsgal::normal_assemble (estimation/graph/normal_kernel.py): every factor's J^T J and J^T r
added at its slots, written out here with numpy's ``add.at``; the C kernel against that for
every block width it takes, both dtypes, summed and per-factor blocks and the strided layouts
the engine hands it; the operator's registration (opcheck, vmap, no derivative, no argument
written) and the engine's use of it."""
from __future__ import annotations

import contextlib

import numpy as np
import pytest
import torch
from test_factor_kernels import needs_kernel
from torch.library import opcheck

from torchsgal.estimation import dense_solve
from torchsgal.estimation.graph import normal_kernel
from torchsgal.functional import native

f64 = torch.float64
op = torch.ops.torchsgal.normal_assemble

def case(B=3, E=5, m=4, Dk=6, size=50, D=11, summed=False, dtype=f64, seed=0):
    """J (B, E, m, Dk), r (B, E, m), slots drawn with repeats, random bases to add into."""
    gen = torch.Generator().manual_seed(seed)
    J = torch.randn(B, E, m, Dk, generator=gen, dtype=f64).to(dtype)
    r = torch.randn(B, E, m, generator=gen, dtype=f64).to(dtype)
    rows = 1 if summed else E
    slots = torch.randint(0, size, (rows, Dk * Dk), generator=gen)
    g_slots = torch.randint(0, D, (rows, Dk), generator=gen)
    values = torch.randn(B, size, generator=gen, dtype=f64).to(dtype)
    g = torch.randn(B, D, generator=gen, dtype=f64).to(dtype)
    return J, r, slots, values, g_slots, g


def written_out(J, r, slots, values, g_slots, g, summed):
    """The sums by numpy in float64: per factor (or over the factors) H = J^T J, J^T r, added
    at the slots with ``np.add.at`` (repeated slots sum)."""
    Jn, rn = J.double().numpy(), r.double().numpy()
    H = np.einsum("bemi,bemj->beij", Jn, Jn)
    gb = np.einsum("bemi,bem->bei", Jn, rn)
    if summed:
        H, gb = H.sum(1, keepdims=True), gb.sum(1, keepdims=True)
    B = J.shape[0]
    want_v, want_g = values.double().numpy().copy(), g.double().numpy().copy()
    rows = np.arange(B)[:, None]
    np.add.at(want_v, (rows, slots.reshape(1, -1).numpy()), H.reshape(B, -1))
    np.add.at(want_g, (rows, g_slots.reshape(1, -1).numpy()), gb.reshape(B, -1))
    return torch.from_numpy(want_v), torch.from_numpy(want_g)


def layouts(J, r):
    """The same J and r in the layouts the engine passes: contiguous, the tangent axis moved
    last (forward mode), a factor axis expanded (a uniform residual), r a transposed view."""
    moved = J.movedim(-1, 0).contiguous().movedim(0, -1)
    yield J, r
    yield moved, r.mT.contiguous().mT
    yield J[:, :1].expand(J.shape), r[:, :1].expand(r.shape)


@pytest.mark.parametrize("kernel", [True, False])
@pytest.mark.parametrize("summed", [False, True])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_blocks_are_the_products_added_at_their_slots(dtype, summed, kernel):
    """Every block width 1..12 (the kernel's fixed-size code) and 13 (the tensor code), each
    layout; the inputs keep their values."""
    tol = dict(rtol=1e-12, atol=1e-11) if dtype is f64 else dict(rtol=1e-5, atol=1e-4)
    for Dk in list(range(1, normal_kernel.MAX_DK + 2)):
        J, r, slots, values, g_slots, g = case(Dk=Dk, summed=summed, dtype=dtype, seed=Dk)
        for Jl, rl in layouts(J, r):
            want = written_out(Jl, rl, slots, values, g_slots, g, summed)
            before = (values.clone(), g.clone())
            with native.disabled() if not kernel else contextlib.nullcontext():
                v, gv = op(Jl, rl, slots, values, g_slots, g, summed)
            assert torch.equal(values, before[0]) and torch.equal(g, before[1])
            assert v.dtype == dtype and gv.dtype == dtype
            torch.testing.assert_close(v.double(), want[0], **tol)
            torch.testing.assert_close(gv.double(), want[1], **tol)


@needs_kernel
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("summed", [False, True])
def test_each_entry_is_the_row_products_summed_in_order(dtype, summed):
    """Every block width (vectors of four from 3 columns, one entry at a time below): entry
    (a, c), a <= c, of a factor's H is ((x_a x_c of row 0 + that of row 1) + ...) over its rows
    in order (a summed block: over its factors' rows in order), mirrored, and added once to the
    value at its slot; g likewise with x_a r.  Written out here with elementwise operations
    (distinct slots: one addition each), equal bit for bit."""
    B, E, m = 3, 4, 3
    for Dk in range(1, normal_kernel.MAX_DK + 1):
        J, r, _, _, _, _ = case(B=B, E=E, m=m, Dk=Dk, dtype=dtype, seed=Dk)
        rows = 1 if summed else E
        size, D = rows * Dk * Dk + 5, rows * Dk + 3
        slots = torch.randperm(size, generator=torch.Generator().manual_seed(Dk))[:rows * Dk * Dk]
        g_slots = torch.randperm(D, generator=torch.Generator().manual_seed(Dk + 1))[:rows * Dk]
        slots, g_slots = slots.reshape(rows, Dk * Dk), g_slots.reshape(rows, Dk)
        values = torch.randn(B, size, dtype=f64).to(dtype)
        g = torch.randn(B, D, dtype=f64).to(dtype)
        Jr = J.reshape(B, 1, E * m, Dk) if summed else J
        rr = r.reshape(B, 1, E * m) if summed else r
        h = torch.zeros(B, rows, Dk, Dk, dtype=dtype)
        gb = torch.zeros(B, rows, Dk, dtype=dtype)
        for i in range(Jr.shape[2]):
            x = Jr[:, :, i]
            h = h + x[..., :, None] * x[..., None, :]
            gb = gb + x * rr[:, :, i, None]
        upper = torch.triu(torch.ones(Dk, Dk, dtype=torch.bool))
        h = torch.where(upper, h, h.mT)  # the kernel forms x_a x_c for a <= c and mirrors it
        want_v, want_g = values.clone(), g.clone()
        want_v[:, slots.reshape(-1)] += h.reshape(B, -1)
        want_g[:, g_slots.reshape(-1)] += gb.reshape(B, -1)
        v, gv = op(J, r, slots, values, g_slots, g, summed)
        assert torch.equal(v, want_v) and torch.equal(gv, want_g), Dk


@needs_kernel
def test_kernel_and_tensor_code_agree_and_blocks_are_symmetric():
    """The kernel's blocks are exactly symmetric (the upper triangle mirrored); against the
    tensor code to rounding; one or two threads give the same bits."""
    J, r, _, _, _, _ = case(B=64, E=7, m=5, Dk=9)
    B, E, Dk = 64, 7, 9
    slots = torch.arange(E * Dk * Dk).reshape(E, Dk * Dk)
    g_slots = torch.arange(E * Dk).reshape(E, Dk)
    values, g = torch.zeros(B, E * Dk * Dk, dtype=f64), torch.zeros(B, E * Dk, dtype=f64)
    v, gv = op(J, r, slots, values, g_slots, g, False)
    H = v.reshape(B, E, Dk, Dk)
    assert torch.equal(H, H.mT)
    with native.disabled():
        v0, g0 = op(J, r, slots, values, g_slots, g, False)
    torch.testing.assert_close(v, v0, rtol=1e-13, atol=1e-13)
    torch.testing.assert_close(gv, g0, rtol=1e-13, atol=1e-13)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1 if threads > 1 else 2)
        again = op(J, r, slots, values, g_slots, g, False)
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(again[0], v) and torch.equal(again[1], gv)


@pytest.mark.parametrize("kernel", [True, False])
def test_empty_batches_and_blocks(kernel):
    """B = 0 problems, E = 0 factors (summed or not): the values and g unchanged."""
    with native.disabled() if not kernel else contextlib.nullcontext():
        for summed in (False, True):
            J, r, slots, values, g_slots, g = case(summed=summed)
            v, gv = op(J[:0], r[:0], slots, values[:0], g_slots, g[:0], summed)
            assert v.shape == (0, values.shape[1]) and gv.shape == (0, g.shape[1])
            rows = slice(None) if summed else slice(0, 0)
            v, gv = op(J[:, :0], r[:, :0], slots[rows], values, g_slots[rows], g, summed)
            assert torch.equal(v, values) and torch.equal(gv, g)


@pytest.mark.parametrize("kernel", [True, False])
def test_a_block_without_columns_adds_nothing(kernel):
    """Dk = 0 (a factor on no tangent directions): values and g unchanged on both paths."""
    J, r, _, values, _, g = case()
    J = J[..., :0]
    slots, g_slots = torch.zeros(5, 0, dtype=torch.int64), torch.zeros(5, 0, dtype=torch.int64)
    with native.disabled() if not kernel else contextlib.nullcontext():
        v, gv = op(J, r, slots, values, g_slots, g, False)
        v2, g2 = normal_kernel.assemble(J, r, slots, values, g_slots, g, False)
    assert torch.equal(v, values) and torch.equal(gv, g)
    assert torch.equal(v2, values) and torch.equal(g2, g)


def test_bad_arguments_name_themselves():
    J, r, slots, values, g_slots, g = case()
    with pytest.raises(ValueError, match=r"J must have shape \(B, E, m, Dk\), got \(5, 4, 6\)"):
        op(J[0], r, slots, values, g_slots, g, False)
    with pytest.raises(ValueError, match=r"r must have shape \(3, 5, 4\), got \(3, 5, 3\)"):
        op(J, r[..., :3], slots, values, g_slots, g, False)
    with pytest.raises(ValueError, match=r"slots must be int64 of shape \(5, 36\)"):
        op(J, r, slots[:, :-1], values, g_slots, g, False)
    with pytest.raises(ValueError, match=r"g_slots must be int64 of shape \(1, 6\)"):
        op(J, r, slots[:1], values, g_slots, g, True)
    with pytest.raises(ValueError, match=r"values must have shape \(3, n\), got \(1, 50\)"):
        op(J, r, slots, values[:1], g_slots, g, False)
    with pytest.raises(TypeError, match="dtype"):
        op(J, r, slots, values.float(), g_slots, g, False)


@needs_kernel
def test_the_kernel_rejects_an_index_out_of_range():
    J, r, slots, values, g_slots, g = case()
    with pytest.raises(ValueError, match="slots must lie in"):
        op(J, r, slots + values.shape[1], values, g_slots, g, False)
    with pytest.raises(ValueError, match="g_slots must lie in"):
        op(J, r, slots, values, g_slots - 1, g, False)


@pytest.mark.parametrize("kernel", [True, False])
def test_no_argument_is_written_and_no_derivative_passes(kernel):
    """A functional operator (its sums are new tensors, the inputs keep their versions) with no
    autograd formula: a backward through it raises; ``assemble`` differentiates the tensor code
    instead, and its gradient is that of the written-out products."""
    J, r, slots, values, g_slots, g = case()
    with native.disabled() if not kernel else contextlib.nullcontext():
        before = (values._version, g._version)
        v, gv = op(J, r, slots, values, g_slots, g, False)
        assert (values._version, g._version) == before
        assert v.data_ptr() != values.data_ptr() and gv.data_ptr() != g.data_ptr()
        Jg = J.clone().requires_grad_()
        with pytest.raises(RuntimeError, match="no autograd formula"):
            op(Jg, r, slots, values, g_slots, g, False)[0].sum().backward()
        v, gv = normal_kernel.assemble(Jg, r, slots, values, g_slots, g, False)
        (v.square().sum() + gv.sum()).backward()
    Jr = J.clone().requires_grad_()
    H = Jr.mT @ Jr
    gb = (Jr.mT @ r.unsqueeze(-1)).squeeze(-1)
    want_v = values.index_add(1, slots.reshape(-1), H.reshape(3, -1))
    want_g = g.index_add(1, g_slots.reshape(-1), gb.reshape(3, -1))
    (want_v.square().sum() + want_g.sum()).backward()
    torch.testing.assert_close(Jg.grad, Jr.grad, rtol=1e-13, atol=1e-12)


def test_opcheck():
    for summed in (False, True):
        J, r, slots, values, g_slots, g = case(B=2, E=3, m=2, Dk=4, summed=summed)
        opcheck(op.default, (J, r, slots, values, g_slots, g, summed))
        opcheck(op.default, (J.float(), r.float(), slots, values.float(), g_slots, g.float(), summed))


@pytest.mark.parametrize("summed", [False, True])
def test_vmap_is_a_loop_over_the_mapped_axis(summed):
    J, r, slots, values, g_slots, g = case(B=6, summed=summed)
    V = 2
    J, r, values, g = (t.unflatten(0, (V, -1)) for t in (J, r, values, g))
    for vdim in (0, 1, None):  # values and g mapped along either axis, or shared
        vals = {0: values, 1: values.movedim(0, 1), None: values[0]}[vdim]
        gs = {0: g, 1: g.movedim(0, 1), None: g[0]}[vdim]
        got = torch.vmap(op, in_dims=(0, 0, None, vdim, None, vdim, None))(
            J, r, slots, vals, g_slots, gs, summed)
        for k in range(V):
            base = (values[k], g[k]) if vdim is not None else (values[0], g[0])
            one = op(J[k], r[k], slots, base[0], g_slots, base[1], summed)
            assert all(torch.equal(a[k], b) for a, b in zip(got, one))
    with pytest.raises(ValueError, match="cannot be vmapped"):
        torch.vmap(op, in_dims=(0, 0, 0, 0, None, 0, None))(
            J, r, slots.expand(V, *slots.shape), values, g_slots, g, summed)


def test_the_engine_assembles_user_factors_through_it(monkeypatch):
    """A user factor's linearisation with the kernels on and off: the same normal equations (to
    rounding); with them on, the kernel runs once per block (a per-factor block on two slots and
    a summed block on one uniform slot with a robust loss)."""
    import torchsgal as ts
    from torchsgal.estimation import graph as fg
    from torchsgal.estimation.graph.linearize import linearize
    from torchsgal.estimation.graph.problem import Problem

    gen = torch.Generator().manual_seed(3)
    B, N = 4, 12
    graph = fg.FactorGraph()
    graph.add_variable("T", ts.SE3.exp(0.3 * torch.randn(B, 2, 6, generator=gen, dtype=f64)))
    p = torch.randn(B, N, 3, generator=gen, dtype=f64)
    q = torch.randn(B, N, 3, generator=gen, dtype=f64)
    idx = torch.arange(N) % 2
    graph.add(fg.Factor(lambda a, b, x, y: a.act(x) - b.act(y), [("T", idx), ("T", 1 - idx)],
                        [p, q], dim=3))
    graph.add(fg.Factor(lambda a, x, y: a.act(x) - y, [("T", torch.zeros(N, dtype=torch.int64))],
                        [p, q], dim=3), loss=fg.Huber(0.5))
    problem = Problem(graph)
    x = problem.initial(graph)
    with native.disabled():
        off = linearize(problem, x)
    calls = []
    if dense_solve._lib is not None:
        real = dense_solve._lib.normal_assemble
        monkeypatch.setattr(dense_solve._lib, "normal_assemble",
                            lambda *a: calls.append(a[-1]) or real(*a))
    on = linearize(problem, x)
    torch.testing.assert_close(on.values, off.values, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(on.g, off.g, rtol=1e-12, atol=1e-12)
    assert len(calls) == (2 if dense_solve.available() and native.enabled() else 0)
