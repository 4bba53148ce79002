"""Street clutter of the detailed world, the negatives a detector must not fire on.

Every static thing is a clutter object of a type (:data:`CLUTTER_TYPES`) with a footprint box
and one or more part boxes: the box world's buildings, walls, poles and trees (walls get gaps,
tree canopies become porous), and street furniture along every road segment: curbs, grass
verges, hedges (porous), fences, low walls with gaps, guardrails, parked bicycles (not cyclists:
cyclists are ridden), benches, bollards, signs, traffic cones and barriers. The ego vehicle's
own body is clutter too.

:func:`clutter_false_positives` counts the detections that land on clutter, per type and frame.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from suit_ros.data.sim.bodies import Body, parked_bicycle_body
from suit_ros.data.sim.config import Realism, SimConfig
from suit_ros.data.sim.world import MATERIAL_IDS, REFLECTIVITY, World
from suit_ros.structures import Detections

CLUTTER_TYPES = ('building', 'wall', 'pole', 'tree', 'hedge', 'fence', 'guardrail',
                 'parked_bicycle', 'bench', 'bollard', 'sign', 'cone', 'barrier', 'curb',
                 'verge', 'ego_body', 'trash_can', 'hydrant', 'parking_meter', 'utility_box',
                 'planter', 'street_tree', 'lamp_post', 'column', 'shelter')
CLUTTER_ID = {name: i for i, name in enumerate(CLUTTER_TYPES)}
OPAQUE = 0.95                                # return probability of ordinary surfaces


@dataclass
class StaticScene:
    """Static part boxes ``(S, 7)`` with their look ``(S,)`` and owning clutter object
    ``(S,)``; clutter objects' footprint boxes ``(O, 7)`` and types ``(O,)``."""

    parts: NDArray[np.float64]
    reflectivity: NDArray[np.float64]
    return_prob: NDArray[np.float64]
    porosity: NDArray[np.float64]
    owner: NDArray[np.int64]
    objects: NDArray[np.float64]
    types: NDArray[np.int64]


class _Builder:
    """Collects clutter objects and their parts."""

    def __init__(self) -> None:
        self.parts: list[list[float]] = []
        self.objects: list[list[float]] = []
        self.types: list[int] = []

    def part(self, box: Sequence[float], refl: float, ret: float = OPAQUE,
             por: float = 0.0) -> None:
        """A part of the object being built (the last one opened)."""
        self.parts.append([*box, refl, ret, por, len(self.objects) - 1])

    def open(self, kind: str, box: Sequence[float]) -> None:
        """Start an object of ``kind`` with footprint ``box``."""
        self.objects.append(list(box))
        self.types.append(CLUTTER_ID[kind])

    def single(self, kind: str, box: Sequence[float], refl: float, ret: float = OPAQUE,
               por: float = 0.0) -> None:
        """An object that is one box."""
        self.open(kind, box)
        self.part(box, refl, ret, por)

    def body(self, kind: str, body: Body, size: NDArray[np.float64], x: float, y: float,
             yaw: float) -> None:
        """An object made from a :class:`Body` placed at ``x, y`` facing ``yaw``."""
        self.open(kind, [x, y, size[2] / 2, *size, yaw])
        c, s = np.cos(yaw), np.sin(yaw)
        for k, b in enumerate(body.parts):
            self.part([x + c * b[0] - s * b[1], y + s * b[0] + c * b[1], b[2], b[3], b[4], b[5],
                       yaw + b[6]], body.reflectivity[k], body.return_prob[k], body.porosity[k])

    def scene(self) -> StaticScene:
        a = np.asarray(self.parts, np.float64).reshape(-1, 11)
        return StaticScene(a[:, :7], a[:, 7], a[:, 8], a[:, 9], a[:, 10].astype(np.int64),
                           np.asarray(self.objects, np.float64).reshape(-1, 7),
                           np.asarray(self.types, np.int64))


def furnish(world: World, cfg: SimConfig, realism: Realism,
            rng: np.random.Generator) -> StaticScene:
    """The static scene: the world's boxes as clutter objects plus street furniture."""
    b = _Builder()
    _world_objects(b, world, realism, rng)
    if realism.clutter > 0:
        for segment in _road_segments(world, cfg):
            _furnish_segment(b, segment, world, cfg, realism, rng)
    return b.scene()


def _world_objects(b: _Builder, world: World, realism: Realism,
                   rng: np.random.Generator) -> None:
    """Buildings, walls (now with gaps), poles and trees (porous canopies) of the box world."""
    names = {v: k for k, v in MATERIAL_IDS.items()}
    boxes, mats = world.boxes, world.materials
    k = 0
    while k < len(boxes):
        box, name = boxes[k], names[int(mats[k])]
        refl = float(REFLECTIVITY[mats[k]])
        if name == 'vegetation':            # a trunk followed by its canopy
            canopy = boxes[k + 1]
            b.open('tree', [box[0], box[1], (canopy[2] + canopy[5] / 2) / 2, canopy[3],
                            canopy[4], canopy[2] + canopy[5] / 2, canopy[6]])
            b.part(box, refl)
            por = float(rng.uniform(*realism.hedge_porosity))
            b.part(canopy, refl, 0.9, por)
            k += 2
            continue
        if name == 'wall':
            _wall_with_gaps(b, box, refl, rng)
        else:
            b.single(name, box, refl)
        k += 1


def _wall_with_gaps(b: _Builder, box: NDArray[np.float64], refl: float,
                    rng: np.random.Generator) -> None:
    """A wall split into pieces 4-12 m long with gates 1-3 m wide between them."""
    b.open('wall', box.tolist())
    c, s = np.cos(box[6]), np.sin(box[6])
    pos = -box[3] / 2
    while pos < box[3] / 2 - 0.5:
        length = min(rng.uniform(4, 12), box[3] / 2 - pos)
        mid = pos + length / 2
        b.part([box[0] + c * mid, box[1] + s * mid, box[2], length, box[4], box[5], box[6]], refl)
        pos += length + rng.uniform(1, 3)


@dataclass(frozen=True)
class _Segment:
    """A stretch of road side between two intersections: from ``a`` to ``b`` along ``axis``
    at ``offset`` across, ``side`` +-1 (which side of the road centre)."""

    axis: int
    a: float
    b: float
    centre: float
    side: float


def _road_segments(world: World, cfg: SimConfig) -> list[_Segment]:
    """Both sides of every road between neighbouring intersections."""
    n, block = world.grid_half, world.block
    kerb = world.road_half_width + cfg.sidewalk_width
    out = []
    for axis in (0, 1):
        for k in range(-n, n + 1):
            for m in range(-n - 1, n + 1):
                for side in (-1.0, 1.0):
                    out.append(_Segment(axis, m * block + kerb + 2, (m + 1) * block - kerb - 2,
                                        k * block, side))
    return out


def _place(seg: _Segment, along: float, across: float) -> tuple[float, float, float]:
    """World ``x, y`` and yaw (along the road) of a point of the segment; ``across`` from the
    road centre, away from it."""
    off = seg.centre + seg.side * across
    if seg.axis == 0:
        return along, off, 0.0
    return off, along, np.pi / 2


def _furnish_segment(b: _Builder, seg: _Segment, world: World, cfg: SimConfig,
                     realism: Realism, rng: np.random.Generator) -> None:
    """Curbs on every segment; per segment a verge, a guardrail, road works and one lot edge
    (hedge, fence, low wall, or furniture: benches, bicycles, bollards, a sign)."""
    road = world.road_half_width
    kerb = road + cfg.sidewalk_width
    length = seg.b - seg.a
    mid = (seg.a + seg.b) / 2
    x, y, yaw = _place(seg, mid, road + 0.1)
    b.single('curb', [x, y, 0.075, length, 0.2, 0.15, yaw], 0.3)
    d = realism.clutter
    if rng.random() < 0.2 * d:
        x, y, yaw = _place(seg, mid, road + 0.7)
        b.single('verge', [x, y, 0.02, length, 1.0, 0.04, yaw], 0.45)
    if rng.random() < 0.1 * d:
        _guardrail(b, seg, road + 0.35, rng)
    if rng.random() < 0.1 * d:
        _road_works(b, seg, road + 0.35, rng)
    edge = rng.random()
    if edge < 0.18 * d:
        _hedge(b, seg, kerb + 0.5, realism, rng)
    elif edge < 0.32 * d:
        _fence(b, seg, kerb + 0.5, rng)
    elif edge < 0.42 * d:
        wall = rng.uniform(0.5, 1.2)
        x, y, yaw = _place(seg, mid, kerb + 0.5)
        _wall_with_gaps(b, np.array([x, y, wall / 2, length, 0.25, wall, yaw]), 0.45, rng)
    elif edge < 0.75 * d:
        _furniture(b, seg, kerb, rng)
    if realism.street_objects > 0:
        _street_objects(b, seg, kerb, road, realism.street_objects, rng)


def _guardrail(b: _Builder, seg: _Segment, across: float, rng: np.random.Generator) -> None:
    """A steel rail at 0.5-0.8 m on posts every 2 m."""
    a = seg.a + rng.uniform(0, 10)
    z = seg.b - rng.uniform(0, 10)
    x, y, yaw = _place(seg, (a + z) / 2, across)
    b.open('guardrail', [x, y, 0.4, z - a, 0.3, 0.8, yaw])
    b.part([x, y, 0.65, z - a, 0.1, 0.3, yaw], 0.6)
    for pos in np.arange(a + 0.1, z, 2.0):
        x, y, yaw = _place(seg, float(pos), across + 0.1)
        b.part([x, y, 0.375, 0.12, 0.12, 0.75, yaw], 0.5)


def _road_works(b: _Builder, seg: _Segment, across: float, rng: np.random.Generator) -> None:
    """A row of traffic cones or a few barriers at the curb."""
    start = rng.uniform(seg.a, seg.b - 10)
    if rng.random() < 0.5:
        for k in range(int(rng.integers(3, 8))):
            x, y, yaw = _place(seg, start + 1.5 * k, across)
            b.open('cone', [x, y, 0.35, 0.36, 0.36, 0.7, yaw])
            b.part([x, y, 0.02, 0.36, 0.36, 0.04, yaw], 0.3)
            b.part([x, y, 0.2, 0.24, 0.24, 0.32, yaw], 0.8)
            b.part([x, y, 0.53, 0.12, 0.12, 0.34, yaw], 0.8)
        return
    for k in range(int(rng.integers(1, 4))):
        x, y, yaw = _place(seg, start + 1.4 * k, across)
        b.open('barrier', [x, y, 0.5, 1.2, 0.35, 1.0, yaw])
        b.part([x, y, 0.85, 1.2, 0.05, 0.25, yaw], 0.85)
        b.part([x, y, 0.45, 1.2, 0.05, 0.2, yaw], 0.85)
        for end in (-0.55, 0.55):
            x2, y2, _ = _place(seg, start + 1.4 * k + end, across)
            b.part([x2, y2, 0.35, 0.06, 0.35, 0.7, yaw], 0.4)


def _hedge(b: _Builder, seg: _Segment, across: float, realism: Realism,
           rng: np.random.Generator) -> None:
    """Porous hedges 3-15 m long with gaps, 0.6-1.8 m high."""
    pos = seg.a
    while pos < seg.b - 2:
        length = min(rng.uniform(3, 15), seg.b - pos)
        h, depth = rng.uniform(0.6, 1.8), rng.uniform(0.6, 1.0)
        x, y, yaw = _place(seg, pos + length / 2, across)
        b.single('hedge', [x, y, h / 2, length, depth, h, yaw], 0.3, 0.9,
                 float(rng.uniform(*realism.hedge_porosity)))
        pos += length + rng.uniform(0.5, 4)


def _fence(b: _Builder, seg: _Segment, across: float, rng: np.random.Generator) -> None:
    """A mesh fence (a panel that passes most rays) on posts every 2.5 m."""
    h = rng.uniform(1.0, 2.0)
    x, y, yaw = _place(seg, (seg.a + seg.b) / 2, across)
    b.open('fence', [x, y, h / 2, seg.b - seg.a, 0.1, h, yaw])
    b.part([x, y, h / 2, seg.b - seg.a, 0.03, h, yaw], 0.5, 0.9, float(rng.uniform(0.6, 0.85)))
    for pos in np.arange(seg.a, seg.b, 2.5):
        x, y, yaw = _place(seg, float(pos), across)
        b.part([x, y, h / 2, 0.08, 0.08, h, yaw], 0.5)


def _furniture(b: _Builder, seg: _Segment, kerb: float, rng: np.random.Generator) -> None:
    """Along the lot edge: benches, a row of parked bicycles, bollards and a sign."""
    pos = seg.a + rng.uniform(0, 5)
    while pos < seg.b - 3:
        kind = rng.random()
        if kind < 0.3:                      # a bench facing the road
            x, y, yaw = _place(seg, pos + 0.9, kerb + 0.5)
            b.open('bench', [x, y, 0.45, 1.8, 0.6, 0.9, yaw])
            b.part([x, y, 0.44, 1.8, 0.45, 0.06, yaw], 0.35)
            x2, y2, _ = _place(seg, pos + 0.9, kerb + 0.72)
            b.part([x2, y2, 0.7, 1.8, 0.06, 0.4, yaw], 0.35)
            for end in (-0.8, 0.8):
                x3, y3, _ = _place(seg, pos + 0.9 + end, kerb + 0.5)
                b.part([x3, y3, 0.21, 0.08, 0.45, 0.42, yaw], 0.5)
            pos += 1.8
        elif kind < 0.55:                   # bicycles side by side, across the strip
            for k in range(int(rng.integers(2, 8))):
                body, size = parked_bicycle_body(rng)
                x, y, yaw = _place(seg, pos + 0.7 * k, kerb + 0.1)
                b.body('parked_bicycle', body, size, x, y, yaw + np.pi / 2 + rng.normal(0, 0.1))
                pos += 0.7
        elif kind < 0.8:                    # bollards
            for _ in range(int(rng.integers(3, 8))):
                x, y, yaw = _place(seg, pos, kerb - 0.3)
                b.single('bollard', [x, y, 0.45, 0.18, 0.18, 0.9, yaw], 0.6)
                pos += 1.5
        else:                               # a sign: a post and a plate
            h = rng.uniform(2.2, 3.0)
            x, y, yaw = _place(seg, pos, kerb + 0.3)
            b.open('sign', [x, y, h / 2 + 0.2, 0.7, 0.1, h + 0.4, yaw])
            b.part([x, y, h / 2, 0.08, 0.08, h, yaw], 0.5)
            b.part([x, y, h, 0.7, 0.04, 0.7, yaw + np.pi / 2], 0.95)
        pos += rng.uniform(3, 12)


def _street_objects(b: _Builder, seg: _Segment, kerb: float, road: float, density: float,
                    rng: np.random.Generator) -> None:
    """Pedestrian-sized things along a sidewalk (about one per 8 m at density 1), at the
    kerb or against the building line: what real sweeps hold and a detector trained on a
    cleaner world takes for pedestrians."""
    pos = seg.a + rng.uniform(0, 8 / density)
    while pos < seg.b - 2:
        kind = rng.random()
        near_kerb = road + rng.uniform(0.4, 0.9)
        at_wall = kerb + rng.uniform(0.6, 1.0)
        if kind < 0.16:                                   # trash can, sometimes a pair
            for k in range(1 + int(rng.random() < 0.3)):
                w = rng.uniform(0.45, 0.7)
                x, y, yaw = _place(seg, pos + 0.75 * k, near_kerb if rng.random() < 0.6
                                   else at_wall)
                hgt = rng.uniform(0.8, 1.2)
                b.single('trash_can', [x, y, hgt / 2, w, w, hgt, yaw + rng.uniform(0, 1.6)],
                         rng.uniform(0.15, 0.6))
        elif kind < 0.26:                                 # hydrant: body and nozzles
            x, y, yaw = _place(seg, pos, near_kerb)
            b.open('hydrant', [x, y, 0.4, 0.45, 0.45, 0.8, yaw])
            b.part([x, y, 0.35, 0.26, 0.26, 0.7, yaw], 0.55)
            b.part([x, y, 0.5, 0.45, 0.12, 0.12, yaw], 0.55)
            b.part([x, y, 0.75, 0.18, 0.18, 0.1, yaw], 0.55)
        elif kind < 0.38:                                 # parking meter(s): post and head
            for k in range(int(rng.integers(1, 4))):
                x, y, yaw = _place(seg, pos + 6.0 * k, road + 0.45)
                b.open('parking_meter', [x, y, 0.75, 0.3, 0.25, 1.5, yaw])
                b.part([x, y, 0.6, 0.09, 0.09, 1.2, yaw], 0.5)
                b.part([x, y, 1.35, 0.28, 0.22, 0.4, yaw], 0.7)
            pos += 12.0
        elif kind < 0.48:                                 # utility / electrical box
            x, y, yaw = _place(seg, pos, at_wall if rng.random() < 0.5 else near_kerb)
            ln, wd, hgt = rng.uniform(0.5, 1.3), rng.uniform(0.35, 0.7), rng.uniform(0.9, 1.6)
            b.single('utility_box', [x, y, hgt / 2, ln, wd, hgt, yaw], rng.uniform(0.3, 0.7))
        elif kind < 0.56:                                 # planter with a porous bush
            x, y, yaw = _place(seg, pos, near_kerb if rng.random() < 0.5 else at_wall)
            w, hgt = rng.uniform(0.7, 1.4), rng.uniform(0.4, 0.8)
            bush = rng.uniform(0.5, 1.2)
            b.open('planter', [x, y, (hgt + bush) / 2, w, w, hgt + bush, yaw])
            b.part([x, y, hgt / 2, w, w, hgt, yaw], 0.35)
            b.part([x, y, hgt + bush / 2, 0.9 * w, 0.9 * w, bush, yaw], 0.4, 0.9,
                   float(rng.uniform(0.3, 0.6)))
        elif kind < 0.70:                                 # street tree: slim trunk, high crown
            x, y, yaw = _place(seg, pos, near_kerb)
            d, crown_z = rng.uniform(0.12, 0.6), rng.uniform(2.2, 3.5)
            crown = rng.uniform(2.0, 5.0)
            b.open('street_tree', [x, y, (crown_z + crown) / 2, crown, crown, crown_z + crown,
                                   yaw])
            b.part([x, y, crown_z / 2 + 0.2, d, d, crown_z + 0.4, yaw], 0.3)
            if rng.random() < 0.4:                        # a tree guard round the trunk
                b.part([x, y, 0.6, d + 0.5, d + 0.5, 1.2, yaw], 0.5, 0.9, 0.7)
            b.part([x, y, crown_z + crown / 2, crown, crown, crown, yaw], 0.4, 0.9,
                   float(rng.uniform(0.25, 0.6)))
        elif kind < 0.80:                                 # lamp or signal post with an arm
            x, y, yaw = _place(seg, pos, near_kerb)
            d, hgt = rng.uniform(0.15, 0.4), rng.uniform(4.0, 8.0)
            b.open('lamp_post', [x, y, hgt / 2, d, d, hgt, yaw])
            b.part([x, y, hgt / 2, d, d, hgt, yaw], 0.5)
            if rng.random() < 0.5:                        # a control box on the post
                b.part([x, y, 1.3, d + 0.25, d + 0.25, 0.6, yaw], 0.55)
            ax, ay, _ = _place(seg, pos, near_kerb - 1.5)
            b.part([ax, ay, hgt - 0.2, 0.12, 3.0, 0.12, yaw], 0.5)
        elif kind < 0.93:                                 # facade columns / pilasters
            pos += _columns(b, seg, pos, kerb, rng)
        else:                                             # bus shelter: posts, roof, glass
            pos += _shelter(b, seg, pos, kerb)
        pos += rng.uniform(2.0, 14.0) / density


def _columns(b: _Builder, seg: _Segment, pos: float, kerb: float,
             rng: np.random.Generator) -> float:
    """2-5 columns against the building line; :return: the length used."""
    for k in range(int(rng.integers(2, 6))):
        x, y, yaw = _place(seg, pos + 3.5 * k, kerb + 0.9)
        w = rng.uniform(0.35, 0.8)
        hgt = rng.uniform(2.5, 6.0)
        b.single('column', [x, y, hgt / 2, w, rng.uniform(0.3, 0.6), hgt, yaw],
                 rng.uniform(0.2, 0.6))
    return 14.0


def _shelter(b: _Builder, seg: _Segment, pos: float, kerb: float) -> float:
    """A bus shelter: two posts, a roof and a glass back wall; :return: the length used."""
    x, y, yaw = _place(seg, pos + 2.0, kerb - 0.8)
    b.open('shelter', [x, y, 1.25, 4.0, 1.5, 2.5, yaw])
    for end in (-1.9, 1.9):
        px, py, _ = _place(seg, pos + 2.0 + end, kerb - 0.8)
        b.part([px, py, 1.15, 0.1, 0.1, 2.3, yaw], 0.5)
    b.part([x, y, 2.4, 4.0, 1.5, 0.1, yaw], 0.5)
    gx, gy, _ = _place(seg, pos + 2.0, kerb - 0.1)
    b.part([gx, gy, 1.2, 3.8, 0.05, 1.8, yaw], 0.3, 0.4, 0.6)
    return 4.0


# ------------------------------------------------------------------ false positives on clutter
class ClutterFrame(Protocol):
    """What :func:`clutter_false_positives` reads of a frame (a ``SimFrame`` has it)."""

    clutter_boxes: NDArray[np.float64]      # (K, 7) footprints, LiDAR frame
    clutter_types: NDArray[np.int64]        # (K,) ids into CLUTTER_TYPES
    gt: Detections


def clutter_false_positives(frames: Sequence[ClutterFrame], detections: Sequence[Detections],
                            match_radius: float = 2.0, margin: float = 0.5
                            ) -> NDArray[np.int64]:
    """False-positive detections on clutter, per frame and clutter type.

    A detection counts against a clutter type when its centre lies within ``margin`` metres of
    an object's footprint (BEV) and no GT box centre of the frame lies within
    ``match_radius`` metres of it. A detection near several objects counts once, for the one
    whose footprint it is nearest to.

    :param frames: the frames (clutter footprints, types and GT, LiDAR frame).
    :param detections: per frame the detections (any class), in the same frame.
    :returns: ``(F, len(CLUTTER_TYPES))`` counts; column ``j`` is ``CLUTTER_TYPES[j]``.
    """
    if len(frames) != len(detections):
        raise ValueError(f'clutter_false_positives needs one detection set per frame; got '
                         f'{len(frames)} frames and {len(detections)} detection sets')
    out = np.zeros((len(frames), len(CLUTTER_TYPES)), np.int64)
    for f, (frame, dets) in enumerate(zip(frames, detections)):
        centres = np.asarray(dets.boxes, np.float64).reshape(-1, 7)[:, :2]
        boxes = np.asarray(frame.clutter_boxes, np.float64).reshape(-1, 7)
        gt = np.asarray(frame.gt.boxes, np.float64).reshape(-1, 7)[:, :2]
        if len(gt) and len(centres):
            near_gt = np.hypot(*(centres[:, None] - gt[None]).transpose(2, 0, 1)).min(1)
            centres = centres[near_gt > match_radius]
        if len(centres) == 0 or len(boxes) == 0:
            continue
        gap = footprint_distance(centres, boxes)                          # (D, K)
        on = gap.min(1) <= margin
        types = np.asarray(frame.clutter_types, np.int64)[gap[on].argmin(1)]
        out[f] = np.bincount(types, minlength=len(CLUTTER_TYPES))
    return out


def footprint_distance(xy: NDArray[np.float64], boxes: NDArray[np.float64]
                       ) -> NDArray[np.float64]:
    """BEV distance ``(N, K)`` from points ``(N, 2)`` to box footprints ``(K, 7)`` (0 inside)."""
    d = xy[:, None, :] - boxes[None, :, :2]
    c, s = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    along = np.abs(d[..., 0] * c + d[..., 1] * s) - boxes[:, 3] / 2
    across = np.abs(-d[..., 0] * s + d[..., 1] * c) - boxes[:, 4] / 2
    out: NDArray[np.float64] = np.hypot(np.clip(along, 0, None), np.clip(across, 0, None))
    return out


def clutter_frames(drives: Sequence[tuple[int, str]], frames: int) -> list[Any]:
    """The validation drives rendered again, for their clutter footprints and types."""
    from suit_ros.data.sim import preset
    from suit_ros.data.sim.scene import Simulation
    out = []
    for seed, sensor in drives:
        sim = Simulation(preset('val-real', sensor=sensor, frames=frames), seed)
        out += [sim.render(k) for k in range(frames)]
    return out


def clutter_fp(runs: Mapping[str, Any], sim_frames: Sequence[Any], min_score: float
               ) -> dict[str, dict[str, float]]:
    """False positives per frame on clutter objects, per clutter type and in all, of each
    run's detections with ``score >= min_score``."""
    out = {}
    for name, run in runs.items():
        c = clutter_false_positives(sim_frames, [d.select(d.scores >= min_score)
                                                 for d in run.det])
        out[name] = {t: float(c[:, j].mean()) for j, t in enumerate(CLUTTER_TYPES)}
        out[name]['all'] = float(c.sum(1).mean())
    return out
