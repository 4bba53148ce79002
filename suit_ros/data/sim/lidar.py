"""Ray casting of a spinning multi-beam LiDAR against the ground plane and oriented boxes.

Vectorised numpy: rays are the (beam, column) grid. Each box is tested only against the rays
that can reach it: the columns of the azimuth sector it covers as seen from the sensor and, for
a level sensor, the beams whose elevation meets its height band. All (ray, box) pairs are then
tested at once with the slab method in the box's frame and reduced to the nearest hit per ray,
so the cost grows with the image area objects cover, not with rays x boxes, and no Python loop
runs per box.

A box may be porous (hedges, glass, canopies): a ray passes through it when the ray's uniform
random number, shifted by the box index, falls below the box's porosity.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from suit_ros.data.sim.config import LidarConfig

GROUND = -1
MISS = -2
_GOLDEN = 0.6180339887498949            # decorrelates the pass-through draws of two boxes


@dataclass
class RangeImage:
    """Nearest hit per ray: range ``(B, C)`` (inf: none), surface id (box index, GROUND, MISS),
    and the cosine of the incidence angle."""

    rng: NDArray[np.float64]
    hit: NDArray[np.int64]
    cos: NDArray[np.float64]


@dataclass(frozen=True)
class Porosity:
    """Pass-through of porous boxes: per-box probability ``(N,)`` and per-ray uniform draws
    ``(B, n)`` for the rays being cast."""

    probability: NDArray[np.float64]
    ray_u: NDArray[np.float64]


def ray_directions(cfg: LidarConfig) -> NDArray[np.float64]:
    """Unit directions ``(B, C, 3)`` in the LiDAR frame; column ``c`` at azimuth
    ``-pi + (c + 0.5) * resolution``."""
    el = cfg.beam_elevations()
    C = cfg.columns
    az = -np.pi + (np.arange(C) + 0.5) * (2 * np.pi / C)
    ce, se = np.cos(el)[:, None], np.sin(el)[:, None]
    return np.stack([ce * np.cos(az)[None], ce * np.sin(az)[None],
                     np.broadcast_to(se, (len(el), C))], axis=-1)


def cast(dirs: NDArray[np.float64], origin: NDArray[np.float64], R: NDArray[np.float64],
         boxes: NDArray[np.float64], columns: slice, max_range: float,
         image: RangeImage, *, first_column: int = 0, sweep_columns: int | None = None,
         porosity: Porosity | None = None) -> None:
    """Cast the rays of ``columns`` from a sensor at ``origin`` with rotation ``R`` (world).

    :param dirs: ``(B, n, 3)`` ray directions in the LiDAR frame, ascending beam elevation.
    :param boxes: ``(N, 7)`` world boxes (yaw-only rotation); their index is the surface id.
    :param columns: which of ``dirs``' columns to cast (``image`` is indexed the same way).
    :param first_column: sweep column of ``dirs[:, 0]``; ``sweep_columns``: columns of the whole
        sweep (default: ``dirs`` is the whole sweep). Box sectors are found in sweep columns.
    :param porosity: pass-through of porous boxes (default: every box is opaque).
    :param image: updated in place with nearer hits.
    """
    n_all = dirs.shape[1]
    cols = np.arange(n_all)[columns]
    C = n_all if sweep_columns is None else sweep_columns
    d_world = dirs[:, cols] @ R.T                                            # (B, n, 3)
    sub_rng = image.rng[:, cols]
    sub_hit = image.hit[:, cols]
    sub_cos = image.cos[:, cols]
    _cast_ground(d_world, origin, max_range, sub_rng, sub_hit, sub_cos)
    if len(boxes):
        beams = _beam_bands(dirs, origin, R, boxes)
        spans = _column_spans(origin, R, boxes, first_column + int(cols[0]), C, len(cols))
        pairs = _ray_box_pairs(beams, spans, len(cols))
        if pairs is not None:
            _cast_pairs(d_world, origin, boxes, pairs, porosity, cols, sub_rng, sub_hit,
                        sub_cos)
    image.rng[:, cols] = sub_rng
    image.hit[:, cols] = sub_hit
    image.cos[:, cols] = sub_cos


def _cast_ground(d_world: NDArray[np.float64], origin: NDArray[np.float64], max_range: float,
                 rng: NDArray[np.float64], hit: NDArray[np.int64],
                 cos: NDArray[np.float64]) -> None:
    """The ground plane ``z = 0``: nearer hits within ``max_range`` overwrite the image."""
    dz = d_world[..., 2]
    with np.errstate(divide='ignore', invalid='ignore'):
        tg = np.where(dz < -1e-6, -origin[2] / dz, np.inf)
    tg = np.where(tg <= max_range, tg, np.inf)
    better = tg < rng
    rng[better] = tg[better]
    hit[better] = GROUND
    cos[better] = np.abs(dz[better])


def _beam_bands(dirs: NDArray[np.float64], origin: NDArray[np.float64], R: NDArray[np.float64],
                boxes: NDArray[np.float64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """First and last beam ``(N,)`` that can meet each box: for a level sensor the beams whose
    elevation lies within the box's height band seen over its horizontal distance; else all."""
    B = dirs.shape[0]
    N = len(boxes)
    if abs(R[2, 2] - 1.0) > 1e-12:
        return np.zeros(N, np.int64), np.full(N, B - 1, np.int64)
    el = np.arcsin(np.clip(dirs[:, 0, 2], -1.0, 1.0))
    dist = np.hypot(boxes[:, 0] - origin[0], boxes[:, 1] - origin[1])
    reach = 0.5 * np.hypot(boxes[:, 3], boxes[:, 4])
    near = np.maximum(dist - reach, 1e-3)
    far = dist + reach
    bottom = boxes[:, 2] - boxes[:, 5] / 2 - origin[2]
    top = boxes[:, 2] + boxes[:, 5] / 2 - origin[2]
    lo = np.minimum(np.arctan2(bottom, near), np.arctan2(bottom, far)) - 1e-3
    hi = np.maximum(np.arctan2(top, near), np.arctan2(top, far)) + 1e-3
    first = np.searchsorted(el, lo, side='left')
    last = np.searchsorted(el, hi, side='right') - 1
    return first.astype(np.int64), last.astype(np.int64)


def _column_spans(origin: NDArray[np.float64], R: NDArray[np.float64],
                  boxes: NDArray[np.float64], first_column: int, C: int, n: int
                  ) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    """Column segments each box covers within the ``n`` cast columns.

    :returns: ``(box, start, count)`` per segment (a sector that wraps past the cast window's
        end gives two), in cast-column indices; boxes around the sensor give none.
    """
    az0 = -np.pi + (first_column + 0.5) * (2 * np.pi / C)
    rel = boxes[:, :2] - origin[:2]
    c, s = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    hx, hy = boxes[:, 3] / 2, boxes[:, 4] / 2
    corners = np.stack([rel + np.stack([sx * hx * c - sy * hy * s, sx * hx * s + sy * hy * c],
                                       1) for sx, sy in ((1, 1), (1, -1), (-1, 1), (-1, -1))],
                       1)                                                   # (N, 4, 2)
    sensor_yaw = np.arctan2(R[1, 0], R[0, 0])
    ang = np.arctan2(corners[..., 1], corners[..., 0]) - sensor_yaw
    ref = np.arctan2(rel[:, 1], rel[:, 0]) - sensor_yaw
    spread = np.angle(np.exp(1j * (ang - ref[:, None])))                 # (N, 4)
    lo = ref + spread.min(1)
    hi = ref + spread.max(1)
    inside = (np.abs(rel[:, 0] * c + rel[:, 1] * s) < hx) & \
             (np.abs(-rel[:, 0] * s + rel[:, 1] * c) < hy)
    res = 2 * np.pi / C
    k0 = np.floor((lo - az0) / res).astype(np.int64) - 1
    k1 = np.ceil((hi - az0) / res).astype(np.int64) + 1
    whole = k1 - k0 >= C
    r0 = np.where(whole, 0, k0 % C)
    r1 = np.where(whole, C - 1, r0 + (k1 - k0))
    box = np.arange(len(boxes))
    seg_a = ~inside & (r0 < n)
    seg_b = ~inside & ~whole & (r1 >= C)
    start = np.concatenate([r0[seg_a], np.zeros(int(seg_b.sum()), np.int64)])
    stop = np.concatenate([np.minimum(r1[seg_a], n - 1), np.minimum(r1[seg_b] - C, n - 1)])
    return (np.concatenate([box[seg_a], box[seg_b]]), start, stop - start + 1)


def _ray_box_pairs(beams: tuple[NDArray[np.int64], NDArray[np.int64]],
                   spans: tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]],
                   n: int) -> tuple[NDArray[np.int64], NDArray[np.int64]] | None:
    """Every (ray, box) pair to test: flat ray index ``beam * n + column`` and box index."""
    box, start, count = spans
    first, last = beams[0][box], beams[1][box]
    nb = np.maximum(last - first + 1, 0)
    per = nb * count
    total = int(per.sum())
    if total == 0:
        return None
    seg = np.repeat(np.arange(len(box)), per)
    local = np.arange(total) - np.repeat(np.cumsum(per) - per, per)
    beam = first[seg] + local % nb[seg]
    col = start[seg] + local // nb[seg]
    return beam * n + col, box[seg]


def _cast_pairs(d_world: NDArray[np.float64], origin: NDArray[np.float64],
                boxes: NDArray[np.float64], pairs: tuple[NDArray[np.int64], NDArray[np.int64]],
                porosity: Porosity | None, cols: NDArray[np.int64], rng: NDArray[np.float64],
                hit: NDArray[np.int64], cos: NDArray[np.float64]) -> None:
    """Slab test of every pair; the nearest hit per ray (the lowest box index on a tie, the
    ground before any box) overwrites ``rng``/``hit``/``cos``."""
    ray, box = pairs
    flat_rng = rng.reshape(-1)
    n = rng.shape[1]
    d = d_world.reshape(-1, 3)[ray]
    c, s = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    o = origin - boxes[:, :3]
    o_l = np.stack([o[:, 0] * c + o[:, 1] * s, -o[:, 0] * s + o[:, 1] * c, o[:, 2]], -1)[box]
    cb, sb = c[box], s[box]
    d_l = np.stack([d[:, 0] * cb + d[:, 1] * sb, -d[:, 0] * sb + d[:, 1] * cb, d[:, 2]], -1)
    half = boxes[box, 3:6] / 2
    with np.errstate(divide='ignore', invalid='ignore'):
        inv = 1.0 / d_l
        t1 = (-half - o_l) * inv
        t2 = (half - o_l) * inv
    tmin_axes = np.minimum(t1, t2)
    tnear = np.fmax(np.fmax(tmin_axes[:, 0], tmin_axes[:, 1]), tmin_axes[:, 2])
    tmax_axes = np.maximum(t1, t2)
    tfar = np.fmin(np.fmin(tmax_axes[:, 0], tmax_axes[:, 1]), tmax_axes[:, 2])
    ok = (tnear <= tfar) & (tnear > 0) & (tnear < flat_rng[ray])
    if porosity is not None:
        u = porosity.ray_u[:, cols].reshape(-1)[ray] + box * _GOLDEN
        ok &= (u - np.floor(u)) >= porosity.probability[box]
    if not ok.any():
        return
    idx = np.nonzero(ok)[0]
    ray_ok, t_ok = ray[idx], tnear[idx]
    best = np.full(flat_rng.shape, np.inf)
    np.minimum.at(best, ray_ok, t_ok)
    tied = t_ok == best[ray_ok]
    first_box = np.full(flat_rng.shape, np.iinfo(np.int64).max)
    np.minimum.at(first_box, ray_ok[tied], box[idx][tied])
    win = idx[tied][box[idx][tied] == first_box[ray_ok[tied]]]
    axis = np.argmax(np.nan_to_num(tmin_axes[win], nan=-np.inf), axis=-1)
    cosine = np.abs(np.take_along_axis(d_l[win], axis[:, None], -1)[:, 0])
    b, k = np.divmod(ray[win], n)
    rng[b, k] = tnear[win]
    hit[b, k] = box[win]
    cos[b, k] = cosine
