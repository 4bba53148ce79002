"""detect-bag (offline) equals the live node; play is byte exact; the demo path works."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from rosgraph import Probe, node_checkpoint, ros_env, start_node, stop, synthetic_bag

# separate processes over DDS: integration tests, outside the fast unit loop
pytestmark = [pytest.mark.ros, pytest.mark.slow]


@pytest.fixture(scope='module')
def bag(tmp_path_factory):
    return synthetic_bag(tmp_path_factory.mktemp('bag'), 8, 4, 'sqlite3')


@pytest.fixture(scope='module')
def checkpoint(tmp_path_factory):
    return node_checkpoint(tmp_path_factory.mktemp('ckpt'))


def read(path, topic):
    from suit_ros.data.bag import open_reader
    from suit_ros.msg_adapters.detections import pointcloud2_to_detections
    from suit_ros.msg_adapters.odometry import stamp_to_ns
    out = {}
    with open_reader(path) as r:
        for c, t, raw in r.messages():
            if c.topic == topic:
                m = r.deserialize(raw, c.msgtype)
                out[stamp_to_ns(m.header.stamp)] = (t, pointcloud2_to_detections(m))
    return out


def feed_paced(probe, pubs, types, recorded, live):
    """Publish the recorded ``(topic, raw)`` messages in order, each cloud once the node has
    answered the one before (``len(live)`` grows per answer), so that none is replaced in its
    mailbox however loaded the machine; then wait for the last answer."""
    from rclpy.serialization import deserialize_message
    sent = 0
    for topic, raw in recorded + [('/points', b'')]:
        if topic == '/points':    # the previous cloud answered first
            assert probe.spin_until(lambda n=sent: len(live) >= n, 60.0), (sent, len(live))
            if not raw:
                break
            sent += 1
        pubs[topic].publish(deserialize_message(raw, types[topic]))


def test_detect_bag_matches_live_node(bag, checkpoint, tmp_path):
    from suit_ros.cli import main
    assert main(['detect-bag', str(bag), str(tmp_path / 'out'), '--checkpoint', checkpoint,
                 '--copy-inputs']) == 0
    offline = read(tmp_path / 'out', '/detector/detections')
    clouds = read_clouds(bag)
    assert sorted(offline) == sorted(clouds)                       # every frame, in order
    assert all(t == s for s, (t, _) in offline.items())             # written at input stamps
    from suit_ros.data.bag import open_reader
    with open_reader(tmp_path / 'out') as r:
        topics = {c.topic for c in r.connections}
    assert {'/points', '/odom', '/gt/objects', '/detector/markers'} <= topics
    # the output bag evaluates against its own GT
    assert main(['eval', '--bag', str(tmp_path / 'out'), '--plot', str(tmp_path / 'pr.png'),
                 '--json-out', str(tmp_path / 'm.json')]) == 0
    assert (tmp_path / 'pr.png').stat().st_size > 5000
    # the live node, fed the recorded messages in their order, each cloud once the node has
    # published the one before (so none is replaced in its mailbox, however loaded the
    # machine), publishes the same detections
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import PointCloud2

    from suit_ros.data.bag import open_reader
    from suit_ros.msg_adapters.detections import pointcloud2_to_detections
    types = {'/points': PointCloud2, '/odom': Odometry}
    with open_reader(bag) as r:
        recorded = [(c.topic, bytes(raw)) for c, _, raw in r.messages() if c.topic in types]
    node = start_node(checkpoint, 'threads:=2')
    probe = Probe()
    live = {}
    probe.node.create_subscription(
        PointCloud2, '/detector/detections',
        lambda m: live.__setitem__(m.header.stamp.sec * 10**9 + m.header.stamp.nanosec,
                                   pointcloud2_to_detections(m)), 50)
    pubs = {t: probe.node.create_publisher(cls, t, 50) for t, cls in types.items()}
    try:
        assert probe.spin_until(lambda: all(p.get_subscription_count() for p in pubs.values())
                                and node.poll() is None, 60.0), stop(node)[-3000:]
        probe.spin_for(2.5)           # the node's points QoS follows the publisher (1 s checks)
        feed_paced(probe, pubs, types, recorded, live)
    finally:
        probe.close()
        stop(node)
    assert sorted(live) == sorted(offline)
    for s, (_, d) in offline.items():
        np.testing.assert_allclose(live[s]['boxes'], d['boxes'], atol=1e-3)
        np.testing.assert_array_equal(live[s]['labels'], d['labels'])
        # the tracker's fields too: the same tracks, equally sure of their velocities
        np.testing.assert_array_equal(live[s]['track_id'], d['track_id'])
        np.testing.assert_allclose(live[s]['vel_std'], d['vel_std'], rtol=1e-3, atol=1e-3)



def test_a_bag_played_in_a_loop_gives_the_same_detections_each_time(bag, checkpoint):
    """A live node over DDS fed the recorded clouds and odometry twice in a row, as a bag
    played in a loop: time goes back between the passes, and every cloud's stamp comes again.
    The node answers every cloud of both passes, and the second pass publishes what the first
    did (memory, sweeps and tracks started again; track ids go on counting). Before, the
    repeated stamps were taken for copies and dropped. (This bag lasts under a second: its
    odometry goes back less than a second, told by three stamps in a row, and comes before
    the pass's last cloud has run, which keeps its own time line; a long loop's odometry is
    test_worker's.)"""
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import PointCloud2

    from suit_ros.data.bag import open_reader
    from suit_ros.msg_adapters.detections import pointcloud2_to_detections
    types = {'/points': PointCloud2, '/odom': Odometry}
    with open_reader(bag) as r:
        recorded = [(c.topic, bytes(raw)) for c, _, raw in r.messages() if c.topic in types]
    node = start_node(checkpoint, 'threads:=2')
    probe = Probe()
    live: list[tuple[int, dict]] = []
    probe.node.create_subscription(
        PointCloud2, '/detector/detections',
        lambda m: live.append((m.header.stamp.sec * 10**9 + m.header.stamp.nanosec,
                               pointcloud2_to_detections(m))), 50)
    pubs = {t: probe.node.create_publisher(cls, t, 50) for t, cls in types.items()}
    try:
        assert probe.spin_until(lambda: all(p.get_subscription_count() for p in pubs.values())
                                and node.poll() is None, 60.0), stop(node)[-3000:]
        probe.spin_for(2.5)
        feed_paced(probe, pubs, types, recorded + recorded, live)
    finally:
        probe.close()
        log = stop(node)
    n = sum(t == '/points' for t, _ in recorded)
    assert len(live) == 2 * n, log[-3000:]
    first, second = live[:n], live[n:]
    assert [s for s, _ in first] == [s for s, _ in second]
    for (_, a), (_, b) in zip(first, second):
        np.testing.assert_allclose(b['boxes'], a['boxes'], atol=1e-4)
        np.testing.assert_array_equal(b['labels'], a['labels'])
        np.testing.assert_allclose(b['scores'], a['scores'], atol=1e-5)
    # the tracks started again, with new ids: none of the first pass's comes back
    ids_first = {int(i) for _, a in first for i in a['track_id'] if i}
    ids_second = {int(i) for _, b in second for i in b['track_id'] if i}
    assert ids_first and ids_second and not ids_first & ids_second
    assert 'memory reset: time went backwards' in log


def read_clouds(path):
    from suit_ros.data.bag import open_reader
    from suit_ros.msg_adapters.odometry import stamp_to_ns
    with open_reader(path) as r:
        return {stamp_to_ns(r.deserialize(raw, c.msgtype).header.stamp): t
                for c, t, raw in r.messages() if c.topic == '/points'}


def test_play_is_byte_exact_with_clock(bag):
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import PointCloud2

    from suit_ros.data.bag import open_reader
    probe = Probe()
    raw_msgs, clocks = [], []
    probe.node.create_subscription(PointCloud2, '/points', raw_msgs.append, 50, raw=True)
    probe.node.create_subscription(Clock, '/clock', clocks.append, 500)
    try:
        player = subprocess.Popen([sys.executable, '-m', 'suit_ros.cli', 'play', str(bag),
                                   '--clock', '--topics', '/points', '--start-delay', '1',
                                   '--wait-subscribers', '20'],
                                  env=ros_env(), stdout=subprocess.PIPE,
                                  stderr=subprocess.STDOUT, text=True)
        probe.spin_until(lambda: player.poll() is not None, 60.0)
        probe.spin_until(lambda: len(raw_msgs) >= 8, 5.0)
        out = stop(player)
    finally:
        probe.close()
    with open_reader(bag) as r:
        expected = [bytes(raw) for c, _, raw in r.messages() if c.topic == '/points']
    # byte exact: every received message is a recorded one, in order (DDS discovery may cost
    # the very first sample on a loaded machine)
    assert len(raw_msgs) >= len(expected) - 1, out
    assert raw_msgs == expected[len(expected) - len(raw_msgs):], out
    assert len(clocks) >= len(expected)


@pytest.mark.parametrize('argv,match', [
    (['detect-bag', '/nonexistent/bag', '/tmp/x'], 'does not exist'),
    (['play', '/nonexistent/bag'], 'does not exist')])
def test_bag_tools_fail_clearly(argv, match, capsys):
    from suit_ros.cli import main
    assert main(argv) == 1
    assert match in capsys.readouterr().err


def test_corrupt_bags_and_checkpoints_are_rejected(bag, tmp_path, capsys):
    import shutil

    from suit_ros.cli import main
    from suit_ros.data.sim import preset
    from suit_ros.data.sim.recording import write_bag
    broken = tmp_path / 'broken'
    shutil.copytree(bag, broken)
    db = next(broken.glob('*.db3'))
    db.write_bytes(db.read_bytes()[:2000])                           # truncated sqlite3
    assert main(['detect-bag', str(broken), str(tmp_path / 'o'), '--checkpoint', 'x']) == 1
    assert 'error' in capsys.readouterr().err
    (broken / 'metadata.yaml').write_text('not: [valid')
    assert main(['play', str(broken)]) == 1
    (broken / 'metadata.yaml').unlink()              # a folder with no metadata: what to do
    assert main(['play', str(broken)]) == 1
    err = capsys.readouterr().err
    assert 'is a folder without metadata.yaml' in err and 'ros2 bag reindex' in err
    write_bag(tmp_path / 'm', preset('test', frames=2), 1, 'mcap')    # truncated mcap
    mcap = next((tmp_path / 'm').glob('*.mcap'))
    mcap.write_bytes(mcap.read_bytes()[:3000])
    assert main(['detect-bag', str(tmp_path / 'm'), str(tmp_path / 'o2')]) == 1
    assert 'error' in capsys.readouterr().err
    write_bag(tmp_path / 'c', preset('test', frames=2), 1, 'mcap')    # damaged in a chunk
    mcap = next((tmp_path / 'c').glob('*.mcap'))
    data = bytearray(mcap.read_bytes())
    data[len(data) // 3:len(data) // 3 + 64] = bytes(64)     # inside a cloud's points
    mcap.write_bytes(bytes(data))
    assert main(['detect-bag', str(tmp_path / 'c'), str(tmp_path / 'o4')]) == 1
    assert 'Chunk checksum mismatch' in capsys.readouterr().err
    assert not (tmp_path / 'o4').exists()            # nothing was read: nothing written
    junk = tmp_path / 'junk.safetensors'
    junk.write_bytes(b'not a checkpoint' * 10)
    assert main(['detect-bag', str(bag), str(tmp_path / 'o3'), '--checkpoint', str(junk)]) == 1
    err = capsys.readouterr().err
    assert 'junk.safetensors' in err and 'error' in err
