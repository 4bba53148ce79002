"""Velocity filter: constant-velocity Kalman tracks over the detections, in the odometry frame.

The head reads an object's velocity from one model frame (a few sweeps, 0.2 s at 10 Hz), and on
CPU-scale training that reading is coarse (docs/results.md). Over several frames the box centres
say more: a car at 10 m/s moves a metre a frame, against centre errors of a few decimetres.

:class:`VelocityFilter` keeps one track per object. Each frame it predicts the tracks to the
frame's stamp and associates the detections to them: same class only, greedy by the
Mahalanobis distance of the centre within a chi-square gate, the confident detections (score >=
``birth_score``) first and the faint ones for the tracks left, and only a confident detection
starts a track (the two-stage association of ByteTrack, so a faint false positive cannot start a
track that takes a real object's detection). A matched detection's centre and the head's
velocity update the track's Kalman filter on ``x, y, vx, vy`` (odometry frame, white-noise
acceleration); the detection's output velocity is the track's posterior. A new track starts at
the head's velocity, so an object's first frame is unchanged, and a faint detection no track
takes keeps the head's velocity.

A tracked detection's score is also smoothed over its track (``score_mix``): ``(1 - mix) x``
its own score ``+ mix x`` the track's running score (each earlier detection weighing half as
much as the next), so an object seen confidently for a while keeps its rank through one weak
frame.

Tracks live in the odometry frame, so ego motion does not move them; they are forgotten by the
same rules as the sweeps (no pose, a time jump, a new sequence, a reset). Every detection gets
a track id (``0``: none).

The settings (:class:`FilterConfig` defaults) were chosen on the ``tune`` split (seeds 8000+,
never trained or validated on) with ``scripts/tune_velocity_filter.py``:
docs/experiments/velocity_filter.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from suit_ros.structures import Detections


@dataclass(frozen=True)
class FilterConfig:
    """Noise model and track bookkeeping of :class:`VelocityFilter`.

    :param pos_sigma: box-centre measurement noise (m, per axis).
    :param vel_sigma: the head's velocity measurement noise (m/s, per axis).
    :param accel_sigma: process noise, white acceleration (m/s^2, per axis).
    :param gate: association gate, squared Mahalanobis distance of the centre (2 dof).
    :param birth_score: detections at least this confident are associated first and may start
        tracks; the others only continue tracks (their velocity is the head's when none is
        left for them).
    :param score_mix: weight of the track's running score in a tracked detection's score (0:
        the model's scores unchanged).
    :param max_misses: frames a track survives without a detection.
    :param max_gap_s: a longer gap between frames (or time going back) drops every track.
    """

    pos_sigma: float = 0.3
    vel_sigma: float = 4.5
    accel_sigma: float = 2.0
    gate: float = 13.8
    birth_score: float = 0.4
    score_mix: float = 0.7
    max_misses: int = 6
    max_gap_s: float = 0.5

    def __post_init__(self) -> None:
        for name in ('pos_sigma', 'vel_sigma', 'accel_sigma', 'gate', 'max_gap_s'):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f'FilterConfig.{name} must be finite and > 0, got {value}')
        for name in ('birth_score', 'score_mix'):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f'FilterConfig.{name} must be within 0..1, got {value}')
        if self.max_misses < 0:
            raise ValueError(f'FilterConfig.max_misses must be >= 0, got {self.max_misses}')


class VelocityFilter:
    """Tracks over frames; :meth:`update` returns the detections with filtered velocities.

    The two horizontal axes have the same noise and are measured together, so their
    ``(position, velocity)`` covariances are equal and uncorrelated: one 2 x 2 covariance per
    track (:attr:`P`) serves both, and every inverse is a 2 x 2 one in closed form.
    """

    def __init__(self, config: FilterConfig | None = None) -> None:
        self.config = config or FilterConfig()
        self.next_id = 1
        self.stamp_ns: int | None = None
        self.reset()

    def reset(self) -> None:
        """Forget every track (ids keep counting up)."""
        self.x = np.zeros((0, 4))               # x, y, vx, vy (odometry frame)
        self.P = np.zeros((0, 2, 2))            # per axis: (position, velocity) covariance
        self.labels = np.zeros(0, np.int64)
        self.ids = np.zeros(0, np.int64)
        self.misses = np.zeros(0, np.int64)
        self.score = np.zeros(0)                # running score (halving weights)
        self.stamp_ns = None

    def __len__(self) -> int:
        return len(self.x)

    def _predict(self, dt: float) -> None:
        F = np.array([[1.0, dt], [0.0, 1.0]])
        Q = np.array([[dt ** 4 / 4, dt ** 3 / 2], [dt ** 3 / 2, dt ** 2]]) \
            * self.config.accel_sigma ** 2
        self.x[:, :2] += dt * self.x[:, 2:]
        self.P = F @ self.P @ F.T + Q

    def _associate(self, centres: NDArray[np.float64], labels: NDArray[np.int64],
                   confident: NDArray[np.bool_]) -> NDArray[np.int64]:
        """Track index per detection (-1: none): greedy over the gated pairs, nearest first,
        the confident detections before the others."""
        match = np.full(len(centres), -1, np.int64)
        if len(self.x) == 0 or len(centres) == 0:
            return match
        var = self.P[:, 0, 0] + self.config.pos_sigma ** 2                # (M,) per axis
        d = centres[None, :, :] - self.x[:, None, :2]                    # (M, N, 2)
        m2 = (d ** 2).sum(-1) / var[:, None]                             # squared Mahalanobis
        ok = (self.labels[:, None] == labels[None, :]) & (m2 < self.config.gate)
        used_t = np.zeros(len(self.x), bool)
        for stage in (confident, ~confident):
            rows, cols = np.nonzero(ok & stage[None, :])
            for k in np.argsort(m2[rows, cols], kind='stable'):
                t, n = rows[k], cols[k]
                if not used_t[t] and match[n] < 0:
                    used_t[t] = True
                    match[n] = t
        return match

    def update(self, det: Detections, stamp_ns: int, T_odom_frame: NDArray[np.float64]
               ) -> tuple[Detections, NDArray[np.int64]]:
        """Filter one frame's detections.

        :param det: detections in some frame (absolute velocities in that frame).
        :param T_odom_frame: that frame's pose in the odometry frame at ``stamp_ns``.
        :return: the detections with filtered velocities and smoothed scores, and their track
            ids (0, and the model's velocity and score, for a detection below ``birth_score``
            that no track took).
        """
        cfg = self.config
        T = np.asarray(T_odom_frame, np.float64)
        if self.stamp_ns is not None:
            dt = (stamp_ns - self.stamp_ns) * 1e-9
            if not 0 < dt <= cfg.max_gap_s:
                self.reset()
            else:
                self._predict(dt)
        self.stamp_ns = stamp_ns
        R = T[:2, :2]
        centres = det.boxes[:, :2].astype(np.float64) @ R.T + T[:2, 3]
        vel = det.velocities.astype(np.float64) @ R.T
        confident = det.scores >= cfg.birth_score
        match = self._associate(centres, np.asarray(det.labels, np.int64), confident)
        Rm = np.diag([cfg.pos_sigma ** 2, cfg.vel_sigma ** 2])            # per axis
        hit = match >= 0
        if hit.any():
            t = match[hit]
            P = self.P[t]                                                  # (H, 2, 2)
            S = P + Rm                                                     # measurement: H = I
            det_S = S[:, 0, 0] * S[:, 1, 1] - S[:, 0, 1] * S[:, 1, 0]
            S_inv = np.stack([np.stack([S[:, 1, 1], -S[:, 0, 1]], -1),
                              np.stack([-S[:, 1, 0], S[:, 0, 0]], -1)], -2) / det_S[:, None, None]
            K = P @ S_inv                                                  # (H, 2, 2)
            for axis in range(2):                                          # x then y
                cols = np.array([axis, axis + 2])
                state = self.x[t][:, cols]
                meas = np.stack([centres[hit, axis], vel[hit, axis]], -1)
                self.x[np.ix_(t, cols)] = state + np.einsum('nij,nj->ni', K, meas - state)
            self.P[t] = P - K @ P
        scores = det.scores.astype(np.float64)
        if hit.any():
            t = match[hit]
            scores[hit] = (1 - cfg.score_mix) * scores[hit] + cfg.score_mix * self.score[t]
            self.score[t] = 0.5 * (self.score[t] + det.scores[hit])
        seen = np.zeros(len(self.x), bool)
        seen[match[hit]] = True
        self.misses = np.where(seen, 0, self.misses + 1)
        new = ~hit & confident
        n_new = int(new.sum())
        new_ids = np.arange(self.next_id, self.next_id + n_new, dtype=np.int64)
        self.next_id += n_new
        ids = np.zeros(len(det), np.int64)
        ids[hit] = self.ids[match[hit]]
        ids[new] = new_ids
        rows = np.full(len(det), -1, np.int64)
        rows[hit] = match[hit]
        rows[new] = len(self.x) + np.arange(n_new)
        self.x = np.concatenate([self.x, np.concatenate([centres, vel], 1)[new]])
        self.P = np.concatenate([self.P, np.broadcast_to(Rm, (n_new, 2, 2))])
        self.labels = np.concatenate([self.labels, det.labels[new]])
        self.ids = np.concatenate([self.ids, new_ids])
        self.misses = np.concatenate([self.misses, np.zeros(n_new, np.int64)])
        self.score = np.concatenate([self.score, det.scores[new]])
        out_vel = det.velocities.astype(np.float64)             # untracked: the head's
        tracked = rows >= 0
        out_vel[tracked] = self.x[rows[tracked], 2:] @ R
        keep = self.misses <= cfg.max_misses
        self.x, self.P = self.x[keep], self.P[keep]
        self.labels, self.ids, self.misses = self.labels[keep], self.ids[keep], self.misses[keep]
        self.score = self.score[keep]
        return Detections(det.boxes, out_vel, scores, det.labels), ids
