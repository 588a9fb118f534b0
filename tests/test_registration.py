"""functional/registration.py: operators defined through torch.library.Library, and the group
functions' direct call of their operators where nothing records a derivative."""
from __future__ import annotations

import pytest
import torch
from torch.autograd import forward_ad

import torchsgal as ts
from torchsgal.functional import registration


@registration.operator("torchsgal::registration_test_scale")
def _scale(x: torch.Tensor, factor: float) -> torch.Tensor:
    return x * factor


_scale.register_fake(lambda x, factor: torch.empty_like(x))


@registration.operator("torchsgal::registration_test_square",
                       schema="(Tensor x) -> Tensor")
def _square(x):
    return x * x


_square.register_fake(lambda x: torch.empty_like(x))
_square.register_autograd(lambda ctx, g: 2.0 * ctx.saved_tensors[0] * g,
                          setup_context=lambda ctx, inputs, output: ctx.save_for_backward(inputs[0]))


@registration.operator("torchsgal::registration_test_cpu_only")
def _cpu_only(x: torch.Tensor) -> torch.Tensor:
    return x + 1.0


@_cpu_only.register_kernel("cpu")
def _cpu_only_cpu(x):
    return x + 2.0  # the CPU kernel, distinguishable from the default implementation


_cpu_only.register_fake(lambda x: torch.empty_like(x))


def test_the_operator_is_the_registered_one_and_passes_opcheck():
    x = torch.randn(3, 4, dtype=torch.float64)
    assert torch.equal(_scale(x, 3.0), x * 3.0)
    assert torch.equal(torch.ops.torchsgal.registration_test_scale(x, 3.0), x * 3.0)
    assert torch.equal(_scale(x, factor=3.0), x * 3.0)  # arguments by name, as the schema names them
    torch.library.opcheck(torch.ops.torchsgal.registration_test_scale.default, (x, 3.0))
    torch.library.opcheck(torch.ops.torchsgal.registration_test_square.default,
                          (x.clone().requires_grad_(),))


def test_a_registered_backward_is_used_and_a_missing_one_raises():
    x = torch.randn(5, dtype=torch.float64, requires_grad=True)
    (grad,) = torch.autograd.grad(_square(x).sum(), x)
    torch.testing.assert_close(grad, 2.0 * x.detach(), rtol=0, atol=0)
    with pytest.raises(RuntimeError, match="torchsgal::registration_test_scale has no autograd formula"):
        _scale(x, 2.0).sum().backward()


def test_a_device_kernel_takes_its_device():
    x = torch.zeros(2)
    assert torch.equal(_cpu_only(x), torch.full((2,), 2.0))
    assert _cpu_only(torch.zeros(2, device="meta")).shape == (2,)  # the fake implementation


def test_vmap_rule_and_compile_see_the_operator():
    x = torch.randn(4, 3, dtype=torch.float64)
    torch.testing.assert_close(torch.func.vmap(lambda r: _scale(r, 2.0))(x), 2.0 * x, rtol=0, atol=0)
    compiled = torch.compile(lambda r: _scale(r, 2.0), fullgraph=True, backend="eager")
    torch.testing.assert_close(compiled(x), 2.0 * x, rtol=0, atol=0)


def test_bad_registrations_are_refused_by_name():
    with pytest.raises(ValueError, match="qualname must be 'torchsgal::<name>', got 'other::f'"):
        registration.operator("other::f")(lambda x: x)
    with pytest.raises(ValueError, match="device must be one of .*got 'tpu'"):
        _square.register_kernel("tpu")


GROUPS = [ts.SO3, ts.SE2, ts.SE3, ts.SE23, ts.SGal3, ts.Sim3]


@pytest.mark.parametrize("G", GROUPS, ids=lambda G: G.__name__)
def test_where_nothing_records_the_group_calls_its_operator_without_the_function(G):
    """The same operator either way: identical values; no graph where nothing records, the
    Function's node (and its derivatives) where something does."""
    xi = 0.7 * torch.randn(300, G.dof, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    plain = G.exp(xi)
    assert plain.as_matrix().grad_fn is None
    recorded = G.exp(xi.clone().requires_grad_())
    assert recorded.as_matrix().grad_fn is not None
    assert torch.equal(plain.as_matrix(), recorded.as_matrix().detach())
    assert torch.equal(plain.log(), recorded.log().detach())
    assert torch.equal(G.jl(xi), G.jl(xi.clone().requires_grad_()).detach())
    M = plain.as_matrix()
    assert torch.equal((plain @ plain).as_matrix(), (recorded @ recorded).as_matrix().detach())
    with forward_ad.dual_level():  # a forward-mode tangent: the Function, with its jvp
        dual = forward_ad.make_dual(xi, torch.ones_like(xi))
        out = G.exp(dual).as_matrix()
        primal, tangent = forward_ad.unpack_dual(out)
        assert tangent is not None and torch.equal(primal, M)
