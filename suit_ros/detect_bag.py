"""``suit-ros detect-bag IN OUT``: every frame of a bag through the node's pipeline, in order.

No drops: odometry is fed from the bag in recording order, each cloud runs the same
:class:`~suit_ros.pipeline.DetectionPipeline` as the live node, and the detections and markers
are written under the node's output topics at the input stamps.
"""
from __future__ import annotations

import argparse
import collections
import math
from pathlib import Path
import shutil
import sys
import time
from typing import Any, get_args

import numpy as np

from suit_ros.errors import BagError, ConfigError
from suit_ros.params import (
    BoxFitParam,
    DetectorParams,
    GroundChoice,
    OverhangChoice,
    TrafficSideParam,
)

DET_TOPIC = '/detector/detections'
MARKER_TOPIC = '/detector/markers'


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Add ``detect-bag`` options (the flags override ``--params``, which overrides defaults)."""
    parser.add_argument('input', help='input bag (sqlite3 or mcap)')
    parser.add_argument('output', help='output bag (must not exist)')
    parser.add_argument('--checkpoint', default=None, help='default: the shipped checkpoint')
    parser.add_argument('--params', help='node parameter YAML (params/detector.yaml layout)')
    parser.add_argument('--points-topic', default=None, help='default: /points')
    parser.add_argument('--odom-topic', default=None, help='default: /odom')
    parser.add_argument('--gt-topic', default='/gt/objects')
    parser.add_argument('--storage', choices=['mcap', 'sqlite3'], default='mcap')
    parser.add_argument('--copy-inputs', action='store_true',
                        help='also copy every input topic into OUT')
    parser.add_argument('--device', default=None, choices=['auto', 'cpu', 'cuda'])
    parser.add_argument('--precision', default=None, choices=['auto', 'float32', 'bfloat16'],
                        help='default: auto (bfloat16 on a CPU with bfloat16 units)')
    parser.add_argument('--ground', default=None, choices=get_args(GroundChoice),
                        help="the input's height reference (the node's ground parameter)")
    parser.add_argument('--overhang', default=None, choices=get_args(OverhangChoice),
                        help="the returns that hang over a gap in their column (the node's "
                        'overhang parameter)')
    parser.add_argument('--box-fit', default=None, choices=get_args(BoxFitParam),
                        help="car boxes moved onto the returns of their visible faces (the "
                        "node's box_fit parameter)")
    parser.add_argument('--traffic-side', default=None, choices=get_args(TrafficSideParam),
                        help="the side of the road traffic keeps to (the node's traffic_side "
                        'parameter: left gives the model the drive mirrored; auto reads it '
                        'from the oncoming vehicles)')
    parser.add_argument('--intensity-scale', type=float,
                        help='intensity / scale -> 0..1 (1 for 0..1 reflectance)')
    parser.add_argument('--score-threshold', type=float, nargs='+', metavar='T',
                        help='one threshold for every class, or one per class')
    parser.add_argument('--min-range', type=float, help='m')
    parser.add_argument('--max-range', type=float, help='m')
    parser.add_argument('--extrinsic-xyz', type=float, nargs=3, metavar=('X', 'Y', 'Z'),
                        help='base_link -> LiDAR translation (m)')
    parser.add_argument('--extrinsic-rpy', type=float, nargs=3, metavar=('R', 'P', 'Y'),
                        help='base_link -> LiDAR roll pitch yaw (rad)')
    parser.add_argument('--intensity-field',
                        help="intensity field name, or 'none' to ignore intensity")
    parser.add_argument('--extrinsic-from-tf', action='store_true',
                        help="read the extrinsic from the bag's /tf_static (base frame -> the "
                        "cloud's frame)")
    parser.add_argument('--base-frame', default='base_link',
                        help='vehicle frame for --extrinsic-from-tf')


FLAG_PARAMS = {'checkpoint': 'checkpoint', 'device': 'device', 'precision': 'precision',
               'ground': 'ground', 'overhang': 'overhang', 'box_fit': 'box_fit',
               'traffic_side': 'traffic_side',
               'points_topic': 'points_topic',
               'odom_topic': 'odom_topic', 'intensity_scale': 'intensity_scale',
               'intensity_field': 'intensity_field',
               'score_threshold': 'score_thresholds', 'min_range': 'min_range',
               'max_range': 'max_range', 'extrinsic_xyz': 'extrinsic_xyz',
               'extrinsic_rpy': 'extrinsic_rpy'}


def params_from_args(args: argparse.Namespace) -> DetectorParams:
    """Defaults, then ``--params`` YAML, then the flags given."""
    params = DetectorParams.from_yaml(args.params) if args.params else DetectorParams()
    flags = {name: getattr(args, flag) for flag, name in FLAG_PARAMS.items()
             if getattr(args, flag, None) is not None}
    return params.updated(flags).validate()


def extrinsic_from_tf_static(reader: Any, base_frame: str, lidar_frame: str
                             ) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """``(xyz, rpy)`` of ``base_frame -> lidar_frame`` from the bag's ``/tf_static``.

    :raises BagError: no such transform in the bag (a direct one; chains are not composed).
    """
    from suit_ros.data.bag import messages, transform_to_matrix
    conns = [c for c in reader.connections if c.topic == '/tf_static']
    seen = []
    for conn, _, raw in messages(reader, conns):
        for tf in reader.deserialize(raw, conn.msgtype).transforms:
            parent = str(tf.header.frame_id).lstrip('/')
            child = str(tf.child_frame_id).lstrip('/')
            seen.append(f'{parent} -> {child}')
            if (parent, child) == (base_frame.lstrip('/'), lidar_frame.lstrip('/')):
                T = transform_to_matrix(tf.transform)
                R = T[:3, :3]
                rpy = (math.atan2(R[2, 1], R[2, 2]), -math.asin(max(-1.0, min(1.0, R[2, 0]))),
                       math.atan2(R[1, 0], R[0, 0]))
                return (float(T[0, 3]), float(T[1, 3]), float(T[2, 3])), rpy
    raise BagError(f'no {base_frame} -> {lidar_frame} transform in /tf_static (found: '
                   f'{seen or "no /tf_static"}); give --extrinsic-xyz/--extrinsic-rpy')


def build_pipeline(params: DetectorParams, classes: Any) -> Any:
    """The pipeline the node would build from the same parameters."""
    from suit_ros.pipeline import DetectionPipeline, load_detector
    runner, cfg, _ = load_detector(params)
    try:
        params.validate(len(cfg.class_names))
    except ConfigError as exc:
        raise ConfigError(f'{exc} (the checkpoint has classes {list(cfg.class_names)})'
                          ) from exc
    return DetectionPipeline(runner, params, classes)


def _cloud_frame(reader: Any, points_topic: str) -> str:
    from suit_ros.data.bag import messages
    conns = [c for c in reader.connections if c.topic == points_topic]
    for conn, _, raw in messages(reader, conns):
        return str(reader.deserialize(raw, conn.msgtype).header.frame_id)
    raise BagError(f'no message on {points_topic}')


def run(args: argparse.Namespace) -> int:
    """Process the bag; print a summary."""
    from suit_ros.heap import keep_freed_memory
    keep_freed_memory()          # the allocator as the node sets it (suit_ros.heap)
    from suit_ros.data.bag import ODOMETRY, POINTCLOUD2, check_topic, open_reader, open_writer
    from suit_ros.msg_adapters.classes import MessageClasses
    from suit_ros.outputs import output_dir
    out_path = Path(args.output)
    params = params_from_args(args)
    if params.points_topic == params.odom_topic:
        raise ConfigError(f'points_topic and odom_topic are both {params.points_topic}: name '
                          'the cloud topic with --points-topic, the odometry with --odom-topic')
    if args.gt_topic in (params.points_topic, params.odom_topic):
        raise ConfigError(f'--gt-topic {args.gt_topic} is also the cloud or odometry topic: '
                          'name the ground-truth boxes topic with --gt-topic')
    t0 = time.monotonic()
    with open_reader(args.input) as reader:
        if out_path.exists():
            raise BagError(f'{out_path} already exists; choose a new output path')
        output_dir(out_path.parent, 'folder of the output bag')
        check_topic(reader, params.points_topic, POINTCLOUD2, hint='use --points-topic')
        # an odometry topic named on the command line must be there (a mistyped one would
        # run every frame single-frame); the default one may be missing
        has_odom = check_topic(reader, params.odom_topic, ODOMETRY,
                               required=args.odom_topic is not None, hint='use --odom-topic')
        if not has_odom:
            print(f'detect-bag: the bag has no {params.odom_topic}: every frame runs '
                  'single-frame (no memory, no sweeps, no tracker motion); name the odometry '
                  'with --odom-topic', file=sys.stderr)
        copied = _copied_topics(reader, args) if args.copy_inputs else set()
        check_topic(reader, args.gt_topic, POINTCLOUD2, required=False, hint='use --gt-topic')
        clouds = sum(c.msgcount for c in reader.connections if c.topic == params.points_topic)
        if clouds == 0:
            raise BagError(f'{args.input} holds no message on {params.points_topic}: nothing '
                           'to detect in')
        if args.extrinsic_from_tf:
            xyz, rpy = extrinsic_from_tf_static(reader, args.base_frame,
                                                _cloud_frame(reader, params.points_topic))
            params = params.updated({'extrinsic_xyz': xyz, 'extrinsic_rpy': rpy})
            print(f'detect-bag: extrinsic from /tf_static: xyz {[round(v, 4) for v in xyz]}, '
                  f'rpy {[round(v, 4) for v in rpy]}')
        try:
            with open_writer(out_path, args.storage) as bag:
                pipe = build_pipeline(params, MessageClasses.from_rosbags(bag.store))
                summary = _process_bag(args, params, reader, bag, pipe, copied)
                if summary.read_error and not summary.frames:
                    raise BagError(summary.read_error)
                if summary.frames and summary.warnings['unusable_cloud'] == summary.frames:
                    raise BagError(f'none of the {summary.frames} clouds could be read: '
                                   f'{summary.examples["unusable_cloud"]}; check the cloud '
                                   'fields (--intensity-field) and --points-topic')
        except BaseException:     # no partial bag left behind to block the next try
            if out_path.is_dir():
                shutil.rmtree(out_path, ignore_errors=True)
            raise
    summary.print(time.monotonic() - t0, pipe.class_names)
    print(f'wrote {out_path} ({DET_TOPIC}, {MARKER_TOPIC}'
          f'{", inputs copied" if args.copy_inputs else ""})', file=sys.stderr)
    if summary.read_error:      # a damaged bag: its frames before the damage are not lost
        print(f'suit-ros detect-bag: error: {summary.read_error}; the {summary.frames} frames '
              f'read before it (messages to {summary.read_until_ns * 1e-9:.3f} s of the '
              f'recording) are in {out_path}', file=sys.stderr)
        return 1
    return 0


class Summary:
    """What ``detect-bag`` saw: frames, per-class counts, warnings per reason, GT pairs."""

    def __init__(self) -> None:
        self.frames = 0
        self.model_ms: list[float] = []
        self.classes: collections.Counter[int] = collections.Counter()
        self.warnings: collections.Counter[str] = collections.Counter()
        self.examples: dict[str, str] = {}
        self.resets: collections.Counter[str] = collections.Counter()
        self.gts: dict[int, Any] = {}
        self.dets: dict[int, Any] = {}
        self.traffic_side = ''              # the last frame's (auto: and the votes)
        self.single: collections.Counter[str] = collections.Counter()   # frames by reason
        # the bag could not be read on (a damaged chunk, a truncated file): why, and the log
        # time of the last message read
        self.read_error = ''
        self.read_until_ns = 0

    def add(self, stamp: int, out: Any) -> None:
        """Count one frame's output."""
        self.frames += 1
        self.model_ms.append(out.timings['model'] * 1e3)
        self.dets[stamp] = out.detections
        self.classes.update(int(k) for k in out.detections.labels)
        for key, text in out.warnings.items():
            self.warnings[key] += 1
            self.examples.setdefault(key, text)
        if out.reset_reason:
            self.resets[out.reset_reason.split(' (')[0]] += 1
        self.traffic_side = out.traffic_side or self.traffic_side
        if out.single_frame is not None:
            self.single[str(out.single_frame)] += 1

    def print(self, seconds: float, names: tuple[str, ...]) -> None:
        """The summary on stdout (and the evaluation when the bag has GT)."""
        from suit_ros.evaluate import evaluate
        from suit_ros.structures import Detections
        model = np.median(self.model_ms) if self.model_ms else float('nan')
        print(f'detect-bag: {self.frames} frames in {seconds:.1f} s '
              f'({self.frames / max(seconds, 1e-9):.1f} frames/s), model p50 {model:.1f} ms, '
              f'{sum(self.warnings.values())} warnings')
        for key, count in self.warnings.most_common():
            print(f'  warning {key}: {count} frames, e.g. {self.examples[key]}')
        for reason, count in self.resets.most_common():
            print(f'  memory reset: {reason}: {count}')
        if self.single:
            print(f'  single-frame (no pose for the memory and the sweeps): '
                  f'{sum(self.single.values())} of {self.frames} frames ('
                  + ', '.join(f'{k} {n}' for k, n in self.single.most_common()) + ')')
        if self.traffic_side:
            print(f'traffic side at the end: {self.traffic_side}')
        print('detections per class: ' + ', '.join(
            f'{c} {self.classes[i]}' for i, c in enumerate(names)))
        paired = [s for s in self.dets if s in self.gts]
        if paired:
            g = [Detections(self.gts[s]['boxes'], self.gts[s]['velocities'],
                            self.gts[s]['scores'], self.gts[s]['labels']) for s in paired]
            result = evaluate(g, [self.dets[s] for s in paired], names,
                              num_points=[self.gts[s].get('num_points') for s in paired])
            print(result.table())


def _copied_topics(reader: Any, args: argparse.Namespace) -> set[str]:
    """The input topics ``--copy-inputs`` copies: every one but this run's outputs (an input
    that is itself a detect-bag output holds the old model's detections: they are not mixed
    with the new ones). A type the bag does not define cannot be written: refused before
    any work is done."""
    ours = {DET_TOPIC, MARKER_TOPIC}
    topics = {c.topic for c in reader.connections}
    skipped = sorted(topics & ours)
    if skipped:
        print(f'detect-bag: not copied: {", ".join(skipped)} (this run writes them anew)',
              file=sys.stderr)
    unknown = set()
    for c in reader.connections:
        if c.topic in ours:
            continue
        try:
            reader.typestore.generate_msgdef(c.msgtype, ros_version=2)
        except Exception:  # noqa: BLE001 - rosbags raises its own kinds for unknown types
            unknown.add(f'{c.topic} ({c.msgtype})')
    if unknown:
        raise BagError(f'--copy-inputs cannot copy {", ".join(sorted(unknown))}: the bag '
                       'carries no definition of the type; run without --copy-inputs (the '
                       'detections are written either way)')
    return topics - ours


def _process_bag(args: argparse.Namespace, params: DetectorParams, reader: Any, bag: Any,
                 pipe: Any, copied: set[str]) -> Summary:
    """Every message of the bag through the pipeline; a bag that cannot be read on (a
    damaged chunk, a truncated file) ends it, said in the summary (``read_error``)."""
    from suit_ros.data.bag import messages
    from suit_ros.msg_adapters.detections import pointcloud2_to_detections
    from suit_ros.msg_adapters.odometry import stamp_to_ns
    summary = Summary()
    try:
        for conn, log_ns, raw in messages(reader):
            summary.read_until_ns = log_ns
            if conn.topic in copied:
                bag.copy(conn, log_ns, raw, reader.typestore)
            if conn.topic == params.odom_topic:
                pipe.add_odometry(reader.deserialize(raw, conn.msgtype))
            elif conn.topic == args.gt_topic:
                msg = reader.deserialize(raw, conn.msgtype)
                summary.gts[stamp_to_ns(msg.header.stamp)] = pointcloud2_to_detections(msg)
            elif conn.topic == params.points_topic:
                msg = reader.deserialize(raw, conn.msgtype)
                out = pipe.process(msg)
                stamp = stamp_to_ns(msg.header.stamp)
                bag.write(DET_TOPIC, 'sensor_msgs/msg/PointCloud2', stamp, out.detections_msg)
                bag.write(MARKER_TOPIC, 'visualization_msgs/msg/MarkerArray', stamp,
                          out.markers_msg)
                summary.add(stamp, out)
    except BagError as exc:     # what was read before it is kept (run: unless nothing)
        summary.read_error = str(exc)
    return summary
