"""The local ground under the model input: real roads are not the vehicle's ground plane.

The model learned its objects standing on a flat road at z = 0 of base_link (the synthetic
world's). On real sensors the road rises and falls around the car (slopes, crowns, the car
pitching on its springs), and a LiDAR extrinsic measured a few centimetres off lifts or
lowers everything: on the Argoverse 2 dev sweeps the lowest returns per 5 m cell lie from
+0.43 m to -0.75 m of base_link (docs/experiments/street). ``ground: local`` levels the input
to the ground around each point before the model sees it, and puts the decoded boxes back on
the road where they stand:

1. a coarse BEV grid (``cell`` m) over the model's point range; per cell, the median height
   of the returns within 0.3 m of its lowest ones (a low percentile, within a band around
   z = 0) is the ground (most returns of a LiDAR sweep are road; objects and walls only add
   returns above it);
2. cells with too few returns, and cells standing clearly above the median of their
   neighbours (the roof of a car or a bus shelter hiding the road), take their neighbours'
   value; the far field falls back to z = 0;
3. beyond ``hold`` m a cell may not rise more than ``rise`` above the ground found nearer on
   its bearing: there a sparse LiDAR's rings leave gaps with no road returns at all (a
   16-beam sensor 2 m up has none between about 38 m and 115 m), and the lowest returns of
   such a cell are the bottoms of the objects in it, 0.3-0.9 m above the road. That error is
   always upward (no return lies under the road), so a far cell lower than the ground nearer
   keeps its own estimate: a road falling away is followed (docs/experiments/ground, "the far
   field");
4. every point's height becomes its height above the ground under it (bilinear between the
   cell centres), and every box's centre is raised by the ground under its centre.

On flat ground (the synthetic world) the correction is a few centimetres within ``hold``; it
is measured on the validation set and the real dev set in docs/experiments/ground.
"""
from __future__ import annotations

import dataclasses
from typing import Any, TypeAlias, get_args

import numpy as np
from numpy.typing import NDArray

from suit_ros.ops.kernels import GROUND_BIN_M as BIN_M
from suit_ros.ops.kernels import height_histograms, level_heights
from suit_ros.params import GroundParam
from suit_ros.structures import Frame

GroundMode: TypeAlias = GroundParam     # one definition: the node parameter's
GROUND_MODES: tuple[GroundMode, ...] = get_args(GroundMode)


class LocalGround:
    """The ground estimate of one model input (see the module docstring).

    :param point_range: the model's ``x0, y0, z0, x1, y1, z1``.
    :param cell: grid cell (m).
    :param band: heights (m, base_link) a ground return may have.
    :param percentile: the share of a cell's returns at or below its ground.
    :param min_points: fewer returns in the band: the cell takes its neighbours' ground.
    :param max_step: a cell more than this above the median of its neighbours takes it.
    :param road_band: the ground is the median height of the returns within this of the
        cell's lowest ones.
    :param hold: range (m) beyond which a cell rises at most ``rise`` above the ground nearer
        on its bearing (``inf``: every cell its own).
    :param rise: see ``hold`` (m).
    """

    def __init__(self, point_range: tuple[float, ...] | list[float], cell: float = 4.0,
                 band: tuple[float, float] = (-2.0, 1.5), percentile: float = 0.05,
                 min_points: int = 20, max_step: float = 0.3,
                 road_band: float = 0.3, hold: float = 30.0,
                 rise: float = 0.1) -> None:
        x0, y0, _, x1, y1, _ = (float(v) for v in point_range)
        if not cell > 0 or not band[1] > band[0] or not 0 < percentile < 1 \
                or not hold > np.sqrt(2.0) * cell or not rise >= 0:
            raise ValueError(f'LocalGround: cell > 0, a band lo < hi, a percentile in (0, 1), '
                             f'hold > 1.42 x cell and rise >= 0 needed, got {cell}, {band}, '
                             f'{percentile}, {hold}, {rise}')
        self.x0, self.y0, self.cell = x0, y0, float(cell)
        self.nx = max(2, int(np.ceil((x1 - x0) / cell)))
        self.ny = max(2, int(np.ceil((y1 - y0) / cell)))
        self.zlo = float(band[0])
        self.n_bins = int(np.ceil((band[1] - band[0]) / BIN_M))
        self.percentile, self.min_points, self.max_step = percentile, min_points, max_step
        self.road_band, self.hold, self.rise = road_band, float(hold), float(rise)
        self.grid = np.zeros((self.ny, self.nx), np.float32)
        # the far cells, and where on their bearing their ground is read: a cell diagonal
        # inside ``hold``, so that the bilinear read touches no far cell
        cx = x0 + (np.arange(self.nx) + 0.5) * self.cell
        cy = y0 + (np.arange(self.ny) + 0.5) * self.cell
        xx, yy = np.meshgrid(cx, cy)
        rr = np.hypot(xx, yy)
        self.far = rr > hold
        inside = (hold - np.sqrt(2.0) * self.cell) / np.maximum(rr[self.far], 1e-9)
        self._far_from = np.stack([xx[self.far] * inside, yy[self.far] * inside], axis=1)

    def fit(self, points: NDArray[np.float32]) -> NDArray[np.float32]:
        """Estimate the ground under ``(N, >= 3)`` float32 points; :return: ``(ny, nx)``."""
        hist = height_histograms(points, self.x0, self.y0, self.cell, self.nx, self.ny,
                                  self.zlo, self.n_bins)
        counts = hist.sum(axis=1)
        valid = counts >= self.min_points
        cum = np.cumsum(hist, axis=1)
        # the lowest returns (the first bin whose cumulative count reaches the percentile),
        # then the median of the returns within ``road_band`` above them: a sloped road
        # spreads over a cell's heights, and its lowest returns alone lie below its middle
        target = np.maximum(1, np.ceil(self.percentile * counts)).astype(np.int64)
        first = (cum >= target[:, None]).argmax(axis=1)
        width = max(1, int(round(self.road_band / BIN_M)))
        idx = np.minimum(first[:, None] + np.arange(width), self.n_bins - 1)
        window = np.cumsum(np.take_along_axis(hist, idx, axis=1), axis=1)
        mid = (window >= 0.5 * window[:, -1:]).argmax(axis=1)
        z = (self.zlo + (first + mid + 0.5) * BIN_M).reshape(self.ny, self.nx)
        valid = valid.reshape(self.ny, self.nx)
        z = np.where(valid, z, np.nan)
        # a cell clearly above its neighbours' median sees no road (a roof over it)
        med = _neighbour_median(z)
        high = valid & np.isfinite(med) & (z > med + self.max_step)
        z[high] = med[high]
        self.grid = _fill(z).astype(np.float32)
        if self.far.any():
            self.grid[self.far] = np.minimum(self.grid[self.far],
                                             self.under(self._far_from) + self.rise)
        return self.grid

    def level(self, points: NDArray[np.float32]) -> NDArray[np.float32]:
        """Fit the ground and :return: a copy of ``points`` with heights above it."""
        pts = np.ascontiguousarray(points, np.float32)
        self.fit(pts)
        out = np.empty_like(pts)
        level_heights(pts, self.grid, self.x0, self.y0, self.cell, out)
        return out

    def under(self, xy: NDArray[np.floating[Any]]) -> NDArray[np.float32]:
        """The fitted ground under ``(M, 2)`` positions (as :meth:`level` subtracts it)."""
        p = np.zeros((len(xy), 3), np.float32)
        p[:, :2] = np.asarray(xy, np.float32).reshape(-1, 2)
        out = np.empty_like(p)
        level_heights(p, self.grid, self.x0, self.y0, self.cell, out)
        return -out[:, 2]


def leveled_frame(frame: Frame, ground: LocalGround) -> Frame:
    """A model frame (points and GT in base_link) as ``ground: local`` shows it to the model:
    its points leveled to their local ground, its GT boxes lowered by the ground under their
    centres (training on what the model sees at inference; the inverse of putting decoded
    boxes back on the road)."""
    points = ground.level(frame.points)
    gt = frame.gt
    if gt is not None and len(gt):
        boxes = gt.boxes.copy()
        boxes[:, 2] -= ground.under(boxes[:, :2])
        gt = dataclasses.replace(gt, boxes=boxes)
    return dataclasses.replace(frame, points=points, gt=gt)


def _neighbours(z: NDArray[np.float64]) -> NDArray[np.float64]:
    """``(8, ny, nx)``: each cell's 8 neighbours (NaN off the grid)."""
    ny, nx = z.shape
    pad = np.pad(z, 1, constant_values=np.nan)
    return np.stack([pad[1 + dy:1 + dy + ny, 1 + dx:1 + dx + nx]
                     for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx])


def _neighbour_median(z: NDArray[np.float64]) -> NDArray[np.float64]:
    """Per cell, the median of the finite values among its 8 neighbours (NaN: none)."""
    stack = np.sort(_neighbours(z), axis=0)                        # NaNs sort last
    n = np.isfinite(stack).sum(axis=0)
    lo = np.take_along_axis(stack, np.maximum(n - 1, 0)[None] // 2, axis=0)[0]
    hi = np.take_along_axis(stack, (n // 2)[None], axis=0)[0]
    out: NDArray[np.float64] = np.where(n > 0, 0.5 * (lo + hi), np.nan)
    return out


def _fill(z: NDArray[np.float64], rounds: int = 4) -> NDArray[np.float64]:
    """NaN cells take the mean of their finite neighbours, growing inwards ``rounds`` times;
    what is still unknown after that is 0 (the vehicle's ground plane)."""
    z = z.copy()
    for _ in range(rounds):
        missing = ~np.isfinite(z)
        if not missing.any():
            break
        stack = _neighbours(z)
        n = np.isfinite(stack).sum(axis=0)
        s = np.nansum(stack, axis=0)
        grow = missing & (n > 0)
        z[grow] = s[grow] / n[grow]
    return np.where(np.isfinite(z), z, 0.0)
