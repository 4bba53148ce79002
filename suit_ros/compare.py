"""``suit-ros compare``: checkpoints and their variants on the fixed validation drives, with
per-drive intervals and paired differences (the one comparison command; ``--ablation`` is the
docs/results.md set).

Each checkpoint runs as it is (its own config: sweeps, temporal mode) over the validation
drives (``val`` seeds 9000.., never trained or tuned on); ``--variant`` adds runs of each
checkpoint changed in one way:

- ``memory dropped``: the feature memory forgotten before every frame (sweeps kept);
- ``zero displacement``: GeoNet replaced by a zero displacement (SUIT checkpoints);
- ``no intensity``: the clouds without their intensity channel;
- ``bfloat16``: the backbone and head convolutions in bfloat16;
- ``tracking``: the node's tracker over the detections (velocities, scores, ids);
- ``overhead``: the drives with canopies and awnings over their objects
  (:func:`suit_ros.data.overhead.overhead_drives`, fixed draws);
- ``ground local``: the input leveled to its local ground (:mod:`suit_ros.ground`), and
  ``ground as given``: not leveled; each runs only for a checkpoint whose config asks for the
  other (the shipped ones ask for ``local``);
- ``overhang drop``: the returns that hang over a gap in their column dropped
  (:mod:`suit_ros.overhang`), and ``overhang keep``: every return kept; each runs only for a
  checkpoint whose config asks for the other (the shipped SUIT model drops them);
  ``overhead, overhang drop`` and ``overhead, overhang keep``: the same on the drives with
  canopies and awnings;
- ``box fit faces``: car boxes moved onto the returns of their visible faces
  (:mod:`suit_ros.box_fit`), and ``tracking, box fit faces``: the same under the node's
  tracker;
- ``real car ends`` and ``tracking, real car ends``: the same drives with half their
  passenger cars shaped at their ends as real cars are (preset ``val-ends``,
  :attr:`~suit_ros.data.sim.config.Realism.real_car_ends`; everything else as it was);
  ``all car ends`` and ``tracking, all car ends``: every passenger car so shaped (preset
  ``val-ends-all``); ``street objects`` and ``tracking, street objects``: every car so
  shaped and the sidewalks holding the street objects of real ones (preset
  ``val-street-ends``); ``bystanders`` and ``tracking, bystanders``: those drives with half
  the pedestrians standing beside a street object or a parked car (preset ``val-bystanders``,
  :mod:`~suit_ros.data.sim.bystanders`; scored against the boxes where they stand);
  ``dark tops`` and ``tracking, dark tops``: the street-objects drives with half the passenger
  cars seen only below the belt (preset ``val-dark-tops``,
  :attr:`~suit_ros.data.sim.config.Realism.dark_tops`); ``parked rows`` and ``tracking,
  parked rows``: the street-objects drives with about half the kerbs near the ego lined with
  rows of parked cars (preset ``val-parked-rows``, :mod:`~suit_ros.data.sim.parked_rows`;
  scored against their own labels, the rows' cars among them); ``fronts`` and ``tracking,
  fronts``: the street-objects drives with half the pedestrians standing close in front of a
  building or a wall (preset ``val-fronts``,
  :func:`~suit_ros.data.sim.bystanders.place_at_fronts`);
- ``mirrored`` and ``tracking, mirrored``: the drives mirrored across the LiDAR's x-z plane,
  odometry frame included (:func:`~suit_ros.data.augment.mirror_world`): left-hand traffic,
  every car parked facing the other way from where it would stand in right-hand traffic, so
  a model that reads headings off the side of the road turns them round;
- ``deskewed`` and ``tracking, deskewed``: the sweeps of the sensors that take them over time
  put back at their stamps (:mod:`suit_ros.deskew`), as the node does by default; every other
  run has them as taken, as the figures in docs/results.md were measured.

Paired differences (same drive resamples): every checkpoint against the first, each variant
against its checkpoint (``memory dropped`` and ``zero displacement`` as checkpoint minus
variant: what the part is worth; the others as variant minus checkpoint; a variant named
``A, B`` minus the run of ``A`` when there is one: the same drives and the same tracker), and
a variant of every checkpoint against the same variant of the first. Writes ``OUT/results.md`` and
``OUT/results.json``.
"""
from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import dataclass, field, replace
import os
from pathlib import Path
import platform
import time
from typing import Any

import numpy as np

from suit_ros.config import TemporalMode
from suit_ros.model.inference import PrecisionChoice
from suit_ros.params import GroundParam, OverhangParam
from suit_ros.structures import Frame

VARIANTS = ('memory dropped', 'zero displacement', 'no intensity', 'bfloat16', 'tracking',
            'overhead', 'ground local', 'ground as given', 'overhang drop', 'overhang keep',
            'overhead, overhang drop', 'overhead, overhang keep', 'box fit faces',
            'tracking, box fit faces', 'real car ends', 'tracking, real car ends',
            'all car ends', 'tracking, all car ends', 'street objects',
            'tracking, street objects', 'bystanders', 'tracking, bystanders', 'dark tops',
            'tracking, dark tops', 'occluders', 'tracking, occluders', 'deskewed',
            'tracking, deskewed', 'parked rows', 'tracking, parked rows', 'mirrored',
            'tracking, mirrored', 'fronts', 'tracking, fronts')
# the validation drives regenerated in another world: passenger cars shaped at their ends as
# real cars are; and with the street objects of real sidewalks too; and pedestrians beside them;
# or cars seen only below the belt; or the kerbs lined with parked cars
WORLDS = {'real car ends': 'val-ends', 'all car ends': 'val-ends-all',
          'street objects': 'val-street-ends', 'bystanders': 'val-bystanders',
          'dark tops': 'val-dark-tops', 'parked rows': 'val-parked-rows', 'fronts': 'val-fronts'}
WORTH = ('memory dropped', 'zero displacement')      # paired as checkpoint minus variant
SHOW = ['mAP', 'NDS', 'mAP moving', 'mAP vis 1-5', 'mAP vis 6-20', 'mAP vis >20', 'mAVE', 'mAOE',
        'car heading err', 'car flipped %', 'moving car vel err', 'moving car speed slope']
DIFF_COLUMNS = ['mAP', 'NDS', 'mAP moving', 'mAVE', 'mAOE', 'moving car vel err']


def no_intensity(frame: Frame) -> Frame:
    """The frame with its intensity channel zeroed."""
    pts = frame.points.copy()
    pts[:, 3] = 0.0
    return replace(frame, points=pts)


def load_as(path: str, temporal: TemporalMode | None = None) -> Any:
    """:func:`~suit_ros.checkpoint.load_model_as` on the CPU."""
    from suit_ros.checkpoint import load_model_as
    return load_model_as(path, temporal, 'cpu')


def variant_run(path: str, model: Any, variant: str, sequences: Any,
                precision: PrecisionChoice, cache_dir: str | None = None) -> Any:
    """One variant's run (None when it does not apply to the model)."""
    from suit_ros.evaluate import run_model
    from suit_ros.tracking import TrackerConfig
    temporal = model.cfg.temporal
    kwargs: dict[str, Any] = {'precision': precision}
    if variant == 'memory dropped':
        if temporal == 'none':
            return None
        return run_model(model, sequences, drop_memory=True, **kwargs)
    if variant == 'zero displacement':
        return None if temporal != 'suit' else run_model(load_as(path, 'sparse'), sequences,
                                                         **kwargs)
    if variant == 'no intensity':
        return run_model(model, sequences, transform=no_intensity, **kwargs)
    if variant == 'bfloat16':
        return run_model(model, sequences, precision='bfloat16')
    if variant == 'tracking':
        return run_model(model, sequences, tracker=TrackerConfig(), **kwargs)
    base = variant.removeprefix('tracking, ')          # the same, under the node's tracker
    tracker = TrackerConfig() if base != variant else None
    if base in WORLDS:
        from suit_ros.data.sequences import synthetic_split
        drives = synthetic_split('val', len(sequences), len(sequences[0]), cache_dir,
                                 preset_name=WORLDS[base])
        return run_model(model, drives, tracker=tracker, **kwargs)
    if base == 'occluders':
        from suit_ros.data.occluders import occluded_drives
        return run_model(model, occluded_drives(sequences), tracker=tracker, **kwargs)
    if base == 'mirrored':          # left-hand traffic
        from suit_ros.data.augment import mirror_world
        return run_model(model, sequences, tracker=tracker, transform=mirror_world, **kwargs)
    if base == 'deskewed':          # sweeps taken over time put back at their stamps
        return run_model(model, sequences, tracker=tracker, deskew=True, **kwargs)
    if base == 'box fit faces':
        return run_model(model, sequences, tracker=tracker, box_fit='faces', **kwargs)
    if variant == 'overhead' or variant.endswith(('overhang drop', 'overhang keep')):
        from suit_ros.data.overhead import overhead_drives
        drives = overhead_drives(sequences) if variant.startswith('overhead') else sequences
        if variant != 'overhead':
            overhang: OverhangParam = 'drop' if variant.endswith('drop') else 'keep'
            if model.cfg.pillars.overhang == overhang:
                return None
            kwargs['overhang'] = overhang
        return run_model(model, drives, **kwargs)
    if variant in ('ground local', 'ground as given'):
        ground: GroundParam = 'local' if variant == 'ground local' else 'as_given'
        if model.cfg.pillars.ground == ground:
            return None
        return run_model(model, sequences, ground=ground, **kwargs)
    raise ValueError(f'unknown variant {variant!r}; choose from {", ".join(VARIANTS)}')


def pairs_of(names: list[str], runs: dict[str, Any], variants: list[str]
             ) -> list[tuple[str, str]]:
    """The paired differences the module docstring names, for the runs that exist."""
    first = names[0]
    pairs = [(n, first) for n in names[1:]]
    for n in names:
        for v in variants:
            key = f'{n}, {v}'
            base = f'{n}, {v.rsplit(", ", 1)[0]}' if ', ' in v else n
            if key in runs:
                pairs.append((n, key) if v in WORTH else
                             (key, base if base in runs else n))
            if n != first and key in runs and f'{first}, {v}' in runs and v not in WORTH:
                pairs.append((key, f'{first}, {v}'))
    return pairs


@dataclass
class Comparison:
    """What :func:`compare` measured (intervals as :class:`~suit_ros.accuracy.Interval`)."""

    stats: dict[str, Any]
    diffs: dict[str, Any]
    latency: dict[str, float]
    memory: dict[str, dict[int, int]]
    meta: dict[str, Any]
    class_names: list[str]
    heldout: dict[str, Any] = field(default_factory=dict)
    clutter: dict[str, dict[str, float]] = field(default_factory=dict)
    share: dict[str, float] = field(default_factory=dict)


def compare(checkpoints: list[tuple[str, str]], variants: list[str], drives: int = 16,
            frames: int = 40, resamples: int = 100, cache_dir: str = 'data_cache',
            precision: PrecisionChoice = 'float32', log: Callable[[str], None] = print
            ) -> tuple[
                Comparison, dict[str, Any], Any]:
    """Run every checkpoint and variant on the validation drives and bootstrap them.

    :return: the comparison, the runs by name, and the validation drives.
    """
    from suit_ros.accuracy import bootstrap
    from suit_ros.data.sequences import split_drives, synthetic_split
    from suit_ros.evaluate import run_model
    t0 = time.monotonic()
    runs: dict[str, Any] = {}
    # every checkpoint loaded and checked before the first run (which may take an hour): a
    # corrupt one or another class set is said now, not after the runs before it
    if not checkpoints:
        raise ValueError('no checkpoints to compare')
    models = [load_as(path) for _, path in checkpoints]
    names = tuple(models[0].cfg.class_names)
    for (_, path), model in zip(checkpoints, models):
        if tuple(model.cfg.class_names) != names:
            raise ValueError(f'{path} has classes {list(model.cfg.class_names)}, not '
                             f'{list(names)} as {checkpoints[0][1]}: compare checkpoints of '
                             'one class set')
    val = synthetic_split('val', drives, frames, cache_dir)
    for (name, path), model in zip(checkpoints, models):
        runs[name] = run_model(model, val, precision=precision)
        for v in variants:
            r = variant_run(path, model, v, val, precision, cache_dir)
            if r is not None:
                runs[f'{name}, {v}'] = r
        log(f'[compare] {name}: {(time.monotonic() - t0) / 60:.1f} min')
    stats, diffs = bootstrap(runs, names, pairs_of([n for n, _ in checkpoints], runs,
                                                   variants), resamples)
    meta = {'machine': f'{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, '
                       f'Python {platform.python_version()}',
            'date': time.strftime('%Y-%m-%d'), 'checkpoints': dict(checkpoints),
            'val_drives': [list(d) for d in split_drives('val', drives)],
            'frames_per_drive': frames, 'resamples': resamples, 'precision': precision,
            'minutes': round((time.monotonic() - t0) / 60, 1)}
    result = Comparison(stats, diffs,
                        {k: float(np.median(r.latency_s)) * 1e3 for k, r in runs.items()},
                        {k: {n: int(np.median(v)) for n, v in r.memory_after.items()}
                         for k, r in runs.items()}, meta, list(names))
    return result, runs, val


def extras(result: Comparison, checkpoints: list[tuple[str, str]], runs: dict[str, Any],
           val: Any, heldout_drives: int, cache_dir: str, log: Callable[[str], None] = print
           ) -> None:
    """The ablation's extra sections: the held-out sensor (each checkpoint with and without
    the tracker), false positives on clutter, and the past term's share at car centres (of the
    last checkpoint)."""
    from suit_ros.accuracy import bootstrap, past_share
    from suit_ros.data.sequences import split_drives, synthetic_split
    from suit_ros.data.sim.clutter import clutter_fp, clutter_frames
    from suit_ros.evaluate import run_model
    from suit_ros.tracking import TrackerConfig
    frames = result.meta['frames_per_drive']
    base = {n: runs[n] for n, _ in checkpoints}
    result.clutter = clutter_fp(base, clutter_frames(split_drives('val', len(val)), frames), 0.3)
    result.share = past_share(load_as(checkpoints[-1][1]), val[:8])
    log(f'[compare] past share at car centres: {result.share}')
    if heldout_drives:
        hv = synthetic_split('heldout', heldout_drives, frames, cache_dir)
        hruns = {}
        for name, path in checkpoints:
            model = load_as(path)
            hruns[name] = run_model(model, hv)
            hruns[f'{name}, tracking'] = run_model(model, hv, tracker=TrackerConfig())
        result.heldout, _ = bootstrap(hruns, result.class_names, (), result.meta['resamples'])
        result.meta['heldout_drives'] = [list(d) for d in split_drives('heldout',
                                                                       heldout_drives)]


def _table(rows: dict[str, Any], cols: list[str]) -> list[str]:
    lines = ['| run | ' + ' | '.join(cols) + ' |', '|---' * (len(cols) + 1) + '|']
    for r, m in rows.items():
        lines.append(f'| {r} | ' + ' | '.join(m[c].fmt(3) if c in m else 'n/a'
                                             for c in cols) + ' |')
    return lines


def render(r: Comparison, title: str, command: str) -> str:
    """The results page (markdown)."""
    meta = r.meta
    sensors = sorted({s for _, s in meta['val_drives']})
    lines = [f'# {title}', '', f'Regenerated by `{command}`.', '',
             f'Validation: {len(meta["val_drives"])} synthetic drives from seeds the training '
             f'never used (9000+), {meta["frames_per_drive"]} frames each at 10 Hz, sensor '
             f'models {", ".join(sensors)}; {meta["precision"]} unless the run says otherwise. '
             f'Every figure: value [95% interval] from {meta["resamples"]} per-drive bootstrap '
             f'resamples. Machine: {meta["machine"]}; {meta["date"]}.', '',
             'NDS has no attribute term: (5 mAP + sum over ATE/ASE/AOE/AVE of (1 - min(1, x)))'
             ' / 9. "moving": GT speed > 1 m/s; "vis a-b": GT with a..b LiDAR points; in a '
             'bucket, detections matched to GT outside it are ignored and unmatched ones count '
             "as false positives (nuScenes' attribute rule). Car heading error is over the "
             'full circle (flipped: > 135 deg), on detections with score >= 0.3 matched within '
             '2 m; velocity error on cars with GT speed > 1 m/s.', '',
             '## Checkpoints', '', '| run | checkpoint |', '|---|---|']
    lines += [f'| {n} | `{p}` |' for n, p in meta['checkpoints'].items()]
    lines += ['', '## Overall and by bucket', ''] + _table(r.stats, SHOW[:6])
    lines += ['', '## Heading, velocity, per class', '']
    lines += _table(r.stats, SHOW[6:] + [f'AP {c}' for c in r.class_names])
    lines += ['', '## Paired differences (same drive resamples)', '']
    lines += _table(r.diffs, DIFF_COLUMNS)
    lines += _left_out(r)
    lines += _extra_sections(r)
    lines += ['', '## Latency and memory', '',
              '| run | model step p50 (ms; runs one after another, not a speed comparison) | '
              'memory bytes after 2 / 10 frames |', '|---|---|---|']
    for name, ms in r.latency.items():
        mem = r.memory.get(name, {})
        lines.append(f'| {name} | {ms:.1f} | {mem.get(2, 0)} / {mem.get(10, 0)} |')
    return '\n'.join(lines) + '\n'


def _variant(run: str, checkpoints: list[str]) -> str:
    """The variant a run (or the first run of a difference) is, without its checkpoint and
    the tracker: 'real car ends' of 'suit, tracking, real car ends - suit, tracking'."""
    name = run.split(' - ')[0]
    for c in checkpoints:
        if name == c:
            return 'plain'
        if name.startswith(c + ', '):
            name = name[len(c) + 2:]
            break
    return name if name == 'tracking' else name.removeprefix('tracking, ')


def _left_out(r: Comparison, heldout: bool = False) -> list[str]:
    """A line naming the intervals that left out resamples in which their metric is undefined
    (none when every resample defined every metric): of the validation tables, or with
    ``heldout`` of the held-out sensor's."""
    from suit_ros.accuracy import left_out_counts
    counts = (left_out_counts(r.heldout) if heldout
              else {**left_out_counts(r.stats), **left_out_counts(r.diffs)})
    if not counts:
        return []
    # the runs that leave out the same, together (most runs share their drives' count): the
    # largest group last, by its size when it is large
    groups: dict[tuple[tuple[str, int], ...], list[str]] = {}
    for run, m in counts.items():
        groups.setdefault(tuple(m.items()), []).append(run)
    ordered = sorted(groups.items(), key=lambda g: len(g[1]))
    parts = []
    for i, (key, runs) in enumerate(ordered):
        what = ', '.join(f'{k} {n}' for k, n in key)
        diffs = sum(' - ' in run for run in runs)
        size = ' and '.join(f'{n} {kind}{"s" if n > 1 else ""}' for n, kind in (
            (len(runs) - diffs, 'run'), (diffs, 'difference')) if n)
        if len(runs) <= 6:
            who = ', '.join(f'`{run}`' for run in runs)      # (names hold commas)
        elif i == len(ordered) - 1 and len(ordered) > 1:
            who = f'the other {size}'
        else:                        # by the variants they are (the same drives)
            names = list(r.meta.get('checkpoints', {}))
            who = ', '.join(dict.fromkeys(_variant(run, names) for run in runs)) + f' ({size})'
        parts.append(f'{what}: {who}')
    return ['', f'Resamples in which a metric is undefined (their drives hold no object of a '
            f'class; for the car heading and velocity figures, the run matched no car, or no '
            f'two moving cars) are left out of its interval, which is then over the resamples '
            f'that define it; of {r.meta["resamples"]}: {"; ".join(parts)}.']


def _extra_sections(r: Comparison) -> list[str]:
    lines: list[str] = []
    if r.heldout:
        held = r.meta['heldout_drives']
        sensors = ', '.join(sorted({s for _, s in held}))
        lines += ['', f'## Held-out sensor ({sensors}, never in training; seeds '
                  f'{held[0][0]}+)', '']
        lines += _table(r.heldout, ['mAP', 'NDS', 'mAVE'] + [f'AP {c}' for c in r.class_names])
        lines += _left_out(r, heldout=True)
    if r.clutter:
        types = [t for t in next(iter(r.clutter.values())) if t != 'all']
        lines += ['', '## False positives on clutter (per frame, score >= 0.3, no GT within '
                  '2 m, centre within 0.5 m of the object)', '',
                  '| run | all | ' + ' | '.join(types) + ' |', '|---' * (len(types) + 2) + '|']
        for name, c in r.clutter.items():
            lines.append(f'| {name} | {c["all"]:.2f} | '
                         + ' | '.join(f'{c[t]:.3f}' for t in types) + ' |')
    if r.share:
        lines += ['', f"The fusion's past term at car centres (first 8 drives, "
                  f'{int(r.share["cells"])} cells): {100 * r.share["past share"]:.1f}% of the '
                  'norm of the current term W1 F_t (0% at the start of stage 2 by construction).']
    return lines


def write(result: Comparison, out: Path, title: str, command: str) -> str:
    """``OUT/results.json`` and ``OUT/results.md``; :return: the page."""
    from suit_ros.accuracy import left_out_counts, plain_intervals
    from suit_ros.outputs import json_text
    out.mkdir(parents=True, exist_ok=True)
    (out / 'results.json').write_text(json_text(
        {'meta': result.meta, 'runs': plain_intervals(result.stats),
         'differences': plain_intervals(result.diffs),
         'heldout_sensor': plain_intervals(result.heldout),
         # resamples without a class: left out of that metric's interval (absent: none)
         'resamples_left_out': {'runs': left_out_counts(result.stats),
                                'differences': left_out_counts(result.diffs),
                                'heldout_sensor': left_out_counts(result.heldout)},
         'latency_p50_ms': result.latency, 'memory_bytes': result.memory,
         'clutter_fp_per_frame': result.clutter,
         'past_share_at_car_centres': result.share}, indent=1), encoding='utf-8')
    text = render(result, title, command)
    (out / 'results.md').write_text(text, encoding='utf-8')
    return text


def read(path: Path) -> Comparison:
    """A comparison back from the ``results.json`` that :func:`write` wrote (to render its
    page again without the runs)."""
    import json

    from suit_ros.accuracy import Interval
    d = json.loads(Path(path).read_text(encoding='utf-8'))
    left = d.get('resamples_left_out', {})

    def intervals(key: str) -> dict[str, dict[str, Interval]]:
        counts = left.get(key, {})
        def interval(run: str, k: str, v: list[float | None]) -> Interval:
            value, low, high = (float('nan') if x is None else float(x) for x in v)
            return Interval(value, low, high, counts.get(run, {}).get(k, 0))
        return {run: {k: interval(run, k, v) for k, v in m.items()}
                for run, m in d.get(key, {}).items()}
    stats = intervals('runs')
    names = [k.removeprefix('AP ') for k in next(iter(stats.values()), {})
             if k.startswith('AP ')]
    return Comparison(stats, intervals('differences'), d.get('latency_p50_ms', {}),
                      {run: {int(n): b for n, b in m.items()}
                       for run, m in d.get('memory_bytes', {}).items()},
                      d['meta'], names, intervals('heldout_sensor'),
                      d.get('clutter_fp_per_frame', {}), d.get('past_share_at_car_centres', {}))


# ------------------------------------------------------------------ command line
def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Add ``compare`` options."""
    parser.add_argument('--run', nargs=2, action='append', default=[],
                        metavar=('NAME', 'CHECKPOINT'), help='a label and a checkpoint '
                        '(repeatable; the first is the reference of the paired differences)')
    parser.add_argument('--variant', action='append', default=[], choices=VARIANTS,
                        help='also run each checkpoint this way (repeatable)')
    parser.add_argument('--ablation', action='store_true',
                        help='the docs/results.md set: --run single SINGLE --run suit SUIT '
                             '(default: the shipped pair), every variant, the held-out sensor, '
                             'clutter and the past share')
    parser.add_argument('--drives', type=int, default=16)
    parser.add_argument('--heldout-drives', type=int, default=4)
    parser.add_argument('--frames', type=int, default=40)
    parser.add_argument('--resamples', type=int, default=100)
    parser.add_argument('--cache-dir', default='data_cache')
    parser.add_argument('--precision', default='float32',
                        choices=['auto', 'float32', 'bfloat16'])
    parser.add_argument('--threads', type=int, default=2, help='torch threads')
    parser.add_argument('--out', required=True, help='folder for results.md and results.json')


def run(args: argparse.Namespace) -> int:
    """Compare; print and write the page."""
    import torch

    from suit_ros.checkpoint import (
        default_checkpoint_path,
        resolve_checkpoint,
        shipped_checkpoints,
    )
    from suit_ros.errors import SuitRosError
    torch.set_num_threads(args.threads)
    checkpoints = [(n, p) for n, p in args.run]
    variants = list(dict.fromkeys(args.variant))
    if args.ablation:
        checkpoints = checkpoints or [('single', 'centerpoint_single'),
                                      ('suit', default_checkpoint_path().stem)]
        variants = list(VARIANTS)
    if not checkpoints:
        raise SuitRosError('give checkpoints to compare (--run NAME CHECKPOINT, repeatable) '
                           'or --ablation')
    if len({n for n, _ in checkpoints}) != len(checkpoints):
        raise SuitRosError('run names must differ')
    for _, path in checkpoints:
        if not resolve_checkpoint(path).is_file():
            raise SuitRosError(f'checkpoint {path} does not exist (a path, or a shipped one '
                               f'by name: {", ".join(shipped_checkpoints())})')
    from suit_ros.outputs import output_dir
    output_dir(args.out, '--out folder')      # before the runs, not after them
    try:
        result, runs, val = compare(checkpoints, variants, args.drives, args.frames,
                                    args.resamples, args.cache_dir, args.precision)
    except ValueError as exc:
        raise SuitRosError(str(exc)) from exc
    if args.ablation:
        extras(result, checkpoints, runs, val, args.heldout_drives, args.cache_dir)
    title = 'Results' if args.ablation else 'Checkpoint comparison'
    command = 'suit-ros compare ' + ('--ablation ' if args.ablation else '') + '...'
    print(write(result, Path(args.out), title, command))
    return 0
