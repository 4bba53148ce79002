"""Building the geometry and visualization messages the adapters emit, through public API only.

Every message is made by its class's public constructor with keyword arguments, for rclpy's
generated classes and rosbags' dataclasses alike; nothing writes private slots or ``__dict__``.
What used to make a MarkerArray expensive (three Markers per box, ~47 us each in rclpy) is
gone from :func:`~suit_ros.msg_adapters.detections.detections_to_markerarray`: boxes are drawn
as one LINE_LIST marker per class (the RViz/Foxglove convention), so a frame costs one Marker
per class plus one TEXT label per box, and a ``geometry_msgs/Point`` per line end (~1 us).
``scripts/bench_markers.py`` prints what that costs, built and published.

Field values must already have the message types (Python ``float``/``int``/``str``).
"""
from __future__ import annotations

import functools
from typing import Any

from .classes import MessageClasses


class MessageFactory:
    """Builds messages of a :class:`MessageClasses` bundle through their constructors."""

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
               scale: Any, color: Any, lifetime: Any, text: str = '',
               points: list[Any] | None = None) -> Any:
        """visualization_msgs/Marker; the fields not named here keep their defaults."""
        return self.classes.Marker(header=header, ns=ns, id=id_, type=type_, action=action,
                                   pose=pose, scale=scale, color=color, lifetime=lifetime,
                                   text=text, points=points if points is not None else [])


@functools.lru_cache(maxsize=16)
def message_factory(classes: MessageClasses) -> MessageFactory:
    """The factory of a message bundle (cached per bundle)."""
    return MessageFactory(classes)
