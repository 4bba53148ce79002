"""The BEV grid: pillar grid and head map geometry, metric <-> cell conversions."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
import torch
from torch import Tensor


@dataclass(frozen=True)
class BEVGrid:
    """Square pillars over ``point_range``; the head map is the pillar grid / ``out_stride``.

    Map index ``[row, col]``: ``col`` along +x from ``x0``, ``row`` along +y from ``y0``; cell
    ``(c, r)`` covers ``x in [x0 + c * cell, x0 + (c + 1) * cell)``.
    """

    point_range: tuple[float, float, float, float, float, float]
    pillar_size: float
    out_stride: int

    @property
    def nx(self) -> int:
        """Pillar grid width (x)."""
        return int(round((self.point_range[3] - self.point_range[0]) / self.pillar_size))

    @property
    def ny(self) -> int:
        """Pillar grid height (y)."""
        return int(round((self.point_range[4] - self.point_range[1]) / self.pillar_size))

    @property
    def W(self) -> int:  # noqa: N802 - the usual name of a map width
        """Head map width."""
        return self.nx // self.out_stride

    @property
    def H(self) -> int:  # noqa: N802
        """Head map height."""
        return self.ny // self.out_stride

    @property
    def cell(self) -> float:
        """Head map cell size in metres."""
        return self.pillar_size * self.out_stride

    def xy_to_cell(self, xy: Tensor) -> Tensor:
        """Metric ``(..., 2)`` -> continuous head-map coordinates ``(..., 2)`` (col, row)."""
        origin = xy.new_tensor(self.point_range[:2])
        return (xy - origin) / self.cell

    def origin_and_cell(self) -> tuple[NDArray[np.float32], np.float32]:
        """The map's origin ``(x0, y0)`` and cell size as float32, as :meth:`xy_to_cell`
        computes in float32 (for compiled passes that find cells the same way)."""
        return np.asarray(self.point_range[:2], np.float32), np.float32(self.cell)

    def cell_to_xy(self, colrow: Tensor) -> Tensor:
        """Head-map cell ``(..., 2)`` (col, row) -> metric centre of that cell ``(..., 2)``."""
        origin = torch.tensor(self.point_range[:2], dtype=torch.float32, device=colrow.device)
        return (colrow.to(torch.float32) + 0.5) * self.cell + origin

    def cell_centres(self, device: torch.device | None = None) -> Tensor:
        """Metric centres of every head-map cell, ``(H, W, 2)``."""
        rows, cols = torch.meshgrid(torch.arange(self.H, device=device),
                                    torch.arange(self.W, device=device), indexing='ij')
        return self.cell_to_xy(torch.stack([cols, rows], dim=-1))


def pooled_occupancy(occupied: Tensor, stride: int, radius: int, compiled: bool = True
                     ) -> Tensor:
    """``(B, ny, nx)`` bool pillar occupancy -> ``(B, ny // stride, nx // stride)`` bool: a head
    cell holding an occupied pillar, grown by ``radius`` cells (a square): what a max pool of
    ``stride`` then one of ``2 radius + 1`` (padded) give, as bool reductions and shifts (the
    float max pools of the 512 x 512 map took 0.8 ms a frame, these 0.2; on the CPU one
    compiled pass, :func:`suit_ros.ops.kernels.pool_occupancy`: 0.02 ms on a 256 x 256 grid
    at stride 2, where these took 0.09)."""
    B, ny, nx = occupied.shape
    H, W = ny // stride, nx // stride
    if compiled and occupied.device.type == 'cpu' and occupied.dtype == torch.bool:
        from suit_ros.ops.kernels import pool_occupancy
        pooled = pool_occupancy(occupied.contiguous().view(-1).numpy(), B, ny, nx, stride,
                                radius)
        return torch.from_numpy(pooled)
    occ = occupied[:, :H * stride, :W * stride].reshape(B, H, stride, W, stride)
    out = occ.any(dim=4).any(dim=2)
    if radius:
        pad = torch.nn.functional.pad(out, (radius, radius, radius, radius))
        k = 2 * radius + 1
        rows = pad[:, :, 0:W]
        for d in range(1, k):
            rows = rows | pad[:, :, d:d + W]
        out = rows[:, 0:H]
        for d in range(1, k):
            out = out | rows[:, d:d + H]
    return out
