"""SE(3) helpers in float64 (numpy): poses, ego transforms, boxes and velocities between frames."""
from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from suit_ros.ops.kernels import as_float, count_in_box_cells, rectangle_cells


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


def transform_points(T: NDArray[np.float64], xyz: NDArray[np.floating[Any]]
                     ) -> NDArray[np.float64]:
    """Apply ``(4, 4)`` T to ``(N, 3)`` points, in float64."""
    out: NDArray[np.float64] = np.asarray(xyz, np.float64) @ T[:3, :3].T + T[:3, 3]
    return out


def transform_boxes(T: NDArray[np.float64], boxes: NDArray[np.floating[Any]],
                    velocities: NDArray[np.floating[Any]] | None = None
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


MIRROR_Y = np.diag([1.0, -1.0, 1.0, 1.0])   # across the x-z plane: left- <-> right-hand traffic


def mirror_transform(T: NDArray[np.floating[Any]]) -> NDArray[np.float64]:
    """A transform between two frames that are both mirrored across their x-z planes
    (``M T M``): still a rotation and a translation."""
    return np.asarray(MIRROR_Y @ np.asarray(T, np.float64) @ MIRROR_Y)


def mirror_points(points: NDArray[np.float32]) -> NDArray[np.float32]:
    """A copy of ``(N, >= 3)`` points with y negated (the other columns as they are)."""
    out = points.copy()
    out[:, 1] = -out[:, 1]
    return out


def mirror_boxes(boxes: NDArray[np.floating[Any]]) -> NDArray[np.float64]:
    """``(N, 7)`` boxes mirrored across the x-z plane: y and yaw negated (a float64 copy)."""
    b = np.asarray(boxes, np.float64).reshape(-1, 7).copy()
    b[:, 1] = -b[:, 1]
    b[:, 6] = -b[:, 6]
    return b


def wrap_angle(a: NDArray[np.floating[Any]] | float) -> NDArray[np.float64]:
    """Wrap angles to ``[-pi, pi)``."""
    return (np.asarray(a, np.float64) + np.pi) % (2.0 * np.pi) - np.pi


def pose_from_xyz_rpy(xyz: tuple[float, float, float] | NDArray[np.floating[Any]],
                      rpy: tuple[float, float, float] | NDArray[np.floating[Any]]
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


def in_box_frames(xyz: NDArray[np.floating[Any]], boxes: NDArray[np.floating[Any]]
                  ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Each point ``(N, 3)`` relative to each ``(M, 7)`` box's centre: ``(N, M)`` along its
    heading, across it (to the left) and up."""
    b = np.asarray(boxes, np.float64).reshape(-1, 7)
    d = np.asarray(xyz, np.float64)[:, None, :] - b[None, :, :3]
    c, s = np.cos(b[:, 6]), np.sin(b[:, 6])
    return d[..., 0] * c + d[..., 1] * s, -d[..., 0] * s + d[..., 1] * c, d[..., 2]


def points_in_boxes(xyz: NDArray[np.floating[Any]], boxes: NDArray[np.floating[Any]]
                    ) -> NDArray[np.bool_]:
    """``(N, M)`` membership of points in ``(M, 7)`` yaw-rotated boxes (closed intervals)."""
    if len(boxes) == 0:
        return np.zeros((len(xyz), 0), bool)
    b = np.asarray(boxes, np.float64)
    along, across, up = in_box_frames(xyz, b)
    inside: NDArray[np.bool_] = ((np.abs(along) <= b[:, 3] / 2)
                                 & (np.abs(across) <= b[:, 4] / 2)
                                 & (np.abs(up) <= b[:, 5] / 2))
    return inside


class CellIndex:
    """The points of a cloud that lie near some rectangles, by a coarse BEV grid.

    A grid of ``cell`` m over the rectangles' cells lists the rectangles each cell touches
    (:meth:`box_lists`); the compiled loops of :func:`count_points_in_boxes` and the tracker
    test each point against the rectangles of its cell, in one pass over the points.

    :param xy: ``(N, >= 2)`` points (x, y first).
    :param lo, hi: ``(M, 2)`` each rectangle's lower and upper corner (m).
    :param oriented: ``(M, 5)`` centre x, y, half length, half width and yaw of a rotated
        rectangle inside each axis-aligned one: a rectangle then keeps only the cells that its
        rotated rectangle can touch (a cell whose centre lies within half a cell diagonal of
        it), so a search along a heading reads a band, not the square around it.
    """

    def __init__(self, xy: NDArray[np.floating[Any]], lo: NDArray[np.floating[Any]],
                 hi: NDArray[np.floating[Any]], cell: float,
                 oriented: NDArray[np.floating[Any]] | None = None) -> None:
        lo_c = np.floor(np.asarray(lo, np.float64).reshape(-1, 2) / cell).astype(np.int64)
        hi_c = np.floor(np.asarray(hi, np.float64).reshape(-1, 2) / cell).astype(np.int64)
        self.points = as_float(xy)
        self.cell = cell
        self.rectangles = len(lo_c)
        # each rectangle's cells (flat, row-major) and its index, rectangle by rectangle
        self.flat = np.zeros(0, np.int64)
        self.owner = np.zeros(0, np.int64)
        self.origin = np.zeros(2, np.int64)
        self.shape = np.zeros(2, np.int64)
        if len(lo_c) == 0 or len(self.points) == 0:
            return
        origin = lo_c.min(0)
        shape = hi_c.max(0) - origin + 1
        band = (np.zeros((0, 5)) if oriented is None
                else np.ascontiguousarray(oriented, np.float64).reshape(-1, 5))
        self.flat, self.owner = rectangle_cells(lo_c - origin, hi_c - origin, int(shape[1]),
                                                origin, float(cell), band,
                                                float(cell * np.sqrt(0.5)))
        self.origin, self.shape = origin, shape

    @property
    def cells(self) -> list[NDArray[np.int64]]:
        """Each rectangle's cells (flat, row-major)."""
        counts = np.bincount(self.owner, minlength=self.rectangles)
        return np.split(self.flat, np.cumsum(counts)[:-1]) if self.rectangles else []

    @property
    def inv_cell(self) -> np.floating[Any]:
        """``1 / cell`` in the points' dtype (the kernels scale the points by it)."""
        return self.points.dtype.type(1.0 / self.cell)

    def points_near(self) -> NDArray[np.bool_]:
        """Which points lie in a cell that some rectangle touches."""
        near = np.zeros(len(self.points), bool)
        if not len(self.flat):
            return near
        touched = np.zeros(int(self.shape[0]) * int(self.shape[1]), bool)
        touched[self.flat] = True
        f = self.points[:, :2] * self.inv_cell         # as the kernels scale them
        rows = np.nonzero(np.isfinite(f).all(1))[0]
        ij = np.floor(f[rows]).astype(np.int64) - self.origin
        inside = (ij >= 0).all(1) & (ij < self.shape).all(1)
        near[rows[inside]] = touched[ij[inside, 0] * self.shape[1] + ij[inside, 1]]
        return near

    def box_lists(self) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """For each cell of the grid (row-major), the rectangles that touch it: ``boxes[
        start[k]:start[k + 1]]`` with ``start`` ``(cells + 1,)``."""
        n_cells = int(self.shape[0]) * int(self.shape[1])
        if not len(self.flat):
            return np.zeros(n_cells + 1, np.int64), np.zeros(0, np.int64)
        flat, owner = self.flat, self.owner
        order = np.argsort(flat, kind='stable')
        start = np.zeros(n_cells + 1, np.int64)
        np.cumsum(np.bincount(flat, minlength=n_cells), out=start[1:])
        return start, owner[order]


def count_points_in_boxes(xyz: NDArray[np.floating[Any]], boxes: NDArray[np.floating[Any]],
                          cell: float = 2.0) -> NDArray[np.uint32]:
    """Number of points inside each ``(M, 7)`` box (the rule of :func:`points_in_boxes`),
    in one pass over the points (each tested against the boxes of its :class:`CellIndex`
    cell; the boxes' bounding squares)."""
    b = np.asarray(boxes, np.float64).reshape(-1, 7)
    out = np.zeros(len(b), np.uint32)
    p = as_float(xyz)
    if len(p) == 0 or len(b) == 0:
        return out
    r = 0.5 * np.hypot(b[:, 3], b[:, 4])
    index = CellIndex(p, b[:, :2] - r[:, None], b[:, :2] + r[:, None], cell)
    start, owners = index.box_lists()
    counts: NDArray[np.uint32] = count_in_box_cells(
        p, index.inv_cell, index.origin, index.shape, start, owners, b, np.cos(b[:, 6]),
        np.sin(b[:, 6]))
    return counts


def thin_per_cell(cell: NDArray[np.integer[Any]], max_points: int) -> NDArray[np.bool_]:
    """Which points to keep so that each cell holds about ``max_points``: a point of a cell
    with ``c > max_points`` points is kept with probability ``max_points / c``, drawn from a
    hash of its index (deterministic, the same in training and inference); sparser cells keep
    every point.

    :param cell: ``(N,)`` a cell id per point (small non-negative integers: counted with
        ``bincount``).
    """
    c = np.asarray(cell)
    if len(c) == 0:
        return np.ones(0, bool)
    per_point = np.bincount(c)[c]
    h = (np.arange(len(c), dtype=np.uint64) * np.uint64(2654435761)) % np.uint64(4294967296)
    keep: NDArray[np.bool_] = h.astype(np.float64) < (max_points / per_point) * 4294967296.0
    return keep | (per_point <= max_points)
