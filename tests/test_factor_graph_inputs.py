"""What the factor-graph engine refuses, with the argument named: an information matrix that is
not symmetric, a residual without its size axis, analytic Jacobians of the wrong count, shape
or dtype, a point observation on the wrong kinds of variables, a non-integer marginal index and
a damping start outside its bounds.  Each case is one the engine would otherwise solve as
another problem without a word, or fail in torch with another argument's name."""
from __future__ import annotations

import re

import pytest
import torch

import torchsgal as ts
from torchsgal.estimation import graph as fg
from torchsgal.estimation.solver import SolverStatus

f64 = torch.float64


def _line(information=None, sqrt_information=None):
    """One unbatched Euclidean variable v (4, 2) and the factor r = v (E = 4, dim 2)."""
    graph = fg.FactorGraph()
    graph.add_variable("v", torch.arange(8, dtype=f64).reshape(4, 2))
    graph.add(fg.Factor(lambda v: v, variables=[("v", torch.arange(4))], dim=2,
                        information=information, sqrt_information=sqrt_information))
    return graph


def _initial_cost(graph):
    return fg.levenberg_marquardt(graph, max_iterations=0).report.initial_cost[0]  # one problem


def test_information_must_be_symmetric():
    """Cholesky reads one triangle: [[1, 50], [0, 1]] would be solved as the identity (cost 1/2
    |r|^2 = 70 for v = 0..7, while 1/2 r^T W r is 70 + 50 * sum(v0 v1) = 2,370)."""
    with pytest.raises(ValueError, match=r"information is not symmetric \(max relative asymmetry"):
        _initial_cost(_line(information=torch.tensor([[1.0, 50.0], [0.0, 1.0]], dtype=f64)))
    # a symmetric W whose transpose differs by rounding is accepted, and gives 1/2 r^T W r
    W = torch.tensor([[2.0, 0.3], [0.3, 1.0]], dtype=f64)
    W_rounded = W.clone()
    W_rounded[0, 1] += 1e-15
    r = torch.arange(8, dtype=f64).reshape(4, 2)
    want = 0.5 * torch.einsum("ei,ij,ej->", r, W, r)
    torch.testing.assert_close(_initial_cost(_line(information=W_rounded)), want, rtol=1e-14, atol=0)
    # a square root information need not be symmetric: r~ = L r
    L = torch.tensor([[1.0, 2.0], [0.0, 1.0]], dtype=f64)
    torch.testing.assert_close(_initial_cost(_line(sqrt_information=L)),
                               0.5 * (r @ L.mT).square().sum(), rtol=1e-14, atol=0)


def test_a_residual_without_dim_must_have_its_size_axis():
    """Without dim=, r (B, E) could be read as one residual of size E repeated over the factors
    (cost E times too large): it is refused; with dim the residual may broadcast."""
    graph = fg.FactorGraph()
    graph.add_variable("v", torch.tensor([[1.0], [2.0], [3.0], [4.0]], dtype=f64))
    graph.add(fg.Factor(lambda v: v[..., 0], variables=[("v", torch.arange(4))]))
    with pytest.raises(ValueError, match=r"must return \(B, E, dim\).*give the factor its dim"):
        _initial_cost(graph)
    ok = fg.FactorGraph()
    ok.add_variable("v", torch.tensor([[1.0], [2.0], [3.0], [4.0]], dtype=f64))
    ok.add(fg.Factor(lambda v: v, variables=[("v", torch.arange(4))]))
    torch.testing.assert_close(_initial_cost(ok), torch.tensor(15.0, dtype=f64), rtol=0, atol=0)


def _pose_graph(jacobians):
    graph = fg.FactorGraph()
    graph.add_variable("X", ts.SE3.exp(torch.randn(4, 6, dtype=f64, generator=torch.Generator().manual_seed(0))))
    graph.add(fg.Factor(lambda X: X.log(), variables=[("X", torch.arange(4))], dim=6,
                        jacobians=jacobians))
    return graph


@pytest.mark.parametrize("jacobians, error, message", [
    (lambda X: (X.log(), [torch.zeros(4, 6, 5, dtype=f64)]), ValueError,
     r"Jacobian 0 has shape \(4, 6, 5\), expected \(\.\.\., 6, 6\)"),
    (lambda X: (X.log(), [torch.zeros(4, 6, 6, dtype=f64)] * 2), TypeError,
     r"one Jacobian per variable \(1\).*got 2"),
    (lambda X: (X.log(), [torch.zeros(4, 6, 6, dtype=torch.float32)]), TypeError,
     "Jacobian 0 must be a tensor of the residual's dtype torch.float64"),
    (lambda X: (X.log().float(), [torch.zeros(4, 6, 6)]), TypeError,
     "the residual is torch.float32 on cpu, the graph's variables torch.float64"),
    (lambda X: X.log(), TypeError, r"jacobians must return \(r, \[J_1, \.\.\.\]\) or \(r, J\)"),
])
def test_analytic_jacobians_are_checked(jacobians, error, message):
    with pytest.raises(error, match=message):
        fg.levenberg_marquardt(_pose_graph(jacobians), max_iterations=1)


def test_a_forward_mode_residual_of_another_dtype_is_refused():
    graph = fg.FactorGraph()
    graph.add_variable("v", torch.zeros(3, 2, dtype=f64))
    graph.add(fg.Factor(lambda v: v.float(), variables=[("v", torch.arange(3))], dim=2))
    with pytest.raises(TypeError, match="the residual is torch.float32"):
        fg.levenberg_marquardt(graph, max_iterations=1)


def test_point_observation_checks_its_variables():
    graph = fg.FactorGraph()
    graph.add_variable("x", ts.SE3.identity((2,), dtype=f64))
    graph.add_variable("p", torch.zeros(3, 3, dtype=f64))
    graph.add_variable("q", torch.zeros(3, 2, dtype=f64))
    z = torch.zeros(2, 3, dtype=f64)
    with pytest.raises(TypeError, match="pose 'p' must be a group variable"):
        graph.add(fg.PointObservation("p", [0, 1], "x", [0, 1], z))
    with pytest.raises(TypeError, match="point 'x' must be a Euclidean variable, got a SE3"):
        graph.add(fg.PointObservation("x", [0, 1], "x", [0, 1], z))
    with pytest.raises(ValueError, match="points of size 3; point 'q' has size 2 and measured 3"):
        graph.add(fg.PointObservation("x", [0, 1], "q", [0, 1], z))
    with pytest.raises(ValueError, match="point 'p' has size 3 and measured 2"):
        graph.add(fg.PointObservation("x", [0, 1], "p", [0, 1], z[:, :2]))
    graph.add(fg.PointObservation("x", [0, 1], "p", [0, 1], z))
    assert len(graph.factors) == 1


def test_a_residual_without_dim_and_noise_of_another_size_is_refused():
    """Without dim the residual's size is known only when it is evaluated: the noise is checked
    against it then, named (torch would fail in a matrix product)."""
    for noise in (dict(information=torch.eye(3, dtype=f64)),
                  dict(sqrt_information=torch.ones(4, 1, 1, dtype=f64))):
        graph = fg.FactorGraph()
        graph.add_variable("v", torch.zeros(4, 2, dtype=f64))
        graph.add(fg.Factor(lambda v: v - 1, variables=[("v", torch.arange(4))], **noise))
        name, = noise
        with pytest.raises(ValueError, match=rf"{name} must be \(2, 2\), \(E, 2, 2\) or \(B, E, 2, 2\) "
                                             rf"for a residual of size 2, got {re.escape(str(tuple(noise[name].shape)))}"):
            fg.levenberg_marquardt(graph)


def test_jacobians_must_be_callable():
    with pytest.raises(TypeError, match="jacobians must be callable or None, got int"):
        fg.Factor(lambda v: v, variables=[("v", torch.arange(4))], dim=2, jacobians=3)


@pytest.mark.parametrize("value", [torch.zeros(0, 3, 2, dtype=f64), torch.zeros(3, 0, dtype=f64),
                                   torch.zeros(0, 2, dtype=f64), ts.SE3.identity((0, 5), dtype=f64),
                                   ts.SE3.identity((0,), dtype=f64)], ids=str)
def test_an_empty_variable_is_refused(value):
    """No problems, no elements or no entries: nothing a solve could return (the solvers failed
    in torch's broadcasting, or in the block analysis with no variable named)."""
    graph = fg.FactorGraph()
    with pytest.raises(ValueError, match=r"variable 'v': a (tensor|group element) .* >= 1, got"):
        graph.add_variable("v", value)


def test_point_observation_measured_needs_its_factor_axis():
    """A (point_dim,) measurement is refused even where E = point_dim (it was read as E points)."""
    with pytest.raises(ValueError, match=r"measured must have shape \(E, point_dim\) or \(B, E, point_dim\), got \(3,\)"):
        fg.PointObservation("x", [0, 0, 0], "p", [0, 1, 2], torch.tensor([1.0, 2.0, 3.0], dtype=f64))


def test_marginal_covariance_takes_integer_indices_only():
    result = fg.levenberg_marquardt(_line())
    want = torch.eye(2, dtype=f64)  # H = I for r = v: the marginal of every element is I
    torch.testing.assert_close(result.marginal_covariance("v", 1), want[None], rtol=1e-14, atol=0)
    for index, error in ((1.7, TypeError), (torch.tensor([0.9, 2.5]), TypeError), (True, TypeError),
                         (torch.tensor([[0, 1]]), ValueError)):
        with pytest.raises(error, match="index"):
            result.marginal_covariance("v", index)


@pytest.mark.parametrize("options", [dict(lambda_initial=1.0, lambda_upper=0.5),
                                     dict(lambda_initial=1e-5, lambda_lower=1e-3)])
def test_lambda_initial_lies_between_its_bounds(options):
    with pytest.raises(ValueError, match=r"lambda_initial must lie in \[lambda_lower, lambda_upper\]"):
        fg.levenberg_marquardt(_line(), **options)


@pytest.mark.parametrize("batch", [(), (1, 1, 1)], ids=str)
def test_group_measurements_need_one_or_two_batch_axes(batch):
    """A group element of batch () or of three axes is no (E,) / (B, E) measurement: it is
    refused by name (unchecked, it would fail in torch's indexing or expand, naming no argument)."""
    Z = ts.SE3.identity(batch, dtype=f64)
    with pytest.raises(ValueError, match=rf"measured must be a group element of batch \(E,\) or "
                                         rf"\(B, E\), got batch {re.escape(str(batch))}"):
        fg.Prior("x", 0, Z)
    with pytest.raises(ValueError, match=r"measured must be a group element of batch \(E,\)"):
        fg.Between("x", 0, 1, Z)
    graph = fg.FactorGraph()
    graph.add_variable("x", ts.SE3.identity((2, 3), dtype=f64))
    graph.add(fg.Factor(lambda X, Z: Z.inverse().compose(X).log(), variables=[("x", 0)], data=[Z],
                        dim=6))
    with pytest.raises(ValueError, match=rf"data\[0\]: expected a leading batch \(E,\) = \(1,\) or "
                                         rf"\(B, E\) = \(2, 1\), got {re.escape(str(batch))}"):
        fg.levenberg_marquardt(graph)


def test_noise_of_another_size_dtype_or_device_is_refused_at_once():
    """A factor of known size refuses noise of another size when it is made,
    and the graph noise of another dtype or device when the factor is added (as its data),
    naming the noise (unchecked, they would surface only in the solve)."""
    Z = ts.SE3.identity((3,), dtype=f64)
    with pytest.raises(ValueError, match=r"information must be \(6, 6\), \(E, 6, 6\) or \(B, E, 6, 6\) "
                                         r"for a residual of size 6, got \(5, 5\)"):
        fg.Prior("x", [0, 1, 2], Z, information=torch.eye(5, dtype=f64))
    with pytest.raises(ValueError, match=r"sqrt_information must be \(6, 6\), .* got \(3, 3, 3\)"):
        fg.Between("x", [0, 1, 2], [1, 2, 3], Z, sqrt_information=torch.eye(3, dtype=f64).expand(3, 3, 3))
    graph = fg.FactorGraph()
    graph.add_variable("x", ts.SE3.identity((3,), dtype=f64))
    with pytest.raises(TypeError, match=r"information has dtype torch.float32 but the graph's first "
                                        r"variable has dtype torch.float64"):
        graph.add(fg.Prior("x", [0, 1, 2], Z, information=torch.eye(6).expand(3, 6, 6)))
    with pytest.raises(ValueError, match=r"sqrt_information is on meta but the graph's first variable"):
        graph.add(fg.Prior("x", 0, Z[:1], sqrt_information=torch.eye(6, dtype=f64, device="meta")))
    assert not graph.factors
    # the shapes the docstring gives are accepted: shared, per factor, per problem and factor
    for W in (torch.eye(6, dtype=f64), torch.eye(6, dtype=f64).expand(3, 6, 6),
              torch.eye(6, dtype=f64).expand(1, 3, 6, 6), torch.eye(6, dtype=f64).expand(1, 1, 6, 6)):
        graph.add(fg.Prior("x", [0, 1, 2], Z, information=2 * W))
    result = fg.levenberg_marquardt(graph)
    assert result.report.status.tolist() == [SolverStatus.CONVERGED]
    torch.testing.assert_close(result.marginal_covariance("x", 0),
                               torch.eye(6, dtype=f64)[None] / 8, rtol=1e-12, atol=0)  # 4 priors of 2 I
