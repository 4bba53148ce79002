"""``suit-ros play BAG``: publish a bag into the live graph at its recorded pace.

Messages go out as their recorded CDR bytes (byte exact), optionally with ``/clock`` for
``use_sim_time``. ``--rate`` scales the pace, ``--loop`` repeats, ``--topics`` selects.
"""
from __future__ import annotations

import argparse
import importlib
import math
import os
import time
from typing import Any

from suit_ros.errors import BagError

POINT_CLOUD = 'sensor_msgs/msg/PointCloud2'
# at the end, reliable publishers wait this long for every reader to acknowledge
ACK_TIMEOUT_S = 5.0
# at the end, best-effort publishers stay this long so the last sample can leave
BEST_EFFORT_LINGER_S = 0.5


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Add ``play`` options."""
    parser.add_argument('bag', help='bag directory (sqlite3 or mcap)')
    parser.add_argument('--rate', type=float, default=1.0, help='playback speed factor')
    parser.add_argument('--loop', action='store_true', help='repeat forever')
    parser.add_argument('--topics', nargs='+', help='only these topics')
    parser.add_argument('--clock', action='store_true', help='publish /clock (sim time)')
    parser.add_argument('--start-delay', type=float, default=1.0,
                        help='seconds to wait for subscribers before the first message')
    parser.add_argument('--max-messages', type=int, default=0, help='stop after N (0: all)')
    parser.add_argument('--wait-subscribers', type=float, default=0.0, metavar='SECONDS',
                        help='first wait up to this long until every topic (and /clock with '
                        '--clock) has a subscriber')
    parser.add_argument('--reliability', choices=['reliable', 'best_effort'],
                        default='reliable',
                        help='QoS reliability of the PointCloud2 publishers (LiDAR drivers often '
                        'use best_effort); other topics are published reliably')


def message_class(msgtype: str) -> Any:
    """The rclpy message class of a ``pkg/msg/Name`` type string."""
    pkg, kind, name = msgtype.split('/')
    try:
        return getattr(importlib.import_module(f'{pkg}.{kind}'), name)
    except (ImportError, AttributeError) as exc:
        raise BagError(f'message type {msgtype} is not installed here ({exc})') from exc


def flush(pubs: dict[str, Any], timeout_s: float) -> list[str]:
    """Keep the publishers alive until their last messages are delivered.

    A writer destroyed right after its last ``publish`` takes the samples its readers have not
    received yet with it (a 1.2 MB cloud is still in flight): reliable publishers wait until
    every reader acknowledged (up to ``timeout_s``), best-effort ones linger
    :data:`BEST_EFFORT_LINGER_S`. Returns the topics still unacknowledged.
    """
    from rclpy.duration import Duration
    from rclpy.qos import ReliabilityPolicy
    deadline = time.monotonic() + timeout_s
    unacked, best_effort = [], False
    for topic, pub in pubs.items():
        if pub.qos_profile.reliability != ReliabilityPolicy.RELIABLE:
            best_effort = True
            continue
        left = max(deadline - time.monotonic(), 0.0)
        if not pub.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9))):
            unacked.append(topic)
    if best_effort:
        time.sleep(BEST_EFFORT_LINGER_S)
    return unacked


def run(args: argparse.Namespace) -> int:
    """Play the bag."""
    from suit_ros.data.bag import open_reader
    if not args.rate > 0 or not math.isfinite(args.rate):          # nan fails both
        raise BagError(f'--rate must be a number > 0, not {args.rate}')
    if not (0 <= args.start_delay < math.inf and 0 <= args.wait_subscribers < math.inf):
        raise BagError('--start-delay and --wait-subscribers are seconds >= 0')
    if args.max_messages < 0:
        raise BagError(f'--max-messages is a count >= 0 (0: all), not {args.max_messages}')
    with open_reader(args.bag) as reader:
        topics = sorted({c.topic for c in reader.connections})
        if not topics:
            raise BagError(f'{args.bag} holds no topic: nothing to play')
        missing = sorted(set(args.topics or ()) - set(topics))
        if missing:                       # a mistyped name among several is not dropped
            raise BagError(f'{args.bag} has no {", ".join(missing)} (topics: {topics}); '
                           'name them with --topics as the bag does')
        conns = [c for c in reader.connections if not args.topics or c.topic in args.topics]
        # streamed from the bag as they are due, not read into memory first: a real
        # recording of 1 MB clouds holds many GB
        return _play(args, reader, conns)


def _play(args: argparse.Namespace, reader: Any, conns: list[Any]) -> int:
    import rclpy
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.utilities import try_shutdown
    from rosgraph_msgs.msg import Clock

    from suit_ros.data.bag import messages
    from suit_ros.dds import use_large_data_profile
    profile = use_large_data_profile(os.environ)   # before rclpy creates the participant
    if profile:
        print(f'play: Fast DDS profile {profile} (large messages over shared memory)')
    rclpy.init()
    node = rclpy.create_node('suit_ros_player')
    pubs = {}
    for topic, msgtype in sorted({(c.topic, c.msgtype) for c in conns}):
        try:
            cls = message_class(msgtype)
        except BagError as exc:
            print(f'play: skipping {topic}: {exc}')
            continue
        latched = topic == '/tf_static'
        best_effort = args.reliability == 'best_effort' and msgtype == POINT_CLOUD
        qos = QoSProfile(depth=10, durability=(DurabilityPolicy.TRANSIENT_LOCAL if latched
                                               else DurabilityPolicy.VOLATILE),
                         reliability=(ReliabilityPolicy.BEST_EFFORT if best_effort
                                      else ReliabilityPolicy.RELIABLE))
        pubs[topic] = node.create_publisher(cls, topic, qos)
    conns = [c for c in conns if c.topic in pubs]
    if not conns:
        node.destroy_node()
        try_shutdown()
        raise BagError(f'no message type of {args.bag} is known here: nothing to play')
    clock_pub = node.create_publisher(Clock, '/clock', 10) if args.clock else None
    sent = 0
    late_max = 0.0
    try:
        end = time.monotonic() + args.wait_subscribers
        waited = list(pubs.values()) + ([clock_pub] if clock_pub is not None else [])
        while time.monotonic() < end and any(p.get_subscription_count() == 0 for p in waited):
            time.sleep(0.05)
        time.sleep(args.start_delay)
        while True:
            t_bag0: int | None = None
            t_wall0 = time.monotonic()
            for conn, t, raw in messages(reader, conns):
                if t_bag0 is None:
                    t_bag0, t_wall0 = t, time.monotonic()
                due = t_wall0 + (t - t_bag0) * 1e-9 / args.rate
                delay = due - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                else:             # behind the recorded pace (a loaded machine): say how far
                    late_max = max(late_max, -delay)
                if clock_pub is not None:
                    clock = Clock()
                    clock.clock.sec, clock.clock.nanosec = divmod(t, 10**9)
                    clock_pub.publish(clock)
                pubs[conn.topic].publish(bytes(raw))
                sent += 1
                if args.max_messages and sent >= args.max_messages:
                    return 0
            if not sent:
                raise BagError(f'{args.bag} has no messages on the selected topics')
            if not args.loop:
                break
    except KeyboardInterrupt:
        pass
    finally:
        unacked = flush(pubs if clock_pub is None else {**pubs, '/clock': clock_pub},
                        ACK_TIMEOUT_S)
        print(f'play: published {sent} messages; at most {late_max * 1e3:.0f} ms behind the '
              'recorded pace' + (f'; not acknowledged by every reliable subscriber within '
                                 f'{ACK_TIMEOUT_S:g} s: {", ".join(unacked)}' if unacked else ''))
        node.destroy_node()
        try_shutdown()
    return 0
