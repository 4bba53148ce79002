"""Sequence datasets for training and evaluation: synthetic drives (cached), bags, nuScenes,
KITTI.

A dataset is a list of sequences, each a list of :class:`~suit_ros.structures.Frame` in time
order. Training samples clips of 1-4 consecutive frames from them.

The synthetic splits use disjoint seed ranges: ``train`` seeds 1000+, ``val`` seeds 9000+,
``heldout`` (a sensor no training drive uses) 9500+, ``tune`` 8000+ (for choosing
post-processing settings such as the tracker's; never trained or validated on),
``outage`` 8500+ (the sensor-outage benchmark, :mod:`suit_ros.outage`). Drive
``i`` of a split uses the sensor ``SPLIT_SENSORS[split][i % len]``. The fixed validation set of
docs/results.md is ``val`` seeds 9000..9015 (16 drives of 40 frames at 10 Hz, four sensor
models). Splits use the detailed world (presets ``train-real`` and ``val-real``: vehicles with a
front and a back, articulated pedestrians, cyclists and motorcycles, street clutter as
negatives).

Data sources yield *sensor frames* (one sweep, LiDAR frame); :class:`ClipSampler` turns them into
*model frames* (accumulated sweeps in base_link) with :func:`suit_ros.model.sweeps.model_frame`.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
import hashlib
import json
import os
from pathlib import Path
import tempfile
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from suit_ros.structures import Detections, Frame

if TYPE_CHECKING:
    from suit_ros.data.kitti import KittiSequence
    from suit_ros.params import TrafficSide

SPLIT_SEEDS = {'train': 1000, 'tune': 8000, 'outage': 8500, 'val': 9000, 'heldout': 9500,
               'demo': 7}
SPLIT_SENSORS: dict[str, tuple[str, ...]] = {
    'train': ('sim32', 'hdl32e', 'sim32', 'vlp16', 'sim32', 'hdl64e', 'sim32', 'os1-64'),
    'val': ('sim32', 'hdl32e', 'vlp16', 'hdl64e'),
    'tune': ('sim32', 'hdl32e', 'vlp16', 'hdl64e'),
    'outage': ('sim32', 'hdl32e', 'vlp16', 'hdl64e'),
    'heldout': ('os1-128',),
}
VAL_SEQUENCES = 16


def _cache_key(preset_name: str, sensor: str, seed: int, frames: int,
               rate_hz: float | None = None) -> str:
    from dataclasses import asdict

    from suit_ros.data.sim import Realism, preset
    rate = {} if rate_hz is None else {'rate_hz': float(rate_hz)}   # 10 and 10.0: one key
    cfg = asdict(preset(preset_name, sensor=sensor, frames=frames, **rate))
    for name in ('realism', 'exact_sectors'):   # off: the box world, keys as before they existed
        if not cfg[name]:
            del cfg[name]
    for name in ('street_objects', 'real_car_ends', 'bystanders', 'dark_tops', 'parked_rows',
                 'real_car_roofs', 'at_fronts'):
        if cfg.get('realism') and not cfg['realism'][name]:
            del cfg['realism'][name]             # off: the world (and its key) as before
    if cfg.get('realism') and cfg['realism']['parked_reversed'] == Realism.parked_reversed:
        del cfg['realism']['parked_reversed']    # the share the rows had before it was a field
    if cfg.get('realism') and cfg['realism'].get('real_car_roofs'):
        # the body the cars get (1: commit ab9fdcc's first greenhouse, never trained on)
        cfg['realism']['roofs_geometry'] = 2
    if cfg.get('realism') and cfg['realism'].get('at_fronts'):
        # where they stand (1: commit c9bb7e2's, which run 38 trained on: garden walls and
        # gates counted as fronts, the box not turned when its gap was drawn)
        cfg['realism']['fronts_geometry'] = 2
    # v3: objects count their own returns where a moving sweep put them outside their box
    blob = json.dumps({'cfg': cfg, 'seed': seed, 'v': 3}, sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


PointsDtype = type[np.float32] | type[np.float16]


def synthetic_sequence(preset_name: str, seed: int, frames: int,
                       cache_dir: str | os.PathLike[str] | None = None,
                       sensor: str = 'sim32', points_dtype: PointsDtype = np.float32,
                       rate_hz: float | None = None) -> list[Frame]:
    """One simulated drive as sensor frames, optionally cached on disk (npz per drive).

    :param points_dtype: float16 halves the memory of a training set (the cache stores float16,
        so nothing is lost against a cached drive; the model input is float32 again after
        :func:`~suit_ros.model.sweeps.accumulate_sweeps`).
    :param rate_hz: the sensor's rate (None: the preset's, 10 Hz).
    """
    from suit_ros.data.sim import preset, sim_frames
    rate = {} if rate_hz is None else {'rate_hz': rate_hz}
    cfg = preset(preset_name, sensor=sensor, frames=frames, **rate)
    path = None
    if cache_dir is not None:
        path = Path(cache_dir) / f'{preset_name}-{sensor}-{seed}-{frames}-' \
            f'{_cache_key(preset_name, sensor, seed, frames, rate_hz)}.npz'
        if path.is_file():
            cached = load_sequence(path, points_dtype)
            # a drive cached before the returns' times, or their owners, were kept is made again
            if (not cfg.lidar.motion_distortion or all(f.times is not None for f in cached)) \
                    and all(f.owners is not None for f in cached):
                return cached
    out = list(sim_frames(cfg, seed))
    if path is not None:
        save_sequence(path, out)
        # the cache keeps float16 points: return what a later (cached) call returns, so the
        # first run of an evaluation gives the same figures as every run after it
        out = [replace(f, points=f.points.astype(np.float16).astype(np.float32),
                       times=None if f.times is None
                       else f.times.astype(np.float16).astype(np.float32)) for f in out]
    if points_dtype is not np.float32:
        out = [replace(f, points=f.points.astype(points_dtype)) for f in out]
    return out


def split_drives(split: str, sequences: int, first: int = 0) -> list[tuple[int, str]]:
    """``(seed, sensor)`` of ``sequences`` drives of a split, from its drive number ``first``."""
    if first < 0 or sequences < 0:
        raise ValueError(f'split_drives needs first >= 0 and sequences >= 0, not {first}, '
                         f'{sequences}')
    sensors = SPLIT_SENSORS.get(split, ('sim32',))
    return [(SPLIT_SEEDS[split] + i, sensors[i % len(sensors)])
            for i in range(first, first + sequences)]


def synthetic_split(split: str, sequences: int, frames: int,
                    cache_dir: str | os.PathLike[str] | None = None,
                    preset_name: str | None = None, points_dtype: PointsDtype = np.float32,
                    first: int = 0, rate_hz: float | None = None) -> list[list[Frame]]:
    """A split (``train``, ``tune``, ``val``, ``heldout``): ``sequences`` drives from drive
    number ``first`` (see module docstring), at ``rate_hz`` (None: 10 Hz)."""
    name = preset_name or ('train-real' if split == 'train' else 'val-real')
    return [synthetic_sequence(name, seed, frames, cache_dir, sensor, points_dtype, rate_hz)
            for seed, sensor in split_drives(split, sequences, first)]


def save_sequence(path: Path, frames: Sequence[Frame]) -> None:
    """Write frames to one compressed npz (atomically)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays: dict[str, NDArray[Any]] = {}
    for i, f in enumerate(frames):
        gt = f.gt if f.gt is not None else Detections.empty()
        arrays.update({f'{i}/points': f.points.astype(np.float16), f'{i}/pose': f.pose,
                       f'{i}/stamp': np.asarray(f.stamp_ns, np.int64), f'{i}/boxes': gt.boxes,
                       f'{i}/vel': gt.velocities, f'{i}/labels': gt.labels,
                       f'{i}/num': (f.num_points if f.num_points is not None
                                    else np.zeros(len(gt), np.uint32)),
                       f'{i}/ids': (f.instance_ids if f.instance_ids is not None
                                    else np.zeros(len(gt), np.uint32)),
                       f'{i}/extrinsic': f.T_base_lidar})
        if f.times is not None:
            arrays[f'{i}/times'] = f.times.astype(np.float16)
        if f.owners is not None:
            arrays[f'{i}/owners'] = f.owners.astype(np.uint32)
    arrays['meta'] = np.frombuffer(json.dumps(
        {'n': len(frames), 'frame_id': frames[0].frame_id if frames else 'lidar',
         'sequence_id': frames[0].sequence_id if frames else ''}).encode(), np.uint8)
    # a temporary name of its own: two processes caching one drive each write their own file
    # (a shared one was renamed under the other writer, and read torn)
    fd, name = tempfile.mkstemp(prefix=path.stem + '.', suffix='.tmp.npz', dir=path.parent)
    try:
        with os.fdopen(fd, 'wb') as out:
            np.savez(out, **arrays)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(name, 0o666 & ~umask)          # as a plain file (mkstemp makes it 0600)
        os.replace(name, path)
    except BaseException:
        Path(name).unlink(missing_ok=True)
        raise


def load_sequence(path: Path, points_dtype: PointsDtype = np.float32) -> list[Frame]:
    """Read frames written by :func:`save_sequence` (no pickle)."""
    with np.load(path, allow_pickle=False) as z:
        meta = json.loads(z['meta'].tobytes().decode())
        out = []
        for i in range(meta['n']):
            gt = Detections(z[f'{i}/boxes'], z[f'{i}/vel'], np.ones(len(z[f'{i}/boxes'])),
                            z[f'{i}/labels'])
            times = (z[f'{i}/times'].astype(np.float32) if f'{i}/times' in z.files
                     else None)
            owners = z[f'{i}/owners'] if f'{i}/owners' in z.files else None
            out.append(Frame(z[f'{i}/points'].astype(points_dtype), z[f'{i}/pose'],
                             int(z[f'{i}/stamp']), meta['frame_id'], gt, z[f'{i}/num'],
                             z[f'{i}/ids'], meta['sequence_id'], z[f'{i}/extrinsic'],
                             times=times, owners=owners))
    return out


def training_view(frame: Frame, min_points: int = 1,
                  keep_ids: set[int] | frozenset[int] | None = None
                  ) -> Frame:
    """The frame with GT restricted to boxes that have at least ``min_points`` returns (or
    whose instance id is in ``keep_ids``: objects seen before an outage)."""
    if frame.gt is None or frame.num_points is None:
        return frame
    keep = frame.num_points >= min_points
    if keep_ids and frame.instance_ids is not None:
        keep |= np.isin(frame.instance_ids, np.fromiter(keep_ids, np.int64))
    return replace(frame, gt=frame.gt.select(keep), num_points=frame.num_points[keep],
                   instance_ids=(frame.instance_ids[keep] if frame.instance_ids is not None
                                 else None))


def seen_ids(frame: Frame) -> frozenset[int]:
    """Instance ids of the frame's GT objects with returns in it."""
    if frame.gt is None or frame.num_points is None or frame.instance_ids is None:
        return frozenset()
    return frozenset(int(i) for i, c in zip(frame.instance_ids, frame.num_points) if c > 0)


def present_ids(frame: Frame) -> frozenset[int]:
    """Instance ids of every GT object of the frame (with returns or not)."""
    if frame.gt is None or frame.instance_ids is None:
        return frozenset()
    return frozenset(int(i) for i in frame.instance_ids)


def occluded_in_clip(seen: Sequence[frozenset[int]], present: Sequence[frozenset[int]],
                     min_gap: int = 1) -> int:
    """Occluded objects of a clip, counted frame by frame: present in a frame, with returns in
    an earlier frame of the clip but in none of the last ``min_gap`` frames (this one
    included; with ``min_gap`` = the model's sweeps, only a memory can still see them)."""
    n, last = 0, dict[int, int]()
    for t, (sn, pr) in enumerate(zip(seen, present)):
        n += sum(1 for i in pr - sn if i in last and t - last[i] >= min_gap)
        last.update((i, t) for i in sn)
    return n


class ClipSampler:
    """Random clips of consecutive model frames (length drawn from ``lengths``).

    :param sweeps: sweeps per model frame (the model config's ``sweeps``); a clip's first frame
        still gets its previous sweeps when the sequence has them.
    :param outage_probability: share of the clips with a sensor outage drawn in (the memory's
        training signal): a sector of ``outage_width_deg`` (uniform within the range) is lost
        from the sensor sweeps from clip frame 1 or 2 to the clip's end, before the sweeps are
        accumulated; the GT of those frames keeps the objects that had returns just before
        the outage (they are still there), so the loss rewards carrying them.
    :param carry_gt: every frame's GT keeps the objects that had returns in an earlier frame of
        the clip (occluded now, still there), in every clip.
    :param passing_probability: share of the clips (of 5 frames or more, without an outage)
        with passing occluders drawn in (:func:`suit_ros.data.occluders.draw_passing`): up to
        two objects with 10 or more returns in clip frame 0 or 1 hidden for 3-7 frames (0.3-0.7 s
        at 10 Hz; frames, whatever their spacing) by something truck-high crossing their line of
        sight; the GT of those frames keeps them and every other object seen just before (the
        screen hides what stands behind it too: all still there), and the frames count as
        outage frames (``lost``).
    :param occlusion_weight: clips are drawn with weight ``1 + occlusion_weight * n``, where
        ``n`` counts the clip's objects that only a memory can see (frame by frame: present,
        with returns earlier in the clip but in none of the last ``sweeps`` frames, see
        :func:`occluded_in_clip`); 0 draws every start alike. Puts natural occlusions beyond
        the sweep window in front of the loss without cutting anything out of the sweeps.
    :param fresh_start_probability: share of the clips cut as a drive starts (or as the node
        starts again after a reset: a time jump, a gap, a new sensor): the clip's first frame
        gets no earlier sweeps, its second one earlier sweep, and so on, so the model learns
        the one- and two-sweep input it meets there (and on single scans, a KITTI object
        frame) from more than the drives' own first frames (1 clip start in 40); 0 draws
        nothing, so a recipe without it replays the same clips.
    """

    def __init__(self, sequences: Sequence[Sequence[Frame]], lengths: Sequence[int],
                 seed: int, sweeps: int = 1, outage_probability: float = 0.0,
                 outage_width_deg: tuple[float, float] = (60.0, 180.0),
                 carry_gt: bool = False, occlusion_weight: float = 0.0,
                 passing_probability: float = 0.0,
                 fresh_start_probability: float = 0.0) -> None:
        span = max(lengths)
        self.sequences = [s for s in sequences if len(s) >= span]
        if not self.sequences:
            from suit_ros.errors import DatasetError
            raise DatasetError(f'no sequence has {span} frames (clips of {span} frames): '
                               'single frames (a KITTI object layout) train only a '
                               'single-frame model (temporal: none)')
        if not 0.0 <= outage_probability <= 1.0:
            raise ValueError(f'outage_probability must be in [0, 1], not {outage_probability}')
        if outage_probability and span < 3:
            raise ValueError('clips with outages need at least 3 frames')
        self.lengths = list(lengths)
        self.sweeps = sweeps
        if not 0.0 <= passing_probability <= 1.0:
            raise ValueError(f'passing_probability must be in [0, 1], not {passing_probability}')
        if passing_probability and span < 5:
            raise ValueError('clips with passing occluders need at least 5 frames')
        self.outage_probability = outage_probability
        self.passing_probability = passing_probability
        if not 0.0 <= fresh_start_probability <= 1.0:
            raise ValueError('fresh_start_probability must be in [0, 1], not '
                             f'{fresh_start_probability}')
        self.fresh_start_probability = fresh_start_probability
        self.outage_width_deg = outage_width_deg
        self.carry_gt = carry_gt
        if not (occlusion_weight >= 0.0 and np.isfinite(occlusion_weight)):
            raise ValueError(f'occlusion_weight must be >= 0, not {occlusion_weight}')
        self.occlusion_weight = occlusion_weight
        self.rng = np.random.default_rng(seed)
        # per clip length: the (sequence, start) pairs and their cumulative draw weights
        self._starts: dict[int, tuple[NDArray[np.int64], NDArray[np.float64]]] = {}
        if occlusion_weight > 0:
            seen = [[seen_ids(f) for f in seq] for seq in self.sequences]
            present = [[present_ids(f) for f in seq] for seq in self.sequences]
            for L in set(self.lengths):
                pairs, weights = [], []
                for i, (sn, pr) in enumerate(zip(seen, present)):
                    for s in range(len(sn) - L + 1):
                        pairs.append((i, s))
                        weights.append(1.0 + occlusion_weight * occluded_in_clip(
                            sn[s:s + L], pr[s:s + L], min_gap=sweeps))
                self._starts[L] = (np.asarray(pairs, np.int64),
                                   np.cumsum(np.asarray(weights, np.float64)))

    def batch(self, batch_size: int) -> list[list[Frame]]:
        """``batch_size`` clips of one common length."""
        return self.batch_with_outages(batch_size)[0]

    def batch_with_outages(self, batch_size: int
                           ) -> tuple[list[list[Frame]], list[list[bool]]]:
        """Clips as :meth:`batch`, and per clip frame whether an outage is active in it."""
        from suit_ros.model.sweeps import model_frame
        L = int(self.rng.choice(self.lengths))
        clips, lost = [], []
        for _ in range(batch_size):
            seq, start = self._draw_start(L)
            first = max(start - self.sweeps + 1, 0)
            if self.fresh_start_probability and self.rng.random() < self.fresh_start_probability:
                first = start           # no sweep before the clip: as a drive starts
            window = list(seq[first:start + L])
            active = [False] * L
            seen: frozenset[int] | None = None
            if L >= 3 and self.rng.random() < self.outage_probability:
                window, active, seen = self._draw_outage(window, start - first, L)
            elif self.passing_probability and L >= 5 \
                    and self.rng.random() < self.passing_probability:
                window, active, seen = self._draw_passing(window, start - first, L)
            clip = []
            earlier = frozenset[int]()
            for t in range(L):
                f = model_frame(window, start - first + t, self.sweeps)
                keep = earlier if self.carry_gt else (seen if active[t] else None)
                clip.append(training_view(f, keep_ids=keep))
                if self.carry_gt:
                    earlier = earlier | seen_ids(window[start - first + t])
            clips.append(clip)
            lost.append(active)
        return clips, lost

    def _draw_start(self, L: int) -> tuple[Sequence[Frame], int]:
        """A sequence and a clip start: uniform, or by occlusion weight."""
        if L in self._starts:
            pairs, cum = self._starts[L]
            k = int(np.searchsorted(cum, self.rng.random() * cum[-1], side='right'))
            i, start = pairs[min(k, len(pairs) - 1)]
            return self.sequences[int(i)], int(start)
        seq = self.sequences[int(self.rng.integers(len(self.sequences)))]
        return seq, int(self.rng.integers(len(seq) - L + 1))

    def _draw_passing(self, window: list[Frame], offset: int, L: int
                      ) -> tuple[list[Frame], list[bool], frozenset[int] | None]:
        """Passing occluders hiding objects of clip frame 0 or 1 from the frame after it."""
        from suit_ros.data.occluders import cast_passing, draw_passing
        begin = int(self.rng.integers(1, 3))
        drawn = draw_passing(window, self.rng, last=offset + begin - 1, come_back=False)
        if not drawn:
            return window, [False] * L, None
        active = [any(p.first <= offset + t < p.first + p.frames for p in drawn)
                  for t in range(L)]
        kept = frozenset(p.instance for p in drawn) | seen_ids(window[offset + begin - 1])
        return cast_passing(window, drawn), active, kept

    def _draw_outage(self, window: list[Frame], offset: int, L: int
                     ) -> tuple[list[Frame], list[bool], frozenset[int]]:
        """Remove a random sector from the window's sweeps from clip frame 1 or 2 on."""
        from suit_ros.outage import Outage, with_outages
        begin = int(self.rng.integers(1, min(2, L - 2) + 1))
        o = Outage(float(self.rng.uniform(-180, 180)),
                   float(self.rng.uniform(*self.outage_width_deg)), offset + begin, L - begin)
        return (with_outages(window, [o]), [t >= begin for t in range(L)],
                seen_ids(window[offset + begin - 1]))

def bag_sequences(paths: Sequence[str | os.PathLike[str]], sweeps: int = 3,
                  deskew: bool = False) -> list[list[Frame]]:
    """Sequences from rosbag2 bags that carry ``/points``, ``/odom`` and ``/gt/objects``: the
    labelled clouds (:func:`labelled_with_sweeps`), each cloud deskewed first with ``deskew``
    (as the node's ``deskew`` does)."""
    from suit_ros.data.bag import read_bag_frames
    out = []
    for p in paths:
        frames = list(read_bag_frames(p))
        if deskew:
            from suit_ros.evaluate import deskewed
            frames = deskewed(frames)
        seq = labelled_with_sweeps(frames, sweeps)
        if seq:
            out.append(seq)
    return out


def labelled_with_sweeps(frames: Sequence[Frame], sweeps: int = 3) -> list[Frame]:
    """The labelled frames of a drive (GT not None). Where some clouds are unlabelled (labels
    at 2 Hz, clouds at 10 Hz), each labelled frame comes with its ``sweeps - 1`` past sweeps
    from every cloud before it, stacked in its LiDAR frame with their time lags, as the node
    stacks them; from the labelled frames alone they would be 0.5 s apart, not 0.1. A drive
    labelled throughout is returned as it is (the model stacks its sweeps)."""
    from suit_ros.model.sweeps import DEFAULT_MAX_AGE_S, Sweep, accumulate_sweeps
    labelled = [t for t, f in enumerate(frames) if f.gt is not None]
    if len(labelled) == len(frames):
        return list(frames)
    out = []
    for t in labelled:
        f = frames[t]
        past = [frames[j] for j in range(t - 1, max(t - sweeps, -1), -1)
                if 0 < f.stamp_ns - frames[j].stamp_ns <= DEFAULT_MAX_AGE_S * 1e9]
        points = accumulate_sweeps([Sweep(f.points, f.pose, f.stamp_ns)]
                                   + [Sweep(p.points, p.pose, p.stamp_ns) for p in past],
                                   np.eye(4))              # in the current LiDAR frame
        out.append(replace(f, points=points, times=None, owners=None))
    return out


def nuscenes_sequences(root: str | os.PathLike[str], version: str = 'v1.0-mini',
                       sweeps: int = 3) -> list[list[Frame]]:
    """Every scene of a nuScenes-format dataset as a sequence of keyframes, each with the
    ``sweeps - 1`` sweeps before it (the model's count: :class:`~suit_ros.data.nuscenes.
    NuScenesReader`)."""
    return nuscenes_scenes(root, version, sweeps)[0]


def nuscenes_scenes(root: str | os.PathLike[str], version: str = 'v1.0-mini', sweeps: int = 3
                    ) -> tuple[list[list[Frame]], list[TrafficSide]]:
    """:func:`nuscenes_sequences` and the side of the road each scene keeps to (left in
    Singapore: the log table's location), from one read of the tables."""
    from suit_ros.data.nuscenes import NuScenesReader
    reader = NuScenesReader(root, version, sweeps)
    scenes = reader.scenes()
    return [list(reader.sequence(s)) for s in scenes], [reader.traffic_side(s) for s in scenes]


def kitti_sequences(root: str | os.PathLike[str], intensity_scale: float = 1.0,
                    fov_points_only: bool = False, ids: Sequence[str] | None = None
                    ) -> list[KittiSequence]:
    """KITTI-format data as sequences read lazily from disk: one per tracking sequence, or
    one single-frame sequence per frame of the object layout (see :mod:`suit_ros.data.kitti`).

    :param fov_points_only: keep only the points the front camera sees (for training).
    """
    from suit_ros.data.kitti import KittiReader
    reader = KittiReader(root, intensity_scale, fov_points_only=fov_points_only, ids=ids)
    return reader.sequences()
