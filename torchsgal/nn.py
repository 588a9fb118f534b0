"""Group elements as trainable parameters of ``torch.nn`` modules.

A ``GroupParameter`` holds an element x of any group (any batch shape) as an anchor and a
tangent perturbation on the right (CONVENTIONS.md):

    x = anchor exp(delta),  delta an nn.Parameter (..., dof), zero at the anchor.

Any ``torch.optim`` optimiser updates ``delta`` as an ordinary Euclidean parameter; the
gradient it sees is the right-trivialised gradient of the loss at ``anchor exp(delta)``.
Re-anchoring (``retract_``) moves the anchor to x and sets ``delta`` back to zero, so that
``delta`` stays small, where exp's Jacobian J_r(delta) is close to the identity.

Optimiser state at re-anchoring: kept as it is.  The old and new coordinates of a nearby
element differ by J_r(delta) = I + O(|delta|): anchor exp(delta + e) ~ anchor exp(delta)
exp(J_r(delta) e).  Re-anchored after every step, delta is one step, so momentum (SGD's
``momentum_buffer``) and moment estimates (Adam's ``exp_avg``, ``exp_avg_sq``) stay valid to
first order in the step; resetting them instead would restart Adam's bias correction at every
step.  ``retract_(optimizer=..., reset_state=True)`` drops the state of the re-anchored
parameters where a large move makes the old estimates meaningless.
"""
from __future__ import annotations

from collections.abc import Iterator
from typing import Any, Generic, TypeVar

import torch
from torch import nn
from torch.utils.hooks import RemovableHandle

from .functional import checks
from .functional._blocking import values_readable
from .groups import LieGroup

G = TypeVar("G", bound=LieGroup)
PROJECT_EVERY = 64  # retract_ puts the anchor back on the group every this many re-anchorings
LOAD_TOL = 1e-4  # load_state_dict's membership tolerance for anchors: from_matrix's float32 one

__all__ = ["GroupParameter", "group_parameters", "retract_all_", "retract_after_step"]


def _check_loaded_anchor(module, state_dict, prefix, local_metadata, strict, missing_keys,
                         unexpected_keys, error_msgs) -> None:
    """A state dict's anchor must be an element of the module's group (a state saved from
    another group of the same matrix size, or a spoiled one, would load without a word)."""
    key = prefix + "anchor"
    anchor = state_dict.get(key)
    if not isinstance(anchor, torch.Tensor) or anchor.shape != module.anchor.shape:
        return  # torch reports a missing key or a size mismatch itself
    if anchor.dtype not in (torch.float32, torch.float64):  # checked as it will be stored
        anchor = anchor.to(module.anchor.dtype)
    # Within float32's tolerance whatever the dtype: a float64 state may hold float32-rounded
    # anchors (a float32 module converted by module.to(torch.float64)), and the test is for
    # another group's or a spoiled state, off the group by O(1), not by rounding.
    try:
        module.group.from_matrix(anchor, check=True, tol=LOAD_TOL)
    except (TypeError, ValueError) as err:  # raised here: torch would still copy the anchor
        raise ValueError(f"{key} is not an element of {module.group.__name__} (a state dict of "
                         f"another group or a spoiled one): {err}") from None


def _check_loaded_delta(module, state_dict, prefix, local_metadata, strict, missing_keys,
                        unexpected_keys, error_msgs) -> None:
    """A state dict's delta must be finite (a spoiled state, NaN or inf, would load without a
    word and make every value NaN); refused before torch copies it, as the anchor is."""
    key = prefix + "delta"
    delta = state_dict.get(key)
    if not isinstance(delta, torch.Tensor) or delta.shape != module.delta.shape:
        return  # torch reports a missing key or a size mismatch itself
    if values_readable(delta) and not bool(torch.isfinite(delta).all()):
        raise ValueError(f"{key} must be finite (a spoiled state dict): found "
                         f"{int((~torch.isfinite(delta)).sum())} non-finite entries of "
                         f"{delta.numel()}")


class GroupParameter(nn.Module, Generic[G]):
    """A trainable element ``anchor exp(delta)`` of a group, batched as the element given.

    ``anchor`` is a buffer (the matrices (..., n, n)), ``delta`` an ``nn.Parameter`` (..., dof),
    zero at construction; both are in ``state_dict`` and follow ``module.to(...)``.  The group
    (``group``, a class such as ``torchsgal.SE3``) is fixed at construction: load a state dict
    into a ``GroupParameter`` of the same group and batch shape (an anchor that is not an
    element of the group, or a non-finite delta, is refused by ``load_state_dict``; membership is
    tested within ``LOAD_TOL`` = 1e-4 whatever the dtype, as a float64 state may hold anchors
    rounded in float32, and the test is for another group's or a spoiled state, off by O(1)).

    Example::

        pose = GroupParameter(ts.SE3.identity(8))
        opt = torch.optim.Adam(pose.parameters(), lr=1e-2)
        retract_after_step(opt, pose)       # re-anchor after every opt.step()
        for _ in range(100):
            opt.zero_grad()
            loss = ((pose().act(p, point_axes=1) - q) ** 2).sum()
            loss.backward()
            opt.step()
    """

    anchor: torch.Tensor
    delta: nn.Parameter

    def __init__(self, element: G, requires_grad: bool = True) -> None:
        """``element``: the initial value, an element of any group (its class is kept: a subclass
        of SE3 gives values of that subclass); its matrices are copied, not shared."""
        super().__init__()
        if not isinstance(element, LieGroup):
            raise TypeError(f"element must be a group element (torchsgal.SE3, ...), got {type(element).__name__}")
        requires_grad = checks.boolean(requires_grad, "requires_grad")
        self.group: type[G] = type(element)
        matrix = element.as_matrix().detach().clone()
        self.register_buffer("anchor", matrix)
        delta = matrix.new_zeros(*element.batch_shape, element.dof)
        self.delta = nn.Parameter(delta, requires_grad=requires_grad)
        self._retractions = 0  # re-anchorings so far (see retract_)
        self.register_load_state_dict_pre_hook(_check_loaded_anchor)
        self.register_load_state_dict_pre_hook(_check_loaded_delta)

    @property
    def value(self) -> G:
        """The element ``anchor exp(delta)``, differentiable with respect to ``delta``."""
        return self.group.from_matrix(self.anchor).rplus(self.delta)

    def forward(self) -> G:
        """The element ``anchor exp(delta)`` (the same as ``value``)."""
        return self.value

    @property
    def batch_shape(self) -> torch.Size:
        """The batch shape of the element."""
        return self.delta.shape[:-1]

    @torch.no_grad()
    def retract_(self, optimizer: torch.optim.Optimizer | None = None, reset_state: bool = False) -> GroupParameter[G]:
        """Re-anchors in place: ``anchor <- anchor exp(delta)``, ``delta <- 0``; the value is
        unchanged (to rounding) and the Parameter object stays the same, so optimisers holding it
        go on.  Every ``PROJECT_EVERY``-th re-anchoring takes ``exp(log(.))`` of the product, which
        puts the anchor back on the group to rounding (a product of many steps drifts off it by
        rounding errors that add up).

        ``optimizer`` and ``reset_state``: with ``reset_state=True``, the optimiser's state of
        ``delta`` (momenta, moment estimates, step count) is dropped, as for a new parameter; by
        default it is kept (see the module docstring).  Returns this module."""
        reset_state = checks.boolean(reset_state, "reset_state")
        if optimizer is not None and not isinstance(optimizer, torch.optim.Optimizer):
            raise TypeError(f"optimizer must be None or a torch.optim.Optimizer, got {type(optimizer).__name__}")
        if reset_state and optimizer is None:
            raise ValueError("reset_state=True needs the optimizer whose state to reset")
        moved = self.group.from_matrix(self.anchor).rplus(self.delta.detach())
        self._retractions += 1
        if self._retractions % PROJECT_EVERY == 0:  # back on the group (products drift off it)
            moved = self.group.exp(moved.log())
        self.anchor.copy_(moved.as_matrix())
        self.delta.zero_()
        if reset_state and optimizer is not None:
            optimizer.state.pop(self.delta, None)
        return self

    def extra_repr(self) -> str:
        return (f"group={self.group.__name__}, batch_shape={tuple(self.batch_shape)}, "
                f"dtype={self.delta.dtype}, device={self.delta.device}")


def group_parameters(module: nn.Module) -> Iterator[GroupParameter[Any]]:
    """The ``GroupParameter`` submodules of ``module`` (itself included)."""
    if not isinstance(module, nn.Module):
        raise TypeError(f"module must be a torch.nn.Module, got {type(module).__name__}")
    return (m for m in module.modules() if isinstance(m, GroupParameter))


def retract_all_(module: nn.Module, optimizer: torch.optim.Optimizer | None = None,
                 reset_state: bool = False) -> nn.Module:
    """``retract_`` on every ``GroupParameter`` in ``module`` (itself included); returns it."""
    reset_state = checks.boolean(reset_state, "reset_state")
    if optimizer is not None and not isinstance(optimizer, torch.optim.Optimizer):
        raise TypeError(f"optimizer must be None or a torch.optim.Optimizer, got {type(optimizer).__name__}")
    for p in group_parameters(module):
        p.retract_(optimizer, reset_state)
    return module


def retract_after_step(optimizer: torch.optim.Optimizer, module: nn.Module,
                       reset_state: bool = False) -> RemovableHandle:
    """Re-anchors every ``GroupParameter`` in ``module`` after each ``optimizer.step()``
    (``Optimizer.register_step_post_hook``); ``handle.remove()`` stops it."""
    if not isinstance(optimizer, torch.optim.Optimizer):
        raise TypeError(f"optimizer must be a torch.optim.Optimizer, got {type(optimizer).__name__}")
    if not isinstance(module, nn.Module):
        raise TypeError(f"module must be a torch.nn.Module, got {type(module).__name__}")
    reset_state = checks.boolean(reset_state, "reset_state")

    def hook(opt: torch.optim.Optimizer, args: Any, kwargs: Any) -> None:
        retract_all_(module, opt, reset_state)

    return optimizer.register_step_post_hook(hook)
