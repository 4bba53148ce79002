"""Returns that hang over a street: canopies, awnings, signal arms, shelter roofs.

The pillar encoder pools every return of a 0.4 m column into one feature: a pedestrian under a
tree canopy or an awning shares its columns with hundreds of returns 2-4 m up, and the
features it was learned by are gone. On the Argoverse 2 dev sweeps three of the four
pedestrians within 50 m stand under such structures; removing the returns above them lifts
one heatmap peak from 0.10 to 0.42, and a synthetic pedestrian that scores 0.46-0.58 drops to
0.05-0.22 under one real pedestrian's canopy (docs/experiments/overhead). The synthetic world
the model learned from has nothing over its sidewalks.

``overhang: drop`` removes, before the model, the returns that float: per column of the
model's pillar grid, its returns are split into stacks wherever ``gap`` (0.5 m) of height has
none (or, with ``gap_per_m``, ``gap_per_m`` times the column's range where that is more: a
sensor's rings spread apart with range, 1 m at 30 m for 2-degree rings), and the returns of
a stack that starts ``height`` (2.0 m) or more above base_link's ground plane are dropped:
higher than a pedestrian, a cyclist or a car reaches, so nothing the model detects starts
there. What stands on the ground keeps every return (a wall, a
pole, a truck's side, a trailer over its open underside: stacks that start low); what hangs
goes (a canopy or an awning over a pedestrian or a parked car, a tree's crown over the road,
an overhead sign, a bus roof above its windows). The ground is the one the model sees: with
``ground: local`` the input is leveled first.

What it costs in accuracy and what it gains, on the synthetic validation drives with and
without overhead structures and on the real dev set: docs/experiments/overhang.
"""
from __future__ import annotations

from typing import TypeAlias, get_args

import numpy as np
from numpy.typing import NDArray

from suit_ros.ops.kernels import OVERHANG_BIN_M, overhang_keep
from suit_ros.params import OverhangParam

OverhangMode: TypeAlias = OverhangParam     # one definition: the node parameter's
OVERHANG_MODES: tuple[OverhangMode, ...] = get_args(OverhangMode)


class Overhang:
    """The overhang filter of a model's input (see the module docstring).

    :param point_range: the model's ``x0, y0, z0, x1, y1, z1`` (the columns span its xy; the
        heights its z).
    :param size: column size (m): the model's pillar size.
    :param gap: metres without returns that split a column's returns into stacks.
    :param height: a stack that starts this high (m) or higher is dropped.
    :param gap_per_m: the gap grows to this many metres per metre of the column's range from
        base_link's origin where that is more than ``gap`` (0: ``gap`` everywhere).
    """

    def __init__(self, point_range: tuple[float, ...] | list[float], size: float,
                 gap: float = 0.5, height: float = 2.0, gap_per_m: float = 0.0) -> None:
        x0, y0, z0, x1, y1, z1 = (float(v) for v in point_range)
        if not size > 0 or not gap > 0 or not z0 < height < z1 or not 0 <= gap_per_m < 1:
            raise ValueError(f'Overhang: size > 0, gap > 0, a height within the range '
                             f'({z0}, {z1}) and 0 <= gap_per_m < 1 needed, got {size}, {gap}, '
                             f'{height} and {gap_per_m}')
        self.x0, self.y0, self.size = x0, y0, float(size)
        self.nx = max(1, int(np.ceil((x1 - x0) / size)))
        self.ny = max(1, int(np.ceil((y1 - y0) / size)))
        self.zlo = max(z0, z1 - 64 * OVERHANG_BIN_M)     # the top 6.4 m (below: the road)
        self.n_bins = max(1, int(np.ceil((z1 - self.zlo) / OVERHANG_BIN_M)))
        self.gap_bins = max(1, int(round(gap / OVERHANG_BIN_M)))
        self.gap_bins_per_m = float(gap_per_m) / OVERHANG_BIN_M
        self.height = float(height)
        self.b_float = max(0, int(round((height - self.zlo) / OVERHANG_BIN_M)))
        self.dropped = 0            # returns the last call dropped

    def keep(self, points: NDArray[np.float32]) -> NDArray[np.bool_]:
        """``(N,)`` bool: the returns of ``(N, >= 3)`` points that do not hang."""
        keep, dropped = overhang_keep(points, self.x0, self.y0, self.size, self.nx, self.ny,
                                      self.zlo, self.n_bins, self.gap_bins, self.b_float,
                                      self.gap_bins_per_m)
        self.dropped = int(dropped)
        return np.asarray(keep)

    def __call__(self, points: NDArray[np.float32]) -> NDArray[np.float32]:
        """The points without the returns that hang (the same array when none do)."""
        keep = self.keep(points)
        return points if self.dropped == 0 else points[keep]
