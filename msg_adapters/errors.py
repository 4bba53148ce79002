"""Exceptions raised by the message adapters."""
from __future__ import annotations

from suit_ros.errors import SuitRosError


class MessageError(SuitRosError, ValueError):
    """A ROS message is malformed or cannot be converted; the text says which field and why."""


class PointCloudError(MessageError):
    """A PointCloud2 is invalid: short data, overlapping/overrunning fields, missing x/y/z..."""


class PoseLookupError(MessageError):
    """A pose was asked for at a stamp the pose buffer cannot answer (outside its span)."""
