"""A bundle of the message classes the adapters build, from rclpy or from rosbags.

The adapters never import rclpy (or any message package): the caller hands them a bundle, so
the same function builds rclpy messages for a live graph and rosbags messages for bag files.
"""
from __future__ import annotations

from dataclasses import dataclass
import importlib
from typing import Any


@dataclass(frozen=True)
class MessageClasses:
    """Message classes by short name; ``kind`` is ``'rclpy'`` or ``'rosbags'``."""

    kind: str
    PointCloud2: Any
    PointField: Any
    Header: Any
    Time: Any
    Duration: Any
    Marker: Any
    MarkerArray: Any
    Point: Any
    Vector3: Any
    Quaternion: Any
    Pose: Any
    ColorRGBA: Any
    Odometry: Any

    @classmethod
    def from_rclpy(cls) -> MessageClasses:
        """The generated Python message classes (``sensor_msgs.msg`` ...), imported lazily."""
        def get(module: str, name: str) -> Any:
            return getattr(importlib.import_module(module), name)
        return cls('rclpy', get('sensor_msgs.msg', 'PointCloud2'),
                   get('sensor_msgs.msg', 'PointField'), get('std_msgs.msg', 'Header'),
                   get('builtin_interfaces.msg', 'Time'),
                   get('builtin_interfaces.msg', 'Duration'),
                   get('visualization_msgs.msg', 'Marker'),
                   get('visualization_msgs.msg', 'MarkerArray'),
                   get('geometry_msgs.msg', 'Point'), get('geometry_msgs.msg', 'Vector3'),
                   get('geometry_msgs.msg', 'Quaternion'), get('geometry_msgs.msg', 'Pose'),
                   get('std_msgs.msg', 'ColorRGBA'), get('nav_msgs.msg', 'Odometry'))

    @classmethod
    def from_rosbags(cls, typestore: Any) -> MessageClasses:
        """The dataclasses of a rosbags typestore (e.g. ``get_typestore(Stores.ROS2_JAZZY)``)."""
        t = typestore.types
        return cls('rosbags', t['sensor_msgs/msg/PointCloud2'], t['sensor_msgs/msg/PointField'],
                   t['std_msgs/msg/Header'], t['builtin_interfaces/msg/Time'],
                   t['builtin_interfaces/msg/Duration'], _rosbags_marker_factory(t),
                   t['visualization_msgs/msg/MarkerArray'], t['geometry_msgs/msg/Point'],
                   t['geometry_msgs/msg/Vector3'], t['geometry_msgs/msg/Quaternion'],
                   t['geometry_msgs/msg/Pose'], t['std_msgs/msg/ColorRGBA'],
                   t['nav_msgs/msg/Odometry'])

    def header(self, stamp_ns: int, frame_id: str) -> Any:
        """A Header with the given stamp and frame."""
        sec, nsec = divmod(int(stamp_ns), 10**9)
        return self.Header(stamp=self.Time(sec=sec, nanosec=nsec), frame_id=frame_id)


def _rosbags_marker_factory(t: Any) -> Any:
    """rosbags dataclasses need every field; fill the ones a caller leaves out."""
    import numpy as np
    marker = t['visualization_msgs/msg/Marker']
    image = t['sensor_msgs/msg/CompressedImage']
    mesh = t['visualization_msgs/msg/MeshFile']
    pose, point, quat = (t['geometry_msgs/msg/Pose'], t['geometry_msgs/msg/Point'],
                         t['geometry_msgs/msg/Quaternion'])
    vec, color, dur = (t['geometry_msgs/msg/Vector3'], t['std_msgs/msg/ColorRGBA'],
                       t['builtin_interfaces/msg/Duration'])
    empty = np.zeros(0, np.uint8)
    no_header = t['std_msgs/msg/Header'](stamp=t['builtin_interfaces/msg/Time'](sec=0, nanosec=0),
                                         frame_id='')

    def make(**kw: Any) -> Any:
        args = {'ns': '', 'id': 0, 'type': 0, 'action': 0,
                'pose': pose(position=point(x=0.0, y=0.0, z=0.0),
                             orientation=quat(x=0.0, y=0.0, z=0.0, w=1.0)),
                'scale': vec(x=0.0, y=0.0, z=0.0), 'color': color(r=0.0, g=0.0, b=0.0, a=0.0),
                'lifetime': dur(sec=0, nanosec=0), 'frame_locked': False, 'points': [],
                'colors': [], 'texture_resource': '', 'uv_coordinates': [], 'text': '',
                'mesh_resource': '', 'mesh_file': mesh(filename='', data=empty),
                'mesh_use_embedded_materials': False}
        args.update(kw)
        if 'texture' not in args:           # as rclpy's default: no texture, an empty header
            args['texture'] = image(header=no_header, format='', data=empty)
        return marker(**args)

    return make
