"""Tracker: constant-velocity Kalman tracks over the detections, in the odometry frame.

The head reads an object's velocity from one model frame (a few sweeps, 0.2 s at 10 Hz), and on
CPU-scale training that reading is coarse (docs/results.md). Over several frames the box centres
say more: a car at 10 m/s moves a metre a frame, against centre errors of a few decimetres.

:class:`Tracker` keeps one track per object. Each frame it predicts the tracks to the
frame's stamp and associates the detections to them: same class only, greedy by the
Mahalanobis distance of the centre within a chi-square gate, the confident detections (score >=
``birth_score``) first and the faint ones for the tracks left, and only a confident detection
starts a track (the two-stage association of ByteTrack, so a faint false positive cannot start a
track that takes a real object's detection). A matched detection's centre and the head's
velocity update the track's Kalman filter on ``x, y, vx, vy`` (odometry frame, white-noise
acceleration); the detection's output velocity is the track's posterior. A new track starts at
the measured velocity (the head's, fused with the sweeps' below), and so does a faint detection
that no track takes.

The head is not the only velocity reading: the model input holds the current sweep and the
earlier ones with ego motion removed, and a moving vehicle's returns are smeared along its path.
:func:`sweep_velocities` reads each vehicle box's speed along its heading from how its returns
shift between the sweeps; where it can be read it is fused with the head's velocity (inverse
variance, ``sweep_sigma`` against ``vel_sigma``) before the Kalman update, so even an object's
first frame gets it. Each earlier sweep reads a speed of its own too; a reading whose sweeps
disagree counts for less (``sweep_spread_gain``), and one that a single earlier sweep gave
counts as ``sweep_single_sigma`` says.

A tracked detection's score is also smoothed over its track (``score_mix``): ``(1 - mix) x``
its own score ``+ mix x`` the track's running score (each earlier detection weighing half as
much as the next), so an object seen confidently for a while keeps its rank through one weak
frame.

Tracks live in the odometry frame, so ego motion does not move them; they are forgotten by the
same rules as the sweeps (no pose, a time jump, a new sequence, a reset). Every detection gets
a track id (``0``: none).

The settings (:class:`TrackerConfig` defaults) were chosen on the ``tune`` split (seeds 8000+,
never trained or validated on) with ``scripts/tune_tracker.py``:
docs/experiments/velocity_filter.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from suit_ros.ops.geometry import CellIndex, wrap_angle
from suit_ros.ops.kernels import as_float, distinct_values, rays_through, sweep_histograms_by_cell
from suit_ros.structures import Detections


@dataclass(frozen=True)
class TrackerConfig:
    """Noise model and track bookkeeping of :class:`Tracker`.

    :param pos_sigma: box-centre measurement noise (m, per axis).
    :param vel_sigma: the head's velocity measurement noise (m/s, per axis).
    :param accel_sigma: process noise, white acceleration (m/s^2, per axis).
    :param gate: association gate, squared Mahalanobis distance of the centre (2 dof).
    :param birth_score: detections at least this confident are associated first and may start
        tracks; the others only continue tracks (their velocity is the measured one when none
        is left for them).
    :param score_mix: weight of the track's running score in a tracked detection's score (0:
        the model's scores unchanged).
    :param sweep_sigma: noise (m/s, per axis) of the velocity read from the sweeps
        (:func:`sweep_velocities`), fused with the head's; None: not read.
    :param sweep_spread_gain: the reading's noise grows with how far its earlier sweeps'
        own speeds lie apart: ``sqrt(sweep_sigma^2 + (gain * spread)^2)``; 0: every reading
        at ``sweep_sigma``.
    :param sweep_single_sigma: the noise of a reading only one earlier sweep gave (no spread
        to judge it by: a stream's second frame, a car seen in the last sweep but not the one
        before); None: not fused. Only read with ``sweep_spread_gain``.
    :param sweep_classes: the classes it is read for (they move along their heading), on
        detections scoring at least ``sweep_min_score``.
    :param heading_min_speed: a tracked vehicle (``sweep_classes``) whose filtered velocity is
        faster than this (m/s) and at least twice its standard deviation is turned round when
        its box's heading points more than 90 degrees away from that velocity (vehicles drive
        forwards); None: headings as the model gives them.
    :param max_miss_s: seconds a track survives without a detection (whole frames, up to a
        quarter of a frame interval more, for stamp jitter), about the same time at any
        sensor rate and under overload (a node that runs on every other cloud). It was
        ``max_misses``, 6 frames: 0.6 s at 10 Hz but 0.3 s at 20 Hz and 1.2 s at half rate
        (docs/experiments/track_time).
    :param max_gap_s: a longer gap between frames (or time going back) drops every track.
    :param coast_s: a confident track (running score >= ``birth_score``) that gets no
        detection is published where it is predicted to be, for up to this many seconds since
        its last detection (whole frames, as ``max_miss_s``; and while it lives), while the
        current sweep shows nothing in or beyond its box on its bearings (:func:`unseen`: a
        lost sector, a blocked sensor, the shadow of an occluder): an object that drove off
        leaves road returns, or a wall seen past it, where the track expects it and is not
        held (0: off; 0.5 s, 5 frames at 10 Hz: docs/experiments/coast; was ``coast_frames``).
    :param coast_margin: see ``coast_s`` (m the box is grown by).
    :param carried_refresh: a carried detection (a carry branch's box where the cloud has no
        returns: :meth:`Tracker.update`'s ``carried``) keeps its track alive and may start
        one; off (default), a track held only by carried boxes ends ``max_miss_s`` after its
        last detection seen in the cloud and no carried box starts a track, so what the
        memory holds cannot keep a track for ever (nor start one anew, under a new id).
    :param carried_as_seen: a carried detection continuing a track is published with the size
        and heading of the track's last box (the carry head guesses them without returns);
        its centre and velocity are measured as any other's.
        Both chosen on the tune split (docs/experiments/carry_default): the boxes held on
        ordinary drives, 22% of them matching an object, were what cost `suit_carry` its
        tracked mAP.
    :param speed_std_fraction: what :attr:`Tracker.velocity_std` adds to the filter's
        standard deviation for a box moving at speed v: ``sqrt(P_vv + (fraction * v)^2)``. The
        head under-reads speed along the direction of travel (by 15-30% on unseen drives, the
        filter's error with it: docs/experiments/velocity_head), an error that is not the white
        noise the filter models; 0.10 makes the published standard deviation's rms equal the
        velocity error's over the cars of the tune split (0.15 before the sweep readings were
        weighed by their spread: docs/experiments/velocity_std).
    """

    pos_sigma: float = 0.3
    vel_sigma: float = 4.5
    accel_sigma: float = 2.0
    gate: float = 13.8
    birth_score: float = 0.4
    score_mix: float = 0.7
    sweep_sigma: float | None = 0.75
    sweep_classes: tuple[str, ...] = ('car', 'truck', 'cyclist')
    sweep_min_score: float = 0.2
    sweep_spread_gain: float = 3.0
    sweep_single_sigma: float | None = 1.0
    heading_min_speed: float | None = 1.5
    max_miss_s: float = 0.6
    max_gap_s: float = 0.5
    coast_s: float = 0.5
    coast_margin: float = 0.5
    speed_std_fraction: float = 0.10
    carried_refresh: bool = False
    carried_as_seen: bool = True

    def __post_init__(self) -> None:
        for name in ('pos_sigma', 'vel_sigma', 'accel_sigma', 'gate', 'max_gap_s'):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f'TrackerConfig.{name} must be finite and > 0, got {value}')
        for name in ('sweep_sigma', 'sweep_single_sigma'):
            value = getattr(self, name)
            if value is not None and not (np.isfinite(value) and value > 0):
                raise ValueError(f'TrackerConfig.{name} must be finite and > 0 (or None), '
                                 f'got {value}')
        for name in ('birth_score', 'score_mix', 'sweep_min_score'):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f'TrackerConfig.{name} must be within 0..1, got {value}')
        for name in ('max_miss_s', 'coast_s', 'coast_margin', 'speed_std_fraction',
                     'sweep_spread_gain'):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f'TrackerConfig.{name} must be finite and >= 0, got {value}')

    def published_std(self, std: NDArray[np.floating[Any]] | float,
                      velocities: NDArray[np.floating[Any]]) -> NDArray[np.float32]:
        """Velocity standard deviations as published: ``std`` (the filter's or the
        measurement's) widened by ``speed_std_fraction`` of each velocity's speed."""
        speed = np.hypot(velocities[:, 0], velocities[:, 1])
        return np.hypot(std, self.speed_std_fraction * speed).astype(np.float32)

    def sweep_targets(self, det: Detections, class_names: Sequence[str]) -> NDArray[np.bool_]:
        """The detections whose velocity is read from the sweeps: ``sweep_classes`` scoring at
        least ``sweep_min_score``."""
        wanted = [i for i, n in enumerate(class_names) if n in self.sweep_classes]
        return np.isin(det.labels, wanted) & (det.scores >= self.sweep_min_score)


class Tracker:
    """Tracks over frames; :meth:`update` returns the detections with filtered velocities.

    The two horizontal axes have the same noise and are measured together, so their
    ``(position, velocity)`` covariances are equal and uncorrelated: one 2 x 2 covariance per
    track (:attr:`P`) serves both, and every inverse is a 2 x 2 one in closed form.
    """

    def __init__(self, config: TrackerConfig | None = None,
                 class_names: Sequence[str] | None = None) -> None:
        from suit_ros import CLASS_NAMES
        self.class_names = tuple(class_names or CLASS_NAMES)
        self.reconfigure(config or TrackerConfig())
        self.next_id = 1
        self.stamp_ns: int | None = None
        self.reset()

    def reconfigure(self, config: TrackerConfig) -> None:
        """Use ``config`` from the next update on; the tracks and their ids go on."""
        self.config = config
        # the classes that move along their heading (the sweep reading's, too)
        self.vehicle_labels = frozenset(i for i, n in enumerate(self.class_names)
                                        if n in config.sweep_classes)

    def reset(self) -> None:
        """Forget every track (ids keep counting up)."""
        self.x = np.zeros((0, 4))               # x, y, vx, vy (odometry frame)
        self.P = np.zeros((0, 2, 2))            # per axis: (position, velocity) covariance
        self.labels = np.zeros(0, np.int64)
        self.ids = np.zeros(0, np.int64)
        self.last_seen_ns = np.zeros(0, np.int64)   # stamp of each track's last detection
        self.score = np.zeros(0)                # running score (halving weights)
        self.shape = np.zeros((0, 5))           # z, length, width, height, yaw (odometry)
        self.stamp_ns = None
        self.frame_s = 0.0                      # the frame interval, smoothed (s)
        self.coasted = 0                        # the last update's coasted detections
        # the last update's detections: each velocity's standard deviation per axis (m/s),
        # the filter's for a tracked one, the measurement's for one no track took, widened by
        # ``speed_std_fraction`` of its speed
        self.velocity_std = np.zeros(0, np.float32)

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

    def update(self, det: Detections, stamp_ns: int, T_odom_frame: NDArray[np.float64],
               swept: SweepReading | None = None,
               carried: NDArray[np.bool_] | None = None,
               current: NDArray[np.floating[Any]] | None = None,
               sensor: NDArray[np.floating[Any]] | None = None
               ) -> tuple[Detections, NDArray[np.int64]]:
        """Filter one frame's detections.

        :param det: detections in some frame (absolute velocities in that frame).
        :param T_odom_frame: that frame's pose in the odometry frame at ``stamp_ns``.
        :param swept: velocities read from the sweeps (:func:`sweep_velocities`, in the
            detections' frame) and where they could be read; fused with the head's velocity
            when ``sweep_sigma`` is set.
        :param carried: ``(N,)`` the detections a memory holds where the cloud has no returns
            (a carry branch's). Such a detection continues its track and is scored with the
            track's running score like any other, but it does not lower that score: an object
            the memory holds through an occlusion keeps the confidence it was tracked with,
            while the track lives (with ``carried_refresh`` off, the default, ``max_miss_s``
            after its last detection seen in the cloud; then the memory's boxes are passed on
            untracked at their own scores while it holds them, ``sampling.carry_s``).
            Without a carry branch (None, or none carried) nothing changes.
        :param current: ``(M, >= 3)`` the current sweep's returns in the detections' frame,
            for ``coast_s`` (None: nothing coasts), and ``sensor`` where they were seen
            from in that frame (default: its origin).
        :return: the detections with filtered velocities and smoothed scores, and their track
            ids (0, the measured velocity and the model's score, for a detection below
            ``birth_score`` that no track took); the last :attr:`coasted` of them are the
            tracks held where the sweep shows nothing (``coast_s``).
        """
        cfg = self.config
        T = np.asarray(T_odom_frame, np.float64)
        if self.stamp_ns is not None:
            dt = (stamp_ns - self.stamp_ns) * 1e-9
            if not 0 < dt <= cfg.max_gap_s:
                self.reset()
            else:
                self._predict(dt)
                # smoothed: one early or late cloud does not move the lifetimes' tolerance
                self.frame_s = dt if self.frame_s == 0 else 0.9 * self.frame_s + 0.1 * dt
        self.stamp_ns = stamp_ns
        R = T[:2, :2]
        centres = det.boxes[:, :2].astype(np.float64) @ R.T + T[:2, 3]
        vel = det.velocities.astype(np.float64)
        var_v = np.full(len(det), cfg.vel_sigma ** 2)
        if swept is not None and cfg.sweep_sigma is not None:
            read = swept.read
            w_h = 1.0 / cfg.vel_sigma ** 2
            w_s = np.full(int(read.sum()), 1.0 / cfg.sweep_sigma ** 2)
            if cfg.sweep_spread_gain > 0:
                spread = swept.spread[read]
                single = ~np.isfinite(spread)
                w_s = 1.0 / (cfg.sweep_sigma ** 2 + (cfg.sweep_spread_gain
                                                     * np.where(single, 0.0, spread)) ** 2)
                w_s[single] = 0.0 if cfg.sweep_single_sigma is None \
                    else 1.0 / cfg.sweep_single_sigma ** 2
            vel[read] = (w_h * vel[read] + w_s[:, None] * swept.velocities[read]) \
                / (w_h + w_s)[:, None]
            var_v[read] = 1.0 / (w_h + w_s)
        measured_vel = vel.copy()                    # the detections' frame
        vel = vel @ R.T
        # a detection with a non-finite centre or velocity (a caller's bad input) is passed
        # on untracked: it would turn its track's state NaN for good
        usable = np.isfinite(centres).all(1) & np.isfinite(vel).all(1)
        confident = (det.scores >= cfg.birth_score) & usable
        held = np.zeros(len(det), bool) if carried is None else np.asarray(carried, bool)
        match = self._associate(np.where(usable[:, None], centres, 1e12),
                                np.asarray(det.labels, np.int64), confident)
        match[~usable] = -1
        Rm = np.zeros((len(det), 2, 2))                                   # per axis
        Rm[:, 0, 0] = cfg.pos_sigma ** 2
        Rm[:, 1, 1] = var_v
        hit = match >= 0
        if hit.any():
            self._correct(match[hit], centres[hit], vel[hit], Rm[hit])
        scores = det.scores.astype(np.float64)
        if hit.any():
            t = match[hit]
            scores[hit] = (1 - cfg.score_mix) * scores[hit] + cfg.score_mix * self.score[t]
            # a carried detection holds its track's score (see ``carried``)
            seen_now = hit if carried is None else hit & ~np.asarray(carried, bool)
            t_seen = match[seen_now]
            self.score[t_seen] = 0.5 * (self.score[t_seen] + det.scores[seen_now])
        seen = np.zeros(len(self.x), bool)
        seen[match[hit] if cfg.carried_refresh else match[hit & ~held]] = True
        self.last_seen_ns[seen] = stamp_ns
        new = ~hit & confident
        if not cfg.carried_refresh:     # nor does a carried box start a track
            new &= ~held
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
        self.P = np.concatenate([self.P, Rm[new]])
        self.shape = np.concatenate([self.shape, np.zeros((n_new, 5))])
        tracked = rows >= 0
        self.labels = np.concatenate([self.labels, det.labels[new]])
        self.ids = np.concatenate([self.ids, new_ids])
        self.last_seen_ns = np.concatenate([self.last_seen_ns,
                                            np.full(n_new, stamp_ns, np.int64)])
        self.score = np.concatenate([self.score, det.scores[new]])
        out_vel = measured_vel                                  # untracked: as measured
        out_vel[tracked] = self.x[rows[tracked], 2:] @ R
        vel_std = np.sqrt(var_v)                                # untracked: the measurement's
        vel_std[tracked] = np.sqrt(self.P[rows[tracked], 1, 1])
        boxes = det.boxes
        if cfg.heading_min_speed is not None and tracked.any():
            boxes = self._settle_headings(det, rows, out_vel)
        yaw_frame = np.arctan2(R[1, 0], R[0, 0])
        as_seen = held & hit if cfg.carried_as_seen else np.zeros(len(det), bool)
        if as_seen.any():           # size and heading as the track's last published box
            boxes = boxes.copy()
            boxes[as_seen, 3:6] = self.shape[rows[as_seen], 1:4]
            boxes[as_seen, 6] = wrap_angle(self.shape[rows[as_seen], 4] - yaw_frame)
        shape = boxes[tracked][:, 2:7].astype(np.float64)      # the box as published
        shape[:, 4] += yaw_frame
        self.shape[rows[tracked]] = shape
        out = Detections(boxes, out_vel, scores, det.labels)
        self.coasted = 0
        if cfg.coast_s and current is not None:
            hit_now = np.zeros(len(self.x), bool)   # taken now, a carried box's included
            hit_now[rows[tracked]] = True
            coast, coast_ids, coast_std = self._coast(stamp_ns, T, current, sensor, hit_now)
            if len(coast):
                out = out.concat(coast)
                ids = np.concatenate([ids, coast_ids])
                vel_std = np.concatenate([vel_std, coast_std])
                self.coasted = len(coast)
        self.velocity_std = cfg.published_std(vel_std, out.velocities)
        keep = self._missed_within(stamp_ns, cfg.max_miss_s)
        self.x, self.P = self.x[keep], self.P[keep]
        self.labels, self.ids = self.labels[keep], self.ids[keep]
        self.last_seen_ns = self.last_seen_ns[keep]
        self.score, self.shape = self.score[keep], self.shape[keep]
        return out, ids

    def _missed_within(self, stamp_ns: int, limit_s: float) -> NDArray[np.bool_]:
        """The tracks whose last detection is at most ``limit_s`` before ``stamp_ns``, or up
        to a quarter of the (smoothed) frame interval more, for stamp jitter: whole frames,
        the limit's time give or take that quarter."""
        missed_s = (stamp_ns - self.last_seen_ns) * 1e-9
        return missed_s <= limit_s + 0.25 * self.frame_s

    def _coast(self, stamp_ns: int, T: NDArray[np.float64], current: NDArray[np.floating[Any]],
               sensor: NDArray[np.floating[Any]] | None, hit_now: NDArray[np.bool_]
               ) -> tuple[Detections, NDArray[np.int64], NDArray[np.float64]]:
        """The boxes of the confident tracks missed this frame (not in ``hit_now``, for at
        most ``coast_s`` since their last detection, while they live) where the current sweep
        shows nothing of them, in the frame of ``T`` (see ``coast_s`` and :func:`unseen`),
        their ids and velocity standard deviations."""
        cfg = self.config
        t = np.nonzero(~hit_now
                       & self._missed_within(stamp_ns, min(cfg.coast_s, cfg.max_miss_s))
                       & (self.score >= cfg.birth_score))[0]
        if len(t) == 0:
            return Detections.empty(), np.zeros(0, np.int64), np.zeros(0)
        R = T[:2, :2]
        boxes = np.zeros((len(t), 7))
        boxes[:, :2] = (self.x[t, :2] - T[:2, 3]) @ R               # odometry -> frame
        boxes[:, 2:6] = self.shape[t, :4]
        boxes[:, 6] = wrap_angle(self.shape[t, 4] - np.arctan2(R[1, 0], R[0, 0]))
        blind = unseen(boxes, current, cfg.coast_margin, sensor)
        t, boxes = t[blind], boxes[blind]
        return (Detections(boxes, self.x[t, 2:] @ R, self.score[t], self.labels[t]),
                self.ids[t], np.sqrt(self.P[t, 1, 1]))

    def _correct(self, t: NDArray[np.int64], centres: NDArray[np.float64],
                 vel: NDArray[np.float64], Rm: NDArray[np.float64]) -> None:
        """The Kalman update of tracks ``t`` with their detections' centres and velocities
        (measurement noise ``Rm`` per axis; the axes share one 2 x 2 covariance)."""
        P = self.P[t]                                                      # (H, 2, 2)
        S = P + Rm                                                         # measurement: H = I
        det_S = S[:, 0, 0] * S[:, 1, 1] - S[:, 0, 1] * S[:, 1, 0]
        S_inv = np.stack([np.stack([S[:, 1, 1], -S[:, 0, 1]], -1),
                          np.stack([-S[:, 1, 0], S[:, 0, 0]], -1)], -2) / det_S[:, None, None]
        K = P @ S_inv                                                      # (H, 2, 2)
        for axis in range(2):                                              # x then y
            cols = np.array([axis, axis + 2])
            state = self.x[t][:, cols]
            meas = np.stack([centres[:, axis], vel[:, axis]], -1)
            self.x[np.ix_(t, cols)] = state + np.einsum('nij,nj->ni', K, meas - state)
        self.P[t] = P - K @ P

    def _settle_headings(self, det: Detections, rows: NDArray[np.int64],
                         vel: NDArray[np.float64]) -> NDArray[np.floating[Any]]:
        """``det.boxes`` with the vehicles that drive backwards by a confident velocity turned
        round (see ``heading_min_speed``)."""
        cfg = self.config
        assert cfg.heading_min_speed is not None
        speed = np.hypot(vel[:, 0], vel[:, 1])
        sigma = np.sqrt(np.where(rows >= 0, self.P[np.maximum(rows, 0), 1, 1], np.inf))
        vehicle = np.isin(det.labels, list(self.vehicle_labels))
        yaw = det.boxes[:, 6].astype(np.float64)
        backwards = np.cos(yaw) * vel[:, 0] + np.sin(yaw) * vel[:, 1] < 0
        turn = ((rows >= 0) & vehicle & (speed > cfg.heading_min_speed)
                & (speed > 2.0 * sigma) & backwards)
        if not turn.any():
            return det.boxes
        boxes = det.boxes.copy()
        boxes[turn, 6] = (yaw[turn] + 2.0 * np.pi) % (2.0 * np.pi) - np.pi
        return boxes


def unseen(boxes: NDArray[np.floating[Any]], points: NDArray[np.floating[Any]],
           margin: float = 0.5, sensor: NDArray[np.floating[Any]] | None = None
           ) -> NDArray[np.bool_]:
    """Which ``(M, 7)`` boxes the sweep ``points`` (``(N, >= 3)``, from a sensor at ``sensor``,
    default the origin) shows nothing of: no return whose ray passed through the box (grown by
    ``margin``): on its bearings, at or beyond its nearest corner, and at the range of that
    corner within its heights. A lost sector or an occluder's shadow leaves a box blind; the
    road where an object no longer is, or a wall seen low past where it would be, does not; a
    wall seen over an occluder's top does not count. A box around the sensor is never blind."""
    b = np.asarray(boxes, np.float64).reshape(-1, 7)
    o = np.zeros(3) if sensor is None else np.ascontiguousarray(sensor, np.float64)[:3]
    out = np.zeros(len(b), bool)
    if len(b) == 0:
        return out
    import torch

    from suit_ros.ops.iou import bev_corners
    grown = b.copy()
    grown[:, 3:5] += 2.0 * margin
    corners = bev_corners(torch.from_numpy(grown)).numpy() - o[:2]                # (M, 4, 2)
    cx, cy = corners[..., 0], corners[..., 1]
    near = np.hypot(cx, cy).min(axis=1)
    bearing = np.arctan2(b[:, 1] - o[1], b[:, 0] - o[0])
    half = np.abs(wrap_angle(np.arctan2(cy, cx) - bearing[:, None])).max(axis=1)
    low = b[:, 2] - b[:, 5] / 2 - margin - o[2]
    high = b[:, 2] + b[:, 5] / 2 + margin - o[2]
    # the sensor inside the grown box, or bearings over half a turn: nothing to reason about
    ok: NDArray[np.bool_] = (near > 1.0) & (half < np.pi / 2)
    if len(points) == 0 or not ok.any():
        return ok
    u = np.stack([np.cos(bearing), np.sin(bearing)], axis=1)[ok]
    hit = rays_through(as_float(np.asarray(points)), o, np.ascontiguousarray(u),
                       np.cos(half[ok]), near[ok], low[ok], high[ok])
    out[ok] = ~hit
    return out


def track_step(tracks: Tracker, det: Detections, stamp_ns: int,
               T_odom_base: NDArray[np.float64], model_points: NDArray[np.floating[Any]] | None,
               swept: SweepReading | None = None,
               carried: NDArray[np.bool_] | None = None,
               current: NDArray[np.floating[Any]] | None = None,
               sensor: NDArray[np.floating[Any]] | None = None
               ) -> tuple[Detections, NDArray[np.int64]]:
    """The streaming detector's tracking step: read the vehicles' velocities from the sweeps
    (when the config asks for it; ``swept`` given: already read), then update the tracks.

    :param det: the frame's detections in base_link (the model frame).
    :param model_points: the model input ``(N, 5)`` in base_link.
    :param carried: which detections a memory carries (:meth:`Tracker.update`).
    :param current: the current sweep's returns in base_link (``coast_s``), seen from
        ``sensor`` (the LiDAR's position in base_link).
    """
    fc = tracks.config
    if swept is None and fc.sweep_sigma is not None and model_points is not None:
        swept = sweep_velocities(model_points, det.boxes,
                                 fc.sweep_targets(det, tracks.class_names))
    return tracks.update(det, stamp_ns, T_odom_base, swept, carried, current, sensor)


class SweepReading(NamedTuple):
    """Velocities read from the sweeps (:func:`sweep_velocities`), per box."""

    velocities: NDArray[np.float64]     # (M, 2), along each box's heading
    read: NDArray[np.bool_]             # (M,) whether it could be read
    spread: NDArray[np.float64]         # (M,) m/s between the earlier sweeps' own readings
                                        # (inf: one earlier sweep read it)


def sweep_velocities(points: NDArray[np.floating[Any]], boxes: NDArray[np.floating[Any]],
                     which: NDArray[np.bool_], max_speed: float = 20.0, bin_m: float = 0.1,
                     min_points: int = 10) -> SweepReading:
    """Each box's velocity read from the motion of its points between the accumulated sweeps.

    The model input holds the current sweep and the previous ones, all in the current frame
    with ego motion removed, each tagged with its time lag: a static object's returns line up,
    a moving one's are smeared along its path. For a box, the returns inside it (widened along
    its heading by ``max_speed`` x the largest lag, ground excluded) are projected on its
    heading and histogrammed per sweep; the speed whose shifts best overlap every earlier
    sweep's histogram with the current one (correlation, summed over the sweeps) is the box's
    speed along its heading. Vehicles move along their heading, so the velocity is that speed
    times the heading direction.

    Each earlier sweep also gives a speed of its own (its correlation's peak); where two or
    more do, how far apart they lie (``spread``) says how far to trust the reading. A sweep
    reads in steps of about ``bin_m`` over its lag (1 m/s for the sweep 0.1 s back, its
    histograms' bins), so sweeps reading one speed can lie up to a step apart; the tracker's
    weights were chosen with that in them (taking the step off read worse on the tune split:
    docs/experiments/velocity_filter).
    A reading whose sweeps disagree is mostly a wrong one: on the tune split's moving cars,
    readings whose sweeps agree within 1 m/s (80% of them) are off by 1.2 m/s on average, the
    others by 4.4, and one read from a single earlier sweep by 3.3
    (docs/experiments/velocity_filter).

    :param points: ``(N, 5)`` x, y, z, intensity, time lag (s) in the boxes' frame, ground at
        z = 0 (the model input).
    :param boxes: ``(M, 7)``; ``which``: ``(M,)`` the boxes to estimate (vehicles).
    :return: the velocities ``(M, 2)``, whether each could be read ``(M,)`` (``min_points``
        current returns and as many in an earlier sweep) and the spread of the earlier
        sweeps' own speeds ``(M,)`` (m/s; inf where fewer than two read it).
    """
    b = np.asarray(boxes, np.float64).reshape(-1, 7)
    vel = np.zeros((len(b), 2))
    ok = np.zeros(len(b), bool)
    spread = np.full(len(b), np.inf)
    pts = as_float(points)
    if pts.ndim != 2 or pts.shape[1] < 5 or len(pts) == 0 or not which.any():
        return SweepReading(vel, ok, spread)
    lags = distinct_values(pts[:, 4])
    past_lags = lags[lags > 0]
    if len(past_lags) == 0:
        return SweepReading(vel, ok, spread)
    # only the points above the ground near the boxes' search areas, by a coarse
    # grid (each box reads the cells its area touches)
    speeds = np.arange(-max_speed, max_speed + 1e-9, 0.25)
    reach = max_speed * float(past_lags.max())
    picked = np.flatnonzero(which)
    r = 0.5 * b[picked, 3] + reach + b[picked, 4]
    bp = b[picked]
    half = 0.5 * bp[:, 3] + reach
    across = 0.5 * bp[:, 4] + 0.3
    band = np.stack([bp[:, 0], bp[:, 1], half, across, bp[:, 6]], axis=1)
    index = CellIndex(pts, bp[:, :2] - r[:, None], bp[:, :2] + r[:, None], 2.0,
                      oriented=band)
    # each box's returns projected on its heading and histogrammed per sweep, in one
    # compiled pass over the points, each against the boxes of its cell (in the cloud's
    # dtype, as numpy computes an array against float scalars)
    cos, sin = np.cos(bp[:, 6]), np.sin(bp[:, 6])
    geometry = np.stack([bp[:, 0], bp[:, 1], cos, sin, half, across,
                         bp[:, 2] + 0.5 * bp[:, 5] + 0.3], axis=1)
    n_bins = (2 * half / bin_m).astype(np.int64) + 1
    start, owners = index.box_lists()
    dt = pts.dtype.type
    hist, length = sweep_histograms_by_cell(pts, index.inv_cell, index.origin, index.shape,
                                            dt(0.3), dt(5.0), start, owners,   # above ground
                                            geometry.astype(pts.dtype), past_lags, dt(bin_m),
                                            n_bins)
    for n, j in enumerate(picked):
        current = hist[n, 0, :length[n]]
        if current.sum() < min_points:
            continue
        score = np.zeros(len(speeds))
        own = []
        for q, L in enumerate(past_lags):
            earlier = hist[n, 1 + q, :length[n]]
            if earlier.sum() < min_points:
                continue
            # corr[k]: overlap when the earlier sweep is shifted by (k - (n - 1)) bins
            corr = np.correlate(current, earlier, 'full') / (current.sum() * earlier.sum())
            shift = speeds * L / bin_m + (len(current) - 1)
            this = np.interp(shift, np.arange(len(corr)), corr)
            own.append(speeds[int(np.argmax(this))])
            score += this
            ok[j] = True
        if ok[j]:
            vel[j] = speeds[int(np.argmax(score))] * np.array([cos[n], sin[n]])
            if len(own) > 1:
                spread[j] = max(own) - min(own)
    return SweepReading(vel, ok, spread)
