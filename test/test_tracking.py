"""The tracker (suit_ros.tracking): tracks in the odometry frame, filtered velocities."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from suit_ros.ops.geometry import pose_from_xyz_rpy
from suit_ros.structures import Detections
from suit_ros.tracking import Tracker, TrackerConfig

DT_NS = 100_000_000          # 10 Hz


def frame(centres, velocities, labels=None, yaw=0.0, scores=None):
    centres = np.asarray(centres, np.float64).reshape(-1, 2)
    n = len(centres)
    boxes = np.zeros((n, 7))
    boxes[:, :2] = centres
    boxes[:, 3:6] = (4.5, 1.9, 1.6)
    boxes[:, 6] = yaw
    labels = np.zeros(n, np.int64) if labels is None else np.asarray(labels)
    scores = np.full(n, 0.8) if scores is None else np.asarray(scores)
    return Detections(boxes, np.asarray(velocities, np.float64).reshape(n, 2), scores, labels)


def ego_pose(t, speed=8.0, yaw_rate=0.3):
    """A vehicle turning at constant speed and yaw rate: its pose in odom at ``t`` s."""
    yaw = yaw_rate * t
    x = speed / yaw_rate * np.sin(yaw)
    y = speed / yaw_rate * (1 - np.cos(yaw))
    return pose_from_xyz_rpy((x, y, 0.0), (0.0, 0.0, yaw))


def to_frame(T, xy_odom, v_odom):
    """Odometry-frame centres and velocities seen from pose ``T``."""
    R = T[:2, :2]
    return (np.asarray(xy_odom) - T[:2, 3]) @ R, np.asarray(v_odom) @ R


def test_a_moving_car_seen_from_a_turning_ego_gets_its_velocity():
    """Centres with 0.2 m noise and a head that says 'standing still': after a second the
    filtered velocity (in the detections' frame) is the car's, and the track id holds."""
    rng = np.random.default_rng(0)
    vf = Tracker()
    v_true = np.array([9.0, -3.0])
    errs, ids = [], set()
    for k in range(20):
        t = k * 0.1
        T = ego_pose(t)
        xy, v = to_frame(T, np.array([20.0, 5.0]) + v_true * t, v_true)
        xy = xy + rng.normal(0, 0.2, 2)
        out, tid = vf.update(frame(xy, [0.0, 0.0]), k * DT_NS, T)
        ids.add(int(tid[0]))
        errs.append(np.linalg.norm(out.velocities[0] - v))
    assert ids == {1}
    assert errs[0] == pytest.approx(np.linalg.norm(v_true))     # first frame: the head's reading
    assert np.mean(errs[10:]) < 1.0
    assert len(vf) == 1


def test_static_objects_stay_static_under_ego_motion():
    vf = Tracker()
    walls = np.array([[15.0, 4.0], [30.0, -6.0], [8.0, 10.0]])
    for k in range(15):
        T = ego_pose(k * 0.1)
        xy, _ = to_frame(T, walls, np.zeros((3, 2)))
        out, ids = vf.update(frame(xy, np.zeros((3, 2))), k * DT_NS, T)
    assert ids.tolist() == [1, 2, 3]
    assert np.abs(out.velocities).max() < 1e-6


def test_classes_never_share_a_track_and_new_objects_get_new_ids():
    vf = Tracker()
    T = np.eye(4)
    _, ids0 = vf.update(frame([[10, 0]], [[0, 0]], labels=[0]), 0, T)
    _, ids1 = vf.update(frame([[10, 0], [10.1, 0]], [[0, 0], [0, 0]], labels=[2, 0]), DT_NS, T)
    assert ids0.tolist() == [1] and ids1.tolist() == [2, 1]
    _, ids2 = vf.update(frame([[40, 0]], [[0, 0]], labels=[0]), 2 * DT_NS, T)   # far: new
    assert ids2.tolist() == [3]


def test_a_detection_with_a_nan_neither_spoils_nor_starts_a_track():
    """A caller's detection with a NaN velocity or centre is passed on untracked (id 0): it
    turned its track's state NaN for good, and the object got a new id a frame later."""
    vf = Tracker(TrackerConfig(sweep_sigma=None))
    T = np.eye(4)
    _, ids = vf.update(frame([[10, 0]], [[0, 0]]), 0, T)
    out, bad = vf.update(frame([[10, 0], [np.nan, 3]], [[np.nan, 0], [0, 0]]), DT_NS, T)
    assert bad.tolist() == [0, 0] and np.isnan(out.velocities[0, 0])
    assert np.isfinite(vf.x).all() and len(vf) == 1
    out, again = vf.update(frame([[10, 0]], [[0, 0]]), 2 * DT_NS, T)
    assert again.tolist() == ids.tolist() == [1] and np.isfinite(out.velocities).all()


def test_tracks_end_after_misses_and_on_time_jumps():
    cfg = TrackerConfig(max_miss_s=0.2)
    vf = Tracker(cfg)
    T = np.eye(4)
    vf.update(frame([[10, 0]], [[0, 0]]), 0, T)
    for k in (1, 2):                                   # two empty frames: still alive
        out, ids = vf.update(Detections.empty(), k * DT_NS, T)
        assert len(out) == 0 and len(ids) == 0 and len(vf) == 1
    vf.update(Detections.empty(), 3 * DT_NS, T)        # third miss: gone
    assert len(vf) == 0
    vf.update(frame([[10, 0]], [[0, 0]]), 4 * DT_NS, T)
    _, ids = vf.update(frame([[10, 0]], [[0, 0]]), 4 * DT_NS, T)   # same stamp again: reset
    assert ids.tolist() == [3] and len(vf) == 1
    _, ids = vf.update(frame([[10, 0]], [[0, 0]]), 9 * DT_NS + 10 ** 9, T)   # 1.5 s gap
    assert ids.tolist() == [4]


def test_nearest_pairs_win_and_each_track_takes_one_detection():
    vf = Tracker()
    T = np.eye(4)
    vf.update(frame([[10, 0], [13, 0]], np.zeros((2, 2))), 0, T)
    _, ids = vf.update(frame([[12.9, 0], [10.1, 0], [11.5, 0]], np.zeros((3, 2))), DT_NS, T)
    assert ids.tolist() == [2, 1, 3]


def test_only_confident_detections_start_tracks_and_they_are_matched_first():
    vf = Tracker(TrackerConfig(birth_score=0.3))
    T = np.eye(4)
    out, ids = vf.update(frame([[10, 0], [20, 0]], [[1, 0], [2, 0]], scores=[0.8, 0.1]), 0, T)
    assert ids.tolist() == [1, 0] and len(vf) == 1
    assert out.velocities[1].tolist() == [2.0, 0.0]          # untracked: the head's velocity
    # a faint detection nearer the track loses it to a confident one
    _, ids = vf.update(frame([[10.05, 0], [10.4, 0]], np.zeros((2, 2)), scores=[0.1, 0.7]),
                       DT_NS, T)
    assert ids.tolist() == [0, 1]
    # with no confident candidate, a faint detection continues the track
    _, ids = vf.update(frame([[10.5, 0]], [[0, 0]], scores=[0.1]), 2 * DT_NS, T)
    assert ids.tolist() == [1]


@pytest.mark.parametrize('field,value', [('pos_sigma', 0.0), ('vel_sigma', -1.0),
                                         ('accel_sigma', float('nan')), ('gate', 0.0),
                                         ('max_gap_s', float('inf')), ('max_miss_s', -0.1),
                                         ('coast_s', float('nan')),
                                         ('birth_score', 1.5), ('score_mix', -0.1),
                                         ('sweep_sigma', 0.0), ('coast_margin', -0.1),
                                         ('speed_std_fraction', -0.1),
                                         ('speed_std_fraction', float('nan'))])
def test_config_is_validated(field, value):
    with pytest.raises(ValueError, match=field):
        TrackerConfig(**{field: value})


def test_scores_are_smoothed_over_the_track():
    vf = Tracker(TrackerConfig(score_mix=0.5))
    T = np.eye(4)
    out, _ = vf.update(frame([[10, 0]], [[0, 0]], scores=[0.8]), 0, T)
    assert out.scores.tolist() == pytest.approx([0.8])        # a new track: its own score
    out, _ = vf.update(frame([[10, 0]], [[0, 0]], scores=[0.2]), DT_NS, T)
    assert out.scores.tolist() == pytest.approx([0.5 * 0.2 + 0.5 * 0.8])
    out, _ = vf.update(frame([[10, 0]], [[0, 0]], scores=[0.6]), 2 * DT_NS, T)
    running = 0.5 * (0.8 + 0.2)                                # halving weights
    assert out.scores.tolist() == pytest.approx([0.5 * 0.6 + 0.5 * running])
    out, ids = vf.update(frame([[30, 0]], [[0, 0]], scores=[0.1]), 3 * DT_NS, T)
    assert ids.tolist() == [0] and out.scores.tolist() == pytest.approx([0.1])   # untracked



def test_a_carried_detection_keeps_its_tracks_score():
    """An object the memory holds where the cloud has no returns (a carry branch's box) is
    scored with its track's confidence, which its low carried scores do not wear down; a box
    seen in the cloud again updates the track as before."""
    mix = 0.7
    held, plain = Tracker(TrackerConfig(score_mix=mix)), Tracker(TrackerConfig(score_mix=mix))
    T = np.eye(4)
    for trk in (held, plain):
        trk.update(frame([[10, 0]], [[0, 0]], scores=[0.8]), 0, T)
    for k in range(1, 6):                                    # five occluded frames at 0.15
        a, ida = held.update(frame([[10, 0]], [[0, 0]], scores=[0.15]), k * DT_NS, T,
                             carried=np.array([True]))
        b, idb = plain.update(frame([[10, 0]], [[0, 0]], scores=[0.15]), k * DT_NS, T)
        assert ida.tolist() == idb.tolist() == [1]             # the same track continues
        assert a.scores.tolist() == pytest.approx([(1 - mix) * 0.15 + mix * 0.8])
    assert b.scores[0] < 0.25 < a.scores[0]                  # plain: worn down to ~0.15
    out, _ = held.update(frame([[10, 0]], [[0, 0]], scores=[0.6]), 6 * DT_NS, T,
                         carried=np.array([False]))          # seen again
    assert out.scores.tolist() == pytest.approx([(1 - mix) * 0.6 + mix * 0.8])
    out, _ = held.update(frame([[10, 0]], [[0, 0]], scores=[0.6]), 7 * DT_NS, T)
    assert out.scores.tolist() == pytest.approx([(1 - mix) * 0.6 + mix * 0.7])
    # a carried box no track takes is published at its own score, untracked (it starts none)
    out, ids = held.update(frame([[10, 0], [40, 0]], [[0, 0], [0, 0]], scores=[0.6, 0.5]),
                           8 * DT_NS, T, carried=np.array([False, True]))
    assert ids[1] == 0 and out.scores[1] == pytest.approx(0.5)


@pytest.mark.parametrize('score', [0.2, 0.6])
def test_carried_boxes_need_not_keep_a_track_alive(score):
    """With ``carried_refresh`` off a track held only by carried boxes ends ``max_miss_s``
    after its last box seen in the cloud, and no carried box starts a track (a memory's boxes
    keep no object tracked for ever, not under a new id either: a sure one is passed on
    untracked, id 0, at its own score); a track a carried box continued is not also coasted
    (one box per object)."""
    T = np.eye(4)
    lives, ids_seen = {}, {}
    for refresh in (True, False):
        trk = Tracker(TrackerConfig(carried_refresh=refresh, max_miss_s=0.3, coast_s=0.3))
        trk.update(frame([[10, 0]], [[0, 0]]), 0, T, current=np.zeros((0, 3)))
        ids_seen[refresh] = set()
        for k in range(1, 12):
            out, ids = trk.update(frame([[10, 0]], [[0, 0]], scores=[score]), k * DT_NS, T,
                                  carried=np.array([True]), current=np.zeros((0, 3)))
            assert trk.coasted == 0 and len(out) == 1
            ids_seen[refresh].add(int(ids[0]))
            if ids[0] == 1:
                lives[refresh] = k
        if not refresh:
            assert ids[0] == 0 and out.scores[0] == pytest.approx(score) and len(trk) == 0
    assert lives == {True: 11, False: 4}    # the last 0.4 s after the box seen (0.3 s + a frame)
    assert ids_seen[False] == {0, 1}


def test_a_carried_box_keeps_the_size_and_heading_it_was_seen_with():
    """With ``carried_as_seen`` (the default) a carried detection continuing a track is
    published with the size and heading of the track's last box, not the carry head's guess
    (here a squashed box turned 90 degrees), at the centre the memory holds it at."""
    T = np.eye(4)
    out = {}
    for as_seen in (False, True):
        trk = Tracker(TrackerConfig(carried_as_seen=as_seen))
        for k in range(6):                               # seen: 10 m/s along x
            trk.update(frame([[10 + k, 0]], [[10, 0]]), k * DT_NS, T)
        guess = frame([[16.1, 0.2]], [[10, 0]], yaw=np.pi / 2)
        guess.boxes[:, 2:6] = (0.3, 2.0, 1.0, 1.0)        # its centre, height included, held
        out[as_seen], _ = trk.update(guess, 6 * DT_NS, T, carried=np.array([True]))
        # a box seen in the cloud again is published as the model gives it
        seen, _ = trk.update(guess, 7 * DT_NS, T, carried=np.array([False]))
        assert seen.boxes[0, 3:6].tolist() == [2.0, 1.0, 1.0]
    assert out[False].boxes[0, 3:7].tolist() == pytest.approx([2.0, 1.0, 1.0, np.pi / 2])
    assert out[True].boxes[0, 3:7].tolist() == pytest.approx([4.5, 1.9, 1.6, 0.0])
    assert out[True].boxes[0, :3].tolist() == pytest.approx([16.1, 0.2, 0.3])  # where held


def car_points(centre, yaw, speed, lags, rng, n=60):
    """Returns on the visible outline of a 4.5 x 1.9 m car moving ``speed`` m/s along its
    heading, one cloud per time lag (the car was ``speed x lag`` behind then), ground at z 0."""
    out = []
    heading = np.array([np.cos(yaw), np.sin(yaw)])
    side = np.array([-np.sin(yaw), np.cos(yaw)])
    for lag in lags:
        u = rng.uniform(-2.25, 2.25, n)
        v = np.where(rng.random(n) < 0.5, -0.95, 0.95)
        u[: n // 4] = 2.25                                   # the front face
        xy = np.asarray(centre) + (u[:, None] - speed * lag) * heading + v[:, None] * side
        z = rng.uniform(0.4, 1.5, n)
        out.append(np.c_[xy, z, np.full(n, 0.5), np.full(n, lag)])
    return np.concatenate(out)


def test_sweep_velocities_read_motion_along_the_heading():
    from suit_ros.tracking import sweep_velocities
    rng = np.random.default_rng(3)
    lags = (0.0, 0.1, 0.2)
    moving = car_points((12.0, 4.0), 0.6, 9.0, lags, rng)
    parked = car_points((-8.0, -6.0), -1.2, 0.0, lags, rng)
    ground = np.c_[rng.uniform(-30, 30, (3000, 2)), np.zeros(3000), np.zeros(3000),
                   rng.choice(lags, 3000)]
    wall = np.c_[np.full(600, 20.0), rng.uniform(-10, 10, 600), rng.uniform(0, 3, 600),
                 np.zeros(600), rng.choice(lags, 600)]
    pts = np.concatenate([moving, parked, ground, wall]).astype(np.float32)
    boxes = np.array([[12.0, 4.0, 0.8, 4.5, 1.9, 1.6, 0.6],
                      [-8.0, -6.0, 0.8, 4.5, 1.9, 1.6, -1.2 + np.pi],   # heading flipped
                      [12.0, 4.0, 0.8, 4.5, 1.9, 1.6, 0.6],
                      [-20.0, 15.0, 0.8, 4.5, 1.9, 1.6, 0.0]])          # nothing there
    vel, ok, spread = sweep_velocities(pts, boxes, np.array([True, True, False, True]))
    assert ok.tolist() == [True, True, False, False]
    np.testing.assert_allclose(vel[0], 9.0 * np.array([np.cos(0.6), np.sin(0.6)]), atol=0.4)
    np.testing.assert_allclose(vel[1], 0.0, atol=0.3)
    assert not vel[2:].any()
    # both earlier sweeps read the same speed; what was not read has no spread
    assert spread[0] <= 1.0 and spread[1] <= 1.0
    assert np.isinf(spread[2:]).all()
    one_sweep = pts[pts[:, 4] == 0]                       # no earlier sweep: nothing to read
    assert not sweep_velocities(one_sweep, boxes, np.ones(4, bool)).read.any()
    two_sweeps = pts[pts[:, 4] < 0.15]                    # one earlier sweep: read, spread inf
    one = sweep_velocities(two_sweeps, boxes, np.array([True, False, False, False]))
    assert one.read[0] and np.isinf(one.spread[0])
    np.testing.assert_allclose(one.velocities[0], vel[0], atol=1.0)


def test_sweep_readings_whose_sweeps_disagree_are_trusted_less():
    """An earlier sweep whose returns sit where another car's would: the two earlier sweeps
    read speeds far apart, and the spread says so."""
    from suit_ros.tracking import sweep_velocities
    rng = np.random.default_rng(4)
    steady = car_points((12.0, 4.0), 0.0, 8.0, (0.0, 0.1, 0.2), rng)
    # the sweep 0.2 s back sees the car 1.2 m further on than a steady 8 m/s puts it: it
    # reads 2 m/s, the sweep 0.1 s back 8 m/s
    jumpy = steady.copy()
    old = np.isclose(jumpy[:, 4], 0.2)
    jumpy[old, 0] += 1.2
    box = np.array([[12.0, 4.0, 0.8, 4.5, 1.9, 1.6, 0.0]])
    calm = sweep_velocities(steady.astype(np.float32), box, np.ones(1, bool))
    torn = sweep_velocities(jumpy.astype(np.float32), box, np.ones(1, bool))
    assert calm.read[0] and torn.read[0]
    assert calm.spread[0] <= 1.0
    assert 4.0 <= torn.spread[0] <= 8.0


def test_swept_velocity_is_fused_with_the_heads():
    from suit_ros.tracking import SweepReading
    cfg = TrackerConfig(vel_sigma=4.0, sweep_sigma=2.0, sweep_spread_gain=0.0)
    vf = Tracker(cfg)
    det = frame([[10, 0], [20, 0]], [[0, 0], [5, 0]])
    swept = SweepReading(np.array([[10.0, 0.0], [9.0, 0.0]]), np.array([True, False]),
                         np.array([np.inf, np.inf]))
    out, _ = vf.update(det, 0, np.eye(4), swept)
    # inverse-variance weights 1/16 and 1/4: (0 * 1 + 10 * 4) / 5 = 8
    np.testing.assert_allclose(out.velocities, [[8.0, 0.0], [5.0, 0.0]])
    plain, _ = Tracker(replace(cfg, sweep_sigma=None)).update(det, 0, np.eye(4), swept)
    np.testing.assert_allclose(plain.velocities, [[0.0, 0.0], [5.0, 0.0]])


def test_a_reading_is_fused_by_how_far_its_sweeps_agree():
    """With ``sweep_spread_gain`` the reading's variance is ``sweep_sigma^2 + (gain x
    spread)^2``: sweeps that agree count as ``sweep_sigma``, a spread of 1 m/s at gain 2 as
    sqrt(4 + 4), and a reading from one earlier sweep (spread inf) as ``sweep_single_sigma``,
    or not at all."""
    from suit_ros.tracking import SweepReading
    cfg = TrackerConfig(vel_sigma=4.0, sweep_sigma=2.0, sweep_spread_gain=2.0,
                        sweep_single_sigma=None)
    # the second box could not be read (its spread inf, its velocity 0): the others keep
    # their own weights
    det = frame([[10, 0], [40, 0], [20, 0], [30, 0]], [[0, 0], [2, 0], [0, 0], [0, 0]])
    swept = SweepReading(np.array([[10.0, 0.0], [0.0, 0.0], [10.0, 0.0], [10.0, 0.0]]),
                         np.array([True, False, True, True]),
                         np.array([0.0, np.inf, 1.0, np.inf]))
    vf = Tracker(cfg)
    out, _ = vf.update(det, 0, np.eye(4), swept)
    # weights: head 1/16; the sweeps 1/4, none, 1/8 and 0
    np.testing.assert_allclose(out.velocities[:, 0], [8.0, 2.0, 10 * 2 / 3, 0.0])
    np.testing.assert_allclose(out.velocities[:, 1], 0.0)
    # the new tracks start with the fused variance
    np.testing.assert_allclose(vf.P[:, 1, 1],
                               [1 / (1 / 16 + 1 / 4), 16, 1 / (1 / 16 + 1 / 8), 16])
    single, _ = Tracker(replace(cfg, sweep_single_sigma=2.0)).update(det, 0, np.eye(4), swept)
    np.testing.assert_allclose(single.velocities[:, 0], [8.0, 2.0, 10 * 2 / 3, 8.0])
    with pytest.raises(ValueError, match='sweep_single_sigma'):
        TrackerConfig(sweep_single_sigma=0.0)
    with pytest.raises(ValueError, match='sweep_spread_gain'):
        TrackerConfig(sweep_spread_gain=-1.0)


def test_a_vehicle_driving_backwards_by_a_confident_velocity_is_turned_round():
    """A car at 10 m/s along +x whose box says it faces -x: once the track's velocity is sure,
    the box is turned round; a slow car, a pedestrian, or the setting off leave it."""
    def drive(cfg, speed, label, frames=10):
        vf = Tracker(cfg)
        for k in range(frames):
            out, _ = vf.update(frame([[10.0 + speed * 0.1 * k, 3.0]], [speed, 0.0], [label],
                                     yaw=np.pi - 0.2), k * DT_NS, np.eye(4))
        return float(out.boxes[0, 6])
    cfg = TrackerConfig()
    assert drive(cfg, 10.0, 0) == pytest.approx(-0.2, abs=1e-5)            # turned round
    assert drive(cfg, 1.0, 0) == pytest.approx(np.pi - 0.2, abs=1e-5)      # too slow to tell
    assert drive(cfg, 10.0, 2) == pytest.approx(np.pi - 0.2, abs=1e-5)     # a pedestrian
    off = replace(cfg, heading_min_speed=None)
    assert drive(off, 10.0, 0) == pytest.approx(np.pi - 0.2, abs=1e-5)
    # 6 m/s on its first frame is the head's reading alone (sigma 4.5 m/s): not sure enough;
    # after a second of centres that agree, it is
    assert drive(cfg, 6.0, 0, frames=1) == pytest.approx(np.pi - 0.2, abs=1e-5)
    assert drive(cfg, 6.0, 0, frames=10) == pytest.approx(-0.2, abs=1e-5)


def road(T, around_odom, half=3.0, step=0.25):
    """Road returns (a flat grid at z -1.8) over a square of the odometry frame, seen from
    pose ``T`` (the detections' frame, its sensor at the origin)."""
    g = np.arange(-half, half + 1e-9, step)
    xx, yy = np.meshgrid(g, g)
    xy_odom = np.c_[xx.ravel(), yy.ravel()] + np.asarray(around_odom)
    xy, _ = to_frame(T, xy_odom, np.zeros_like(xy_odom))
    return np.c_[xy, np.full(len(xy), -1.8)]


def test_coasting_holds_a_confident_track_only_where_the_sweep_shows_nothing():
    """A car tracked for 8 frames loses its detection: where the sweep has no return around
    its predicted box (a lost sector) it is published there, with its id, running score and
    velocity, for ``coast_s`` (0.3 s: 3 frames); where the road shows through (it drove off),
    not."""
    v_true = np.array([6.0, 1.0])
    start = np.array([15.0, -3.0])
    held = []
    for blind in (True, False):
        vf = Tracker(TrackerConfig(coast_s=0.3))
        for k in range(14):
            t = k * 0.1
            T = ego_pose(t)
            xy_odom = start + v_true * t
            xy, v = to_frame(T, xy_odom, v_true)
            seen = k < 8
            det = frame(xy, v) if seen else Detections.empty()
            det.boxes[:, 2] = -1.0             # on the road 1.8 m below the sensor
            current = np.zeros((0, 3)) if blind and not seen else road(T, xy_odom)
            out, ids = vf.update(det, k * DT_NS, T, current=current)
            if seen:
                assert vf.coasted == 0 and ids.tolist() == [1]
                continue
            assert vf.coasted == len(out)
            if blind and k < 8 + 3:
                assert ids.tolist() == [1] and out.labels.tolist() == [0]
                assert np.linalg.norm(out.boxes[0, :2] - xy) < 0.3      # where it is now
                assert np.linalg.norm(out.velocities[0] - v) < 0.5
                assert out.boxes[0, 2:6].tolist() == pytest.approx([-1.0, 4.5, 1.9, 1.6])
                # its heading as last published (0 then), turned by the ego's yaw since
                assert out.boxes[0, 6] == pytest.approx(-0.3 * (t - 0.7), abs=1e-4)
                assert out.scores[0] == pytest.approx(0.8)              # its running score
                held.append(k)
            else:
                assert len(out) == 0, (blind, k)
    assert held == [8, 9, 10]


def test_velocity_std_is_the_filters_and_says_how_far_to_trust_a_young_track():
    """Each returned detection carries its velocity's standard deviation: the head's noise
    (``vel_sigma``) at birth and for a faint detection no track took, falling as the track
    gathers centres, growing again while it coasts; widened by ``speed_std_fraction`` of the
    box's speed (the head's speed error is no white noise); and the errors of the filtered
    velocity of a car the head reads as standing still lie within about two of them."""
    runs = {}
    for fraction in (0.0, 0.15):
        rng = np.random.default_rng(1)
        cfg = TrackerConfig(coast_s=0.3, speed_std_fraction=fraction)
        vf = Tracker(cfg)
        assert vf.velocity_std.shape == (0,)
        v_true = np.array([9.0, -3.0])
        stds, speeds, z = [], [], []
        for k in range(25):
            t = k * 0.1
            T = ego_pose(t)
            xy_odom = np.array([20.0, 5.0]) + v_true * t
            xy, v = to_frame(T, xy_odom, v_true)
            seen = k < 20
            det = (frame(np.stack([xy + rng.normal(0, 0.2, 2), xy + 12.0]), [[0.0, 0.0]] * 2,
                         scores=[0.8, 0.2]) if seen else Detections.empty())
            det.boxes[:, 2] = -1.0
            current = road(T, xy_odom) if seen else np.zeros((0, 3))
            out, ids = vf.update(det, k * DT_NS, T, current=current)
            assert vf.velocity_std.shape == (len(out),) and vf.velocity_std.dtype == np.float32
            if not seen and k >= 23:
                assert len(out) == 0                    # coasted for 3 frames, then not
                continue
            i = 0 if seen else int(np.nonzero(ids == 1)[0][0])
            stds.append(float(vf.velocity_std[i]))
            speeds.append(float(np.hypot(*out.velocities[i])))
            if seen:                                    # the faint one: the head's own noise
                assert ids[1] == 0 and vf.velocity_std[1] == pytest.approx(cfg.vel_sigma)
                if k >= 3:
                    z.append(np.abs(out.velocities[0] - v) / vf.velocity_std[0])
        runs[fraction] = np.array(stds), np.array(speeds), np.concatenate(z)
    stds, speeds, z = runs[0.0]
    assert stds[0] == pytest.approx(TrackerConfig().vel_sigma)   # born: the head's reading
    assert all(b < a for a, b in zip(stds[:10], stds[1:10]))      # settles as centres come
    assert stds[19] < 1.0
    assert stds[20] > stds[19] and stds[21] > stds[20]            # coasting: less sure
    assert np.mean(z < 2.0) > 0.9
    wide, wide_speeds, _ = runs[0.15]                # the same filter, widened by its speed
    np.testing.assert_allclose(wide_speeds, speeds)
    np.testing.assert_allclose(wide, np.hypot(stds, 0.15 * speeds), rtol=1e-5)
    assert wide[19] > stds[19] + 0.8                  # ~9.2 m/s filtered: 0.15 of it, 1.4


def test_coasting_needs_a_confident_track_and_can_be_turned_off():
    T = np.eye(4)
    for cfg, score, expect in ((TrackerConfig(coast_s=0.3), 0.8, 1),
                               (TrackerConfig(coast_s=0.3), 0.35, 0),   # never confident
                               (TrackerConfig(coast_s=0.0), 0.8, 0),   # off
                               (TrackerConfig(), 0.8, 1)):                # the default: 0.5 s
        vf = Tracker(cfg)
        for k in range(4):
            vf.update(frame([10.0, 0.0], [0.0, 0.0], scores=[score]), k * DT_NS, T,
                      current=np.zeros((0, 3)))
        out, _ = vf.update(Detections.empty(), 4 * DT_NS, T, current=np.zeros((0, 3)))
        assert len(out) == expect == vf.coasted, (cfg, score)
    # no current sweep given: nothing coasts
    vf = Tracker(TrackerConfig(coast_s=0.3))
    vf.update(frame([10.0, 0.0], [0.0, 0.0]), 0, T)
    assert len(vf.update(Detections.empty(), DT_NS, T)[0]) == 0
    with pytest.raises(ValueError, match='coast_s'):
        TrackerConfig(coast_s=-1.0)
    with pytest.raises(ValueError, match='coast_margin'):
        TrackerConfig(coast_s=0.2, coast_margin=float('nan'))
    # a track lives max_miss_s without a detection, and coasts no longer than that
    vf = Tracker(TrackerConfig(max_miss_s=0.2))             # coast_s 0.5 by default
    vf.update(frame([10.0, 0.0], [0.0, 0.0]), 0, T)
    held = [len(vf.update(Detections.empty(), k * DT_NS, T, current=np.zeros((0, 3)))[0])
            for k in range(1, 5)]
    assert held == [1, 1, 0, 0]


@pytest.mark.parametrize('rate_hz,coasted,lived', [(5.0, 2, 3), (10.0, 5, 6), (20.0, 10, 12),
                                                    (12.5, 6, 7)])
def test_track_lifetimes_are_seconds_at_any_frame_rate(rate_hz, coasted, lived):
    """``coast_s`` (0.5) and ``max_miss_s`` (0.6) are seconds since the last detection, in
    whole frames: a blind confident track is held 2 / 5 / 10 frames at 5 / 10 / 20 Hz (a node
    that runs on every other cloud of a 10 Hz sensor, the sensor, a 20 Hz sensor) and lives 3 /
    6 / 12; with stamps jittered by up to 8 ms at 10 Hz the same frames as without jitter."""
    rng = np.random.default_rng(3)
    T = np.eye(4)
    blind = np.zeros((0, 3))
    dt_ns = int(round(1e9 / rate_hz))
    for jitter_ns in ((0, 8_000_000) if rate_hz == 10.0 else (0,)):
        def stamp(k, jitter_ns=jitter_ns):
            return k * dt_ns + int(rng.integers(-jitter_ns, jitter_ns + 1))
        vf = Tracker()
        for k in range(3):
            vf.update(frame([10.0, 0.0], [0.0, 0.0], scores=[0.8]), stamp(k), T, current=blind)
        held, alive = [], []
        for k in range(3, 3 + 15):
            out, _ = vf.update(Detections.empty(), stamp(k), T, current=blind)
            held.append(len(out))
            alive.append(len(vf))
        assert held == [1] * coasted + [0] * (15 - coasted), (rate_hz, jitter_ns)
        assert alive == [1] * lived + [0] * (15 - lived), (rate_hz, jitter_ns)


def test_unseen_boxes_are_those_no_ray_passed_through():
    """A car 20 m ahead (sensor 1.8 m up): blind with no returns or only returns in front of
    it or over an occluder's top; seen with road returns under it, or a wall behind it whose
    rays passed low through where it would be."""
    from suit_ros.tracking import unseen
    car = np.array([[20.0, 0.0, 0.8, 4.5, 1.9, 1.6, 0.3]])
    sensor = np.array([0.0, 0.0, 1.8])

    def cloud(*xyz):
        return np.array(xyz, np.float64).reshape(-1, 3)
    assert unseen(car, np.zeros((0, 3)), 0.5, sensor).tolist() == [True]
    assert unseen(car, cloud([10, 0, 0.0], [15, 1, 0.5]), 0.5, sensor).tolist() == [True]
    assert unseen(car, cloud([21, 0.5, 0.0]), 0.5, sensor).tolist() == [False]  # road under
    # a wall 10 m behind: a return 0.5 m up crossed the car's range 1.3 m up (through it)
    assert unseen(car, cloud([31, 0, 0.5]), 0.5, sensor).tolist() == [False]
    # the same wall seen 6 m up (over a truck in front): the ray was 4.5 m up at the car
    assert unseen(car, cloud([31, 0, 6.0]), 0.5, sensor).tolist() == [True]
    # off its bearings: a return beside it
    assert unseen(car, cloud([25, 8, 0.0]), 0.5, sensor).tolist() == [True]
    # behind the sensor, across the +-pi cut: the same rules
    back = car.copy()
    back[0, :2] = (-20.0, 0.1)
    assert unseen(back, cloud([-21, -0.4, 0.0]), 0.5, sensor).tolist() == [False]
    assert unseen(back, cloud([-21, 6, 0.0]), 0.5, sensor).tolist() == [True]
    # the sensor inside the grown box: never blind
    around = car.copy()
    around[0, :2] = (0.5, 0.0)
    assert unseen(around, np.zeros((0, 3)), 0.5, sensor).tolist() == [False]


def test_unseen_matches_its_definition_on_random_clouds():
    """The compiled pass (ops.kernels.rays_through) against the definition written out in
    numpy: bearings, range from the nearest corner, the ray's height at that range."""
    from suit_ros.tracking import unseen
    rng = np.random.default_rng(7)
    o = np.array([0.9, 0.0, 1.8])
    for trial in range(20):
        n = int(rng.integers(0, 400))
        pts = np.c_[rng.uniform(-40, 40, (n, 2)), rng.uniform(-0.5, 4, n)].astype(np.float32)
        boxes = np.c_[rng.uniform(-30, 30, (8, 2)), rng.uniform(0.3, 1.5, 8),
                      rng.uniform(0.5, 5, (8, 3)), rng.uniform(-np.pi, np.pi, 8)]
        got = unseen(boxes, pts, 0.5, o)
        for m, b in enumerate(boxes):
            c, s = np.cos(b[6]), np.sin(b[6])
            corners = np.array([[b[0] + i * (b[3] / 2 + 0.5) * c - j * (b[4] / 2 + 0.5) * s,
                                 b[1] + i * (b[3] / 2 + 0.5) * s + j * (b[4] / 2 + 0.5) * c]
                                for i in (1, -1) for j in (1, -1)]) - o[:2]
            near = np.hypot(*corners.T).min()
            bearing = np.arctan2(b[1] - o[1], b[0] - o[0])
            wrap = lambda a: (a + np.pi) % (2 * np.pi) - np.pi       # noqa: E731
            half = np.abs(wrap(np.arctan2(corners[:, 1], corners[:, 0]) - bearing)).max()
            if near <= 1.0 or half >= np.pi / 2:
                assert not got[m]
                continue
            p = pts.astype(np.float64) - o
            r = np.hypot(p[:, 0], p[:, 1])
            on = (r >= near) & (np.abs(wrap(np.arctan2(p[:, 1], p[:, 0]) - bearing)) <= half)
            z = p[on, 2] * near / r[on]
            lo, hi = b[2] - b[5] / 2 - 0.5 - o[2], b[2] + b[5] / 2 + 0.5 - o[2]
            assert got[m] == (not np.any((z >= lo) & (z <= hi))), (trial, m)


def test_keyframes_half_a_second_apart_keep_their_tracks_offline():
    """nuScenes keyframes come at 2 Hz, about 0.5 s apart with jitter. At the node's
    max_gap_s (0.5 s) a keyframe 0.52 s late drops every track; the offline run's tracker
    (``tracker_for``) widens the gap to 2.5 frame intervals and keeps them, while a 10 Hz
    drive keeps the node's setting."""
    from types import SimpleNamespace

    from suit_ros.evaluate import tracker_for
    stamps = np.cumsum([0, 0.48, 0.52, 0.5, 0.55, 0.47]) * 1e9
    keyframes = [[SimpleNamespace(stamp_ns=int(t)) for t in stamps]]
    cfg = tracker_for(keyframes)
    assert cfg.max_gap_s == pytest.approx(2.5 * 0.5)
    ten_hz = [[SimpleNamespace(stamp_ns=k * DT_NS) for k in range(6)]]
    assert tracker_for(ten_hz) == TrackerConfig()
    assert tracker_for([[SimpleNamespace(stamp_ns=0)]]) == TrackerConfig()
    custom = TrackerConfig(score_mix=0.2)
    assert tracker_for(keyframes, custom).score_mix == 0.2

    def ids_over(config):
        vf, out = Tracker(config), []
        for k, t in enumerate(stamps):
            _, ids = vf.update(frame([[10.0 + 5.0 * k * 0.5, 2.0]], [[5.0, 0.0]]), int(t),
                               np.eye(4))
            out.append(int(ids[0]))
        return out
    assert ids_over(cfg) == [1] * len(stamps)
    assert len(set(ids_over(TrackerConfig()))) > 1       # the late keyframes restart it
