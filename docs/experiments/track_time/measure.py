#!/usr/bin/env python3
"""Track lifetimes counted in frames or in seconds: a 20 Hz sensor and an overloaded node.

The tracker holds a confident track that gets no detection where the sweep shows nothing of it
(coasting) and keeps a track alive without detections for a while. Both were counted in frames
(5 and 6: 0.5 and 0.6 s at 10 Hz); they are now seconds (``coast_s`` 0.5, ``max_miss_s`` 0.6).
Frames counted at another rate are the same seconds scaled, so each comparison below runs the
shipped SUIT checkpoint, tracked and deskewed as the node runs it, twice: with the lifetimes the
frame counts gave at that rate, and with the seconds.

(a) ``20hz``: the ``outage`` split's drives (seeds 8500+, never trained, tuned or validated on;
    four sensor models) simulated at 20 Hz for 80 frames (4 s), a 120-degree sector lost for 12
    frames (0.6 s, the benchmark's 6 frames at 10 Hz) every 28 frames from frame 6. Frames:
    coast 5, live 6 (0.25 / 0.30 s). Recall at the published thresholds of the objects in the
    lost sector that had returns before it, by time into the outage, sector precision, and
    mAP / NDS over every frame three ways: as the standard rule scores (an object with no
    return is no object: a box held in the lost sector is a false positive), with the objects
    scored where the sensor would have seen them without the outage (they are still there),
    and on the frames outside the outages.
(b) ``half``: the validation drives (16, seeds 9000+, 40 frames at 10 Hz), the model on every
    other cloud (the skipped ones buffered as the node does). Frames: coast 5, live 6 (1.0 /
    1.2 s at 5 Hz). mAP, NDS, moving-car velocity error.

Per-drive bootstrap (200 resamples), paired over the same drives and frames.
Usage: docs/experiments/track_time/measure.py [--part 20hz half] [--drives 16] [--out F.json]
"""
from __future__ import annotations

import argparse
from dataclasses import replace
import json
import time
from typing import Any


def main() -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or '').splitlines()[0])
    parser.add_argument('--part', nargs='+', choices=['20hz', 'half'], default=['20hz', 'half'])
    parser.add_argument('--drives', type=int, default=16)
    parser.add_argument('--cache-dir', default='data_cache')
    parser.add_argument('--out', default='')
    args = parser.parse_args()
    import torch
    torch.set_num_threads(2)
    from suit_ros.accuracy import bootstrap, plain_intervals
    from suit_ros.checkpoint import load_checkpoint, published_thresholds
    from suit_ros.data.sequences import synthetic_split
    from suit_ros.evaluate import ModelRun, run_model
    from suit_ros.outage import (
        count_outage,
        intervals,
        outages_for,
        published_by_drive,
        with_outages,
    )
    from suit_ros.tracking import TrackerConfig

    model, cfg, meta = load_checkpoint('suit_default', 'cpu')
    names = list(cfg.class_names)
    thr = published_thresholds(meta, names)
    carry = published_thresholds(meta, names, carried=True)
    keys = ['mAP', 'NDS', 'AP car', 'AP pedestrian', 'moving car vel err']
    report: dict[str, Any] = {}

    def node_run(seqs: list[list[Any]], tracker: TrackerConfig, **kw: Any) -> ModelRun:
        t0 = time.monotonic()
        run = run_model(model, seqs, tracker=tracker, deskew=True, **kw)
        print(f'  coast {tracker.coast_s} s, live {tracker.max_miss_s} s {kw or ""}: '
              f'{len(run.det)} frames in {time.monotonic() - t0:.0f} s', flush=True)
        return run

    def compare(runs: dict[str, ModelRun]) -> dict[str, Any]:
        a, b = list(runs)
        point, diffs = bootstrap(runs, names, pairs=[(b, a)])
        for n, m in point.items():
            print(f'  {n:32s} ' + '  '.join(f'{k} {m[k].fmt()}' for k in keys if k in m))
        for n, m in diffs.items():
            print(f'  {n:60s} ' + '  '.join(f'{k} {m[k].fmt()}' for k in keys if k in m))
        return {'runs': plain_intervals(point), 'paired': plain_intervals(diffs)}

    if '20hz' in args.part:
        frames, length = 80, 12
        plain = synthetic_split('outage', args.drives, frames, args.cache_dir, rate_hz=20.0)
        outs = [outages_for(i, frames, 120.0, length, period=28) for i in range(len(plain))]
        seqs = [with_outages(seq, o) for seq, o in zip(plain, outs)]
        print(f'20 Hz: {len(seqs)} drives x {frames} frames, {sum(map(len, outs))} outages '
              f'of {length} frames', flush=True)
        runs = {'frames (0.25 / 0.30 s)': node_run(seqs, TrackerConfig(coast_s=0.25,
                                                                        max_miss_s=0.3)),
                'seconds (0.5 / 0.6 s)': node_run(seqs, TrackerConfig())}
        print('every frame, objects scored where they have returns (the standard rule: an '
              'object in a lost sector is no object, a box held there a false positive)')
        part: dict[str, Any] = compare(runs)
        # the objects are still there: scored where the sensor would have seen them
        seen = [f.num_points for seq in plain for f in seq]
        print('every frame, objects scored where the sensor would have seen them without '
              'the outage')
        part['objects_kept'] = compare({n: replace(r, num_points=seen) for n, r in runs.items()})
        quiet = [i for i, (d, k) in enumerate((d, k) for d, seq in enumerate(seqs)
                                              for k in range(len(seq)))
                 if not any(o.active(k) for o in outs[d])]
        print(f'the {len(quiet)} frames outside the outages')
        part['outside_outages'] = compare({n: r.select_frames(quiet) for n, r in runs.items()})
        part['outage'] = {}
        for n, run in runs.items():
            counts = count_outage(seqs, published_by_drive(run, thr, carry), outs,
                                  [0.0] * len(thr), length)
            band = intervals(counts)
            rec = band['recall']
            prec = band['sector_precision']
            late = counts.found[:, 6:].sum() / max(counts.objects[:, 6:].sum(), 1)
            late_boxes = counts.boxes[:, 6:].sum()
            late_prec = counts.true[:, 6:].sum() / late_boxes if late_boxes else float('nan')
            print(f'  {n}: outage recall by 0.05 s frame ' + ' '.join(f'{r[0]:.2f}'
                                                                      for r in rec))
            print(f'  {n}: sector precision by frame  ' + ' '.join(f'{p[0]:.2f}'
                                                                   for p in prec))
            print(f'  {n}: frames 7-12 (0.35-0.6 s): recall {late:.3f}, sector precision '
                  f'{late_prec:.3f} of {late_boxes} boxes', flush=True)
            part['outage'][n] = {**band, 'recall_0.35_0.6s': float(late),
                                 'sector_precision_0.35_0.6s': float(late_prec)}
        report['20hz'] = part
    if 'half' in args.part:
        seqs = synthetic_split('val', args.drives, 40, args.cache_dir)
        print(f'half rate: {len(seqs)} validation drives x 40 frames', flush=True)
        runs = {'frames (1.0 / 1.2 s)': node_run(seqs, TrackerConfig(coast_s=1.0,
                                                                      max_miss_s=1.2),
                                                 run_every=2),
                'seconds (0.5 / 0.6 s)': node_run(seqs, TrackerConfig(), run_every=2)}
        report['half'] = compare(runs)
    if args.out:
        with open(args.out, 'w', encoding='utf-8') as f:
            json.dump(report, f, indent=1, default=float)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
