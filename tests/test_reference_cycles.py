"""No workflow leaves tensors to Python's cyclic collector: reference counting frees what a call
made as soon as the caller lets go of it.  A reference cycle that holds tensors (a factor holding
a bound method of itself held the TLS solve's linearisation, 239 MB a chunk of 400 trials) keeps
them until the cyclic collector runs, which grew the study's process to 5 GB."""
from __future__ import annotations

import ast
import gc
import os
import subprocess
import sys

import pytest
import torch
from test_factor_graph import _graph, pose_graphs, rigid_fit_graph, rigid_fit_problem

import torchsgal as ts
from torchsgal import imu
from torchsgal.estimation import graph as fg
from torchsgal.estimation import study, tls
from torchsgal.uncertainty import ConcentratedGaussian

f64 = torch.float64


def _pose_graph(linear_solver):
    def run():
        _, Z, Z0, x0 = pose_graphs(B=1 if linear_solver == "sparse" else 4)
        result = fg.levenberg_marquardt(_graph(Z, Z0, x0), linear_solver=linear_solver)
        return result.marginal_covariance("x", 1)
    return run


def _implicit():
    _, Z, Z0, x0 = pose_graphs(B=4)
    M = Z.as_matrix().requires_grad_(True)
    result = fg.levenberg_marquardt(_graph(ts.SE3.from_matrix(M), Z0, x0), backward_mode="implicit")
    result.values["x"].as_matrix().sum().backward()
    return M.grad


def _robust_user_factor():
    _, p, q = rigid_fit_problem(B=4, K=20, outliers=3)
    return fg.levenberg_marquardt(rigid_fit_graph(p, q, loss=fg.Cauchy(0.1))).values["T"]


def _tls(variant):
    def run():
        cfg = study.StudyConfig(trials=8, seed=0)
        P = study.simulate(cfg).problem
        return tls.solve_sgal3(P, variant=variant, dtau0=cfg.nominal_dtau), \
            tls.solve_baseline(P, variant=variant, dtau0=cfg.nominal_dtau)
    return run


def _imu():
    gen = torch.Generator().manual_seed(0)
    gyro, acc = torch.randn(3, 20, 3, generator=gen, dtype=f64), torch.randn(3, 20, 3, generator=gen, dtype=f64)
    batch = imu.preintegrate(gyro, acc, 0.01, gyro_noise_density=1e-3, acc_noise_density=1e-2)
    stream = imu.StreamingPreintegration(3, gyro_noise_density=1e-3, acc_noise_density=1e-2, dtype=f64)
    for k in range(20):
        stream.integrate(gyro[:, k], acc[:, k], 0.01)
    return batch, stream.result()


def _groups_with_autograd():
    out = []
    for G in ts.ALL_GROUPS:
        xi = torch.randn(5, G.dof, dtype=f64, requires_grad=True)
        g = G.exp(xi)
        (g.compose(g.inverse()).log().sum() + g.act(torch.randn(5, G.point_dim, dtype=f64)).sum()).backward()
        out.append(xi.grad)
    return out


def _uncertainty():
    mean = ts.SE3.exp(torch.randn(4, 6, dtype=f64))
    gauss = ConcentratedGaussian(mean, 0.01 * torch.eye(6, dtype=f64).expand(4, 6, 6))
    return gauss.compose(gauss).act(torch.randn(4, 3, dtype=f64))


WORKFLOWS = {
    "pose graphs, block": _pose_graph("block"),
    "pose graphs, dense": _pose_graph("dense"),
    "pose graphs, sparse": _pose_graph("sparse"),
    "implicit backward": _implicit,
    "robust user factor": _robust_user_factor,
    "TLS iterated": _tls("iterated"),
    "TLS paper-style": _tls("paper"),
    "IMU": _imu,
    "groups under autograd": _groups_with_autograd,
    "Gaussians": _uncertainty,
}


def _tensors_left_to_the_collector(name: str) -> list[str]:
    """Runs a workflow twice (the first fills caches that live on purpose) and returns the
    tensors that only the cyclic collector frees from the second run."""
    run = WORKFLOWS[name]
    run()
    while gc.collect():
        pass
    gc.garbage.clear()
    gc.set_debug(gc.DEBUG_SAVEALL)
    try:
        run()
        while gc.collect():
            pass
        return [f"{tuple(o.shape)} {o.dtype}" for o in gc.garbage if isinstance(o, torch.Tensor)]
    finally:
        gc.garbage.clear()
        gc.set_debug(0)


@pytest.mark.parametrize("name", WORKFLOWS)
def test_no_tensor_is_left_to_the_cyclic_collector(name):
    """In a fresh interpreter, so that no other test's garbage (fake tensors in cycles, entries
    that a cache drops) is collected in the same pass."""
    code = (f"import sys; sys.path.insert(0, {os.path.dirname(__file__)!r}); "
            f"import test_reference_cycles as t; print(repr(t._tensors_left_to_the_collector({name!r})))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    held = ast.literal_eval(out.stdout.strip().splitlines()[-1])
    assert held == [], f"{len(held)} tensors freed only by the cyclic collector: {held[:10]}"
