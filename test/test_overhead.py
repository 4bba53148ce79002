"""Overhead slabs (canopies, awnings) over the street: placement, returns, fixed in the world."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from suit_ros.data.overhead import add_slabs, draw_slabs, overhead_drives, with_overhead
from suit_ros.ops.geometry import pose_from_xyz_rpy
from suit_ros.structures import Detections, Frame


def _frame(t: int, n: int = 4000) -> Frame:
    rng = np.random.default_rng(t)
    pts = np.c_[rng.uniform(-30, 30, (n, 2)), rng.uniform(-0.05, 0.05, n), rng.uniform(0, 1, n),
                np.zeros(n)].astype(np.float32)
    x = 10.0 - 1.0 * t                                  # parked objects, the ego drives by
    gt = Detections(np.array([[x, 3.0, 0.9, 0.6, 0.6, 1.8, 0.0],       # a pedestrian
                              [x, -6.0, 0.8, 4.5, 1.9, 1.6, 0.0]]),    # a car
                    np.zeros((2, 2)), np.ones(2), np.array([2, 0]))
    return Frame(pts, pose_from_xyz_rpy((t * 1.0, 0.0, 0.0), (0, 0, 0)), int(t * 1e8),
                 'base_link', gt)


def test_slabs_sit_over_the_objects_above_head_height_and_stay_in_the_world():
    clip = [_frame(t) for t in range(3)]
    rng = np.random.default_rng(0)
    slabs = draw_slabs(clip[0], rng, small_probability=1.0, large_probability=0.0, extra=1)
    assert len(slabs) == 3                      # the pedestrian, and two empty places
    ped = slabs[0]
    assert np.hypot(ped.centre[0] - 10.0, ped.centre[1] - 3.0) < 3.0
    assert 2.2 <= ped.base <= 4.0 and abs(ped.ground - 0.0) < 1e-6
    out = with_overhead(clip, np.random.default_rng(1))
    for f, o in zip(clip, out):
        extra = o.points[len(f.points):]
        assert len(extra) > 0 and np.array_equal(o.points[:len(f.points)], f.points)
        assert o.gt is f.gt                     # the objects are still there
        assert extra[:, 2].min() >= 2.2 - 1e-4 and extra[:, 2].max() <= 5.2 + 1e-4
        assert (extra[:, 3] <= 0.25).all() and (extra[:, 4] == 0).all()
    # one slab alone: its returns move with the ego (fixed in the odometry frame)
    one = [add_slabs(f, [ped], np.random.default_rng(2)) for f in clip]
    centres = [o.points[len(f.points):, :2].mean(0) + f.pose[:2, 3] for f, o in zip(clip, one)]
    assert np.ptp(np.array(centres), axis=0).max() < 0.5


def test_no_objects_and_no_ground_give_no_slabs():
    f = _frame(0, n=0)
    f = replace(f, gt=None)
    assert draw_slabs(f, np.random.default_rng(0)) == []
    assert add_slabs(f, [], np.random.default_rng(0)) is f


def test_overhead_drives_are_fixed_per_seed():
    drives = [[_frame(t) for t in range(4)]]
    a, b = overhead_drives(drives, window=2), overhead_drives(drives, window=2)
    assert all(np.array_equal(x.points, y.points) for x, y in zip(a[0], b[0]))
    assert len(a[0][0].points) > len(drives[0][0].points)
