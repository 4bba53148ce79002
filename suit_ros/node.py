"""The ``detector`` node: PointCloud2 + Odometry in, 3D detections out, SUIT memory kept inside.

Subscribes (sensor-data QoS, keep last 1) to the cloud topic and to odometry; a worker thread runs
the shared :class:`~suit_ros.pipeline.DetectionPipeline` on the newest cloud only (a cloud that
arrives while the worker is busy replaces the waiting one and is counted as dropped), so the
executor is never blocked by inference. Publishes ``~/detections`` (custom-field PointCloud2) and
``~/markers`` (MarkerArray) with the input header, ``/diagnostics`` at 1 Hz, and serves
``~/reset_memory`` (std_srvs/Trigger).
"""
from __future__ import annotations

import collections
import os
import sys
import threading
import time
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from nav_msgs.msg import Odometry
import numpy as np
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import HistoryPolicy, QoSProfile, QoSReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from suit_ros.errors import SuitRosError

READ_ONLY = ('checkpoint', 'device', 'threads', 'points_topic', 'odom_topic', 'class_names')


def _desc(text: str, read_only: bool = False, lo: float | None = None, hi: float | None = None,
          integer: bool = False) -> ParameterDescriptor:
    d = ParameterDescriptor(description=text, read_only=read_only)
    if lo is not None and hi is not None:
        if integer:
            d.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=1)]
        else:
            d.floating_point_range = [FloatingPointRange(from_value=float(lo),
                                                         to_value=float(hi), step=0.0)]
    return d


class DetectorNode(Node):
    """See the module docstring."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('detector', **kwargs)
        from suit_ros.checkpoint import default_checkpoint_path, load_checkpoint
        from suit_ros.model.streaming import StreamingDetector
        from suit_ros.msg_adapters.classes import MessageClasses
        from suit_ros.pipeline import DetectionPipeline, PipelineParams

        p = self.declare_parameter
        p('checkpoint', '', _desc('model checkpoint (.safetensors); empty: the shipped one',
                                  True))
        p('device', 'auto', _desc('auto | cpu | cuda', True))
        p('threads', 0, _desc('torch CPU threads (0: torch default)', True, 0, 64, True))
        p('points_topic', '/points', _desc('input PointCloud2 topic', True))
        p('odom_topic', '/odom', _desc('input Odometry topic', True))
        p('score_thresholds', [0.0], _desc('per-class score thresholds (one value: all '
                                           'classes; [0.0]: the checkpoint default)'))
        p('nms_iou_threshold', 0.2, _desc('BEV IoU NMS threshold', lo=0.0, hi=1.0))
        p('max_detections', 200, _desc('detections per frame', lo=1, hi=1000, integer=True))
        p('min_range', 1.0, _desc('drop points closer than this (m, xy)', lo=0.0, hi=50.0))
        p('max_range', 80.0, _desc('drop points farther than this (m, xy)', lo=1.0, hi=500.0))
        p('intensity_scale', 255.0, _desc('divide intensity by this to reach 0..1',
                                          lo=1e-6, hi=1e6))
        p('extrinsic_xyz', [0.9, 0.0, 1.8], _desc('base_link -> LiDAR translation (m)'))
        p('extrinsic_rpy', [0.0, 0.0, 0.0], _desc('base_link -> LiDAR roll pitch yaw (rad)'))
        p('odom_tolerance_s', 0.15, _desc('max time outside the odometry buffer for a pose',
                                          lo=0.0, hi=5.0))
        p('max_gap_s', 0.5, _desc('reset the memory after a longer gap between clouds',
                                  lo=0.01, hi=60.0))
        p('max_pose_jump_m', 5.0, _desc('reset the memory when the pose jumps farther',
                                        lo=0.1, hi=1000.0))
        p('diagnostics_period_s', 1.0, _desc('diagnostics publishing period', lo=0.05,
                                             hi=60.0))

        threads = self.get_parameter('threads').value
        if threads:
            import torch
            torch.set_num_threads(int(threads))
        ckpt = self.get_parameter('checkpoint').value or str(default_checkpoint_path())
        device = self.get_parameter('device').value
        if device not in ('auto', 'cpu', 'cuda'):
            raise SuitRosError(f'parameter device must be auto, cpu or cuda, not {device!r}')
        import torch
        dev = 'cuda' if device == 'cuda' or (device == 'auto' and torch.cuda.is_available()) \
            else 'cpu'
        model, cfg, meta = load_checkpoint(ckpt, dev)
        self.class_names = tuple(cfg.class_names)
        self.detector = StreamingDetector(model, dev)
        self.pipeline = DetectionPipeline(self.detector, self._pipeline_params(PipelineParams),
                                          MessageClasses.from_rclpy())
        self._apply_thresholds()
        self.get_logger().info(
            f'loaded {ckpt} (temporal={cfg.temporal}, classes={list(self.class_names)}, '
            f'code {meta.get("code_version")}) on {dev}; suit_ros from '
            f'{os.path.dirname(os.path.abspath(__file__))}')

        qos_points = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                                reliability=QoSReliabilityPolicy.BEST_EFFORT)
        overrides = QoSOverridingOptions.with_default_policies()
        self.create_subscription(PointCloud2, self.get_parameter('points_topic').value,
                                 self._on_cloud, qos_points, qos_overriding_options=overrides)
        self.create_subscription(Odometry, self.get_parameter('odom_topic').value,
                                 self._on_odom, QoSProfile(depth=100),
                                 qos_overriding_options=overrides)
        self.pub_det = self.create_publisher(PointCloud2, '~/detections', 10,
                                             qos_overriding_options=overrides)
        self.pub_markers = self.create_publisher(MarkerArray, '~/markers', 10,
                                                 qos_overriding_options=overrides)
        self.pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self.create_service(Trigger, '~/reset_memory', self._on_reset)
        self.add_on_set_parameters_callback(self._on_params)

        self._cv = threading.Condition()
        self._slot: PointCloud2 | None = None
        self._odom: collections.deque[Odometry] = collections.deque(maxlen=1000)
        self._reset_request: str | None = None
        self._param_update = False
        self._stop = False
        self.frames_in = 0
        self.frames_out = 0
        self.dropped = 0
        self._arrivals: collections.deque[float] = collections.deque(maxlen=50)
        self._stats: collections.deque[dict[str, float]] = collections.deque(maxlen=100)
        self._last: Any = None
        self._worker = threading.Thread(target=self._work, name='suit_ros_worker', daemon=True)
        self._worker.start()
        self.create_timer(self.get_parameter('diagnostics_period_s').value, self._diagnostics)

    # ------------------------------------------------------------------ parameters
    def _pipeline_params(self, cls: Any) -> Any:
        g = self.get_parameter
        return cls(intensity_scale=g('intensity_scale').value,
                   extrinsic_xyz=tuple(g('extrinsic_xyz').value),
                   extrinsic_rpy=tuple(g('extrinsic_rpy').value),
                   odom_tolerance_s=g('odom_tolerance_s').value,
                   max_gap_s=g('max_gap_s').value, max_pose_jump_m=g('max_pose_jump_m').value,
                   min_range=g('min_range').value, max_range=g('max_range').value)

    def _apply_thresholds(self) -> None:
        thr = list(self.get_parameter('score_thresholds').value)
        K = len(self.class_names)
        values = None if thr == [0.0] else (thr * K if len(thr) == 1 else thr)
        self.detector.set_thresholds(values, self.get_parameter('nms_iou_threshold').value,
                                     self.get_parameter('max_detections').value)

    def _on_params(self, params: list[Parameter]) -> SetParametersResult:
        K = len(self.class_names)
        for prm in params:
            if prm.name in READ_ONLY:
                return SetParametersResult(successful=False,
                                           reason=f'{prm.name} is read-only (restart the node)')
            if prm.name == 'score_thresholds':
                v = list(prm.value)
                if len(v) not in (1, K) or any(not 0.0 <= x <= 1.0 for x in v):
                    return SetParametersResult(
                        successful=False,
                        reason=f'score_thresholds needs 1 or {K} values within 0..1')
            if prm.name in ('extrinsic_xyz', 'extrinsic_rpy'):
                v = list(prm.value)
                if len(v) != 3 or not np.isfinite(v).all():
                    return SetParametersResult(successful=False,
                                               reason=f'{prm.name} needs 3 finite numbers')
        with self._cv:
            self._param_update = True
        return SetParametersResult(successful=True)

    # ------------------------------------------------------------------ callbacks
    def _on_cloud(self, msg: PointCloud2) -> None:
        with self._cv:
            self.frames_in += 1
            self._arrivals.append(time.monotonic())
            if self._slot is not None:
                self.dropped += 1
            self._slot = msg
            self._cv.notify()

    def _on_odom(self, msg: Odometry) -> None:
        self._odom.append(msg)

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response
                  ) -> Trigger.Response:
        with self._cv:
            self._reset_request = 'reset_memory service call'
        response.success = True
        response.message = 'memory will be reset before the next frame'
        self.get_logger().info('memory reset requested by service call')
        return response

    # ------------------------------------------------------------------ the worker
    def _work(self) -> None:
        from suit_ros.pipeline import PipelineParams
        while True:
            with self._cv:
                while self._slot is None and not self._stop:
                    self._cv.wait(0.5)
                if self._stop:
                    return
                msg, self._slot = self._slot, None
                reset, self._reset_request = self._reset_request, None
                update, self._param_update = self._param_update, False
            while self._odom:
                if not self.pipeline.add_odometry(self._odom.popleft()):
                    self.get_logger().warn(f'odometry rejected: {self.pipeline.last_odom_error}',
                                           throttle_duration_sec=5.0)
            if update:
                old = self.pipeline.params
                new = self._pipeline_params(PipelineParams)
                self.pipeline.params = new
                if (old.extrinsic_xyz, old.extrinsic_rpy) != (new.extrinsic_xyz,
                                                              new.extrinsic_rpy):
                    self.pipeline.set_extrinsic(new.extrinsic_xyz, new.extrinsic_rpy)
                self._apply_thresholds()
            if reset:
                self.pipeline.reset(reset)
            try:
                self._process(msg)
            except Exception as exc:  # keep the node alive; say what happened
                self.get_logger().error(f'frame failed: {type(exc).__name__}: {exc}')

    def _process(self, msg: PointCloud2) -> None:
        # building ~3 markers per box costs more than the rest of the output: skip it when
        # nobody subscribes to ~/markers
        out = self.pipeline.process(msg, markers=self.pub_markers.get_subscription_count() > 0)
        t0 = time.perf_counter()
        self.pub_det.publish(out.detections_msg)
        if out.markers_msg is not None:
            self.pub_markers.publish(out.markers_msg)
        publish = time.perf_counter() - t0
        now = self.get_clock().now().nanoseconds
        stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
        stats = {'convert': out.timings['convert'], 'model': out.timings['model'],
                 'publish': out.timings['publish'] + publish, 'latency': (now - stamp) * 1e-9}
        self.frames_out += 1
        self._stats.append(stats)
        self._last = out
        if out.reset_reason:
            self.get_logger().info(f'memory reset: {out.reset_reason}')
        if out.warning:
            self.get_logger().warn(out.warning, throttle_duration_sec=2.0)

    # ------------------------------------------------------------------ diagnostics
    def _diagnostics(self) -> None:
        status = DiagnosticStatus(name='suit_ros: detector', hardware_id='suit_ros')
        values: dict[str, str] = {}
        with self._cv:
            arrivals = list(self._arrivals)
            stats = list(self._stats)
        rate = ((len(arrivals) - 1) / (arrivals[-1] - arrivals[0])
                if len(arrivals) > 1 and arrivals[-1] > arrivals[0] else 0.0)
        values['input_rate_hz'] = f'{rate:.2f}'
        values['frames_in'] = str(self.frames_in)
        values['frames_out'] = str(self.frames_out)
        values['dropped_frames'] = str(self.dropped)
        for key in ('convert', 'model', 'publish'):
            arr = [s[key] for s in stats]
            values[f'{key}_ms_p50'] = f'{np.median(arr) * 1e3:.1f}' if arr else 'nan'
        lat = [s['latency'] for s in stats]
        values['latency_ms_p50'] = f'{np.median(lat) * 1e3:.1f}' if lat else 'nan'
        values['latency_ms_p95'] = f'{np.percentile(lat, 95) * 1e3:.1f}' if lat else 'nan'
        last = self._last
        level, message = DiagnosticStatus.OK, 'running'
        if last is None:
            level, message = DiagnosticStatus.WARN, 'no point cloud received yet'
        else:
            values.update({
                'points_in': str(last.points_in), 'points_used': str(last.points_used),
                'points_nonfinite': str(last.points_nonfinite),
                'has_intensity': str(last.has_intensity),
                'detections': str(len(last.detections)),
                'memory_samples': str(last.memory_samples),
                'memory_bytes': str(last.memory_bytes),
                'used_memory': str(last.used_memory),
                'pose_source': last.pose_source,
                'pose_age_s': f'{last.pose_age_s:.3f}',
                'last_warning': last.warning or 'none'})
            if last.warning:
                level, message = DiagnosticStatus.WARN, last.warning
            elif not last.pose_source.startswith('odometry'):
                level, message = DiagnosticStatus.WARN, f'single-frame: {last.pose_source}'
        values['last_reset_reason'] = self.pipeline.last_reset_reason
        values['memory_resets'] = str(self.pipeline.resets)
        values['odometry_rejected'] = str(self.pipeline.odom_rejected)
        status.level, status.message = level, message
        status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
        arr = DiagnosticArray(status=[status])
        arr.header.stamp = self.get_clock().now().to_msg()
        self.pub_diag.publish(arr)

    def destroy_node(self) -> None:
        """Stop the worker, then the node."""
        with self._cv:
            self._stop = True
            self._cv.notify()
        self._worker.join(timeout=5.0)
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    """Entry point of ``ros2 run suit_ros detector``."""
    rclpy.init(args=args)
    try:
        node = DetectorNode()
    except SuitRosError as exc:
        print(f'[detector] cannot start: {exc}', file=sys.stderr)
        rclpy.try_shutdown()
        return 1
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
