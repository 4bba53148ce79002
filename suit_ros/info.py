"""``suit-ros info``: the versions and devices this installation runs with."""
from __future__ import annotations

import argparse
from importlib import metadata
import os
import platform
import sys

from suit_ros import __version__


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Add ``info`` options."""
    parser.add_argument('--json', action='store_true', help='print JSON instead of a table')


def _dist_version(name: str) -> str:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return 'not installed'


def _rmw() -> str:
    """The RMW implementation rclpy loads, asked in a child process: with an
    ``RMW_IMPLEMENTATION`` that is not installed, importing rclpy ends the process (exit 102),
    which would take everything else this command reports with it."""
    import subprocess
    code = ('from rclpy.utilities import get_rmw_implementation_identifier as g; '
            'print(g())')
    try:
        done = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                              timeout=60, check=False)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f'unknown ({exc})'
    if done.returncode == 0 and done.stdout.strip():
        return done.stdout.strip().splitlines()[-1]
    said = (done.stderr.strip().splitlines() or ['no message'])[-1][:300]
    wanted = os.environ.get('RMW_IMPLEMENTATION', 'the default')
    return (f'cannot load {wanted} (exit {done.returncode}: {said}); install it or unset '
            'RMW_IMPLEMENTATION')


def collect() -> dict[str, str]:
    """Return a flat mapping of what this installation runs with."""
    import numpy
    info: dict[str, str] = {
        'suit_ros': __version__,
        'python': f'{platform.python_version()} ({sys.executable})',
        'platform': platform.platform(),
        'numpy': numpy.__version__,
    }
    try:
        import torch
        info['torch'] = torch.__version__
        info['torch threads'] = str(torch.get_num_threads())
        cuda = torch.cuda.is_available()
        info['torch device'] = (f'cuda ({torch.cuda.get_device_name(0)})' if cuda else 'cpu')
    except ImportError:
        info['torch'] = 'not installed'
    info['rclpy'] = _dist_version('ros-rclpy')
    info['rmw'] = _rmw()
    info['rosbags'] = _dist_version('rosbags')
    info['ROS_DOMAIN_ID'] = os.environ.get('ROS_DOMAIN_ID', '(unset: 0)')
    info['ROS_AUTOMATIC_DISCOVERY_RANGE'] = os.environ.get(
        'ROS_AUTOMATIC_DISCOVERY_RANGE', '(unset: SUBNET)')
    for name in ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE'):
        info[name] = os.environ.get(name, '(unset)')
    return info


def run(args: argparse.Namespace) -> int:
    """Print the information."""
    info = collect()
    if args.json:
        import json
        print(json.dumps(info, indent=2))
    else:
        width = max(len(k) for k in info)
        for key, value in info.items():
            print(f'{key:<{width}}  {value}')
    return 0
