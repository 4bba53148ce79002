"""nav_msgs/Odometry -> 4x4 poses, stamps, and a time-bounded pose buffer with interpolation."""
from __future__ import annotations

import bisect
import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .errors import MessageError, PoseLookupError


def stamp_to_ns(stamp: Any) -> int:
    """builtin_interfaces/Time -> integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def ns_to_stamp(ns: int, time_class: Any) -> Any:
    """Integer nanoseconds -> a Time message of ``time_class``."""
    sec, nsec = divmod(int(ns), 1_000_000_000)
    return time_class(sec=sec, nanosec=nsec)


def quaternion_to_matrix(x: float, y: float, z: float, w: float) -> NDArray[np.float64]:
    """Unit quaternion -> 3x3 rotation (the quaternion is normalised; zero/non-finite raise)."""
    q = np.array([x, y, z, w], np.float64)
    n = float(np.linalg.norm(q))
    if not np.isfinite(q).all() or n < 1e-6:
        raise MessageError(f'orientation quaternion {q.tolist()} is not a valid rotation '
                           '(non-finite or zero norm)')
    x, y, z, w = q / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def matrix_to_quaternion(R: NDArray[np.float64]) -> NDArray[np.float64]:
    """3x3 rotation -> quaternion ``(x, y, z, w)`` with ``w >= 0``."""
    m = np.asarray(R, np.float64)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        q = [s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        q = [(m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4, (m[1, 0] - m[0, 1]) / s]
    out = np.array(q, np.float64)
    out /= np.linalg.norm(out)
    return out if out[3] >= 0 else -out


def odometry_to_pose(msg: Any) -> tuple[NDArray[np.float64], int]:
    """Odometry -> ``(T_frame_child (4, 4) float64, stamp_ns)``."""
    p = msg.pose.pose.position
    o = msg.pose.pose.orientation
    t = np.array([p.x, p.y, p.z], np.float64)
    if not np.isfinite(t).all():
        raise MessageError(f'odometry position {t.tolist()} is not finite')
    T = np.eye(4)
    T[:3, :3] = quaternion_to_matrix(o.x, o.y, o.z, o.w)
    T[:3, 3] = t
    return T, stamp_to_ns(msg.header.stamp)


def slerp(q0: NDArray[np.float64], q1: NDArray[np.float64], f: float) -> NDArray[np.float64]:
    """Spherical linear interpolation of unit quaternions ``(x, y, z, w)`` (shortest arc).

    :param f: 0 gives ``q0``, 1 gives ``q1`` (or ``-q1``, the same rotation).
    """
    if float(np.dot(q0, q1)) < 0:
        q1 = -q1
    # the angle between the two 4-vectors, accurate also when they are nearly equal (acos of
    # the dot product loses half the digits there)
    omega = 2.0 * math.atan2(float(np.linalg.norm(q1 - q0)), float(np.linalg.norm(q1 + q0)))
    if omega < 1e-9:
        q = q0 + f * (q1 - q0)
    else:
        s = math.sin(omega)
        q = (math.sin((1 - f) * omega) / s) * q0 + (math.sin(f * omega) / s) * q1
    return np.asarray(q / np.linalg.norm(q), np.float64)


Pose = tuple[int, NDArray[np.float64], NDArray[np.float64]]     # stamp, position, quaternion
REWIND_NS = 1_000_000_000   # a stamp this far before the newest: late, or time went back
NEAR_RUN = 3                # stamps in a row before the newest, each after the last: went back


class TimeLine:
    """Whether stamps went back, to another time line (a looped bag, a simulator or clock
    reset), or only came late (out of order), at any message rate:

    - far: two stamps in a row more than ``rewind_ns`` before the newest, the second not more
      than ``rewind_ns`` before the first (one alone is a late message). A late message just
      before the time line went back is not taken for the new line's first stamp: the stamp
      after it lies far before it too, and takes its place;
    - near: ``near_run`` stamps in a row before the newest, each after the one before and
      within ``rewind_ns`` of it: a time line that went back by less than ``rewind_ns`` (a
      simulator reset soon after its start, a short bag looped) goes on from there, where late
      messages (one writer's arrive in order) do not line up so.

    :attr:`run` holds the stamps before the newest in a row so far (not yet either).
    ``rewind_ns`` None: time never goes back (offline, where every stamp is kept in place).
    """

    def __init__(self, rewind_ns: int | None = REWIND_NS, near_run: int = NEAR_RUN) -> None:
        self.rewind_ns = None if rewind_ns is None else int(rewind_ns)
        self.near_run = int(near_run)
        self.run: list[int] = []
        self.far = False        # whether the run's stamps lie far before the newest

    def went_back(self, stamp_ns: int, newest_ns: int) -> bool:
        """Observe ``stamp_ns`` against the newest so far; True once time went back (the run,
        ending with ``stamp_ns``, is the new line's first stamps)."""
        run, rewind = self.run, self.rewind_ns
        if rewind is None or stamp_ns >= newest_ns:
            run.clear()
            return False
        far = stamp_ns < newest_ns - rewind
        if run and far == self.far and (stamp_ns >= run[-1] - rewind if far
                                        else run[-1] < stamp_ns <= run[-1] + rewind):
            run.append(stamp_ns)
            if len(run) >= (2 if far else self.near_run):
                run.clear()
                return True
            return False
        run[:] = [stamp_ns]
        self.far = far
        return False


class PoseBuffer:
    """Recent poses by stamp; interpolates (linear position, slerp rotation) at any stamp.

    A duplicate stamp replaces the old pose, poses older than ``max_age_ns`` before the newest
    are dropped. A pose stamped before the newest pose but one is held aside until the poses
    after it say what it is (:class:`TimeLine`): a late message, then inserted in place; or
    the first of a time line that went back (a looped bag, a simulator or clock reset), then
    the buffer starts again from the held poses (counted in :attr:`rewinds`): a lookup at the
    new stamps must not interpolate between two lines. The line before is kept as it was
    (:attr:`previous`), for its clouds still on their way. Poses after the newest but one go
    in place at once (a message late by less than one, or the way on after a single pose
    stamped ahead: a glitch, which goes once three such come, counted too). Held poses are
    not looked up (the line is the one before them). A step back shorter than
    ``NEAR_RUN - 1`` messages of the odometry is not seen: its poses go in place as late ones.
    ``rewind_ns`` None (offline: every pose of a recording at once, in any order): every pose
    goes in place at once. A lookup within ``tolerance_ns`` outside the buffered span returns
    the edge pose; further out raises PoseLookupError.
    """

    def __init__(self, max_age_ns: int = 10_000_000_000, tolerance_ns: int = 100_000_000,
                 rewind_ns: int | None = REWIND_NS) -> None:
        self.max_age_ns = int(max_age_ns)
        self.tolerance_ns = int(tolerance_ns)
        self.rewinds = 0
        # the time line before the last time the stamps went back, as it was then (for the
        # clouds of that line still on their way)
        self.previous: PoseBuffer | None = None
        self._line = TimeLine(rewind_ns)
        # the poses of the TimeLine's run (before the newest, in a row), each with whether it
        # is in place already (or held aside)
        self._run: list[tuple[Pose, bool]] = []
        self._stamps: list[int] = []
        self._t: list[NDArray[np.float64]] = []
        self._q: list[NDArray[np.float64]] = []

    def __len__(self) -> int:
        return len(self._stamps)

    def clear(self) -> None:
        """Drop every pose (those held aside too)."""
        self._stamps.clear()
        self._t.clear()
        self._q.clear()
        self._run = []
        self._line.run.clear()

    def span(self) -> tuple[int, int] | None:
        """``(first_ns, last_ns)`` or None when empty."""
        return (self._stamps[0], self._stamps[-1]) if self._stamps else None

    def add(self, stamp_ns: int, T: NDArray[np.float64]) -> None:
        """Insert a pose ``T (4, 4)``."""
        T = np.asarray(T, np.float64)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise MessageError('pose must be a finite 4x4 matrix')
        pose = (int(stamp_ns), T[:3, 3].copy(), matrix_to_quaternion(T[:3, :3]))
        if not self._stamps or self._line.rewind_ns is None:
            self._insert(*pose)
        elif self._line.went_back(pose[0], self._stamps[-1]):
            self._went_back([p for p, _ in self._run] + [pose],
                            {p[0] for p, placed in self._run if placed})
            self._run = []
            self.rewinds += 1
        elif pose[0] < self._stamps[-1]:   # before the newest: late, or a new line's first
            if len(self._line.run) == 1:   # a run of its own: the one before was late
                self._place_held()
            # after the newest but one: late by less than a message, or the way on after one
            # pose stamped ahead; in place now. Further back: held until the line is settled
            placed = len(self._stamps) < 2 or pose[0] > self._stamps[-2]
            if placed:
                self._insert(*pose)
            self._run.append((pose, placed))
        else:                              # the newest: whatever was held came late
            self._place_held()
            self._insert(*pose)
        cut = bisect.bisect_left(self._stamps, self._stamps[-1] - self.max_age_ns)
        if cut:
            del self._stamps[:cut], self._t[:cut], self._q[:cut]

    def _place_held(self) -> None:
        """The held poses of the run were late messages: in place."""
        for pose, placed in self._run:
            if not placed:
                self._insert(*pose)
        self._run = []

    def _went_back(self, run: list[Pose], placed: set[int]) -> None:
        """The poses of ``run`` are a time line that went back (``placed``: those already in
        place): the buffer starts again from them, the line before kept as :attr:`previous`;
        where a single pose lies after their first that is not one of them, it was stamped
        ahead (a glitch), and only it goes."""
        i = bisect.bisect_left(self._stamps, min(p[0] for p in run))
        others = [k for k in range(i, len(self._stamps)) if self._stamps[k] not in placed]
        if len(others) <= 1:
            for k in reversed(others):
                del self._stamps[k], self._t[k], self._q[k]
        else:
            keep = [k for k, stamp in enumerate(self._stamps) if stamp not in placed]
            self.previous = PoseBuffer(self.max_age_ns, self.tolerance_ns, None)
            self.previous._stamps = [self._stamps[k] for k in keep]
            self.previous._t = [self._t[k] for k in keep]
            self.previous._q = [self._q[k] for k in keep]
            self._stamps, self._t, self._q = [], [], []
        for pose in run:
            self._insert(*pose)

    def _insert(self, stamp_ns: int, t: NDArray[np.float64], q: NDArray[np.float64]) -> None:
        i = bisect.bisect_left(self._stamps, stamp_ns)
        if i < len(self._stamps) and self._stamps[i] == stamp_ns:
            self._t[i], self._q[i] = t, q
        else:
            self._stamps.insert(i, stamp_ns)
            self._t.insert(i, t)
            self._q.insert(i, q)

    def lookup(self, stamp_ns: int) -> NDArray[np.float64]:
        """The pose at ``stamp_ns`` as a 4x4 float64 matrix."""
        if not self._stamps:
            raise PoseLookupError('no pose buffered yet')
        first, last = self._stamps[0], self._stamps[-1]
        if stamp_ns < first - self.tolerance_ns or stamp_ns > last + self.tolerance_ns:
            raise PoseLookupError(
                f'stamp {stamp_ns * 1e-9:.3f} s is outside the buffered poses '
                f'[{first * 1e-9:.3f}, {last * 1e-9:.3f}] s by more than '
                f'{self.tolerance_ns * 1e-9:.3f} s')
        i = bisect.bisect_left(self._stamps, stamp_ns)
        if i == 0:
            t, q = self._t[0], self._q[0]
        elif i >= len(self._stamps):
            t, q = self._t[-1], self._q[-1]
        elif self._stamps[i] == stamp_ns:
            t, q = self._t[i], self._q[i]
        else:
            s0, s1 = self._stamps[i - 1], self._stamps[i]
            f = (stamp_ns - s0) / (s1 - s0)
            t = self._t[i - 1] + f * (self._t[i] - self._t[i - 1])
            q = slerp(self._q[i - 1], self._q[i], f)
        T = np.eye(4)
        T[:3, :3] = quaternion_to_matrix(*q)
        T[:3, 3] = t
        return T
