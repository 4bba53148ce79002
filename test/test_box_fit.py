"""Car boxes moved onto the returns of their visible faces (suit_ros/box_fit.py), on returns
drawn the way a LiDAR sees a box: the faces that face the sensor, ring by ring."""
from __future__ import annotations

import numpy as np
import pytest

from suit_ros.box_fit import FaceFit, fit_to_faces, object_extent

CLASSES = ('car', 'truck', 'pedestrian', 'cyclist')


def seen_faces(box, sensor=(0.0, 0.0), step=0.05, heights=(0.5, 0.8, 1.1, 1.4), roof=True):
    """Returns on the faces of ``box`` (x, y, z centre, l, w, h, yaw; bottom at z - h/2) that
    the sensor at ``sensor`` sees (a face is seen when the sensor lies beyond it), and on its
    roof (a sensor 1.8 m up sees a car's roof)."""
    cx, cy, cz, length, width, height, yaw = box
    c, s = np.cos(yaw), np.sin(yaw)
    ex, ey = sensor[0] - cx, sensor[1] - cy
    su, sv = ex * c + ey * s, -ex * s + ey * c
    local = []
    for along, half, other in ((True, length / 2, width / 2), (False, width / 2, length / 2)):
        side = su if along else sv
        if abs(side) <= half:
            continue
        t = np.arange(-other, other + 1e-9, step)
        u = np.full_like(t, np.sign(side) * half)
        local.append(np.stack([u, t], 1) if along else np.stack([t, u], 1))
    uv = np.concatenate(local)
    pts = []
    for h in heights:
        x = cx + uv[:, 0] * c - uv[:, 1] * s
        y = cy + uv[:, 0] * s + uv[:, 1] * c
        pts.append(np.stack([x, y, np.full_like(x, cz - height / 2 + h)], 1))
    if roof:
        u, v = np.meshgrid(np.linspace(-length / 2, length / 2, 23),
                           np.linspace(-width / 2, width / 2, 10))
        u, v = u.ravel(), v.ravel()
        pts.append(np.stack([cx + u * c - v * s, cy + u * s + v * c,
                             np.full_like(u, cz + height / 2 - 0.05)], 1))
    return np.concatenate(pts).astype(np.float32)


def moved(box, along, across):
    """``box`` moved in its own frame."""
    b = np.array(box, np.float64)
    c, s = np.cos(b[6]), np.sin(b[6])
    b[0] += along * c - across * s
    b[1] += along * s + across * c
    return b


def fit(boxes, points, labels=None, scores=None, sensor=(0.0, 0.0), cfg=None):
    boxes = np.atleast_2d(np.asarray(boxes, np.float32))
    labels = np.zeros(len(boxes), np.int64) if labels is None else np.asarray(labels)
    scores = np.full(len(boxes), 0.9, np.float32) if scores is None else np.asarray(scores)
    return fit_to_faces(boxes, labels, scores, points, np.asarray(sensor), CLASSES,
                        cfg or FaceFit())


TRUE = np.array([15.0, 0.0, 0.8, 4.4, 1.9, 1.6, 0.0])           # straight ahead
OBLIQUE = np.array([12.0, 7.0, 0.8, 4.4, 1.9, 1.6, 0.3])         # ahead and to the left


def test_a_box_placed_too_far_is_brought_back_onto_its_near_face():
    pts = seen_faces(TRUE)
    out = fit(moved(TRUE, 0.6, 0.0), pts)[0]
    assert out[:2] == pytest.approx(TRUE[:2], abs=0.03)
    assert out[2:] == pytest.approx(TRUE[2:].astype(np.float32))       # size, heading kept


def test_seen_at_an_angle_both_faces_place_the_box():
    pts = seen_faces(OBLIQUE)
    assert len(pts) > 200
    out = fit(moved(OBLIQUE, 0.7, 0.3), pts)[0]      # away from the sensor on both axes
    assert np.hypot(*(out[:2] - OBLIQUE[:2])) < 0.05


def test_a_box_is_never_pushed_away_by_returns_it_lacks():
    """Too close, or a near end whose returns are missing: the box stays."""
    pts = seen_faces(TRUE)
    near = moved(TRUE, -0.5, 0.0)
    assert fit(near, pts)[0][:2] == pytest.approx(near[:2], abs=1e-5)
    ahead = seen_faces(OBLIQUE)
    # only the side is seen: the rear's returns are lost (dark paint)
    c, s = np.cos(OBLIQUE[6]), np.sin(OBLIQUE[6])
    u = (ahead[:, 0] - OBLIQUE[0]) * c + (ahead[:, 1] - OBLIQUE[1]) * s
    side_only = ahead[u > -OBLIQUE[3] / 2 + 0.3]
    assert fit(OBLIQUE, side_only)[0][:2] == pytest.approx(OBLIQUE[:2], abs=1e-5)


def test_sensor_beside_the_car_centres_it_on_its_side():
    beside = np.array([0.5, 6.0, 0.8, 4.4, 1.9, 1.6, 0.0])
    pts = seen_faces(beside)
    out = fit(moved(beside, 0.5, 0.0), pts)[0]
    assert out[:2] == pytest.approx(beside[:2], abs=0.05)


def test_a_neighbour_past_a_gap_does_not_pull_the_box():
    """A car parked 1 m nearer the sensor, bumper to bumper: its returns are the car's only
    up to the gap."""
    neighbour = TRUE.copy()
    neighbour[0] -= TRUE[3] + 1.0
    pts = np.concatenate([seen_faces(TRUE), seen_faces(neighbour)])
    out = fit(moved(TRUE, 0.3, 0.0), pts)[0]
    assert out[:2] == pytest.approx(TRUE[:2], abs=0.03)
    bridged = fit(moved(TRUE, 0.3, 0.0), pts, cfg=FaceFit(gap=1.5))[0]  # no gap: pulled
    assert bridged[0] < TRUE[0] - 0.5


def test_a_pole_is_not_a_face():
    """A pole 0.35 m in front of a car whose rear shows nothing (only its roof): the pole's
    returns run on from the car's, but a pole is not a face, so the box stays."""
    z = np.linspace(0.3, 2.0, 20)
    pole = np.stack([np.full_like(z, TRUE[0] - TRUE[3] / 2 - 0.35), np.full_like(z, 0.1), z], 1)
    roof = seen_faces(TRUE, heights=())
    pts = np.concatenate([pole, roof]).astype(np.float32)
    assert fit(TRUE, pts)[0][:2] == pytest.approx(TRUE[:2], abs=1e-5)
    loose = fit(TRUE, pts, cfg=FaceFit(face_spread=0.0))[0]     # without the face check
    assert loose[0] == pytest.approx(TRUE[0] - 0.35, abs=1e-3)


def test_only_confident_cars_move():
    pts = seen_faces(TRUE)
    box = moved(TRUE, 0.6, 0.0)
    boxes = np.stack([box] * 4)
    out = fit(boxes, pts, labels=[0, 1, 2, 0], scores=[0.9, 0.9, 0.9, 0.1])
    assert out[0, :2] == pytest.approx(TRUE[:2], abs=0.03)
    for k in (1, 2, 3):                  # a truck, a pedestrian, a car below min_score
        assert out[k] == pytest.approx(box.astype(np.float32))


def test_a_move_is_bounded():
    pts = seen_faces(TRUE)
    out = fit(moved(TRUE, 3.0, 0.0), pts, cfg=FaceFit(max_shift=1.2))[0]
    assert out[0] - moved(TRUE, 3.0, 0.0)[0] >= -1.2 - 1e-5


def test_nothing_to_fit():
    box = moved(TRUE, 0.6, 0.0)
    assert fit(box, np.zeros((0, 3), np.float32))[0] == pytest.approx(box.astype(np.float32))
    assert fit(np.zeros((0, 7)), seen_faces(TRUE)).shape == (0, 7)
    few = seen_faces(TRUE)[:3]                       # fewer returns than min_points
    assert fit(box, few)[0] == pytest.approx(box.astype(np.float32))


def test_object_extent_runs_on_from_the_inside_values_without_a_gap():
    v = np.array([-5.0, -2.9, -2.6, -2.3, -1.0, 0.0, 1.0, 1.3, 3.0])
    assert object_extent(v, -2.0, 1.0, 0.4) == (-1.0, 1.3)
    assert object_extent(v, -2.0, 1.0, 1.5) == (-2.9, 1.3)
    assert object_extent(v, 4.0, 5.0, 0.4) is None
