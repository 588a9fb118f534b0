"""The IMU preintegration kernel (torchsgal/imu/_native_imu.h) and its torch operator
``torch.ops.torchsgal.imu_preintegrate`` (torchsgal/imu/_kernels.py): the C loop against the
tensor code it transcribes (every branch of the exp series, both dtypes), torch.library.opcheck,
vmap against a loop, torch.compile against eager, the errors of bad arguments, and the rule and
the switches that decide where the C loop runs.  The tensor code is itself checked against GTSAM,
Monte Carlo and quadrature in tests/test_imu.py."""
from __future__ import annotations

import math
import os
import subprocess
import sys
import threading

import numpy as np
import pytest
import torch
from torch.library import opcheck

from torchsgal.functional import native
from torchsgal.imu import _kernels, preintegrate
from torchsgal.imu.preintegration import _integrate

# ``kernels``: tests of the C kernels themselves, left out of the run with the kernels switched off
# (TORCHSGAL_NATIVE=0, the second test run of .ci/run).
pytestmark = [pytest.mark.kernels,
              pytest.mark.skipif(not _kernels.available() and os.environ.get("TORCHSGAL_NO_SKIPS") != "1",
                                 reason="the IMU C kernel was not compiled for this installation")]

OP = torch.ops.torchsgal.imu_preintegrate
# Half-step rotation angles |omega| dt / 2 cycled over the samples: both branches of the exp
# series (numerics.SERIES_THRESHOLD = 1) and the angles up to pi.
ANGLES = [0.0, 1e-12, 1e-9, 1e-6, 1e-4, 1e-3, 0.3, 0.5, 0.7, 1.0 - 1e-9, 1.0, 1.0 + 1e-9, 1.5,
          math.pi / 2, 2.0, 3.0, math.pi - 1e-6]


def imu_stream(n, K, dtype, seed=0):
    """n windows of K samples whose half-step rotation angles run over ANGLES, with a zero dt
    among them, and biases."""
    rng = np.random.default_rng(seed)
    dt = rng.uniform(0.001, 0.05, (n, K))
    dt[0, 0] = 0.0
    axis = rng.standard_normal((n, K, 3))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    angle = np.resize(np.array(ANGLES), n * K).reshape(n, K)
    gyro = axis * (2 * angle / np.where(dt > 0, dt, 1.0))[..., None]
    acc = rng.normal(0, 5.0, (n, K, 3))
    b_g, b_a = rng.normal(0, 0.01, (n, 3)), rng.normal(0, 0.1, (n, 3))
    return [torch.tensor(x, dtype=dtype) for x in (gyro, acc, dt, b_g, b_a)]


def imu_results(gyro, acc, dt, b_g, b_a, **flags):
    r = preintegrate(gyro, acc, dt, gyro_bias=b_g, acc_bias=b_a, gyro_noise_density=1e-3,
                     acc_noise_density=1e-2, time_noise_density=1e-4, **flags)
    return [x for x in (r.delta.as_matrix(), r.covariance, r.bias_jacobian) if x is not None]


class _Recorder:
    """Stands in for the compiled module and records which kernels were called, by which thread."""

    def __init__(self, lib):
        self.lib, self.calls, self.threads = lib, [], []

    def __getattr__(self, name):
        fn = getattr(self.lib, name)

        def record(*args):
            self.calls.append(name)
            self.threads.append(threading.current_thread().name)
            return fn(*args)

        return record


@pytest.fixture
def recorder(monkeypatch):
    rec = _Recorder(_kernels._lib)
    monkeypatch.setattr(_kernels, "_lib", rec)
    return rec


def test_the_imu_kernel_is_built_where_the_suite_requires_every_dependency():
    # .ci/run sets TORCHSGAL_NO_SKIPS=1 on a machine with a C compiler: pip must have built it.
    if os.environ.get("TORCHSGAL_NO_SKIPS") == "1":
        assert _kernels.available(), "pip install did not build torchsgal.imu._native"
    expected = "none" if sys.platform == "win32" else (
        "openmp" if "ATen parallel backend: OpenMP" in torch.__config__.parallel_info() else "pthreads")
    assert _kernels._lib.parallel_backend() == expected


# ------------------------------------------------------------- the C loop against the tensor code
# float64: the kernel's order of operations differs from the tensor code's (a sequential product
# per window, not a scan; its own summation order): measured 2.8e-15 (bias Jacobian), 1.8e-15
# (increment), 1.1e-15 (covariance).  float32: the kernel computes in double and rounds once,
# the covariance is formed from the rounded sums in float32: measured 1.7e-7, against the float64
# reference (the float32 tensor code itself is 3.0e-6 off it there: its scan rounds in float32).
IMU_TOL = {torch.float64: 1e-14, torch.float32: 1e-6}


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["float64", "float32"])
@pytest.mark.parametrize("K", [1, 2, 3, 64])
@pytest.mark.parametrize("nodes", [True, False], ids=["covariance", "increment"])
def test_imu_kernel_matches_the_tensor_code(dtype, K, nodes):
    stream = imu_stream(12, K, dtype, seed=K)
    flags = {} if nodes else dict(covariance=False, bias_jacobian=False)
    out = imu_results(*stream, **flags)
    with native.disabled():  # the reference: the tensor code in float64 on the same values
        ref = imu_results(*(x.double() for x in stream), **flags)
    assert len(out) == len(ref) == (3 if nodes else 1)
    for a, e in zip(out, ref):
        assert a.dtype == dtype and a.shape == e.shape
        scale = e.abs().amax(dim=(-2, -1)).clamp_min(1e-300)  # a zero-length window: all zero
        err = float(((a.double() - e).abs().amax(dim=(-2, -1)) / scale).max())
        assert err <= IMU_TOL[dtype], f"kernel vs tensor code: {err:.3g} > {IMU_TOL[dtype]:.1g}"


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["float64", "float32"])
def test_operator_node_sums_match_the_plain_tensor_code(dtype, monkeypatch):
    """The operator's packed node sums, unpacked, against preintegration._integrate (the plain,
    differentiable tensor code, float64): the same sums feed the covariance and bias Jacobian.
    Each sum is compared relative to its largest entry (some are of size dt^3)."""
    gyro, acc, dt, b_g, b_a = imu_stream(7, 5, dtype, seed=11)
    delta, packed = OP(gyro, acc, dt, b_g, b_a, True)
    assert packed.shape == (7, _kernels.WIDTH)
    sums = _kernels.node_sums(packed)
    captured = {}
    import torchsgal.imu.preintegration as P
    original = P._node_moments

    def capture(groups, w_identity):
        captured.update(original(groups, w_identity))
        return captured

    monkeypatch.setattr(P, "_node_moments", capture)
    ref = _integrate(*(x.double() for x in (gyro, acc, dt, b_g, b_a)), 0.0, 0.0, 0.0, True, False, True)
    assert set(sums) == set(captured)
    torch.testing.assert_close(delta.double(), ref[0], rtol=0, atol=IMU_TOL[dtype] * ref[0].abs().max())
    for k, e in captured.items():
        a = sums[k]
        assert a.shape == e.shape and a.dtype == dtype, k
        err = float((a.double() - e).abs().max() / e.abs().max())
        assert err <= IMU_TOL[dtype], f"{k}: {err:.3g}"


def test_imu_kernel_reads_strided_and_broadcast_inputs_by_value():
    gyro, acc, dt, b_g, b_a = imu_stream(6, 9, torch.float64, seed=5)
    gyro_t = gyro.transpose(0, 1).contiguous().transpose(0, 1)  # window-minor memory
    assert not gyro_t.is_contiguous()
    kw = dict(gyro_noise_density=1e-3, acc_noise_density=1e-2)
    for args in [(gyro_t, acc, dt[0], b_g[0], None), (gyro, acc, 0.01, b_g, b_a[:1])]:
        out = preintegrate(args[0], acc, args[2], gyro_bias=args[3], acc_bias=args[4], **kw)
        with native.disabled():
            ref = preintegrate(args[0].contiguous(), acc, args[2], gyro_bias=args[3], acc_bias=args[4], **kw)
        for a, e in [(out.delta.as_matrix(), ref.delta.as_matrix()), (out.covariance, ref.covariance),
                     (out.bias_jacobian, ref.bias_jacobian)]:
            assert torch.allclose(a, e, rtol=0, atol=2e-14 * e.abs().max())
    # the operator itself: strided and stride-0 (expanded) views read by value
    d1, m1 = OP(gyro_t, acc, dt, b_g[:1].expand(6, 3), b_a, True)
    d2, m2 = OP(gyro_t.contiguous(), acc, dt, b_g[:1].expand(6, 3).contiguous(), b_a, True)
    assert torch.equal(d1, d2) and torch.equal(m1, m2)


def test_imu_kernel_threads_split_the_windows_without_changing_a_bit():
    stream = imu_stream(200, 100, torch.float64, seed=6)  # 200 x 100 samples: over 2 threads
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = imu_results(*stream)
        torch.set_num_threads(2)
        two = imu_results(*stream)
    finally:
        torch.set_num_threads(before)
    assert all(torch.equal(a, b) for a, b in zip(one, two))


def test_imu_kernel_keeps_a_non_finite_sample_in_its_window():
    gyro, acc, dt, b_g, b_a = imu_stream(4, 5, torch.float64, seed=7)
    gyro[1, 2, 0], acc[2, 4, 1] = math.nan, math.inf
    out = imu_results(gyro, acc, dt, b_g, b_a)
    with native.disabled():
        ref = imu_results(gyro, acc, dt, b_g, b_a)
    for a, e in zip(out, ref):
        assert torch.equal(torch.isfinite(a), torch.isfinite(e))
        assert torch.isfinite(a[[0, 3]]).all() and not torch.isfinite(a[1]).all()
        finite = torch.isfinite(e)
        assert torch.allclose(a[finite], e[finite], rtol=0, atol=2e-14 * e[finite].abs().max())


# ------------------------------------------------------------------------------ the operator
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["float64", "float32"])
@pytest.mark.parametrize("n, K", [(1, 1), (3, 4), (2, 33), (0, 2)])
@pytest.mark.parametrize("nodes", [True, False], ids=["nodes", "increment"])
@pytest.mark.parametrize("kernel", [True, False], ids=["C", "tensor"])
def test_opcheck(dtype, n, K, nodes, kernel):
    """Schema, fake (meta) implementation, autograd registration and AOT dispatch, for the C
    loop and the tensor code (native.disabled())."""
    args = tuple(imu_stream(max(n, 1), K, dtype, seed=n + K)) if n else tuple(
        torch.zeros(s, dtype=dtype) for s in ((0, K, 3), (0, K, 3), (0, K), (0, 3), (0, 3)))
    with contextlib_disabled(not kernel):
        result = opcheck(OP.default, args + (nodes,))
        delta, moments = OP(*args, nodes)
    assert all(v == "SUCCESS" for v in result.values()), result
    assert delta.shape == (n, 5, 5) and moments.shape == (n, _kernels.WIDTH if nodes else 0)
    assert delta.dtype == moments.dtype == dtype


def contextlib_disabled(off: bool):
    import contextlib
    return native.disabled() if off else contextlib.nullcontext()


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["float64", "float32"])
def test_operator_c_loop_equals_its_tensor_code(dtype):
    gyro, acc, dt, b_g, b_a = imu_stream(9, 6, dtype, seed=3)
    for nodes in (True, False):
        c = OP(gyro, acc, dt, b_g, b_a, nodes)
        with native.disabled():
            t = OP(*(x.double() for x in (gyro, acc, dt, b_g, b_a)), nodes)
        for a, e in zip(c, t):
            assert a.dtype == dtype and a.shape == e.shape
            if e.numel():
                scale = e.abs().amax(dim=-1, keepdim=True).clamp_min(1e-300)
                err = float(((a.double() - e).abs() / scale).max())
                assert err <= IMU_TOL[dtype], f"{err:.3g}"


@pytest.mark.parametrize("kernel", [True, False], ids=["C", "tensor"])
def test_vmap_over_the_operator_equals_the_loop(kernel):
    B = 3
    gyro, acc, dt, b_g, b_a = imu_stream(B * 4, 5, torch.float64, seed=9)
    gyro, acc, dt = gyro.view(B, 4, 5, 3), acc.view(B, 4, 5, 3), dt.view(B, 4, 5)
    b_g, b_a = b_g.view(B, 4, 3), b_a.view(B, 4, 3)
    with contextlib_disabled(not kernel):
        loop = [OP(gyro[i], acc[i], dt[i], b_g[i], b_a[i], True) for i in range(B)]
        # every argument batched, along its first dimension
        out = torch.func.vmap(OP, in_dims=(0, 0, 0, 0, 0, None))(gyro, acc, dt, b_g, b_a, True)
        for j, part in enumerate(out):
            assert torch.equal(part, torch.stack([x[j] for x in loop]))
        # only gyro batched, along a middle dimension, out_dims elsewhere; the rest shared
        shared = [OP(gyro[i], acc[0], dt[0], b_g[0], b_a[0], False) for i in range(B)]
        out = torch.func.vmap(OP, in_dims=(1, None, None, None, None, None), out_dims=1)(
            gyro.movedim(0, 1), acc[0], dt[0], b_g[0], b_a[0], False)
        for j, part in enumerate(out):
            assert part.shape[1] == B
            assert torch.equal(part, torch.stack([x[j] for x in shared], dim=1))
        # nested vmap: two batch dimensions joined into the windows
        nested = torch.func.vmap(torch.func.vmap(OP, in_dims=(0, 0, 0, 0, 0, None)),
                                 in_dims=(0, 0, 0, 0, 0, None))(
            gyro.view(B, 2, 2, 5, 3), acc.view(B, 2, 2, 5, 3), dt.view(B, 2, 2, 5), b_g.view(B, 2, 2, 3),
            b_a.view(B, 2, 2, 3), True)
        assert torch.equal(nested[1], torch.stack([x[1] for x in loop]).view(B, 2, 2, _kernels.WIDTH))


@pytest.mark.parametrize("backend", ["aot_eager", "inductor"])
def test_a_compiled_function_calling_the_operator_matches_eager(backend, recorder):
    gyro, acc, dt, b_g, b_a = imu_stream(5, 8, torch.float64, seed=10)

    def f(gyro, acc, dt, b_g, b_a):
        delta, moments = OP(gyro * 1.0, acc, dt, b_g, b_a, True)
        sums = _kernels.node_sums(moments)
        return delta[:, :3, :3] @ delta[:, :3, 4:5], sums["Y"].sum(1) * sums["w"][:, None, None]

    torch.compiler.reset()
    compiled = torch.compile(f, fullgraph=True, backend=backend)
    got = compiled(gyro, acc, dt, b_g, b_a)
    assert recorder.calls == ["imu_preintegrate"]  # the C loop runs inside the compiled graph
    expected = f(gyro, acc, dt, b_g, b_a)
    for a, e in zip(got, expected):
        torch.testing.assert_close(a, e, rtol=1e-14, atol=1e-14)
    with native.disabled():  # the switch is read when the graph runs, not when it is traced
        compiled(gyro, acc, dt, b_g, b_a)
    assert recorder.calls == ["imu_preintegrate", "imu_preintegrate"]


def test_bad_arguments_are_refused_by_name():
    gyro, acc, dt, b_g, b_a = imu_stream(2, 3, torch.float64)
    with pytest.raises(ValueError, match=r"acc must have shape \(2, 3, 3\).*got \(2, 4, 3\)"):
        OP(gyro, torch.zeros(2, 4, 3, dtype=torch.float64), dt, b_g, b_a, True)
    with pytest.raises(ValueError, match=r"dt must have shape \(2, 3\)"):
        OP(gyro, acc, dt[:, :2], b_g, b_a, True)
    with pytest.raises(ValueError, match=r"b_a must have shape \(2, 3\)"):
        OP(gyro, acc, dt, b_g, b_a[:1], True)
    with pytest.raises(ValueError, match=r"gyro must have shape \(n, K, 3\) with K >= 1"):
        OP(gyro[:, :0], acc[:, :0], dt[:, :0], b_g, b_a, True)
    with pytest.raises(TypeError, match="b_g has dtype torch.float32 but gyro has dtype torch.float64"):
        OP(gyro, acc, dt, b_g.float(), b_a, True)
    with pytest.raises(TypeError, match="gyro must have a floating dtype"):
        OP(gyro.half(), acc.half(), dt.half(), b_g.half(), b_a.half(), True)


def test_a_backward_through_the_operator_raises():
    gyro, acc, dt, b_g, b_a = imu_stream(2, 3, torch.float64)
    delta, _ = OP(gyro.clone().requires_grad_(), acc, dt, b_g, b_a, False)
    with pytest.raises(RuntimeError, match="no autograd formula"):
        delta.sum().backward()


# --------------------------------------------------------------------- where the C loop runs
def test_imu_kernel_runs_only_where_unobserved_and_isotropic(recorder):
    gyro, acc, dt, b_g, b_a = imu_stream(3, 4, torch.float64, seed=8)
    imu_results(gyro, acc, dt, b_g, b_a)
    imu_results(gyro, acc, dt, b_g, b_a, covariance=False, bias_jacobian=False)
    preintegrate(gyro, acc, dt, covariance=False)  # bias Jacobian only
    assert recorder.calls == ["imu_preintegrate"] * 3
    recorder.calls.clear()
    per_axis = torch.tensor([1e-2, 2e-2, 3e-2], dtype=torch.float64)
    preintegrate(gyro, acc, dt, acc_noise_density=per_axis)  # the general covariance: tensor code
    preintegrate(gyro.clone().requires_grad_(), acc, dt)  # recorded by autograd
    torch.func.vmap(lambda g: preintegrate(g, acc[0], dt[0]).delta.as_matrix())(gyro)
    with native.disabled():
        imu_results(gyro, acc, dt, b_g, b_a)
    assert "imu_preintegrate" not in recorder.calls
    # a window of no samples is refused by the kernel itself (preintegrate refuses it first)
    with pytest.raises(ValueError, match="K >= 1"):
        _kernels._lib.imu_preintegrate(0, 0, 0, 0, 0, 0, 0, 1, 0, 1, True)


def test_disabled_in_one_thread_leaves_another_threads_imu_kernel_on(recorder):
    gyro, acc, dt, b_g, b_a = imu_stream(3, 4, torch.float64, seed=12)
    inside, other_done = threading.Event(), threading.Event()
    errors = []

    def switched_off():
        try:
            with native.disabled():
                inside.set()
                assert other_done.wait(30)  # the other thread has run while this block is open
                OP(gyro, acc, dt, b_g, b_a, True)
                imu_results(gyro, acc, dt, b_g, b_a)
        except BaseException as e:  # reported by the main thread
            errors.append(e)

    def switched_on():
        try:
            assert inside.wait(30)
            OP(gyro, acc, dt, b_g, b_a, True)
            imu_results(gyro, acc, dt, b_g, b_a)
        except BaseException as e:
            errors.append(e)
        finally:
            other_done.set()

    threads = [threading.Thread(target=switched_off, name="off"), threading.Thread(target=switched_on, name="on")]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert not errors, errors
    assert recorder.threads == ["on", "on"] and recorder.calls == ["imu_preintegrate"] * 2


_ENV_OFF = """
import torch
from torchsgal.functional import native
from torchsgal.imu import _kernels
calls = []
lib = _kernels._lib
_kernels._lib = type("R", (), {"__getattr__": lambda self, name: (lambda *a: calls.append(name) or getattr(lib, name)(*a))})()
g = torch.randn(2, 3, 3, dtype=torch.float64)
z = torch.zeros(2, 3, dtype=torch.float64)
d, m = torch.ops.torchsgal.imu_preintegrate(g, g, torch.full((2, 3), 0.01, dtype=torch.float64), z, z, True)
print(native.enabled(), calls, tuple(d.shape), tuple(m.shape))
"""


def test_environment_variable_turns_the_imu_kernel_off():
    env = dict(os.environ, TORCHSGAL_NATIVE="0")
    out = subprocess.run([sys.executable, "-c", _ENV_OFF], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.split("\n")[-2] == "False [] (2, 5, 5) (2, 117)"
