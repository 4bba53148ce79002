"""suit_ros: the SUIT multi-frame LiDAR 3D detector as a ROS 2 node and offline tools.

Importing this package is cheap: torch and rclpy are imported only by the modules that need them.
"""
from suit_ros._version import __version__

# The detection classes, in label order (label ``i`` is ``CLASS_NAMES[i]``).
CLASS_NAMES: tuple[str, ...] = ('car', 'truck', 'pedestrian', 'cyclist')

__all__ = ['CLASS_NAMES', '__version__']
