"""The C kernels of SGal(3) exp, log and their backward maps (torchsgal/functional/_native.c,
run by the operators of functional/ops.py) against the tensor closed forms they transcribe, at
every angle band and in both dtypes, and the rule that decides where they run (the IMU
preintegration kernel: tests/test_imu_kernels.py; opcheck and transforms: tests/test_ops.py).  The tensor code is itself checked against scipy, mpmath and
GTSAM elsewhere; the rest of the suite runs through the kernels wherever they are eligible."""
from __future__ import annotations

import math
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from torchsgal import SGal3
from torchsgal.functional import native
from torchsgal.functional import sgal3 as F

# ``kernels``: tests of the C kernels themselves, left out of the run with the kernels switched off
# (TORCHSGAL_NATIVE=0, the second test run of .ci/run).
pytestmark = [pytest.mark.kernels,
              pytest.mark.skipif(not native.available() and os.environ.get("TORCHSGAL_NO_SKIPS") != "1",
                                 reason="the C kernels were not compiled for this installation")]



class KERNELS:
    """The operators, which run the C kernels for CPU inputs of one batch shape and dtype (the
    ``recorder`` tests check that they do)."""
    exp = torch.ops.torchsgal.sgal3_exp
    log = torch.ops.torchsgal.sgal3_log
    exp_vjp = torch.ops.torchsgal.sgal3_exp_vjp
    log_vjp = torch.ops.torchsgal.sgal3_log_vjp
    jl = torch.ops.torchsgal.sgal3_jl
    jl_inv = torch.ops.torchsgal.sgal3_jl_inv

# Both branches of every series and threshold: numerics.SERIES_THRESHOLD = 1, JINV_THRESHOLD =
# 0.5, LOG_SIN_TAYLOR = 1e-4 and the symmetric-part log below cos = 0 (theta > pi/2).
ANGLES = [0.0, 1e-12, 1e-9, 1e-8, 1e-6, 1e-5, 1e-4, 1.0001e-4, 1e-3, 0.3, 0.5, 0.5 + 1e-9, 0.7,
          1.0 - 1e-9, 1.0, 1.0 + 1e-9, 1.5, math.pi / 2, 2.0, 3.0, math.pi - 1e-3, math.pi - 1e-6,
          math.pi - 1e-9]
# Largest deviation allowed between kernel and tensor code, relative to the largest entry of the
# compared quantity: rounding of a differently ordered but identical sequence of operations.
# Measured worst over the samples below: 6.4e-16 (float64), 4.9e-7 (float32) for exp and log;
# 2.3e-16 / 3.1e-7 for the backward maps.
REL_TOL = {torch.float64: 4e-15, torch.float32: 3e-6}


def tangents(dtype, seed=0, copies=4):
    rng = np.random.default_rng(seed)
    ang = np.repeat(ANGLES, copies)
    xi = rng.standard_normal((ang.size, 10))
    axis = rng.standard_normal((ang.size, 3))
    xi[:, 6:9] = axis / np.linalg.norm(axis, axis=-1, keepdims=True) * ang[:, None]
    return torch.tensor(xi, dtype=dtype)


def assert_rowwise_close(actual, expected, dtype):
    """Per batch element, the largest deviation relative to that element's largest entry."""
    a, e = actual.flatten(1).double(), expected.flatten(1).double()
    scale = e.abs().amax(dim=1).clamp_min(1.0)
    err = ((a - e).abs().amax(dim=1) / scale).max().item()
    assert torch.isfinite(actual).all()
    assert err <= REL_TOL[dtype], f"kernel vs tensor code: {err:.3g} > {REL_TOL[dtype]:.1g}"


def test_the_kernels_are_built_where_the_suite_requires_every_dependency():
    # .ci/run sets TORCHSGAL_NO_SKIPS=1 on a machine with a C compiler: pip must have built them.
    if os.environ.get("TORCHSGAL_NO_SKIPS") == "1":
        assert native.available(), "pip install did not build torchsgal.functional._native"
    assert native.enabled() == (native.available() and os.environ.get(native.ENV_VAR, "1") != "0")


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["float64", "float32"])
def test_exp_and_log_match_the_tensor_code_at_every_angle(dtype):
    xi = tangents(dtype)
    M = KERNELS.exp(xi)
    with native.disabled():
        M_ref = F.exp(xi)
    assert_rowwise_close(M, M_ref, dtype)
    # log of the same matrices: the rotation log's near-0, closed-form and near-pi branches.
    assert_rowwise_close(KERNELS.log(M_ref), F.log_impl(M_ref), dtype)
    assert torch.equal(M[:, 3:, :], M_ref[:, 3:, :])  # the bottom rows exactly


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["float64", "float32"])
def test_backward_maps_match_the_tensor_code_at_every_angle(dtype):
    xi = tangents(dtype, seed=1)
    gen = torch.Generator().manual_seed(2)
    M = F.exp_impl(xi)
    G = torch.randn(M.shape, generator=gen, dtype=dtype)
    g = torch.randn(xi.shape, generator=gen, dtype=dtype)
    assert_rowwise_close(KERNELS.exp_vjp(xi, M, G), F._jl_tmv(-xi, F._exp_pullback(M, G)), dtype)
    assert_rowwise_close(KERNELS.log_vjp(M, xi, g), F._log_pullback(M, F._jl_inv_tmv(-xi, g)), dtype)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["float64", "float32"])
def test_jacobians_match_the_tensor_code_at_every_angle(dtype):
    xi = tangents(dtype, seed=3)
    assert_rowwise_close(KERNELS.jl(xi), F.jl_impl(xi), dtype)
    assert_rowwise_close(KERNELS.jl_inv(xi), F.jl_inv_impl(xi), dtype)


def test_jacobian_kernels_run_in_eager_code(recorder):
    xi = tangents(torch.float64)[:8]
    F.jl(xi), F.jr_inv(xi), SGal3.jr(xi)
    assert recorder.calls == ["sgal3_jl", "sgal3_jl_inv", "sgal3_jl"]


def test_log_at_exactly_pi_and_the_identity():
    # cos = -1 exactly (the symmetric-part branch with s = 0) and C = I (sin = 0, the Taylor ratio).
    M = torch.eye(5, dtype=torch.float64).repeat(4, 1, 1)
    M[1, :3, :3] = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))
    M[2, :3, :3] = torch.diag(torch.tensor([-1.0, 1.0, -1.0], dtype=torch.float64))
    M[3, :3, :3] = torch.diag(torch.tensor([-1.0, -1.0, 1.0], dtype=torch.float64))
    M[:, :3, 3:] = torch.randn(4, 3, 2, dtype=torch.float64)
    M[:, 3, 4] = torch.tensor([0.5, -1.0, 2.0, 0.0], dtype=torch.float64)
    assert torch.equal(KERNELS.log(M)[:, 6:9], F.log_impl(M)[:, 6:9])
    assert_rowwise_close(KERNELS.log(M), F.log_impl(M), torch.float64)


def test_non_finite_input_gives_the_same_non_finite_output():
    xi = tangents(torch.float64)[:6].clone()
    xi[0, 0], xi[1, 7], xi[2, 9], xi[3, 6] = math.nan, math.inf, -math.inf, math.nan
    with native.disabled():
        ref = F.exp(xi)
    out = F.exp(xi)
    assert torch.equal(torch.isnan(out), torch.isnan(ref))
    finite = torch.isfinite(ref)
    assert torch.equal(finite, torch.isfinite(out))
    assert torch.allclose(out[finite], ref[finite], rtol=0, atol=1e-14)


@pytest.mark.parametrize("shape", [(), (5,), (2, 3, 1), (0,), (3, 0, 2)])
def test_batch_shapes_and_layouts(shape):
    xi = tangents(torch.float64)[: math.prod(shape)].reshape(*shape, 10)
    with native.disabled():
        ref = F.exp(xi)
    assert KERNELS.exp(xi).shape == ref.shape == (*shape, 5, 5)
    assert torch.allclose(KERNELS.exp(xi), ref, rtol=0, atol=1e-14)
    assert KERNELS.log(ref).shape == (*shape, 10)


def test_strided_negated_and_expanded_inputs_are_read_by_value():
    base = tangents(torch.float64)[:12]
    with native.disabled():
        ref = F.exp(base)
    strided = base.t().contiguous().t()  # column-major
    assert not strided.is_contiguous()
    neg_view = torch._neg_view(-base)  # lazily negated memory
    assert neg_view.is_neg()
    for x in (strided, neg_view):
        assert torch.allclose(KERNELS.exp(x), ref, rtol=0, atol=1e-14)
    one = base[:1].expand(7, 10)  # stride 0
    assert torch.allclose(KERNELS.exp(one), ref[:1].expand(7, 5, 5), rtol=0, atol=1e-14)
    # An output written from another tensor's layout would be wrong in the transposed places.
    M_t = ref.transpose(-1, -2).contiguous().transpose(-1, -2)
    assert torch.allclose(KERNELS.log(M_t), KERNELS.log(ref), rtol=0, atol=0)


def test_threads_split_the_batch_without_changing_a_bit():
    xi = tangents(torch.float64, copies=1500)  # 34,500 elements: split over 2 threads
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = KERNELS.exp(xi), KERNELS.log(F.exp_impl(xi))
        torch.set_num_threads(2)
        two = KERNELS.exp(xi), KERNELS.log(F.exp_impl(xi))
    finally:
        torch.set_num_threads(before)
    assert all(torch.equal(a, b) for a, b in zip(one, two))


_SPLIT_EXP = """
import hashlib, torch
from torchsgal.functional import native
torch.set_num_threads(2)
xi = torch.randn(40001, 10, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
out = torch.ops.torchsgal.sgal3_exp(xi)
print(native._lib.parallel_backend(), hashlib.sha256(out.numpy().tobytes()).hexdigest())
"""


def test_large_batches_run_on_torchs_openmp_threads_or_on_pthreads_alike():
    # Where torch runs on OpenMP its threads take the split batches (they would otherwise
    # spin-wait beside fresh pthreads); TORCHSGAL_NATIVE_OPENMP=0 keeps pthreads.  Same bits.
    import hashlib
    expected = ("none" if sys.platform == "win32" else "openmp"
                if "ATen parallel backend: OpenMP" in torch.__config__.parallel_info() else "pthreads")
    assert native._lib.parallel_backend() == expected
    before = torch.get_num_threads()
    xi = torch.randn(40001, 10, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    try:
        torch.set_num_threads(1)
        alone = hashlib.sha256(KERNELS.exp(xi).numpy().tobytes()).hexdigest()
        torch.set_num_threads(2)  # handed out in chunks of 2,501 (the last one shorter)
        here = hashlib.sha256(KERNELS.exp(xi).numpy().tobytes()).hexdigest()
    finally:
        torch.set_num_threads(before)
    assert here == alone
    env = dict(os.environ, TORCHSGAL_NATIVE_OPENMP="0")
    backend, digest = subprocess.run([sys.executable, "-c", _SPLIT_EXP], env=env, capture_output=True,
                                     text=True, check=True).stdout.split()
    assert backend == ("none" if sys.platform == "win32" else "pthreads")
    assert digest == here


_POOL = """
import hashlib, os, sys, threading, torch
from torchsgal.functional import native
assert native._lib.parallel_backend() == "pthreads"
xi = torch.randn(40001, 10, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
def digest(out):
    return hashlib.sha256(out.numpy().tobytes()).hexdigest()
torch.set_num_threads(1)
alone = digest(torch.ops.torchsgal.sgal3_exp(xi))
seen = set()
for threads in (2, 4, 3, 2):  # the pool grows to 3 helpers; fewer take part where fewer are asked
    torch.set_num_threads(threads)
    seen |= {digest(torch.ops.torchsgal.sgal3_exp(xi)) for _ in range(20)}
results = []
def calls():  # calls from several threads at once: one job on the pool, the others alone
    results.extend(digest(torch.ops.torchsgal.sgal3_exp(xi)) for _ in range(20))
workers = [threading.Thread(target=calls) for _ in range(4)]
for w in workers:
    w.start()
for w in workers:
    w.join()
seen |= set(results)
pid = os.fork()  # the child starts helpers of its own
if pid == 0:
    os._exit(0 if digest(torch.ops.torchsgal.sgal3_exp(xi)) == alone else 1)
_, status = os.waitpid(pid, 0)
print(len(results), status, seen == {alone})
"""


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX threads and fork")
def test_the_pthreads_pool_gives_the_same_bits_from_many_threads_and_after_fork():
    # TORCHSGAL_NATIVE_OPENMP=0: the helper threads' pool (_native_common.h), with 2 to 4
    # threads, calls from four Python threads at once, and a forked child's own helpers
    env = dict(os.environ, TORCHSGAL_NATIVE_OPENMP="0")
    out = subprocess.run([sys.executable, "-c", _POOL], env=env, capture_output=True, text=True,
                         check=True, timeout=300).stdout.split()
    assert out == ["80", "0", "True"]


class _Recorder:
    """Stands in for the compiled module and records which kernels were called."""

    def __init__(self, lib):
        self.lib, self.calls = lib, []

    def __getattr__(self, name):
        fn = getattr(self.lib, name)

        def record(*args):
            self.calls.append(name)
            return fn(*args)

        return record


@pytest.fixture
def recorder(monkeypatch):
    rec = _Recorder(native._lib)
    monkeypatch.setattr(native, "_lib", rec)
    return rec


def test_eager_cpu_calls_use_the_kernels(recorder):
    xi = tangents(torch.float64)[:8]
    g = SGal3.exp(xi)
    g.log()
    g.rplus(xi)
    assert recorder.calls == ["sgal3_exp", "sgal3_log", "sgal3_exp"]
    x = xi.clone().requires_grad_()
    F.log(F.exp(x)).sum().backward()
    assert recorder.calls[3:] == ["sgal3_exp", "sgal3_log", "sgal3_log_vjp", "sgal3_exp_vjp"]


def test_every_context_runs_the_kernels(recorder):
    """The operators run the C kernel whatever observes the call: recorded backward passes,
    vmap, torch.func transforms, forward AD and compiled inference."""
    xi = tangents(torch.float64)[:8]
    x = xi.clone().requires_grad_()
    (grad,) = torch.autograd.grad(F.exp(x).sum(), x, create_graph=True)
    assert recorder.calls == ["sgal3_exp", "sgal3_exp_vjp"]  # a recorded backward: the kernel
    grad.sum().backward()  # its own derivative: the closed form of the backward map, which
    # reaches exp's output and so exp's backward (the kernel) once more
    assert recorder.calls == ["sgal3_exp", "sgal3_exp_vjp", "sgal3_exp_vjp"]
    recorder.calls.clear()
    torch.func.vmap(F.exp)(xi)
    torch.func.jacrev(F.log)(F.exp_impl(xi[0]))
    torch.func.vmap(torch.func.jacrev(F.exp))(xi)
    with torch.autograd.forward_ad.dual_level():
        F.exp(torch.autograd.forward_ad.make_dual(xi, torch.ones_like(xi)))  # jvp: J_r = J_l(-xi)
    assert recorder.calls == ["sgal3_exp", "sgal3_log", "sgal3_log_vjp", "sgal3_exp",
                              "sgal3_exp_vjp", "sgal3_exp", "sgal3_jl"]
    recorder.calls.clear()
    with torch.no_grad():
        torch.compile(F.exp, backend="eager", fullgraph=True)(xi)
    assert recorder.calls == ["sgal3_exp"]


def test_the_tensor_code_runs_where_a_kernel_does_not_apply(recorder):
    xi = tangents(torch.float64)[:8]
    M = F.exp_impl(xi)
    with native.disabled():
        F.exp(xi)
    # differing batch shapes or dtypes (not produced by autograd itself): the closed form
    G = torch.ones(5, 5, dtype=torch.float64)
    torch.testing.assert_close(KERNELS.exp_vjp(xi, M, G), F._jl_tmv(-xi, F._exp_pullback(M, G.expand(8, 5, 5))))
    KERNELS.exp_vjp(xi, M, torch.ones(8, 5, 5, dtype=torch.float32))
    assert recorder.calls == []


def test_gradcheck_through_the_kernels():
    xi = tangents(torch.float64, copies=1)[::3].clone().requires_grad_()
    assert torch.autograd.gradcheck(F.exp, (xi,))
    # log's backward projects onto the group (see _autograd.py): check it along the group.
    d = torch.randn(xi.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    x0 = xi.detach()

    def log_along(t):
        return F.log(F.exp_impl(x0) @ F.exp_impl(t * d))

    t = torch.zeros(xi.shape[:-1], dtype=torch.float64)[..., None].requires_grad_()
    assert torch.autograd.gradcheck(log_along, (t,))


def test_environment_variable_turns_the_kernels_off():
    code = "from torchsgal.functional import native; print(native.enabled())"
    env = dict(os.environ, TORCHSGAL_NATIVE="0")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
