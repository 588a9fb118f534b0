"""Python and PyTorch protocols of the group classes, over all seven groups: components round
trips, membership checks, iteration and truth value, equality, serialisation, pytrees (torch.func
transforms taking and returning group objects) and scalar arguments."""
from __future__ import annotations

import pytest
import torch

from torchsgal import ALL_GROUPS, SGal3

IDS = lambda g: g.__name__  # noqa: E731
F64 = torch.float64


@pytest.mark.parametrize("G", ALL_GROUPS, ids=IDS)
def test_from_components_of_functional_components_round_trip(G):
    """The class constructor takes what the functional layer's components returns: the same
    batch shape (no extra axis broadcasting in) and the same matrix."""
    M = G.random((4,), dtype=F64, generator=torch.Generator().manual_seed(1)).as_matrix()
    parts = G._f.components(M)
    g = G.from_components(*parts)
    assert g.batch_shape == (4,)
    # Sim3 stores 1/s: the round trip through s is exact up to one rounding
    torch.testing.assert_close(g.as_matrix(), M, rtol=3e-16, atol=0)
    # and under vmap, one element at a time
    logs = torch.func.vmap(lambda m: G.from_components(*G._f.components(m)).log())(M)
    assert logs.shape == (4, G.dof)


def test_sgal3_components_time_shape():
    g = SGal3.random((4, 2), dtype=F64)
    C, v, r, tau = g._f.components(g.as_matrix())
    assert tau.shape == (4, 2) and torch.equal(tau, g.time())
