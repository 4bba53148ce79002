"""``suit-ros train``: train the detector (single-frame pretraining or SUIT fine-tuning).

AdamW with a one-cycle schedule (weight decay 0.01, momentum cycled 0.85-0.95, as the paper)
that follows the larger of the step and the wall-time progress when ``max_minutes`` is set (so a
time-budgeted run on a shared machine still anneals to the end),
gradient clipping, clips of mixed length (memory passed frame to frame), clip-consistent
augmentation, CSV log, resume, and torch.distributed when launched by ``torchrun``.
"""
from __future__ import annotations

import argparse
import csv
from dataclasses import dataclass, replace
import math
import os
from pathlib import Path
import time
import typing
from typing import Any, Literal

import numpy as np
import yaml

from suit_ros.errors import ConfigError
from suit_ros.structures import Frame

if typing.TYPE_CHECKING:
    from suit_ros.ground import LocalGround


@dataclass(frozen=True)
class TrainConfig:
    """A training run (``params/train_*.yaml``)."""

    model_config: str = 'params/model_cpu.yaml'
    dataset: str = 'synthetic'       # synthetic | bags | nuscenes | kitti | av2
    dataset_paths: tuple[str, ...] = ()   # bags, or the nuScenes / KITTI root (first entry)
    nuscenes_version: str = 'v1.0-mini'
    temporal: Literal['', 'none', 'dense', 'sparse', 'sparse_velocity', 'suit'] = ''
    # '' keeps the model config's temporal mode
    init_from: str = ''              # stage 2: initialise shared weights from this checkpoint
    train_sequences: int = 16
    train_first_sequence: int = 0    # drive number of the first training drive (a fresh window)
    train_frames: int = 60
    val_sequences: int = 4
    val_frames: int = 40
    cache_dir: str = 'data_cache'
    batch_size: int = 2
    clip_lengths: tuple[int, ...] = (2, 3, 4)
    lr: float = 2e-3
    weight_decay: float = 0.01
    grad_clip: float = 35.0
    steps: int = 1000
    max_minutes: float = 0.0         # 0: no time limit
    seed: int = 0
    augment: bool = True
    temporal_lr_scale: float = 1.0   # lr multiplier of the temporal modules (fusion, GeoNet)
    flip_probability: float = 0.0    # 0: keep the front/back cue of box-shaped actors
    intensity_dropout: float = 0.2   # clips trained without intensity
    tilt_deg: float = 0.0            # ground tilt: roll and pitch std (deg) per clip
    lift_m: float = 0.0              # ground height offset, uniform +-lift_m per clip
    point_dropout: float = 0.0       # half the clips lose up to this fraction of points
    overhead_probability: float = 0.0   # clips with canopies/awnings over objects (overhead)
    # clips with screens standing between the sensor and some objects (suit_ros/data/occluders)
    occluder_probability: float = 0.0
    # the input's height reference in training (suit_ros/ground.py; '' keeps the model
    # config's pillars.ground): local levels every frame's points to their ground and lowers
    # its GT boxes by it, as ``ground: local`` shows the model its input at inference; the
    # checkpoint records it (pillars.ground), so the node runs it so by default
    ground: Literal['', 'as_given', 'local'] = ''
    # sweeps taken over time (frames with their returns' times: synthetic sweeps of real
    # sensors, bags with a time field) deskewed as the node does (suit_ros/deskew.py); the
    # shipped checkpoints were trained on them as taken
    deskew: bool = False
    preset: str = ''                 # synthetic world of the training drives ('': train-real)
    # the same drives again in further worlds, trained on alongside (each adds train_sequences
    # drives): a world change learned without dropping the drives the model already knows
    more_presets: tuple[str, ...] = ()
    freeze: tuple[str, ...] = ()     # modules kept as loaded (pillars, backbone, fusion, ...)
    outage_probability: float = 0.0  # clips with a sensor sector lost (ClipSampler)
    outage_width_deg: tuple[float, float] = (60.0, 180.0)
    distill_weight: float = 0.0      # ordinary frames kept near the starting model (distill)
    frozen_batchnorm: bool = False   # every batch norm keeps its statistics (small batches)
    carry_gt: bool = False           # GT keeps objects seen earlier in the clip (ClipSampler)
    # clips with passing occluders hiding well-seen objects 0.3-0.7 s (ClipSampler; no draw at 0)
    passing_probability: float = 0.0
    occlusion_weight: float = 0.0    # clips drawn by 1 + weight * occluded objects (ClipSampler)
    # clips cut as a drive starts: no sweep before the clip's first frame (ClipSampler)
    fresh_start_probability: float = 0.0
    eval_at_end: bool = True
    checkpoint_every: int = 200


def load_train_config(path: str | os.PathLike[str]) -> TrainConfig:
    """Load a training YAML strictly."""
    from suit_ros.config import dataclass_from_dict
    try:
        with open(path, encoding='utf-8') as f:
            data = yaml.safe_load(f) or {}
    except FileNotFoundError as exc:
        raise ConfigError(f'training config {path} does not exist') from exc
    except OSError as exc:
        raise ConfigError(f'cannot read the training config {path}: '
                          f'{exc.strerror or exc}') from exc
    except yaml.YAMLError as exc:
        raise ConfigError(f'training config {path} is not valid YAML: {exc}') from exc
    tc = typing.cast(TrainConfig, dataclass_from_dict(TrainConfig, data, os.fspath(path)))
    check_budget(tc, os.fspath(path))
    for name in ('batch_size', 'checkpoint_every'):
        if getattr(tc, name) < 1:
            raise ConfigError(f'{path}: {name} must be at least 1, not {getattr(tc, name)}')
    if not tc.clip_lengths or min(tc.clip_lengths) < 1:
        raise ConfigError(f'{path}: clip_lengths must list one or more clip lengths of 1 frame '
                          f'or more, not {list(tc.clip_lengths)}')
    if tc.train_sequences < 1 or tc.train_first_sequence < 0:
        raise ConfigError(f'{path}: train_sequences must be >= 1 and train_first_sequence >= 0, '
                          f'not {tc.train_sequences} and {tc.train_first_sequence}')
    unknown = set(tc.freeze) - set(FREEZABLE)
    if unknown:
        raise ConfigError(f'{path}: freeze names modules {sorted(unknown)}; choose from '
                          f'{", ".join(FREEZABLE)}')
    for name in ('overhead_probability', 'occluder_probability', 'passing_probability',
                 'fresh_start_probability'):
        if not 0.0 <= getattr(tc, name) <= 1.0:
            raise ConfigError(f'{path}: {name} must be in [0, 1], not {getattr(tc, name)}')
    if not tc.augment and (tc.overhead_probability > 0 or tc.occluder_probability > 0):
        raise ConfigError(f'{path}: overhead_probability and occluder_probability draw into '
                          'augmented clips; with augment: false set them to 0')
    if tc.passing_probability > 0 and max(tc.clip_lengths) < 5:
        raise ConfigError(f'{path}: passing_probability needs clips of 5 frames or more '
                          f'(clip_lengths {list(tc.clip_lengths)}): 3-7 hidden frames after one '
                          'seen')
    if tc.occluder_probability > 0 and tc.carry_gt:
        raise ConfigError(f'{path}: occluder_probability and carry_gt cannot be combined (a '
                          'screen may hide an object that carry_gt would keep)')
    from suit_ros.data.sim.config import PRESETS
    unknown_worlds = [p for p in (tc.preset, *tc.more_presets) if p and p not in PRESETS]
    if unknown_worlds:
        raise ConfigError(f'{path}: unknown synthetic world(s) {unknown_worlds}; choose from '
                          f'{", ".join(sorted(PRESETS))}')
    if tc.more_presets and tc.dataset != 'synthetic':
        raise ConfigError(f'{path}: more_presets are synthetic worlds; dataset is {tc.dataset}')
    if not tc.occlusion_weight >= 0:
        raise ConfigError(f'{path}: occlusion_weight must be >= 0, not {tc.occlusion_weight}')
    if not 0.0 <= tc.outage_probability <= 1.0 or tc.distill_weight < 0:
        raise ConfigError(f'{path}: outage_probability must be in [0, 1] and distill_weight '
                          f'>= 0, not {tc.outage_probability} and {tc.distill_weight}')
    return tc


def check_budget(tc: TrainConfig, where: str) -> None:
    """``steps`` at least 1 and ``max_minutes`` not negative (from the file or the flags).

    :raises ConfigError: naming ``where`` (the file, or the flags)."""
    if tc.steps < 1:
        raise ConfigError(f'{where}: steps must be at least 1, not {tc.steps}')
    if not tc.max_minutes >= 0:
        raise ConfigError(f'{where}: max_minutes must be >= 0 (0 or none: no time limit), '
                          f'not {tc.max_minutes}')


FREEZABLE = ('pillars', 'backbone', 'fusion', 'fusion.current', 'fusion.past', 'geonet',
             'head')


def freeze(module: Any, names: tuple[str, ...]) -> list[Any]:
    """Stop the gradients of the named submodules (dotted: ``fusion.current`` is the fusion's
    current-frame conv W1); :return: those modules (kept in eval mode while training, so
    batch-norm statistics stay)."""
    frozen = []
    for n in names:
        try:
            frozen.append(module.get_submodule(n))
        except AttributeError:       # a module this temporal mode lacks
            continue
    for m in frozen:
        m.requires_grad_(False)
    return frozen


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Add ``train`` options."""
    parser.add_argument('--config', required=True, help='training YAML (params/train_*.yaml)')
    parser.add_argument('--out', required=True, help='output directory')
    parser.add_argument('--steps', type=int, help='override the number of steps')
    parser.add_argument('--max-minutes', type=float, help='stop after this wall time')
    parser.add_argument('--temporal', choices=['none', 'dense', 'sparse', 'sparse_velocity',
                                               'suit'], help='override the temporal mode')
    parser.add_argument('--init-from', help='initialise shared weights from a checkpoint')
    parser.add_argument('--resume', action='store_true', help='resume from OUT/last.pt')
    parser.add_argument('--seed', type=int)
    parser.add_argument('--device', default='auto', choices=['auto', 'cpu', 'cuda'])
    parser.add_argument('--threads', type=int, default=0, help='torch threads (0: default)')


def one_cycle(progress: float, max_lr: float, pct_start: float = 0.3, div: float = 10.0,
              final_div: float = 100.0) -> tuple[float, float]:
    """Learning rate and Adam beta1 at ``progress`` in [0, 1]: cosine warm-up from
    ``max_lr / div`` to ``max_lr`` over ``pct_start``, then cosine annealing to
    ``max_lr / (div * final_div)``; beta1 goes 0.95 -> 0.85 -> 0.95 (torch's OneCycleLR)."""
    p = min(max(progress, 0.0), 1.0)

    def cos(a: float, b: float, t: float) -> float:
        return b + (a - b) * (1.0 + math.cos(math.pi * t)) / 2.0
    if p < pct_start:
        t = p / pct_start
        return cos(max_lr / div, max_lr, t), cos(0.95, 0.85, t)
    t = (p - pct_start) / (1.0 - pct_start)
    return cos(max_lr, max_lr / (div * final_div), t), cos(0.85, 0.95, t)


def _dist_info() -> tuple[int, int]:
    return int(os.environ.get('RANK', '0')), int(os.environ.get('WORLD_SIZE', '1'))


def run(args: argparse.Namespace) -> int:
    """Train; write ``model.safetensors``, ``last.pt`` and ``log.csv`` under ``--out``."""
    tc = load_train_config(args.config)
    overrides: dict[str, Any] = {}
    for key in ('steps', 'max_minutes', 'temporal', 'init_from', 'seed'):
        value = getattr(args, key, None)
        if value is not None:
            overrides[key] = value
    tc = replace(tc, **overrides)
    check_budget(tc, f'{args.config} with the flags')
    from suit_ros.outputs import output_dir
    train(tc, output_dir(args.out, '--out folder'), device=args.device, threads=args.threads,
          resume=args.resume)
    return 0


def training_sequences(tc: TrainConfig, class_names: tuple[str, ...], sweeps: int = 3) -> Any:
    """The training data a config names (sequences of sensor frames; KITTI and Argoverse 2 are
    read lazily, a real split does not fit in memory); ``sweeps``: the model's (a nuScenes
    keyframe comes with the earlier sweeps it takes)."""
    from suit_ros.data.sequences import synthetic_split
    data: Any
    if tc.dataset == 'synthetic':
        data = synthetic_split('train', tc.train_sequences, tc.train_frames, tc.cache_dir,
                               preset_name=tc.preset or None,
                               points_dtype=np.float16,     # half the RAM; inputs are float32
                               first=tc.train_first_sequence)
        for name in tc.more_presets:
            data += synthetic_split('train', tc.train_sequences, tc.train_frames, tc.cache_dir,
                                    preset_name=name, points_dtype=np.float16,
                                    first=tc.train_first_sequence)
        if tc.deskew:
            from suit_ros.evaluate import deskewed
            data = [[replace(f, points=f.points.astype(np.float16)) for f in deskewed(seq)]
                    for seq in data]
    elif tc.dataset == 'bags':
        from suit_ros.data.sequences import bag_sequences
        data = bag_sequences(tc.dataset_paths, sweeps, tc.deskew)
    elif tc.dataset == 'nuscenes':
        from suit_ros.data.sequences import nuscenes_sequences
        if not tc.dataset_paths:
            raise ConfigError('dataset nuscenes needs dataset_paths: [ROOT]')
        data = nuscenes_sequences(tc.dataset_paths[0], tc.nuscenes_version, sweeps)
    elif tc.dataset == 'kitti':
        from suit_ros.data.sequences import kitti_sequences
        if not tc.dataset_paths:
            raise ConfigError('dataset kitti needs dataset_paths: [ROOT]')
        # read lazily (a KITTI split does not fit in memory); ClipSampler takes any Sequence
        data = kitti_sequences(
            tc.dataset_paths[0], fov_points_only=True)
    elif tc.dataset == 'av2':
        from suit_ros.data.av2 import av2_sequences
        if not tc.dataset_paths:
            raise ConfigError('dataset av2 needs dataset_paths: [ROOT]')
        data = av2_sequences(
            tc.dataset_paths[0], class_names)
    else:
        raise ConfigError('dataset must be synthetic, bags, nuscenes, kitti or av2, not '
                          f'{tc.dataset!r}')
    return data


class _LossLog:
    """``log.csv``: one row per step. A resumed run keeps the rows up to the step it resumes
    from (rows written after its last snapshot, and a row cut short by a kill, are dropped:
    those steps run again); a new run starts the file afresh."""

    HEADER = ['step', 'time_s', 'lr', 'loss', 'hm_loss', 'loc_loss', 'geo_loss',
              'distill_loss']

    def __init__(self, path: Path, resumed_step: int | None = None) -> None:
        kept: list[list[str]] = []
        if resumed_step is not None and path.is_file():
            with open(path, newline='', encoding='utf-8') as f:
                for row in list(csv.reader(f))[1:]:
                    if len(row) == len(self.HEADER) and row[0].isdigit() \
                            and int(row[0]) <= resumed_step:
                        kept.append(row)
        self.file = open(path, 'w', newline='', encoding='utf-8')
        self.writer = csv.writer(self.file)
        self.writer.writerow(self.HEADER)
        self.writer.writerows(kept)

    def row(self, step: int, time_s: float, lr: float, vals: dict[str, float]) -> None:
        """Log one step."""
        self.writer.writerow([step, round(time_s, 2), lr, vals['loss'], vals['hm_loss'],
                              vals['loc_loss'], vals['geo_loss'], vals['distill_loss']])

    def flush(self) -> None:
        """Write what is buffered."""
        self.file.flush()

    def close(self) -> None:
        """Close the file."""
        self.file.close()


def _schedule(opt: Any, progress: float, max_lr: float) -> float:
    """Set the one-cycle learning rate and momentum for ``progress``; :return: the lr."""
    lr, beta1 = one_cycle(progress, max_lr)
    for group in opt.param_groups:
        group['lr'] = lr * group['lr_scale']
        group['betas'] = (beta1, group['betas'][1])
    return lr


def agreed(progress: float, world: int, device: Any = None) -> float:
    """The furthest ``progress`` over the ranks of a distributed run (``progress`` itself in
    one process). Each rank reads its own clock: with a time budget one rank would end a step
    before the others (which then wait in their next gradient exchange for good), and each
    would set its own learning rate (the ranks' weights would drift apart)."""
    if world <= 1:
        return progress
    import torch
    import torch.distributed as dist
    t = torch.tensor([progress], dtype=torch.float64, device=device)
    dist.all_reduce(t, op=dist.ReduceOp.MAX)
    return float(t.item())


def _device(device: str, threads: int, rank: int, world: int) -> Any:
    """The torch device of this process (joining the process group when distributed)."""
    import torch
    if world > 1:
        import torch.distributed as dist
        dist.init_process_group('nccl' if device == 'cuda' else 'gloo')
    if threads:
        torch.set_num_threads(threads)
    dev = torch.device('cuda' if device == 'cuda' or (device == 'auto'
                                                     and torch.cuda.is_available()) else 'cpu')
    if dev.type == 'cuda' and world > 1:
        dev = torch.device('cuda', rank % torch.cuda.device_count())
    return dev


def _optimizer(module: Any, tc: TrainConfig) -> Any:
    """AdamW with the temporal modules (fusion, GeoNet) in their own group at
    ``temporal_lr_scale`` x the learning rate."""
    import torch
    temporal = [p for n, p in module.named_parameters() if n.startswith(('fusion.', 'geonet.'))]
    ids = {id(p) for p in temporal}
    groups = [{'params': [p for p in module.parameters() if id(p) not in ids], 'lr_scale': 1.0}]
    if temporal:
        groups.append({'params': temporal, 'lr_scale': tc.temporal_lr_scale})
    return torch.optim.AdamW(groups, lr=tc.lr, weight_decay=tc.weight_decay, betas=(0.95, 0.99))


def _augmented(clips: list[list[Frame]], tc: TrainConfig, rng: np.random.Generator,
               ground: LocalGround | None = None) -> list[list[Frame]]:
    """A batch's clips augmented as the config asks, then leveled with ``ground``."""
    if tc.augment:
        from suit_ros.data import augment
        clips = [augment.apply_clip(_overhead(_occluded(c, tc, rng), tc, rng), _draw(tc, rng))
                 for c in clips]
    if ground is not None:
        from suit_ros.ground import leveled_frame
        clips = [[leveled_frame(f, ground) for f in c] for c in clips]
    return clips


def _overhead(clip: list[Frame], tc: TrainConfig, rng: np.random.Generator) -> list[Frame]:
    """The clip with overhead slabs in ``overhead_probability`` of the clips (no draw at 0,
    so older recipes replay the same augmentations)."""
    if tc.overhead_probability <= 0 or rng.random() >= tc.overhead_probability:
        return clip
    from suit_ros.data.overhead import with_overhead
    return with_overhead(clip, rng)


def _occluded(clip: list[Frame], tc: TrainConfig, rng: np.random.Generator) -> list[Frame]:
    """The clip with screens before some objects in ``occluder_probability`` of the clips (no
    draw at 0, so older recipes replay the same augmentations); an object a screen hides
    entirely loses its label, as one without returns has none."""
    if tc.occluder_probability <= 0 or rng.random() >= tc.occluder_probability:
        return clip
    from suit_ros.data.occluders import with_screens
    from suit_ros.data.sequences import training_view
    return [training_view(f) for f in with_screens(clip, rng)]


def _draw(tc: TrainConfig, rng: np.random.Generator) -> Any:
    """One clip's augmentation as the config asks."""
    from suit_ros.data import augment
    return augment.draw(rng, flip_probability=tc.flip_probability,
                        intensity_dropout=tc.intensity_dropout, tilt_deg=tc.tilt_deg,
                        lift_m=tc.lift_m, point_dropout=tc.point_dropout)


def _optimise(model: Any, module: Any, opt: Any, clips: Any, grad_clip: float,
              lost: Any = None, distiller: Any = None) -> dict[str, float]:
    """One optimisation step; :return: the losses."""
    import torch
    losses = model(clips, lost, distiller)
    opt.zero_grad(set_to_none=True)
    losses['loss'].backward()
    torch.nn.utils.clip_grad_norm_(module.parameters(), grad_clip)
    opt.step()
    return {k: float(v.detach()) for k, v in losses.items()}


# what a resumed run may change: its budget (to train on longer), where it started from (the
# weights come from last.pt), how often it saves, whether it evaluates at the end
RESUMABLE_CHANGES = ('steps', 'max_minutes', 'init_from', 'checkpoint_every', 'eval_at_end')


def _differences(before: dict[str, Any], now: dict[str, Any], prefix: str = '') -> list[str]:
    """The settings (dotted) whose values differ, over the keys both have: a setting a later
    release added is no difference (a run saved before it resumes)."""
    out: list[str] = []
    for k in sorted(set(before) & set(now)):
        a, b = before[k], now[k]
        if isinstance(a, dict) and isinstance(b, dict):
            out += _differences(a, b, f'{prefix}{k}.')
        elif a != b:
            out.append(f'{prefix}{k}')
    return out


def carry_span_warning(data: list[list[Frame]], lengths: list[int], carry_s: float,
                       tc: TrainConfig) -> str:
    """Why the clips ask the carry for more than it keeps ('' when they do not): with
    ``carry_gt`` or outages drawn in (lasting to a clip's end), a clip spanning longer than
    ``carry_s`` (its frames' median gap times its length) keeps GT of objects the memory
    has let go, and the loss teaches the carry head to invent them (2 Hz labelled frames:
    bags, nuScenes keyframes)."""
    if not carry_s or not (tc.carry_gt or tc.outage_probability > 0):
        return ''
    gaps = [b.stamp_ns - a.stamp_ns for seq in data for a, b in zip(seq, seq[1:])]
    if not gaps:
        return ''
    gap_s = float(np.median(gaps)) / 1e9
    span = (max(lengths) - 1) * gap_s
    if span <= carry_s:
        return ''
    return (f'clips of {max(lengths)} frames {gap_s:.2f} s apart span {span:.2f} s, longer '
            f'than the carry ({carry_s:g} s, sampling.carry_s): with carry_gt or outages the '
            'loss asks for objects the memory has already let go; raise sampling.carry_s or '
            'shorten clip_lengths')


def _model_differences(before: dict[str, Any], now: dict[str, Any], source: str) -> list[str]:
    """:func:`_differences` of two model configs, a run saved before a setting was renamed
    read as it is named now (``sampling.carry_frames`` as ``carry_s``)."""
    from suit_ros.config import carry_in_seconds
    return _differences(carry_in_seconds(before, source), now)


def _config_dict(tc: TrainConfig) -> dict[str, Any]:
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in tc.__dict__.items()}


def _resume(last: Path, module: Any, opt: Any, tc: TrainConfig, mcfg: Any
            ) -> tuple[int, float, dict[str, Any]]:
    """Load a run's ``last.pt`` (weights only, no pickled code); :return: its step, the
    wall time it had used, and the states of its data and augmentation generators (empty for
    a run saved before they were kept).

    :raises ConfigError: the file cannot be read, or the run was made with another model or
        training config than ``tc`` (but for :data:`RESUMABLE_CHANGES`)."""
    import torch
    try:
        state = torch.load(last, map_location='cpu', weights_only=True)
    except Exception as exc:  # torch raises several types for truncated or foreign files
        raise ConfigError(f'cannot resume from {last}: {type(exc).__name__}: {exc}; the file '
                          'may be truncated (a run killed while saving it before this '
                          'release): train into a new --out, init_from its '
                          'snapshot.safetensors') from exc
    needed = ('model', 'optimizer', 'step', 'torch_rng')
    if not isinstance(state, dict) or any(k not in state for k in needed):
        raise ConfigError(f'cannot resume from {last}: it holds '
                          + (f'a {type(state).__name__}' if not isinstance(state, dict) else
                             f'no {", ".join(k for k in needed if k not in state)}')
                          + ", not a suit-ros training run's state; train into a new --out")
    before = state.get('model_config')
    diff = [] if before is None else _model_differences(before, mcfg.to_dict(), str(last))
    if diff:
        raise ConfigError(f'{last} was trained with another model config ({", ".join(diff)} '
                          "differ): resume with the run's own, or train into a new --out")
    before_tc = state.get('train_config')
    if before_tc is not None:
        now = _config_dict(tc)
        diff = _differences({k: v for k, v in before_tc.items()
                             if k not in RESUMABLE_CHANGES}, now)
        if diff:
            raise ConfigError(
                f'{last} was trained with other settings: '
                + '; '.join(f'{k} {before_tc.get(k)!r} -> {now.get(k)!r}' for k in diff)
                + f'. A resumed run may change only {", ".join(RESUMABLE_CHANGES)}; '
                'train into a new --out (init_from its model) to change the rest')
    module.load_state_dict(state['model'])
    opt.load_state_dict(state['optimizer'])
    torch.set_rng_state(state['torch_rng'])
    step = int(state['step'])
    print(f'[train] resumed from {last} at step {step}')
    return step, float(state.get('elapsed_s', 0.0)), dict(state.get('generators', {}))


def _snapshot(out: Path, module: Any, opt: Any, mcfg: Any, tc: TrainConfig, step: int,
              elapsed_s: float, generators: dict[str, Any]) -> None:
    """``last.pt`` (to resume; with the configs it was made with, and ``generators``: the
    states of the numpy generators that draw the clips and their augmentation, so that a
    resumed run draws what the run would have drawn) and
    ``snapshot.safetensors`` (to evaluate mid-run), each replaced whole (a kill or a power
    loss while saving leaves the previous one)."""
    import torch

    from suit_ros.checkpoint import save_checkpoint
    from suit_ros.outputs import durable_replace
    tmp = out / 'last.pt.tmp'
    torch.save({'model': module.state_dict(), 'optimizer': opt.state_dict(), 'step': step,
                'elapsed_s': elapsed_s, 'torch_rng': torch.get_rng_state(),
                'generators': generators,
                'model_config': mcfg.to_dict(), 'train_config': _config_dict(tc)}, tmp)
    durable_replace(tmp, out / 'last.pt')
    save_checkpoint(out / 'snapshot.safetensors', module, mcfg, {'steps': step},
                    {'snapshot': True})


def _finish(tc: TrainConfig, out: Path, module: Any, mcfg: Any, dev: Any, step: int,
            elapsed: float, rank: int, world: int) -> dict[str, Any]:
    """The run's metrics; rank 0 writes the model (and evaluates it when asked)."""
    if tc.max_minutes and step < tc.steps:
        print(f'[train] time budget reached at step {step}')
    metrics: dict[str, Any] = {'steps': step, 'train_minutes': round(elapsed / 60, 2),
                               'device': str(dev), 'world_size': world}
    if rank == 0:
        _write_model(tc, out, module, mcfg, metrics, dev)
        print(f'[train] wrote {out / "model.safetensors"} ({elapsed / 60:.1f} min)')
    return metrics


def _write_model(tc: TrainConfig, out: Path, module: Any, mcfg: Any, metrics: dict[str, Any],
                 dev: Any) -> None:
    """``model.safetensors``, before the end-of-run evaluation too (a failing evaluation
    cannot lose the model), then with its figures."""
    from suit_ros.checkpoint import save_checkpoint
    from suit_ros.data.sequences import synthetic_split
    extra = {'train_config': _config_dict(tc)}
    save_checkpoint(out / 'model.safetensors', module, mcfg, metrics, extra)
    if tc.eval_at_end:
        from suit_ros.evaluate import evaluate_model
        val = synthetic_split('val', tc.val_sequences, tc.val_frames, tc.cache_dir)
        result = evaluate_model(module, val, dev)
        metrics.update(result.summary())
        print(result.table())
        save_checkpoint(out / 'model.safetensors', module, mcfg, metrics, extra)


def _distiller(tc: TrainConfig, module: Any, dev: Any) -> Any:
    """The frozen teacher of :mod:`suit_ros.model.distill` (None: no distillation)."""
    if tc.distill_weight <= 0:
        return None
    from suit_ros.model.distill import Distiller
    return Distiller(module.head, module.fusion.current if module.fusion else None,
                     tc.distill_weight).to(dev)


def _train_mode(model: Any, module: Any, frozen: list[Any], frozen_batchnorm: bool) -> None:
    """Training mode, except the frozen modules (and every batch norm when asked)."""
    import torch
    model.train()
    for m in frozen:
        m.eval()
    if frozen_batchnorm:
        for m in module.modules():
            if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
                m.eval()


def train(tc: TrainConfig, out: Path, device: str = 'auto', threads: int = 0,
          resume: bool = False) -> dict[str, Any]:
    """Run one training stage; return the final metrics."""
    import torch
    from tqdm import tqdm  # type: ignore[import-untyped]

    from suit_ros.checkpoint import load_weights_into
    from suit_ros.config import load_model_config
    from suit_ros.data.sequences import ClipSampler
    from suit_ros.model.detector import SUITDetector

    rank, world = _dist_info()
    if not resume and (out / 'last.pt').is_file():
        raise ConfigError(f'{out} holds a training run (last.pt): --resume to go on with it, or '
                          'give a new --out (a new run there would overwrite its snapshot and '
                          'its log)')
    if not (out / 'last.pt').is_file():     # a finished run (its last.pt removed) or a copy
        made = [n for n in ('model.safetensors', 'snapshot.safetensors') if (out / n).is_file()]
        if made:
            raise ConfigError(f'{out} holds a trained model ({", ".join(made)}) and no last.pt '
                              'to resume from: give a new --out (a run there would overwrite '
                              'it)')
    dev = _device(device, threads, rank, world)
    torch.manual_seed(tc.seed + rank)
    mcfg = load_model_config(tc.model_config)
    from suit_ros import CLASS_NAMES
    if tc.dataset == 'synthetic' and tuple(mcfg.class_names) != CLASS_NAMES:
        # its labels are indices into these: another set trains until an index overruns
        raise ConfigError(f'{tc.model_config} detects {list(mcfg.class_names)}, but the '
                          f'synthetic world labels {list(CLASS_NAMES)}: use those class_names')
    if tc.temporal:
        mcfg = replace(mcfg, temporal=tc.temporal)
    if tc.ground:
        mcfg = replace(mcfg, pillars=replace(mcfg.pillars, ground=tc.ground))
    module = SUITDetector(mcfg).to(dev)
    if tc.init_from:
        fresh = load_weights_into(module, tc.init_from)
        if rank == 0:
            print(f'[train] initialised from {tc.init_from}; new: {len(fresh)} tensors')
    model: Any = module
    if world > 1:
        from torch.nn.parallel import DistributedDataParallel
        model = DistributedDataParallel(module, find_unused_parameters=True)
    out.mkdir(parents=True, exist_ok=True)
    data = training_sequences(tc, mcfg.class_names, mcfg.sweeps)
    lengths = [1] if mcfg.temporal == 'none' else list(tc.clip_lengths)
    if rank == 0:
        span = carry_span_warning(data, lengths, mcfg.sampling.carry_s, tc)
        if span:
            print(f'[train] warning: {span}')
    batch = tc.batch_size * (2 if mcfg.temporal == 'none' else 1)
    ground = None
    if mcfg.pillars.ground == 'local':
        from suit_ros.ground import LocalGround
        ground = LocalGround(mcfg.pillars.point_range)
    sampler = ClipSampler(data, lengths, tc.seed * 1000 + rank, mcfg.sweeps,
                          tc.outage_probability, tc.outage_width_deg, tc.carry_gt,
                          tc.occlusion_weight, tc.passing_probability,
                          tc.fresh_start_probability)
    frozen = freeze(module, tc.freeze)
    distiller = _distiller(tc, module, dev)
    aug_rng = np.random.default_rng(tc.seed * 7919 + rank)
    opt = _optimizer(module, tc)
    step, done_s = 0, 0.0            # done_s: wall time of earlier runs of a resumed training
    last = out / 'last.pt'
    resumed = resume and last.is_file()
    if resumed:
        step, done_s, generators = _resume(last, module, opt, tc, mcfg)
        if rank == 0 and {'sampler', 'augment'} <= set(generators):
            # the draws the run would have made next (rank 0 saves; the other ranks of a
            # distributed run, and runs saved before, draw afresh from the step)
            sampler.rng.bit_generator.state = generators['sampler']
            aug_rng.bit_generator.state = generators['augment']
        else:
            sampler.rng = np.random.default_rng([tc.seed, step, rank])
            aug_rng = np.random.default_rng([tc.seed, step, rank, 1])
    elif resume and rank == 0:
        print(f'[train] nothing to resume in {out} (no last.pt): starting at step 0')
    start = time.monotonic() - done_s

    def progress() -> float:
        by_time = ((time.monotonic() - start) / (tc.max_minutes * 60) if tc.max_minutes
                   else 0.0)
        return agreed(max(step / tc.steps, by_time), world, dev)
    done = progress()                # each step's lr and the decision to stop: one for all
    if resumed and done >= 1.0 and (out / 'model.safetensors').is_file():
        # a run that had finished (a recipe resumed as a whole): its model stands as written,
        # unless it was killed while evaluating (then it is evaluated and written again)
        from suit_ros.checkpoint import read_metadata
        written = dict(read_metadata(out / 'model.safetensors').get('metrics', {}))
        if written.get('steps') == step and (not tc.eval_at_end or 'mAP' in written):
            if rank == 0:
                print(f'[train] {out} finished at step {step} within this budget: nothing to '
                      'do')
            return written
        return _finish(tc, out, module, mcfg, dev, step, done_s, rank, world)
    log = _LossLog(out / 'log.csv', step if resumed else None) if rank == 0 else None
    bar = tqdm(total=tc.steps, initial=step, disable=rank != 0, dynamic_ncols=True,
               desc=f'train[{mcfg.temporal}]')
    _train_mode(model, module, frozen, tc.frozen_batchnorm)
    while True:                      # at least one step per call, then until the budget is spent
        lr = _schedule(opt, done, tc.lr)
        clips, lost = sampler.batch_with_outages(batch)
        clips = _augmented(clips, tc, aug_rng, ground)
        vals = _optimise(model, module, opt, clips, tc.grad_clip, lost, distiller)
        step += 1
        if not math.isfinite(vals['loss']):
            raise RuntimeError(f'loss became {vals["loss"]} at step {step}; lower the lr')
        if log:
            log.row(step, time.monotonic() - start, lr, vals)
        bar.set_postfix({k.replace('_loss', ''): f'{v:.3f}' for k, v in vals.items()})
        bar.update(1)
        done = progress()
        finished = done >= 1.0
        if rank == 0 and (step % tc.checkpoint_every == 0 or finished):
            _snapshot(out, module, opt, mcfg, tc, step, time.monotonic() - start,
                      {'sampler': sampler.rng.bit_generator.state,
                       'augment': aug_rng.bit_generator.state})
            if log:
                log.flush()
        if finished:
            break
    bar.close()
    metrics = _finish(tc, out, module, mcfg, dev, step, time.monotonic() - start, rank, world)
    if log:
        log.close()
    if world > 1:       # every rank past its last collective before any tears down (gloo
        torch.distributed.barrier()         # aborts a rank whose peer is gone mid-exchange)
        torch.distributed.destroy_process_group()
    return metrics
