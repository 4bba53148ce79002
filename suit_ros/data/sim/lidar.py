"""Ray casting of a spinning multi-beam LiDAR against the ground plane and oriented boxes.

Vectorised numpy: rays are the (beam, column) grid; each box is tested only against the columns
of the azimuth sector it covers as seen from the sensor (the slab method in the box's frame),
so the cost grows with the image area objects cover, not with rays x boxes.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from suit_ros.data.sim.config import LidarConfig

GROUND = -1
MISS = -2


@dataclass
class RangeImage:
    """Nearest hit per ray: range ``(B, C)`` (inf: none), surface id (box index, GROUND, MISS),
    and the cosine of the incidence angle."""

    rng: NDArray[np.float64]
    hit: NDArray[np.int64]
    cos: NDArray[np.float64]


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
         image: RangeImage) -> None:
    """Cast the rays of ``columns`` from a sensor at ``origin`` with rotation ``R`` (world).

    :param boxes: ``(N, 7)`` world boxes (yaw-only rotation); their index is the surface id.
    :param image: updated in place with nearer hits.
    """
    C = dirs.shape[1]
    cols = np.arange(C)[columns]
    d_world = dirs[:, columns] @ R.T                                         # (B, n, 3)
    # ground plane z = 0
    dz = d_world[..., 2]
    with np.errstate(divide='ignore', invalid='ignore'):
        tg = np.where(dz < -1e-6, -origin[2] / dz, np.inf)
    tg = np.where(tg <= max_range, tg, np.inf)
    sub_rng = image.rng[:, columns]
    sub_hit = image.hit[:, columns]
    sub_cos = image.cos[:, columns]
    better = tg < sub_rng
    sub_rng[better] = tg[better]
    sub_hit[better] = GROUND
    sub_cos[better] = np.abs(dz[better])
    if len(boxes):
        # azimuth interval of each box seen from the sensor, in sensor columns
        az0 = -np.pi + (cols[0] + 0.5) * (2 * np.pi / C)
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
        for i in range(len(boxes)):
            if inside[i]:
                continue                    # the sensor is inside this box: ignore it
            k0 = int(np.floor((lo[i] - az0) / res)) - 1
            k1 = int(np.ceil((hi[i] - az0) / res)) + 1
            span = np.arange(k0, k1 + 1) % C if k1 - k0 < C else np.arange(C)
            span = span[span < len(cols)]
            if len(span) == 0:
                continue
            _slab(d_world[:, span], origin, boxes[i], i, span, sub_rng, sub_hit, sub_cos)
    image.rng[:, columns] = sub_rng
    image.hit[:, columns] = sub_hit
    image.cos[:, columns] = sub_cos


def _slab(d: NDArray[np.float64], origin: NDArray[np.float64], box: NDArray[np.float64],
          box_id: int, span: NDArray[np.int64], rng: NDArray[np.float64],
          hit: NDArray[np.int64], cos: NDArray[np.float64]) -> None:
    """Ray vs one oriented box; nearer hits overwrite ``rng``/``hit``/``cos`` at ``span``."""
    c, s = np.cos(box[6]), np.sin(box[6])
    o = origin - box[:3]
    o_l = np.array([o[0] * c + o[1] * s, -o[0] * s + o[1] * c, o[2]])
    d_l = np.stack([d[..., 0] * c + d[..., 1] * s, -d[..., 0] * s + d[..., 1] * c, d[..., 2]],
                   -1)
    half = box[3:6] / 2
    with np.errstate(divide='ignore', invalid='ignore'):
        inv = 1.0 / d_l
        t1 = (-half - o_l) * inv
        t2 = (half - o_l) * inv
    tmin_axes = np.minimum(t1, t2)
    tnear = np.nanmax(tmin_axes, axis=-1)
    tfar = np.nanmin(np.maximum(t1, t2), axis=-1)
    ok = (tnear <= tfar) & (tnear > 0)
    current = rng[:, span]
    better = ok & (tnear < current)
    if not better.any():
        return
    axis = np.argmax(np.nan_to_num(tmin_axes, nan=-np.inf), axis=-1)
    cosine = np.abs(np.take_along_axis(d_l, axis[..., None], -1)[..., 0])
    rng[:, span] = np.where(better, tnear, current)
    hit[:, span] = np.where(better, box_id, hit[:, span])
    cos[:, span] = np.where(better, cosine, cos[:, span])
