"""Every use of a private PyTorch interface, in one place, each with a fallback.

The package relies on public torch API everywhere else (``tests/test_compat.py`` checks that no
other module names ``torch._``).  The interfaces below have no public equivalent; each is looked
up once, and where a torch release moves or removes it the fallback keeps results correct at
some cost in speed (``tests/test_compat.py`` runs the library on every fallback):

=============================  =====================================  ==============================
what                           private interface                      fallback
=============================  =====================================  ==============================
is a tensor a torch.func       ``torch._C._functorch.                 every tensor counts as wrapped:
wrapper?                       is_functorch_wrapped_tensor``          the plain closed forms run
how many forward-mode          ``torch._functorch.pyfunctorch.        nested whenever wrapped: the
transforms are active?         retrieve_all_functorch_interpreters``  closed forms under autograd
a fake-tensor trace?           ``torch._C._get_dispatch_mode``        always: constants not cached
autograd.Function.apply        ``torch.autograd.function.             ``Function.apply`` as it is
without signature binding      _SingleLevelFunction``
a getter folded as constant    the ``_dynamo_marked_constant`` mark   the same mark (an attribute:
by torch.compile               of ``assume_constant_result``          ignored where unknown)
group classes as pytree nodes  ``torch.utils._pytree.                 not registered: torch.func
(torch.func takes and returns  register_pytree_node``                 takes the elements' matrices
group elements)                                                       (``g.as_matrix()``)
=============================  =====================================  ==============================

The bound on torch in ``pyproject.toml`` (checked in CI) names the releases these were tested on.
"""
from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch

try:
    _is_wrapped_tensor: Callable[[torch.Tensor], bool] | None = torch._C._functorch.is_functorch_wrapped_tensor
except AttributeError:  # pragma: no cover - exercised by tests/test_compat.py's fallback runs
    _is_wrapped_tensor = None

_TransformType: Any
_interpreters: Callable[[], list[Any]] | None
try:
    from torch._C._functorch import TransformType as _TransformType
    from torch._functorch.pyfunctorch import retrieve_all_functorch_interpreters as _interpreters
except ImportError:  # pragma: no cover
    _TransformType = _interpreters = None

try:
    _get_dispatch_mode: Callable[[Any], Any] | None = torch._C._get_dispatch_mode
    _FAKE_KEY: Any = torch._C._TorchDispatchModeKey.FAKE
except AttributeError:  # pragma: no cover
    _get_dispatch_mode = _FAKE_KEY = None

_pytree: Any
try:
    from torch.utils import _pytree
except ImportError:  # pragma: no cover
    _pytree = None

_SingleLevelFunction: Any
try:
    from torch._functorch.utils import unwrap_dead_wrappers as _unwrap_dead_wrappers
    from torch.autograd.function import _SingleLevelFunction

    _transforms_active: Callable[[], bool] | None = torch._C._are_functorch_transforms_active
except ImportError:  # pragma: no cover
    _SingleLevelFunction = None
    _transforms_active = None


def is_functorch_wrapped(t: torch.Tensor) -> bool:
    """Whether ``t`` is a torch.func wrapper (inside vmap, grad, jacrev, jacfwd, ...)."""
    return True if _is_wrapped_tensor is None else bool(_is_wrapped_tensor(t))


def forward_mode_depth() -> int:
    """How many torch.func forward-mode transforms (jvp, jacfwd) are active; 2 (nested) where
    torch offers no way to count them, so that callers take their always-correct path."""
    if _interpreters is None or _TransformType is None:
        return 2
    return sum(i.key() == _TransformType.Jvp for i in _interpreters())


def fake_tensor_mode_active() -> bool:
    """Whether a FakeTensorMode (tracing without data, outside torch.compile) is active; True
    where torch offers no way to tell, so that callers build fresh constants."""
    if _get_dispatch_mode is None:
        return True
    return _get_dispatch_mode(_FAKE_KEY) is not None


def register_pytree_node(cls: type, flatten: Callable[[Any], tuple[list[Any], Any]],
                         unflatten: Callable[[list[Any], Any], Any], leaf_attribute: str) -> bool:
    """Registers ``cls`` as a pytree node whose one leaf is the attribute ``leaf_attribute``
    (``flatten(obj) -> ([leaf], context)``, ``unflatten([leaf], context) -> obj``), so that
    torch.func transforms take and return its instances; False, registering nothing, where
    torch offers no registry (its instances are then opaque to torch.func: pass tensors)."""
    if _pytree is None:
        return False

    def flatten_with_keys(obj: Any) -> tuple[list[Any], Any]:
        leaves, context = flatten(obj)
        return [(_pytree.GetAttrKey(leaf_attribute), leaves[0])], context

    _pytree.register_pytree_node(cls, flatten, unflatten,
                                 serialized_type_name=f"{cls.__module__}.{cls.__qualname__}",
                                 flatten_with_keys_fn=flatten_with_keys)
    return True


def mark_compile_constant(getter: Callable[[], Any]) -> Callable[[], Any]:
    """Marks a zero-argument getter so that torch.compile folds its result into the graph as a
    constant: the attribute ``torch.compiler.assume_constant_result`` sets (torch 2.1-2.13), set
    directly because calling that function imports torch's compiler stack (~1.3 s at import)."""
    getter._dynamo_marked_constant = True  # type: ignore[attr-defined]
    return getter


class FastApply:
    """Mixin for ``torch.autograd.Function`` subclasses: ``apply`` as torch's ``Function.apply``
    minus its ``inspect.signature`` binding of default arguments (the forwards it serves have
    none), which costs ~25 us per call in torch 2.13, several times the rest of the call for
    small batches.  Outside torch.func transforms it calls the C ``_FunctionBase.apply`` exactly
    as torch's eager branch does (dead functorch wrappers unwrapped first); inside them, or where
    torch's layout differs, torch's own ``apply``."""

    @classmethod
    def apply(cls, *args: Any) -> Any:
        if _SingleLevelFunction is not None and _transforms_active is not None and not _transforms_active():
            return super(_SingleLevelFunction, cls).apply(*_unwrap_dead_wrappers(args))  # type: ignore[misc]
        return super().apply(*args)  # type: ignore[misc]


def torch_version() -> str:
    """torch's version string."""
    return str(torch.version.__version__)
