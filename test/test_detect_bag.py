"""``detect-bag``: the node's parameter set, its flags, the /tf_static extrinsic, the summary."""
from __future__ import annotations

import argparse

import numpy as np
import pytest
from rosgraph import node_checkpoint, synthetic_bag

from suit_ros.detect_bag import configure_parser, params_from_args
from suit_ros.errors import BagError, ConfigError
from suit_ros.params import DetectorParams


def parse(*argv):
    parser = argparse.ArgumentParser()
    configure_parser(parser)
    return parser.parse_args(['in', 'out', *argv])


def test_flags_override_the_yaml_which_overrides_defaults(tmp_path):
    yaml = tmp_path / 'p.yaml'
    yaml.write_text('detector:\n  ros__parameters:\n    intensity_scale: 1.0\n'
                    '    max_range: 60.0\n')
    assert params_from_args(parse()) == DetectorParams()
    p = params_from_args(parse('--params', str(yaml), '--max-range', '40',
                               '--score-threshold', '0.3', '--extrinsic-xyz', '0', '0', '1.9',
                               '--extrinsic-rpy', '0', '0.1', '0', '--min-range', '2'))
    assert p.intensity_scale == 1.0 and p.max_range == 40.0 and p.min_range == 2.0
    assert p.score_thresholds == (0.3,) and p.extrinsic_xyz == (0.0, 0.0, 1.9)
    assert p.extrinsic_rpy == (0.0, 0.1, 0.0)
    assert p.precision == 'auto'
    assert params_from_args(parse('--precision', 'float32')).precision == 'float32'
    assert params_from_args(parse()).overhang == 'checkpoint'
    assert params_from_args(parse('--overhang', 'drop', '--ground', 'local')).overhang == 'drop'
    with pytest.raises(SystemExit):
        parse('--overhang', 'cut')
    assert params_from_args(parse()).box_fit == 'off'
    assert params_from_args(parse('--box-fit', 'faces')).box_fit == 'faces'
    with pytest.raises(SystemExit):
        parse('--box-fit', 'snap')
    assert params_from_args(parse()).traffic_side == 'right'
    assert params_from_args(parse('--traffic-side', 'left')).traffic_side == 'left'
    with pytest.raises(SystemExit):
        parse('--traffic-side', 'middle')
    with pytest.raises(SystemExit):
        parse('--precision', 'float16')
    with pytest.raises(ConfigError, match='min_range'):
        params_from_args(parse('--min-range', '50', '--max-range', '40'))


@pytest.fixture(scope='module')
def bag(tmp_path_factory):
    return synthetic_bag(tmp_path_factory.mktemp('bag'), 4, 11, 'mcap')


def test_extrinsic_from_tf_static_and_warning_summary(bag, tmp_path, capsys):
    from suit_ros.cli import main
    from suit_ros.data.bag import open_reader
    from suit_ros.data.sim import preset
    from suit_ros.data.sim.scene import Simulation
    from suit_ros.detect_bag import extrinsic_from_tf_static
    with open_reader(bag) as reader:
        xyz, rpy = extrinsic_from_tf_static(reader, 'base_link', 'lidar')
    T = Simulation(preset('test', frames=1), 11).T_base_lidar
    np.testing.assert_allclose(xyz, T[:3, 3], atol=1e-9)
    from suit_ros.ops.geometry import pose_from_xyz_rpy
    np.testing.assert_allclose(pose_from_xyz_rpy(xyz, rpy), T, atol=1e-9)
    with open_reader(bag) as reader, pytest.raises(BagError, match='no base_link -> os1'):
        extrinsic_from_tf_static(reader, 'base_link', 'os1')
    ckpt = node_checkpoint(tmp_path)
    # 0..255 intensities read as 0..1 reflectance: every frame flagged, and said so by reason
    assert main(['detect-bag', str(bag), str(tmp_path / 'out'), '--checkpoint', ckpt,
                 '--extrinsic-from-tf', '--intensity-scale', '1']) == 0
    out = capsys.readouterr().out
    assert f'extrinsic from /tf_static: xyz {[round(v, 4) for v in xyz]}' in out
    assert '4 warnings' in out
    assert 'warning intensity_range: 4 frames, e.g. intensity up to' in out


def test_what_a_user_gets_wrong_is_named_and_leaves_no_partial_bag(bag, tmp_path, capsys):
    """Per-class thresholds as the help promises; a topic of another type, the same topic for
    clouds and odometry, an output under a file, a checkpoint that fails after the output was
    opened: each exits 1 with what to do (no traceback), and no half-written bag is left to
    block the next try."""
    from suit_ros.cli import main
    ckpt = node_checkpoint(tmp_path)
    assert main(['detect-bag', str(bag), str(tmp_path / 'per_class'), '--checkpoint', ckpt,
                 '--score-threshold', '0.3', '0.3', '0.2', '0.2']) == 0
    capsys.readouterr()
    cases = [
        (['--points-topic', '/tf_static'], 'carries tf2_msgs/msg/TFMessage, not '
         'sensor_msgs/msg/PointCloud2'),
        (['--points-topic', '/points', '--odom-topic', '/points'], 'are both /points'),
        (['--points-topic', '/gt/objects'], '--gt-topic /gt/objects is also the cloud'),
        (['--odom-topic', '/odometry/filtered'], 'no /odometry/filtered topic'),
        (['--intensity-field', 'reflect'], 'none of the 4 clouds could be read: unusable'),
        (['--score-threshold', '0.3', '0.3'], 'score_thresholds needs 1 or 4 values'),
        (['--checkpoint', str(tmp_path / 'missing.safetensors')], 'does not exist'),
    ]
    for k, (flags, message) in enumerate(cases):
        out = tmp_path / f'out{k}'
        args = ['detect-bag', str(bag), str(out)] + (
            [] if '--checkpoint' in flags else ['--checkpoint', ckpt]) + flags
        assert main(args) == 1, flags
        err = capsys.readouterr().err
        assert message in err and 'Traceback' not in err, (flags, err)
        assert not out.exists(), flags                      # nothing left behind
    (tmp_path / 'file').write_text('x')
    assert main(['detect-bag', str(bag), str(tmp_path / 'file' / 'out'), '--checkpoint',
                 ckpt]) == 1
    assert 'folder of the output bag' in capsys.readouterr().err


def _with_extra_topics(src, dst, extra):
    """``src`` copied to ``dst`` (mcap) with ``extra``: (topic, msgtype, msg definition or
    None for a Jazzy type, message) written at the last stamp."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import get_types_from_msg

    from suit_ros.data.bag import messages, open_reader, typestore
    store = typestore()
    for _, msgtype, definition, _ in extra:
        if definition:
            store.register(get_types_from_msg(definition, msgtype))
    w = Writer(dst, version=9, storage_plugin=StoragePlugin.MCAP)
    w.open()
    conns = {}
    with open_reader(src) as r:
        for c, t, raw in messages(r):
            if c.topic not in conns:
                conns[c.topic] = w.add_connection(c.topic, c.msgtype, typestore=store)
            w.write(conns[c.topic], t, bytes(raw))
    for topic, msgtype, _, msg in extra:
        conn = w.add_connection(topic, msgtype, typestore=store)
        w.write(conn, t, msg if isinstance(msg, bytes) else store.serialize_cdr(msg, msgtype))
    w.close()
    return dst


def test_copy_inputs_keeps_a_vendor_type_and_not_an_old_runs_detections(bag, tmp_path,
                                                                         capsys):
    """A vendor message type in the input (its definition in the bag) is copied unchanged;
    an input that is itself a detect-bag output does not get the old model's detections
    mixed with the new ones."""
    from rosbags.typesys import get_types_from_msg

    from suit_ros.cli import main
    from suit_ros.data.bag import messages, open_reader, typestore
    ckpt = node_checkpoint(tmp_path)
    store = typestore()
    store.register(get_types_from_msg('int32 a\nstring b\n', 'vendor_msgs/msg/Custom'))
    custom = store.types['vendor_msgs/msg/Custom'](a=7, b='hi')
    vendor = _with_extra_topics(bag, tmp_path / 'vendor', [
        ('/vendor/status', 'vendor_msgs/msg/Custom', 'int32 a\nstring b\n', custom)])
    out = tmp_path / 'out'
    assert main(['detect-bag', str(vendor), str(out), '--checkpoint', ckpt,
                 '--copy-inputs']) == 0
    with open_reader(out) as r:
        counts = {c.topic: c.msgcount for c in r.connections}
        got = [r.deserialize(raw, c.msgtype) for c, _, raw in messages(r)
               if c.topic == '/vendor/status']
    assert counts['/vendor/status'] == 1 and (got[0].a, got[0].b) == (7, 'hi')
    assert counts['/detector/detections'] == counts['/points'] == 4
    capsys.readouterr()
    again = tmp_path / 'again'
    assert main(['detect-bag', str(out), str(again), '--checkpoint', ckpt,
                 '--copy-inputs']) == 0
    assert 'not copied: /detector/detections, /detector/markers' in capsys.readouterr().err
    with open_reader(again) as r:
        counts = {c.topic: c.msgcount for c in r.connections}
    assert counts['/detector/detections'] == counts['/detector/markers'] == 4
    assert counts['/vendor/status'] == 1


def test_a_bag_without_odometry_is_said_to_run_single_frame(tmp_path, capsys):
    from suit_ros.cli import main
    from suit_ros.data.bag import messages, open_reader, open_writer
    src = synthetic_bag(tmp_path, 3, 5, 'mcap')
    bare = tmp_path / 'bare'
    with open_reader(src) as r, open_writer(bare) as w:
        for c, t, raw in messages(r):
            if c.topic != '/odom':
                w.copy(c, t, raw, r.typestore)
    ckpt = node_checkpoint(tmp_path)
    assert main(['detect-bag', str(bare), str(tmp_path / 'out'), '--checkpoint', ckpt]) == 0
    captured = capsys.readouterr()
    assert 'the bag has no /odom: every frame runs single-frame' in captured.err
    assert 'single-frame (no pose for the memory and the sweeps): 3 of 3 frames' in captured.out


def test_bag_frames_take_the_lidar_extrinsic_and_every_pose_of_a_long_bag(bag, tmp_path):
    """read_bag_frames (eval --bag, training on bags): the extrinsic is base_link -> the
    clouds' frame even when /tf_static holds others after it (an IMU here), and a bag whose
    odometry spans more than 1,000 s still places its first clouds (all poses are read
    before any cloud; they used to age out of the buffer)."""
    import copy

    from suit_ros.data.bag import open_reader, open_writer, read_bag_frames
    plain = list(read_bag_frames(bag))
    longer = tmp_path / 'long'
    with open_reader(bag) as r, open_writer(longer, 'sqlite3') as w:
        last_odom = None
        for c, t, raw in r.messages():
            if c.topic == '/tf_static':
                msg = r.deserialize(raw, c.msgtype)
                imu = copy.deepcopy(msg.transforms[0])
                imu.child_frame_id = 'imu'
                imu.transform.translation.x = 5.0
                w.write(c.topic, c.msgtype, t, type(msg)(transforms=[*msg.transforms, imu]))
                continue
            if c.topic == '/odom':
                last_odom = (c, t, raw)
            w.write(c.topic, c.msgtype, t, bytes(raw))
        c, t, raw = last_odom
        late = r.deserialize(raw, c.msgtype)
        late.header.stamp.sec += 1200
        w.write(c.topic, c.msgtype, t + 1200 * 10**9, late)
    long_frames = list(read_bag_frames(longer))
    assert len(long_frames) == len(plain)
    for a, b in zip(plain, long_frames):
        np.testing.assert_allclose(b.T_base_lidar, a.T_base_lidar)
        np.testing.assert_allclose(b.pose, a.pose, atol=1e-9)


def test_the_lidar_extrinsic_is_the_transform_into_the_clouds_frame(capsys):
    from types import SimpleNamespace as Ns

    from suit_ros.data.bag import lidar_extrinsic

    def tf(parent, child, x):
        return Ns(header=Ns(frame_id=parent), child_frame_id=child,
                  transform=Ns(translation=Ns(x=x, y=0.0, z=0.0),
                               rotation=Ns(x=0.0, y=0.0, z=0.0, w=1.0)))
    imu = tf('base_link', 'imu', 5.0)
    assert lidar_extrinsic([tf('base_link', 'lidar', 1.0), imu], 'lidar', 'b')[0, 3] == 1.0
    # another vehicle frame: taken, and said
    assert lidar_extrinsic([imu, tf('base_footprint', '/lidar', 2.0)], '/lidar', 'b')[0, 3] == 2
    assert 'the LiDAR extrinsic is base_footprint -> lidar' in capsys.readouterr().err
    # none into the clouds' frame: the vehicle frame, said
    assert (lidar_extrinsic([imu], 'lidar', 'b') == np.eye(4)).all()
    assert 'no /tf_static transform into lidar' in capsys.readouterr().err


def test_the_mcap_bags_written_here_carry_chunk_crcs(tmp_path):
    """rosbags writes 0 ("not checked") as each chunk's CRC; the bags this package writes
    carry the real ones (as ros2 bag's do), which rosbags checks as it reads."""
    import struct
    from zlib import crc32

    from suit_ros.data.bag import MCAP_MAGIC, open_writer, write_chunk_crcs
    with open_writer(tmp_path / 'b') as bag:
        for k in range(3):
            bag.write('/n', 'std_msgs/msg/String', k, bag.store.types['std_msgs/msg/String'](
                data='x' * 1000))
    data = next((tmp_path / 'b').glob('*.mcap')).read_bytes()
    assert data[:8] == MCAP_MAGIC
    pos, crcs = 8, []
    while data[pos] != 0x0F:
        length = struct.unpack_from('<Q', data, pos + 1)[0]
        if data[pos] == 0x06:
            body = pos + 9
            crc, name_len = struct.unpack_from('<II', data, body + 24)
            size = struct.unpack_from('<Q', data, body + 32 + name_len)[0]
            records = data[body + 40 + name_len:body + 40 + name_len + size]
            crcs.append((crc, crc32(records)))
        pos += 9 + length
    assert crcs and all(c == want != 0 for c, want in crcs)
    not_mcap = tmp_path / 'x.mcap'
    not_mcap.write_bytes(b'not an mcap file')
    with pytest.raises(BagError, match='not an mcap file'):
        write_chunk_crcs(not_mcap)


def test_a_bag_damaged_part_way_keeps_the_frames_before_the_damage(tmp_path, capsys):
    """A long bag with one damaged chunk late in it: detect-bag exits 1 and says why, and the
    detections of the frames read before the damage are kept in the output, not thrown away
    with the run (a bag damaged before any cloud leaves nothing: test_playback)."""
    from suit_ros.cli import main
    from suit_ros.data.bag import open_reader, write_chunk_crcs
    from suit_ros.data.sim import preset
    from suit_ros.data.sim.recording import write_bag
    write_bag(tmp_path / 'b', preset('test', frames=6), 1, 'mcap')
    mcap = next((tmp_path / 'b').glob('*.mcap'))
    assert write_chunk_crcs(mcap) >= 2               # rosbags cuts the bag into chunks
    data = bytearray(mcap.read_bytes())
    at = int(len(data) * 0.8)                         # inside the last clouds
    data[at:at + 64] = bytes(64)
    mcap.write_bytes(bytes(data))
    assert main(['detect-bag', str(tmp_path / 'b'), str(tmp_path / 'o')]) == 1
    err = capsys.readouterr().err
    assert 'Chunk checksum mismatch' in err and 'frames read before it' in err
    with open_reader(tmp_path / 'o') as r:
        kept = sum(1 for c, _, _ in r.messages() if c.topic == '/detector/detections')
    assert 0 < kept < 6 and f'the {kept} frames' in err
