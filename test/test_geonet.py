"""GeoNet: displacement bins, targets and learning them."""
from __future__ import annotations

import pytest
import torch

from suit_ros.model.geonet import GeoNet


def test_geonet_target_bins():
    g = GeoNet(8, 3, bins=7, velocity_step=5.0)
    v = torch.tensor([[0.0, 0.0], [5.0, 0.0], [-10.0, 15.0], [40.0, -40.0], [2.4, -2.6]])
    assert g.target_bins(v).tolist() == [24, 25, 43, 6, 17]
    # a bin's displacement is its velocity times the real gap: 10 Hz vs 20 Hz
    k = 25
    assert g.bin_velocities[k].tolist() == [5.0, 0.0]
    assert (g.bin_velocities[k] * 0.1).tolist() == pytest.approx([0.5, 0.0])
    assert (g.bin_velocities[k] * 0.05).tolist() == pytest.approx([0.25, 0.0])
    logits = g(torch.randn(5, 8, 3, 3))
    assert logits.shape == (5, 49)


@pytest.mark.slow
def test_geonet_learns_bins_from_the_head_velocity():
    """With velocity_input the displacement bin is learnable from the velocity alone."""
    torch.manual_seed(0)
    g = GeoNet(4, 3, bins=7, velocity_step=5.0, velocity_input=True)
    with pytest.raises(ValueError, match='velocities'):
        g(torch.zeros(1, 4, 3, 3))
    v = (torch.rand(256, 2) - 0.5) * 30.0
    patches = torch.randn(256, 4, 3, 3)                 # no information in the features
    opt = torch.optim.Adam(g.parameters(), lr=1e-2)
    for _ in range(300):
        loss = g.loss(g(patches, v), v)
        opt.zero_grad()
        loss.backward()
        opt.step()
    acc = (g(patches, v).argmax(1) == g.target_bins(v)).float().mean()
    assert acc > 0.9, float(acc)

