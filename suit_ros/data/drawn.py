"""What the things drawn into recorded frames share (``overhead`` slabs, ``occluders`` screens):
the ground height where one stands, and fixed draws over the frames of evaluation drives."""
from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from suit_ros.structures import Frame


def ground_near(points: NDArray[np.floating[Any]], x: float, y: float,
                radius: float = 3.0, min_points: int = 20) -> float | None:
    """The ground height near ``(x, y)``: the 5th percentile of the heights of the points
    within ``radius``; None with fewer than ``min_points`` there."""
    near = points[np.hypot(points[:, 0] - x, points[:, 1] - y) < radius, 2]
    return float(np.percentile(near, 5)) if len(near) >= min_points else None


def windowed_drives(drives: list[list[Frame]],
                    draw: Callable[[list[Frame], np.random.Generator], list[Frame]],
                    seed: int = 0, window: int = 10) -> list[list[Frame]]:
    """Each drive with ``draw`` applied to every ``window`` frames in turn (one generator a
    drive, seeded by ``(seed, drive)``: the same drives give the same draws)."""
    out = []
    for d, frames in enumerate(drives):
        rng = np.random.default_rng([seed, d])
        seq: list[Frame] = []
        for a in range(0, len(frames), window):
            seq += draw(list(frames[a:a + window]), rng)
        out.append(seq)
    return out
