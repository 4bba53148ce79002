#!/usr/bin/env python3
"""How far a dataset's car labels reach past the returns on the side the sensor sees.

For every labelled car seen from the side (45-90 degrees between the line of sight and its
axis) within 4-15 m with at least 100 returns in or near its box, prints how far inside the
labelled near side its nearest returns lie (5th percentile of the returns' distance across the
box, in metres: 0 when the label is tight on the visible side), and the median over the cars.
The detector places the box's near side where it learned a car's side lies against its returns;
a dataset whose labels sit farther out reads as boxes placed too far (``suit-ros report``'s
car placement). Measures only the labels and the points, not a model.

Usage: . scripts/env.sh && python scripts/label_margin.py --av2 ../shared/data/real-dev/av2
       python scripts/label_margin.py --preset val-ends-all --seeds 9000 9001 9002 9003
"""
from __future__ import annotations

import argparse
from collections.abc import Iterable
import sys
from typing import Any

import numpy as np
from numpy.typing import NDArray

from suit_ros.structures import Frame


def near_side_gap(points: NDArray[np.floating[Any]], box: NDArray[np.floating[Any]],
                  origin: NDArray[np.floating[Any]]) -> tuple[float, int]:
    """Metres between the labelled side facing ``origin`` and the nearest returns (5th
    percentile across the box), and the returns counted (within 0.5 m of the box's sides,
    0.15 m above its bottom up to 0.3 m above its top)."""
    x, y, z, l, w, h, yaw = (float(v) for v in box[:7])
    c, s = np.cos(yaw), np.sin(yaw)
    d = points[:, :2] - (x, y)
    along = d[:, 0] * c + d[:, 1] * s
    across = -d[:, 0] * s + d[:, 1] * c
    o = origin[:2] - (x, y)
    if -o[0] * s + o[1] * c > 0:                # the near side at -w/2
        across = -across
    up = points[:, 2] - (z - h / 2)
    m = (np.abs(along) < l / 2 + 0.3) & (np.abs(across) < w / 2 + 0.5) & (up > 0.15) \
        & (up < h + 0.3)
    if not m.any():
        return float('nan'), 0
    return float(np.percentile(across[m], 5) + w / 2), int(m.sum())


def side_view(box: NDArray[np.floating[Any]], origin: NDArray[np.floating[Any]]
              ) -> tuple[float, float]:
    """Range from ``origin`` and the angle (0-90 degrees) between the line of sight and the
    box's axis."""
    dx, dy = float(box[0] - origin[0]), float(box[1] - origin[1])
    a = abs(np.degrees(np.angle(np.exp(1j * (np.arctan2(dy, dx) - float(box[6]))))))
    return float(np.hypot(dx, dy)), min(a, 180.0 - a)


def frames_of(args: argparse.Namespace) -> Iterable[Frame]:
    if args.av2:
        from suit_ros.data.av2 import av2_sequences
        for seq in av2_sequences(args.av2):
            yield from (seq.frame(k) for k in range(len(seq)))
    else:
        from suit_ros.data.sim import preset, sim_frames
        for seed in args.seeds:
            yield from list(sim_frames(preset(args.preset, frames=args.frames), seed))[::4]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    src = parser.add_mutually_exclusive_group(required=True)
    src.add_argument('--av2', help='an Argoverse 2 dataset, split or log folder')
    src.add_argument('--preset', help='a synthetic world preset (suit_ros.data.sim.PRESETS)')
    parser.add_argument('--seeds', type=int, nargs='+', default=[9000, 9001, 9002, 9003])
    parser.add_argument('--frames', type=int, default=40)
    args = parser.parse_args()
    from suit_ros import CLASS_NAMES
    car = CLASS_NAMES.index('car')
    gaps = []
    for f in frames_of(args):
        g = f.gt
        if g is None:
            continue
        T = f.T_base_lidar
        origin = np.zeros(3) if T is None else T[:3, 3]
        for i in np.flatnonzero(g.labels == car):
            r, angle = side_view(g.boxes[i], origin)
            if not (4.0 <= r <= 15.0 and angle >= 45.0):
                continue
            gap, n = near_side_gap(f.points, g.boxes[i], origin)
            if n < 100:
                continue
            gaps.append(gap)
            print(f'car at {r:5.1f} m, {angle:3.0f} deg, {n:5d} returns, width '
                  f'{g.boxes[i][4]:.2f} m: nearest returns {gap:+.2f} m inside the label')
    if not gaps:
        print('no car seen from the side within 4-15 m with 100 returns', file=sys.stderr)
        return 1
    print(f'{len(gaps)} cars: median {np.median(gaps):+.2f} m inside the labelled near side '
          f'(range {min(gaps):+.2f} to {max(gaps):+.2f})')
    return 0


if __name__ == '__main__':
    sys.exit(main())
