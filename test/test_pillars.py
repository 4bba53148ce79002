"""The pillar encoder: pillarization, voxel keys, the time-lag scale, the cap, the folded
inference path."""
from __future__ import annotations

from modelkit import GRID, cloud_in_grid, small_config
import numpy as np
import torch

from suit_ros.model.detector import SUITDetector
from suit_ros.model.grid import BEVGrid
from suit_ros.model.pillars import PillarEncoder


def test_pillarization_matches_numpy_loop():
    torch.manual_seed(0)
    enc = PillarEncoder(GRID, 5, 8).eval()
    pts = torch.cat([torch.zeros(300, 1), torch.rand(300, 5) * torch.tensor([8, 8, 2, 1, 0])
                     - torch.tensor([4, 4, 1, 0, 0])], 1)
    pts = torch.cat([pts, torch.tensor([[0, 40.0, 0, 0, 0, 0]])])      # out of range: dropped
    with torch.no_grad():
        bev = enc(pts, 1)
        kept, inverse, keys = enc.voxelize(pts)
        assert len(kept) == 300
        # independent per-pillar max of the point features
        feats = torch.relu(enc.norm(enc.linear(_decorate(kept[:, 1:], inverse, keys))))
    for u, key in enumerate(keys.tolist()):
        iy, ix = (key // GRID.nx) % GRID.ny, key % GRID.nx
        ref = feats[inverse == u].max(0).values
        torch.testing.assert_close(bev[0, :, iy, ix], ref)
    assert int((bev.abs().sum(1) > 0).sum()) <= len(keys)


def _decorate(f, inverse, keys):
    out = []
    for i in range(len(f)):
        members = f[inverse == inverse[i]]
        mean = members[:, :3].mean(0)
        key = int(keys[inverse[i]])
        ix, iy = key % GRID.nx, (key // GRID.nx) % GRID.ny
        cx = (ix + 0.5) * GRID.pillar_size + GRID.point_range[0]
        cy = (iy + 0.5) * GRID.pillar_size + GRID.point_range[1]
        out.append(torch.cat([f[i], f[i, :3] - mean, torch.tensor([f[i, 0] - cx,
                                                                    f[i, 1] - cy])]))
    return torch.stack(out)


def test_voxelize_equals_torch_unique_over_batches():
    torch.manual_seed(1)
    enc = PillarEncoder(GRID, 5, 8)
    n = 5000
    pts = torch.cat([torch.randint(0, 3, (n, 1)).float(),
                     torch.randn(n, 2) * 8, torch.rand(n, 3) - 0.5], 1)
    kept, inverse, keys = enc.voxelize(pts)
    ix = ((kept[:, 1] - GRID.point_range[0]) / GRID.pillar_size).long()
    iy = ((kept[:, 2] - GRID.point_range[1]) / GRID.pillar_size).long()
    key = (kept[:, 0].long() * GRID.ny + iy) * GRID.nx + ix
    want_keys, want_inverse = torch.unique(key, return_inverse=True)
    assert torch.equal(keys, want_keys) and torch.equal(inverse, want_inverse)
    empty = enc.voxelize(torch.zeros(0, 6))
    assert empty[0].shape[0] == 0 and empty[2].numel() == 0


def test_time_scale_multiplies_the_lag_in_training_and_in_the_folded_copy():
    """``time_scale`` = the lag multiplied before the encoder, in the training path and in the
    folded inference path (which scales the weight column instead of the points)."""
    from suit_ros.model.inference import fold_batchnorm
    grid = BEVGrid((-25.6, -25.6, -3.0, 25.6, 25.6, 3.0), 0.4, 2)
    torch.manual_seed(0)
    plain = PillarEncoder(grid, 5, 16)
    plain.norm.running_mean.uniform_(-0.5, 0.5)                      # as after training
    scaled = PillarEncoder(grid, 5, 16, time_scale=10.0)
    scaled.load_state_dict(plain.state_dict())
    pts = torch.from_numpy(cloud_in_grid(1))
    pts[:, 4] = torch.randint(0, 3, (len(pts),)).float() * 0.1       # lags of 3 sweeps
    rows = torch.cat([torch.zeros(len(pts), 1), pts], 1)
    times10 = rows.clone()
    times10[:, 5] *= 10.0
    plain.eval()
    scaled.eval()
    with torch.no_grad():
        want = plain(times10, 1)
        assert torch.allclose(scaled(rows, 1), want, atol=1e-5)
        assert not torch.allclose(plain(rows, 1), want, atol=1e-3)   # the scale matters
        fold_batchnorm(plain)
        fold_batchnorm(scaled)
        assert torch.allclose(scaled(rows, 1), want, atol=1e-4)


def test_folded_pillars_are_the_same_in_chunks_of_points(monkeypatch):
    """The inference encoder takes its per-pillar max over chunks of points (no large fresh
    allocation per frame); the pseudo-image equals the one-chunk result exactly."""
    from suit_ros.model.inference import inference_copy
    torch.manual_seed(1)
    fast = inference_copy(SUITDetector(small_config()).eval(), channels_last=False)
    pts = torch.from_numpy(np.concatenate([cloud_in_grid(k) for k in range(8)]))
    rows = torch.cat([torch.zeros(len(pts), 1), pts], 1)
    with torch.no_grad():
        whole = fast.pillars(rows, 1)
        monkeypatch.setattr(type(fast.pillars), 'CHUNK', 97)
        assert len(rows) > 10 * 97
        assert torch.equal(fast.pillars(rows, 1), whole)


def test_pillar_cap_thins_only_dense_pillars_deterministically():
    """``pillars.max_points_per_pillar``: a pillar of c > cap points keeps about cap of them
    (a hash of the index, the same every call); sparser pillars keep every point; no pillar is
    emptied; 0 keeps everything."""
    grid = BEVGrid((-25.6, -25.6, -3.0, 25.6, 25.6, 3.0), 0.4, 2)
    enc = PillarEncoder(grid, 5, 16, max_points=32)
    g = torch.Generator().manual_seed(0)
    dense = torch.rand(2000, 5, generator=g) * torch.tensor([0.39, 0.39, 1, 1, 0]) \
        + torch.tensor([0.01, 0.01, 0, 0, 0])                          # one pillar
    sparse = torch.rand(20, 5, generator=g) * torch.tensor([0.39, 0.39, 1, 1, 0]) \
        + torch.tensor([4.01, 0.01, 0, 0, 0])                          # another pillar
    rows = torch.cat([torch.zeros(2020, 1), torch.cat([dense, sparse])], 1)
    kept = enc.cap(rows)
    assert torch.equal(kept, enc.cap(rows))
    in_dense = kept[:, 1] < 1.0
    assert 16 <= int(in_dense.sum()) <= 56 and int((~in_dense).sum()) == 20
    off, loose = PillarEncoder(grid, 5, 16).eval(), PillarEncoder(grid, 5, 16, 10_000).eval()
    loose.load_state_dict(off.state_dict())
    with torch.no_grad():                     # a cap above every pillar changes nothing
        assert torch.equal(loose(rows, 1), off(rows, 1))
        enc.load_state_dict(off.state_dict())
        enc.eval()
        assert not torch.equal(enc(rows, 1), off(rows, 1))        # the dense pillar thinned

