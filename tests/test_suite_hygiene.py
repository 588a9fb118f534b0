"""Checks of the test suite itself."""
from __future__ import annotations

import ast
from pathlib import Path

CLOSE = {"np.testing.assert_allclose", "numpy.testing.assert_allclose", "torch.allclose",
         "np.allclose", "numpy.allclose"}


def test_every_stated_atol_comes_with_an_rtol():
    """numpy's assert_allclose and torch.allclose add a relative tolerance (1e-7, 1e-5) unless
    told otherwise: an assert that states only ``atol`` checks less than it says.  Every such
    call must state ``rtol`` too (``rtol=0`` for an absolute bound)."""
    loose = []
    for path in sorted(Path(__file__).parent.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and ast.unparse(node.func) in CLOSE:
                keywords = {k.arg for k in node.keywords}
                if "atol" in keywords and "rtol" not in keywords:
                    loose.append(f"{path.name}:{node.lineno}")
    assert not loose, f"atol without rtol: {loose}"
