"""``suit-ros choose-thresholds``: the per-class score thresholds the node publishes at.

AP evaluation decodes every candidate down to a low score (the checkpoint's
``head.score_threshold``, 0.1), because AP integrates the whole precision-recall curve; a user
should see fewer, surer boxes. This command runs a checkpoint as the node runs it by default
(3 sweeps, the tracker with score smoothing) over the synthetic ``tune`` split (seeds 8000+,
never trained on, never validated on), matches its detections as ``suit-ros report`` does (same
class, BEV centre within 2 m, GT with returns within 50 m), and picks per class the threshold
of best F1 on a 0.05 grid. ``--write`` stores them in the checkpoint's metadata
(``publish_thresholds``), apart from the decoding threshold; the node's ``score_thresholds``
parameter still overrides them.

A model with a carry branch also gets ``carry_publish_thresholds``, for the boxes it holds where
the cloud shows nothing: the same tune drives are played with outages drawn in (a 120-degree
sector lost for 6 frames, as in ``suit-ros outage``, other seeds), and one factor on the
published thresholds is chosen, the one of best F1 between recall of the lost sector's objects
on outage frames 3 and later (those only a memory can hold) and the precision of what is
published where the cloud shows nothing: the boxes in the lost sector on those frames and the
held boxes of the tune drives as they are (an object hidden behind another, the edge of the
view), pooled (docs/experiments/carry_default; before, the lost sectors' boxes alone).
"""
from __future__ import annotations

import argparse
from collections.abc import Sequence
from typing import Any

from suit_ros.report import SWEEP, ClassCounts

TUNE_DRIVES = 16
TUNE_FRAMES = 40
CARRY_FACTORS = tuple(round(0.3 + 0.05 * i, 2) for i in range(15))     # 0.30 .. 1.00


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Add ``choose-thresholds`` options."""
    parser.add_argument('--checkpoint', default='', help='default: the shipped checkpoint')
    parser.add_argument('--write', action='store_true',
                        help='store the chosen thresholds in the checkpoint (metadata only)')
    parser.add_argument('--drives', type=int, default=TUNE_DRIVES, help='tune-split drives')
    parser.add_argument('--cache-dir', default='data_cache')
    parser.add_argument('--keep-published', action='store_true',
                        help="keep the checkpoint's published thresholds (a model whose cells "
                        'with returns decode as before, e.g. a retrained carry branch) and '
                        'choose only the carry thresholds')


def best_f1(counts: ClassCounts, grid: Sequence[float] = SWEEP) -> dict[str, Any]:
    """The grid point of best F1 (the lowest threshold among ties); a class without GT keeps
    the highest grid threshold (nothing to find, only false positives to avoid)."""
    rows = [counts.at(t) for t in grid]
    if counts.npos == 0:
        return rows[-1]
    return max(rows, key=lambda r: (r['f1'], -r['threshold']))


def run(args: argparse.Namespace) -> int:
    """Choose (and with ``--write`` store) the published thresholds."""
    from suit_ros.checkpoint import (
        default_checkpoint_path,
        load_checkpoint,
        published_thresholds,
        update_metadata,
    )
    from suit_ros.data.sequences import synthetic_split
    from suit_ros.errors import ConfigError
    from suit_ros.evaluate import run_model
    from suit_ros.report import class_counts
    from suit_ros.tracking import TrackerConfig
    if args.drives < 1:
        raise ConfigError(f'--drives must be at least 1 (thresholds need GT), got {args.drives}')
    path = args.checkpoint or default_checkpoint_path()
    if args.write:
        check_writable(args.checkpoint)      # before the tune split is run, not after
    model, cfg, meta = load_checkpoint(path)
    names = tuple(cfg.class_names)
    if args.keep_published and getattr(model, 'carry', None) is None:
        raise ConfigError(f'--keep-published chooses carry thresholds only: {path} has no '
                          'carry branch')
    # (a checkpoint `suit-ros train` wrote has none: it would keep the decoding threshold,
    # 0.1, and choose carry thresholds for that)
    missing = [c for c in names if c not in (meta.get('publish_thresholds') or {})]
    if args.keep_published and missing:
        raise ConfigError(f'--keep-published: {path} has no published thresholds for '
                          f'{", ".join(missing)} to keep; copy them from the checkpoint it '
                          'was trained from (its publish_thresholds metadata), or choose them '
                          'all without --keep-published')
    seqs = synthetic_split('tune', args.drives, TUNE_FRAMES, args.cache_dir)
    run_ = run_model(model, seqs, tracker=TrackerConfig(), deskew=True)   # as the node
    counts = class_counts(run_.gt, run_.det, names, run_.num_points)
    chosen: dict[str, float] = {}
    print(f'{path}: tune split, {args.drives} drives x {TUNE_FRAMES} frames, node defaults')
    print(f'{"class":<12}{"threshold":>10}{"recall":>8}{"precision":>10}{"F1":>7}{"GT":>6}')
    kept = published_thresholds(meta, list(names)) if args.keep_published else None
    for k, c in enumerate(names):
        row = best_f1(counts[c], [kept[k]] if kept is not None else SWEEP)
        chosen[c] = float(row['threshold'])
        print(f'{c:<12}{row["threshold"]:>10.2f}{row["recall"]:>8.3f}'
              f'{row["precision"]:>10.3f}{row["f1"]:>7.3f}{row["gt"]:>6d}')
    extra: dict[str, Any] = {}
    if getattr(model, 'carry', None) is not None:
        factor, carry = carry_thresholds(model, seqs, [chosen[c] for c in names], run_)
        extra = {'carry_publish_thresholds': dict(zip(names, carry)),
                 'carry_publish_thresholds_source': (
                     f'{factor:.2f} x the published ones: best F1 of recall on outage frames 3+ '
                     f'of the tune drives with outages drawn in and the precision of the boxes '
                     f'published there and of the held boxes of the tune drives as they are')}
        print('carry thresholds (boxes held where the cloud shows nothing): '
              + ', '.join(f'{c} {v:.3f}' for c, v in zip(names, carry)))
    if args.write and kept is not None:
        update_metadata(path, **extra)
    elif args.write:
        update_metadata(path, publish_thresholds=chosen, publish_thresholds_source=(
            f'best F1 per class on the synthetic tune split ({args.drives} drives x '
            f'{TUNE_FRAMES} frames, seeds 8000+), node defaults, BEV centre <= 2 m within 50 m'),
            **extra)
    if args.write:
        print(f'stored in {path}')
    return 0


def check_writable(given: str) -> None:
    """What ``--write`` would rewrite (a shipped checkpoint by its name too, as the recipe
    does) can be written: checked before the tune split is run, not after it.

    :raises ConfigError: a read-only file, or a folder that cannot be written.
    """
    import stat

    from suit_ros.checkpoint import resolve_checkpoint
    from suit_ros.errors import ConfigError
    from suit_ros.outputs import output_file
    target = resolve_checkpoint(given)
    if target.is_file() and not stat.S_IMODE(target.stat().st_mode) & stat.S_IWUSR:
        raise ConfigError(f'{target} is read-only: --write would replace it; make it writable '
                          'or give a copy')
    output_file(target, 'checkpoint to --write')


def carry_thresholds(model: Any, seqs: Sequence[Sequence[Any]], published: list[float],
                     ordinary: Any = None) -> tuple[float, list[float]]:
    """The factor on ``published`` (:func:`best_carry_factor`) for the carry thresholds, from
    ``seqs`` played with outages (node defaults) and ``ordinary``, the run of ``seqs`` as they
    are (node defaults; None: not counted), and the thresholds."""
    from suit_ros.evaluate import run_model
    from suit_ros.outage import outages_for, with_outages
    from suit_ros.tracking import TrackerConfig
    outs = [outages_for(i, len(seq), seed=1) for i, seq in enumerate(seqs)]
    played = [with_outages(seq, o) for seq, o in zip(seqs, outs)]
    rows = carry_factor_rows(run_model(model, played, tracker=TrackerConfig(), deskew=True),
                             played, outs, published, ordinary)
    for r in rows:
        print(f'  carry factor {r["factor"]:.2f}: outage frames 3+ recall {r["recall"]:.3f}, '
              f'sector precision {r["sector_precision"]:.3f}, held on the drives as they are '
              f'{r["held_boxes"]:.0f} at {r["held_precision"]:.3f}; pooled precision '
              f'{r["precision"]:.3f}, F1 {r["f1"]:.3f}')
    factor = best_carry_factor(rows)
    return factor, [round(factor * t, 4) for t in published]


def carry_factor_rows(run: Any, played: Sequence[Sequence[Any]], outs: Sequence[Sequence[Any]],
                      published: list[float], ordinary: Any = None) -> list[dict[str, float]]:
    """Per factor of :data:`CARRY_FACTORS`: recall of the lost sectors' objects on outage
    frames 3+, the precision of the boxes published there (``sector_precision``) and of the
    held boxes of ``ordinary`` (a run of the drives as they are; None: none), that precision
    pooled over both (``precision``) and its F1 with the recall, with the carried boxes cut at
    factor x ``published`` (the others at ``published``)."""
    from suit_ros.outage import count_outage, published_by_drive
    rows = []
    for f in CARRY_FACTORS:
        carry = [f * t for t in published]
        det = published_by_drive(run, published, carry)
        counts = count_outage(played, det, outs, [0.0] * len(published),
                              max((o.frames for d in outs for o in d), default=0))
        recall = counts.found[:, 2:].sum() / max(counts.objects[:, 2:].sum(), 1)
        held, held_true = held_counts(ordinary, published, carry) if ordinary else (0, 0)
        boxes, true = counts.boxes[:, 2:].sum(), counts.true[:, 2:].sum()
        precision = (true + held_true) / max(boxes + held, 1)
        rows.append({'factor': f, 'recall': float(recall), 'precision': float(precision),
                     'sector_precision': float(true / max(boxes, 1)), 'held_boxes': held,
                     'held_precision': held_true / max(held, 1),
                     'f1': float(2 * recall * precision / max(recall + precision, 1e-9))})
    return rows


def held_counts(run: Any, published: list[float], carry: list[float]) -> tuple[int, int]:
    """The boxes ``run`` publishes where the cloud shows nothing (``carried``: a carry head's
    or the tracker's coasted ones, at ``carry``; the rest at ``published``) and how many of
    them match an object (same class, BEV centre within 2 m, all published boxes of the frame
    matched greedily by score)."""
    from suit_ros.evaluate import match_frame
    from suit_ros.outage import MATCH_DIST
    boxes = true = 0
    for gt, d, c, m in zip(run.gt, run.det, run.held(), run.published_masks(published, carry)):
        det, held = d.select(m), c[m]
        boxes += int(held.sum())
        for k in range(len(published)):
            tp = match_frame(gt, det, k, MATCH_DIST).tp
            true += int(tp[held[det.labels == k]].sum())
    return boxes, true


def best_carry_factor(rows: Sequence[dict[str, float]]) -> float:
    """The factor of best F1, the highest among ties (fewer boxes for the same F1)."""
    return max(rows, key=lambda r: (r['f1'], r['factor']))['factor']
