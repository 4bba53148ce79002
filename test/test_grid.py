"""The BEV grid's helpers (suit_ros/model/grid.py)."""
from __future__ import annotations

import pytest
import torch


@pytest.mark.parametrize('stride, radius', [(4, 1), (4, 0), (2, 2), (3, 1)])
def test_pooled_occupancy_is_the_max_pools_it_replaced(stride, radius):
    """Head-cell occupancy from pillar occupancy equals the float max pools it replaced (a
    stride pool, then a padded 2r+1 one), a batch of two, a grid the stride does not divide:
    the compiled pass the CPU takes and the tensor code elsewhere alike."""
    from suit_ros.model.grid import pooled_occupancy
    g = torch.Generator().manual_seed(stride * 10 + radius)
    occ = torch.rand(2, 50, 61, generator=g) < 0.02
    want = torch.nn.functional.max_pool2d(occ[:, None].float(), stride, stride)
    if radius:
        want = torch.nn.functional.max_pool2d(want, 2 * radius + 1, 1, radius)
    for compiled in (True, False):
        assert torch.equal(pooled_occupancy(occ, stride, radius, compiled), want[:, 0] > 0)
    empty = torch.zeros(1, 8, 8, dtype=torch.bool)
    assert not pooled_occupancy(empty, stride, radius).any()
