"""Occluders: vertical screens between the sensor and the objects, cast into training clips.

On the real dev sweeps the cars the shipped model misses are mostly seen in part: a 0.5 x 0.9 m
corner at 8 m (186-195 returns) past a parked car, a full-length side below a tall near object
at 23 m, a 1.7 x 2.7 m patch behind 2,900 returns of clutter at 24 m, a 0.3 x 0.6 m roof at
33 m (docs/experiments/occluders). In the synthetic world the occluders are other cars in
their rows and lanes, so the partial views the model learns from are few and alike.

A :class:`Screen` is a vertical rectangle standing on the ground (a van's side, a hedge, a
wall, a trunk), fixed in the odometry frame so it stays put across the frames of a clip while
the ego moves. :func:`occlude` casts it into a frame as the sensor would see it: every return
whose ray from the sensor crosses the screen below its top is moved back along its ray onto the
screen (the beam stops there), taking the screen's intensity; returns whose rays pass over it
keep their place, so a low screen hides a car's lower half and shows its roof. Nothing is
added or removed: the ray pattern stays the sensor's.

:func:`draw_screens` places screens in front of some objects (covering 30-90% of the object's
width as the sensor sees it, from one side, at a random distance between the sensor and the
object) and a few at random places (so that a screen is no cue for an object); none passes
through an object. The labels stay; an object hidden entirely loses its label in training (as
one with no return does).
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from suit_ros.data.drawn import ground_near, windowed_drives
from suit_ros.ops.geometry import (
    count_points_in_boxes,
    in_box_frames,
    se3_inverse,
    transform_points,
)
from suit_ros.structures import Frame, object_returns

# where the sensor is in a model frame's base_link (the frame keeps no extrinsic): the synthetic
# sensor models sit 0.76-0.94 m ahead of the rear axle and 1.60-1.84 m up (data/sim/config.py).
# A model frame's earlier sweeps are cast from here too, where the ego is now (it moved up to
# 2 m since): an approximation that :func:`occluded_drives` (sensor frames) does not make
SENSOR_IN_BASE = (0.85, 0.0, 1.75)


@dataclass(frozen=True)
class Screen:
    """A vertical screen from ``a`` to ``b`` (odometry frame x, y), from ``ground`` (odometry
    frame z) up ``height`` m; its returns have ``intensity`` (0..1)."""

    a: tuple[float, float]
    b: tuple[float, float]
    ground: float
    height: float
    intensity: float


def _footprint(box: NDArray[np.float64], grow: float = 0.0) -> NDArray[np.float64]:
    """The ``(4, 2)`` corners (x, y) of ``box``'s footprint grown by ``grow`` m on every side."""
    c, s = np.cos(box[6]), np.sin(box[6])
    half = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]]) * (0.5 * box[3:5] + grow)
    corners: NDArray[np.float64] = box[:2] + half @ np.array([[c, s], [-s, c]])
    return corners


def _screen_before(box: NDArray[np.float64], sensor: NDArray[np.float64],
                   rng: np.random.Generator) -> NDArray[np.float64] | None:
    """Endpoints ``(2, 2)`` (the frame's x, y) of a screen hiding part of ``box`` from
    ``sensor``, or None when the box is too near."""
    corners = _footprint(box) - sensor[:2]
    centre = box[:2] - sensor[:2]
    theta = float(np.arctan2(centre[1], centre[0]))
    rel = np.angle(np.exp(1j * (np.arctan2(corners[:, 1], corners[:, 0]) - theta)))
    near = float(np.hypot(corners[:, 0], corners[:, 1]).min())
    lo_r, hi_r = max(2.0, 0.2 * near), near - 0.7
    if hi_r - lo_r < 0.5:
        return None
    dist = float(rng.uniform(lo_r, hi_r))
    lo, hi = float(rel.min()), float(rel.max())
    cover = float(rng.uniform(0.3, 0.9)) * (hi - lo)
    beyond = float(rng.uniform(0.3, 3.0)) / dist          # past the object's edge (rad)
    if rng.random() < 0.5:
        window = (lo - beyond, lo + cover)
    else:
        window = (hi - cover, hi + beyond)
    if dist * np.cos(0.5 * (window[1] - window[0])) < 2.0:
        return None                     # a wide screen this near would stand in the ego
    ang = theta + np.asarray(window)
    ends: NDArray[np.float64] = sensor[:2] + dist * np.stack([np.cos(ang), np.sin(ang)], 1)
    return ends


def _crosses(seg: NDArray[np.float64], boxes: NDArray[np.floating[Any]],
             margin: float = 0.2) -> bool:
    """Whether the segment ``(2, 2)`` passes through a box's footprint grown by ``margin``."""
    b = np.asarray(boxes, np.float64).reshape(-1, 7)
    t = np.linspace(0.0, 1.0, 41)[:, None]
    xy = seg[0] + t * (seg[1] - seg[0])                                  # (41, 2)
    along, across, _ = in_box_frames(np.c_[xy, np.zeros(len(xy))], b)
    return bool(((np.abs(along) <= b[:, 3] / 2 + margin)
                 & (np.abs(across) <= b[:, 4] / 2 + margin)).any())


def draw_screens(frame: Frame, rng: np.random.Generator,
                 sensor: tuple[float, float, float] = SENSOR_IN_BASE,
                 targets: int = 3, extra: int = 1, reach_m: float = 40.0) -> list[Screen]:
    """Screens in front of up to ``targets`` of ``frame``'s GT objects 5-``reach_m`` m away
    and ``extra`` at random places 4-30 m away, fixed in the odometry frame (``frame.pose``
    maps the points' frame to it; ``sensor``: the sensor's position in the points' frame)."""
    s = np.asarray(sensor, np.float64)
    pts = np.asarray(frame.points[:, :3], np.float64)
    placed: list[tuple[NDArray[np.float64], float]] = []
    if frame.gt is not None and len(frame.gt):
        boxes = np.asarray(frame.gt.boxes, np.float64)
        dist = np.hypot(boxes[:, 0] - s[0], boxes[:, 1] - s[1])
        candidates = np.flatnonzero((dist > 5.0) & (dist < reach_m))
        for j in rng.permutation(candidates)[:int(rng.integers(1, targets + 1))]:
            found = _screen_before(boxes[j], s, rng)
            if found is not None:
                bottom = float(boxes[j, 2] - boxes[j, 5] / 2)
                mid = found.mean(0)
                ground = ground_near(pts, mid[0], mid[1])
                placed.append((found, bottom if ground is None else ground))
    for _ in range(extra):
        r, a = rng.uniform(4.0, 30.0), rng.uniform(-np.pi, np.pi)
        mid = s[:2] + r * np.array([np.cos(a), np.sin(a)])
        along = np.array([-np.sin(a), np.cos(a)]) * rng.uniform(0.5, 3.0)
        ground = ground_near(pts, mid[0], mid[1])
        placed.append((np.stack([mid - along, mid + along]),
                       s[2] - SENSOR_IN_BASE[2] if ground is None else ground))
    if frame.gt is not None and len(frame.gt):
        placed = [(seg, g) for seg, g in placed if not _crosses(seg, frame.gt.boxes)]
    screens = []
    for seg, ground in placed:
        w = transform_points(frame.pose, np.c_[seg, np.full(2, ground)])
        screens.append(Screen((float(w[0, 0]), float(w[0, 1])), (float(w[1, 0]), float(w[1, 1])),
                              float(w[:, 2].mean()), float(rng.uniform(0.8, 3.0)),
                              float(rng.uniform(0.02, 0.3))))
    return screens


def occlude(frame: Frame, screens: list[Screen],
            sensor: tuple[float, float, float] = SENSOR_IN_BASE) -> Frame:
    """``frame`` as its sensor at ``sensor`` (the points' frame) sees it with ``screens``
    standing: each return whose ray crosses a screen below its top is moved onto the screen,
    with the screen's intensity. ``num_points`` (the current sweep's returns in each GT box:
    time lag 0 where the points have one) loses the returns moved off each box; GT and the
    rest are kept."""
    if not screens or len(frame.points) == 0:
        return frame
    pts = frame.points.copy()
    p = pts[:, :3].astype(np.float64)
    moved = np.zeros(len(p), bool)
    s = np.asarray(sensor, np.float64)
    inv = se3_inverse(np.asarray(frame.pose, np.float64))
    for sc in screens:
        ends = transform_points(inv, np.array([[*sc.a, sc.ground], [*sc.b, sc.ground]]))
        a, d = ends[0, :2] - s[:2], ends[1, :2] - ends[0, :2]
        ground = float(ends[:, 2].mean())
        ray = p[:, :2] - s[:2]
        # s + t * ray = a + u * d  (2-D): t along the ray (the point at 1), u along the screen
        det = ray[:, 1] * d[0] - ray[:, 0] * d[1]
        ok = np.abs(det) > 1e-9
        safe = np.where(ok, det, 1.0)
        t = (a[1] * d[0] - a[0] * d[1]) / safe
        u = (ray[:, 0] * a[1] - ray[:, 1] * a[0]) / safe
        z = s[2] + t * (p[:, 2] - s[2])
        hit = ok & (t > 0) & (t < 1) & (u >= 0) & (u <= 1) & (z >= ground) \
            & (z <= ground + sc.height)
        p[hit, :2] = s[:2] + t[hit, None] * ray[hit]
        p[hit, 2] = z[hit]
        pts[hit, 3] = sc.intensity
        moved |= hit
    pts[:, :3] = p.astype(pts.dtype)
    times = frame.times
    if times is not None and moved.any():       # a screen stands in the frame at the stamp
        times = np.where(moved, np.float32(0.0), times).astype(np.float32)
    num = frame.num_points
    owners = frame.owners
    if owners is not None and moved.any():       # a return moved onto a screen is the screen's
        owners = np.where(moved, 0, owners).astype(np.uint32)
    if frame.gt is not None and num is not None and len(num):
        current = pts[:, 4] == 0 if pts.shape[1] > 4 else np.ones(len(pts), bool)
        if owners is not None and current.all():
            # a sensor frame with its returns' owners: counted again as the world counts
            num = object_returns(np.where(moved[:, None], np.inf, pts[:, :3]),
                                 frame.gt.boxes, owners, frame.instance_ids)
        else:
            # the current returns each box lost (where they were) off the source's count; a
            # screen's returns are the screen's, wherever they land
            lost = count_points_in_boxes(frame.points[current & moved, :3], frame.gt.boxes)
            num = np.maximum(num.astype(np.int64) - lost.astype(np.int64), 0).astype(num.dtype)
    return replace(frame, points=pts, num_points=num, times=times, owners=owners)


def with_screens(clip: list[Frame], rng: np.random.Generator,
                 sensor: tuple[float, float, float] = SENSOR_IN_BASE
                 ) -> list[Frame]:
    """A clip with screens drawn on its first frame cast into every frame."""
    screens = draw_screens(clip[0], rng, sensor)
    return [occlude(f, screens, sensor) for f in clip]


def occluded_drives(drives: list[list[Frame]], seed: int = 0, window: int = 10
                    ) -> list[list[Frame]]:
    """Drives (sensor frames: the sensor at the points' origin) with screens before their
    objects (fixed draws per drive; a new set every ``window`` frames): the evaluation set of
    the occluder robustness (``suit-ros compare --variant occluders``)."""
    return windowed_drives(drives, lambda clip, rng: with_screens(clip, rng, (0.0, 0.0, 0.0)),
                           seed, window)


# ------------------------------------------------------------------ passing occluders
PASSING_FRAMES = (3, 7)     # frames a passing occluder hides its target: 0.3-0.7 s at 10 Hz
PASSING_NEAREST_M = 3.5     # no nearer to the sensor: the ego's bonnet ends ~2.8 m ahead of it


@dataclass(frozen=True)
class Passing:
    """A passing occluder: something truck-high that crosses the line of sight between the
    sensor and one object (``instance``) and hides it entirely for ``frames`` frames from the
    clip's frame ``first``, at ``fraction`` of the object's distance, moving ``slide`` m across
    the line of sight (``direction`` +1: to the sensor's left) over those frames."""

    instance: int
    first: int
    frames: int
    fraction: float
    height: float
    slide: float
    direction: int
    intensity: float


def _passing_segment(box: NDArray[np.float64], p: Passing, q: float, edge: float = 0.3
                     ) -> NDArray[np.float64] | None:
    """Endpoints ``(2, 2)`` (the frame's x, y; the sensor at its origin) of ``p``'s screen at
    progress ``q`` (0: the event's first frame, 1: its last) hiding ``box`` with ``edge`` m to
    spare on either side; None when the box is too near to stand a screen before it (the
    screen stands at least :data:`PASSING_NEAREST_M` from the sensor, clear of the ego)."""
    corners = _footprint(box, edge)
    theta = float(np.arctan2(box[1], box[0]))
    u = np.array([np.cos(theta), np.sin(theta)])
    v = np.array([-u[1], u[0]])
    depth = corners @ u
    if depth.min() < PASSING_NEAREST_M + 0.5:
        return None
    dist = max(p.fraction * float(depth.min()), PASSING_NEAREST_M)
    lateral = (corners @ v) * dist / depth            # the box's shadow on the screen's line
    lo, hi = float(lateral.min()) - edge, float(lateral.max()) + edge
    if p.direction > 0:
        lo, hi = lo - p.slide * (1.0 - q), hi + p.slide * q
    else:
        lo, hi = lo - p.slide * q, hi + p.slide * (1.0 - q)
    return np.stack([dist * u + lo * v, dist * u + hi * v])


def draw_passing(clip: list[Frame], rng: np.random.Generator, last: int = 1,
                 come_back: bool = True, targets: int = 2, min_returns: int = 10,
                 reach_m: float = 40.0) -> list[Passing]:
    """Passing occluders for a clip of sensor frames: up to ``targets`` objects of its frame
    ``last`` with at least ``min_returns`` returns 6-``reach_m`` m away, at bearings 30
    degrees apart, each hidden from the frame after it for :data:`PASSING_FRAMES` frames and
    labelled through them (and in the frame after them, which the clip then holds: the frame
    it comes back in, with ``come_back``; else the event may run to the clip's end)."""
    after = 1 if come_back else 0
    longest = min(PASSING_FRAMES[1], len(clip) - last - 1 - after)
    f = clip[last] if 0 <= last < len(clip) else None
    if longest < PASSING_FRAMES[0] or f is None or f.gt is None or f.instance_ids is None \
            or f.num_points is None or not len(f.gt):
        return []
    boxes = np.asarray(f.gt.boxes, np.float64)
    dist = np.hypot(boxes[:, 0], boxes[:, 1])
    cand = np.flatnonzero((f.num_points >= min_returns) & (dist > 6.0) & (dist < reach_m))
    out: list[Passing] = []
    bearings: list[float] = []
    for j in rng.permutation(cand):
        if len(out) >= targets:
            break
        frames = int(rng.integers(PASSING_FRAMES[0], longest + 1))
        iid = int(f.instance_ids[j])
        if not all(g.instance_ids is not None and iid in g.instance_ids
                   for g in clip[last + 1:last + 1 + frames + after]):
            continue
        bearing = float(np.arctan2(boxes[j, 1], boxes[j, 0]))
        if any(abs(np.angle(np.exp(1j * (bearing - b)))) < np.radians(30) for b in bearings):
            continue
        bearings.append(bearing)
        out.append(Passing(iid, last + 1, frames, float(rng.uniform(0.3, 0.7)),
                           float(rng.uniform(3.2, 4.0)), float(rng.uniform(1.0, 4.0)),
                           int(rng.choice([-1, 1])), float(rng.uniform(0.02, 0.3))))
    return out


def cast_passing(clip: list[Frame], passing: list[Passing]) -> list[Frame]:
    """A clip of sensor frames (the sensor at the points' origin) with ``passing`` cast into
    the frames they stand in. A screen that would pass through another labelled object in a
    frame is left out of that frame (its target then shows there)."""
    out = list(clip)
    for k in range(len(clip)):
        f = clip[k]
        screens = []
        xyz = np.asarray(f.points[:, :3], np.float64)
        for p in passing:
            j = k - p.first
            if not 0 <= j < p.frames or f.gt is None or f.instance_ids is None:
                continue
            rows = np.flatnonzero(f.instance_ids == p.instance)
            if not len(rows):
                continue
            box = np.asarray(f.gt.boxes[rows[0]], np.float64)
            seg = _passing_segment(box, p, j / max(p.frames - 1, 1))
            if seg is None or _crosses(seg, np.delete(f.gt.boxes, rows, axis=0)):
                continue
            mid = seg.mean(0)
            ground = ground_near(xyz, mid[0], mid[1])
            bottom = float(box[2] - box[5] / 2) if ground is None else ground
            # tall enough that the rays to the box's top cross it (a bus beside a slope): the
            # screen stands ``dist`` along the box's bearing
            r = float(np.hypot(box[0], box[1]))
            dist = float(seg[0] @ box[:2]) / r
            reach = r + np.array([-0.5, 0.5]) * np.hypot(*box[3:5])
            top = float(box[2] + box[5] / 2) * dist / np.maximum(reach, dist + 0.1)
            height = max(p.height, float(top.max()) + 0.3 - bottom)
            w = transform_points(np.asarray(f.pose, np.float64), np.c_[seg, np.full(2, bottom)])
            screens.append(Screen((float(w[0, 0]), float(w[0, 1])),
                                  (float(w[1, 0]), float(w[1, 1])), float(w[:, 2].mean()),
                                  height, p.intensity))
        out[k] = occlude(f, screens, (0.0, 0.0, 0.0))
    return out


def with_passing(clip: list[Frame], rng: np.random.Generator) -> list[Frame]:
    """A clip of sensor frames with passing occluders drawn on its frame 1 (:func:`draw_passing`)
    cast into it (:func:`cast_passing`)."""
    return cast_passing(clip, draw_passing(clip, rng))


def passing_drives(drives: list[list[Frame]], seed: int = 0, window: int = 10
                   ) -> list[list[Frame]]:
    """Drives (sensor frames) with passing occluders: in every ``window`` frames up to two
    well-seen objects hidden 0.3-0.7 s by something truck-high crossing their line of sight
    (fixed draws per drive): the occlusion set of ``suit-ros outage``, issue 21's "vehicles
    passing between the ego and objects", where a drive's own occlusions are few and mostly far
    objects flickering between one or two returns and none."""
    return windowed_drives(drives, with_passing, seed, window)
