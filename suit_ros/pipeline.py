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
from typing import Any

import numpy as np
from numpy.typing import NDArray

from suit_ros.model.streaming import StreamingDetector
from suit_ros.msg_adapters.classes import MessageClasses
from suit_ros.msg_adapters.detections import detections_to_markerarray, detections_to_pointcloud2
from suit_ros.msg_adapters.errors import MessageError, PoseLookupError
from suit_ros.msg_adapters.odometry import PoseBuffer, odometry_to_pose, stamp_to_ns
from suit_ros.msg_adapters.pointcloud2 import pointcloud2_to_xyzi
from suit_ros.ops.geometry import pose_from_xyz_rpy
from suit_ros.structures import Detections


@dataclass
class PipelineParams:
    """Pipeline settings (the node's parameters of the same names)."""

    intensity_scale: float = 255.0
    extrinsic_xyz: tuple[float, float, float] = (0.9, 0.0, 1.8)
    extrinsic_rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)
    odom_buffer_s: float = 10.0
    odom_tolerance_s: float = 0.15
    max_gap_s: float = 0.5
    max_pose_jump_m: float = 5.0
    min_range: float = 1.0
    max_range: float = 80.0


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
    pose_age_s: float = float('nan')
    used_memory: bool = False
    memory_samples: int = 0
    memory_bytes: int = 0
    reset_reason: str = ''
    warning: str = ''
    timings: dict[str, float] = field(default_factory=dict)


class DetectionPipeline:
    """Stateful per-sensor pipeline; not thread-safe (the node runs it on one worker)."""

    def __init__(self, detector: StreamingDetector, params: PipelineParams | None = None,
                 classes: MessageClasses | None = None) -> None:
        self.detector = detector
        self.params = params or PipelineParams()
        self.classes = classes
        self.class_names = tuple(detector.cfg.class_names)
        self.poses = PoseBuffer(int(self.params.odom_buffer_s * 1e9),
                                int(self.params.odom_tolerance_s * 1e9))
        self.T_base_lidar = pose_from_xyz_rpy(self.params.extrinsic_xyz,
                                              self.params.extrinsic_rpy)
        self.last_stamp_ns: int | None = None
        self.last_frame_id: str | None = None
        self.last_pose: NDArray[np.float64] | None = None
        self.last_reset_reason = 'start'
        self.resets = 0
        self.odom_rejected = 0
        self.last_odom_error = ''

    # ------------------------------------------------------------------ inputs
    def add_odometry(self, msg: Any) -> bool:
        """Buffer an Odometry message; False (and a counted reason) when it is unusable."""
        try:
            T, stamp = odometry_to_pose(msg)
        except MessageError as exc:
            self.odom_rejected += 1
            self.last_odom_error = str(exc)
            return False
        self.poses.add(stamp, T)
        return True

    def reset(self, reason: str) -> None:
        """Forget the temporal memory."""
        self.detector.reset(reason)
        self.last_reset_reason = reason
        self.resets += 1
        self.last_pose = None

    def set_extrinsic(self, xyz: tuple[float, float, float],
                      rpy: tuple[float, float, float]) -> None:
        """Change the LiDAR extrinsic (resets the memory)."""
        self.T_base_lidar = pose_from_xyz_rpy(xyz, rpy)
        self.reset('extrinsic changed')

    # ------------------------------------------------------------------ the step
    def process(self, cloud: Any, markers: bool = True) -> PipelineOutput:
        """Detect in one PointCloud2; never raises for bad input.

        :param markers: build the MarkerArray too (the node skips it when nobody listens).
        """
        p = self.params
        t0 = time.perf_counter()
        header = cloud.header
        stamp_ns = stamp_to_ns(header.stamp)
        frame_id = str(header.frame_id)
        out = PipelineOutput(header, Detections.empty())
        try:
            xyzi = pointcloud2_to_xyzi(cloud)
            points = xyzi.points
            out.points_in = xyzi.num_input
            out.points_nonfinite = xyzi.num_nonfinite
            out.has_intensity = xyzi.has_intensity
        except MessageError as exc:
            out.warning = f'unusable cloud: {exc}'
            points = np.zeros((0, 4), np.float32)
        if len(points):
            r = np.hypot(points[:, 0], points[:, 1])
            points = points[(r >= p.min_range) & (r <= p.max_range)]
            if p.intensity_scale != 1.0:
                points = points.copy() if not points.flags.writeable else points
                points[:, 3] *= 1.0 / p.intensity_scale
        out.points_used = len(points)
        t1 = time.perf_counter()
        reason = self._reset_reason(stamp_ns, frame_id)
        pose, out.pose_source, out.pose_age_s = self._pose(stamp_ns)
        if reason is None and pose is not None and self.last_pose is not None:
            jump = float(np.linalg.norm(pose[:3, 3] - self.last_pose[:3, 3]))
            if jump > p.max_pose_jump_m:
                reason = f'pose jumped {jump:.1f} m between frames'
        if reason is not None:
            self.reset(reason)
            out.reset_reason = reason
        self.last_stamp_ns, self.last_frame_id = stamp_ns, frame_id
        self.last_pose = pose
        if out.warning == '' and len(points) == 0:
            out.warning = 'empty cloud (no finite points in range)'
        t2 = time.perf_counter()
        model_timings: dict[str, float] = {}
        if len(points):
            result = self.detector.step(points, stamp_ns, pose, self.T_base_lidar)
            out.detections = result.detections
            out.used_memory = result.used_memory
            out.memory_samples = result.memory_samples
            out.memory_bytes = result.memory_bytes
            model_timings = result.timings
        else:   # nothing to detect in: publish an empty result, keep the memory as it is
            out.memory_bytes = self.detector.memory_bytes
        t3 = time.perf_counter()
        if self.classes is not None:
            d = out.detections
            out.detections_msg = detections_to_pointcloud2(
                d.boxes, d.velocities, d.scores, d.labels, header, self.classes)
            if markers:
                out.markers_msg = detections_to_markerarray(
                    d.boxes, d.velocities, d.scores, d.labels, header, self.class_names,
                    self.classes)
        t4 = time.perf_counter()
        out.timings = {'convert': (t1 - t0) + (t2 - t1), 'model': t3 - t2, 'publish': t4 - t3}
        out.timings.update({f'model.{k}': v for k, v in model_timings.items()})
        return out

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

    def _pose(self, stamp_ns: int) -> tuple[NDArray[np.float64] | None, str, float]:
        span = self.poses.span()
        if span is None:
            return None, 'none: no odometry received', float('nan')
        age = (stamp_ns - span[1]) * 1e-9
        try:
            T_odom_base = self.poses.lookup(stamp_ns)
        except PoseLookupError as exc:
            return None, f'none: {exc}', age
        return T_odom_base, 'odometry', age
