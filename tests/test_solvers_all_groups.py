"""The generic estimation solvers on unknowns of every group (the feature table's claim): the
nearest-element problem min |log(t^-1 x)|^2, whose answer (x = t) and Laplace covariance
(J = J_r^-1(0) = I, so the identity) are known exactly, with a Euclidean unknown beside it."""
from __future__ import annotations

import pytest
import torch

import torchsgal as ts
from torchsgal.estimation import gauss_newton
from torchsgal.estimation.lbfgs import lbfgs

F64 = torch.float64


def _problem(G, B=4, seed=0):
    gen = torch.Generator().manual_seed(seed)
    target = G.exp(torch.randn(B, G.dof, generator=gen, dtype=F64))
    start = target.rplus(0.3 * torch.randn(B, G.dof, generator=gen, dtype=F64))
    offset = torch.randn(B, 2, generator=gen, dtype=F64)
    return target, start, offset


@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=lambda G: G.__name__)
def test_gauss_newton_recovers_an_element_of_every_group(G):
    target, start, offset = _problem(G)

    def residual(x):
        g, y = x
        return torch.cat([g.rminus(target), y - offset], dim=-1)

    sol = gauss_newton(residual, (start, torch.zeros(4, 2, dtype=F64)))
    g, y = sol.x
    assert bool(sol.report.converged.all())
    assert g.rminus(target).abs().max() < 1e-12
    assert (y - offset).abs().max() < 1e-12
    eye = torch.eye(G.dof + 2, dtype=F64).expand(4, -1, -1)
    assert (sol.covariance - eye).abs().max() < 1e-10


@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=lambda G: G.__name__)
def test_lbfgs_recovers_an_element_of_every_group_and_reports_it(G):
    target, start, _ = _problem(G)
    x, _, report = lbfgs(lambda x, _e: x[0].rminus(target).square().sum(-1), (start,))
    # The status agrees with LBFGS's own stopping test (max-abs gradient): before, SGal3 and
    # Sim3 problems that LBFGS had stopped on reported MAX_ITERATIONS.
    assert bool(report.converged.all())
    # |gradient| = 2 |r| <= 1e-6 at convergence (gradient_tol), so |r| is at most ~5e-7.
    assert x[0].rminus(target).abs().max() < 1e-6
