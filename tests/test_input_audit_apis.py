"""Bad input to the converters, the nn helpers, the IMU, kinematics and factor-graph APIs:
each case raises at once, naming the argument, instead of failing inside torch or Python
(or being accepted)."""
from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from conftest import needs_robot_data

import torchsgal as ts
from torchsgal import load
from torchsgal import nn as tsnn
from torchsgal.estimation import g2o
from torchsgal.estimation.graph import (
    Between,
    Cauchy,
    FactorGraph,
    GemanMcClure,
    Huber,
    PointObservation,
    Prior,
    TrivialLoss,
    Tukey,
)
from torchsgal.estimation.graph.robust import correct
from torchsgal.imu import data as imu_data
from torchsgal.imu.factors import implied_increment
from torchsgal.interop import gtsam as igtsam
from torchsgal.interop import pypose as ipypose
from torchsgal.kinematics import dh, robots

D = torch.float64


# ------------------------------------------------------------------ interop.pypose
@pytest.mark.parametrize("fn", [ipypose.covariance_from_pypose, ipypose.covariance_to_pypose])
def test_pypose_covariance_dtype_and_batch(fn):
    at = ts.SE3.identity(2, dtype=D)
    with pytest.raises(TypeError, match="at has dtype torch.float64 but P has dtype torch.float32"):
        fn(torch.eye(6), at)
    with pytest.raises(ValueError, match=r"batch shapes do not broadcast: P \(3,\), at \(2,\)"):
        fn(torch.eye(6, dtype=D).expand(3, 6, 6), at)
    with pytest.raises(ValueError, match="at is on cpu but P is on meta"):
        fn(torch.eye(6, dtype=D, device="meta"), at)


@pytest.mark.parametrize("fn", [ipypose.jacobian_from_pypose, ipypose.jacobian_to_pypose])
def test_pypose_jacobian_dtype_and_batch(fn):
    with pytest.raises(TypeError, match="output has dtype torch.float64 but J has dtype torch.float32"):
        fn(torch.zeros(6, 6), output=ts.SE3.identity(dtype=D), input=None)
    with pytest.raises(ValueError, match=r"batch shapes do not broadcast: J \(3,\), input \(2,\)"):
        fn(torch.zeros(3, 3, 6, dtype=D), output=None, input=ts.SE3.identity(2, dtype=D))
    with pytest.raises(TypeError, match="output has dtype torch.float32 but J has dtype torch.float64"):
        fn(torch.zeros(6, 6, dtype=D), output=ts.SE3.identity(dtype=torch.float32),
           input=ts.SE3.identity(dtype=D))


# ------------------------------------------------------------------ interop.gtsam
def test_gtsam_converters_refuse_meta_tensors():
    pytest.importorskip("gtsam")
    with pytest.raises(ValueError, match="g is on the 'meta' device"):
        igtsam.to_gtsam(ts.SE3.identity(dtype=D, device="meta"))
    with pytest.raises(ValueError, match="p is on the 'meta' device"):
        igtsam.points_to_gtsam(torch.zeros(3, dtype=D, device="meta"))


# ------------------------------------------------------------------ nn
@pytest.mark.parametrize("kwargs, error", [
    (dict(reset_state="no"), "reset_state must be True or False, got 'no'"),
    (dict(optimizer="adam"), "optimizer must be None or a torch.optim.Optimizer, got str"),
])
def test_retract_all_checks_its_arguments_without_group_parameters(kwargs, error):
    with pytest.raises(TypeError, match=error):
        tsnn.retract_all_(torch.nn.Linear(2, 2), **kwargs)


# ------------------------------------------------------------------ graph.robust
def test_correct_checks_its_arguments():
    r = torch.full((2, 3), 5.0, dtype=D)
    with pytest.raises(TypeError, match="loss must be a RobustLoss or None, got str"):
        correct("huber", r, None)
    with pytest.raises(TypeError, match="r must be a torch.Tensor, got list"):
        correct(Huber(), [1.0, 2.0], None)
    with pytest.raises(TypeError, match="r must have a floating dtype"):
        correct(Huber(), torch.ones(2, 3, dtype=torch.int64), None)
    with pytest.raises(ValueError, match=r"J must have shape \(\.\.\., 3, n\) .* got \(2, 4, 6\)"):
        correct(Huber(), r, torch.ones(2, 4, 6, dtype=D))
    with pytest.raises(TypeError, match="J has dtype torch.float32 but r has dtype torch.float64"):
        correct(Huber(), r, torch.ones(2, 3, 6))
    with pytest.raises(ValueError, match=r"batch shapes do not broadcast: r \(2,\), J \(4,\)"):
        correct(Huber(), r, torch.ones(4, 3, 6, dtype=D))


@pytest.mark.parametrize("loss", [TrivialLoss(), Huber(), Cauchy(), GemanMcClure(), Tukey()], ids=repr)
def test_losses_check_s(loss):
    with pytest.raises(TypeError, match="s must be a torch.Tensor, got list"):
        loss.evaluate([1.0])
    with pytest.raises(TypeError, match="s must be a torch.Tensor, got str"):
        loss("x")
    with pytest.raises(TypeError, match="s must have a floating dtype"):
        loss(torch.tensor([4]))


def test_correct_is_unchanged_for_good_input():
    """The checks leave the result alone: Huber beyond its scale scales r by sqrt(rho') (the
    plain IRLS weighting where rho'' < 0), rho'(s) = a / sqrt(s)."""
    r = torch.tensor([[3.0, 4.0, 0.0]], dtype=D)  # s = 25, a = 1
    J = torch.eye(3, dtype=D).expand(1, 3, 3)
    r_new, J_new, rho = correct(Huber(1.0), r, J)
    w = math.sqrt(1.0 / 5.0)
    torch.testing.assert_close(r_new, w * r)
    torch.testing.assert_close(J_new, w * J)
    torch.testing.assert_close(rho, torch.tensor([2 * 5.0 - 1.0], dtype=D))


# ------------------------------------------------------------------ graph.factors / graph
def test_factor_indices_of_the_wrong_type():
    m = ts.SE3.identity(1, dtype=D)
    for bad in (None, "a"):
        with pytest.raises(TypeError, match=r"variables\[0\] index must be an integer index"):
            Prior("x", bad, m)
    with pytest.raises(TypeError, match=r"variables\[1\] index must be an integer index"):
        Between("x", 0, [[0], [1, 2]], m)


def test_factor_noise_checked_at_construction():
    m = ts.SE3.identity(1, dtype=D)
    with pytest.raises(TypeError, match="information must be a torch.Tensor, got str"):
        Prior("x", 0, m, information="identity")
    with pytest.raises(ValueError, match=r"information must have shape \(m, m\), .* got \(6, 5\)"):
        Prior("x", 0, m, information=torch.ones(6, 5, dtype=D))
    with pytest.raises(TypeError, match="sqrt_information must have a floating dtype"):
        Prior("x", 0, m, sqrt_information=torch.eye(6, dtype=torch.int64))
    with pytest.raises(ValueError, match=r"sqrt_information must have shape .* got \(6,\)"):
        Prior("x", 0, m, sqrt_information=torch.ones(6, dtype=D))
    Prior("x", [0, 1], ts.SE3.identity(2, dtype=D), information=torch.eye(6, dtype=D).expand(2, 6, 6))


def test_point_observation_scalar_measurement():
    with pytest.raises(ValueError, match=r"measured must have shape \(E, point_dim\) .* got \(\)"):
        PointObservation("x", 0, "p", 0, torch.tensor(1.0, dtype=D))


def test_graph_add_checks_measurement_group_dtype_and_device():
    g = FactorGraph()
    g.add_variable("x", ts.SE3.identity(3, dtype=D))
    g.add_variable("p", torch.zeros(2, 3, dtype=D))
    with pytest.raises(TypeError, match="measured is a SO3 but the variable 'x' is SE3"):
        g.add(Prior("x", 0, ts.SO3.identity(1, dtype=D)))
    with pytest.raises(TypeError, match="measured is a SE3 but the variable 'p' is a Euclidean tensor"):
        g.add(Prior("p", 0, ts.SE3.identity(1, dtype=D)))
    with pytest.raises(TypeError, match=r"data\[0\] has dtype torch.float32 but the graph's first variable"):
        g.add(Between("x", 0, 1, ts.SE3.identity(1)))
    with pytest.raises(ValueError, match=r"data\[0\] is on meta but the graph's first variable"):
        g.add(PointObservation("x", 0, "p", 0, torch.zeros(1, 3, dtype=D, device="meta")))
    assert not g.factors
    g.add(Between("x", 0, 1, ts.SE3.identity(1, dtype=D)))
    assert len(g.factors) == 1


def test_graph_size_of_an_unknown_variable():
    g = FactorGraph()
    g.add_variable("x", ts.SE3.identity(3, dtype=D))
    for query in (g.size, g.dof):
        with pytest.raises(KeyError, match=r"no variable 'y' in the graph; its variables are \['x'\]"):
            query("y")


# ------------------------------------------------------------------ g2o
def test_g2o_paths(tmp_path: Path):
    with pytest.raises(TypeError, match="path must be a str or an os.PathLike, got NoneType"):
        g2o.read_pose_graph(None)
    with pytest.raises(FileNotFoundError, match="no pose-graph file at"):
        g2o.read_pose_graph(tmp_path)
    (tmp_path / "a.g2o").write_text("EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n")
    graph = g2o.read_pose_graph(tmp_path / "a.g2o")
    with pytest.raises(TypeError, match="path must be a str or an os.PathLike, got int"):
        g2o.write_pose_graph(3, graph)
    assert graph.edges.tolist() == [[0, 1]]


def test_g2o_functions_need_a_pose_graph(tmp_path: Path):
    with pytest.raises(TypeError, match="graph must be a PoseGraph .*got str"):
        g2o.odometry_initial_guess("graph.g2o")
    with pytest.raises(TypeError, match="graph must be a PoseGraph .*got dict"):
        g2o.write_pose_graph(tmp_path / "out.g2o", {})
    assert not (tmp_path / "out.g2o").exists()


# ------------------------------------------------------------------ imu
def _recording(seconds: float) -> imu_data.ImuRecording:
    time = torch.tensor([0.0, seconds / 2, seconds], dtype=D)
    z3 = torch.zeros(3, 3, dtype=D)
    return imu_data.ImuRecording((time * 1e9).long(), time, z3, z3, torch.zeros(3, 4, dtype=D), [(0, 3)])


def test_imu_csv_path_type():
    with pytest.raises(TypeError, match="path must be a str or an os.PathLike, got int"):
        imu_data.load_ros_imu_csv(3)


def test_windows_checks_the_recording_and_the_count():
    with pytest.raises(TypeError, match="recording must be an ImuRecording, got str"):
        imu_data.windows("imu.csv", 1.0)
    with pytest.raises(ValueError, match="length must give at most"):
        imu_data.windows(_recording(2.0), 1e-320)
    assert imu_data.windows(_recording(2.0), 1.0) == [(0, 2), (1, 3)]


def test_streaming_biases_must_be_finite():
    from torchsgal.imu import StreamingPreintegration

    nan = torch.tensor([0.0, math.nan, 0.0], dtype=D)
    with pytest.raises(ValueError, match="gyro_bias must be finite"):
        StreamingPreintegration((2,), gyro_bias=nan, dtype=D)
    imu = StreamingPreintegration((2,), dtype=D)
    with pytest.raises(ValueError, match="acc_bias must be finite"):
        imu.reset(acc_bias=nan)
    StreamingPreintegration((2,), gyro_bias=nan, dtype=D, validate=False)  # validate=False: no read


def test_implied_increment_batches_and_dtypes():
    g = torch.tensor([0.0, 0.0, -9.81], dtype=D)
    with pytest.raises(ValueError, match=r"batch shapes do not broadcast: start \(2,\), end \(3,\)"):
        implied_increment(ts.SGal3.identity(2, dtype=D), ts.SGal3.identity(3, dtype=D), g)
    with pytest.raises(TypeError, match="end has dtype torch.float32 but start has dtype torch.float64"):
        implied_increment(ts.SGal3.identity(dtype=D), ts.SGal3.identity(), g)
    with pytest.raises(TypeError, match="gravity has dtype torch.float32 but start"):
        implied_increment(ts.SGal3.identity(dtype=D), ts.SGal3.identity(dtype=D), g.float())


def _preintegration(E: int):
    from torchsgal.imu import preintegrate

    z = torch.zeros(E, 4, 3, dtype=D)
    return preintegrate(z, z, 0.01, gyro_noise_density=1e-3, acc_noise_density=1e-2,
                        time_noise_density=1e-4)


def test_imu_factor_gravity_batch_and_factor_count():
    from torchsgal.imu import ImuFactor

    pre, g = _preintegration(3), torch.tensor([0.0, 0.0, -9.81], dtype=D)
    with pytest.raises(ValueError, match=r"batch shapes do not broadcast: the preintegration \(3,\), gravity \(2,\)"):
        ImuFactor("x", [0, 1, 2], [1, 2, 3], "b", 0, pre, g.expand(2, 3))
    with pytest.raises(ValueError, match="earth_rate of shape .* must broadcast to the preintegration's batch"):
        ImuFactor("x", [0, 1, 2], [1, 2, 3], "b", 0, pre, g, torch.zeros(2, 3, 3, dtype=D))
    with pytest.raises(ValueError, match=r"preintegration has batch \(3,\): .* E = 2"):
        ImuFactor("x", [0, 1], [1, 2], "b", 0, pre, g)
    assert ImuFactor("x", [0, 1, 2], [1, 2, 3], "b", 0, pre, g.expand(3, 3)).size == 3


def test_imu_residual_and_jacobians_check_their_arguments():
    from torchsgal.imu import imu_jacobians, imu_residual

    pre = _preintegration(1)
    X, b = ts.SGal3.identity(dtype=D), torch.zeros(6, dtype=D)
    good = dict(X_i=X, X_j=X, bias_i=b, delta=pre.delta, bias_jacobian=pre.bias_jacobian,
                linearization_bias=b, gravity=torch.tensor([0.0, 0.0, -9.81], dtype=D),
                earth_rate=torch.zeros(3, dtype=D))
    cases = [
        (dict(bias_i=[0.0] * 6), TypeError, "bias_i must be a torch.Tensor, got list"),
        (dict(bias_i=torch.zeros(5, dtype=D)), ValueError, r"bias_i must have shape \(\.\.\., 6\), got \(5,\)"),
        (dict(X_i="x"), TypeError, "X_i and X_j must be both SGal3 or both SE23, got str and SGal3"),
        (dict(X_j=ts.SE23.identity(dtype=D)), TypeError, "both SGal3 or both SE23, got SGal3 and SE23"),
        (dict(bias_i=torch.zeros(6)), TypeError, "bias_i has dtype torch.float32 but X_i has dtype torch.float64"),
        (dict(bias_jacobian=torch.zeros(10, 5, dtype=D)), ValueError, r"bias_jacobian must have shape \(\.\.\., 10, 6\)"),
        (dict(delta=ts.SE3.identity(dtype=D)), TypeError, "delta must be an SGal3, got SE3"),
        (dict(X_i=ts.SGal3.identity(2, dtype=D), X_j=ts.SGal3.identity(3, dtype=D)), ValueError,
         r"batch shapes do not broadcast: X_i \(2,\), X_j \(3,\)"),
    ]
    for fn in (imu_residual, imu_jacobians):
        for change, error, message in cases:
            with pytest.raises(error, match=message):
                fn(**{**good, **change})
    # the checks pass good input through: X_j predicted from X_i by the increment has r = 0
    X_j = pre.predict(X, good["gravity"])
    r = imu_residual(**{**good, "X_j": X_j})
    torch.testing.assert_close(r, torch.zeros(1, 10, dtype=D), atol=1e-12, rtol=0)


def test_gtsam_imu_converters_check_dtype_batch_and_gravity():
    pytest.importorskip("gtsam")
    from torchsgal.imu import gtsam_interop

    with pytest.raises(ValueError, match=r"gravity must be finite, got \[0.0, 0.0, nan\]"):
        gtsam_interop.to_gtsam_params(torch.tensor([0.0, 0.0, math.nan], dtype=D))
    with pytest.raises(TypeError, match="theta has dtype torch.float32 but delta_rotation has dtype torch.float64"):
        gtsam_interop.gtsam_tangent_map(torch.eye(3, dtype=D), torch.zeros(3))
    with pytest.raises(ValueError, match=r"batch shapes do not broadcast: delta_rotation \(2,\), theta \(3,\)"):
        gtsam_interop.gtsam_tangent_map(torch.eye(3, dtype=D).expand(2, 3, 3), torch.zeros(3, 3, dtype=D))
    delta = ts.SGal3.identity(dtype=D)
    with pytest.raises(TypeError, match="covariance has dtype torch.float32 but delta has dtype torch.float64"):
        gtsam_interop.to_gtsam_covariance(torch.eye(10), delta)
    with pytest.raises(TypeError, match="bias_jacobian has dtype torch.float32 but delta"):
        gtsam_interop.to_gtsam_bias_jacobian(torch.zeros(10, 6), delta)
    z = torch.zeros(2, 3, dtype=D)
    with pytest.raises(TypeError, match="dt must be a torch.Tensor, got list"):
        gtsam_interop.sensor_to_body(z, z, ts.SE3.identity(dtype=D), dt=[0.1, 0.1])
    with pytest.raises(ValueError, match=r"dt must be a number or broadcast to \(2,\), got shape \(3,\)"):
        gtsam_interop.sensor_to_body(z, z, ts.SE3.identity(dtype=D), dt=torch.ones(3, dtype=D))


def test_gtsam_pim_checks_params_and_biases():
    pytest.importorskip("gtsam")
    import gtsam

    from torchsgal.imu import gtsam_interop

    z = torch.zeros(2, 3, dtype=D)
    with pytest.raises(TypeError, match="params must be gtsam.PreintegrationParams .*got str"):
        gtsam_interop.gtsam_pim(z, z, 0.1, "params")
    params = gtsam.PreintegrationParams.MakeSharedU(9.81)
    with pytest.raises(TypeError, match="gyro_bias must be a torch.Tensor, got list"):
        gtsam_interop.gtsam_pim(z, z, 0.1, params, gyro_bias=[0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match=r"acc_bias must be None or a finite tensor \(3,\)"):
        gtsam_interop.gtsam_pim(z, z, 0.1, params, acc_bias=torch.full((3,), math.nan, dtype=D))
    with pytest.raises(TypeError, match="dt must be a torch.Tensor, got list"):
        gtsam_interop.gtsam_pim(z, z, [0.1, 0.1], params)
    with pytest.raises(ValueError, match="dt must be finite and > 0 everywhere"):
        gtsam_interop.gtsam_pim(z, z, torch.tensor([0.1, -0.1], dtype=D), params)
    pim = gtsam_interop.gtsam_pim(z, z, torch.tensor([0.1, 0.2], dtype=D), params)
    assert pim.deltaTij() == pytest.approx(0.3)


# ------------------------------------------------------------------ kinematics
@pytest.fixture(scope="module")
def panda():
    needs_robot_data()
    return robots.panda()


def test_chain_link_and_generator_types(panda):
    q = torch.zeros(7, dtype=D)
    with pytest.raises(TypeError, match="links must be a link name, a list of them or None, got 3"):
        panda.pose(q, link=3)
    with pytest.raises(TypeError, match="generator must be None or a torch.Generator, got str"):
        panda.random_configuration(2, generator="seed")


def test_ik_generator_type(panda):
    from torchsgal.kinematics.ik import inverse_kinematics

    q0 = torch.zeros(1, 7, dtype=D)
    with pytest.raises(TypeError, match="generator must be None or a torch.Generator, got int"):
        inverse_kinematics(panda, ts.SE3.identity(1, dtype=D), q0=q0, generator=0)


def test_urdf_end_link_type():
    needs_robot_data()
    with pytest.raises(TypeError, match="end_link must be a link name, a list of them or None, got 3"):
        robots.load_robot("panda", end_link=3)


def test_dh_column_not_a_sequence():
    with pytest.raises(TypeError, match=r"a \(a DH table column\) must be a sequence of numbers or a "
                                        r"1-D tensor, got NoneType"):
        dh.dh_links(None, [0.0], [0.0], [0.0], "R")
    with pytest.raises(TypeError, match=r"lower\[0\] must be a number \(inf for no limit\), got 'a'"):
        dh.dh_links([0.0], [0.0], [0.0], [0.0], "R", lower=["a"], upper=[1.0])
    with pytest.raises(TypeError, match=r"upper\[0\] must be a number .*got nan"):
        dh.dh_links([0.0], [0.0], [0.0], [0.0], "R", lower=[0.0], upper=[math.nan])
    joints, _ = dh.dh_links([0.0], [0.0], [0.0], [0.0], "R", lower=[-1.0], upper=[math.inf])
    assert (joints[0].lower, joints[0].upper) == (-1.0, math.inf)


# ------------------------------------------------------------------ load
def test_idle_cores_interval_beyond_float_range():
    with pytest.raises(ValueError, match="interval must be a finite number > 0"):
        load.idle_cores(10**400)


def test_a_non_finite_number_bias_is_refused_by_name():
    """A bias given as a number went into the increment unchecked: nan gave a NaN increment."""
    from torchsgal.imu import preintegrate

    gyro = torch.zeros(4, 3, dtype=torch.float64)
    pre = preintegrate(gyro, gyro + torch.tensor([0.0, 0.0, 9.81], dtype=torch.float64), 0.01)
    for bad in (float("nan"), float("inf")):
        with pytest.raises(ValueError, match=r"^gyro_bias must be a finite number"):
            pre.corrected(gyro_bias=bad)
        with pytest.raises(ValueError, match=r"^acc_bias must be a finite number"):
            preintegrate(gyro, gyro, 0.01, acc_bias=bad)

