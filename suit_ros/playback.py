"""``suit-ros detect-bag IN OUT``: every frame of a bag through the node's pipeline, in order.

No drops: odometry is fed from the bag in recording order, each cloud runs the same
:class:`~suit_ros.pipeline.DetectionPipeline` as the live node, and the detections and markers
are written under the node's output topics at the input stamps.
"""
from __future__ import annotations

import argparse
import collections
from pathlib import Path
import sys
import time
from typing import Any

import numpy as np

from suit_ros.errors import BagError

DET_TOPIC = '/detector/detections'
MARKER_TOPIC = '/detector/markers'


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Add ``detect-bag`` options."""
    parser.add_argument('input', help='input bag (sqlite3 or mcap)')
    parser.add_argument('output', help='output bag (must not exist)')
    parser.add_argument('--checkpoint', default='', help='default: the shipped checkpoint')
    parser.add_argument('--params', help='node parameter YAML (params/detector.yaml layout)')
    parser.add_argument('--points-topic', default='/points')
    parser.add_argument('--odom-topic', default='/odom')
    parser.add_argument('--gt-topic', default='/gt/objects')
    parser.add_argument('--storage', choices=['mcap', 'sqlite3'], default='mcap')
    parser.add_argument('--copy-inputs', action='store_true',
                        help='also copy every input topic into OUT')
    parser.add_argument('--device', default='auto', choices=['auto', 'cpu', 'cuda'])


def load_node_params(path: str | None) -> dict[str, Any]:
    """The ``detector: ros__parameters`` mapping of a node parameter file (or {})."""
    if not path:
        return {}
    import yaml
    with open(path, encoding='utf-8') as f:
        data = yaml.safe_load(f) or {}
    for key in ('detector', '/detector', '/**'):
        if key in data and 'ros__parameters' in data[key]:
            return dict(data[key]['ros__parameters'])
    return {}


def build_pipeline(checkpoint: str, device: str, params: dict[str, Any], classes: Any) -> Any:
    """The pipeline the node would build from the same parameters."""
    import torch

    from suit_ros.checkpoint import default_checkpoint_path, load_checkpoint
    from suit_ros.model.streaming import StreamingDetector
    from suit_ros.pipeline import DetectionPipeline, PipelineParams
    dev = 'cuda' if device == 'cuda' or (device == 'auto' and torch.cuda.is_available()) \
        else 'cpu'
    model, cfg, _ = load_checkpoint(checkpoint or default_checkpoint_path(), dev)
    det = StreamingDetector(model, dev)
    keys = PipelineParams.__dataclass_fields__
    pp = PipelineParams(**{k: (tuple(v) if isinstance(v, list) else v)
                           for k, v in params.items() if k in keys})
    thr = params.get('score_thresholds', [0.0])
    K = len(cfg.class_names)
    det.set_thresholds(None if list(thr) == [0.0] else (list(thr) * K if len(thr) == 1
                                                         else list(thr)),
                       params.get('nms_iou_threshold'), params.get('max_detections'))
    return DetectionPipeline(det, pp, classes)


def run(args: argparse.Namespace) -> int:
    """Process the bag; print a summary."""
    from suit_ros.data.bag import messages, open_reader, open_writer
    from suit_ros.evaluate import evaluate
    from suit_ros.msg_adapters.classes import MessageClasses
    from suit_ros.msg_adapters.detections import pointcloud2_to_detections
    from suit_ros.msg_adapters.odometry import stamp_to_ns
    from suit_ros.structures import Detections
    out_path = Path(args.output)
    if out_path.exists():
        raise BagError(f'{out_path} already exists; choose a new output path')
    t0 = time.monotonic()
    with open_reader(args.input) as reader:
        topics = {c.topic: c for c in reader.connections}
        if args.points_topic not in topics:
            raise BagError(f'{args.input} has no {args.points_topic} topic; topics: '
                           f'{sorted(topics)} (use --points-topic)')
        with open_writer(out_path, args.storage) as bag:
            pipe = build_pipeline(args.checkpoint, args.device, load_node_params(args.params),
                                  MessageClasses.from_rosbags(bag.store))
            names = pipe.class_names
            counts: collections.Counter[str] = collections.Counter()
            gts: dict[int, Any] = {}
            dets: dict[int, Any] = {}
            model_ms = []
            frames = 0
            warnings = 0
            for conn, log_ns, raw in messages(reader):
                if args.copy_inputs:
                    bag.write(conn.topic, conn.msgtype, log_ns, bytes(raw))
                if conn.topic == args.odom_topic:
                    pipe.add_odometry(reader.deserialize(raw, conn.msgtype))
                elif conn.topic == args.gt_topic:
                    msg = reader.deserialize(raw, conn.msgtype)
                    gts[stamp_to_ns(msg.header.stamp)] = pointcloud2_to_detections(msg)
                elif conn.topic == args.points_topic:
                    msg = reader.deserialize(raw, conn.msgtype)
                    out = pipe.process(msg)
                    stamp = stamp_to_ns(msg.header.stamp)
                    bag.write(DET_TOPIC, 'sensor_msgs/msg/PointCloud2', stamp,
                              out.detections_msg)
                    bag.write(MARKER_TOPIC, 'visualization_msgs/msg/MarkerArray', stamp,
                              out.markers_msg)
                    frames += 1
                    warnings += bool(out.warning)
                    model_ms.append(out.timings['model'] * 1e3)
                    dets[stamp] = out.detections
                    counts.update(names[int(k)] for k in out.detections.labels)
    dt = time.monotonic() - t0
    print(f'detect-bag: {frames} frames in {dt:.1f} s ({frames / max(dt, 1e-9):.1f} frames/s), '
          f'model p50 {np.median(model_ms) if model_ms else float("nan"):.1f} ms, '
          f'{warnings} frames with warnings')
    print('detections per class: ' + ', '.join(f'{c} {counts[c]}' for c in names))
    paired = [s for s in dets if s in gts]
    if paired:
        g = [Detections(gts[s]['boxes'], gts[s]['velocities'], gts[s]['scores'],
                        gts[s]['labels']) for s in paired]
        result = evaluate(g, [dets[s] for s in paired], names,
                          num_points=[gts[s].get('num_points') for s in paired])
        print(result.table())
    print(f'wrote {out_path} ({DET_TOPIC}, {MARKER_TOPIC}'
          f'{", inputs copied" if args.copy_inputs else ""})', file=sys.stderr)
    return 0
