"""Significant sampling (paper section IV-A): coarse, top-K, refined NMS, relaxation.

From a frame's heatmap p(R_t | I_t) it keeps only a few locations around likely objects:
cells whose max-class score is at least ``alpha`` (coarse), the ``K`` best of them (top-K), one
per object after NMS on the boxes decoded there (refined), and a neighbourhood around each
(relaxation: a square ``Hs x Ws`` window, a circle of radius ``rho`` cells, or the decoded box's
rectangle). The features at these cells, their positions and probabilities form the memory.

Carry (``carry_s > 0``, with the unobserved-cell fusion gate): a sample whose object the
current input no longer sees (no return at its centre cell) is kept as it was last stored,
moved by ego motion and GeoNet, for up to ``carry_s`` seconds (:func:`keep_carried`), so an
object held through a sensor outage or an occlusion keeps the features it had when seen instead
of fading through re-sampling. Where the input sees the place again the carried sample goes:
either the object is detected there anew or it is gone.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray
import torch
from torch import Tensor

from suit_ros.config import SamplingConfig
from suit_ros.model.fusion import FoldedFused
from suit_ros.model.grid import BEVGrid
from suit_ros.model.inference import compiled_ok
from suit_ros.model.memory import SparseMemory
from suit_ros.ops.nms import compiled_rotated_nms, greedy_suppression, rotated_suppression


@dataclass
class Samples:
    """Where the samples are: ``(M,)`` batch index, ``(M, 2)`` centre cells (col, row)."""

    batch_index: Tensor
    cells: Tensor
    scores: Tensor
    boxes: Tensor
    velocities: Tensor


def coarse_topk(prob: Tensor, alpha: float, k: int) -> tuple[Tensor, Tensor, Tensor]:
    """Cells with ``prob >= alpha``, at most ``k`` per frame, best first.

    :param prob: ``(B, H, W)`` max-class heatmap probability.
    :return: batch index ``(N,)``, cells ``(N, 2)`` (col, row), scores ``(N,)``.
    """
    B, H, W = prob.shape
    flat = prob.reshape(B, -1)
    scores, idx = flat.topk(min(k, H * W), dim=1)
    keep = scores >= alpha
    if B == 1:          # a node's frame
        idx, scores = idx[0][keep[0]], scores[0][keep[0]]
        b = torch.zeros(len(idx), dtype=torch.long, device=prob.device)
        return b, torch.stack([idx % W, idx // W], dim=1), scores
    b = torch.arange(B, device=prob.device)[:, None].expand_as(idx)[keep]
    idx, scores = idx[keep], scores[keep]
    cells = torch.stack([idx % W, idx // W], dim=1)
    return b, cells, scores


def refined_nms(boxes: Tensor, scores: Tensor, batch_index: Tensor, iou_threshold: float,
                min_distance: float) -> Tensor:
    """Class-agnostic NMS within each frame: a kept sample suppresses any other whose decoded box
    overlaps it (BEV IoU > ``iou_threshold``) or whose decoded centre lies closer than
    ``min_distance`` metres (so small objects, whose neighbouring cells all point at the same
    centre, also keep one sample). Returns kept indices, best first."""
    if boxes.shape[0] == 0:
        return torch.zeros(0, dtype=torch.long, device=boxes.device)
    order = torch.argsort(scores, descending=True, stable=True)
    b, bi = boxes[order], batch_index[order]
    kept = compiled_rotated_nms(b, bi, order, iou_threshold, min_distance)
    if kept is not None:
        return kept
    same = bi[:, None] == bi[None, :]
    close = (torch.cdist(b[:, :2].float(), b[:, :2].float()) < min_distance) & same
    close.fill_diagonal_(False)
    # IoU only where closeness does not already decide
    suppress = rotated_suppression(b, same & ~close, iou_threshold) | close
    return greedy_suppression(suppress, order)


_OFFSETS: dict[tuple[int, torch.device], Tensor] = {}


def _window_offsets(window: int, device: torch.device) -> Tensor:
    """The ``(window^2, 2)`` (col, row) offsets of a square window's cells, row-major."""
    key = (window, device)
    if key not in _OFFSETS:
        R = window // 2
        rng = torch.arange(-R, R + 1, device=device)
        dr, dc = torch.meshgrid(rng, rng, indexing='ij')
        _OFFSETS[key] = torch.stack([dc.reshape(-1), dr.reshape(-1)], dim=1)
    return _OFFSETS[key]


def relaxation_window(samples: Samples, cfg: SamplingConfig, grid: BEVGrid
                      ) -> tuple[Tensor, Tensor]:
    """The relaxed neighbourhood of each sample.

    :return: cells ``(M, P, 2)`` (col, row) of the ``window x window`` patch around each centre
        (row-major, P = window^2), and a mask ``(M, P)`` of the cells that belong to the
        neighbourhood: all of the square, the disc of radius ``cfg.radius`` cells, or the cells
        whose centre lies inside the decoded box (the centre cell always), and inside the map.
    """
    offsets = _window_offsets(cfg.window, samples.cells.device)                # (P, 2)
    cells = samples.cells[:, None, :] + offsets[None]                          # (M, P, 2)
    inside = ((cells[..., 0] >= 0) & (cells[..., 0] < grid.W) & (cells[..., 1] >= 0)
              & (cells[..., 1] < grid.H))
    if cfg.relaxation == 'square':
        return cells, inside
    if cfg.relaxation == 'circle':
        member = (offsets.pow(2).sum(-1) <= cfg.radius ** 2)[None].expand_as(inside)
    else:   # rectangle: cell centres inside the decoded box footprint
        xy = grid.cell_to_xy(cells)                                             # (M, P, 2)
        box = samples.boxes
        d = xy - box[:, None, :2]
        c, s = torch.cos(box[:, 6])[:, None], torch.sin(box[:, 6])[:, None]
        along = d[..., 0] * c + d[..., 1] * s
        across = -d[..., 0] * s + d[..., 1] * c
        member = ((along.abs() <= box[:, None, 3] / 2) & (across.abs() <= box[:, None, 4] / 2))
        member[:, offsets.shape[0] // 2] = True
    return cells, inside & member


def significant_sampling(heatmap_logits: Tensor,
                         decode_cells: Callable[[Tensor, Tensor], tuple[Tensor, Tensor]],
                         cfg: SamplingConfig,
                         grid: BEVGrid, prob: Tensor | None = None) -> Samples:
    """Select the significant samples of a batch of frames.

    :param heatmap_logits: ``(B, K, H, W)``.
    :param decode_cells: ``(batch_index, cells) -> (boxes (N, 7), velocities (N, 2))``, the
        head's decoder at given cells.
    :param prob: the max-class probability ``(B, H, W)`` of ``heatmap_logits`` when the caller
        has it already.
    """
    if prob is None:
        prob = torch.sigmoid(heatmap_logits).amax(dim=1)
    b, cells, scores = coarse_topk(prob, cfg.alpha, cfg.top_k)
    boxes, vel = decode_cells(b, cells)
    keep = refined_nms(boxes.detach(), scores.detach(), b, cfg.nms_iou_threshold, grid.cell)
    return Samples(b[keep], cells[keep], scores[keep], boxes[keep], vel[keep])


def gather_window(features: Tensor | FoldedFused, prob: Tensor, batch_index: Tensor,
                  cells: Tensor, mask: Tensor) -> tuple[Tensor, Tensor]:
    """Features ``(M, P, C)`` and probabilities ``(M, P)`` at window cells (zero outside mask).

    :param features: ``(B, C, H, W)`` (or a fused map not formed, whose rows are computed);
        ``prob``: ``(B, H, W)``.
    """
    M, P, _ = cells.shape
    B, C, H, W = features.shape
    col = cells[..., 0].clamp(0, W - 1)
    row = cells[..., 1].clamp(0, H - 1)
    b = batch_index[:, None].expand(M, P)
    flat = (b * H + row) * W + col                                             # (M, P)
    feat = (features.rows(flat.reshape(-1)) if isinstance(features, FoldedFused) else
            features.permute(0, 2, 3, 1).reshape(B * H * W, C)[flat.reshape(-1)])
    feat = feat.view(M, P, C) * mask[..., None].to(feat.dtype)
    p = prob.reshape(-1)[flat.reshape(-1)].view(M, P) * mask.to(prob.dtype)
    return feat, p


def cell_flags(flags: Tensor, batch_index: Tensor, xy: Tensor, grid: BEVGrid) -> Tensor:
    """``flags[b, row, col]`` (``(B, H, W)`` bool) at metric positions ``xy`` ``(M, 2)``;
    False outside the map."""
    if compiled_ok(flags, xy) and xy.dtype == torch.float32:
        from suit_ros.ops.kernels import flags_at
        return torch.from_numpy(flags_at(
            flags.contiguous().numpy(), batch_index.to(torch.int64).contiguous().numpy(),
            xy.contiguous().numpy(), *grid.origin_and_cell()))
    cr = torch.floor(grid.xy_to_cell(xy)).long()
    inside = (cr[:, 0] >= 0) & (cr[:, 0] < grid.W) & (cr[:, 1] >= 0) & (cr[:, 1] < grid.H)
    col, row = cr[:, 0].clamp(0, grid.W - 1), cr[:, 1].clamp(0, grid.H - 1)
    out: Tensor = flags[batch_index, row, col] & inside
    return out


def max_age_ns(cfg: SamplingConfig) -> int:
    """The oldest a carried sample may be (``carry_s`` in nanoseconds); a sample the memory
    made where nothing is seen starts one past it, so it is never carried."""
    return int(round(cfg.carry_s * 1e9))


def keep_carried(new: SparseMemory, carried: SparseMemory, observed: Tensor,
                 cfg: SamplingConfig, grid: BEVGrid, keep_new: bool = False) -> SparseMemory:
    """The next memory: this frame's samples and the carried ones, one per object.

    :param new: this frame's significant samples (ages unset).
    :param carried: the previous memory moved into this frame (:func:`moved_memory`, ages
        already one frame older).
    :param observed: ``(B, H, W)`` cells with returns in the current input.

    Priority, then the refined NMS of :func:`significant_sampling`: a new sample at an observed
    centre (the object is seen now; age 0) wins over a carried one of age <= ``carry_s``
    at an unobserved centre inside the map, which wins over a new sample at an unobserved
    centre (a detection the memory made; it is not carried further, so nothing the memory
    invents can keep itself alive).

    :param keep_new: (a carry branch) every new sample stays, whatever its centre, so the
        model's own memory is what it would be without a carry; a carried sample stays only
        where no new one is; :attr:`SparseMemory.own` marks the new ones.
    """
    kept = _keep_carried_compiled(new, carried, observed, cfg, grid, keep_new)
    if kept is not None:
        return kept
    P = new.cell_xy.shape[1]
    seen_new = cell_flags(observed, new.batch_index, new.cell_xy[:, P // 2], grid)
    unseen_old = cell_flags(~observed, carried.batch_index, carried.cell_xy[:, P // 2], grid)
    carried = carried.select(torch.nonzero(unseen_old
                                           & (carried.age() <= max_age_ns(cfg)))[:, 0])
    new = replace(new, ages=torch.where(seen_new, 0, max_age_ns(cfg) + 1))
    both = concat_memories(new, carried)
    centre_p = both.probs[:, P // 2].detach().float()
    tier = torch.cat([torch.where(seen_new | keep_new, 2.0, 0.0),
                      centre_p.new_ones(carried.num_samples)])
    if keep_new:
        both = replace(both, own=torch.arange(both.num_samples,
                                              device=both.batch_index.device) < new.num_samples)
    # (new samples already passed this NMS among themselves: with keep_new none is dropped)
    keep = refined_nms(both.boxes.detach(), tier + centre_p, both.batch_index,
                       cfg.nms_iou_threshold, grid.cell)
    return both.select(keep)


# the memory's dtypes whose numpy views the compiled selection takes as they are
_PLAIN: tuple[torch.dtype, ...] = (torch.float32, torch.int64, torch.bool)


def _keep_carried_compiled(new: SparseMemory, carried: SparseMemory, observed: Tensor,
                           cfg: SamplingConfig, grid: BEVGrid, keep_new: bool
                           ) -> SparseMemory | None:
    """:func:`keep_carried` at inference on the CPU: the samples chosen in one compiled pass
    (:func:`suit_ros.ops.kernels.carry_selection`) and their rows taken in numpy, instead of
    some 150 tensor operations on a few dozen rows; the same memory. None where it does not
    apply: autograd, another device, an ``observed`` map that is not ``(B, H, W)`` bool,
    positions, probabilities and boxes not float32, batch indices or ages not int64, a field
    whose dtype differs between the two memories or is none of :data:`_PLAIN`, windows of
    different sizes."""
    fields = ('batch_index', 'cell_xy', 'features', 'probs', 'mask', 'boxes', 'velocities')
    a = [getattr(new, f) for f in fields]
    b = [getattr(carried, f) for f in fields]
    ages = carried.age()
    if not (compiled_ok(observed, *a, *b) and observed.dtype == torch.bool
            and observed.dim() == 3
            and all(t.dtype in _PLAIN and t.dtype == u.dtype for t, u in zip(a, b))
            and new.cell_xy.dtype == new.probs.dtype == new.boxes.dtype == torch.float32
            and new.batch_index.dtype == ages.dtype == torch.int64
            and new.cell_xy.shape[1:] == carried.cell_xy.shape[1:]):
        return None
    from suit_ros.ops.kernels import carry_selection
    origin, cell = grid.origin_and_cell()

    def arr(t: Tensor) -> NDArray[Any]:     # C-ordered, as the kernel is compiled for
        return np.ascontiguousarray(t.numpy())

    index, seen = carry_selection(
        arr(observed), arr(new.batch_index), arr(new.cell_xy), arr(new.probs), arr(new.boxes),
        arr(carried.batch_index), arr(carried.cell_xy), arr(carried.probs),
        arr(carried.boxes), arr(ages), max_age_ns(cfg), bool(keep_new), origin, cell,
        np.float32(cfg.nms_iou_threshold), float(grid.cell))

    def rows(x: NDArray[Any], y: NDArray[Any]) -> Tensor:
        return torch.from_numpy(np.concatenate((x, y))[index])

    bi, xy, feats, probs, mask, boxes, vel = (rows(t.numpy(), u.numpy()) for t, u in zip(a, b))
    new_ages = np.where(seen, 0, max_age_ns(cfg) + 1).astype(np.int64)
    if keep_new:
        own: Tensor | None = torch.from_numpy(index < new.num_samples)
    elif new.own is None and carried.own is None:
        own = None
    else:
        own = rows(new.owned().numpy(), carried.owned().numpy())
    return SparseMemory(bi, xy, feats, probs, mask, boxes, vel, new.stamps_ns, new.poses,
                        new.window, rows(new_ages, ages.numpy()), own)


def concat_memories(a: SparseMemory, b: SparseMemory) -> SparseMemory:
    """``a``'s samples then ``b``'s (``a``'s frame stamps and poses)."""
    return SparseMemory(torch.cat([a.batch_index, b.batch_index]),
                        torch.cat([a.cell_xy, b.cell_xy]),
                        torch.cat([a.features, b.features.to(a.features.dtype)]),
                        torch.cat([a.probs, b.probs.to(a.probs.dtype)]),
                        torch.cat([a.mask, b.mask]),
                        torch.cat([a.boxes, b.boxes.to(a.boxes.dtype)]),
                        torch.cat([a.velocities, b.velocities.to(a.velocities.dtype)]),
                        a.stamps_ns, a.poses, a.window, torch.cat([a.age(), b.age()]),
                        None if a.own is None and b.own is None
                        else torch.cat([a.owned(), b.owned()]))
