#!/usr/bin/env python3
"""Synthetic generation speed: median seconds per frame for each sensor preset, for the box
world (as generated before this script existed, bit for bit) and the detailed world, measured
in one process so that the ratios hold on a loaded machine.

Usage: scripts/bench_sim.py [--frames 12] [--sensors sim32 os1-128 ...] [--exact]
"""
from __future__ import annotations

import argparse
from dataclasses import replace
import os
import statistics
import time

from suit_ros.data.sim import preset
from suit_ros.data.sim.config import SENSORS
from suit_ros.data.sim.scene import Simulation


def seconds_per_frame(name: str, sensor: str, frames: int, seed: int,
                      distortion: bool | None) -> float:
    """Median render time of ``frames`` frames (after one warm-up frame)."""
    cfg = preset(name, sensor=sensor, frames=frames + 1)
    if distortion is not None:
        cfg = replace(cfg, lidar=replace(cfg.lidar, motion_distortion=distortion))
    sim = Simulation(cfg, seed)
    sim.render(0)
    times = []
    for k in range(1, frames + 1):
        t0 = time.perf_counter()
        sim.render(k)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--frames', type=int, default=12)
    parser.add_argument('--seed', type=int, default=5)
    parser.add_argument('--sensors', nargs='+', default=list(SENSORS))
    args = parser.parse_args()
    load = os.getloadavg()[0]
    print(f'{os.cpu_count()} CPUs, load average {load:.2f}; median ms per frame '
          f'(frames/s), train preset, {args.frames} frames')
    print(f'{"sensor":10} {"distortion":>10} {"box world":>18} {"detailed world":>18} '
          f'{"ratio":>6}')
    cases = [('sim32', False)] + [(s, None) for s in args.sensors if s != 'sim32']
    for sensor, distortion in cases:
        if sensor not in args.sensors:
            continue
        box = seconds_per_frame('train', sensor, args.frames, args.seed, distortion)
        real = seconds_per_frame('train-real', sensor, args.frames, args.seed, distortion)
        on = SENSORS[sensor].motion_distortion if distortion is None else distortion
        print(f'{sensor:10} {"on" if on else "off":>10} {1e3 * box:8.1f} ({1 / box:5.1f}/s) '
              f'{1e3 * real:8.1f} ({1 / real:5.1f}/s) {real / box:6.2f}')


if __name__ == '__main__':
    main()
