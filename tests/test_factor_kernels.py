"""The built-in SE(3) and SE(2) priors' and betweens' residuals and Jacobians as operators
(``torch.ops.torchsgal.se3_factor_terms``, ``se2_factor_terms``, ``graph.factor_kernels``; their
C kernels ``estimation/_native_factors.h``): against the formulas written out with the groups'
closed forms as tensor code (``log_impl``, ``jl_inv_impl`` / ``jr_inv``, ``adjoint``) and
against central differences
of the residual along right perturbations, at small angles, around the series threshold and
near pi, in float64 and float32; the engine's choice of it; fake tensors; bad arguments."""
from __future__ import annotations

import contextlib
import math
import os
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import pytest
import torch
from torch.library import opcheck

from torchsgal.estimation import dense_solve
from torchsgal.estimation.graph import factor_kernels
from torchsgal.functional import native, se2, se3

f64 = torch.float64
ANGLES = [0.0, 1e-9, 1e-4, 0.3, 0.999, 1.001, 2.0, 3.0, math.pi - 1e-6]

_no_kernel = pytest.mark.skipif(not dense_solve.available()
                                and os.environ.get("TORCHSGAL_NO_SKIPS") != "1",
                                reason="the estimation C kernels were not compiled")


def needs_kernel(test):
    """Tests of the C kernel itself: left out of the run with the kernels off (.ci/run)."""
    return pytest.mark.kernels(_no_kernel(test))


def elements(n, angle, seed, dtype=f64):
    """n SE(3) matrices with rotation angles in [angle / 2, angle]."""
    gen = torch.Generator().manual_seed(seed)
    xi = torch.randn(n, 6, generator=gen, dtype=f64)
    phi = xi[:, 3:] / xi[:, 3:].norm(dim=-1, keepdim=True)
    scale = angle * (0.5 + 0.5 * torch.rand(n, 1, generator=gen, dtype=f64))
    return se3.exp_impl(torch.cat([xi[:, :3], phi * scale], dim=-1)).to(dtype)


def written_out(Zinv, Ti, Tj):
    """r and J from the definitions (factors.py), in float64 tensor code."""
    Zinv, Tj = Zinv.double(), Tj.double()
    if Ti is None:
        E = Zinv @ Tj
        r = se3.log_impl(E)
        return r, se3.jl_inv_impl(-r)
    Ti = Ti.double()
    A = torch.linalg.inv(Ti) @ Tj
    r = se3.log_impl(Zinv @ A)
    Jj = se3.jl_inv_impl(-r)
    Ji = -Jj @ se3.adjoint(torch.linalg.inv(A))
    return r, torch.cat([Ji, Jj], dim=-1)


def _pair(angle, n=40, seed=0, dtype=f64):
    """Ti, Tj with an error E = Z^-1 Ti^-1 Tj whose angle is about ``angle``."""
    Ti = elements(n, 2.0, seed, dtype)
    E = elements(n, angle, seed + 1, dtype)
    Z = elements(n, 1.0, seed + 2, dtype)
    Tj = (Ti.double() @ Z.double() @ E.double()).to(dtype)
    return torch.linalg.inv(Z.double()).to(dtype), Ti, Tj


def elements2(n, angle, seed, dtype=f64):
    gen = torch.Generator().manual_seed(seed)
    xi = torch.randn(n, 3, generator=gen, dtype=f64)
    sign = torch.where(torch.rand(n, generator=gen, dtype=f64) < 0.5, -1.0, 1.0)
    xi[:, 2] = sign * angle * (0.5 + 0.5 * torch.rand(n, generator=gen, dtype=f64))
    return se2.exp_impl(xi).to(dtype)


def _pair2(angle, n=40, seed=0, dtype=f64):
    Ti, E, Z = elements2(n, 2.0, seed), elements2(n, angle, seed + 1), elements2(n, 1.0, seed + 2)
    return (torch.linalg.inv(Z).to(dtype), Ti.to(dtype), (Ti @ Z @ E).to(dtype))


def written_out2(Zinv, Ti, Tj):
    """r and J of SE(2) from the definitions, in float64 tensor code."""
    Zinv, Tj = Zinv.double(), Tj.double()
    if Ti is None:
        r = se2.log_impl(Zinv @ Tj)
        return r, se2.jr_inv(r)
    A = torch.linalg.inv(Ti.double()) @ Tj
    r = se2.log_impl(Zinv @ A)
    Jj = se2.jr_inv(r)
    return r, torch.cat([-Jj @ se2.adjoint(torch.linalg.inv(A)), Jj], dim=-1)


class Group(NamedTuple):
    op: object
    dof: int
    pair: Callable
    written_out: Callable
    exp: Callable
    tensor_code: Callable


GROUPS = {"SE3": Group(torch.ops.torchsgal.se3_factor_terms, 6, _pair, written_out, se3.exp_impl,
                       factor_kernels._tensor_code),
          "SE2": Group(torch.ops.torchsgal.se2_factor_terms, 3, _pair2, written_out2, se2.exp_impl,
                       factor_kernels._se2_tensor_code)}


@pytest.mark.parametrize("group", GROUPS)
@pytest.mark.parametrize("kernel", [True, False])
@pytest.mark.parametrize("angle", ANGLES)
def test_betweens_and_priors_match_their_definitions(angle, kernel, group):
    g = GROUPS[group]
    Zinv, Ti, Tj = g.pair(angle)
    with native.disabled() if not kernel else contextlib.nullcontext():
        rb, Jb = g.op(Zinv, Ti, Tj, True)
        rp, Jp = g.op(Zinv, None, Tj, True)
        r_only, empty = g.op(Zinv, Ti, Tj, False)
    rb_ref, Jb_ref = g.written_out(Zinv, Ti, Tj)
    rp_ref, Jp_ref = g.written_out(Zinv, None, Tj)
    d = g.dof
    assert Jb.shape == (40, d, 2 * d) and Jp.shape == (40, d, d) and empty.shape == (40, d, 0)
    torch.testing.assert_close(rb, rb_ref, rtol=0, atol=1e-12)
    torch.testing.assert_close(Jb, Jb_ref, rtol=0, atol=1e-10)
    torch.testing.assert_close(rp, rp_ref, rtol=0, atol=1e-12)
    torch.testing.assert_close(Jp, Jp_ref, rtol=0, atol=1e-10)
    assert torch.equal(r_only, rb)


@pytest.mark.parametrize("group", GROUPS)
@pytest.mark.parametrize("angle", [1e-3, 0.5, 2.5])
def test_jacobians_are_the_residuals_derivatives(angle, group):
    """Central differences of r along right perturbations T exp(eps e_k) of T_i and T_j."""
    g = GROUPS[group]
    Zinv, Ti, Tj = g.pair(angle, n=6, seed=3)
    _, J = g.op(Zinv, Ti, Tj, True)
    h = 1e-6
    numeric = []
    for which in (0, 1):
        for k in range(g.dof):
            e = torch.zeros(g.dof, dtype=f64)
            e[k] = h
            plus, minus = [Ti, Tj], [Ti, Tj]
            plus[which] = plus[which] @ g.exp(e)
            minus[which] = minus[which] @ g.exp(-e)
            numeric.append((g.op(Zinv, *plus, False)[0] - g.op(Zinv, *minus, False)[0]) / (2 * h))
    torch.testing.assert_close(J, torch.stack(numeric, -1), rtol=0, atol=1e-7)


@needs_kernel
@pytest.mark.parametrize("group", GROUPS)
@pytest.mark.parametrize("angle", [1e-4, 0.5, 3.0])
def test_float32_kernel(angle, group):
    g = GROUPS[group]
    Zinv, Ti, Tj = (t.float() for t in g.pair(angle, seed=4))
    r, J = g.op(Zinv, Ti, Tj, True)
    assert r.dtype == J.dtype == torch.float32
    r_ref, J_ref = g.written_out(Zinv, Ti, Tj)
    torch.testing.assert_close(r.double(), r_ref, rtol=0, atol=2e-5)
    torch.testing.assert_close(J.double(), J_ref, rtol=0, atol=2e-4)


@needs_kernel
@pytest.mark.parametrize("group", GROUPS)
def test_kernel_and_tensor_code_agree_to_rounding_and_threads_change_nothing(group):
    g = GROUPS[group]
    Zinv, Ti, Tj = g.pair(1.3, n=40000, seed=5)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = g.op(Zinv, Ti, Tj, True)
        torch.set_num_threads(2)
        two = g.op(Zinv, Ti, Tj, True)
    finally:
        torch.set_num_threads(before)
    assert torch.equal(one[0], two[0]) and torch.equal(one[1], two[1])
    with native.disabled():  # the closed forms as tensor code, no kernel inside
        tensor = g.tensor_code(Zinv, Ti, Tj, True)
    torch.testing.assert_close(one[0], tensor[0], rtol=0, atol=1e-13)
    torch.testing.assert_close(one[1], tensor[1], rtol=0, atol=1e-12)


def test_the_engine_calls_it_only_where_nothing_differentiates():
    T = elements(3, 1.0, 6)
    assert factor_kernels.usable(T) == (dense_solve.available() and native.enabled())
    assert not factor_kernels.usable(T.clone().requires_grad_())
    with torch.no_grad():
        assert factor_kernels.usable(T.clone().requires_grad_()) == (
            dense_solve.available() and native.enabled())
    with native.disabled():
        assert not factor_kernels.usable(T)
    assert not factor_kernels.usable(T.half())


@pytest.mark.parametrize("group", GROUPS)
def test_fake_tensors_and_bad_arguments(group):
    g = GROUPS[group]
    Zinv, Ti, Tj = g.pair(0.5, n=4, seed=7)
    opcheck(g.op.default, (Zinv, Ti, Tj, True))
    opcheck(g.op.default, (Zinv, None, Tj, False))
    with pytest.raises(ValueError, match="one shape"):
        g.op(Zinv[:2], Ti, Tj, True)
    with pytest.raises(ValueError, match="Tj"):
        g.op(Zinv, Ti, Tj[..., :2], True)
    with pytest.raises((TypeError, ValueError), match="float64|dtype"):
        g.op(Zinv, Ti.float(), Tj, True)


@pytest.mark.parametrize("group", ["SE3", "SE2"])
def test_forward_mode_through_a_linearisation_is_the_tensor_codes(group):
    """jvp and jacfwd of the cost and gradient of a pose graph along a step: the engine keeps
    the tensor path wherever a derivative is taken (the operators have none in forward mode),
    so they equal central differences."""
    import torchsgal as ts
    from torchsgal.estimation import graph as fg
    from torchsgal.estimation.graph.linearize import Problem, evaluate_cost, linearize

    G = getattr(ts, group)
    gen = torch.Generator().manual_seed(8)
    poses = G.exp(0.5 * torch.randn(2, 5, G.dof, generator=gen, dtype=f64))
    Z = G.exp(0.5 * torch.randn(2, 4, G.dof, generator=gen, dtype=f64))
    graph = fg.FactorGraph()
    graph.add_variable("x", poses)
    graph.add(fg.Prior("x", 0, poses[:, :1]))
    graph.add(fg.Between("x", torch.arange(4), torch.arange(1, 5), Z))
    problem = Problem(graph)
    x = problem.initial(graph)
    d = torch.randn(problem.B, problem.D, generator=gen, dtype=f64)

    def cost(t):
        return evaluate_cost(problem, problem.retract(x, t * d))

    def gradient(t):
        return linearize(problem, problem.retract(x, t * d)).g

    zero = torch.zeros((), dtype=f64)
    h = 1e-6
    for fn in (cost, gradient):
        numeric = (fn(zero + h) - fn(zero - h)) / (2 * h)
        assert float(numeric.abs().amax()) > 1e-3
        torch.testing.assert_close(torch.func.jvp(fn, (zero,), (torch.ones_like(zero),))[1], numeric,
                                   rtol=1e-6, atol=1e-6)
        torch.testing.assert_close(torch.func.jacfwd(fn)(zero), numeric, rtol=1e-6, atol=1e-6)


NORMAL_OPS = {"SE3": torch.ops.torchsgal.se3_factor_normal, "SE2": torch.ops.torchsgal.se2_factor_normal}


@pytest.mark.parametrize("group", GROUPS)
@pytest.mark.parametrize("kernel", [True, False])
@pytest.mark.parametrize("noise", ["shared", "per factor", "none"])
def test_normal_blocks_are_the_whitened_terms_products(noise, kernel, group):
    """se3/se2_factor_normal: r~ = L r, H = (L J)^T (L J), g = (L J)^T r~ with (r, J) written
    out from the definitions, for a shared L, one per factor and none, priors and betweens."""
    g = GROUPS[group]
    d = g.dof
    Zinv, Ti, Tj = g.pair(0.7, n=30, seed=11)
    gen = torch.Generator().manual_seed(12)
    L = {"shared": torch.randn(d, d, generator=gen, dtype=f64).tril() + 3 * torch.eye(d, dtype=f64),
         "per factor": torch.randn(30, d, d, generator=gen, dtype=f64).tril() + 3 * torch.eye(d, dtype=f64),
         "none": None}[noise]
    for ti in (Ti, None):
        with native.disabled() if not kernel else contextlib.nullcontext():
            r, H, gv = NORMAL_OPS[group](Zinv, ti, Tj, L)
        r0, J0 = g.written_out(Zinv, ti, Tj)
        Lm = torch.eye(d, dtype=f64) if L is None else L
        rw, Jw = (Lm @ r0.unsqueeze(-1)).squeeze(-1), Lm @ J0
        Dk = d if ti is None else 2 * d
        assert r.shape == (30, d) and H.shape == (30, Dk, Dk) and gv.shape == (30, Dk)
        torch.testing.assert_close(r, rw, rtol=0, atol=1e-11)
        torch.testing.assert_close(H, Jw.mT @ Jw, rtol=1e-11, atol=1e-10)
        torch.testing.assert_close(gv, (Jw.mT @ rw.unsqueeze(-1)).squeeze(-1), rtol=1e-11, atol=1e-10)
    opcheck(NORMAL_OPS[group].default, (Zinv[:3], Ti[:3], Tj[:3], None if L is None else L[..., :d, :d]
                                        if L.dim() == 2 else L[:3]))
    with pytest.raises(ValueError, match="L must have shape"):
        NORMAL_OPS[group](Zinv, Ti, Tj, torch.eye(d + 1, dtype=f64))


@needs_kernel
def test_the_engine_linearises_unweighted_built_in_factors_through_the_assemble_kernel():
    """The engine's normal equations of a pose graph with the assemble operators' kernels equal
    those assembled from the residuals and Jacobians as tensor code (the kernels off)."""
    import torchsgal as ts
    from torchsgal.estimation import graph as fg
    from torchsgal.estimation.graph.linearize import Problem, linearize

    gen = torch.Generator().manual_seed(13)
    poses = ts.SE3.exp(0.5 * torch.randn(3, 6, 6, generator=gen, dtype=f64))
    Z = ts.SE3.exp(0.5 * torch.randn(3, 7, 6, generator=gen, dtype=f64))
    graph = fg.FactorGraph()
    graph.add_variable("x", poses)
    graph.add(fg.Prior("x", 0, poses[:, :1], information=torch.eye(6, dtype=f64) * 4))
    graph.add(fg.Between("x", torch.tensor([0, 1, 2, 3, 4, 0, 2]), torch.tensor([1, 2, 3, 4, 5, 3, 5]),
                         Z, sqrt_information=torch.rand(7, 6, 6, generator=gen, dtype=f64).tril()
                         + torch.eye(6, dtype=f64)))
    problem = Problem(graph)
    x = problem.initial(graph)
    fused = linearize(problem, x)
    with native.disabled():
        plain = linearize(problem, x)
    for name in ("values", "g", "cost", "model_cost"):
        torch.testing.assert_close(getattr(fused, name), getattr(plain, name), rtol=1e-12, atol=1e-9)


def test_a_noise_that_requires_grad_keeps_the_differentiable_whitening():
    """A square-root information that requires grad (a learned noise) is applied by tensor
    operations after the kernel's terms, so the normal equations carry its gradient."""
    import torchsgal as ts
    from torchsgal.estimation import graph as fg
    from torchsgal.estimation.graph.linearize import Problem, linearize

    gen = torch.Generator().manual_seed(14)
    poses = ts.SE3.exp(0.5 * torch.randn(2, 4, 6, generator=gen, dtype=f64))
    scale = torch.tensor(2.0, dtype=f64, requires_grad=True)
    graph = fg.FactorGraph()
    graph.add_variable("x", poses)
    graph.add(fg.Between("x", torch.arange(3), torch.arange(1, 4), poses[:, 1:],
                         sqrt_information=scale * torch.eye(6, dtype=f64)))
    problem = Problem(graph, attach=True)
    lin = linearize(problem, problem.initial(graph))
    (grad,) = torch.autograd.grad(lin.values.sum(), scale)
    # H = scale^2 J^T J: d(sum H)/d(scale) = 2 sum(H) / scale
    torch.testing.assert_close(grad, 2 * lin.values.sum().detach() / scale.detach())


@pytest.mark.parametrize("group", GROUPS)
def test_vmap_of_the_normal_operators_is_a_loop_over_the_mapped_axis(group):
    g = GROUPS[group]
    d = g.dof
    Zinv, Ti, Tj = g.pair(0.4, n=12, seed=15)
    Zinv, Ti = Zinv.reshape(3, 4, *Zinv.shape[1:]), Ti.reshape(3, 4, *Ti.shape[1:])
    Tj = Tj[:4]
    gen = torch.Generator().manual_seed(16)
    L = torch.randn(d, d, generator=gen, dtype=f64).tril() + 3 * torch.eye(d, dtype=f64)
    Lv = torch.randn(3, d, d, generator=gen, dtype=f64).tril() + 3 * torch.eye(d, dtype=f64)
    op = NORMAL_OPS[group]
    for args, dims in (((Zinv, Ti, Tj, L), (0, 0, None, None)), ((Zinv, Ti, Tj, Lv), (0, 0, None, 0)),
                       ((Zinv, None, Tj, None), (0, None, None, None))):
        got = torch.vmap(op, in_dims=dims)(*args)
        loop = [op(*[t if dim is None or t is None else t[v] for t, dim in zip(args, dims)])
                for v in range(3)]
        for k in range(3):
            torch.testing.assert_close(got[k], torch.stack([out[k] for out in loop]), rtol=0, atol=0)


@pytest.mark.parametrize("group", GROUPS)
def test_vmap_of_the_terms_operators_is_a_loop_over_the_mapped_axis(group):
    g = GROUPS[group]
    Zinv, Ti, Tj = g.pair(0.4, n=12, seed=17)
    Zinv, Ti = Zinv.reshape(3, 4, *Zinv.shape[1:]), Ti.reshape(3, 4, *Ti.shape[1:])
    Tj = Tj[:4]
    for ti, dims in ((Ti, (0, 0, None)), (None, (0, None, None))):
        got = torch.vmap(lambda z, a, b: g.op(z, a, b, True), in_dims=dims)(Zinv, ti, Tj)
        loop = [g.op(Zinv[v], None if ti is None else ti[v], Tj, True) for v in range(3)]
        for k in range(2):
            torch.testing.assert_close(got[k], torch.stack([out[k] for out in loop]), rtol=0, atol=0)


ASSEMBLE_OPS = {"SE3": torch.ops.torchsgal.se3_factor_assemble,
                "SE2": torch.ops.torchsgal.se2_factor_assemble}


def _assemble_case(group, B=3, E=5, size=40, D=9, seed=21):
    """Matrices (B, E, n, n), slots drawn with repeats, random bases to add into."""
    g = GROUPS[group]
    Zinv, Ti, Tj = (t.reshape(B, E, *t.shape[1:]) for t in g.pair(0.8, n=B * E, seed=seed))
    gen = torch.Generator().manual_seed(seed + 1)
    values = torch.randn(B, size, generator=gen, dtype=f64)
    gvec = torch.randn(B, D, generator=gen, dtype=f64)
    return g, Zinv, Ti, Tj, values, gvec, gen


@pytest.mark.parametrize("group", GROUPS)
@pytest.mark.parametrize("kernel", [True, False])
@pytest.mark.parametrize("noise", ["shared", "per factor", "none"])
def test_assembled_blocks_are_the_normal_blocks_added_at_their_slots(noise, kernel, group):
    """se3/se2_factor_assemble: each factor's whitened blocks written out from the definitions,
    added at its slots to the values and g (repeated slots sum; the inputs unchanged), priors
    and betweens; one or two threads give the same bits."""
    g, Zinv, Ti, Tj, values, gvec, gen = _assemble_case(group)
    B, E, d = Zinv.shape[0], Zinv.shape[1], g.dof
    L = {"shared": torch.randn(d, d, generator=gen, dtype=f64).tril() + 3 * torch.eye(d, dtype=f64),
         "per factor": torch.randn(B, E, d, d, generator=gen, dtype=f64).tril() + 3 * torch.eye(d, dtype=f64),
         "none": None}[noise]
    for ti in (Ti, None):
        Dk = d if ti is None else 2 * d
        slots = torch.randint(0, values.shape[1], (E, Dk * Dk), generator=gen)
        g_slots = torch.randint(0, gvec.shape[1], (E, Dk), generator=gen)
        v0, g0 = values.clone(), gvec.clone()
        with native.disabled() if not kernel else contextlib.nullcontext():
            r, v, gv = ASSEMBLE_OPS[group](Zinv, ti, Tj, L, slots, v0, g_slots, g0)
        assert torch.equal(v0, values) and torch.equal(g0, gvec)
        r0, J0 = g.written_out(Zinv.flatten(0, 1), None if ti is None else ti.flatten(0, 1),
                               Tj.flatten(0, 1))
        Lm = torch.eye(d, dtype=f64) if L is None else (L if L.dim() == 2 else L.flatten(0, 1))
        rw, Jw = (Lm @ r0.unsqueeze(-1)).squeeze(-1), Lm @ J0
        H = (Jw.mT @ Jw).reshape(B, E * Dk * Dk).numpy()
        gf = (Jw.mT @ rw.unsqueeze(-1)).reshape(B, E * Dk).numpy()
        want_v, want_g = values.numpy().copy(), gvec.numpy().copy()
        rows = np.arange(B)[:, None]
        np.add.at(want_v, (rows, slots.reshape(1, -1).numpy()), H)
        np.add.at(want_g, (rows, g_slots.reshape(1, -1).numpy()), gf)
        torch.testing.assert_close(r, rw.reshape(B, E, d), rtol=0, atol=1e-11)
        torch.testing.assert_close(v, torch.from_numpy(want_v), rtol=1e-11, atol=1e-9)
        torch.testing.assert_close(gv, torch.from_numpy(want_g), rtol=1e-11, atol=1e-9)
        if kernel:
            threads = torch.get_num_threads()
            try:
                torch.set_num_threads(1 if threads > 1 else 2)
                again = ASSEMBLE_OPS[group](Zinv, ti, Tj, L, slots, values, g_slots, gvec)
            finally:
                torch.set_num_threads(threads)
            assert all(torch.equal(a, b) for a, b in zip(again, (r, v, gv)))
    opcheck(ASSEMBLE_OPS[group].default, (Zinv[:2, :2], None, Tj[:2, :2],  # the priors' slots
                                          None if L is None else L if L.dim() == 2 else L[:2, :2],
                                          slots[:2], values[:2].clone(), g_slots[:2], gvec[:2].clone()))


@pytest.mark.parametrize("group", GROUPS)
def test_assemble_rejects_bad_index_maps(group):
    g, Zinv, Ti, Tj, values, gvec, _ = _assemble_case(group)
    E, Dk = Zinv.shape[1], 2 * g.dof
    slots, g_slots = torch.zeros(E, Dk * Dk, dtype=torch.int64), torch.zeros(E, Dk, dtype=torch.int64)
    op = ASSEMBLE_OPS[group]
    with pytest.raises(ValueError, match="slots must be int64 of shape"):
        op(Zinv, Ti, Tj, None, slots[:, :-1], values, g_slots, gvec)
    with pytest.raises(ValueError, match="g_slots must be int64"):
        op(Zinv, Ti, Tj, None, slots, values, g_slots.int(), gvec)
    with pytest.raises(ValueError, match=r"values must have shape \(3, n\), got \(1, 40\)"):
        op(Zinv, Ti, Tj, None, slots, values[:1], g_slots, gvec)
    with pytest.raises(ValueError, match=r"g must have shape \(3, n\), got \(9,\)"):
        op(Zinv, Ti, Tj, None, slots, values, g_slots, gvec[0])


@pytest.mark.parametrize("kernel", [True, False])
@pytest.mark.parametrize("group", GROUPS)
def test_assemble_writes_no_argument_and_has_no_derivative(group, kernel):
    """The operator is functional (its inputs keep their versions and values, its sums are new
    tensors), and no gradient passes silently through it: a backward through any of its
    outputs and torch.func.grad raise (torch.func's message names the missing formula's
    autograd.Function)."""
    g, Zinv, Ti, Tj, values, gvec, _ = _assemble_case(group)
    E, Dk = Zinv.shape[1], 2 * g.dof
    slots = torch.arange(E * Dk * Dk).remainder(values.shape[1]).reshape(E, Dk * Dk)
    g_slots = torch.arange(E * Dk).remainder(gvec.shape[1]).reshape(E, Dk)
    op = ASSEMBLE_OPS[group]
    with native.disabled() if not kernel else contextlib.nullcontext():
        before = (values._version, gvec._version, values.clone(), gvec.clone())
        _, v, gv = op(Zinv, Ti, Tj, None, slots, values, g_slots, gvec)
        assert (values._version, gvec._version) == before[:2]
        assert torch.equal(values, before[2]) and torch.equal(gvec, before[3])
        assert v.data_ptr() != values.data_ptr() and gv.data_ptr() != gvec.data_ptr()

        def loss(T, k=0):
            out = op(Zinv, Ti, T, None, slots, torch.zeros_like(values), g_slots, torch.zeros_like(gvec))
            return (out[k] ** 2).sum()

        for k in (1, 2):
            with pytest.raises(RuntimeError, match="no autograd formula"):
                loss(Tj.clone().requires_grad_(), k).backward()

        with pytest.raises(RuntimeError, match="no autograd formula"):
            loss(Tj.clone().requires_grad_()).backward()
        with pytest.raises(RuntimeError, match="no autograd formula|setup_context"):
            torch.func.grad(loss)(Tj.clone())


@pytest.mark.parametrize("kernel", [True, False])
@pytest.mark.parametrize("group", GROUPS)
def test_assemble_takes_an_empty_batch(group, kernel):
    """B = 0 problems (or E = 0 factors): empty residuals and the values and g unchanged, on the
    kernel and on the tensor code."""
    g, Zinv, Ti, Tj, values, gvec, _ = _assemble_case(group)
    E, Dk = Zinv.shape[1], 2 * g.dof
    slots = torch.zeros(E, Dk * Dk, dtype=torch.int64)
    g_slots = torch.zeros(E, Dk, dtype=torch.int64)
    op = ASSEMBLE_OPS[group]
    with native.disabled() if not kernel else contextlib.nullcontext():
        r, v, gv = op(Zinv[:0], Ti[:0], Tj[:0], None, slots, values[:0], g_slots, gvec[:0])
        assert r.shape == (0, E, g.dof) and v.shape == (0, values.shape[1]) and gv.shape == (0, gvec.shape[1])
        r, v, gv = op(Zinv[:, :0], Ti[:, :0], Tj[:, :0], None, slots[:0], values, g_slots[:0], gvec)
        assert r.shape == (Zinv.shape[0], 0, g.dof) and torch.equal(v, values) and torch.equal(gv, gvec)


@needs_kernel
@pytest.mark.parametrize("group", GROUPS)
def test_the_assemble_kernel_rejects_an_index_out_of_range(group):
    g, Zinv, Ti, Tj, values, gvec, _ = _assemble_case(group)
    E, Dk = Zinv.shape[1], 2 * g.dof
    slots, g_slots = torch.zeros(E, Dk * Dk, dtype=torch.int64), torch.zeros(E, Dk, dtype=torch.int64)
    with pytest.raises(ValueError, match="slots must lie in"):
        ASSEMBLE_OPS[group](Zinv, Ti, Tj, None, slots + values.shape[1], values, g_slots, gvec)
    with pytest.raises(ValueError, match="g_slots must lie in"):
        ASSEMBLE_OPS[group](Zinv, Ti, Tj, None, slots, values, g_slots - 1, gvec)


@pytest.mark.parametrize("group", GROUPS)
def test_vmap_of_the_assemble_operators_is_a_loop_over_the_mapped_axis(group):
    g, Zinv, Ti, Tj, values, gvec, gen = _assemble_case(group, B=6)
    V, d, E = 2, g.dof, Zinv.shape[1]
    Zinv, Ti, Tj, values, gvec = (t.unflatten(0, (V, -1)) for t in (Zinv, Ti, Tj, values, gvec))
    Lv = torch.randn(V, 3, E, d, d, generator=gen, dtype=f64).tril() + 3 * torch.eye(d, dtype=f64)
    slots = torch.randint(0, values.shape[-1], (E, 4 * d * d), generator=gen)
    g_slots = torch.randint(0, gvec.shape[-1], (E, 2 * d), generator=gen)
    op = ASSEMBLE_OPS[group]
    Ls = torch.randn(V, d, d, generator=gen, dtype=f64).tril() + 3 * torch.eye(d, dtype=f64)
    for L, ldim in ((None, None), (Lv, 0), (Ls, 0)):  # none, per factor, shared by the factors
        for vdim in (0, 1, None):  # values and g mapped along either axis, or shared
            vals = {0: values, 1: values.movedim(0, 1), None: values[0]}[vdim]
            gs = {0: gvec, 1: gvec.movedim(0, 1), None: gvec[0]}[vdim]
            dims = (0, 0, 0, ldim, None, vdim, None, vdim)
            got = torch.vmap(op, in_dims=dims)(Zinv, Ti, Tj, L, slots, vals, g_slots, gs)
            for v in range(V):  # each slice as one call gives it
                base = (values[v], gvec[v]) if vdim is not None else (values[0], gvec[0])
                one = op(Zinv[v], Ti[v], Tj[v], None if L is None else L[v], slots, base[0],
                         g_slots, base[1])
                assert all(torch.equal(a[v], b) for a, b in zip(got, one))
    with pytest.raises(ValueError, match="cannot be vmapped"):
        torch.vmap(op, in_dims=(0, 0, 0, None, 0, 0, None, 0))(
            Zinv, Ti, Tj, None, slots.expand(V, *slots.shape), values, g_slots, gvec)
