#!/usr/bin/env python3
"""DDS delivery of ~1.2 MB clouds between processes, with and without the large-data profile.

Plays the 100-frame demo bag's ``/points`` with ``suit-ros play`` (its own process) into a
subscriber in this process (no model: delivery only), for each combination of the player's
Fast DDS profile (Fast DDS defaults, or the shipped ``fastdds_large_data.xml``), the
publisher's reliability and the subscriber's reliability, and prints the clouds received.

Usage: . scripts/env.sh && python scripts/bench_delivery.py [--bag out/demo/demo-seed7-100f]
"""
from __future__ import annotations

import argparse
import os
from pathlib import Path
import sys
import tempfile

EMPTY_PROFILE = ('<?xml version="1.0" encoding="UTF-8"?>\n'
                 '<dds xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">'
                 '<profiles/></dds>\n')


def count(bag: str, profile: str, publisher: str, subscriber: str) -> tuple[int, int]:
    """Clouds received and published for one combination."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2

    from suit_ros.harness import Probe, start_player, stop
    probe = Probe('bench_delivery')
    got: list[int] = []
    rel = (ReliabilityPolicy.RELIABLE if subscriber == 'reliable'
           else ReliabilityPolicy.BEST_EFFORT)
    probe.node.create_subscription(PointCloud2, '/points', lambda m: got.append(1),
                                   QoSProfile(depth=1, reliability=rel))
    env = dict(os.environ, FASTRTPS_DEFAULT_PROFILES_FILE=profile)
    player = start_player(bag, '--topics', '/points', '--wait-subscribers', '20',
                          '--start-delay', '1.5', '--reliability', publisher, env=env,
                          quiet=False)
    try:
        probe.spin_while_running(player, 120, 0.01)
        probe.spin_for(1.0, 0.01)
    finally:
        out = stop(player)
        probe.close()
    sent = next((int(w) for line in out.splitlines() if 'published' in line
                 for w in line.split() if w.isdigit()), -1)
    return len(got), sent


def main() -> int:
    """Run every combination and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--bag', default='out/demo/demo-seed7-100f')
    args = parser.parse_args()
    from suit_ros.dds import LARGE_DATA_PROFILE
    if not Path(args.bag).exists():
        from suit_ros.data.sim import preset
        from suit_ros.data.sim.recording import write_bag
        write_bag(args.bag, preset('demo', frames=100), 7, 'mcap')
    with tempfile.TemporaryDirectory() as tmp:
        default = Path(tmp) / 'fastdds_defaults.xml'
        default.write_text(EMPTY_PROFILE)
        print('clouds received / published (demo bag, ~1.2 MB per cloud, 10 Hz):')
        for name, profile in (('Fast DDS defaults', default),
                              ('fastdds_large_data.xml', LARGE_DATA_PROFILE)):
            for pub, sub in (('reliable', 'best_effort'), ('reliable', 'reliable'),
                             ('best_effort', 'best_effort')):
                got, sent = count(args.bag, str(profile), pub, sub)
                print(f'  player profile {name:<24} publisher {pub:<12} subscriber '
                      f'{sub:<12}: {got}/{sent}', flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
