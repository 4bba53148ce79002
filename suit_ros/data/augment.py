"""Augmentations applied consistently to every frame of a sequence.

A clip is augmented by one similarity ``A = s * R_aug`` (random flip about the x axis, rotation
about z, scaling) of the LiDAR frame. Points and GT boxes become ``A p``; yaw turns with the
rotation (and changes sign under the flip); sizes and velocities scale with ``s``; each pose
becomes ``T' = (R R_aug^T, s t)`` so that the ego transform between any two frames of the clip is
``A T_rel A^-1``: static objects still map onto each other through the augmented poses.

A ground tilt (``tilt``: roll and pitch of the clip about the vehicle origin) and a lift
(``lift``: a height offset) put the road where a hilly city puts it: on a real sweep the road
40 m away lies up to a metre above or below the vehicle's ground plane (the Argoverse 2 dev
sweeps), while the synthetic road is flat. Boxes stay upright (their centres move with the
points). Point dropout thins the whole clip (missing returns, sparser sensors).

The flip is off by default: with box-shaped actors the side of the road a car drives on is the
only front/back cue, and a mirror erases it. That cue does not hold on real streets (one-way
streets, cars parked either way, left-hand traffic), and a model trained with the flip off
reads a parked car's heading off the side of the road (docs/experiments/parked_rows and
either_way). :func:`mirror_world` mirrors a whole drive, its odometry frame included, into
left-hand traffic for evaluation. Intensity dropout (the whole clip without
intensity, as from a driver that publishes none) teaches the model to work from geometry alone.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from suit_ros.structures import Detections, Frame


@dataclass(frozen=True)
class Augmentation:
    """One draw of the clip-level augmentation."""

    flip: bool
    angle: float
    scale: float
    drop_intensity: bool = False
    tilt: tuple[float, float] = (0.0, 0.0)      # roll, pitch (rad)
    lift: float = 0.0                           # m, added to every z
    point_dropout: float = 0.0                  # fraction of points removed

    @property
    def matrix(self) -> NDArray[np.float64]:
        """``R_aug`` (3x3, improper when flipped)."""
        c, s = np.cos(self.angle), np.sin(self.angle)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        if self.flip:
            R = R @ np.diag([1.0, -1.0, 1.0])
        if self.tilt != (0.0, 0.0):
            from suit_ros.ops.geometry import pose_from_xyz_rpy
            R = pose_from_xyz_rpy((0.0, 0.0, 0.0), (*self.tilt, 0.0))[:3, :3] @ R
        return R


def draw(rng: np.random.Generator, max_angle: float = np.pi / 4,
         scale_range: tuple[float, float] = (0.95, 1.05), flip_probability: float = 0.0,
         intensity_dropout: float = 0.0, tilt_deg: float = 0.0, lift_m: float = 0.0,
         point_dropout: float = 0.0) -> Augmentation:
    """A random augmentation. ``tilt_deg``: roll and pitch drawn from a normal of this
    standard deviation (clipped at 2.5 of them); ``lift_m``: uniform within +-this;
    ``point_dropout``: half the clips lose a uniform 0..this fraction of their points. At 0
    (the defaults) they draw nothing, so older recipes replay the same augmentations."""
    aug = Augmentation(bool(rng.random() < flip_probability),
                       float(rng.uniform(-max_angle, max_angle)),
                       float(rng.uniform(*scale_range)), bool(rng.random() < intensity_dropout))
    if tilt_deg > 0:
        t = np.clip(rng.normal(0.0, np.deg2rad(tilt_deg), 2), -2.5 * np.deg2rad(tilt_deg),
                    2.5 * np.deg2rad(tilt_deg))
        aug = replace(aug, tilt=(float(t[0]), float(t[1])))
    if lift_m > 0:
        aug = replace(aug, lift=float(rng.uniform(-lift_m, lift_m)))
    if point_dropout > 0 and rng.random() < 0.5:
        aug = replace(aug, point_dropout=float(rng.uniform(0.0, point_dropout)))
    return aug


def apply(frame: Frame, aug: Augmentation) -> Frame:
    """Return the augmented copy of a frame (the input is not modified)."""
    R = aug.matrix
    s = aug.scale
    pts = frame.points.copy()
    times = frame.times
    if aug.point_dropout > 0:
        keep = _hash_unit(pts) >= aug.point_dropout
        pts = pts[keep]
        times = None if times is None else times[keep]
    pts[:, :3] = (pts[:, :3].astype(np.float64) @ R.T * s).astype(np.float32)
    pts[:, 2] += np.float32(aug.lift)
    if aug.drop_intensity:
        pts[:, 3] = 0.0
    pose = frame.pose.copy()
    pose[:3, :3] = frame.pose[:3, :3] @ R.T
    pose[:3, 3] = frame.pose[:3, 3] * s - pose[:3, :3] @ np.array([0.0, 0.0, aug.lift])

    def moved(given: NDArray[np.floating[Any]]) -> NDArray[np.float64]:
        boxes = np.asarray(given, np.float64).reshape(-1, 7).copy()
        boxes[:, :3] = boxes[:, :3] @ R.T * s
        boxes[:, 2] += aug.lift
        boxes[:, 3:6] *= s
        yaw = -boxes[:, 6] if aug.flip else boxes[:, 6]
        boxes[:, 6] = np.arctan2(np.sin(yaw + aug.angle), np.cos(yaw + aug.angle))
        return boxes
    gt = frame.gt
    if gt is not None:
        vel = gt.velocities.astype(np.float64) @ R[:2, :2].T * s
        gt = Detections(moved(gt.boxes), vel, gt.scores, gt.labels)
    ignore = None if frame.ignore_boxes is None else \
        moved(frame.ignore_boxes).astype(np.float32)          # they go with the GT
    return replace(frame, points=pts, pose=pose, gt=gt, times=times, ignore_boxes=ignore,
                   owners=None)


def mirror_detections(det: Detections) -> Detections:
    """Boxes (or GT) mirrored across the x-z plane: y, yaw and vy negated."""
    from suit_ros.ops.geometry import mirror_boxes
    return Detections(mirror_boxes(det.boxes), det.velocities * np.array([1.0, -1.0], np.float32),
                      det.scores, det.labels)


def mirror_world(frame: Frame) -> Frame:
    """The frame of a drive mirrored across its LiDAR x-z plane, odometry frame included
    (``T' = M T M`` with ``M = diag(1, -1, 1)``): right-hand traffic becomes left-hand traffic,
    every pose stays a rotation (so a tracker, unlike a training clip's flip, sees a drive that
    could be real), and boxes, velocities and labels keep their objects. Mirroring twice gives
    the frame back."""
    from suit_ros.ops.geometry import mirror_boxes, mirror_points, mirror_transform
    gt = None if frame.gt is None else mirror_detections(frame.gt)
    ignore = None if frame.ignore_boxes is None else \
        mirror_boxes(frame.ignore_boxes).astype(np.float32)
    return replace(frame, points=mirror_points(frame.points), pose=mirror_transform(frame.pose),
                   gt=gt, T_base_lidar=mirror_transform(frame.T_base_lidar),
                   ignore_boxes=ignore)


def _hash_unit(points: NDArray[np.float32]) -> NDArray[np.float64]:
    """A value in [0, 1) per point from its bytes (deterministic, independent of order)."""
    raw = np.ascontiguousarray(points[:, :3]).view(np.uint32).astype(np.uint64)
    h = (raw[:, 0] * np.uint64(73856093)) ^ (raw[:, 1] * np.uint64(19349663)) \
        ^ (raw[:, 2] * np.uint64(83492791))
    return np.asarray((h % np.uint64(1_000_003)).astype(np.float64) / 1_000_003.0)


def apply_clip(frames: list[Frame], aug: Augmentation) -> list[Frame]:
    """Augment every frame of a clip with the same draw."""
    return [apply(f, aug) for f in frames]
