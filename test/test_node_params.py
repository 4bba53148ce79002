"""The node's own runtime parameters and its QoS choice, on a real node in this process.

A private rclpy Context; parameters are changed through ``set_parameters`` (the same callback
a ``ros2 param set`` reaches); the points QoS is decided from publishers discovered over DDS.
"""
from __future__ import annotations

import re
import time

import pytest
from rosgraph import node_checkpoint

pytestmark = pytest.mark.ros

S = 10**9


@pytest.fixture(scope='module')
def checkpoint(tmp_path_factory):
    return node_checkpoint(tmp_path_factory.mktemp('ckpt'))


@pytest.fixture()
def make_node(checkpoint):
    import rclpy
    from rclpy.context import Context
    from rclpy.parameter import Parameter

    from suit_ros.node import DetectorNode
    made = []

    def make(cli_args=None, **params):
        ctx = Context()
        rclpy.init(context=ctx)
        overrides = [Parameter('checkpoint', value=checkpoint)]
        overrides += [Parameter(k.replace('__', '.'), value=v) for k, v in params.items()]
        try:
            node = DetectorNode(context=ctx, parameter_overrides=overrides, cli_args=cli_args)
        except BaseException:
            rclpy.try_shutdown(context=ctx)
            raise
        made.append((ctx, node))
        return node
    yield make
    for ctx, node in made:
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)


def set_param(node, name, value):
    from rclpy.parameter import Parameter
    result = node.set_parameters([Parameter(name, value=value)])[0]
    assert result.successful, result.reason


def cloud(stamp_ns, n=3000):
    import numpy as np

    from suit_ros.msg_adapters.classes import MessageClasses
    from suit_ros.msg_adapters.pointcloud2 import array_to_pointcloud2
    C = MessageClasses.from_rclpy()
    rng = np.random.default_rng(stamp_ns % 1000)
    a = np.zeros(n, [('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('intensity', '<f4')])
    a['x'], a['y'] = rng.uniform(-30, 30, n), rng.uniform(-30, 30, n)
    a['intensity'] = rng.uniform(0, 200, n)
    return array_to_pointcloud2(a, C.header(stamp_ns, 'lidar'), C)


def odom(stamp_ns):
    from nav_msgs.msg import Odometry
    m = Odometry()
    m.header.stamp.sec, m.header.stamp.nanosec = divmod(stamp_ns, S)
    m.pose.pose.orientation.w = 1.0
    return m


def wait_frames(node, n, timeout=30.0):
    end = time.monotonic() + timeout
    while node.worker.frames_out < n and time.monotonic() < end:
        time.sleep(0.02)
    assert node.worker.frames_out >= n


def diag(node):
    st = node.diagnostic_status()
    return st.level, st.message, {kv.key: kv.value for kv in st.values}


@pytest.mark.slow
def test_stale_input_warns_then_errors(make_node):
    from diagnostic_msgs.msg import DiagnosticStatus
    node = make_node()
    level, message, _ = diag(node)
    assert level == DiagnosticStatus.WARN and 'no point cloud received yet' in message
    now = node.get_clock().now().nanoseconds
    for k in range(5):                               # 10 Hz input
        node._on_cloud(cloud(now + k * S // 10), None)
        time.sleep(0.1)
    rate = float(diag(node)[2]['input_rate_hz'])     # while the input is fresh
    assert rate > 0
    wait_frames(node, 1)
    set_param(node, 'input_timeout_s', 30.0)
    assert _until(lambda: 'no point cloud for' in diag(node)[1])   # > 3 periods of 0.1 s
    level, message, values = diag(node)
    assert level == DiagnosticStatus.WARN and 'no point cloud for' in message, message
    period = float(values['input_period_ms']) / 1e3  # the clouds' median gap as they came
    said = re.search(r'expected every (\d+\.\d\d) s', message)
    assert said and 0.1 <= period < 0.2 and abs(float(said[1]) - period) <= 0.0051, message
    set_param(node, 'stale_periods', 100.0)
    level, message, _ = diag(node)
    assert 'no point cloud for' not in message
    set_param(node, 'input_timeout_s', 0.3)
    level, message, values = diag(node)
    assert level == DiagnosticStatus.ERROR and 'input_timeout_s 0.3' in message
    assert _until(lambda: float(diag(node)[2]['input_rate_hz']) < rate)   # decays without input


def test_latency_reference_follows_max_stamp_skew_s(make_node):
    node = make_node()
    node._on_cloud(cloud(1_600_000_000 * S), None)            # a 2020 stamp: far from the clock
    wait_frames(node, 1)
    values = diag(node)[2]
    assert values['latency_reference'].startswith('receive time (header stamps')
    assert float(values['latency_ms_p50']) < 60_000
    set_param(node, 'max_stamp_skew_s', 1e9)
    time.sleep(0.05)
    node._on_cloud(cloud(1_600_000_000 * S + S // 10), None)
    wait_frames(node, 2)
    values = diag(node)[2]
    assert values['latency_reference'] == 'header stamp'
    assert float(values['latency_ms_p50']) > 1e9                  # years, in ms


def test_odom_wait_s_waits_for_covering_odometry(make_node):
    node = make_node(odom_tolerance_s=0.0, odom_wait_s=0.0)
    t = node.get_clock().now().nanoseconds
    node._on_odom(odom(t - S // 2))
    node._on_odom(odom(t - S // 20))
    node._on_cloud(cloud(t), None)                             # odometry ends 50 ms before
    wait_frames(node, 1)
    assert node.worker.last.pose_source.startswith('none')
    set_param(node, 'odom_wait_s', 2.0)
    node._on_cloud(cloud(t + S // 10), None)
    assert _until(lambda: node.worker.odometry.waits == 1)      # the worker took it: waiting
    time.sleep(0.3)
    assert node.worker.frames_out == 1                          # still waiting for odometry
    node._on_odom(odom(t + S // 10 + S // 50))
    wait_frames(node, 2)
    assert node.worker.last.pose_source == 'odometry' and node.worker.odometry.waits == 1


def _publisher(node, reliability):
    from rclpy.qos import QoSProfile
    from sensor_msgs.msg import PointCloud2
    return node.create_publisher(PointCloud2, '/points',
                                 QoSProfile(depth=1, reliability=reliability))


def _until(cond, timeout=10.0):
    end = time.monotonic() + timeout
    while not cond() and time.monotonic() < end:
        time.sleep(0.05)
    return cond()


def test_points_qos_auto_follows_the_publishers(make_node):
    from rclpy.qos import ReliabilityPolicy as R
    node = make_node()
    assert node.points.reliability == R.BEST_EFFORT      # nobody publishes yet
    other = make_node(points_topic='/unused')
    reliable = _publisher(other, R.RELIABLE)

    def check(expected):
        node.points.update()
        return node.points.reliability == expected
    assert _until(lambda: check(R.RELIABLE))
    best_effort = _publisher(other, R.BEST_EFFORT)
    assert _until(lambda: check(R.BEST_EFFORT))
    other.destroy_publisher(best_effort)
    assert _until(lambda: check(R.RELIABLE))
    other.destroy_publisher(reliable)


def test_odometry_from_a_best_effort_publisher_is_heard(make_node):
    """A reliable reader never hears a best-effort publisher (PX4's bridge, some simulators),
    and nothing says so: every cloud would wait ``odom_wait_s`` and run single-frame. The
    odometry subscription follows its publishers as the points one does, and a pose sent
    best effort over DDS reaches the node's odometry gate."""
    from nav_msgs.msg import Odometry
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile
    from rclpy.qos import ReliabilityPolicy as R
    node = make_node()
    other = make_node(points_topic='/unused', odom_topic='/unused_odom')
    pub = other.create_publisher(Odometry, '/odom',
                                 QoSProfile(depth=10, reliability=R.BEST_EFFORT))

    def check():
        node.odom.update()
        return node.odom.reliability == R.BEST_EFFORT and pub.get_subscription_count() > 0
    assert _until(check)
    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(node)
    t = node.get_clock().now().nanoseconds
    sent = 0

    def heard():
        nonlocal sent
        pub.publish(odom(t + sent * S // 100))
        sent += 1
        executor.spin_once(timeout_sec=0.05)
        return node.worker.odometry.latest_ns >= t
    assert _until(heard)
    executor.remove_node(node)
    values = diag(node)[2]
    assert values['odometry_reliability'] == 'best_effort'
    assert values['points_reliability'] == 'best_effort'     # nobody publishes clouds


def test_odometry_publishers_are_counted_on_the_remapped_topic(make_node):
    """rclpy's publisher count does not remap: with ``/odom`` remapped the node counted
    nobody on the remapped topic, and its clouds never waited for odometry."""
    from nav_msgs.msg import Odometry
    node = make_node(cli_args=['--ros-args', '-r', '/odom:=/vehicle/odom'])
    assert node._odom_topic == '/vehicle/odom'
    assert not node.worker.odometry_published()
    other = make_node(points_topic='/unused', odom_topic='/unused_odom')
    other.create_publisher(Odometry, '/vehicle/odom', 10)
    assert _until(node.worker.odometry_published)


@pytest.mark.parametrize('name', ['', 'a b', '/x//y'])
def test_an_invalid_topic_name_stops_the_node_with_what_it_got(make_node, name):
    from suit_ros.errors import SuitRosError
    with pytest.raises(SuitRosError, match=r'odom_topic .* is not a valid ROS topic name'):
        make_node(odom_topic=name)
    with pytest.raises(SuitRosError, match=r'points_topic .* is not a valid ROS topic name'):
        make_node(points_topic=name)


@pytest.mark.parametrize('params,expected', [
    ({'points_qos': 'sensor_data'}, 'BEST_EFFORT'),
    ({'points_qos': 'reliable'}, 'RELIABLE'),
    ({'qos_overrides__/points__subscription__reliability': 'reliable'}, 'RELIABLE'),
])
def test_fixed_points_qos(make_node, params, expected):
    from rclpy.qos import ReliabilityPolicy as R
    node = make_node(**params)
    other = make_node(points_topic='/unused')
    pub = _publisher(other, R.BEST_EFFORT if expected == 'RELIABLE' else R.RELIABLE)
    assert _until(lambda: node.count_publishers('/points') > 0)
    node.points.update()
    assert node.points.reliability == getattr(R, expected)
    other.destroy_publisher(pub)


def test_read_only_parameters_are_refused_by_rclpy(make_node):
    from rclpy.parameter import Parameter
    node = make_node()
    result = node.set_parameters([Parameter('checkpoint', value='x')])[0]
    assert not result.successful
    result = node.set_parameters([Parameter('score_thresholds', value=[2.0])])[0]
    assert not result.successful and 'score_thresholds' in result.reason


def test_each_input_contract_case_raises_its_diagnostic(make_node):
    from diagnostic_msgs.msg import DiagnosticStatus
    # clouds come only as the test sends them: on a loaded machine more than a second may
    # pass between two, which is input_timeout_s's error, not what this test is about
    node = make_node(input_timeout_s=60.0)
    t = node.get_clock().now().nanoseconds
    no_x = cloud(t + 5 * S // 10)
    no_x.fields = [f for f in no_x.fields if f.name != 'x']
    no_i = cloud(t + S // 10)
    no_i.fields = [f for f in no_i.fields if f.name != 'intensity']
    other_frame = cloud(t + 6 * S // 10)
    other_frame.header.frame_id = 'velodyne'
    cases = [('no_intensity', no_i, 'no intensity field'),
             ('too_few_points', cloud(t + 2 * S // 10, n=50), 'points after filtering'),
             ('empty_cloud', cloud(t + 3 * S // 10, n=0), 'empty cloud'),
             ('unusable_cloud', no_x, 'unusable cloud'),
             ('frame_changed', other_frame, "frame_id changed from 'lidar' to 'velodyne'")]
    node._on_cloud(cloud(t), None)
    wait_frames(node, 1)
    level, message, values = diag(node)
    assert values['input_warnings'] == 'none'
    for n, (reason, msg, text) in enumerate(cases, start=2):
        node._on_cloud(msg, None)
        wait_frames(node, n)
        level, message, values = diag(node)
        assert level == DiagnosticStatus.WARN and text in message, (reason, message)
        assert values['input_warnings'] == reason and values[f'warnings.{reason}'] == '1'
    no_i2 = cloud(t + 7 * S // 10)                       # the same reason again: counted
    no_i2.fields = [f for f in no_i2.fields if f.name != 'intensity']
    no_i2.header.frame_id = 'velodyne'
    node._on_cloud(no_i2, None)
    wait_frames(node, len(cases) + 2)       # one cloud at a time: none replaced in the slot
    assert diag(node)[2]['warnings.no_intensity'] == '2'
    assert node.reasons.logged() == {r for r, _, _ in cases}     # one log line per reason


def test_intensity_as_reflectance_raises_its_diagnostic(make_node):
    import numpy as np
    node = make_node()
    msg = cloud(node.get_clock().now().nanoseconds)
    data = np.frombuffer(bytes(msg.data), np.float32).reshape(-1, 4).copy()
    data[:, 3] /= 255.0                                          # 0..1 reflectance
    msg.data = data.tobytes()
    node._on_cloud(msg, None)
    wait_frames(node, 1)
    level, message, values = diag(node)
    assert 'likely 0..1 reflectance' in message and values['input_warnings'] == 'intensity_range'


def test_clouds_lost_before_the_callback_are_counted_and_raise_a_warning(make_node):
    from diagnostic_msgs.msg import DiagnosticStatus
    node = make_node()
    t = node.get_clock().now().nanoseconds
    now_ns = time.time_ns()

    def info(seq):
        return {'publication_sequence_number': seq, 'received_timestamp': now_ns - 3_000_000,
                'source_timestamp': now_ns - 4_000_000, 'reception_sequence_number': None}
    node._on_cloud(cloud(t), info(1))
    node._on_cloud(cloud(t + S // 10), info(2))
    wait_frames(node, 1)
    level, message, values = diag(node)
    assert values['lost_before_callback'] == '0' and 'never received' not in message
    assert float(values['reader_delay_ms_p50']) >= 3.0       # receive time -> callback
    node._on_cloud(cloud(t + 5 * S // 10), info(5))           # 3 and 4 never arrived
    level, message, values = diag(node)
    assert values['lost_before_callback'] == '2'
    assert level >= DiagnosticStatus.WARN and '2 clouds published but never received' in message
    node._on_cloud(cloud(t + 6 * S // 10), info(1))           # a restarted publisher: no gap
    node._on_cloud(cloud(t + 7 * S // 10), None)              # a middleware without numbers
    assert diag(node)[2]['lost_before_callback'] == '2'


def test_a_renamed_parameter_stops_the_node_with_its_new_name(make_node):
    """A launch file that still sets ``coast_frames`` (now ``coast_s``, in seconds) would be
    ignored by rclpy without a word: the node refuses to start and names the new one; an
    integer where a float belongs stops it with what to write instead of a traceback."""
    from suit_ros.errors import SuitRosError
    with pytest.raises(SuitRosError, match=r'coast_frames is now coast_s \(seconds'):
        make_node(coast_frames=3)
    # an integer for a float parameter (coast_frames: 0 becoming coast_s: 0) says what to write
    with pytest.raises(SuitRosError, match=r'coast_s must be a float \(a float needs a decimal'):
        make_node(coast_s=0)
    # a value outside the declared range, and a device this torch does not have
    with pytest.raises(SuitRosError, match=r'parameter threads must be within 0..256'):
        make_node(threads=300)
    import torch
    if not torch.cuda.is_available():
        with pytest.raises(SuitRosError, match=r'device is cuda, but this torch sees no CUDA'):
            make_node(device='cuda')
    node = make_node(coast_s=0.3)
    assert node.params.coast_s == 0.3
    # the diagnostics status is named for this node and its sensor's topic, so that two
    # detectors (one per LiDAR) are two statuses for an aggregator
    status = node.diagnostic_status()
    assert (status.name, status.hardware_id) == ('/detector: suit_ros detector', '/points')
    assert node.pipeline.detector.tracks.config.coast_s == 0.3
    assert node.ignored_parameters == []


def test_a_parameter_the_node_does_not_have_is_named_not_dropped_in_silence(make_node):
    """rclpy ignores an override for a parameter nobody declares: a misspelt
    ``score_threshold`` would leave the thresholds at their defaults without a word. The node
    names such parameters (and logs them); its own, ``use_sim_time`` and a QoS override of one
    of its endpoints are not among them."""
    node = make_node(score_threshold=0.5, use_sim_time=False,
                     **{'qos_overrides./odom.subscription.depth': 50})
    assert node.ignored_parameters == ['score_threshold']
    assert node.params.score_thresholds == (0.0,)
    values = {kv.key: kv.value for kv in node.diagnostic_status().values}
    assert values['ignored_parameters'] == 'score_threshold'
    values = {kv.key: kv.value for kv in make_node().diagnostic_status().values}
    assert values['ignored_parameters'] == 'none'



def test_a_set_the_pipeline_cannot_apply_is_set_back_on_the_node(make_node):
    """A parameter set the node accepts but the pipeline fails on past validation (here
    made to fail): the frames run on the settings before, and the node's parameters are set
    back to them, so that a parameter read says what the node does; a later set applies."""
    node = make_node(input_timeout_s=60.0)
    real = node.pipeline.configure

    def refuse(params):
        real(params)
        if params.max_detections == 7:
            raise RuntimeError('cannot apply')

    node.pipeline.configure = refuse
    set_param(node, 'max_detections', 7)
    assert node.get_parameter('max_detections').value == 7        # accepted, not yet run
    t = node.get_clock().now().nanoseconds
    node._on_cloud(cloud(t), None)
    wait_frames(node, 1)
    assert node.pipeline.params.max_detections == 200              # the settings before
    node._restore_parameters()                                     # (the node's 1 s timer)
    assert node.get_parameter('max_detections').value == 200
    assert node.params.max_detections == 200 and node.worker.pending is None
    set_param(node, 'max_detections', 9)
    node._on_cloud(cloud(t + S // 10), None)
    wait_frames(node, 2)
    assert node.pipeline.params.max_detections == 9
    node._restore_parameters()
    assert node.get_parameter('max_detections').value == 9


def test_odometry_the_pipeline_refuses_covers_no_cloud(make_node):
    """A zero quaternion is refused when the worker drains it (counted, said); its stamp
    must not tell the worker that odometry reached a cloud it will have no pose for."""
    node = make_node(input_timeout_s=60.0)
    t = node.get_clock().now().nanoseconds
    bad = odom(t)
    bad.pose.pose.orientation.w = 0.0
    node._on_odom(bad)
    assert node.worker.odometry.latest_ns == -1
    node._on_odom(odom(t - S // 10))
    assert node.worker.odometry.latest_ns == t - S // 10
