"""Input checks of the functional layer (torchsgal.functional.*): every public function refuses
bad input at once with a message naming the argument, the expectation and what was given
(CONVENTIONS.md, Errors), instead of a raw torch error, garbage-shaped output or a silent
dtype promotion."""
from __future__ import annotations

import pytest
import torch

import torchsgal.functional as TF

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
