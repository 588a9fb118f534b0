"""Input checks of the functional layer (torchsgal.functional.*): every public function refuses
bad input at once with a message naming the argument, the expectation and what was given
(CONVENTIONS.md, Errors), instead of a raw torch error, garbage-shaped output or a silent
dtype promotion."""
from __future__ import annotations

import numpy as np
import pytest
import torch

import torchsgal.functional as TF
from torchsgal.functional import checks

D = torch.float64
MODS = list(TF.GROUPS.values())
IDS = list(TF.GROUPS)


def _acts(mod):
    """(function, argument name, size of the vector) for every action of the group."""
    point = 4 if mod is TF.sgal3 else (2 if mod in (TF.so2, TF.se2) else 3)
    rot = 2 if mod in (TF.so2, TF.se2) else 3
    out = [(mod.act, "e" if mod is TF.sgal3 else "p", point), (mod.act_direction, "d", rot)]
    if hasattr(mod, "act_velocity"):
        out.append((mod.act_velocity, "u", 3))
    return out


@pytest.mark.parametrize("mod", MODS, ids=IDS)
def test_act_checks_the_matrix(mod):
    n = mod.MATRIX_DIM
    M = mod.random((4,), D, "cpu")
    for f, name, k in _acts(mod):
        x = torch.randn(4, k, dtype=D)
        assert f(M, x).shape == (4, k)
        with pytest.raises(ValueError, match=rf"g must have shape \(\.\.\., {n}, {n}\), got \(4, {n + 1}, {n + 1}\)"):
            f(torch.randn(4, n + 1, n + 1, dtype=D), x)
        with pytest.raises(ValueError, match=rf"g must have shape \(\.\.\., {n}, {n}\), got \(4, {n}, 7\)"):
            f(torch.randn(4, n, 7, dtype=D), x)
        with pytest.raises(ValueError, match=r"g must have shape .*, got \(3,\)"):
            f(torch.randn(3, dtype=D), x)
        with pytest.raises(ValueError, match=r"g must have shape .*, got \(\)"):
            f(torch.tensor(1.0, dtype=D), x)
        with pytest.raises(TypeError, match=r"g must be a torch.Tensor, got list"):
            f(M[0].tolist(), x)
        with pytest.raises(TypeError, match=r"g must have a floating dtype .* got torch.int64"):
            f(M.long(), x)
        with pytest.raises(ValueError, match=rf"{name} must have shape \(\.\.\., {k}\)"):
            f(M, torch.randn(4, k + 1, dtype=D))


def test_sgal3_packed_checks():
    F = TF.sgal3
    P = F.exp_packed(torch.randn(3, 10, dtype=D))
    with pytest.raises(ValueError, match=r"batch shapes do not broadcast: P1 \(3,\), P2 \(2,\)"):
        F.compose_packed(P, F.exp_packed(torch.randn(2, 10, dtype=D)))
    with pytest.raises(ValueError, match=r"P2 is on meta but P1 is on cpu"):
        F.compose_packed(P, P.to("meta"))
    with pytest.raises(TypeError, match=r"P2 has dtype torch.float32 but P1 has dtype torch.float64"):
        F.compose_packed(P, P.float())
    for bad in (torch.int64, torch.float16):
        with pytest.raises(TypeError, match=rf"P1 must have a floating dtype .* got {bad}"):
            F.compose_packed(P.to(bad), P.to(bad))
        with pytest.raises(TypeError, match=rf"P must have a floating dtype .* got {bad}"):
            F.unpack(P.to(bad))
        with pytest.raises(TypeError, match=rf"like must have a floating dtype .* got {bad}"):
            F.packed_identity(P.to(bad))
    with pytest.raises(TypeError, match=r"P must be a torch.Tensor, got list"):
        F.unpack(P.tolist())
    # broadcasting batches still work: (16, 3) with (16, 1)
    assert F.compose_packed(P, P[:, :1]).shape == (16, 3)


def _parts(mod):
    """(names, trailing shapes) of from_components' arguments."""
    k = 2 if mod in (TF.so2, TF.se2) else 3
    return {
        TF.so2: ("C",), TF.so3: ("C",), TF.se2: ("C", "r"), TF.se3: ("C", "r"), TF.se23: ("C", "v", "r"),
        TF.sgal3: ("C", "v", "r", "tau"), TF.sim3: ("C", "r", "s"),
    }[mod], k


@pytest.mark.parametrize("mod", MODS, ids=IDS)
def test_components_and_from_components_check(mod):
    n = mod.MATRIX_DIM
    M = mod.random((4,), D, "cpu", torch.Generator().manual_seed(3))
    parts = mod.components(M)
    if mod is TF.sim3:  # Sim3 stores 1/s: the round trip through s is exact up to one rounding
        np.testing.assert_allclose(mod.from_components(*parts).numpy(), M.numpy(), rtol=2.3e-16, atol=0)
    else:
        assert torch.equal(mod.from_components(*parts), M)
    with pytest.raises(ValueError, match=rf"M must have shape \(\.\.\., {n}, {n}\), got \(3,\)"):
        mod.components(torch.randn(3, dtype=D))
    with pytest.raises(TypeError, match=r"M must have a floating dtype"):
        mod.components(M.long())
    names, k = _parts(mod)
    with pytest.raises(ValueError, match=rf"C must have shape \(\.\.\., {k}, {k}\), got \({k + 1}, {k + 1}\)"):
        mod.from_components(torch.eye(k + 1, dtype=D), *parts[1:])
    with pytest.raises(TypeError, match=r"C must have a floating dtype .* got torch.int64"):
        mod.from_components(parts[0].long(), *parts[1:])
    if len(parts) == 1:
        return
    with pytest.raises(ValueError, match=rf"{names[1]} must have shape \(\.\.\., {k}\), got \(4, {k + 1}\)"):
        mod.from_components(parts[0], torch.zeros(4, k + 1, dtype=D), *parts[2:])
    with pytest.raises(TypeError, match=rf"{names[1]} has dtype torch.float32 but C has dtype torch.float64"):
        mod.from_components(parts[0], parts[1].float(), *parts[2:])
    with pytest.raises(ValueError, match=rf"{names[-1]} is on meta but C is on cpu"):
        mod.from_components(*parts[:-1], parts[-1].to("meta"))
    with pytest.raises(ValueError, match=rf"batch shapes do not broadcast: C \(4,\), {names[1]} \(3,\)"):
        mod.from_components(parts[0], parts[1][:3], *parts[2:])
    # batches broadcast: one rotation for four of everything else
    assert torch.equal(mod.from_components(parts[0][:1], *parts[1:])[1:], mod.from_components(parts[0][0].expand(3, k, k), *(p[1:] for p in parts[1:])))


@pytest.mark.parametrize("mod", MODS, ids=IDS)
def test_backward_parts_check(mod):
    """The public jl_tmv, jl_inv_tmv, exp_pullback and log_pullback check their input; they
    agree with the unchecked versions the backward passes use, and with J_l^T w."""
    n, dof = mod.MATRIX_DIM, mod.DOF
    gen = torch.Generator().manual_seed(42)
    xi = 0.5 * torch.randn(4, dof, dtype=D, generator=gen)
    w = torch.randn(4, dof, dtype=D, generator=gen)
    M = mod.exp(xi)
    G = torch.randn(4, n, n, dtype=D, generator=gen)
    want = (mod.jl(xi).transpose(-1, -2) @ w.unsqueeze(-1)).squeeze(-1)
    torch.testing.assert_close(mod.jl_tmv(xi, w), want)
    torch.testing.assert_close(mod.jl_inv_tmv(xi, want), w)
    assert torch.equal(mod.exp_pullback(M, G), mod._exp_pullback(M, G))
    assert torch.equal(mod.log_pullback(M, w), mod._log_pullback(M, w))
    for f, a, an, b, bn in ((mod.jl_tmv, xi, "xi", w, "w"), (mod.jl_inv_tmv, xi, "xi", w, "g"),
                            (mod.exp_pullback, M, "M", G, "G"), (mod.log_pullback, M, "M", w, "w")):
        tail = "" if a.dim() == 2 else f", {n}"
        with pytest.raises(ValueError, match=rf"{an} must have shape \(\.\.\., {a.shape[-1]}{tail}\)"):
            f(a[..., :-1], b)
        with pytest.raises(ValueError, match=rf"{bn} must have shape"):
            f(a, b[..., :-1])
        with pytest.raises(TypeError, match=rf"{bn} has dtype torch.float32 but {an} has dtype torch.float64"):
            f(a, b.float())
        with pytest.raises(TypeError, match=rf"{an} must have a floating dtype .* got torch.int64"):
            f(a.long(), b.long())
        with pytest.raises(ValueError, match=rf"batch shapes do not broadcast: {an} \(4,\), {bn} \(3,\)"):
            f(a, b[:3])


@pytest.mark.parametrize("mod", MODS, ids=IDS)
def test_random_checks_dtype(mod):
    assert mod.random((2,), torch.float32, "cpu").dtype == torch.float32
    for bad in (torch.float16, torch.int64):
        with pytest.raises(TypeError, match=rf"dtype must be torch.float32 or torch.float64, got {bad}"):
            mod.random((2,), bad, "cpu")


@pytest.mark.parametrize("mod", MODS, ids=IDS)
def test_backward_parts_broadcast_batches_of_different_ranks(mod):
    """A (1,) batch against a (3, 1) one, either way round: each element equals the unbatched
    call (component-first code once aligned one argument's components with the other's batch)."""
    n, dof = mod.MATRIX_DIM, mod.DOF
    gen = torch.Generator().manual_seed(5)
    xi = 0.5 * torch.randn(1, dof, dtype=D, generator=gen)
    xi3 = 0.5 * torch.randn(3, 1, dof, dtype=D, generator=gen)
    w = torch.randn(3, 1, dof, dtype=D, generator=gen)
    G = torch.randn(3, 1, n, n, dtype=D, generator=gen)
    M, M3 = mod.exp(xi), mod.exp(xi3)
    for f, a, b in ((mod.jl_tmv, xi, w), (mod.jl_inv_tmv, xi, w), (mod.exp_pullback, M, G),
                    (mod.log_pullback, M, w), (mod.jl_tmv, xi3, w[0]), (mod.jl_inv_tmv, xi3, w[0]),
                    (mod.exp_pullback, M3, G[0]), (mod.log_pullback, M3, w[0])):
        out = f(a, b)
        first = [a[0] if a.dim() in (2, 3) and a.shape[0] == 1 else a[i, 0] for i in range(3)]
        second = [b[0] if b.shape[0] == 1 else b[i, 0] for i in range(3)]
        expect = torch.stack([f(x, y) for x, y in zip(first, second)])
        assert out.shape[:2] == (3, 1)
        torch.testing.assert_close(out[:, 0], expect, rtol=1e-14, atol=1e-14)


_SHAPES = [(), (1,), (0,), (3,), (4,), (1, 1), (2, 1), (1, 3), (2, 3), (0, 3), (2, 0), (5, 1, 3),
           (5, 2, 1), (1, 2, 3), (7, 1, 1, 1)]


@pytest.mark.parametrize("extra", [(), (1, 3), (2, 1, 1)])
def test_broadcast_shapes_is_torchs(extra):
    """checks.broadcast_shapes against torch.broadcast_shapes over pairs and triples of shapes:
    the same Size where torch broadcasts, the same RuntimeError where it refuses."""
    for a in _SHAPES:
        for b in _SHAPES:
            shapes = (torch.Size(a), b, *([extra] if extra else []))
            try:
                want = torch.broadcast_shapes(*shapes)
            except RuntimeError as e:
                with pytest.raises(RuntimeError) as got:
                    checks.broadcast_shapes(*shapes)
                assert str(got.value) == str(e)
                continue
            got = checks.broadcast_shapes(*shapes)
            assert type(got) is torch.Size and got == want, (shapes, got, want)
    assert checks.broadcast_shapes() == torch.broadcast_shapes() == torch.Size()
