"""A reader for KITTI-format LiDAR data: the object layout and the tracking layout.

Two on-disk layouts are read (``ROOT`` may be the dataset folder or its ``training/`` folder):

- object detection: ``velodyne/NNNNNN.bin``, ``label_2/NNNNNN.txt``, ``calib/NNNNNN.txt``; each
  frame is its own one-frame sequence with an identity pose;
- tracking: ``velodyne/SSSS/NNNNNN.bin``, ``label_02/SSSS.txt``, ``calib/SSSS.txt``,
  ``oxts/SSSS.txt``; one sequence per ``SSSS`` at 10 Hz, poses ``T_odom_lidar`` from the GPS/IMU
  (oxts) records, and GT velocities from the same track id in the neighbouring frames.

Conventions (what the :class:`~suit_ros.structures.Frame` s hold):

- points ``(N, 5)`` ``x y z reflectance time_lag`` in the Velodyne frame (x forward, y left,
  z up, as REP 103); KITTI reflectance is already 0..1, the model's intensity contract, so it
  is not scaled (``intensity_scale`` divides it for KITTI-format files written with 0..255);
- boxes: a label's ``h w l x y z ry`` is a box standing on the ground in the rectified camera
  frame (``x y z`` the bottom centre, camera y down, ``ry`` about camera y). Its geometric centre
  ``(x, y - h / 2, z)`` is moved into the Velodyne frame by ``inv(Tr_velo_to_cam) @
  inv(R0_rect)``; the heading ``(cos ry, 0, -sin ry)`` is rotated likewise, which gives
  ``yaw = -ry - pi / 2`` for KITTI's nominal axes. ``l w h`` become ``length`` (along the
  heading), ``width``, ``height``;
- classes: Car and Van -> car, Truck -> truck, Pedestrian, Person_sitting (tracking labels:
  Person) -> pedestrian, Cyclist -> cyclist; Tram and Misc are ignore boxes (neither objects
  nor false positives); DontCare (2D regions only) is left out;
- labels exist only where the front camera (P2) sees: :func:`in_camera_fov` says which points or
  box centres are in front of the camera and inside the image width, and
  :func:`camera_fov_run` restricts an evaluation to that region;
- ``T_base_lidar`` is a translation of :data:`LIDAR_HEIGHT_M` (KITTI's Velodyne HDL-64E is
  mounted 1.73 m above the road: Geiger, Lenz, Stiller, Urtasun, "Vision meets Robotics: The
  KITTI Dataset", IJRR 32(11), 2013, fig. 3).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
import os
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from suit_ros.data.lazy import LazySequence
from suit_ros.errors import DatasetError
from suit_ros.ops.geometry import count_points_in_boxes, transform_points, wrap_angle
from suit_ros.structures import Detections, Frame

CLASS_MAP = {'Car': 'car', 'Van': 'car', 'Truck': 'truck', 'Pedestrian': 'pedestrian',
             'Person_sitting': 'pedestrian', 'Person': 'pedestrian', 'Cyclist': 'cyclist'}
# (``Person``: the tracking labels' name of a sitting person, the object labels'
# ``Person_sitting``)
KNOWN_TYPES = frozenset(CLASS_MAP) | {'Tram', 'Misc', 'DontCare'}
# labelled objects that are not a class here: a box on one is no false positive (ignore boxes,
# as the Argoverse 2 reader's parked bicycles); DontCare regions are 2D only
IGNORED_TYPES = frozenset({'Tram', 'Misc'})
LIDAR_HEIGHT_M = 1.73
IMAGE_WIDTH_PX = 1242.0
FRAME_PERIOD_NS = 100_000_000          # the tracking sequences are recorded at 10 Hz
MAX_VELOCITY_GAP_S = 1.5               # as nuScenes' box_velocity: neighbours at most 1.5 s away
FRAME_ID = 'velodyne'
EARTH_RADIUS_M = 6378137.0
_CALIB_KEYS = {'P2': ('P2',), 'R0_rect': ('R0_rect', 'R_rect'),
               'Tr_velo_to_cam': ('Tr_velo_to_cam', 'Tr_velo_cam'),
               'Tr_imu_to_velo': ('Tr_imu_to_velo', 'Tr_imu_velo')}


def map_kitti_class(name: str) -> str | None:
    """KITTI object type -> this project's class (None: not a detection class)."""
    return CLASS_MAP.get(name)


def lidar_mounting() -> NDArray[np.float64]:
    """The KITTI Velodyne's mounting: :data:`LIDAR_HEIGHT_M` above the road, axes aligned."""
    T = np.eye(4)
    T[2, 3] = LIDAR_HEIGHT_M
    return T


def _homogeneous(M: NDArray[np.float64]) -> NDArray[np.float64]:
    T = np.eye(4)
    T[:M.shape[0], :M.shape[1]] = M
    return T


@dataclass(frozen=True)
class KittiCalib:
    """The matrices of a KITTI calibration file that the LiDAR needs.

    :param P2: ``(3, 4)`` projection of the rectified left colour camera.
    :param R0_rect: ``(4, 4)`` rectifying rotation (camera 0 -> rectified camera).
    :param Tr_velo_to_cam: ``(4, 4)`` Velodyne -> camera 0.
    :param Tr_imu_to_velo: ``(4, 4)`` GPS/IMU -> Velodyne, or None where the file has none.
    """

    P2: NDArray[np.float64]
    R0_rect: NDArray[np.float64]
    Tr_velo_to_cam: NDArray[np.float64]
    Tr_imu_to_velo: NDArray[np.float64] | None = None

    @property
    def rect_from_velo(self) -> NDArray[np.float64]:
        """``(4, 4)`` Velodyne -> rectified camera: ``R0_rect @ Tr_velo_to_cam``."""
        return self.R0_rect @ self.Tr_velo_to_cam

    @property
    def velo_from_rect(self) -> NDArray[np.float64]:
        """``(4, 4)`` rectified camera -> Velodyne: ``inv(Tr_velo_to_cam) @ inv(R0_rect)``."""
        return np.linalg.inv(self.Tr_velo_to_cam) @ np.linalg.inv(self.R0_rect)


def read_calib(path: str | os.PathLike[str]) -> KittiCalib:
    """Read an object (``P2: ...``) or tracking (``R_rect ...``) calibration file."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f'missing calibration file {path}: every frame (object layout) or '
                           'sequence (tracking layout) needs one in calib/')
    values: dict[str, list[float]] = {}
    for n, line in enumerate(path.read_text(encoding='utf-8').splitlines(), 1):
        parts = line.replace(':', ' ', 1).split()
        if not parts:
            continue
        try:
            values[parts[0]] = [float(v) for v in parts[1:]]
        except ValueError as exc:
            raise DatasetError(f'{path}:{n}: {parts[0]} has a value that is not a number; '
                               'expected KEY: v1 v2 ... (KITTI calibration)') from exc
    found: dict[str, NDArray[np.float64]] = {}
    for key, aliases in _CALIB_KEYS.items():
        name = next((a for a in aliases if a in values), None)
        if name is None:
            if key == 'Tr_imu_to_velo':
                continue
            raise DatasetError(f'{path} has no {" or ".join(aliases)} line; a KITTI calibration '
                               'needs P2, R0_rect and Tr_velo_to_cam')
        size = 9 if key == 'R0_rect' else 12
        if len(values[name]) != size:
            raise DatasetError(f'{path}: {name} has {len(values[name])} values, expected {size}')
        M = np.asarray(values[name], np.float64).reshape(-1, 3 if size == 9 else 4)
        found[key] = M if key == 'P2' else _homogeneous(M)
    return KittiCalib(found['P2'], found['R0_rect'], found['Tr_velo_to_cam'],
                      found.get('Tr_imu_to_velo'))


@dataclass(frozen=True)
class KittiLabels:
    """The label lines of one frame (camera-frame boxes), as arrays.

    :param types: KITTI object types (``Car``, ``DontCare``, ...).
    :param hwl: ``(N, 3)`` height, width, length (m).
    :param location: ``(N, 3)`` bottom centre in the rectified camera frame (m).
    :param rotation_y: ``(N,)`` rotation about the camera's y axis (rad).
    :param track_ids: ``(N,)`` track ids (tracking layout; -1 in the object layout).
    """

    types: tuple[str, ...]
    hwl: NDArray[np.float64]
    location: NDArray[np.float64]
    rotation_y: NDArray[np.float64]
    track_ids: NDArray[np.int64]


def _parse_label_lines(path: Path, tracking: bool) -> tuple[list[int], KittiLabels]:
    """Parse ``label_2`` (15 or 16 fields) or ``label_02`` (17 or 18) lines."""
    skip = 2 if tracking else 0
    fields = 'frame track_id type ...' if tracking else 'type truncated occluded alpha ...'
    frames: list[int] = []
    types: list[str] = []
    ids: list[int] = []
    rows: list[list[float]] = []
    for n, line in enumerate(path.read_text(encoding='utf-8').splitlines(), 1):
        parts = line.split()
        if not parts:
            continue
        where = f'{path}:{n}'
        if len(parts) not in (15 + skip, 16 + skip):
            raise DatasetError(f'{where}: {len(parts)} fields, expected {15 + skip} '
                               f'({fields} h w l x y z rotation_y) or one more (score); '
                               'is this a KITTI label file?')
        kind = parts[skip]
        if kind not in KNOWN_TYPES:
            raise DatasetError(f'{where}: unknown object type {kind!r}; KITTI types are '
                               f'{sorted(KNOWN_TYPES)}')
        try:
            if tracking:
                frames.append(int(parts[0]))
                ids.append(int(parts[1]))
            rows.append([float(v) for v in parts[skip + 8:skip + 15]])
        except ValueError as exc:
            raise DatasetError(f'{where}: a field is not a number ({exc}); fix or remove the '
                               'line') from exc
        types.append(kind)
    data = np.asarray(rows, np.float64).reshape(-1, 7)
    if not np.isfinite(data).all():
        raise DatasetError(f'{path}: a box has a non-finite value; fix or remove the line')
    labels = KittiLabels(tuple(types), data[:, 0:3], data[:, 3:6], data[:, 6],
                         np.asarray(ids if tracking else [-1] * len(types), np.int64))
    return frames, labels


def read_labels(path: str | os.PathLike[str]) -> KittiLabels:
    """Read one object-layout label file (``label_2/NNNNNN.txt``)."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f'missing label file {path}: the object layout needs label_2/ next '
                           'to velodyne/ (the testing split has no labels; use training)')
    return _parse_label_lines(path, tracking=False)[1]


def camera_boxes_to_lidar(hwl: NDArray[np.floating[Any]], location: NDArray[np.floating[Any]],
                          rotation_y: NDArray[np.floating[Any]], calib: KittiCalib
                          ) -> NDArray[np.float64]:
    """KITTI camera-frame boxes -> ``(N, 7)`` ``x y z l w h yaw`` in the Velodyne frame.

    :param hwl: ``(N, 3)`` height, width, length.
    :param location: ``(N, 3)`` bottom centre in the rectified camera frame.
    :param rotation_y: ``(N,)`` rotation about the rectified camera's y axis.
    """
    hwl = np.asarray(hwl, np.float64).reshape(-1, 3)
    loc = np.asarray(location, np.float64).reshape(-1, 3)
    ry = np.asarray(rotation_y, np.float64).reshape(-1)
    T = calib.velo_from_rect
    centre_rect = loc - np.c_[np.zeros(len(loc)), hwl[:, 0] / 2, np.zeros(len(loc))]
    heading = np.c_[np.cos(ry), np.zeros(len(ry)), -np.sin(ry)] @ T[:3, :3].T
    yaw = wrap_angle(np.arctan2(heading[:, 1], heading[:, 0]))
    boxes: NDArray[np.float64] = np.c_[transform_points(T, centre_rect), hwl[:, 2], hwl[:, 1],
                                       hwl[:, 0], yaw]
    return boxes


def in_camera_fov(xyz: NDArray[np.floating[Any]], calib: KittiCalib,
                  image_width: float = IMAGE_WIDTH_PX) -> NDArray[np.bool_]:
    """Which Velodyne-frame points (or box centres) the front camera sees.

    A point is in view when it is in front of the camera (positive depth after ``P2 @ R0_rect
    @ Tr_velo_to_cam``) and its column ``u`` is inside ``[0, image_width)``. Rows are not
    checked: KITTI labels every object the image shows, whatever its height.

    :param xyz: ``(N, 3)`` Velodyne-frame positions.
    :return: ``(N,)`` mask.
    """
    xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
    uvw = np.c_[xyz, np.ones(len(xyz))] @ (calib.P2 @ calib.rect_from_velo).T
    w = uvw[:, 2]
    u = np.divide(uvw[:, 0], w, out=np.full(len(w), -1.0), where=w > 0)
    mask: NDArray[np.bool_] = (w > 0) & (u >= 0) & (u < image_width)
    return mask


def read_velodyne(path: str | os.PathLike[str], intensity_scale: float = 1.0
                  ) -> NDArray[np.float32]:
    """A ``.bin`` scan as ``(N, 5)`` float32 ``x y z reflectance time_lag(0)``.

    :param intensity_scale: divides the file's reflectance (1 for KITTI, 255 for 0..255 files).
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f'missing LiDAR file {path}')
    raw = np.fromfile(path, dtype='<f4')
    if raw.size % 4:
        raise DatasetError(f'{path} has {path.stat().st_size} bytes, not a multiple of 16: a '
                           'KITTI .bin holds float32 records x y z reflectance')
    pts = np.zeros((raw.size // 4, 5), np.float32)
    pts[:, :4] = raw.reshape(-1, 4)
    pts[:, 3] /= np.float32(intensity_scale)
    pts = pts[np.isfinite(pts[:, :4]).all(1)]
    if len(pts) and float(pts[:, 3].max()) > 1.0 + 1e-3:
        raise DatasetError(f'{path}: reflectance up to {float(pts[:, 3].max()):.4g} after '
                           f'dividing by {intensity_scale:g}; KITTI-format reflectance is 0..1. '
                           'If the files hold 0..255, pass intensity_scale=255 (suit-ros eval '
                           '--kitti-intensity-scale 255)')
    out: NDArray[np.float32] = pts
    return out


def oxts_poses(path: str | os.PathLike[str], Tr_imu_to_velo: NDArray[np.float64]
               ) -> NDArray[np.float64]:
    """``(F, 4, 4)`` ``T_odom_lidar`` per line of an oxts file (KITTI raw-data devkit rule).

    Latitude/longitude go through a Mercator projection scaled by the first record's latitude;
    roll, pitch, yaw give ``R = Rz(yaw) Ry(pitch) Rx(roll)`` of the IMU. The odometry frame is
    the first record's IMU position (axes east, north, up), so translations stay small.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f'missing {path}: the tracking layout needs oxts/ for the ego poses '
                           '(the multi-frame model cannot use a sequence without them)')
    rows = []
    for n, line in enumerate(path.read_text(encoding='utf-8').splitlines(), 1):
        if not line.strip():
            continue
        try:
            rows.append([float(v) for v in line.split()[:6]])
        except ValueError as exc:
            raise DatasetError(f'{path}:{n}: not an oxts record ({exc})') from exc
        if len(rows[-1]) < 6:
            raise DatasetError(f'{path}:{n}: an oxts record starts lat lon alt roll pitch yaw')
    o = np.asarray(rows, np.float64).reshape(-1, 6)
    scale = np.cos(np.deg2rad(o[0, 0])) if len(o) else 1.0
    t = np.c_[scale * EARTH_RADIUS_M * np.deg2rad(o[:, 1]),
              scale * EARTH_RADIUS_M * np.log(np.tan(np.deg2rad(90.0 + o[:, 0]) / 2)), o[:, 2]]
    imu_from_velo = np.linalg.inv(Tr_imu_to_velo)
    out = np.zeros((len(o), 4, 4))
    for k, (roll, pitch, yaw) in enumerate(o[:, 3:6]):
        cr, sr, cp, sp, cy, sy = (np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch),
                                  np.cos(yaw), np.sin(yaw))
        T = np.eye(4)
        T[:3, :3] = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]]) @ np.array(
            [[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]]) @ np.array([[1, 0, 0], [0, cr, -sr],
                                                                [0, sr, cr]])
        T[:3, 3] = t[k] - t[0]
        out[k] = T @ imu_from_velo
    return out


def _velocities(boxes: list[NDArray[np.float64]], ids: list[NDArray[np.int64]],
                poses: NDArray[np.float64], stamps_ns: list[int]) -> list[NDArray[np.float64]]:
    """Per-frame ``(N, 2)`` velocities (LiDAR frame) from the same track id in the neighbouring
    labelled frames, by centre differences in the odometry frame as nuScenes' ``box_velocity``
    (neighbours at most 1.5 s away; NaN, unknown, for an isolated box or a negative id)."""
    t = np.asarray(stamps_ns, np.int64) * 1e-9
    tracks: dict[int, dict[int, NDArray[np.float64]]] = {}
    for k, (b, tid) in enumerate(zip(boxes, ids)):
        centres = transform_points(poses[k], b[:, :3]) if len(b) else np.zeros((0, 3))
        for i, c in zip(tid.tolist(), centres):
            if i >= 0:
                tracks.setdefault(i, {})[k] = c
    out = []
    for k, tid in enumerate(ids):
        v = np.full((len(tid), 3), np.nan)
        for j, i in enumerate(tid.tolist()):
            seen = tracks.get(i, {})
            prev = max((f for f in seen if f < k and t[k] - t[f] <= MAX_VELOCITY_GAP_S),
                       default=k)
            nxt = min((f for f in seen if f > k and t[f] - t[k] <= MAX_VELOCITY_GAP_S),
                      default=k)
            if nxt != prev:
                v[j] = (seen[nxt] - seen[prev]) / (t[nxt] - t[prev])
        out.append((v @ poses[k][:3, :3])[:, :2])         # R^T v: odometry -> LiDAR frame
    return out


class KittiSequence(LazySequence):
    """One sequence of KITTI frames, read from disk when indexed (a KITTI split does not fit in
    memory). Boxes, velocities and poses are computed once; points and ``num_points`` per read.

    :param calib: the sequence's calibration (object layout: the frame's own).
    """

    def __init__(self, sequence_id: str, scans: list[Path], calib: KittiCalib,
                 poses: NDArray[np.float64], labels: list[KittiLabels],
                 stamps_ns: list[int], intensity_scale: float = 1.0,
                 class_names: tuple[str, ...] | None = None,
                 fov_points_only: bool = False, image_width: float = IMAGE_WIDTH_PX) -> None:
        from suit_ros import CLASS_NAMES
        names = class_names or CLASS_NAMES
        self.sequence_id = sequence_id
        self.scans = scans
        self.calib = calib
        self.poses = poses
        self.stamps_ns = stamps_ns
        self.intensity_scale = intensity_scale
        self.fov_points_only = fov_points_only
        self.image_width = image_width
        self.boxes: list[NDArray[np.float64]] = []
        self.labels: list[NDArray[np.int64]] = []
        self.track_ids: list[NDArray[np.int64]] = []
        self.ignored: list[NDArray[np.float64]] = []
        for lab in labels:
            other = np.array([t in IGNORED_TYPES for t in lab.types], bool).reshape(-1)
            self.ignored.append(camera_boxes_to_lidar(lab.hwl[other], lab.location[other],
                                                      lab.rotation_y[other], calib))
            cls = [map_kitti_class(t) for t in lab.types]
            keep = np.array([c is not None and c in names for c in cls], bool).reshape(-1)
            self.boxes.append(camera_boxes_to_lidar(lab.hwl[keep], lab.location[keep],
                                                    lab.rotation_y[keep], calib))
            self.labels.append(np.array([names.index(c) for c, k in zip(cls, keep) if k and c],
                                        np.int64))
            self.track_ids.append(lab.track_ids[keep])
        self.velocities = _velocities(self.boxes, self.track_ids, poses, stamps_ns)

    def __len__(self) -> int:
        return len(self.scans)

    def frame(self, k: int) -> Frame:
        """Read frame ``k``: its scan, with the GT boxes and their point counts."""
        points = read_velodyne(self.scans[k], self.intensity_scale)
        if self.fov_points_only:
            points = points[in_camera_fov(points[:, :3], self.calib, self.image_width)]
        boxes = self.boxes[k]
        gt = Detections(boxes.astype(np.float32), self.velocities[k].astype(np.float32),
                        np.ones(len(boxes), np.float32), self.labels[k].copy())
        return Frame(points, self.poses[k].copy(), self.stamps_ns[k], FRAME_ID, gt,
                     count_points_in_boxes(points[:, :3], boxes), self._instance_ids(k),
                     self.sequence_id, lidar_mounting(),
                     ignore_boxes=self.ignored[k].astype(np.float32).reshape(-1, 7))

    def _instance_ids(self, k: int) -> NDArray[np.uint32]:
        ids = self.track_ids[k]
        return np.where(ids >= 0, ids, np.arange(len(ids))).astype(np.uint32)


class KittiReader:
    """Find the layout under ``root`` and build its sequences.

    :param root: the dataset folder, or its ``training/`` folder.
    :param intensity_scale: divides the files' reflectance (1 for KITTI).
    :param fov_points_only: keep only the points the front camera sees (for training: outside
        its view nothing is labelled, so objects there would be taught as background).
    :param ids: object layout: the frame ids to read (e.g. from ``ImageSets/val.txt``);
        tracking layout: the sequence ids. None: all.
    """

    def __init__(self, root: str | os.PathLike[str], intensity_scale: float = 1.0,
                 class_names: tuple[str, ...] | None = None, fov_points_only: bool = False,
                 image_width: float = IMAGE_WIDTH_PX, ids: Sequence[str] | None = None
                 ) -> None:
        root = Path(root)
        if not (root / 'velodyne').is_dir() and (root / 'training' / 'velodyne').is_dir():
            root = root / 'training'
        self.root = root
        velodyne = root / 'velodyne'
        if not velodyne.is_dir():
            raise DatasetError(f'{velodyne} does not exist: expected KITTI-format data, '
                               'velodyne/ label_2/ calib/ (object) or velodyne/SSSS/ label_02/ '
                               'calib/ oxts/ (tracking), in ROOT or ROOT/training')
        self.tracking = any(p.is_dir() for p in velodyne.iterdir())
        self.ids = list(ids) if ids is not None else None
        self.options: dict[str, Any] = {
            'intensity_scale': intensity_scale, 'class_names': class_names,
            'fov_points_only': fov_points_only, 'image_width': image_width}

    def sequences(self) -> list[KittiSequence]:
        """Every sequence, sorted by id (object layout: one per frame)."""
        return self._tracking() if self.tracking else self._object()

    def _object(self) -> list[KittiSequence]:
        scans = sorted((self.root / 'velodyne').glob('*.bin'))
        if self.ids is not None:
            scans = [self.root / 'velodyne' / f'{i}.bin' for i in self.ids]
            missing = [s.name for s in scans if not s.is_file()]
            if missing:
                raise DatasetError(f'{len(missing)} listed frame(s) have no scan in '
                                   f'{self.root / "velodyne"} (first: {missing[0]}); check the '
                                   'id list against ROOT')
        if not scans:
            raise DatasetError(f'{self.root / "velodyne"} holds no .bin scan')
        out = []
        for scan in scans:
            calib = read_calib(self.root / 'calib' / f'{scan.stem}.txt')
            labels = read_labels(self.root / 'label_2' / f'{scan.stem}.txt')
            out.append(KittiSequence(scan.stem, [scan], calib, np.eye(4)[None], [labels], [0],
                                     **self.options))
        return out

    def _tracking(self) -> list[KittiSequence]:
        seqs = sorted(p.name for p in (self.root / 'velodyne').iterdir() if p.is_dir())
        out = []
        for sid in (self.ids if self.ids is not None else seqs):
            scans = sorted((self.root / 'velodyne' / sid).glob('*.bin'))
            if not scans:
                raise DatasetError(f'{self.root / "velodyne" / sid} holds no .bin scan')
            calib = read_calib(self.root / 'calib' / f'{sid}.txt')
            if calib.Tr_imu_to_velo is None:
                raise DatasetError(f'{self.root / "calib" / sid}.txt has no Tr_imu_velo line, '
                                   'needed to turn the oxts records into LiDAR poses')
            poses = oxts_poses(self.root / 'oxts' / f'{sid}.txt', calib.Tr_imu_to_velo)
            frames = [int(s.stem) for s in scans]
            if frames[-1] >= len(poses):
                raise DatasetError(f'{self.root / "oxts" / sid}.txt has {len(poses)} records '
                                   f'but velodyne/{sid}/ goes up to frame {frames[-1]}')
            path = self.root / 'label_02' / f'{sid}.txt'
            if not path.is_file():
                raise DatasetError(f'missing label file {path}: the tracking layout needs '
                                   'label_02/SSSS.txt for every sequence')
            line_frames, labels = _parse_label_lines(path, tracking=True)
            lf = np.asarray(line_frames, np.int64)
            per_frame = [_select(labels, lf == f) for f in frames]
            out.append(KittiSequence(sid, scans, calib, poses[frames], per_frame,
                                     [f * FRAME_PERIOD_NS for f in frames], **self.options))
        return out


def _select(labels: KittiLabels, mask: NDArray[np.bool_]) -> KittiLabels:
    return KittiLabels(tuple(t for t, m in zip(labels.types, mask) if m), labels.hwl[mask],
                       labels.location[mask], labels.rotation_y[mask], labels.track_ids[mask])


def camera_fov_run(run: Any, sequences: Sequence[KittiSequence],
                   image_width: float = IMAGE_WIDTH_PX) -> Any:
    """Restrict a :class:`~suit_ros.evaluate.ModelRun` over ``sequences`` to the camera's view.

    Detections and GT whose centres the camera does not see are dropped before matching (KITTI
    labels nothing outside the view, so detections there would count as false positives); a
    detection's carried flag goes with it.
    """
    calibs = [s.calib for s in sequences for _ in range(len(s))]
    if len(calibs) != len(run.det):
        raise ValueError(f'the run has {len(run.det)} frames, the sequences {len(calibs)}')
    det, gt, num, carried = [], [], [], []
    for k, (calib, d, g, n) in enumerate(zip(calibs, run.det, run.gt, run.num_points)):
        seen = in_camera_fov(d.boxes[:, :3], calib, image_width)
        det.append(d.select(seen))
        if run.carried:
            carried.append(run.carried[k][seen])
        keep = in_camera_fov(g.boxes[:, :3], calib, image_width)
        gt.append(g.select(keep))
        num.append(n[keep] if n is not None else None)
    return replace(run, det=det, gt=gt, num_points=num, carried=carried)
