"""Shared pytest setup: keep DDS on this machine and give each run its own ROS domain."""
from __future__ import annotations

import os

# Set before any test imports rclpy (and inherited by every process a test starts).
from suit_ros.rosenv import local_ros_env  # noqa: E402

os.environ.pop('ROS_LOCALHOST_ONLY', None)
os.environ.update(local_ros_env())     # keeps a ROS_DOMAIN_ID set by scripts/test
