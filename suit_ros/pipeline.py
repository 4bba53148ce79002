"""The detection pipeline shared by the live node and ``suit-ros detect-bag``.

Message in, messages out: PointCloud2 -> (N, 4) points (non-finite dropped, range-limited,
intensity scaled) -> ego pose from the odometry buffer at the cloud stamp composed with the
LiDAR extrinsic -> memory-reset rules -> the model's streaming step -> detections PointCloud2 and
MarkerArray with the input header. Every failure becomes a counted, explained status instead of
an exception, so a caller can always publish a (possibly empty) correctly stamped result.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import time
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from suit_ros.coverage import SectorCoverage
from suit_ros.data.augment import mirror_detections
from suit_ros.deskew import TIME_FIELDS, deskew_sweep, relative_times, sweep_speed
from suit_ros.errors import ConfigError
from suit_ros.model.streaming import StreamingDetector
from suit_ros.msg_adapters.classes import MessageClasses
from suit_ros.msg_adapters.detections import detections_to_markerarray, detections_to_pointcloud2
from suit_ros.msg_adapters.errors import MessageError, PoseLookupError
from suit_ros.msg_adapters.odometry import PoseBuffer, odometry_to_pose, stamp_to_ns
from suit_ros.msg_adapters.pointcloud2 import pointcloud2_to_xyzi
from suit_ros.ops.geometry import mirror_points, mirror_transform, pose_from_xyz_rpy
from suit_ros.ops.kernels import in_range, in_range_times
from suit_ros.params import DetectorParams, TrafficSide
from suit_ros.structures import Detections
from suit_ros.tracking import TrackerConfig
from suit_ros.traffic_side import TrafficSideVote

# the pipeline's settings are the node's: one owner (suit_ros.params)
PipelineParams = DetectorParams
# max_pose_jump_m is a distance per this much of the gap between two clouds (at least one such
# distance): 5 m per 0.1 s is 50 m/s, so a cloud dropped at highway speed is no jump
POSE_JUMP_PERIOD_S = 0.1

# why a frame ran on its own sweep (no pose): the pipeline says it, diagnostics count it
SingleFrameReason = Literal['no_odometry', 'outside_odometry']

# input-contract reasons a frame can be flagged with (diagnostics and detect-bag count them)
InputWarning = Literal['unusable_cloud', 'empty_cloud', 'no_intensity', 'intensity_range',
                       'too_few_points', 'frame_changed', 'sector_gap', 'point_times']


def load_detector(params: DetectorParams) -> tuple[StreamingDetector, Any, dict[str, Any]]:
    """The streaming detector ``params`` asks for: its checkpoint (the shipped one when empty),
    device (``auto``: CUDA when available) and precision (``auto``: see
    :func:`suit_ros.model.inference.resolve_precision`).

    :return: ``(detector, model config, checkpoint metadata)``.
    """
    import torch

    from suit_ros.checkpoint import load_checkpoint, published_thresholds
    if params.device == 'cuda' and not torch.cuda.is_available():
        raise ConfigError('device is cuda, but this torch sees no CUDA device (a CPU build, '
                          'or no GPU visible): set device to auto or cpu')
    dev = ('cuda' if params.device == 'cuda'
           or (params.device == 'auto' and torch.cuda.is_available()) else 'cpu')
    model, cfg, meta = load_checkpoint(params.checkpoint, dev)
    runner = StreamingDetector(model, dev, precision=params.precision,
                               ground=params.ground_mode(), overhang=params.overhang_mode(),
                               box_fit=params.box_fit)
    # the first clouds are not slower than the rest (compiled kernels, oneDNN primitives)
    runner.warm_up()
    runner.published_thresholds = published_thresholds(meta, cfg.class_names)
    runner.published_carry_thresholds = published_thresholds(meta, cfg.class_names, True)
    return runner, cfg, meta


# how a cloud is read into points: the buffered sweeps and the memory were made with them
INPUT_SETTINGS = ('intensity_scale', 'intensity_field', 'min_range', 'max_range', 'deskew',
                  'time_field', 'ego_box_min', 'ego_box_max')


@dataclass
class PipelineOutput:
    """What one cloud produced (messages are None when no classes were given)."""

    header: Any
    detections: Detections
    detections_msg: Any = None
    markers_msg: Any = None
    points_in: int = 0
    points_used: int = 0
    points_nonfinite: int = 0
    has_intensity: bool = True
    pose_source: str = 'none'
    single_frame: SingleFrameReason | None = None          # None: the frame had a pose
    pose_age_s: float = float('nan')
    # each box's track id (0: not tracked; all 0 with the tracker off, so the message keeps
    # one layout whether the tracker runs or not)
    track_ids: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    num_points: NDArray[np.uint32] = field(                # current returns in each box
        default_factory=lambda: np.zeros(0, np.uint32))
    # each box: 0 seen in this cloud, 1 carried by the memory, 2 coasted by the tracker
    held: NDArray[np.uint8] = field(default_factory=lambda: np.zeros(0, np.uint8))
    tracks: int | None = None            # the tracker's live tracks (None: the tracker is off)
    # each velocity's standard deviation (m/s): the filter's, or with the tracker off the
    # head's measurement noise, widened by a fraction of the speed (TrackerConfig)
    velocity_std: NDArray[np.float32] = field(default_factory=lambda: np.zeros(0, np.float32))
    used_memory: bool = False
    memory_samples: int = 0
    memory_bytes: int = 0
    reset_reason: str = ''
    deskew: str = 'off'                 # what deskew did (diagnostics)
    input_lags_s: tuple[float, ...] = ()   # the model input's sweeps, lags newest first
    buffered: bool = False              # a skipped cloud taken into the sweep buffer
    traffic_side: str = ''              # the side in use (auto: and the votes behind it)
    warnings: dict[str, str] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def warning(self) -> str:
        """Every input-contract warning of this frame in one line ('' when none)."""
        return '; '.join(self.warnings.values())


class DetectionPipeline:
    """Stateful per-sensor pipeline; not thread-safe (the node runs it on one worker)."""

    def __init__(self, detector: StreamingDetector, params: DetectorParams | None = None,
                 classes: MessageClasses | None = None) -> None:
        self.detector = detector
        self.classes = classes
        self.class_names = tuple(detector.cfg.class_names)
        self.params = DetectorParams()
        self.poses = PoseBuffer(int(self.params.odom_buffer_s * 1e9),
                                int(self.params.odom_tolerance_s * 1e9))
        self.T_base_lidar = pose_from_xyz_rpy(self.params.extrinsic_xyz,
                                              self.params.extrinsic_rpy)
        self.last_stamp_ns: int | None = None
        self.last_frame_id: str | None = None
        self.last_pose: NDArray[np.float64] | None = None
        self.last_pose_ns = 0                 # the stamp of the cloud last_pose was read for
        # the odometry's time line the clouds are on (PoseBuffer.rewinds; one more: the clouds
        # went back in time and the odometry not yet, until they pass ahead_until, the stamp
        # of the cloud before or of the odometry then: that one was only late)
        self.cloud_line = 0
        self.ahead_until = 0
        self.last_reset_reason = 'start'
        self.resets = 0
        self.odom_rejected = 0
        self.last_odom_error = ''
        self.last_odom_refused = False          # whether the last odometry message was refused
        self.coverage = SectorCoverage()
        self.side_vote = TrafficSideVote(self.class_names)    # traffic_side: auto
        self.configure(params or DetectorParams())

    def configure(self, params: DetectorParams) -> None:
        """Apply a parameter set; every runtime-changeable setting takes effect here.

        Thresholds go to the model's decoder, the odometry buffer's age and tolerance are
        updated in place (poses kept), a changed extrinsic, ground or overhang mode resets the
        memory, the sweeps and the tracks, a change of how the cloud is read
        (:data:`INPUT_SETTINGS`) the memory and the sweeps; the rest is read per frame.

        :raises ConfigError: an invalid set (nothing is applied then).
        """
        params.validate(len(self.class_names))
        old, old_side = self.params, self.traffic_side
        self.params = params
        chosen = params.class_thresholds(len(self.class_names))   # the user's, for every box
        self.detector.set_thresholds(chosen or self.detector.published_thresholds,
                                     params.nms_iou_threshold, params.max_detections,
                                     params.candidates,
                                     None if chosen else self.detector.published_carry_thresholds)
        self.detector.set_tracker(
            TrackerConfig(max_gap_s=params.max_gap_s, score_mix=params.track_score_mix,
                          coast_s=params.coast_s)
            if params.tracking else None)
        self.detector.sweeps.max_age_s = params.max_gap_s     # one staleness threshold
        self.detector.set_box_fit(params.box_fit)      # boxes only: the memory stands
        before_ground = self.detector.ground
        self.detector.set_ground(params.ground_mode())
        if self.detector.ground != before_ground and self.last_stamp_ns is not None:
            self.reset('ground changed')           # the memory was made on other heights
        before = self.detector.overhang
        self.detector.set_overhang(params.overhang_mode())
        if self.detector.overhang != before and self.last_stamp_ns is not None:
            self.reset('overhang changed')     # the memory was made of other returns
        self.poses.max_age_ns = int(params.odom_buffer_s * 1e9)
        self.poses.tolerance_ns = int(params.odom_tolerance_s * 1e9)
        if params.traffic_side == 'auto' and old.traffic_side != 'auto':
            self.side_vote.restart(old_side)    # auto goes on from the side in use
        if self.traffic_side != old_side and self.last_stamp_ns is not None:
            self.reset('traffic side changed')   # what is held was seen in the other world
        if (old.extrinsic_xyz, old.extrinsic_rpy) != (params.extrinsic_xyz,
                                                      params.extrinsic_rpy):
            self.T_base_lidar = pose_from_xyz_rpy(params.extrinsic_xyz, params.extrinsic_rpy)
            if self.last_stamp_ns is not None:      # (at start-up there is nothing to forget)
                self.reset('extrinsic changed')
        changed = [name for name in INPUT_SETTINGS if getattr(old, name) != getattr(params, name)]
        if changed and self.last_stamp_ns is not None:
            # the buffered sweeps and the memory were read with the old settings (another
            # intensity scale, other ranges, not deskewed): the next input must not mix them
            # with the new; the tracks (boxes in the odometry frame) go on
            self.reset('input settings changed: ' + ', '.join(changed), tracks=False)

    # ------------------------------------------------------------------ inputs
    def add_odometry(self, msg: Any, now_ns: int | None = None) -> bool:
        """Buffer an Odometry message; False (and a counted reason) when it is unusable.

        :param now_ns: the receiver's clock: odometry stamped more than ``max_stamp_skew_s``
            ahead of it is refused (one pose from the future would otherwise hide a later
            odometry outage: lookups interpolate toward it and the buffer's age limit drops
            the real poses). None or 0 (a simulated clock not started yet): not checked.
        """
        try:
            T, stamp = odometry_to_pose(msg)
        except MessageError as exc:
            self.odom_rejected += 1
            self.last_odom_refused = True
            self.last_odom_error = str(exc)
            return False
        ahead = (stamp - now_ns) * 1e-9 if now_ns else 0.0
        if ahead > self.params.max_stamp_skew_s:
            self.odom_rejected += 1
            self.last_odom_refused = True
            self.last_odom_error = (f'odometry stamped {ahead:.2f} s ahead of the clock (more '
                                    f'than max_stamp_skew_s {self.params.max_stamp_skew_s:g})')
            return False
        self.poses.add(stamp, T)
        self.last_odom_refused = False
        return True

    @property
    def odom_rewinds(self) -> int:
        """How often odometry went back in time (:attr:`PoseBuffer.rewinds`)."""
        return self.poses.rewinds

    @property
    def traffic_side(self) -> TrafficSide:
        """The side of the road the model is given traffic on: the parameter's, or with
        ``auto`` the side the oncoming vehicles say (:mod:`suit_ros.traffic_side`)."""
        side = self.params.traffic_side
        return self.side_vote.side if side == 'auto' else side

    def reset(self, reason: str, tracks: bool = True) -> None:
        """Forget the temporal memory: the feature memory, the sweeps and (with ``tracks``)
        the tracks."""
        self.detector.reset(reason, tracks=tracks)
        self.last_reset_reason = reason
        self.resets += 1
        self.last_pose = None

    def set_extrinsic(self, xyz: tuple[float, float, float],
                      rpy: tuple[float, float, float]) -> None:
        """Change the LiDAR extrinsic (resets the memory)."""
        self.configure(self.params.updated({'extrinsic_xyz': xyz, 'extrinsic_rpy': rpy}))

    # ------------------------------------------------------------------ the step
    def process(self, cloud: Any, markers: bool = True) -> PipelineOutput:
        """Detect in one PointCloud2; never raises for bad input.

        :param markers: build the MarkerArray too (``detect-bag``; the node builds it with
            :meth:`markers` after it has published the detections, and only while someone
            subscribes).
        """
        t0 = time.perf_counter()
        out = PipelineOutput(cloud.header, Detections.empty())
        points, stamp_ns, pose = self._prepare(cloud, out)
        # (an unusable cloud's header is not trusted: it changes no state)
        stale = (None if 'unusable_cloud' in out.warnings
                 else self.detector.drop_stale_memory(stamp_ns, self.params.max_gap_s))
        if stale is not None:                          # the sweeps just before it stand
            self.last_reset_reason = out.reset_reason = stale
            self.resets += 1
        t1 = time.perf_counter()
        model_timings: dict[str, float] = {}
        if len(points):
            pts, T_odom_base, T_base_lidar = self._as_trained(points, pose)
            result = self.detector.step(pts, stamp_ns, T_odom_base, T_base_lidar)
            out.input_lags_s = self.detector.sweeps.last_lags_s
            out.detections = self._from_model(result.detections)
            out.used_memory = result.used_memory
            out.memory_samples = result.memory_samples
            out.memory_bytes = result.memory_bytes
            out.num_points = result.num_points
            out.held = result.held
            model_timings = result.timings
        else:   # nothing to detect in: publish an empty result, keep the memory as it is
            out.memory_bytes = self.detector.memory_bytes
        if self.detector.tracks is not None:
            if len(points):
                out.track_ids, out.velocity_std = result.track_ids, result.velocity_std
            out.tracks = len(self.detector.tracks)
        else:       # the same fields, so that a consumer sees one layout (ids 0: not tracked)
            d, head = out.detections, TrackerConfig()
            out.track_ids = np.zeros(len(d), np.int64)
            out.velocity_std = head.published_std(head.vel_sigma, d.velocities)
        # the side this frame's boxes were made in; then its tracked vehicles vote
        out.traffic_side = (self.params.traffic_side if self.params.traffic_side != 'auto'
                            else self.side_vote.describe() if self.detector.tracks is not None
                            else f'{self.side_vote.side} (auto reads the side from tracks: '
                                 'tracking is off)')
        if len(points) and self.detector.tracks is not None:
            self._vote_side(out, pose, stamp_ns)
        t2 = time.perf_counter()
        if self.classes is not None:
            d = out.detections
            out.detections_msg = detections_to_pointcloud2(
                d.boxes, d.velocities, d.scores, d.labels, out.header, self.classes,
                track_ids=out.track_ids, num_points=out.num_points,
                vel_std=out.velocity_std, held=out.held)
            if markers:
                out.markers_msg = self.markers(out)
        t3 = time.perf_counter()
        out.timings = {'convert': t1 - t0, 'model': t2 - t1, 'publish': t3 - t2}
        out.timings.update({f'model.{k}': v for k, v in model_timings.items()})
        return out

    def markers(self, out: PipelineOutput) -> Any:
        """The MarkerArray of a processed frame's detections (with their track ids), in its
        header: what :meth:`process` builds with ``markers``; the node builds it after it has
        published the detections, which then go out without waiting for it."""
        if self.classes is None:
            raise ValueError('markers need message classes: the pipeline was made without')
        d = out.detections
        return detections_to_markerarray(d.boxes, d.velocities, d.scores, d.labels, out.header,
                                         self.class_names, self.classes,
                                         track_ids=out.track_ids, held=out.held)

    def buffer(self, cloud: Any) -> PipelineOutput:
        """Take a cloud the model will not run on (the node skipped it while the model was
        busy with an earlier one) into the sweep buffer only; never raises for bad input.

        It is converted, checked (but for the sector-gap check) and deskewed as
        :meth:`process` does, so the next input
        holds the sweeps just before it, 0.1 s apart at 10 Hz, as the model was trained (fed
        only the clouds it ran on, an overloaded node would give it sweeps 0.2-0.3 s apart:
        docs/experiments/overload). No detections; its input warnings and resets count.
        """
        t0 = time.perf_counter()
        out = PipelineOutput(cloud.header, Detections.empty())
        # the sector-gap check reads the clouds the model runs on (a third of a buffered
        # 260k-point cloud's cost: docs/experiments/overload)
        points, stamp_ns, pose = self._prepare(cloud, out, coverage=False)
        if len(points):
            pts, T_odom_base, T_base_lidar = self._as_trained(points, pose)
            out.buffered = self.detector.add_sweep(pts, stamp_ns, T_odom_base, T_base_lidar)
        out.timings = {'convert': time.perf_counter() - t0}
        return out

    def _as_trained(self, points: NDArray[np.float32], pose: NDArray[np.float64] | None
                    ) -> tuple[NDArray[np.float32], NDArray[np.float64] | None,
                               NDArray[np.float64]]:
        """The model's ``points, pose, T_base_lidar`` as its training world had them: as
        they are in right-hand traffic, mirrored across the x-z plane in left-hand traffic
        (``traffic_side``; the whole world mirrored, odometry frame too, so every pose stays
        a rotation and the memory and the tracks move as in a right-hand drive)."""
        if self.traffic_side == 'right':
            return points, pose, self.T_base_lidar
        return (mirror_points(points), None if pose is None else mirror_transform(pose),
                mirror_transform(self.T_base_lidar))

    def _from_model(self, det: Detections) -> Detections:
        """The model's boxes back in the cloud's world (see :meth:`_as_trained`)."""
        return det if self.traffic_side == 'right' else mirror_detections(det)

    def _vote_side(self, out: PipelineOutput, pose: NDArray[np.float64] | None,
                   stamp_ns: int) -> None:
        """``traffic_side: auto``: this frame's tracked vehicles vote; when the side in use
        changes, the memory and the tracks go (the next cloud is the model's in the other
        world; this frame's boxes stand)."""
        if self.params.traffic_side != 'auto':
            return
        d = out.detections
        if self.side_vote.update(d.boxes, d.velocities, d.labels, out.track_ids,
                                 self.T_base_lidar, pose, stamp_ns):
            reason = f'traffic side {self.side_vote.describe()}'
            self.reset(reason)
            out.reset_reason = '; '.join(filter(None, (out.reset_reason, reason)))

    def _prepare(self, cloud: Any, out: PipelineOutput, coverage: bool = True
                 ) -> tuple[NDArray[np.float32], int, NDArray[np.float64] | None]:
        """A cloud's points (converted, filtered, deskewed), stamp and pose, after the
        stream's checks (time jumps, gaps, frame and pose changes reset the memory); input
        warnings, the pose's source and the reset reason go into ``out``.

        :param coverage: check the azimuth coverage (``sector_gap``) and add the cloud to its
            norm: a cloud the model runs on (a skipped cloud need not pay for it, and without
            a pose it is only not buffered, where the model's step forgets what it holds).
        """
        header = cloud.header
        stamp_ns = stamp_to_ns(header.stamp)
        frame_id = str(header.frame_id)
        points, times = self._points(cloud, stamp_ns, out, coverage)
        if 'unusable_cloud' in out.warnings:
            # a message that cannot be decoded: its header is no more to be trusted than its
            # data (a bogus frame_id or stamp would reset everything twice); it changes nothing
            out.pose_source = 'none: unusable cloud'
            return points, stamp_ns, None
        reason = self._reset_reason(stamp_ns, frame_id)
        if self.last_frame_id is not None and frame_id != self.last_frame_id:
            self.coverage.reset()                    # another sensor: another norm
            out.warnings.pop('sector_gap', None)
            out.warnings['frame_changed'] = (f'frame_id changed from {self.last_frame_id!r} '
                                             f'to {frame_id!r} (memory reset)')
        back = self.last_stamp_ns is not None and stamp_ns < self.last_stamp_ns
        pose, out.pose_source, out.pose_age_s, poses = self._pose(stamp_ns, back)
        if pose is None:
            out.single_frame = 'no_odometry' if self.poses.span() is None else 'outside_odometry'
            if (coverage and reason is None and len(points)      # a cloud the model runs on
                    and (self.detector.memory is not None or len(self.detector.sweeps))):
                # the model cannot move what it holds without a pose: the step forgets it
                # (StreamingDetector.step); said here, as every other reset is
                reason = f'no pose for the cloud ({out.pose_source.removeprefix("none: ")})'
        if reason is None and pose is not None and self.last_pose is not None:
            jump = float(np.linalg.norm(pose[:3, 3] - self.last_pose[:3, 3]))
            gap_s = (stamp_ns - self.last_pose_ns) * 1e-9
            if gap_s > self.params.max_gap_s:
                # clouds with nothing to place in between (empty, no pose): what the model
                # holds is as old as that, whatever the pose did meanwhile
                reason = (f'no cloud placed for {gap_s:.2f} s (empty or without a pose), more '
                          f'than max_gap_s')
            # per 0.1 s of the gap: a dropped cloud at highway speed is no jump (the gap read
            # at most as max_gap_s: clouds that could not be placed do not widen it further)
            steps = min(gap_s, self.params.max_gap_s) / POSE_JUMP_PERIOD_S
            if reason is None and jump > self.params.max_pose_jump_m * max(1.0, steps):
                reason = f'pose jumped {jump:.1f} m in {gap_s:.2f} s between frames'
        if reason is not None:
            self.reset(reason)
            out.reset_reason = reason
        self.last_stamp_ns, self.last_frame_id = stamp_ns, frame_id
        if reason is not None or (len(points) and (coverage or pose is not None)):
            # the pose the memory and the sweeps are placed with from now; a cloud with no
            # points, or a skipped one without a pose, places nothing, so the next one is
            # checked against the last placed pose
            self.last_pose, self.last_pose_ns = pose, stamp_ns
        if times is not None and len(points):
            points = self._deskew(points, times, stamp_ns, poses, out)
        elif times is not None:
            out.deskew = 'off: no points'
        return points, stamp_ns, pose

    def _points(self, cloud: Any, stamp_ns: int, out: PipelineOutput, coverage: bool = True
                ) -> tuple[NDArray[np.float32], NDArray[np.float32] | None]:
        """``(N, 4)`` filtered, scaled points and, for deskew, each one's time after the stamp
        (s; None without usable times); input-contract warnings into ``out``."""
        p = self.params
        wanted = ((p.time_field,) if p.time_field else TIME_FIELDS) if p.deskew else ()
        try:
            xyzi = pointcloud2_to_xyzi(cloud, p.intensity_field, wanted)
        except MessageError as exc:
            out.warnings['unusable_cloud'] = f'unusable cloud: {exc}'
            return np.zeros((0, 4), np.float32), None
        points = xyzi.points
        times = self._times(xyzi.times, xyzi.time_field, stamp_ns, out) if p.deskew else None
        out.points_in = xyzi.num_input
        out.points_nonfinite = xyzi.num_nonfinite
        out.has_intensity = xyzi.has_intensity
        if not xyzi.has_intensity and xyzi.num_input and p.intensity_field != 'none':
            out.warnings['no_intensity'] = ('cloud has no intensity field (intensity, i or '
                                            'reflectivity): intensity set to 0, detections '
                                            'degrade')
        if len(points):               # the range filter in one compiled pass
            points = np.ascontiguousarray(points, np.float32)
            lo, hi = np.float32(p.min_range), np.float32(p.max_range)
            if times is None:
                points = in_range(points, lo, hi)
            else:                     # the times' rows with their points
                points, times = in_range_times(points, times, lo, hi)
            if p.ego_box_enabled and len(points):
                keep = ~self._in_ego_box(points)
                points = points[keep]
                times = None if times is None else times[keep]
        if xyzi.has_intensity and len(points):
            self._check_intensity(points[:, 3], out)
            if p.intensity_scale != 1.0:
                points[:, 3] *= 1.0 / p.intensity_scale      # a fresh array after the mask
        out.points_used = len(points)
        gap = self.coverage.update(points[:, :3]) if coverage and len(points) else None
        if gap is not None:
            out.warnings['sector_gap'] = (f'sector_gap: no returns from azimuth {gap[0]:.0f} to '
                                          f'{gap[1]:.0f} deg, normally covered (a blocked '
                                          'sensor, something alongside, or lost packets)')
        if 'unusable_cloud' not in out.warnings and len(points) == 0:
            out.warnings['empty_cloud'] = 'empty cloud (no finite points in range)'
        elif len(points) < p.min_points:
            out.warnings['too_few_points'] = (f'only {len(points)} points after filtering '
                                              f'(min_points {p.min_points})')
        return points, times

    def _times(self, values: NDArray[Any] | None, name: str, stamp_ns: int,
               out: PipelineOutput) -> NDArray[np.float32] | None:
        """The returns' times after the stamp (s) from the cloud's time field, or None (and
        why, in ``out.deskew``; a warning when the field is unusable or the named one
        missing)."""
        if values is None:
            wanted = self.params.time_field
            if wanted:
                out.warnings['point_times'] = (f'cloud has no {wanted!r} field (time_field): '
                                               'not deskewed')
            out.deskew = f'off: no time field ({wanted or ", ".join(TIME_FIELDS)})'
            return None
        times, why = relative_times(values, stamp_ns)
        if times is None:
            out.warnings['point_times'] = f'time field {name!r}: {why}: not deskewed'
            out.deskew = f'off: {name} unusable'
        return times

    def _deskew(self, points: NDArray[np.float32], times: NDArray[np.float32], stamp_ns: int,
                poses: PoseBuffer | None, out: PipelineOutput) -> NDArray[np.float32]:
        """The points moved to the sensor's pose at the stamp (:mod:`suit_ros.deskew`) by the
        odometry the cloud's pose came from (``poses``: None without one), or as they are
        (and why, in ``out.deskew``) when the odometry cannot say how the vehicle moved over
        the sweep; a motion no vehicle makes is an input warning too."""
        if poses is None:
            out.deskew = 'off: no odometry at the stamp'
            return points
        moved, twist, why = deskew_sweep(points, times, stamp_ns, poses, self.T_base_lidar)
        if twist is None:
            out.deskew = f'off: {why}'
            if why.startswith('odometry '):     # a jump: implausible or uneven
                out.warnings['point_times'] = f'not deskewed: {why}'
            return moved
        span = float(times.max()) - min(float(times.min()), 0.0)
        out.deskew = f'on: sweep {span:.3f} s at {sweep_speed(twist):.1f} m/s'
        return moved

    def _in_ego_box(self, points: NDArray[np.float32]) -> NDArray[np.bool_]:
        """Points (LiDAR frame) that fall inside the ego crop box (base_link)."""
        T = self.T_base_lidar
        lo = np.asarray(self.params.ego_box_min)
        hi = np.asarray(self.params.ego_box_max)
        xyz = [points[:, k].astype(np.float64) for k in range(3)]
        inside = np.ones(len(points), bool)
        # each base_link axis as a sum of products, not a matrix product: numpy's BLAS would
        # wake its threads for a 100k-point cloud, and they spin after it (a core lost)
        for i in range(3):
            axis = xyz[0] * T[i, 0] + xyz[1] * T[i, 1] + xyz[2] * T[i, 2] + T[i, 3]
            inside &= (axis >= lo[i]) & (axis <= hi[i])
        return inside

    def _check_intensity(self, intensity: NDArray[np.float32], out: PipelineOutput) -> None:
        """Warn when the raw intensities do not fit ``intensity_scale``."""
        scale = self.params.intensity_scale
        top = float(intensity.max())
        if top > scale * 1.001:
            out.warnings['intensity_range'] = (
                f'intensity up to {top:.3g} exceeds intensity_scale {scale:g}: set '
                'intensity_scale to the sensor maximum')
        elif scale > 1.0 and 0.0 < top <= 1.0:
            out.warnings['intensity_range'] = (
                f'intensity within 0..{top:.3g} but intensity_scale is {scale:g}: likely 0..1 '
                'reflectance, set intensity_scale to 1')

    def _reset_reason(self, stamp_ns: int, frame_id: str) -> str | None:
        if self.last_stamp_ns is None:
            return None
        if stamp_ns < self.last_stamp_ns:
            return 'time went backwards (looped bag or clock reset)'
        if stamp_ns == self.last_stamp_ns:
            return 'duplicate stamp'
        gap = (stamp_ns - self.last_stamp_ns) * 1e-9
        if gap > self.params.max_gap_s:
            return f'gap of {gap:.2f} s since the last frame exceeds max_gap_s'
        if frame_id != self.last_frame_id:
            return f'frame_id changed from {self.last_frame_id!r} to {frame_id!r}'
        return None

    def odometry_covers(self, stamp_ns: int) -> bool:
        """Whether buffered odometry reaches ``stamp_ns`` (interpolation, not extrapolation)."""
        span = self.poses.span()
        return span is not None and span[1] >= stamp_ns

    def _pose(self, stamp_ns: int, went_back: bool = False
              ) -> tuple[NDArray[np.float64] | None, str, float, PoseBuffer | None]:
        """The cloud's pose, its source, the odometry's age and the poses it came from.

        Clouds and odometry each go back in time on their own (a loop, a reset), in either
        order. A cloud whose stamp ``went_back`` before the last one's takes its pose from
        odometry that went back too (:attr:`cloud_line`); while the odometry has not, the
        poses about its stamp are of the time before, and the clouds take none (the cloud was
        only late once they are stamped past the cloud before it, or past the odometry
        buffered then: a cloud stamped ahead may have gone before it). The clouds of the line
        before that are still on their way when the odometry went back take their poses from
        that line as it was (:attr:`PoseBuffer.previous`).
        """
        span = self.poses.span()
        if span is None:
            if self.last_odom_refused:       # odometry comes, but none of it is usable
                return (None, f'none: odometry rejected: {self.last_odom_error}',
                        float('nan'), None)
            return None, 'none: no odometry received', float('nan'), None
        now = self.poses.rewinds
        if went_back:
            if now > self.cloud_line:         # the odometry went back before the cloud did
                self.cloud_line = now
            else:       # not yet: until the clouds pass the cloud before (or the odometry)
                self.cloud_line = now + 1
                self.ahead_until = min(self.last_stamp_ns or 0, span[1])
        if self.cloud_line > now:
            if stamp_ns <= self.ahead_until:
                return None, ('none: the clouds went back in time and the odometry has not '
                              '(yet): its poses are of the time before'), \
                    (stamp_ns - span[1]) * 1e-9, None
            self.cloud_line = now             # only late: one time line after all
        lines = [self.poses]
        if self.cloud_line < now and self.poses.previous is not None:
            lines.insert(0, self.poses.previous)   # a cloud of the line before, on its way
        error = ''
        for poses in lines:
            try:
                T_odom_base = poses.lookup(stamp_ns)
            except PoseLookupError as exc:
                error = error or str(exc)
                continue
            if poses is self.poses:
                self.cloud_line = now
            newest = poses.span() or span
            return T_odom_base, 'odometry', (stamp_ns - newest[1]) * 1e-9, poses
        return None, f'none: {error}', (stamp_ns - span[1]) * 1e-9, None
