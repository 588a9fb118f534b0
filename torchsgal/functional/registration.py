"""How the package registers its torch operators (``torchsgal::<name>``).

``@operator("torchsgal::<name>", schema=...)`` defines the operator through
``torch.library.Library`` (``define``, and the decorated function as its
``CompositeExplicitAutograd`` implementation) and returns an :class:`Operator` with the
registration methods of ``torch.library.custom_op``'s objects: ``register_kernel(device)``,
``register_fake``, ``register_autograd`` and ``register_vmap`` (the last three by
``torch.library``'s functions of the same names).  Autograd, ``torch.func``, ``torch.compile``
and ``torch.library.opcheck`` see the same operator either way; what differs is the cost of a
call: ``custom_op`` reaches the implementation through Python wrappers that cost 13-19 us per
call (``torchsgal::sgal3_exp`` of one element: 75.2 us through ``custom_op``, 56.4 us through
``Library``, one thread, ``benchmarks/bench_call_cost.py``), part of the fixed cost of every
group operation on small batches.

An operator without a backward formula raises on a backward through it ("no autograd formula"),
as a ``custom_op`` does: every operator has one autograd registration, whose formula
``register_autograd`` supplies.
"""
from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch

_NAMESPACE = "torchsgal"
_LIBRARY = torch.library.Library(_NAMESPACE, "FRAGMENT")  # kept alive: it owns the registrations
_DISPATCH_KEYS = {"cpu": "CPU", "cuda": "CUDA"}


class Operator:
    """A registered operator: calling it calls ``torch.ops.torchsgal.<name>.default``."""

    def __init__(self, qualname: str, fn: Callable, schema: str | None) -> None:
        namespace, _, name = qualname.partition("::")
        if namespace != _NAMESPACE or not name:
            raise ValueError(f"operator: qualname must be '{_NAMESPACE}::<name>', got {qualname!r}")
        schema = schema if schema is not None else torch.library.infer_schema(fn, mutates_args=())
        _LIBRARY.define(name + schema)
        _LIBRARY.impl(name, fn, "CompositeExplicitAutograd")
        self.__name__ = name
        self.__doc__ = fn.__doc__
        self.__wrapped__ = fn
        self._qualname = qualname
        self._overload = getattr(getattr(torch.ops, namespace), name).default
        self._backward: Callable | None = None
        self._setup_context: Callable | None = None
        torch.library.register_autograd(qualname, self._run_backward, setup_context=self._run_setup_context,
                                        lib=_LIBRARY)

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return self._overload(*args, **kwargs)

    def __repr__(self) -> str:
        return f"<operator {self._qualname}>"

    def register_kernel(self, device: str) -> Callable[[Callable], Callable]:
        """Decorator: ``fn`` implements the operator on ``device`` ("cpu" or "cuda")."""
        if device not in _DISPATCH_KEYS:
            raise ValueError(f"register_kernel: device must be one of {tuple(_DISPATCH_KEYS)}, got {device!r}")

        def register(fn: Callable) -> Callable:
            _LIBRARY.impl(self.__name__, fn, _DISPATCH_KEYS[device])
            return fn
        return register

    def register_fake(self, fn: Callable) -> Callable:
        """``fn`` gives the outputs' shapes, dtypes and devices (``torch.library.register_fake``)."""
        torch.library.register_fake(self._qualname, fn, lib=_LIBRARY)
        return fn

    def register_vmap(self, fn: Callable) -> Callable:
        """``fn`` is the operator's vmap rule (``torch.library.register_vmap``)."""
        torch.library.register_vmap(self._qualname, fn, lib=_LIBRARY)
        return fn

    def register_autograd(self, backward: Callable, setup_context: Callable | None = None) -> None:
        """The backward formula, as ``torch.library.register_autograd`` takes it."""
        self._backward, self._setup_context = backward, setup_context

    def _run_setup_context(self, ctx, inputs, output) -> None:
        if self._setup_context is not None:
            self._setup_context(ctx, inputs, output)

    def _run_backward(self, ctx, *grads):
        if self._backward is None:
            raise RuntimeError(f"{self._qualname} has no autograd formula: it is not differentiable")
        return self._backward(ctx, *grads)


def operator(qualname: str, *, schema: str | None = None) -> Callable[[Callable], Operator]:
    """Decorator: the function becomes the operator ``qualname`` (``torchsgal::<name>``) with the
    given schema (``"(Tensor x, bool flag) -> Tensor"``), or the one ``torch.library.infer_schema``
    reads from its annotations; the function is its implementation on every device that has no
    ``register_kernel``."""
    def define(fn: Callable) -> Operator:
        return Operator(qualname, fn, schema)
    return define
