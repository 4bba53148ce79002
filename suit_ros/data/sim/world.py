"""A town tile from a seed: a grid of two-way roads, sidewalks, buildings, walls, poles, trees.

Everything static is an oriented box ``(x, y, z, l, w, h, yaw)`` with a material; the ground is
the plane ``z = 0`` of the odom (world) frame. Routes for the ego and the actors are polylines
over the road grid (right-hand traffic), with rounded corners at turns.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from suit_ros.data.sim.config import SimConfig

# material -> reflectivity (0..1); intensity scales it by the incidence angle
MATERIALS = {'ground': 0.12, 'building': 0.35, 'wall': 0.45, 'pole': 0.6, 'vegetation': 0.3,
             'car': 0.7, 'truck': 0.6, 'pedestrian': 0.25, 'cyclist': 0.4}
MATERIAL_IDS = {name: i for i, name in enumerate(MATERIALS)}
REFLECTIVITY = np.array(list(MATERIALS.values()), np.float64)


@dataclass
class World:
    """Static geometry of a town tile and its road grid."""

    boxes: NDArray[np.float64]        # (S, 7) static boxes
    materials: NDArray[np.int64]      # (S,) material id
    block: float
    grid_half: int
    road_half_width: float
    lane_width: float
    lanes: int
    sidewalk_width: float

    def node_xy(self, i: int, j: int) -> NDArray[np.float64]:
        """Centre of intersection ``(i, j)``."""
        return np.array([i * self.block, j * self.block], np.float64)


def build_world(cfg: SimConfig, rng: np.random.Generator) -> World:
    """Lay out roads, sidewalks (implicit: free space), buildings, walls, poles and vegetation."""
    block, n = cfg.block, cfg.grid_half
    road_half = cfg.lanes_per_direction * cfg.lane_width
    kerb = road_half + cfg.sidewalk_width          # from road centre to the building line
    boxes: list[list[float]] = []
    mats: list[int] = []

    def add(x: float, y: float, z: float, l: float, w: float, h: float, yaw: float,
            mat: str) -> None:
        boxes.append([x, y, z, l, w, h, yaw])
        mats.append(MATERIAL_IDS[mat])

    for i in range(-n - 1, n + 1):
        for j in range(-n - 1, n + 1):
            # the block between roads i..i+1 (x) and j..j+1 (y)
            x0, x1 = i * block + kerb + 1.0, (i + 1) * block - kerb - 1.0
            y0, y1 = j * block + kerb + 1.0, (j + 1) * block - kerb - 1.0
            if x1 - x0 < 6 or y1 - y0 < 6:
                continue
            kind = rng.random()
            if kind < 0.7:      # buildings along the block edges with gaps
                for side in range(4):
                    along = np.array([x0, x1]) if side < 2 else np.array([y0, y1])
                    pos = along[0]
                    while pos < along[1] - 4:
                        length = min(rng.uniform(8, 25), along[1] - pos)
                        depth = rng.uniform(6, 14)
                        height = rng.uniform(4, 20)
                        c = pos + length / 2
                        if side == 0:
                            add(c, y0 + depth / 2, height / 2, length, depth, height, 0,
                                'building')
                        elif side == 1:
                            add(c, y1 - depth / 2, height / 2, length, depth, height, 0,
                                'building')
                        elif side == 2:
                            add(x0 + depth / 2, c, height / 2, length, depth, height,
                                np.pi / 2, 'building')
                        else:
                            add(x1 - depth / 2, c, height / 2, length, depth, height,
                                np.pi / 2, 'building')
                        pos += length + rng.uniform(2, 10)
            elif kind < 0.85:   # a walled lot
                h = rng.uniform(1.0, 2.5)
                add((x0 + x1) / 2, y0, h / 2, x1 - x0, 0.3, h, 0, 'wall')
                add((x0 + x1) / 2, y1, h / 2, x1 - x0, 0.3, h, 0, 'wall')
                add(x0, (y0 + y1) / 2, h / 2, y1 - y0, 0.3, h, np.pi / 2, 'wall')
            else:               # a park: trees
                for _ in range(rng.integers(6, 16)):
                    tx, ty = rng.uniform(x0 + 2, x1 - 2), rng.uniform(y0 + 2, y1 - 2)
                    _tree(add, tx, ty, rng)
    # poles and trees along the sidewalks
    for axis in (0, 1):
        for k in range(-n, n + 1):
            for side in (-1, 1):
                offset = k * block + side * (road_half + cfg.sidewalk_width - 0.5)
                pos = -(n + 1) * block
                while pos < (n + 1) * block:
                    pos += rng.uniform(12, 30)
                    if abs(((pos + block / 2) % block) - block / 2) < kerb + 2:
                        continue                    # keep intersections clear
                    x, y = (pos, offset) if axis == 0 else (offset, pos)
                    if rng.random() < 0.6:
                        add(x, y, 3.0, 0.3, 0.3, 6.0, 0, 'pole')
                    else:
                        _tree(add, x, y, rng)
    return World(np.asarray(boxes, np.float64), np.asarray(mats, np.int64), block, n,
                 road_half, cfg.lane_width, cfg.lanes_per_direction, cfg.sidewalk_width)


def _tree(add: Callable[..., None], x: float, y: float, rng: np.random.Generator) -> None:
    trunk_h = rng.uniform(1.5, 3.0)
    add(x, y, trunk_h / 2, 0.4, 0.4, trunk_h, 0, 'vegetation')
    s = rng.uniform(2.0, 4.5)
    add(x, y, trunk_h + s / 2, s, s, s, rng.uniform(0, np.pi), 'vegetation')


# ---------------------------------------------------------------------- routes
DIRS = [(1, 0), (0, 1), (-1, 0), (0, -1)]


def random_route(world: World, rng: np.random.Generator, length: float,
                 start: tuple[int, int] | None = None, heading: int | None = None
                 ) -> list[tuple[int, int]]:
    """A random walk over intersections, at least ``length`` metres, never leaving the grid
    and never making a U-turn."""
    n = world.grid_half
    node = start if start is not None else (int(rng.integers(-n + 1, n)),
                                            int(rng.integers(-n + 1, n)))
    d = heading if heading is not None else int(rng.integers(4))
    nodes = [node]
    travelled = 0.0
    while travelled < length + world.block:
        options = [d, (d + 1) % 4, (d + 3) % 4]
        weights = np.array([0.6, 0.2, 0.2])
        ok = [abs(node[0] + DIRS[o][0]) <= n and abs(node[1] + DIRS[o][1]) <= n for o in options]
        if not any(ok):
            options, ok, weights = [(d + 2) % 4], [True], np.array([1.0])
        w = weights * np.array(ok, float)
        d = options[int(rng.choice(len(options), p=w / w.sum()))]
        node = (node[0] + DIRS[d][0], node[1] + DIRS[d][1])
        nodes.append(node)
        travelled += world.block
    return nodes


def route_polyline(world: World, nodes: list[tuple[int, int]], offset: float,
                   spacing: float = 0.5, corner_radius: float = 8.0) -> NDArray[np.float64]:
    """Dense polyline ``(K, 2)`` following the route ``offset`` metres right of the centre line,
    with corners rounded (a moving average over about ``corner_radius`` metres)."""
    centre = np.array([world.node_xy(*nd) for nd in nodes])
    seg = np.diff(centre, axis=0)
    normals = np.stack([seg[:, 1], -seg[:, 0]], 1) / np.linalg.norm(seg, axis=1, keepdims=True)
    pts: list[NDArray[np.float64]] = []
    for k in range(len(seg)):
        a = centre[k] + normals[k] * offset
        b = centre[k + 1] + normals[k] * offset
        m = max(2, int(np.linalg.norm(b - a) / spacing))
        pts.append(a + (b - a) * np.linspace(0, 1, m, endpoint=False)[:, None])
    poly = np.concatenate(pts + [(centre[-1] + normals[-1] * offset)[None]])
    win = max(1, int(corner_radius / spacing))
    kernel = np.ones(2 * win + 1) / (2 * win + 1)
    padded = np.concatenate([np.repeat(poly[:1], win, 0), poly, np.repeat(poly[-1:], win, 0)])
    smooth = np.stack([np.convolve(padded[:, i], kernel, mode='valid') for i in range(2)], 1)
    return smooth
