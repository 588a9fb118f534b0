"""The examples of docs/guide/factor_graphs.md run, in order, in one namespace (their asserts
check the results they describe)."""
import re
from pathlib import Path

import torch

GUIDE = Path(__file__).resolve().parents[1] / "docs" / "guide" / "factor_graphs.md"


def test_guide_examples_run():
    blocks = re.findall(r"```python\n(.*?)```", GUIDE.read_text(), flags=re.S)
    assert len(blocks) == 6
    namespace: dict = {}
    for block in blocks:
        exec(compile(block, str(GUIDE), "exec"), namespace)
    assert namespace["cov"].shape == (32, 2, 6, 6)
    assert namespace["T_robust"].batch_shape == (64,)
    # the GPU section's solve equals the same graph's solve on the CPU; where no GPU is (the
    # section then solves on the CPU), the CPU solve takes the dense linear solver instead of
    # the block-sparse one the section's takes, so that the two are different computations
    n = namespace
    fg, W = n["fg"], n["W"]
    graph = fg.FactorGraph()
    graph.add_variable("x", n["x0"])
    graph.add(fg.Prior("x", 0, n["truth"][:, :1], information=W))
    graph.add(fg.Between("x", n["i"], n["j"], n["Z"], information=W))
    gpu = n["result_gpu"]
    on_cpu = gpu.report.status.device.type == "cpu"
    cpu = fg.levenberg_marquardt(graph, linear_solver="dense" if on_cpu else "auto")
    assert gpu.values["x"].batch_shape == (32, 8)
    assert gpu.report.iterations.cpu().tolist() == cpu.report.iterations.tolist()
    torch.testing.assert_close(gpu.report.cost.cpu(), cpu.report.cost, rtol=1e-10, atol=0)
