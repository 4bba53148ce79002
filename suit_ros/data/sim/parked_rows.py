"""Rows of parked cars along the kerbs, as real city streets are lined.

On the two Argoverse 2 dev sweeps (Pittsburgh) 16 labelled cars stand within 50 m of the
sensor, 10-11 of them standing; the world without this has a median of 6 cars within 50 m (2
of them standing), each parked alone. A car in a row is seen in part: its neighbours hide its
ends, the sensor sees a corner past the car in front, or only its roof over the next one (the
dev set's missed cars at 8 and 24 m look like such views; docs/experiments/parked_rows).

:attr:`~suit_ros.data.sim.config.Realism.parked_rows` sets how densely the kerbs are lined, on
both sides of every block edge with an end within 100 m of the ego's path: :func:`park_rows`
walks each kerb from 10 m past one intersection to 10 m before the next, alternating rows of
2-8 cars (0.4-2.5 m apart, 0.15-0.35 m off the kerb, a share ``parked_reversed`` of them
against their side's traffic) with empty stretches whose mean length puts rows on about that
share of the kerb (less where a row is cut at the kerb's end or a car is left out). A car is
left out where its footprint would come within 0.3 m of anything that drives past or stands
during the drive (the ego, traffic, cyclists; a pedestrian within 0.2 m), each at its own size
and heading at every step, or within 0.25 m of another parked vehicle. Its own generator keeps
the rest of the world as it was, and 0 adds nothing.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from suit_ros import CLASS_NAMES
from suit_ros.data.sim.actors import Actor, Trajectories, _actor, dark_top, id_fraction, real_roof
from suit_ros.data.sim.bodies import car_body, paint, vehicle_kind
from suit_ros.data.sim.config import Realism
from suit_ros.data.sim.world import World

CLEAR_END = 10.0      # m: no car this close to an intersection's centre line crossing
NEAR_EGO = 100.0      # m: block edges with an end this close to the ego's path get rows
ROW_CARS = (2, 8)     # cars a row holds (inclusive)
ROW_GAP = (0.4, 2.5)  # m between cars of a row
KERB_GAP = (0.15, 0.35)   # m between a car's side and the kerb
YAW_SD = 0.015        # rad: how far a car stands off its kerb's line
PATH_CLEAR = 0.3      # m between a row car and anything that drives past or stands
WALK_CLEAR = 0.2      # m between a row car and a pedestrian
PARKED_CLEAR = 0.25   # m between two parked vehicles


def _overlap(rects: NDArray[np.float64], box: NDArray[np.float64],
             clear: float | NDArray[np.float64]) -> bool:
    """Whether the footprint ``box`` (x, y, l, w, yaw) comes within ``clear`` (m; one value or
    one per rectangle) of any of the footprints ``rects`` ``(K, 5)``: two rectangles grown by
    half of ``clear`` each overlap unless one of their four axes separates them."""
    if len(rects) == 0:
        return False
    d = rects[:, :2] - box[:2]
    ua = np.array([np.cos(box[4]), np.sin(box[4])])
    va = np.array([-ua[1], ua[0]])
    ub = np.stack([np.cos(rects[:, 4]), np.sin(rects[:, 4])], 1)
    vb = np.stack([-ub[:, 1], ub[:, 0]], 1)
    separated = np.zeros(len(rects), bool)
    for n in (np.broadcast_to(ua, ub.shape), np.broadcast_to(va, ub.shape), ub, vb):
        half_a = np.abs(n @ ua) * box[2] / 2 + np.abs(n @ va) * box[3] / 2
        half_b = (np.abs((n * ub).sum(1)) * rects[:, 2] / 2
                  + np.abs((n * vb).sum(1)) * rects[:, 3] / 2)
        separated |= np.abs((n * d).sum(1)) > half_a + half_b + clear
    return bool((~separated).any())


def _edges_near(world: World, path: NDArray[np.float64]) -> list[tuple[tuple[int, int],
                                                                       tuple[int, int]]]:
    """The block edges (pairs of neighbouring intersections, each once) with an end within
    :data:`NEAR_EGO` of the ego's ``path`` ``(K, 2)``."""
    n = world.grid_half
    near: set[tuple[int, int]] = set()
    for i in range(-n, n + 1):
        for j in range(-n, n + 1):
            d = np.hypot(*(path - world.node_xy(i, j)).T).min()
            if d <= NEAR_EGO:
                near.add((i, j))
    edges: set[tuple[tuple[int, int], tuple[int, int]]] = set()
    for i, j in near:
        for di, dj in ((1, 0), (0, 1), (-1, 0), (0, -1)):
            k = (i + di, j + dj)
            if max(abs(k[0]), abs(k[1])) <= n:
                edges.add(((i, j), k) if (i, j) < k else (k, (i, j)))
    return sorted(edges)


def park_rows(actors: Sequence[Actor], ego: Actor, world: World, realism: Realism,
              rng: np.random.Generator) -> list[Actor]:
    """Parked cars in rows along the kerbs near the ``ego``'s path (module docstring), dressed
    as :func:`~suit_ros.data.sim.actors.dress_actors` dresses cars. :return: the new actors
    (ids after the largest one in ``actors``)."""
    share = realism.parked_rows
    if share <= 0 or not actors:
        return []
    everyone = [ego, *actors]
    traj = Trajectories.sample(everyone)
    steps = traj.x.shape[1]
    parked = np.array([len(a.poly) == 1 and CLASS_NAMES[a.label] in ('car', 'truck')
                       for a in everyone])
    walker = np.array([CLASS_NAMES[a.label] == 'pedestrian' for a in everyone])
    # what moves or stands during the drive, as a footprint at every step (the ego, traffic,
    # cyclists, pedestrians: their own sizes and headings), and the parked vehicles
    size = np.array([a.size[:2] for a in everyone])[~parked]
    paths = np.concatenate([np.stack([traj.x[~parked].ravel(), traj.y[~parked].ravel()], 1),
                            np.repeat(size, steps, axis=0), traj.yaw[~parked].ravel()[:, None]],
                           1)
    path_clear = np.repeat(np.where(walker[~parked], WALK_CLEAR, PATH_CLEAR), steps)
    taken = np.array([[a.poly[0, 0], a.poly[0, 1], a.size[0], a.size[1], a.heading]
                      for a, p in zip(everyone, parked) if p], np.float64).reshape(-1, 5)
    ego_path = np.stack([traj.x[0], traj.y[0]], 1)
    next_id = max(a.instance_id for a in actors) + 1
    still = np.zeros(steps)
    out: list[Actor] = []
    mean_row = 0.5 * (ROW_CARS[0] + ROW_CARS[1]) * (4.6 + np.mean(ROW_GAP))
    mean_gap = mean_row * (1.0 - share) / share if share < 1 else 0.0

    def gap() -> float:
        """An empty stretch of kerb before a row (none at a full share)."""
        return float(rng.exponential(mean_gap)) if mean_gap else 0.0

    for p, q in _edges_near(world, ego_path):
        a, b = world.node_xy(*p), world.node_xy(*q)
        length = float(np.linalg.norm(b - a))
        d = (b - a) / length
        normal = np.array([d[1], -d[0]])                      # right of a -> b
        for side in (1.0, -1.0):
            s = CLEAR_END + gap()
            while s < length - CLEAR_END:
                for _ in range(int(rng.integers(ROW_CARS[0], ROW_CARS[1] + 1))):
                    kind, size = vehicle_kind(rng)
                    if s + size[0] > length - CLEAR_END:
                        s = length              # the kerb is full: on to the next
                        break
                    centre = s + size[0] / 2
                    off = world.road_half_width - size[1] / 2 - float(rng.uniform(*KERB_GAP))
                    xy = a + d * centre + normal * side * off
                    yaw = float(np.arctan2(d[1], d[0])) + (0.0 if side > 0 else np.pi)
                    if rng.random() < realism.parked_reversed:
                        yaw += np.pi
                    yaw = float((yaw + float(rng.normal(0.0, YAW_SD)) + np.pi) % (2 * np.pi)
                                - np.pi)
                    box = np.array([xy[0], xy[1], size[0], size[1], yaw])
                    coat = paint(rng, realism)
                    s += size[0] + float(rng.uniform(*ROW_GAP))
                    if _overlap(paths, box, path_clear) or _overlap(taken, box, PARKED_CLEAR):
                        continue
                    car = _actor(next_id, 'car', 'car', size, xy[None, :].copy(), still.copy(),
                                 still.copy())
                    car.heading = yaw
                    car.body = car_body(kind, size, coat, realism,
                                        real_ends=id_fraction(next_id) < realism.real_car_ends,
                                        dark_top=dark_top(next_id, realism.dark_tops),
                                        real_roof=real_roof(next_id, realism.real_car_roofs))
                    out.append(car)
                    taken = np.concatenate([taken, box[None]])
                    next_id += 1
                s += gap()
    return out
