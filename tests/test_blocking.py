"""Cache blocking of large CPU batches (torchsgal.functional._blocking).

The blocks are shrunk to a few elements so that small batches take the blocked path, with a
partial last block; every blocked result must equal the unblocked function's.
"""
from __future__ import annotations

import math

import pytest
import torch
from conftest import GROUP_CLASSES, all_groups, gname, sample_group, sample_tangent
from torch.autograd import forward_ad as fwAD

from torchsgal.functional import _autograd, _blocking, native, ops

BATCH = (4, 9)  # 36 elements: five blocks of 7 and a last one of 1


@pytest.fixture(autouse=True)
def tensor_code_only(monkeypatch):
    """These tests are about the tensor code's blocking: SGal3's C kernels (native.py), which
    take the same calls where they are compiled, are switched off."""
    monkeypatch.setitem(native._state, "on", False)


@pytest.fixture
def small_blocks(monkeypatch):
    monkeypatch.setattr(_blocking, "BLOCK", 7)
    monkeypatch.setattr(_blocking, "MIN_BATCH", 14)


def _blocked_names(G):
    return [n for n in ("jl", "jl_inv", "jr", "jr_inv", "adjoint", "inverse")
            if hasattr(getattr(G._f, n, None), "__wrapped__")]


def _record_calls(monkeypatch):
    """Every function that run_blocked runs (the blocked decorator and the custom Functions of
    _autograd) appends (name, batch elements of its first argument, whether that argument
    carries a forward-mode tangent) to the returned list, once per block."""
    calls = []
    real = _blocking.run_blocked

    def recording(fn, args, event_dims):
        def counted(*a):
            n = math.prod(a[0].shape[: a[0].dim() - event_dims[0]])
            calls.append((fn.__name__, n, fwAD.unpack_dual(a[0]).tangent is not None))
            return fn(*a)

        return real(counted, args, event_dims)

    monkeypatch.setattr(_blocking, "run_blocked", recording)
    monkeypatch.setattr(_autograd, "run_blocked", recording)
    return calls


def _eps(dtype):
    return torch.finfo(dtype).eps


def _assert_same(a, b, dtype, msg):
    # Elementwise kernels give the same bits whatever the block; vectorised sin/cos may differ
    # from their scalar tails by an ulp, hence a few eps rather than equality.
    scale = max(1.0, b.abs().max().item())
    err = (a - b).abs().max().item()
    assert err <= 8 * _eps(dtype) * scale, f"{msg}: blocked differs by {err:.3g}"


def test_decorated_functions_exist():
    """The groups whose closed forms allocate many temporaries carry the blocked wrappers."""
    names = {gname(G): _blocked_names(G) for G in GROUP_CLASSES}
    assert set(names["Sim3"]) >= {"jr", "jr_inv"}, names["Sim3"]
    # the Jacobians, adjoints and inverses of SGal(3), SE(3), SE_2(3) and Sim(3), and the
    # Jacobians of SO(3) and SE(2), are operators (ops.py); their closed forms are blocked inside them
    from torchsgal.functional import se2, se3, se23, sgal3, sim3, so3
    for mod in (se3, se23, sgal3, sim3):
        for impl in (mod.jl_impl, mod.jl_inv_impl, mod.adjoint_impl, mod.inverse_impl):
            assert hasattr(impl, "__wrapped__"), impl
    for impl in (so3.jl_impl, so3.jl_inv_impl, se2.jl_impl, se2.jl_inv_impl, se2.inverse_impl, se2.adjoint_impl):
        assert hasattr(impl, "__wrapped__"), impl


@all_groups(batch_shapes=[BATCH])
def test_blocked_matches_unblocked(G, batch_shape, dtype, small_blocks):
    xi = sample_tangent(G, batch_shape, dtype, seed=3)
    M = sample_group(G, batch_shape, dtype, seed=4).as_matrix()
    _assert_same(G._f.exp(xi), G._f.exp_impl(xi), dtype, "exp")
    _assert_same(G._f.log(M), G._f.log_impl(M), dtype, "log")
    for name in _blocked_names(G):
        fn = getattr(G._f, name)
        arg = M if name in ("adjoint", "inverse") else xi
        _assert_same(fn(arg), fn.__wrapped__(arg), dtype, name)


@all_groups(batch_shapes=[BATCH], dtypes=[torch.float64])
def test_blocked_backward_matches(G, batch_shape, dtype, small_blocks, monkeypatch):
    """The custom Functions' forward and backward run blocked (no autograd recording inside);
    their gradients equal the unblocked ones."""
    xi = sample_tangent(G, batch_shape, dtype, seed=5)
    W = torch.randn(batch_shape + (G.matrix_dim, G.matrix_dim), dtype=dtype, generator=torch.Generator().manual_seed(5))

    def grads():
        x = xi.clone().requires_grad_(True)
        (gx,) = torch.autograd.grad((G._f.exp(x) * W).sum(), x)
        M = G._f.exp_impl(xi).requires_grad_(True)
        (gM,) = torch.autograd.grad(G._f.log(M).sin().sum(), M)
        return gx, gM

    blocked = grads()
    monkeypatch.setattr(_blocking, "MIN_BATCH", 10**9)
    plain = grads()
    for a, b, what in zip(blocked, plain, ("exp backward", "log backward")):
        _assert_same(a, b, dtype, what)


# SGal(3)'s exp and log are registered operators (functional/ops.py): under every transform the
# operator runs its kernel on the whole logical batch (tests/test_ops.py)
TENSOR_CODE_GROUPS = [G for G in GROUP_CLASSES if G._f.NAME not in ops.GROUPS]


@pytest.mark.parametrize("G", TENSOR_CODE_GROUPS, ids=gname)
def test_blocking_stays_out_of_transforms(G, small_blocks, monkeypatch):
    """Under vmap, recording autograd and torch.func.grad the unblocked function runs, in one
    call over the whole batch (no writes into a fresh output); results equal the blocked ones.
    (Inside a custom Function's forward nothing is recorded, so exp's forward may block.)"""
    xi = sample_tangent(G, (3, 20), torch.float64, seed=6)
    ref = G._f.exp(xi)
    calls = _record_calls(monkeypatch)
    torch.testing.assert_close(torch.func.vmap(G._f.exp)(xi), ref, rtol=0, atol=8 * _eps(xi.dtype) * 10)
    assert calls == [("exp_impl", 20, False)]  # one call on the logical batch of vmap
    x = xi.clone().requires_grad_(True)
    calls.clear()
    out = G.jl(x)  # records autograd: plain path
    if "jl" in _blocked_names(G):
        assert calls == [("jl", 60, False)]
        assert out.grad_fn is not None
        _assert_same(out.detach(), G._f.jl.__wrapped__(xi), xi.dtype, "jl")
    calls.clear()
    g = torch.func.grad(lambda v: G._f.exp(v).sum())(xi)
    assert [c for c in calls if c[0] == "_exp_backward"] == [("_exp_backward", 60, False)]
    # against the ordinary backward, which runs blocked (nothing records it)
    calls.clear()
    (want,) = torch.autograd.grad(G._f.exp(x).sum(), x)
    assert [c[1] for c in calls if c[0] == "_exp_backward"] == [7] * 8 + [4]
    _assert_same(g, want, xi.dtype, "func.grad")


@pytest.mark.parametrize("G", GROUP_CLASSES, ids=gname)
def test_forward_mode_tangents_survive_blocking(G, small_blocks, monkeypatch):
    """Dual tensors (torch.autograd.forward_ad): a function given a dual tensor runs unblocked
    in one call, and the whole tangent equals the one computed with blocking switched off
    (exp's custom Function gets the primal alone and its forward and jvp block)."""
    xi = sample_tangent(G, BATCH, torch.float64, seed=8)
    t = torch.randn(xi.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(8))

    def tangents():
        out = {}
        for name in ["exp"] + _blocked_names(G):
            fn = (lambda v: G._f.inverse(G._f.exp(v))) if name == "inverse" else (
                (lambda v: G._f.adjoint(G._f.exp(v))) if name == "adjoint" else getattr(G._f, name))
            with fwAD.dual_level():
                out[name] = fwAD.unpack_dual(fn(fwAD.make_dual(xi, t))).tangent
        return out

    calls = _record_calls(monkeypatch)
    blocked = tangents()
    assert any(n < 36 for _, n, _ in calls)  # the blocked path did run (exp's primal forward)
    assert all(n == 36 for _, n, dual in calls if dual)
    assert {name for name, _, dual in calls if dual} >= set(_blocked_names(G))
    monkeypatch.setattr(_blocking, "MIN_BATCH", 10**9)
    plain = tangents()
    for name, tangent in blocked.items():
        assert tangent is not None, name
        assert tangent.shape == plain[name].shape, name
        _assert_same(tangent, plain[name], xi.dtype, f"{name} tangent")


def test_blocked_errors_name_the_callers_shapes(small_blocks):
    from torchsgal.functional import sgal3

    with pytest.raises(ValueError, match=r"\(40, 9\)"):
        sgal3.jl(torch.zeros(40, 9, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"\(40, 9\)"):
        sgal3.exp(torch.zeros(40, 9, dtype=torch.float64))


def test_broadcast_arguments_are_blocked(small_blocks):
    """Arguments with broadcast batch shapes are expanded before blocking."""
    from torchsgal.functional import _blocking as blk

    def f(a, b):
        return a * b.sum(-1, keepdim=True)

    a = torch.randn(5, 8, 3, dtype=torch.float64)
    b = torch.randn(1, 8, 4, dtype=torch.float64)
    torch.testing.assert_close(blk.run_blocked(f, (a, b), (1, 1)), f(a, b), rtol=0, atol=0)


def test_default_blocks_on_a_large_batch(monkeypatch):
    """The default block sizes on a batch just over MIN_BATCH (two full blocks and a partial
    one, counted): SGal3 exp, log and jl equal the unblocked closed forms."""
    from torchsgal import SGal3
    from torchsgal.functional import sgal3

    n = _blocking.MIN_BATCH + 3
    xi = sample_tangent(SGal3, (n,), torch.float32, seed=8)
    M = sgal3.exp_impl(xi)
    calls = []
    plain = sgal3.exp_impl
    monkeypatch.setattr(sgal3, "exp_impl", lambda x: calls.append(x.shape[0]) or plain(x))
    _assert_same(sgal3.exp(xi), M, torch.float32, "exp")
    assert calls == [_blocking.BLOCK, _blocking.BLOCK, 3]
    _assert_same(sgal3.log(M), sgal3.log_impl(M), torch.float32, "log")
    _assert_same(sgal3.jl(xi), sgal3.jl_impl.__wrapped__(xi), torch.float32, "jl")
