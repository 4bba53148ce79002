"""Dynamic pillarization, the PointNet pillar encoder (PFN) and the scatter to a BEV image.

No fixed maximum of points per pillar: every point in range contributes, pillar statistics are
segment reductions over the occupied pillars, found without sorting: an occupancy mask over the
grid and its running count give each point its pillar's index (pure torch; 4x faster than
``torch.unique`` on 150k points, same keys in the same order).
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor, nn

from suit_ros.model.grid import BEVGrid
from suit_ros.overhang import OVERHANG_MODES, Overhang, OverhangMode


class PillarEncoder(nn.Module):
    """Points -> pillar features -> pseudo-image ``(B, C, ny, nx)``.

    Each point is decorated with its offsets to the pillar's point mean (3) and to the pillar
    centre (2), as PointPillars does, passed through Linear + BatchNorm + ReLU, and max-pooled
    per pillar.

    :param time_scale: the time lag (input channel 4) is multiplied by this; applied to the
        linear layer's lag column, so it costs nothing per point. A checkpoint trained at
        another scale is moved to this one by :meth:`rescale_time_weights`.
    :param overhang: ``drop``: the returns that hang over a gap in their column are removed
        from every cloud before it is encoded (:mod:`suit_ros.overhang`); ``keep``: none.
    :param overhang_gap_per_m: the gap grows with the column's range
        (:class:`suit_ros.overhang.Overhang`'s ``gap_per_m``; 0: 0.5 m everywhere).
    """

    TIME_CHANNEL = 4
    CHUNK = 32768                # points per product in the inference path (see _folded_pillars)

    def __init__(self, grid: BEVGrid, in_channels: int = 5, channels: int = 32,
                 time_scale: float = 1.0, max_points: int = 0,
                 overhang: OverhangMode = 'keep', overhang_gap_per_m: float = 0.0) -> None:
        super().__init__()
        self.overhang_gap_per_m = float(overhang_gap_per_m)
        self.max_points = max_points
        self.grid = grid
        self.in_channels = in_channels
        self.learned_channels = channels
        self.out_channels = channels           # the pseudo-image's channels
        self.time_scale = time_scale
        self.linear = nn.Linear(in_channels + 5, channels, bias=False)
        self.norm: nn.Module = nn.BatchNorm1d(channels, eps=1e-3, momentum=0.01)
        # the pseudo-image's dtype (None: the pillar features'); an inference copy that runs
        # the backbone in bfloat16 writes it in bfloat16 directly
        self.canvas_dtype: torch.dtype | None = None
        self.set_overhang(overhang)

    def set_overhang(self, overhang: OverhangMode) -> None:
        """Keep or drop the returns that hang over a gap in their column (see ``overhang``)."""
        if overhang not in OVERHANG_MODES:
            raise ValueError(f'overhang must be one of {OVERHANG_MODES}, got {overhang!r}')
        self.overhang: OverhangMode = overhang
        self._overhang = (Overhang(self.grid.point_range, self.grid.pillar_size,
                                   gap_per_m=self.overhang_gap_per_m)
                          if overhang == 'drop' else None)

    def unhung(self, cloud: Tensor) -> Tensor:
        """``cloud`` ``(N, >= 3)`` without the returns that hang (itself with ``keep``, or
        when none hang)."""
        if self._overhang is None or not len(cloud):
            return cloud
        keep = self._overhang.keep(cloud.detach().cpu().float().numpy())
        if self._overhang.dropped == 0:
            return cloud
        return cloud.index_select(0, torch.from_numpy(np.flatnonzero(keep)).to(cloud.device))

    # (layer, norm) attribute pairs an inference copy may fold (suit_ros.model.inference)
    fold_pairs = (('linear', 'norm'),)

    def weight(self) -> Tensor:
        """The linear layer's weight with the time-lag column scaled by ``time_scale``."""
        W = self.linear.weight
        if self.time_scale == 1.0 or self.in_channels <= self.TIME_CHANNEL:
            return W
        scale = torch.ones(W.shape[1], dtype=W.dtype, device=W.device)
        scale[self.TIME_CHANNEL] = self.time_scale
        return W * scale

    @torch.no_grad()
    def rescale_time_weights(self, from_scale: float) -> None:
        """Make weights learned with ``time_scale = from_scale`` compute the same function
        at this encoder's ``time_scale``."""
        if self.in_channels > self.TIME_CHANNEL and from_scale != self.time_scale:
            self.linear.weight[:, self.TIME_CHANNEL] *= from_scale / self.time_scale

    def voxelize(self, points: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Assign points to pillars.

        :param points: ``(P, 1 + in_channels)``: batch index, x, y, z, features...
        :return: the in-range points ``(P', 1 + in_channels)``, their pillar id ``(P',)``
            (index into the unique pillars) and the unique pillar keys ``(U,)`` encoded as
            ``(b * ny + iy) * nx + ix``.
        """
        g = self.grid
        x0, y0, z0, x1, y1, z1 = g.point_range
        xyz = points[:, 1:4]
        inside = ((xyz[:, 0] >= x0) & (xyz[:, 0] < x1) & (xyz[:, 1] >= y0) & (xyz[:, 1] < y1)
                  & (xyz[:, 2] >= z0) & (xyz[:, 2] < z1))
        pts = (points if bool(inside.all())
               else points.index_select(0, torch.nonzero(inside, as_tuple=True)[0]))
        ix = ((pts[:, 1] - x0) / g.pillar_size).long().clamp_(0, g.nx - 1)
        iy = ((pts[:, 2] - y0) / g.pillar_size).long().clamp_(0, g.ny - 1)
        key = (pts[:, 0].long() * g.ny + iy) * g.nx + ix
        batch = int(pts[:, 0].max().item()) + 1 if len(pts) else 1
        occupied = torch.zeros(batch * g.ny * g.nx, dtype=torch.bool, device=pts.device)
        occupied[key] = True
        keys = torch.nonzero(occupied, as_tuple=True)[0]
        inverse = (torch.cumsum(occupied, 0) - 1)[key]
        return pts, inverse, keys

    def _folded_terms(self, C: int) -> Tensor:
        """The folded encoder's linear map split for the per-pillar max: the linear map of a
        point's offsets from its pillar's mean and centre splits into a per-point term
        (``A``, ``(32, C)``, applied to the raw features) and a per-pillar one
        (:meth:`_per_pillar`); the max over a pillar's points is taken on the per-point term,
        then the per-pillar term is subtracted and the ReLU applied (both commute with that
        max)."""
        W = self.weight()
        A = W[:, :C].clone()
        A[:, :3] += W[:, C:C + 3]
        A[:, 0] += W[:, C + 3]
        A[:, 1] += W[:, C + 4]
        return A

    def _per_pillar(self, C: int, mean: Tensor, keys: Tensor) -> Tensor:
        """The per-pillar term of :meth:`_folded_terms` for pillars at ``keys`` (cells)."""
        g = self.grid
        W = self.weight()
        centre_x = ((keys % g.nx).to(mean.dtype) + 0.5) * g.pillar_size + g.point_range[0]
        centre_y = (((keys // g.nx) % g.ny).to(mean.dtype) + 0.5) * g.pillar_size \
            + g.point_range[1]
        per_pillar = (mean @ W[:, C:C + 3].T + centre_x[:, None] * W[:, C + 3]
                      + centre_y[:, None] * W[:, C + 4])
        if self.linear.bias is not None:
            per_pillar = per_pillar - self.linear.bias
        return per_pillar

    def _folded_pillars(self, feats: Tensor, inverse: Tensor, mean: Tensor, keys: Tensor
                        ) -> Tensor:
        """The same pillar features when the norm is folded into ``linear`` (inference copy),
        without building the decorated points (:meth:`_folded_terms`)."""
        C = feats.shape[1]
        per_pillar = self._per_pillar(C, mean, keys)
        # in chunks of points: a (P, C) product of a 64-beam input (over 40 MB) would be a
        # fresh allocation every frame (above the allocator's reuse threshold, paid in page
        # faults, 3x the work itself); the max does not depend on the order of the points
        pillar = torch.full(per_pillar.shape, float('-inf'), dtype=feats.dtype,
                            device=feats.device)
        A_t = self._folded_terms(C).T.to(feats.dtype)
        for a in range(0, feats.shape[0], self.CHUNK):
            z = feats[a:a + self.CHUNK] @ A_t
            pillar.scatter_reduce_(0, inverse[a:a + self.CHUNK, None].expand_as(z), z, 'amax')
        # the per-pillar term is the same for every point of the pillar: subtract it after
        # the max
        return torch.relu_(pillar.sub_(per_pillar))

    def compiled(self, clouds: Sequence[Tensor]) -> bool:
        """Whether :meth:`encode_clouds` takes the compiled path for these clouds: the
        folded inference copy (no norm, no gradient), no cap, the five usual input channels,
        float32 clouds on the CPU, a float32 or bfloat16 pseudo-image."""
        return (not self.training and isinstance(self.norm, nn.Identity) and not self.max_points
                and self.in_channels == 5 and not torch.is_grad_enabled()
                and self.canvas_dtype in (None, torch.float32, torch.bfloat16)
                and all(c.device.type == 'cpu' and c.dtype == torch.float32 for c in clouds))

    def encode_clouds(self, clouds: Sequence[Tensor], occupancy: bool = False
                      ) -> tuple[Tensor, Tensor | None]:
        """Encode a batch of ``(N_i, in_channels)`` clouds into ``(B, C, ny, nx)``, and with
        ``occupancy`` where the pseudo-image is non-zero ``(B, ny, nx)`` bool (an occupied
        pillar whose features are not all zero: the input has returns there; None without).

        The inference copy on the CPU pillarizes and reduces each cloud in two compiled
        passes over its points (:func:`suit_ros.ops.kernels.pillar_max`) and reads the
        occupancy off its pillars, not the whole image; the same values as :meth:`forward`
        (the tests compare), which every other case runs.
        """
        g = self.grid
        if not self.compiled(clouds):
            clouds = [self.unhung(c) for c in clouds]
            rows = [torch.cat([pts.new_full((pts.shape[0], 1), float(i)), pts], dim=1)
                    for i, pts in enumerate(clouds)]
            bev: Tensor = self(torch.cat(rows, dim=0), len(clouds))
            return bev, (bev != 0).any(dim=1) if occupancy else None
        from suit_ros.ops.kernels import pillar_features, pillar_max
        C = self.in_channels
        A = self._folded_terms(C).T.contiguous().numpy()
        W = self.weight().detach().contiguous().numpy()
        bias = None if self.linear.bias is None else self.linear.bias.detach().numpy()
        cells = g.ny * g.nx
        canvas = torch.zeros(len(clouds) * cells, self.out_channels,
                             dtype=self.canvas_dtype or torch.float32)
        # bfloat16 is written as its bits (numpy has no bfloat16)
        image = (canvas.view(torch.int16).numpy().view(np.uint16)
                if canvas.dtype == torch.bfloat16 else canvas.numpy())
        occupied = torch.zeros(len(clouds) * cells, dtype=torch.bool) if occupancy else None
        for b, pts in enumerate(clouds):
            points = pts.numpy()
            # the returns that hang are left out of the pillars, not copied out of the cloud
            keep = (self._overhang.keep(points)
                    if self._overhang is not None and len(points) else None)
            keys, mean, top = pillar_max(points, g.point_range, g.pillar_size, g.nx, g.ny, A,
                                         keep)
            pillar_features(top, mean, keys, W, bias,
                            (g.point_range[0], g.point_range[1], g.pillar_size, g.nx, g.ny),
                            image, b * cells, None if occupied is None else occupied.numpy())
        return (canvas.view(len(clouds), g.ny, g.nx, self.out_channels).permute(0, 3, 1, 2),
                None if occupied is None else occupied.view(len(clouds), g.ny, g.nx))

    def cap(self, points: Tensor) -> Tensor:
        """``points`` with the denser pillars thinned to about ``max_points`` each
        (:func:`~suit_ros.ops.geometry.thin_per_cell`)."""
        from suit_ros.ops.geometry import thin_per_cell
        pts, inverse, keys = self.voxelize(points)
        keep = thin_per_cell(inverse.cpu().numpy(), self.max_points)
        return pts if keep.all() else pts[torch.from_numpy(keep).to(pts.device)]

    def forward(self, points: Tensor, batch_size: int) -> Tensor:
        """Encode ``(P, 1 + in_channels)`` points into ``(B, C, ny, nx)``."""
        g = self.grid
        if self.max_points:
            points = self.cap(points)
        pts, inverse, keys = self.voxelize(points)
        feats = pts[:, 1:]
        U = keys.shape[0]
        ones = torch.ones_like(inverse, dtype=feats.dtype)
        count = torch.zeros(U, dtype=feats.dtype, device=feats.device).index_add_(0, inverse, ones)
        mean = torch.zeros(U, 3, dtype=feats.dtype, device=feats.device)
        mean.index_add_(0, inverse, feats[:, :3])
        mean = mean / count.clamp(min=1.0)[:, None]
        if self.training or not isinstance(self.norm, nn.Identity):
            ix = (keys % g.nx).to(feats.dtype)
            iy = ((keys // g.nx) % g.ny).to(feats.dtype)
            centre_x = (ix + 0.5) * g.pillar_size + g.point_range[0]
            centre_y = (iy + 0.5) * g.pillar_size + g.point_range[1]
            decorated = torch.cat([
                feats,
                feats[:, :3] - mean[inverse],
                (feats[:, 0] - centre_x[inverse])[:, None],
                (feats[:, 1] - centre_y[inverse])[:, None],
            ], dim=1)
            x = torch.relu(self.norm(nn.functional.linear(decorated, self.weight(),
                                                          self.linear.bias)))
            pillar = torch.zeros(U, self.learned_channels, dtype=x.dtype, device=x.device)
            pillar = pillar.scatter_reduce_(0, inverse[:, None].expand_as(x), x, 'amax',
                                            include_self=False)
        else:
            pillar = self._folded_pillars(feats, inverse, mean, keys)
        canvas = torch.zeros(batch_size * g.ny * g.nx, self.out_channels,
                             dtype=self.canvas_dtype or pillar.dtype, device=pillar.device)
        canvas[keys] = pillar.to(canvas.dtype)
        return canvas.view(batch_size, g.ny, g.nx, self.out_channels).permute(0, 3, 1, 2)
