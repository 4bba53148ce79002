"""The one place that keeps the project's own ROS graphs on this machine.

Every process the tests, the demo, the benchmarks and the scripts start runs with
``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` (not the deprecated ``ROS_LOCALHOST_ONLY``, which
overrides the range and is removed) and a per-run ``ROS_DOMAIN_ID``, so that no discovery
traffic leaves the machine and concurrent runs do not meet. The detector node itself sets no
discovery variable: in a car it talks across machines.

``python -m suit_ros.rosenv`` prints the same settings as shell exports (``scripts/env.sh``
evaluates them); ``--keep-domain`` keeps a ``ROS_DOMAIN_ID`` already set.
"""
from __future__ import annotations

from collections.abc import Mapping
import os
import sys
import time


def run_domain_id() -> int:
    """A per-run domain id within 1..100 (ids above 101 collide with ephemeral ports)."""
    return (os.getpid() + int(time.time())) % 100 + 1


def local_ros_env(base: Mapping[str, str] | None = None, keep_domain: bool = True
                  ) -> dict[str, str]:
    """``base`` (default: this process's environment) with DDS kept on this machine.

    :param keep_domain: keep a ``ROS_DOMAIN_ID`` that is already set (a test session's, so
        its child processes meet); False draws a new one.
    """
    env = dict(os.environ if base is None else base)
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env.pop('ROS_LOCALHOST_ONLY', None)
    if not (keep_domain and env.get('ROS_DOMAIN_ID')):
        env['ROS_DOMAIN_ID'] = str(run_domain_id())
    env['PYTHONUNBUFFERED'] = '1'
    return env


def shell_exports(keep_domain: bool = False) -> str:
    """The settings as ``export``/``unset`` lines for a POSIX shell."""
    env = local_ros_env(keep_domain=keep_domain)
    return '\n'.join(['unset ROS_LOCALHOST_ONLY'] + [
        f'export {k}={env[k]}' for k in ('ROS_AUTOMATIC_DISCOVERY_RANGE', 'ROS_DOMAIN_ID',
                                         'PYTHONUNBUFFERED')]) + '\n'


if __name__ == '__main__':
    sys.stdout.write(shell_exports(keep_domain='--keep-domain' in sys.argv[1:]))
