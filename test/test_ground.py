"""The local ground under the model input (suit_ros/ground.py, ``ground: local``)."""
from __future__ import annotations

import numpy as np
import pytest

from suit_ros.ground import LocalGround

RANGE = (-51.2, -51.2, -2.0, 51.2, 51.2, 4.5)


def road(rng: np.random.Generator, height, n: int = 60000, reach: float = 50.0) -> np.ndarray:
    """``(n, 5)`` returns of a road whose height at (x, y) is ``height(x, y)``, denser near
    the sensor as a LiDAR's are."""
    r = reach * np.sqrt(rng.random(n)) + 2.0
    a = rng.uniform(-np.pi, np.pi, n)
    x, y = r * np.cos(a), r * np.sin(a)
    z = height(x, y) + rng.normal(0, 0.02, n)
    return np.c_[x, y, z, np.full(n, 0.3), np.zeros(n)].astype(np.float32)


def block(rng, centre, size, z0, z1, n=800) -> np.ndarray:
    """Returns spread through a box (an object or a roof)."""
    lo = np.array([centre[0] - size[0] / 2, centre[1] - size[1] / 2, z0])
    hi = np.array([centre[0] + size[0] / 2, centre[1] + size[1] / 2, z1])
    p = rng.uniform(lo, hi, (n, 3))
    return np.c_[p, np.full(n, 0.5), np.zeros(n)].astype(np.float32)


def test_a_lowered_road_with_objects_on_it_is_leveled_to_zero():
    rng = np.random.default_rng(0)
    ground = road(rng, lambda x, y: np.full_like(x, -0.45))
    car = block(rng, (12.0, 3.0), (4.5, 1.9), -0.45 + 0.3, -0.45 + 1.6)
    wall = block(rng, (-20.0, 15.0), (0.3, 12.0), -0.45, -0.45 + 4.0, n=3000)
    est = LocalGround(RANGE)
    out = est.level(np.concatenate([ground, car, wall]))
    near = np.hypot(ground[:, 0], ground[:, 1]) < 45
    assert abs(np.median(out[: len(ground)][near, 2])) < 0.05
    assert np.abs(est.grid[est.grid != 0] + 0.45).max() < 0.1     # every cell that saw road
    lifted = out[len(ground): len(ground) + len(car), 2]
    assert 0.25 < lifted.min() and lifted.max() < 1.65            # the car keeps its shape
    np.testing.assert_array_equal(out[:, [0, 1, 3, 4]],
                                  np.concatenate([ground, car, wall])[:, [0, 1, 3, 4]])
    assert est.under(np.array([[12.0, 3.0]]))[0] == pytest.approx(-0.45, abs=0.06)


def test_a_slope_and_a_crown_follow_the_road():
    rng = np.random.default_rng(1)
    height = lambda x, y: 0.04 * x - 0.02 * np.abs(y)              # noqa: E731 (4% climb, crown)
    ground = road(rng, height)
    out = LocalGround(RANGE, hold=np.inf).level(ground)
    near = np.hypot(ground[:, 0], ground[:, 1]) < 40
    residual = out[near, 2]
    raw = ground[near, 2]
    assert np.abs(np.median(residual)) < 0.05 and np.percentile(np.abs(residual), 95) < 0.15
    assert np.percentile(np.abs(raw), 95) > 1.0                   # what the model got before
    # with the default hold (30 m) the slope is followed within it; beyond it the climb is
    # capped at the ground nearer on the bearing + rise, and the fall is followed
    est = LocalGround(RANGE)
    out = est.level(ground)
    r = np.hypot(ground[:, 0], ground[:, 1])
    read = est.hold - np.sqrt(2) * est.cell                       # where the far cells read
    assert np.percentile(np.abs(out[r < read, 2]), 95) < 0.15
    ahead, behind = est.under(np.array([[45.0, 0.0], [-45.0, 0.0]]))
    assert ahead == pytest.approx(height(read, 0.0) + est.rise, abs=0.1)   # not 1.8
    assert behind == pytest.approx(height(-45.0, 0.0), abs=0.1)           # -1.8, followed


def test_beyond_the_last_ring_the_bottoms_of_objects_are_not_taken_for_the_road():
    """A sparse LiDAR's last road ring at 30 m: beyond it a cell holds only the returns of
    the objects in it (a car's side from 0.3 m up), whose lowest returns a cell's own
    estimate takes for the road; with the far cells' rise capped, the car's cell stays within
    ``rise`` of the road nearer on its bearing."""
    rng = np.random.default_rng(3)
    ground = road(rng, lambda x, y: np.full_like(x, -0.2), reach=28.0)
    cars = [block(rng, (x, y), (4.5, 1.9), -0.2 + 0.3, -0.2 + 1.5, n=1000)
            for x, y in ((44.0, 3.0), (-41.0, -20.0), (10.0, 46.0))]
    pts = np.concatenate([ground, *cars])
    held = LocalGround(RANGE)
    held.fit(pts)
    own = LocalGround(RANGE, hold=np.inf)
    own.fit(pts)
    at = np.array([[44.0, 3.0], [-41.0, -20.0], [10.0, 46.0]])
    assert np.all(own.under(at) > 0.05)                          # what the cells alone say
    assert np.all(held.under(at) < -0.2 + held.rise + 0.06)        # at most the cap above
    assert np.all(held.under(at) > -0.2 - 0.06)
    assert held.under(np.array([[5.0, 5.0]]))[0] == pytest.approx(-0.2, abs=0.06)


def test_a_roof_hiding_the_road_takes_its_neighbours_ground():
    rng = np.random.default_rng(2)
    ground = road(rng, lambda x, y: np.zeros_like(x))
    # a bus shelter roof over a whole cell, the road under it hidden
    cell = LocalGround(RANGE).cell
    cx, cy = 20.0 + cell / 2, 8.0 + cell / 2
    hidden = (np.abs(ground[:, 0] - cx) < cell) & (np.abs(ground[:, 1] - cy) < cell)
    roof = block(rng, (cx, cy), (2 * cell, 2 * cell), 0.9, 1.2, n=4000)
    est = LocalGround(RANGE)
    est.fit(np.concatenate([ground[~hidden], roof]))
    assert abs(est.under(np.array([[cx, cy]]))[0]) < 0.1


def test_empty_sparse_and_non_finite_input():
    est = LocalGround(RANGE)
    assert est.level(np.zeros((0, 5), np.float32)).shape == (0, 5)
    assert not est.grid.any()                                     # nothing seen: z = 0
    few = np.array([[5.0, 5.0, -0.7, 0.1, 0.0]] * 5, np.float32)
    np.testing.assert_array_equal(est.level(few), few)             # too few returns: as given
    bad = np.array([[np.nan, 1.0, 0.0, 0.1, 0.0], [np.inf, 0.0, 0.0, 0.1, 0.0],
                    [1.0, 1.0, np.nan, 0.1, 0.0]], np.float32)
    out = est.level(bad)
    assert out.shape == bad.shape and np.isnan(out[2, 2])
    with pytest.raises(ValueError, match='cell > 0'):
        LocalGround(RANGE, cell=0.0)
    with pytest.raises(ValueError, match='hold > 1.42 x cell'):
        LocalGround(RANGE, hold=5.0)                               # read behind the sensor
    with pytest.raises(ValueError, match='rise >= 0'):
        LocalGround(RANGE, rise=-0.1)


@pytest.mark.slow
def test_a_detector_fed_a_lifted_cloud_finds_the_boxes_of_the_true_one(tmp_path):
    """A LiDAR extrinsic 0.5 m too high lifts the whole input: with ``ground: local`` the
    shipped model finds the boxes it finds in the true cloud, raised by the same 0.5 m."""
    from suit_ros.checkpoint import default_checkpoint_path, load_checkpoint
    from suit_ros.data.sequences import synthetic_sequence
    from suit_ros.evaluate import step_inputs
    from suit_ros.model.streaming import StreamingDetector
    model, _, _ = load_checkpoint(str(default_checkpoint_path()), 'cpu')
    seq = synthetic_sequence('test', 5, 6, tmp_path)

    def boxes(ground, lift):
        runner = StreamingDetector(model, ground=ground)
        for f in seq:
            points, *rest = step_inputs(f)
            points = points.copy()
            points[:, 2] += lift
            out = runner.step(points, *rest).detections
        return out.boxes[out.scores >= 0.3]

    true = boxes('as_given', 0.0)
    lifted = boxes('local', 0.5)
    assert len(true) >= 3
    d = np.hypot(*(true[:, None, :2] - lifted[None, :, :2]).transpose(2, 0, 1))
    found = d.min(axis=1) < 0.5
    assert found.mean() >= 0.8
    dz = lifted[d.argmin(axis=1)[found], 2] - true[found, 2]
    assert np.median(dz) == pytest.approx(0.5, abs=0.1)
    with pytest.raises(ValueError, match='ground must be one of'):
        StreamingDetector(model, ground='flat')                   # type: ignore[arg-type]


def test_a_training_frame_is_leveled_with_its_gt_as_the_node_shows_it():
    """``ground: local`` in training (``leveled_frame``): the points as ``level`` makes them and
    each GT box lowered by the ground under its centre, so that decoding on leveled input and
    putting the box back (the node) gives the true box."""
    from suit_ros.ground import leveled_frame
    from suit_ros.structures import Detections, Frame
    rng = np.random.default_rng(5)
    slope = lambda x, y: 0.03 * x - 0.4                            # noqa: E731
    car = block(rng, (15.0, -3.0), (4.5, 1.9), slope(15.0, 0) + 0.3, slope(15.0, 0) + 1.6)
    pts = np.concatenate([road(rng, slope), car])
    box = np.array([[15.0, -3.0, slope(15.0, 0) + 0.8, 4.5, 1.9, 1.6, 0.2]], np.float32)
    gt = Detections(box, np.array([[3.0, 0.0]]), np.ones(1), np.zeros(1, np.int64))
    f = Frame(pts, np.eye(4), 7, 'base_link', gt, instance_ids=np.ones(1, np.uint32))
    est = LocalGround(RANGE)
    out = leveled_frame(f, est)
    np.testing.assert_array_equal(out.points, LocalGround(RANGE).level(pts))
    assert out.gt is not None and out.gt.boxes[0, 2] == pytest.approx(0.8, abs=0.08)
    back = out.gt.boxes[0, 2] + est.under(out.gt.boxes[:, :2])[0]  # what the node does
    assert back == pytest.approx(box[0, 2], abs=1e-5)
    np.testing.assert_array_equal(out.gt.boxes[:, [0, 1, 3, 4, 5, 6]], box[:, [0, 1, 3, 4, 5, 6]])
    np.testing.assert_array_equal(out.gt.velocities, gt.velocities)
    assert f.points is pts and f.gt.boxes[0, 2] == box[0, 2]       # the input is not changed
    empty = Frame(pts[:0], np.eye(4), 8, 'base_link', Detections.empty())
    assert len(leveled_frame(empty, est).points) == 0


def test_a_model_trained_on_leveled_input_runs_leveled_unless_told_otherwise():
    """The checkpoint records its input convention (``pillars.ground``, written by training
    with ``ground: local``); the streaming detector and the node's ``ground: checkpoint``
    follow it, and an explicit choice wins."""
    import torch

    from suit_ros.config import ModelConfig, model_config_from_dict
    from suit_ros.errors import ConfigError
    from suit_ros.model.detector import SUITDetector
    from suit_ros.model.streaming import StreamingDetector
    from suit_ros.params import DetectorParams
    torch.manual_seed(0)
    cfg = model_config_from_dict({'temporal': 'none', 'pillars': {'ground': 'local'}}, 'test')
    det = StreamingDetector(SUITDetector(cfg).eval(), 'cpu')
    assert det.ground == 'local'
    det.set_ground('as_given')
    assert det.ground == 'as_given'
    det.set_ground(None)
    assert det.ground == 'local'
    assert StreamingDetector(SUITDetector(cfg).eval(), 'cpu', ground='as_given').ground \
        == 'as_given'
    plain = StreamingDetector(SUITDetector(ModelConfig(temporal='none')).eval(), 'cpu')
    assert plain.ground == 'as_given'
    assert DetectorParams().ground == 'checkpoint' and DetectorParams().ground_mode() is None
    assert DetectorParams(ground='local').ground_mode() == 'local'
    with pytest.raises(ConfigError, match='ground'):
        model_config_from_dict({'pillars': {'ground': 'flat'}}, 'test')
