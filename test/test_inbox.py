"""The node's mailbox and odometry gate (suit_ros.inbox), rclpy-free, with real threads."""
from __future__ import annotations

import threading
import time

from suit_ros.inbox import CloudMailbox, OdometryGate

S = 10**9


def test_the_newest_cloud_wins_and_replaced_ones_are_dropped():
    box: CloudMailbox[str] = CloudMailbox()
    for k in range(5):
        assert box.put(f'c{k}', k, {'publication_sequence_number': k + 1})
    assert box.take(0.01) == 'c4'
    assert (box.frames_in, box.dropped, box.lost) == (5, 4, 0)
    assert box.take(0.01) is None                          # empty: waits, then None
    assert not box.put('again', 4) and box.duplicates == 1  # the same cloud twice


def test_the_last_replaced_clouds_go_to_the_worker_with_the_newest():
    box: CloudMailbox[str] = CloudMailbox(keep_replaced=2)
    for k in range(5):
        box.put(f'c{k}', k)
    assert box.take_all(0.01) == ('c4', ['c2', 'c3'])     # oldest first; c0, c1 let go
    assert box.dropped == 4                               # still dropped: no detection
    box.put('c5', 5)
    assert box.take_all(0.01) == ('c5', [])               # nothing replaced since
    assert box.take_all(0.01) == (None, [])
    box.put('c6', 6)
    box.put('c7', 7)
    box.close()
    assert box.take_all(0.01) == (None, [])               # closed: nothing handed out
    plain: CloudMailbox[str] = CloudMailbox()
    plain.put('a', 'a')
    plain.put('b', 'b')
    assert plain.take_all(0.01) == ('b', [])              # keeps none by default


def test_sequence_gaps_count_as_lost_only_when_asked():
    box: CloudMailbox[int] = CloudMailbox()
    box.put(1, 'a', {'publication_sequence_number': 1})
    box.put(2, 'b', {'publication_sequence_number': 5})
    assert box.lost == 3 and len(box.losses) == 1
    box.put(3, 'c', {'publication_sequence_number': 9}, count_gaps=False)
    assert box.lost == 3
    box.put(4, 'd', {'publication_sequence_number': 10,
                     'received_timestamp': time.time_ns() - 20_000_000})
    assert box.lost == 3 and 0.015 < box.reader_delays[-1] < 1.0


def test_a_publisher_that_left_is_no_baseline_for_the_next():
    """Sequence numbers count per publisher: when one leaves right after it sent, the one
    that stays is not measured against its numbers (the graph, asked at the gap, already
    holds one publisher). Real losses after that are counted again."""
    one = lambda: True  # noqa: E731 - the graph holds one publisher when asked
    box: CloudMailbox[int] = CloudMailbox()
    box.put(1, 'a', {'publication_sequence_number': 50_000}, count_gaps=one)
    box.put(2, 'b', {'publication_sequence_number': 7}, count_gaps=one)    # B, then it left
    box.put(3, 'c', {'publication_sequence_number': 50_001}, count_gaps=one)
    assert box.lost == 0 and not box.losses
    box.put(4, 'd', {'publication_sequence_number': 50_002}, count_gaps=one)
    box.put(5, 'e', {'publication_sequence_number': 50_005}, count_gaps=one)
    assert box.lost == 2
    # two publishers taking turns, the graph saying so, then B leaves: nothing counted
    two = [False]
    box2: CloudMailbox[int] = CloudMailbox()
    for k in range(5):
        box2.put(2 * k, f'a{k}', {'publication_sequence_number': 10 + k},
                 count_gaps=lambda: not two[0])
        two[0] = True
        box2.put(2 * k + 1, f'b{k}', {'publication_sequence_number': 5000 + k},
                 count_gaps=lambda: not two[0])
    two[0] = False
    box2.put(99, 'a5', {'publication_sequence_number': 15}, count_gaps=lambda: not two[0])
    box2.put(100, 'a6', {'publication_sequence_number': 16}, count_gaps=lambda: not two[0])
    assert box2.lost == 0


def test_a_waiting_worker_is_woken_by_a_cloud_and_by_close():
    box: CloudMailbox[str] = CloudMailbox()
    got: list[object] = []
    worker = threading.Thread(target=lambda: got.append(box.take(5.0)))
    worker.start()
    time.sleep(0.05)
    box.put('cloud', 1)
    worker.join(2.0)
    assert got == ['cloud']
    worker = threading.Thread(target=lambda: got.append(box.take(5.0)))
    worker.start()
    t0 = time.monotonic()
    box.close()
    worker.join(2.0)
    assert got[-1] is None and time.monotonic() - t0 < 1.0


def test_odometry_gate_waits_for_the_stamp_and_ignores_the_future():
    gate: OdometryGate[str] = OdometryGate()
    now = 100 * S
    gate.put('a', now - S // 10, now, 1.0)
    assert gate.covers(now - S // 10) and not gate.covers(now)
    gate.put('future', now + 10 * S, now, 1.0)             # queued, but ends no wait
    assert gate.latest_ns == now - S // 10
    t0 = time.monotonic()
    assert not gate.wait_for(now, 0.1) and 0.09 < time.monotonic() - t0 < 1.0
    threading.Timer(0.05, lambda: gate.put('b', now + S // 100, now, 1.0)).start()
    assert gate.wait_for(now, 2.0)
    assert gate.drain() == ['a', 'future', 'b'] and gate.drain() == []
    assert gate.waits == 2
    sim: OdometryGate[str] = OdometryGate()
    sim.put('sim', 500 * S, 0, 1.0)                         # no clock yet: not checked
    assert sim.latest_ns == 500 * S
    gate.close()
    assert not gate.wait_for(10**12, 5.0)


def test_repeated_stamps_are_new_clouds_unless_a_subscription_overlaps():
    """The node keys a cloud by its stamp, frame and the publisher's sequence number and
    source time: a driver that stamps every cloud 0, or a bag played in a loop, sends new
    clouds, all taken; only a copy (same key) while a retiring subscription overlaps the new
    one is dropped, and counted."""
    box: CloudMailbox[int] = CloudMailbox()
    for k in range(20):
        key = (0, 0, 'lidar', k + 1, 12345 + k)
        assert box.put(k, key, {'publication_sequence_number': k + 1}, dedupe=False)
    assert (box.frames_in, box.duplicates) == (20, 0)
    assert box.put(20, ('a',), dedupe=True) and not box.put(21, ('a',), dedupe=True)
    assert box.duplicates == 1 and box.frames_in == 21
    assert box.put(22, ('a',), dedupe=False) and box.frames_in == 22


def test_the_odometry_gate_follows_time_back():
    """After a loop or a clock reset the gate's newest stamp goes back with the odometry, so
    the worker waits for the new time line's poses again instead of seeing them covered."""
    gate: OdometryGate[str] = OdometryGate()
    gate.put('a', 1000 * S, 0, 1.0)
    assert gate.covers(999 * S)
    gate.put('b', 5 * S, 0, 1.0)                       # 995 s back: late, or a new line?
    assert gate.latest_ns == 1000 * S
    gate.put('c', 5 * S + S // 50, 0, 1.0)             # a second one: time went back
    assert gate.latest_ns == 5 * S + S // 50 and not gate.covers(6 * S)
    gate.put('d', 5 * S - S // 2, 0, 1.0)              # a little late: the newest stays
    assert gate.latest_ns == 5 * S + S // 50
    slow: OdometryGate[str] = OdometryGate()           # 1 Hz odometry (GNSS only) loops too
    for t in (100, 101, 102, 3, 4):
        slow.put('o', t * S, 0, 1.0)
    assert slow.latest_ns == 4 * S


def test_the_odometry_gate_follows_time_back_a_little():
    """Time goes back 0.3 s (a simulator reset soon after its start): three stamps in a row
    before the newest, each after the last, are the new time line. A cloud that went back is
    covered only by odometry that went back since the clouds last did (``since``), and
    settled: while the run is open the odometry about its stamp may be either line's. A cloud
    that did not go back is on the line before (one still on its way)."""
    gate: OdometryGate[str] = OdometryGate()
    for k in range(21):                                # 0 .. 0.4 s at 50 Hz
        gate.put('o', k * S // 50, 0, 1.0)
    since = gate.rewinds
    assert gate.covers(S // 4) and not gate.covers(S // 4, True, since)
    gate.put('r', S // 10, 0, 1.0)                     # 0.3 s back: settling
    assert gate.latest_ns == 2 * S // 5 and not gate.covers(S // 10, True, since)
    assert gate.covers(S // 4)                         # a cloud in order: as before
    gate.put('r', S // 10 + S // 50, 0, 1.0)
    gate.put('r', S // 10 + 2 * S // 50, 0, 1.0)       # the third: the new line
    assert gate.latest_ns == S // 10 + 2 * S // 50 and gate.rewinds == since + 1
    assert gate.covers(S // 10, True, since) and not gate.covers(S // 10, True, gate.rewinds)
    # the line before's last cloud, on its way: covered by the line before, without a wait
    assert gate.covers(2 * S // 5, False, since) and not gate.covers(2 * S // 5)


def test_odometry_from_before_a_cloud_that_went_back_is_not_its_odometry():
    """After time went back the first cloud of the new time line (its stamp before the last
    cloud's) can come before its odometry: the old line's does not cover it (60 s ahead, or
    a little), so the worker waits (odom_wait_s) for the new line's. A cloud that is only
    late (none went back) waits as long, then runs (the pipeline gives it no pose)."""
    gate: OdometryGate[str] = OdometryGate()
    gate.put('a', 1000 * S, 0, 1.0)
    assert gate.covers(1000 * S - S // 2) and gate.covers(995 * S)      # in order: covered
    assert not gate.covers(1000 * S - S // 2, True, 0) and not gate.covers(940 * S, True, 0)
    t0 = time.monotonic()
    assert not gate.wait_for(940 * S, 0.05, True, 0) and time.monotonic() - t0 >= 0.04
    assert gate.wait_for(995 * S, 0.05) and gate.waits == 1          # in order: no wait
    waiter = threading.Thread(target=lambda: got.append(gate.wait_for(940 * S, 5.0, True, 0)))
    got: list[bool] = []
    waiter.start()
    for t in (939 * S, 939 * S + S // 2, 940 * S):       # the new line's odometry comes
        time.sleep(0.02)
        gate.put('b', t, 0, 1.0)
    waiter.join(2.0)
    assert got == [True]


def test_odometry_the_pipeline_will_refuse_is_no_odometry_to_wait_for():
    """A message with a NaN position or a zero quaternion is queued (the pipeline counts and
    reports it) but moves neither the gate's newest stamp nor its time line: a cloud must not
    be taken as covered, nor time as gone back, by poses that will never be buffered."""
    gate: OdometryGate[str] = OdometryGate()
    gate.put('a', 10 * S, 0, 1.0)
    gate.put('bad', 11 * S, 0, 1.0, usable=False)          # ahead: not the newest
    assert gate.latest_ns == 10 * S and not gate.covers(10 * S + S // 2)
    for k in range(3):                                    # back, three in a row: no rewind
        gate.put('bad', 9 * S + k * S // 10, 0, 1.0, usable=False)
    assert gate.rewinds == 0 and gate.latest_ns == 10 * S
    assert gate.drain() == ['a', 'bad', 'bad', 'bad', 'bad']
