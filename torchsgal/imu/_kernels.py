"""The IMU preintegration kernel as a torch operator: ``torch.ops.torchsgal.imu_preintegrate``.

One registration that eager code, torch.func.vmap and torch.compile all see
(``functional.registration``, through ``torch.library``): the operator preintegrates n
flattened windows of K samples and returns their increments and the node sums from which
``preintegrate`` forms the isotropic covariance and the bias Jacobian (``moments._node_moments``,
Simpson's rule on each sample: instants and midpoints, docs/guide/imu.md).

* CPU: the C loop of ``_native_imu.h`` (the extension ``torchsgal.imu._native``, built by
  ``pip install`` where a C compiler is found), one window at a time in double precision,
  windows split over ``torch.get_num_threads()`` threads; where it was not built, or is switched
  off (``functional.native.enabled()``: ``TORCHSGAL_NATIVE=0``, or a ``native.disabled()`` block
  of the calling thread), the tensor code below.
* Other devices: the tensor code (``_fast_path._blocked``: the same arithmetic as batched
  tensor operations, in blocks of windows).
* Fake tensors (torch.compile, meta): shapes only.
* vmap: the windows are independent, so the vmapped dimension joins the window batch.

No autograd formula is registered: ``preintegrate`` calls the operator only where nothing
records a derivative (``functional._blocking.unobserved``: plain CPU tensors, no autograd, no
torch.func transform, not compiling), and its differentiable path is the tensor code
(``preintegration._integrate``).  A backward through the operator raises.
"""
import math

import torch

from ..functional import checks, native
from ..functional.registration import operator

try:
    from . import _native as _lib  # type: ignore[attr-defined]  # compiled: mypy reads no .so
except ImportError:  # not compiled: the tensor code runs everywhere
    _lib = None

if _lib is not None:
    native.set_constants(_lib)

# Offsets of the node sums in the operator's (n, 117) output (_native_imu.h, IMU_W ... IMU_Y),
# as the dict of moments._node_moments: name -> (offset, shape).
MOMENTS = {"w": (0, ()), "wt": (1, ()), "wtt": (2, ()), "wl": (3, (3,)), "wv": (6, (3,)),
           "outer": (9, (6, 6)), "Y": (45, (8, 3, 3))}
WIDTH = 117


def available() -> bool:
    """Whether the IMU C kernel was compiled for this installation."""
    return _lib is not None


def node_sums(moments: torch.Tensor) -> dict[str, torch.Tensor]:
    """The dict of ``moments._node_moments`` (views, each (n, ...)) of the operator's
    packed (n, 117) node sums."""
    n = moments.shape[0]
    return {k: moments[:, o : o + math.prod(shape)].reshape(n, *shape) for k, (o, shape) in MOMENTS.items()}


def _pack(sums: dict[str, torch.Tensor], n: int) -> torch.Tensor:
    """The packed (n, 117) node sums of a ``_node_moments`` dict (the inverse of ``node_sums``)."""
    return torch.cat([sums[k].reshape(n, -1) for k in MOMENTS], dim=1)


def _check(gyro, acc, dt, b_g, b_a, nodes) -> tuple[int, int]:
    """(n, K) of valid operator arguments; a TypeError or ValueError naming the argument else."""
    checks.floating(gyro, "gyro")
    checks.same_device_dtype(gyro=gyro, acc=acc, dt=dt, b_g=b_g, b_a=b_a)
    checks.boolean(nodes, "nodes")
    if gyro.dim() != 3 or gyro.shape[-1] != 3 or gyro.shape[1] < 1:
        raise ValueError(f"gyro must have shape (n, K, 3) with K >= 1 samples, got {tuple(gyro.shape)}")
    n, K = gyro.shape[0], gyro.shape[1]
    for name, t, shape in (("acc", acc, (n, K, 3)), ("dt", dt, (n, K)), ("b_g", b_g, (n, 3)), ("b_a", b_a, (n, 3))):
        if t.shape != shape:
            raise ValueError(f"{name} must have shape {shape} (gyro is {tuple(gyro.shape)}), got {tuple(t.shape)}")
    return n, K


def _tensor_code(gyro, acc, dt, b_g, b_a, nodes: bool) -> tuple[torch.Tensor, torch.Tensor]:
    n, _ = _check(gyro, acc, dt, b_g, b_a, nodes)
    if n == 0:
        return gyro.new_empty(0, 5, 5), gyro.new_empty(0, WIDTH if nodes else 0)
    from ._fast_path import _blocked  # _fast_path imports this module

    delta, sums, _ = _blocked(gyro, acc, dt, b_g, b_a, nodes)
    return delta, _pack(sums, n) if sums is not None else gyro.new_empty(n, 0)


@operator(
    "torchsgal::imu_preintegrate",
    schema="(Tensor gyro, Tensor acc, Tensor dt, Tensor b_g, Tensor b_a, bool nodes) -> (Tensor, Tensor)")
def imu_preintegrate(gyro: torch.Tensor, acc: torch.Tensor, dt: torch.Tensor, b_g: torch.Tensor,
                     b_a: torch.Tensor, nodes: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """(delta (n, 5, 5), node sums (n, 117), or (n, 0) without ``nodes``) of n windows: gyro and
    acc (n, K, 3), dt (n, K), biases b_g, b_a (n, 3), all of one float dtype and device, K >= 1.
    The sums are packed in the order of ``MOMENTS`` (``node_sums`` unpacks them), the identity
    node included.  Not differentiable (see the module's docstring)."""
    return _tensor_code(gyro, acc, dt, b_g, b_a, nodes)


@imu_preintegrate.register_kernel("cpu")
def _cpu(gyro, acc, dt, b_g, b_a, nodes):
    """The C loop where it was built and is switched on in the calling thread, else the tensor code."""
    if _lib is None or not native.enabled():
        return _tensor_code(gyro, acc, dt, b_g, b_a, nodes)
    n, K = _check(gyro, acc, dt, b_g, b_a, nodes)
    ins = [t.resolve_neg().contiguous() for t in (gyro, acc, dt, b_g, b_a)]  # the values, packed
    delta = torch.empty(n, 5, 5, dtype=gyro.dtype)
    moments = torch.empty(n, WIDTH if nodes else 0, dtype=gyro.dtype)
    _lib.imu_preintegrate(*(t.data_ptr() for t in ins), delta.data_ptr(), moments.data_ptr() if nodes else 0,
                          n, K, torch.get_num_threads(), gyro.dtype is torch.float64)
    return delta, moments


@imu_preintegrate.register_fake
def _fake(gyro, acc, dt, b_g, b_a, nodes):
    n, _ = _check(gyro, acc, dt, b_g, b_a, nodes)
    return gyro.new_empty(n, 5, 5), gyro.new_empty(n, WIDTH if nodes else 0)


@imu_preintegrate.register_vmap
def _vmap(info, in_dims, gyro, acc, dt, b_g, b_a, nodes):
    """Windows are independent: the vmapped dimension (size B) becomes part of the window batch,
    (B, n, ...) -> (B n, ...), and the results are split back to (B, n, ...)."""
    B = info.batch_size
    args = [x.movedim(d, 0) if d is not None else x.expand(B, *x.shape)
            for x, d in zip((gyro, acc, dt, b_g, b_a), in_dims[:5])]
    n = args[2].shape[1]
    delta, moments = torch.ops.torchsgal.imu_preintegrate(*(x.reshape(B * n, *x.shape[2:]) for x in args), nodes)
    return (delta.view(B, n, 5, 5), moments.view(B, n, moments.shape[-1])), (0, 0)
