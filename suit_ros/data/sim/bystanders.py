"""Pedestrians that stand where real ones do: beside street objects and parked cars.

Real pedestrians wait at the kerb by a signal post, pay at a parking meter, stand by a bus
shelter, a trash can or a column, or get out beside a parked car. In the world without this
every pedestrian walks or stands in the middle of the sidewalk, away from the street objects
that training teaches the detector to ignore, and a model trained on those objects scores the
pedestrians that stand beside them lower (the KITTI sample's pedestrian beside parked cars and
a post: 0.40 -> 0.27 once the street objects were in training; docs/experiments/street).

:attr:`~suit_ros.data.sim.config.Realism.bystanders` is the share of pedestrians, chosen by
their ids, that :func:`place_bystanders` moves to stand beside the nearest free anchor (a
street object or a parked vehicle) near where they would have started.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from suit_ros import CLASS_NAMES
from suit_ros.data.sim.actors import Actor, id_fraction
from suit_ros.data.sim.bodies import pedestrian_body
from suit_ros.data.sim.clutter import CLUTTER_ID, StaticScene
from suit_ros.data.sim.world import MATERIAL_IDS, World

# clutter a pedestrian stands beside (footprint boxes of the static scene)
ANCHOR_TYPES = ('pole', 'sign', 'bollard', 'bench', 'parked_bicycle', 'trash_can', 'hydrant',
                'parking_meter', 'utility_box', 'planter', 'lamp_post', 'column', 'shelter')
# clutter the spot must stay clear of: not flat curbs and verges (stood on), nor trees, whose
# footprint is their crown (stood under)
SOLID_TYPES = tuple(t for t in CLUTTER_ID
                    if t not in ('curb', 'verge', 'ego_body', 'tree', 'street_tree'))
REACH = 40.0          # m: how far from its own start a pedestrian looks for an anchor
CLEAR = 0.3           # m: the spot keeps this far off every other solid footprint


def chosen(instance_id: int, share: float) -> bool:
    """Whether a pedestrian is a bystander: drawn from its id (a hash apart from the one that
    shapes car ends), so the rest of the world keeps its draws."""
    return id_fraction(instance_id * 31 + 17) < share


def sidewalk_distance(xy: NDArray[np.float64], world: World) -> NDArray[np.float64]:
    """Distance ``(N,)`` of points ``(N, 2)`` from the nearest road axis (the roads run along
    the grid lines ``x = i * block`` and ``y = j * block``)."""
    off = np.abs(xy - np.round(xy / world.block) * world.block)
    return np.asarray(off.min(axis=1), np.float64)


def _inside(xy: NDArray[np.float64], boxes: NDArray[np.float64], pad: float
            ) -> NDArray[np.bool_]:
    """Whether a point ``(2,)`` lies in each oriented footprint ``(K, 7)`` grown by ``pad``."""
    d = xy[None, :] - boxes[:, :2]
    c, s = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    u = np.abs(c * d[:, 0] + s * d[:, 1])
    v = np.abs(-s * d[:, 0] + c * d[:, 1])
    return np.asarray((u <= boxes[:, 3] / 2 + pad) & (v <= boxes[:, 4] / 2 + pad))


def _spots(anchor: NDArray[np.float64], size: NDArray[np.float64],
           rng: np.random.Generator) -> list[NDArray[np.float64]]:
    """Candidate places beside an anchor footprint: off each end and each side, with a gap
    of 0.1-0.6 m between the anchor and the pedestrian's box, in random order."""
    x, y, _, length, width, _, yaw = anchor
    c, s = np.cos(yaw), np.sin(yaw)
    half = float(max(size[0], size[1])) / 2
    out = []
    for along, across in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        gap = float(rng.uniform(0.1, 0.6)) + half
        du = along * (length / 2 + gap)
        dv = across * (width / 2 + gap)
        out.append(np.array([x + c * du - s * dv, y + s * du + c * dv]))
    order = rng.permutation(len(out))
    return [out[i] for i in order]


def building_line(world: World) -> float:
    """Distance from a road axis at which the buildings start (1 m past the sidewalk)."""
    return world.road_half_width + world.sidewalk_width + 1.0


def _parked_and_blocked(actors: Sequence[Actor], scene: StaticScene
                        ) -> tuple[list[NDArray[np.float64]], NDArray[np.float64]]:
    """The parked vehicles' footprints, and every footprint a standing pedestrian must keep
    clear of: the solid clutter and those vehicles ``(K, 7)``."""
    solid = scene.objects[np.isin(scene.types, [CLUTTER_ID[t] for t in SOLID_TYPES])]
    parked = [np.array([a.poly[0, 0], a.poly[0, 1], a.size[2] / 2, *a.size, a.heading])
              for a in actors if len(a.poly) == 1 and CLASS_NAMES[a.label] in ('car', 'truck')]
    return parked, np.concatenate([solid, np.array(parked, np.float64).reshape(-1, 7)])


def place_bystanders(actors: Sequence[Actor], scene: StaticScene, world: World, share: float,
                     rng: np.random.Generator) -> list[int]:
    """Move ``share`` of the pedestrians (by id) to stand beside a street object or a parked
    vehicle near their start, on the sidewalk and clear of everything else; each gets a
    standing body drawn from ``rng``. :return: the indices of the actors moved."""
    if share <= 0:
        return []
    anchor_ids = np.array([CLUTTER_ID[t] for t in ANCHOR_TYPES])
    anchors = list(scene.objects[np.isin(scene.types, anchor_ids)])
    parked, blocked = _parked_and_blocked(actors, scene)
    anchors += parked
    if not anchors:
        return []
    boxes = np.array(anchors, np.float64).reshape(-1, 7)
    used = np.zeros(len(boxes), bool)
    stood: list[NDArray[np.float64]] = []
    lo = world.road_half_width + 0.2                  # off the road
    hi = building_line(world) - 0.1                   # 0.1 m short of the buildings
    moved = []
    for i, a in enumerate(actors):
        if CLASS_NAMES[a.label] != 'pedestrian' or not chosen(a.instance_id, share):
            continue
        start = np.array(a.state(0.0)[:2])
        dist = np.linalg.norm(boxes[:, :2] - start, axis=1)
        for k in np.argsort(dist):
            if dist[k] > REACH:
                break
            if used[k]:
                continue
            spot = next((p for p in _spots(boxes[k], a.size, rng)
                         if _free(p, a.size, boxes[k], blocked, stood, lo, hi, world)), None)
            if spot is None:
                continue
            used[k] = True
            stood.append(spot)
            _stand(a, spot, float(boxes[k, 6]), rng)
            moved.append(i)
            break
    return moved


def _free(p: NDArray[np.float64], size: NDArray[np.float64], anchor: NDArray[np.float64],
          blocked: NDArray[np.float64], stood: Sequence[NDArray[np.float64]], lo: float,
          hi: float, world: World) -> bool:
    """A spot on the sidewalk, off every solid footprint but its anchor's, and not on a
    pedestrian placed before."""
    half = float(max(size[0], size[1])) / 2
    d = float(sidewalk_distance(p[None, :], world)[0])
    if not lo + half <= d <= hi - half:
        return False
    others = blocked[np.any(np.abs(blocked - anchor) > 1e-9, axis=1)]
    if len(others) and _inside(p, others, half + CLEAR).any():
        return False
    return all(float(np.linalg.norm(p - q)) > 1.0 for q in stood)


def _stand(a: Actor, spot: NDArray[np.float64], anchor_yaw: float,
           rng: np.random.Generator, turned: bool = True) -> None:
    """Make ``a`` stand still at ``spot``, facing along or across the anchor (``turned``: a
    quarter turn and a little drawn from ``rng``; else ``anchor_yaw`` is the heading),
    standing limbs."""
    a.poly = spot.reshape(1, 2).astype(np.float64)
    a.cum = np.zeros(1)
    a.s = np.zeros_like(a.s)
    a.v = np.zeros_like(a.v)
    a.heading = (float(anchor_yaw + rng.integers(4) * np.pi / 2 + rng.normal(0.0, 0.3))
                 if turned else float(anchor_yaw))
    a.body = pedestrian_body(a.size, rng, moving=False)


# ------------------------------------------------------------------ close in front of buildings
FRONT_TYPES = ('building', 'wall')
FRONT_TRIES = 4       # places drawn along each face of a front before the next front is tried
FRONT_GAP = (0.1, 0.5)    # m between the front and the pedestrian's box
FRONT_DEPTH = 1.5     # m: the pedestrian's box ends within this of the building line (the
#                       walkers keep 1.5 m or more off it, so none walks through one standing)


def front_chosen(instance_id: int, share: float) -> bool:
    """Whether a pedestrian stands in front of a building (:attr:`Realism.at_fronts`): drawn
    from its id, a hash apart from the bystanders' and the car shapes'."""
    return id_fraction(instance_id * 37 + 11) < share


def fronts(scene: StaticScene, world: World) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """What pedestrians stand in front of: the layout's buildings and the pieces of the walls
    round walled lots (not their gates; not the low garden walls along the sidewalk, which
    are street furniture). :return: the faces ``(F, 7)`` and, per face, the footprint of the
    scene object it belongs to ``(F, 7)`` (the one solid thing a spot may touch)."""
    layout = world.boxes[np.isin(world.materials, [MATERIAL_IDS[t] for t in FRONT_TYPES])]
    faces: list[NDArray[np.float64]] = []
    owners: list[NDArray[np.float64]] = []
    for k in np.flatnonzero(np.isin(scene.types, [CLUTTER_ID[t] for t in FRONT_TYPES])):
        if not len(layout) or not np.any(np.all(np.abs(layout - scene.objects[k]) < 1e-9, 1)):
            continue
        pieces = scene.parts[scene.owner == k]
        faces += list(pieces)
        owners += [scene.objects[k]] * len(pieces)
    return (np.array(faces, np.float64).reshape(-1, 7),
            np.array(owners, np.float64).reshape(-1, 7))


def _reach(size: NDArray[np.float64], angle: float) -> tuple[float, float]:
    """A ``(length, width)`` box turned by ``angle`` from an axis: its half extent along the
    axis and across it."""
    c, s = abs(np.cos(angle)), abs(np.sin(angle))
    l, w = float(size[0]) / 2, float(size[1]) / 2
    return l * c + w * s, l * s + w * c


def _front_spots(face: NDArray[np.float64], size: NDArray[np.float64],
                 rng: np.random.Generator) -> list[tuple[NDArray[np.float64], float, float]]:
    """Candidate places in front of each side of a face: a heading (along or across the face,
    give or take), a random place along the side clear of its corners, the turned box
    0.1-0.5 m off it. :return: ``(spot, heading, the box's half extent off the face)``."""
    x, y, _, length, width, _, yaw = face
    out = []
    for normal, half_depth, half_side in ((0.0, length / 2, width / 2),
                                          (np.pi, length / 2, width / 2),
                                          (np.pi / 2, width / 2, length / 2),
                                          (-np.pi / 2, width / 2, length / 2)):
        n = float(yaw + normal)
        for _ in range(FRONT_TRIES):
            heading = float(yaw + rng.integers(4) * np.pi / 2 + rng.normal(0.0, 0.3))
            off, along = _reach(size, heading - n)
            extent = half_side - along - 0.2
            if extent <= 0:
                continue
            d = half_depth + float(rng.uniform(*FRONT_GAP)) + off
            t = float(rng.uniform(-extent, extent))
            spot = np.array([x + d * np.cos(n) - t * np.sin(n), y + d * np.sin(n) + t * np.cos(n)])
            out.append((spot, heading, off))
    order = rng.permutation(len(out))
    return [out[i] for i in order]


def _front_free(p: NDArray[np.float64], size: NDArray[np.float64], off: float,
                owner: NDArray[np.float64], blocked: NDArray[np.float64],
                stood: Sequence[NDArray[np.float64]], world: World) -> bool:
    """A place on the street side of the building line, the box within ``FRONT_DEPTH`` of it
    and off the road, clear of every solid footprint but its front's, and not on a pedestrian
    placed before."""
    line = building_line(world)
    d = float(sidewalk_distance(p[None, :], world)[0])
    if not (d <= line and d - off >= max(line - FRONT_DEPTH, world.road_half_width + 0.2)):
        return False
    half = float(max(size[0], size[1])) / 2
    others = blocked[np.any(np.abs(blocked - owner) > 1e-9, axis=1)]
    if len(others) and _inside(p, others, half + CLEAR).any():
        return False
    return all(float(np.linalg.norm(p - q)) > 1.0 for q in stood)


def place_at_fronts(actors: Sequence[Actor], scene: StaticScene, world: World, share: float,
                    rng: np.random.Generator, taken: Sequence[int] = ()) -> list[int]:
    """Move ``share`` of the pedestrians (by id; not the actors ``taken``, the bystanders) to
    stand still close in front of the nearest building or lot wall near their start that has
    a free place on the sidewalk (:func:`_front_free`); each gets a standing body drawn from
    ``rng``. :return: the indices of the actors moved."""
    if share <= 0:
        return []
    faces, owners = fronts(scene, world)
    if not len(faces):
        return []
    _, blocked = _parked_and_blocked(actors, scene)
    stood = [np.asarray(actors[i].poly[0], np.float64) for i in taken]
    moved = []
    for i, a in enumerate(actors):
        if (CLASS_NAMES[a.label] != 'pedestrian' or i in taken
                or not front_chosen(a.instance_id, share)):
            continue
        start = np.array(a.state(0.0)[:2])
        # the nearest faces by the distance from the start to their footprint
        d = start[None, :] - faces[:, :2]
        c, s = np.cos(faces[:, 6]), np.sin(faces[:, 6])
        u = np.maximum(np.abs(c * d[:, 0] + s * d[:, 1]) - faces[:, 3] / 2, 0)
        v = np.maximum(np.abs(-s * d[:, 0] + c * d[:, 1]) - faces[:, 4] / 2, 0)
        dist = np.hypot(u, v)
        for k in np.argsort(dist):
            if dist[k] > REACH:
                break
            spot = next(((p, h) for p, h, off in _front_spots(faces[k], a.size, rng)
                         if _front_free(p, a.size, off, owners[k], blocked, stood, world)),
                        None)
            if spot is None:
                continue
            stood.append(spot[0])
            _stand(a, spot[0], spot[1], rng, turned=False)
            moved.append(i)
            break
    return moved
