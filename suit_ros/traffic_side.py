"""The side of the road traffic keeps to, read from the traffic itself (``traffic_side: auto``).

The shipped models read a parked vehicle's front partly off the side of the road it stands
on, as right-hand traffic parks it (docs/experiments/either_way): in left-hand traffic half
the car headings come out turned round unless the node mirrors the world for the model
(``traffic_side: left``). A user who forgets the parameter, or a car that crosses a border,
gets flipped boxes. The traffic says which side it keeps to: on a two-way road the oncoming
vehicles pass on the driver's side, the ego's left in right-hand traffic and its right in
left-hand traffic.

:class:`TrafficSideVote` watches the tracked vehicles. A track that comes towards the ego
(its filtered velocity within ``oncoming_angle`` of straight against the ego's heading, at
least ``min_speed``), beside it (``min_lateral`` to ``max_lateral`` across, within
``max_ahead`` along) in ``frames`` updates votes once, by the side it passed on (its mean
lateral offset). The positions and the velocities come from the tracker, so the vote does not
depend on the headings it is there to put right, nor on the side in use when it was cast.
The side in use changes when at least ``min_votes`` of the latest ``window`` votes, and at
least ``share`` of them, say the other side: from an empty window, 3 vehicles in a row; after
a long stretch on one side, 12 of the last 15. Parked and crossing vehicles, and one-way
streets, cast no votes.
"""
from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from suit_ros.params import TrafficSide

VEHICLE_CLASSES = ('car', 'truck', 'bus')


@dataclass(frozen=True)
class SideVoteConfig:
    """When a tracked vehicle votes, and when the votes change the side (see the module)."""

    min_speed: float = 3.0            # m/s, the track's filtered speed
    oncoming_angle: float = 30.0      # degrees from straight against the ego's heading
    min_lateral: float = 1.0          # m across the ego's heading (its own lane: no vote)
    max_lateral: float = 20.0
    max_ahead: float = 50.0           # m along the ego's heading, either way
    frames: int = 3                   # updates a track is seen oncoming before it votes
    window: int = 15                  # the latest votes weighed
    min_votes: int = 3
    share: float = 0.8

    def __post_init__(self) -> None:
        if not (self.min_speed > 0 and 0 < self.oncoming_angle < 90
                and 0 <= self.min_lateral < self.max_lateral and self.max_ahead > 0
                and self.frames >= 1 and 1 <= self.min_votes <= self.window
                and 0.5 < self.share <= 1.0):
            raise ValueError(f'invalid SideVoteConfig: {self}')


class TrafficSideVote:
    """The side in use and the votes for it (one per sensor stream; see the module).

    :param start: the side until the traffic says otherwise.
    :param class_names: the detector's classes; the vehicles' (:data:`VEHICLE_CLASSES`) vote,
        not cyclists, whose lane is the kerb's in either traffic.
    """

    def __init__(self, class_names: Sequence[str], start: TrafficSide = 'right',
                 config: SideVoteConfig | None = None) -> None:
        self.config = config or SideVoteConfig()
        self.side: TrafficSide = start
        self.vehicle_labels = np.asarray([i for i, name in enumerate(class_names)
                                          if name in VEHICLE_CLASSES], np.int64)
        self.votes: deque[TrafficSide] = deque(maxlen=self.config.window)
        self.switches = 0
        self.updates = 0
        # track id -> [updates seen oncoming, sum of its lateral offsets, last update seen,
        # voted (1) or not (0)]
        self._tracks: dict[int, list[float]] = {}

    def restart(self, start: TrafficSide) -> None:
        """Forget the votes and the tracks; use ``start`` until the traffic says otherwise."""
        self.side = start
        self.votes.clear()
        self._tracks.clear()

    @property
    def counts(self) -> tuple[int, int]:
        """The latest votes: (for right-hand traffic, for left-hand traffic)."""
        right = sum(1 for v in self.votes if v == 'right')
        return right, len(self.votes) - right

    def describe(self) -> str:
        """The side and the votes behind it, for diagnostics and logs."""
        right, left = self.counts
        if not right + left:
            return f'{self.side} (auto: no oncoming traffic seen yet)'
        return (f'{self.side} (auto: of the latest {right + left} oncoming vehicles, '
                f'{right} passed on the left, {left} on the right)')

    def update(self, boxes: NDArray[np.floating[Any]], velocities: NDArray[np.floating[Any]],
               labels: NDArray[np.integer[Any]], track_ids: NDArray[np.integer[Any]],
               T_base_frame: NDArray[np.floating[Any]]) -> bool:
        """Take one frame's tracked detections; return whether the side in use changed.

        :param boxes: ``(N, 7)`` in the detections' frame (the LiDAR's), in the real world
            (mirrored back where the model saw it mirrored).
        :param velocities: ``(N, 2)`` absolute, in the same frame.
        :param track_ids: per box its track (0: untracked: it does not vote).
        :param T_base_frame: ``(4, 4)`` the detections' frame in the vehicle's base frame
            (x forward: the ego's heading).
        """
        cfg = self.config
        self.updates += 1
        T = np.asarray(T_base_frame, np.float64)
        ids = np.asarray(track_ids, np.int64).reshape(-1)
        keep = (ids > 0) & np.isin(np.asarray(labels).reshape(-1), self.vehicle_labels)
        if keep.any():
            b = np.asarray(boxes, np.float64).reshape(-1, 7)[keep]
            v = np.asarray(velocities, np.float64).reshape(-1, 2)[keep]
            centre = b[:, :3] @ T[:3, :3].T + T[:3, 3]
            vel = v @ T[:2, :2].T
            speed = np.hypot(vel[:, 0], vel[:, 1])
            against = -vel[:, 0] / np.maximum(speed, 1e-9)
            lateral = np.abs(centre[:, 1])
            oncoming = ((speed >= cfg.min_speed)
                        & (against >= math.cos(math.radians(cfg.oncoming_angle)))
                        & (lateral >= cfg.min_lateral) & (lateral <= cfg.max_lateral)
                        & (np.abs(centre[:, 0]) <= cfg.max_ahead))
            for tid, y in zip(ids[keep][oncoming].tolist(), centre[oncoming, 1].tolist()):
                entry = self._tracks.setdefault(tid, [0.0, 0.0, 0.0, 0.0])
                entry[0] += 1.0
                entry[1] += y
                entry[2] = self.updates
                if entry[3] == 0.0 and entry[0] >= cfg.frames:
                    entry[3] = 1.0
                    self.votes.append('right' if entry[1] > 0 else 'left')
        for tid in [t for t, e in self._tracks.items() if self.updates - e[2] > 50]:
            del self._tracks[tid]               # long gone (the tracker forgets in ~6 frames)
        return self._decide()

    def _decide(self) -> bool:
        cfg = self.config
        right, left = self.counts
        other: TrafficSide = 'left' if self.side == 'right' else 'right'
        against = left if other == 'left' else right
        if against >= cfg.min_votes and against >= cfg.share * (right + left):
            self.side = other
            self.switches += 1
            return True
        return False
