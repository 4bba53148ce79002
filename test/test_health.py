"""The node's health report (suit_ros.health), rclpy-free: levels, reasons and values."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from suit_ros.health import ERROR, OK, WARN, HealthSnapshot, health_report
from suit_ros.pipeline import PipelineOutput
from suit_ros.structures import Detections


def snap(**kw):
    base = HealthSnapshot(now=100.0, started=90.0, arrivals=[], stats=[], odom_delays=[],
                          reader_delays=[], losses=[], last=None, held_warnings=[],
                          single_reasons=[], reason_counts=[], counters={'frames_in': 0},
                          facts={'model_device': 'cpu'}, last_reset_reason='start',
                          memory_resets=0, odometry_rejected=0, input_timeout_s=1.0,
                          stale_periods=3.0)
    return replace(base, **kw)


def frame_stats(n, model=0.05):
    return [{'convert': 0.005, 'model': model, 'publish': 0.002, 'latency': 0.07,
             'by_receive': False, 'skew': 0.0} for _ in range(n)]


def healthy(**kw):
    arrivals = list(np.arange(95.0, 100.0, 0.1))
    last = PipelineOutput(header=None, detections=Detections.empty(), pose_source='odometry',
                          pose_age_s=0.01)
    return snap(arrivals=arrivals, stats=frame_stats(20), last=last, **kw)


def test_running_when_clouds_flow():
    level, message, values = health_report(healthy())
    assert (level, message) == (OK, 'running')
    assert values['input_rate_hz'] == '10.00' and values['input_period_ms'] == '100.0'
    assert values['latency_reference'] == 'header stamp' and values['model_device'] == 'cpu'
    assert values['held_boxes'] == '0'
    # three boxes published: one coasted by the tracker, and one seen now whose returns lie
    # just outside it (no return in it is not held: the held field says)
    three = Detections(np.zeros((3, 7)), np.zeros((3, 2)), np.ones(3), np.zeros(3, np.int64))
    last = replace(healthy().last, detections=three, num_points=np.array([12, 0, 0], np.uint32),
                   held=np.array([0, 0, 2], np.uint8))
    values = health_report(replace(healthy(), last=last))[2]
    assert values['held_boxes'] == '1' and values['detections'] == '3'


def test_no_input_yet_then_timeout():
    # a node that starts before its LiDAR driver warns, as the docs say, for the timeout
    # and 10 s to start up; the first diagnostics (1 s in) were an ERROR before
    level, message, _ = health_report(snap(now=91.1))
    assert (level, message) == (WARN, 'no point cloud received yet (1.1 s since the start)')
    assert health_report(snap(now=100.9))[0] == WARN
    level, message, _ = health_report(snap(now=101.5))
    assert level == ERROR and 'no point cloud received in 11.5 s since the start' in message
    # once clouds flowed, input_timeout_s alone decides
    level, message, _ = health_report(healthy(now=101.5))
    assert level == ERROR and 'no point cloud for 1.6 s' in message
    stale = healthy(now=100.35)                               # 0.45 s since the last: > 3 x 0.1
    assert 'expected every 0.10 s' in health_report(stale)[1]


def test_slow_processing_lost_clouds_held_warnings_and_single_frame():
    level, message, _ = health_report(replace(healthy(), stats=frame_stats(20, model=0.2)))
    assert level == WARN and 'exceeds the input period' in message
    lost = replace(healthy(), losses=[99.0], counters={'lost_before_callback': 3})
    assert 'the network or the reader lost them' in health_report(lost)[1]
    held = replace(healthy(), held_warnings=['frame_id changed'])
    assert health_report(held)[:2] == (WARN, 'frame_id changed')
    single = healthy()
    single.last.single_frame = 'no_odometry'
    single.last.pose_source = 'none: no odometry received'
    assert 'single-frame: none: no odometry' in health_report(single)[1]
    counts = replace(healthy(), single_reasons=[('no_odometry', 2)],
                     reason_counts=[('sector_gap', 4)])
    values = health_report(counts)[2]
    assert values['single_frame.no_odometry'] == '2' and values['warnings.sector_gap'] == '4'


def test_reasons_are_counted_held_and_logged_sparingly():
    from suit_ros.health import Reasons
    lines: list[str] = []
    r = Reasons(lines.append, hold_s=5.0, log_period_s=30.0)
    r.report({'frame_changed': 'frame_id changed'}, 100.0)
    r.report({'frame_changed': 'frame_id changed'}, 101.0)
    r.report({'odometry_rejected': 'odometry rejected'}, 101.0, hold=False)
    assert lines == ['frame_id changed [frame_changed: 1 so far]',
                     'odometry rejected [odometry_rejected: 1 so far]']
    assert r.held(105.5) == ['frame_id changed'] and r.held(106.5) == []
    r.report({'frame_changed': 'frame_id changed'}, 131.0)          # 30 s on: logged again
    assert lines[-1] == 'frame_id changed [frame_changed: 3 so far]'
    assert r.sorted_counts() == [('frame_changed', 3), ('odometry_rejected', 1)]
