"""The detector node's worker, rclpy-free: takes the newest cloud from the mailbox, waits for
odometry that covers it, runs the pipeline, hands the messages to the node's publishers and
keeps the counters that the health report reads.

The node gives it its clock, its publishers (as callables) and a question for the ROS graph
(whether anybody publishes odometry); everything else is here and runs without ROS.
"""
from __future__ import annotations

import collections
from collections.abc import Callable
from dataclasses import dataclass
import os
import re
import threading
import time
import traceback
from typing import Any, Generic, Protocol, TypeVar

from suit_ros.health import HealthSnapshot, Reasons, frame_stats
from suit_ros.inbox import CloudMailbox, OdometryGate
from suit_ros.params import DetectorParams

# the worker runs this much nicer than the executor, so that on a loaded machine the OS runs
# the odometry and cloud callbacks before more inference
WORKER_NICENESS = 5
MAX_LOG_KINDS = 100          # kinds of rate-limited log lines remembered
RATE_WINDOW_S = 5.0          # the input rate counts this window (it decays when input stops)
RESET_LOG_PERIOD_S = 30.0    # a kind of memory reset or failure is logged at most this often

M = TypeVar('M')


@dataclass
class Received(Generic[M]):
    """A cloud and when it arrived (node clock ns and monotonic s)."""

    msg: M
    clock_ns: int
    monotonic: float


def stamp_ns(msg: Any) -> int:
    """A message's header stamp in nanoseconds."""
    return int(msg.header.stamp.sec) * 10**9 + int(msg.header.stamp.nanosec)


class Pipeline(Protocol):
    """What the worker needs of :class:`~suit_ros.pipeline.DetectionPipeline`."""

    last_odom_error: str
    last_reset_reason: str
    params: DetectorParams
    last_stamp_ns: int | None
    resets: int
    odom_rejected: int

    @property
    def odom_rewinds(self) -> int: ...

    def configure(self, params: DetectorParams) -> None: ...

    def reset(self, reason: str) -> None: ...

    def add_odometry(self, msg: Any, now_ns: int) -> bool: ...

    def process(self, msg: Any, markers: bool = True) -> Any: ...

    def markers(self, out: Any) -> Any: ...

    def buffer(self, msg: Any) -> Any: ...


class FrameWorker:
    """The loop of the node's worker thread (:meth:`run`) and its counters.

    :param clock_ns: the node clock (ns).
    :param publish: ``publish(out)`` sends a frame's messages; :param want_markers: whether
        anybody subscribes to the markers (they cost more than the rest of the output).
    :param publish_markers: ``publish_markers(out)`` sends a frame's MarkerArray: given, the
        markers are built after ``publish`` has sent the detections, which then do not wait
        for them (about 1 ms at 10 boxes, 10 at 200); None: ``publish`` sends both, built
        together.
    :param odometry_published: whether anybody publishes odometry (no wait otherwise).
    :param keep_skipped: the model's previous sweeps (``sweeps - 1``): of the clouds skipped
        while the model was busy, this many (the newest) are taken into the sweep buffer
        before the next cloud runs.
    """

    def __init__(self, pipeline: Pipeline, params: Callable[[], DetectorParams],
                 clock_ns: Callable[[], int], publish: Callable[[Any], None],
                 want_markers: Callable[[], bool], odometry_published: Callable[[], bool],
                 reasons: Reasons, log: Any, keep_skipped: int = 0,
                 publish_markers: Callable[[Any], None] | None = None) -> None:
        self.pipeline, self.params, self.clock_ns = pipeline, params, clock_ns
        self.publish, self.want_markers = publish, want_markers
        self.publish_markers = publish_markers
        self.odometry_published, self.reasons, self.log = odometry_published, reasons, log
        self.lock = threading.Condition()      # requests, counters and the last frame
        self.mailbox: CloudMailbox[Received[Any]] = CloudMailbox(keep_replaced=keep_skipped)
        self.frames_sweeps_only = 0     # skipped clouds taken into the sweeps (no detection)
        self.odometry: OdometryGate[Any] = OdometryGate()
        self.back_rewinds = 0           # the odometry's rewinds when the clouds last went back
        self.reset_request: str | None = None
        self.pending: DetectorParams | None = None
        # the settings applied again after a set the pipeline could not apply, until the node
        # sets its parameters back to them (take_restored)
        self.restored: DetectorParams | None = None
        self.stopping = False
        self.started = time.monotonic()
        self.failing_since: float | None = None     # the first failure since the last frame out
        self.frames_out = self.frames_single = 0
        self.frames_failed = 0      # clouds whose step raised (logged, counted, held)
        # log lines by kind (numbers aside): how many so far, when last logged
        self.log_counts: collections.Counter[str] = collections.Counter()
        self.logged: dict[str, float] = {}
        self.single_reasons: collections.Counter[str] = collections.Counter()
        self.stats: collections.deque[dict[str, Any]] = collections.deque(maxlen=100)
        self.last: Any = None

    def request(self, reset: str | None = None, params: DetectorParams | None = None) -> None:
        """Ask for a memory reset and/or new pipeline settings before the next frame."""
        with self.lock:
            self.reset_request = reset or self.reset_request
            self.pending = params or self.pending

    def stop(self) -> None:
        """End :meth:`run` (a frame in progress is abandoned, not reported as failed)."""
        self.stopping = True
        self.mailbox.close()
        self.odometry.close()

    def run(self) -> None:
        """Process clouds until :meth:`stop`."""
        try:
            tid = threading.get_native_id()
            os.setpriority(os.PRIO_PROCESS, tid,
                           os.getpriority(os.PRIO_PROCESS, tid) + WORKER_NICENESS)
        except (AttributeError, OSError):    # not Linux: threads share the process priority
            pass
        while not self.stopping:
            received, skipped = self.mailbox.take_all(0.5)
            if received is None:
                continue
            with self.lock:
                reset, self.reset_request = self.reset_request, None
                pending, self.pending = self.pending, None
            if pending is not None:
                self._configure(pending)
            try:
                if reset:
                    self.pipeline.reset(reset)
                self._wait_for_odometry(stamp_ns(received.msg))
                self._drain_odometry()
                t0 = time.perf_counter()
                for old in ([] if reset else self._in_order(skipped, received)):
                    self.buffer(old)
                self.process(received, time.perf_counter() - t0)
            except Exception as exc:  # keep the node alive; say what happened
                if self.stopping:
                    return
                self._log_limited(f'frame failed: {type(exc).__name__}: {exc}', 'error', exc)
                with self.lock:
                    self.frames_failed += 1
                    if self.failing_since is None:
                        self.failing_since = time.monotonic()
                # held: the diagnostics warn while frames fail, not only the log
                self.reasons.report({'frame_failed': f'frame failed: {type(exc).__name__}: '
                                     f'{exc}'}, time.monotonic())

    def _configure(self, params: DetectorParams) -> None:
        """Apply a parameter set the node accepted; if the pipeline cannot (a failure past
        validation, after part of it may have been applied), the settings before are applied
        again and the frame runs with them, and the diagnostics hold why (the node's
        parameters are set back to them: :meth:`take_restored`)."""
        before = self.pipeline.params
        with self.lock:
            self.restored = None            # a set before, not applied: this one says now
        try:
            self.pipeline.configure(params)
        except Exception as exc:  # the node goes on with what it had
            if self.stopping:
                return
            try:
                self.pipeline.configure(before)
                with self.lock:
                    self.restored = before
            except Exception as again:  # noqa: BLE001 - said, and the frame still runs
                self.log.error(f'settings before not restored either: {again}')
            self.log.error(f'parameters not applied: {type(exc).__name__}: {exc}')
            self.reasons.report({'params_not_applied': 'parameters not applied: '
                                 f'{type(exc).__name__}: {exc}'}, time.monotonic())

    def take_restored(self) -> DetectorParams | None:
        """The settings the pipeline runs on after a set it could not apply (once; None when
        there are none, or while a newer set waits, which says for itself)."""
        with self.lock:
            if self.pending is not None:
                return None
            restored, self.restored = self.restored, None
            return restored

    def _wait_for_odometry(self, stamp: int) -> None:
        """Wait up to ``odom_wait_s`` for odometry at or after ``stamp`` of the cloud's time
        line (:meth:`OdometryGate.covers`: for a cloud whose stamp went back, odometry that
        went back since the clouds last did); no wait while nobody publishes odometry."""
        wait = self.params().odom_wait_s
        last = self.pipeline.last_stamp_ns
        back = last is not None and stamp < last
        gate = self.odometry
        if not (gate.covers(stamp, back, self.back_rewinds) or wait <= 0.0 or (
                gate.latest_ns < 0 and not self.odometry_published())):
            gate.wait_for(stamp, wait, back, self.back_rewinds)
        if back:
            self.back_rewinds = gate.rewinds

    def _drain_odometry(self) -> None:
        now = self.clock_ns()
        rewinds = self.pipeline.odom_rewinds
        for odom in self.odometry.drain():
            if not self.pipeline.add_odometry(odom, now):
                self.reasons.report({'odometry_rejected': 'odometry rejected: '
                                     f'{self.pipeline.last_odom_error}'}, time.monotonic(),
                                    hold=False)
        if self.pipeline.odom_rewinds != rewinds:       # (Reasons logs it)
            message = ('odometry went back in time (a looped bag, a simulator or clock reset, '
                       'or after one pose stamped ahead): the poses stamped after it were '
                       'dropped')
            self.reasons.report({'odometry_rewound': message}, time.monotonic(), hold=False)

    def _in_order(self, skipped: list[Received[Any]], newest: Received[Any]
                  ) -> list[Received[Any]]:
        """The skipped clouds that fall between the last cloud taken and the newest, in stamp
        order (one that arrived out of order must not read as time going backwards)."""
        last = self.pipeline.last_stamp_ns
        top = stamp_ns(newest.msg)
        return sorted((r for r in skipped if (last is None or stamp_ns(r.msg) > last)
                       and stamp_ns(r.msg) < top), key=lambda r: stamp_ns(r.msg))

    def buffer(self, received: Received[Any]) -> None:
        """Take a skipped cloud into the model's sweeps (no detection); its input warnings
        and resets count as a processed cloud's do. A failure is logged and the newest
        cloud still runs."""
        try:
            out = self.pipeline.buffer(received.msg)
        except Exception as exc:  # the cloud the model runs on next is not lost with it
            if not self.stopping:
                self._log_limited(f'skipped cloud not buffered: {type(exc).__name__}: {exc}',
                                  'error', exc)
            return
        with self.lock:
            self.frames_sweeps_only += int(out.buffered)
            self.reasons.report(out.warnings, received.monotonic)
        if out.reset_reason:
            self._log_reset(out.reset_reason)

    def process(self, received: Received[Any], buffer_s: float = 0.0) -> None:
        """Run one cloud through the pipeline, publish, count.

        :param buffer_s: the time spent before it on the skipped clouds (in its latency).
        """
        markers = self.want_markers()
        later = markers and self.publish_markers is not None
        out = self.pipeline.process(received.msg, markers=markers and not later)
        out.timings['buffer'] = buffer_s
        t0 = time.perf_counter()
        self.publish(out)
        stats = frame_stats(out.timings, time.perf_counter() - t0, received.clock_ns,
                            stamp_ns(received.msg), self.clock_ns(),
                            self.params().max_stamp_skew_s)
        with self.lock:
            self.frames_out += 1
            self.failing_since = None
            if out.single_frame is not None:
                self.frames_single += 1
                self.single_reasons[out.single_frame] += 1
            self.stats.append(stats)
            self.last = out
            # counted with the frame, so a diagnostic never shows a frame without its reasons
            self.reasons.report(out.warnings, received.monotonic)
        if out.reset_reason:
            self._log_reset(out.reset_reason)
        if later and self.publish_markers is not None and out.detections_msg is not None:
            # (``last`` gets its markers now: the diagnostics do not read them)
            t1 = time.perf_counter()
            try:        # the detections are out: a failure here loses only the picture
                out.markers_msg = self.pipeline.markers(out)
                self.publish_markers(out)
            except Exception as exc:  # noqa: BLE001 - said (held, rate-limited); the frame went out
                if not self.stopping:
                    self.reasons.report({'markers_failed': 'markers not published: '
                                         f'{type(exc).__name__}: {exc}'}, time.monotonic())
            with self.lock:     # the worker's time on the frame: in the processing figure
                stats['markers'] = time.perf_counter() - t1

    def _log_reset(self, reason: str) -> None:
        """Log a memory reset: the first of a kind, then at most every
        :data:`RESET_LOG_PERIOD_S` with the count (a publisher that repeats one stamp resets
        every frame; the counter and diagnostics count them all)."""
        self._log_limited(f'memory reset: {reason}')

    def _log_limited(self, line: str, level: str = 'info',
                     exc: BaseException | None = None) -> None:
        """Log ``line``: the first of its kind (numbers aside: 'pose jumped N m in N s'),
        with ``exc``'s traceback, then at most every :data:`RESET_LOG_PERIOD_S` with the
        count (a frame that fails on every cloud must not flood the log at the sensor's
        rate; the diagnostics count them all)."""
        kind = re.sub(r'[-+]?\d[\d.]*', 'N', line)
        now = time.monotonic()
        if len(self.logged) > MAX_LOG_KINDS and kind not in self.logged:
            self.log_counts.clear()     # kinds that name ever new things: forget, log again
            self.logged.clear()
        self.log_counts[kind] += 1
        last = self.logged.get(kind)
        if last is not None and now - last < RESET_LOG_PERIOD_S:
            return
        self.logged[kind] = now
        count = self.log_counts[kind]
        if count > 1:
            line += f' [{count} so far]'
        elif exc is not None:
            line += '\n' + ''.join(traceback.format_exception(exc)).rstrip()
        getattr(self.log, level)(line)

    def snapshot(self, facts: dict[str, str]) -> HealthSnapshot:
        """The counters now, for :func:`~suit_ros.health.health_report`."""
        now, box, params, pipeline = time.monotonic(), self.mailbox, self.params(), self.pipeline
        with self.lock:
            return HealthSnapshot(
                now=now, started=self.started, arrivals=list(box.arrivals),
                stats=list(self.stats), odom_delays=list(self.odometry.delays),
                reader_delays=list(box.reader_delays),
                losses=[t for t in box.losses if t >= now - RATE_WINDOW_S], last=self.last,
                held_warnings=self.reasons.held(now),
                single_reasons=sorted(self.single_reasons.items()),
                reason_counts=self.reasons.sorted_counts(),
                counters={'frames_in': box.frames_in, 'frames_out': self.frames_out,
                          'dropped_frames': box.dropped, 'lost_before_callback': box.lost,
                          'duplicate_clouds': box.duplicates,
                          'frames_failed': self.frames_failed,
                          'frames_single_frame': self.frames_single,
                          'frames_sweeps_only': self.frames_sweeps_only,
                          'odometry_waits': self.odometry.waits},
                facts=facts, last_reset_reason=pipeline.last_reset_reason,
                memory_resets=pipeline.resets, odometry_rejected=pipeline.odom_rejected,
                input_timeout_s=params.input_timeout_s, stale_periods=params.stale_periods,
                rate_window_s=RATE_WINDOW_S, failing_since=self.failing_since)
