"""The detector node's health report: diagnostics level, message and values from a snapshot of
its counters. No rclpy here: the node fills a :class:`HealthSnapshot` and turns the report
into a ``diagnostic_msgs/DiagnosticStatus``.

Levels: ERROR when no cloud arrived for ``input_timeout_s`` (none at all: for
``input_timeout_s`` + :data:`STARTUP_GRACE_S` from the start), and when every frame failed
for ``input_timeout_s``; WARN when no cloud arrived yet,
when none arrived for ``stale_periods`` times the measured input period, when clouds were
lost before the callback in the last window, when processing (p50) takes longer than the
input period, on an input-contract warning of the last few seconds, and when the last frame
ran single-frame; OK (``running``) otherwise.
"""
from __future__ import annotations

import collections
from dataclasses import dataclass
import threading
from typing import Any

import numpy as np

OK, WARN, ERROR = 0, 1, 2
STARTUP_GRACE_S = 10.0     # s past input_timeout_s before no first cloud is an ERROR


@dataclass
class HealthSnapshot:
    """What the node knows at one instant (monotonic seconds, node counters).

    :param stats: per processed frame ``convert``, ``model``, ``publish`` (s), ``latency``
        (s), ``by_receive`` (latency from the receive time), ``skew`` (stamp skew, s).
    :param last: the last frame's :class:`~suit_ros.pipeline.PipelineOutput` (None: none yet).
    :param held_warnings: the input-contract warnings of the last hold period.
    """

    now: float
    started: float
    arrivals: list[float]
    stats: list[dict[str, Any]]
    odom_delays: list[float]
    reader_delays: list[float]
    losses: list[float]
    last: Any
    held_warnings: list[str]
    single_reasons: list[tuple[str, int]]
    reason_counts: list[tuple[str, int]]
    counters: dict[str, int]
    facts: dict[str, str]
    last_reset_reason: str
    memory_resets: int
    odometry_rejected: int
    input_timeout_s: float
    stale_periods: float
    rate_window_s: float = 5.0
    failing_since: float | None = None     # frames have failed since then, none got out


def frame_stats(timings: dict[str, float], publish_s: float, received_ns: int, stamp_ns: int,
                now_ns: int, max_skew_s: float) -> dict[str, Any]:
    """One processed frame's entry of :attr:`HealthSnapshot.stats`: its stage times, and its
    latency from the cloud's stamp, or from its arrival when the stamp is off the node clock
    by more than ``max_skew_s`` (a sender with another clock)."""
    skew = (received_ns - stamp_ns) * 1e-9
    by_receive = abs(skew) > max_skew_s
    return {'convert': timings['convert'], 'model': timings['model'],
            'publish': timings['publish'] + publish_s,
            # the skipped clouds taken into the sweeps before it (an overloaded node)
            'buffer': timings.get('buffer', 0.0),
            'latency': (now_ns - (received_ns if by_receive else stamp_ns)) * 1e-9,
            'by_receive': by_receive, 'skew': skew}


def _ms(values: list[float], how: str) -> str:
    if not values:
        return 'nan'
    v = float(np.median(values)) if how == 'p50' else float(max(values))
    return f'{v * 1e3:.1f}'


def _input(s: HealthSnapshot, levels: list[tuple[int, str]], values: dict[str, str]
           ) -> float | None:
    """Input rate, period and staleness; returns the measured period (s) or None."""
    recent = [t for t in s.arrivals if t >= s.now - s.rate_window_s]
    window = max(min(s.rate_window_s, s.now - s.started), 1e-3)
    values['input_rate_hz'] = f'{len(recent) / window:.2f}'
    period = float(np.median(np.diff(s.arrivals[-20:]))) if len(s.arrivals) >= 3 else None
    values['input_period_ms'] = f'{period * 1e3:.1f}' if period else 'nan'
    since = s.now - (s.arrivals[-1] if s.arrivals else s.started)
    values['seconds_since_last_cloud'] = f'{since:.2f}' if s.arrivals else 'nan'
    if not s.arrivals:
        # a node often starts before its LiDAR driver: a WARN while that is plausible, an
        # ERROR once no cloud came in STARTUP_GRACE_S past the timeout
        if since > s.input_timeout_s + STARTUP_GRACE_S:
            levels.append((ERROR, f'no point cloud received in {since:.1f} s since the start '
                                  f'(input_timeout_s {s.input_timeout_s:g} + '
                                  f'{STARTUP_GRACE_S:g} s to start up)'))
        else:
            levels.append((WARN, f'no point cloud received yet ({since:.1f} s since the '
                                 'start)'))
    elif since > s.input_timeout_s:
        levels.append((ERROR, f'no point cloud for {since:.1f} s (input_timeout_s '
                              f'{s.input_timeout_s:g})'))
    elif period and since > s.stale_periods * period:
        levels.append((WARN, f'no point cloud for {since:.2f} s (expected every '
                             f'{period:.2f} s)'))
    return period


def _timing(s: HealthSnapshot, period: float | None, levels: list[tuple[int, str]],
            values: dict[str, str]) -> None:
    """Per-stage times, processing against the period, latency and what it is measured from."""
    for key in ('convert', 'model', 'publish', 'markers', 'buffer'):
        values[f'{key}_ms_p50'] = _ms([st.get(key, 0.0) for st in s.stats], 'p50')
    # the markers are built after the detections go out, but before the next cloud is taken
    processing = [st['convert'] + st['model'] + st['publish'] + st.get('markers', 0.0)
                  for st in s.stats]
    if processing and period and float(np.median(processing)) > period:
        levels.append((WARN, f'processing {np.median(processing) * 1e3:.0f} ms exceeds the '
                              f'input period {period * 1e3:.0f} ms: clouds are dropped'))
    if not s.stats:
        values.update(latency_ms_p50='nan', latency_ms_p95='nan', latency_reference='none')
        return
    ref = s.stats[-1]['by_receive']
    lat = [st['latency'] for st in s.stats if st['by_receive'] == ref]
    values['latency_ms_p50'] = f'{np.median(lat) * 1e3:.1f}'
    values['latency_ms_p95'] = f'{np.percentile(lat, 95) * 1e3:.1f}'
    values['latency_reference'] = (
        f'receive time (header stamps {s.stats[-1]["skew"]:.1f} s from the node clock)'
        if ref else 'header stamp')


def _last_frame(s: HealthSnapshot, levels: list[tuple[int, str]],
                values: dict[str, str]) -> None:
    last = s.last
    if last is None:
        return
    values.update({
        'points_in': str(last.points_in), 'points_used': str(last.points_used),
        'points_nonfinite': str(last.points_nonfinite),
        'has_intensity': str(last.has_intensity), 'detections': str(len(last.detections)),
        # published where this cloud shows nothing of them: carried by a carry branch or
        # coasted by the tracker (the detections' held field)
        'held_boxes': str(int((last.held > 0).sum())),
        'memory_samples': str(last.memory_samples), 'memory_bytes': str(last.memory_bytes),
        'used_memory': str(last.used_memory),
        'tracks': 'off' if last.tracks is None else str(last.tracks),
        'pose_source': last.pose_source, 'pose_age_s': f'{last.pose_age_s:.3f}',
        'deskew': last.deskew,
        'traffic_side': last.traffic_side or 'n/a',
        # the last model input's sweeps and the oldest one's lag: an overloaded node still
        # gives the model the sweeps just before the cloud (skipped clouds buffered)
        'input_sweeps': (f'{len(last.input_lags_s)} over {max(last.input_lags_s):.2f} s'
                         if last.input_lags_s else 'none'),
        'input_warnings': ','.join(last.warnings) or 'none',
        'last_warning': last.warning or 'none'})
    if last.single_frame is not None:
        levels.append((WARN, f'single-frame: {last.pose_source}'))


def health_report(s: HealthSnapshot) -> tuple[int, str, dict[str, str]]:
    """``(level, message, values)``: the worst level of every reason, the reasons joined
    (``running`` when there is none), and the diagnostic values as strings."""
    levels: list[tuple[int, str]] = []
    values: dict[str, str] = {}
    period = _input(s, levels, values)
    values.update({k: str(v) for k, v in s.counters.items()})
    values.update(s.facts)
    if s.losses:
        levels.append((WARN, f'{s.counters.get("lost_before_callback", 0)} clouds published '
                             'but never received so far (gaps in the publisher sequence; last '
                             f'{s.now - s.losses[-1]:.1f} s ago): the network or the reader '
                             'lost them'))
    # how long clouds waited in the reader; odometry receive time minus its stamp
    values['reader_delay_ms_p50'] = _ms(s.reader_delays, 'p50')
    values['reader_delay_ms_max'] = _ms(s.reader_delays, 'max')
    values['odometry_delay_ms_p50'] = _ms(s.odom_delays, 'p50')
    values['odometry_delay_ms_max'] = _ms(s.odom_delays, 'max')
    _timing(s, period, levels, values)
    # the held reasons seen lately, also before any frame got through (a failed frame)
    levels.extend((WARN, text) for text in s.held_warnings)
    failing = None if s.failing_since is None else s.now - s.failing_since
    if failing is not None and failing > s.input_timeout_s:
        # clouds come but nothing goes out: as bad as no input (the reason is held above)
        levels.append((ERROR, f'every frame failed for {failing:.1f} s: no detections '
                              'published'))
    _last_frame(s, levels, values)
    for key, count in s.single_reasons:
        values[f'single_frame.{key}'] = str(count)
    for key, count in s.reason_counts:
        values[f'warnings.{key}'] = str(count)
    values['last_reset_reason'] = s.last_reset_reason
    values['memory_resets'] = str(s.memory_resets)
    values['odometry_rejected'] = str(s.odometry_rejected)
    level = max((lvl for lvl, _ in levels), default=OK)
    return level, '; '.join(text for _, text in levels) or 'running', values


class Reasons:
    """Input-contract and odometry reasons: counted, held for the diagnostics a while after
    their last frame (so a once-a-second report shows a one-frame event), and logged the first
    time and then at most every ``log_period_s`` per reason. Thread-safe.

    :param log: called with the line to log (``"<text> [<reason>: <n> so far]"``).
    """

    def __init__(self, log: Any, hold_s: float = 5.0, log_period_s: float = 30.0) -> None:
        self._lock = threading.Lock()
        self._log = log
        self.hold_s = hold_s
        self.log_period_s = log_period_s
        self.counts: collections.Counter[str] = collections.Counter()
        self._logged: dict[str, float] = {}
        self._seen: dict[str, tuple[str, float]] = {}

    def report(self, reasons: dict[str, str], when: float, hold: bool = True) -> None:
        """Count, hold (unless ``hold`` is False) and log ``reason -> text`` seen at ``when``
        (monotonic seconds)."""
        lines = []
        with self._lock:
            for key, text in reasons.items():
                self.counts[key] += 1
                if hold:
                    self._seen[key] = (text, when)
                last = self._logged.get(key)
                if last is None or when - last >= self.log_period_s:
                    self._logged[key] = when
                    lines.append(f'{text} [{key}: {self.counts[key]} so far]')
        for line in lines:
            self._log(line)

    def held(self, now: float) -> list[str]:
        """The texts of the reasons seen within ``hold_s`` before ``now``."""
        with self._lock:
            return [text for text, when in self._seen.values() if now - when <= self.hold_s]

    def logged(self) -> set[str]:
        """The reasons logged so far."""
        with self._lock:
            return set(self._logged)

    def sorted_counts(self) -> list[tuple[str, int]]:
        """``(reason, count)`` pairs, sorted."""
        with self._lock:
            return sorted(self.counts.items())
