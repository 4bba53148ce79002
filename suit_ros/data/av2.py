"""A reader for the Argoverse 2 Sensor Dataset (Wilson et al., NeurIPS 2021 Datasets and
Benchmarks): LiDAR sweeps, 3D annotations and ego poses, for evaluation and training.

On-disk layout (``ROOT`` may be the dataset folder holding ``sensor/``, a split folder, or one
log folder; every folder below ``ROOT`` with a ``sensors/lidar/`` is a log)::

    sensor/<split>/<log_id>/
        sensors/lidar/<timestamp_ns>.feather     x y z (egovehicle frame) intensity (0..255)
                                                 laser_number offset_ns
        annotations.feather                      timestamp_ns track_uuid category length_m
                                                 width_m height_m qw qx qy qz tx_m ty_m tz_m
        calibration/egovehicle_SE3_sensor.feather   sensor poses (not needed: points arrive in
                                                 the egovehicle frame)
        city_SE3_egovehicle.feather              timestamp_ns qw qx qy qz tx_m ty_m tz_m

The files are Apache Arrow feather tables, read with ``pyarrow``.

Conventions (what the :class:`~suit_ros.structures.Frame` s hold):

- points ``(N, 5)`` ``x y z intensity time_lag`` in the **egovehicle frame** (origin at the
  centre of the rear axle, x forward, y left, z up), from the two stacked 32-beam LiDARs of
  the AV2 car merged into one sweep; intensity ``0..255`` divided by 255;
- ``T_base_lidar`` lifts the egovehicle frame by :data:`EGO_HEIGHT_M` to base_link (z = 0 on
  the road): the rear axle sits at wheel-radius height;
- ``pose`` is ``city_SE3_egovehicle`` at the sweep's stamp (interpolated between the pose
  records), so multi-sweep input and the memory work;
- boxes: the annotation's centre and rotation (about z) in the egovehicle frame; ``length``
  along the heading; labels cover 360 degrees around the car;
- classes (:data:`CLASS_MAP`): REGULAR_VEHICLE -> car; BUS, SCHOOL_BUS, ARTICULATED_BUS,
  BOX_TRUCK, TRUCK, TRUCK_CAB, VEHICULAR_TRAILER -> truck; PEDESTRIAN -> pedestrian;
  BICYCLIST, MOTORCYCLIST -> cyclist. A parked BICYCLE or MOTORCYCLE (the product's cyclist is
  a rider) and a LARGE_VEHICLE (RVs, vans, fire trucks: between car and truck) are
  :data:`IGNORED` : neither objects nor false positives (``Frame.ignore_boxes``). Every other
  category (bollards, cones, signs, strollers, animals, ...) is background: a detection on one
  is a false positive;
- an object annotated twice (two ``track_uuid`` s with the same category and the same box, as
  one car on the dev log of ../shared/data/real-dev is) is one object: the second row is left
  out (:func:`first_of_duplicates`), so one box cannot find both nor miss one of them;
- GT velocities from the same ``track_uuid`` at the neighbouring annotated stamps (centre
  differences in the city frame, at most 1.5 s apart, as nuScenes' ``box_velocity``), in the
  egovehicle frame, absolute; NaN (unknown) for an annotation without a neighbour: evaluation
  skips it in the velocity error and training in the velocity loss.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
import os
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from suit_ros.data.lazy import LazySequence
from suit_ros.errors import DatasetError
from suit_ros.ops.geometry import count_points_in_boxes
from suit_ros.structures import Detections, Frame

CLASS_MAP = {'REGULAR_VEHICLE': 'car',
             'BUS': 'truck', 'SCHOOL_BUS': 'truck', 'ARTICULATED_BUS': 'truck',
             'BOX_TRUCK': 'truck', 'TRUCK': 'truck', 'TRUCK_CAB': 'truck',
             'VEHICULAR_TRAILER': 'truck',
             'PEDESTRIAN': 'pedestrian',
             'BICYCLIST': 'cyclist', 'MOTORCYCLIST': 'cyclist'}
IGNORED = frozenset({'BICYCLE', 'MOTORCYCLE', 'LARGE_VEHICLE'})
# the egovehicle origin (rear axle centre) above the road: the AV2 car's wheel radius; on the
# dev log of ../shared/data/real-dev the 10th percentile of returns 4-20 m away lies 0.35 m
# below the origin
EGO_HEIGHT_M = 0.35
FRAME_ID = 'egovehicle'
INTENSITY_MAX = 255.0
MAX_VELOCITY_GAP_S = 1.5
LIDAR_COLUMNS = ('x', 'y', 'z', 'intensity')
ANNOTATION_COLUMNS = ('timestamp_ns', 'track_uuid', 'category', 'length_m', 'width_m',
                      'height_m', 'qw', 'qx', 'qy', 'qz', 'tx_m', 'ty_m', 'tz_m')
POSE_COLUMNS = ('timestamp_ns', 'qw', 'qx', 'qy', 'qz', 'tx_m', 'ty_m', 'tz_m')


def map_av2_class(category: str) -> str | None:
    """AV2 category -> this project's class (None: background or ignored)."""
    return CLASS_MAP.get(category)


def ego_mounting() -> NDArray[np.float64]:
    """base_link -> egovehicle: a lift of :data:`EGO_HEIGHT_M`."""
    T = np.eye(4)
    T[2, 3] = EGO_HEIGHT_M
    return T


def read_table(path: Path, columns: Sequence[str]) -> dict[str, NDArray[Any]]:
    """The named columns of a feather file as numpy arrays (strings as object arrays)."""
    import pyarrow as pa
    import pyarrow.feather as feather
    if not path.is_file():
        raise DatasetError(f'missing {path}: expected the Argoverse 2 sensor-dataset layout '
                           '(sensor/<split>/<log>/...; see suit_ros/data/av2.py)')
    try:
        table = feather.read_table(str(path))
    except (pa.ArrowInvalid, pa.ArrowIOError, OSError) as exc:
        raise DatasetError(f'{path} is not a readable feather (Apache Arrow) file: {exc}; '
                           'it may be truncated or corrupt') from exc
    missing = [c for c in columns if c not in table.column_names]
    if missing:
        raise DatasetError(f'{path} lacks the column(s) {missing} (has {table.column_names})')
    return {c: table.column(c).to_numpy(zero_copy_only=False) for c in columns}


def yaw_from_quaternion(qw: NDArray[np.float64], qx: NDArray[np.float64],
                        qy: NDArray[np.float64], qz: NDArray[np.float64]
                        ) -> NDArray[np.float64]:
    """Heading (rotation about z) of ``(w, x, y, z)`` quaternions."""
    return np.asarray(np.arctan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz)),
                      np.float64)


@dataclass
class Av2Annotations:
    """One log's annotations, grouped by stamp: per stamp, the row indices into the arrays."""

    stamps: NDArray[np.int64]
    rows: dict[int, NDArray[np.int64]]
    track: NDArray[Any]
    category: NDArray[Any]
    boxes: NDArray[np.float64]          # (R, 7) egovehicle frame at the row's stamp

    @staticmethod
    def read(path: Path) -> Av2Annotations:
        """Read ``annotations.feather``."""
        t = read_table(path, ANNOTATION_COLUMNS)
        stamp = t['timestamp_ns'].astype(np.int64)
        boxes = np.stack([t['tx_m'], t['ty_m'], t['tz_m'], t['length_m'], t['width_m'],
                          t['height_m'],
                          yaw_from_quaternion(t['qw'], t['qx'], t['qy'], t['qz'])], 1
                         ).astype(np.float64).reshape(-1, 7)
        if not np.isfinite(boxes).all():
            raise DatasetError(f'{path} has non-finite box values')
        order = np.argsort(stamp, kind='stable')
        stamps, starts = np.unique(stamp[order], return_index=True)
        rows = {int(s): order[a:b] for s, a, b in
                zip(stamps, starts, list(starts[1:]) + [len(order)])}
        return Av2Annotations(stamps, rows, t['track_uuid'], t['category'], boxes)


DUPLICATE_TOLERANCE_M = 0.05       # centre and size (m) within which two rows are one box
DUPLICATE_TOLERANCE_RAD = np.deg2rad(2.0)


def first_of_duplicates(boxes: NDArray[np.floating[Any]], keys: Sequence[object]
                        ) -> NDArray[np.bool_]:
    """``(R,)`` bool: False for a row that repeats an earlier row's key (category) and box
    ``(R, 7)`` (centre and size within :data:`DUPLICATE_TOLERANCE_M`, heading within
    :data:`DUPLICATE_TOLERANCE_RAD` modulo pi)."""
    b = np.asarray(boxes, np.float64).reshape(-1, 7)
    # candidate pairs (row i after row j) by x alone, then the whole test on those few
    i, j = np.nonzero(np.tril(np.abs(b[:, None, 0] - b[None, :, 0]) <= DUPLICATE_TOLERANCE_M,
                              -1))
    turn = (b[i, 6] - b[j, 6]) % np.pi
    same = ((np.abs(b[i, :6] - b[j, :6]).max(axis=1, initial=0.0) <= DUPLICATE_TOLERANCE_M)
            & (np.minimum(turn, np.pi - turn) <= DUPLICATE_TOLERANCE_RAD)
            & np.array([keys[p] == keys[q] for p, q in zip(i, j)], bool).reshape(-1))
    keep = np.ones(len(b), bool)
    for p, q in zip(i[same], j[same]):      # row order (np.nonzero is row-major): earlier first
        if keep[q]:
            keep[p] = False
    return keep


class Av2Sequence(LazySequence):
    """One AV2 log, its sweeps read from disk when indexed.

    :param class_names: the model's classes (a mapped class not among them is left out).
    """

    def __init__(self, log_dir: str | os.PathLike[str],
                 class_names: Sequence[str] | None = None) -> None:
        from suit_ros import CLASS_NAMES
        from suit_ros.msg_adapters.odometry import PoseBuffer, quaternion_to_matrix
        self.log_dir = Path(log_dir)
        self.sequence_id = self.log_dir.name
        self.class_names = tuple(class_names or CLASS_NAMES)
        self.sweeps = sorted((self.log_dir / 'sensors' / 'lidar').glob('*.feather'),
                             key=lambda p: int(p.stem) if p.stem.isdigit() else -1)
        bad = [p.name for p in self.sweeps if not p.stem.isdigit()]
        if bad:
            raise DatasetError(f'{self.log_dir / "sensors/lidar"}: {bad[0]} is not named '
                               '<timestamp_ns>.feather')
        if not self.sweeps:
            raise DatasetError(f'{self.log_dir / "sensors/lidar"} holds no sweep (.feather)')
        self.stamps_ns = [int(p.stem) for p in self.sweeps]
        poses = read_table(self.log_dir / 'city_SE3_egovehicle.feather', POSE_COLUMNS)
        self.poses = PoseBuffer(max_age_ns=2 ** 62, tolerance_ns=50_000_000, rewind_ns=None)
        for k in np.argsort(poses['timestamp_ns'], kind='stable'):
            T = np.eye(4)
            T[:3, :3] = quaternion_to_matrix(poses['qx'][k], poses['qy'][k], poses['qz'][k],
                                             poses['qw'][k])
            T[:3, 3] = (poses['tx_m'][k], poses['ty_m'][k], poses['tz_m'][k])
            self.poses.add(int(poses['timestamp_ns'][k]), T)
        self.annotations = Av2Annotations.read(self.log_dir / 'annotations.feather')
        # one id per object (its track_uuid) over the log, as the KITTI tracking reader's
        self.track_ids = {u: i + 1 for i, u in
                          enumerate(sorted({str(t) for t in self.annotations.track}))}

    def __len__(self) -> int:
        return len(self.sweeps)

    def pose(self, stamp_ns: int) -> NDArray[np.float64]:
        """``city_SE3_egovehicle`` at a stamp."""
        from suit_ros.msg_adapters.errors import PoseLookupError
        try:
            return self.poses.lookup(stamp_ns)
        except PoseLookupError as exc:
            raise DatasetError(f'{self.log_dir / "city_SE3_egovehicle.feather"}: no pose for '
                               f'stamp {stamp_ns} ({exc})') from exc

    def labelled(self, stamp_ns: int
                 ) -> tuple[Detections, NDArray[np.float64], NDArray[np.uint32]]:
        """GT (in the project's classes, with velocities), the ignored boxes and the GT
        boxes' object ids (one per track over the log) at a stamp (none when the stamp has no
        annotation)."""
        ann = self.annotations
        rows = ann.rows.get(int(stamp_ns), np.zeros(0, np.int64))
        rows = rows[first_of_duplicates(ann.boxes[rows], [str(c) for c in ann.category[rows]])]
        cls = [map_av2_class(str(c)) for c in ann.category[rows]]
        keep = np.array([c is not None and c in self.class_names for c in cls], bool)
        ignore = np.array([str(c) in IGNORED for c in ann.category[rows]], bool)
        kept = rows[keep]
        labels = np.array([self.class_names.index(c) for c, k in zip(cls, keep) if k and c],
                          np.int64)
        velocities = self._velocities(int(stamp_ns), kept)
        ids = np.array([self.track_ids[str(ann.track[r])] for r in kept], np.uint32)
        boxes = ann.boxes[kept]
        gt = Detections(boxes, velocities, np.ones(len(kept)), labels)
        return gt, ann.boxes[rows[ignore]], ids

    def _velocities(self, stamp_ns: int, rows: NDArray[np.int64]) -> NDArray[np.float64]:
        ann = self.annotations
        i = int(np.searchsorted(ann.stamps, stamp_ns))
        out = np.full((len(rows), 2), np.nan)        # unknown without a neighbour
        neighbours = []
        for j in (i - 1, i + 1):
            if 0 <= j < len(ann.stamps) and abs(int(ann.stamps[j]) - stamp_ns) * 1e-9 \
                    <= MAX_VELOCITY_GAP_S:
                s = int(ann.stamps[j])
                by_track = {str(ann.track[r]): r for r in ann.rows[s]}
                neighbours.append((s, by_track))
        if not neighbours or not len(rows):
            return out
        T_now = self.pose(stamp_ns)
        poses: dict[int, NDArray[np.float64]] = {}          # each neighbour's, looked up once
        for n, r in enumerate(rows):
            track = str(ann.track[r])
            ends = [(stamp_ns, T_now, ann.boxes[r, :3])]
            for s, by_track in neighbours:
                if track in by_track:
                    if s not in poses:
                        poses[s] = self.pose(s)
                    ends.append((s, poses[s], ann.boxes[by_track[track], :3]))
            if len(ends) < 2:
                continue
            ends.sort(key=lambda e: e[0])
            (s0, T0, c0), (s1, T1, c1) = ends[0], ends[-1]
            v_city = (T1[:3, :3] @ c1 + T1[:3, 3] - T0[:3, :3] @ c0 - T0[:3, 3]) \
                / ((s1 - s0) * 1e-9)
            out[n] = (T_now[:3, :3].T @ v_city)[:2]
        return out

    def frame(self, k: int) -> Frame:
        """Read sweep ``k`` with its GT, point counts and ignored boxes."""
        path = self.sweeps[k]
        t = read_table(path, LIDAR_COLUMNS)
        pts = np.zeros((len(t['x']), 5), np.float32)
        for i, c in enumerate(LIDAR_COLUMNS):
            pts[:, i] = t[c]
        pts[:, 3] /= np.float32(INTENSITY_MAX)
        pts = pts[np.isfinite(pts[:, :3]).all(1)]
        stamp = self.stamps_ns[k]
        gt, ignore, ids = self.labelled(stamp)
        return Frame(pts, self.pose(stamp), stamp, FRAME_ID, gt,
                     count_points_in_boxes(pts[:, :3], gt.boxes), ids,
                     self.sequence_id,
                     ego_mounting(), ignore_boxes=ignore.astype(np.float32))


def find_logs(root: str | os.PathLike[str]) -> list[Path]:
    """Every log folder (one with ``sensors/lidar/``) at or below ``root``, sorted."""
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f'{root} is not a folder; pass the Argoverse 2 dataset folder '
                           '(holding sensor/<split>/<log>/), a split folder or a log folder')
    if (root / 'sensors' / 'lidar').is_dir():
        return [root]
    logs = sorted(p.parent.parent for p in root.glob('**/sensors/lidar') if p.is_dir())
    if not logs:
        raise DatasetError(f'no Argoverse 2 log under {root}: expected '
                           'sensor/<split>/<log>/sensors/lidar/<timestamp_ns>.feather')
    return logs


def av2_sequences(root: str | os.PathLike[str], class_names: Sequence[str] | None = None
                  ) -> list[Av2Sequence]:
    """Every log under ``root`` as a lazily read sequence of sweeps."""
    return [Av2Sequence(log, class_names) for log in find_logs(root)]
