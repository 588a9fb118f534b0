"""The operators of SGal(3)'s subgroups SO(3), SE(3) and SE_2(3), of SE(2) and of Sim(3)
(``torchsgal::so3_*``, ``se3_*``, ``se23_*``, ``se2_*``, ``sim3_*``, functional/ops.py) and their C
kernels (functional/_native_sgal3.h, _native_se2.h and _native_sim3.h: exp, log, J_l and J_l^-1 of
each) against the tensor closed forms of functional/so3.py, se3.py, se23.py, se2.py and sim3.py at
every angle band (Sim(3): and every band of the scale's moments), in both dtypes; opcheck of the
six operators of each; where the kernels run.  The tensor code is itself checked against its definitions and
peers elsewhere (tests/test_definitions.py, tests/test_gtsam.py)."""
from __future__ import annotations

import math
import os

import numpy as np
import pytest
import torch
from test_native import ANGLES, _Recorder, assert_rowwise_close

from torchsgal import SE2, SE3, SE23, SO3, Sim3
from torchsgal.functional import native, se2, se3, se23, sim3, so3

GROUPS = {"so3": (SO3, so3), "se3": (SE3, se3), "se23": (SE23, se23), "se2": (SE2, se2), "sim3": (Sim3, sim3)}
# Sim(3)'s lambda = log s: both recursions of every scale moment (the switch at |lambda| = j + 1/2
# for order j, to 2 x 11 + 2), the series' own orders, and the normalised Jacobians beyond
# lambda = -30 (numerics.sim3_coefficients)
LAMBDAS = [0.0, 1e-9, -1e-4, 0.3, -0.49, 0.51, -1.5, 1.51, 6.0, -8.49, 12.5, -22.4, 22.6, -24.4,
           24.6, -29.9, 31.0, -31.0, 40.0, -40.0]


def _op(name):
    return getattr(torch.ops.torchsgal, name).default


def tangents(F, dtype, seed=0, copies=4):
    """Tangents with |phi| (the last three components; SE(2): |theta|, the last one) at every angle
    of ``ANGLES`` (both branches of every series and threshold, the near-pi symmetric-part log),
    the rest standard normal x 3."""
    rng = np.random.default_rng(seed)
    ang = np.repeat(ANGLES, copies)
    xi = 3.0 * rng.standard_normal((ang.size, F.DOF))
    if F.NAME == "SE2":  # theta, the last component, at every angle, of either sign
        xi[:, -1] = np.where(rng.standard_normal(ang.size) < 0, -1.0, 1.0) * ang
        return torch.tensor(xi, dtype=dtype)
    axis = rng.standard_normal((ang.size, 3))
    xi[:, F.PHI] = axis / np.linalg.norm(axis, axis=-1, keepdims=True) * ang[:, None]
    if F.NAME == "Sim3":  # every band of lambda at every angle
        xi = np.tile(xi, (len(LAMBDAS), 1))
        xi[:, 6] = np.repeat(LAMBDAS, ang.size)
    return torch.tensor(xi, dtype=dtype)


def kernel_test(fn):
    """A test of the C kernels themselves: left out of the run with the kernels switched off
    (TORCHSGAL_NATIVE=0, the second test run of .ci/run), as tests/test_native.py."""
    built = pytest.mark.skipif(not native.available() and os.environ.get("TORCHSGAL_NO_SKIPS") != "1",
                               reason="the C kernels were not compiled for this installation")
    return pytest.mark.kernels(built(fn))


@kernel_test
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["float64", "float32"])
@pytest.mark.parametrize("name", GROUPS)
def test_kernels_match_the_tensor_code_at_every_angle(name, dtype):
    _, F = GROUPS[name]
    xi = tangents(F, dtype)
    M = _op(f"{name}_exp")(xi)
    M_ref = F.exp_impl(xi)
    assert_rowwise_close(M, M_ref, dtype)
    # the constant bottom rows (none for SO(3); Sim(3)'s last entry is e^-lambda) exactly
    fixed = 2 if name == "se2" else 3
    assert torch.equal(M[:, fixed:, :fixed], M_ref[:, fixed:, :fixed])
    if name != "sim3":
        assert torch.equal(M[:, fixed:, :], M_ref[:, fixed:, :])
    assert_rowwise_close(_op(f"{name}_log")(M_ref), F.log_impl(M_ref), dtype)
    assert_rowwise_close(_op(f"{name}_jl")(xi), F.jl_impl(xi), dtype)
    assert_rowwise_close(_op(f"{name}_jl_inv")(xi), F.jl_inv_impl(xi), dtype)


@kernel_test
def test_se2_log_at_exactly_pi_and_the_identity():
    M = torch.eye(3, dtype=torch.float64).repeat(3, 1, 1)
    M[1, :2, :2] = -torch.eye(2, dtype=torch.float64)  # a rotation by pi: atan2(+0, -1) = pi
    M[2, :2, :2] = torch.tensor([[-1.0, 0.0], [-0.0, -1.0]], dtype=torch.float64)  # atan2(-0, -1) = -pi
    M[:, :2, 2] = torch.randn(3, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    out = _op("se2_log")(M)
    assert torch.equal(out[:, 2], se2.log_impl(M)[:, 2])
    assert torch.equal(out[:, 2], torch.tensor([0.0, math.pi, -math.pi], dtype=torch.float64))
    assert_rowwise_close(out, se2.log_impl(M), torch.float64)


@kernel_test
def test_float32_kernels_angle_over_every_octant():
    """The float32 kernels take atan2 from a polynomial (atan2_f32, _native_common.h), not
    glibc's atan2f: SE(2)'s angle over a dense sweep of (-pi, pi] and SO(3)'s over [0, pi] (both
    octants of every quadrant, the signed zeros and pi exactly) within 3e-7 of the float64 log of
    the same float32 matrices (relative, 1e-7 absolute: the polynomial's error with the entries'
    rounding), and a NaN entry gives a NaN angle."""
    theta = torch.linspace(-math.pi, math.pi, 200_001, dtype=torch.float64)
    xi = torch.stack([torch.zeros_like(theta), torch.zeros_like(theta), theta], -1)
    M = se2.exp_impl(xi).float()
    got, want = _op("se2_log")(M)[:, 2].double(), se2.log_impl(M.double())[:, 2]
    torch.testing.assert_close(got, want, rtol=3e-7, atol=1e-7)
    axis = torch.nn.functional.normalize(torch.randn(theta.numel(), 3, dtype=torch.float64,
                                                     generator=torch.Generator().manual_seed(3)), dim=-1)
    C = so3.exp_impl(axis * theta.abs()[:, None]).float()
    torch.testing.assert_close(_op("so3_log")(C).double(), so3.log_impl(C.double()), rtol=3e-7, atol=1e-7)
    exact = torch.eye(3).repeat(5, 1, 1)
    exact[1, :2, :2] = torch.tensor([[-1.0, 0.0], [0.0, -1.0]])  # atan2(+0, -1) = pi
    exact[2, :2, :2] = torch.tensor([[-1.0, 0.0], [-0.0, -1.0]])  # atan2(-0, -1) = -pi
    exact[3, :2, :2] = torch.tensor([[0.0, -1.0], [1.0, 0.0]])  # pi / 2
    exact[4, :2, :2] = torch.tensor([[-0.0, 1.0], [-1.0, -0.0]])  # atan2(-1, -0) = -pi / 2
    angles = _op("se2_log")(exact)[:, 2]
    assert angles.tolist() == torch.tensor([0.0, math.pi, -math.pi, math.pi / 2, -math.pi / 2]).tolist()
    for entry in ((0, 1), (0, 0)):  # NaN in atan2's y, and in its x
        bad = exact.clone()
        bad[:, entry[0], entry[1]] = float("nan")
        assert torch.isnan(_op("se2_log")(bad)[:, 2]).all()


@kernel_test
def test_float32_so3_log_lanes_give_the_bits_of_the_per_element_loop(recorder):
    """SO(3)'s float32 log runs eight elements per pass with both of rotation_log's paths and a
    select (_native_lanes_f32.h), the tail of a batch element by element: an element's bits do not
    depend on where it falls.  Rotations at every angle band (the series near 0, the symmetric
    part near pi, pi exactly), the identity, matrices that are not rotations, huge entries (atan2's
    rare branches: the pass is redone element by element), infinities and NaNs, shuffled; the
    whole batch against batches of seven (fewer than a pass: only the per-element loop runs) and
    against the batch shifted by three (every element in another lane)."""
    gen = torch.Generator().manual_seed(11)
    blocks = [torch.eye(3).expand(16, 3, 3)]
    for angle in (1e-30, 1e-8, 1e-4, 1e-3, 0.1, 1.0, 2.0, 3.0, math.pi - 1e-3, math.pi - 1e-6, math.pi):
        axis = torch.nn.functional.normalize(torch.randn(600, 3, dtype=torch.float64, generator=gen), dim=-1)
        scale = torch.rand(600, 1, dtype=torch.float64, generator=gen) if angle < 3.0 else torch.ones(600, 1)
        blocks.append(so3.exp_impl(angle * scale * axis).float())
    for size in (1.0, 1e30, 1e38):
        blocks.append(size * torch.randn(600, 3, 3, generator=gen))
    special = torch.randn(600, 3, 3, generator=gen)
    special[::7, 1, 0] = float("nan")
    special[::5, 0, 0] = float("inf")
    special[::11, 1, 1] = -float("inf")
    blocks.append(special)
    M = torch.cat(blocks)
    M = M[torch.randperm(M.shape[0], generator=gen)].contiguous()
    whole = _op("so3_log")(M)
    sevens = torch.cat([_op("so3_log")(M[k:k + 7]) for k in range(0, M.shape[0], 7)])
    shifted = _op("so3_log")(M[3:])
    assert recorder.calls == ["so3_log"] * (2 + math.ceil(M.shape[0] / 7))  # every call ran the kernel

    def same_bits(a, b):
        return bool(((a.view(torch.int32) == b.view(torch.int32)) | (a.isnan() & b.isnan())).all())

    assert same_bits(whole, sevens) and same_bits(whole[3:], shifted)
    rotations = torch.cat(blocks[:12])  # against the float64 log of the same float32 matrices
    torch.testing.assert_close(_op("so3_log")(rotations).double(), so3.log_impl(rotations.double()),
                               rtol=3e-7, atol=1e-7)


@kernel_test
@pytest.mark.parametrize("name", [g for g in GROUPS if g != "se2"])
def test_log_at_exactly_pi_and_the_identity(name):
    _, F = GROUPS[name]
    n = F.MATRIX_DIM
    M = torch.eye(n, dtype=torch.float64).repeat(4, 1, 1)
    for k, d in enumerate(([1.0, -1.0, -1.0], [-1.0, 1.0, -1.0], [-1.0, -1.0, 1.0])):
        M[k + 1, :3, :3] = torch.diag(torch.tensor(d, dtype=torch.float64))
    M[:, :3, 3:] = torch.randn(4, 3, n - 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    out = _op(f"{name}_log")(M)
    assert torch.equal(out[:, F.PHI], F.log_impl(M)[:, F.PHI])
    assert_rowwise_close(out, F.log_impl(M), torch.float64)
    assert torch.equal(out[0, F.PHI], torch.zeros(3, dtype=torch.float64))


@pytest.fixture
def recorder(monkeypatch):
    rec = _Recorder(native._lib)
    monkeypatch.setattr(native, "_lib", rec)
    return rec


@kernel_test
@pytest.mark.parametrize("name", GROUPS)
def test_eager_calls_run_the_kernels_and_the_backward_its_closed_form(recorder, name):
    G, F = GROUPS[name]
    xi = tangents(F, torch.float64)[:8]
    g = G.exp(xi)
    g.log()
    g.rplus(xi)
    G.jr(xi), G.jl_inv(xi)
    assert recorder.calls == [f"{name}_{k}" for k in ("exp", "log", "exp", "jl", "jl_inv")]
    recorder.calls.clear()
    x = xi.clone().requires_grad_()
    (grad,) = torch.autograd.grad(F.log(F.exp(x)).sum(), x)
    # the backward operators have no kernel: they run the closed forms (nothing recorded)
    assert recorder.calls == [f"{name}_exp", f"{name}_log"]
    with native.disabled():
        (expected,) = torch.autograd.grad(F.log(F.exp(x)).sum(), x)
    torch.testing.assert_close(grad, expected, rtol=0, atol=1e-12)
    recorder.calls.clear()
    with native.disabled():
        G.exp(xi)
    G.exp(xi.float()[None].expand(2, 8, F.DOF))  # broadcast views are read by value
    assert recorder.calls == [f"{name}_exp"]


@pytest.mark.parametrize("name", GROUPS)
def test_gradients_through_the_operators(name):
    G, F = GROUPS[name]
    xi = tangents(F, torch.float64, copies=1)[::3]
    if name == "sim3":  # |lambda| <= 6: finite differences of entries of size e^|lambda|
        xi = xi[xi[:, 6].abs() <= 6][::3]
    xi = xi.clone().requires_grad_()
    assert torch.autograd.gradcheck(F.exp, (xi,))
    spread = xi[:: max(1, xi.shape[0] // 4)][:4]  # four angles (Sim(3): and scales) across the bands
    assert torch.autograd.gradcheck(F.jl, (spread,))
    assert torch.autograd.gradcheck(F.jl_inv, (spread,))
    # the log away from the cut at pi, where a finite difference of the principal log jumps
    x0 = xi.detach()[xi.detach()[:, F.PHI].norm(dim=-1) < math.pi - 1e-3]
    d = torch.randn(x0.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(3))

    def log_along(t):  # log's backward projects onto the group: checked along the group
        return F.log(F.exp_impl(x0) @ F.exp_impl(t * d))

    t = torch.zeros(x0.shape[:-1], dtype=torch.float64)[..., None].requires_grad_()
    assert torch.autograd.gradcheck(log_along, (t,))


def _arguments(name, op, batch, dtype):
    F = GROUPS[name][1]
    n, dof = F.MATRIX_DIM, F.DOF
    g = torch.Generator().manual_seed(7)
    xi = (0.8 * torch.randn(*batch, dof, generator=g, dtype=torch.float64)).to(dtype)
    M = F.exp_impl(xi.double()).to(dtype)
    G = torch.randn(*batch, n, n, generator=g, dtype=torch.float64).to(dtype)
    w = torch.randn(*batch, dof, generator=g, dtype=torch.float64).to(dtype)
    args = {"exp": (xi,), "log": (M,), "exp_vjp": (xi, M, G), "log_vjp": (M, xi, w), "jl": (xi,),
            "jl_inv": (xi,)}[op]
    return tuple(a.clone().requires_grad_(dtype is torch.float64) for a in args)


# The registration code is ops._define, shared with SGal(3), whose operators tests/test_ops.py
# opchecks over every batch shape and dtype, with the kernels (the first test run of .ci/run) and
# without (the second, TORCHSGAL_NATIVE=0); here each operator once with gradients (float64, the
# kernel on) and once without (float32, the closed form), and the backward operators (closed
# forms only) with second derivatives for SE(3), without for SE_2(3).
@pytest.mark.parametrize("dtype,batch,kernels", [(torch.float64, (2, 3), True), (torch.float32, (), False)],
                         ids=["f64-kernels_on", "f32-kernels_off"])
@pytest.mark.parametrize("op", ("exp", "log", "jl", "jl_inv"))
@pytest.mark.parametrize("name", GROUPS)
def test_opcheck(name, op, dtype, batch, kernels):
    args = _arguments(name, op, batch, dtype)
    if kernels:
        torch.library.opcheck(_op(f"{name}_{op}"), args)
    else:
        with native.disabled():
            torch.library.opcheck(_op(f"{name}_{op}"), args)


@pytest.mark.parametrize("op", ("exp_vjp", "log_vjp"))
@pytest.mark.parametrize("name,dtype,batch", [("se3", torch.float64, (2, 3)), ("se23", torch.float32, (2,))],
                         ids=["se3-f64", "se23-f32"])
def test_opcheck_of_the_backward_operators(name, dtype, batch, op):
    torch.library.opcheck(_op(f"{name}_{op}"), _arguments(name, op, batch, dtype))


@pytest.mark.parametrize("shape", [(), (5,), (2, 3, 1), (0,)])
@pytest.mark.parametrize("name", GROUPS)
def test_batch_shapes(name, shape):
    G, F = GROUPS[name]
    xi = tangents(F, torch.float64)[: math.prod(shape)].reshape(*shape, F.DOF)
    M = G.exp(xi).as_matrix()
    assert M.shape == (*shape, F.MATRIX_DIM, F.MATRIX_DIM)
    torch.testing.assert_close(M, F.exp_impl(xi), rtol=0, atol=1e-13)
    assert G(M).log().shape == (*shape, F.DOF)
    assert G.jl(xi).shape == (*shape, F.DOF, F.DOF)


@pytest.mark.parametrize("name", GROUPS)
def test_operators_refuse_bad_shapes_by_name(name):
    F = GROUPS[name][1]
    with pytest.raises(ValueError, match=rf"xi must have shape \(\.\.\., {F.DOF}\), got \(5, 10\)"):
        _op(f"{name}_exp")(torch.zeros(5, 10, dtype=torch.float64))
    with pytest.raises(ValueError, match=rf"M must have shape \(\.\.\., {F.MATRIX_DIM}, {F.MATRIX_DIM}\)"):
        _op(f"{name}_log")(torch.zeros(5, 6, 6, dtype=torch.float64))
    with pytest.raises(ValueError, match=rf"xi must have shape \(\.\.\., {F.DOF}\)"):
        _op(f"{name}_jl_inv")(torch.zeros(2, 11, dtype=torch.float32))


@pytest.mark.parametrize("name", ["so3", "se3", "se23", "sgal3", "sim3", "se2", "so2"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["f32", "f64"])
def test_log_of_a_matrix_with_an_infinite_entry_is_nan(name, dtype):
    """An infinite entry of the rotation block gives a NaN rotation part, as a NaN entry does, in
    the kernels and the tensor code alike (the log read it as a rotation of angle 0, pi/2 or pi:
    a finite, wrong tangent); every other element of the batch is unchanged."""
    from torchsgal import functional as F
    m = getattr(F, name)
    xi = 0.5 * torch.randn(9, m.DOF, dtype=dtype, generator=torch.Generator().manual_seed(4))
    M = m.exp_impl(xi)
    k = 2 if name in ("se2", "so2") else 3
    spoiled = M.clone()
    entries = [(r, c) for r in range(k) for c in range(k)]
    for b in range(8):  # every entry of the rotation block, +inf and -inf
        r, c = entries[b % len(entries)]
        spoiled[b, r, c] = math.inf if (b // len(entries) + b) % 2 else -math.inf
    phi = slice(m.DOF - 1, m.DOF) if name in ("se2", "so2") else slice(3, 6) if name in ("se3", "sim3") \
        else slice(0, 3) if name == "so3" else slice(6, 9)
    for log in (m.log, lambda M: _without_kernels(m.log, M)):
        out = log(spoiled)
        assert out[:8, phi].isnan().all(), name
        assert torch.equal(out[8], log(M)[8])


def _without_kernels(fn, *args):
    with native.disabled():
        return fn(*args)
