"""Bodies of the detailed world: actors built from a few oriented boxes with a front and a back.

A :class:`Body` holds parts in the object's own frame (x forward, y left, z up from the ground,
centred on the object's footprint) with what a LiDAR sees of each: reflectivity, the probability
that a hit gives a return (glass, dark paint and tyres return less), and porosity (glass, wheels
with spokes, hedges pass some rays through). Walking legs and arms swing along x with the
distance travelled. Every part lies inside the object's extent ``l x w x h``, which stays its
GT box.

Vehicles: sedan, hatchback, SUV, van and pickup (hood in front, lower than the cabin; the cabin
a glass greenhouse under an opaque roof; a trunk step, a hatch or a cargo bed at the back;
wheels below the body; mirrors), trucks with a cab and a cargo box, buses with a window band and
seats behind it. Pedestrians: legs, torso, arms and head, sometimes a backpack, bag or suitcase.
Cyclists: a bicycle (spoked wheels, frame, handlebar) and a rider; motorcycles with a rider.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from suit_ros.data.sim.config import Realism

VEHICLE_KINDS = ('sedan', 'hatchback', 'suv', 'van', 'pickup')
VEHICLE_SHARE = (0.35, 0.2, 0.25, 0.1, 0.1)
# (length, width, height) ranges per kind (m), from typical catalogue dimensions
VEHICLE_SIZES = {'sedan': ((4.4, 5.0), (1.75, 1.9), (1.4, 1.5)),
                 'hatchback': ((3.7, 4.35), (1.7, 1.82), (1.45, 1.6)),
                 'suv': ((4.4, 5.0), (1.82, 2.0), (1.65, 1.85)),
                 'van': ((4.8, 5.5), (1.95, 2.1), (1.9, 2.4)),
                 'pickup': ((5.1, 5.9), (1.85, 2.05), (1.75, 1.95))}
TYRE = (0.05, 0.8, 0.0)                     # reflectivity, return probability, porosity


@dataclass
class Body:
    """Parts ``(P, 7)`` in the object frame and what a LiDAR sees of each ``(P,)``."""

    parts: NDArray[np.float64]
    reflectivity: NDArray[np.float64]
    return_prob: NDArray[np.float64]
    porosity: NDArray[np.float64]
    swing: NDArray[np.float64]              # amplitude of the walking swing along x (m)
    stride: float = 1.4                     # distance travelled per swing cycle (m)


class _Parts:
    """Collects axis-aligned parts given by their extents in the object frame."""

    def __init__(self) -> None:
        self.rows: list[list[float]] = []

    def add(self, x: tuple[float, float], y: tuple[float, float], z: tuple[float, float],
            look: tuple[float, float, float], swing: float = 0.0) -> None:
        """A part spanning ``x``, ``y``, ``z``; ``look`` is (reflectivity, return, porosity)."""
        self.rows.append([(x[0] + x[1]) / 2, (y[0] + y[1]) / 2, (z[0] + z[1]) / 2,
                          x[1] - x[0], y[1] - y[0], z[1] - z[0], 0.0, *look, swing])

    def body(self, stride: float = 1.4) -> Body:
        a = np.asarray(self.rows, np.float64)
        return Body(a[:, :7], a[:, 7], a[:, 8], a[:, 9], a[:, 10], stride)


def vehicle_kind(rng: np.random.Generator) -> tuple[str, NDArray[np.float64]]:
    """A passenger vehicle kind and its size ``(l, w, h)``."""
    kind = VEHICLE_KINDS[int(rng.choice(len(VEHICLE_KINDS), p=VEHICLE_SHARE))]
    size = np.array([rng.uniform(*r) for r in VEHICLE_SIZES[kind]])
    return kind, size


def paint(rng: np.random.Generator, realism: Realism) -> tuple[float, float, float]:
    """A car paint: dark (little light back, returns lost) or light."""
    if rng.random() < realism.dark_paint:
        return float(rng.uniform(0.05, 0.12)), float(rng.uniform(0.55, 0.75)), 0.0
    return float(rng.uniform(0.35, 0.9)), 0.97, 0.0


def glass(realism: Realism) -> tuple[float, float, float]:
    """Vehicle glass: dark, few returns, passes most rays."""
    return 0.05, realism.glass_return, realism.glass_porosity


BUMPER = (0.08, 0.5, 0.0)                   # black plastic: little light back
SEATS = (0.2, 0.8, 0.0)
DARK_ROOF = (0.05, 0.16, 0.0)               # a dark top: one hit in six returns
DIM_SEATS = (0.1, 0.3, 0.0)                 # seats behind tinted glass


# a raked screen's and back light's run along the car (m) where the roof is placed as on real
# cars (:attr:`Realism.real_car_roofs`): the roof starts near the middle and runs back
ROOF_RUNS = {'sedan': (0.95, 0.55), 'hatchback': (0.85, 0.0), 'suv': (0.75, 0.0),
             'pickup': (0.7, 0.0)}
TRUNK_DECK = 0.72                           # a sedan's trunk lid, of its height, on such cars
# the opaque rear pillars (C or D) along the greenhouse's sides on such cars (m)
PILLARS = {'sedan': 0.75, 'hatchback': 0.5, 'suv': 0.5, 'pickup': 0.15}
REAR_SET_BACK = 0.12                        # such a car's body behind the bumper (m)
GRAZING_GLASS = 0.15                        # a raked screen's returns, as a share of glass's


def car_body(kind: str, size: NDArray[np.float64], coat: tuple[float, float, float],
             realism: Realism, real_ends: bool = False, dark_top: bool = False,
             real_roof: bool = False) -> Body:
    """A passenger vehicle of ``kind`` (see :data:`VEHICLE_KINDS`) filling ``size``.

    :param real_ends: ends as real cars have them (:attr:`Realism.real_car_ends`): a bumper
        of dark plastic, narrower than the body (rounded corners), 0.1 m inside the box's
        ends; the painted body above it set back 0.35 m (at the back 0.12 m with
        ``real_roof``) and the cabin's glass another 0.3 m (a sloped screen); seats behind
        the glass. Real cars' returns start about 0.35 m
        inside their labelled ends, synthetic boxy ones at them (docs/experiments/box_fit).
    :param dark_top: seen only below the belt (:attr:`Realism.dark_tops`): tinted glass that
        sends nothing back (rays it passes reach dim seats), a roof that returns one hit in
        six, as real cars' sloped glass and roofs do at grazing incidence beyond 20 m.
    :param real_roof: the greenhouse placed as on real cars (:attr:`Realism.real_car_roofs`;
        vans keep their body): opaque rear pillars (:data:`PILLARS`), a tailgate up to the
        roof (a sedan's trunk lid at :data:`TRUNK_DECK` of its height), a windscreen raked
        over 0.7-0.95 m (:data:`ROOF_RUNS`) that returns little (grazing glass, up to half the
        greenhouse's height; a sedan's back light the same) and the roof from the screen's
        top edge back to the tailgate. With ``real_ends`` the body's back sits
        :data:`REAR_SET_BACK` inside the box, not 0.35 m; the hood and trunk, fractions of
        that longer body, move back 0.03-0.06 m and the rear axle 0.23 m. The seats stay where
        ``real_ends`` puts them, so the first 0.1-0.35 m of them show over the screen's top
        edge, as real seats show through a windscreen. Real cars on the dev sweeps, seen from
        the front: their highest returns over the last eighth of the box reach 0.76 of their
        height, over the first 0.47 (docs/experiments/car_front).
    """
    l, w, h = (float(v) for v in size)
    p = _Parts()
    if real_ends:
        wb0 = w / 2 - 0.09
        for end in (-1.0, 1.0):             # a label leaves ~0.1 m past the curved bumper
            p.add(_band(end * (l / 2 - 0.1), -end * 0.25), (-wb0 + 0.2, wb0 - 0.2),
                  (0.25, 0.7), BUMPER)
        l -= 0.7                            # the painted body between the bumpers
    front, rear = l / 2, -l / 2
    raked = real_roof and kind in ROOF_RUNS
    run, back = ROOF_RUNS[kind] if raked else (0.4, 0.0)    # (today's: the roof 0.4 m back)
    if raked and real_ends:                 # a compact back: the body near the bumper
        rear -= 0.35 - REAR_SET_BACK
        l = front - rear
    wb = w / 2 - 0.09                       # body half width; mirrors reach w / 2
    r = 0.3 if kind in ('sedan', 'hatchback') else 0.36
    low = 0.2 if kind in ('sedan', 'hatchback') else 0.3
    belt = {'sedan': 0.6, 'hatchback': 0.58, 'suv': 0.56, 'van': 0.5, 'pickup': 0.55}[kind] * h
    hood = {'sedan': 0.25, 'hatchback': 0.22, 'suv': 0.21, 'van': 0.13, 'pickup': 0.22}[kind] * l
    tail = {'sedan': 0.19, 'hatchback': 0.04, 'suv': 0.04, 'van': 0.0, 'pickup': 0.36}[kind] * l
    if raked and kind in ('hatchback', 'suv'):
        tail = 0.0                          # the tailgate at the back, up to the roof
    cab_front, cab_rear = front - hood, rear + tail
    p.add((front - 0.45, front), (-wb, wb), (low, belt - 0.12), coat)           # nose, lower
    p.add((cab_front, front - 0.45), (-wb, wb), (low, belt), coat)              # hood
    p.add((cab_rear, cab_front), (-wb, wb), (low, belt), coat)                  # doors
    if kind == 'pickup':                                                        # open bed
        p.add((rear, cab_rear), (-wb, wb), (low, low + 0.35), coat)
        for side in (-1.0, 1.0):
            p.add((rear, cab_rear), _band(side * wb, -side * 0.07), (low, belt + 0.05), coat)
        p.add((rear, rear + 0.07), (-wb, wb), (low, belt + 0.05), coat)         # tailgate
    elif tail > 0:                                                              # trunk step
        deck = TRUNK_DECK * h if raked else belt + 0.04
        p.add((rear, cab_rear), (-wb, wb), (low + 0.05, deck), coat)
    roof_top = h - 0.06
    pane = glass(realism)
    roof, seats = coat, SEATS
    if dark_top:
        pane, roof, seats = (pane[0], 0.0, pane[2]), DARK_ROOF, DIM_SEATS
    if kind == 'van':                       # glass up front, a closed cargo box behind
        split = cab_front - 0.35 * (cab_front - cab_rear)
        p.add((split, cab_front), (-wb + 0.05, wb - 0.05), (belt, roof_top), pane)
        p.add((cab_rear, split), (-wb, wb), (belt, roof_top), coat)
    elif raked:
        screen = (pane[0], pane[1] * GRAZING_GLASS, pane[2])
        mid = belt + 0.5 * (roof_top - belt)
        p.add((cab_front - run, cab_front), (-wb + 0.1, wb - 0.1), (belt, mid), screen)
        pillar = PILLARS[kind]
        p.add((cab_rear + pillar, cab_front - run), (-wb + 0.1, wb - 0.1), (belt, roof_top),
              pane)
        for side in (-1.0, 1.0):            # the rear pillars (a dark top's look)
            p.add((cab_rear, cab_rear + pillar), _band(side * wb, -side * 0.08),
                  (belt, roof_top), roof)
        if back > 0:                        # a sedan's raked back light over its trunk
            p.add((cab_rear, cab_rear + back), (-wb + 0.1, wb - 0.1), (belt, mid), screen)
        else:                               # a tailgate (a pickup's cab back) to the roof
            bottom = belt if kind == 'pickup' else low + 0.05
            if dark_top:                    # its window a dark top's
                p.add((cab_rear, cab_rear + 0.12), (-wb, wb), (bottom, belt), coat)
                bottom = belt
            p.add((cab_rear, cab_rear + 0.12), (-wb, wb), (bottom, roof_top), roof)
    else:
        slope = 0.3 if real_ends else 0.0
        p.add((cab_rear + slope, cab_front - slope), (-wb + 0.1, wb - 0.1), (belt, roof_top),
              pane)
    if real_ends:                           # seats, seen through the glass
        p.add((cab_rear + 0.5, cab_front - 0.6), (-wb + 0.25, wb - 0.25),
              (belt - 0.1, belt + 0.45), seats)
    inset = back + 0.02 if raked else 0.12 if kind in ('van', 'suv') else 0.3
    p.add((cab_rear + inset, cab_front - run), (-wb + 0.12, wb - 0.12), (roof_top, h), roof)
    for side in (-1.0, 1.0):                                                    # mirrors
        p.add((cab_front - 0.2, cab_front), _band(side * w / 2, -side * 0.09),
              (belt, belt + 0.14), coat)
    _wheels(p, l, wb, r, (front - 0.8, rear + 0.85))
    return p.body()


def heavy_body(size: NDArray[np.float64], coat: tuple[float, float, float],
               realism: Realism) -> Body:
    """A bus (11 m and longer: window band, seats behind it) or a truck (a cab and a cargo
    box on a chassis)."""
    l, w, h = (float(v) for v in size)
    p = _Parts()
    front, rear, half = l / 2, -l / 2, w / 2
    if l >= 10.4:
        p.add((rear, front), (-half, half), (0.35, 1.15), coat)
        p.add((rear + 0.15, front - 0.15), (-half, half), (1.15, h - 0.35), glass(realism))
        p.add((rear + 0.6, front - 1.8), (-half + 0.3, half - 0.3), (0.35, 1.6),
              (0.15, 0.9, 0.0))                                                 # seats
        p.add((front - 0.15, front), (-half, half), (1.15, h - 0.35), glass(realism))
        p.add((rear, rear + 0.15), (-half, half), (1.15, h - 0.35), coat)       # rear panel
        p.add((rear, front), (-half, half), (h - 0.35, h), coat)
        _wheels(p, l, half, 0.5, (front - 2.6, rear + 3.0))
        return p.body()
    cab = min(2.3, 0.3 * l)
    cab_h = min(h, 3.0)
    p.add((front - cab, front), (-half, half), (0.45, 0.6 * cab_h), coat)
    p.add((front - cab + 0.3, front), (-half + 0.05, half - 0.05), (0.6 * cab_h, cab_h - 0.3),
          glass(realism))
    p.add((front - cab, front - cab + 0.3), (-half, half), (0.6 * cab_h, cab_h), coat)
    p.add((front - cab, front), (-half, half), (cab_h - 0.3, cab_h), coat)
    cargo = (rear, front - cab - 0.3)
    p.add(cargo, (-half, half), (1.05, h), (0.5, 0.95, 0.0))                    # cargo box
    p.add((rear + 0.5, front - cab), (-half + 0.35, half - 0.35), (0.5, 1.05),
          (0.08, 0.9, 0.0))                                                     # chassis
    axles = (front - cab / 2, rear + 1.3) if l < 8 else (front - cab / 2, rear + 1.3, rear + 2.6)
    _wheels(p, l, half, 0.5, axles)
    return p.body()


def _band(edge: float, depth: float) -> tuple[float, float]:
    """The interval from ``edge`` reaching ``depth`` inwards (either sign)."""
    return (min(edge, edge + depth), max(edge, edge + depth))


def _wheels(p: _Parts, l: float, half_width: float, r: float, axles: tuple[float, ...]) -> None:
    """Two wheels per axle, ``r`` in radius, just inside the body's sides."""
    del l
    for x in axles:
        for side in (-1.0, 1.0):
            p.add((x - r, x + r), _band(side * half_width, -side * 0.24), (0.0, 2 * r), TYRE)


def pedestrian_body(size: NDArray[np.float64], rng: np.random.Generator,
                    moving: bool) -> Body:
    """Legs, torso, arms and head (walking legs and arms swing), sometimes a carried object."""
    l, w, h = (float(v) for v in size)
    p = _Parts()
    cloth = (float(rng.uniform(0.08, 0.5)), float(rng.uniform(0.85, 1.0)), 0.0)
    skin = (0.3, 0.95, 0.0)
    step = (l / 2 - 0.08) if moving else float(rng.uniform(0.0, 0.1))
    hip, shoulder = 0.5 * h, 0.82 * h
    torso = min(0.36, w - 0.22) / 2
    for side in (-1.0, 1.0):
        p.add((-0.065, 0.065), (side * 0.1 - 0.065, side * 0.1 + 0.065), (0.0, hip), cloth,
              side * step)
        y = side * (torso + 0.055)
        p.add((-0.045, 0.045), (y - 0.045, y + 0.045), (hip + 0.02, shoulder), cloth,
              -side * 0.6 * step)
    p.add((-0.11, 0.11), (-torso, torso), (hip, shoulder), cloth)
    p.add((-0.09, 0.1), (-0.08, 0.08), (0.86 * h, h), skin)
    carry = rng.random()
    if carry < 0.15 and l >= 0.5:                                               # backpack
        p.add((-min(0.26, l / 2), -0.11), (-torso + 0.03, torso - 0.03),
              (0.58 * h, 0.78 * h), (0.2, 0.95, 0.0))
    elif carry < 0.25:                                                          # bag at the side
        y = torso + 0.055
        p.add((-0.12, 0.12), (y - 0.05, min(y + 0.07, w / 2)), (0.3 * h, 0.45 * h),
              (0.15, 0.95, 0.0))
    elif carry < 0.3 and l >= 0.6:                                              # suitcase behind
        p.add((-l / 2, -l / 2 + 0.22), (-torso, torso - 0.1), (0.0, 0.62), (0.25, 0.95, 0.0))
    return p.body(stride=float(rng.uniform(1.2, 1.6)))


def bicycle_parts(p: _Parts, l: float, w: float) -> None:
    """A bicycle filling ``l`` along x: spoked wheels, frame, handlebar."""
    spokes = (0.2, 0.9, 0.55)
    r = min(0.34, l / 4)
    for x in (-l / 2 + r, l / 2 - r):
        p.add((x - r, x + r), (-0.025, 0.025), (0.0, 2 * r), spokes)
    p.add((-l / 2 + r, l / 2 - r), (-0.03, 0.03), (r + 0.05, r + 0.45), (0.4, 0.9, 0.5))
    bar = min(0.28, w / 2)
    p.add((l / 2 - r - 0.12, l / 2 - r), (-bar, bar), (0.95, 1.05), (0.4, 0.9, 0.0))


def cyclist_body(size: NDArray[np.float64], rng: np.random.Generator) -> Body:
    """A bicycle with its rider (pedalling legs, leaning torso, arms to the handlebar, head)."""
    l, w, h = (float(v) for v in size)
    p = _Parts()
    bicycle_parts(p, l, w)
    cloth = (float(rng.uniform(0.08, 0.5)), 0.95, 0.0)
    for side in (-1.0, 1.0):
        p.add((-0.12, 0.05), (side * 0.1 - 0.06, side * 0.1 + 0.06), (0.3, 0.95), cloth,
              side * 0.12)
        p.add((-0.05, l / 2 - 0.45), (side * 0.2 - 0.04, side * 0.2 + 0.04),
              (h - 0.6, h - 0.45), cloth)
    p.add((-0.3, 0.05), (-0.17, 0.17), (0.95, h - 0.3), cloth)
    p.add((-0.08, 0.12), (-0.09, 0.09), (h - 0.27, h), (0.3, 0.95, 0.0))
    return p.body(stride=1.6)


def motorcycle_body(size: NDArray[np.float64], coat: tuple[float, float, float],
                    rng: np.random.Generator) -> Body:
    """A motorcycle (wheels, engine, tank and seat, fairing) with its rider."""
    l, w, h = (float(v) for v in size)
    p = _Parts()
    r = 0.31
    for x in (-l / 2 + r, l / 2 - r):
        p.add((x - r, x + r), (-0.08, 0.08), (0.0, 2 * r), TYRE)
    p.add((-0.45, 0.45), (-0.22, 0.22), (0.3, 0.8), (0.3, 0.9, 0.0))            # engine
    p.add((-0.7, 0.35), (-0.17, 0.17), (0.8, 0.95), coat)                       # tank, seat
    p.add((0.35, 0.7), (-w / 2, w / 2), (0.8, 1.15), coat)                      # fairing
    cloth = (float(rng.uniform(0.05, 0.3)), 0.95, 0.0)
    p.add((-0.35, 0.1), (-0.22, 0.22), (0.5, 0.95), cloth)                      # legs
    p.add((-0.4, 0.0), (-0.2, 0.2), (0.95, h - 0.28), cloth)
    p.add((-0.22, 0.06), (-0.14, 0.14), (h - 0.28, h), (0.5, 0.95, 0.0))        # helmet
    return p.body(stride=1.6)


def parked_bicycle_body(rng: np.random.Generator) -> tuple[Body, NDArray[np.float64]]:
    """A bicycle without a rider, and its size."""
    size = np.array([rng.uniform(1.6, 1.85), rng.uniform(0.45, 0.6), rng.uniform(1.05, 1.15)])
    p = _Parts()
    bicycle_parts(p, float(size[0]), float(size[1]))
    return p.body(), size


def ego_body(size: NDArray[np.float64]) -> Body:
    """The ego vehicle itself, as the roof-mounted LiDAR sees it: hood, glass, roof, mirrors."""
    return car_body('sedan', size, (0.5, 0.97, 0.0), Realism(glass_porosity=0.0))
