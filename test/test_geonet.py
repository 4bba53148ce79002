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


@pytest.mark.parametrize('velocity_input', [False, True])
def test_geonet_as_products_gives_the_convolutions_logits(velocity_input):
    """An inference copy's GeoNet runs its three convolutions over the window x window patch
    as three matrix products (composed once from the convolutions): the same logits up to
    float rounding, for no sample, one and many; another patch size still takes the
    convolutions."""
    torch.manual_seed(1)
    g = GeoNet(6, 3, bins=7, channels=8, velocity_step=5.0, velocity_input=velocity_input).eval()
    with torch.no_grad():
        for p in g.parameters():
            p.normal_(0, 0.3)
    import copy
    fast = copy.deepcopy(g)
    assert fast.as_products() == 3
    with torch.no_grad():
        for m in (0, 1, 40):
            patches, v = torch.randn(m, 6, 3, 3), torch.randn(m, 2) * 8
            want = g(patches, v if velocity_input else None)
            got = fast(patches, v if velocity_input else None)
            assert got.shape == want.shape == (m, 49)
            torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)
            # a memory's samples as stored: (M, P, C) rows, zero off their mask
            feats, mask = torch.randn(m, 9, 6), torch.rand(m, 9) > 0.3
            want = g(feats.mul(mask[..., None]).permute(0, 2, 1).reshape(m, 6, 3, 3),
                     v if velocity_input else None)
            for net in (g, fast):
                torch.testing.assert_close(net.memory_logits(feats, mask,
                                                             v if velocity_input else None),
                                           want, rtol=1e-5, atol=1e-5)
        big = torch.randn(2, 6, 5, 5)
        v2 = torch.randn(2, 2)
        torch.testing.assert_close(fast(big, v2 if velocity_input else None),
                                   g(big, v2 if velocity_input else None))


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

