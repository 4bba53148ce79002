"""Shared helpers of the model tests: a small model config, its grid, frames and clouds."""
from __future__ import annotations

import numpy as np
import torch

from suit_ros.config import BackboneConfig, ModelConfig, PillarConfig
from suit_ros.model.grid import BEVGrid
from suit_ros.model.head import draw_gaussian
from suit_ros.ops.geometry import pose_from_xyz_rpy
from suit_ros.structures import Detections, Frame

GRID = BEVGrid((-25.6, -25.6, -3.0, 25.6, 25.6, 3.0), 0.4, 2)


def small_config(temporal='suit') -> ModelConfig:
    return ModelConfig(temporal=temporal,
                       pillars=PillarConfig(point_range=(-25.6, -25.6, -3.0, 25.6, 25.6, 3.0),
                                            pillar_size=0.4, channels=16),
                       backbone=BackboneConfig(num_filters=(16, 32, 32),
                                               num_upsample_filters=(16, 16, 16)))


def peaks_heatmap(centres_cells, H=GRID.H, W=GRID.W):
    hm = torch.zeros(1, 4, H, W)
    for c, r in centres_cells:
        draw_gaussian(hm[0, 0], c, r, 2)
    return torch.logit(hm.clamp(1e-4, 1 - 1e-4))


def frame(t, seed=0, n=3000):
    rng = np.random.default_rng(seed)
    pts = np.c_[rng.uniform(-25, 25, (n, 2)), rng.uniform(-2, 0, n), rng.uniform(0, 1, n),
                np.zeros(n)].astype(np.float32)
    pts[:200, :2] = rng.normal([5 + 0.5 * t, 3], 0.5, (200, 2))      # a moving blob
    gt = Detections(np.array([[5 + 0.5 * t, 3, -1, 4.5, 1.9, 1.6, 0.0],
                              [-8, -6, -1, 0.7, 0.7, 1.8, 0]]),
                    np.array([[5.0, 0.0], [0.0, 0.0]]), np.ones(2), np.array([0, 2]))
    return Frame(pts, pose_from_xyz_rpy((t * 1.0, 0, 1.8), (0, 0, 0.01 * t)),
                 int(1e9 + t * 1e8), 'lidar', gt)


def cloud_in_grid(seed: int, n: int = 3000) -> np.ndarray:
    """``(n, 5)`` points (x, y, z, intensity, time lag 0) inside the small config's grid."""
    rng = np.random.default_rng(seed)
    return np.c_[rng.uniform(-20, 20, (n, 2)), rng.uniform(-1, 2, (n, 1)),
                 rng.uniform(0, 1, (n, 1)), np.zeros((n, 1))].astype(np.float32)

