"""Chain products by log-depth trees of batched products: the window product E_0 E_1 ... E_{K-1}
and the suffix products S_k = E_k ... E_{K-1} (a work-efficient parallel scan) of a chain of K
square matrices, and the same trees along any axis for a product ``mul`` of one's choice
(preintegration.py runs them on SGal3's packed layout, functional.sgal3.compose_packed)."""
from __future__ import annotations

import torch

from ..functional import checks


def _along(E: torch.Tensor, axis: int, index) -> torch.Tensor:
    """E indexed by ``index`` (an int or a slice) on ``axis`` (non-negative)."""
    return E[(slice(None),) * axis + (index,)]


def _pair_products(E: torch.Tensor, mul, axis: int) -> torch.Tensor:
    """E_0 E_1, E_2 E_3, ... along ``axis`` (an odd tail kept): ceil(K/2) factors."""
    K = E.shape[axis]
    head = mul(_along(E, axis, slice(0, K - 1, 2)), _along(E, axis, slice(1, K, 2)))
    if K % 2:
        head = torch.cat((head, _along(E, axis, slice(K - 1, None))), dim=axis)
    return head


def _window_product(E: torch.Tensor, mul, axis: int) -> torch.Tensor:
    while E.shape[axis] > 1:
        E = _pair_products(E, mul, axis)
    return _along(E, axis, 0)


def _suffix_products(E: torch.Tensor, mul, axis: int, identity: torch.Tensor) -> torch.Tensor:
    """S_k = E_k ... E_{K-1} along ``axis``; ``identity`` broadcasts against one factor."""
    K = E.shape[axis]
    if K == 1:
        return E
    S_pairs = _suffix_products(_pair_products(E, mul, axis), mul, axis, identity)  # S_pairs[j] = S_{2j}
    # S_{2j+1} = E_{2j+1} S_{2j+2}, with S_K = I.
    n_odd = K // 2
    one = identity.expand_as(_along(S_pairs, axis, slice(0, 1)))
    odd = mul(_along(E, axis, slice(1, None, 2)),
              _along(torch.cat((S_pairs, one), dim=axis), axis, slice(1, n_odd + 1)))
    inter = torch.stack((_along(S_pairs, axis, slice(0, n_odd)), odd), dim=axis + 1).flatten(axis, axis + 1)
    return torch.cat((inter, _along(S_pairs, axis, slice(n_odd, None))), dim=axis) if K % 2 else inter


def _check_chain(E, name: str = "E") -> None:
    checks.floating(E, name)
    if E.dim() < 3 or E.shape[-1] != E.shape[-2]:
        raise ValueError(f"{name} must have shape (..., K, n, n) (K square matrices), got "
                         f"{tuple(E.shape)}")


def window_product(E: torch.Tensor) -> torch.Tensor:
    """E_0 E_1 ... E_{K-1} of (..., K, n, n) by a log-depth tree of batched products; the
    identity (..., n, n) for an empty chain (K = 0).  Always a new tensor (never a view of E)."""
    _check_chain(E)
    if E.shape[-3] == 0:
        eye = torch.eye(E.shape[-1], dtype=E.dtype, device=E.device)
        return eye.expand(*E.shape[:-3], *eye.shape).clone()
    if E.shape[-3] == 1:
        return E[..., 0, :, :].clone()  # a new tensor, as for any other K
    return _window_product(E, torch.matmul, E.dim() - 3)


def suffix_products(E: torch.Tensor) -> torch.Tensor:
    """S_k = E_k E_{k+1} ... E_{K-1} for k = 0..K-1 of (..., K, n, n) (a work-efficient parallel
    scan: 2 log2 K levels of batched products, about 2K products in all); empty (..., 0, n, n)
    for an empty chain (K = 0).  Always a new tensor (never E or a view of it)."""
    _check_chain(E)
    if E.shape[-3] <= 1:
        return E.clone()  # a new tensor, as for any other K
    eye = torch.eye(E.shape[-1], dtype=E.dtype, device=E.device)
    return _suffix_products(E, torch.matmul, E.dim() - 3, eye)
