"""Robust losses (torchsgal.estimation.graph.robust): values against their definitions, first
and second derivatives against autograd, Ceres' corrector against Triggs' model, and a line fit
with outliers that the robust losses recover and the plain loss does not."""
import math

import pytest
import torch

from torchsgal.estimation import SolverStatus
from torchsgal.estimation import graph as fg
from torchsgal.estimation.graph.robust import RobustLoss, correct

f64 = torch.float64
S = torch.tensor([0.0, 1e-8, 0.3, 0.99, 1.0, 1.01, 2.5, 4.0, 9.0, 30.0, 1e4], dtype=f64)


def _definition(name, a, s):
    """The losses written out from their definitions, per element (Python floats)."""
    e = math.sqrt(s)
    if name == "Huber":  # 2 x the Huber function of e: e^2/2 inside, a|e| - a^2/2 outside
        return 2 * (e * e / 2 if e <= a else a * e - a * a / 2)
    if name == "Cauchy":
        return a * a * math.log(1 + e * e / (a * a))
    if name == "GemanMcClure":  # 2 x GTSAM's c^2 e^2 / (2 (c^2 + e^2))
        return 2 * a * a * e * e / (2 * (a * a + e * e))
    if name == "Tukey":  # 2 x Tukey's biweight (a^2/6)(1 - (1 - e^2/a^2)^3), capped at a^2/6
        return 2 * (a * a / 6 * (1 - (1 - e * e / (a * a)) ** 3) if e <= a else a * a / 6)
    if name == "TrivialLoss":
        return s
    raise AssertionError(name)


LOSSES = ["TrivialLoss", "Huber", "Cauchy", "GemanMcClure", "Tukey"]


def _make(name, a):
    cls = getattr(fg, name)
    return cls() if name == "TrivialLoss" else cls(a)


@pytest.mark.parametrize("name", LOSSES)
@pytest.mark.parametrize("a", [0.5, 1.0, 3.0])
def test_values_match_the_definitions(name, a):
    loss = _make(name, a)
    rho, d1, _ = loss.evaluate(S)
    expected = torch.tensor([_definition(name, a, float(s)) for s in S], dtype=f64)
    torch.testing.assert_close(rho, expected, rtol=1e-13, atol=1e-15)
    assert rho[0] == 0 and d1[0] == 1
    torch.testing.assert_close(loss(S), rho)


@pytest.mark.parametrize("name", LOSSES)
@pytest.mark.parametrize("a", [0.5, 2.0])
def test_derivatives_match_autograd(name, a):
    loss = _make(name, a)
    s = S[1:]  # autograd of the definitions' sqrt is undefined at 0
    s = s[(s - a * a).abs() > 1e-6]  # the kinks of Huber and Tukey
    grad = torch.func.vmap(torch.func.grad(lambda t: loss.evaluate(t)[0]))
    grad2 = torch.func.vmap(torch.func.grad(torch.func.grad(lambda t: loss.evaluate(t)[0])))
    _, d1, d2 = loss.evaluate(s)
    torch.testing.assert_close(d1, grad(s), rtol=1e-12, atol=1e-15)
    torch.testing.assert_close(d2, grad2(s), rtol=1e-12, atol=1e-15)
    # and against finite differences of the written-out definitions
    h = torch.minimum(1e-6 * (1 + s), s / 2)
    fd = torch.tensor([(_definition(name, a, float(x + dx)) - _definition(name, a, float(x - dx)))
                       / (2 * float(dx)) for x, dx in zip(s, h)], dtype=f64)
    torch.testing.assert_close(d1, fd, rtol=1e-6, atol=1e-9)


def test_scale_is_checked():
    with pytest.raises(ValueError, match="scale"):
        fg.Huber(0.0)
    with pytest.raises(ValueError, match="scale"):
        fg.Cauchy(float("nan"))
    # a^2 and a^4 must be normal numbers (1e200 ** 2 overflows; 1e-200 ** 2 is 0: NaN costs)
    for loss in (fg.Huber, fg.Cauchy, fg.GemanMcClure, fg.Tukey):
        for a in (1e200, 1e-200):
            with pytest.raises(ValueError, match=r"scale must be within \[1e-75, 1e75\]"):
                loss(a)
    s = torch.tensor([0.0, 1e-300, 1.0, 1e300], dtype=f64)
    for loss in (fg.Huber(1e-75), fg.Cauchy(1e-75), fg.GemanMcClure(1e75), fg.Tukey(1e75)):
        assert all(torch.isfinite(v).all() for v in loss.evaluate(s[:3])), loss


def test_a_negative_squared_norm_is_refused():
    for loss in (fg.Huber(1.0), fg.Cauchy(1.0), fg.GemanMcClure(1.0), fg.Tukey(1.0), fg.TrivialLoss()):
        with pytest.raises(ValueError, match=r"s must be >= 0 \(a squared whitened norm\), got a minimum of -2"):
            loss(torch.tensor([1.0, -2.0], dtype=f64))


def test_rho_runs_where_its_values_cannot_be_read():
    """rho(s) under vmap, on 'meta' tensors and compiled (fullgraph): the values its definition
    gives (the check on s reads values only where they can be read)."""
    s = torch.tensor([[0.0, 0.5, 4.0], [1.0, 2.0, 9.0]], dtype=f64)
    for loss in (fg.Huber(1.0), fg.Cauchy(1.0), fg.GemanMcClure(1.0), fg.Tukey(2.0)):
        want = torch.stack([loss.evaluate(row)[0] for row in s])
        torch.testing.assert_close(torch.func.vmap(loss)(s), want, rtol=1e-15, atol=0)
        assert loss(torch.empty(3, device="meta", dtype=f64)).shape == (3,)
        torch.testing.assert_close(torch.compile(loss, fullgraph=True)(s[0]), want[0], rtol=1e-15, atol=0)


class _Convex(RobustLoss):
    """rho(s) = s + s^2 / 4 (rho'' > 0: Ceres applies the full Triggs correction)."""

    def evaluate(self, s):
        return s + s * s / 4, 1 + s / 2, torch.full_like(s, 0.5)


@pytest.mark.parametrize("loss", [_Convex(), fg.Huber(0.7), fg.Cauchy(1.0), fg.GemanMcClure(1.0),
                                  fg.Tukey(3.0), None], ids=repr)
def test_corrector_matches_the_gradient_and_triggs_curvature(loss):
    """J~^T r~ is the gradient of 1/2 rho(|r|^2) (rho' J^T r); J~^T J~ is Triggs' curvature
    J^T (rho' I + 2 rho'' r r^T) J where rho'' > 0, the IRLS weighting rho' J^T J elsewhere."""
    gen = torch.Generator().manual_seed(0)
    r = torch.randn(6, 4, generator=gen, dtype=f64)
    J = torch.randn(6, 4, 3, generator=gen, dtype=f64)
    r_c, J_c, rho = correct(loss, r, J)
    s = (r * r).sum(-1)
    d1, d2 = (torch.ones_like(s), torch.zeros_like(s)) if loss is None else loss.evaluate(s)[1:]
    JTr = (J.mT @ r[..., None])[..., 0]
    torch.testing.assert_close((J_c.mT @ r_c[..., None])[..., 0], d1[:, None] * JTr)
    curv = torch.where(d2 > 0, d2, torch.zeros_like(d2))[:, None, None]
    expected = d1[:, None, None] * J.mT @ J + 2 * curv * JTr[:, :, None] * JTr[:, None, :]
    torch.testing.assert_close(J_c.mT @ J_c, expected)
    torch.testing.assert_close(rho, s if loss is None else loss.evaluate(s)[0])


def _line_fit(x, y, loss, start=None):
    graph = fg.FactorGraph()
    graph.add_variable("ab", torch.zeros(1, 2, dtype=f64) if start is None else start)
    K = x.shape[0]
    graph.add(fg.Factor(lambda ab, xk, yk: (ab[..., :1] * xk + ab[..., 1:]) - yk,
                        [("ab", torch.zeros(K, dtype=torch.int64))], [x[:, None], y[:, None]],
                        dim=1, sqrt_information=torch.tensor([[1 / 0.01]], dtype=f64)), loss=loss)
    result = fg.levenberg_marquardt(graph)
    return result


@pytest.mark.parametrize("loss", [fg.Huber(1.345), fg.Cauchy(2.0), fg.GemanMcClure(2.0),
                                  fg.Tukey(4.685)], ids=repr)
def test_line_fit_with_outliers(loss):
    gen = torch.Generator().manual_seed(3)
    x = torch.linspace(-1, 1, 80, dtype=f64)
    y = 0.7 * x - 0.2 + 0.01 * torch.randn(80, generator=gen, dtype=f64)
    y[::5] += 3.0 + torch.rand(16, generator=gen, dtype=f64)  # 20 % gross outliers, one side
    plain = _line_fit(x, y, None)
    ab_plain = plain.values["ab"][0]
    assert (ab_plain - torch.tensor([0.7, -0.2], dtype=f64)).abs().max() > 0.3
    start = None
    if isinstance(loss, (fg.Tukey, fg.GemanMcClure)):  # redescending: start from a Huber fit
        start = _line_fit(x, y, fg.Huber(1.345)).values["ab"]
    robust = _line_fit(x, y, loss, start)
    ab = robust.values["ab"][0]
    assert robust.report.status.item() in (SolverStatus.CONVERGED, SolverStatus.CONVERGED_RANK_DEFICIENT)
    tol = 0.02 if isinstance(loss, fg.Huber) else 0.01
    assert (ab - torch.tensor([0.7, -0.2], dtype=f64)).abs().max() < tol, ab
