"""SO3.from_quaternion / as_quaternion against scipy's Rotation (an independent implementation),
in both component orders, over batch shapes and dtypes, at the identity, at tiny angles and
near pi; gradients by gradcheck; bad input."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

import torchsgal as ts

F64 = torch.float64
SHAPES = [(), (5,), (2, 3, 1)]


def _xyzw(q: np.ndarray, order: str) -> np.ndarray:
    return q if order == "xyzw" else np.roll(q, -1, axis=-1)


@pytest.mark.parametrize("order", ["wxyz", "xyzw"])
@pytest.mark.parametrize("shape", SHAPES, ids=str)
@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_quaternions_match_scipy(order, shape, dtype):
    gen = torch.Generator().manual_seed(len(shape))
    q = 3.0 * torch.randn(*shape, 4, dtype=F64, generator=gen)  # not unit: normalised
    R = ts.SO3.from_quaternion(q.to(dtype), order=order)
    ref = Rotation.from_quat(_xyzw(q.numpy(), order).reshape(-1, 4)).as_matrix().reshape(*shape, 3, 3)
    tol = 1e-15 if dtype == F64 else 1e-6  # worst over 20 seeds: 7.8e-16 / 4.0e-7
    np.testing.assert_allclose(R.as_matrix().double().numpy(), ref, rtol=0, atol=4 * tol)
    back = ts.SO3.from_matrix(torch.tensor(ref, dtype=dtype)).as_quaternion(order=order)
    want = Rotation.from_matrix(ref.reshape(-1, 3, 3)).as_quat(canonical=True).reshape(*shape, 4)
    np.testing.assert_allclose(_xyzw(back.double().numpy(), order), want, rtol=0, atol=4 * tol)
    assert R.batch_shape == shape and back.shape == (*shape, 4) and back.dtype == dtype


def test_quaternions_at_the_identity_small_angles_and_near_pi():
    gen = torch.Generator().manual_seed(3)
    angles = torch.tensor([0.0, 1e-12, 1e-6, 1e-3, 1.0, math.pi - 1e-3, math.pi - 1e-9], dtype=F64)
    axes = torch.nn.functional.normalize(torch.randn(len(angles), 3, dtype=F64, generator=gen), dim=-1)
    phi = axes * angles[:, None]
    q = ts.SO3.exp(phi).as_quaternion(order="wxyz")
    # exact: w = cos(theta/2), (x, y, z) = sin(theta/2) axis
    exact = torch.cat((torch.cos(angles / 2)[:, None], torch.sin(angles / 2)[:, None] * axes), -1)
    torch.testing.assert_close(q, exact, rtol=0, atol=1e-15)  # measured 2.1e-16
    # at pi (w = 0) q and -q are the same rotation: compared up to sign
    g = ts.SO3.exp(axes * math.pi)
    q = g.as_quaternion(order="xyzw")
    assert ((q[:, :3] - axes).abs().amax(-1).minimum((q[:, :3] + axes).abs().amax(-1)) < 1e-15).all()
    torch.testing.assert_close(ts.SO3.from_quaternion(q, order="xyzw").as_matrix(), g.as_matrix(),
                               rtol=0, atol=1e-15)


def test_a_quaternion_and_its_negative_give_one_rotation():
    q = torch.randn(6, 4, dtype=F64, generator=torch.Generator().manual_seed(4))
    a, b = (ts.SO3.from_quaternion(x, order="wxyz").as_matrix() for x in (q, -q))
    assert torch.equal(a, b)
    back = ts.SO3.from_quaternion(q, order="wxyz").as_quaternion(order="wxyz")
    unit = q / q.norm(dim=-1, keepdim=True)
    torch.testing.assert_close(back, unit * unit[:, :1].sign(), rtol=0, atol=1e-15)


def test_quaternion_gradients_and_transforms():
    gen = torch.Generator().manual_seed(5)
    q = torch.randn(4, 4, dtype=F64, generator=gen, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: ts.SO3.from_quaternion(x, order="xyzw").as_matrix(), (q,))
    M = ts.SO3.random((4,), dtype=F64, generator=gen).as_matrix().requires_grad_()
    assert torch.autograd.gradcheck(lambda m: ts.functional.so3.to_quaternion(m, "wxyz"), (M,))
    # the identity: finite gradients in float32
    I = torch.eye(3).requires_grad_()
    ts.functional.so3.to_quaternion(I, "wxyz").sum().backward()
    assert torch.isfinite(I.grad).all()
    # vmap and jacrev agree with the batched call
    f = lambda x: ts.SO3.from_quaternion(x, order="wxyz").as_quaternion(order="wxyz")  # noqa: E731
    x = q.detach()
    torch.testing.assert_close(torch.func.vmap(f)(x), f(x), rtol=0, atol=1e-15)
    J = torch.func.vmap(torch.func.jacrev(f))(x)
    unit = x / x.norm(dim=-1, keepdim=True)
    s = unit[:, :1].sign()[..., None]  # d(s q/|q|)/dq = s (I - u u^T)/|q|
    want = s * (torch.eye(4, dtype=F64) - unit[:, :, None] * unit[:, None, :]) / x.norm(dim=-1)[:, None, None]
    torch.testing.assert_close(J, want, rtol=0, atol=1e-13)


def test_quaternion_bad_input():
    q = torch.randn(3, 4)
    with pytest.raises(ValueError, match=r"order must be 'wxyz' \(scalar first.* got 'zyxw'"):
        ts.SO3.from_quaternion(q, order="zyxw")
    with pytest.raises(TypeError, match=r"missing 1 required keyword-only argument: 'order'"):
        ts.SO3.from_quaternion(q)
    with pytest.raises(ValueError, match=r"q must have shape \(\.\.\., 4\), got \(3, 3\)"):
        ts.SO3.from_quaternion(torch.randn(3, 3), order="wxyz")
    with pytest.raises(TypeError, match=r"q must have a floating dtype"):
        ts.SO3.from_quaternion(torch.ones(4, dtype=torch.int64), order="wxyz")
    with pytest.raises(ValueError, match=r"q has a quaternion of zero length"):
        ts.SO3.from_quaternion(torch.zeros(2, 4), order="wxyz")
    with pytest.raises(ValueError, match=r"order must be"):
        ts.SO3.identity().as_quaternion(order="WXYZ")
    # meta: shapes only (the zero-length check reads values, skipped there)
    assert ts.SO3.from_quaternion(torch.empty(2, 4, device="meta"), order="xyzw").batch_shape == (2,)
    assert ts.SO3.random(2, device="meta").as_quaternion(order="wxyz").shape == (2, 4)
