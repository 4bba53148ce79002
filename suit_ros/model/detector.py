"""SUITDetector: the CenterPoint-pillar base with SUIT's sparse temporal path (and its baselines).

Per frame: points -> pillars -> BEV backbone -> F_t; if a memory from the previous frame is
usable, the past term (equation 11, or the dense warp) is fused with F_t; the CenterHead runs on
the fused map; the next memory is sampled from the fused map (induction). ``temporal`` selects
``none`` (single frame), ``dense`` (whole previous map warped by ego motion), ``sparse`` (sparse
memory, zero displacement), ``sparse_velocity`` (shifted by predicted velocity) or ``suit``
(GeoNet's displacement distribution).
"""
from __future__ import annotations

from collections.abc import Sequence
import copy
import typing

import numpy as np
from numpy.typing import NDArray
import torch
from torch import Tensor, nn

from suit_ros.config import ModelConfig
from suit_ros.model.backbone import BEVBackbone
from suit_ros.model.distill import Distiller
from suit_ros.model.fusion import (
    BranchTerms,
    FoldedFused,
    PastTerm,
    TemporalFusion,
    sparse_past_term,
    sparse_past_terms,
    warp_dense,
)
from suit_ros.model.geonet import GeoNet
from suit_ros.model.grid import BEVGrid, pooled_occupancy
from suit_ros.model.head import CenterHead, dilated_cells
from suit_ros.model.inference import one_thread
from suit_ros.model.memory import (
    DenseMemory,
    SparseMemory,
    ego_transforms,
    moved_memory,
    rotate_velocities,
    transform_sample_positions,
)
from suit_ros.model.pillars import PillarEncoder
from suit_ros.model.sampling import (
    gather_window,
    keep_carried,
    relaxation_window,
    significant_sampling,
)
from suit_ros.ops.geometry import se3_inverse
from suit_ros.ops.nms import suppress_near
from suit_ros.structures import Frame

Memory = SparseMemory | DenseMemory
Past = Tensor | PastTerm | BranchTerms
OWN = 'own.'    # with a carry branch, the model's own head outputs in the predictions, by name
# cells around the gated carry term a carry head answers for: its two 3 x 3 layers' reach
CARRY_REACH = 2


class CarryBranch(nn.Module):
    """``fusion_gate: carry_branch``: the unobserved cells' own past projection (W2, zero at
    the start) and head (a copy of the model's head until trained), so that what the memory
    carries is read there without changing how the observed cells decode."""

    def __init__(self, channels: int, head: CenterHead) -> None:
        super().__init__()
        self.past = nn.Linear(channels, channels, bias=False)
        with torch.no_grad():
            self.past.weight.zero_()
        self.head = copy.deepcopy(head)


class SUITDetector(nn.Module):
    """The detector; see the module docstring."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        p, b, h, g = cfg.pillars, cfg.backbone, cfg.head, cfg.geonet
        self.grid = BEVGrid(p.point_range, p.pillar_size, cfg.out_stride)
        self.pillars = PillarEncoder(self.grid, p.in_channels, p.channels, p.time_scale,
                                     p.max_points_per_pillar, p.overhang,
                                     p.overhang_gap_per_m)
        self.backbone = BEVBackbone(self.pillars.out_channels, b.layer_nums, b.layer_strides,
                                    b.num_filters, b.upsample_strides, b.num_upsample_filters)
        C = self.backbone.out_channels
        self.fusion = TemporalFusion(C) if cfg.temporal != 'none' else None
        self.geonet = (GeoNet(C, cfg.sampling.window, g.bins, g.channels, g.velocity_step,
                              g.velocity_input)
                       if cfg.temporal == 'suit' else None)
        self.head = CenterHead(C, len(cfg.class_names), self.grid, h.head_channels,
                               h.code_weights, h.loc_weight, h.min_overlap, h.min_radius,
                               h.max_objects, h.yaw_velocity_min_speed)
        self.carry = (CarryBranch(C, self.head)
                      if cfg.fusion_gate == 'carry_branch' and self.fusion is not None else None)
        # set on an inference copy: the head's regression only where it is read
        # (CenterHead.forward_lazy); not with the output gate, which merges whole maps
        self.lazy_regression = False
        # the carry head at its cells on one torch thread (inference.one_thread)
        self.small_work_one_thread = True

    @property
    def device(self) -> torch.device:
        """Where the weights live."""
        return next(self.parameters()).device

    # ------------------------------------------------------------------ per-frame pieces
    def encode(self, points: Sequence[Tensor]) -> Tensor:
        """Pillars + backbone for a batch of ``(N_i, 5)`` clouds -> ``(B, C, H, W)``."""
        return self.encode_observed(points)[0]

    def encode_observed(self, points: Sequence[Tensor]) -> tuple[Tensor, Tensor | None]:
        """:meth:`encode`, and where the input has returns (``(B, H, W)`` bool at the head
        grid, ``fusion_gate_radius`` cells around each occupied pillar; None without a gate)."""
        # a frozen base (temporal fine-tuning) builds no graph: no backward through it
        grad = torch.is_grad_enabled() and any(
            p.requires_grad for m in (self.pillars, self.backbone) for p in m.parameters())
        gated = self.cfg.fusion_gate != 'none' and self.fusion is not None
        with torch.set_grad_enabled(grad):
            bev, occupied = self.pillars.encode_clouds(points, occupancy=gated)
            out: Tensor = self.backbone(bev)
        if occupied is None:
            return out, None
        with torch.no_grad():
            # an occupied pillar has a non-zero feature (max over its points after a ReLU)
            observed = pooled_occupancy(occupied, self.cfg.out_stride,
                                        self.cfg.fusion_gate_radius)
        return out, observed

    @staticmethod
    def usable(memory: Memory | None, stamps_ns: Sequence[int]
               ) -> tuple[NDArray[np.bool_], NDArray[np.float64]]:
        """Which frames of the batch may fuse the memory (time moved forward), and the gaps (s).

        Staleness (a gap too long, a changed sensor) is the caller's rule: the pipeline resets
        the memory (``max_gap_s``) before it gets here.
        """
        B = len(stamps_ns)
        if memory is None:
            return np.zeros(B, bool), np.zeros(B)
        dt = (np.asarray(stamps_ns, np.int64) - np.asarray(memory.stamps_ns, np.int64)) * 1e-9
        return dt > 0, dt

    def past_term(self, memory: Memory | None, poses: NDArray[np.float64],
                  stamps_ns: Sequence[int]) -> tuple[Past | None, dict[str, Tensor]]:
        """The W2-projected past features in the current grid, or None when nothing is fused.

        :return: the term (``(B, C, H, W)`` for a dense memory, a sparse :class:`PastTerm` for
            a sparse one, two of them as :class:`BranchTerms` with a carry branch) and aux
            outputs (``geo_logits``, ``sample_index``, ``T_now_prev``) for the GeoNet loss;
            with a carry (``sampling.carry_s``) also ``carry_index``,
            ``carry_positions`` and ``carry_shift`` for :meth:`carried`.
        """
        aux: dict[str, Tensor] = {}
        if self.fusion is None or memory is None:
            return None, aux
        ok, dt = self.usable(memory, stamps_ns)
        if not ok.any():
            return None, aux
        B = len(stamps_ns)
        T_now_prev = ego_transforms(np.asarray(poses), memory.poses)
        if isinstance(memory, DenseMemory):
            warped = warp_dense(memory.features, np.stack([se3_inverse(T) for T in T_now_prev]),
                                self.grid)
            warped = warped * torch.from_numpy(ok).to(warped)[:, None, None, None]
            return self.fusion.past_dense(warped), aux
        if ok.all():        # every frame of the batch fuses its memory (a node's one frame)
            sel = torch.arange(memory.num_samples, device=memory.batch_index.device)
            sub = memory
        else:
            okt = torch.from_numpy(ok).to(memory.batch_index.device)
            sel = torch.nonzero(okt[memory.batch_index], as_tuple=True)[0]
            sub = memory.select(sel)
        bi, feats, probs, mask = sub.batch_index, sub.features, sub.probs, sub.mask
        positions = transform_sample_positions(sub, T_now_prev)
        dts = torch.from_numpy(dt).to(feats)[bi]                               # (M,)
        M = feats.shape[0]
        if self.geonet is not None:
            logits = self.geonet.memory_logits(
                feats, mask, rotate_velocities(sub.velocities, bi, T_now_prev)
                if self.geonet.velocity_input else None)
            q = torch.softmax(logits, dim=1)
            bins = typing.cast(Tensor, self.geonet.bin_velocities)
            disp = bins[None] * dts[:, None, None]
            aux.update(geo_logits=logits, sample_index=sel)
            prune = 0.0 if self.training else self.cfg.geonet.prune_probability
        elif self.cfg.temporal == 'sparse_velocity':
            v = rotate_velocities(sub.velocities, bi, T_now_prev)
            disp, q, prune = (v * dts[:, None])[:, None, :], feats.new_ones(M, 1), 0.0
        else:   # sparse: zero displacement
            disp, q, prune = feats.new_zeros(M, 1, 2), feats.new_ones(M, 1), 0.0
        aux['T_now_prev'] = torch.from_numpy(T_now_prev)
        if self.cfg.sampling.carry_s:
            # the object's own expected displacement since the memory's frame
            shift = disp[:, 0] if q.shape[1] == 1 else (q[:, :, None] * disp).sum(dim=1)
            aux.update(carry_index=sel, carry_positions=positions, carry_shift=shift)
        if self.carry is None:
            return sparse_past_term(feats, probs, mask, positions, bi, disp, q,
                                    self.fusion.past, self.grid, B, prune), aux
        # the model's own term from its own samples (as without a carry), the carry's from all;
        # an inference copy whose own W2 is zero (a carry branch on the single-frame model)
        # has no own term to compute
        own = torch.nonzero(sub.owned(), as_tuple=True)[0]
        if self.fusion.zero_past:
            own = own[:0]
        own_term, carry_term = sparse_past_terms(
            feats, probs, mask, positions, bi, disp, q,
            [(self.fusion.past, own), (self.carry.past, None)], self.grid, B, prune)
        return BranchTerms(own_term, carry_term), aux

    def fuse(self, current: Tensor, past: Past | None,
             observed: Tensor | None = None) -> Tensor | FoldedFused:
        """Concatenate-and-fuse (a no-op for the single-frame model). With ``observed``
        (``fusion_gate: unobserved``) the past term enters only the cells without returns;
        with a carry branch this is the model's own fused map, as without a gate."""
        if self.fusion is None:
            return current
        # an inference copy whose heads read the fused map through W1 (HeadFold): not formed
        folded = self.head.fold is not None
        if isinstance(past, BranchTerms) and observed is not None:
            carry = past.carry_gated = gate_past(past.carry, observed)
            if folded and isinstance(carry, PastTerm):
                past.carry_input = FoldedFused(current, carry, self.fusion)
                return FoldedFused(current, past.own, self.fusion)
            own_fused, past.carry_input = self.fusion.forward_branches(current, past.own, carry)
            return own_fused
        if isinstance(past, BranchTerms):
            past = past.own
        elif observed is not None and past is not None:
            past = gate_past(past, observed)
        if folded and not isinstance(past, Tensor):
            return FoldedFused(current, past, self.fusion)
        fused: Tensor = self.fusion(current, past)
        return fused

    def carried(self, memory: Memory | None, aux: dict[str, Tensor],
                poses: NDArray[np.float64], stamps_ns: Sequence[int]) -> SparseMemory | None:
        """The previous memory's samples moved into the current frame, older by the frames'
        stamp gap, for the carry of :meth:`sample_memory` (None without a carry or a usable
        memory)."""
        if not isinstance(memory, SparseMemory) or 'carry_index' not in aux:
            return None
        # every sample (a node's frame fuses its whole memory; the index is sorted): no copy
        index = aux['carry_index']
        held = memory if len(index) == memory.num_samples else memory.select(index)
        return moved_memory(held, aux['carry_positions'],
                            aux['carry_shift'], aux['T_now_prev'].numpy(), poses,
                            list(stamps_ns))

    def predict(self, current: Tensor, past: Past | None, fused: Tensor | FoldedFused,
                observed: Tensor | None) -> dict[str, Tensor]:
        """The head on the fused map; with ``fusion_gate: unobserved_output`` its outputs at
        the observed cells are those of the current frame alone (the head's receptive field
        would otherwise carry the past term from the unobserved cells next to them); with
        ``carry_branch`` the unobserved cells' outputs are the carry head's on the current
        features plus the carry projection's past term there (the model's own outputs stay
        in the predictions under ``own.<name>``, for the memory's sampling). An inference copy
        (``lazy_regression``) returns the heatmap and the shared map (``shared``) for the
        regression to be read where decoded, and a carry head's rows where it answered
        (``carry_cells``, ``carry_reg``): :meth:`CenterHead.forward_lazy`."""
        preds: dict[str, Tensor] = (self.head.forward_lazy(fused) if self.lazy_regression
                                    else self.head(fused))
        if past is None or observed is None or self.fusion is None:
            return preds
        seen = observed[:, None]
        if isinstance(past, BranchTerms) and self.carry is not None:
            carry_term = (past.carry_gated if past.carry_gated is not None
                          else gate_past(past.carry, observed))
            carry_input = (past.carry_input if past.carry_input is not None
                           else self.fusion(current, carry_term))
            if self.training or not isinstance(carry_term, PastTerm):
                # the carry head's outputs where inference reads them (below), the own head's
                # elsewhere: training optimises the path the node runs (it took the carry
                # head at every cell without returns before stop 64, which inference never did)
                carried: dict[str, Tensor] = self.carry.head(carry_input)
                use = carry_cells(carry_term, observed)
                merged = {k: torch.where(use, carried[k], v) for k, v in preds.items()}
            else:
                # inference: the carry head only at the cells without returns within its
                # two-cell receptive field of the carry term, gathered; the own outputs
                # elsewhere (the observed cells among them), as in training
                _, _, H, W = carry_input.shape
                needed = dilated_cells(carry_term.index, H, W, CARRY_REACH, skip=observed)
                with one_thread(self.small_work_one_thread):
                    merged = self.carry.head.forward_at(carry_input, needed, preds)
            merged.update({OWN + k: v for k, v in preds.items()})
            return merged
        if self.cfg.fusion_gate != 'unobserved_output':
            return preds
        own: dict[str, Tensor] = self.head(self.fusion(current, None))
        return {k: torch.where(seen, own[k], v) for k, v in preds.items()}

    def decode(self, preds: dict[str, Tensor], observed: Tensor | None, k: int,
               score_threshold: Tensor, nms_iou_threshold: float, max_detections: int
               ) -> dict[str, Tensor]:
        """The boxes of one frame (a batch of one; :meth:`CenterHead.decode`, the config's NMS) and
        ``carried`` ``(N,)``: decoded by the carry branch (at a cell without returns). A
        carried box of which a surer box of its class lies within ``head.carry_nms_radius``
        is dropped: the carry head answers a relaxed window of a carried sample with a
        plateau, not one peak, and rotated-IoU NMS leaves its neighbours standing."""
        h = self.cfg.head
        radius = torch.tensor(h.circle_nms_radius, device=score_threshold.device)
        out = self.head.decode(preds, k, score_threshold, h.nms, nms_iou_threshold, radius,
                               max_detections)[0]
        n = out['scores'].shape[0]
        carried = torch.zeros(n, dtype=torch.bool, device=out['scores'].device)
        if observed is not None and OWN + 'heatmap' in preds:
            cells = out['cells']
            carried = ~observed[0, cells[:, 1], cells[:, 0]]
            keep = suppress_near(out['boxes'][:, :2].float(), out['labels'], carried,
                                 torch.tensor(h.carry_nms_radius))
            out = {name: v[keep] for name, v in out.items()}
            carried = carried[keep]
        out['carried'] = carried
        return out

    def sample_memory(self, fused: Tensor | FoldedFused, preds: dict[str, Tensor],
                      poses: NDArray[np.float64], stamps_ns: Sequence[int],
                      carried: SparseMemory | None = None,
                      observed: Tensor | None = None) -> Memory | None:
        """The state handed to the next frame (None for the single-frame model); with
        ``carried`` (:meth:`carried`) and ``observed`` (:meth:`encode_observed`), the carried
        samples the current input does not see are kept (``sampling.carry_s``). With a
        carry branch the samples come from the model's own outputs (``own.<name>``), so its
        own memory is the one it would have without the branch."""
        poses = np.asarray(poses, np.float64).copy()
        if self.cfg.temporal == 'none':
            return None
        if self.cfg.temporal == 'dense':
            dense = fused.dense() if isinstance(fused, FoldedFused) else fused
            return DenseMemory(dense.float(), list(stamps_ns), poses)
        if OWN + 'heatmap' in preds:
            preds = {k[len(OWN):]: v for k, v in preds.items() if k.startswith(OWN)}
        head = self.head
        prob = torch.sigmoid(preds['heatmap']).amax(dim=1)
        samples = significant_sampling(
            preds['heatmap'], lambda b, c: head.decode_cells(preds, b, c), self.cfg.sampling,
            self.grid, prob)
        cells, mask = relaxation_window(samples, self.cfg.sampling, self.grid)
        feats, probs = gather_window(fused, prob, samples.batch_index, cells, mask)
        feats = feats.float()           # float32 memory, also from a bfloat16 inference copy
        new = SparseMemory(samples.batch_index, self.grid.cell_to_xy(cells), feats, probs,
                           mask, samples.boxes, samples.velocities, list(stamps_ns), poses,
                           self.cfg.sampling.window)
        if carried is None or observed is None or not self.cfg.sampling.carry_s:
            return new
        return keep_carried(new, carried, observed, self.cfg.sampling, self.grid,
                            keep_new=self.carry is not None)

    # ------------------------------------------------------------------ training
    def forward(self, frames: Sequence[Sequence[Frame]],
                lost: Sequence[Sequence[bool]] | None = None,
                distiller: Distiller | None = None) -> dict[str, Tensor]:
        """Training forward (what DistributedDataParallel calls): :meth:`forward_sequence`."""
        return self.forward_sequence(frames, lost, distiller)

    def forward_sequence(self, frames: Sequence[Sequence[Frame]],
                         lost: Sequence[Sequence[bool]] | None = None,
                         distiller: Distiller | None = None) -> dict[str, Tensor]:
        """Losses over a batch of ``B`` sequences of ``T`` frames, memory passed frame to frame.

        :param lost: per sequence and frame, whether a sensor outage is active (those frames
            are not distilled); :param distiller: keeps ordinary frames' outputs near a frozen
            teacher's (:mod:`suit_ros.model.distill`).
        :return: ``hm_loss``, ``loc_loss``, ``geo_loss``, ``distill_loss`` (averaged over
            frames) and ``loss``.
        """
        T = len(frames[0])
        if any(len(seq) != T for seq in frames):
            raise ValueError('all sequences of a batch must have the same length')
        device = self.device
        memory: Memory | None = None
        prev_gt: list[Frame] | None = None
        totals = {'hm_loss': torch.zeros((), device=device),
                  'loc_loss': torch.zeros((), device=device),
                  'geo_loss': torch.zeros((), device=device),
                  'distill_loss': torch.zeros((), device=device)}
        geo_terms = 0
        for t in range(T):
            step = [seq[t] for seq in frames]
            points = [frame_points(f, device) for f in step]
            poses = np.stack([f.pose for f in step])
            stamps = [f.stamp_ns for f in step]
            current, observed = self.encode_observed(points)
            past, aux = self.past_term(memory, poses, stamps)
            fused = self.fuse(current, past, observed)
            preds = self.predict(current, past, fused, observed)
            targets = self.head.build_targets(*gt_tensors(step, device))
            losses = self.head.loss(preds, targets)
            totals['hm_loss'] = totals['hm_loss'] + losses['hm_loss']
            totals['loc_loss'] = totals['loc_loss'] + losses['loc_loss']
            if distiller is not None:
                # with the memory gate: every frame, on the cells with returns; else the
                # frames without an outage
                ordinary = torch.tensor([observed is not None or not (lost and lost[b][t])
                                         for b in range(len(step))], device=device)
                totals['distill_loss'] = (totals['distill_loss']
                                          + distiller.loss(current, preds, ordinary, observed))
            if 'geo_logits' in aux and prev_gt is not None and isinstance(memory, SparseMemory):
                totals['geo_loss'] = totals['geo_loss'] + self.geo_loss(memory, aux, prev_gt)
                geo_terms += 1
            memory = self.sample_memory(fused, preds, poses, stamps,
                                        self.carried(memory, aux, poses, stamps), observed)
            prev_gt = step
        out = {k: v / (max(geo_terms, 1) if k == 'geo_loss' else T) for k, v in totals.items()}
        out['loss'] = (out['hm_loss'] + self.cfg.head.loc_weight * out['loc_loss']
                       + self.cfg.geo_loss_weight * out['geo_loss'] + out['distill_loss'])
        return out

    def geo_loss(self, memory: SparseMemory, aux: dict[str, Tensor],
                 prev: Sequence[Frame]) -> Tensor:
        """GeoNet cross-entropy: each sample's target is the bin of its assigned GT velocity
        (rotated into the current frame), zero velocity when no GT box contains it; a sample in
        a box whose velocity is unknown (NaN) is left out."""
        sel = aux['sample_index']
        bi = memory.batch_index[sel]
        centres = memory.cell_xy[sel][:, memory.cell_xy.shape[1] // 2]          # (M, 2)
        vel, valid = assign_velocities(centres, bi, prev)
        # a sample on an object whose motion is unknown (NaN) teaches nothing either way
        keep = ~(valid & ~torch.isfinite(vel).all(dim=1))
        vel = rotate_velocities(vel[keep], bi[keep], aux['T_now_prev'].numpy())
        if self.geonet is None:
            raise RuntimeError('geo_loss needs the suit variant (GeoNet)')
        return self.geonet.loss(aux['geo_logits'][keep], vel, valid[keep])


def carry_cells(carry_term: Tensor | PastTerm, observed: Tensor, reach: int = CARRY_REACH
                ) -> Tensor:
    """``(B, 1, H, W)`` bool: the cells a carry head answers for, those without returns
    within ``reach`` cells (a square: its 3 x 3 layers' receptive field) of a cell the gated
    carry term adds to; what inference gathers (:func:`~suit_ros.model.head.dilated_cells`)."""
    B, H, W = observed.shape
    if isinstance(carry_term, PastTerm):
        mask = torch.zeros(B * H * W, dtype=torch.bool, device=observed.device)
        mask[dilated_cells(carry_term.index, H, W, reach, skip=observed)] = True
        return mask.view(B, 1, H, W)
    support = (carry_term.detach() != 0).any(1, keepdim=True).float()
    grown = torch.nn.functional.max_pool2d(support, 2 * reach + 1, 1, reach) > 0
    return grown & ~observed[:, None]


def gate_past(past: Tensor | PastTerm, observed: Tensor) -> Tensor | PastTerm:
    """The past term without its entries at ``observed`` cells (``(B, H, W)`` bool)."""
    if isinstance(past, PastTerm):
        keep = ~observed.reshape(-1)[past.index]
        return PastTerm(past.index[keep], past.values[keep], past.shape, past.distinct)
    gated: Tensor = past * (~observed)[:, None].to(past.dtype)
    return gated


def frame_points(frame: Frame, device: torch.device) -> Tensor:
    """A frame's ``(N, 5)`` float32 points on ``device`` (time lag 0 appended to 4 columns)."""
    pts = np.asarray(frame.points, np.float32)
    if pts.shape[1] == 4:
        pts = np.concatenate([pts, np.zeros((len(pts), 1), np.float32)], axis=1)
    return torch.from_numpy(np.ascontiguousarray(pts[:, :5])).to(device)


def gt_tensors(frames: Sequence[Frame], device: torch.device
               ) -> tuple[list[Tensor], list[Tensor], list[Tensor], list[Tensor]]:
    """GT boxes, velocities and labels of each frame as tensors (empty when a frame has none),
    and its ignore boxes ``(K, 7)``."""
    boxes, vels, labels, ignore = [], [], [], []
    for f in frames:
        if f.gt is None:
            raise ValueError(f'frame {f.stamp_ns} of {f.sequence_id!r} has no ground truth')
        boxes.append(torch.from_numpy(f.gt.boxes).to(device))
        vels.append(torch.from_numpy(f.gt.velocities).to(device))
        labels.append(torch.from_numpy(f.gt.labels).to(device))
        ig = np.zeros((0, 7), np.float32) if f.ignore_boxes is None else f.ignore_boxes
        ignore.append(torch.from_numpy(np.asarray(ig, np.float32).reshape(-1, 7)).to(device))
    return boxes, vels, labels, ignore


def assign_velocities(centres: Tensor, batch_index: Tensor, frames: Sequence[Frame],
                      margin: float = 0.5) -> tuple[Tensor, Tensor]:
    """GT velocity of the box (enlarged by ``margin`` m) containing each sample centre.

    Among several containing boxes the nearest centre wins. :return: velocities ``(M, 2)``
    (zeros when unassigned; NaN where the box's velocity is unknown) and a validity mask
    ``(M,)`` (inside a box).
    """
    M = centres.shape[0]
    vel = centres.new_zeros(M, 2)
    valid = torch.zeros(M, dtype=torch.bool, device=centres.device)
    for b, f in enumerate(frames):
        idx = torch.nonzero(batch_index == b, as_tuple=True)[0]
        if idx.numel() == 0 or f.gt is None or len(f.gt) == 0:
            continue
        boxes = torch.from_numpy(f.gt.boxes).to(centres)
        d = centres[idx][:, None, :] - boxes[None, :, :2]                         # (m, G, 2)
        c, s = torch.cos(boxes[:, 6]), torch.sin(boxes[:, 6])
        along = (d[..., 0] * c + d[..., 1] * s).abs()
        across = (-d[..., 0] * s + d[..., 1] * c).abs()
        inside = (along <= boxes[:, 3] / 2 + margin) & (across <= boxes[:, 4] / 2 + margin)
        dist = d.norm(dim=-1).masked_fill(~inside, float('inf'))
        best = dist.argmin(dim=1)
        hit = torch.isfinite(dist.gather(1, best[:, None]))[:, 0]
        gv = torch.from_numpy(f.gt.velocities).to(centres)
        vel[idx[hit]] = gv[best[hit]]
        valid[idx[hit]] = True
    return vel, valid
