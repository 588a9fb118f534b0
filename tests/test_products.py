"""The product, inverse and adjoint operators of SGal(3), SE(3), SE_2(3), SO(3) and SE(2)
(``torchsgal::<group>_compose``, ``<group>_inverse``, ``<group>_adjoint``; functional/ops.py, C
kernels in functional/_native_products.h; the inverse and adjoint of SO(3) and SE(2) are their
tensor code): against the tensor code (``A @ B`` and the block
closed forms ``inverse_impl`` and ``adjoint_impl``) and the definitions (A A^-1 = I,
Ad(M) xi = vee(M xi^ M^-1)), opcheck, derivatives in reverse and forward mode, vmap,
torch.compile, where the operators run, and bad arguments."""
from __future__ import annotations

import pickle

import pytest
import torch
import torch.autograd.forward_ad as fwAD
from test_native_subgroups import kernel_test
from test_ops import _operators_run

import torchsgal as ts
from torchsgal.functional import _autograd, native, se2, se3, se23, sgal3, sim3, so3

# the groups whose public compose, inverse and adjoint run the operators
GROUPS = {"sgal3": (ts.SGal3, sgal3), "se3": (ts.SE3, se3), "se23": (ts.SE23, se23), "sim3": (ts.Sim3, sim3)}
# and SO(3) and SE(2), whose public inverse and adjoint run their tensor code
# (test_so3_and_se2_public_functions)
OPERATOR_GROUPS = {**GROUPS, "so3": (ts.SO3, so3), "se2": (ts.SE2, se2)}
f64 = torch.float64


def _op(name):
    return getattr(torch.ops.torchsgal, name).default


def _elements(group, batch, dtype=f64, seed=0):
    G, mod = OPERATOR_GROUPS[group]
    gen = torch.Generator().manual_seed(seed)
    xi = 2.0 * torch.randn(*batch, mod.DOF, generator=gen, dtype=f64)
    return G.exp(xi).as_matrix().to(dtype)


def _adjoint_definition(mod, M, xi):
    """Ad(M) xi = vee(M xi^ M^-1), the adjoint's definition."""
    return mod.vee(M @ mod.hat(xi) @ torch.linalg.inv(M))


@pytest.mark.parametrize("kernels", [True, False], ids=["kernels_on", "kernels_off"])
@pytest.mark.parametrize("dtype", [torch.float32, f64], ids=["f32", "f64"])
@pytest.mark.parametrize("batch", [(), (2, 3), (0,)], ids=str)
@pytest.mark.parametrize("group", OPERATOR_GROUPS)
def test_opcheck(group, batch, dtype, kernels):
    A, B = _elements(group, batch, dtype, 1), _elements(group, batch, dtype, 2)
    grad = dtype is f64
    for name, args in ((f"{group}_compose", (A, B)), (f"{group}_adjoint", (A,)), (f"{group}_inverse", (A,))):
        args = tuple(a.clone().requires_grad_(grad) for a in args)
        if kernels:
            torch.library.opcheck(_op(name), args)
        else:
            with native.disabled():
                torch.library.opcheck(_op(name), args)


@kernel_test
@pytest.mark.parametrize("dtype", [torch.float32, f64], ids=["f32", "f64"])
@pytest.mark.parametrize("group", OPERATOR_GROUPS)
def test_kernels_match_the_tensor_code_and_the_definition(group, dtype):
    # 261 products: 32 passes of the lanes and a tail of 5; the identity among them
    _, mod = OPERATOR_GROUPS[group]
    A, B = _elements(group, (261,), dtype, 3), _elements(group, (261,), dtype, 4)
    A[7] = torch.eye(mod.MATRIX_DIM, dtype=dtype)
    eps = torch.finfo(dtype).eps
    product = _op(f"{group}_compose")(A, B)
    scale = A.abs().amax((-2, -1), keepdim=True) * B.abs().amax((-2, -1), keepdim=True)
    assert ((product - A @ B).abs() / scale).max() <= 8 * eps
    torch.testing.assert_close(product[7], B[7], rtol=0, atol=0)
    Ad = _op(f"{group}_adjoint")(A)
    reference = mod.adjoint_impl(A)
    # relative to the adjoint's own size (Sim(3)'s blocks s C and s r^ C scale with s = 1/M[3, 3])
    assert ((Ad - reference).abs() / (1 + reference.abs().amax((-2, -1), keepdim=True))).max() <= 8 * eps
    inverse = _op(f"{group}_inverse")(A)
    torch.testing.assert_close(inverse, mod.inverse_impl(A), rtol=0, atol=0)  # the same operations
    eye = torch.eye(mod.MATRIX_DIM, dtype=dtype)
    # rounding of the product A A^-1, relative to its factors' sizes (Sim(3)'s inverse holds s C^T r)
    scale_inverse = A.abs().amax((-2, -1), keepdim=True) * inverse.abs().amax((-2, -1), keepdim=True)
    assert ((A @ inverse - eye).abs() / scale_inverse).max() <= 64 * eps
    xi = torch.randn(261, mod.DOF, dtype=f64, generator=torch.Generator().manual_seed(5))
    definition = _adjoint_definition(mod, A.double(), xi)
    tol = 1e-11 if dtype is f64 else 1e-3
    torch.testing.assert_close((Ad.double() @ xi[..., None])[..., 0], definition, rtol=tol, atol=tol)


@kernel_test
@pytest.mark.parametrize("group", OPERATOR_GROUPS)
def test_kernel_bits_do_not_depend_on_the_batch_or_the_threads(group):
    A, B = _elements(group, (70_001,), f64, 5), _elements(group, (70_001,), f64, 6)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        many = _op(f"{group}_compose")(A, B), _op(f"{group}_adjoint")(A), _op(f"{group}_inverse")(A)
        torch.set_num_threads(1)
        one = _op(f"{group}_compose")(A, B), _op(f"{group}_adjoint")(A), _op(f"{group}_inverse")(A)
    finally:
        torch.set_num_threads(threads)
    for m, o in zip(many, one):
        assert torch.equal(m, o)
    for i in (0, 13, 70_000):  # in the lanes, and the last element (the tail)
        single = _op(f"{group}_compose")(A[i:i + 1], B[i:i + 1])
        assert torch.equal(single[0], many[0][i])


@pytest.mark.parametrize("group", OPERATOR_GROUPS)
def test_first_and_second_derivatives_match_finite_differences(group):
    A = _elements(group, (3,), f64, 7).requires_grad_(True)
    B = _elements(group, (3,), f64, 8).requires_grad_(True)
    assert torch.autograd.gradcheck(_op(f"{group}_compose"), (A, B))
    assert torch.autograd.gradgradcheck(_op(f"{group}_compose"), (A, B))
    assert torch.autograd.gradcheck(_op(f"{group}_adjoint"), (A,))
    assert torch.autograd.gradgradcheck(_op(f"{group}_adjoint"), (A,))
    assert torch.autograd.gradcheck(_op(f"{group}_inverse"), (A,))
    assert torch.autograd.gradgradcheck(_op(f"{group}_inverse"), (A,))


@pytest.mark.parametrize("group", GROUPS)
def test_public_functions_run_the_operators_and_differentiate_as_the_tensor_code(group):
    _, mod = GROUPS[group]
    n = _autograd.COMPOSE_MIN_BATCH
    A, B = _elements(group, (n,), f64, 9), _elements(group, (n,), f64, 10)
    assert _operators_run(mod.compose, A, B) == {f"torchsgal::{group}_compose"}
    assert _operators_run(mod.compose, A[: n - 1], B[: n - 1]) == set()  # below: A @ B
    assert _operators_run(mod.adjoint, A[:1]) == {f"torchsgal::{group}_adjoint"}
    assert _operators_run(mod.inverse, A[:1]) == {f"torchsgal::{group}_inverse"}
    # differentiated, the inverse and adjoint run their tensor code (its backward is cheaper than
    # a second evaluation), the product its operator (the product rule's products)
    a, b = A.clone().requires_grad_(True), B.clone().requires_grad_(True)
    assert _operators_run(lambda x: (mod.inverse(x), mod.adjoint(x)), a) == set()
    assert _operators_run(lambda x, y: mod.compose(x, y).sum().backward(), a, b) == {
        f"torchsgal::{group}_compose"}
    W = torch.randn(n, mod.DOF, mod.DOF, dtype=f64, generator=torch.Generator().manual_seed(11))

    def f(a, b):
        return (mod.compose(a, b) ** 2).sum() + (mod.adjoint(a) * W).sum() + (mod.inverse(b) ** 3).sum()

    def g(a, b):
        return ((a @ b) ** 2).sum() + (mod.adjoint_impl(a) * W).sum() + (mod.inverse_impl(b) ** 3).sum()

    dA, dB = torch.randn_like(A), torch.randn_like(B)
    for transform in (lambda h: torch.func.grad(h, argnums=(0, 1))(A, B),
                      lambda h: torch.func.jvp(h, (A, B), (dA, dB))[1],
                      lambda h: torch.func.jvp(torch.func.grad(h), (A, B), (dA, dB))[1]):
        torch.testing.assert_close(transform(f), transform(g), rtol=1e-11, atol=1e-11)
    # vmap over a leading axis (the operators' vmap rule), one argument unbatched
    batched = torch.func.vmap(mod.compose, in_dims=(0, None))(A.unflatten(0, (2, -1)), B[: n // 2])
    torch.testing.assert_close(batched, A.unflatten(0, (2, -1)) @ B[: n // 2], rtol=1e-14, atol=1e-14)


@pytest.mark.parametrize("group", ["so3", "se2"])
def test_so3_and_se2_public_functions(group):
    """The 3 x 3 products run their operator from 2048 elements (below, A @ B, which is faster
    there), through the product rule in reverse and forward mode; the inverse and adjoint run
    their tensor code, no operator (SO(3)'s are views of C: C^T and C itself)."""
    _, mod = OPERATOR_GROUPS[group]
    n = 2048
    A, B = _elements(group, (n,), f64, 20), _elements(group, (n,), f64, 21)
    assert _operators_run(mod.compose, A, B) == {f"torchsgal::{group}_compose"}
    assert _operators_run(mod.compose, A[: n - 1], B[: n - 1]) == set()
    torch.testing.assert_close(mod.compose(A, B), A @ B, rtol=1e-15, atol=1e-15)
    assert _operators_run(lambda x: (mod.inverse(x), mod.adjoint(x)), A) == set()
    if group == "so3":
        inverse = so3.inverse(A)  # C^T, sharing C's memory
        assert inverse.data_ptr() == A.data_ptr() and torch.equal(inverse, A.mT)
        assert so3.adjoint(A) is A
    a, b = A.clone().requires_grad_(True), B.clone().requires_grad_(True)
    W = torch.randn(n, 3, 3, dtype=f64, generator=torch.Generator().manual_seed(22))
    (mod.compose(a, b) * W).sum().backward()
    torch.testing.assert_close(a.grad, W @ B.mT, rtol=1e-14, atol=1e-14)
    torch.testing.assert_close(b.grad, A.mT @ W, rtol=1e-14, atol=1e-14)
    dA, dB = torch.randn_like(A), torch.randn_like(B)
    tangent = torch.func.jvp(mod.compose, (A, B), (dA, dB))[1]
    torch.testing.assert_close(tangent, dA @ B + A @ dB, rtol=1e-14, atol=1e-14)


@pytest.mark.parametrize("group", GROUPS)
def test_dual_tensors_autocast_and_pickling(group):
    # torch.autograd.forward_ad: the product rule's jvp and the tensor code's
    _, mod = GROUPS[group]
    n = _autograd.COMPOSE_MIN_BATCH
    A, B = _elements(group, (n,), f64, 18), _elements(group, (n,), f64, 19)
    dA, dB = torch.randn_like(A), torch.randn_like(B)
    with fwAD.dual_level():
        a, b = fwAD.make_dual(A, dA), fwAD.make_dual(B, dB)
        tangents = [fwAD.unpack_dual(out).tangent for out in (mod.compose(a, b), mod.inverse(a), mod.adjoint(a))]
    torch.testing.assert_close(tangents[0], dA @ B + A @ dB, rtol=1e-14, atol=1e-14)
    for t, impl in zip(tangents[1:], (mod.inverse_impl, mod.adjoint_impl)):
        torch.testing.assert_close(t, torch.func.jvp(impl, (A,), (dA,))[1], rtol=1e-14, atol=1e-14)
    # under autocast the product is torch's (lower precision), whatever the batch size
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert mod.compose(A.float(), B.float()).dtype == torch.bfloat16
    for f in (mod.compose, mod.inverse, mod.adjoint):
        assert pickle.loads(pickle.dumps(f)) is f


@pytest.mark.parametrize("group", GROUPS)
def test_broadcast_batches(group):
    _, mod = GROUPS[group]
    n = _autograd.COMPOSE_MIN_BATCH
    A, B = _elements(group, (n,), f64, 12), _elements(group, (1,), f64, 13)
    torch.testing.assert_close(mod.compose(A, B), A @ B, rtol=1e-15, atol=1e-15)
    torch.testing.assert_close(mod.compose(B, A), B @ A, rtol=1e-15, atol=1e-15)
    C = _elements(group, (2, 1, 3), f64, 14)
    D = _elements(group, (1, 200, 1), f64, 15)
    torch.testing.assert_close(mod.compose(C, D), C @ D, rtol=1e-15, atol=1e-15)
    # shapes only (meta tensors: the tensor code's shape rules)
    meta = torch.empty(n, mod.MATRIX_DIM, mod.MATRIX_DIM, dtype=f64, device="meta")
    assert mod.compose(meta, meta).shape == meta.shape and mod.inverse(meta).shape == meta.shape
    assert mod.adjoint(meta).shape == (n, mod.DOF, mod.DOF)


def test_compiled_inference_runs_the_operators():
    A, B = _elements("sgal3", (300,), f64, 16), _elements("sgal3", (300,), f64, 17)

    def f(a, b):
        g, h = ts.SGal3(a), ts.SGal3(b)
        return g.compose(h.inverse()).adjoint()

    compiled = torch.compile(f, fullgraph=True, dynamic=False)
    with torch.no_grad():
        torch.testing.assert_close(compiled(A, B), f(A, B), rtol=1e-14, atol=1e-14)
        assert {"torchsgal::sgal3_compose", "torchsgal::sgal3_adjoint",
                "torchsgal::sgal3_inverse"} <= _operators_run(compiled, A, B)


@pytest.mark.parametrize("name,args,message", [
    ("sgal3_compose", (torch.zeros(3, 5, 5, dtype=f64), torch.zeros(3, 4, 4, dtype=f64)),
     r"B must have shape \(\.\.\., 5, 5\), got \(3, 4, 4\)"),
    ("se3_compose", (torch.zeros(3, 4, 4, dtype=f64), torch.zeros(3, 4, 4, dtype=torch.float32)),
     r"B has dtype torch.float32 but A has dtype torch.float64"),
    ("se23_adjoint", (torch.zeros(3, 4, 4, dtype=f64),), r"M must have shape \(\.\.\., 5, 5\)"),
    ("se3_adjoint", (torch.zeros(3, 4, 4, dtype=torch.int64),), r"M must have a floating dtype"),
    ("sgal3_inverse", (torch.zeros(2, 4, 5, dtype=f64),), r"M must have shape \(\.\.\., 5, 5\)"),
    ("se23_compose", (torch.zeros(3, 5, 5, dtype=f64), torch.zeros(2, 5, 5, dtype=f64)),
     r"batch shapes do not broadcast: A \(3,\), B \(2,\)"),
])
def test_operators_refuse_bad_arguments_by_name(name, args, message):
    with pytest.raises((ValueError, TypeError), match=message):
        _op(name)(*args)
