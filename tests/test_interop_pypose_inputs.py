"""from_pypose of a Sim3 with a scale that is not finite and positive raises, naming x, where
the values can be read; a positive scale gives [[C, t / s], [0, 1 / s]]."""
from __future__ import annotations

import math

import pytest
import torch

from torchsgal.interop import pypose as tp

pp = pytest.importorskip("pypose")

F64 = torch.float64


def _sim3_data(scales):
    """pypose Sim3 storage [t, qx, qy, qz, qw, s], identity rotation, t = (1, 2, 3)."""
    s = torch.tensor(scales, dtype=F64)
    rest = torch.tensor([1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0], dtype=F64).expand(*s.shape, 7)
    return torch.cat((rest, s[..., None]), dim=-1)


@pytest.mark.parametrize("scale", [0.0, -2.0, math.inf, math.nan])
def test_from_pypose_refuses_a_bad_scale(scale):
    with pytest.raises(ValueError, match=r"x must be a pypose Sim3 with finite scales > 0"):
        tp.from_pypose(pp.Sim3(_sim3_data(scale)))
    with pytest.raises(ValueError, match=r"x must be a pypose Sim3 .* got a scale of"):
        tp.from_pypose(pp.Sim3(_sim3_data([[2.0, 1.0], [scale, 3.0]])))  # one bad in a batch


def test_from_pypose_positive_scale():
    M = tp.from_pypose(pp.Sim3(_sim3_data([0.5, 4.0]))).as_matrix()
    for b, s in enumerate((0.5, 4.0)):
        expected = torch.eye(4, dtype=F64)
        expected[:3, 3] = torch.tensor([1.0, 2.0, 3.0], dtype=F64) / s
        expected[3, 3] = 1 / s
        torch.testing.assert_close(M[b], expected, rtol=0, atol=1e-15)


def test_from_pypose_scale_not_read_where_values_are_not_readable():
    out = torch.func.vmap(lambda d: tp.from_pypose(pp.Sim3(d)).as_matrix())(_sim3_data([2.0, 4.0]))
    torch.testing.assert_close(out[1, 3, 3], torch.tensor(0.25, dtype=F64), rtol=0, atol=0)
    meta = tp.from_pypose(pp.Sim3(torch.zeros(2, 8, dtype=F64, device="meta")))
    assert meta.batch_shape == (2,)


def test_errors_name_the_argument_that_holds_the_element():
    """A zero or non-finite quaternion, or a bad Sim3 scale, is reported under the name of the
    argument that was passed: x for from_pypose, at for the covariance maps, output and input
    for the Jacobian maps (not q, which the caller never named)."""
    import torchsgal as ts
    zero_so3 = pp.SO3(torch.zeros(4, dtype=F64))
    zero_se3 = pp.SE3(torch.tensor([1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 0.0], dtype=F64))
    nan_sim3 = pp.Sim3(torch.tensor([0.0, 0.0, 0.0, math.nan, 0.0, 0.0, 1.0, 1.0], dtype=F64))
    for x in (zero_so3, zero_se3):
        with pytest.raises(ValueError, match=r"^x has a quaternion of zero length"):
            tp.from_pypose(x)
    with pytest.raises(ValueError, match=r"^x has a quaternion that is not finite"):
        tp.from_pypose(nan_sim3)
    P6 = torch.eye(6, dtype=F64)
    for fn in (tp.covariance_from_pypose, tp.covariance_to_pypose):
        with pytest.raises(ValueError, match=r"^at has a quaternion of zero length"):
            fn(P6, zero_se3)
        with pytest.raises(ValueError, match=r"^at must be a pypose Sim3 with finite scales > 0"):
            fn(torch.eye(7, dtype=F64), pp.Sim3(_sim3_data(0.0)))
    with pytest.raises(ValueError, match=r"^at has a quaternion of zero length"):
        tp.perturbation_map(zero_so3)
    good = ts.SE3.identity(dtype=F64)
    for fn in (tp.jacobian_from_pypose, tp.jacobian_to_pypose):
        with pytest.raises(ValueError, match=r"^output has a quaternion of zero length"):
            fn(P6, output=zero_se3, input=good)
        with pytest.raises(ValueError, match=r"^input has a quaternion of zero length"):
            fn(P6, output=good, input=zero_se3)
