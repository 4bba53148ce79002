"""Shared pytest setup: keep DDS on this machine and give each run its own ROS domain."""
from __future__ import annotations

import os
import sys

# Byte-code caches on, here and in every process a test starts: with PYTHONDONTWRITEBYTECODE
# set (as on this project's machines) every run compiled the package and re-rewrote every
# test module (collection 5.6 s -> 2.9 s; each node process a test starts imports faster).
sys.dont_write_bytecode = False
os.environ.pop('PYTHONDONTWRITEBYTECODE', None)

# Set before any test imports rclpy (and inherited by every process a test starts).
from suit_ros.rosenv import local_ros_env  # noqa: E402

os.environ.pop('ROS_LOCALHOST_ONLY', None)
os.environ.update(local_ros_env())     # keeps a ROS_DOMAIN_ID set by scripts/test

# pytest-xdist: each worker is its own ROS graph (the session's id plus the worker's number,
# wrapped within 1..100), so two workers' nodes and probes never discover each other.
_worker = os.environ.get('PYTEST_XDIST_WORKER', '')
if _worker.startswith('gw'):
    os.environ['ROS_DOMAIN_ID'] = str(
        (int(os.environ['ROS_DOMAIN_ID']) + int(_worker[2:])) % 100 + 1)

# detect-bag and bench keep freed memory in their process as the node does (suit_ros.heap);
# this pytest process runs them in-process among many tests, so it keeps glibc's defaults
# (test/test_heap.py checks the setting in fresh processes).
import suit_ros.heap  # noqa: E402

suit_ros.heap.keep_freed_memory = lambda: False
