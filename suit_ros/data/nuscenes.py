"""A reader for nuScenes-format data (v1.0 JSON tables, ``samples/`` and ``sweeps/`` LIDAR_TOP).

Yields one :class:`~suit_ros.structures.Frame` per keyframe, in time order per scene: the
keyframe's LiDAR points plus the previous sweeps moved into the keyframe's LiDAR frame (through
each sweep's ego pose and calibration) with a time-lag channel, the pose ``T_global_lidar``, and
GT boxes and velocities in the LiDAR frame. Velocities are computed as the devkit's
``box_velocity`` does (centre differences of the neighbouring annotations, at most 1.5 s apart);
where the devkit says NaN (an isolated annotation) the reader keeps NaN: unknown, skipped by
the velocity error and the velocity loss. Bicycles and motorcycles
without a rider (`cycle.without_rider`) are ignore boxes; pedestrians are the devkit's four
subclasses, the other ``human.pedestrian`` ones (strollers, wheelchairs, personal mobility)
ignore boxes; each object keeps its instance's id over the keyframes.
"""
from __future__ import annotations

from collections.abc import Iterator
import json
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from suit_ros.errors import DatasetError
from suit_ros.model.sweeps import Sweep, accumulate_sweeps
from suit_ros.msg_adapters.odometry import quaternion_to_matrix
from suit_ros.structures import Detections, Frame

if TYPE_CHECKING:
    from suit_ros.params import TrafficSide

CLASS_MAP = {'vehicle.car': 'car', 'vehicle.truck': 'truck', 'vehicle.bus.bendy': 'truck',
             'vehicle.bus.rigid': 'truck', 'vehicle.construction': 'truck',
             'vehicle.trailer': 'truck', 'vehicle.bicycle': 'cyclist',
             'vehicle.motorcycle': 'cyclist'}
# the devkit's detection classes count these four as pedestrians (not a stroller, a wheelchair
# or a personal mobility device)
PEDESTRIANS = ('human.pedestrian.adult', 'human.pedestrian.child',
               'human.pedestrian.construction_worker', 'human.pedestrian.police_officer')
RIDERLESS = 'cycle.without_rider'      # a parked bicycle or motorcycle: not a cyclist
TABLES = ('scene', 'sample', 'sample_data', 'ego_pose', 'calibrated_sensor', 'sensor',
          'sample_annotation', 'instance', 'category')
OPTIONAL_TABLES = ('attribute',       # without it, every bicycle and motorcycle is a cyclist
                   'log')             # without it, every scene keeps to the right
LEFT_HAND = ('singapore',)            # log locations (prefixes) where traffic keeps left


def map_category(name: str) -> str | None:
    """nuScenes category -> this project's class (None: not a detection class)."""
    if name in PEDESTRIANS:
        return 'pedestrian'
    return CLASS_MAP.get(name)


def _pose(translation: Any, rotation_wxyz: Any) -> NDArray[np.float64]:
    w, x, y, z = rotation_wxyz
    T = np.eye(4)
    T[:3, :3] = quaternion_to_matrix(x, y, z, w)
    T[:3, 3] = translation
    return T


class NuScenesReader:
    """Index the tables of ``root/version`` once; read frames on demand."""

    def __init__(self, root: str | os.PathLike[str], version: str = 'v1.0-mini',
                 sweeps: int = 3, class_names: tuple[str, ...] | None = None,
                 min_distance: float = 1.0) -> None:
        """:param sweeps: sweeps per keyframe input, the keyframe and the sweeps before it
            (as the devkit's ``from_file_multisweep`` stacks them): the model's count (3 for
            the shipped models; the 10 of nuScenes recipes cost a 3-sweep model 0.09 mAP on
            20 Hz drives: docs/experiments/sweep_spacing)."""
        from suit_ros import CLASS_NAMES
        if sweeps < 1:
            raise DatasetError(f'sweeps must be at least 1, got {sweeps}')
        self.root = Path(root)
        self.sweeps = sweeps
        self.min_distance = min_distance
        self.class_names = class_names or CLASS_NAMES
        table_dir = self.root / version
        if not table_dir.is_dir():
            raise DatasetError(f'{table_dir} does not exist: expected the nuScenes tables of '
                               f'{version} under {self.root}')
        self.t: dict[str, dict[str, dict[str, Any]]] = {}
        for name in TABLES + OPTIONAL_TABLES:
            path = table_dir / f'{name}.json'
            if not path.is_file():
                if name in OPTIONAL_TABLES:
                    self.t[name] = {}
                    continue
                raise DatasetError(f'missing table {path}')
            with open(path, encoding='utf-8') as f:
                self.t[name] = {r['token']: r for r in json.load(f)}
        # one id per object over the whole dataset (the instance), as the other readers'
        self.instance_ids = {tok: i + 1 for i, tok in enumerate(sorted(self.t['instance']))}
        self.lidar_keyframe: dict[str, dict[str, Any]] = {}
        for sd in self.t['sample_data'].values():
            channel = self.t['sensor'][self.t['calibrated_sensor'][sd['calibrated_sensor_token']]
                                       ['sensor_token']]['channel']
            if channel == 'LIDAR_TOP' and sd['is_key_frame']:
                self.lidar_keyframe[sd['sample_token']] = sd
        self.anns: dict[str, list[dict[str, Any]]] = {}
        for ann in self.t['sample_annotation'].values():
            self.anns.setdefault(ann['sample_token'], []).append(ann)

    def scenes(self) -> list[str]:
        """Scene tokens, sorted by name."""
        return [s['token'] for s in sorted(self.t['scene'].values(), key=lambda s: s['name'])]

    def traffic_side(self, scene_token: str) -> TrafficSide:
        """The side of the road traffic keeps to where the scene was recorded: left in
        Singapore (the log's location), right elsewhere (Boston) and without a log table."""
        log = self.t['log'].get(self.t['scene'][scene_token].get('log_token', ''), {})
        return 'left' if str(log.get('location', '')).startswith(LEFT_HAND) else 'right'

    def sequence(self, scene_token: str) -> Iterator[Frame]:
        """The keyframes of one scene, in order."""
        scene = self.t['scene'][scene_token]
        token = scene['first_sample_token']
        while token:
            yield self.frame(token, scene['name'])
            token = self.t['sample'][token]['next']

    def sd_pose(self, sd: dict[str, Any]) -> NDArray[np.float64]:
        """``T_global_lidar`` of a sample_data record."""
        ego = self.t['ego_pose'][sd['ego_pose_token']]
        cal = self.t['calibrated_sensor'][sd['calibrated_sensor_token']]
        return _pose(ego['translation'], ego['rotation']) @ _pose(cal['translation'],
                                                                   cal['rotation'])

    def load_points(self, sd: dict[str, Any]) -> NDArray[np.float32]:
        """``(N, 5)`` x, y, z, intensity, ring of a ``.pcd.bin``."""
        path = self.root / sd['filename']
        if not path.is_file():
            raise DatasetError(f'missing LiDAR file {path}')
        raw = np.fromfile(path, dtype=np.float32)
        if raw.size % 5:
            raise DatasetError(f'{path} is not a nuScenes .pcd.bin (size {raw.size * 4} bytes)')
        return raw.reshape(-1, 5)

    def frame(self, sample_token: str, sequence_id: str = '') -> Frame:
        """One keyframe with its sweeps and GT."""
        ref = self.lidar_keyframe.get(sample_token)
        if ref is None:
            raise DatasetError(f'sample {sample_token} has no LIDAR_TOP keyframe')
        T_ref = self.sd_pose(ref)
        T_ref_inv = np.linalg.inv(T_ref)
        t_ref = ref['timestamp']
        sweeps = []
        sd: dict[str, Any] | None = ref
        for _ in range(self.sweeps):
            if sd is None:
                break
            pts = self.load_points(sd)
            near = (np.abs(pts[:, 0]) < self.min_distance) & (np.abs(pts[:, 1])
                                                               < self.min_distance)
            pts = pts[~near]
            xyzi = np.concatenate([pts[:, :3], pts[:, 3:4] / 255.0], 1).astype(np.float32)
            sweeps.append(Sweep(xyzi, self.sd_pose(sd), int(sd['timestamp']) * 1000))
            sd = self.t['sample_data'].get(sd['prev']) if sd['prev'] else None
        # the keyframe's own LiDAR frame (identity extrinsic here); model_frame moves it to
        # base_link with the LIDAR_TOP calibration kept in the Frame
        points = accumulate_sweeps(sweeps, np.eye(4))
        boxes: list[list[float]] = []
        vels: list[NDArray[np.float64]] = []
        labels: list[int] = []
        nums: list[int] = []
        ids: list[int] = []
        ignored: list[list[float]] = []
        for ann in self.anns.get(sample_token, []):
            inst = self.t['instance'][ann['instance_token']]
            category = self.t['category'][inst['category_token']]['name']
            cls = map_category(category)
            # a stroller, a wheelchair, a personal mobility device: not a pedestrian to find,
            # and a pedestrian box on one (its rider) no false positive
            other_person = category.startswith('human.pedestrian') and cls is None
            if (cls is None or cls not in self.class_names) and not (
                    other_person and 'pedestrian' in self.class_names):
                continue
            R = quaternion_to_matrix(ann['rotation'][1], ann['rotation'][2], ann['rotation'][3],
                                     ann['rotation'][0])
            c = T_ref_inv @ np.r_[ann['translation'], 1.0]
            heading = T_ref_inv[:3, :3] @ R[:, 0]
            w, length, h = ann['size']
            box = [c[0], c[1], c[2], length, w, h, np.arctan2(heading[1], heading[0])]
            attributes = {self.t['attribute'].get(a, {}).get('name')
                          for a in ann.get('attribute_tokens', [])}
            if other_person or (cls == 'cyclist' and RIDERLESS in attributes):
                ignored.append(box)     # neither an object nor a false positive (as AV2's)
                continue
            boxes.append(box)
            v = self.box_velocity(ann)
            v_l = T_ref_inv[:3, :3] @ np.r_[v, 0.0]     # NaN stays NaN: unknown, not standing
            vels.append(v_l[:2])
            labels.append(self.class_names.index(cls))
            nums.append(ann['num_lidar_pts'])
            ids.append(self.instance_ids[ann['instance_token']])
        gt = Detections(np.asarray(boxes).reshape(-1, 7), np.asarray(vels).reshape(-1, 2),
                        np.ones(len(boxes)), np.asarray(labels, np.int64))
        cal = self.t['calibrated_sensor'][ref['calibrated_sensor_token']]
        return Frame(points, T_ref, int(t_ref) * 1000, 'LIDAR_TOP', gt,
                     np.asarray(nums, np.uint32), np.asarray(ids, np.uint32), sequence_id,
                     _pose(cal['translation'], cal['rotation']),
                     ignore_boxes=np.asarray(ignored, np.float32).reshape(-1, 7))

    def box_velocity(self, ann: dict[str, Any], max_time_diff: float = 1.5
                     ) -> NDArray[np.float64]:
        """Global velocity (x, y) of an annotation, as the devkit computes it (NaN if none)."""
        has_prev, has_next = bool(ann['prev']), bool(ann['next'])
        if not has_prev and not has_next:
            return np.array([np.nan, np.nan])
        first = self.t['sample_annotation'][ann['prev']] if has_prev else ann
        last = self.t['sample_annotation'][ann['next']] if has_next else ann
        t0 = self.t['sample'][first['sample_token']]['timestamp'] * 1e-6
        t1 = self.t['sample'][last['sample_token']]['timestamp'] * 1e-6
        dt = t1 - t0
        if has_prev and has_next:
            max_time_diff *= 2
        if dt > max_time_diff or dt <= 0:
            return np.array([np.nan, np.nan])
        d = np.asarray(last['translation'], np.float64) - np.asarray(first['translation'],
                                                                      np.float64)
        return np.asarray(d[:2] / dt, np.float64)
