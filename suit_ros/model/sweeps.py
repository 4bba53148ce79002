"""Multi-sweep input: the current sweep and the previous N-1, in the ground-referenced frame.

A model input is the current LiDAR sweep and the previous ``sweeps - 1`` sweeps, each moved into
the vehicle frame (base_link) at the current stamp with the odometry poses and the LiDAR
extrinsic, and tagged with its time lag (seconds) in the fifth column, as CenterPoint does on
nuScenes. Velocity becomes observable in one input; mounting height and tilt stop being a domain
gap (the ground is at z = 0 for every sensor).

One implementation serves every path: :func:`accumulate_sweeps` is called by
:class:`SweepBuffer` (the node and ``detect-bag``, through the streaming detector) and by
:func:`model_frame` (training and evaluation data).

A sweep whose points already carry non-zero time lags (a nuScenes keyframe with its sweeps, as
the dataset ships them) is an accumulation already: it is used as it is, without adding the
previous frames, and it clears the buffer.
"""
from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from suit_ros.ops.geometry import se3_inverse, transform_boxes
from suit_ros.ops.kernels import transform_sweep
from suit_ros.structures import Detections, Frame

DEFAULT_MAX_AGE_S = 0.5


def already_accumulated(points: NDArray[np.float32]) -> bool:
    """Whether a sweep's points carry time lags (a fifth column with a value > 0)."""
    return points.ndim == 2 and points.shape[1] == 5 and len(points) > 0 \
        and bool(points[:, 4].max() > 0)


@dataclass(frozen=True)
class Sweep:
    """One sweep as the sensor reported it.

    :param points: ``(N, 4)`` or ``(N, 5)`` float32 x, y, z, intensity (0..1) [, time lag] in
        the LiDAR frame.
    :param T_odom_lidar: ``(4, 4)`` float64 LiDAR pose at ``stamp_ns``.
    """

    points: NDArray[np.float32]
    T_odom_lidar: NDArray[np.float64]
    stamp_ns: int


def accumulate_sweeps(sweeps: Sequence[Sweep], T_base_lidar: NDArray[np.float64]
                      ) -> NDArray[np.float32]:
    """Stack sweeps (``sweeps[0]`` is the current one) in base_link at the current stamp.

    Transforms are composed in float64 (odometry coordinates can be kilometres) and applied
    relative to the current pose, so float32 points keep their precision.

    :return: ``(sum N_i, 5)`` float32 x, y, z, intensity, time lag (s, current sweep 0; a lag
        already present in a sweep's fifth column is kept and added to).
    """
    if not sweeps:
        raise ValueError('accumulate_sweeps needs at least the current sweep')
    now = sweeps[0]
    T_base_odom = np.asarray(T_base_lidar, np.float64) @ se3_inverse(now.T_odom_lidar)
    arrays = [np.ascontiguousarray(s.points, np.float32) for s in sweeps]
    for pts in arrays:
        if pts.ndim != 2 or pts.shape[1] not in (4, 5):
            raise ValueError(f'sweep points must be (N, 4) or (N, 5), got {pts.shape}')
    # one output written in place (no per-sweep parts to concatenate)
    out = np.empty((sum(len(p) for p in arrays), 5), np.float32)
    a = 0
    for i, (s, pts) in enumerate(zip(sweeps, arrays)):
        b = a + len(pts)
        T = (np.asarray(T_base_lidar, np.float64) if i == 0
             else T_base_odom @ np.asarray(s.T_odom_lidar, np.float64))
        # one pass a sweep (compiled): moved, intensity copied, lag written
        transform_sweep(pts, T[:3, :3].astype(np.float32), T[:3, 3].astype(np.float32),
                        np.float32((now.stamp_ns - s.stamp_ns) * 1e-9), out[a:b])
        a = b
    return out


class SweepBuffer:
    """The previous sweeps of a stream (bounded), kept beside the feature memory.

    :param sweeps: sweeps per model input (current included); 1 keeps nothing.
    :param max_age_s: previous sweeps older than this (relative to the current stamp) are
        dropped; a gap that long means the stream restarted.
    """

    def __init__(self, sweeps: int, max_age_s: float = DEFAULT_MAX_AGE_S) -> None:
        if sweeps < 1:
            raise ValueError(f'sweeps must be >= 1, got {sweeps}')
        self.sweeps = sweeps
        self.max_age_s = max_age_s
        self.past: deque[Sweep] = deque(maxlen=max(sweeps - 1, 0))
        # the time lags (s) of the sweeps in the last input :meth:`push` made, newest first
        self.last_lags_s: tuple[float, ...] = ()

    def clear(self) -> None:
        """Forget the previous sweeps (the next input has the current sweep only)."""
        self.past.clear()

    def __len__(self) -> int:
        return len(self.past)

    @property
    def nbytes(self) -> int:
        """Bytes of the buffered points."""
        return int(sum(s.points.nbytes for s in self.past))

    def push(self, points: NDArray[np.float32], T_odom_lidar: NDArray[np.float64] | None,
             stamp_ns: int, T_base_lidar: NDArray[np.float64]) -> NDArray[np.float32]:
        """Accumulate the current sweep with the buffered ones, then buffer it.

        :param T_odom_lidar: the LiDAR pose, or None: past sweeps cannot be placed, so the
            buffer is cleared and the input is the current sweep alone.
        :return: the model input ``(N, 5)`` in base_link.
        """
        if T_odom_lidar is None or already_accumulated(points):
            self.clear()
            self.last_lags_s = (0.0,)
            return accumulate_sweeps([Sweep(points, np.eye(4), stamp_ns)], T_base_lidar)
        current = self._current(points, T_odom_lidar, stamp_ns)
        used = [current, *reversed(self.past)]
        self.last_lags_s = tuple((stamp_ns - s.stamp_ns) * 1e-9 for s in used)
        out = accumulate_sweeps(used, T_base_lidar)
        if self.past.maxlen:
            self.past.append(current)
        return out

    def add(self, points: NDArray[np.float32], T_odom_lidar: NDArray[np.float64] | None,
            stamp_ns: int) -> bool:
        """Buffer a sweep that the model does not run on (a cloud the node skipped while it
        was busy), so the next input still holds the sweeps just before it, as in training.

        :param T_odom_lidar: the LiDAR pose, or None: the sweep cannot be placed and is not
            buffered (the buffered ones still can be).
        :return: whether it was buffered.
        """
        if T_odom_lidar is None:
            return False
        if already_accumulated(points):
            self.clear()
            return False
        current = self._current(points, T_odom_lidar, stamp_ns)
        if not self.past.maxlen:
            return False
        self.past.append(current)
        return True

    def _current(self, points: NDArray[np.float32], T_odom_lidar: NDArray[np.float64],
                 stamp_ns: int) -> Sweep:
        """The sweep at ``stamp_ns``, after dropping the buffered ones it outdates (all of
        them when time went backwards or repeated: the stream restarted)."""
        if self.past and stamp_ns <= self.past[-1].stamp_ns:
            self.clear()
        while self.past and stamp_ns - self.past[0].stamp_ns > self.max_age_s * 1e9:
            self.past.popleft()
        return Sweep(np.asarray(points, np.float32), np.asarray(T_odom_lidar, np.float64),
                     stamp_ns)


def model_frame(sequence: Sequence[Frame], t: int, sweeps: int,
                max_age_s: float = DEFAULT_MAX_AGE_S) -> Frame:
    """The model input for ``sequence[t]`` (sensor frames in time order): accumulated sweeps,
    GT and pose in base_link (``pose = T_odom_base``, ``T_base_lidar`` identity)."""
    f = sequence[t]
    T_bl = np.asarray(f.T_base_lidar, np.float64)
    past = [sequence[j] for j in range(t - 1, max(t - sweeps, -1), -1)]
    past = [p for p in past if 0 < f.stamp_ns - p.stamp_ns <= max_age_s * 1e9
            and not already_accumulated(f.points)]
    points = accumulate_sweeps([Sweep(f.points, f.pose, f.stamp_ns)]
                               + [Sweep(p.points, p.pose, p.stamp_ns) for p in past], T_bl)
    gt = f.gt
    if gt is not None:
        boxes, vel = transform_boxes(T_bl, gt.boxes, gt.velocities)
        gt = Detections(boxes, gt.velocities if vel is None else vel, gt.scores, gt.labels)
    ignore = f.ignore_boxes
    if ignore is not None:                  # in base_link with the GT
        ignore = transform_boxes(T_bl, np.asarray(ignore, np.float64).reshape(-1, 7))[0]
        ignore = ignore.astype(np.float32)
    return replace(f, points=points, pose=np.asarray(f.pose, np.float64) @ se3_inverse(T_bl),
                   gt=gt, T_base_lidar=np.eye(4), times=None, ignore_boxes=ignore,
                   owners=None)


def boxes_to_lidar(det: Detections, T_base_lidar: NDArray[np.float64]) -> Detections:
    """Detections in base_link moved into the LiDAR (cloud) frame."""
    if len(det) == 0:
        return det
    boxes, vel = transform_boxes(se3_inverse(np.asarray(T_base_lidar, np.float64)), det.boxes,
                                 det.velocities)
    return Detections(boxes, det.velocities if vel is None else vel, det.scores, det.labels)
