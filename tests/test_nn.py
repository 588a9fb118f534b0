"""torchsgal.nn.GroupParameter: a group element trained through its right perturbation."""
from __future__ import annotations

import io
import os
import subprocess
import sys

import pytest
import torch
from torch import nn

import torchsgal as ts
from torchsgal.nn import GroupParameter, group_parameters, retract_after_step, retract_all_

F64, F32 = torch.float64, torch.float32
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BATCHES = [(), (3,), (2, 2)]


def _gen(seed):
    return torch.Generator().manual_seed(seed)


def _tol(dtype):
    return 1e-10 if dtype == F64 else 1e-5


@pytest.mark.parametrize("G", ts.ALL_GROUPS)
@pytest.mark.parametrize("batch", BATCHES)
@pytest.mark.parametrize("dtype", [F64, F32])
def test_starts_at_the_element_with_zero_delta(G, batch, dtype):
    g = G.random(batch, dtype=dtype, generator=_gen(0))
    p = GroupParameter(g)
    assert p.group is G and p.batch_shape == batch and p.delta.shape == (*batch, G.dof)
    assert p.delta.dtype == dtype and isinstance(p.delta, nn.Parameter) and p.delta.requires_grad
    assert torch.equal(p.delta, torch.zeros_like(p.delta))
    v = p()
    assert type(v) is G and torch.equal(v.as_matrix(), g.as_matrix())
    assert p.anchor.data_ptr() != g.as_matrix().data_ptr()  # a copy: the element is not shared
    assert [n for n, _ in p.named_parameters()] == ["delta"] and [n for n, _ in p.named_buffers()] == ["anchor"]


@pytest.mark.parametrize("G", ts.ALL_GROUPS)
def test_delta_gradient_is_the_right_perturbation_gradient(G):
    """d loss / d delta at delta = 0 equals the central finite difference of
    loss(anchor exp(h e_i)) (float64)."""
    g = G.random((2,), dtype=F64, generator=_gen(1))
    x = torch.randn(2, 4, G.point_dim, dtype=F64, generator=_gen(2))
    target = torch.randn(2, 4, G.point_dim, dtype=F64, generator=_gen(3))

    def loss(element):
        return ((element.act(x, point_axes=1) - target) ** 2).sum()

    p = GroupParameter(g)
    loss(p()).backward()
    h = 1e-6
    fd = torch.zeros(2, G.dof, dtype=F64)
    for b in range(2):
        for i in range(G.dof):
            e = torch.zeros(2, G.dof, dtype=F64)
            e[b, i] = h
            plus = G.from_matrix(g.as_matrix() @ G.exp(e).as_matrix())
            minus = G.from_matrix(g.as_matrix() @ G.exp(-e).as_matrix())
            fd[b, i] = (loss(plus) - loss(minus)) / (2 * h)
    torch.testing.assert_close(p.delta.grad, fd, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("G", ts.ALL_GROUPS)
@pytest.mark.parametrize("dtype", [F64, F32])
def test_retract_moves_the_anchor_and_keeps_the_value(G, dtype):
    g = G.random((3,), dtype=dtype, generator=_gen(4))
    p = GroupParameter(g)
    delta = p.delta
    with torch.no_grad():
        p.delta.copy_(0.3 * torch.randn(3, G.dof, dtype=dtype, generator=_gen(5)))
    before = p().as_matrix().detach().clone()
    # the value is g exp(delta), the product of the matrices
    torch.testing.assert_close(before, g.as_matrix() @ G.exp(p.delta.detach()).as_matrix(),
                               rtol=_tol(dtype), atol=_tol(dtype))
    assert p.retract_() is p
    assert p.delta is delta and torch.equal(p.delta, torch.zeros_like(p.delta))
    torch.testing.assert_close(p.anchor, before, rtol=_tol(dtype), atol=_tol(dtype) * 10)
    G.from_matrix(p.anchor, check=True)  # on the group


@pytest.mark.parametrize("G", [ts.SO3, ts.SE3, ts.Sim3])
def test_every_64th_retraction_puts_the_anchor_back_on_the_group(G):
    from torchsgal.nn import PROJECT_EVERY
    g = G.random((2,), dtype=F64, generator=_gen(10))
    p = GroupParameter(g)
    with torch.no_grad():
        p.anchor[..., :3, :3] *= 1 + 1e-6  # a rotation block off the group, as rounding leaves it

    def deviation():
        C = p.anchor[..., :3, :3]
        return (C.transpose(-1, -2) @ C - torch.eye(3, dtype=F64)).abs().max().item()

    assert deviation() > 1e-6
    for _ in range(PROJECT_EVERY - 1):
        p.retract_()
    assert deviation() > 1e-6  # kept as it is until the 64th
    p.retract_()
    assert deviation() < 1e-14
    torch.testing.assert_close(p.anchor, g.as_matrix(), rtol=0, atol=1e-5)


def _fit(G, optimizer_factory, steps, retract, seed=6):
    """Fits an element of G (batch 2) to exact correspondences from the identity (the action
    on points, and on velocities where G has one); returns the
    final error |log(truth^-1 x)| per element and the optimiser."""
    truth = G.exp(0.8 * torch.randn(2, G.dof, dtype=F64, generator=_gen(seed)))
    x = torch.randn(2, 12, G.point_dim, dtype=F64, generator=_gen(seed + 1))
    u = torch.randn(2, 3, 3, dtype=F64, generator=_gen(seed + 2))

    def observe(g):  # points, and for SE23 and SGal3 velocities too (SE23's points miss v)
        y = g.act(x, point_axes=1).flatten(-2)
        return torch.cat([y, g.act_velocity(u, point_axes=1).flatten(-2)], -1) if hasattr(g, "act_velocity") else y

    y = observe(truth)
    p = GroupParameter(G.identity((2,), dtype=F64))
    opt = optimizer_factory(p.parameters())
    if retract:
        retract_after_step(opt, p)
    for _ in range(steps):
        opt.zero_grad()
        ((observe(p()) - y) ** 2).sum().backward()
        opt.step()
    return p().rminus(truth).detach().norm(dim=-1), opt, p


OPTIMISERS = {
    "sgd-momentum": (lambda params: torch.optim.SGD(params, lr=0.001, momentum=0.9), 400),
    "adam": (lambda params: torch.optim.Adam(params, lr=0.03), 600),
}


@pytest.mark.parametrize("G", ts.ALL_GROUPS)
@pytest.mark.parametrize("name", list(OPTIMISERS))
def test_optimisers_converge_across_re_anchoring(G, name):
    factory, steps = OPTIMISERS[name]
    err, opt, p = _fit(G, factory, steps, retract=True)
    assert torch.equal(p.delta.detach(), torch.zeros_like(p.delta))  # re-anchored after the last step
    state = opt.state[p.delta]  # the optimiser's state was kept through the re-anchoring
    assert ("momentum_buffer" in state) if name.startswith("sgd") else (int(state["step"]) == steps)
    assert err.max() < 1e-4, err


@pytest.mark.parametrize("G", [ts.SO3, ts.SE3, ts.SGal3])
def test_float32_training(G):
    """Adam in float32: the element is found to float32 accuracy, the anchor stays on the group."""
    truth = G.exp(0.8 * torch.randn(4, G.dof, dtype=F32, generator=_gen(11)))
    x = torch.randn(4, 12, G.point_dim, dtype=F32, generator=_gen(12))
    y = truth.act(x, point_axes=1)
    p = GroupParameter(G.identity((4,), dtype=F32))
    opt = torch.optim.Adam(p.parameters(), lr=0.03)
    retract_after_step(opt, p)
    for _ in range(600):
        opt.zero_grad()
        ((p().act(x, point_axes=1) - y) ** 2).sum().backward()
        opt.step()
    assert p.anchor.dtype == F32 and p().rminus(truth).detach().abs().max() < 1e-3
    G.from_matrix(p.anchor, check=True)  # float32 membership tolerance 1e-4


@pytest.mark.parametrize("name", list(OPTIMISERS))
def test_re_anchoring_matches_plain_training_to_first_order(name):
    """Re-anchored every step or never, SGD and Adam reach the same element."""
    factory, steps = OPTIMISERS[name]
    err_r, _, p_r = _fit(ts.SE3, factory, steps, retract=True)
    err_n, _, p_n = _fit(ts.SE3, factory, steps, retract=False)
    assert p_n.delta.detach().abs().max() > 0.1  # the plain run moved delta far from zero
    assert err_r.max() < 1e-4 and err_n.max() < 1e-4
    assert p_r().rminus(p_n()).detach().abs().max() < 1e-4


def test_reset_state_drops_the_optimiser_state():
    p = GroupParameter(ts.SO3.identity((2,), dtype=F64))
    opt = torch.optim.Adam(p.parameters(), lr=0.1)
    p().log().sum().backward()
    opt.step()
    assert p.delta in opt.state
    p.retract_(opt)
    assert p.delta in opt.state  # kept by default
    p.retract_(opt, reset_state=True)
    assert p.delta not in opt.state
    opt.step()  # Adam starts the parameter's state afresh
    assert int(opt.state[p.delta]["step"]) == 1


def test_retract_after_step_hook_and_its_removal():
    p = GroupParameter(ts.SE3.identity((2,), dtype=F64))
    opt = torch.optim.SGD(p.parameters(), lr=0.1)
    handle = retract_after_step(opt, p)
    p().log().pow(2).sum().backward()
    p.delta.grad.fill_(1.0)
    opt.step()
    assert torch.equal(p.delta.detach(), torch.zeros(2, 6, dtype=F64))
    want = ts.SE3.exp(torch.full((2, 6), -0.1, dtype=F64))
    torch.testing.assert_close(p.anchor, want.as_matrix(), rtol=1e-12, atol=1e-12)
    handle.remove()
    opt.step()
    torch.testing.assert_close(p.delta.detach(), torch.full((2, 6), -0.1, dtype=F64), rtol=0, atol=0)


def test_modules_holding_several_group_parameters():
    class Rig(nn.Module):
        def __init__(self):
            super().__init__()
            self.body = GroupParameter(ts.SE3.identity((4,), dtype=F64))
            self.calib = GroupParameter(ts.SO3.identity(dtype=F64))
            self.gain = nn.Parameter(torch.ones(3, dtype=F64))

    rig = Rig()
    assert list(group_parameters(rig)) == [rig.body, rig.calib]
    assert {n for n, _ in rig.named_parameters()} == {"body.delta", "calib.delta", "gain"}
    with torch.no_grad():
        rig.body.delta.fill_(0.1)
        rig.calib.delta.fill_(-0.2)
    want_body, want_calib = rig.body().as_matrix().detach(), rig.calib().as_matrix().detach()
    assert retract_all_(rig) is rig
    assert not rig.body.delta.detach().any() and not rig.calib.delta.detach().any()
    torch.testing.assert_close(rig.body.anchor, want_body, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(rig.calib.anchor, want_calib, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("G", ts.ALL_GROUPS)
@pytest.mark.parametrize("dtype", [F64, F32])
def test_state_dict_round_trip(G, dtype):
    p = GroupParameter(G.random((2, 3), dtype=dtype, generator=_gen(7)))
    with torch.no_grad():
        p.delta.copy_(0.1 * torch.randn(2, 3, G.dof, dtype=dtype, generator=_gen(8)))
    buffer = io.BytesIO()
    torch.save(p.state_dict(), buffer)
    buffer.seek(0)
    q = GroupParameter(G.identity((2, 3), dtype=dtype))
    q.load_state_dict(torch.load(buffer))  # weights_only=True, torch's default
    assert torch.equal(q.anchor, p.anchor) and torch.equal(q.delta, p.delta)
    assert torch.equal(q().as_matrix(), p().as_matrix())
    with pytest.raises(RuntimeError, match="size mismatch"):
        GroupParameter(G.identity((3,), dtype=dtype)).load_state_dict(p.state_dict())


def test_a_state_dict_of_another_group_or_off_the_group_is_refused():
    """SE(2)'s and SO(3)'s anchors are both 3 x 3: torch's size checks pass, the group's
    membership test does not; nor does a spoiled (NaN or arbitrary) anchor, and the module keeps
    its own.  A float32 state loads into a float64 module (checked at float32's tolerance)."""
    so3 = GroupParameter(ts.SO3.identity(3, dtype=F64))
    before = so3.anchor.clone()
    delta = torch.zeros(3, 3, dtype=F64)
    for state in (GroupParameter(ts.SE2.random((3,), dtype=F64, generator=_gen(10))).state_dict(),
                  {"anchor": torch.full((3, 3, 3), 7.0, dtype=F64), "delta": delta},
                  {"anchor": torch.full((3, 3, 3), float("nan"), dtype=F64), "delta": delta}):
        with pytest.raises(ValueError, match="anchor is not an element of SO3"):
            so3.load_state_dict(state)
        assert torch.equal(so3.anchor, before)
    single = GroupParameter(ts.SO3.random((3,), dtype=F32, generator=_gen(11)))
    so3.load_state_dict(single.state_dict())
    assert torch.equal(so3.anchor, single.anchor.double())


def test_a_state_dict_with_a_non_finite_delta_is_refused():
    """A NaN or inf delta is refused by key, and the module keeps its own delta (unchecked, it
    would load without a word and make the value NaN)."""
    p = GroupParameter(ts.SE3.identity((2,), dtype=F64))
    holder = nn.Module()
    holder.pose = p
    for bad in (float("nan"), float("inf"), -float("inf")):
        delta = torch.zeros(2, 6, dtype=F64)
        delta[1, 4] = bad
        with pytest.raises(ValueError, match=r"^delta must be finite .*found 1 non-finite entries of 12$"):
            p.load_state_dict({"anchor": torch.eye(4, dtype=F64).expand(2, 4, 4), "delta": delta})
        with pytest.raises(ValueError, match=r"^pose\.delta must be finite"):
            holder.load_state_dict({"pose.anchor": torch.eye(4, dtype=F64).expand(2, 4, 4),
                                    "pose.delta": delta})
        assert torch.equal(p.delta.detach(), torch.zeros(2, 6, dtype=F64))
    finite = torch.full((2, 6), 0.25, dtype=F64)
    p.load_state_dict({"anchor": torch.eye(4, dtype=F64).expand(2, 4, 4), "delta": finite})
    assert torch.equal(p.delta.detach(), finite)


def test_module_to_converts_anchor_and_delta():
    p = GroupParameter(ts.SGal3.random((2,), dtype=F32, generator=_gen(9))).to(F64)
    assert p.anchor.dtype == F64 and p.delta.dtype == F64 and p().dtype == F64
    assert "group=SGal3, batch_shape=(2,), dtype=torch.float64" in repr(p)


def test_errors_name_the_argument():
    with pytest.raises(TypeError, match="element must be a group element .*got Tensor"):
        GroupParameter(torch.eye(4))
    with pytest.raises(TypeError, match="requires_grad must be True or False"):
        GroupParameter(ts.SE3.identity(), requires_grad=1)
    p = GroupParameter(ts.SE3.identity())
    with pytest.raises(TypeError, match="optimizer must be None or a torch.optim.Optimizer, got list"):
        p.retract_([])
    with pytest.raises(ValueError, match="reset_state=True needs the optimizer"):
        p.retract_(reset_state=True)
    with pytest.raises(TypeError, match="optimizer must be a torch.optim.Optimizer, got GroupParameter"):
        retract_after_step(p, p)
    with pytest.raises(TypeError, match="module must be a torch.nn.Module, got SE3"):
        list(group_parameters(ts.SE3.identity()))


def test_frozen_parameter():
    p = GroupParameter(ts.SO3.identity(), requires_grad=False)
    assert not p.delta.requires_grad and not p().as_matrix().requires_grad


def test_example_runs():
    out = subprocess.run([sys.executable, "examples/train_manifold_parameter.py", "--poses", "4", "--points", "16",
                          "--steps", "300"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    last = [line for line in out.stdout.splitlines() if line.startswith("final rot_err_deg=")]
    assert last, out.stdout
    fields = dict(kv.split("=") for kv in last[0].split()[1:])
    # Adam reaches the closed-form least squares; its error to the truth is the noise's
    assert float(fields["kabsch_gap"]) < 1e-3, out.stdout
    assert float(fields["rot_err_deg"]) < 1.0 and float(fields["trans_err"]) < 0.05, out.stdout


@pytest.mark.parametrize("G", [ts.SO3, ts.SE3, ts.SGal3])
def test_a_module_converted_to_float64_reloads_its_own_state(G):
    """``module.to(torch.float64)`` of a float32 GroupParameter holds float32-rounded anchors in
    float64 tensors (|C^T C - I| about 1e-7): its own state dict must load back, into itself
    and into a fresh float64 module, unchanged."""
    p = GroupParameter(G.random((50,), dtype=F32, generator=_gen(12))).to(F64)
    state = {k: v.clone() for k, v in p.state_dict().items()}
    p.load_state_dict(state)
    assert torch.equal(p.anchor, state["anchor"])
    q = GroupParameter(G.identity((50,), dtype=F64))
    q.load_state_dict(state)
    assert torch.equal(q.anchor, state["anchor"]) and torch.equal(q.delta, state["delta"])
