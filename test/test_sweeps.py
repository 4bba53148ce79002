"""Multi-sweep accumulation: poses, extrinsic, time lags, the bounded buffer and its resets."""
from __future__ import annotations

import numpy as np
import pytest

from suit_ros.model.sweeps import Sweep, SweepBuffer, accumulate_sweeps, model_frame
from suit_ros.ops.geometry import pose_from_xyz_rpy, se3_inverse
from suit_ros.structures import Detections, Frame

T_BL = pose_from_xyz_rpy((0.9, 0.1, 1.8), (0.0, 0.02, 0.01))
FAR = np.array([250_000.0, -130_000.0, 40.0])         # odometry kilometres from its origin
WORLD = FAR + np.array([[12.0, -3.0, 0.4], [30.0, 8.0, 1.1], [-5.0, 2.0, 0.0]])


def base_pose(t: float) -> np.ndarray:
    T = pose_from_xyz_rpy(FAR + [8.0 * t, 1.5 * t, 0.0], (0.0, 0.0, 0.3 + 0.2 * t))
    return T


def sweep_at(t: float, intensity: float = 0.5) -> Sweep:
    """The static world points seen by the LiDAR at time t (LiDAR frame)."""
    T_ol = base_pose(t) @ T_BL
    local = (se3_inverse(T_ol) @ np.c_[WORLD, np.ones(len(WORLD))].T).T[:, :3]
    pts = np.c_[local, np.full(len(local), intensity)].astype(np.float32)
    return Sweep(pts, T_ol, int(1e9 + t * 1e9))


def expected_in_base(t: float) -> np.ndarray:
    return (se3_inverse(base_pose(t)) @ np.c_[WORLD, np.ones(len(WORLD))].T).T[:, :3]


def test_static_points_coincide_across_sweeps_in_base_link():
    sweeps = [sweep_at(0.2), sweep_at(0.1), sweep_at(0.0)]
    out = accumulate_sweeps(sweeps, T_BL)
    assert out.shape == (9, 5) and out.dtype == np.float32
    want = expected_in_base(0.2)
    for k in range(3):   # each sweep lands on the same base_link coordinates (float64 poses)
        np.testing.assert_allclose(out[3 * k:3 * k + 3, :3], want, atol=2e-3)
    np.testing.assert_allclose(out[:, 4], np.repeat([0.0, 0.1, 0.2], 3), atol=1e-6)
    np.testing.assert_allclose(out[:, 3], 0.5)


def test_existing_time_lag_is_kept_and_added():
    s = sweep_at(0.1)
    five = Sweep(np.c_[s.points, np.full(3, 0.05, np.float32)], s.T_odom_lidar, s.stamp_ns)
    out = accumulate_sweeps([sweep_at(0.2), five], T_BL)
    np.testing.assert_allclose(out[3:, 4], 0.15, atol=1e-6)


def test_bad_shapes_raise():
    with pytest.raises(ValueError, match='at least'):
        accumulate_sweeps([], T_BL)
    with pytest.raises(ValueError, match=r'\(N, 4\)'):
        accumulate_sweeps([Sweep(np.zeros((3, 3), np.float32), np.eye(4), 0)], T_BL)


def test_buffer_is_bounded_and_resets():
    buf = SweepBuffer(3, max_age_s=0.5)
    sizes = []
    for k in range(6):
        s = sweep_at(0.1 * k)
        sizes.append(len(buf.push(s.points, s.T_odom_lidar, s.stamp_ns, T_BL)))
    assert sizes == [3, 6, 9, 9, 9, 9] and len(buf) == 2
    assert buf.nbytes == 2 * sweep_at(0).points.nbytes
    # no pose: past sweeps cannot be placed; the buffer is cleared
    s = sweep_at(0.6)
    assert len(buf.push(s.points, None, s.stamp_ns, T_BL)) == 3 and len(buf) == 0
    # time going backwards (a looped bag) starts over
    for k in (7, 8):
        s = sweep_at(0.1 * k)
        buf.push(s.points, s.T_odom_lidar, s.stamp_ns, T_BL)
    s = sweep_at(0.1)
    assert len(buf.push(s.points, s.T_odom_lidar, s.stamp_ns, T_BL)) == 3
    # a gap longer than max_age_s drops the old sweeps
    s = sweep_at(2.0)
    assert len(buf.push(s.points, s.T_odom_lidar, s.stamp_ns, T_BL)) == 3
    buf.clear()
    assert len(buf) == 0
    with pytest.raises(ValueError):
        SweepBuffer(0)


def test_single_sweep_buffer_keeps_nothing():
    buf = SweepBuffer(1)
    for k in range(3):
        s = sweep_at(0.1 * k)
        out = buf.push(s.points, s.T_odom_lidar, s.stamp_ns, T_BL)
        assert len(out) == 3 and len(buf) == 0
        np.testing.assert_allclose(out[:, :3], expected_in_base(0.1 * k), atol=2e-3)


def test_model_frame_equals_the_streaming_buffer():
    """Training data (model_frame) and the node (SweepBuffer) build identical inputs."""
    frames = []
    for k in range(5):
        s = sweep_at(0.1 * k, intensity=0.1 * k)
        gt = Detections(np.array([[5.0, 1.0, -1.0, 4.0, 2.0, 1.5, 0.3]]), np.array([[3.0, 0.0]]),
                        np.ones(1), np.zeros(1, np.int64))
        frames.append(Frame(np.c_[s.points, np.zeros(3, np.float32)], s.T_odom_lidar,
                            s.stamp_ns, 'lidar', gt, T_base_lidar=T_BL))
    buf = SweepBuffer(3)
    for t, f in enumerate(frames):
        live = buf.push(f.points[:, :4], f.pose, f.stamp_ns, f.T_base_lidar)
        mf = model_frame(frames, t, 3)
        np.testing.assert_array_equal(mf.points, live)
        np.testing.assert_allclose(mf.pose, f.pose @ se3_inverse(T_BL))
        np.testing.assert_allclose(mf.T_base_lidar, np.eye(4))
    # GT moves into base_link with the extrinsic (centre, yaw, velocity rotated)
    gt = mf.gt
    assert gt is not None
    want = T_BL @ np.r_[5.0, 1.0, -1.0, 1.0]
    np.testing.assert_allclose(gt.boxes[0, :3], want[:3], atol=1e-5)
    assert gt.boxes[0, 6] == pytest.approx(0.3 + 0.01, abs=1e-4)
    assert np.hypot(*gt.velocities[0]) == pytest.approx(3.0, abs=1e-3)   # pitch 0.02
    # ignore boxes move into base_link as the GT does
    from dataclasses import replace
    ig = model_frame([replace(f, ignore_boxes=f.gt.boxes.astype(np.float32)) for f in frames],
                     4, 3).ignore_boxes
    assert ig is not None
    np.testing.assert_allclose(ig, gt.boxes, atol=1e-5)


def test_labels_sparser_than_clouds_keep_the_nodes_sweeps():
    """A bag labelled at half its cloud rate: each labelled frame's input stacks the clouds
    0.1 and 0.2 s before it, as the node does, not the labelled ones (0.2 and 0.4 s)."""
    from dataclasses import replace

    from suit_ros.data.sequences import labelled_with_sweeps
    frames = []
    for k in range(7):
        s = sweep_at(0.1 * k, intensity=0.1 * k)
        gt = Detections(np.array([[5.0, 1.0, -1.0, 4.0, 2.0, 1.5, 0.3]]), np.zeros((1, 2)),
                        np.ones(1), np.zeros(1, np.int64)) if k % 2 == 0 else None
        frames.append(Frame(s.points, s.T_odom_lidar, s.stamp_ns, 'lidar', gt,
                            T_base_lidar=T_BL))
    seq = labelled_with_sweeps(frames, 3)
    assert [f.stamp_ns for f in seq] == [frames[k].stamp_ns for k in (0, 2, 4, 6)]
    for i, k in enumerate((0, 2, 4, 6)):
        mf = model_frame(seq, i, 3)
        np.testing.assert_allclose(mf.points, model_frame(frames, k, 3).points, atol=1e-5)
        lags = sorted(set(np.round(mf.points[:, 4].astype(np.float64), 3).tolist()))
        assert lags == ([0.0] if k == 0 else [0.0, 0.1, 0.2])
    labelled = [replace(f, gt=frames[0].gt) for f in frames]
    assert labelled_with_sweeps(labelled, 3) == labelled          # all labelled: as they are


def test_skipped_sweeps_added_make_the_input_training_makes():
    """A node that ran the model on every other cloud but buffered the skipped ones gives it
    the input model_frame gives training: the same sweeps, 0.1 s apart; fed only the clouds
    it ran on, the input's sweeps would be 0.2 s apart."""
    frames = []
    for k in range(7):
        s = sweep_at(0.1 * k, intensity=0.1 * k)
        frames.append(Frame(np.c_[s.points, np.zeros(3, np.float32)], s.T_odom_lidar,
                            s.stamp_ns, 'lidar', None, T_base_lidar=T_BL))
    buf, only_run = SweepBuffer(3), SweepBuffer(3)
    for t, f in enumerate(frames):
        if t % 2:
            buf.add(f.points[:, :4], f.pose, f.stamp_ns)
            continue
        live = buf.push(f.points[:, :4], f.pose, f.stamp_ns, f.T_base_lidar)
        np.testing.assert_array_equal(model_frame(frames, t, 3).points, live)
        assert buf.last_lags_s == pytest.approx([0.0, 0.1, 0.2][:t + 1])
        only_run.push(f.points[:, :4], f.pose, f.stamp_ns, f.T_base_lidar)
        assert only_run.last_lags_s == pytest.approx([0.0, 0.2, 0.4][:t // 2 + 1])
    # a sweep without a pose is not buffered, and the buffered ones stand
    before = len(buf)
    buf.add(sweep_at(0.7).points, None, sweep_at(0.7).stamp_ns)
    assert len(buf) == before
    # added sweeps follow push's rules: time going backwards starts over, age drops old ones
    buf.add(sweep_at(0.1).points, sweep_at(0.1).T_odom_lidar, sweep_at(0.1).stamp_ns)
    assert len(buf) == 1
    s = sweep_at(1.0)
    buf.push(s.points, s.T_odom_lidar, s.stamp_ns, T_BL)
    assert buf.last_lags_s == (0.0,)


def test_an_accumulation_already_is_used_as_it_is():
    """nuScenes keyframes come with their sweeps stacked (time lags > 0): nothing is added."""
    buf = SweepBuffer(3)
    for k in range(3):
        s = sweep_at(0.1 * k)
        buf.push(s.points, s.T_odom_lidar, s.stamp_ns, T_BL)
    s = sweep_at(0.3)
    stacked = np.c_[s.points, np.array([0.0, 0.05, 0.1], np.float32)]
    out = buf.push(stacked, s.T_odom_lidar, s.stamp_ns, T_BL)
    assert len(out) == 3 and len(buf) == 0
    np.testing.assert_allclose(out[:, 4], [0.0, 0.05, 0.1], atol=1e-7)
    frames = [Frame(np.c_[sweep_at(0.5 * k).points, np.full(3, 0.05, np.float32)],
                    sweep_at(0.5 * k).T_odom_lidar, int(1e9 + 5e8 * k), T_base_lidar=T_BL)
              for k in range(2)]
    assert len(model_frame(frames, 1, 3).points) == 3


def test_training_drives_kept_in_float16_give_float32_inputs_equal_to_the_cache(tmp_path):
    """Training keeps sensor frames in float16 (half the RAM); the model frames built from them
    are float32 and equal to those built from the same cached drive read as float32."""
    from suit_ros.data.sequences import ClipSampler, synthetic_sequence
    fresh = synthetic_sequence('test', 3, 4, tmp_path, points_dtype=np.float16)   # simulated
    cached = synthetic_sequence('test', 3, 4, tmp_path, points_dtype=np.float16)  # from cache
    full = synthetic_sequence('test', 3, 4, tmp_path)
    for a, b, c in zip(fresh, cached, full):
        assert a.points.dtype == b.points.dtype == np.float16 and c.points.dtype == np.float32
        np.testing.assert_array_equal(a.points, b.points)
        np.testing.assert_array_equal(b.points.astype(np.float32), c.points)
    half = model_frame(cached, 3, 3)
    assert half.points.dtype == np.float32
    np.testing.assert_array_equal(half.points, model_frame(full, 3, 3).points)
    clip = ClipSampler([cached], [2], 0, sweeps=3).batch(1)[0]
    assert all(f.points.dtype == np.float32 and f.points.shape[1] == 5 for f in clip)


def test_clip_sampler_takes_consecutive_frames(tmp_path):
    """Clips of consecutive sensor frames, each with its own consecutive sweeps; a drive too
    short for a whole clip is left out, none: an error."""
    from suit_ros.data.sequences import ClipSampler, synthetic_sequence
    seq = synthetic_sequence('test', 3, 8, tmp_path)
    period = seq[1].stamp_ns - seq[0].stamp_ns
    for clip in ClipSampler([seq], [3], 0, sweeps=2).batch(4):
        assert np.diff([f.stamp_ns for f in clip]).tolist() == [period] * 2
        lags = np.unique(np.round(clip[-1].points[:, 4], 3))
        np.testing.assert_allclose(lags, [0.0, period * 1e-9], atol=1e-3)
    from suit_ros.errors import DatasetError
    with pytest.raises(DatasetError, match='7 frames'):       # a message, not a traceback
        ClipSampler([seq[:6]], [7], 0)


def test_a_fresh_and_a_cached_drive_are_the_same_frames(tmp_path):
    """The first call simulates and caches (float16 points); it returns what every later call
    reads, so an evaluation's first run gives the same figures as its reruns."""
    from suit_ros.data.sequences import synthetic_sequence
    fresh = synthetic_sequence('test', 5, 3, tmp_path)
    cached = synthetic_sequence('test', 5, 3, tmp_path)
    for a, b in zip(fresh, cached):
        assert a.points.dtype == b.points.dtype == np.float32
        np.testing.assert_array_equal(a.points, b.points)
        assert a.owners is not None and b.owners is not None         # the returns' owners
        np.testing.assert_array_equal(a.owners, b.owners)
        assert len(b.owners) == len(b.points) and set(b.owners.tolist()) > {0}
    uncached = synthetic_sequence('test', 5, 3, None)          # no cache: full precision
    assert any(not np.array_equal(a.points, u.points) for a, u in zip(fresh, uncached))


def test_outage_clips_lose_a_sector_and_keep_the_objects_seen_before(tmp_path):
    """An outage clip loses one sector of its sweeps from clip frame 1 or 2 on; the GT of
    those frames keeps the objects that had returns just before (so the loss asks the memory
    to carry them), and the frames before the outage are untouched."""
    from suit_ros.data.sequences import ClipSampler, seen_ids, synthetic_sequence
    seq = synthetic_sequence('test', 3, 8, tmp_path)
    lossy = ClipSampler([seq], [6], 4, sweeps=3, outage_probability=1.0,
                        outage_width_deg=(120.0, 120.0))
    stamps = [f.stamp_ns for f in seq]
    carried = 0
    for _ in range(4):
        (b,), (lost,) = lossy.batch_with_outages(1)
        start = stamps.index(b[0].stamp_ns)
        a = [model_frame(seq, start + t, 3) for t in range(6)]
        begin = lost.index(True)
        assert begin in (1, 2) and all(lost[begin:]) and not any(lost[:begin])
        for t in range(begin):
            np.testing.assert_array_equal(a[t].points, b[t].points)
        assert len(b[-1].points) < len(a[-1].points)
        seen = seen_ids(b[begin - 1])
        for f in b[begin:]:
            kept = set(f.instance_ids.tolist())
            with_returns = {int(i) for i, c in zip(f.instance_ids, f.num_points) if c > 0}
            assert kept == with_returns | (seen & set(kept))
            carried += len(kept - with_returns)
    assert carried > 0           # some seen objects lost their returns and stayed in the GT
    with pytest.raises(ValueError, match='outage_probability'):
        ClipSampler([seq], [6], 0, outage_probability=1.5)


def test_carry_gt_keeps_objects_seen_earlier_in_the_clip(tmp_path):
    """With ``carry_gt`` a frame's GT also holds the objects that had returns in an earlier
    frame of the clip (occluded now); the first frame keeps only those with returns."""
    from suit_ros.data.sequences import ClipSampler, seen_ids, synthetic_sequence
    seq = synthetic_sequence('test', 3, 8, tmp_path)
    sampler = ClipSampler([seq], [6], 2, sweeps=3, outage_probability=1.0, carry_gt=True)
    kept_unseen = 0
    for _ in range(3):
        (clip,), _ = sampler.batch_with_outages(1)
        earlier: set[int] = set()
        for t, f in enumerate(clip):
            ids = set(f.instance_ids.tolist())
            now = {int(i) for i, c in zip(f.instance_ids, f.num_points) if c > 0}
            assert now <= ids and ids - now <= earlier
            if t == 0:
                assert ids == now
            kept_unseen += len(ids - now)
            earlier |= seen_ids(f)
    assert kept_unseen > 0


def test_occluded_in_clip_counts_objects_hidden_after_being_seen():
    """Frame by frame: an object counts while it is present without returns after a frame of
    the clip in which it had returns; never seen, or gone from the GT, does not count."""
    from suit_ros.data.sequences import occluded_in_clip
    seen = [frozenset({1, 2}), frozenset({2}), frozenset(), frozenset({1})]
    present = [frozenset({1, 2, 3}), frozenset({1, 2, 3}), frozenset({1, 3}), frozenset({1, 3})]
    # frame 1: object 1 hidden (seen in 0); frame 2: object 1 hidden, 2 gone; frame 3: 1 back
    assert occluded_in_clip(seen, present) == 2
    assert occluded_in_clip(seen[:1], present[:1]) == 0
    assert occluded_in_clip([], []) == 0
    # min_gap 2: only frame 2 counts (object 1 last had returns two frames before)
    assert occluded_in_clip(seen, present, min_gap=2) == 1
    assert occluded_in_clip(seen, present, min_gap=3) == 0


def test_occlusion_weight_draws_clips_with_occlusions_more_often(tmp_path):
    """With a large ``occlusion_weight`` the drawn clips hold far more occluded objects than
    clips drawn uniformly; weight 0 keeps the uniform draw; a negative weight is refused."""
    from suit_ros.data.sequences import (
        ClipSampler,
        occluded_in_clip,
        present_ids,
        seen_ids,
        synthetic_sequence,
    )
    seqs = [synthetic_sequence('test', s, 14, tmp_path) for s in (3, 4)]
    L = 4
    by_start = {(i, s): occluded_in_clip([seen_ids(f) for f in seq[s:s + L]],
                                         [present_ids(f) for f in seq[s:s + L]])
                for i, seq in enumerate(seqs) for s in range(len(seq) - L + 1)}
    assert max(by_start.values()) > 0 and min(by_start.values()) == 0

    def drawn(weight: float) -> float:
        sampler = ClipSampler(seqs, [L], 5, occlusion_weight=weight)
        counts = []
        for _ in range(200):
            seq, start = sampler._draw_start(L)
            counts.append(by_start[([id(q) for q in seqs].index(id(seq)), start)])
        return float(np.mean(counts))
    uniform = float(np.mean(list(by_start.values())))
    assert drawn(50.0) > 1.5 * uniform
    assert abs(drawn(0.0) - uniform) < 0.5 * uniform + 0.5
    with pytest.raises(ValueError, match='occlusion_weight'):
        ClipSampler(seqs, [L], 0, occlusion_weight=-1.0)


def test_clips_cut_as_a_drive_starts(tmp_path):
    """``fresh_start_probability``: a clip drawn so has no sweep before its first frame (one
    sweep there, two in its second frame, as a drive's start or the node after a reset);
    0 draws nothing, so a recipe without it replays the clips it drew before; out of [0, 1]
    is an error, in the training config a message."""
    from suit_ros.data.sequences import ClipSampler, synthetic_sequence
    seq = synthetic_sequence('test', 3, 8, tmp_path)
    period = seq[1].stamp_ns - seq[0].stamp_ns

    def lags(f):
        return np.unique(np.round(f.points[:, 4], 3)).tolist()

    starts = set()
    for clip in ClipSampler([seq], [3], 1, sweeps=3, fresh_start_probability=1.0).batch(6):
        assert lags(clip[0]) == [0.0]
        np.testing.assert_allclose(lags(clip[1]), [0.0, period * 1e-9], atol=1e-3)
        assert len(lags(clip[2])) == 3
        starts.add(clip[0].stamp_ns)
    assert len(starts) > 1                     # not only the drive's own first frame
    ordinary = ClipSampler([seq], [3], 1, sweeps=3).batch(6)
    assert sum(len(lags(c[0])) == 3 for c in ordinary) >= 4
    off = ClipSampler([seq], [3], 1, sweeps=3, fresh_start_probability=0.0).batch(6)
    assert all(np.array_equal(a.points, b.points)
               for p, q in zip(ordinary, off) for a, b in zip(p, q))
    with pytest.raises(ValueError, match='fresh_start_probability'):
        ClipSampler([seq], [3], 1, fresh_start_probability=1.5)


def test_the_fresh_start_training_option_is_validated(tmp_path):
    from suit_ros.errors import ConfigError
    from suit_ros.train import load_train_config
    cfg = tmp_path / 'fresh.yaml'
    cfg.write_text('fresh_start_probability: 0.25\n')
    assert load_train_config(cfg).fresh_start_probability == 0.25
    cfg.write_text('fresh_start_probability: -0.1\n')
    with pytest.raises(ConfigError, match='fresh_start_probability must be in'):
        load_train_config(cfg)
