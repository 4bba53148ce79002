"""rosbag2 reading and writing with rosbags (sqlite3 and mcap), shared by every bag command."""
from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager
import os
from pathlib import Path
import sys
from typing import Any

import numpy as np
from numpy.typing import NDArray

from suit_ros.errors import BagError
from suit_ros.structures import Detections, Frame

STORAGES = ('mcap', 'sqlite3')


def typestore() -> Any:
    """The ROS 2 Jazzy typestore."""
    from rosbags.typesys import Stores, get_typestore
    return get_typestore(Stores.ROS2_JAZZY)


class BagWriter:
    """A rosbag2 writer that takes rosbags messages or raw CDR bytes."""

    def __init__(self, writer: Any, store: Any) -> None:
        self._writer = writer
        self.store = store
        self._connections: dict[str, Any] = {}

    def connection(self, topic: str, msgtype: str, store: Any = None,
                   qos: Sequence[Any] = ()) -> Any:
        """The connection for ``topic`` (created on first use; its type defined in ``store``,
        by default this writer's, and offered with ``qos``)."""
        if topic not in self._connections:
            self._connections[topic] = self._writer.add_connection(
                topic, msgtype, typestore=store or self.store, offered_qos_profiles=qos)
        return self._connections[topic]

    def copy(self, conn: Any, stamp_ns: int, raw: bytes | memoryview, store: Any) -> None:
        """Write a message read from another bag unchanged: ``conn`` its connection (its
        type defined in ``store``, the reader's typestore, which holds the bag's own types;
        its offered QoS kept, so a latched /tf_static stays latched)."""
        qos = getattr(getattr(conn, 'ext', None), 'offered_qos_profiles', None) or ()
        self._writer.write(self.connection(conn.topic, conn.msgtype, store, qos),
                           int(stamp_ns), bytes(raw))

    def write(self, topic: str, msgtype: str, stamp_ns: int, msg: Any) -> None:
        """Serialise (unless ``msg`` is already CDR bytes) and write."""
        conn = self.connection(topic, msgtype)
        data = msg if isinstance(msg, (bytes, bytearray, memoryview)) else \
            self.store.serialize_cdr(msg, msgtype)
        self._writer.write(conn, int(stamp_ns), data)


@contextmanager
def open_writer(path: str | os.PathLike[str], storage: str = 'mcap') -> Iterator[BagWriter]:
    """Open a new bag for writing (the path must not exist)."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    if storage not in STORAGES:
        raise BagError(f'storage must be one of {STORAGES}, not {storage!r}')
    path = Path(path)
    if path.exists():
        raise BagError(f'{path} already exists; choose a new output path or delete it')
    plugin = StoragePlugin.MCAP if storage == 'mcap' else StoragePlugin.SQLITE3
    writer = Writer(path, version=9, storage_plugin=plugin)
    writer.open()
    try:
        yield BagWriter(writer, typestore())
    finally:
        writer.close()
    for mcap in sorted(path.glob('*.mcap')):
        write_chunk_crcs(mcap)


MCAP_MAGIC = b'\x89MCAP0\r\n'


def write_chunk_crcs(path: str | os.PathLike[str]) -> int:
    """Write each uncompressed chunk's CRC-32 into an mcap file (rosbags writes 0: "not
    checked"; ros2 bag's writer computes them), so that a reader finds a corrupt chunk
    instead of reading its damaged clouds. :return: the chunks checked so.

    :raises BagError: the file is not an mcap file this can walk.
    """
    import mmap
    import struct
    from zlib import crc32
    path = Path(path)
    done = 0
    with open(path, 'r+b') as f, mmap.mmap(f.fileno(), 0) as m:
        if m[:8] != MCAP_MAGIC:
            raise BagError(f'{path} is not an mcap file')
        pos = 8
        while pos + 9 <= len(m):
            op, length = m[pos], struct.unpack_from('<Q', m, pos + 1)[0]
            body = pos + 9
            if body + length > len(m):
                raise BagError(f'{path}: a record at byte {pos} runs past the end of the '
                               'file (truncated)')
            if op == 0x0F:          # data end: the summary follows
                break
            if op == 0x06:          # chunk: 3 x u64, crc u32, compression, records
                crc_at = body + 24
                (name_len,) = struct.unpack_from('<I', m, crc_at + 4)
                at = crc_at + 8 + name_len
                (size,) = struct.unpack_from('<Q', m, at)
                if name_len == 0:   # uncompressed (what rosbags writes by default)
                    struct.pack_into('<I', m, crc_at, crc32(m[at + 8:at + 8 + size]))
                    done += 1
            pos = body + length
        m.flush()
    return done


@contextmanager
def open_reader(path: str | os.PathLike[str]) -> Iterator[Any]:
    """Open a bag (either storage) with rosbags' AnyReader; clear errors for bad files."""
    from rosbags.highlevel import AnyReader
    path = Path(path)
    if not path.exists():
        raise BagError(f'bag {path} does not exist')
    if path.is_dir() and not (path / 'metadata.yaml').exists():
        inside = sorted(p.name for p in path.iterdir() if p.suffix in ('.mcap', '.db3'))
        raise BagError(f'{path} is a folder without metadata.yaml, so not a rosbag2 bag'
                       + (f'; it holds {", ".join(inside)}: pass the .mcap file itself, or '
                          'write the metadata again with `ros2 bag reindex`' if inside else ''))
    try:
        reader = AnyReader([path], default_typestore=typestore())
        reader.open()
    except Exception as exc:   # rosbags raises several types for corrupt or foreign files
        raise BagError(f'cannot open bag {path}: {exc}') from exc
    try:
        yield reader
    finally:
        reader.close()


POINTCLOUD2 = 'sensor_msgs/msg/PointCloud2'
ODOMETRY = 'nav_msgs/msg/Odometry'


def check_topic(reader: Any, topic: str, msgtype: str, required: bool = True,
                hint: str = '') -> bool:
    """Whether the bag has ``topic``, checking that it carries ``msgtype``.

    :raises BagError: a required topic is missing, or the topic carries another type (a
        mistyped topic name would otherwise fail deep inside, or be read as nothing).
    """
    types = {c.topic: c.msgtype for c in reader.connections}
    if topic not in types:
        if required:
            raise BagError(f'the bag has no {topic} topic (topics: {sorted(types)})'
                           + (f'; {hint}' if hint else ''))
        return False
    if types[topic] != msgtype:
        raise BagError(f'{topic} carries {types[topic]}, not {msgtype}: name the topic of '
                       f'the {msgtype.rsplit("/", 1)[-1]} messages'
                       + (f'; {hint}' if hint else ''))
    return True


def messages(reader: Any, connections: Any = None) -> Iterator[tuple[Any, int, bytes]]:
    """``reader.messages()`` with storage errors (truncated, corrupt) raised as BagError."""
    from suit_ros.errors import SuitRosError
    it = reader.messages(connections=connections) if connections is not None \
        else reader.messages()
    while True:
        try:
            item = next(it)
        except StopIteration:
            return
        except SuitRosError:
            raise
        except Exception as exc:   # rosbags / mcap / sqlite raise many types for bad data
            raise BagError(f'cannot read the bag: {type(exc).__name__}: {exc}; the file may '
                           'be truncated or corrupt') from exc
        yield item


def read_bag_frames(path: str | os.PathLike[str], points_topic: str = '/points',
                    odom_topic: str = '/odom', gt_topic: str = '/gt/objects',
                    intensity_scale: float = 255.0) -> Iterator[Frame]:
    """Frames (points, pose, GT) from a bag with clouds, odometry and GT in the cloud's frame.

    The extrinsic comes from ``/tf_static`` (base_link -> the cloud's frame) when present.
    """
    from suit_ros.deskew import TIME_FIELDS, relative_times
    from suit_ros.msg_adapters.detections import pointcloud2_to_detections
    from suit_ros.msg_adapters.odometry import PoseBuffer, odometry_to_pose, stamp_to_ns
    from suit_ros.msg_adapters.pointcloud2 import pointcloud2_to_xyzi
    with open_reader(path) as reader:
        check_topic(reader, points_topic, POINTCLOUD2, hint=str(path))
        check_topic(reader, odom_topic, ODOMETRY, hint=str(path))
        check_topic(reader, gt_topic, POINTCLOUD2, required=False)
        # every pose is read before any cloud: none may age out of the buffer (a bag longer
        # than the buffer's age failed at its first cloud), and none is a time jump
        buf = PoseBuffer(max_age_ns=2**62, tolerance_ns=150_000_000, rewind_ns=None)
        extr = np.eye(4)
        gts: dict[int, dict[str, Any]] = {}
        clouds = []
        static: list[Any] = []
        conns = [c for c in reader.connections
                 if c.topic in (points_topic, odom_topic, gt_topic, '/tf_static')]
        for conn, _, raw in messages(reader, conns):
            msg = reader.deserialize(raw, conn.msgtype)
            if conn.topic == odom_topic:
                T, s = odometry_to_pose(msg)
                buf.add(s, T)
            elif conn.topic == gt_topic:
                gts[stamp_to_ns(msg.header.stamp)] = pointcloud2_to_detections(msg)
            elif conn.topic == '/tf_static':
                static.extend(msg.transforms)
            else:
                clouds.append(msg)
        if clouds:
            extr = lidar_extrinsic(static, str(clouds[0].header.frame_id), str(path))
        for msg in clouds:
            stamp = stamp_to_ns(msg.header.stamp)
            cloud = pointcloud2_to_xyzi(msg, time_fields=TIME_FIELDS)
            xyzi = cloud.points
            times = (None if cloud.times is None
                     else relative_times(cloud.times, stamp)[0])   # None: unusable ones
            if times is not None and not times.any():
                times = None                                      # a sweep of one instant
            pts = np.concatenate([xyzi, np.zeros((len(xyzi), 1), np.float32)], 1)
            pts[:, 3] /= intensity_scale
            g = gts.get(stamp)
            gt = (Detections(g['boxes'], g['velocities'], g['scores'], g['labels'])
                  if g is not None else None)
            yield Frame(pts, buf.lookup(stamp) @ extr, stamp, str(msg.header.frame_id), gt,
                        g.get('num_points') if g else None, g.get('instance_id') if g else None,
                        str(path), extr.copy(), times=times)


def lidar_extrinsic(static: Sequence[Any], lidar_frame: str, where: str) -> NDArray[np.float64]:
    """The vehicle -> LiDAR transform among a bag's ``/tf_static`` ones (a bag may hold IMU
    or camera ones too): the one into the clouds' frame, from ``base_link`` if there is one
    (another parent, such as ``base_footprint``, is said on stderr); identity, said too, when
    none leads into the clouds' frame."""
    lidar = lidar_frame.lstrip('/')
    into = [tf for tf in static if str(tf.child_frame_id).lstrip('/') == lidar]
    from_base = [tf for tf in into if str(tf.header.frame_id).lstrip('/') == 'base_link']
    if from_base or into:
        tf = (from_base or into)[0]
        if not from_base:
            print(f'{where}: the LiDAR extrinsic is {tf.header.frame_id} -> {lidar} (no '
                  'base_link one)', file=sys.stderr)
        return transform_to_matrix(tf.transform)
    if static:
        print(f'{where}: no /tf_static transform into {lidar}: the clouds are taken as in the '
              'vehicle frame', file=sys.stderr)
    return np.eye(4)


def transform_to_matrix(tr: Any) -> NDArray[np.float64]:
    """A geometry_msgs/Transform as a ``(4, 4)`` matrix."""
    from suit_ros.msg_adapters.odometry import quaternion_to_matrix
    T = np.eye(4)
    q = tr.rotation
    T[:3, :3] = quaternion_to_matrix(q.x, q.y, q.z, q.w)
    T[:3, 3] = [tr.translation.x, tr.translation.y, tr.translation.z]
    return T
