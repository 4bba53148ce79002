"""Azimuth coverage of the clouds: a lost sector (a blocked sensor, a truck alongside, dropped
UDP packets) said in diagnostics, against the sensor's own running norm.

The azimuth about the sensor is cut into bins; a bin is *covered* in a cloud when it holds at
least ``min_points`` returns. Each bin keeps an exponential average of being covered; a bin
normally covered (average >= ``normal``) and empty now is missing. The largest run of missing
bins, if at least ``min_gap_deg`` wide, is reported as ``(start, end)`` degrees (counter-
clockwise from the sensor's +x, 0..360). A sensor that never sees some azimuths (a forward
LiDAR) has no norm there and raises nothing; after a long outage the norm forgets the lost
sector (the warning stops: the outage is the new normal).
"""
from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from suit_ros.ops.kernels import azimuth_counts


class SectorCoverage:
    """Running azimuth coverage; :meth:`update` per cloud returns the missing sector or None.

    :param bins: azimuth bins over 360 degrees.
    :param decay: weight of the newest cloud in the running average.
    :param warmup: clouds seen before anything is reported.
    """

    def __init__(self, bins: int = 72, decay: float = 0.05, normal: float = 0.8,
                 min_points: int = 3, min_gap_deg: float = 30.0, warmup: int = 5) -> None:
        if bins < 4 or not 0 < decay <= 1 or not 0 < normal <= 1:
            raise ValueError('SectorCoverage needs bins >= 4, 0 < decay <= 1, 0 < normal <= 1')
        self.bins = bins
        self.decay = decay
        self.normal = normal
        self.min_points = min_points
        self.min_gap_deg = min_gap_deg
        self.warmup = warmup
        self.reset()

    def reset(self) -> None:
        """Forget the norm (a new sensor or frame)."""
        self.average = np.zeros(self.bins)
        self.seen = 0

    def covered(self, xyz: NDArray[np.floating[Any]]) -> NDArray[np.bool_]:
        """Which bins hold at least ``min_points`` of these points (sensor frame)."""
        p = np.asarray(xyz)
        if len(p) == 0:
            return np.zeros(self.bins, bool)
        if p.dtype not in (np.float32, np.float64):
            p = p.astype(np.float64)
        # one compiled pass (a 260k-point cloud: 12 ms in numpy on the slow 2-core machine)
        return np.asarray(azimuth_counts(p, self.bins) >= self.min_points)

    def update(self, xyz: NDArray[np.floating[Any]]) -> tuple[float, float] | None:
        """Add a cloud; return its missing sector ``(start_deg, end_deg)`` or None."""
        now = self.covered(xyz)
        missing = (self.average >= self.normal) & ~now
        # the plain mean while the norm is young, an exponential average after
        self.average += max(self.decay, 1.0 / (self.seen + 1)) * (now - self.average)
        self.seen += 1
        if self.seen <= self.warmup or not missing.any():
            return None
        if missing.all():
            return (0.0, 360.0)
        # longest circular run of missing bins
        start = int(np.argmin(missing))          # a bin that is not missing: runs start after
        rolled = np.roll(missing, -start)
        best, best_at, run, at = 0, 0, 0, 0
        for i, m in enumerate(rolled):
            if m:
                if run == 0:
                    at = i
                run += 1
                if run > best:
                    best, best_at = run, at
            else:
                run = 0
        width = 360.0 / self.bins
        if best * width < self.min_gap_deg:
            return None
        first = (best_at + start) % self.bins
        return (first * width, (first * width + best * width) % 360.0 or 360.0)
