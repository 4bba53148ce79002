"""``suit-ros simulate``: write a synthetic drive as a rosbag2 bag
(:func:`suit_ros.data.sim.recording.write_bag`)."""
from __future__ import annotations

import argparse
from pathlib import Path
import time
from typing import Any

from suit_ros.data.sim.recording import write_bag
from suit_ros.errors import ConfigError


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Add ``simulate`` options."""
    parser.add_argument('--out', required=True, help='output bag directory (must not exist)')
    parser.add_argument('--seed', type=int, default=0)
    group = parser.add_mutually_exclusive_group()
    group.add_argument('--frames', type=int, help='number of LiDAR frames')
    group.add_argument('--duration', type=float, help='seconds of driving')
    parser.add_argument('--storage', choices=['mcap', 'sqlite3'], default='mcap')
    parser.add_argument('--beams', type=int, help='16, 32, 64 or 128')
    parser.add_argument('--preset', default='demo-real',
                        help='demo-real | train-real | val-real (the detailed world the shipped '
                             'model is trained on) | demo | train | val | test (box world)')
    parser.add_argument('--sensor', help='a real-sensor model: sim32, hdl32e, hdl64e, vlp16, '
                        'os1-64, os1-128 (docs/sensors.md); the intensity field keeps the '
                        "sensor's convention (hdl64e: 0..1, the others 0..255)")
    parser.add_argument('--motion-distortion', action='store_true',
                        help='cast each azimuth sector at its firing time')


def run(args: argparse.Namespace) -> int:
    """Write the bag and print a summary."""
    from suit_ros.data.sim import preset
    overrides: dict[str, Any] = {}
    if args.beams is not None:
        overrides['beams'] = args.beams
    if args.motion_distortion:
        overrides['motion_distortion'] = True
    cfg = preset(args.preset, sensor=args.sensor, **overrides)
    rate = cfg.lidar.rate_hz
    frames = args.frames if args.frames is not None else (
        int(round(args.duration * rate)) if args.duration is not None else cfg.frames)
    if frames < 1:
        raise ConfigError('--frames/--duration must give at least one frame')
    from dataclasses import replace
    cfg = replace(cfg, frames=frames).validate()
    t0 = time.monotonic()
    summary = write_bag(Path(args.out), cfg, args.seed, args.storage, progress=True)
    dt = time.monotonic() - t0
    print(f'wrote {args.out} ({args.storage}): {summary["frames"]} frames in {dt:.1f} s '
          f'({summary["frames"] / dt:.1f} frames/s)')
    print(f'points per frame: {summary["points_per_frame_mean"]:.0f}')
    print('objects with returns per frame: ' + ', '.join(
        f'{c} {v:.1f}' for c, v in summary['objects_per_frame'].items()))
    return 0
