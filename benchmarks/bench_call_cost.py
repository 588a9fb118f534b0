"""The fixed cost of one group operation: what a call of SGal3.exp costs beyond its arithmetic,
layer by layer, with the peers' one-element calls in the same run.

On small batches (one pose, a few thousand factors) a call's fixed cost is its whole cost.  The
cases, per batch size and dtype (medians, microseconds per call):

- ``torch.sin``: one aten operation, the floor of any torch call;
- the implementation of ``torchsgal::sgal3_exp`` called as a Python function (checks, output
  allocation, the C kernel): no dispatch;
- the operator ``torch.ops.torchsgal.sgal3_exp``, defined through ``torch.library.Library``
  (``functional/registration.py``);
- the same implementation, fake and autograd formula registered by ``torch.library.custom_op``
  (``bench::sgal3_exp``): the registration torchsgal does not use, in the same run;
- ``SGal3.exp``: the group API; nothing records, so it calls the operator;
- ``SGal3.exp`` on an input that requires grad: the custom autograd Function around the
  operator (forward only);
- the closed form ``sgal3.exp_impl`` as eager tensor code;
- ``torch.linalg.matrix_exp`` of the hat matrix and pypose's SE(3) ``Exp`` (peers).

Usage::

    python benchmarks/bench_call_cost.py [--sizes 1 1000] [--threads 1]
"""
from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import sys
from pathlib import Path

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _timing import cpu_model, measure  # noqa: E402

from torchsgal import SGal3  # noqa: E402
from torchsgal.functional import native, ops  # noqa: E402
from torchsgal.functional import sgal3 as F  # noqa: E402

HERE = Path(__file__).resolve().parent
EXP = ops.register(F)[0]


def custom_op_twin():
    """``bench::sgal3_exp``: the operator's implementation, fake and backward registered by
    ``torch.library.custom_op``."""
    impl = EXP.__wrapped__

    @torch.library.custom_op("bench::sgal3_exp", mutates_args=())
    def twin(xi: torch.Tensor) -> torch.Tensor:
        return impl(xi)

    twin.register_fake(lambda xi: xi.new_empty(xi.shape[:-1] + (5, 5)))

    def setup(ctx, inputs, output):
        ctx.save_for_backward(inputs[0], output)

    def backward(ctx, grad):
        xi, M = ctx.saved_tensors
        return torch.ops.torchsgal.sgal3_exp_vjp(xi, M, grad)

    twin.register_autograd(backward, setup_context=setup)
    return twin


def cases(n: int, dtype: torch.dtype):
    gen = torch.Generator().manual_seed(0)
    xi = 0.5 * torch.randn(n, 10, dtype=dtype, generator=gen)
    xi_grad = xi.clone().requires_grad_()
    hat = F.hat(xi)
    twin = custom_op_twin() if not hasattr(torch.ops.bench, "sgal3_exp") else torch.ops.bench.sgal3_exp
    out = {
        "torch.sin (one aten op)": lambda: torch.sin(xi),
        "implementation, no dispatch": lambda: EXP.__wrapped__(xi),
        "operator (torch.library.Library)": lambda: EXP(xi),
        "same, registered by torch.library.custom_op": lambda: twin(xi),
        "SGal3.exp": lambda: SGal3.exp(xi),
        "SGal3.exp, input requires grad (Function)": lambda: SGal3.exp(xi_grad),
        "closed form, eager tensor code": lambda: F.exp_impl(xi),
        "matrix_exp of the hat matrix": lambda: torch.linalg.matrix_exp(hat),
    }
    try:
        import pypose as pp
        x6 = pp.se3(xi[:, :6].clone())
        out["pypose SE3 Exp"] = lambda: x6.Exp()
    except ImportError:
        pass
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=float, nargs="+", default=[1, 1000])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default=str(HERE / "results"))
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    if not native.available():
        sys.exit("the C kernels are not built: python setup.py build_ext --inplace")
    sizes = [int(s) for s in args.sizes]
    columns = [(n, dt) for dt in (torch.float64, torch.float32) for n in sizes]
    table: dict[str, dict[str, float]] = {}
    for n, dt in columns:
        key = f"{str(dt).split('.')[-1]} {n:g}"
        for name, fn in cases(n, dt).items():
            table.setdefault(name, {})[key] = measure(fn, target_s=1.0)["median_s"] * 1e6
            print(f"{key:>14}  {name:45s} {table[name][key]:8.1f} us", flush=True)
    keys = [f"{str(dt).split('.')[-1]} {n:g}" for n, dt in columns]

    def ratio(a: str, b: str) -> list[str]:
        return [f"{table[a][k] / table[b][k]:.2f}" if a in table and b in table else "–" for k in keys]

    ratios = {
        "custom_op / Library registration (the operator's dispatch)":
            ratio("same, registered by torch.library.custom_op", "operator (torch.library.Library)"),
        "operator minus implementation (us): dispatch": [
            f"{table['operator (torch.library.Library)'][k] - table['implementation, no dispatch'][k]:.1f}"
            for k in keys],
        "Function / operator (an input that requires grad)":
            ratio("SGal3.exp, input requires grad (Function)", "SGal3.exp"),
        "matrix_exp / SGal3.exp": ratio("matrix_exp of the hat matrix", "SGal3.exp"),
        "pypose SE3 Exp / SGal3.exp": ratio("pypose SE3 Exp", "SGal3.exp"),
        "closed form / SGal3.exp": ratio("closed form, eager tensor code", "SGal3.exp"),
    }
    stamp = _dt.date.today().isoformat()
    head = (f"# The fixed cost of a call ({cpu_model()}, torch {torch.__version__}, "
            f"{args.threads} thread{'s' if args.threads > 1 else ''}, {stamp})")
    lines = [head, "", "Microseconds per call (medians):", "",
             "| case | " + " | ".join(keys) + " |", "|---|" + "---:|" * len(keys)]
    lines += [f"| {name} | " + " | ".join(f"{row[k]:,.1f}" for k in keys) + " |" for name, row in table.items()]
    lines += ["", "| ratio | " + " | ".join(keys) + " |", "|---|" + "---:|" * len(keys)]
    lines += [f"| {name} | " + " | ".join(vals) + " |" for name, vals in ratios.items()]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "call_cost_cpu.md").write_text("\n".join(lines) + "\n")
    (out / "call_cost_cpu.json").write_text(json.dumps(
        {"cpu": cpu_model(), "torch": torch.__version__, "threads": args.threads, "date": stamp,
         "us_per_call": table, "ratios": ratios}, indent=1) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
