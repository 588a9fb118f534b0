"""torchsgal._compat holds every use of a private torch interface; each has a fallback, and the
library gives the same results on every fallback."""
from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest
import torch
from conftest import sample_tangent

import torchsgal as ts
from torchsgal import _compat

PACKAGE = Path(ts.__file__).resolve().parent
# a private name anywhere on a torch path (torch._C, torch.utils._pytree, forward_ad._x, ...)
PRIVATE = re.compile(r"torch(\.\w+)*\._[A-Za-z]")

# Each fallback: the module attributes that a torch without the interface leaves unset.
FALLBACKS = {
    "functorch_wrapped": {"_is_wrapped_tensor": None},
    "transform_depth": {"_interpreters": None},
    "fake_mode": {"_get_dispatch_mode": None},
    "fast_apply": {"_SingleLevelFunction": None, "_transforms_active": None},
}


def test_no_private_torch_interface_outside_compat():
    """``grep -rn "torch\\._" torchsgal/`` lists only _compat.py (the Python and the C sources),
    and so does the wider search for private names on any torch path (``torch.utils._pytree``)."""
    hits = [f"{p.relative_to(PACKAGE)}:{i}" for p in sorted(PACKAGE.rglob("*"))
            if p.suffix in {".py", ".c", ".h"} and p.name != "_compat.py"
            for i, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1) if PRIVATE.search(line)]
    assert not hits, f"private torch interfaces outside torchsgal/_compat.py: {hits}"


def _private_uses(tree: ast.AST) -> list[int]:
    """Lines that import a private name from a torch module (``from torch.x import a, _b``,
    ``import torch._x``, in any layout) or read one by ``getattr(<torch...>, "_x")``."""
    lines = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "torch":
            if any(part.startswith("_") for part in node.module.split(".")) or any(
                    a.name.startswith("_") for a in node.names):
                lines.append(node.lineno)
        elif isinstance(node, ast.Import):
            if any(a.name.split(".")[0] == "torch" and any(p.startswith("_") for p in a.name.split("."))
                   for a in node.names):
                lines.append(node.lineno)
        elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "getattr"
              and len(node.args) >= 2 and isinstance(node.args[1], ast.Constant)
              and isinstance(node.args[1].value, str) and node.args[1].value.startswith("_")
              and "torch" in ast.unparse(node.args[0]).split(".")[0]):
            lines.append(node.lineno)
    return lines


def test_no_private_torch_import_outside_compat():
    """The same by the syntax tree: no module but _compat.py imports a private torch name or
    reads one with getattr, however the import is laid out."""
    hits = [f"{p.relative_to(PACKAGE)}:{line}" for p in sorted(PACKAGE.rglob("*.py")) if p.name != "_compat.py"
            for line in _private_uses(ast.parse(p.read_text(encoding="utf-8")))]
    assert not hits, f"private torch interfaces outside torchsgal/_compat.py: {hits}"
    found = _private_uses(ast.parse("from torch.utils import (\n    cpp_extension,\n    _pytree,\n)\n"
                                    "import torch._dynamo\nx = getattr(torch.autograd, '_secret')\n"))
    assert found == [1, 5, 6]  # the search itself finds each form


def test_every_interface_is_found_on_the_supported_torch():
    """On the torch versions pyproject.toml admits, no fallback is in use (a fallback in use
    means torch moved an interface: the bound must not admit that version unnoticed)."""
    for attrs in FALLBACKS.values():
        for name in attrs:
            assert getattr(_compat, name) is not None, name
    assert _compat._pytree is not None


def test_without_a_pytree_registry_torch_func_takes_the_matrices(monkeypatch):
    """The pytree fallback: a class made while torch offers no registry is not registered
    (flattening keeps its instances whole), and torch.func still maps over its matrices with
    the same results as the registered built-in class."""
    from torch.utils import _pytree as pytree

    monkeypatch.setattr(_compat, "_pytree", None)

    class Unregistered(ts.SE3):
        __slots__ = ()

    g = Unregistered.exp(sample_tangent(ts.SE3, (5,), torch.float64, seed=4))
    assert pytree.tree_flatten(g)[0] == [g]  # one opaque leaf: not a pytree node
    assert len(pytree.tree_flatten(ts.SE3(g.as_matrix()))[0]) == 1  # the built-in: its matrix
    assert pytree.tree_flatten(ts.SE3(g.as_matrix()))[0][0] is g.as_matrix()
    got = torch.func.vmap(lambda m: Unregistered(m).log())(g.as_matrix())
    want = torch.func.vmap(lambda h: h.log())(ts.SE3(g.as_matrix()))
    torch.testing.assert_close(got, want, rtol=0, atol=0)


def _results(G, dtype):
    xi = sample_tangent(G, (6,), dtype, seed=3).requires_grad_(True)
    w = torch.linspace(-1.0, 1.0, G.dof, dtype=dtype)
    g = G.exp(xi)
    out = {"exp": g.as_matrix().detach(), "log": g.log().detach()}
    (grad,) = torch.autograd.grad((g.log() * w).sum() + g.as_matrix().sum(), xi)
    out["grad"] = grad
    x0 = xi.detach()[1]
    out["jacfwd_jacfwd"] = torch.func.jacfwd(torch.func.jacfwd(lambda x: G.exp(x).as_matrix()))(x0)
    out["vmap_jacrev"] = torch.func.vmap(torch.func.jacrev(lambda x: G.exp(x).log()))(xi.detach())
    return out


@pytest.mark.parametrize("fallback", sorted(FALLBACKS))
@pytest.mark.parametrize("G", [ts.SO3, ts.SE3, ts.SGal3, ts.Sim3], ids=lambda g: g.__name__)
def test_fallback_gives_the_same_results(G, fallback, monkeypatch):
    want = _results(G, torch.float64)
    for name, value in FALLBACKS[fallback].items():
        monkeypatch.setattr(_compat, name, value)
    got = _results(G, torch.float64)
    for key in want:
        torch.testing.assert_close(got[key], want[key], rtol=1e-12, atol=1e-12, msg=key)


def test_fallbacks_answer_conservatively(monkeypatch):
    for attrs in FALLBACKS.values():
        for name, value in attrs.items():
            monkeypatch.setattr(_compat, name, value)
    t = torch.zeros(2)
    assert _compat.is_functorch_wrapped(t) is True
    assert _compat.forward_mode_depth() == 2
    assert _compat.fake_tensor_mode_active() is True


def test_interfaces_report_what_they_see():
    t = torch.zeros(3)
    assert _compat.is_functorch_wrapped(t) is False
    assert torch.func.vmap(lambda x: torch.tensor(_compat.is_functorch_wrapped(x)))(t).all()
    assert _compat.forward_mode_depth() == 0
    depths = []
    torch.func.jacfwd(lambda x: depths.append(_compat.forward_mode_depth()) or x)(t)
    torch.func.jacfwd(torch.func.jacfwd(lambda x: depths.append(_compat.forward_mode_depth()) or x))(t)
    assert depths == [1, 2]
    assert _compat.fake_tensor_mode_active() is False
    from torch.fx.experimental.proxy_tensor import make_fx

    seen = []
    make_fx(lambda x: seen.append(_compat.fake_tensor_mode_active()) or x, tracing_mode="fake")(t)
    assert seen == [True]
