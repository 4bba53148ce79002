"""The compiled per-point loops (suit_ros/ops/kernels.py) against the array code they replace:
the same results, bit for bit, on LiDAR-shaped clouds and on the inputs users get wrong."""
from __future__ import annotations

import math
from typing import Any

from modelkit import cloud_in_grid, small_config
import numpy as np
import pytest
import torch

from suit_ros.model.detector import SUITDetector
from suit_ros.model.inference import inference_copy
from suit_ros.ops import kernels
from suit_ros.ops.geometry import CellIndex


def lidar_like(n: int, seed: int, lags: tuple[float, ...] = (0.0, 0.1, 0.2)) -> np.ndarray:
    """Rings of returns in scan order (range 2-80 m, some beyond the grid), several sweeps."""
    rng = np.random.default_rng(seed)
    parts = []
    for lag in lags:
        az = np.sort(rng.uniform(-np.pi, np.pi, n))
        rng_m = rng.uniform(2, 80, n) * rng.choice([1.0, 0.3], n, p=[0.7, 0.3])
        z = rng.uniform(-2.5, 5.0, n)
        parts.append(np.c_[rng_m * np.cos(az), rng_m * np.sin(az), z, rng.uniform(0, 1, n),
                           np.full(n, lag)])
    return np.concatenate(parts).astype(np.float32)


def test_the_compiled_pillar_encoder_equals_the_torch_one_bit_for_bit():
    """Folded inference copy, float32 and bfloat16 canvas: a batch of two clouds (points out
    of range in x, y and z, dense and single-point pillars), an empty cloud, one with every
    point out of range."""
    torch.manual_seed(0)
    model = SUITDetector(small_config()).eval()
    clouds = [torch.from_numpy(np.concatenate([cloud_in_grid(k) for k in range(6)])),
              torch.from_numpy(lidar_like(4000, 1)), torch.zeros(0, 5),
              torch.tensor([[90.0, 0.0, 0.0, 0.5, 0.0]])]
    for precision in ('float32', 'bfloat16'):
        enc = inference_copy(model, precision=precision).pillars
        with torch.inference_mode():
            assert enc.compiled(clouds)
            fast, occupied = enc.encode_clouds(clouds, occupancy=True)
            rows = torch.cat([torch.cat([torch.full((len(c), 1), float(i)), c], 1)
                              for i, c in enumerate(clouds)])
            slow = enc(rows, len(clouds))
            assert torch.equal(fast, slow)
            assert torch.equal(occupied, (slow != 0).any(dim=1))
            assert int((fast[0].abs().sum(0) > 0).sum()) > 100
            assert not fast[2:].any()


def test_the_encoder_takes_the_torch_path_when_training_or_with_gradients():
    enc = SUITDetector(small_config()).pillars
    cloud = [torch.from_numpy(lidar_like(100, 2))]
    assert not enc.compiled(cloud)                                  # training mode, a norm
    folded = inference_copy(SUITDetector(small_config()).eval()).pillars
    with torch.enable_grad():
        assert not folded.compiled(cloud)
    with torch.no_grad():
        assert folded.compiled(cloud)
        assert not folded.compiled([cloud[0].double()])


def test_pillar_features_refuses_writes_outside_the_image():
    """The compiled loop does not check its indices: the wrapper refuses what would write
    outside the image (a cell past the grid, an offset past the batch, mismatched sizes)."""
    cells, mean, top = kernels.pillar_max(lidar_like(500, 4), (-20, -20, -3, 20, 20, 3), 0.5,
                                          80, 80, np.ones((5, 4), np.float32))
    W, grid = np.ones((4, 10), np.float32), (-20.0, -20.0, 0.5, 80, 80)
    rows = np.zeros((2 * 80 * 80, 4), np.float32)
    kernels.pillar_features(top, mean, cells, W, None, grid, rows, 80 * 80)
    assert rows[80 * 80:].any() and not rows[:80 * 80].any()
    for bad in ({'offset': 80 * 80 + 1}, {'cells': cells + 80 * 80}, {'mean': mean[:-1]},
                {'occupied': np.zeros(5, bool)}, {'rows': np.zeros((80 * 80, 3), np.float32)}):
        args = {'top': top, 'mean': mean, 'cells': cells, 'W': W, 'bias': None, 'grid': grid,
                'rows': rows, 'offset': 0, 'occupied': None} | bad
        with pytest.raises(ValueError):
            kernels.pillar_features(**args)


def test_the_range_filter_keeps_what_the_array_mask_keeps():
    """The node's range filter: the rows the array code's mask keeps, in order, points on the
    limits (float32 ranges) included, empty clouds and clouds with nothing in range."""
    cloud = lidar_like(20000, 7)[:, :4].copy()
    cloud[:5, :2] = [[0.5, 0.0], [0.0, -0.5], [80.0, 0.0], [3.0, 4.0], [48.0, 64.0]]
    for lo, hi in ((0.5, 80.0), (5.0, 5.0), (0.0, 1e9), (200.0, 300.0)):
        r = np.hypot(cloud[:, 0], cloud[:, 1])
        want = cloud[(r >= lo) & (r <= hi)]
        got = kernels.in_range(cloud, np.float32(lo), np.float32(hi))
        assert got.shape == want.shape and got.tobytes() == want.tobytes()
    assert kernels.in_range(np.zeros((3, 4), np.float32), np.float32(0.0),
                            np.float32(1.0)).shape == (3, 4)
    assert kernels.in_range(cloud[:0], np.float32(0.0), np.float32(1.0)).shape == (0, 4)


def test_azimuth_counts_bin_as_numpy_does_in_float64():
    """The sector-gap check's returns per azimuth bin: the C library's atan2 binning in
    float64, on a cloud, strided xyz slices of float32 and float64 clouds, the axes and both
    zeros, points on the bin edges; a NaN counts nowhere. (The reference is ``math.atan2``:
    numpy's SIMD arctan2 on a CPU with AVX-512 differs from it in the last bit, which moves a
    point lying on a bin edge.)"""
    def atan2(p: np.ndarray) -> np.ndarray:
        return np.array([math.atan2(y, x) for x, y in p[:, :2].tolist()], np.float64)
    cloud = lidar_like(20000, 3)[:, :4].copy()
    cloud[:8, :2] = [[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0], [-1.0, -0.0],
                     [0.0, 0.0], [-0.0, -0.0], [1.0, -1e-30]]
    for pts, bins in ((cloud[:, :3], 72), (cloud.astype(np.float64)[:, :3], 72),
                      (cloud[:, :3], 360), (cloud[:, :2], 4)):
        az = atan2(pts.astype(np.float64)) % (2 * np.pi)
        k = np.minimum((az * (bins / (2 * np.pi))).astype(np.int64), bins - 1)
        want = np.bincount(k, minlength=bins)
        np.testing.assert_array_equal(kernels.azimuth_counts(pts, bins), want)
    edges = np.linspace(0, 2 * np.pi, 73)[:-1]
    ring = np.c_[np.cos(edges), np.sin(edges)]
    az = atan2(ring) % (2 * np.pi)
    want = np.bincount(np.minimum((az * (72 / (2 * np.pi))).astype(np.int64), 71), minlength=72)
    np.testing.assert_array_equal(kernels.azimuth_counts(ring, 72), want)
    nan = np.array([[np.nan, 1.0, 0.0], [1.0, 0.0, 0.0]], np.float32)
    assert kernels.azimuth_counts(nan, 4).tolist() == [1, 0, 0, 0]


def test_pillar_max_refuses_other_feature_counts():
    with pytest.raises(ValueError, match=r'\(N, 5\)'):
        kernels.pillar_max(np.zeros((3, 4), np.float32), (-1, -1, -1, 1, 1, 1), 0.5, 4, 4,
                           np.zeros((5, 2), np.float32))


def read_by_box(index: CellIndex, xy: np.ndarray) -> list[set[int]]:
    """Which points each rectangle of ``index`` tests: those whose grid cell lists it
    (``CellIndex.box_lists``; the cells by the array rule)."""
    start, owners = index.box_lists()
    ix = np.floor(xy[:, 0] / index.cell).astype(np.int64) - index.origin[0]
    iy = np.floor(xy[:, 1] / index.cell).astype(np.int64) - index.origin[1]
    ok = (ix >= 0) & (ix < index.shape[0]) & (iy >= 0) & (iy < index.shape[1])
    out: list[set[int]] = [set() for _ in index.cells]
    for i in np.flatnonzero(ok):
        k = ix[i] * index.shape[1] + iy[i]
        for b in owners[start[k]:start[k + 1]]:
            out[b].add(int(i))
    return out


def test_every_point_of_an_oriented_rectangle_is_in_its_selection():
    """A search band along a heading keeps only the cells it can touch, and loses no point."""
    rng = np.random.default_rng(5)
    xy = rng.uniform(-30, 30, (40_000, 2))
    band = np.array([[3.0, -4.0, 7.0, 1.2, 0.7], [-10.0, 12.0, 4.0, 1.0, -2.0]])
    r = band[:, 2] + band[:, 3]
    index = CellIndex(xy, band[:, :2] - r[:, None], band[:, :2] + r[:, None], 2.0,
                      oriented=band)
    square = CellIndex(xy, band[:, :2] - r[:, None], band[:, :2] + r[:, None], 2.0)
    banded, squared = read_by_box(index, xy), read_by_box(square, xy)
    for k, (cx, cy, hl, hw, yaw) in enumerate(band):
        d = xy - [cx, cy]
        u = d[:, 0] * np.cos(yaw) + d[:, 1] * np.sin(yaw)
        v = -d[:, 0] * np.sin(yaw) + d[:, 1] * np.cos(yaw)
        inside = np.flatnonzero((np.abs(u) <= hl) & (np.abs(v) <= hw))
        assert set(inside.tolist()) <= banded[k]
        assert len(banded[k]) < 0.7 * len(squared[k])                 # fewer points read


def test_distinct_values_equal_numpy_unique():
    rng = np.random.default_rng(6)
    lags = np.repeat(np.array([0.0, 0.1, 0.2], np.float32), 1000)
    lags[::97] = np.nan
    np.testing.assert_array_equal(kernels.distinct_values(lags),
                                  np.array([0.0, 0.1, 0.2], np.float32))
    many = rng.normal(size=500).astype(np.float32)                  # past the limit
    np.testing.assert_array_equal(kernels.distinct_values(many), np.unique(many))
    assert len(kernels.distinct_values(np.zeros(0, np.float32))) == 0
    assert len(kernels.distinct_values(np.full(4, np.nan, np.float32))) == 0


@pytest.mark.parametrize('carry', [False, True])
def test_after_the_warm_up_a_detector_step_compiles_nothing(carry):
    """The node warms the kernels up when it loads its model: its first cloud compiles no
    kernel (a multi-second stall) for the types a step uses, also with a carry branch (the
    carried samples' moves and the next memory's choice)."""
    from dataclasses import replace

    from suit_ros.model.streaming import StreamingDetector
    from suit_ros.tracking import TrackerConfig
    kernels.warm_up()
    dispatchers = [getattr(kernels, n) for n in dir(kernels)
                   if hasattr(getattr(kernels, n), 'signatures')]
    before = {d: set(map(str, d.signatures)) for d in dispatchers}
    cfg = small_config()
    if carry:
        cfg = replace(cfg, fusion_gate='carry_branch',
                      sampling=replace(cfg.sampling, carry_s=0.35, alpha=0.01, top_k=20))
    runner = StreamingDetector(SUITDetector(cfg).eval(), tracker=TrackerConfig())
    pose = np.eye(4)
    for t in range(3):
        pose[0, 3] = 0.5 * t
        runner.step(lidar_like(3000, 7 + t, lags=(0.0,))[:, :4], int(1e9 + t * 1e8), pose)
    new = {d.__name__: set(map(str, d.signatures)) - before[d] for d in dispatchers}
    assert not any(new.values()), new
    if carry:       # the carry chose the memory (only its choice sets the ages)
        assert runner.memory is not None and runner.memory.ages is not None


def test_a_moved_sweep_equals_the_float32_matrix_product():
    from suit_ros.model.sweeps import Sweep, accumulate_sweeps
    from suit_ros.ops.geometry import pose_from_xyz_rpy, se3_inverse
    T_bl = pose_from_xyz_rpy((0.9, 0.1, 1.8), (0.0, 0.02, 0.01))
    T0 = pose_from_xyz_rpy((250_000.0, -130_000.0, 40.0), (0.01, 0.0, 0.3))
    T1 = pose_from_xyz_rpy((250_000.8, -130_000.1, 40.0), (0.01, 0.0, 0.32))
    a, b = lidar_like(5000, 8, (0.0,))[:, :4], lidar_like(5000, 9, (0.05,))
    out = accumulate_sweeps([Sweep(a, T1, 2 * 10**9), Sweep(b, T0, 19 * 10**8)], T_bl)
    T = (T_bl @ se3_inverse(T1)) @ T0                   # as accumulate_sweeps composes it
    R, t = T[:3, :3].astype(np.float32), T[:3, 3].astype(np.float32)
    want = b[:, :3] @ R.T + t
    # equal to float32 rounding: BLAS and the kernel may order (and fuse) the three products
    # and the sum differently by CPU (one ulp was seen on an AVX-512 Xeon), while a product in
    # float64 or an unmoved sweep would be off by far more
    bound = 4 * np.finfo(np.float32).eps * (np.abs(b[:, :3]) @ np.abs(R.T) + np.abs(t))
    assert np.all(np.abs(out[5000:, :3] - want) <= bound)
    assert np.abs(out[5000:, :3] - b[:, :3]).max() > 0.1     # the sweep did move
    np.testing.assert_array_equal(out[5000:, 4], b[:, 4] + np.float32(0.1))
    np.testing.assert_array_equal(out[:5000, 3], a[:, 3])


def _numpy_sweep_velocities(pts: np.ndarray, boxes: np.ndarray, which: np.ndarray
                            ) -> tuple[np.ndarray, np.ndarray]:
    """sweep_velocities as array code, box by box (the implementation before the kernels)."""
    max_speed, bin_m, min_points = 20.0, 0.1, 10
    vel, ok = np.zeros((len(boxes), 2)), np.zeros(len(boxes), bool)
    pts = pts[(pts[:, 2] > 0.3) & (pts[:, 2] < 5.0)]
    past = np.unique(pts[:, 4][pts[:, 4] > 0])
    speeds = np.arange(-max_speed, max_speed + 1e-9, 0.25)
    reach = max_speed * float(past.max())
    for j in np.flatnonzero(which):
        cx, cy, cz, length, width, height, yaw = boxes[j]
        half = 0.5 * length + reach
        c, s = np.cos(yaw), np.sin(yaw)
        dx, dy = pts[:, 0] - cx, pts[:, 1] - cy
        u = dx * c + dy * s
        inside = ((np.abs(u) < half) & (np.abs(-dx * s + dy * c) < 0.5 * width + 0.3)
                  & (pts[:, 2] < cz + 0.5 * height + 0.3))
        bins = ((u[inside] + half) / bin_m).astype(np.int64)
        lag = pts[inside, 4]
        n_bins = int(2 * half / bin_m) + 1
        current = np.bincount(bins[lag == 0], minlength=n_bins).astype(np.float64)
        if current.sum() < min_points:
            continue
        score = np.zeros(len(speeds))
        for L in past:
            earlier = np.bincount(bins[lag == L], minlength=n_bins).astype(np.float64)
            if earlier.sum() < min_points:
                continue
            corr = np.correlate(current, earlier, 'full') / (current.sum() * earlier.sum())
            score += np.interp(speeds * L / bin_m + (len(current) - 1),
                               np.arange(len(corr)), corr)
            ok[j] = True
        if ok[j]:
            vel[j] = speeds[int(np.argmax(score))] * np.array([c, s])
    return vel, ok


def test_sweep_velocities_equal_the_array_code_on_moving_cars():
    """Cars at 0-15 m/s, three sweeps, boxes off by up to half a metre, and a ground."""
    from suit_ros.tracking import sweep_velocities
    rng = np.random.default_rng(10)
    parts, boxes = [lidar_like(20_000, 11)], []
    for _ in range(25):
        centre, yaw, speed = rng.uniform(-40, 40, 2), rng.uniform(-3, 3), rng.uniform(0, 15)
        heading = np.array([np.cos(yaw), np.sin(yaw)])
        for lag in (0.0, 0.1, 0.2):
            body = rng.uniform([-2.2, -0.9, 0.2], [2.2, 0.9, 1.5], (300, 3))
            xy = centre - speed * lag * heading + body[:, :1] * heading \
                + body[:, 1:2] * heading[::-1] * [-1, 1]
            parts.append(np.c_[xy, body[:, 2], np.full(300, 0.5), np.full(300, lag)])
        boxes.append([*(centre + rng.normal(0, 0.3, 2)), 0.8, 4.5, 1.9, 1.6, yaw])
    pts = np.concatenate(parts).astype(np.float32)
    boxes_a = np.array(boxes)
    which = rng.random(len(boxes_a)) < 0.9
    vel, ok, _ = sweep_velocities(pts, boxes_a, which)
    want_vel, want_ok = _numpy_sweep_velocities(pts, boxes_a, which)
    assert ok.sum() >= 15
    np.testing.assert_array_equal(ok, want_ok)
    np.testing.assert_array_equal(vel, want_vel)


def test_a_warmed_up_detector_answers_a_drive_as_a_fresh_one():
    """The warm-up's made-up frames leave nothing behind: memory, sweeps, tracks and track
    ids are those of a fresh detector (the shipped model, a synthetic drive)."""
    from suit_ros.checkpoint import default_checkpoint_path, load_checkpoint
    from suit_ros.data.sim import preset, sim_frames
    from suit_ros.evaluate import step_inputs
    from suit_ros.model.streaming import StreamingDetector
    from suit_ros.tracking import TrackerConfig
    model, _, _ = load_checkpoint(default_checkpoint_path(), 'cpu')
    fresh, warmed = (StreamingDetector(model, tracker=TrackerConfig()) for _ in range(2))
    tracks = warmed.tracks
    warmed.warm_up(points=5000)
    assert warmed.memory is None and len(warmed.sweeps) == 0
    assert warmed.tracks is tracks and len(tracks) == 0
    assert warmed.last_reset_reason == 'start'
    frames = list(sim_frames(preset('test-real', frames=4), 5))
    for f in frames:
        a, b = fresh.step(*step_inputs(f)), warmed.step(*step_inputs(f))
        np.testing.assert_array_equal(a.detections.boxes, b.detections.boxes)
        np.testing.assert_array_equal(a.detections.scores, b.detections.scores)
        np.testing.assert_array_equal(a.track_ids, b.track_ids)
    assert len(a.detections) > 0 and a.used_memory


def test_counts_and_sweep_velocities_take_float16_clouds():
    """Training drives are kept in float16: they are counted as their float64 values are."""
    from suit_ros.ops.geometry import count_points_in_boxes
    from suit_ros.tracking import sweep_velocities
    pts = lidar_like(3000, 12).astype(np.float16)
    boxes = np.array([[5.0, 2.0, 0.5, 4.5, 1.9, 1.6, 0.3], [-12.0, 7.0, 0.5, 4.5, 1.9, 1.6, 2.0]])
    wide = pts.astype(np.float64)
    np.testing.assert_array_equal(count_points_in_boxes(pts[:, :3], boxes),
                                  count_points_in_boxes(wide[:, :3], boxes))
    for a, b in zip(sweep_velocities(pts, boxes, np.ones(2, bool)),
                    sweep_velocities(wide, boxes, np.ones(2, bool))):
        np.testing.assert_array_equal(a, b)


def test_a_kernel_without_a_cache_location_still_compiles():
    """numba refuses to cache a function it cannot place on disk (here: one without a source
    file, as a read-only install and home would be); the kernel is compiled uncached."""
    namespace: dict[str, Any] = {}
    exec('def twice(x):\n    return 2 * x\n', namespace)
    twice = kernels.compiled()(namespace['twice'])
    assert twice(21) == 42


def test_the_compiled_pair_iou_equals_the_tensor_one():
    """Rotated BEV IoU of 6,000 pairs: random, identical, turned by 90 degrees, contained,
    touching edge to edge, far apart; the compiled loop gives the tensor code's values (the
    NMS decisions at 0.2 and 0.5 the same), and the NMS takes it for float32 CPU boxes."""
    from suit_ros.ops.iou import paired_bev_iou
    from suit_ros.ops.nms import pair_iou
    rng = np.random.default_rng(3)
    K = 6000
    a = np.c_[rng.uniform(-3, 3, (K, 2)), rng.uniform(-1, 1, K), rng.uniform(0.3, 6, (K, 3)),
              rng.uniform(-np.pi, np.pi, K)].astype(np.float32)
    b = a.copy()
    b[:, :2] += rng.normal(0, 1.0, (K, 2))
    b[:, 3:6] *= rng.uniform(0.7, 1.3, (K, 3))
    b[:, 6] += rng.normal(0, 0.5, K)
    b[:500] = a[:500]
    b[500:1000] = a[500:1000]
    b[500:1000, 6] += np.float32(np.pi / 2)
    b[1000:1500] = a[1000:1500]
    b[1000:1500, 3:5] *= 0.5
    a[1500:2000, 6] = 0
    b[1500:2000] = a[1500:2000]
    b[1500:2000, 0] += a[1500:2000, 3]
    b[2000:2500, :2] = a[2000:2500, :2] + 50
    want = paired_bev_iou(torch.from_numpy(a), torch.from_numpy(b)).numpy()
    got = kernels.paired_bev_iou(a, b)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)
    for threshold in (0.2, 0.5):
        assert np.array_equal(got > threshold, want > threshold)
    np.testing.assert_allclose(got[:500], 1.0, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(got[2000:2500], 0.0)
    assert 0.1 < float(np.mean(want[2500:] > 0)) < 1.0
    assert pair_iou(torch.from_numpy(a), torch.from_numpy(b)).numpy().tobytes() == got.tobytes()
    assert pair_iou(torch.from_numpy(a).double(), torch.from_numpy(b).double()).dtype == \
        torch.float64                               # float64 boxes keep the tensor code
    assert len(kernels.paired_bev_iou(a[:0], b[:0])) == 0


def test_the_memory_moves_the_same_compiled_as_in_tensors():
    """Inference moves a memory's cells, boxes and velocities in compiled passes
    (``move_cells``, ``move_boxes``); with autograd the tensor code runs: both give the same
    positions, boxes, velocities and ages on a batch of two frames with turning transforms."""
    from suit_ros.model.memory import (
        SparseMemory,
        moved_memory,
        rotate_velocities,
        transform_sample_positions,
    )
    rng = np.random.default_rng(3)
    M, P = 6, 9
    T = np.stack([np.eye(4), np.eye(4)])
    for b, yaw in enumerate((0.3, -1.2)):
        T[b, :2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
        T[b, :3, 3] = rng.uniform(-5, 5, 3)
    T[1, :3, :3] = T[1, :3, :3] @ np.array([[1, 0, 0], [0, np.cos(0.05), -np.sin(0.05)],
                                           [0, np.sin(0.05), np.cos(0.05)]])   # a roll
    mem = SparseMemory(torch.tensor([0, 1, 1, 0, 1, 0]),
                       torch.from_numpy(rng.uniform(-50, 50, (M, P, 2)).astype(np.float32)),
                       torch.zeros(M, P, 4), torch.ones(M, P), torch.ones(M, P, dtype=torch.bool),
                       torch.from_numpy(rng.uniform(-3, 3, (M, 7)).astype(np.float32)),
                       torch.from_numpy(rng.uniform(-9, 9, (M, 2)).astype(np.float32)),
                       [0, 0], np.stack([np.eye(4)] * 2), 3)
    shift = torch.from_numpy(rng.uniform(-1, 1, (M, 2)).astype(np.float32))
    results = []
    for grad in (False, True):
        with torch.set_grad_enabled(grad):
            pos = transform_sample_positions(mem, T)
            moved = moved_memory(mem, pos, shift, T, np.stack([np.eye(4)] * 2), [5, 7])
            results.append((pos, moved, rotate_velocities(mem.velocities, mem.batch_index, T)))
    (pos_c, mov_c, vel_c), (pos_t, mov_t, vel_t) = results
    torch.testing.assert_close(pos_c, pos_t, rtol=0, atol=2e-6)
    torch.testing.assert_close(mov_c.cell_xy, mov_t.cell_xy, rtol=0, atol=2e-6)
    torch.testing.assert_close(mov_c.boxes, mov_t.boxes, rtol=0, atol=2e-6)
    torch.testing.assert_close(mov_c.velocities, mov_t.velocities, rtol=0, atol=2e-6)
    torch.testing.assert_close(vel_c, vel_t, rtol=0, atol=2e-6)
    assert mov_c.age().tolist() == mov_t.age().tolist() == [5, 7, 7, 5, 7, 5]   # ns, by frame
    with pytest.raises(IndexError, match='without a transform'):
        kernels.move_cells(mem.cell_xy.numpy(), mem.boxes[:, 2].numpy().copy(), T[:1],
                           mem.batch_index.numpy(), np.empty((M, P, 2), np.float32))


def test_the_cell_flags_and_the_carry_cells_are_the_tensor_code_s():
    """The flags at the cells of metric positions (on the map's edges, off it, on cell
    borders) and the cells a carry head answers (within two cells of the carry term, less
    the observed ones) and those that feed them, compiled and as the tensor code finds them."""
    from suit_ros.model.grid import BEVGrid
    from suit_ros.model.head import dilated_cells, unflatten_cells
    from suit_ros.model.sampling import cell_flags
    grid = BEVGrid((-51.2, -51.2, -2.0, 51.2, 51.2, 4.5), 0.4, 2)
    g = torch.Generator().manual_seed(2)
    B, H, W = 2, grid.H, grid.W
    flags = torch.rand(B, H, W, generator=g) < 0.5
    xy = torch.rand(400, 2, generator=g) * 120 - 60
    xy[:8] = torch.tensor([[-51.2, -51.2], [51.2, 0.0], [0.0, 51.2], [51.19, 51.19],
                           [-51.21, 3.0], [0.8, 0.8], [0.0, 0.0], [-0.4, 0.4]])
    bi = torch.randint(0, B, (400,), generator=g)
    with torch.no_grad():
        fast = cell_flags(flags, bi, xy, grid)
    with torch.enable_grad():
        slow = cell_flags(flags, bi, xy, grid)
    assert torch.equal(fast, slow) and fast.any() and not fast.all()
    observed = torch.rand(B * H * W, generator=g) < 0.6
    index = torch.randint(0, B * H * W, (60,), generator=g)
    index = torch.cat([index, index[:4], torch.tensor([0, H * W - 1, B * H * W - 1])])
    near = dilated_cells(index, H, W, 2)
    want = near[~observed[near]]
    got = dilated_cells(index, H, W, 2, skip=observed.view(B, H, W))
    assert torch.equal(got, want)
    with pytest.raises(IndexError, match='off the map'):
        dilated_cells(torch.tensor([B * H * W]), H, W, 2, skip=observed.view(B, H, W))
    cells, flat, feeding, where = kernels.feeding_map(want.numpy(), B, H, W)
    assert torch.equal(torch.from_numpy(cells), unflatten_cells(want, H, W))
    assert torch.equal(torch.from_numpy(flat), dilated_cells(want, H, W, 1))
    assert torch.equal(torch.from_numpy(feeding), unflatten_cells(torch.from_numpy(flat), H, W))
    assert (where[flat] == np.arange(len(flat))).all()
    assert (np.delete(where, flat) == -1).all()
    with pytest.raises(IndexError, match='off the map'):
        kernels.feeding_map(np.array([B * H * W]), B, H, W)


def _random_memory(g: torch.Generator, M: int, B: int, ages: bool, own: bool) -> Any:
    from suit_ros.model.memory import SparseMemory
    P, C = 9, 5
    centre = torch.rand(M, 2, generator=g) * 110 - 55          # some off the map
    centre[: M // 4] = centre[M // 4: 2 * (M // 4)] + 0.3       # neighbours to suppress
    xy = centre[:, None] + torch.linspace(-0.4, 0.4, P)[None, :, None]
    probs = torch.rand(M, P, generator=g)
    probs[:3, P // 2] = probs[3, P // 2]                        # ties, kept in row order
    boxes = torch.cat([centre, torch.rand(M, 1, generator=g),
                       1 + 3 * torch.rand(M, 3, generator=g),
                       torch.rand(M, 1, generator=g) * 6], 1)
    return SparseMemory(torch.randint(0, B, (M,), generator=g), xy,
                        torch.randn(M, P, C, generator=g), probs,
                        torch.rand(M, P, generator=g) < 0.8, boxes,
                        torch.randn(M, 2, generator=g), [7] * B, np.stack([np.eye(4)] * B), 3,
                        torch.randint(0, 12, (M,), generator=g) * 100_000_000 if ages else None,
                        torch.rand(M, generator=g) < 0.5 if own else None)


@pytest.mark.parametrize('keep_new', [False, True])
@pytest.mark.parametrize('seed', [0, 1, 2, 3])
def test_the_next_memory_s_samples_are_the_tensor_code_s(keep_new, seed):
    """The carry's choice of the next memory's samples (``keep_carried``: this frame's and the
    carried ones, by tier, centre probability and the refined NMS) in one compiled pass and
    numpy, and by the tensor code: the same samples, rows and order; two frames, samples off
    the map, next to each other and next to the other memory's, tied probabilities, carried
    ones too old, with and without ages and own flags, no new or no carried samples."""
    from suit_ros.config import SamplingConfig
    from suit_ros.model.grid import BEVGrid
    from suit_ros.model.sampling import _keep_carried_compiled, keep_carried
    grid = BEVGrid((-51.2, -51.2, -2.0, 51.2, 51.2, 4.5), 0.4, 2)
    g = torch.Generator().manual_seed(seed)
    B = 2
    observed = torch.rand(B, grid.H, grid.W, generator=g) < 0.5
    new = _random_memory(g, 40, B, ages=False, own=seed == 2)
    carried = _random_memory(g, 60, B, ages=seed != 1, own=seed == 3)
    # carried samples on this frame's objects, 0.3 m off: the tiers decide between them
    carried.cell_xy[:15] = new.cell_xy[:15] + 0.3
    carried.boxes[:15] = new.boxes[:15]
    carried.boxes[:15, :2] += 0.3
    carried.batch_index[:15] = new.batch_index[:15]
    none = torch.zeros(0, dtype=torch.long)
    cfg = SamplingConfig(carry_s=0.8)
    results = []
    for a, b in ((new, carried), (new.select(none), carried), (new, carried.select(none))):
        with torch.no_grad():
            fast = _keep_carried_compiled(a, b, observed, cfg, grid, keep_new)
            assert fast is not None
            via = keep_carried(a, b, observed, cfg, grid, keep_new)
        with torch.enable_grad():
            slow = keep_carried(a, b, observed, cfg, grid, keep_new)
        for got in (fast, via):
            for f in ('batch_index', 'cell_xy', 'features', 'probs', 'mask', 'boxes',
                      'velocities'):
                assert torch.equal(getattr(got, f), getattr(slow, f)), f
            assert torch.equal(got.age(), slow.age())
            assert (got.own is None) == (slow.own is None)
            assert torch.equal(got.owned(), slow.owned())
            assert got.stamps_ns == slow.stamps_ns and got.window == slow.window
        results.append(slow)
    # with both memories: some of each kind kept and some dropped
    both = results[0]
    assert 0 < both.num_samples < new.num_samples + carried.num_samples
    is_new = (both.cell_xy[:, None] == new.cell_xy[None]).all(-1).all(-1).any(1)
    assert 0 < int(is_new.sum()) < both.num_samples
    # what the pass does not take (bfloat16 features, a map of another dtype): tensor code
    low = _random_memory(g, 4, B, ages=False, own=False)
    low.features = low.features.to(torch.bfloat16)
    with torch.no_grad():
        assert _keep_carried_compiled(low, carried, observed, cfg, grid, keep_new) is None
        assert _keep_carried_compiled(new, carried, observed.to(torch.uint8), cfg, grid,
                                      keep_new) is None


@pytest.mark.parametrize('low', [False, True])
def test_the_dense_spread_adds_what_the_sparse_term_adds(low):
    """A fold's ``K past`` and edge correction added into a whole channels-last map in one
    pass equal the term's rows added by ``index_add_`` (float32: to rounding; bfloat16: each
    add rounded to nearest even, within a bfloat16 step of the tensor code's)."""
    from suit_ros.model.fusion import PastTerm
    rng = np.random.default_rng(5)
    B, H, W, hc = 2, 7, 9, 4
    index = np.array([0, W - 1, H * W - 1, H * W, 2 * H * W - 1, 3 * W + 4, 3 * W + 4])
    spread = rng.normal(size=(len(index), 9, hc)).astype(np.float32)
    edge_index = np.array([0, 1, W, H * W - 1])
    edge_values = rng.normal(size=(len(edge_index), hc)).astype(np.float32)
    base = torch.from_numpy(rng.normal(size=(B * H * W, hc)).astype(np.float32))
    # the tensor code: each input row's taps as a term at the output cells they feed
    rows, cells = [], []
    for r, f in enumerate(index):
        b, y, x = f // (H * W), f // W % H, f % W
        for t in range(9):
            ty, tx = y - (t // 3 - 1), x - (t % 3 - 1)
            if 0 <= ty < H and 0 <= tx < W:
                cells.append((b * H + ty) * W + tx)
                rows.append(spread[r, t])
    for b in range(B):
        cells += list(b * H * W + edge_index)
        rows += list(edge_values)
    term = PastTerm(torch.tensor(cells), torch.from_numpy(np.stack(rows)), (B, hc, H, W))
    want = base.to(torch.bfloat16) if low else base.clone()
    want.index_add_(0, term.index, term.values.to(want.dtype))
    got = base.to(torch.bfloat16) if low else base.clone()
    if low:
        kernels.add_tap_spread_dense_bf16(got.view(torch.int16).numpy().view(np.uint16), spread,
                                          index, edge_index, edge_values, H, W)
        exact = base.double().index_add(0, term.index, term.values.double())
        assert ((got.double() - exact).abs() <= 2 * (exact.abs() + 1) / 128).all()
        torch.testing.assert_close(got.float(), want.float(), rtol=2 ** -6, atol=2 ** -6)
        assert not torch.equal(got, base.to(torch.bfloat16))
    else:
        kernels.add_tap_spread_dense(got.numpy(), spread, index, edge_index, edge_values, H, W)
        torch.testing.assert_close(got, want, rtol=1e-6, atol=1e-6)
    nan = torch.zeros(1, 1, dtype=torch.bfloat16)
    kernels.add_tap_spread_dense_bf16(nan.view(torch.int16).numpy().view(np.uint16),
                                      np.full((0, 9, 1), 0, np.float32), np.zeros(0, np.int64),
                                      np.zeros(1, np.int64), np.full((1, 1), np.nan, np.float32),
                                      1, 1)
    assert torch.isnan(nan).all()


def test_a_bfloat16_sum_rounds_to_nearest_even_as_torch_converts():
    """Each value added into a bfloat16 map is rounded as torch rounds a float32 to bfloat16
    (to nearest, ties to even): ties both ways, a carry into the exponent, a negative."""
    for start, add in ((1.0, 2 ** -8), (1.0 + 2 ** -7, 2 ** -8), (1.0, 2 ** -8 + 2 ** -20),
                       (2.0 - 2 ** -7, 2 ** -8), (-3.0, -0.01), (0.0, 1e-30)):
        got = torch.tensor([[start]], dtype=torch.bfloat16)
        kernels.add_tap_spread_dense_bf16(
            got.view(torch.int16).numpy().view(np.uint16), np.zeros((0, 9, 1), np.float32),
            np.zeros(0, np.int64), np.zeros(1, np.int64), np.full((1, 1), add, np.float32), 1, 1)
        want = (torch.tensor([[start]], dtype=torch.bfloat16).float()
                + torch.tensor(add, dtype=torch.float32)).to(torch.bfloat16)
        assert torch.equal(got, want), (start, add)
