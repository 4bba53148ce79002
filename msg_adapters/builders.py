"""Fast construction of the geometry and visualization messages the adapters emit in bulk.

A MarkerArray for 500 boxes holds ~1500 Markers and ~6000 sub-messages. The generated rclpy
constructors parse keywords, build default sub-messages only to replace them, and run a setter
per field: ~20 us per Marker, ~40 ms per array. The factories here create the objects without
``__init__`` and fill their storage directly: the ``_<field>`` slots of rclpy's generated
classes, the ``__dict__`` of rosbags' dataclasses. Each factory checks when it is made that
every class has exactly the expected fields, and otherwise (another ROS distro, or
``ROS_PYTHON_CHECK_FIELDS=1`` asking rclpy to check every field) the constructors are used.

Field values must already have the message types (Python ``float``/``int``/``str``).
"""
from __future__ import annotations

import dataclasses
import functools
from typing import Any

from .classes import MessageClasses

POINT = ('x', 'y', 'z')
QUATERNION = ('x', 'y', 'z', 'w')
COLOR = ('r', 'g', 'b', 'a')
POSE = ('position', 'orientation')
MARKER = ('header', 'ns', 'id', 'type', 'action', 'pose', 'scale', 'color', 'lifetime',
          'frame_locked', 'points', 'colors', 'texture_resource', 'texture', 'uv_coordinates',
          'text', 'mesh_resource', 'mesh_file', 'mesh_use_embedded_materials')


class MessageFactory:
    """Builds messages of a :class:`MessageClasses` bundle through their constructors.

    The reference behaviour; the subclasses build identical messages faster.
    """

    def __init__(self, classes: MessageClasses) -> None:
        self.classes = classes

    def point(self, x: float, y: float, z: float) -> Any:
        """geometry_msgs/Point."""
        return self.classes.Point(x=x, y=y, z=z)

    def vector3(self, x: float, y: float, z: float) -> Any:
        """geometry_msgs/Vector3."""
        return self.classes.Vector3(x=x, y=y, z=z)

    def quaternion(self, x: float, y: float, z: float, w: float) -> Any:
        """geometry_msgs/Quaternion."""
        return self.classes.Quaternion(x=x, y=y, z=z, w=w)

    def color(self, r: float, g: float, b: float, a: float) -> Any:
        """std_msgs/ColorRGBA."""
        return self.classes.ColorRGBA(r=r, g=g, b=b, a=a)

    def pose(self, position: Any, orientation: Any) -> Any:
        """geometry_msgs/Pose from a Point and a Quaternion."""
        return self.classes.Pose(position=position, orientation=orientation)

    def marker(self, header: Any, ns: str, id_: int, type_: int, action: int, pose: Any,
               scale: Any, color: Any, lifetime: Any, text: str = '') -> Any:
        """visualization_msgs/Marker; the fields not named here keep their defaults."""
        return self.classes.Marker(header=header, ns=ns, id=id_, type=type_, action=action,
                                   pose=pose, scale=scale, color=color, lifetime=lifetime,
                                   text=text)


def _has_slots(cls: Any, names: tuple[str, ...]) -> bool:
    slots = getattr(cls, '__slots__', None)
    return slots is not None and set(slots) == {'_' + n for n in names} | {'_check_fields'}


class _SlotsFactory(MessageFactory):
    """rclpy generated classes: ``object.__new__`` and direct slot writes."""

    def __init__(self, classes: MessageClasses) -> None:
        super().__init__(classes)
        c = classes
        self._empty_texture = c.Marker().texture
        self._empty_mesh = c.Marker().mesh_file

    @staticmethod
    def usable(classes: MessageClasses) -> bool:
        c = classes
        shapes = ((c.Point, POINT), (c.Vector3, POINT), (c.Quaternion, QUATERNION),
                  (c.ColorRGBA, COLOR), (c.Pose, POSE), (c.Marker, MARKER))
        return (all(_has_slots(cls, names) for cls, names in shapes)
                and not c.Point()._check_fields)

    def point(self, x: float, y: float, z: float) -> Any:
        o = object.__new__(self.classes.Point)
        o._x, o._y, o._z, o._check_fields = x, y, z, False
        return o

    def vector3(self, x: float, y: float, z: float) -> Any:
        o = object.__new__(self.classes.Vector3)
        o._x, o._y, o._z, o._check_fields = x, y, z, False
        return o

    def quaternion(self, x: float, y: float, z: float, w: float) -> Any:
        o = object.__new__(self.classes.Quaternion)
        o._x, o._y, o._z, o._w, o._check_fields = x, y, z, w, False
        return o

    def color(self, r: float, g: float, b: float, a: float) -> Any:
        o = object.__new__(self.classes.ColorRGBA)
        o._r, o._g, o._b, o._a, o._check_fields = r, g, b, a, False
        return o

    def pose(self, position: Any, orientation: Any) -> Any:
        o = object.__new__(self.classes.Pose)
        o._position, o._orientation, o._check_fields = position, orientation, False
        return o

    def marker(self, header: Any, ns: str, id_: int, type_: int, action: int, pose: Any,
               scale: Any, color: Any, lifetime: Any, text: str = '') -> Any:
        o = object.__new__(self.classes.Marker)
        o._header, o._ns, o._id, o._type, o._action = header, ns, id_, type_, action
        o._pose, o._scale, o._color, o._lifetime = pose, scale, color, lifetime
        o._frame_locked, o._points, o._colors, o._texture_resource = False, [], [], ''
        o._texture, o._uv_coordinates, o._text = self._empty_texture, [], text
        o._mesh_resource, o._mesh_file = '', self._empty_mesh
        o._mesh_use_embedded_materials, o._check_fields = False, False
        return o


def _has_fields(cls: Any, names: tuple[str, ...]) -> bool:
    """``cls`` is a dataclass whose fields without a default are ``names``, in order, and whose
    defaulted fields (rosbags: constants, ``__msgtype__``) are readable class attributes."""
    if not dataclasses.is_dataclass(cls):
        return False
    fields = dataclasses.fields(cls)
    required = tuple(f.name for f in fields
                     if f.default is dataclasses.MISSING
                     and f.default_factory is dataclasses.MISSING)
    defaulted = [f.name for f in fields if f.default is not dataclasses.MISSING]
    return (required == names and len(required) + len(defaulted) == len(fields)
            and all(hasattr(cls, n) for n in defaulted))


class _DictFactory(MessageFactory):
    """rosbags dataclasses: ``object.__new__`` and a ready ``__dict__``."""

    def __init__(self, classes: MessageClasses) -> None:
        super().__init__(classes)
        self._marker_cls = type(classes.Marker(header=classes.header(0, '')))
        template = classes.Marker(header=classes.header(0, ''))
        self._empty_texture = template.texture
        self._empty_mesh = template.mesh_file

    @staticmethod
    def usable(classes: MessageClasses) -> bool:
        c = classes
        if c.kind != 'rosbags':
            return False
        marker_cls = type(c.Marker(header=c.header(0, '')))
        shapes = ((c.Point, POINT), (c.Vector3, POINT), (c.Quaternion, QUATERNION),
                  (c.ColorRGBA, COLOR), (c.Pose, POSE), (marker_cls, MARKER))
        return all(_has_fields(cls, names) for cls, names in shapes)

    @staticmethod
    def _new(cls: Any, values: dict[str, Any]) -> Any:
        o = object.__new__(cls)
        o.__dict__ = values
        return o

    def point(self, x: float, y: float, z: float) -> Any:
        return self._new(self.classes.Point, {'x': x, 'y': y, 'z': z})

    def vector3(self, x: float, y: float, z: float) -> Any:
        return self._new(self.classes.Vector3, {'x': x, 'y': y, 'z': z})

    def quaternion(self, x: float, y: float, z: float, w: float) -> Any:
        return self._new(self.classes.Quaternion, {'x': x, 'y': y, 'z': z, 'w': w})

    def color(self, r: float, g: float, b: float, a: float) -> Any:
        return self._new(self.classes.ColorRGBA, {'r': r, 'g': g, 'b': b, 'a': a})

    def pose(self, position: Any, orientation: Any) -> Any:
        return self._new(self.classes.Pose, {'position': position, 'orientation': orientation})

    def marker(self, header: Any, ns: str, id_: int, type_: int, action: int, pose: Any,
               scale: Any, color: Any, lifetime: Any, text: str = '') -> Any:
        return self._new(self._marker_cls, {
            'header': header, 'ns': ns, 'id': id_, 'type': type_, 'action': action,
            'pose': pose, 'scale': scale, 'color': color, 'lifetime': lifetime,
            'frame_locked': False, 'points': [], 'colors': [], 'texture_resource': '',
            'texture': self._empty_texture, 'uv_coordinates': [], 'text': text,
            'mesh_resource': '', 'mesh_file': self._empty_mesh,
            'mesh_use_embedded_materials': False})


@functools.lru_cache(maxsize=16)
def message_factory(classes: MessageClasses) -> MessageFactory:
    """The fastest factory that builds correct messages of ``classes`` (cached per bundle).

    Messages from the fast factories share the empty ``texture`` and ``mesh_file`` of a Marker
    between markers; treat what they build as read-only.
    """
    if _SlotsFactory.usable(classes):
        return _SlotsFactory(classes)
    if _DictFactory.usable(classes):
        return _DictFactory(classes)
    return MessageFactory(classes)
