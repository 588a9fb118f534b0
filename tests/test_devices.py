"""Device-generic code, checked on the ``meta`` device (no GPU is lent to CI).

A meta tensor has a shape, a dtype and a device but no data, so running the library on meta
inputs checks two things a CUDA run would, without a GPU:

* every constant is made on the input's device: an operation mixing a meta tensor with a CPU
  tensor of one or more dimensions raises, as it would between CUDA and CPU (0-d CPU tensors are
  allowed by both, as scalars);
* nothing reads tensor values on the host: ``.item()``, ``bool(t)``, ``float(t)`` or a
  data-dependent shape raise on meta, where on CUDA they would be a silent device-to-host sync.

Each case also checks the output's shape, dtype and device.  What meta lets pass, a
host-to-device copy (``torch.tensor(list, device=d)``, a CPU constant moved with ``.to(d)``) or
a linalg error check, the host-sync sniffer at the end of this file sees at torch's dispatch
level: the group operations and ``imu.preintegrate`` must make none.  The only host syncs the library
makes on purpose (input validation such as ``from_matrix(check=True)`` and the estimation
solvers, which run on CPU tensors) are left out, and one test shows that such a sync is caught.
The uncertainty package's covariance checks and the convergence test of
``ConcentratedGaussian.fuse`` are skipped on 'meta' (there is no data to read), so they run here
with their defaults.
"""
from __future__ import annotations

import pytest
import torch
from host_syncs import HostSyncs

import torchsgal as ts
from torchsgal import imu
from torchsgal import kinematics as kin
from torchsgal import regression as reg
from torchsgal.uncertainty import ConcentratedGaussian, fuse_event

META = torch.device("meta")
IDS = [G.__name__ for G in ts.ALL_GROUPS]
BATCH = (4, 2)


def _meta(*shape, dtype=torch.float32) -> torch.Tensor:
    return torch.empty(shape, dtype=dtype, device=META)


def _check(out, shape, dtype=torch.float32):
    assert isinstance(out, torch.Tensor), type(out)
    assert out.device == META, f"output on {out.device}, not on the inputs' device"
    assert out.dtype == dtype, f"output dtype {out.dtype}, expected {dtype}"
    assert tuple(out.shape) == tuple(shape), f"output shape {tuple(out.shape)}, expected {shape}"


def test_meta_catches_host_syncs_and_cpu_constants():
    """The premise of this file: meta raises where CUDA would sync or mix devices."""
    x = _meta(3)
    with pytest.raises(RuntimeError):
        x.sum().item()
    with pytest.raises(RuntimeError):
        bool((x > 0).all())
    with pytest.raises(RuntimeError):
        x + torch.ones(3)  # a CPU constant of one dimension
    _check(x + torch.tensor(1.0), (3,))  # a 0-d CPU tensor is a scalar, allowed on CUDA too
    # The group membership check reads values (one sync on CUDA, by design); on meta, which has
    # none, it is skipped like the uncertainty module's value checks, and only shapes are checked.
    assert ts.SO3.from_matrix(torch.eye(3, device=META), check=True).device == META
    with pytest.raises(ValueError, match=r"matrix must have shape"):
        ts.SO3.from_matrix(torch.eye(4, device=META), check=True)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["float64", "float32"])
@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=IDS)
def test_group_api_on_device(G, dtype):
    n, dof = G.matrix_dim, G.dof
    xi = _meta(*BATCH, dof, dtype=dtype)
    g, h = G.exp(xi), G.random(BATCH, dtype=dtype, device=META)
    mat = (*BATCH, n, n)
    for name, out, shape in [
        ("exp", g.as_matrix(), mat),
        ("log", g.log(), (*BATCH, dof)),
        ("identity", G.identity(BATCH, dtype=dtype, device=META).as_matrix(), mat),
        ("random", h.as_matrix(), mat),
        ("compose", (g @ h).as_matrix(), mat),
        ("inverse", g.inverse().as_matrix(), mat),
        ("adjoint", g.adjoint(), (*BATCH, dof, dof)),
        ("rplus", g.rplus(xi).as_matrix(), mat),
        ("lplus", g.lplus(xi).as_matrix(), mat),
        ("rminus", g.rminus(h), (*BATCH, dof)),
        ("lminus", g.lminus(h), (*BATCH, dof)),
        ("between", g.between(h).as_matrix(), mat),
        ("interpolate", g.interpolate(h, _meta(*BATCH, dtype=dtype)).as_matrix(), mat),
        ("rotation", g.rotation(), (*BATCH, G.rotation_dim, G.rotation_dim)),
        ("act", g.act(_meta(*BATCH, G.point_dim, dtype=dtype)), (*BATCH, G.point_dim)),
        ("act_direction", g.act_direction(_meta(*BATCH, G.rotation_dim, dtype=dtype)),
         (*BATCH, G.rotation_dim)),
        ("hat", G.hat(xi), mat),
        ("vee", G.vee(G.hat(xi)), (*BATCH, dof)),
        ("ad", G.ad(xi), (*BATCH, dof, dof)),
        ("jl", G.jl(xi), (*BATCH, dof, dof)),
        ("jr", G.jr(xi), (*BATCH, dof, dof)),
        ("jl_inv", G.jl_inv(xi), (*BATCH, dof, dof)),
        ("jr_inv", G.jr_inv(xi), (*BATCH, dof, dof)),
    ]:
        try:
            _check(out, shape, dtype)
        except AssertionError as err:
            raise AssertionError(f"{G.__name__}.{name}: {err}") from None
    if hasattr(g, "act_velocity"):
        _check(g.act_velocity(_meta(*BATCH, 3, dtype=dtype)), (*BATCH, 3), dtype)


@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=IDS)
def test_custom_autograd_on_device(G):
    """The custom backward and forward mode of exp and log (their closed-form Jacobians)."""
    xi = _meta(*BATCH, G.dof).requires_grad_()
    (grad,) = torch.autograd.grad(G.exp(xi).log().sum(), xi)
    _check(grad, (*BATCH, G.dof))
    _, tangent = torch.func.jvp(lambda x: G.exp(x).log(), (xi.detach(),), (_meta(*BATCH, G.dof),))
    _check(tangent, (*BATCH, G.dof))


@pytest.mark.parametrize("per_axis", [False, True], ids=["isotropic", "per_axis"])
def test_imu_preintegration_on_device(per_axis):
    windows, samples = 3, 7
    gyro, acc = _meta(windows, samples, 3), _meta(windows, samples, 3)
    dt = _meta(windows, samples)
    density = _meta(3) if per_axis else 1e-3
    pre = imu.preintegrate(gyro, acc, dt, gyro_bias=_meta(windows, 3),
                           gyro_noise_density=density, acc_noise_density=1e-2)
    _check(pre.delta.as_matrix(), (windows, 5, 5))
    _check(pre.covariance, (windows, 10, 10))
    _check(pre.bias_jacobian, (windows, 10, 6))
    start = ts.SGal3.identity((windows,), device=META)
    gravity = imu.gravity_vector(device=META)
    earth = imu.earth_rate_vector(0.8, device=META)
    _check(pre.predict(start, gravity, earth, gyro_bias=_meta(3)).as_matrix(), (windows, 5, 5))
    _check(pre.predict_covariance(start, _meta(windows, 10, 10), gravity, earth), (windows, 10, 10))
    _check(imu.preintegrate(gyro, acc, dt, covariance=False, bias_jacobian=False).delta.as_matrix(),
           (windows, 5, 5))


@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=IDS)
def test_concentrated_gaussian_on_device(G):
    dof = G.dof
    d = ConcentratedGaussian(G.random(BATCH, device=META), _meta(*BATCH, dof, dof))
    _check(d.sample((5,)).as_matrix(), (5, *BATCH, G.matrix_dim, G.matrix_dim))
    _check(d.mahalanobis(d.mean), BATCH)
    _check(d.log_prob(d.mean), BATCH)
    for moved in (d.to_side("left"), d.inverse(), d.compose(d), d.between(d)):
        _check(moved.covariance, (*BATCH, dof, dof))
    _check(d.compose(d, cross_covariance=_meta(*BATCH, dof, dof)).covariance, (*BATCH, dof, dof))
    k = G.rotation_dim
    acted = d.act_direction(_meta(*BATCH, k), _meta(*BATCH, k, k))
    _check(acted.mean, (*BATCH, k))
    _check(acted.covariance, (*BATCH, k, k))
    if G is ts.SGal3:  # fusion: one group (meta dispatch is slow; the code is generic)
        _check(d.fuse(d, iterations=1).covariance, (*BATCH, dof, dof))
        post = fuse_event(d, _meta(*BATCH, 4), _meta(*BATCH, 4, 4))
        _check(post.covariance, (*BATCH, dof, dof))
        _check(post.mean.as_matrix(), (*BATCH, 5, 5))


@pytest.mark.parametrize("robot", [kin.ur5, kin.iiwa7, kin.scara], ids=["ur5", "iiwa7", "scara"])
def test_gdh_chain_on_device(robot):
    chain = robot(dtype=torch.float32, device=META)
    q = _meta(*BATCH, chain.n_joints)
    state = chain.forward(q, q)
    _check(state.pose, (*BATCH, 4, 4))
    _check(chain.link_transforms(q, q).as_matrix(), (*BATCH, chain.n_joints, 5, 5))
    for out in (state.linear_velocity, state.angular_velocity, *chain.acceleration(q, q, q)):
        _check(out, (*BATCH, 3))


@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=IDS)
def test_regression_flows_on_device(G):
    tau = _meta(6)
    Phi, X = reg.geodesic_flow(G, _meta(*BATCH, G.dof), tau, _meta(G.dof))
    _check(Phi, (*BATCH, 6, G.matrix_dim, G.matrix_dim))
    _check(X, (*BATCH, 6, G.dof))
    _check(reg.log_distance(G.random(BATCH, device=META), G.random(BATCH, device=META)), BATCH)


# ------------------------------------------------------------------------ host-sync sniffer
# Meta raises on value reads, but a host-to-device copy (torch.tensor(list, device=d), a CPU
# constant moved with .to(d)) or a linalg error check passes on meta silently, where on CUDA it
# stalls the host.  This sniffer sees them at torch's dispatch level and fails the hot paths.
# The recorder: tests/host_syncs.py (shared with test_uncertainty's read counts).


def _assert_no_host_sync(cases, dtype=torch.float32) -> None:
    """Each ``(label, fn)`` of ``cases`` makes no host sync.  The one constant cache of the
    library, functional.numerics' series coefficients per (order, dtype, device), is filled
    first: it copies its constants to the device on their first use only, as designed."""
    from torchsgal.functional import numerics

    for order in range(1, numerics.MAX_ORDER + 1):
        numerics.series_coefficients(_meta(1, dtype=dtype), order)
    for label, fn in cases:
        with HostSyncs() as sniffer:
            fn()
        assert not sniffer.events, f"{label}: host syncs {sniffer.events}"


def test_host_sync_sniffer_catches_syncs():
    """The sniffer's premise: each kind of sync it looks for is seen, on meta too."""
    cases = [
        ("value read", lambda: _meta(3).sum().item()),  # raises on meta after being seen
        ("value read (tolist)", lambda: torch.ones(3).tolist()),  # not dispatched on CPU
        ("linalg error check", lambda: torch.linalg.cholesky(_meta(3, 3))),
        ("host-to-device copy (tensor", lambda: torch.tensor([1.0, 2.0], device=META)),
        ("host-to-device copy (as_tensor", lambda: torch.as_tensor(2.0, device=META)),
        ("host-to-device copy (new_tensor", lambda: _meta(2).new_tensor([1.0, 2.0])),
        ("host-to-device copy (.to)", lambda: torch.ones(3).to(META)),
        ("host-to-device copy (copy_)", lambda: _meta(3).copy_(torch.ones(3))),
        ("host-to-device copy (copy_)", lambda: _meta(3).__setitem__(0, torch.tensor(1.0))),
        ("host-to-device copy (setitem of a number", lambda: _meta(3).__setitem__(0, 1.0)),
        ("host-to-device copy (setitem of a number", lambda: _meta(2, 3).__setitem__((..., 1, 2), 1.0)),
    ]
    for what, fn in cases:
        with HostSyncs() as sniffer:
            try:
                fn()
            except (RuntimeError, NotImplementedError):
                pass
        assert any(w.startswith(what) for w, _ in sniffer.events), (what, sniffer.events)
    with HostSyncs() as sniffer:  # what is not a sync: fills, scalars, factories on the device
        x = torch.zeros(3, device=META)
        x[0:2] = 1.0
        _check(x * 2.0 + torch.tensor(1.0) + torch.full((3,), 0.5, device=META), (3,))
    assert not sniffer.events, sniffer.events


@pytest.mark.parametrize("batch", [BATCH, ()], ids=["batched", "unbatched"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["float64", "float32"])
@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=IDS)
def test_group_hot_paths_make_no_host_sync(G, dtype, batch):
    """The group operations, their Jacobians, interpolation and exp/log's custom backward (which
    runs on meta) make no host sync, batched or not (x[..., i, j] = 1.0 copies on an unbatched
    tensor only).  Left out on purpose: from_matrix(check=True), a documented entry check that
    reads its measures in one sync (and skips it on meta)."""
    xi = _meta(*batch, G.dof, dtype=dtype)
    g, h = G.exp(xi), G.random(batch, dtype=dtype, device=META)

    def backward():
        x = xi.clone().requires_grad_()
        (grad,) = torch.autograd.grad(G.exp(x).log().sum(), x)
        _check(grad, (*batch, G.dof), dtype)

    _assert_no_host_sync([(f"{G.__name__}.{name} ({dtype})", fn) for name, fn in [
        ("exp", lambda: G.exp(xi)), ("log", g.log), ("compose", lambda: g @ h),
        ("inverse", g.inverse), ("act", lambda: g.act(_meta(*batch, G.point_dim, dtype=dtype))),
        ("adjoint", g.adjoint), ("jl", lambda: G.jl(xi)), ("jr", lambda: G.jr(xi)),
        ("jl_inv", lambda: G.jl_inv(xi)), ("jr_inv", lambda: G.jr_inv(xi)),
        ("interpolate(number)", lambda: g.interpolate(h, 0.3)),
        ("interpolate(tensor)", lambda: g.interpolate(h, _meta(*batch, dtype=dtype))),
        ("exp/log backward", backward),
    ]], dtype)


@pytest.mark.parametrize("per_axis", [False, True], ids=["isotropic", "per_axis"])
def test_imu_preintegration_makes_no_host_sync(per_axis):
    """preintegrate with covariance and bias Jacobians (number densities are used as Python
    floats, constants are filled on the device), and the prediction built on it.  CUDA takes
    this plain path too (the fast path is CPU only)."""
    windows, samples = 3, 7
    gyro, acc, dt = _meta(windows, samples, 3), _meta(windows, samples, 3), _meta(windows, samples)
    density = _meta(2, 1, 3) if per_axis else 1e-3
    kw = dict(gyro_bias=_meta(windows, 3), acc_bias=0.1, gyro_noise_density=density,
              acc_noise_density=1e-2, time_noise_density=1e-4)
    batch = (2, windows) if per_axis else (windows,)

    def run():
        pre = imu.preintegrate(gyro, acc, dt, **kw)
        _check(pre.covariance, (*batch, 10, 10))
        _check(pre.bias_jacobian, (*batch, 10, 6))
        return pre

    pre = run()
    start, gravity, earth = ts.SGal3.identity((windows,), device=META), _meta(3), _meta(3)
    _assert_no_host_sync([
        ("imu.preintegrate", run),
        ("imu.preintegrate (increment only)",
         lambda: imu.preintegrate(gyro, acc, dt, covariance=False, bias_jacobian=False)),
        ("Preintegration.predict", lambda: pre.predict(start, gravity, earth, gyro_bias=_meta(3))),
        ("gravity_vector", lambda: imu.gravity_vector(device=META)),
        ("earth_rate_vector", lambda: imu.earth_rate_vector(0.8, frame="ned", device=META)),
        ("Preintegration.predict_covariance",
         lambda: pre.predict_covariance(start, _meta(windows, 10, 10), gravity, earth)),
    ])


@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=IDS)
def test_gaussian_propagation_makes_no_host_sync(G):
    """Propagation of concentrated Gaussians, on either side (the side change inverts Ad in
    closed form; it used linalg.inv, a linalg error check).  Left out on purpose: the covariance
    checks (one documented read, skipped on meta anyway) and sample/log_prob/mahalanobis, whose
    Cholesky factorisation raises for a covariance that is not positive definite."""
    dof = G.dof
    d = ConcentratedGaussian(G.random(BATCH, device=META), _meta(*BATCH, dof, dof))
    left = ConcentratedGaussian(G.random(BATCH, device=META), _meta(*BATCH, dof, dof), side="left")
    k = G.rotation_dim
    _assert_no_host_sync([(f"{G.__name__} Gaussian {name}", fn) for name, fn in [
        ("to_side", lambda: d.to_side("left")), ("inverse", d.inverse),
        ("compose", lambda: d.compose(d)), ("compose(left)", lambda: left.compose(left)),
        ("compose(second_order)", lambda: d.compose(d, second_order=True)),
        ("compose(cross_covariance)", lambda: d.compose(d, cross_covariance=_meta(*BATCH, dof, dof))),
        ("between", lambda: d.between(left)),
        ("act_direction", lambda: d.act_direction(_meta(*BATCH, k), _meta(*BATCH, k, k), validate=False)),
    ]])


@pytest.mark.parametrize("batch", [BATCH, ()], ids=["batched", "unbatched"])
@pytest.mark.parametrize("robot", [kin.ur5, kin.iiwa7, kin.scara], ids=["ur5", "iiwa7", "scara"])
def test_gdh_chain_makes_no_host_sync(robot, batch):
    """Forward kinematics, velocities and accelerations of a chain built on the device (its
    table's finiteness check at construction is the one documented read, skipped on meta)."""
    chain = robot(dtype=torch.float32, device=META)
    q = _meta(*batch, chain.n_joints)
    _assert_no_host_sync([(f"{robot.__name__} {name}", fn) for name, fn in [
        ("forward", lambda: chain.forward(q, q)), ("forward(q, q).pose", lambda: chain.forward(q, q).pose),
        ("acceleration", lambda: chain.acceleration(q, q, q)),
        ("link_transforms", lambda: chain.link_transforms(q, q)),
    ]])


@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=IDS)
def test_regression_flows_make_no_host_sync(G):
    """The regression curves' flows and log distance (the fits themselves run the solvers,
    whose stop tests read values by design)."""
    tau = _meta(6)
    a, b = G.random(BATCH, device=META), G.random(BATCH, device=META)
    _assert_no_host_sync([(f"{G.__name__} {name}", fn) for name, fn in [
        ("geodesic_flow", lambda: reg.geodesic_flow(G, _meta(*BATCH, G.dof), tau, _meta(G.dof))),
        ("log_distance", lambda: reg.log_distance(a, b)),
        ("log_distance(weights)", lambda: reg.log_distance(a, b, _meta(G.dof))),
    ]])


def test_estimation_covariance_checks_on_device():
    """The estimators' covariance checks read values (one read per block, measures and the
    diagonal test together): skipped on meta, as the Gaussians' are, where a block is then
    factorised as a full one."""
    from torchsgal.estimation import study, tls
    from torchsgal.estimation.gauss_helmert import _CovarianceBlocks

    f64 = torch.float64
    S = study.paper_covariance()
    F = ts.SGal3.random((2, 3), dtype=f64, device=META)
    problem = tls.TLSProblem(F, F, S.to(META), S.to(META))
    assert problem.cov_a.device == META
    blocks = _CovarianceBlocks((S.to(META), _meta(3, 3, dtype=f64)))
    assert blocks.diagonal == [False, False]
    _check(blocks.factors[0], (10, 10), f64)
    F = ts.SGal3.random((2, 3), dtype=f64)
    with HostSyncs() as reads:
        tls.TLSProblem(F, F, S, S)
    assert len(reads.events) == 2, reads.events  # cov_a and cov_b, one read each
    with HostSyncs() as reads:
        blocks = _CovarianceBlocks((S, torch.eye(3, dtype=f64)))
    assert len(reads.events) == 2 and blocks.diagonal == [S.diagonal().diag().equal(S), True]
