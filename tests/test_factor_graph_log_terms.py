"""The engine's SE(3) and SE(2) logs and inverse Jacobians (``graph.log_terms``; on SE(3) the
group's operators, C kernels on the CPU, or its one-pass form where autograd records) against the closed forms as tensor code (``log_impl``,
``jl_inv_impl``: component-wise Gamma blocks) and against the Bernoulli series
J_l^-1 = sum_n B_n/n! ad^n of the definition, at small angles, around the series threshold, at
generic angles and near pi, in float64 and float32; and their gradients (gradcheck, finite at
the identity)."""
import math

import pytest
import torch

from torchsgal.estimation.graph.log_terms import (
    SERIES_THRESHOLD,
    _se3_one_pass,
    se2_log_jacobians,
    se3_inverse,
    se3_log_jacobians,
)
from torchsgal.functional import se2, se3

f64 = torch.float64


def _xi(n, angle, seed):
    """Tangents with rotation angles in [angle / 2, angle] and translations of size ~1."""
    gen = torch.Generator().manual_seed(seed)
    xi = torch.randn(n, 6, generator=gen, dtype=f64)
    phi = xi[:, 3:] / xi[:, 3:].norm(dim=-1, keepdim=True)
    scale = angle * (0.5 + 0.5 * torch.rand(n, 1, generator=gen, dtype=f64))
    return torch.cat([xi[:, :3], phi * scale], dim=-1)


ANGLES = [0.0, 1e-12, 1e-6, 1e-3, 0.2, SERIES_THRESHOLD * 0.999, SERIES_THRESHOLD * 1.001, 2.0,
          3.0, math.pi - 1e-9]


@pytest.mark.parametrize("angle", ANGLES)
def test_matches_the_group_module_float64(angle):
    E = se3.exp(_xi(300, angle, seed=1))
    r, Jr, Jl = se3_log_jacobians(E, True)
    ref = se3.log_impl(E)
    torch.testing.assert_close(r, ref, rtol=0, atol=1e-13)
    torch.testing.assert_close(Jr, se3.jl_inv_impl(-ref), rtol=0, atol=1e-12)
    torch.testing.assert_close(Jl, se3.jl_inv_impl(ref), rtol=0, atol=1e-12)
    Jr1, Jl1 = _se3_one_pass(r)  # the form taken where autograd records
    torch.testing.assert_close(Jr1, se3.jl_inv_impl(-ref), rtol=0, atol=1e-12)
    torch.testing.assert_close(Jl1, se3.jl_inv_impl(ref), rtol=0, atol=1e-12)
    r_only, none_r, none_l = se3_log_jacobians(E, False)
    assert none_r is None and none_l is None
    assert torch.equal(r_only, r)


@pytest.mark.parametrize("angle", [1e-4, 0.5, 1.5, 3.0])
def test_matches_the_group_module_float32(angle):
    E = se3.exp(_xi(300, angle, seed=2)).float()
    r, Jr, Jl = se3_log_jacobians(E, True)
    assert r.dtype == Jr.dtype == Jl.dtype == torch.float32
    ref = se3.log_impl(E.double())
    torch.testing.assert_close(r.double(), ref, rtol=0, atol=5e-6)
    torch.testing.assert_close(Jr.double(), se3.jl_inv_impl(-ref), rtol=0, atol=5e-6)
    torch.testing.assert_close(Jl.double(), se3.jl_inv_impl(ref), rtol=0, atol=5e-6)


def _bernoulli_series(xi, terms=60):
    """sum_n B_n/n! ad(xi)^n with B_1 = -1/2 (J_l^-1), directly from the definition."""
    B = [1.0]
    for m in range(1, terms + 1):
        B.append(-sum(math.comb(m + 1, k) * B[k] for k in range(m)) / (m + 1))
    ad = se3.ad(xi)
    out, power = torch.zeros_like(ad), torch.eye(6, dtype=f64).expand_as(ad)
    for n in range(terms + 1):
        out = out + (B[n] / math.factorial(n)) * power
        power = power @ ad
    return out


@pytest.mark.parametrize("angle", [0.3, 1.0, 2.0])
def test_inverse_jacobians_equal_the_bernoulli_series(angle):
    xi = _xi(50, angle, seed=3)
    xi = torch.cat([0.5 * xi[:, :3], xi[:, 3:]], dim=-1)  # |ad| < 2 pi: the series converges
    r, Jr, Jl = se3_log_jacobians(se3.exp(xi), True)
    torch.testing.assert_close(r, xi, rtol=0, atol=1e-13)
    torch.testing.assert_close(Jl, _bernoulli_series(xi), rtol=0, atol=1e-11)
    torch.testing.assert_close(Jr, _bernoulli_series(-xi), rtol=0, atol=1e-11)
    Jr1, Jl1 = _se3_one_pass(r)
    torch.testing.assert_close(Jl1, _bernoulli_series(xi), rtol=0, atol=1e-11)
    torch.testing.assert_close(Jr1, _bernoulli_series(-xi), rtol=0, atol=1e-11)


def test_gradients_are_correct_and_finite_at_the_identity():
    """Under autograd: the one-pass form (``_se3_one_pass``), checked by finite differences."""
    xi = torch.cat([_xi(3, 0.3, seed=4), _xi(3, 1.5, seed=5)]).requires_grad_(True)

    def fn(v):
        r, Jr, Jl = se3_log_jacobians(se3.exp(v), True)
        return r, Jr, Jl

    assert torch.autograd.gradcheck(fn, (xi,), eps=1e-6, atol=1e-7)
    zero = torch.zeros(2, 6, dtype=f64, requires_grad=True)
    r, Jr, Jl = fn(zero)
    (g,) = torch.autograd.grad(r.sum() + Jr.sum() + Jl.sum(), zero)
    assert torch.isfinite(g).all()
    # d/dxi of the sum of r at 0 is 1 per component (log(exp(xi)) = xi)
    (g_r,) = torch.autograd.grad(fn(zero)[0].sum(), zero)
    torch.testing.assert_close(g_r, torch.ones_like(g_r), rtol=0, atol=1e-12)


def test_rotation_log_at_and_near_pi_about_every_kind_of_axis():
    """Half turns about the coordinate axes, diagonals and random axes (where the axis comes from
    the symmetric part and ties between diagonal entries occur), and angles just below pi."""
    axes = torch.tensor([[1.0, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [1, 0, 1], [0, 1, 1],
                         [1, 1, 1], [1, -1, 1], [-1, 2, 3]], dtype=f64)
    axes = torch.cat([axes, torch.randn(50, 3, generator=torch.Generator().manual_seed(10),
                                        dtype=f64)])
    axes = axes / axes.norm(dim=-1, keepdim=True)
    for angle in (math.pi, math.pi - 1e-10, math.pi - 1e-5, 0.5 * math.pi + 1e-9,
                  0.5 * math.pi - 1e-9):
        xi = torch.cat([torch.ones_like(axes), angle * axes], dim=-1)
        E = se3.exp(xi)
        r, Jr, _ = se3_log_jacobians(E, True)
        ref = se3.log_impl(E)  # the closed form as tensor code (r: the operator's C kernel)
        torch.testing.assert_close(r, ref, rtol=0, atol=1e-12)
        torch.testing.assert_close(se3.exp(r), E, rtol=0, atol=1e-12)
        torch.testing.assert_close(Jr, se3.jl_inv_impl(-ref), rtol=0, atol=1e-10)


def test_inverse_matches_the_group_module_and_the_matrix_inverse():
    E = se3.exp(_xi(100, 2.0, seed=11))
    inv = se3_inverse(E)
    torch.testing.assert_close(inv, se3.inverse(E), rtol=0, atol=1e-14)
    torch.testing.assert_close(inv, torch.linalg.inv(E), rtol=0, atol=1e-12)
    xi = _xi(4, 1.0, seed=12).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda v: se3_inverse(se3.exp(v)), (xi,), eps=1e-6, atol=1e-7)


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-4, 0.5, SERIES_THRESHOLD * 0.999,
                                   SERIES_THRESHOLD * 1.001, 2.0, math.pi - 1e-9])
def test_se2_matches_the_group_module_and_the_bernoulli_series(angle):
    gen = torch.Generator().manual_seed(13)
    xi = torch.randn(300, 3, generator=gen, dtype=f64)
    xi[:, 2] = angle * (2 * torch.rand(300, generator=gen, dtype=f64) - 1)
    E = se2.exp(xi)
    r, Jr, Jl = se2_log_jacobians(E, True)
    ref = se2.log(E)
    torch.testing.assert_close(r, ref, rtol=0, atol=1e-13)
    torch.testing.assert_close(Jr, se2.jr_inv(ref), rtol=0, atol=1e-13)
    torch.testing.assert_close(Jl, se2.jl_inv(ref), rtol=0, atol=1e-13)
    small = xi[:40] * torch.tensor([0.5, 0.5, 1.0], dtype=f64)  # |ad| < 2 pi: the series converges
    B = [1.0]
    for m in range(1, 61):
        B.append(-sum(math.comb(m + 1, k) * B[k] for k in range(m)) / (m + 1))
    ad = torch.zeros(40, 3, 3, dtype=f64)
    ad[:, 0, 1], ad[:, 1, 0] = -small[:, 2], small[:, 2]  # [[theta J, -J rho], [0, 0]]
    ad[:, 0, 2], ad[:, 1, 2] = small[:, 1], -small[:, 0]
    series, power = torch.zeros_like(ad), torch.eye(3, dtype=f64).expand_as(ad)
    for n in range(61):
        series = series + (B[n] / math.factorial(n)) * power
        power = power @ ad
    torch.testing.assert_close(se2_log_jacobians(se2.exp(small), True)[2], series, rtol=0,
                               atol=1e-11)
    r_only, none_r, none_l = se2_log_jacobians(E, False)
    assert none_r is None and none_l is None and torch.equal(r_only, r)


def test_se2_gradients_are_correct_and_finite_at_the_identity():
    xi = torch.tensor([[0.3, -0.2, 0.4], [1.0, 2.0, -2.5], [0.1, 0.0, 1e-3]], dtype=f64,
                      requires_grad=True)
    assert torch.autograd.gradcheck(lambda v: se2_log_jacobians(se2.exp(v), True), (xi,),
                                    eps=1e-6, atol=1e-7)
    zero = torch.zeros(2, 3, dtype=f64, requires_grad=True)
    r, Jr, Jl = se2_log_jacobians(se2.exp(zero), True)
    (g,) = torch.autograd.grad(r.sum() + Jr.sum() + Jl.sum(), zero)
    assert torch.isfinite(g).all()
