"""Augmentations applied consistently to every frame of a sequence.

A clip is augmented by one similarity ``A = s * R_aug`` (random flip about the x axis, rotation
about z, scaling) of the LiDAR frame. Points and GT boxes become ``A p``; yaw turns with the
rotation (and changes sign under the flip); sizes and velocities scale with ``s``; each pose
becomes ``T' = (R R_aug^T, s t)`` so that the ego transform between any two frames of the clip is
``A T_rel A^-1``: static objects still map onto each other through the augmented poses.

The flip is off by default: with box-shaped actors the side of the road a car drives on is the
only front/back cue, and a mirror erases it. Intensity dropout (the whole clip without
intensity, as from a driver that publishes none) teaches the model to work from geometry alone.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

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

    @property
    def matrix(self) -> NDArray[np.float64]:
        """``R_aug`` (3x3, improper when flipped)."""
        c, s = np.cos(self.angle), np.sin(self.angle)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        if self.flip:
            R = R @ np.diag([1.0, -1.0, 1.0])
        return R


def draw(rng: np.random.Generator, max_angle: float = np.pi / 4,
         scale_range: tuple[float, float] = (0.95, 1.05), flip_probability: float = 0.0,
         intensity_dropout: float = 0.0) -> Augmentation:
    """A random augmentation."""
    return Augmentation(bool(rng.random() < flip_probability),
                        float(rng.uniform(-max_angle, max_angle)),
                        float(rng.uniform(*scale_range)), bool(rng.random() < intensity_dropout))


def apply(frame: Frame, aug: Augmentation) -> Frame:
    """Return the augmented copy of a frame (the input is not modified)."""
    R = aug.matrix
    s = aug.scale
    pts = frame.points.copy()
    pts[:, :3] = (pts[:, :3].astype(np.float64) @ R.T * s).astype(np.float32)
    if aug.drop_intensity:
        pts[:, 3] = 0.0
    pose = frame.pose.copy()
    pose[:3, :3] = frame.pose[:3, :3] @ R.T
    pose[:3, 3] = frame.pose[:3, 3] * s
    gt = frame.gt
    if gt is not None:
        boxes = gt.boxes.astype(np.float64).copy()
        boxes[:, :3] = boxes[:, :3] @ R.T * s
        boxes[:, 3:6] *= s
        yaw = -gt.boxes[:, 6] if aug.flip else gt.boxes[:, 6].astype(np.float64)
        boxes[:, 6] = np.arctan2(np.sin(yaw + aug.angle), np.cos(yaw + aug.angle))
        vel = gt.velocities.astype(np.float64) @ R[:2, :2].T * s
        gt = Detections(boxes, vel, gt.scores, gt.labels)
    return replace(frame, points=pts, pose=pose, gt=gt)


def apply_clip(frames: list[Frame], aug: Augmentation) -> list[Frame]:
    """Augment every frame of a clip with the same draw."""
    return [apply(f, aug) for f in frames]
