"""The examples of docs/guide/factor_graphs.md run, in order, in one namespace (their asserts
check the results they describe)."""
import re
from pathlib import Path

GUIDE = Path(__file__).resolve().parents[1] / "docs" / "guide" / "factor_graphs.md"


def test_guide_examples_run():
    blocks = re.findall(r"```python\n(.*?)```", GUIDE.read_text(), flags=re.S)
    assert len(blocks) == 5
    namespace: dict = {}
    for block in blocks:
        exec(compile(block, str(GUIDE), "exec"), namespace)
    assert namespace["cov"].shape == (32, 2, 6, 6)
    assert namespace["T_robust"].batch_shape == (64,)
