"""``suit-ros demo``: the quick start, end to end over real DDS.

Generates the demo bag from the synthetic world if missing, starts the detector node as its own
process, plays the bag into it with ``suit-ros play``, records what the node publishes, and
prints frames in/out, rate, latency, detections per class and mAP/NDS against the bag's GT;
writes a bird's-eye-view PNG of one frame with GT and detections.
"""
from __future__ import annotations

import argparse
import os
from pathlib import Path
import sys
from typing import Any

import numpy as np


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Add ``demo`` options."""
    parser.add_argument('--out', default='out/demo', help='working directory')
    parser.add_argument('--frames', type=int, default=100, help='frames in the demo bag')
    parser.add_argument('--seed', type=int, default=7)
    parser.add_argument('--rate', type=float, default=1.0, help='playback speed factor')
    parser.add_argument('--checkpoint', default='', help='default: the shipped checkpoint')
    parser.add_argument('--timeout', type=float, default=120.0, help='give up after (s)')


def run(args: argparse.Namespace) -> int:
    """Run the demo."""
    from suit_ros.rosenv import local_ros_env
    # the demo's own node, player and recorder: a private graph on this machine
    os.environ.update(local_ros_env())
    from suit_ros.outputs import output_dir
    out = output_dir(args.out, '--out folder')
    from suit_ros.node_probe import demo_bag
    bag = Path(demo_bag(str(out), args.seed, args.frames, progress=True))
    from suit_ros.checkpoint import default_checkpoint_path, read_metadata
    ckpt = args.checkpoint or str(default_checkpoint_path())
    read_metadata(ckpt)   # fail early with a clear message
    from suit_ros.harness import node_and_probe, play_into, wait_ready
    from suit_ros.node_probe import OutputRecorder
    with node_and_probe(ckpt, name='suit_ros_demo_recorder') as (node, probe):
        rec = OutputRecorder(probe.node)
        print('[demo] waiting for the detector node ...', flush=True)
        wait_ready(probe, node, lambda: bool(rec.diags), args.timeout)
        print(f'[demo] playing {bag} at rate {args.rate} ...', flush=True)
        play_s = play_into(probe, str(bag), ['--rate', str(args.rate), '--start-delay', '1.0',
                                             '--wait-subscribers', '20'], args.timeout,
                           settle_s=3.0)
    return _report(bag, rec.clouds, rec.dets, rec.diags, play_s, out)


def _report(bag: Path, clouds: dict[int, float], dets: dict[int, Any],
            diags: list[dict[str, str]], play_s: float, out: Path) -> int:
    from suit_ros.data.bag import open_reader
    from suit_ros.evaluate import evaluate
    from suit_ros.msg_adapters.detections import pointcloud2_to_detections
    from suit_ros.msg_adapters.odometry import stamp_to_ns
    from suit_ros.structures import Detections
    gts: dict[int, dict[str, Any]] = {}
    frames_in = 0
    with open_reader(bag) as reader:
        for conn, _, raw in reader.messages():
            if conn.topic == '/gt/objects':
                msg = reader.deserialize(raw, conn.msgtype)
                gts[stamp_to_ns(msg.header.stamp)] = pointcloud2_to_detections(msg)
            elif conn.topic == '/points':
                frames_in += 1
    lat = [dets[s][0] - clouds[s] for s in dets if s in clouds]
    received = sorted(t for t, _ in dets.values())
    rate = ((len(received) - 1) / (received[-1] - received[0])
            if len(received) > 1 and received[-1] > received[0] else 0.0)
    last = diags[-1] if diags else {}
    print('\n=== suit_ros demo ===')
    print(f'frames in {frames_in}, frames out {len(dets)}, dropped (node) '
          f'{last.get("dropped_frames", "?")} (taken into the sweeps: '
          f'{last.get("frames_sweeps_only", "?")}; last input: '
          f'{last.get("input_sweeps", "?")}), output rate {rate:.1f} Hz (playback and '
          f'settling took {play_s:.1f} s)')
    if lat:
        print(f'latency (cloud received -> detections received, through DDS): p50 '
              f'{np.median(lat) * 1e3:.1f} ms, p95 {np.percentile(lat, 95) * 1e3:.1f} ms; '
              f'model p50 {last.get("model_ms_p50", "?")} ms')
    print(f'temporal memory: {last.get("memory_samples", "?")} samples, '
          f'{last.get("memory_bytes", "?")} bytes; pose source: {last.get("pose_source", "?")}')
    paired = sorted(s for s in dets if s in gts)
    if paired:
        g = [Detections(gts[s]['boxes'], gts[s]['velocities'], gts[s]['scores'],
                        gts[s]['labels']) for s in paired]
        d = [Detections(dets[s][1]['boxes'], dets[s][1]['velocities'], dets[s][1]['scores'],
                        dets[s][1]['labels']) for s in paired]
        npts = [gts[s].get('num_points') for s in paired]
        _print_published(g, d, npts)
        result = evaluate(g, d, num_points=npts)
        print('AP of the published boxes (they are cut at the published thresholds, so AP, '
              "which integrates the whole precision-recall curve, is lower than the model's: "
              '`suit-ros eval --synthetic demo`):')
        print(result.table())
        png = out / 'bev.png'
        mid = paired[len(paired) // 2]
        draw_bev(bag, mid, g[len(paired) // 2], d[len(paired) // 2], png)
        print(f"bird's-eye view of frame {mid}: {png}")
    if not dets:
        print('no detections were received: check the node output above', file=sys.stderr)
        return 1
    return 0


def _print_published(gt: list[Any], det: list[Any], num_points: list[Any]) -> None:
    """Published boxes per frame against the objects present (GT with returns), per class,
    and recall / precision of the published boxes (BEV centre within 2 m, within 50 m)."""
    from suit_ros import CLASS_NAMES
    from suit_ros.report import class_counts
    n = max(len(gt), 1)
    print(f'published boxes per frame within 50 m (objects with returns there) [in all {n} '
          'frames], recall / precision:')

    def three(x: float) -> str:
        return 'n/a  ' if x != x else f'{x:.3f}'
    for c, counts in class_counts(gt, det, CLASS_NAMES, num_points).items():
        boxes, present = len(counts.scores) / n, counts.npos / n
        at = counts.at(0.0)
        print(f'  {c:<11} {boxes:6.1f} ({present:5.1f}) [{len(counts.scores):5d} for '
              f'{counts.npos:5d}]   recall {three(at["recall"])}  '
              f'precision {three(at["precision"])}')


def draw_bev(bag: Path, stamp: int, gt: Any, det: Any, path: Path) -> None:
    """PNG of one frame: points (grey), GT boxes (green), detections (blue, with score)."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    import torch

    from suit_ros.data.bag import open_reader
    from suit_ros.msg_adapters.odometry import stamp_to_ns
    from suit_ros.msg_adapters.pointcloud2 import pointcloud2_to_xyzi
    from suit_ros.ops.iou import bev_corners
    pts = np.zeros((0, 4), np.float32)
    with open_reader(bag) as reader:
        for conn, _, raw in reader.messages():
            if conn.topic == '/points':
                msg = reader.deserialize(raw, conn.msgtype)
                if stamp_to_ns(msg.header.stamp) == stamp:
                    pts = pointcloud2_to_xyzi(msg).points
                    break
    fig, ax = plt.subplots(figsize=(9, 9))
    ax.scatter(pts[:, 0], pts[:, 1], s=0.2, c='0.6')
    for boxes, colour, scores in ((gt.boxes, 'tab:green', None),
                                  (det.boxes, 'tab:blue', det.scores)):
        if len(boxes) == 0:
            continue
        corners = bev_corners(torch.as_tensor(boxes, dtype=torch.float64)).numpy()
        for i, c in enumerate(corners):
            poly = np.vstack([c, c[:1]])
            ax.plot(poly[:, 0], poly[:, 1], color=colour, lw=1.2)
            if scores is not None:
                ax.text(c[0, 0], c[0, 1], f'{scores[i]:.2f}', fontsize=6, color=colour)
    ax.set_xlim(-50, 50)
    ax.set_ylim(-50, 50)
    ax.set_aspect('equal')
    ax.set_title('suit_ros demo: GT (green), detections (blue)')
    fig.savefig(path, dpi=100)
    plt.close(fig)
