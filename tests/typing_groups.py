"""Type-checked (not run) by tests/test_typing.py: each annotated assignment fails mypy if the
group API returned ``LieGroup`` or ``Any`` instead of the class (``warn_return_any`` and
``disallow_any_expr`` are not needed: an ``Any`` result is caught by the ``assert_type`` lines)."""
from __future__ import annotations

from collections.abc import Iterator

import torch
from typing_extensions import assert_type

import torchsgal as ts

xi = torch.zeros(6)

# constructors return the class they are called on
x: ts.SE3 = ts.SE3.exp(xi)
assert_type(ts.SE3.exp(xi), ts.SE3)
assert_type(ts.SO3.identity(), ts.SO3)
assert_type(ts.SE23.random(4), ts.SE23)
assert_type(ts.SGal3.from_matrix(torch.eye(5)), ts.SGal3)
assert_type(ts.Sim3.from_components(torch.eye(3), torch.zeros(3), torch.ones(())), ts.Sim3)
assert_type(ts.SO2.from_components(torch.eye(2)), ts.SO2)
assert_type(ts.SE2.from_components(torch.eye(2), torch.zeros(2)), ts.SE2)
assert_type(ts.SO3.from_rotation(torch.eye(3)), ts.SO3)
assert_type(ts.SE3.stack([x, x]), ts.SE3)
assert_type(ts.SE3.cat([x[None], x[None]]), ts.SE3)

# group operations return the class of self
y: ts.SE3 = x.compose(x).inverse()
assert_type(x @ x, ts.SE3)
assert_type(x.rplus(xi), ts.SE3)
assert_type(x.lplus(xi), ts.SE3)
assert_type(x.between(y), ts.SE3)
assert_type(x.interpolate(y, 0.5), ts.SE3)

# batch handling returns the class too
assert_type(x[None], ts.SE3)
assert_type(x.reshape(1).flatten().squeeze().unsqueeze(0).expand(3), ts.SE3)
assert_type(x.to(torch.float64).float().double().cpu().detach().clone(), ts.SE3)
assert_type(x.requires_grad_(), ts.SE3)
assert_type(iter(ts.SE3.identity(2)), Iterator[ts.SE3])

# a user subclass keeps its class through the API
class Pose(ts.SE3):
    __slots__ = ()


p: Pose = Pose.exp(xi).compose(x).inverse()
assert_type(Pose.identity(3)[0], Pose)

# tensors and plain values
assert_type(x.log(), torch.Tensor)
assert_type(x.adjoint(), torch.Tensor)
assert_type(x.rminus(y), torch.Tensor)
assert_type(x.lminus(y), torch.Tensor)
assert_type(x.act(torch.zeros(3)), torch.Tensor)
assert_type(x.act_direction(torch.zeros(3)), torch.Tensor)
assert_type(x.rotation(), torch.Tensor)
assert_type(x.position(), torch.Tensor)
assert_type(x.as_matrix(), torch.Tensor)
assert_type(x.allclose(y), bool)
assert_type(x.batch_shape, torch.Size)
assert_type(x.shape, torch.Size)
assert_type(x.requires_grad, bool)
assert_type(ts.SE3.hat(xi), torch.Tensor)
assert_type(ts.SE3.vee(ts.SE3.hat(xi)), torch.Tensor)
assert_type(ts.SE3.ad(xi), torch.Tensor)
assert_type(ts.SE3.jl(xi), torch.Tensor)
assert_type(ts.SE3.jr(xi), torch.Tensor)
assert_type(ts.SE3.jl_inv(xi), torch.Tensor)
assert_type(ts.SE3.jr_inv(xi), torch.Tensor)
assert_type(ts.SGal3.identity().time(), torch.Tensor)
assert_type(ts.SE23.identity().act_velocity(torch.zeros(3)), torch.Tensor)
assert_type(ts.Sim3.identity().scale(), torch.Tensor)
assert_type(ts.SO3.identity().as_quaternion(order="wxyz"), torch.Tensor)
