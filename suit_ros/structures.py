"""Plain-numpy data structures shared by the model, the data sources, the node and evaluation."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray


@dataclass
class Detections:
    """One frame's 3D boxes (detections, or ground truth with ``scores == 1``).

    :param boxes: ``(N, 7)`` float32 ``x, y, z, l, w, h, yaw`` (geometric centre, REP 103).
    :param velocities: ``(N, 2)`` float32 ``vx, vy`` in m/s, absolute, in the boxes' frame
        (ground truth: NaN where unknown, an object annotated in one frame only).
    :param scores: ``(N,)`` float32 confidence in ``[0, 1]``.
    :param labels: ``(N,)`` int64 index into the class names.
    """

    boxes: NDArray[np.floating[Any]]
    velocities: NDArray[np.floating[Any]]
    scores: NDArray[np.floating[Any]]
    labels: NDArray[np.integer[Any]]

    def __post_init__(self) -> None:
        self.boxes = np.ascontiguousarray(self.boxes, dtype=np.float32).reshape(-1, 7)
        n = len(self.boxes)
        self.velocities = np.ascontiguousarray(self.velocities, dtype=np.float32).reshape(n, 2)
        self.scores = np.ascontiguousarray(self.scores, dtype=np.float32).reshape(n)
        self.labels = np.ascontiguousarray(self.labels, dtype=np.int64).reshape(n)

    def __len__(self) -> int:
        return len(self.boxes)

    @staticmethod
    def empty() -> Detections:
        """Return a frame with no boxes."""
        return Detections(np.zeros((0, 7), np.float32), np.zeros((0, 2), np.float32),
                          np.zeros(0, np.float32), np.zeros(0, np.int64))

    def concat(self, other: Detections) -> Detections:
        """Return these boxes followed by ``other``'s."""
        return Detections(np.concatenate([self.boxes, other.boxes]),
                          np.concatenate([self.velocities, other.velocities]),
                          np.concatenate([self.scores, other.scores]),
                          np.concatenate([self.labels, other.labels]))

    def select(self, mask: NDArray[np.bool_] | NDArray[np.int64]) -> Detections:
        """Return the boxes picked by a boolean mask or an index array."""
        return Detections(self.boxes[mask], self.velocities[mask], self.scores[mask],
                          self.labels[mask])


@dataclass
class Frame:
    """One LiDAR frame with everything the model, training and evaluation need.

    A *sensor frame* (what data sources yield) holds one sweep in the LiDAR frame; a *model
    frame* (what :class:`~suit_ros.model.detector.SUITDetector` trains on) holds the accumulated
    sweeps in the ground-referenced vehicle frame (base_link at the stamp), made by
    :func:`suit_ros.model.sweeps.model_frame`.

    :param points: ``(N, 5)`` float32 ``x, y, z, intensity (0..1), time_lag (s, >= 0)`` in the
        LiDAR frame (sensor frame) or base_link (model frame).
    :param pose: ``(4, 4)`` float64 ``T_odom_lidar`` at ``stamp_ns`` (sensor frame) or
        ``T_odom_base`` (model frame).
    :param gt: ground-truth boxes in the points' frame at the stamp, or None at inference.
    :param T_base_lidar: ``(4, 4)`` float64 LiDAR mounting extrinsic (identity in a model
        frame, or when the points are already in base_link).
    :param ignore_boxes: ``(M, 7)`` boxes (points' frame) of things that count as neither
        objects nor false positives in evaluation, nor background in training (real datasets:
        parked bicycles), or None.
    :param times: ``(N,)`` float32 each return's time after the stamp (s) in a sensor frame
        whose sweep was taken over time (:mod:`suit_ros.deskew`), or None: at one instant.
    :param owners: ``(N,)`` uint32 per return the GT object (instance id) whose surface it is
        on, 0 for none: a synthetic sensor frame's (None elsewhere, and after anything that
        changes the points' count or order). :func:`object_returns` counts with it.
    """

    points: NDArray[np.float32]
    pose: NDArray[np.float64]
    stamp_ns: int
    frame_id: str = 'lidar'
    gt: Detections | None = None
    num_points: NDArray[np.uint32] | None = None
    instance_ids: NDArray[np.uint32] | None = None
    sequence_id: str = ''
    T_base_lidar: NDArray[np.float64] = field(default_factory=lambda: np.eye(4))
    ignore_boxes: NDArray[np.float32] | None = None
    times: NDArray[np.float32] | None = None
    owners: NDArray[np.uint32] | None = None


def object_returns(xyz: NDArray[np.floating[Any]], boxes: NDArray[np.floating[Any]],
                   owners: NDArray[np.integer[Any]] | None = None,
                   ids: NDArray[np.integer[Any]] | None = None) -> NDArray[np.uint32]:
    """Each object's returns: those in its box, or its own (``owners == ids[i]``) where more.

    Range noise puts returns just outside a box's faces, and a sweep taken while the sensor and
    the object move puts a moving object's returns up to a sweep's motion outside its box at
    the stamp; counted in its box alone, such a visible object would count 0.
    """
    from suit_ros.ops.geometry import count_points_in_boxes
    num = count_points_in_boxes(np.asarray(xyz)[:, :3], boxes).astype(np.uint32)
    if owners is None or ids is None or not len(ids):
        return num
    ids = np.asarray(ids, np.int64)
    owned = np.asarray(owners, np.int64)
    order = np.argsort(ids)
    own = np.bincount(np.searchsorted(ids[order], owned[np.isin(owned, ids)]),
                      minlength=len(ids))[np.argsort(order)]
    return np.asarray(np.maximum(num, own), np.uint32)
