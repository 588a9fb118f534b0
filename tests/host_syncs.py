"""One recorder of host syncs for the tests (test_devices on 'meta', test_uncertainty on CPU).

``HostSyncs`` lists (what, where) for every operation that synchronises the host on CUDA:
value reads (item/bool/float/int, which dispatch aten._local_scalar_dense, and tolist, which
does not dispatch on CPU and so is caught as a method call), linalg error checks
(cholesky/inv/solve), eigh, data-dependent shapes (nonzero, masked_select), torch.equal,
host-to-device copies (aten _to_copy/copy_ from a CPU tensor to another device) and
torch.tensor/as_tensor/asarray/new_tensor of host data onto another device, and ``t[i, j] = 1.0``
with a Python number into a single element of a device tensor (torch copies the number as a
0-d CPU tensor there, a blocking copy on CUDA; into a larger view it fills).  On 'meta' the
reads raise after being recorded; the copies and checks pass there silently, which is why
this recorder exists.
"""
from __future__ import annotations

import functools
import traceback
from pathlib import Path

import torch

import torchsgal

_ATEN = torch.ops.aten
SYNC_OPS = {
    _ATEN._local_scalar_dense.default: "value read (item/bool/float)",
    _ATEN._linalg_check_errors.default: "linalg error check (cholesky/inv/solve)",
    _ATEN._linalg_eigh.default: "eigh",
    _ATEN.nonzero.default: "data-dependent shape (nonzero, mask indexing)",
    _ATEN.masked_select.default: "data-dependent shape (masked_select)",
    _ATEN.equal.default: "torch.equal",
}


_PACKAGE = Path(torchsgal.__file__).resolve().parent


@functools.cache
def _in_package(filename: str) -> bool:
    """Whether ``filename`` is a file of the torchsgal package itself (by its resolved path:
    not any path that contains the word, such as a virtualenv inside a checkout of that name)."""
    try:
        return Path(filename).resolve().is_relative_to(_PACKAGE)
    except (OSError, ValueError):  # '<frozen ...>', '<string>' and the like
        return False


def _caller() -> str:
    """The innermost torchsgal frame of the current stack, as 'path:line'."""
    frames = [f for f in traceback.extract_stack() if _in_package(f.filename)]
    return f"{frames[-1].filename}:{frames[-1].lineno}" if frames else "?"


class HostSyncs:
    """Context manager recording host syncs in ``events`` (see the module docstring)."""

    def __enter__(self):
        from torch.overrides import TorchFunctionMode
        from torch.utils._python_dispatch import TorchDispatchMode

        events = self.events = []

        class Dispatch(TorchDispatchMode):
            def __torch_dispatch__(self, func, types, args=(), kwargs=None):
                kwargs = kwargs or {}
                why = SYNC_OPS.get(func)
                if func is _ATEN._to_copy.default:
                    dst = kwargs.get("device")
                    if dst is not None and torch.device(dst).type != "cpu" and args[0].device.type == "cpu":
                        why = "host-to-device copy (.to)"
                elif func is _ATEN.copy_.default and args[0].device.type != "cpu" and args[1].device.type == "cpu":
                    why = "host-to-device copy (copy_)"
                if why:
                    events.append((why, _caller()))
                return func(*args, **kwargs)

        class Functions(TorchFunctionMode):
            def __torch_function__(self, func, types, args=(), kwargs=None):
                kwargs = kwargs or {}
                device = data = None
                if func is torch.Tensor.tolist:
                    events.append(("value read (tolist)", _caller()))
                elif (func is torch.Tensor.__setitem__ and len(args) == 3 and args[0].device.type != "cpu"
                      and isinstance(args[2], (bool, int, float, complex)) and args[0][args[1]].dim() == 0):
                    events.append(("host-to-device copy (setitem of a number into one element)", _caller()))
                elif func in (torch.tensor, torch.as_tensor, torch.asarray):
                    device, data = kwargs.get("device"), args[0] if args else kwargs.get("data")
                elif func is torch.Tensor.new_tensor:  # self's device unless given
                    device, data = kwargs.get("device", args[0].device), args[1] if len(args) > 1 else kwargs.get("data")
                if (device is not None and torch.device(device).type != "cpu"
                        and not isinstance(data, torch.Tensor)):
                    events.append((f"host-to-device copy ({func.__name__} of host data)", _caller()))
                return func(*args, **kwargs)

        self._modes = [Functions(), Dispatch()]
        for mode in self._modes:
            mode.__enter__()
        return self

    def __exit__(self, *exc):
        for mode in reversed(self._modes):
            mode.__exit__(*exc)
        return False


def solve_loop_reads(solve):
    """Runs ``solve()`` (a Levenberg-Marquardt solve of the factor-graph engine) under
    ``HostSyncs`` and sorts its reads: (result, reads inside the hot functions (linearisation,
    retraction, the dense solve, one LM round), reads by the solve loop itself)."""
    import importlib
    import inspect

    lm, linear_system, lz, problem = (importlib.import_module(f"torchsgal.estimation.graph.{m}")
                                      for m in ("levenberg_marquardt", "linear_system", "linearize",
                                                "problem"))

    def lines(fn):
        src, start = inspect.getsourcelines(fn)
        return range(start, start + len(src))

    with HostSyncs() as syncs:
        result = solve()
    hot = {lz.__file__: [lines(f) for f in (lz.linearize, lz.evaluate_cost, lz._block_terms,
                                            lz._residual_and_jacobian)],
           problem.__file__: [lines(problem.Problem.retract)],
           linear_system.__file__: [lines(linear_system.DenseSystem.solve)],
           lm.__file__: [lines(lm._round)]}
    in_hot = [(why, where) for why, where in syncs.events
              for path, ranges in hot.items()
              if where.rsplit(":", 1)[0] == path and any(int(where.rsplit(":", 1)[1]) in r for r in ranges)]
    loop = [e for e in syncs.events if e[1].rsplit(":", 1)[0] == lm.__file__]
    return result, in_hot, loop
