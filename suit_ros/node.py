"""The ``detector`` node: PointCloud2 + Odometry in, 3D detections out, SUIT memory kept inside.

A thin shell over rclpy-free parts: parameters come from :class:`~suit_ros.params.DetectorParams`
(:mod:`suit_ros.ros_params`); the points and odometry subscriptions follow their publishers'
reliability (:mod:`suit_ros.points_subscription`); the callbacks only queue
(:mod:`suit_ros.inbox`: a one-slot cloud mailbox, an odometry gate); a worker thread runs the
shared :class:`~suit_ros.pipeline.DetectionPipeline` on the newest cloud after waiting up to
``odom_wait_s`` for odometry that covers its stamp; :mod:`suit_ros.health` turns the counters
into ``/diagnostics``. Publishes ``~/detections`` (custom-field PointCloud2) and ``~/markers``
(MarkerArray) with the input header, and serves ``~/reset_memory``.
"""
from __future__ import annotations

from collections.abc import Callable
import gc
import os
import sys
import threading
import time
from typing import Any, cast

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import SetParametersResult
import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos_overriding_options import QoSOverridingOptions
from rclpy.utilities import ok, try_shutdown
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from suit_ros.errors import ConfigError, SuitRosError
from suit_ros.health import Reasons, health_report
from suit_ros.msg_adapters.errors import MessageError
from suit_ros.msg_adapters.odometry import odometry_to_pose
from suit_ros.params import DetectorParams, parameter_descriptions
from suit_ros.points_subscription import FollowingSubscription
from suit_ros.ros_params import (
    declare_detector_parameters,
    ignored_overrides,
    limit_threads,
    torch_threads,
)
from suit_ros.worker import FrameWorker, Received, stamp_ns

REASON_LOG_PERIOD_S = 30.0   # between two log lines of the same input-contract reason
QOS_CHECK_PERIOD_S = 1.0     # how often the publishers' QoS is re-checked
WARNING_HOLD_S = 5.0         # an input-contract WARN stays this long (diagnostics: 1 Hz)
# clouds the reader holds until the executor takes them: a burst must not be replaced in the
# reader (it would read as lost); the mailbox keeps the newest and counts the rest as dropped
POINTS_READER_DEPTH = 10
QOS_OVERLAP_S = 3.0          # a replaced subscription lives on this long
ODOM_READER_DEPTH = 100      # a buffer of recent poses


DIAGNOSTIC_TASK = 'suit_ros detector'   # the status name: '<node's full name>: <this>'

class DetectorNode(Node):
    """See the module docstring."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('detector', **kwargs)
        from suit_ros.msg_adapters.classes import MessageClasses
        from suit_ros.pipeline import DetectionPipeline
        params = declare_detector_parameters(self)
        self.detector = self._load_model(params)
        self.class_names = tuple(self.detector.cfg.class_names)
        try:
            self.params = params.validate(len(self.class_names))
        except ConfigError as exc:
            raise SuitRosError(f'invalid parameters: {exc}') from exc
        # resolved once (remapping, namespace): rclpy's publisher counts do not remap
        self._points_topic = self._resolve('points_topic', self.params.points_topic)
        self._odom_topic = self._resolve('odom_topic', self.params.odom_topic)
        self.pipeline = DetectionPipeline(self.detector, self.params,
                                          MessageClasses.from_rclpy())
        self.reasons = Reasons(lambda line: self.get_logger().warn(line), WARNING_HOLD_S,
                               REASON_LOG_PERIOD_S)
        self.worker = FrameWorker(
            self.pipeline, lambda: self.params, lambda: self.get_clock().now().nanoseconds,
            self._publish, lambda: self.pub_markers.get_subscription_count() > 0,
            lambda: self.count_publishers(self._odom_topic) > 0, self.reasons,
            self.get_logger(), keep_skipped=max(self.detector.cfg.sweeps - 1, 0),
            publish_markers=lambda out: self.pub_markers.publish(out.markers_msg))
        self.points = FollowingSubscription(
            self, self._points_topic, cast(Callable[[Any], None], self._on_cloud),
            lambda: self.params.points_qos, POINTS_READER_DEPTH, QOS_OVERLAP_S)
        # a reliable reader never hears a best-effort publisher (a PX4 bridge, a simulator):
        # every cloud would wait odom_wait_s for a pose that cannot come
        self.odom = FollowingSubscription(
            self, self._odom_topic, self._on_odom, lambda: 'auto', ODOM_READER_DEPTH,
            QOS_OVERLAP_S, msg_type=Odometry, label='odometry', setting='following')
        overrides = QoSOverridingOptions.with_default_policies()
        self.pub_det = self.create_publisher(PointCloud2, '~/detections', 10,
                                             qos_overriding_options=overrides)
        self.pub_markers = self.create_publisher(MarkerArray, '~/markers', 10,
                                                 qos_overriding_options=overrides)
        self.pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self.create_service(Trigger, '~/reset_memory', self._on_reset)
        self._restoring = False     # parameters being set back to what the pipeline runs
        self.add_on_set_parameters_callback(self._on_params)
        self._worker = threading.Thread(target=self.worker.run, name='suit_ros_worker',
                                        daemon=True)
        self._worker.start()
        self.create_timer(QOS_CHECK_PERIOD_S, self._update_subscriptions)
        self.create_timer(self.params.diagnostics_period_s, self._diagnostics)
        self.ignored_parameters = ignored_overrides(self)
        if self.ignored_parameters:
            self.get_logger().warn(
                f'parameters given to this node that it does not have, ignored (misspelt? '
                f"the README's parameter table lists them): {self.ignored_parameters}")

    def _resolve(self, name: str, topic: str) -> str:
        """``topic`` resolved (namespace, remapping); an invalid name a clear error."""
        try:
            return self.resolve_topic_name(topic)
        except Exception as exc:  # noqa: BLE001 - rclpy raises RCLError or its own kinds
            raise SuitRosError(f'invalid parameters: {name} {topic!r} is not a valid ROS topic '
                               f'name ({type(exc).__name__}: {exc})') from exc

    def _update_subscriptions(self) -> None:
        self.points.update()
        self.odom.update()
        self._restore_parameters()

    def _restore_parameters(self) -> None:
        """After a set the pipeline could not apply (the worker applied the settings before
        again), the node's parameters are set back to what runs: a parameter read then says
        what the node does."""
        restored = self.worker.take_restored()
        if restored is None:
            return
        now, back = self.params.ros_values(), restored.ros_values()
        changed = sorted(n for n in back if back[n] != now[n])
        if not changed:
            return
        self._restoring = True
        try:        # at once: one at a time, a pair such as min/max_range may not validate
            result = self.set_parameters_atomically(
                [Parameter(n, value=back[n]) for n in changed])
        finally:
            self._restoring = False
        self.get_logger().warn(
            'parameters set back to the settings in use (the new ones were not applied): '
            + ', '.join(f'{n}={back[n]!r}' for n in changed)
            + ('' if result.successful else f'; not set back: {result.reason}'))

    def _load_model(self, params: DetectorParams) -> Any:
        from suit_ros.checkpoint import resolve_checkpoint
        from suit_ros.pipeline import load_detector
        threads = limit_threads(torch_threads(params.threads))
        runner, cfg, meta = load_detector(params)
        self.get_logger().info(
            f'loaded {resolve_checkpoint(params.checkpoint)} (temporal={cfg.temporal}'
            f', classes={list(cfg.class_names)}, code {meta.get("code_version")}) on '
            f'{runner.device.type}, {runner.precision}, {threads}; suit_ros from '
            f'{os.path.dirname(os.path.abspath(__file__))}')
        return runner

    # ------------------------------------------------------------------ callbacks
    def _on_params(self, params: list[Parameter]) -> SetParametersResult:
        values = {p.name: p.value for p in params if p.name in parameter_descriptions()}
        if not values:
            return SetParametersResult(successful=True)
        try:
            candidate = self.params.updated(values).validate(len(self.class_names))
        except ConfigError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        self.params = candidate                # node-side settings take effect now
        if not self._restoring:                # (set back: the pipeline runs on them)
            self.worker.request(params=candidate)  # pipeline settings before the next frame
        return SetParametersResult(successful=True)

    def _on_cloud(self, msg: PointCloud2, info: dict[str, Any] | None) -> None:
        # (rclpy passes the message info to a two-argument callback.) The same cloud through a
        # retiring subscription is taken once: a copy has the same stamp, publisher sequence
        # number and source time, while a publisher that repeats a stamp (0, a looped bag)
        # sends new messages. Sequence gaps count as losses only while one publisher and one
        # subscription exist
        received = Received(msg, self.get_clock().now().nanoseconds, time.monotonic())
        key = (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id,
               *((info.get('publication_sequence_number'), info.get('source_timestamp'))
                 if info else ()))
        overlapping = self.points.overlapping
        self.worker.mailbox.put(received, key, info, count_gaps=lambda: not overlapping
                                and self.count_publishers(self._points_topic) <= 1,
                                dedupe=overlapping)

    def _on_odom(self, msg: Odometry) -> None:
        try:
            odometry_to_pose(msg)
            usable = True
        except MessageError:      # refused (and counted) when the worker drains it
            usable = False
        self.worker.odometry.put(msg, stamp_ns(msg), self.get_clock().now().nanoseconds,
                                 self.params.max_stamp_skew_s, usable)

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response
                  ) -> Trigger.Response:
        self.worker.request(reset='reset_memory service call')
        response.success = True
        response.message = 'memory will be reset before the next frame'
        self.get_logger().info('memory reset requested by service call')
        return response

    def _publish(self, out: Any) -> None:
        self.pub_det.publish(out.detections_msg)
        if out.markers_msg is not None:
            self.pub_markers.publish(out.markers_msg)

    # ------------------------------------------------------------------ diagnostics
    def diagnostic_status(self) -> DiagnosticStatus:
        """The node's health now (what ``/diagnostics`` carries): :func:`health_report` of a
        snapshot of the node's counters."""
        snap = self.worker.snapshot({'points_reliability': self.points.reliability.name.lower(),
                                     'odometry_reliability':
                                     self.odom.reliability.name.lower(),
                                     'model_device': self.detector.device.type,
                                     'model_precision': self.detector.precision,
                                     # what `checkpoint` resolved to (the model's input)
                                     'model_ground': self.detector.ground,
                                     'model_overhang': self.detector.overhang,
                                     # given at launch, not this node's: rclpy ignored them
                                     'ignored_parameters': ', '.join(self.ignored_parameters)
                                     or 'none'})
        level, message, values = health_report(snap)
        # one status per node and sensor: two detectors (one per LiDAR, or in namespaces)
        # must not share a name, or a diagnostics aggregator merges them
        return DiagnosticStatus(
            name=f'{self.get_fully_qualified_name()}: {DIAGNOSTIC_TASK}',
            hardware_id=self._points_topic, message=message,
            level=(DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR)[level],
            values=[KeyValue(key=k, value=v) for k, v in values.items()])

    def _diagnostics(self) -> None:
        arr = DiagnosticArray(status=[self.diagnostic_status()])
        arr.header.stamp = self.get_clock().now().to_msg()
        self.pub_diag.publish(arr)

    def destroy_node(self) -> None:
        """Stop the worker, then the node."""
        self.worker.stop()
        self._worker.join(timeout=5.0)
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    """Entry point of ``ros2 run suit_ros detector`` (sets no discovery variable).

    rclpy's own SIGINT handler shuts the context down at once, while the worker may be
    publishing a frame; a KeyboardInterrupt raised anywhere inside the executor can leave its
    locks held (seen as a hang on Ctrl-C under load). Here SIGINT and SIGTERM only set a flag;
    the executor spins in steps of at most 0.1 s and, once the flag is up, the worker is
    stopped (:meth:`DetectorNode.destroy_node`) before the context goes.
    """
    import signal

    from rclpy.signals import SignalHandlerOptions

    from suit_ros.heap import keep_freed_memory
    kept = keep_freed_memory()      # before any thread allocates: frames reuse their pages
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    try:
        node = DetectorNode()
    except SuitRosError as exc:
        print(f'[detector] cannot start: {exc}', file=sys.stderr)
        try_shutdown()
        return 1
    node.get_logger().info('allocator: freed memory kept for the next frames (suit_ros.heap)'
                           if kept else "allocator: the C library's own (suit_ros.heap not "
                           'applied)')
    # Everything start-up allocated (torch, rclpy, the model: about 250k objects) leaves the
    # garbage collector's view: a full collection, which Python starts now and then as frames
    # allocate, walked them all (140 ms measured, a stall of one frame and a backlog of the
    # next ones); it now walks what the frames made.
    gc.freeze()
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    # One executor thread: every callback only queues its message, and the model runs in the
    # worker thread. rclpy's MultiThreadedExecutor (tried: 3 threads, one callback group per
    # input) kept two cores busy spinning and lost 13-69 of 100 reliable clouds in the reader.
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        while not stop.is_set() and ok():
            executor.spin_once(timeout_sec=0.1)
    except ExternalShutdownException:
        pass
    finally:
        executor.shutdown()
        node.destroy_node()
        try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
