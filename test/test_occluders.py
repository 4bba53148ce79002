"""Occluders: screens cast into frames as the sensor sees them, fixed in the world, drawn before
objects; the training option and the evaluation variant."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from suit_ros.data.occluders import Screen, draw_screens, occlude, occluded_drives, with_screens
from suit_ros.errors import ConfigError
from suit_ros.ops.geometry import count_points_in_boxes, pose_from_xyz_rpy
from suit_ros.structures import Detections, Frame

SENSOR = (0.0, 0.0, 2.0)


def _frame(points: np.ndarray, x_ego: float = 0.0, gt: Detections | None = None) -> Frame:
    pts = np.asarray(points, np.float32)
    if pts.shape[1] == 3:
        pts = np.c_[pts, np.full(len(pts), 0.5), np.zeros(len(pts))].astype(np.float32)
    num = None if gt is None else count_points_in_boxes(pts[:, :3], gt.boxes)
    return Frame(pts, pose_from_xyz_rpy((x_ego, 0.0, 0.0), (0, 0, 0)), 0, 'base_link', gt,
                 num)


# a screen across the x axis 5 m ahead, 4 m wide, 1.5 m high, standing on z = 0
WALL = Screen((5.0, -2.0), (5.0, 2.0), 0.0, 1.5, 0.1)


def test_a_return_behind_the_screen_moves_onto_it_along_its_ray():
    pts = np.array([[10.0, 0.0, 0.0],      # behind, its ray crosses the screen at 1.0 m up
                    [10.0, 0.0, 2.0],      # behind, its ray passes over (2.0 m > 1.5 m)
                    [3.0, 0.0, 0.5],       # in front of the screen
                    [10.0, 6.0, 0.5],      # behind, but its ray passes beside the screen
                    [10.0, 0.0, -8.0]])    # its ray meets the screen below the ground
    out = occlude(_frame(pts), [WALL], SENSOR)
    p = out.points
    np.testing.assert_allclose(p[0, :3], [5.0, 0.0, 1.0], atol=1e-5)   # 2 + 0.5 * (0 - 2)
    assert p[0, 3] == pytest.approx(0.1)                                # the screen's intensity
    np.testing.assert_array_equal(p[1:], _frame(pts).points[1:])
    assert len(p) == len(pts)                                           # nothing added or lost


def test_a_low_screen_hides_a_cars_lower_half_and_shows_its_roof():
    rng = np.random.default_rng(0)
    car = np.c_[rng.uniform(18, 22, 400), rng.uniform(-1, 1, 400), rng.uniform(0.2, 1.6, 400)]
    box = np.array([[20.0, 0.0, 0.9, 4.0, 2.0, 1.8, 0.0]])
    gt = Detections(box, np.zeros((1, 2)), np.ones(1), np.zeros(1, np.int64))
    f = _frame(car, gt=gt)
    low = Screen((10.0, -3.0), (10.0, 3.0), 0.0, 1.2, 0.1)
    out = occlude(f, [low], SENSOR)
    kept = out.points[:, 0] > 17.0
    # a ray from 2 m up reaching the car at height z crosses x = 10 at 2 + (z - 2) * 10 / x
    crossing = 2.0 + (car[:, 2] - 2.0) * 10.0 / car[:, 0]
    np.testing.assert_array_equal(kept, crossing > 1.2)
    assert 0 < kept.sum() < len(car)
    assert out.num_points is not None and f.num_points is not None
    assert out.num_points[0] == f.num_points[0] - (~kept).sum()
    assert out.gt is f.gt


def test_screens_stay_in_the_world_while_the_ego_moves_and_turns():
    world = np.array([[12.0, 0.5, 0.5], [14.0, -0.5, 0.3]])        # behind the screen
    screen = Screen((8.0, -2.0), (8.0, 2.0), 0.0, 2.5, 0.2)          # odometry frame
    for x_ego, yaw in ((0.0, 0.0), (2.0, 0.1), (4.0, -0.15)):
        pose = pose_from_xyz_rpy((x_ego, 0.3, 0.0), (0, 0, yaw))
        local = (world - pose[:3, 3]) @ pose[:3, :3]                # odometry -> ego frame
        f = replace(_frame(local), pose=pose)
        before = f.points.copy()
        out = occlude(f, [screen], (0.0, 0.0, 2.0))
        np.testing.assert_array_equal(f.points, before)              # the input is kept
        back = out.points[:, :3].astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
        np.testing.assert_allclose(back[:, 0], 8.0, atol=1e-4)      # on the screen
    # once the ego has passed the screen, the returns are seen again
    out = occlude(_frame(world - [9.0, 0, 0], 9.0), [screen], SENSOR)
    np.testing.assert_allclose(out.points[:, :3], world - [9.0, 0, 0], atol=1e-6)


def test_a_box_loses_the_returns_moved_off_it_and_gains_none_from_a_screen():
    rng = np.random.default_rng(2)
    far = np.c_[rng.uniform(19, 21, 300), rng.uniform(-0.8, 0.8, 300), rng.uniform(0.2, 1.4, 300)]
    near = np.c_[rng.uniform(8.5, 9.9, 50), rng.uniform(-0.3, 0.3, 50), rng.uniform(0.2, 1.0, 50)]
    boxes = np.array([[20.0, 0.0, 0.8, 2.0, 1.6, 1.6, 0.0],     # hidden by the screen
                      [10.0, 0.0, 0.8, 4.0, 4.0, 1.6, 0.0]])    # the screen stands in it,
    # its returns in front of the screen; the far box's land on the screen inside it
    gt = Detections(boxes, np.zeros((2, 2)), np.ones(2), np.zeros(2, np.int64))
    f = _frame(np.r_[far, near], gt=gt)
    assert f.num_points is not None and list(f.num_points) == [300, 50]
    out = occlude(f, [Screen((10.0, -3.0), (10.0, 3.0), 0.0, 3.0, 0.1)], SENSOR)
    assert out.num_points is not None and list(out.num_points) == [0, 50]


def test_drawn_screens_stand_between_the_sensor_and_part_of_their_object():
    boxes = np.array([[20.0, 5.0, 0.9, 4.5, 1.9, 1.6, 0.3],
                      [-15.0, -10.0, 0.9, 0.6, 0.6, 1.8, 0.0],
                      [2.0, 1.0, 0.9, 4.5, 1.9, 1.6, 0.0]])             # the last one too near
    for k, target in enumerate(boxes):
        gt = Detections(target[None], np.zeros((1, 2)), np.ones(1), np.zeros(1, np.int64))
        f = _frame(np.zeros((0, 3)), 0.0, gt)
        c, s = np.cos(target[6]), np.sin(target[6])
        grid = np.array([[target[0] + x * c - y * s, target[1] + x * s + y * c, 0.3]
                         for x in np.linspace(-0.5, 0.5, 41) * target[3]
                         for y in np.linspace(-0.5, 0.5, 41) * target[4]])
        for seed in range(20):
            screens = draw_screens(f, np.random.default_rng(seed), SENSOR, extra=0)
            assert len(screens) == (0 if k == 2 else 1)
            for sc in screens:
                assert 0.8 <= sc.height <= 3.0 and 0.02 <= sc.intensity <= 0.3
                # as tall as the sky, it hides some but not all rays to its object
                tall = replace(sc, height=100.0, ground=-50.0)
                moved = np.abs(occlude(_frame(grid), [tall], SENSOR).points[:, :3] - grid
                               ).sum(1) > 1e-6
                assert 0 < moved.mean() < 1
    # no screen passes through an object: a row of parked cars in front of the target
    row = np.array([[20.0, 5.0, 0.9, 4.5, 1.9, 1.6, 0.3]] +
                   [[x, 2.5, 0.9, 4.5, 1.9, 1.6, 0.0] for x in (6.0, 11.0, 16.0)])
    gt_row = Detections(row, np.zeros((4, 2)), np.ones(4), np.zeros(4, np.int64))
    f_row = _frame(np.zeros((0, 3)), 0.0, gt_row)
    for seed in range(20):
        for sc in draw_screens(f_row, np.random.default_rng(seed), SENSOR):
            seg = np.linspace(sc.a, sc.b, 200)
            for b in row:
                c, s = np.cos(b[6]), np.sin(b[6])
                d = seg - b[:2]
                inside = (np.abs(d @ [c, s]) <= b[3] / 2) & (np.abs(d @ [-s, c]) <= b[4] / 2)
                assert not inside.any()
            assert np.hypot(*np.linspace(sc.a, sc.b, 50).T).min() >= 2.0 - 1e-6
    gt = Detections(boxes, np.zeros((3, 2)), np.ones(3), np.array([0, 2, 0]))
    f = _frame(np.zeros((0, 3)), 0.0, gt)
    a = draw_screens(f, np.random.default_rng(3), SENSOR)
    assert a == draw_screens(f, np.random.default_rng(3), SENSOR)     # fixed per seed
    assert 2 <= len(a) <= 3                      # one or two of the objects, and one extra


def test_clips_and_drives_keep_their_labels_and_are_fixed_per_seed():
    rng = np.random.default_rng(1)
    pts = np.c_[rng.uniform(-30, 30, (5000, 2)), rng.uniform(-1.9, -1.7, 5000)]
    boxes = np.array([[15.0, 3.0, -1.0, 4.5, 1.9, 1.6, 0.0],
                      [-20.0, -4.0, -1.0, 4.5, 1.9, 1.6, 0.0]])
    gt = Detections(boxes, np.zeros((2, 2)), np.ones(2), np.zeros(2, np.int64))
    drive = [_frame(pts - [t, 0, 0], float(t), gt) for t in range(4)]
    a, b = occluded_drives([drive], window=2), occluded_drives([drive], window=2)
    assert len(a[0]) == 4
    assert all(np.array_equal(x.points, y.points) for x, y in zip(a[0], b[0]))
    assert all(x.gt is f.gt for x, f in zip(a[0], drive))
    assert any(not np.array_equal(x.points, f.points) for x, f in zip(a[0], drive))
    clip = with_screens(drive[:2], np.random.default_rng(5))
    assert [len(c.points) for c in clip] == [len(f.points) for f in drive[:2]]


def _refused(tmp_path: Path, text: str, message: str) -> None:
    """A training config with ``text`` is refused with ``message``."""
    from suit_ros.train import load_train_config
    path = tmp_path / 'refused.yaml'
    path.write_text(text)
    with pytest.raises(ConfigError, match=message):
        load_train_config(path)


def test_the_training_option_is_validated_and_draws_nothing_when_off(tmp_path: Path,
                                                                    monkeypatch):
    from suit_ros.train import TrainConfig, _occluded
    _refused(tmp_path, 'occluder_probability: 1.5\n', 'occluder_probability must be in')
    _refused(tmp_path, 'occluder_probability: 0.5\ncarry_gt: true\n', 'cannot be combined')
    _refused(tmp_path, 'occluder_probability: 0.5\naugment: false\n', 'augment: false')
    clip = [_frame(np.array([[10.0, 0.0, 0.5]]))]
    rng = np.random.default_rng(0)
    assert _occluded(clip, TrainConfig(), rng) is clip
    assert rng.random() == np.random.default_rng(0).random()     # no draw at 0
    # on: an object the screens hide entirely loses its label
    box = np.array([[20.0, 0.0, 0.9, 4.0, 2.0, 1.8, 0.0]])
    gt = Detections(box, np.zeros((1, 2)), np.ones(1), np.zeros(1, np.int64))
    f = _frame(np.array([[20.0, 0.0, 0.5], [19.0, 0.5, 1.0]]), gt=gt)
    hidden = [occlude(f, [Screen((10.0, -5.0), (10.0, 5.0), -5.0, 10.0, 0.1)])]
    assert hidden[0].num_points is not None and hidden[0].num_points[0] == 0
    # the training path: screens cast, and the object they hide entirely unlabelled
    import suit_ros.data.occluders as occluders
    wall = Screen((10.0, -5.0), (10.0, 5.0), -5.0, 10.0, 0.1)
    monkeypatch.setattr(occluders, 'draw_screens', lambda *args, **kwargs: [wall])
    out = _occluded([f, f], TrainConfig(occluder_probability=1.0), np.random.default_rng(0))
    assert [len(o.gt) for o in out] == [0, 0]
    assert np.allclose(out[0].points[:, 0], 10.0, atol=1e-4)


# ------------------------------------------------------------------ passing occluders
def _passing_drive(frames: int = 10) -> list[Frame]:
    """Sensor frames (the sensor at the origin, 1.8 m above the road) of a car 20 m ahead,
    id 7, one 20 m to the left, id 8, and a pedestrian 3 m in front of the left car, id 9:
    each surface's returns are its own (``owners``), the road's none."""
    rng = np.random.default_rng(4)
    road = np.c_[rng.uniform(-40, 40, (6000, 2)), np.full(6000, -1.8)]
    car_a = np.c_[rng.uniform(18.0, 22.0, 300), rng.uniform(-0.9, 0.9, 300),
                  rng.uniform(-1.6, -0.3, 300)]
    car_b = np.c_[rng.uniform(-0.9, 0.9, 300), rng.uniform(18.0, 22.0, 300),
                  rng.uniform(-1.6, -0.3, 300)]
    ped = np.c_[rng.uniform(-0.25, 0.25, 60), rng.uniform(16.7, 17.2, 60),
                rng.uniform(-1.7, -0.1, 60)]
    pts = np.concatenate([road, car_a, car_b, ped])
    pts = np.c_[pts, np.full(len(pts), 0.5), np.zeros(len(pts))].astype(np.float32)
    owners = np.concatenate([np.zeros(6000), np.full(300, 7), np.full(300, 8),
                             np.full(60, 9)]).astype(np.uint32)
    boxes = np.array([[20.0, 0.0, -0.9, 4.0, 1.8, 1.5, 0.0],
                      [0.0, 20.0, -0.9, 4.0, 1.8, 1.5, np.pi / 2],
                      [0.0, 17.0, -0.9, 0.6, 0.6, 1.8, 0.0]])
    gt = Detections(boxes, np.zeros((3, 2)), np.ones(3), np.array([0, 0, 2]))
    ids = np.array([7, 8, 9], np.uint32)
    from suit_ros.structures import object_returns
    num = object_returns(pts[:, :3], boxes, owners, ids)
    return [Frame(pts, np.eye(4), k * 10**8, 'lidar', gt, num, ids, owners=owners)
            for k in range(frames)]


def test_a_passing_screen_stands_before_its_object_and_covers_it_as_it_slides():
    from suit_ros.data.occluders import Passing, _passing_segment
    box = np.array([20.0, 5.0, -0.9, 4.0, 1.8, 1.5, 0.3])
    for direction in (1, -1):
        p = Passing(7, 2, 5, 0.5, 3.5, 2.0, direction, 0.1)
        ends = [_passing_segment(box, p, q) for q in (0.0, 0.5, 1.0)]
        assert all(e is not None for e in ends)
        bearing = np.arctan2(box[1], box[0])
        c, s = np.cos(box[6]), np.sin(box[6])
        corners = box[:2] + np.array([[2, 0.9], [2, -0.9], [-2, -0.9], [-2, 0.9]]) \
            @ np.array([[c, s], [-s, c]])
        span = np.arctan2(corners[:, 1], corners[:, 0]) - bearing
        for e in ends:
            assert e is not None
            ang = np.sort(np.arctan2(e[:, 1], e[:, 0]) - bearing)
            assert ang[0] < span.min() and ang[1] > span.max()        # the whole box hidden
            depth = e @ np.array([np.cos(bearing), np.sin(bearing)])
            assert np.allclose(depth, depth[0]) and 3.5 <= depth[0] < np.hypot(*corners.T).min()
        mid = [np.arctan2(e[:, 1], e[:, 0]).mean() for e in ends if e is not None]
        assert np.sign(mid[2] - mid[0]) == direction                  # it moves across
    near = np.array([3.0, 0.0, -0.9, 4.0, 1.8, 1.5, 0.0])
    assert _passing_segment(near, Passing(7, 2, 5, 0.5, 3.5, 2.0, 1, 0.1), 0.0) is None
    # never nearer than 3.5 m: the ego's bonnet ends about 2.8 m ahead of the sensor
    ahead = np.array([8.0, 0.0, -0.9, 4.0, 1.8, 1.5, 0.0])
    seg = _passing_segment(ahead, Passing(7, 2, 5, 0.3, 3.5, 2.0, 1, 0.1), 0.0)
    assert seg is not None and seg[:, 0].min() == pytest.approx(3.5)


def test_a_passing_screen_grows_to_hide_a_tall_truck_uphill(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A 3.6 m truck 25 m ahead on a 0.5 m rise, seen from 1.8 m up: a 3.2 m screen at 70% of
    its distance would show its top rows; the screen is raised until it hides them all."""
    import suit_ros.data.occluders as occ
    rng = np.random.default_rng(5)
    road = np.c_[rng.uniform(-40, 40, (4000, 2)), np.full(4000, -1.8)]
    truck = np.c_[rng.uniform(22.0, 28.0, 500), rng.uniform(-1.2, 1.2, 500),
                  rng.uniform(-1.3, 2.3, 500)]
    pts = np.concatenate([road, truck])
    pts = np.c_[pts, np.full(len(pts), 0.5), np.zeros(len(pts))].astype(np.float32)
    owners = np.r_[np.zeros(4000), np.full(500, 3)].astype(np.uint32)
    box = np.array([[25.0, 0.0, 0.5, 6.0, 2.4, 3.6, 0.0]])
    gt = Detections(box, np.zeros((1, 2)), np.ones(1), np.array([1]))
    ids = np.array([3], np.uint32)
    frames = [Frame(pts, np.eye(4), k * 10**8, 'lidar', gt, np.array([500], np.uint32), ids,
                    owners=owners) for k in range(6)]
    low = occ.Passing(3, 2, 3, 0.7, 3.2, 1.0, 1, 0.1)
    monkeypatch.setattr(occ, 'draw_passing', lambda clip, rng: [low])
    out = occ.with_passing(frames, np.random.default_rng(0))
    assert [int(f.num_points[0]) for f in out] == [500, 500, 0, 0, 0, 500]


def test_a_passing_occluder_hides_its_object_for_its_frames_then_shows_it_again(
        monkeypatch: pytest.MonkeyPatch) -> None:
    import suit_ros.data.occluders as occ
    from suit_ros.outage import occlusion_events
    drive = _passing_drive()
    hidden = occ.Passing(7, 2, 4, 0.5, 3.5, 2.0, 1, 0.1)
    through_ped = occ.Passing(8, 2, 4, 0.95, 3.5, 2.0, 1, 0.1)   # its screen would cross id 9
    monkeypatch.setattr(occ, 'draw_passing', lambda clip, rng: [hidden, through_ped])
    out = occ.with_passing(drive, np.random.default_rng(0))
    monkeypatch.undo()
    counts = np.array([f.num_points for f in out])
    assert (counts[2:6, 0] == 0).all() and counts[1, 0] == 300 and counts[6, 0] == 300
    assert (counts[:, 1] == 300).all()          # left out: it would pass through the pedestrian
    assert (counts[:, 2] == 60).all()
    assert [len(f.points) for f in out] == [len(f.points) for f in drive]
    events = occlusion_events(out)
    assert [int(e[0]) for e in events] == [0, 0, 1, 2, 3, 4, 0, 0, 0, 0]
    # drawn: the well-seen objects hidden for 3-7 frames, fixed per seed
    a, b = occ.passing_drives([drive]), occ.passing_drives([drive])
    assert all(np.array_equal(x.points, y.points) for x, y in zip(a[0], b[0]))
    ev = np.array(occlusion_events(a[0]))
    assert ev.max() >= 3 and all(x.gt is f.gt for x, f in zip(a[0], drive))
    assert occ.passing_drives([drive[:5]])[0][0] is drive[0]       # too short a clip: none drawn


def test_training_clips_with_passing_occluders_keep_the_hidden_objects_labels():
    from suit_ros.data.sequences import ClipSampler
    drive = _passing_drive(12)
    sampler = ClipSampler([drive], [6], seed=3, sweeps=1, passing_probability=1.0)
    hidden_frames = 0
    for _ in range(6):
        clips, lost = sampler.batch_with_outages(1)
        clip, active = clips[0], lost[0]
        assert len(clip) == 6 and not active[0] and sum(active) >= 3
        for f, on in zip(clip, active):
            assert f.gt is not None and f.num_points is not None
            if on:                # a hidden target: labelled, with no returns
                hidden_frames += 1
                assert (f.num_points == 0).any()
            else:
                assert (f.num_points > 0).all()
            # what the screen hides besides its target is still there too: labelled
            assert len(f.gt) == 3
    assert hidden_frames >= 18
    # off: no draw, so a recipe with outages replays the same clips as before the option
    a = ClipSampler([drive], [6], seed=3, sweeps=1, outage_probability=0.5)
    b = ClipSampler([drive], [6], seed=3, sweeps=1, outage_probability=0.5,
                    passing_probability=0.0)
    for _ in range(4):
        (ca, la), (cb, lb) = a.batch_with_outages(2), b.batch_with_outages(2)
        assert la == lb and all(np.array_equal(x.points, y.points)
                                for p, q in zip(ca, cb) for x, y in zip(p, q))
    with pytest.raises(ValueError, match='passing_probability'):
        ClipSampler([drive], [6], seed=3, passing_probability=1.5)
    with pytest.raises(ValueError, match='5 frames'):
        ClipSampler([drive], [2, 3, 4], seed=3, passing_probability=0.5)


def test_the_passing_training_option_is_validated(tmp_path: Path) -> None:
    from suit_ros.train import load_train_config
    # the default clips of 2-4 frames hold no 3-7 hidden frames after a seen one
    _refused(tmp_path, 'passing_probability: 0.5\n', '5 frames or more')
    _refused(tmp_path, 'passing_probability: -0.1\nclip_lengths: [8]\n',
             'passing_probability must be in')
    ok = tmp_path / 'ok.yaml'
    ok.write_text('passing_probability: 0.5\nclip_lengths: [8]\ncarry_gt: true\n')
    assert load_train_config(ok).passing_probability == 0.5
