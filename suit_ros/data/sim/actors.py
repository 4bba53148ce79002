"""Actors (cars, trucks and buses, pedestrians, cyclists) and the ego vehicle.

Each actor follows a polyline route with a speed profile integrated once at creation (targets
that change every few seconds, bounded acceleration), so its pose and its exact velocity are
available at any time. Parked vehicles and standing pedestrians have speed 0.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from suit_ros import CLASS_NAMES
from suit_ros.data.sim.bodies import (
    Body,
    car_body,
    cyclist_body,
    heavy_body,
    motorcycle_body,
    paint,
    pedestrian_body,
    vehicle_kind,
)
from suit_ros.data.sim.config import Realism, SimConfig
from suit_ros.data.sim.world import MATERIAL_IDS, World, random_route, route_polyline

LABEL = {name: i for i, name in enumerate(CLASS_NAMES)}
STEP = 0.02   # s, integration step of the speed profiles


@dataclass
class Actor:
    """One moving or static object (or the ego vehicle)."""

    instance_id: int
    label: int
    material: int
    size: NDArray[np.float64]            # (3,) l, w, h
    poly: NDArray[np.float64]            # (K, 2) route
    cum: NDArray[np.float64]             # (K,) arc length along the route
    s: NDArray[np.float64]               # arc length at t = k * STEP
    v: NDArray[np.float64]               # speed at t = k * STEP
    heading: float = 0.0                 # yaw of a static, single-point actor
    body: Body | None = None             # parts in the detailed world (None: one cuboid)

    def state(self, t: float) -> tuple[float, float, float, float, float]:
        """``x, y, yaw, vx, vy`` at time ``t`` (s, world frame)."""
        k = min(max(t / STEP, 0.0), len(self.s) - 1.000001)
        i = int(k)
        f = k - i
        s = self.s[i] * (1 - f) + self.s[i + 1] * f
        v = self.v[i] * (1 - f) + self.v[i + 1] * f
        if len(self.poly) == 1:
            return float(self.poly[0, 0]), float(self.poly[0, 1]), self.heading, 0.0, 0.0
        j = int(np.clip(np.searchsorted(self.cum, s) - 1, 0, len(self.cum) - 2))
        seg = self.poly[j + 1] - self.poly[j]
        L = max(self.cum[j + 1] - self.cum[j], 1e-9)
        p = self.poly[j] + seg * np.clip((s - self.cum[j]) / L, 0.0, 1.0)
        # heading from a short chord around s (smooth through the rounded corners)
        a = np.interp(s - 1.0, self.cum, self.poly[:, 0]), np.interp(s - 1.0, self.cum,
                                                                     self.poly[:, 1])
        b = np.interp(s + 1.0, self.cum, self.poly[:, 0]), np.interp(s + 1.0, self.cum,
                                                                     self.poly[:, 1])
        yaw = float(np.arctan2(b[1] - a[1], b[0] - a[0]))
        tangent = seg / L
        return float(p[0]), float(p[1]), yaw, float(v * tangent[0]), float(v * tangent[1])

    def box(self, t: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """World box ``(7,)`` and velocity ``(2,)`` at time ``t``."""
        x, y, yaw, vx, vy = self.state(t)
        l, w, h = self.size
        return np.array([x, y, h / 2, l, w, h, yaw]), np.array([vx, vy])


def speed_profile(rng: np.random.Generator, duration: float, v_range: tuple[float, float],
                  accel: float, length: float, stop_probability: float = 0.0
                  ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Integrate a speed profile: arc length and speed at ``k * STEP`` for the whole drive."""
    n = int(duration / STEP) + 2
    s = np.zeros(n)
    v = np.zeros(n)
    speed = rng.uniform(*v_range)
    target = speed
    next_change = rng.uniform(2, 8)
    for k in range(1, n):
        t = k * STEP
        if t >= next_change:
            target = 0.0 if rng.random() < stop_probability else rng.uniform(*v_range)
            next_change = t + rng.uniform(2, 8)
        speed += np.clip(target - speed, -accel * STEP, accel * STEP)
        if s[k - 1] >= length - 0.5:
            speed = 0.0
        v[k] = speed
        s[k] = min(s[k - 1] + speed * STEP, length)
    v[0] = v[1]
    return s, v


def _actor(instance_id: int, label: str, material: str, size: NDArray[np.float64],
           poly: NDArray[np.float64], s: NDArray[np.float64], v: NDArray[np.float64]) -> Actor:
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poly, axis=0), axis=1))])
    return Actor(instance_id, LABEL[label], MATERIAL_IDS[material], size, poly, cum, s, v)


def vehicle_size(rng: np.random.Generator, truck: bool) -> tuple[str, NDArray[np.float64]]:
    """nuScenes-like sizes: cars ~4.6 x 1.9 x 1.7; trucks 6-10 m; buses ~11 x 2.9 x 3.4."""
    if not truck:
        return 'car', np.array([rng.normal(4.6, 0.3), rng.normal(1.95, 0.1),
                                rng.normal(1.7, 0.15)]).clip([3.5, 1.6, 1.3], [5.6, 2.2, 2.1])
    if rng.random() < 0.35:
        return 'truck', np.array([rng.uniform(10.5, 12.5), rng.uniform(2.8, 3.0),
                                  rng.uniform(3.2, 3.6)])
    return 'truck', np.array([rng.uniform(6.0, 10.0), rng.uniform(2.3, 2.7),
                              rng.uniform(2.6, 3.6)])


def make_ego(world: World, cfg: SimConfig, rng: np.random.Generator, duration: float) -> Actor:
    """The ego vehicle: a random route in the outer lane, 0..ego_max_speed, with stops."""
    length = cfg.ego_max_speed * duration + 50
    nodes = random_route(world, rng, length, start=(0, 0))
    poly = route_polyline(world, nodes, world.lane_width * 0.5)
    cum_len = float(np.sum(np.linalg.norm(np.diff(poly, axis=0), axis=1)))
    s, v = speed_profile(rng, duration, (4.0, cfg.ego_max_speed), 2.0, cum_len, 0.15)
    return _actor(0, 'car', 'car', np.array([4.7, 1.9, 1.6]), poly, s, v)


def make_actors(world: World, cfg: SimConfig, rng: np.random.Generator, duration: float,
                ego: Actor) -> list[Actor]:
    """Populate the area around the ego's route."""
    actors: list[Actor] = []
    route_nodes = np.round(ego.poly[::40] / world.block).astype(int)
    n = world.grid_half

    def near_node() -> tuple[int, int]:
        i, j = route_nodes[rng.integers(len(route_nodes))]
        i = int(np.clip(i + rng.integers(-1, 2), -n, n))
        j = int(np.clip(j + rng.integers(-1, 2), -n, n))
        return i, j

    def next_id() -> int:
        return len(actors) + 1

    for _ in range(cfg.moving_vehicles):
        name, size = vehicle_size(rng, rng.random() < cfg.truck_fraction)
        nodes = random_route(world, rng, 15.0 * duration + 100, start=near_node())
        lane = int(rng.integers(world.lanes))
        poly = route_polyline(world, nodes, world.lane_width * (lane + 0.5))
        start = rng.uniform(0, world.block)
        poly = poly[int(start / 0.5):]
        cum = float(np.sum(np.linalg.norm(np.diff(poly, axis=0), axis=1)))
        vmax = 11.0 if name == 'truck' else 15.0
        s, v = speed_profile(rng, duration, (3.0, vmax), 2.5, cum, 0.1)
        actors.append(_actor(next_id(), name, name, size, poly, s, v))
    for _ in range(cfg.parked_vehicles):
        name, size = vehicle_size(rng, rng.random() < cfg.truck_fraction * 0.5)
        nodes = random_route(world, rng, world.block, start=near_node())
        edge = world.road_half_width - size[1] / 2 - 0.2
        poly = route_polyline(world, nodes[:2], edge, corner_radius=0.5)
        k = int(rng.integers(len(poly) // 5, 4 * len(poly) // 5))
        d = poly[min(k + 1, len(poly) - 1)] - poly[k - 1]
        yaw = float(np.arctan2(d[1], d[0]))
        still = np.zeros(int(duration / STEP) + 2)
        a = _actor(next_id(), name, name, size, poly[k:k + 1], still, still.copy())
        a.heading = yaw
        actors.append(a)
    for _ in range(cfg.pedestrians):
        size = np.array([rng.uniform(0.5, 0.9), rng.uniform(0.5, 0.8), rng.uniform(1.5, 1.9)])
        nodes = random_route(world, rng, 2.0 * duration + 60, start=near_node())
        side = world.road_half_width + world.sidewalk_width * rng.uniform(0.3, 0.7)
        poly = route_polyline(world, nodes, side, corner_radius=2.0)
        poly = poly[int(rng.uniform(0, world.block) / 0.5):]
        cum = float(np.sum(np.linalg.norm(np.diff(poly, axis=0), axis=1)))
        standing = rng.random() < 0.25
        s, v = speed_profile(rng, duration, (0.0, 0.0) if standing else (0.8, 1.8), 0.5, cum)
        actors.append(_actor(next_id(), 'pedestrian', 'pedestrian', size, poly, s, v))
    for _ in range(cfg.cyclists):
        size = np.array([rng.uniform(1.6, 1.9), rng.uniform(0.5, 0.7), rng.uniform(1.5, 1.8)])
        nodes = random_route(world, rng, 7.0 * duration + 60, start=near_node())
        poly = route_polyline(world, nodes, world.road_half_width - 0.7, corner_radius=4.0)
        poly = poly[int(rng.uniform(0, world.block) / 0.5):]
        cum = float(np.sum(np.linalg.norm(np.diff(poly, axis=0), axis=1)))
        s, v = speed_profile(rng, duration, (2.5, 7.0), 1.0, cum, 0.05)
        actors.append(_actor(next_id(), 'cyclist', 'cyclist', size, poly, s, v))
    return actors


# ------------------------------------------------------------------ the detailed world
def id_fraction(instance_id: int) -> float:
    """A number in [0, 1) drawn from an actor's id (Knuth's multiplicative hash): a choice
    made per actor without a draw from the world's generator, which stays as it was."""
    return ((instance_id * 2654435761) % 2**32) / 2**32


def dark_top(instance_id: int, share: float) -> bool:
    """Whether a passenger car is seen only below the belt (:attr:`Realism.dark_tops`): drawn
    from its id (a hash apart from the ones that shape car ends and place bystanders)."""
    return id_fraction(instance_id * 13 + 5) < share


def real_roof(instance_id: int, share: float) -> bool:
    """Whether a passenger car's greenhouse sits as on real cars (:attr:`Realism.real_car_roofs`):
    drawn from its id (a hash apart from the others)."""
    return id_fraction(instance_id * 17 + 3) < share


def dress_actors(actors: list[Actor], realism: Realism, rng: np.random.Generator) -> None:
    """Give every actor a :class:`Body` (and a size that fits it): cars become sedans,
    hatchbacks, SUVs, vans or pickups; trucks and buses get cabs, cargo boxes or window bands;
    pedestrians limbs and carried objects; cyclists a bicycle (some a motorcycle)."""
    for a in actors:
        name = CLASS_NAMES[a.label]
        if name == 'car':
            kind, a.size = vehicle_kind(rng)
            real = id_fraction(a.instance_id) < realism.real_car_ends
            a.body = car_body(kind, a.size, paint(rng, realism), realism, real_ends=real,
                              dark_top=dark_top(a.instance_id, realism.dark_tops),
                              real_roof=real_roof(a.instance_id, realism.real_car_roofs))
        elif name == 'truck':
            a.body = heavy_body(a.size, paint(rng, realism), realism)
        elif name == 'pedestrian':
            a.body = pedestrian_body(a.size, rng, moving=bool(a.v.max() > 0))
        elif rng.random() < 0.3:
            a.size = np.array([rng.uniform(2.0, 2.3), rng.uniform(0.75, 0.9),
                               rng.uniform(1.45, 1.6)])
            a.body = motorcycle_body(a.size, paint(rng, realism), rng)
        else:
            a.body = cyclist_body(a.size, rng)


@dataclass
class Trajectories:
    """Every actor's state sampled at ``k * STEP`` once, so that all actors' poses at any time
    are one interpolation: ``(A, K)`` arrays (yaw unwrapped over time)."""

    x: NDArray[np.float64]
    y: NDArray[np.float64]
    yaw: NDArray[np.float64]
    vx: NDArray[np.float64]
    vy: NDArray[np.float64]
    s: NDArray[np.float64]

    @classmethod
    def sample(cls, actors: list[Actor]) -> Trajectories:
        """Sample the actors' routes and speed profiles (all have the same length)."""
        rows = [_sampled_state(a) for a in actors]
        return cls(*(np.array([r[i] for r in rows]).reshape(len(actors), -1) for i in range(6)))

    def at(self, t: float) -> tuple[NDArray[np.float64], ...]:
        """``x, y, yaw, vx, vy, s`` of every actor ``(A,)`` at time ``t``."""
        k = min(max(t / STEP, 0.0), self.x.shape[1] - 1.000001)
        i = int(k)
        f = k - i
        return tuple(v[:, i] * (1 - f) + v[:, i + 1] * f
                     for v in (self.x, self.y, self.yaw, self.vx, self.vy, self.s))


def _sampled_state(a: Actor) -> tuple[NDArray[np.float64], ...]:
    """``x, y, yaw, vx, vy, s`` of one actor at every ``k * STEP`` (as :meth:`Actor.state`)."""
    s, v = a.s, a.v
    if len(a.poly) == 1:
        one = np.ones_like(s)
        return (a.poly[0, 0] * one, a.poly[0, 1] * one, a.heading * one, 0 * one, 0 * one, s)
    x = np.interp(s, a.cum, a.poly[:, 0])
    y = np.interp(s, a.cum, a.poly[:, 1])
    ax, ay = np.interp(s - 1.0, a.cum, a.poly[:, 0]), np.interp(s - 1.0, a.cum, a.poly[:, 1])
    bx, by = np.interp(s + 1.0, a.cum, a.poly[:, 0]), np.interp(s + 1.0, a.cum, a.poly[:, 1])
    yaw = np.unwrap(np.arctan2(by - ay, bx - ax))
    j = np.clip(np.searchsorted(a.cum, s) - 1, 0, len(a.cum) - 2)
    seg = a.poly[j + 1] - a.poly[j]
    tangent = seg / np.maximum(np.linalg.norm(seg, axis=1, keepdims=True), 1e-9)
    return x, y, yaw, v * tangent[:, 0], v * tangent[:, 1], s
