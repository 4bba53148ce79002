#!/usr/bin/env python3
"""Mean top profile (the highest return per eighth of the box over its height, the front at
the right) of cars within 35 m, by the side they are seen from: the real dev sweeps (to
diagnose only), the validation street world, and its drives with `real_car_roofs` (in the
commit that added this page; cached drives of `val-street-roofs` needed).

Usage: views.py AV2_ROOT
"""
from __future__ import annotations

from collections.abc import Iterable
import glob
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from probe import CAR, profile  # noqa: E402

from suit_ros.data.sequences import load_sequence  # noqa: E402
from suit_ros.structures import Frame  # noqa: E402


def view(box: np.ndarray) -> float:
    """Cosine between the car's heading and its direction to the sensor (+1: seen from the
    front)."""
    to_sensor = -box[:2] / np.linalg.norm(box[:2])
    return float(np.cos(box[6]) * to_sensor[0] + np.sin(box[6]) * to_sensor[1])


def gather(frames: Iterable[Frame], max_range: float = 35.0) -> dict[str, np.ndarray]:
    out: dict[str, list[np.ndarray]] = {'front': [], 'side': [], 'rear': []}
    for f in frames:
        g = f.gt
        assert g is not None
        pts = f.points[f.points[:, 4] < 0.01] if f.points.shape[1] > 4 else f.points
        for k in np.nonzero(g.labels == CAR)[0]:
            b = g.boxes[k].astype(np.float64)
            if np.hypot(*b[:2]) > max_range:
                continue
            fp = profile(pts, b)
            if fp is None:
                continue
            c = view(b)
            out['front' if c > 0.5 else 'rear' if c < -0.5 else 'side'].append(fp)
    return {k: np.array(v) for k, v in out.items()}


def show(name: str, d: dict[str, np.ndarray]) -> None:
    for k, F in d.items():
        if len(F):
            print(f'{name:28s} {k:5s} n={len(F):4d} top {F[:, :8].mean(0)} '
                  f'roof u {np.nanmean(F[:, 16]):+.2f}', flush=True)


def cached(pattern: str, every: int = 4) -> Iterable[Frame]:
    for p in sorted(glob.glob(pattern)):
        yield from load_sequence(p)[::every]


if __name__ == '__main__':
    from suit_ros.data.av2 import av2_sequences
    np.set_printoptions(precision=2, suppress=True, linewidth=160)
    show('real dev', gather(f for s in av2_sequences(sys.argv[1]) for f in s))
    show('val-street-ends', gather(cached('data_cache/val-street-ends-*-900[0-7]-40-*.npz')))
    show('val-street-roofs', gather(cached('data_cache/val-street-roofs-*-900[0-7]-40-*.npz')))
