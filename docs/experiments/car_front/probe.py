#!/usr/bin/env python3
"""Can a car's own returns say which end is its front? A probe, no model: each labelled car's
current-sweep returns in its box frame, profiled along its length (per bin: the highest return
and the share of returns, over the box's height), and a logistic regression on the profile
less its mirror image (antisymmetric: turning the box round negates the answer, so no road,
side or traffic cue can enter). Trained on training-preset drives (jittered boxes, as a
detector's), scored on validation presets and, to diagnose only, on the real dev sweeps.

Usage: probe.py [AV2_ROOT]
"""
from __future__ import annotations

import glob
import sys
from typing import Any

import numpy as np

from suit_ros.data.sequences import load_sequence

BINS = 8
CAR = 0


def profile(points: np.ndarray, box: np.ndarray) -> np.ndarray | None:
    """(2 BINS + 2,) features of the returns in ``box`` in its frame (x along its heading)."""
    x, y, z, l, w, h, yaw = box
    c, s = np.cos(yaw), np.sin(yaw)
    d = points[:, :3] - np.array([x, y, z])
    u = d[:, 0] * c + d[:, 1] * s
    v = -d[:, 0] * s + d[:, 1] * c
    inside = (np.abs(u) < l / 2 + 0.2) & (np.abs(v) < w / 2 + 0.2) & (d[:, 2] > -h / 2 + 0.15) \
        & (d[:, 2] < h / 2 + 0.3)
    if inside.sum() < 10:
        return None
    u, hz = u[inside] / (l / 2), (d[inside, 2] + h / 2) / h
    b = np.clip(((u + 1) / 2 * BINS).astype(int), 0, BINS - 1)
    top = np.zeros(BINS)
    np.maximum.at(top, b, hz)
    share = np.bincount(b, minlength=BINS) / len(b)
    high = hz > 0.75 * hz.max()
    return np.concatenate([top, share, [u[high].mean(), u.mean()]])


def anti(f: np.ndarray) -> np.ndarray:
    """The profile less its mirror image (the box turned round)."""
    top, share, rest = f[:BINS], f[BINS:2 * BINS], f[2 * BINS:]
    return np.concatenate([top - top[::-1], share - share[::-1], 2 * rest])


def collect(paths: list[str], rng: np.random.Generator, jitter: bool, every: int = 4
            ) -> tuple[np.ndarray, np.ndarray]:
    X, meta = [], []
    for p in paths:
        for f in load_sequence(p)[::every]:
            g = f.gt
            pts = f.points[f.points[:, 4] < 0.01] if f.points.shape[1] > 4 else f.points
            for k in np.nonzero(g.labels == CAR)[0]:
                box = g.boxes[k].astype(np.float64).copy()
                r = np.hypot(box[0], box[1])
                if r > 50:
                    continue
                if jitter:
                    box[:2] += rng.normal(0, 0.15, 2)
                    box[3:6] *= rng.normal(1, 0.05, 3)
                    box[6] += rng.normal(0, 0.05)
                fp = profile(pts, box)
                if fp is None:
                    continue
                X.append(anti(fp))
                sp = np.hypot(*g.velocities[k]) if np.isfinite(g.velocities[k]).all() else 0.0
                meta.append((r, sp, fp.size))
    return np.array(X), np.array(meta)


def real_cars(frames: list[Any], max_range: float = 50.0) -> tuple[np.ndarray, np.ndarray]:
    """The antisymmetric profiles of a real dataset's labelled cars (the current sweep's
    returns) and their centres."""
    X, centres = [], []
    for f in frames:
        g = f.gt
        pts = f.points[f.points[:, 4] < 0.01] if f.points.shape[1] > 4 else f.points
        for k in np.nonzero(g.labels == CAR)[0]:
            if np.hypot(*g.boxes[k, :2]) > max_range:
                continue
            fp = profile(pts, g.boxes[k].astype(np.float64))
            if fp is not None:
                X.append(anti(fp))
                centres.append(g.boxes[k, :2])
    return np.array(X), np.array(centres)


def fit(X: np.ndarray, epochs: int = 300) -> np.ndarray:
    """Logistic regression without bias: y = 1 for each profile, 0 for it turned round."""
    A = np.concatenate([X, -X])
    y = np.concatenate([np.ones(len(X)), np.zeros(len(X))])
    w = np.zeros(A.shape[1])
    for _ in range(epochs):
        p = 1 / (1 + np.exp(-A @ w))
        grad = A.T @ (p - y) / len(y) + 1e-3 * w
        w -= 2.0 * grad
    return w


def report(name: str, X: np.ndarray, w: np.ndarray) -> None:
    z = X @ w
    p = 1 / (1 + np.exp(-z))
    conf = np.maximum(p, 1 - p)
    line = f'{name}: {len(z)} cars, right {np.mean(z > 0):.3f}'
    for c in (0.7, 0.8, 0.9, 0.95):
        sel = conf >= c
        line += f' | conf>={c}: {sel.mean():.2f} of cars, right {np.mean(z[sel] > 0):.3f}'
    print(line, flush=True)



def main() -> None:
    rng = np.random.default_rng(0)
    train = sorted(glob.glob('data_cache/train-street-ends-*.npz')
                   + glob.glob('data_cache/train-parked-either-*.npz'))
    Xtr, _ = collect(train, rng, jitter=True)
    w = fit(Xtr)
    print('weights', np.round(w, 2))
    report('train (jittered)', Xtr, w)
    for pre in ('val-real', 'val-street-ends', 'val-parked-rows'):
        Xv, mv = collect(sorted(glob.glob(f'data_cache/{pre}-*.npz')), rng, jitter=True)
        report(pre, Xv, w)
        near = mv[:, 0] < 25
        report(pre + ' within 25 m', Xv[near], w)
    if len(sys.argv) > 1:
        from suit_ros.data.av2 import av2_sequences
        X, centres = real_cars([f for seq in av2_sequences(sys.argv[1]) for f in seq])
        for x, c in zip(X, centres):
            print(f'  real car at {c[0]:6.1f} {c[1]:6.1f}: z {x @ w:+.2f}')
        report('real dev (labelled boxes)', X, w)

if __name__ == '__main__':
    main()
