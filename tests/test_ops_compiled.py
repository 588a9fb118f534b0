"""The operators' compiled closed forms (functional/ops.py: what runs them on CUDA), exercised on
the CPU: the compiled path is switched on for CPU tensors with the C kernels out of the way, and
torch.compile gets a backend that records each graph it is given and each run of one.  That
tests the mechanism (which calls take the compiled path, one graph per operator and dtype for
every batch shape, every context reaching it, the thread switch); the code inductor generates on
CUDA is checked against the CPU by tests/test_cuda.py on a GPU machine."""
from __future__ import annotations

import pytest
import torch
from test_ops import OPS, _arguments, _op

from torchsgal.functional import native, ops, sgal3

# ``kernels``: like the C kernels' own tests, these test a path that TORCHSGAL_NATIVE=0 switches
# off (native.py: the compiled path goes with the kernels); the ``compiled`` fixture switches it
# back on and the C kernels out of the way, so that a run with TORCHSGAL_NATIVE=0 would repeat
# the first run's tests unchanged: the second test run of .ci/run (-m "not kernels") leaves them
# out.
pytestmark = pytest.mark.kernels


class Recorder:
    """A torch.compile backend: records every graph it compiles and every run of one."""

    def __init__(self):
        self.graphs: list[str] = []
        self.runs: list[str] = []

    def __call__(self, gm, example_inputs):
        name = str(len(self.graphs))
        self.graphs.append(name)

        def run(*args):
            self.runs.append(name)
            return gm.forward(*args)

        return run


@pytest.fixture
def compiled(monkeypatch):
    recorder = Recorder()
    monkeypatch.setattr(ops, "COMPILED_DEVICE_TYPES", ("cpu",))
    monkeypatch.setattr(ops, "COMPILED_DTYPES", (torch.float32, torch.float64))
    monkeypatch.setattr(ops, "COMPILE_BACKEND", recorder)
    monkeypatch.setattr(ops, "_COMPILED", {})
    monkeypatch.setattr(ops, "_kernel", lambda *args: None)  # the C kernels would come first
    monkeypatch.setitem(native._state, "compiled", False)
    monkeypatch.setitem(native._state, "env_off", False)
    native.use_compiled_cuda(True)  # the opt-in (restored by monkeypatch)
    return recorder


def _eager(name, args):
    with native.disabled():
        return _op(name)(*args)


@pytest.mark.parametrize("name", OPS)
def test_one_graph_per_operator_for_every_batch_shape(compiled, name):
    for batch in [(5,), (2, 3), (1,), (), (7,)]:
        args = _arguments(name, batch, torch.float64)
        out = _op(name)(*args)
        assert out.shape == _eager(name, args).shape
        torch.testing.assert_close(out, _eager(name, args), rtol=1e-14, atol=1e-14)
    assert len(compiled.graphs) == 1  # batch sizes 1 and 0/1-specialisation reuse it
    assert len(compiled.runs) == 5


def test_an_empty_batch_runs_no_graph(compiled):
    out = _op("sgal3_exp")(torch.zeros(0, 10, dtype=torch.float64))
    assert out.shape == (0, 5, 5) and compiled.runs == []


def test_one_graph_per_dtype(compiled):
    for dtype in (torch.float32, torch.float64, torch.float32):
        _op("sgal3_exp")(*_arguments("sgal3_exp", (4,), dtype))
    assert len(compiled.graphs) == 2 and len(compiled.runs) == 3


def test_broadcast_arguments_run_the_compiled_graph(compiled):
    xi, M, G = _arguments("sgal3_exp_vjp", (3,), torch.float64)
    args = (xi[:1], M.unsqueeze(1), G.unsqueeze(1))  # batches (1,), (3, 1), (3, 1): broadcast (3, 1)
    out = _op("sgal3_exp_vjp")(*args)
    torch.testing.assert_close(out, _eager("sgal3_exp_vjp", args), rtol=1e-14, atol=1e-14)
    assert out.shape == (3, 1, 10) and len(compiled.runs) == 1


# The compiled path is one mechanism for every operator (ops._define): opcheck's traced check
# (test_aot_dispatch_dynamic: the operator inside an aot_autograd graph with dynamic shapes, values
# and gradients against eager) on a forward and a backward operator; the registration checks
# (schema, autograd registration, fake tensors against the real outputs) on every operator.  The
# traced check runs on every operator through the kernels and the closed forms in tests/test_ops.py.
TRACED = ("sgal3_exp", "sgal3_log_vjp")


@pytest.mark.parametrize("name", OPS)
def test_opcheck_with_the_compiled_path(compiled, name):
    utils = None if name in TRACED else ("test_schema", "test_autograd_registration", "test_faketensor")
    args = _arguments(name, (3,), torch.float64, requires_grad=True)
    torch.library.opcheck(_op(name), args, **({} if utils is None else {"test_utils": utils}))
    assert compiled.runs


def test_every_context_reaches_the_compiled_graphs(compiled):
    xi = 0.5 * torch.randn(4, 10, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    M = sgal3.exp(xi)
    assert len(compiled.runs) == 1

    x = xi.clone().requires_grad_(True)  # autograd: exp and log, then their backward operators
    sgal3.log(sgal3.exp(x)).sum().backward()
    assert len(compiled.runs) == 5
    torch.testing.assert_close(x.grad, _eager_grad(xi), rtol=1e-12, atol=1e-12)

    torch.func.vmap(sgal3.exp)(xi.reshape(2, 2, 10))
    assert len(compiled.runs) == 6
    torch.func.grad(lambda v: sgal3.log(sgal3.exp(v)).sum())(xi)
    assert len(compiled.runs) == 10
    with torch.inference_mode():
        sgal3.log(M)
    assert len(compiled.runs) == 11

    with native.disabled():  # the thread switch turns the compiled path off too
        sgal3.exp(xi)
        sgal3.log(sgal3.exp(x)).sum().backward()
    assert len(compiled.runs) == 11


def _eager_grad(xi):
    with native.disabled():
        x = xi.clone().requires_grad_(True)
        sgal3.log(sgal3.exp(x)).sum().backward()
    return x.grad


def test_the_switch_is_per_thread(compiled):
    import threading

    xi, = _arguments("sgal3_exp", (3,), torch.float64)
    seen = []
    with native.disabled():
        thread = threading.Thread(target=lambda: seen.append(_op("sgal3_exp")(xi)))
        thread.start()
        thread.join()
        _op("sgal3_exp")(xi)
    assert len(seen) == 1 and len(compiled.runs) == 1  # the other thread's call only


def test_the_compiled_path_is_an_opt_in(compiled):
    native.use_compiled_cuda(False)
    _op("sgal3_exp")(*_arguments("sgal3_exp", (3,), torch.float64))
    assert compiled.runs == []
    with pytest.raises(TypeError, match="enabled must be True or False"):
        native.use_compiled_cuda(1)


def test_the_environment_switch_turns_the_opt_in_off(compiled, monkeypatch):
    monkeypatch.setitem(native._state, "env_off", True)  # TORCHSGAL_NATIVE=0 at import
    _op("sgal3_exp")(*_arguments("sgal3_exp", (3,), torch.float64))
    assert compiled.runs == [] and not native.compiled_enabled()


def test_a_missing_compiler_leaves_the_eager_closed_form(compiled, monkeypatch):
    monkeypatch.setattr(ops, "_COMPILER_NEEDS", {"cpu": "a_module_that_is_not_installed"})
    monkeypatch.setattr(ops, "_FOUND", {})
    _op("sgal3_exp")(*_arguments("sgal3_exp", (3,), torch.float64))
    assert compiled.runs == []


def test_float64_is_left_to_the_eager_closed_form(compiled, monkeypatch):
    monkeypatch.setattr(ops, "COMPILED_DTYPES", (torch.float32,))  # the default
    _op("sgal3_exp")(*_arguments("sgal3_exp", (3,), torch.float64))
    assert compiled.runs == []
    _op("sgal3_exp")(*_arguments("sgal3_exp", (3,), torch.float32))
    assert len(compiled.runs) == 1


def test_a_failing_compilation_warns_once_and_runs_the_eager_closed_form(compiled, monkeypatch):
    def failing_backend(gm, example_inputs):
        raise RuntimeError("no code for this device")

    monkeypatch.setattr(ops, "COMPILE_BACKEND", failing_backend)
    args = _arguments("sgal3_log", (4,), torch.float64)
    with pytest.warns(RuntimeWarning, match="torchsgal::sgal3_log: compiling its closed form failed"):
        out = _op("sgal3_log")(*args)
    torch.testing.assert_close(out, _eager("sgal3_log", args), rtol=0, atol=0)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # once: the next call runs the eager code quietly
        torch.testing.assert_close(_op("sgal3_log")(*args), out, rtol=0, atol=0)


def test_compiled_closed_forms_keep_one_graph_whatever_the_batch_size():
    """The series constants are built inside a compiled graph, not read from the cache as
    inputs: a batch as long as a constant table (numerics.TAYLOR_TERMS) once recompiled."""
    recorder = Recorder()
    sgal3.exp_impl(torch.zeros(3, 10, dtype=torch.float64))  # the constants cache is filled
    fn = torch.compile(sgal3.exp_impl, dynamic=True, backend=recorder)
    for n in (5, 7, 11, 2, 9):
        xi = 0.5 * torch.randn(n, 10, dtype=torch.float64, generator=torch.Generator().manual_seed(n))
        torch.testing.assert_close(fn(xi), sgal3.exp_impl(xi), rtol=1e-14, atol=1e-14)
    assert len(recorder.graphs) == 1 and len(recorder.runs) == 5
