"""The side of the road traffic keeps to, read from the traffic itself (``traffic_side: auto``).

The shipped models read a parked vehicle's front partly off the side of the road it stands
on, as right-hand traffic parks it (docs/experiments/either_way): in left-hand traffic half
the car headings come out turned round unless the node mirrors the world for the model
(``traffic_side: left``). A user who forgets the parameter, or a car that crosses a border,
gets flipped boxes. The traffic says which side it keeps to: on a two-way road the oncoming
vehicles pass on the driver's side, the ego's left in right-hand traffic and its right in
left-hand traffic.

:class:`TrafficSideVote` watches the tracked vehicles while the ego drives forward (at least
``min_ego_speed`` by its odometry). A track that comes towards the ego (its filtered velocity
within ``oncoming_angle`` of straight against the ego's heading, at least ``min_speed`` and
half the ego's speed) as it comes by (``min_lateral`` to ``max_lateral`` beside the ego and
within ``max_ahead`` along it: near abeam, where a bend in the road has not yet moved the
oncoming lane across the ego's axis) in ``frames`` updates votes once, by the side its mean
offset says. The positions and the velocities come from the tracker, so the vote does not
depend on the headings it is there to put right, nor on the side in use when it was cast. The
side in use changes when ``min_votes`` of the latest ``window`` votes say the other side: 4 of
the latest 5, from the start as after a long stretch, so that a false change is undone as
fast as it was made. Parked and crossing vehicles and one-way streets cast no votes; nor does
anything while the ego stands or the odometry is missing (a frozen odometry would make the
parked cars beside the ego look oncoming).
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

    min_speed: float = 3.0            # m/s, the track's filtered speed (and half the ego's)
    oncoming_angle: float = 30.0      # degrees from straight against the ego's heading
    min_lateral: float = 1.5          # m across the ego's heading (its own lane: no vote)
    max_lateral: float = 10.0         # (a parallel road's near lane runs the other way)
    max_ahead: float = 15.0           # m along the ego's heading, either way
    frames: int = 3                   # updates a track is seen so before it votes
    min_ego_speed: float = 2.0        # m/s forward, by the odometry
    max_pose_gap_s: float = 1.0       # the ego's speed from poses at most this far apart
    window: int = 5                   # the latest votes weighed
    min_votes: int = 4                # of them for the other side, to change to it

    def __post_init__(self) -> None:
        if not (self.min_speed > 0 and 0 < self.oncoming_angle < 90
                and 0 <= self.min_lateral < self.max_lateral and self.max_ahead > 0
                and self.frames >= 1 and self.min_ego_speed > 0 and self.max_pose_gap_s > 0
                and self.window // 2 < self.min_votes <= self.window):
            raise ValueError(f'invalid SideVoteConfig: {self}')


class TrafficSideVote:
    """The side in use and the votes for it (one per sensor stream; see the module).

    :param class_names: the detector's classes; the vehicles' (:data:`VEHICLE_CLASSES`) vote,
        not cyclists, whose lane is the kerb's in either traffic.
    :param start: the side until the traffic says otherwise.
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
        self.ego_speed = math.nan          # m/s forward at the last update (nan: unknown)
        self._last_pose: tuple[NDArray[np.float64], int] | None = None
        # track id -> [updates seen oncoming, sum of its lateral offsets, last update seen];
        # it votes at the update its count reaches ``frames``
        self._tracks: dict[int, list[float]] = {}

    def restart(self, start: TrafficSide) -> None:
        """Forget the votes and the tracks; use ``start`` until the traffic says otherwise
        (the ego's last pose stands)."""
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
            why = ('no odometry: no tracked velocities' if self._last_pose is None
                   else 'no oncoming traffic seen yet')
            return f'{self.side} (auto: {why})'
        return (f'{self.side} (auto: of the latest {right + left} oncoming vehicles, '
                f'{right} passed on the left, {left} on the right)')

    def _ego_speed(self, T_odom_base: NDArray[np.floating[Any]] | None, stamp_ns: int) -> float:
        """The ego's forward speed since the last pose (nan: no pose, or too long ago)."""
        if T_odom_base is None:
            self._last_pose = None
            return math.nan
        T = np.asarray(T_odom_base, np.float64)
        last, self._last_pose = self._last_pose, (T, stamp_ns)
        if last is None:
            return math.nan
        dt = (stamp_ns - last[1]) * 1e-9
        if not 0.0 < dt <= self.config.max_pose_gap_s:
            return math.nan
        return float((T[:3, 3] - last[0][:3, 3]) @ T[:3, 0]) / dt

    def update(self, boxes: NDArray[np.floating[Any]], velocities: NDArray[np.floating[Any]],
               labels: NDArray[np.integer[Any]], track_ids: NDArray[np.integer[Any]],
               T_base_frame: NDArray[np.floating[Any]],
               T_odom_base: NDArray[np.floating[Any]] | None, stamp_ns: int) -> bool:
        """Take one frame's tracked detections; return whether the side in use changed.

        :param boxes: ``(N, 7)`` in the detections' frame (the LiDAR's), in the real world
            (mirrored back where the model saw it mirrored).
        :param velocities: ``(N, 2)`` absolute, in the same frame.
        :param track_ids: per box its track (0: untracked: it does not vote).
        :param T_base_frame: ``(4, 4)`` the detections' frame in the vehicle's base frame
            (x forward: the ego's heading).
        :param T_odom_base: the ego's pose at ``stamp_ns`` (None: no odometry), in the real
            world: its forward speed from the last one.
        """
        cfg = self.config
        self.updates += 1
        self.ego_speed = self._ego_speed(T_odom_base, stamp_ns)
        ids = np.asarray(track_ids, np.int64).reshape(-1)
        keep = (ids > 0) & np.isin(np.asarray(labels).reshape(-1), self.vehicle_labels)
        if keep.any() and self.ego_speed >= cfg.min_ego_speed:
            T = np.asarray(T_base_frame, np.float64)
            b = np.asarray(boxes, np.float64).reshape(-1, 7)[keep]
            v = np.asarray(velocities, np.float64).reshape(-1, 2)[keep]
            centre = b[:, :3] @ T[:3, :3].T + T[:3, 3]
            vel = v @ T[:2, :2].T
            speed = np.hypot(vel[:, 0], vel[:, 1])
            against = -vel[:, 0] / np.maximum(speed, 1e-9)
            lateral = np.abs(centre[:, 1])
            oncoming = ((speed >= max(cfg.min_speed, 0.5 * self.ego_speed))
                        & (against >= math.cos(math.radians(cfg.oncoming_angle)))
                        & (lateral >= cfg.min_lateral) & (lateral <= cfg.max_lateral)
                        & (np.abs(centre[:, 0]) <= cfg.max_ahead))
            for tid, y in zip(ids[keep][oncoming].tolist(), centre[oncoming, 1].tolist()):
                entry = self._tracks.setdefault(tid, [0.0, 0.0, 0.0])
                entry[0] += 1.0
                entry[1] += y
                entry[2] = self.updates
                if entry[0] == cfg.frames:
                    self.votes.append('right' if entry[1] > 0 else 'left')
        for tid in [t for t, e in self._tracks.items() if self.updates - e[2] > 50]:
            del self._tracks[tid]               # long gone (the tracker forgets in ~6 frames)
        return self._decide()

    def _decide(self) -> bool:
        right, left = self.counts
        other: TrafficSide = 'left' if self.side == 'right' else 'right'
        if (left if other == 'left' else right) >= self.config.min_votes:
            self.side = other
            self.switches += 1
            return True
        return False
