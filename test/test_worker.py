"""The node's worker without a ROS graph: a real pipeline (real model, real message classes),
clouds and odometry put in its mailbox and gate as the callbacks do, the thread it runs in."""
from __future__ import annotations

from dataclasses import replace
import threading
import time

import pytest
from test_pipeline import T0, S, classes, cloud, model, odom  # noqa: F401 - fixtures

from suit_ros.health import Reasons, health_report
from suit_ros.params import DetectorParams
from suit_ros.worker import FrameWorker, Received, stamp_ns


class Log:
    def __init__(self):
        self.lines = []

    def info(self, line):
        self.lines.append(('info', line))

    def error(self, line):
        self.lines.append(('error', line))


@pytest.fixture
def worker(request):
    from test_pipeline import make_pipeline
    mc = request.getfixturevalue('classes')
    pipe = make_pipeline(request.getfixturevalue('model'), mc)
    params = DetectorParams(odom_wait_s=0.3)
    published, log, warnings = [], Log(), []
    clock = {'ns': T0}
    w = FrameWorker(pipe, lambda: params, lambda: clock['ns'], published.append,
                    lambda: False, lambda: True, Reasons(warnings.append, 5.0, 30.0), log)
    thread = threading.Thread(target=w.run, daemon=True)
    thread.start()
    yield w, mc, published, log, clock
    w.stop()
    thread.join(5.0)
    assert not thread.is_alive()


def until(cond, timeout=20.0):
    end = time.monotonic() + timeout
    while not cond() and time.monotonic() < end:
        time.sleep(0.02)
    return cond()


def put_cloud(w, mc, stamp):
    msg = cloud(mc, stamp)
    w.mailbox.put(Received(msg, stamp, time.monotonic()), (stamp, 'lidar'), None,
                  count_gaps=lambda: False)


def test_the_worker_waits_for_odometry_then_publishes_and_counts(worker):
    w, mc, published, log, clock = worker
    for t in range(T0 - S // 2, T0 + 1, S // 20):
        w.odometry.put(odom(t), t, clock['ns'], 1.0)
    put_cloud(w, mc, T0)
    assert until(lambda: w.frames_out == 1)
    assert published[0].detections_msg.header.frame_id == 'lidar'
    assert published[0].markers_msg is None                      # nobody wants markers
    assert w.last.pose_source == 'odometry' and w.odometry.waits == 0
    # a cloud ahead of the odometry waits for it (up to odom_wait_s), then runs with it
    put_cloud(w, mc, T0 + S // 10)
    assert until(lambda: w.odometry.waits == 1)                  # the worker took it: waiting
    w.odometry.put(odom(T0 + S // 10), T0 + S // 10, clock['ns'], 1.0)
    assert until(lambda: w.frames_out == 2)
    assert w.last.pose_source == 'odometry'
    level, _, values = health_report(w.snapshot({'points_reliability': 'reliable'}))
    assert values['frames_out'] == '2' and values['points_reliability'] == 'reliable'
    assert not [line for kind, line in log.lines if kind == 'error']


def test_a_reset_and_new_settings_apply_before_the_next_frame(worker):
    from dataclasses import replace
    w, mc, published, log, clock = worker
    w.request(reset='test', params=replace(DetectorParams(), max_detections=1))
    put_cloud(w, mc, T0)
    assert until(lambda: w.frames_out == 1)
    assert len(published[0].detections_msg.data) <= published[0].detections_msg.point_step
    assert w.pipeline.last_reset_reason == 'test'
    assert stamp_ns(published[0].detections_msg) == T0



def test_a_looped_bag_runs_on_its_odometry_again_and_says_so(worker):
    """Time goes back (a bag played in a loop): the worker's odometry wait and the pose
    buffer follow it, the cloud runs with odometry (not single-frame), the diagnostics say
    that odometry went back; the clouds of the loop, which repeat stamps, are all taken (keyed
    as the node keys them: with the publisher's sequence number)."""
    w, mc, published, log, clock = worker
    seq = [0]

    def put(stamp, odometry_after=()):
        # keyed as the node keys a cloud (with the publisher's sequence number; deduplicated
        # only while a retiring subscription overlaps, not here)
        seq[0] += 1
        w.mailbox.put(Received(cloud(mc, stamp), stamp, time.monotonic()),
                      (stamp, 'lidar', seq[0]), None, count_gaps=False, dedupe=False)
        for t in odometry_after:        # odometry that comes after the cloud: waited for
            time.sleep(0.01)
            w.odometry.put(odom(t), t, clock['ns'], 1.0)
        assert until(lambda: w.frames_out == seq[0])
        assert w.last.pose_source == 'odometry', w.last.pose_source

    for _ in range(2):
        for t in range(T0 - S // 2, T0 + 1, S // 20):
            w.odometry.put(odom(t), t, clock['ns'], 1.0)
        put(T0)
        # the bag ends and plays again: odometry restarts 60 s back, the first cloud of the
        # loop waits for it (the gate's newest stamp went back with the odometry)
        put(T0 - 60 * S, range(T0 - 61 * S, T0 - 60 * S + 1, S // 20))
        for t in range(T0 - 60 * S, T0 - 60 * S + S // 5, S // 20):   # and forward again
            w.odometry.put(odom(t), t, clock['ns'], 1.0)
        put(T0 - 60 * S + S // 10)
    _, message, values = health_report(w.snapshot({}))
    assert int(values['warnings.odometry_rewound']) == 2      # back twice (forward: no)
    assert w.odometry.waits >= 2
    assert values['duplicate_clouds'] == '0' and values['frames_out'] == '6'
    assert not [line for kind, line in log.lines if kind == 'error']


def test_refused_odometry_is_named_as_the_reason_for_single_frame(worker):
    w, mc, published, log, clock = worker
    for t in range(T0 - S // 2, T0 + 1, S // 20):
        bad = odom(t)
        bad.pose.pose.orientation.w = float('nan')
        w.odometry.put(bad, t, clock['ns'], 1.0)
    put_cloud(w, mc, T0)
    assert until(lambda: w.frames_out == 1)
    assert w.last.pose_source.startswith('none: odometry rejected: '), w.last.pose_source
    _, message, _ = health_report(w.snapshot({}))
    assert 'odometry rejected' in message and 'no odometry received' not in message


def test_a_frame_that_fails_is_counted_and_held_in_the_diagnostics(worker):
    """Whatever makes a step raise (here the pipeline made to raise once), the node goes on
    and its diagnostics warn, not only its log."""
    w, mc, published, log, clock = worker
    real = w.pipeline.process
    calls = []

    def failing_once(msg, markers=True):
        calls.append(1)
        if len(calls) == 1:
            raise RuntimeError('out of memory')
        return real(msg, markers)

    w.pipeline.process = failing_once
    put_cloud(w, mc, T0)
    assert until(lambda: w.frames_failed == 1)
    level, message, values = health_report(w.snapshot({}))
    assert level >= 1 and 'frame failed: RuntimeError: out of memory' in message
    assert values['frames_failed'] == '1'
    put_cloud(w, mc, T0 + S // 10)
    assert until(lambda: w.frames_out == 1)               # and the next frame runs


def one_round(pipe, mc, stamps, reset=None):
    """A fresh worker (keep_skipped 2) on ``pipe`` finds clouds of ``stamps`` waiting in
    arrival order, runs until it published once, stops; returns it and what it published."""
    published, log = [], Log()
    w = FrameWorker(pipe, lambda: DetectorParams(), lambda: T0, published.append,
                    lambda: False, lambda: True, Reasons(lambda _: None, 5.0, 30.0), log,
                    keep_skipped=2)
    if reset:
        w.request(reset=reset)
    for stamp in stamps:
        put_cloud(w, mc, stamp)
    thread = threading.Thread(target=w.run, daemon=True)
    thread.start()
    try:
        assert until(lambda: w.frames_out == 1)
    finally:
        w.stop()
        thread.join(5.0)
    assert not [line for kind, line in log.lines if kind == 'error']
    return w, published


def test_clouds_skipped_while_busy_feed_the_next_inputs_sweeps(request):
    """Clouds wait when the worker starts: it buffers the last two it skips (no detection,
    counted) and runs the newest on all three sweeps, as the model was trained; a cloud that
    arrived out of order is not taken for time going backwards; after a reset request the
    skipped clouds (from before it) are let go."""
    from test_pipeline import make_pipeline
    mc = request.getfixturevalue('classes')
    pipe = make_pipeline(request.getfixturevalue('model'), mc)
    for t in range(T0 - S // 2, T0 + 2 * S, S // 50):
        assert pipe.add_odometry(odom(t))
    w, published = one_round(pipe, mc, [T0 + k * S // 10 for k in range(4)])
    assert w.frames_sweeps_only == 2 and w.mailbox.dropped == 3
    assert stamp_ns(published[0].detections_msg) == T0 + 3 * S // 10
    assert w.last.input_lags_s == pytest.approx((0.0, 0.1, 0.2))
    _, _, values = health_report(w.snapshot({}))
    assert values['frames_sweeps_only'] == '2' and values['input_sweeps'] == '3 over 0.20 s'
    assert float(values['buffer_ms_p50']) > 0.0
    # arrivals 0.5, 0.7, 0.6 s: the newest to arrive runs; 0.7 is past it and let go, 0.5 goes
    # into the sweeps before it; no reset
    resets = pipe.resets
    w, published = one_round(pipe, mc, [T0 + 5 * S // 10, T0 + 7 * S // 10, T0 + 6 * S // 10])
    assert stamp_ns(published[0].detections_msg) == T0 + 6 * S // 10
    assert w.frames_sweeps_only == 1 and pipe.resets == resets
    assert w.last.input_lags_s == pytest.approx((0.0, 0.1, 0.3))
    # a reset requested: the clouds skipped before it are not buffered, the input is one sweep
    w, published = one_round(pipe, mc, [T0 + 8 * S // 10, T0 + 9 * S // 10, T0 + S], 'test')
    assert w.frames_sweeps_only == 0 and pipe.last_reset_reason == 'test'
    assert w.last.input_lags_s == (0.0,)


def test_a_frame_that_fails_on_every_cloud_is_logged_once_with_its_traceback(worker):
    """A failure that repeats on every cloud (here the pipeline made to raise each time) is
    logged once with where it came from, not at the sensor's rate; every one is counted."""
    w, mc, published, log, clock = worker
    real = w.pipeline.process

    def failing(msg, markers=True):
        raise ValueError(f'bad cloud of {len(msg.data)} bytes')

    w.pipeline.process = failing
    for k in range(5):
        put_cloud(w, mc, T0 + k * S // 10)
        assert until(lambda n=k: w.frames_failed == n + 1)
    errors = [line for kind, line in log.lines if kind == 'error']
    assert len(errors) == 1 and errors[0].startswith('frame failed: ValueError: bad cloud of')
    assert 'Traceback' in errors[0] and 'in failing' in errors[0]
    level, message, values = health_report(w.snapshot({}))
    assert values['frames_failed'] == '5'
    # clouds come, nothing goes out: an ERROR once it lasts input_timeout_s
    snap = w.snapshot({})
    assert snap.failing_since is not None
    level, message, _ = health_report(replace(snap, now=snap.failing_since + 1.5))
    assert level == 2 and 'every frame failed for 1.5 s' in message
    assert health_report(replace(snap, now=snap.failing_since + 0.5))[0] == 1
    w.pipeline.process = real
    put_cloud(w, mc, T0 + 6 * S // 10)
    assert until(lambda: w.frames_out == 1)
    assert w.snapshot({}).failing_since is None            # a frame got out: no longer


def test_resets_of_one_kind_are_logged_once_in_a_while(worker):
    """A publisher that stamps every cloud the same: each is a new cloud (a memory reset
    each, counted), and the log says so once, not ten times a second."""
    w, mc, published, log, clock = worker
    for t in range(T0 - S // 2, T0 + 1, S // 20):
        w.odometry.put(odom(t), t, clock['ns'], 1.0)
    for k in range(5):
        w.mailbox.put(Received(cloud(mc, T0), T0, time.monotonic()), (T0, 'lidar', k), None,
                      count_gaps=False, dedupe=False)
        assert until(lambda n=k: w.frames_out == n + 1)
    assert w.pipeline.resets == 4
    lines = [line for kind, line in log.lines if 'memory reset: duplicate stamp' in line]
    assert len(lines) == 1


def test_settings_the_pipeline_cannot_apply_leave_the_frame_running(worker):
    """A parameter set that fails past validation (here the pipeline made to fail on it):
    the frame runs with the settings before, and the diagnostics hold why."""
    from dataclasses import replace
    w, mc, published, log, clock = worker

    real = w.pipeline.configure
    before = w.pipeline.params

    def refuse(params):
        real(params)                         # applied in part, then it fails
        if params.max_detections == 1:
            raise RuntimeError('cannot load the new thresholds')

    w.pipeline.configure = refuse
    w.request(params=replace(DetectorParams(), max_detections=1))
    put_cloud(w, mc, T0)
    assert until(lambda: w.frames_out == 1)
    assert w.frames_failed == 0 and w.pipeline.params == before      # the settings before
    level, message, _ = health_report(w.snapshot({}))
    assert level >= 1 and 'parameters not applied: RuntimeError' in message
    # what the node sets its parameters back to, once; not after a later set that applied
    assert w.take_restored() == before and w.take_restored() is None
    w.request(params=replace(DetectorParams(), max_detections=1))
    put_cloud(w, mc, T0 + S // 10)
    assert until(lambda: w.frames_out == 2)
    w.request(params=replace(DetectorParams(), max_detections=5))
    put_cloud(w, mc, T0 + 2 * S // 10)
    assert until(lambda: w.frames_out == 3)
    assert w.pipeline.params.max_detections == 5 and w.take_restored() is None


def test_the_detections_go_out_before_their_markers_are_built(request):
    """With a markers publisher (the node's), a frame's detections are published first, then
    its MarkerArray is built and published once (its boxes, its header), its time counted
    with the frame's processing; a marker build that fails loses only the markers: the frame
    counts as out, and the diagnostics say what failed."""
    from test_pipeline import make_pipeline
    mc = request.getfixturevalue('classes')
    pipe = make_pipeline(request.getfixturevalue('model'), mc)
    for t in range(T0 - S // 2, T0 + S, S // 50):
        assert pipe.add_odometry(odom(t))
    events, log = [], Log()
    built = pipe.markers

    def markers(out):
        events.append(('built', out.detections_msg is not None))
        return built(out)

    pipe.markers = markers
    w = FrameWorker(pipe, lambda: DetectorParams(), lambda: T0,
                    lambda out: events.append(('detections', out.markers_msg)),
                    lambda: True, lambda: True, Reasons(lambda _: None, 5.0, 30.0), log,
                    publish_markers=lambda out: events.append(('markers', out.markers_msg)))
    thread = threading.Thread(target=w.run, daemon=True)
    thread.start()
    try:
        put_cloud(w, mc, T0)
        assert until(lambda: len(events) >= 3 and 'markers' in w.stats[-1])
        assert len(events) == 3                                 # each once
        (first, unbuilt), second, (third, array) = events
        assert (first, unbuilt) == ('detections', None)         # out before the markers
        assert second == ('built', True) and third == 'markers'
        d = w.last.detections
        assert len(d) > 0                                       # a frame with boxes
        assert all(m.header is w.last.header for m in array.markers)
        labels = [m for m in array.markers if m.ns.endswith('/labels')]
        assert len(labels) == len(d)                             # one label a box: its boxes
        assert w.stats[-1]['markers'] > 0                        # in the processing figure
        assert not [line for kind, line in log.lines if kind == 'error']

        def broken(out):
            raise RuntimeError('no markers today')
        pipe.markers = broken
        put_cloud(w, mc, T0 + S // 10)
        assert until(lambda: w.frames_out == 2 and len(events) == 4)
        assert events[3:] == [('detections', None)] and w.frames_failed == 0
        _, message, _ = health_report(w.snapshot({}))
        assert 'markers not published: RuntimeError: no markers today' in message
    finally:
        w.stop()
        thread.join(5.0)
