"""``suit-ros bench``: latency, memory and scaling of the detector, measured in one run.

Prints a table (``--json`` for machines, ``--markdown PATH`` for docs/bench.md): per-stage
latency p50/p95 of the CPU default config, single-frame vs SUIT step, temporal memory of SUIT vs
the dense variant after 2 and 10 frames, scaling with points per cloud and with objects in the
scene, end-to-end node latency through DDS with the demo bag at 10 and 20 Hz, peak RSS.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import time
from typing import Any

import numpy as np

from suit_ros.config import TemporalMode


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Add ``bench`` options."""
    parser.add_argument('--checkpoint', default='', help='default: the shipped checkpoint')
    parser.add_argument('--frames', type=int, default=30, help='frames per measurement')
    parser.add_argument('--threads', type=int, default=2, help='torch threads of the step '
                        'measurements')
    parser.add_argument('--node-threads', type=int, default=0, help="the node's threads "
                        'parameter in the DDS measurement (0: its default, all cores but one)')
    parser.add_argument('--device', default='cpu', choices=['cpu', 'cuda'])
    parser.add_argument('--precision', default='auto', choices=['auto', 'float32', 'bfloat16'],
                        help="the step's precision (default: auto, as the node's parameter)")
    parser.add_argument('--config', default='', help='model config for an untrained '
                        'measurement instead of the checkpoint (e.g. params/model_paper.yaml)')
    parser.add_argument('--skip-node', action='store_true', help='skip the DDS measurement')
    parser.add_argument('--json', action='store_true', help='print JSON')
    parser.add_argument('--markdown', help='also write the table to this file')


def pct(values: list[float], q: float) -> float:
    """Percentile in milliseconds."""
    return float(np.percentile(np.asarray(values) * 1e3, q)) if values else float('nan')


def _model(args: argparse.Namespace, temporal: TemporalMode) -> Any:
    from dataclasses import replace

    from suit_ros.checkpoint import default_checkpoint_path, load_model_as
    from suit_ros.config import load_model_config
    from suit_ros.model.detector import SUITDetector
    if args.config:
        cfg = replace(load_model_config(args.config), temporal=temporal)
        return SUITDetector(cfg).eval()
    return load_model_as(args.checkpoint or default_checkpoint_path(), temporal)


def _per_stage(runners: dict[Any, Any], frames: list[Any], clouds: list[Any], C: Any
               ) -> dict[str, Any]:
    """Per stage, SUIT (memory carried) and single frame; the models step frame by frame in
    turn, so a change of the machine's speed hits all of them alike."""
    from suit_ros.evaluate import step_inputs
    from suit_ros.msg_adapters.detections import (
        detections_to_markerarray,
        detections_to_pointcloud2,
    )
    from suit_ros.msg_adapters.pointcloud2 import pointcloud2_to_xyzi
    stage_times: dict[str, list[float]] = {k: [] for k in (
        'convert', 'sweeps', 'encode', 'head_decode', 'sampling', 'fusion', 'tracking',
        'output')}
    temporals = tuple(runners)
    names = runners['suit'].cfg.class_names
    steps: dict[str, list[float]] = {t: [] for t in temporals}
    memory: dict[str, dict[int, int]] = {t: {} for t in temporals}
    for i, (f, msg) in enumerate(zip(frames, clouds)):
        for temporal, runner in runners.items():
            t0 = time.perf_counter()
            pts = pointcloud2_to_xyzi(msg).points
            pts[:, 3] /= 255.0
            t1 = time.perf_counter()
            r = runner.step(pts, *step_inputs(f)[1:])
            t2 = time.perf_counter()
            d = r.detections
            detections_to_pointcloud2(d.boxes, d.velocities, d.scores, d.labels,
                                      msg.header, C, track_ids=r.track_ids,
                                      num_points=r.num_points,
                                      vel_std=(r.velocity_std if runner.tracks is not None
                                               else None))
            detections_to_markerarray(d.boxes, d.velocities, d.scores, d.labels, msg.header,
                                      names, C, track_ids=r.track_ids)
            t3 = time.perf_counter()
            if i + 1 in (2, 10):
                memory[temporal][i + 1] = r.memory_bytes
            if i < 3:
                continue                                  # warm-up
            steps[temporal].append(t2 - t1)
            if temporal == 'suit':
                stage_times['convert'].append(t1 - t0)
                stage_times['output'].append(t3 - t2)
                for k in ('sweeps', 'encode', 'head_decode', 'sampling', 'fusion', 'tracking'):
                    stage_times[k].append(r.timings[k])
    res: dict[str, Any] = {}
    res['stages_ms'] = {k: {'p50': pct(v, 50), 'p95': pct(v, 95)} for k, v in
                        stage_times.items()}
    res['step_ms'] = {k: {'p50': pct(v, 50), 'p95': pct(v, 95)} for k, v in steps.items()}
    res['suit_over_single'] = res['step_ms']['suit']['p50'] / res['step_ms']['none']['p50']
    res['memory_bytes'] = memory
    res['memory_ratio_suit_dense'] = {k: memory['suit'].get(k, 0) / max(memory['dense'].get(k, 1),
                                                                          1) for k in (2, 10)}
    return res


SENSOR_SIZES = (('37k', 'sim32', 1.0), ('114k', 'hdl64e', 1.0), ('260k', 'hdl64e', 2.3))
# the node over DDS: rate (Hz), size, sensor, densified, frames (60 at 260k: a 0.6 GB bag)
NODE_RUNS = ((10, '37k', 'sim32', 1.0, 100), (20, '37k', 'sim32', 1.0, 100),
             (10, '114k', 'hdl64e', 1.0, 100), (10, '260k', 'hdl64e', 2.3, 60))


def _sensor_sizes(model_args: argparse.Namespace, n: int) -> dict[str, Any]:
    """The SUIT step by stage at real sensor sizes: the demo drive as a 32-beam (about 37k
    points a sweep) and a 64-beam sensor (hdl64e, about 114k) sees it, and the 64-beam sweeps
    densified 2.3x by jittered copies of their points (about 260k, an OS1-128 or AT128), each
    copy beside its original so the sweep keeps its scan order, as a driver publishes it
    (:func:`~suit_ros.data.sim.recording.densified`)
    (shuffled, the same points cost 13-16% more: the per-point loops lose their locality).
    Three sweeps in each input, tracker on; the three step frame by frame in turn."""
    from dataclasses import replace

    from suit_ros.data.sequences import synthetic_sequence
    from suit_ros.data.sim.recording import densified
    from suit_ros.evaluate import step_inputs
    from suit_ros.model.streaming import StreamingDetector
    from suit_ros.tracking import TrackerConfig
    rng = np.random.default_rng(0)
    drives = {}
    for name, sensor, factor in SENSOR_SIZES:
        frames = synthetic_sequence('demo-real', 7, max(n, 8), sensor=sensor)
        if factor != 1.0:
            frames = [replace(f, points=densified(f.points, factor, rng), times=None,
                              owners=None)
                      for f in frames]
        drives[name] = frames
    model = _model(model_args, 'suit')
    runners = {k: StreamingDetector(model, model_args.device, precision=model_args.precision,
                                    tracker=TrackerConfig()) for k in drives}
    keys = ('sweeps', 'encode', 'fusion', 'head_decode', 'sampling', 'tracking', 'total')
    times: dict[str, dict[str, list[float]]] = {k: {s: [] for s in keys} for k in drives}
    for i in range(max(n, 8)):
        for name, frames in drives.items():
            r = runners[name].step(*step_inputs(frames[i]))
            if i >= 3:                                           # warm-up
                for key in keys:
                    times[name][key].append(r.timings[key])
    out: dict[str, Any] = {}
    for name, frames in drives.items():
        out[name] = {'points': int(np.median([len(f.points) for f in frames])),
                     **{k: pct(v, 50) for k, v in times[name].items()}}
    base = out['37k']['total']
    for name in drives:
        out[name]['ratio'] = out[name]['total'] / base
    return out


def _scaling_objects(runner: Any) -> list[dict[str, float]]:
    """Step p50 (ms) with 10, 40 and 120 actors in the scene."""
    from suit_ros.data.sim import preset
    from suit_ros.data.sim.scene import Simulation, to_frame
    from suit_ros.evaluate import step_inputs
    by_objects = []
    for actors in (10, 40, 120):
        cfg = preset('demo-real', frames=6, moving_vehicles=actors // 2,
                     parked_vehicles=actors // 4, pedestrians=actors // 4, cyclists=2)
        runner.reset('bench')
        s = Simulation(cfg, 3)
        times, objs = [], []
        for frame_index in range(6):
            fr = to_frame(s.render(frame_index), 3)
            r = runner.step(*step_inputs(fr))
            times.append(r.timings['total'])
            objs.append(int(np.count_nonzero(np.asarray(fr.num_points) > 0)))
        by_objects.append({'objects_with_points': float(np.mean(objs[2:])),
                           'step_ms_p50': pct(times[2:], 50),
                           'detections': len(r.detections)})
    return by_objects


def run(args: argparse.Namespace) -> int:
    """Run every measurement and print the table."""
    import torch

    from suit_ros.outputs import output_file
    if args.markdown:
        output_file(args.markdown, '--markdown file')   # before the runs, not after them
    from suit_ros.heap import keep_freed_memory
    keep_freed_memory()          # the allocator as the node sets it (suit_ros.heap)

    from suit_ros.data.sim import preset
    from suit_ros.data.sim.scene import Simulation, to_frame
    from suit_ros.model.streaming import StreamingDetector
    from suit_ros.msg_adapters.classes import MessageClasses
    from suit_ros.msg_adapters.pointcloud2 import array_to_pointcloud2
    from suit_ros.tracking import TrackerConfig
    torch.set_num_threads(args.threads)
    n = args.frames
    sim = Simulation(preset('demo-real', frames=max(n, 12)), 7)
    simframes = [sim.render(k) for k in range(n)]
    frames = [to_frame(f, 7) for f in simframes]
    C = MessageClasses.from_rclpy()
    clouds = [array_to_pointcloud2(f.cloud, C.header(f.stamp_ns, 'lidar'), C)
              for f in simframes]
    from suit_ros.model.inference import resolve_precision
    res: dict[str, Any] = {'machine': machine(), 'threads': args.threads, 'device': args.device,
                           'precision': resolve_precision(args.precision, args.device),
                           'points_per_frame': int(np.mean([len(f.cloud) for f in simframes])),
                           # other work on the machine skews every figure: said up front
                           'load_before': round(os.getloadavg()[0], 2)}
    temporals: tuple[TemporalMode, ...] = ('none', 'suit', 'dense')
    # as the node runs them by default: tracker on
    runners = {t: StreamingDetector(_model(args, t), args.device, precision=args.precision,
                                    tracker=TrackerConfig())
               for t in temporals}
    res.update(_per_stage(runners, frames, clouds, C))
    runner = runners['suit']
    res['sensor_sizes'] = _sensor_sizes(args, n)
    res['scaling_objects'] = _scaling_objects(runner)
    if not args.skip_node:
        from suit_ros.node_probe import node_latency
        res['node'] = {
            f'{hz}Hz {size} ({sensor}{"" if dense == 1.0 else f" x{dense:g}"})': node_latency(
                args.checkpoint, rate=hz / 10.0, frames=frames, threads=args.node_threads,
                precision=args.precision, sensor=sensor, densify=dense)
            for hz, size, sensor, dense, frames in NODE_RUNS}
    res['peak_rss_mb'] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    text = table(res)
    if args.json:
        print(json.dumps(res, indent=2, default=str))
    else:
        print(text)
    if args.markdown:
        with open(args.markdown, 'w', encoding='utf-8') as md:
            md.write('# Benchmarks\n\nRegenerated by `suit-ros bench --markdown docs/bench.md`.'
                    '\n\n```\n' + text + '\n```\n')
    return 0


def machine() -> str:
    """A one-line description of this machine."""
    cpu = platform.processor() or platform.machine()
    try:
        with open('/proc/cpuinfo', encoding='utf-8') as f:
            for line in f:
                if line.startswith('model name'):
                    cpu = line.split(':', 1)[1].strip()
                    break
    except OSError:
        pass
    return f'{cpu}, {os.cpu_count()} CPUs, Python {platform.python_version()}'


def table(r: dict[str, Any]) -> str:
    """The human-readable table."""
    lines = [f'machine: {r["machine"]}; torch threads {r["threads"]}; device {r["device"]}; '
             f'precision {r.get("precision", "float32")}; demo scene '
             f'~{r["points_per_frame"]} points/frame; load average before the run '
             f'{r.get("load_before", float("nan")):.2f} (busy if near the CPU count)', '',
             f'{"stage (SUIT step, memory carried)":<36}{"p50 ms":>9}{"p95 ms":>9}']
    for k, v in r['stages_ms'].items():
        lines.append(f'{k:<36}{v["p50"]:>9.1f}{v["p95"]:>9.1f}')
    lines += ['', f'{"model step":<36}{"p50 ms":>9}{"p95 ms":>9}']
    for k, v in r['step_ms'].items():
        lines.append(f'{k:<36}{v["p50"]:>9.1f}{v["p95"]:>9.1f}')
    lines.append(f'SUIT / single-frame step (p50): {r["suit_over_single"]:.2f}x')
    m = r['memory_bytes']
    for k in (2, 10):
        lines.append(f'temporal memory after {k:>2} frames: SUIT {m["suit"].get(k, 0):,} B, '
                     f'dense {m["dense"].get(k, 0):,} B, ratio '
                     f'{r["memory_ratio_suit_dense"][k] * 100:.2f}%')
    lines += ['', 'SUIT step by points a sweep (3 sweeps in the input; p50 ms; ratio: total '
              'over the 37k total)',
              f'{"sweep":<8}{"points":>8}' + ''.join(f'{k:>12}' for k in (
                  'sweeps', 'encode', 'fusion', 'head_decode', 'sampling', 'tracking', 'total',
                  'ratio'))]
    for name, v in r['sensor_sizes'].items():
        lines.append(f'{name:<8}{v["points"]:>8}' + ''.join(f'{v[k]:>12.1f}' for k in (
            'sweeps', 'encode', 'fusion', 'head_decode', 'sampling', 'tracking', 'total'))
            + f'{v["ratio"]:>11.2f}x')
    lines.append('scaling with objects in the scene: ' + ', '.join(
        f'{o["objects_with_points"]:.0f} objects: {o["step_ms_p50"]:.1f} ms'
        for o in r['scaling_objects']))
    if 'node' in r:
        for hz, v in r['node'].items():
            lines.append(f'node (threads:={v.get("node_threads", 2)}, precision:='
                         f'{v.get("node_precision", "float32")}) through DDS at {hz}: '
                         f'CPU {v.get("cpu_cores", float("nan")):.2f} cores (steal '
                         f'{v.get("cpu_steal_pct", float("nan")):.1f}% of the machine), '
                         f'latency at a subscriber p50 {v["latency_ms_p50"]:.1f} ms, '
                         f'p95 {v["latency_ms_p95"]:.1f} ms (in the node, '
                         f'{v.get("node_latency_from", "stamp")} to published: '
                         f'p50 {v.get("node_latency_ms_p50", float("nan")):.1f}, p95 '
                         f'{v.get("node_latency_ms_p95", float("nan")):.1f}), output '
                         f'{v["rate_hz"]:.1f} Hz, '
                         f'{v["frames_out"]}/{v["frames_in"]} frames out, dropped '
                         f'{v["dropped"]} (of them buffered as sweeps '
                         f'{v.get("sweeps_only", "n/a")}), last input '
                         f'{v.get("input_sweeps", "n/a")}, node overhead '
                         f'{v["overhead_pct"]:.1f}% of the model step')
    lines.append(f'peak RSS: {r["peak_rss_mb"]:.0f} MB')
    return '\n'.join(lines)
