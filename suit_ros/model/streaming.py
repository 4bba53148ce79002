"""StreamingDetector: the node's model step. One call per frame; the SUIT memory lives inside.

The same object serves the live node and ``suit-ros detect-bag``, so both produce the same
detections for the same frames.
"""
from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor, wait
from dataclasses import dataclass, field
import os
import threading
import time
from typing import Any, TypeVar, cast

import numpy as np
from numpy.typing import NDArray
import torch

from suit_ros.box_fit import BOX_FIT_MODES, BoxFitMode, fit_to_faces
from suit_ros.ground import GROUND_MODES, GroundMode, LocalGround
from suit_ros.model.detector import Memory, SUITDetector
from suit_ros.model.fusion import BranchTerms, PastTerm
from suit_ros.model.inference import (
    PrecisionChoice,
    inference_copy,
    one_thread,
    resolve_precision,
)
from suit_ros.model.memory import SparseMemory
from suit_ros.model.sweeps import SweepBuffer, already_accumulated, boxes_to_lidar
from suit_ros.msg_adapters.detections import HELD_CARRIED, HELD_COASTED, HELD_SEEN
from suit_ros.ops.geometry import count_points_in_boxes
from suit_ros.overhang import OverhangMode
from suit_ros.structures import Detections
from suit_ros.tracking import Tracker, TrackerConfig, track_step


@dataclass
class StepResult:
    """What one frame produced.

    :param model_points: points in the model input (all accumulated sweeps).
    :param timings: seconds per stage: ``sweeps`` (accumulation), ``encode`` (pillars +
        backbone), ``fusion`` (GeoNet and the past term, or the wait for them where they run
        beside the encoder, and the fusion), ``head_decode``, ``sampling``, ``tracking``
        (detections to numpy, the tracker, the published cut, the returns in each box,
        boxes into the LiDAR frame), ``total``.
    :param track_ids: per detection, its velocity-filter track (0: no filter, or no pose).
    :param num_points: per detection, the current sweep's returns inside its box (0: a box
        held by the memory or the tracker where the sweep shows nothing).
    :param held: per detection, why it is there (the detections cloud's ``held`` field): 0
        decoded from what the input shows, 1 decoded by a carry branch where it has no returns,
        2 coasted by the tracker (no detection this frame).
    :param velocity_std: per detection, the standard deviation of each velocity component
        (m/s; :attr:`suit_ros.tracking.Tracker.velocity_std`); empty without a tracker.
    """

    detections: Detections
    memory_samples: int
    memory_bytes: int
    used_memory: bool
    model_points: int = 0
    timings: dict[str, float] = field(default_factory=dict)
    track_ids: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    num_points: NDArray[np.uint32] = field(default_factory=lambda: np.zeros(0, np.uint32))
    velocity_std: NDArray[np.float32] = field(default_factory=lambda: np.zeros(0, np.float32))
    held: NDArray[np.uint8] = field(default_factory=lambda: np.zeros(0, np.uint8))

    @property
    def carried(self) -> NDArray[np.bool_]:
        """Per detection, held where the input has no returns: decoded by a carry branch or
        coasted by the tracker (published at the carry thresholds): ``held > 0``."""
        return self.held > HELD_SEEN


Result = TypeVar('Result')


def _in_inference_mode(fn: Callable[..., Result], *args: Any) -> Result:
    """``fn(*args)`` in inference mode (a thread's own: it is not inherited)."""
    with torch.inference_mode():
        return fn(*args)


def _usable_cores() -> int:
    """The cores this process may run on (all of the machine's where that is not known)."""
    if hasattr(os, 'sched_getaffinity'):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def _one_torch_thread() -> None:
    """Set the calling thread's torch thread count to 1 (after torch's own first setting of
    it, which a thread makes on its first use and would otherwise make later)."""
    torch.get_num_threads()
    torch.set_num_threads(1)


def _as_points(points: NDArray[np.floating[Any]]) -> NDArray[np.float32]:
    """A sweep as the streaming detector takes it: ``(N, 4)`` or ``(N, 5)`` float32."""
    pts = np.asarray(points, np.float32)
    if pts.ndim != 2 or pts.shape[1] not in (4, 5):
        raise ValueError(f'points must be (N, 4) or (N, 5), got {pts.shape}')
    return pts


class StreamingDetector:
    """Run a SUITDetector frame by frame, carrying its temporal memory.

    :param score_thresholds: per-class thresholds of what is returned (published), applied to
        the final scores (after the tracker's smoothing); the model still decodes down to the
        config's ``head.score_threshold`` so the tracker sees faint detections. None: the
        config's single threshold (what AP evaluation uses). Changeable at runtime with
        :meth:`set_thresholds`.
    :param precision: the inference copy's precision (:mod:`suit_ros.model.inference`):
        ``float32`` (default), ``bfloat16``, or ``auto`` (bfloat16 on a CPU with bfloat16
        units); the one chosen is :attr:`precision`.
    :param tracker: when given, the detections' velocities are filtered over frames
        (:mod:`suit_ros.tracking`) and each gets a track id; None: the head's velocities.
    :param ground: ``as_given``: the input's heights as they come (base_link's ground plane);
        ``local``: leveled to the ground estimated under each point before the model sees
        them, the boxes put back on it (:mod:`suit_ros.ground`); None: as the checkpoint was
        trained (``pillars.ground``).
    :param overhang: ``keep``: every return; ``drop``: the returns that hang over a gap in
        their column (canopies, awnings) removed before the model (:mod:`suit_ros.overhang`);
        None: as the checkpoint's config says (``pillars.overhang``).
    :param box_fit: ``faces``: car boxes moved onto the returns of the faces the sensor sees
        (:mod:`suit_ros.box_fit`); ``off``: as the model places them.
    :param beside: compute a sparse memory's past term (the last memory moved into this
        frame and projected: GeoNet, the sparse terms) in a second thread, on one torch thread,
        while the encoder runs on this cloud; it needs the memory and the pose, not the cloud.
        The same results; the step's latency shorter by about the past term's time (1-2 ms),
        its CPU time the same. The thread is started by the thread that steps (it takes that
        thread's priority: the node's model thread runs below its callbacks); :meth:`close`
        ends it. None: on the CPU where the process may use a core that torch's threads
        leave free, decided at each step (the node's default on two cores: one torch
        thread): where the encoder's threads take every core, the past term's thread
        lengthens the encoder by more than it saves (docs/experiments/carry_node_default). The next
        memory's sampling stays in the step's own thread: beside the tracker (both mostly
        interpreter work) it lengthened the step (docs/experiments/step_beside).
    """

    def __init__(self, model: SUITDetector, device: torch.device | str | None = None,
                 score_thresholds: list[float] | None = None,
                 nms_iou_threshold: float | None = None, max_detections: int | None = None,
                 candidates: int | None = None, precision: PrecisionChoice = 'float32',
                 tracker: TrackerConfig | None = None, ground: GroundMode | None = None,
                 overhang: OverhangMode | None = None, box_fit: BoxFitMode = 'off',
                 beside: bool | None = None) -> None:
        self.device = torch.device(device) if device is not None else model.device
        self.beside: bool | None = None if beside is None else bool(beside)
        self._worker: ThreadPoolExecutor | None = None
        self._worker_owner = 0
        self.precision = resolve_precision(precision, self.device)
        # steps run on an inference copy (batch norms folded); ``model`` itself is untouched
        self.model = cast(SUITDetector, inference_copy(model.to(self.device),
                                                       precision=self.precision))
        self.cfg = model.cfg
        # the memory sampled at the last frame: the next frame fuses it
        self._memory: Memory | None = None
        self.sweeps = SweepBuffer(self.cfg.sweeps)
        self.set_ground(ground)
        self.set_overhang(overhang)
        self.set_box_fit(box_fit)
        self.tracks = (None if tracker is None
                       else Tracker(tracker, self.cfg.class_names))
        self._next_track_id = 1        # a tracker turned on again goes on from here
        self.last_reset_reason = 'start'
        # the checkpoint's published thresholds (set by whoever loaded it; None: not known),
        # and those of the boxes its carry branch holds where the cloud shows nothing
        self.published_thresholds: list[float] | None = None
        self.published_carry_thresholds: list[float] | None = None
        # set keep_terms to inspect the fusion: (W1 F_t, past term or None) of the last step
        self.keep_terms = False
        self.last_terms: tuple[torch.Tensor, torch.Tensor | None] | None = None
        self.set_thresholds(score_thresholds, nms_iou_threshold, max_detections, candidates)

    def set_thresholds(self, score_thresholds: list[float] | None = None,
                       nms_iou_threshold: float | None = None,
                       max_detections: int | None = None, candidates: int | None = None,
                       carry_thresholds: list[float] | None = None) -> None:
        """Change the published score thresholds and the decoding settings (safe between
        frames).

        :param candidates: heatmap peaks kept before the score threshold and NMS (default: the
            config's ``head.top_k``).
        :param carry_thresholds: per class, for the boxes a carry branch decodes where the
            input has no returns (None: ``score_thresholds``).
        """
        K = len(self.cfg.class_names)
        thr = ([self.cfg.head.score_threshold] * K if score_thresholds is None
               else [float(v) for v in score_thresholds])
        carry = thr if carry_thresholds is None else [float(v) for v in carry_thresholds]
        if len(thr) != K or len(carry) != K:
            raise ValueError(f'need {K} score thresholds (one per class), got {len(thr)}'
                             f' and {len(carry)} carry thresholds')
        self.score_thresholds = np.asarray(thr, np.float32)
        self.carry_thresholds = np.asarray(carry, np.float32)
        # decode down to the evaluation threshold (or lower, when a published one is lower)
        self.decode_thresholds = torch.tensor(
            np.minimum(np.minimum(thr, carry), self.cfg.head.score_threshold),
            dtype=torch.float32, device=self.device)
        self.nms_iou_threshold = (self.cfg.head.nms_iou_threshold if nms_iou_threshold is None
                                  else float(nms_iou_threshold))
        self.max_detections = (self.cfg.head.max_detections if max_detections is None
                               else int(max_detections))
        self.candidates = self.cfg.head.top_k if candidates is None else int(candidates)
        if self.candidates < 1:
            raise ValueError(f'candidates must be >= 1, got {self.candidates}')

    def set_ground(self, ground: GroundMode | None) -> None:
        """Choose how the input's heights are referenced (see ``ground``; None: as the
        checkpoint was trained)."""
        if ground is None:
            ground = self.cfg.pillars.ground
        if ground not in GROUND_MODES:
            raise ValueError(f'ground must be one of {GROUND_MODES}, got {ground!r}')
        self.ground: GroundMode = ground
        self._ground = (LocalGround(self.cfg.pillars.point_range) if ground == 'local'
                        else None)

    def set_overhang(self, overhang: OverhangMode | None) -> None:
        """Keep or drop the returns that hang over a gap in their column (see ``overhang``;
        None: the checkpoint's choice)."""
        self.model.pillars.set_overhang(self.cfg.pillars.overhang if overhang is None
                                        else overhang)

    @property
    def overhang(self) -> OverhangMode:
        """Whether the returns that hang are kept or dropped now."""
        return self.model.pillars.overhang

    def set_box_fit(self, box_fit: BoxFitMode) -> None:
        """Fit the car boxes to their visible faces, or not (see ``box_fit``)."""
        if box_fit not in BOX_FIT_MODES:
            raise ValueError(f'box_fit must be one of {BOX_FIT_MODES}, got {box_fit!r}')
        self.box_fit: BoxFitMode = box_fit

    def set_tracker(self, config: TrackerConfig | None) -> None:
        """Turn the tracker on (with ``config``) or off (None). A tracker already on takes a
        changed config in place: its tracks and their ids go on, and a tracker turned off and on
        again goes on counting ids where the last one stopped (a downstream stack must not see
        an id used twice)."""
        if config is None:
            if self.tracks is not None:          # turned on again later, ids go on from here
                self._next_track_id = self.tracks.next_id
            self.tracks = None
        elif self.tracks is None:
            self.tracks = Tracker(config, self.cfg.class_names)
            self.tracks.next_id = self._next_track_id
        elif self.tracks.config != config:
            self.tracks.reconfigure(config)

    def reset(self, reason: str = 'reset', sweeps: bool = True,
              tracks: bool | None = None) -> None:
        """Forget the feature memory and (unless ``sweeps`` is False) the buffered sweeps and
        the tracker's tracks (``tracks``: whether the tracks go too; None: with the sweeps):
        the next frame runs single-frame."""
        self._memory = None
        if sweeps:
            self.sweeps.clear()
        if (sweeps if tracks is None else tracks) and self.tracks is not None:
            self.tracks.reset()
        self.last_reset_reason = reason

    def warm_up(self, points: int = 130_000) -> None:
        """Run the model on a made-up cloud (ground rings and a few walls, ``points`` returns)
        as many times as it reads sweeps, so the last input has as many points as a 128-beam
        stream gives, then forget it: the first real clouds do not pay for the compiled
        kernels' loading, oneDNN's primitive creation and the allocator's growth (100-180 ms
        extra on the first frames of a 64-beam drive, measured). A throwaway tracker runs
        (the node turns its own on later) and the state is reset, so what follows is what it
        would have been without this (tracks and track ids included)."""
        from suit_ros.ops.kernels import warm_up
        warm_up()
        rng = np.random.default_rng(0)
        az = rng.uniform(-np.pi, np.pi, points)
        r = np.where(rng.random(points) < 0.7, rng.uniform(3, 40, points),
                     rng.uniform(8, 20, points))
        z = np.where(r > 7.9, rng.uniform(-1.8, 1.5, points), -1.8)
        cloud = np.c_[r * np.cos(az), r * np.sin(az), z,
                      rng.uniform(0, 1, points)].astype(np.float32)
        tracks = self.tracks          # a throwaway tracker, whether one is on or not yet
        self.tracks = Tracker(tracks.config if tracks is not None else TrackerConfig(),
                              self.cfg.class_names)
        reason = self.last_reset_reason
        try:
            pose = np.eye(4)
            for k in range(max(self.cfg.sweeps, 2)):
                pose[0, 3] = 0.8 * k
                self.step(cloud, 10**9 + k * 10**8, pose)
        finally:
            self.tracks = tracks
            self.reset()
            self.last_reset_reason = reason
            self.close()        # the thread that steps next starts its own

    @property
    def memory(self) -> Memory | None:
        """The memory the next frame fuses (None after a reset)."""
        return self._memory

    @property
    def memory_bytes(self) -> int:
        """Bytes held by the temporal feature memory now (the sweep buffer not included)."""
        return self._memory.nbytes if self._memory is not None else 0

    def _start(self, fn: Callable[..., Result], *args: Any) -> Future[Result] | None:
        """``fn(*args)`` started in the step's second thread (:attr:`beside`; in inference
        mode), or None: the caller runs it itself."""
        if not self.uses_beside():
            return None
        caller = threading.get_ident()
        if self._worker is not None and self._worker_owner != caller:
            # made by another thread (a warm-up before the node's model thread started): a
            # new thread takes the priority of the thread that starts it, so it follows the
            # one that steps now (the node lowers its model thread's)
            self.close()
        if self._worker is None:
            threads = torch.get_num_threads()
            # one torch thread, beside the encoder's team (the process-wide default for
            # threads that start later, which this sets too, put back)
            self._worker = ThreadPoolExecutor(1, thread_name_prefix='suit_memory',
                                              initializer=_one_torch_thread)
            self._worker_owner = caller
            self._worker.submit(int).result()
            torch.set_num_threads(threads)
        return self._worker.submit(_in_inference_mode, fn, *args)

    def uses_beside(self) -> bool:
        """Whether a step now computes the past term in the second thread (:attr:`beside`;
        None: on the CPU, where torch's threads leave this process a core)."""
        if self.beside is not None:
            return self.beside
        return self.device.type == 'cpu' and _usable_cores() > torch.get_num_threads()

    def close(self) -> None:
        """End the second thread (:attr:`beside`), if one runs; a later step starts another."""
        if self._worker is not None:
            self._worker.shutdown(wait=True)
            self._worker = None

    def _sync(self) -> float:
        if self.device.type == 'cuda':
            torch.cuda.synchronize(self.device)
        return time.perf_counter()

    def add_sweep(self, points: NDArray[np.float32], stamp_ns: int,
                  T_odom_base: NDArray[np.float64] | None,
                  T_base_lidar: NDArray[np.float64] | None = None) -> bool:
        """Buffer a sweep without detecting in it: a cloud the node skipped while the model
        was busy. The next :meth:`step`'s input then holds the sweeps just before it (0.1 s
        apart at 10 Hz, as in training) instead of the last ones the model ran on; the memory
        and the tracks are untouched. A sweep without a pose is not buffered.

        :param points: as :meth:`step`'s.
        :return: whether it was buffered (no pose, an accumulation already, or a model of one
            sweep: not).
        """
        pts = _as_points(points)
        if T_odom_base is None:
            return False
        T_bl = np.eye(4) if T_base_lidar is None else np.asarray(T_base_lidar, np.float64)
        return self.sweeps.add(pts, np.asarray(T_odom_base, np.float64) @ T_bl, stamp_ns)

    def drop_stale_memory(self, stamp_ns: int, max_age_s: float) -> str | None:
        """Forget the feature memory (the sweeps and the tracks stay) when it is older than
        ``max_age_s`` at ``stamp_ns``: the model ran on no cloud for that long while the
        stream went on (the clouds in between only buffered, :meth:`add_sweep`).

        :return: why it was dropped, or None (kept, or none held).
        """
        if self._memory is None:
            return None
        age = (stamp_ns - max(self._memory.stamps_ns)) * 1e-9
        if age <= max_age_s:
            return None
        reason = f'memory {age:.2f} s old (the model ran on no cloud since) exceeds max_gap_s'
        self.reset(reason, sweeps=False)
        return reason

    def _published(self, out: dict[str, torch.Tensor], pts: NDArray[np.float32],
                   model_points: NDArray[np.float32], stamp_ns: int,
                   poses: NDArray[np.float64], posed: bool, T_bl: NDArray[np.float64]
                   ) -> tuple[Detections, NDArray[np.int64], NDArray[np.uint8],
                              NDArray[np.float32], NDArray[np.uint32]]:
        """A step's decoded boxes as published: fitted to their faces, tracked (with a pose:
        ``posed``), back on the road, cut at the published thresholds, in the LiDAR frame,
        with this cloud's returns in each; and their track ids, held flags (``held`` of
        :class:`StepResult`), velocity standard deviations and returns."""
        det = Detections(out['boxes'].float().cpu().numpy(),
                         out['velocities'].float().cpu().numpy(),
                         out['scores'].float().cpu().numpy(), out['labels'].cpu().numpy())
        carried = out['carried'].cpu().numpy()
        held = np.where(carried, HELD_CARRIED, HELD_SEEN).astype(np.uint8)
        ids = np.zeros(len(det), np.int64)
        vel_std = np.zeros(0, np.float32)
        # this cloud's own returns, the same rows of the input as it came and of the model
        # input: the first ones, or those without a time lag when it came accumulated
        now = pts[:, 4] == 0 if already_accumulated(pts) else slice(None, len(pts))
        if self.box_fit == 'faces' and len(det):
            det.boxes[:] = fit_to_faces(det.boxes, det.labels, det.scores, model_points[now],
                                        T_bl[:2, 3], tuple(self.cfg.class_names))
        if self.tracks is not None and posed:
            # in the frame of the model input (leveled or not): the sweep velocities read
            # the boxes' returns from the input's heights; coasting, the current sweep's
            det, ids = track_step(self.tracks, det, stamp_ns, poses[0], model_points,
                                  carried=carried, current=model_points[now],
                                  sensor=T_bl[:3, 3])
            # the tracks held where the sweep shows nothing: coasted (and carried, for the cut)
            held = np.concatenate([held, np.full(self.tracks.coasted, HELD_COASTED, np.uint8)])
            carried = held > HELD_SEEN
            vel_std = self.tracks.velocity_std
        elif self.tracks is not None:   # no pose: nothing tracked, each as the head measured it
            fc = self.tracks.config
            vel_std = fc.published_std(fc.vel_sigma, det.velocities)
        if self._ground is not None and len(det):
            det.boxes[:, 2] += self._ground.under(det.boxes[:, :2])   # back on the road
        published = det.scores >= np.where(carried, self.carry_thresholds[det.labels],
                                           self.score_thresholds[det.labels])
        if not published.all():
            det, ids, held = det.select(published), ids[published], held[published]
            if self.tracks is not None:
                vel_std = vel_std[published]
        det = boxes_to_lidar(det, T_bl)
        # the returns of this cloud in each box, counted on the input as it came (LiDAR
        # frame), not on the accumulated sweeps
        num_points = count_points_in_boxes(pts[now, :3], det.boxes)
        return det, ids, held, vel_std, num_points

    @torch.inference_mode()
    def step(self, points: NDArray[np.float32], stamp_ns: int,
             T_odom_base: NDArray[np.float64] | None,
             T_base_lidar: NDArray[np.float64] | None = None) -> StepResult:
        """Detect in one sweep.

        :param points: ``(N, 4)`` x, y, z, intensity (0..1) (or ``(N, 5)`` with a time lag) in
            the LiDAR frame.
        :param T_odom_base: the vehicle pose at the stamp, or None: the frame runs single-frame
            and the memory and sweep buffer are reset (no way to move them without a pose).
        :param T_base_lidar: the LiDAR extrinsic (identity when None: points in base_link).
        :return: detections in the LiDAR frame (the input cloud's frame).
        """
        m = self.model
        t0 = self._sync()
        pts = _as_points(points)
        T_bl = np.eye(4) if T_base_lidar is None else np.asarray(T_base_lidar, np.float64)
        if T_odom_base is None and (self.memory is not None or len(self.sweeps)
                                    or (self.tracks is not None and len(self.tracks))):
            self.reset('no pose')       # (tracks kept by a reset of the input's reading too)
        T_ol = None if T_odom_base is None else np.asarray(T_odom_base, np.float64) @ T_bl
        poses = np.asarray(T_odom_base if T_odom_base is not None else np.eye(4),
                           np.float64)[None]
        model_points = self.sweeps.push(pts, T_ol, stamp_ns, T_bl)
        if self._ground is not None:
            model_points = self._ground.level(model_points)
        tensor = torch.from_numpy(model_points).to(self.device)
        t1 = self._sync()
        # the past term needs the last memory and this pose, not this cloud: it is computed
        # beside the encoder (whose convolutions leave the interpreter to it); a dense
        # memory's warp is no small work and stays here
        small = self.model.small_work_one_thread
        past_term = (self._start(m.past_term, self.memory, poses, [stamp_ns])
                     if isinstance(self.memory, SparseMemory) else None)
        try:
            current, observed = m.encode_observed([tensor])
        except BaseException:
            if past_term is not None:       # not left running past the step
                wait([past_term])
            raise
        t2 = self._sync()
        if past_term is not None:
            past, aux = past_term.result()
        else:
            with one_thread(small and isinstance(self.memory, SparseMemory)):
                past, aux = m.past_term(self.memory, poses, [stamp_ns])
        used = past is not None
        fused = m.fuse(current, past, observed)
        if self.keep_terms:
            own = m.fusion.current(current) if m.fusion is not None else current
            shown = past.own if isinstance(past, BranchTerms) else past
            self.last_terms = (own.float(),
                               shown.dense() if isinstance(shown, PastTerm) else shown)
        t3 = self._sync()
        preds = m.predict(current, past, fused, observed)
        with one_thread(small):     # the small work that is left, on one torch thread
            out = m.decode(preds, observed, self.candidates, self.decode_thresholds,
                           self.nms_iou_threshold, self.max_detections)
            t4 = self._sync()
            if T_odom_base is not None:
                memory = m.sample_memory(fused, preds, poses, [stamp_ns],
                                         m.carried(self.memory, aux, poses, [stamp_ns]),
                                         observed)
                if memory is not None:
                    self._memory = memory
            t5 = self._sync()
            det, ids, held, vel_std, num_points = self._published(
                out, pts, model_points, stamp_ns, poses, T_odom_base is not None, T_bl)
        t6 = self._sync()
        timings = {'sweeps': t1 - t0, 'encode': t2 - t1, 'fusion': t3 - t2,
                   'head_decode': t4 - t3, 'sampling': t5 - t4, 'tracking': t6 - t5,
                   'total': t6 - t0}
        samples = self._memory.num_samples if self._memory is not None else 0
        return StepResult(det, samples, self.memory_bytes, used, len(model_points), timings,
                          ids, num_points, vel_std, held)
