"""What the detector node's callbacks hand to its worker thread, rclpy-free.

- :class:`CloudMailbox`: one slot. A cloud that arrives while the worker is busy replaces the
  waiting one (counted as dropped: the model always takes the newest, a stale cloud is never
  queued), and the last few replaced ones go to the worker with it, so that they still feed the
  model's sweeps; the same cloud arriving twice (through a retiring subscription, while one
  overlaps the new one) is taken once; the publisher's sequence numbers tell the clouds lost
  before the callback.
- :class:`OdometryGate`: odometry queued by its callback and drained by the worker, and the
  worker's wait (up to a timeout) for odometry that reaches a cloud's stamp, as a tf2 message
  filter would. A stamp further ahead of the clock than the skew tolerance does not end a
  wait (the pipeline refuses that message when it is drained); when time goes back (stamps in
  a row before the newest: ``TimeLine``), the newest is the new time line's.

Both are thread-safe; :meth:`close` wakes every waiter for shutdown.
"""
from __future__ import annotations

import collections
from collections.abc import Callable, Hashable
import threading
import time
from typing import Any, Generic, TypeVar

from suit_ros.msg_adapters.odometry import REWIND_NS, TimeLine

T = TypeVar('T')


class CloudMailbox(Generic[T]):
    """The newest cloud for the worker, with the counts the diagnostics report.

    :param keep_replaced: how many of the clouds replaced in the slot since the last take are
        handed to the worker with the newest (:meth:`take_all`; the older ones are let go).
    """

    def __init__(self, dedupe: int = 8, keep_replaced: int = 0) -> None:
        self._cv = threading.Condition()
        self._slot: T | None = None
        self._replaced: collections.deque[T] = collections.deque(maxlen=max(keep_replaced, 0))
        self._recent: collections.deque[Hashable] = collections.deque(maxlen=dedupe)
        self._last_seq: int | None = None
        # the last sequence number may be another publisher's: the next gap is a new baseline
        self._rebase = False
        self.closed = False
        self.frames_in = 0
        self.dropped = 0            # replaced in the slot before the worker took them
        self.duplicates = 0
        self.lost = 0               # never reached the callback (publisher sequence gaps)
        self.arrivals: collections.deque[float] = collections.deque(maxlen=1000)
        self.losses: collections.deque[float] = collections.deque(maxlen=100)
        self.reader_delays: collections.deque[float] = collections.deque(maxlen=200)

    def put(self, item: T, key: Hashable, info: dict[str, Any] | None = None,
            count_gaps: bool | Callable[[], bool] = True, dedupe: bool = True) -> bool:
        """Offer a cloud; False for a duplicate.

        :param key: what tells one message from another (two copies of one message share it;
            a publisher that repeats a header stamp sends different messages, so the key needs
            more than the stamp: the node adds the publisher's sequence number).
        :param dedupe: whether a key seen among the last few clouds means a copy (only while a
            retiring subscription overlaps the new one can a message arrive twice).

        :param info: the middleware's message info (``publication_sequence_number``,
            ``received_timestamp`` in ns since the epoch) or None.
        :param count_gaps: whether sequence gaps mean losses now (only while one publisher and
            one subscription exist: sequence numbers count per publisher); a callable is asked
            only when a gap appears (it may query the ROS graph). A gap just after the numbers
            went back, or just after a gap not counted, starts a new baseline instead: the
            numbers before it may be a publisher's that has just left.
        """
        now = time.monotonic()
        with self._cv:
            if dedupe and key in self._recent:
                self.duplicates += 1
                return False
            self._recent.append(key)
            self._account(info, count_gaps, now)
            self.frames_in += 1
            self.arrivals.append(now)
            if self._slot is not None:
                self.dropped += 1
                if self._replaced.maxlen:
                    self._replaced.append(self._slot)
            self._slot = item
            self._cv.notify_all()
        return True

    def _account(self, info: dict[str, Any] | None, count_gaps: bool | Callable[[], bool],
                 now: float) -> None:
        if not info:
            return
        recv = info.get('received_timestamp')
        if recv:
            self.reader_delays.append((time.time_ns() - int(recv)) * 1e-9)
        seq = info.get('publication_sequence_number')
        if seq is None:
            return
        last, self._last_seq = self._last_seq, int(seq)
        if last is None or int(seq) == last + 1:
            self._rebase = False
            return
        if int(seq) <= last:            # another publisher's numbers, or a restarted one
            self._rebase = True
            return
        # a gap: a loss, unless the numbers before it may be another publisher's (one that
        # has just left: the publishers are counted now, not when it sent)
        if self._rebase:
            self._rebase = False        # this number is the new baseline
        elif count_gaps() if callable(count_gaps) else count_gaps:
            self.lost += int(seq) - last - 1
            self.losses.append(now)
        else:
            self._rebase = True         # several publishers now: the next gap may be theirs

    def take(self, timeout: float = 0.5) -> T | None:
        """The waiting cloud (emptying the slot), or None after ``timeout`` s or on close."""
        return self.take_all(timeout)[0]

    def take_all(self, timeout: float = 0.5) -> tuple[T | None, list[T]]:
        """The waiting cloud (None after ``timeout`` s or on close) and the last
        ``keep_replaced`` clouds it replaced, oldest first (both emptied)."""
        with self._cv:
            if self._slot is None and not self.closed:
                self._cv.wait(timeout)
            item, self._slot = self._slot, None
            replaced = list(self._replaced)
            self._replaced.clear()
            if self.closed or item is None:
                return None, []
            return item, replaced

    def close(self) -> None:
        """Wake the worker for shutdown; later takes return None."""
        with self._cv:
            self.closed = True
            self._cv.notify_all()


class OdometryGate(Generic[T]):
    """Odometry between its callback and the worker."""

    def __init__(self, capacity: int = 10_000) -> None:
        self._cv = threading.Condition()
        self._queue: collections.deque[T] = collections.deque(maxlen=capacity)
        self.latest_ns = -1         # newest usable stamp (not from beyond the clock)
        self._line = TimeLine(REWIND_NS)
        self.rewinds = 0            # how often the odometry's time went back
        self.previous_latest = -1   # the newest stamp before it last went back
        self.waits = 0
        self.delays: collections.deque[float] = collections.deque(maxlen=500)
        self.closed = False

    def put(self, msg: T, stamp_ns: int, now_ns: int, max_ahead_s: float,
            usable: bool = True) -> None:
        """Queue a message; ``now_ns`` 0 (a simulated clock not started) checks nothing. One
        the pipeline will refuse (not ``usable``: a NaN position, a zero quaternion) is
        queued to be counted there, but its stamp is no odometry a cloud can wait for."""
        delay = (now_ns - stamp_ns) * 1e-9
        with self._cv:
            self.delays.append(delay)
            self._queue.append(msg)
            if usable and (not now_ns or -delay <= max_ahead_s):
                if self._line.went_back(stamp_ns, self.latest_ns):
                    self.previous_latest, self.latest_ns = self.latest_ns, stamp_ns
                    self.rewinds += 1
                else:
                    self.latest_ns = max(self.latest_ns, stamp_ns)
            self._cv.notify_all()

    def drain(self) -> list[T]:
        """Every queued message, oldest first."""
        with self._cv:
            batch = list(self._queue)
            self._queue.clear()
        return batch

    def _reached(self, stamp_ns: int, went_back: bool, since: int) -> bool:
        if went_back:
            # a cloud whose stamp went back (a loop, a reset) comes before its time line's
            # odometry: the odometry buffered before it is another line's, so only odometry
            # that went back since the clouds last did (and settled) is its own
            return (self.rewinds > since and stamp_ns <= self.latest_ns
                    and not (self._line.run and not self._line.far))
        # the odometry went back and the clouds not yet: theirs is the line before
        return stamp_ns <= self.latest_ns or (self.rewinds > since
                                              and stamp_ns <= self.previous_latest)

    def covers(self, stamp_ns: int, went_back: bool = False, since: int | None = None
               ) -> bool:
        """Whether odometry reached ``stamp_ns``. For a cloud whose stamp ``went_back``
        before the last one's, only odometry that went back since :attr:`rewinds` was
        ``since`` (when the clouds last went back) does; a cloud that did not is on the line
        before while the odometry went back since then. ``since`` None: the count now."""
        with self._cv:
            return self._reached(stamp_ns, went_back,
                                 self.rewinds if since is None else since)

    def wait_for(self, stamp_ns: int, timeout: float, went_back: bool = False,
                 since: int | None = None) -> bool:
        """Wait up to ``timeout`` s for odometry that covers ``stamp_ns`` (:meth:`covers`);
        True if it did."""
        deadline = time.monotonic() + timeout
        with self._cv:
            since = self.rewinds if since is None else since
            if self._reached(stamp_ns, went_back, since):
                return True
            self.waits += 1
            while not self._reached(stamp_ns, went_back, since) and not self.closed:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cv.wait(left)
            return self._reached(stamp_ns, went_back, since)

    def close(self) -> None:
        """Wake a waiting worker for shutdown."""
        with self._cv:
            self.closed = True
            self._cv.notify_all()
