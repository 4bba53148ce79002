#!/usr/bin/env python3
"""The vote's settings on the tune split (seeds 8000+, never validation): the shipped model and
the node's tracker run once over each tune drive as it is (right-hand) and mirrored
(left-hand), given as right-hand traffic; each setting's votes are then replayed over the
recorded tracks (until a side changes, nothing else differs): the frame a mirrored drive
goes over to left, and any drive as it is that would (a false change).

Usage: tune.py DRIVES FRAMES
"""
from __future__ import annotations

from dataclasses import replace
import itertools
import sys

import numpy as np

from suit_ros.checkpoint import load_checkpoint
from suit_ros.data.augment import mirror_world
from suit_ros.data.sequences import synthetic_split
from suit_ros.evaluate import step_inputs
from suit_ros.model.streaming import StreamingDetector
from suit_ros.tracking import TrackerConfig
from suit_ros.traffic_side import SideVoteConfig, TrafficSideVote

drives, frames = int(sys.argv[1]), int(sys.argv[2])
seqs = synthetic_split('tune', drives, frames, 'data_cache')
model, cfg, _ = load_checkpoint('suit_default')
runner = StreamingDetector(model, tracker=TrackerConfig())
recorded: dict[str, list[list[tuple]]] = {'plain': [], 'mirrored': []}
for seq in seqs:
    for world, drive in (('plain', seq), ('mirrored', [mirror_world(f) for f in seq])):
        runner.reset('new drive')
        rows = []
        for f in drive:
            points, stamp, T_odom_base, T_bl = step_inputs(f)
            res = runner.step(points, stamp, T_odom_base, T_bl)
            d = res.detections
            rows.append((d.boxes, d.velocities, d.labels, res.track_ids, T_bl, T_odom_base,
                         stamp))
        recorded[world].append(rows)
print(f'recorded {drives} tune drives x {frames} frames, as they are and mirrored', flush=True)


def replay(config: SideVoteConfig, rows: list[tuple]) -> int | None:
    """The frame the side changes at (None: never)."""
    vote = TrafficSideVote(cfg.class_names, config=config)
    for t, row in enumerate(rows):
        if vote.update(*row):
            return t
    return None


base = SideVoteConfig()
print('| frames | max_ahead | max_lateral | min_ego_speed | votes | mirrored drives changed '
      '| median frame | false changes |')
print('|---|---|---|---|---|---|---|---|')
for n, ahead, lateral, ego, (window, need) in itertools.product(
        (2, 3), (15.0, 25.0), (10.0, 15.0), (1.0, 2.0), ((5, 4), (4, 3), (3, 2))):
    c = replace(base, frames=n, max_ahead=ahead, max_lateral=lateral, min_ego_speed=ego,
                window=window, min_votes=need)
    left = [replay(c, rows) for rows in recorded['mirrored']]
    false = sum(replay(c, rows) is not None for rows in recorded['plain'])
    changed = [t for t in left if t is not None]
    med = float(np.median(changed)) if changed else float('nan')
    print(f'| {n} | {ahead:g} | {lateral:g} | {ego:g} | {need} of {window} | {len(changed)} of '
          f'{drives} | {med:.0f} | {false} |', flush=True)
