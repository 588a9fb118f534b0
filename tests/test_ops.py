"""SGal(3)'s registered operators (torchsgal/functional/ops.py): torch.library.opcheck, the same
operator under eager autograd, vmap and torch.compile, and their derivatives."""
from __future__ import annotations

import pytest
import torch
from test_native import _Recorder
from test_native_subgroups import kernel_test

import torchsgal as ts
from torchsgal.functional import native, sgal3

OPS = ("sgal3_exp", "sgal3_log", "sgal3_exp_vjp", "sgal3_log_vjp", "sgal3_jl", "sgal3_jl_inv")
EXP_LOG_OPS = OPS[:4]
BATCHES = [(), (2, 4), (0,)]  # a scalar, a two-axis and an empty batch (one axis adds nothing)


def _small(*shape, seed=0):
    """Tangents with rotation angles well below pi (log(exp(xi)) = xi)."""
    return 0.5 * torch.randn(*shape, dtype=torch.float64, generator=torch.Generator().manual_seed(seed))


def _op(name):
    return getattr(torch.ops.torchsgal, name).default


def _arguments(name, batch, dtype, requires_grad=False):
    g = torch.Generator().manual_seed(7)
    xi = (0.8 * torch.randn(*batch, 10, generator=g, dtype=torch.float64)).to(dtype)
    M = sgal3.exp_impl(xi.double()).to(dtype)
    G = torch.randn(*batch, 5, 5, generator=g, dtype=torch.float64).to(dtype)
    w = torch.randn(*batch, 10, generator=g, dtype=torch.float64).to(dtype)
    args = {"sgal3_exp": (xi,), "sgal3_log": (M,), "sgal3_exp_vjp": (xi, M, G),
            "sgal3_log_vjp": (M, xi, w), "sgal3_jl": (xi,), "sgal3_jl_inv": (xi,)}[name]
    return tuple(a.clone().requires_grad_(requires_grad) for a in args)


# opcheck takes each operator as this run executes it: its C kernel in the first test run of
# .ci/run, its closed form in the second (TORCHSGAL_NATIVE=0) and wherever the kernels are not
# built.  (A kernels-off variant in every run opchecked the closed form in both runs of .ci/run,
# twice in the second.)
RUN_PATH = "kernels_on" if native.enabled() else "kernels_off"
# The operators whose backward runs an operator: exp's and log's run sgal3_exp_vjp and
# sgal3_log_vjp (C kernels).  The other four differentiate their closed form, which reads only the
# inputs and runs no operator: their gradients are the same with the kernels on or off
# (test_a_closed_form_backward_runs_no_kernel).
BACKWARD_RUNS_OPERATORS = ("sgal3_exp", "sgal3_log")


@pytest.mark.parametrize("path", [RUN_PATH])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["f32", "f64"])
@pytest.mark.parametrize("batch", BATCHES, ids=str)
@pytest.mark.parametrize("name", OPS)
def test_opcheck(name, batch, dtype, path):
    # schema, fake implementation, autograd registration and AOT dispatch (dynamic shapes), with
    # gradients in float64 where they depend on the run's path: with the kernels on, the four
    # closed-form backwards are left to the kernels-off run, which opchecks the same backward
    # (trace and values), and for sgal3_log_vjp also to tests/test_ops_compiled.py's opcheck
    assert native.enabled() is (path == "kernels_on")
    grad = dtype is torch.float64 and (path == "kernels_off" or name in BACKWARD_RUNS_OPERATORS)
    torch.library.opcheck(_op(name), _arguments(name, batch, dtype, requires_grad=grad))


@kernel_test
@pytest.mark.parametrize("batch", BATCHES, ids=str)
@pytest.mark.parametrize("name", [n for n in OPS if n not in BACKWARD_RUNS_OPERATORS])
def test_a_closed_form_backward_runs_no_kernel(monkeypatch, name, batch):
    """What lets test_opcheck leave these operators' gradients to the kernels-off run: their
    backward calls no kernel (nor do its derivatives, autograd through tensor operations) and
    gives the same bits with the kernels on and off."""
    def gradients():
        args = _arguments(name, batch, torch.float64, requires_grad=True)
        out = _op(name)(*args)
        g = torch.randn(out.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(5))
        return torch.autograd.grad(out, args, g, create_graph=True)

    recorder = _Recorder(native._lib)
    monkeypatch.setattr(native, "_lib", recorder)
    on = gradients()
    assert recorder.calls == [name]  # the forward's
    with native.disabled():
        off = gradients()
    assert recorder.calls == [name]
    assert all(torch.equal(a, b) for a, b in zip(on, off))


@pytest.mark.kernels
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["f32", "f64"])
@pytest.mark.parametrize("name", OPS)
def test_the_kernel_and_the_closed_form_agree(name, dtype):
    assert native.available() and native.enabled(), "the kernels must run: this test compares them"
    args = _arguments(name, (257,), dtype)
    out = _op(name)(*args)
    with native.disabled():
        reference = _op(name)(*args)
    tol = 1e-12 if dtype is torch.float64 else 2e-5
    torch.testing.assert_close(out, reference, rtol=tol, atol=tol)


@pytest.mark.parametrize("name", ["sgal3_exp", "sgal3_exp_vjp", "sgal3_log_vjp", "sgal3_jl", "sgal3_jl_inv"])
def test_first_and_second_derivatives_match_finite_differences(name):
    # two elements (the checks' cost grows with the square of the batch), rotation angles 0.998
    # (the series below numerics.SERIES_THRESHOLD = 1) and 1.51 (the closed form): the branches
    # of the three of this draw (the third, 0.776, took the series); two still show each
    # element's derivatives leaving the other's alone
    args = tuple(a[:2].clone().requires_grad_(True) for a in _arguments(name, (3,), torch.float64))
    assert torch.autograd.gradcheck(_op(name), args)
    assert torch.autograd.gradgradcheck(_op(name), args)


def test_log_backward_is_the_group_projection():
    # log's derivative is taken along the group (perturbations M exp(dzeta^)), as _autograd.py
    xi, = _arguments("sgal3_exp", (4,), torch.float64)
    M = sgal3.exp_impl(xi)
    g = torch.randn(4, 10, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    dzeta = torch.randn(4, 10, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    Mr = M.clone().requires_grad_(True)
    (grad_M,) = torch.autograd.grad((_op("sgal3_log")(Mr) * g).sum(), Mr)
    h = 1e-6
    moved = lambda s: sgal3.log_impl(M @ sgal3.exp_impl(s * h * dzeta))  # noqa: E731
    numeric = ((moved(1) - moved(-1)) * g).sum() / (2 * h)
    analytic = (grad_M * (M @ sgal3.hat(dzeta))).sum()
    torch.testing.assert_close(analytic, numeric, rtol=1e-7, atol=1e-8)


def _operators_run(fn, *args) -> set:
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
        fn(*args)
    return {e.name for e in prof.events() if e.name.startswith("torchsgal::")}


def test_eager_autograd_runs_the_operators():
    xi = _small(5, 10, seed=12).requires_grad_(True)

    def f(x):
        y = ts.SGal3.exp(x).log()
        y.sum().backward()

    assert _operators_run(f, xi) == {f"torchsgal::{n}" for n in EXP_LOG_OPS}


def test_vmap_runs_the_operators_and_matches_the_loop():
    xi = _small(6, 10, seed=11)
    f = lambda x: ts.SGal3.exp(x).log()  # noqa: E731
    out = torch.func.vmap(f)(xi)
    torch.testing.assert_close(out, torch.stack([f(x) for x in xi]), rtol=0, atol=0)
    assert {"torchsgal::sgal3_exp", "torchsgal::sgal3_log"} <= _operators_run(torch.func.vmap(f), xi)
    # jacrev over a vmapped batch: the backward operators under vmap
    J = torch.func.vmap(torch.func.jacrev(f))(xi)
    torch.testing.assert_close(J, torch.eye(10, dtype=torch.float64).expand(6, 10, 10),
                               rtol=1e-10, atol=1e-10)
    assert {"torchsgal::sgal3_exp_vjp", "torchsgal::sgal3_log_vjp"} <= _operators_run(
        torch.func.vmap(torch.func.jacrev(f)), xi)


def test_vmap_with_an_unbatched_argument():
    xi, M, G = _arguments("sgal3_exp_vjp", (4,), torch.float64)
    op = _op("sgal3_exp_vjp")
    out = torch.func.vmap(op, in_dims=(0, 0, None))(xi, M, G[0])
    torch.testing.assert_close(out, op(xi, M, G[0].expand(4, 5, 5)), rtol=0, atol=0)


def test_compiled_code_runs_the_operators_with_eager_values_and_derivatives():
    # compiled inference (grad mode off) runs the operators; where grad mode is on, compiled code
    # differentiates the closed forms (functional/_autograd.py: torch 2.13 compiles no double
    # backward and no torch.func transform of a custom operator's autograd)
    def f(x):
        return ts.SGal3.exp(x).log()

    compiled = torch.compile(f, fullgraph=True, dynamic=False)
    xi = _small(7, 10, seed=13)
    with torch.no_grad():
        torch.testing.assert_close(compiled(xi), f(xi), rtol=1e-13, atol=1e-13)
        assert {"torchsgal::sgal3_exp", "torchsgal::sgal3_log"} <= _operators_run(compiled, xi)

    w = _small(7, 10, seed=14)
    grads = []
    for fn in (f, compiled):
        x = xi.clone().requires_grad_(True)
        (g,) = torch.autograd.grad((fn(x) * w).sum(), x)
        grads.append(g)
    torch.testing.assert_close(grads[1], grads[0], rtol=1e-10, atol=1e-10)
    # second derivatives: torch.func transforms inside the compiled function (aot_autograd has
    # no double backward); the operators' backward is differentiated
    hess = lambda x: torch.func.hessian(lambda v: (f(v) * w[0]).sum())(x)  # noqa: E731
    compiled_hess = torch.compile(hess, fullgraph=True, backend="aot_eager")
    torch.testing.assert_close(compiled_hess(xi[0]), hess(xi[0]), rtol=1e-9, atol=1e-9)


def _aten_trigonometry_runs(fn, *args) -> bool:
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
        fn(*args)
    return any(e.name in ("aten::sin", "aten::cos") for e in prof.events())


@pytest.mark.kernels
def test_the_thread_local_kernel_switch_reaches_compiled_code():
    compiled = torch.compile(lambda x: ts.SGal3.exp(x).as_matrix(), fullgraph=True, dynamic=False)
    xi = _small(3, 10, seed=15)
    with torch.no_grad():
        on = compiled(xi)
        with native.disabled():
            off = compiled(xi)
            assert _aten_trigonometry_runs(compiled, xi)  # the closed form inside the operator
        assert not _aten_trigonometry_runs(compiled, xi)  # the C kernel
    torch.testing.assert_close(on, off, rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("name", ["jl", "jl_inv", "jr", "jr_inv"])
def test_jacobians_run_their_operators_and_differentiate_as_the_closed_form(name):
    xi = _small(4, 10, seed=16)
    public = getattr(sgal3, name)
    sign = -1 if name.startswith("jr") else 1
    closed = sgal3.jl_impl if name in ("jl", "jr") else sgal3.jl_inv_impl
    torch.testing.assert_close(public(xi), closed(sign * xi), rtol=1e-13, atol=1e-13)
    assert _operators_run(public, xi) == {f"torchsgal::sgal3_{name.replace('jr', 'jl')}"}
    f = lambda x: (public(x) ** 2).sum()  # noqa: E731
    g = lambda x: (closed(sign * x) ** 2).sum()  # noqa: E731
    for transform in (torch.func.grad, lambda h: torch.func.jacfwd(torch.func.grad(h)),
                      lambda h: torch.func.jacrev(torch.func.grad(h))):
        torch.testing.assert_close(transform(f)(xi[0]), transform(g)(xi[0]), rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(torch.func.vmap(public)(xi), closed(sign * xi), rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("name,args,message", [
    ("sgal3_exp", (torch.zeros(5, 9, dtype=torch.float64),), r"xi must have shape \(\.\.\., 10\), got \(5, 9\)"),
    ("sgal3_log", (torch.zeros(5, 4, 4, dtype=torch.float64),), r"M must have shape \(\.\.\., 5, 5\)"),
    ("sgal3_exp_vjp", (torch.zeros(5, 10, dtype=torch.float64), torch.zeros(5, 5, 5, dtype=torch.float64),
                       torch.zeros(5, 4, 5, dtype=torch.float64)), r"G must have shape"),
    ("sgal3_log_vjp", (torch.zeros(5, 5, 5, dtype=torch.float64), torch.zeros(5, 10, dtype=torch.float64),
                       torch.zeros(5, 9, dtype=torch.float64)), r"g must have shape"),
    ("sgal3_jl", (torch.zeros(3, 10, dtype=torch.int64),), r"xi must have a floating dtype"),
    ("sgal3_jl_inv", (torch.zeros(2, 11, dtype=torch.float32),), r"xi must have shape"),
])
def test_operators_called_directly_refuse_bad_shapes_by_name(name, args, message):
    # a C loop given a (..., 9) tensor would read past its end: the operators check first
    with pytest.raises((ValueError, TypeError), match=message):
        _op(name)(*args)


@pytest.mark.parametrize("name", ["jl", "jl_inv"])
def test_jacobians_take_dual_tensors(name):
    # torch.autograd.forward_ad: the closed form's tangent (the Function's jvp, torch.func.jvp,
    # cannot nest inside a dual level)
    import torch.autograd.forward_ad as fwAD
    xi, d = _small(4, 10, seed=17), _small(4, 10, seed=18)
    closed = sgal3.jl_impl if name == "jl" else sgal3.jl_inv_impl
    with fwAD.dual_level():
        tangent = fwAD.unpack_dual(getattr(sgal3, name)(fwAD.make_dual(xi, d))).tangent
    torch.testing.assert_close(tangent, torch.func.jvp(closed, (xi,), (d,))[1], rtol=1e-13, atol=1e-13)
