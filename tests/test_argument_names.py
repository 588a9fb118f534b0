"""Errors name the caller's arguments: the quaternion interop's pose layouts and the
regression simulator's group, start and generator."""
from __future__ import annotations

import pytest
import torch

import torchsgal as ts
from torchsgal.interop import quaternion as Q
from torchsgal.regression.simulate import simulate_maneuver

f64 = torch.float64


@pytest.mark.parametrize("call, error, message", [
    (lambda: Q.from_quaternion_translation(torch.tensor([1.0, 0, 0, 0], dtype=f64), torch.zeros(3),
                                           order="wxyz"),
     TypeError, "t has dtype torch.float32 but q has dtype torch.float64"),
    (lambda: Q.from_quaternion_translation(torch.eye(4, dtype=f64)[:2], torch.zeros(3, 3, dtype=f64),
                                           order="wxyz"),
     ValueError, r"batch shapes do not broadcast: q \(2,\), t \(3,\)"),
    (lambda: Q.from_pose7(torch.zeros(7, dtype=f64), order="xyzw"),
     ValueError, r"pose\[\.\.\., 3:7\] has a quaternion of zero length"),
    (lambda: Q.from_pose7(torch.zeros(7, dtype=f64).index_fill(0, torch.tensor([6]), float("nan")),
                          order="xyzw"),
     ValueError, r"pose\[\.\.\., 3:7\] has a quaternion that is not finite"),
])
def test_quaternion_interop_names_the_arguments(call, error, message):
    with pytest.raises(error, match=message):
        call()


def test_pose7_reads_translation_then_quaternion():
    pose = torch.tensor([1.0, 2.0, 3.0, 0.0, 0.0, 1.0, 0.0], dtype=f64)  # t, then xyzw: z by pi
    g = Q.from_pose7(pose, order="xyzw")
    want = torch.tensor([[-1.0, 0, 0, 1], [0, -1, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]], dtype=f64)
    torch.testing.assert_close(g.as_matrix(), want, rtol=0, atol=1e-15)


@pytest.mark.parametrize("kwargs, error, message", [
    (dict(G="SE3"), TypeError, "G must be a group class"),
    (dict(start=ts.SGal3.identity(dtype=torch.float32)), TypeError,
     "start has dtype torch.float32 but velocity has dtype torch.float64"),
    (dict(velocity=torch.zeros(2, 10, dtype=f64), start=ts.SGal3.identity((3,), dtype=f64)), ValueError,
     r"batch shapes do not broadcast: velocity \(2,\), start \(3,\)"),
    (dict(start=ts.SE3.identity(dtype=f64)), TypeError, "start must be a SGal3, got SE3"),
    (dict(generator=3), TypeError, "generator must be a torch.Generator or None, got int"),
])
def test_simulate_maneuver_names_the_arguments(kwargs, error, message):
    args = dict(G=ts.SGal3, velocity=torch.zeros(10, dtype=f64), n_samples=5, noise_std=0.1) | kwargs
    with pytest.raises(error, match=message):
        simulate_maneuver(args.pop("G"), args.pop("velocity"), args.pop("n_samples"),
                          args.pop("noise_std"), **args)
