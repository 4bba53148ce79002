"""The node benchmark (suit_ros/node_probe.py): what it counts."""
from __future__ import annotations

import pytest

from suit_ros.node_probe import _summary


def test_rate_and_latency_are_counted_over_the_playback():
    """Rate from the first cloud to the last detections; latency per answered cloud."""
    clouds = {k: 10.0 + 0.1 * k for k in range(10)}
    dets = {k: t + 0.05 + 0.01 * (k == 9) for k, t in clouds.items() if k != 4}
    out = _summary(clouds, dets, {'model_ms_p50': '40.0', 'convert_ms_p50': '2.0',
                                  'publish_ms_p50': '2.0', 'dropped_frames': '1',
                                  'frames_sweeps_only': '1', 'input_sweeps': '3 over 0.20 s'})
    assert out['frames_in'] == 10 and out['frames_out'] == 9 and out['dropped'] == 1
    assert out['sweeps_only'] == 1 and out['input_sweeps'] == '3 over 0.20 s'
    assert out['rate_hz'] == pytest.approx(9 / (0.9 + 0.06))
    assert out['latency_ms_p50'] == pytest.approx(50.0)
    assert out['overhead_pct'] == pytest.approx(10.0)
    assert out['node_latency_ms_p95'] != out['node_latency_ms_p95']     # nan: not reported
    own = _summary(clouds, dets, {'latency_ms_p50': '61.5', 'latency_ms_p95': '88.0',
                                  'latency_reference': 'header stamp'})
    assert own['node_latency_ms_p50'] == 61.5 and own['node_latency_ms_p95'] == 88.0
    assert own['node_latency_from'] == 'stamp'
    assert _summary(clouds, dets, {'latency_reference': 'receive time (header stamps 9e7 s '
                                   'from the node clock)'})['node_latency_from'] == 'receipt'
    assert _summary({}, {}, {})['rate_hz'] == 0.0


def test_a_densified_cloud_keeps_every_point_and_its_scan_order():
    """The 260k-point load test's clouds: every original point as it was, and jittered
    copies each right after its original; the other fields copied; plain arrays alike."""
    import numpy as np

    from suit_ros.data.sim.recording import densified
    n = 5000
    cloud = np.zeros(n, dtype=[('x', 'f4'), ('y', 'f4'), ('z', 'f4'), ('intensity', 'f4'),
                               ('ring', 'u2')])
    az = np.linspace(-np.pi, np.pi, n, endpoint=False)
    cloud['x'], cloud['y'], cloud['z'] = 20 * np.cos(az), 20 * np.sin(az), -1.5
    cloud['intensity'] = np.arange(n)
    cloud['ring'] = np.arange(n) % 64
    out = densified(cloud, 2.3, np.random.default_rng(0))
    assert len(out) == int(n * 2.3) and out.dtype == cloud.dtype
    src = out['intensity'].astype(int)                  # each row's original
    assert (np.diff(src) >= 0).all()                    # scan order kept
    first = np.r_[True, np.diff(src) > 0]               # the first row of each point
    assert first.sum() == n and (out[first] == cloud).all()     # every original, unchanged
    assert (out['ring'] == cloud['ring'][src]).all()
    moved = np.hypot(out['x'] - cloud['x'][src], out['y'] - cloud['y'][src])[~first]
    assert 0.01 < float(np.median(moved)) < 0.1
    plain = np.c_[cloud['x'], cloud['y'], cloud['z'], cloud['intensity']]
    dense = densified(plain, 1.5, np.random.default_rng(1))
    assert len(dense) == int(n * 1.5) and (np.diff(dense[:, 3]) >= 0).all()
    assert len(np.unique(dense[:, 3])) == n


def test_steal_is_the_share_of_all_cpu_time_between_two_readings():
    from suit_ros.node_probe import cpu_jiffies, steal_pct
    assert steal_pct((10, 1000), (60, 2000)) == 5.0
    assert steal_pct((10, 1000), (10, 1000)) != steal_pct((10, 1000), (10, 1000))   # nan
    steal, total = cpu_jiffies()
    assert 0 <= steal <= total
