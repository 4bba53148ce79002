"""``suit-ros eval``: nuScenes-style metrics for a bag with detections and GT, or for a model
on a synthetic split, nuScenes-format, KITTI-format or Argoverse 2 data."""
from __future__ import annotations

import argparse
from typing import Any

from suit_ros.errors import BagError, ConfigError, DatasetError


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Add ``eval`` options."""
    src = parser.add_mutually_exclusive_group(required=True)
    src.add_argument('--bag', help='a bag with detections and GT (e.g. detect-bag --copy-inputs)')
    src.add_argument('--synthetic', choices=['val', 'demo'],
                     help='run --checkpoint over a synthetic split')
    src.add_argument('--nuscenes', metavar='ROOT',
                     help='run --checkpoint over nuScenes-format data (tables + samples/sweeps)')
    src.add_argument('--kitti', metavar='ROOT',
                     help='run --checkpoint over KITTI-format data (velodyne/ label_2/ calib/, '
                     'or the tracking layout), scoring only the camera field of view')
    src.add_argument('--av2', metavar='ROOT',
                     help='run --checkpoint over Argoverse 2 sensor-dataset logs (the dataset '
                     'folder, a split folder or one log folder); parked bicycles and '
                     'motorcycles are neither objects nor false positives')
    parser.add_argument('--version', default='v1.0-mini', help='nuScenes table version')
    parser.add_argument('--sweeps', type=int, default=None,
                        help="sweeps per nuScenes keyframe input (default: the checkpoint's): "
                        'the keyframe and the sweeps before it')
    parser.add_argument('--image-width', type=float, default=1242.0,
                        help='KITTI camera image width (px) that bounds the scored view')
    parser.add_argument('--kitti-intensity-scale', type=float, default=1.0,
                        help='divide the .bin reflectance by this (1: KITTI, 0..1)')
    parser.add_argument('--kitti-ids', metavar='FILE',
                        help='evaluate only the frame (object) or sequence (tracking) ids listed '
                        'in FILE, one a line (e.g. ImageSets/val.txt); default: all')
    parser.add_argument('--det-topic', default='/detector/detections')
    parser.add_argument('--unanswered', choices=['skip', 'empty'], default='skip',
                        help='--bag: GT frames with no detections at their stamp (a live node '
                        'skipped or failed them): left out (skip, said on stderr) or scored as '
                        'frames with no box (empty: what a user of the output got)')
    parser.add_argument('--gt-topic', default='/gt/objects')
    parser.add_argument('--checkpoint', default='', help='default: the shipped checkpoint')
    parser.add_argument('--history', type=int, help='frames of history (default: all)')
    parser.add_argument('--tracker', action='store_true',
                        help='track the detections as the node does by default (velocities '
                        "filtered, scores smoothed: suit_ros/tracking.py); default: the model's "
                        'own output. On nuScenes keyframes (2 Hz) the tracks outlast a gap of '
                        "2.5 keyframes instead of the node's 0.5 s")
    parser.add_argument('--deskew', choices=['on', 'off'], default='on',
                        help="sweeps taken over time put back at their stamps, as the node's "
                        "`deskew` does (frames with their returns' times: synthetic sweeps of "
                        'real sensors)')
    from suit_ros.report import add_traffic_side_option
    add_traffic_side_option(parser)
    parser.add_argument('--run-every', type=int, default=1, metavar='K',
                        help='run the model on every K-th frame only, as a node too slow for '
                        'its sensor does (the skipped frames feed its sweeps, as the node '
                        'buffers them); only those frames are scored (default 1: every frame)')
    parser.add_argument('--cache-dir', default='data_cache')
    parser.add_argument('--json-out', help='write the metrics as JSON here')
    parser.add_argument('--plot', help='write precision-recall curves (PNG) here')
    parser.add_argument('--max-range', type=float, default=None, metavar='M',
                        help="score every class within M m (BEV); default: nuScenes' class "
                        'ranges (car, truck 50; pedestrian, cyclist 40), and 50 for every class '
                        'with --av2 and --kitti, as `suit-ros report` scores real data')


def _from_bag(args: argparse.Namespace) -> Any:
    from suit_ros.data.bag import POINTCLOUD2, check_topic, messages, open_reader
    from suit_ros.evaluate import evaluate
    from suit_ros.msg_adapters.detections import pointcloud2_to_detections
    from suit_ros.msg_adapters.odometry import stamp_to_ns
    from suit_ros.structures import Detections
    given = [flag for flag, on in (('--checkpoint', bool(args.checkpoint)),
                                   ('--tracker', args.tracker),
                                   ('--history', args.history is not None),
                                   ('--run-every', args.run_every != 1)) if on]
    if given:      # they would change nothing: the bag holds detections already made
        raise ConfigError(f'eval --bag scores the detections recorded in the bag; '
                          f'{", ".join(given)} do not apply there: give them to `suit-ros '
                          'detect-bag IN OUT --copy-inputs`, then evaluate OUT')
    found: dict[str, dict[int, Any]] = {args.det_topic: {}, args.gt_topic: {}}
    with open_reader(args.bag) as reader:
        for t in found:
            check_topic(reader, t, POINTCLOUD2, hint=f'{args.bag}: run `suit-ros detect-bag '
                        'IN OUT --copy-inputs` on a bag with GT')
        conns = [c for c in reader.connections if c.topic in found]
        for conn, _, raw in messages(reader, conns):
            msg = reader.deserialize(raw, conn.msgtype)
            found[conn.topic][stamp_to_ns(msg.header.stamp)] = pointcloud2_to_detections(msg)
    det, gt = found[args.det_topic], found[args.gt_topic]
    stamps = sorted(set(det) & set(gt))
    if not stamps:
        raise BagError(f'no frame of {args.bag} has both detections and GT at the same stamp')
    unanswered = sorted(set(gt) - set(det))
    if unanswered:        # clouds a live node skipped (busy) or failed: it published nothing
        import sys
        if args.unanswered == 'empty':
            stamps = sorted(gt)
            how = 'scored as frames with no box (--unanswered empty)'
        else:
            how = ('not scored: the figures are of the frames it answered; --unanswered empty '
                   'scores them as frames with no box')
        print(f'{len(unanswered)} of {len(gt)} GT frames have no detections at their stamp on '
              f'{args.det_topic} (the detector skipped or failed them): {how}', file=sys.stderr)

    def d_or_empty(x: dict[str, Any] | None) -> Detections:
        return Detections.empty() if x is None else d(x)

    def d(x: dict[str, Any]) -> Detections:
        return Detections(x['boxes'], x['velocities'], x['scores'], x['labels'])
    return evaluate([d(gt[s]) for s in stamps], [d_or_empty(det.get(s)) for s in stamps],
                    ranges=_ranges(args, None),
                    num_points=[gt[s].get('num_points') for s in stamps])


def _ranges(args: argparse.Namespace, class_names: Any) -> dict[str, float] | None:
    """The scored range per class (None: nuScenes' class ranges)."""
    from suit_ros import CLASS_NAMES
    names = tuple(class_names or CLASS_NAMES)
    if args.max_range is not None:
        return dict.fromkeys(names, float(args.max_range))
    if args.av2 or args.kitti:           # the real-data report's rule: 50 m, every class
        return dict.fromkeys(names, 50.0)
    return None


def _from_kitti(args: argparse.Namespace) -> Any:
    from suit_ros.checkpoint import default_checkpoint_path, load_checkpoint
    from suit_ros.data.kitti import camera_fov_run
    from suit_ros.data.sequences import kitti_sequences
    from suit_ros.evaluate import run_model
    filt = _tracker(args)
    model, _, _ = load_checkpoint(args.checkpoint or default_checkpoint_path())
    ids = None
    if args.kitti_ids:
        try:
            with open(args.kitti_ids, encoding='utf-8') as f:
                ids = [line.strip() for line in f if line.strip()]
        except OSError as exc:
            raise DatasetError(f'cannot read --kitti-ids {args.kitti_ids}: {exc}') from exc
    seqs = kitti_sequences(args.kitti, args.kitti_intensity_scale, ids=ids)
    from suit_ros.report import traffic_sides
    run = camera_fov_run(run_model(model, seqs, history=args.history, tracker=filt,
                                   traffic_side=traffic_sides(args.traffic_side, len(seqs),
                                                              None, filt is not None
                                                              and args.history is None)),
                         seqs, args.image_width)
    result = run.evaluate(model.cfg.class_names, _ranges(args, model.cfg.class_names))
    result.extra['scored_region'] = f'camera field of view ({args.image_width:g} px)'
    return result


def _tracker(args: argparse.Namespace) -> Any:
    from suit_ros.tracking import TrackerConfig
    if args.tracker and args.history is not None:
        raise ConfigError('--tracker needs the whole history (tracks over frames); '
                           'drop --history')
    return TrackerConfig() if args.tracker else None


def synthetic_sequences(which: str, cache_dir: str) -> list[Any]:
    """``val``: the fixed validation set of docs/results.md (``val`` seeds 9000..9015, four
    sensor models); ``demo``: the demo drive."""
    from suit_ros.data.sequences import (
        SPLIT_SEEDS,
        VAL_SEQUENCES,
        synthetic_sequence,
        synthetic_split,
    )
    if which == 'val':
        return synthetic_split('val', VAL_SEQUENCES, 40, cache_dir)
    return [synthetic_sequence('demo-real', SPLIT_SEEDS['demo'], 100, cache_dir)]


def run(args: argparse.Namespace) -> int:
    """Evaluate and report."""
    if args.run_every < 1:
        raise ConfigError(f'--run-every must be at least 1, got {args.run_every}')
    if args.sweeps is not None and args.sweeps < 1:
        raise ConfigError(f'--sweeps must be at least 1, got {args.sweeps}')
    if args.history is not None and args.history < 1:
        raise ConfigError(f'--history must be at least 1 frame, got {args.history}')
    if args.max_range is not None and not 0.0 < args.max_range < float('inf'):
        raise ConfigError(f'--max-range must be a positive number of metres, got '
                          f'{args.max_range}')
    from suit_ros.outputs import output_file
    for option, path in (('--json-out', args.json_out), ('--plot', args.plot)):
        if path:                    # checked before the run, not after it
            output_file(path, f'{option} file')
    if args.run_every != 1 and (args.bag or args.kitti or args.nuscenes
                                or args.history is not None):
        # nuScenes keyframes come with their sweeps accumulated: nothing to buffer
        raise ConfigError('--run-every applies to a model run over drives of single sweeps '
                          '(--synthetic, --av2), without --history')
    if args.unanswered != 'skip' and not args.bag:
        raise ConfigError('--unanswered applies to --bag (frames a recorded detector did not '
                          'answer); a model run here answers every frame')
    if args.bag and args.traffic_side != 'auto':
        # the bag's detections were made by detect-bag (or the node): the side was theirs
        raise ConfigError('--traffic-side applies where eval runs the model; a bag holds '
                          'detections already made: give it to detect-bag --traffic-side')
    if args.bag:
        result = _from_bag(args)
    elif args.kitti:
        result = _from_kitti(args)
    else:
        from suit_ros.checkpoint import default_checkpoint_path, load_checkpoint
        from suit_ros.evaluate import run_model
        filt = _tracker(args)
        model, _, _ = load_checkpoint(args.checkpoint or default_checkpoint_path())
        seqs: Any
        own_sides = None
        if args.nuscenes:
            from suit_ros.data.sequences import nuscenes_scenes
            seqs, own_sides = nuscenes_scenes(
                args.nuscenes, args.version,
                model.cfg.sweeps if args.sweeps is None else args.sweeps)
        elif args.av2:
            from suit_ros.data.av2 import av2_sequences
            seqs = av2_sequences(args.av2, model.cfg.class_names)
        else:
            seqs = synthetic_sequences(args.synthetic, args.cache_dir)
        if not seqs or not seqs[0]:
            raise DatasetError('no frame to evaluate: ' + (
                f'{args.nuscenes} holds no nuScenes sample' if args.nuscenes else
                f'{args.av2} holds no Argoverse 2 sweep' if args.av2 else
                'the synthetic split is empty'))
        if filt is not None and args.nuscenes:
            from suit_ros.evaluate import tracker_for
            filt = tracker_for(seqs, filt)          # keyframes 0.5 s apart: see tracker_for
        from suit_ros.report import traffic_sides
        result = run_model(model, seqs, history=args.history, tracker=filt,
                           deskew=args.deskew == 'on', run_every=args.run_every,
                           traffic_side=traffic_sides(args.traffic_side, len(seqs), own_sides,
                                                      filt is not None and args.history is None)
                           ).evaluate(model.cfg.class_names,
                                      _ranges(args, model.cfg.class_names))
    print(result.table())
    if args.json_out:
        from suit_ros.evaluate import dump_json
        dump_json(result, args.json_out)
    if args.plot:
        result.plot_pr(args.plot)
    return 0
