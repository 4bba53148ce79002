"""Is it the real 13 m pedestrian's own returns, or where it stands? Its returns moved, and the
18 m pedestrian (found) cut to a torso, in both real dev sweeps (a probe, not a fix).

Variants (points in the egovehicle frame; a move is a rotation about the upper LiDAR's
vertical axis, x 1.35 m, so range and elevation of every return stay as the sensor saw them):
- as recorded;
- the 18 m pedestrian with its own returns below 0.9 m taken out (what the 13 m one shows);
- the 13 m pedestrian's own returns copied to the 18 m one's bearing (at 13 m, in front of it,
  where the ground is seen), and to a bearing picked by hand in the open road;
- the 18 m pedestrian's own returns copied to the 13 m one's bearing (at 18 m, behind it).
Heatmap: the highest probability of each class within 3 cells (1.2 m) of the place, per sweep;
the places: the 13 m pedestrian, the 18 m pedestrian, and where a copy went.

Usage: python transplant.py [CHECKPOINT_NAME]
"""
from dataclasses import replace
import sys
from typing import Any

import numpy as np
from probe import heatmaps  # this folder's (the script's folder is on the path)
import torch

from suit_ros.checkpoint import load_model_as
from suit_ros.data.av2 import av2_sequences
from suit_ros.evaluate import step_inputs
from suit_ros.ground import LocalGround
from suit_ros.model.streaming import StreamingDetector

torch.set_num_threads(2)
name = sys.argv[1] if len(sys.argv) > 1 else 'suit_default'
seq = av2_sequences('../shared/data/real-dev/av2')[0]
frames = [seq[i] for i in range(len(seq))]
SENSOR_XY = np.array([1.35, 0.0])


def pedestrian(f: Any, lo: float, hi: float) -> np.ndarray:
    """The pedestrian box ``lo``-``hi`` m from the sensor (egovehicle frame)."""
    for b, label in zip(f.gt.boxes, f.gt.labels):
        if label == 2 and lo < np.hypot(*(b[:2] - SENSOR_XY)) < hi:
            return b
    raise SystemExit(f'no pedestrian {lo}-{hi} m away')


def inside(p: np.ndarray, b: np.ndarray) -> np.ndarray:
    d = p[:, :2] - b[:2]
    c, s = np.cos(b[6]), np.sin(b[6])
    return ((np.abs(d[:, 0] * c + d[:, 1] * s) <= b[3] / 2)
            & (np.abs(-d[:, 0] * s + d[:, 1] * c) <= b[4] / 2)
            & (np.abs(p[:, 2] - b[2]) <= b[5] / 2))


def bearing(xy: np.ndarray) -> float:
    return float(np.arctan2(*(xy[..., :2] - SENSOR_XY)[::-1]))


def rotated(p: np.ndarray, angle: float) -> np.ndarray:
    q = p.copy()
    c, s = np.cos(angle), np.sin(angle)
    d = p[:, :2] - SENSOR_XY
    q[:, 0] = SENSOR_XY[0] + c * d[:, 0] - s * d[:, 1]
    q[:, 1] = SENSOR_XY[1] + s * d[:, 0] + c * d[:, 1]
    return q


def place(b: np.ndarray, angle: float) -> np.ndarray:
    return rotated(b[None, :3], angle)[0, :2]


def with_points(f: Any, keep: np.ndarray, extra: np.ndarray | None = None) -> Any:
    pts = f.points[keep]
    times = None if f.times is None else f.times[keep]
    if extra is not None:
        pts = np.concatenate([pts, extra])
        if times is not None:
            times = np.concatenate([times, np.zeros(len(extra), times.dtype)])
    return replace(f, points=pts, times=times)


def torso_of_18(f: Any) -> tuple[Any, str]:
    b = pedestrian(f, 16, 20)
    cut = inside(f.points, b) & (f.points[:, 2] < b[2] - b[5] / 2 + 0.9)
    return with_points(f, ~cut), f'{int(cut.sum())} below 0.9 m taken out'


def copy(f: Any, src: tuple[float, float], to_bearing: float | None,
         to_ped: tuple[float, float] | None) -> tuple[Any, str, np.ndarray]:
    """The pedestrian ``src`` m away copied to ``to_bearing`` (radians from the sensor) or to
    the bearing of the pedestrian ``to_ped`` m away."""
    b = pedestrian(f, *src)
    own = inside(f.points, b)
    target = to_bearing if to_ped is None else bearing(pedestrian(f, *to_ped)[:2])
    angle = target - bearing(b[:2])
    moved = rotated(f.points[own], angle)
    at = place(b, angle)
    there = int((np.hypot(*(f.points[:, :2] - at).T) < 1.5).sum())
    return with_points(f, np.ones(len(f.points), bool), moved), (
        f'{int(own.sum())} copied, {there} returns within 1.5 m there'), at


def heat_at(heat: dict[str, torch.Tensor], model: Any, xy_ego: np.ndarray, f: Any) -> str:
    T = np.asarray(f.T_base_lidar)
    xy = xy_ego @ T[:2, :2].T + T[:2, 3]
    col, row = (int(v) for v in model.grid.xy_to_cell(torch.tensor(xy[None]).float())[0])
    m = heat['map'][:, max(row - 3, 0):row + 4, max(col - 3, 0):col + 4].amax((1, 2))
    return ' '.join(f'{n[:3]} {v:.2f}' for n, v in zip(model.cfg.class_names, m.tolist()))


def car_in_front(f: Any) -> np.ndarray:
    """The labelled car nearest the sensor within 15 deg of the 13 m pedestrian's bearing."""
    to = bearing(pedestrian(f, 12, 14)[:2])
    cars = [b for b, label in zip(f.gt.boxes, f.gt.labels) if label == 0
            and abs(np.angle(np.exp(1j * (bearing(b[:2]) - to)))) < np.radians(15)
            and np.hypot(*(b[:2] - SENSOR_XY)) < 12]
    return min(cars, key=lambda b: float(np.hypot(*(b[:2] - SENSOR_XY))))


def without_car(f: Any, radius: float) -> tuple[Any, str, None]:
    """Without the car in front's returns (grown 0.3 m), and those within ``radius`` of the
    13 m pedestrian outside its box."""
    car = car_in_front(f).copy()
    car[3:6] += 0.6
    b = pedestrian(f, 12, 14)
    out = inside(f.points, car)
    near = (np.hypot(*(f.points[:, :2] - b[:2]).T) < radius) & ~inside(f.points, b)
    return with_points(f, ~(out | near)), (f'{int(out.sum())} car returns and {int(near.sum())} '
                                           f'within {radius} m out'), None


OPEN_BEARING = float(sys.argv[2]) if len(sys.argv) > 2 else None


def run(label: str, change: Any) -> None:
    runner = StreamingDetector(load_model_as(f'suit_ros/checkpoints/{name}.safetensors', None),
                               'cpu', precision='float32', ground='local')
    heat = heatmaps(runner.model)
    print(f'## {label}')
    for i, f in enumerate(frames):
        g, what, at = change(f)
        runner.step(*step_inputs(g))
        near = heat_at(heat, runner.model, pedestrian(f, 12, 14)[:2], f)
        far = heat_at(heat, runner.model, pedestrian(f, 16, 20)[:2], f)
        line = f'  sweep {i}: {what}; 13 m: {near} | 18 m: {far}'
        if at is not None:
            line += f' | the copy: {heat_at(heat, runner.model, at, f)}'
        print(line, flush=True)


for f in frames[:1]:
    for lo, hi in ((12, 14), (16, 20)):
        b = pedestrian(f, lo, hi)
        own = f.points[inside(f.points, b)]
        print(f'pedestrian at {np.hypot(*(b[:2] - SENSOR_XY)):.1f} m, bearing '
              f'{np.degrees(bearing(b[:2])):.1f} deg, box {b[3]:.2f} x {b[4]:.2f} x {b[5]:.2f}, '
              f'{len(own)} returns')

run('as recorded', lambda f: (f, 'as recorded', None))
run('the 18 m pedestrian cut to a torso (its returns below 0.9 m out)',
    lambda f: (*torso_of_18(f), None))
run("the 13 m pedestrian copied to the 18 m one's bearing (at 13 m)",
    lambda f: copy(f, (12, 14), None, (16, 20)))
run("the 18 m pedestrian copied to the 13 m one's bearing (at 18 m)",
    lambda f: copy(f, (16, 20), None, (12, 14)))
run('without the car in front', lambda f: without_car(f, 0.0))
run('without the car in front and the returns within 3 m', lambda f: without_car(f, 3.0))
for f in frames:
    ground = LocalGround(load_model_as(f'suit_ros/checkpoints/{name}.safetensors',
                                       None).cfg.pillars.point_range)
    T = np.asarray(f.T_base_lidar)
    pts = f.points.copy()
    pts[:, :3] = pts[:, :3] @ T[:3, :3].T + T[:3, 3]
    ground.fit(pts)
    for lo, hi in ((12, 14), (16, 20)):
        b = pedestrian(f, lo, hi)
        xy = b[:2] @ T[:2, :2].T + T[:2, 3]
        bottom = b[2] + T[2, 3] - b[5] / 2
        print(f'ground under the {lo}-{hi} m pedestrian: {float(ground.under(xy[None])[0]):+.2f} '
              f'm (its box bottom {bottom:+.2f} m, base_link)')
if OPEN_BEARING is not None:
    run(f'the 13 m pedestrian copied to bearing {OPEN_BEARING:.0f} deg',
        lambda f: copy(f, (12, 14), np.radians(OPEN_BEARING), None))
if len(sys.argv) > 3 and sys.argv[3] == 'scan':
    print('## the 13 m pedestrian copied round the sensor at 13 m (every 15 deg), sweep 1')
    f = frames[1]
    for deg in range(-180, 180, 15):
        runner = StreamingDetector(load_model_as(f'suit_ros/checkpoints/{name}.safetensors',
                                                 None), 'cpu', precision='float32',
                                   ground='local')
        heat = heatmaps(runner.model)
        runner.step(*step_inputs(frames[0]))
        g, what, at = copy(f, (12, 14), np.radians(deg), None)
        runner.step(*step_inputs(g))
        within3 = int((np.hypot(*(f.points[:, :2] - at).T) < 3.0).sum())
        print(f'  {deg:4d} deg: {what}, {within3} within 3 m; the copy: '
              f'{heat_at(heat, runner.model, at, f)}', flush=True)
