"""Gradients: gradcheck (finite differences) of every operation at the delicate angles, the
custom exp/log backward against plain autograd through the same closed form, finite
gradients at the identity in float32, forward mode (jvp, jacfwd, hessian), torch.func (vmap,
jacrev) and torch.compile."""
from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
import reference as ref
import torch
from conftest import np64, sample_tangent

import torchsgal as ts

GROUPS = ts.ALL_GROUPS
IDS = lambda g: g.__name__  # noqa: E731
GRAD_ANGLES = [None, 0.0, 1e-9, 1e-5, 1e-3, math.pi - 1e-4]
ANGLE_IDS = ["generic", "0", "1e-9", "1e-5", "1e-3", "pi-1e-4"]


def _xi(G, angle, n=2, seed=0):
    angles = np.linspace(0.4, 2.5, n) if angle is None else [angle] * n
    return sample_tangent(G, (n,), torch.float64, seed=seed, angles=angles).requires_grad_(True)


def _operations(G):
    f = G._f
    E = lambda x: f.exp(x)  # noqa: E731
    other = f.exp(sample_tangent(G, (2,), torch.float64, seed=9))
    p = torch.randn(2, G.point_dim, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    k = G.rotation_dim
    ops = {
        "exp": E,
        # log of a group-valued function of x built independently (matrix_exp + autograd)
        "log": lambda x: f.log(torch.linalg.matrix_exp(f.hat(x))),
        "compose": lambda x: f.compose(E(x), other) + f.compose(other, E(x)),
        "inverse": lambda x: f.inverse(E(x)),
        "act": lambda x: f.act(E(x), p),
        "act_direction": lambda x: f.act_direction(E(x), p[..., :k]),
        "adjoint": lambda x: f.adjoint(E(x)),
        "jl": f.jl,
        "jr": f.jr,
        "jl_inv": f.jl_inv,
        "jr_inv": f.jr_inv,
        "log_exp": lambda x: f.log(E(x)),
    }
    if hasattr(f, "act_velocity"):
        ops["act_velocity"] = lambda x: f.act_velocity(E(x), p[..., :3])
    return ops


OP_NAMES = ["exp", "log", "compose", "inverse", "act", "act_direction", "adjoint", "jl", "jr",
            "jl_inv", "jr_inv", "log_exp"]


# J_r(xi) = J_l(-xi) in every group (functional/*.py: jr and jr_inv call jl and jl_inv at -xi;
# SO(2)'s four are the same constant function), so the right Jacobians' derivatives at every
# angle band are the left ones' at the negated samples: jl and jl_inv are checked over the
# bands, jr and jr_inv at the generic angles.
BANDED = [(op, angle) for op in OP_NAMES for angle in GRAD_ANGLES
          if op not in ("jr", "jr_inv") or angle is None]


@pytest.mark.parametrize("op,angle", BANDED,
                         ids=[f"{op}-{ANGLE_IDS[GRAD_ANGLES.index(a)]}" for op, a in BANDED])
@pytest.mark.parametrize("G", GROUPS, ids=IDS)
def test_gradcheck(G, op, angle):
    fn = _operations(G)[op]
    assert torch.autograd.gradcheck(fn, (_xi(G, angle),), eps=1e-6, atol=1e-6, rtol=1e-5)


@pytest.mark.parametrize("G", [ts.SE23, ts.SGal3], ids=IDS)
def test_gradcheck_act_velocity(G):
    assert torch.autograd.gradcheck(_operations(G)["act_velocity"], (_xi(G, 1e-5),))


@pytest.mark.parametrize("angle", GRAD_ANGLES, ids=ANGLE_IDS)
@pytest.mark.parametrize("G", GROUPS, ids=IDS)
def test_custom_backward_equals_plain_autograd(G, angle):
    """The plain implementation (autograd through the closed form) is the oracle."""
    f = G._f
    xi = _xi(G, angle, n=4)
    gen = torch.Generator().manual_seed(21)
    W = torch.randn(4, G.matrix_dim, G.matrix_dim, dtype=torch.float64, generator=gen)
    w = torch.randn(4, G.dof, dtype=torch.float64, generator=gen)
    (g1,) = torch.autograd.grad((f.exp(xi) * W).sum(), xi)
    (g2,) = torch.autograd.grad((f.exp_impl(xi) * W).sum(), xi)
    np.testing.assert_allclose(g1.numpy(), g2.numpy(), atol=1e-11, rtol=1e-10)
    # log: the incoming perturbations are tangent to the group (they come from exp_impl), and
    # log(exp(x)) = x below pi, so both gradients of <w, log(exp(x))> are exactly w (measured
    # worst 3.7e-15 over these angles, every group, 5 seeds of w)
    (h1,) = torch.autograd.grad((f.log(f.exp_impl(xi)) * w).sum(), xi)
    (h2,) = torch.autograd.grad((f.log_impl(f.exp_impl(xi)) * w).sum(), xi)
    np.testing.assert_allclose(h1.numpy(), w.numpy(), rtol=0, atol=1e-12)
    np.testing.assert_allclose(h2.numpy(), w.numpy(), rtol=0, atol=1e-12)


@pytest.mark.parametrize("G", GROUPS, ids=IDS)
def test_float32_gradients_at_identity(G):
    """Finite and correct at xi = 0 in float32: d<W, exp(xi)>/dxi = hat^T(W) there."""
    f = G._f
    gen = torch.Generator().manual_seed(22)
    W = torch.randn(G.matrix_dim, G.matrix_dim, generator=gen)
    basis = ref.basis(G.__name__)  # hat(e_j)
    expected = np.einsum("jab,ab->j", basis, W.numpy().astype(float))
    for fn in (f.exp, f.exp_impl):
        xi = torch.zeros(G.dof, requires_grad=True)
        (g,) = torch.autograd.grad((fn(xi) * W).sum(), xi)
        assert torch.isfinite(g).all()
        np.testing.assert_allclose(g.numpy(), expected, rtol=0, atol=1e-5)
    # log at the identity: gradient of <w, log(exp(x))> is w
    w = torch.randn(G.dof, generator=gen)
    for fn in (f.log, f.log_impl):
        xi = torch.zeros(G.dof, requires_grad=True)
        (g,) = torch.autograd.grad((fn(f.exp(xi)) * w).sum(), xi)
        assert torch.isfinite(g).all()
        np.testing.assert_allclose(g.numpy(), w.numpy(), rtol=0, atol=1e-5)
    # Jacobians: finite gradients at zero
    for name in ("jl", "jr", "jl_inv", "jr_inv"):
        xi = torch.zeros(G.dof, requires_grad=True)
        out = getattr(f, name)(xi).sum()
        if not out.requires_grad:  # SO2: the Jacobians are constant
            continue
        (g,) = torch.autograd.grad(out, xi)
        assert torch.isfinite(g).all(), name


@pytest.mark.parametrize("G", GROUPS, ids=IDS)
def test_vmap_and_jacrev(G):
    f = G._f
    xi = sample_tangent(G, (5,), torch.float64, seed=4)
    np.testing.assert_allclose(
        torch.func.vmap(f.exp)(xi).numpy(), f.exp(xi).numpy(), atol=0, rtol=0
    )
    M = f.exp(xi)
    np.testing.assert_allclose(torch.func.vmap(f.log)(M).numpy(), f.log(M).numpy(), rtol=0, atol=1e-15)

    # jacrev of d -> log(exp(x0)^-1 exp(x0 + d)) at d = 0 is J_r(x0); vmapped over the batch
    def local(x0):
        E0inv = f.inverse(f.exp(x0))
        return torch.func.jacrev(lambda d: f.log(f.compose(E0inv, f.exp(x0 + d))))(
            torch.zeros_like(x0)
        )

    J = torch.func.vmap(local)(xi)
    np.testing.assert_allclose(J.numpy(), ref.jr_series(G.__name__, np64(xi)), rtol=0, atol=1e-10)


@pytest.mark.parametrize("G", GROUPS, ids=IDS)
def test_vmap_whole_api(G):
    """Every batched operation of the class API under torch.func.vmap equals the batched call
    (the angles cycle through the small-angle branches and near pi)."""
    x, y = (sample_tangent(G, (12,), torch.float64, seed=s) for s in (5, 6))
    alpha = torch.linspace(-0.5, 1.5, 12, dtype=torch.float64)
    p = torch.randn(12, G.point_dim, dtype=torch.float64, generator=torch.Generator().manual_seed(7))
    d = p[..., : G.rotation_dim]
    ops = {
        "compose": lambda a, b: (G.exp(a) @ G.exp(b)).as_matrix(),
        "inverse": lambda a, b: G.exp(a).inverse().as_matrix(),
        "adjoint": lambda a, b: G.exp(a).adjoint(),
        "rplus": lambda a, b: G.exp(a).rplus(b).as_matrix(),
        "lplus": lambda a, b: G.exp(a).lplus(b).as_matrix(),
        "rminus": lambda a, b: G.exp(a).rminus(G.exp(b)),
        "lminus": lambda a, b: G.exp(a).lminus(G.exp(b)),
        "between": lambda a, b: G.exp(a).between(G.exp(b)).as_matrix(),
        "from_matrix": lambda a, b: G.from_matrix(G.exp(a).as_matrix()).log(),
        "rotation": lambda a, b: G.exp(a).rotation(),
        "hat_vee": lambda a, b: G.vee(G.hat(a)),
        "ad": lambda a, b: G.ad(a),
        "jl": lambda a, b: G.jl(a),
        "jr": lambda a, b: G.jr(a),
        "jl_inv": lambda a, b: G.jl_inv(a),
        "jr_inv": lambda a, b: G.jr_inv(a),
        "interpolate": lambda a, b, t: G.exp(a).interpolate(G.exp(b), t).as_matrix(),
        "act": lambda a, q: G.exp(a).act(q),
        "act_direction": lambda a, q: G.exp(a).act_direction(q),
    }
    args = {"interpolate": (x, y, alpha), "act": (x, p), "act_direction": (x, d)}
    if hasattr(G, "act_velocity"):
        ops["act_velocity"] = lambda a, q: G.exp(a).act_velocity(q)
        args["act_velocity"] = (x, p[..., :3])
    for name, fn in ops.items():
        a = args.get(name, (x, y))
        np.testing.assert_allclose(torch.func.vmap(fn)(*a).numpy(), fn(*a).numpy(), rtol=0,
                                   atol=1e-13, err_msg=name)


@pytest.mark.parametrize("angle", GRAD_ANGLES, ids=ANGLE_IDS)
@pytest.mark.parametrize("G", GROUPS, ids=IDS)
def test_forward_mode(G, angle):
    """The custom jvp of exp and log against finite differences (gradcheck's forward-mode
    check), at the delicate angles."""
    f = G._f
    x = _xi(G, angle, seed=13)
    assert torch.autograd.gradcheck(f.exp, (x,), check_forward_ad=True, check_backward_ad=False)
    # log of a group-valued function of x built independently (matrix_exp + forward AD)
    log_of = lambda v: f.log(torch.linalg.matrix_exp(f.hat(v)))  # noqa: E731
    assert torch.autograd.gradcheck(log_of, (x,), check_forward_ad=True, check_backward_ad=False)


@pytest.mark.parametrize("G", GROUPS, ids=IDS)
def test_jacfwd_equals_jacrev_and_hessian(G):
    """jacfwd (custom jvp) and jacrev (custom backward) give the same Jacobians of exp and of
    log, the latter over all matrix entries (both project onto the group the same way); the
    hessian of |log(exp(x))|^2 = |x|^2 is 2 I."""
    f = G._f
    xi = sample_tangent(G, (4,), torch.float64, seed=14)
    jf = torch.func.vmap(torch.func.jacfwd(f.exp))(xi)
    jr = torch.func.vmap(torch.func.jacrev(f.exp))(xi)
    np.testing.assert_allclose(jf.numpy(), jr.numpy(), rtol=0, atol=1e-13)
    M = f.exp(xi)
    jf = torch.func.vmap(torch.func.jacfwd(f.log))(M)
    jr = torch.func.vmap(torch.func.jacrev(f.log))(M)
    np.testing.assert_allclose(jf.numpy(), jr.numpy(), rtol=0, atol=1e-12)
    H = torch.func.hessian(lambda v: f.log(f.exp(v)).square().sum())(xi[1])
    np.testing.assert_allclose(H.numpy(), 2.0 * np.eye(G.dof), rtol=0, atol=1e-12)


@pytest.mark.parametrize("G", GROUPS, ids=IDS)
def test_jacobians_and_adjoints_are_connected_to_the_graph(G):
    """jl, jr, their inverses, ad and adjoint are differentiable in their input for every group:
    SO2's constants (1 and 0) must not be fresh tensors, or torch.autograd.grad would raise 'does
    not require grad' for SO2 alone.  Their gradients against finite differences."""
    x = sample_tangent(G, (1,), torch.float64, seed=8, angles=[1.3]).requires_grad_(True)
    ops = {name: getattr(G, name) for name in ("jl", "jr", "jl_inv", "jr_inv", "ad")}
    ops["adjoint"] = lambda v: G.exp(v).adjoint()
    for name, op in ops.items():
        out = op(x)
        assert out.requires_grad, name
        assert torch.autograd.gradcheck(lambda v: op(v), (x,), fast_mode=True), name


@pytest.mark.parametrize("G", GROUPS, ids=IDS)
def test_float32_forward_mode_of_one_element(G):
    """Forward mode in float32 on one (unbatched) element: functorch's jvp gave a Python number
    times a 0-d float32 tensor a float64 tangent (pytorch/functorch#1073), so jacfwd of the
    Jacobians and hessian could raise in lerp or return float64.  Each result is float32 and
    agrees with the float64 one (checked against finite differences by the tests above)."""
    jacfwd, hessian, vmap = torch.func.jacfwd, torch.func.hessian, torch.func.vmap
    f = lambda v: G.exp(v).log().square().sum()  # noqa: E731
    cases = {
        "jacfwd jl": lambda x: jacfwd(G.jl)(x[0]),
        "jacfwd jr": lambda x: jacfwd(G.jr)(x[0]),
        "jacfwd jl_inv": lambda x: jacfwd(G.jl_inv)(x[0]),
        "jacfwd jr_inv": lambda x: jacfwd(G.jr_inv)(x[0]),
        "jacfwd adjoint": lambda x: jacfwd(lambda v: G.exp(v).adjoint())(x[0]),
        "jacfwd exp": lambda x: jacfwd(lambda v: G.exp(v).as_matrix())(x[0]),
        "jacfwd log": lambda x: jacfwd(lambda v: G.exp(v).log())(x[0]),
        "jacfwd rminus": lambda x: jacfwd(lambda v: G.exp(v).rminus(G.exp(x[1])))(x[0]),
        "hessian": lambda x: hessian(f)(x[0]),
        "jacfwd(jacfwd)": lambda x: jacfwd(jacfwd(f))(x[0]),
        "vmap(hessian)": lambda x: vmap(hessian(f))(x),
    }
    x64 = sample_tangent(G, (3,), torch.float64, seed=31, angles=[0.5, 1e-4, 2.5])
    for name, case in cases.items():
        want = case(x64)
        got = case(x64.float())
        assert got.dtype == torch.float32, name
        np.testing.assert_allclose(got.double().numpy(), want.numpy(), rtol=1e-4, atol=1e-4,
                                   err_msg=name)


@pytest.mark.parametrize("G", GROUPS, ids=IDS)
def test_second_derivatives(G):
    """The custom backward is itself differentiable (hessian against finite differences)."""
    f = G._f
    x0 = sample_tangent(G, (), torch.float64, seed=5, angles=[0.8])
    gen = torch.Generator().manual_seed(23)
    W = torch.randn(G.matrix_dim, G.matrix_dim, dtype=torch.float64, generator=gen)
    loss = lambda x: (f.exp(x) * W).sum()  # noqa: E731
    assert torch.autograd.gradgradcheck(loss, (x0.clone().requires_grad_(True),))
    w = torch.randn(G.dof, dtype=torch.float64, generator=gen)
    loss2 = lambda x: (f.log(torch.linalg.matrix_exp(f.hat(x))) * w).sum()  # noqa: E731
    assert torch.autograd.gradgradcheck(loss2, (x0.clone().requires_grad_(True),))


@pytest.mark.parametrize("G", GROUPS, ids=IDS)
def test_torch_compile_smoke(G):
    """exp, compose, log and the custom backward under torch.compile match eager.

    SGal3 goes through inductor (generated C++ kernels, about 80 s on a cold inductor cache);
    the other groups through aot_eager, which traces the same dynamo and AOTAutograd graph
    without compiling kernels, to keep the suite's time on a fresh CI machine in bounds."""
    f = G._f

    def loss(x, y):
        return f.log(f.compose(f.exp(x), f.exp(y))).square().sum()

    backend = "inductor" if G is ts.SGal3 else "aot_eager"
    compiled = torch.compile(loss, fullgraph=True, backend=backend)
    x = sample_tangent(G, (8,), torch.float64, seed=6).requires_grad_(True)
    y = sample_tangent(G, (8,), torch.float64, seed=7)
    eager_val = loss(x, y)
    (eager_grad,) = torch.autograd.grad(eager_val, x)
    comp_val = compiled(x, y)
    (comp_grad,) = torch.autograd.grad(comp_val, x)
    np.testing.assert_allclose(comp_val.item(), eager_val.item(), rtol=1e-12)
    np.testing.assert_allclose(comp_grad.numpy(), eager_grad.numpy(), rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("G", GROUPS, ids=IDS)
def test_torch_compile_dynamic_shapes(G):
    """exp -> log with its custom backward under torch.compile(dynamic=True): one graph serves
    two batch sizes, values and gradients match eager.  (A module-level float threshold read
    in two custom Functions' graphs would break dynamo here; numerics reads them through constant
    getters.)  aot_eager: that failure is in dynamo's tracing, no kernels need compiling."""
    f = G._f

    def loss(x):
        return f.log(f.exp(x)).square().sum()

    compiled = torch.compile(loss, fullgraph=True, dynamic=True, backend="aot_eager")
    for n, seed in ((5, 11), (7, 12)):
        x = sample_tangent(G, (n,), torch.float64, seed=seed).requires_grad_(True)
        eager_val = loss(x)
        (eager_grad,) = torch.autograd.grad(eager_val, x)
        comp_val = compiled(x)
        (comp_grad,) = torch.autograd.grad(comp_val, x)
        np.testing.assert_allclose(comp_val.item(), eager_val.item(), rtol=1e-12)
        np.testing.assert_allclose(comp_grad.numpy(), eager_grad.numpy(), rtol=1e-10, atol=1e-12)


def test_threshold_getters_carry_dynamo_constant_mark():
    """numerics marks its threshold getters as torch.compiler.assume_constant_result does (without
    importing torch._dynamo at import time); the mark must be the one that function sets."""
    from torchsgal.functional import numerics

    marked = torch.compiler.assume_constant_result(lambda: 0.0)
    marks = {k: v for k, v in vars(marked).items()}
    assert marks, "assume_constant_result no longer marks by an attribute"
    for getter in (numerics.series_threshold_sq, numerics.jinv_threshold_sq, numerics.log_symmetric_cos):
        assert {k: getattr(getter, k, None) for k in marks} == marks


def test_import_does_not_load_dynamo():
    """import torchsgal stays light: torch._dynamo (about 1.3 s) is not imported by it."""
    code = "import sys, torchsgal; sys.exit(int('torch._dynamo' in sys.modules))"
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0


@pytest.mark.parametrize("G", GROUPS, ids=IDS)
def test_torch_compile_class_methods(G):
    """The class API traces in one graph: group objects as inputs and outputs, and the methods
    built on composition (rplus, lplus, rminus, lminus, between, interpolate), which call
    ``compose`` because dynamo (torch 2.13) cannot trace ``@`` between non-tensor objects.
    backend="eager": only dynamo's tracing is under test."""

    def methods(g, h, x, alpha):
        return (g.compose(h).as_matrix(), g.rplus(x).as_matrix(), g.lplus(x).as_matrix(),
                g.rminus(h), g.lminus(h), g.between(h).as_matrix(),
                g.interpolate(h, alpha).as_matrix(), g.inverse().adjoint())

    compiled = torch.compile(methods, fullgraph=True, backend="eager")
    x = sample_tangent(G, (6,), torch.float64, seed=13)
    g, h = G.exp(sample_tangent(G, (6,), torch.float64, seed=14)), G.exp(x)
    alpha = torch.linspace(0.0, 1.0, 6, dtype=torch.float64)
    for got, want in zip(compiled(g, h, x, alpha), methods(g, h, x, alpha)):
        np.testing.assert_allclose(got.numpy(), want.numpy(), rtol=0, atol=1e-14)


@pytest.mark.parametrize("G", [ts.SO3, ts.SGal3], ids=["SO3", "SGal3"])
def test_torch_compile_second_derivatives(G):
    """Compiled second derivatives through exp and log equal eager ones.  Compiled code runs the
    closed forms under autograd, not custom Functions: torch 2.13 differentiates a compiled
    Function's backward with its saved tensors held constant (a ten-line Function y = log(x)
    with backward g / x gives d2/dv2 log(v v) = +0.5 at v = 2 compiled, -0.5 eager), and custom
    Functions would give silently wrong results (SE3: Hessian diagonal
    [0, 0, 0, 0.16, 0.11, 0.05] for 2 I)."""
    from torch.func import jacrev

    f = G._f
    gen = torch.Generator().manual_seed(9)
    A = f.exp_impl(0.7 * torch.randn(G.dof, dtype=torch.float64, generator=gen))
    x = 0.5 * torch.randn(G.dof, dtype=torch.float64, generator=gen)

    def loss(v):  # log's input depends on v through a product, exp's directly
        return f.log(A @ f.exp(v)).square().sum() + f.exp(2.0 * v).sum()

    eager = jacrev(jacrev(loss))(x)
    torch._dynamo.reset()
    compiled = torch.compile(jacrev(jacrev(loss)), fullgraph=True, backend="eager")(x)
    torch.testing.assert_close(compiled, eager, rtol=1e-10, atol=1e-12)
    assert eager.abs().max() > 0.1  # a Hessian with substance


def test_first_call_inside_a_nested_transform_does_not_poison_the_constants():
    """The series constants are cached per dtype and device on first use; a first use inside
    torch.func.hessian must not cache functorch wrappers, or every later grad/jacrev/jacfwd/hessian
    of the process would fail with an internal assert ("level <= current_level").  Run in a fresh
    interpreter so that the first use is the transformed one."""
    import subprocess
    import sys

    code = (
        "import torch, torchsgal as ts\n"
        "from torch.func import grad, hessian, jacrev\n"
        "f = lambda v: torch.linalg.slogdet(ts.SE3.jr(v))[1]\n"
        "x = torch.tensor([0.3, -0.2, 0.1, 0.4, 0.5, -0.6], dtype=torch.float64)\n"
        "H = hessian(f)(x)\n"
        "g = grad(f)(x)\n"
        "J = jacrev(f)(x)\n"
        "assert torch.allclose(g, J) and torch.isfinite(H).all()\n"
        "print('ok')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-2000:]


@pytest.mark.parametrize("G", [ts.SO3, ts.SE23, ts.Sim3], ids=["SO3", "SE23", "Sim3"])
def test_forward_over_forward_second_derivatives(G):
    """jacfwd(jacfwd(.)) through exp and log equals the other orders and the plain closed
    forms.  Through the custom Functions torch 2.13 returns wrong second derivatives there
    (max |jacfwd(jacfwd(SO3.exp))| = 0 against 0.91; pytorch/pytorch#197867)."""
    from torch.func import jacfwd, jacrev

    f = G._f
    gen = torch.Generator().manual_seed(5)
    A = f.exp_impl(0.7 * torch.randn(G.dof, dtype=torch.float64, generator=gen))
    x = 0.5 * torch.randn(G.dof, dtype=torch.float64, generator=gen)
    for fn, oracle in ((lambda v: A @ f.exp(v), lambda v: A @ f.exp_impl(v)),
                       (lambda v: f.log(A @ f.exp_impl(v)), lambda v: f.log_impl(A @ f.exp_impl(v)))):
        want = jacrev(jacrev(oracle))(x)
        assert want.abs().max() > 0.05  # second derivatives with substance
        for name, H in (("fwd(fwd)", jacfwd(jacfwd(fn))(x)), ("fwd(rev)", jacfwd(jacrev(fn))(x)),
                        ("rev(fwd)", jacrev(jacfwd(fn))(x))):
            torch.testing.assert_close(H, want, rtol=1e-10, atol=1e-12, msg=name)


def test_torch_compile_of_vmap_jacrev_and_hessian():
    """torch.compile(vmap(jacrev(f))) and torch.compile(hessian(f)) through exp and log: they
    must not raise "You tried to vmap over ApplyTemplate, but it does not have vmap support", as
    they would if compiled code ran the custom Functions."""
    from torch.func import hessian, jacrev, vmap

    f = lambda v: ts.SO3.exp(v).log().square().sum()  # noqa: E731  (= |v|^2 for |v| < pi)
    x = sample_tangent(ts.SO3, (4,), torch.float64, seed=3)
    torch._dynamo.reset()
    got = torch.compile(vmap(jacrev(f)), backend="eager", fullgraph=True)(x)
    torch.testing.assert_close(got, 2 * x, rtol=1e-12, atol=1e-12)
    H = torch.compile(hessian(f), backend="eager", fullgraph=True)(x[0])
    torch.testing.assert_close(H, 2 * torch.eye(3, dtype=torch.float64), rtol=0, atol=1e-12)
