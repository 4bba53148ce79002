"""Car heading flips with and without the tracker turning round vehicles that drive backwards
(FilterConfig.heading_min_speed), at the published thresholds, node defaults otherwise.

    python docs/experiments/heading/measure.py [--av2 ROOT] [--split val|tune]
"""
from __future__ import annotations

import argparse
from dataclasses import replace

from suit_ros.checkpoint import default_checkpoint_path, load_checkpoint, published_thresholds
from suit_ros.evaluate import run_model
from suit_ros.report import build_report
from suit_ros.tracking import FilterConfig


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument('--av2')
    parser.add_argument('--split', default='val')
    parser.add_argument('--checkpoint', default=str(default_checkpoint_path()))
    args = parser.parse_args()
    model, cfg, meta = load_checkpoint(args.checkpoint)
    thr = published_thresholds(meta, cfg.class_names)
    if args.av2:
        from suit_ros.data.av2 import av2_sequences
        seqs = list(av2_sequences(args.av2, cfg.class_names))
    else:
        from suit_ros.data.sequences import synthetic_split
        seqs = synthetic_split(args.split, 16, 40, 'data_cache')
    for name, fc in (('tracker, heading as the model gives it',
                      replace(FilterConfig(), heading_min_speed=None)),
                     ('tracker, heading settled by velocity', FilterConfig())):
        rep = build_report(run_model(model, seqs, velocity_filter=fc), cfg.class_names, thr,
                           args.av2 or args.split)
        h = rep.to_json()['car_heading']
        print(f'{name}: matched cars {h["matched"]}, flipped {h["flipped"]} '
              f'({h["flip_rate"]}), mean error {h["mean_deg"]} deg, median '
              f'{h["median_deg"]} deg', flush=True)


if __name__ == '__main__':
    main()
