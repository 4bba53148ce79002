"""SE(3) helpers in float64 (numpy): poses, ego transforms, boxes and velocities between frames."""
from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


def se3_inverse(T: NDArray[np.float64]) -> NDArray[np.float64]:
    """Invert a rigid transform ``(4, 4)`` exactly (R^T, -R^T t)."""
    R = T[:3, :3]
    out = np.eye(4, dtype=np.float64)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ T[:3, 3]
    return out


def ego_transform(pose_now: NDArray[np.float64], pose_prev: NDArray[np.float64]
                  ) -> NDArray[np.float64]:
    """Return ``T_now_prev = inv(T_odom_now) @ T_odom_prev``: previous LiDAR frame -> current."""
    return se3_inverse(np.asarray(pose_now, np.float64)) @ np.asarray(pose_prev, np.float64)


def yaw_of(T: NDArray[np.float64]) -> float:
    """Heading of a transform's rotation about +z (radians)."""
    return float(np.arctan2(T[1, 0], T[0, 0]))


def transform_points(T: NDArray[np.float64], xyz: NDArray[np.floating]) -> NDArray[np.float64]:
    """Apply ``(4, 4)`` T to ``(N, 3)`` points, in float64."""
    xyz = np.asarray(xyz, np.float64)
    return xyz @ T[:3, :3].T + T[:3, 3]


def transform_boxes(T: NDArray[np.float64], boxes: NDArray[np.floating],
                    velocities: NDArray[np.floating] | None = None
                    ) -> tuple[NDArray[np.float32], NDArray[np.float32] | None]:
    """Move ``(N, 7)`` boxes (and ``(N, 2)`` velocities) into another frame by T.

    The rotation is assumed to be mostly about z (ground vehicles): yaw gains the transform's
    yaw; velocities are rotated (they are free vectors: no translation).
    """
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    out = boxes.copy()
    out[:, :3] = transform_points(T, boxes[:, :3])
    out[:, 6] = wrap_angle(boxes[:, 6] + yaw_of(T))
    vel_out = None
    if velocities is not None:
        v = np.zeros((len(boxes), 3))
        v[:, :2] = np.asarray(velocities, np.float64).reshape(-1, 2)
        vel_out = (v @ T[:3, :3].T)[:, :2].astype(np.float32)
    return out.astype(np.float32), vel_out


def wrap_angle(a: NDArray[np.floating] | float) -> NDArray[np.float64]:
    """Wrap angles to ``[-pi, pi)``."""
    return (np.asarray(a, np.float64) + np.pi) % (2.0 * np.pi) - np.pi


def pose_from_xyz_rpy(xyz: tuple[float, float, float] | NDArray[np.floating],
                      rpy: tuple[float, float, float] | NDArray[np.floating]
                      ) -> NDArray[np.float64]:
    """Build ``(4, 4)`` from a translation and roll, pitch, yaw (ZYX, as URDF/tf)."""
    r, p, y = (float(v) for v in rpy)
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    T = np.eye(4)
    T[:3, :3] = [[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                 [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                 [-sp, cp * sr, cp * cr]]
    T[:3, 3] = np.asarray(xyz, np.float64)
    return T
