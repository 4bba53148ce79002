"""The pipeline: every runtime parameter takes effect; every input-contract case is flagged.

A real model (the shipped checkpoint, or an untrained real one), real rclpy message classes.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from rosgraph import node_checkpoint

from suit_ros.errors import ConfigError
from suit_ros.params import DetectorParams, runtime_parameters

S = 10**9
T0 = 1_700_000_000 * S


@pytest.fixture(scope='module')
def classes():
    from suit_ros.msg_adapters.classes import MessageClasses
    return MessageClasses.from_rclpy()


@pytest.fixture(scope='module')
def model(tmp_path_factory):
    from suit_ros.checkpoint import load_checkpoint
    model, _, _ = load_checkpoint(node_checkpoint(tmp_path_factory.mktemp('ckpt')), 'cpu')
    return model


@pytest.fixture(scope='module')
def coasting_model():
    """The shipped SUIT model without a carry branch (``suit_default``): what it publishes
    where the cloud shows nothing is the tracker's coasting alone."""
    from suit_ros.checkpoint import load_checkpoint
    return load_checkpoint('suit_default', 'cpu')[0]


@pytest.fixture(scope='module')
def scene():
    """A synthetic frame with objects: ``(structured cloud array, stamp)``."""
    from suit_ros.data.sim import preset
    from suit_ros.data.sim.scene import Simulation
    f = Simulation(preset('test', frames=3), 5).render(2)
    return f.cloud


def make_pipeline(model, classes, **changes):
    from suit_ros.model.streaming import StreamingDetector
    from suit_ros.pipeline import DetectionPipeline
    return DetectionPipeline(StreamingDetector(model, 'cpu'),
                             replace(DetectorParams(), **changes), classes)


def cloud(classes, stamp, array=None, n=3000, frame='lidar', intensity=100.0, fields='xyzi'):
    from suit_ros.msg_adapters.pointcloud2 import array_to_pointcloud2
    if array is None:
        rng = np.random.default_rng(stamp % 997)
        names = list(fields)
        array = np.zeros(n, [(k if k != 'i' else 'intensity', '<f4') for k in names])
        array['x'] = rng.uniform(-30, 30, n)
        array['y'] = rng.uniform(-30, 30, n)
        array['z'] = rng.uniform(-1.5, 0.5, n)
        if 'i' in names:
            array['intensity'] = rng.uniform(0, 1, n) * intensity
    return array_to_pointcloud2(array, classes.header(stamp, frame), classes)


def odom(stamp, x=0.0):
    from nav_msgs.msg import Odometry
    m = Odometry()
    m.header.stamp.sec, m.header.stamp.nanosec = divmod(stamp, S)
    m.header.frame_id, m.child_frame_id = 'odom', 'base_link'
    m.pose.pose.position.x = float(x)
    m.pose.pose.orientation.w = 1.0
    return m


def feed_odometry(pipe, start, end, step=S // 50, speed=10.0):
    for t in range(start, end + 1, step):
        assert pipe.add_odometry(odom(t, speed * (t - T0) / S))


# ------------------------------------------------------------------ runtime parameters
RUNTIME_TESTED_HERE = {'score_thresholds', 'nms_iou_threshold', 'max_detections', 'candidates',
                       'intensity_field', 'tracking', 'track_score_mix', 'coast_s',
                       'ground', 'overhang', 'box_fit', 'traffic_side', 'deskew', 'time_field',
                       'min_range',
                       'max_range', 'intensity_scale', 'extrinsic_xyz', 'extrinsic_rpy',
                       'ego_box_min', 'ego_box_max', 'min_points', 'odom_buffer_s',
                       'odom_tolerance_s', 'max_gap_s', 'max_pose_jump_m', 'max_stamp_skew_s'}
RUNTIME_TESTED_IN_NODE = {'odom_wait_s', 'max_stamp_skew_s', 'stale_periods',
                          'input_timeout_s'}


def test_every_runtime_parameter_has_a_behaviour_test():
    assert set(runtime_parameters()) == RUNTIME_TESTED_HERE | RUNTIME_TESTED_IN_NODE


def test_score_thresholds_and_max_detections(model, classes, scene):
    pipe = make_pipeline(model, classes, score_thresholds=(0.05,))
    many = len(pipe.process(cloud(classes, T0, scene)).detections)
    assert many >= 3
    pipe.configure(replace(pipe.params, max_detections=2))
    assert len(pipe.process(cloud(classes, T0 + S // 10, scene)).detections) == 2
    pipe.configure(replace(pipe.params, max_detections=200, score_thresholds=(0.999,)))
    assert len(pipe.process(cloud(classes, T0 + 2 * S // 10, scene)).detections) < many


def test_default_thresholds_are_the_checkpoints_published_ones(model, classes, scene):
    """``score_thresholds: [0.0]`` publishes at the checkpoint's published thresholds, cut on
    the final (track-smoothed) scores, while the model still decodes down to its low
    evaluation threshold for the tracker; an explicit value overrides them."""
    from suit_ros.model.streaming import StreamingDetector
    from suit_ros.pipeline import DetectionPipeline
    detector = StreamingDetector(model, 'cpu')
    detector.published_thresholds = [0.5, 0.5, 0.6, 0.6]
    pipe = DetectionPipeline(detector, DetectorParams(), classes)
    assert pipe.detector.score_thresholds.tolist() == pytest.approx([0.5, 0.5, 0.6, 0.6])
    low = model.cfg.head.score_threshold
    assert pipe.detector.decode_thresholds.tolist() == pytest.approx([low] * 4)
    feed_odometry(pipe, T0, T0 + S, speed=0.0)
    outs = [pipe.process(cloud(classes, T0 + k * S // 10, scene)) for k in range(3)]
    for out in outs:
        d = out.detections
        assert (d.scores >= np.array([0.5, 0.5, 0.6, 0.6])[d.labels] - 1e-6).all()
    assert len(outs[-1].detections) >= 1
    pipe.configure(replace(pipe.params, score_thresholds=(0.05,)))
    assert pipe.detector.score_thresholds.tolist() == pytest.approx([0.05] * 4)
    assert pipe.detector.decode_thresholds.tolist() == pytest.approx([0.05] * 4)
    more = pipe.process(cloud(classes, T0 + 3 * S // 10, scene))
    assert len(more.detections) > len(outs[-1].detections)
    # a carry branch's thresholds: the checkpoint's with the default, the user's value for
    # every box otherwise
    detector.published_carry_thresholds = [0.3, 0.3, 0.35, 0.35]
    pipe.configure(replace(pipe.params, score_thresholds=(0.0,)))
    assert pipe.detector.carry_thresholds.tolist() == pytest.approx([0.3, 0.3, 0.35, 0.35])
    pipe.configure(replace(pipe.params, score_thresholds=(0.05,)))
    assert pipe.detector.carry_thresholds.tolist() == pytest.approx([0.05] * 4)
    with pytest.raises(ValueError, match='carry thresholds'):
        detector.set_thresholds([0.5] * 4, carry_thresholds=[0.5])


def test_each_detection_carries_the_returns_inside_its_box(model, classes, scene):
    """``num_points``: the current cloud's points inside each published box (what tells a box
    seen now from one the memory carries), in the message too."""
    from suit_ros.msg_adapters.detections import pointcloud2_to_detections
    from suit_ros.msg_adapters.pointcloud2 import pointcloud2_to_xyzi
    from suit_ros.ops.geometry import points_in_boxes
    pipe = make_pipeline(model, classes, score_thresholds=(0.3,))
    msg = cloud(classes, T0, scene)
    out = pipe.process(msg)
    d = out.detections
    assert len(d) >= 3 and len(out.num_points) == len(d)
    xyz = pointcloud2_to_xyzi(msg).points[:, :3]
    np.testing.assert_array_equal(out.num_points, points_in_boxes(xyz, d.boxes).sum(0))
    assert (out.num_points > 0).mean() > 0.8
    np.testing.assert_array_equal(pointcloud2_to_detections(out.detections_msg)['num_points'],
                                  out.num_points)
    # nothing held on a first frame: every box says seen
    assert (pointcloud2_to_detections(out.detections_msg)['held'] == 0).all()
    assert len(out.held) == len(d)


def test_a_lost_sector_is_an_input_warning(model, classes):
    pipe = make_pipeline(model, classes)
    rng = np.random.default_rng(3)
    n = 6000
    az = rng.uniform(-np.pi, np.pi, n)
    r = rng.uniform(3, 40, n)
    array = np.zeros(n, [('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('intensity', '<f4')])
    array['x'], array['y'] = r * np.cos(az), r * np.sin(az)
    array['z'], array['intensity'] = -1.5, 50.0
    for k in range(8):
        assert 'sector_gap' not in pipe.process(cloud(classes, T0 + k * S // 10,
                                                      array)).warnings
    lost = array[(az < 0.0) | (az > np.deg2rad(120))]
    out = pipe.process(cloud(classes, T0 + 8 * S // 10, lost))
    assert 'sector_gap' in out.warnings and 'azimuth 0 to 120 deg' in out.warnings['sector_gap']


def test_candidates_bound_the_detections_before_the_threshold(model, classes, scene):
    pipe = make_pipeline(model, classes, score_thresholds=(0.0,))
    pipe.configure(replace(pipe.params, score_thresholds=(1e-6,), candidates=3))
    assert pipe.detector.candidates == 3
    assert len(pipe.process(cloud(classes, T0, scene)).detections) <= 3
    pipe.configure(replace(pipe.params, candidates=400))
    assert len(pipe.process(cloud(classes, T0 + S // 10, scene)).detections) > 3


def test_nms_iou_threshold_reaches_the_decoder(model, classes, scene):
    """What the decoder keeps changes with the threshold: a loose one lets overlapping boxes
    through, a strict one leaves no pair overlapping above it."""
    import torch

    from suit_ros.ops.iou import bev_iou
    pipe = make_pipeline(model, classes, score_thresholds=(0.02,), tracking=False)

    def overlaps(threshold, k):
        pipe.configure(replace(pipe.params, nms_iou_threshold=threshold))
        d = pipe.process(cloud(classes, T0 + k * S // 10, scene)).detections
        b = torch.as_tensor(d.boxes, dtype=torch.float64)
        iou = bev_iou(b, b).numpy() if len(d) else np.zeros((0, 0))
        same = d.labels[:, None] == d.labels[None, :]
        np.fill_diagonal(iou, 0.0)
        return len(d), float((iou * same).max()) if len(d) > 1 else 0.0
    n_loose, worst_loose = overlaps(0.9, 0)
    n_strict, worst_strict = overlaps(0.05, 1)
    assert worst_strict <= 0.05 + 1e-6
    assert n_loose > n_strict and worst_loose > 0.05


def test_tracks_and_can_be_turned_off(model, classes, scene):
    from suit_ros.msg_adapters.detections import pointcloud2_to_detections
    pipe = make_pipeline(model, classes, score_thresholds=(0.05,))
    assert pipe.params.tracking and pipe.detector.tracks is not None
    feed_odometry(pipe, T0, T0 + S, speed=0.0)
    outs = [pipe.process(cloud(classes, T0 + k * S // 10, scene)) for k in range(3)]
    first, last = outs[0], outs[-1]
    assert len(first.detections) >= 3 and first.track_ids is not None
    msg = pointcloud2_to_detections(last.detections_msg)
    assert np.array_equal(msg['track_id'], last.track_ids)
    # each velocity's standard deviation: the measurement's where nothing tracks it (the
    # head's noise, less where the sweeps read a vehicle's motion too), the filter's (smaller
    # after three frames of a static scene) where a track does
    # (each widened by a fraction of its speed: TrackerConfig.speed_std_fraction)
    cfg = pipe.detector.tracks.config
    vel_sigma = cfg.vel_sigma
    assert last.velocity_std is not None and len(last.velocity_std) == len(last.detections)
    np.testing.assert_array_equal(msg['vel_std'], last.velocity_std)
    for out in (first, last):
        new = out.track_ids == 0 if out is last else slice(None)
        born = out.velocity_std[new]
        speed = np.hypot(*out.detections.velocities[new].T)
        head = np.hypot(vel_sigma, cfg.speed_std_fraction * speed)
        assert len(born) and np.all((born > 0) & (born <= head + 1e-4))
        assert np.any(np.isclose(born, head, rtol=1e-5))
    # the same static scene: the confident objects are tracked and keep their ids
    birth = pipe.detector.tracks.config.birth_score
    sure = last.track_ids[last.detections.scores >= birth]
    began = first.track_ids[first.detections.scores >= birth]
    assert len(began) >= 2 and 0 not in set(sure) and set(began) <= set(sure)
    older = np.isin(last.track_ids, began)
    assert older.any() and np.all(last.velocity_std[older] < 0.5 * vel_sigma)
    assert last.tracks == len(pipe.detector.tracks) >= len(sure)
    pipe.configure(replace(pipe.params, tracking=False))
    off = pipe.process(cloud(classes, T0 + 3 * S // 10, scene))
    # off: the message keeps its layout (a consumer that parses by field name goes on): ids
    # 0 (not tracked), the head's own measurement noise for the velocities
    assert pipe.detector.tracks is None and off.tracks is None
    msg_off = pointcloud2_to_detections(off.detections_msg)
    assert off.detections_msg.point_step == last.detections_msg.point_step
    assert len(off.detections) and (msg_off['track_id'] == 0).all()
    speed = np.hypot(*off.detections.velocities.T)
    np.testing.assert_allclose(msg_off['vel_std'], np.hypot(vel_sigma,
                                                             cfg.speed_std_fraction * speed),
                               rtol=1e-5)
    # the filter's gap is the pipeline's one staleness threshold
    pipe.configure(replace(pipe.params, tracking=True, max_gap_s=2.0))
    assert pipe.detector.tracks is not None and pipe.detector.tracks.config.max_gap_s == 2.0


def test_coast_s_holds_tracked_objects_where_the_cloud_shows_nothing(coasting_model, classes,
                                                                     scene):
    """A static scene tracked for three frames, then three clouds with everything ahead
    (x > 0) lost: on the third, when the earlier sweeps no longer show them either, the
    confident objects there are still published with coasting (the default), with no return
    in them and their track ids; with ``coast_s: 0`` nothing is; the parameter reaches
    the tracker at runtime. (A model with a carry branch, the node's default, holds such
    boxes itself, untracked where no track takes them: docs/experiments/carry_default.)"""
    ahead = scene[scene['x'] <= 0]

    def last(coast):
        pipe = make_pipeline(coasting_model, classes, coast_s=coast)
        assert pipe.detector.tracks.config.coast_s == coast
        feed_odometry(pipe, T0, T0 + S, speed=0.0)
        outs = [pipe.process(cloud(classes, T0 + k * S // 10, scene)) for k in range(3)]
        sure = outs[-1].track_ids[outs[-1].detections.boxes[:, 0] > 2.0]
        for k in range(3, 6):
            out = pipe.process(cloud(classes, T0 + k * S // 10, ahead))
        return sure, out, pipe
    sure, held, pipe = last(0.5)
    boxes = held.detections.boxes
    blind = (boxes[:, 0] > 2.0) & (held.num_points == 0)
    assert len(sure) >= 1 and blind.sum() >= 1
    assert set(held.track_ids[blind]) <= set(sure) and 0 not in set(held.track_ids[blind])
    _, none, _ = last(0.0)
    assert not ((none.detections.boxes[:, 0] > 2.0) & (none.num_points == 0)).any()
    tracks, ids = pipe.detector.tracks, pipe.detector.tracks.ids.copy()
    pipe.configure(replace(pipe.params, coast_s=0.2))
    assert pipe.detector.tracks.config.coast_s == 0.2
    # the tracks and their ids go on (a new tracker would hand out id 1 again)
    assert pipe.detector.tracks is tracks and pipe.detector.tracks.ids.tolist() == ids.tolist()


@pytest.fixture(scope='module')
def dense_scene():
    """A frame of the detailed world seen by a 64-beam sensor (cars with many returns)."""
    from suit_ros.data.sim import preset
    from suit_ros.data.sim.scene import Simulation
    return Simulation(preset('test-real', sensor='hdl64e', frames=3), 5).render(2).cloud


def test_box_fit_moves_car_boxes_onto_their_faces(model, classes, dense_scene):
    """``box_fit: faces`` moves the published car boxes as :func:`suit_ros.box_fit.fit_to_faces`
    does on the same cloud (in the LiDAR frame: the fit moves boxes in x and y only, relative
    to the sensor), and nothing else; the parameter switches at runtime. The cloud's cars are
    made 0.8 m longer at the end the sensor sees (their returns copied forward), as a real
    car looks to a model that puts it too far away."""
    from suit_ros.box_fit import fit_to_faces
    pipe = make_pipeline(model, classes, tracking=False, score_thresholds=(0.2,))
    scene = dense_scene
    first = pipe.process(cloud(classes, T0, scene)).detections
    xyz = np.stack([scene['x'], scene['y'], scene['z']], 1)
    copies = []
    for box in first.boxes[first.labels == 0]:
        c, s = np.cos(box[6]), np.sin(box[6])
        d = xyz[:, :2] - box[:2]
        along = d[:, 0] * c + d[:, 1] * s
        inside = (np.abs(along) <= box[3] / 2) & (np.abs(-d[:, 0] * s + d[:, 1] * c) <= box[4] / 2)
        toward = -np.sign(box[0] * c + box[1] * s)       # along the car, toward the sensor
        for k in (0.2, 0.4, 0.6, 0.8):
            copy = scene[inside].copy()
            copy['x'] += toward * k * c
            copy['y'] += toward * k * s
            copies.append(copy)
    longer = np.concatenate([scene, *copies])
    xyz = np.stack([longer['x'], longer['y'], longer['z']], 1)
    off = pipe.process(cloud(classes, T0 + S // 10, longer)).detections
    pipe.configure(replace(pipe.params, box_fit='faces'))
    assert pipe.detector.box_fit == 'faces'
    faces = pipe.process(cloud(classes, T0 + 2 * S // 10, longer)).detections
    assert np.array_equal(off.labels, faces.labels) and np.allclose(off.scores, faces.scores)
    expected = fit_to_faces(off.boxes, off.labels, off.scores, xyz, np.zeros(2),
                            tuple(model.cfg.class_names))
    assert np.allclose(faces.boxes[:, :2], expected[:, :2], atol=2e-3)
    # heights, sizes and headings as the model gave them (the ground estimate runs on)
    assert np.allclose(faces.boxes[:, 2:], off.boxes[:, 2:], atol=1e-2)
    car = off.labels == 0
    assert np.allclose(faces.boxes[~car, :2], off.boxes[~car, :2])
    moved = np.hypot(*(faces.boxes[:, :2] - off.boxes[:, :2]).T)
    assert (moved > 0.05).any()
    # toward the sensor (the LiDAR frame's origin), never away
    assert (np.hypot(*faces.boxes[moved > 0.05, :2].T)
            < np.hypot(*off.boxes[moved > 0.05, :2].T)).all()
    pipe.configure(replace(pipe.params, box_fit='off'))
    again = pipe.process(cloud(classes, T0 + 3 * S // 10, longer)).detections
    assert np.allclose(again.boxes, off.boxes, atol=1e-2)


@pytest.mark.slow
def test_track_score_mix_smooths_tracked_scores(model, classes, scene):
    def scores(mix):
        pipe = make_pipeline(model, classes, score_thresholds=(0.05,), track_score_mix=mix)
        feed_odometry(pipe, T0, T0 + S, speed=0.0)
        outs = [pipe.process(cloud(classes, T0 + k * S // 10, scene)) for k in range(3)]
        return outs[-1]
    raw, mixed = scores(0.0), scores(1.0)
    assert np.array_equal(raw.track_ids, mixed.track_ids)     # the same tracks either way
    tracked = raw.track_ids > 0
    assert tracked.sum() >= 3
    # mix 0: the model's scores; mix 1: each tracked score is its track's history alone
    assert not np.allclose(raw.detections.scores[tracked], mixed.detections.scores[tracked])
    assert np.array_equal(raw.detections.scores[~tracked], mixed.detections.scores[~tracked])


def test_intensity_field_chooses_or_ignores_intensity(model, classes):
    pipe = make_pipeline(model, classes)
    out = pipe.process(cloud(classes, T0))
    assert out.has_intensity and 'no_intensity' not in out.warnings
    pipe.configure(replace(pipe.params, intensity_field='none'))
    out = pipe.process(cloud(classes, T0 + S // 10))
    assert not out.has_intensity and 'no_intensity' not in out.warnings   # chosen, no warning
    pipe.configure(replace(pipe.params, intensity_field='reflectivity'))
    out = pipe.process(cloud(classes, T0 + 2 * S // 10))
    assert 'reflectivity' in out.warnings['unusable_cloud'] and out.points_used == 0


def test_ranges_and_ego_box_drop_points(model, classes):
    pipe = make_pipeline(model, classes)
    msg = cloud(classes, T0, n=4000)
    full = pipe.process(msg).points_used
    pipe.configure(replace(pipe.params, max_range=10.0))
    near = pipe.process(cloud(classes, T0 + S // 10, n=4000)).points_used
    assert near < full / 3
    pipe.configure(replace(pipe.params, max_range=80.0, min_range=20.0))
    far = pipe.process(cloud(classes, T0 + 2 * S // 10, n=4000)).points_used
    assert far < full
    # an ego box around base_link: x -1..3, y -1..1, z -1..3; the LiDAR is 1.8 m above it
    pipe.configure(replace(pipe.params, min_range=0.0, max_range=80.0))
    a = np.zeros(4, [('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('intensity', '<f4')])
    a['x'] = [0.5, 1.0, 20.0, -25.0]       # LiDAR frame; base_link x = LiDAR x + 0.9
    a['z'] = [-1.0, -1.5, -1.0, -1.0]
    assert pipe.process(cloud(classes, T0 + 3 * S // 10, a)).points_used == 4
    pipe.configure(replace(pipe.params, ego_box_min=(-1.0, -1.0, -1.0),
                           ego_box_max=(3.0, 1.0, 3.0)))
    assert pipe.process(cloud(classes, T0 + 4 * S // 10, a)).points_used == 2


def test_intensity_scale_and_min_points(model, classes):
    pipe = make_pipeline(model, classes)
    out = pipe.process(cloud(classes, T0, intensity=1.0))          # 0..1 reflectance
    assert 'intensity_range' in out.warnings and 'reflectance' in out.warnings['intensity_range']
    pipe.configure(replace(pipe.params, intensity_scale=1.0))
    assert 'intensity_range' not in pipe.process(cloud(classes, T0 + S // 10,
                                                        intensity=1.0)).warnings
    out = pipe.process(cloud(classes, T0 + 2 * S // 10, intensity=255.0))
    assert 'exceeds intensity_scale' in out.warnings['intensity_range']
    assert 'too_few_points' not in out.warnings
    pipe.configure(replace(pipe.params, min_points=5000))
    out = pipe.process(cloud(classes, T0 + 3 * S // 10, intensity=255.0))
    assert 'only' in out.warnings['too_few_points']


def timed_cloud(classes, stamp, times, n=3000):
    """A cloud whose returns carry a ``time`` field (s after the stamp), and its xyz."""
    rng = np.random.default_rng(7)
    a = np.zeros(n, [('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('intensity', '<f4'),
                     ('time', '<f4')])
    a['x'], a['y'] = rng.uniform(5, 30, n), rng.uniform(-20, 20, n)
    a['z'], a['intensity'] = rng.uniform(-1.5, 0.5, n), 100.0
    a['time'] = times(n)
    return cloud(classes, stamp, a), a


def test_deskew_moves_each_return_by_the_odometry_over_the_sweep(model, classes):
    sweep = lambda n: np.linspace(0.0, 0.1, n, dtype=np.float32)      # noqa: E731
    for on in (True, False):
        pipe = make_pipeline(model, classes, deskew=on)
        feed_odometry(pipe, T0 - S, T0 + S, speed=10.0)        # 10 m/s along x
        msg, a = timed_cloud(classes, T0, sweep)
        out = pipe.process(msg)
        seen = pipe.detector.sweeps.past[-1].points
        # a return taken t s after the stamp was seen from 10 t m further on
        want = a['x'] + (10.0 * a['time'] if on else 0.0)
        np.testing.assert_allclose(seen[:, 0], want, atol=1e-4)
        np.testing.assert_allclose(seen[:, 1], a['y'], atol=1e-4)
        assert out.deskew == ('on: sweep 0.100 s at 10.0 m/s' if on else 'off')
        assert 'point_times' not in out.warnings


def test_time_field_and_what_deskew_does_without_times_or_odometry(model, classes):
    sweep = lambda n: np.linspace(0.0, 0.1, n, dtype=np.float32)      # noqa: E731
    pipe = make_pipeline(model, classes, time_field='t')
    feed_odometry(pipe, T0 - S, T0 + S)
    out = pipe.process(timed_cloud(classes, T0, sweep)[0])
    assert "no 't' field" in out.warnings['point_times'] and out.deskew.startswith('off')
    assert len(pipe.detector.sweeps) == 1                      # detected all the same
    pipe.configure(replace(pipe.params, time_field='time'))
    assert pipe.process(timed_cloud(classes, T0 + S // 10, sweep)[0]).deskew.startswith('on')
    bad = lambda n: np.where(np.arange(n) == 5, np.nan, 0.05).astype(np.float32)  # noqa: E731
    out = pipe.process(timed_cloud(classes, T0 + 2 * S // 10, bad)[0])
    assert 'not finite' in out.warnings['point_times'] and out.deskew == 'off: time unusable'
    assert out.points_used == 3000                             # the points all the same
    # a cloud without a time field (an already deskewed driver): as given, no warning
    pipe.configure(replace(pipe.params, time_field=''))
    out = pipe.process(cloud(classes, T0 + 3 * S // 10))
    assert out.deskew.startswith('off: no time field') and 'point_times' not in out.warnings
    lone = make_pipeline(model, classes)                       # no odometry: single frame
    out = lone.process(timed_cloud(classes, T0, sweep)[0])
    assert out.deskew == 'off: no odometry at the stamp'


def test_extrinsic_change_resets_and_moves_the_model_input(model, classes):
    pipe = make_pipeline(model, classes)
    feed_odometry(pipe, T0 - S, T0 + S)
    pipe.process(cloud(classes, T0))
    z0 = pipe.last_pose[2, 3]
    assert len(pipe.detector.sweeps) == 1
    resets = pipe.resets
    pipe.configure(replace(pipe.params, extrinsic_xyz=(0.9, 0.0, 2.5)))
    assert pipe.resets == resets + 1 and pipe.last_reset_reason == 'extrinsic changed'
    assert len(pipe.detector.sweeps) == 0 and pipe.detector.memory is None
    assert pipe.T_base_lidar[2, 3] == pytest.approx(2.5)
    pipe.process(cloud(classes, T0 + S // 10))
    # the vehicle pose does not depend on the extrinsic; the model input (base_link) does
    assert pipe.last_pose[2, 3] == pytest.approx(z0)
    buffered = pipe.detector.sweeps.past[-1]
    np.testing.assert_allclose(buffered.T_odom_lidar[2, 3], z0 + 2.5)
    yaw0 = np.arctan2(pipe.last_pose[1, 0], pipe.last_pose[0, 0])
    pipe.configure(replace(pipe.params, extrinsic_rpy=(0.0, 0.0, 0.5)))
    assert pipe.resets == resets + 2
    assert np.arctan2(pipe.T_base_lidar[1, 0], pipe.T_base_lidar[0, 0]) == pytest.approx(0.5)
    pipe.process(cloud(classes, T0 + 2 * S // 10))
    assert np.arctan2(pipe.last_pose[1, 0], pipe.last_pose[0, 0]) == pytest.approx(yaw0)


def test_traffic_side_left_gives_the_model_the_right_hand_world(model, classes, scene):
    """``traffic_side: left``: a left-hand drive (the right-hand one mirrored: its clouds, its
    odometry, its mounting) comes out as the right-hand drive's boxes mirrored, because the
    model is given the right-hand world; a change resets the memory and the tracks."""
    def turning_odom(stamp, mirrored):
        t = (stamp - T0) / S
        x, y, yaw = 8.0 * t, 0.5 * t * t, 0.15 * t
        m = odom(stamp, x)
        m.pose.pose.position.y = -y if mirrored else y
        half = (-yaw if mirrored else yaw) / 2
        m.pose.pose.orientation.z, m.pose.pose.orientation.w = np.sin(half), np.cos(half)
        return m

    def drive(side, mirrored):
        xyz, rpy = (1.0, 0.3, 1.8), (0.0, 0.0, 0.1)
        if mirrored:
            xyz, rpy = (1.0, -0.3, 1.8), (0.0, 0.0, -0.1)
        pipe = make_pipeline(model, classes, score_thresholds=(0.05,), traffic_side=side,
                             extrinsic_xyz=xyz, extrinsic_rpy=rpy)
        for t in range(T0 - S, T0 + S, S // 50):
            assert pipe.add_odometry(turning_odom(t, mirrored))
        outs = []
        array = scene.copy()
        if mirrored:
            array['y'] = -array['y']
        for k in range(3):
            if k:       # a cloud the node skipped while busy: only buffered, as a past sweep
                assert pipe.buffer(cloud(classes, T0 + k * S // 10 - S // 20, array)).buffered
            outs.append(pipe.process(cloud(classes, T0 + k * S // 10, array)))
        return pipe, outs

    _, right = drive('right', False)
    pipe, left = drive('left', True)
    for a, b in zip(right, left):
        da, db = a.detections, b.detections
        assert len(da) >= 3 and len(da) == len(db)
        np.testing.assert_allclose(db.scores, da.scores, atol=1e-4)
        np.testing.assert_allclose(db.boxes[:, [0, 2, 3, 4, 5]], da.boxes[:, [0, 2, 3, 4, 5]],
                                   atol=1e-3)
        np.testing.assert_allclose(db.boxes[:, 1], -da.boxes[:, 1], atol=1e-3)
        np.testing.assert_allclose(np.cos(db.boxes[:, 6] + da.boxes[:, 6]), 1.0, atol=1e-5)
        np.testing.assert_allclose(db.velocities * [1, -1], da.velocities, atol=1e-3)
        assert np.array_equal(a.track_ids, b.track_ids) and np.array_equal(a.num_points,
                                                                           b.num_points)
    # the left-hand drive read as right-hand traffic: the model sees another world
    _, unmirrored = drive('right', True)
    u, m = unmirrored[-1].detections, right[-1].detections
    assert not (len(u) == len(m) and np.allclose(u.scores, m.scores, atol=1e-4)
                and np.allclose(u.boxes[:, 1], -m.boxes[:, 1], atol=1e-3))
    resets = pipe.resets
    pipe.configure(replace(pipe.params, traffic_side='right'))
    assert pipe.resets == resets + 1 and pipe.last_reset_reason == 'traffic side changed'
    assert pipe.detector.memory is None and len(pipe.detector.tracks) == 0
    assert len(pipe.detector.sweeps) == 0
    assert len(pipe.process(cloud(classes, T0 + 3 * S // 10, scene)).detections)
    with pytest.raises(ConfigError, match='traffic_side'):
        pipe.configure(replace(pipe.params, traffic_side='middle'))


def test_ground_local_levels_the_input_and_a_change_resets(model, classes, scene):
    """``ground: local``: a cloud lowered by 0.6 m (an extrinsic height 0.6 m off) gives the
    boxes of the true cloud, 0.6 m lower, where the ground is found on road returns (within
    18 m here); switching the mode forgets the memory.

    Farther, a 4 m cell whose returns are mostly a wall's is not leveled alike: its lowest 5 %
    are counted within a fixed band of base_link heights (-2.0 to 1.5 m), a cloud lowered by
    0.6 m brings 0.6 m more of the wall into it, and the percentile climbs off the road (on
    this frame cells at 20-30 m by the buildings read 0.15-0.33 m above it: boxes there rise
    as much)."""
    def boxes(ground, dz):
        pipe = make_pipeline(model, classes, ground=ground, score_thresholds=(0.3,))
        lowered = scene.copy()
        lowered['z'] -= dz
        return pipe, pipe.process(cloud(classes, T0, lowered)).detections.boxes

    pipe, true = boxes('local', 0.0)
    _, low = boxes('local', 0.6)
    assert pipe.detector.ground == 'local' and len(true) >= 3
    # the ground is found in 5 cm bins: a box or two near the cut may differ
    d = np.hypot(*(true[:, None, :2] - low[None, :, :2]).transpose(2, 0, 1))
    found = d.min(axis=1) < 0.3
    assert found.mean() >= 0.8
    near = found & (np.hypot(true[:, 0], true[:, 1]) < 18.0)
    assert near.sum() >= 2
    dz = low[d.argmin(axis=1)[near], 2] - true[near, 2]
    assert np.median(dz) == pytest.approx(-0.6, abs=0.06)
    assert np.all(dz <= -0.3)               # every box lower, nearly all the way
    resets = pipe.resets
    pipe.configure(replace(pipe.params, ground='as_given'))
    assert pipe.resets == resets + 1 and pipe.last_reset_reason == 'ground changed'
    assert pipe.detector.ground == 'as_given' and len(pipe.detector.sweeps) == 0
    pipe.configure(replace(pipe.params, ground='checkpoint'))    # as the model was trained
    trained = pipe.detector.cfg.pillars.ground
    assert pipe.detector.ground == trained
    assert pipe.resets == resets + 1 + (trained != 'as_given')
    with pytest.raises(Exception, match='ground must be one of'):
        pipe.configure(replace(pipe.params, ground='flat'))


def test_overhang_drop_removes_a_canopy_and_a_change_resets(model, classes, scene):
    """``overhang: drop``: a canopy over the scene's objects changes nothing the model sees;
    ``keep`` lets it through; switching resets the memory; 'checkpoint' is the config's."""
    # canopies over the columns (0.4 m, base_link: the LiDAR at 0.9, 0, 1.8) whose returns
    # all lie below 1.3 m: 2.8-3.2 m up, clear of everything that stands, within 25 m (the
    # gap that splits a column grows with range where the config's gap_per_m says so: at
    # 0.05 m a metre it needs 1.25 m there, the canopy leaves 1.5 m)
    x, y, z = scene['x'] + 0.9, scene['y'], scene['z'] + 1.8
    col = np.floor(np.c_[x, y] / 0.4).astype(int)
    tall = {tuple(c) for c in col[(z >= 1.3) | (np.hypot(x, y) > 24.0)]}
    low = np.array(sorted({tuple(c) for c in col} - tall))
    rng = np.random.default_rng(0)
    at = low[rng.integers(0, len(low), 4000)]
    canopy = np.zeros(4000, scene.dtype)
    canopy['x'], canopy['y'] = ((at + rng.uniform(0.05, 0.95, at.shape)) * 0.4).T
    canopy['x'] -= 0.9
    canopy['z'] = rng.uniform(2.8, 3.2, 4000) - 1.8
    covered = np.concatenate([scene, canopy])

    def boxes(overhang, array):
        pipe = make_pipeline(model, classes, overhang=overhang, score_thresholds=(0.3,))
        return pipe, pipe.process(cloud(classes, T0, array)).detections.boxes

    pipe, clear = boxes('drop', scene)
    assert pipe.detector.overhang == 'drop' and len(clear) >= 3
    _, dropped = boxes('drop', covered)
    _, kept = boxes('keep', covered)
    np.testing.assert_array_equal(dropped, clear)
    assert kept.shape != clear.shape or not np.array_equal(kept, clear)
    resets = pipe.resets
    pipe.configure(replace(pipe.params, overhang='keep'))
    assert pipe.resets == resets + 1 and pipe.last_reset_reason == 'overhang changed'
    pipe.configure(replace(pipe.params, overhang='checkpoint'))
    assert pipe.detector.overhang == model.cfg.pillars.overhang
    with pytest.raises(Exception, match='overhang must be one of'):
        pipe.configure(replace(pipe.params, overhang='cut'))


def test_odometry_tolerance_and_buffer(model, classes):
    pipe = make_pipeline(model, classes)
    assert pipe.process(cloud(classes, T0 - S)).single_frame == 'no_odometry'   # typed reason
    feed_odometry(pipe, T0, T0 + S)
    assert pipe.process(cloud(classes, T0 + S // 2)).single_frame is None
    assert pipe.process(cloud(classes, T0 + 5 * S)).single_frame == 'outside_odometry'
    pipe.reset('test')
    late = T0 + S + 3 * S // 10                       # 0.3 s after the newest odometry
    assert pipe.process(cloud(classes, late)).pose_source.startswith('none')
    pipe.configure(replace(pipe.params, odom_tolerance_s=0.5))
    assert pipe.process(cloud(classes, late + 1)).pose_source == 'odometry'
    # a 0.5 s buffer keeps only the newest half second of odometry
    pipe.configure(replace(pipe.params, odom_buffer_s=0.5, odom_tolerance_s=0.0))
    feed_odometry(pipe, T0 + S + S // 50, T0 + 2 * S)
    assert pipe.poses.span()[0] >= T0 + 3 * S // 2 - 1
    assert pipe.process(cloud(classes, T0 + S + 2 * S // 10)).pose_source.startswith('none')


def test_odometry_from_the_future_is_refused_and_counted(model, classes):
    """One pose stamped 10 s ahead of the receiver's clock must not hide a later odometry
    outage (the lookup would interpolate toward it, the buffer drop the real poses)."""
    pipe = make_pipeline(model, classes)
    now = T0 + S
    feed_odometry(pipe, T0, now)
    assert not pipe.add_odometry(odom(now + 10 * S, 100.0), now_ns=now)
    assert pipe.odom_rejected == 1 and 'ahead of the clock' in pipe.last_odom_error
    assert pipe.poses.span() == (T0, now)
    # the odometry stops: a cloud 0.5 s later runs single-frame, as it should
    assert pipe.process(cloud(classes, now + S // 2)).pose_source.startswith('none')
    # within max_stamp_skew_s, or with no clock yet (simulated time before /clock): taken
    assert pipe.add_odometry(odom(now + S // 2, 5.0), now_ns=now)
    assert pipe.add_odometry(odom(now + 20 * S, 5.0), now_ns=0)
    pipe.configure(replace(pipe.params, max_stamp_skew_s=30.0))
    assert pipe.add_odometry(odom(now + 25 * S, 5.0), now_ns=now)
    assert pipe.odom_rejected == 1


def test_a_cloud_that_went_back_takes_a_pose_only_from_odometry_that_went_back(model,
                                                                              classes):
    """A simulator reset 0.4 s back, to another place: a cloud of the new time line takes
    its pose from the new line's odometry once that went back too; a cloud that went back
    while the odometry did not runs without a pose, and says why (the poses about its stamp
    are of the time before)."""
    pipe = make_pipeline(model, classes)
    feed_odometry(pipe, T0, T0 + S)
    assert pipe.process(cloud(classes, T0 + 9 * S // 10)).pose_source == 'odometry'
    back = T0 + S // 2
    for k in range(3):                         # the new line's odometry comes first
        assert pipe.add_odometry(odom(back - S // 50 + k * S // 50, -300.0))
    assert pipe.odom_rewinds == 1
    out = pipe.process(cloud(classes, back))
    assert 'backwards' in out.reset_reason and out.pose_source == 'odometry'
    doubt = 'none: the clouds went back in time and the odometry has not'
    out = pipe.process(cloud(classes, back - S // 5))      # back again, the odometry not
    assert 'backwards' in out.reset_reason and out.pose_source.startswith(doubt)
    assert out.single_frame == 'outside_odometry'
    # the next cloud, in order, is no surer: the odometry about it is still the line before
    assert pipe.process(cloud(classes, back - S // 10)).pose_source.startswith(doubt)
    for k in range(3):                         # until the odometry goes back too
        assert pipe.add_odometry(odom(back - S // 5 + k * S // 50, 700.0))
    assert pipe.odom_rewinds == 2
    feed_odometry(pipe, back - S // 5 + 3 * S // 50, back + S)
    assert pipe.process(cloud(classes, back - S // 10 + S // 100)).pose_source == 'odometry'
    # a cloud that was only late: the next ones past the odometry buffered then have poses
    assert pipe.process(cloud(classes, back + S // 2)).pose_source == 'odometry'
    assert pipe.process(cloud(classes, back + S // 4)).pose_source.startswith(doubt)
    assert pipe.process(cloud(classes, back + 2 * S // 5)).pose_source.startswith(doubt)
    # past the cloud before it: it was only late
    assert pipe.process(cloud(classes, back + 3 * S // 5)).pose_source == 'odometry'


def test_a_cloud_on_its_way_when_the_odometry_went_back_keeps_its_time_line(model, classes):
    """A clock stepped back 0.9 s: the new time line's odometry comes before the last cloud
    of the time before has run, and reaches past its stamp. That cloud takes its pose from
    its own time line, as it was (not from the new line's pose at its stamp, a second of
    driving away); the new line's first cloud from the new line."""
    pipe = make_pipeline(model, classes)
    feed_odometry(pipe, T0, T0 + S)                      # x = 10 m/s from T0
    assert pipe.process(cloud(classes, T0 + 8 * S // 10)).pose_source == 'odometry'
    for k in range(45):                # the loop's odometry, 0.9 s back, past the next cloud
        assert pipe.add_odometry(odom(T0 + S // 10 + k * S // 50, -300.0))
    assert pipe.odom_rewinds == 1
    out = pipe.process(cloud(classes, T0 + 9 * S // 10))  # the pass before's last cloud
    assert out.pose_source == 'odometry' and out.reset_reason == ''
    assert pipe.last_pose[0, 3] == pytest.approx(9.0)
    out = pipe.process(cloud(classes, T0 + S // 10 + S // 50))     # the loop's first
    assert 'backwards' in out.reset_reason and out.pose_source == 'odometry'
    assert pipe.last_pose[0, 3] == pytest.approx(-300.0)


@pytest.mark.slow
def test_max_gap_s_is_the_one_staleness_threshold(model, classes):
    pipe = make_pipeline(model, classes)
    pipe.process(cloud(classes, T0))
    assert 'max_gap_s' in pipe.process(cloud(classes, T0 + 8 * S // 10)).reset_reason
    pipe.configure(replace(pipe.params, max_gap_s=1.0))
    assert pipe.process(cloud(classes, T0 + 16 * S // 10)).reset_reason == ''
    # the sweep buffer and the tracker follow it too (no second staleness setting)
    assert pipe.detector.sweeps.max_age_s == 1.0
    assert pipe.detector.tracks is not None and pipe.detector.tracks.config.max_gap_s == 1.0
    feed_odometry(pipe, T0 + 16 * S // 10, T0 + 26 * S // 10, speed=0.0)
    pipe.process(cloud(classes, T0 + 17 * S // 10))
    pipe.process(cloud(classes, T0 + 25 * S // 10))     # 0.8 s later: the sweep is kept
    assert len(pipe.detector.sweeps) == 2


def test_skipped_clouds_buffered_keep_the_inputs_sweeps_as_in_training(model, classes):
    """The node skips clouds while the model is busy; buffered, they keep the next input's
    sweeps 0.1 s apart (docs/experiments/overload); not buffered, the sweeps spread."""
    pipe, plain = make_pipeline(model, classes), make_pipeline(model, classes)
    for p in (pipe, plain):
        feed_odometry(p, T0, T0 + 2 * S)
        p.process(cloud(classes, T0))
    seen = pipe.coverage.seen
    out = pipe.buffer(cloud(classes, T0 + S // 10))
    assert out.warnings == {} and out.detections_msg is None and out.reset_reason == ''
    assert out.buffered and pipe.coverage.seen == seen     # the sector check: processed only
    assert len(pipe.detector.sweeps) == 2
    out = pipe.process(cloud(classes, T0 + 2 * S // 10))
    assert out.input_lags_s == pytest.approx((0.0, 0.1, 0.2))
    assert plain.process(cloud(classes, T0 + 2 * S // 10)).input_lags_s == pytest.approx(
        (0.0, 0.2))
    # bad skipped clouds: said, nothing buffered, nothing raised
    assert set(pipe.buffer(cloud(classes, T0 + 3 * S // 10, n=0)).warnings) == {'empty_cloud'}
    bad = cloud(classes, T0 + 4 * S // 10)
    bad.fields = [f for f in bad.fields if f.name != 'x']
    assert set(pipe.buffer(bad).warnings) == {'unusable_cloud'}
    out = pipe.process(cloud(classes, T0 + 5 * S // 10))
    assert out.input_lags_s == pytest.approx((0.0, 0.3, 0.4))   # only the good sweeps
    # clouds only buffered for longer than max_gap_s: the memory is too old to fuse, the
    # sweeps just before the cloud stand
    pipe.process(cloud(classes, T0 + 6 * S // 10))
    for k in range(7, 13):
        assert pipe.buffer(cloud(classes, T0 + k * S // 10)).reset_reason == ''
    out = pipe.process(cloud(classes, T0 + 13 * S // 10))
    assert 'memory 0.70 s old' in out.reset_reason and not out.used_memory
    assert out.input_lags_s == pytest.approx((0.0, 0.1, 0.2))
    # the stream's checks run on a skipped cloud too: time going backwards resets
    assert 'backwards' in pipe.buffer(cloud(classes, T0 + 12 * S // 10)).reset_reason
    # without a pose a skipped cloud is not buffered (it cannot be placed), nothing is reset,
    # and the next cloud's pose-jump check still sees the last pose
    short = make_pipeline(model, classes)
    feed_odometry(short, T0, T0 + 3 * S // 10)
    short.process(cloud(classes, T0 + 2 * S // 10))
    assert len(short.detector.sweeps) == 1 and short.last_pose is not None
    out = short.buffer(cloud(classes, T0 + 5 * S // 10))       # past the odometry + 0.15 s
    assert out.single_frame == 'outside_odometry' and not out.buffered
    assert out.reset_reason == '' and len(short.detector.sweeps) == 1
    assert short.last_pose is not None


def test_max_pose_jump_m(model, classes):
    pipe = make_pipeline(model, classes)
    feed_odometry(pipe, T0, T0 + 2 * S, speed=30.0)   # 3 m per 0.1 s
    pipe.process(cloud(classes, T0))
    assert pipe.process(cloud(classes, T0 + S // 10)).reset_reason == ''
    pipe.configure(replace(pipe.params, max_pose_jump_m=2.0))
    assert 'jumped 3.0 m' in pipe.process(cloud(classes, T0 + 2 * S // 10)).reset_reason


def test_a_dropped_cloud_at_highway_speed_is_no_pose_jump(model, classes):
    """The limit is per 0.1 s of the gap between the clouds (at least 5 m): at 35 m/s a
    dropped cloud (7 m in 0.2 s) and a skipped one that could not be placed keep the memory;
    an odometry that leaps 12 m in 0.1 s resets it, and so does one that leaps 12 m in 0.2 s
    while standing (the gap is read from the cloud the last pose was read for)."""
    pipe = make_pipeline(model, classes)
    feed_odometry(pipe, T0, T0 + 2 * S, speed=35.0)
    pipe.process(cloud(classes, T0))
    out = pipe.process(cloud(classes, T0 + 2 * S // 10))              # one cloud lost
    assert out.reset_reason == '' and out.used_memory
    short = make_pipeline(model, classes)
    feed_odometry(short, T0, T0 + 3 * S // 10, speed=35.0)
    short.process(cloud(classes, T0 + 2 * S // 10))
    assert not short.buffer(cloud(classes, T0 + 5 * S // 10)).buffered   # no pose for it
    for t in range(T0 + 3 * S // 10 + S // 50, T0 + S, S // 50):
        assert short.add_odometry(odom(t, 35.0 * (t - T0) / S))
    out = short.process(cloud(classes, T0 + 6 * S // 10))           # 14 m in 0.4 s
    assert out.reset_reason == '', out.reset_reason
    for stand_still, dt in ((False, S // 10), (True, 2 * S // 10)):
        leap = make_pipeline(model, classes)
        for t in range(T0, T0 + S, S // 50):
            x = (0.0 if stand_still else 10.0 * (t - T0) / S) + (12.0 if t > T0 + S // 20 else 0)
            assert leap.add_odometry(odom(t, x))
        leap.process(cloud(classes, T0))
        reason = leap.process(cloud(classes, T0 + dt)).reset_reason
        assert 'pose jumped' in reason and f'in {dt / S:.2f} s' in reason, reason
    # clouds that could not be placed for 2 s (odometry gone): what the model holds is 2 s
    # old when the odometry comes back (30 m relocalised): a reset, said as the gap it is
    lost = make_pipeline(model, classes)
    feed_odometry(lost, T0, T0 + 3 * S // 10, speed=0.0)
    lost.process(cloud(classes, T0 + 2 * S // 10))
    for k in range(5, 21, 3):
        assert lost.buffer(cloud(classes, T0 + k * S // 10)).reset_reason == ''
    for t in range(T0 + 19 * S // 10, T0 + 23 * S // 10, S // 50):
        assert lost.add_odometry(odom(t, 30.0))
    reason = lost.process(cloud(classes, T0 + 22 * S // 10)).reset_reason
    assert reason.startswith('no cloud placed for 2.00 s'), reason


# ------------------------------------------------------------------ the input contract
def test_input_contract_cases(model, classes):
    pipe = make_pipeline(model, classes)
    assert pipe.process(cloud(classes, T0)).warnings == {}
    out = pipe.process(cloud(classes, T0 + S // 10, fields='xyz'))
    assert set(out.warnings) == {'no_intensity'} and not out.has_intensity
    out = pipe.process(cloud(classes, T0 + 2 * S // 10, n=0))
    assert set(out.warnings) == {'empty_cloud'}
    bare = cloud(classes, T0 + 25 * S // 100, n=0)       # no fields at all: still just empty
    bare.fields, bare.point_step, bare.height = [], 0, 0
    out = pipe.process(bare)
    assert set(out.warnings) == {'empty_cloud'} and out.detections_msg.width == 0
    out = pipe.process(cloud(classes, T0 + 3 * S // 10, n=50))
    assert set(out.warnings) == {'too_few_points'}
    out = pipe.process(cloud(classes, T0 + 4 * S // 10, frame='velodyne'))
    assert set(out.warnings) == {'frame_changed'} and 'frame_id changed' in out.reset_reason
    bad = cloud(classes, T0 + 5 * S // 10, frame='velodyne')
    bad.fields = [f for f in bad.fields if f.name != 'x']
    out = pipe.process(bad)
    assert set(out.warnings) == {'unusable_cloud'} and out.detections_msg.width == 0
    assert out.warning == out.warnings['unusable_cloud']


def test_deskew_says_why_not_for_an_odometry_jump_and_an_empty_cloud(model, classes):
    sweep = lambda n: np.linspace(0.0, 0.1, n, dtype=np.float32)      # noqa: E731
    pipe = make_pipeline(model, classes, time_field='time', max_pose_jump_m=50.0)
    feed_odometry(pipe, T0 - S, T0)
    assert pipe.add_odometry(odom(T0 + S // 50, 40.0))             # relocalised: 40 m on
    out = pipe.process(timed_cloud(classes, T0, sweep)[0])
    assert out.deskew.startswith('off: odometry moved') and 'a jump' in out.warnings['point_times']
    assert out.points_used == 3000
    empty = pipe.process(timed_cloud(classes, T0 + S // 10, sweep, n=0)[0])
    assert 'point_times' not in empty.warnings and empty.deskew == 'off: no points'
    # standing still, then a 0.4 m relocalisation inside the sweep: slow over the whole
    # window (4 m/s), but not one motion
    step = make_pipeline(model, classes, time_field='time')
    feed_odometry(step, T0 - S, T0, speed=0.0)
    for t in range(T0 + S // 50, T0 + S // 5, S // 50):
        assert step.add_odometry(odom(t, 0.4))
    out = step.process(timed_cloud(classes, T0, sweep)[0])
    assert out.deskew.startswith('off: odometry changed')
    assert 'a jump' in out.warnings['point_times'] and out.points_used == 3000


def test_state_survives_what_should_not_touch_it(model, classes):
    """From an audit of the state kept between frames: a cloud that cannot be decoded changes
    nothing (its header is not trusted); an empty cloud outside the odometry does not switch
    off the next frame's pose-jump check; a cloud without a pose says that the memory was
    forgotten; tracking turned off and on goes on counting ids; a change of how clouds are
    read empties the sweeps and the memory but keeps the tracks; a non-default extrinsic at
    start-up is no reset."""
    def odometry(start, end, x):
        for t in range(start, end + 1, S // 50):
            pipe.add_odometry(odom(t, x))

    pipe = make_pipeline(model, classes, extrinsic_xyz=(0.9, 0.0, 1.8))
    assert pipe.resets == 0 and pipe.last_reset_reason == 'start'
    odometry(T0, T0 + 3 * S // 10, 0.0)
    pipe.process(cloud(classes, T0))
    pipe.process(cloud(classes, T0 + S // 10))
    resets, sweeps = pipe.resets, len(pipe.detector.sweeps)
    # undecodable, with a bogus frame and stamp: a warning, and nothing else
    bad = cloud(classes, T0 + 50 * S, frame='')
    bad.fields = [f for f in bad.fields if f.name != 'x']
    out = pipe.process(bad)
    assert set(out.warnings) == {'unusable_cloud'} and out.reset_reason == ''
    assert pipe.resets == resets and len(pipe.detector.sweeps) == sweeps
    assert pipe.last_frame_id == 'lidar' and pipe.last_stamp_ns == T0 + S // 10
    out = pipe.process(cloud(classes, T0 + 2 * S // 10))
    assert out.reset_reason == '' and out.used_memory
    # an empty cloud past the odometry, then a cloud whose pose leapt 100 m: still a jump
    out = pipe.process(cloud(classes, T0 + 5 * S // 10, n=0))
    assert out.pose_source.startswith('none') and out.reset_reason == ''
    odometry(T0 + 4 * S // 10, T0 + 8 * S // 10, 100.0)
    assert 'pose jumped 100.0 m' in pipe.process(cloud(classes, T0 + 6 * S // 10)).reset_reason
    # a cloud with points but no pose: the memory is forgotten, and said
    pipe.process(cloud(classes, T0 + 7 * S // 10))
    resets = pipe.resets
    out = pipe.process(cloud(classes, T0 + 10 * S // 10))
    assert out.reset_reason.startswith('no pose for the cloud') and pipe.resets == resets + 1
    assert not out.used_memory
    # tracking off and on: the ids go on
    ids_before = pipe.detector.tracks.next_id
    pipe.configure(replace(pipe.params, tracking=False))
    pipe.configure(replace(pipe.params, tracking=True))
    assert pipe.detector.tracks.next_id == ids_before
    # reading the clouds another way: sweeps and memory go, the tracks stay
    odometry(T0 + 10 * S // 10, T0 + 14 * S // 10, 100.0)
    pipe.process(cloud(classes, T0 + 11 * S // 10))
    pipe.process(cloud(classes, T0 + 12 * S // 10))
    tracks = pipe.detector.tracks
    ids, live = tracks.ids.copy(), len(tracks)
    assert len(pipe.detector.sweeps) >= 1 and live >= 1
    pipe.configure(replace(pipe.params, intensity_scale=1.0, max_range=60.0))
    assert pipe.last_reset_reason == 'input settings changed: intensity_scale, max_range'
    assert len(pipe.detector.sweeps) == 0 and pipe.detector.memory is None
    assert pipe.detector.tracks is tracks and len(tracks) == live
    assert np.array_equal(tracks.ids, ids)
    # clouds with nothing to place for longer than max_gap_s while the vehicle drove on: said
    # as such, not as a pose jump
    pipe.process(cloud(classes, T0 + 13 * S // 10))
    for k in range(14, 20):
        pipe.process(cloud(classes, T0 + k * S // 10, n=0))
    odometry(T0 + 14 * S // 10, T0 + 21 * S // 10, 130.0)
    out = pipe.process(cloud(classes, T0 + 20 * S // 10))
    assert out.reset_reason.startswith('no cloud placed for 0.70 s'), out.reset_reason


def test_limit_threads_bounds_torch_and_numpys_blas():
    """The node's ``threads`` bound numpy's BLAS pool too: its idle workers spin after each
    large product (the node at 114k points used a core more); restored after the test."""
    threadpoolctl = pytest.importorskip('threadpoolctl')
    import torch

    from suit_ros.ros_params import limit_threads
    threadpool_info, threadpool_limits = threadpoolctl.threadpool_info, \
        threadpoolctl.threadpool_limits
    torch_before = torch.get_num_threads()
    blas_before = {p['filepath']: p['num_threads'] for p in threadpool_info()
                   if p['user_api'] == 'blas'}
    try:
        said = limit_threads(1)
        assert torch.get_num_threads() == 1 and 'BLAS threads 1' in said
        blas = [p['num_threads'] for p in threadpool_info() if p['user_api'] == 'blas']
        assert blas and all(n == 1 for n in blas)
    finally:
        torch.set_num_threads(torch_before)
        for path, n in blas_before.items():
            threadpool_limits(limits={path: n})


def test_the_ego_crop_is_the_box_in_base_link():
    """The crop of the vehicle's own returns tests each point in base_link (the extrinsic's
    rotation and translation applied), inclusive at the box's faces."""
    from suit_ros.params import DetectorParams
    from suit_ros.pipeline import DetectionPipeline
    p = DetectorParams(ego_box_min=(-1.0, -0.5, -1.0), ego_box_max=(2.0, 1.0, 1.0))
    pipe = DetectionPipeline.__new__(DetectionPipeline)
    pipe.params = p
    T = np.eye(4)
    T[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]     # yaw +90 degrees
    T[:3, 3] = [0.5, 0.0, 0.0]
    pipe.T_base_lidar = T
    pts = np.array([[0.0, -1.5, 0.0, 0], [0.0, -1.4, 0.0, 0], [1.0, 0.0, 0.0, 0],
                    [0.0, 0.0, 1.0, 0], [0.0, 0.0, 1.5, 0], [0.9, 0.0, 0.0, 0],
                    [0.0, -1.7, 0.0, 0]], np.float32)
    # base_link x = 0.5 - y, y = x: (2.0, 0), (1.9, 0), (0.5, 1.0), (0.5, 0) z 1, z 1.5,
    # (0.5, 0.9) (the rotation transposed: y -0.9, out), (2.2, 0) (no translation: 1.7, in)
    assert pipe._in_ego_box(pts).tolist() == [True, True, True, True, False, True, False]


@pytest.mark.slow
def test_traffic_side_auto_goes_over_to_left_hand_traffic_on_a_left_hand_drive(model, classes):
    """``traffic_side: auto`` in the node's pipeline, the shipped model: a left-hand drive (a
    validation drive mirrored, with oncoming traffic) fed as clouds and odometry. The
    oncoming vehicles pass on the ego's right, so within its first 4 seconds the side in use
    goes over to left, the memory and the tracks reset once with the reason given, and from
    the next cloud on the boxes are those of ``traffic_side: left`` started there; the
    diagnostics' line says the side each frame's boxes were made in and the votes. Set to a
    fixed side again, it resets."""
    from suit_ros.data.augment import mirror_world
    from suit_ros.data.sequences import synthetic_split
    from suit_ros.msg_adapters.odometry import matrix_to_quaternion
    from suit_ros.ops.geometry import se3_inverse
    drive = [mirror_world(f) for f in synthetic_split('val', 1, 40, first=13)[0]]
    T_bl = np.asarray(drive[0].T_base_lidar)
    R = T_bl[:3, :3]
    rpy = (float(np.arctan2(R[2, 1], R[2, 2])), float(-np.arcsin(R[2, 0])),
           float(np.arctan2(R[1, 0], R[0, 0])))

    def run(side, frames):
        pipe = make_pipeline(model, classes, traffic_side=side, intensity_scale=1.0,
                             deskew=False, extrinsic_xyz=tuple(float(v) for v in T_bl[:3, 3]),
                             extrinsic_rpy=rpy)
        outs = []
        for f in frames:
            T = np.asarray(f.pose) @ se3_inverse(T_bl)
            m = odom(f.stamp_ns)
            p, q = m.pose.pose.position, m.pose.pose.orientation
            p.x, p.y, p.z = (float(v) for v in T[:3, 3])
            q.x, q.y, q.z, q.w = (float(v) for v in matrix_to_quaternion(T[:3, :3]))
            assert pipe.add_odometry(m)
            array = np.zeros(len(f.points), [(k, '<f4') for k in ('x', 'y', 'z', 'intensity')])
            for i, k in enumerate(('x', 'y', 'z', 'intensity')):
                array[k] = f.points[:, i]
            outs.append(pipe.process(cloud(classes, f.stamp_ns, array)))
        return pipe, outs

    pipe, auto = run('auto', drive)
    assert pipe.params.traffic_side == 'auto' and pipe.traffic_side == 'left'
    switch = next(k for k, o in enumerate(auto) if o.reset_reason)
    assert 10 <= switch <= 38 and pipe.resets == 1
    assert auto[switch].reset_reason.startswith('traffic side left (auto: of the latest ')
    assert pipe.last_reset_reason == auto[switch].reset_reason
    assert all(o.traffic_side.startswith('right (auto: ') for o in auto[:switch + 1])
    assert all(o.traffic_side.startswith('left (auto: ') for o in auto[switch + 1:])
    right, left_votes = pipe.side_vote.counts
    assert left_votes >= 4 and right <= 1
    said = f'{right} passed on the left, {left_votes} on the right)'
    assert auto[-1].traffic_side.endswith(said)
    _, left = run('left', drive[switch + 1:])
    assert all(o.traffic_side == 'left' for o in left)
    for a, b in zip(auto[switch + 1:], left):
        assert len(a.detections) > 3
        np.testing.assert_allclose(a.detections.boxes, b.detections.boxes, atol=1e-3)
        np.testing.assert_allclose(a.detections.scores, b.detections.scores, atol=1e-4)
    pipe.configure(replace(pipe.params, traffic_side='left'))     # the side in use: no reset
    assert pipe.resets == 1
    pipe.configure(replace(pipe.params, traffic_side='auto'))     # goes on from left
    assert pipe.resets == 1 and pipe.traffic_side == 'left'
    pipe.configure(replace(pipe.params, traffic_side='right'))
    assert pipe.resets == 2 and pipe.last_reset_reason == 'traffic side changed'
