"""Shared pytest setup: keep DDS on this machine and give each run its own ROS domain."""
from __future__ import annotations

import os

# Set before any test imports rclpy (and inherited by every process a test starts).
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ.pop('ROS_LOCALHOST_ONLY', None)   # deprecated; it would override the range
if 'ROS_DOMAIN_ID' not in os.environ:
    os.environ['ROS_DOMAIN_ID'] = str((os.getpid() % 100) + 1)
