"""Rows of parked cars along the kerbs, as real city streets are lined.

On the two Argoverse 2 dev sweeps (Pittsburgh) 16 labelled cars stand within 50 m of the
sensor, most of them parked in rows; the world without this has a median of 6 cars within 50 m
(2 of them standing), each parked alone. A car in a row is seen in part: its neighbours hide
its ends, the sensor sees a corner past the car in front, or only its roof over the next one
(the dev set's missed cars at 8 and 24 m are such views; docs/experiments/parked_rows).

:attr:`~suit_ros.data.sim.config.Realism.parked_rows` is the share of kerb length, on both
sides of every block edge that the ego passes within 100 m of, lined with parked cars:
:func:`park_rows` walks each kerb from 10 m past one intersection to 10 m before the next,
alternating rows of 2-8 cars (0.4-2.5 m apart, most facing the traffic on their side) and
empty stretches; a car is left out where anything else stands or passes during the drive
(another actor's path, a parked vehicle, a pedestrian). Its own generator keeps the rest of the
world as it was, and 0 adds nothing.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from suit_ros import CLASS_NAMES
from suit_ros.data.sim.actors import Actor, Trajectories, _actor, dark_top, id_fraction
from suit_ros.data.sim.bodies import car_body, paint, vehicle_kind
from suit_ros.data.sim.config import Realism
from suit_ros.data.sim.world import World

CLEAR_END = 10.0      # m: no car this close to an intersection's centre line crossing
NEAR_EGO = 100.0      # m: block edges with an end this close to the ego's path get rows
ROW_CARS = (2, 8)     # cars a row holds (inclusive)
ROW_GAP = (0.4, 2.5)  # m between cars of a row
PATH_PAD = 1.4        # m: a moving actor's centre stays this far outside a parked car
REVERSED = 0.15       # share of cars parked against their side's traffic


def _inside(points: NDArray[np.float64], box: NDArray[np.float64], pad_l: float,
            pad_w: float) -> bool:
    """Whether any of ``points`` ``(N, 2)`` lies in the footprint ``box`` (x, y, l, w, yaw)
    grown by ``pad_l`` along it and ``pad_w`` across."""
    if len(points) == 0:
        return False
    d = points - box[:2]
    c, s = np.cos(box[4]), np.sin(box[4])
    u = np.abs(c * d[:, 0] + s * d[:, 1])
    v = np.abs(-s * d[:, 0] + c * d[:, 1])
    return bool(((u <= box[2] / 2 + pad_l) & (v <= box[3] / 2 + pad_w)).any())


def _overlaps(boxes: NDArray[np.float64], box: NDArray[np.float64], clear: float = 0.3
              ) -> bool:
    """Whether a footprint ``box`` (x, y, l, w, yaw) comes within ``clear`` of any of
    ``boxes`` ``(K, 5)`` (bounding circles along and across ``box``'s axes: a test that may
    say yes for two boxes at an angle that do not touch, never no for two that do)."""
    if len(boxes) == 0:
        return False
    d = boxes[:, :2] - box[:2]
    c, s = np.cos(box[4]), np.sin(box[4])
    u = np.abs(c * d[:, 0] + s * d[:, 1])
    v = np.abs(-s * d[:, 0] + c * d[:, 1])
    reach = 0.5 * np.hypot(boxes[:, 2], boxes[:, 3])
    return bool(((u < box[2] / 2 + reach + clear) & (v < box[3] / 2 + reach + clear)).any())


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
    traj = Trajectories.sample([ego, *actors])
    steps = traj.x.shape[1]
    moving = np.array([True] + [len(a.poly) > 1 for a in actors])
    vehicle = np.array([True] + [CLASS_NAMES[a.label] in ('car', 'truck') for a in actors])
    # where everything is during the drive: the moving along their paths, standing pedestrians
    # and cyclists where they stand; parked vehicles as footprints (x, y, l, w, yaw)
    paths = np.stack([traj.x[moving | ~vehicle].ravel(), traj.y[moving | ~vehicle].ravel()], 1)
    taken = np.array([[a.poly[0, 0], a.poly[0, 1], a.size[0], a.size[1], a.heading]
                      for a in actors if len(a.poly) == 1
                      and CLASS_NAMES[a.label] in ('car', 'truck')], np.float64).reshape(-1, 5)
    ego_path = np.stack([traj.x[0], traj.y[0]], 1)
    next_id = max(a.instance_id for a in actors) + 1
    still = np.zeros(steps)
    out: list[Actor] = []
    mean_row = 0.5 * (ROW_CARS[0] + ROW_CARS[1]) * (4.6 + np.mean(ROW_GAP))
    mean_gap = mean_row * (1.0 - share) / share if share < 1 else 0.0
    for p, q in _edges_near(world, ego_path):
        a, b = world.node_xy(*p), world.node_xy(*q)
        length = float(np.linalg.norm(b - a))
        d = (b - a) / length
        normal = np.array([d[1], -d[0]])                      # right of a -> b
        for side in (1.0, -1.0):
            s = CLEAR_END + float(rng.exponential(mean_gap)) if mean_gap else CLEAR_END
            while s < length - CLEAR_END:
                for _ in range(int(rng.integers(ROW_CARS[0], ROW_CARS[1] + 1))):
                    kind, size = vehicle_kind(rng)
                    if s + size[0] > length - CLEAR_END:
                        break
                    centre = s + size[0] / 2
                    off = world.road_half_width - size[1] / 2 - float(rng.uniform(0.1, 0.35))
                    xy = a + d * centre + normal * side * off
                    yaw = float(np.arctan2(d[1], d[0])) + (0.0 if side > 0 else np.pi)
                    if rng.random() < REVERSED:
                        yaw += np.pi
                    yaw = float((yaw + float(rng.normal(0.0, 0.03)) + np.pi) % (2 * np.pi) - np.pi)
                    box = np.array([xy[0], xy[1], size[0], size[1], yaw])
                    coat = paint(rng, realism)
                    s += size[0] + float(rng.uniform(*ROW_GAP))
                    if _inside(paths, box, 0.3, PATH_PAD) or _overlaps(taken, box):
                        continue
                    car = _actor(next_id, 'car', 'car', size, xy[None, :].copy(), still,
                                 still.copy())
                    car.heading = yaw
                    car.body = car_body(kind, size, coat, realism,
                                        real_ends=id_fraction(next_id) < realism.real_car_ends,
                                        dark_top=dark_top(next_id, realism.dark_tops))
                    out.append(car)
                    taken = np.concatenate([taken, box[None]])
                    next_id += 1
                s += float(rng.exponential(mean_gap)) if mean_gap else 0.0
    return out
