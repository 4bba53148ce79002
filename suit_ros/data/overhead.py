"""Overhead structures over the street: tree canopies, awnings, shelter roofs, signal arms.

On real sweeps pedestrians stand under trees and awnings, and the returns above their heads
(2.2-4.5 m up, hundreds per square metre on a 64-beam sensor) share their pillars: on the
Argoverse 2 dev sweeps a synthetic pedestrian pasted under a real canopy drops from a heatmap
score of about 0.5 to 0.05-0.2, while the same real pedestrian's own points, alone, score as a
synthetic one does (docs/experiments/overhead). The synthetic world has no such structure over
its sidewalks, so the model never learned to look under one.

:func:`draw_slabs` places flat slabs of returns (a footprint of 1.5-5 m, 2.2-4 m above the
ground, 0.1-1.2 m thick) over about half the small objects of a clip (pedestrians, cyclists),
over a quarter of the large ones (cars parked under street trees) and over as many empty
places (so that a roof is no cue for an object); :func:`add_slabs` adds their returns to a
frame. Slabs are fixed in the odometry frame, so they stay put across the frames of a clip
while the ego moves; each frame draws fresh returns, denser near the sensor, with the time
lags of the frame's own sweeps.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from suit_ros.data.drawn import ground_near, windowed_drives
from suit_ros.structures import Frame

SMALL_FOOTPRINT_M2 = 1.5       # a box footprint below this is a pedestrian or a rider


@dataclass(frozen=True)
class Slab:
    """A horizontal slab of returns: footprint centre (odometry frame) at ground height
    ``ground``, ``size`` (m), ``yaw`` (odometry frame), bottom ``base`` m above the ground,
    ``thickness`` m, returns per square metre at 15 m from the sensor."""

    centre: tuple[float, float]
    ground: float
    size: tuple[float, float]
    yaw: float
    base: float
    thickness: float
    density: float


def draw_slabs(frame: Frame, rng: np.random.Generator, small_probability: float = 0.5,
               large_probability: float = 0.25, extra: int = 2, reach_m: float = 40.0
               ) -> list[Slab]:
    """Slabs over some of ``frame``'s GT objects and over empty places (model frame: points
    and boxes in base_link, ``pose`` = ``T_odom_base``)."""
    places: list[tuple[float, float, float]] = []       # x, y, ground (base_link)
    if frame.gt is not None:
        for box in np.asarray(frame.gt.boxes, np.float64):
            small = box[3] * box[4] < SMALL_FOOTPRINT_M2
            if rng.random() < (small_probability if small else large_probability):
                dx, dy = rng.normal(0.0, 0.7, 2)
                places.append((box[0] + dx, box[1] + dy, box[2] - box[5] / 2))
    for _ in range(len(places) + extra):
        r, a = rng.uniform(5.0, reach_m), rng.uniform(-np.pi, np.pi)
        x, y = r * np.cos(a), r * np.sin(a)
        ground = ground_near(frame.points, x, y)
        if ground is not None:
            places.append((x, y, ground))
    slabs = []
    for x, y, ground in places:
        world = frame.pose @ np.array([x, y, ground, 1.0])
        slabs.append(Slab((float(world[0]), float(world[1])), float(world[2]),
                          (float(rng.uniform(1.5, 5.0)), float(rng.uniform(1.5, 5.0))),
                          float(rng.uniform(-np.pi, np.pi)),
                          float(rng.uniform(2.2, 4.0)), float(rng.uniform(0.1, 1.2)),
                          float(rng.uniform(10.0, 150.0))))
    return slabs


def slab_points(slab: Slab, pose: NDArray[np.float64], rng: np.random.Generator,
                lags: NDArray[np.float32] | None, max_points: int = 3000
                ) -> NDArray[np.float32]:
    """One frame's returns of a slab, ``(n, 4 or 5)`` in the frame of ``pose``
    (``T_odom_base``); the lag column drawn from ``lags`` when given."""
    inv = np.linalg.inv(pose)
    c = inv @ np.array([slab.centre[0], slab.centre[1], slab.ground, 1.0])
    yaw = slab.yaw - float(np.arctan2(pose[1, 0], pose[0, 0]))
    dist = max(float(np.hypot(c[0], c[1])), 5.0)
    area = slab.size[0] * slab.size[1]
    n = min(int(rng.poisson(slab.density * area * min(15.0 / dist, 3.0))), max_points)
    u = rng.uniform(-0.5, 0.5, (n, 2)) * np.asarray(slab.size)
    cs, sn = np.cos(yaw), np.sin(yaw)
    x = c[0] + u[:, 0] * cs - u[:, 1] * sn
    y = c[1] + u[:, 0] * sn + u[:, 1] * cs
    z = c[2] + slab.base + slab.thickness * rng.random(n) ** 2     # most returns underneath
    cols = [x, y, z, rng.uniform(0.0, 0.25, n)]
    if lags is not None:
        cols.append(rng.choice(lags, n) if len(lags) else np.zeros(n))
    out: NDArray[np.float32] = np.stack(cols, axis=1).astype(np.float32)
    return out


def add_slabs(frame: Frame, slabs: list[Slab], rng: np.random.Generator) -> Frame:
    """``frame`` with the returns of ``slabs`` added (GT unchanged)."""
    if not slabs:
        return frame
    lags = None
    if frame.points.shape[1] > 4:
        lags = np.unique(frame.points[:, 4])
    extra = [slab_points(s, frame.pose, rng, lags) for s in slabs]
    added = sum(len(e) for e in extra)
    times = frame.times              # a slab is cast from the pose at the stamp: time 0
    if times is not None:
        times = np.concatenate([times, np.zeros(added, np.float32)])
    owners = frame.owners            # a slab's returns are the slab's
    if owners is not None:
        owners = np.concatenate([owners, np.zeros(added, np.uint32)])
    return replace(frame, points=np.concatenate([frame.points, *extra]).astype(np.float32),
                   times=times, owners=owners)


def with_overhead(clip: list[Frame], rng: np.random.Generator) -> list[Frame]:
    """A clip with slabs drawn on its first frame added to every frame."""
    slabs = draw_slabs(clip[0], rng)
    return [add_slabs(f, slabs, rng) for f in clip]


def overhead_drives(drives: list[list[Frame]], seed: int = 0, window: int = 10
                    ) -> list[list[Frame]]:
    """Drives with slabs over their objects (fixed draws per drive; a new set of slabs every
    ``window`` frames): the evaluation set of the overhead robustness (``suit-ros compare
    --variant overhead``)."""
    return windowed_drives(drives, with_overhead, seed, window)
