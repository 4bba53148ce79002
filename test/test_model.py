"""The SUIT model: targets, decoding, significant sampling, GeoNet, ego transform, fusion."""
from __future__ import annotations

from dataclasses import replace
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from suit_ros.config import BackboneConfig, ModelConfig, PillarConfig, SamplingConfig
from suit_ros.model.detector import SUITDetector
from suit_ros.model.fusion import sparse_past_term
from suit_ros.model.geonet import GeoNet
from suit_ros.model.grid import BEVGrid
from suit_ros.model.head import CenterHead, draw_gaussian, gaussian_radius
from suit_ros.model.memory import SparseMemory, transform_sample_positions
from suit_ros.model.pillars import PillarEncoder
from suit_ros.model.sampling import Samples, relaxation_window, significant_sampling
from suit_ros.model.streaming import StreamingDetector
from suit_ros.ops.geometry import ego_transform, pose_from_xyz_rpy, se3_inverse
from suit_ros.structures import Detections, Frame

GRID = BEVGrid((-25.6, -25.6, -3.0, 25.6, 25.6, 3.0), 0.4, 2)


def small_config(temporal='suit') -> ModelConfig:
    return ModelConfig(temporal=temporal,
                       pillars=PillarConfig(point_range=(-25.6, -25.6, -3.0, 25.6, 25.6, 3.0),
                                            pillar_size=0.4, channels=16),
                       backbone=BackboneConfig(num_filters=(16, 32, 32),
                                               num_upsample_filters=(16, 16, 16)))


def test_gaussian_radius_formula():
    # CornerNet's rule as CenterPoint applies it: the larger root of each of the three
    # quadratics, with the published "(b + sqrt(b^2 - 4ac)) / 2" normalisation (not / 2a)
    for h, w in [(5.6, 2.4), (1.0, 1.0), (14.0, 3.5)]:
        cands = []
        for a, b, c in [(1, h + w, w * h * 0.9 / 1.1), (4, 2 * (h + w), 0.9 * w * h),
                        (0.4, -0.2 * (h + w), -0.9 * w * h)]:
            root = max(np.roots([a, -b, c]).real)            # the true quadratic root
            cands.append(root * a)                           # == (b + sqrt(...)) / 2
        assert gaussian_radius(h, w, 0.1) == pytest.approx(min(cands), rel=1e-9)
    assert gaussian_radius(4.0, 2.0, 0.1) < 4.0


def test_draw_gaussian_peak_and_clipping():
    hm = torch.zeros(10, 10)
    draw_gaussian(hm, 0, 9, 2)
    assert hm[9, 0] == 1.0 and hm.max() == 1.0 and (hm > 0).sum() == 9   # 3x3 quarter left


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


def test_targets_decode_round_trip():
    head = CenterHead(8, 4, GRID)
    boxes = torch.tensor([[3.3, -7.1, -0.9, 4.5, 1.9, 1.6, 0.7],
                          [-10.2, 4.4, -0.8, 0.7, 0.6, 1.8, -2.5],
                          [15.0, 15.0, -0.5, 11.0, 2.9, 3.3, 3.0]])
    vel = torch.tensor([[5.0, -1.0], [0.5, 0.5], [0.0, 12.0]])
    labels = torch.tensor([0, 2, 1])
    tgt = head.build_targets([boxes], [vel], [labels])
    assert tgt['mask'].sum() == 3
    # predictions equal to the targets: logits +/- large, regression maps written at centres
    preds = {'heatmap': torch.where(tgt['heatmap'] == 1, 10.0, -10.0)}
    reg = torch.zeros(1, 10, GRID.H, GRID.W)
    for k in range(3):
        idx = tgt['index'][0, k]
        reg[0, :, idx // GRID.W, idx % GRID.W] = tgt['reg'][0, k]
    from suit_ros.model.head import REG_SLICES
    for name, (a, b) in REG_SLICES.items():
        preds[name] = reg[:, a:b]
    out = head.decode(preds, k=10, score_threshold=0.5)[0]
    order = torch.argsort(out['labels'])
    torch.testing.assert_close(out['boxes'][order], boxes[[0, 2, 1]], atol=1e-4, rtol=0)
    torch.testing.assert_close(out['velocities'][order], vel[[0, 2, 1]])
    assert out['labels'][order].tolist() == [0, 1, 2]


def peaks_heatmap(centres_cells, H=GRID.H, W=GRID.W):
    hm = torch.zeros(1, 4, H, W)
    for c, r in centres_cells:
        draw_gaussian(hm[0, 0], c, r, 2)
    return torch.logit(hm.clamp(1e-4, 1 - 1e-4))


def test_significant_sampling_one_sample_per_object():
    cells = [(10, 10), (30, 12), (40, 50), (12, 14)]                 # separated objects
    logits = peaks_heatmap(cells)

    def decode(b, c):   # a perfect regressor: every cell points at its object's centre
        xy = GRID.cell_to_xy(c)
        ctr = GRID.cell_to_xy(torch.tensor(cells))
        nearest = torch.cdist(xy, ctr).argmin(1)
        boxes = torch.cat([ctr[nearest], torch.zeros(len(c), 1),
                           torch.tensor([[1.0, 1.0, 1.5, 0.0]]).expand(len(c), 4)], 1)
        return boxes, torch.zeros(len(c), 2)
    s = significant_sampling(logits, decode, SamplingConfig(alpha=0.1, top_k=200), GRID)
    assert sorted(map(tuple, s.cells.tolist())) == sorted(cells)
    coarse = (torch.sigmoid(logits).amax(1) >= 0.1).sum().item()
    assert coarse > len(cells)                          # NMS did the reduction
    few = significant_sampling(logits, decode, SamplingConfig(alpha=0.1, top_k=3), GRID)
    assert len(few.cells) <= 3


@pytest.mark.parametrize('relax,cell,count', [
    ('square', (20, 20), 9), ('square', (0, 0), 4), ('circle', (20, 20), 5),
    ('rectangle', (20, 20), 3)])
def test_relaxation_windows(relax, cell, count):
    xy = GRID.cell_to_xy(torch.tensor([cell]))[0]
    box = torch.tensor([[xy[0], xy[1], 0.0, 2.0, 0.5, 1.5, 0.0]])     # 2.5 cells along x
    s = Samples(torch.zeros(1, dtype=torch.long), torch.tensor([cell]), torch.ones(1), box,
                torch.zeros(1, 2))
    cfg = SamplingConfig(relaxation=relax, window=3, radius=1.0)
    cells, mask = relaxation_window(s, cfg, GRID)
    assert int(mask.sum()) == count
    chosen = {tuple(c) for c in cells[0][mask[0]].tolist()}
    assert cell in chosen
    if relax == 'rectangle':
        assert chosen == {(cell[0] - 1, cell[1]), cell, (cell[0] + 1, cell[1])}


def test_ego_transform_static_object_lands_on_same_cell():
    world_xy = np.array([8.3, -4.1])
    p0 = pose_from_xyz_rpy((0, 0, 1.8), (0, 0, 0.0))
    p1 = pose_from_xyz_rpy((2.0, 0.5, 1.8), (0, 0, 0.3))
    in0 = (se3_inverse(p0) @ np.r_[world_xy, 0, 1])[:2]
    in1 = (se3_inverse(p1) @ np.r_[world_xy, 0, 1])[:2]
    mem = SparseMemory(torch.zeros(1, dtype=torch.long),
                       torch.tensor(in0, dtype=torch.float32)[None, None], torch.zeros(1, 1, 4),
                       torch.ones(1, 1), torch.ones(1, 1, dtype=torch.bool),
                       torch.tensor([[in0[0], in0[1], -1.8, 1, 1, 1, 0]], dtype=torch.float32),
                       torch.zeros(1, 2), [0], p0[None], 1)
    moved = transform_sample_positions(mem, ego_transform(p1, p0)[None])[0, 0]
    np.testing.assert_allclose(moved.numpy(), in1, atol=1e-5)
    assert torch.equal(torch.floor(GRID.xy_to_cell(moved)),
                       torch.floor(GRID.xy_to_cell(torch.tensor(in1, dtype=torch.float32))))


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


@pytest.mark.parametrize('dt', [0.1, 0.05])
def test_fusion_equation_11_single_sample(dt):
    C = 4
    proj = torch.nn.Linear(C, C, bias=False)
    with torch.no_grad():
        proj.weight.copy_(torch.eye(C) * 2.0)
    f = torch.tensor([[[1.0, 2.0, 3.0, 4.0]]])
    pos = torch.tensor([[[5.2, -3.3]]])
    vel_bins = torch.tensor([[0.0, 0.0], [10.0, 0.0]])
    disp = (vel_bins * dt)[None]                                    # (1, 2, 2)
    q = torch.tensor([[0.25, 0.75]])
    out = sparse_past_term(f, torch.tensor([[0.8]]), torch.ones(1, 1, dtype=torch.bool), pos,
                           torch.zeros(1, dtype=torch.long), disp, q, proj, GRID, 1)
    expect = torch.zeros(1, C, GRID.H, GRID.W)
    for k in range(2):
        c, r = torch.floor(GRID.xy_to_cell(pos[0, 0] + disp[0, k])).long().tolist()
        expect[0, :, r, c] += 0.8 * q[0, k] * 2.0 * f[0, 0]
    torch.testing.assert_close(out.dense(), expect)
    # added in place: only the touched rows of a channels-last map, a dense add otherwise
    base = torch.randn(1, C, GRID.H, GRID.W)
    for x in (base.clone(), base.clone().contiguous(memory_format=torch.channels_last)):
        assert out.add_to(x) is x
        torch.testing.assert_close(x, base + expect)
    with pytest.raises(ValueError, match='shape'):
        out.add_to(torch.zeros(2, C, GRID.H, GRID.W))


def test_sparse_past_term_in_place_add_has_the_dense_gradients():
    """Training adds the sparse term in place into the channels-last conv output: W2, the
    features and the current conv get the same gradients as with a dense add."""
    torch.manual_seed(0)
    C, M, P = 6, 5, 9
    conv = torch.nn.Conv2d(C, C, 1)
    proj = torch.nn.Linear(C, C, bias=False)
    feats = torch.randn(M, P, C, requires_grad=True)
    pos = torch.rand(M, P, 2) * 30 - 15
    disp = torch.randn(M, 3, 2)
    q = torch.softmax(torch.randn(M, 3), 1)
    probs = torch.rand(M, P)
    x = torch.randn(1, C, GRID.H, GRID.W).contiguous(memory_format=torch.channels_last)
    weight = torch.randn(1, C, GRID.H, GRID.W)
    grads = []
    for sparse in (True, False):
        for t in (conv.weight, proj.weight, feats):
            t.grad = None
        term = sparse_past_term(feats, probs, torch.ones(M, P, dtype=torch.bool), pos,
                                torch.zeros(M, dtype=torch.long), disp, q, proj, GRID, 1)
        out = conv(x)
        assert out.is_contiguous(memory_format=torch.channels_last)
        fused = term.add_to(out) if sparse else out + term.dense()
        (fused * weight).sum().backward()
        grads.append([t.grad.clone() for t in (conv.weight, proj.weight, feats)])
    for a, b in zip(*grads):
        torch.testing.assert_close(a, b)
    assert grads[0][1].abs().sum() > 0


def frame(t, seed=0, n=3000):
    rng = np.random.default_rng(seed)
    pts = np.c_[rng.uniform(-25, 25, (n, 2)), rng.uniform(-2, 0, n), rng.uniform(0, 1, n),
                np.zeros(n)].astype(np.float32)
    pts[:200, :2] = rng.normal([5 + 0.5 * t, 3], 0.5, (200, 2))      # a moving blob
    gt = Detections(np.array([[5 + 0.5 * t, 3, -1, 4.5, 1.9, 1.6, 0.0],
                              [-8, -6, -1, 0.7, 0.7, 1.8, 0]]),
                    np.array([[5.0, 0.0], [0.0, 0.0]]), np.ones(2), np.array([0, 2]))
    return Frame(pts, pose_from_xyz_rpy((t * 1.0, 0, 1.8), (0, 0, 0.01 * t)),
                 int(1e9 + t * 1e8), 'lidar', gt)


@pytest.mark.parametrize('temporal', ['none', 'dense', 'sparse', 'sparse_velocity', 'suit'])
def test_variants_train_and_stream(temporal):
    torch.manual_seed(0)
    model = SUITDetector(small_config(temporal))
    losses = model.forward_sequence([[frame(0), frame(1), frame(2)]])
    assert set(losses) == {'hm_loss', 'loc_loss', 'geo_loss', 'distill_loss', 'loss'}
    assert torch.isfinite(losses['loss'])
    losses['loss'].backward()
    runner = StreamingDetector(model)
    used = [runner.step(frame(t).points[:, :4], frame(t).stamp_ns,
                        frame(t).pose).used_memory for t in range(3)]
    assert used == [False] + [temporal != 'none'] * 2


def test_memory_size_constant_over_frames_and_reset():
    torch.manual_seed(0)
    runner = StreamingDetector(SUITDetector(small_config('suit')))
    f = frame(0)
    sizes = {}
    for t in range(10):
        r = runner.step(f.points, int(1e9 + t * 1e8), f.pose)
        sizes[t + 1] = r.memory_bytes
    assert sizes[2] == sizes[10] > 0
    assert runner.memory.num_samples <= runner.cfg.sampling.top_k
    runner.reset('test')
    assert runner.memory_bytes == 0
    assert not runner.step(f.points, int(3e9), f.pose).used_memory
    # time going backwards or a missing pose never fuses the memory
    assert not runner.step(f.points, int(2e9), f.pose).used_memory
    assert not runner.step(f.points, int(2.1e9), None).used_memory
    assert runner.memory is None and len(runner.sweeps) == 0
    dense = StreamingDetector(SUITDetector(small_config('dense')))
    for t in range(2):
        d = dense.step(f.points, int(1e9 + t * 1e8), f.pose)
    assert d.memory_bytes > sizes[10]


def test_velocity_filter_in_the_stream_follows_the_reset_rules():
    from suit_ros.tracking import FilterConfig
    torch.manual_seed(0)
    model = SUITDetector(small_config('suit'))
    K = len(model.cfg.class_names)
    filt = FilterConfig(birth_score=0.0)         # an untrained head is never confident
    runner = StreamingDetector(model, score_thresholds=[0.0] * K, velocity_filter=filt)
    f = frame(0)
    r1 = runner.step(f.points, int(1e9), f.pose)
    assert len(r1.detections) > 0 and (r1.track_ids > 0).all()
    assert len(set(r1.track_ids.tolist())) == len(r1.detections)
    r2 = runner.step(f.points, int(1.1e9), f.pose)
    assert set(r2.track_ids.tolist()) & set(r1.track_ids.tolist())
    assert runner.tracks is not None and 'tracking' in r2.timings
    tracks = runner.tracks
    runner.reset('drop memory', sweeps=False)     # the feature memory only: tracks stay
    assert len(tracks) > 0
    runner.set_velocity_filter(filt)              # unchanged settings keep the tracks
    assert runner.tracks is tracks
    runner.reset('test')
    assert len(tracks) == 0
    r3 = runner.step(f.points, int(1.2e9), None)  # no pose: no odometry frame to track in
    assert len(r3.detections) and not r3.track_ids.any()
    runner.set_velocity_filter(None)
    r4 = runner.step(f.points, int(1.3e9), f.pose)
    assert runner.tracks is None and not r4.track_ids.any()


@pytest.mark.slow
def test_optimisation_reduces_every_loss():
    torch.manual_seed(0)
    model = SUITDetector(small_config('suit'))
    batch = [[frame(t, seed=1) for t in range(3)]]
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    first = {k: float(v) for k, v in model.forward_sequence(batch).items()}
    for _ in range(25):
        losses = model.forward_sequence(batch)
        opt.zero_grad()
        losses['loss'].backward()
        opt.step()
    last = {k: float(v) for k, v in model.forward_sequence(batch).items()}
    for k in ('hm_loss', 'loc_loss', 'geo_loss'):
        assert last[k] < first[k], (k, first[k], last[k])
    assert math.isfinite(last['loss'])


def test_config_validation():
    from suit_ros.errors import ConfigError
    with pytest.raises(ConfigError, match='temporal'):
        ModelConfig(temporal='lstm')
    with pytest.raises(ConfigError, match='alpha'):
        replace(ModelConfig(), sampling=SamplingConfig(alpha=1.5))
    with pytest.raises(ConfigError, match='time_scale'):
        replace(ModelConfig(), pillars=PillarConfig(time_scale=0.0))
    # retired experiment settings: accepted at their 'off' value (older checkpoints carry
    # them), refused otherwise with where to find the experiment
    from suit_ros.config import model_config_from_dict
    old = ModelConfig().to_dict()
    old['memory_stride'] = 1
    old['pillars']['time_channels'] = False
    assert model_config_from_dict(old) == ModelConfig()
    old['pillars']['time_channels'] = True
    with pytest.raises(ConfigError, match='time_channels.*44202bd'):
        model_config_from_dict(old)
    with pytest.raises(ConfigError, match='memory_stride'):
        model_config_from_dict({'memory_stride': 3})


def test_decode_turns_moving_boxes_to_face_their_velocity():
    grid = BEVGrid((-25.6, -25.6, -3.0, 25.6, 25.6, 3.0), 0.4, 2)
    preds = {'heatmap': torch.full((1, 1, grid.H, grid.W), -10.0),
             'offset': torch.zeros(1, 2, grid.H, grid.W), 'z': torch.zeros(1, 1, grid.H, grid.W),
             'size': torch.zeros(1, 3, grid.H, grid.W), 'rot': torch.zeros(1, 2, grid.H, grid.W),
             'vel': torch.zeros(1, 2, grid.H, grid.W)}
    preds['rot'][0, 1] = 1.0                                      # yaw 0 everywhere
    for col, vx in ((10, -5.0), (20, -0.5), (30, 5.0)):          # backwards fast/slow, forwards
        preds['heatmap'][0, 0, 5, col] = 5.0
        preds['vel'][0, 0, 5, col] = vx
    yaws = {}
    for min_speed in (1.0, 0.0):
        head = CenterHead(8, 1, grid, 8, yaw_velocity_min_speed=min_speed)
        out = head.decode(preds, 10, 0.5, 'circle', 0.2, torch.tensor([0.1]), 10)[0]
        yaws[min_speed] = {int(c): float(y) for c, y in zip(out['cells'][:, 0],
                                                             out['boxes'][:, 6])}
    assert yaws[1.0][10] == pytest.approx(-math.pi) or yaws[1.0][10] == pytest.approx(math.pi)
    assert yaws[1.0][20] == 0.0 and yaws[1.0][30] == 0.0        # slow or forwards: untouched
    assert set(yaws[0.0].values()) == {0.0}                       # disabled


def test_streaming_candidates_and_literal_modes():
    from suit_ros.config import model_config_from_dict
    from suit_ros.errors import ConfigError
    runner = StreamingDetector(SUITDetector(small_config('none')), candidates=7)
    assert runner.candidates == 7
    runner.set_thresholds(candidates=None)
    assert runner.candidates == runner.cfg.head.top_k == 500
    with pytest.raises(ValueError, match='candidates'):
        runner.set_thresholds(candidates=0)
    with pytest.raises(ConfigError, match='head.nms must be one of'):
        model_config_from_dict({'head': {'nms': 'iou'}})
    assert model_config_from_dict({'sweeps': 3}).sweeps == 3
    with pytest.raises(ConfigError, match='sweeps'):
        model_config_from_dict({'sweeps': 0})


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


def cloud_in_grid(seed: int, n: int = 3000) -> np.ndarray:
    """``(n, 5)`` points (x, y, z, intensity, time lag 0) inside the small config's grid."""
    rng = np.random.default_rng(seed)
    return np.c_[rng.uniform(-20, 20, (n, 2)), rng.uniform(-1, 2, (n, 1)),
                 rng.uniform(0, 1, (n, 1)), np.zeros((n, 1))].astype(np.float32)


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


def test_inference_copy_folds_batch_norms_exactly():
    from suit_ros.model.inference import fold_batchnorm, inference_copy
    torch.manual_seed(0)
    model = SUITDetector(small_config())
    # non-trivial running statistics and affine parameters, as after training
    for m in model.modules():
        if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
            m.running_mean.uniform_(-0.5, 0.5)
            m.running_var.uniform_(0.5, 2.0)
            m.weight.data.uniform_(0.5, 1.5)
            m.bias.data.uniform_(-0.2, 0.2)
    model.eval()
    before = {k: v.clone() for k, v in model.state_dict().items()}
    fast = inference_copy(model)
    n_bn = sum(isinstance(m, torch.nn.modules.batchnorm._BatchNorm) for m in model.modules())
    assert n_bn > 0 and not any(isinstance(m, torch.nn.modules.batchnorm._BatchNorm)
                                for m in fast.modules())
    assert all(torch.equal(before[k], v) for k, v in model.state_dict().items())  # untouched
    convs = [m for m in fast.modules() if isinstance(m, torch.nn.Conv2d)]
    assert convs and all(m.weight.is_contiguous(memory_format=torch.channels_last)
                         for m in convs)                     # NHWC for oneDNN
    assert all(m.weight.is_contiguous() for m in inference_copy(model, channels_last=False)
               .modules() if isinstance(m, torch.nn.Conv2d))
    pts = cloud_in_grid(0)
    with torch.no_grad():
        a = model.encode([torch.from_numpy(pts)])
        b = fast.encode([torch.from_numpy(pts)])
        assert torch.allclose(a, b, atol=1e-4, rtol=1e-4)
        pa, pb = model.head(a), fast.head(b)
        for k in pa:
            assert torch.allclose(pa[k], pb[k], atol=1e-4, rtol=1e-4), k
    with pytest.raises(ValueError, match='eval mode'):
        fold_batchnorm(SUITDetector(small_config()).train())


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


def test_bfloat16_inference_copy_wraps_the_convolutions_and_keeps_float32_outputs():
    from suit_ros.model.inference import Cast, inference_copy
    torch.manual_seed(0)
    model = SUITDetector(small_config()).eval()
    fast = inference_copy(model, precision='bfloat16')
    assert isinstance(fast.backbone, Cast) and isinstance(fast.head.shared, Cast)
    assert isinstance(fast.fusion.current, Cast)
    assert all(p.dtype == torch.bfloat16 for p in fast.backbone.parameters())
    # the final 1x1 projections, the pillar encoder and GeoNet stay float32
    assert fast.head.heatmap[-1].weight.dtype == torch.float32
    assert fast.head.regression[-1].weight.dtype == torch.float32
    assert all(p.dtype == torch.float32 for p in fast.pillars.parameters())
    assert all(p.dtype == torch.float32 for p in fast.geonet.parameters())
    assert all(p.dtype == torch.float32 for p in model.parameters())        # untouched
    pts = cloud_in_grid(1)
    with torch.no_grad():
        a = model.encode([torch.from_numpy(pts)])
        b = fast.encode([torch.from_numpy(pts)])
        assert b.dtype == torch.bfloat16                 # handed on to the fusion as it is
        # bfloat16 keeps 8 significant bits: relative error about 2^-8 per layer
        assert (a - b.float()).abs().max() <= 0.05 * a.abs().max()
        fused = fast.fuse(b, None)
        assert fused.dtype == torch.bfloat16             # the head takes it as it is
        pa, pb = model.head(model.fuse(a, None)), fast.head(fused)
        for k in pa:
            assert pb[k].dtype == torch.float32
            assert (pa[k] - pb[k]).abs().max() <= 0.05 * pa[k].abs().max() + 1e-3, k
        # the memory holds float32 features, and the next frame's past term fuses in bfloat16
        memory = fast.sample_memory(fused, pb, np.eye(4)[None], [0])
        assert memory.num_samples > 0 and memory.features.dtype == torch.float32
        past, _ = fast.past_term(memory, np.eye(4)[None], [100_000_000])
        assert past is not None and past.values.dtype == torch.float32
        assert fast.fuse(b, past).dtype == torch.bfloat16
    with pytest.raises(ValueError, match='precision'):
        inference_copy(model, precision='float16')


def test_precision_auto_follows_the_cpu_flags(tmp_path, monkeypatch):
    from suit_ros.model import inference
    amx = tmp_path / 'amx'
    amx.write_text('processor\t: 0\nflags\t\t: fpu avx2 avx512f amx_bf16 amx_tile\n')
    plain = tmp_path / 'plain'
    plain.write_text('processor\t: 0\nflags\t\t: fpu avx2 avx512f avx512bw\n')
    assert inference.cpu_has_bf16_units(str(amx))
    assert not inference.cpu_has_bf16_units(str(plain))
    assert not inference.cpu_has_bf16_units(str(tmp_path / 'missing'))
    for has_units, want in ((True, 'bfloat16'), (False, 'float32')):
        monkeypatch.setattr(inference, 'cpu_has_bf16_units', lambda h=has_units: h)
        assert inference.resolve_precision('auto', 'cpu') == want
    assert inference.resolve_precision('auto', 'cuda') == 'float32'
    assert inference.resolve_precision('bfloat16', 'cpu') == 'bfloat16'
    with pytest.raises(ValueError, match='precision'):
        inference.resolve_precision('half', 'cpu')
    runner = StreamingDetector(SUITDetector(small_config()), precision='bfloat16')
    assert runner.precision == 'bfloat16'


def test_model_yaml_base_and_overrides(tmp_path):
    from suit_ros.config import load_model_config
    from suit_ros.errors import ConfigError
    repo = Path(__file__).resolve().parents[1]
    shipped = load_model_config(repo / 'params/model_cpu_time10.yaml')
    base = load_model_config(repo / 'params/model_cpu.yaml')
    assert shipped.pillars.time_scale == 10.0 and base.pillars.time_scale == 1.0
    assert shipped.diff(base) == ['pillars.time_scale']
    (tmp_path / 'a.yaml').write_text('_base_: b.yaml\nmodel:\n  sweeps: 2\n')
    (tmp_path / 'b.yaml').write_text('_base_: a.yaml\n')
    with pytest.raises(ConfigError, match='cycle'):
        load_model_config(tmp_path / 'a.yaml')


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
