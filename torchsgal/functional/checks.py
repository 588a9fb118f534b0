"""Input validation: every error names the argument, what was expected and what was given.

Only metadata (shape, dtype, device) is inspected, so these checks cost no host sync and
are transparent to torch.func.vmap and torch.compile.
"""
from __future__ import annotations

import math
import numbers
import sys
from typing import cast

import torch

SUPPORTED_DTYPES = (torch.float32, torch.float64)


def floating(x, name: str) -> torch.Tensor:
    """A tensor of a supported dtype: float32 or float64.  Half precision (float16, bfloat16)
    is refused rather than silently computed: the closed forms, their thresholds and the tests
    are made for float32 and float64."""
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    dense(x, name)
    if x.dtype not in SUPPORTED_DTYPES:
        hint = "; convert with .float() or .double()" if x.is_floating_point() else ""
        raise TypeError(
            f"{name} must have a floating dtype (torch.float32 or torch.float64), got {x.dtype}{hint}"
        )
    return x


def dense(x: torch.Tensor, name: str) -> torch.Tensor:
    """A tensor of the strided (dense) layout: sparse and other layouts are refused by name
    rather than failing inside torch's kernels."""
    if x.layout != torch.strided:
        raise TypeError(f"{name} must be a dense (strided) torch.Tensor, got layout {x.layout}; "
                        f"convert with .to_dense()")
    return x


def numbers_as_tensor(value, name: str, dtype: torch.dtype, device) -> torch.Tensor:
    """A tensor argument that may also be given as a real number or a (nested) sequence of
    them, converted to ``dtype`` on ``device``; a tensor is returned as it is (dense).  A
    string, a bool (also inside a sequence or numpy array), or anything torch cannot read as
    numbers, is a TypeError naming the argument."""
    if isinstance(value, torch.Tensor):
        return dense(value, name)
    message = (f"{name} must be a torch.Tensor, a real number or a sequence of real numbers, "
               f"got {value!r}")
    if isinstance(value, (str, bytes)):
        raise TypeError(message)
    if holds_bool(value):  # a bool is no number here (torch reads True as 1.0)
        raise TypeError(f"{name} must be a torch.Tensor, a real number or a sequence of real "
                        f"numbers (not bools), got {value!r}")
    try:
        return torch.as_tensor(value, dtype=dtype, device=device)
    except (TypeError, ValueError, RuntimeError):
        raise TypeError(message) from None


def holds_bool(value) -> bool:
    """Whether ``value`` is a bool (Python or numpy) or a (nested) list, tuple or numpy array
    holding one: torch would read True as 1.0, but a bool is no number where numbers are asked
    for (``numbers_as_tensor``)."""
    np = sys.modules.get("numpy")  # a numpy bool or array can only come from an imported numpy
    if isinstance(value, bool) or (np is not None and isinstance(value, np.bool_)):
        return True
    if np is not None and isinstance(value, np.ndarray):
        if value.dtype == np.bool_:
            return True
        return value.dtype == object and any(holds_bool(v) for v in value.flat)
    if isinstance(value, (list, tuple)):
        return any(holds_bool(v) for v in value)
    return False


def dtype_arg(dtype, name: str = "dtype") -> torch.dtype:
    """A dtype argument (identity, random, ...): float32 or float64."""
    if dtype not in SUPPORTED_DTYPES:
        raise TypeError(f"{name} must be torch.float32 or torch.float64, got {dtype}")
    return dtype


def vector(x, size: int, name: str) -> torch.Tensor:
    """A tensor of shape (..., size)."""
    floating(x, name)
    if x.dim() < 1 or x.shape[-1] != size:
        raise ValueError(f"{name} must have shape (..., {size}), got {tuple(x.shape)}")
    return x


def matrix(x, n: int, name: str) -> torch.Tensor:
    """A tensor of shape (..., n, n)."""
    floating(x, name)
    if x.dim() < 2 or x.shape[-2:] != (n, n):
        raise ValueError(f"{name} must have shape (..., {n}, {n}), got {tuple(x.shape)}")
    return x


def same_device_dtype(**tensors: torch.Tensor) -> None:
    items = list(tensors.items())
    (n0, t0) = items[0]
    for n, t in items[1:]:
        if t.device != t0.device:
            raise ValueError(
                f"{n} is on {t.device} but {n0} is on {t0.device}; move them to one device"
            )
        if t.dtype != t0.dtype:
            raise TypeError(f"{n} has dtype {t.dtype} but {n0} has dtype {t0.dtype}")


def broadcast_shapes(*shapes) -> torch.Size:
    """``torch.broadcast_shapes`` of shapes (torch.Size or tuples of ints), the same result and
    the same RuntimeError, computed in Python: ~1 us for two shapes where torch's costs 6-10 us
    (it builds its result through tensor metadata), paid by every call that broadcasts batches.
    While torch.compile traces, torch's function (symbolic sizes)."""
    if not shapes:
        return torch.Size()
    first = shapes[0]
    if all(s == first for s in shapes[1:]):
        return torch.Size(first)
    if torch.compiler.is_compiling():
        return torch.broadcast_shapes(*shapes)
    out = [1] * max(len(s) for s in shapes)
    for s in shapes:
        offset = len(out) - len(s)
        for i, size in enumerate(s):
            held = out[offset + i]
            if size != held:
                if held == 1:
                    out[offset + i] = size
                elif size != 1:
                    return torch.broadcast_shapes(*shapes)  # raises torch's error
    return torch.Size(out)


def broadcast_batch(**batch_shapes: torch.Size) -> torch.Size:
    try:
        return broadcast_shapes(*batch_shapes.values())
    except RuntimeError:
        desc = ", ".join(f"{k} {tuple(v)}" for k, v in batch_shapes.items())
        raise ValueError(f"batch shapes do not broadcast: {desc}") from None


def binary(a: torch.Tensor, a_tail: int, b: torch.Tensor, b_tail: int, a_name: str, b_name: str):
    """Checks device, dtype and broadcastable batch shapes of two operands."""
    if a.device != b.device or a.dtype != b.dtype:
        same_device_dtype(**{a_name: a, b_name: b})
    a_batch, b_batch = a.shape[: a.dim() - a_tail], b.shape[: b.dim() - b_tail]
    if a_batch != b_batch:  # equal shapes broadcast
        broadcast_batch(**{a_name: a_batch, b_name: b_batch})


def matrix_pair(a, b, n: int, a_name: str, b_name: str) -> None:
    """Two (..., n, n) operands with one dtype and device and broadcastable batch shapes."""
    matrix(a, n, a_name)
    matrix(b, n, b_name)
    binary(a, 2, b, 2, a_name, b_name)


def components(**parts):
    """from_components' arguments: name -> (tensor, trailing shape).  Each a supported float
    with that trailing shape, one dtype and device, batches broadcast; returns the tensors
    expanded to the common batch (views)."""
    for name, (t, tail) in parts.items():
        floating(t, name)
        if t.dim() < len(tail) or tuple(t.shape[t.dim() - len(tail):]) != tail:
            want = ", ".join(["..."] + [str(k) for k in tail])
            raise ValueError(f"{name} must have shape ({want}), got {tuple(t.shape)}")
    same_device_dtype(**{n: t for n, (t, _) in parts.items()})
    batch = broadcast_batch(**{n: t.shape[: t.dim() - len(tail)] for n, (t, tail) in parts.items()})
    # one tuple argument: expand(*()) (an unbatched scalar part) would be a call without size
    return [t.expand(tuple(batch) + tuple(tail)) for t, tail in parts.values()]


def integer(value, name: str, minimum: int | None = None) -> int:
    """A Python/numpy integer (bool refused), at least ``minimum``: for counts and sizes.
    TypeError for another type, ValueError below ``minimum``; one message for both."""
    bound = "" if minimum is None else f" >= {minimum}"
    message = f"{name} must be an integer{bound}, got {value!r}"
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise TypeError(message)
    if minimum is not None and value < minimum:
        raise ValueError(message)
    return int(value)


def shape(batch_shape, name: str) -> tuple[int, ...]:
    """A shape argument: an int n (meaning (n,)) or a sequence of ints >= 0 (numpy integers and
    traced sizes too)."""
    if isinstance(batch_shape, (numbers.Integral, torch.SymInt)) and not isinstance(batch_shape, bool):
        batch_shape = (batch_shape,)  # numpy integers are Integral
    try:
        dims = tuple(batch_shape)
    except TypeError:
        raise TypeError(f"{name} must be an int or a sequence of ints, "
                        f"got {type(batch_shape).__name__}") from None
    sizes: list[int] = []
    for s in dims:
        if isinstance(s, torch.SymInt):  # a traced size (torch.compile, dynamic shapes)
            sizes.append(cast(int, s))  # a SymInt stands in for an int in shapes
            continue
        if isinstance(s, bool) or not isinstance(s, numbers.Integral):  # numpy integers are Integral
            raise TypeError(f"{name} must be an int or a sequence of ints, got {batch_shape!r}")
        sizes.append(int(s))
        if sizes[-1] < 0:
            raise ValueError(f"{name} must have sizes >= 0, got {dims}")
    return tuple(sizes)


def boolean(value, name: str) -> bool:
    """A flag (``check=...``): a Python or numpy bool only, so that a string such as "no", an
    integer or a tensor is refused rather than read by its truth value.  TypeError otherwise."""
    if isinstance(value, bool):
        return value
    np = sys.modules.get("numpy")  # a numpy bool can only come from an imported numpy
    if np is not None and isinstance(value, np.bool_):
        return bool(value)
    raise TypeError(f"{name} must be True or False, got {value!r}")


_BOUNDS = {"": lambda v: True, ">= 0": lambda v: v >= 0, "> 0": lambda v: v > 0,
           "in [0, 1]": lambda v: 0 <= v <= 1, "in [-40, 40]": lambda v: -40 <= v <= 40}


def finite_number(value, name: str, bound: str = "") -> float:
    """A finite real number (bool refused); ``bound`` one of "", ">= 0", "> 0", "in [0, 1]",
    "in [-40, 40]".
    TypeError for another type, ValueError for a non-finite or out-of-bound value."""
    ok = _BOUNDS[bound]
    if type(value) is float and math.isfinite(value) and ok(value):  # the common case, no message
        return value
    message = f"{name} must be a finite number{' ' + bound if bound else ''}, got {value!r}"
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(message)
    try:
        finite = math.isfinite(value)  # an int beyond the float range overflows
    except OverflowError:
        finite = False
    if not finite or not ok(value):
        raise ValueError(message)
    return float(value)
