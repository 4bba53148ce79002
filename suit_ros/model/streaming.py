"""StreamingDetector: the node's model step. One call per frame; the SUIT memory lives inside.

The same object serves the live node and ``suit-ros detect-bag``, so both produce the same
detections for the same frames.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import time

import numpy as np
from numpy.typing import NDArray
import torch

from suit_ros.model.detector import Memory, SUITDetector
from suit_ros.structures import Detections


@dataclass
class StepResult:
    """What one frame produced.

    :param timings: seconds per stage: ``pillars``, ``backbone``, ``fusion`` (GeoNet + fusion),
        ``head_decode``, ``sampling``, ``total``.
    """

    detections: Detections
    memory_samples: int
    memory_bytes: int
    used_memory: bool
    timings: dict[str, float] = field(default_factory=dict)


class StreamingDetector:
    """Run a SUITDetector frame by frame, carrying its temporal memory.

    :param score_thresholds: per-class thresholds (defaults to the config's single threshold);
        changeable at runtime with :meth:`set_thresholds`.
    """

    def __init__(self, model: SUITDetector, device: torch.device | str | None = None,
                 score_thresholds: list[float] | None = None,
                 nms_iou_threshold: float | None = None, max_detections: int | None = None
                 ) -> None:
        self.device = torch.device(device) if device is not None else model.device
        self.model = model.to(self.device).eval()
        self.cfg = model.cfg
        self.memory: Memory | None = None
        self.last_reset_reason = 'start'
        self.set_thresholds(score_thresholds, nms_iou_threshold, max_detections)

    def set_thresholds(self, score_thresholds: list[float] | None = None,
                       nms_iou_threshold: float | None = None,
                       max_detections: int | None = None) -> None:
        """Change the decoding thresholds (safe between frames)."""
        K = len(self.cfg.class_names)
        thr = ([self.cfg.head.score_threshold] * K if score_thresholds is None
               else [float(v) for v in score_thresholds])
        if len(thr) != K:
            raise ValueError(f'need {K} score thresholds (one per class), got {len(thr)}')
        self.score_thresholds = torch.tensor(thr, dtype=torch.float32, device=self.device)
        self.nms_iou_threshold = (self.cfg.head.nms_iou_threshold if nms_iou_threshold is None
                                  else float(nms_iou_threshold))
        self.max_detections = (self.cfg.head.max_detections if max_detections is None
                               else int(max_detections))

    def reset(self, reason: str = 'reset') -> None:
        """Forget the memory: the next frame runs single-frame."""
        self.memory = None
        self.last_reset_reason = reason

    @property
    def memory_bytes(self) -> int:
        """Bytes held by the temporal memory now."""
        return 0 if self.memory is None else self.memory.nbytes

    def _sync(self) -> float:
        if self.device.type == 'cuda':
            torch.cuda.synchronize(self.device)
        return time.perf_counter()

    @torch.inference_mode()
    def step(self, points: NDArray[np.float32], pose: NDArray[np.float64] | None,
             stamp_ns: int, frame_id: str) -> StepResult:
        """Detect in one frame.

        :param points: ``(N, 4)`` x, y, z, intensity (0..1) or ``(N, 5)`` with time lag.
        :param pose: ``T_odom_lidar`` at the stamp, or None: the frame runs single-frame and
            the memory is reset (no way to move it without a pose).
        """
        m = self.model
        t0 = self._sync()
        pts = np.asarray(points, np.float32)
        if pts.ndim != 2 or pts.shape[1] not in (4, 5):
            raise ValueError(f'points must be (N, 4) or (N, 5), got {pts.shape}')
        if pts.shape[1] == 4:
            pts = np.concatenate([pts, np.zeros((len(pts), 1), np.float32)], axis=1)
        tensor = torch.from_numpy(np.ascontiguousarray(pts)).to(self.device)
        if pose is None and self.memory is not None:
            self.reset('no pose')
        rows = torch.cat([tensor.new_zeros((tensor.shape[0], 1)), tensor], dim=1)
        bev = m.pillars(rows, 1)
        t1 = self._sync()
        current = m.backbone(bev)
        t2 = self._sync()
        poses = np.asarray(pose if pose is not None else np.eye(4), np.float64)[None]
        past, _ = m.past_term(self.memory, poses, [stamp_ns], [frame_id])
        used = past is not None
        fused = m.fuse(current, past)
        t3 = self._sync()
        preds = m.head(fused)
        h = self.cfg.head
        radius = torch.tensor(h.circle_nms_radius, device=self.device)
        out = m.head.decode(preds, h.top_k, self.score_thresholds, h.nms,
                            self.nms_iou_threshold, radius, self.max_detections)[0]
        t4 = self._sync()
        self.memory = (m.sample_memory(fused, preds, poses, [stamp_ns], [frame_id])
                       if pose is not None else None)
        t5 = self._sync()
        det = Detections(out['boxes'].float().cpu().numpy(),
                         out['velocities'].float().cpu().numpy(),
                         out['scores'].float().cpu().numpy(), out['labels'].cpu().numpy())
        timings = {'pillars': t1 - t0, 'backbone': t2 - t1, 'fusion': t3 - t2,
                   'head_decode': t4 - t3, 'sampling': t5 - t4, 'total': t5 - t0}
        samples = 0 if self.memory is None else self.memory.num_samples
        return StepResult(det, samples, self.memory_bytes, used, timings)
