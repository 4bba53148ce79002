"""The node benchmark (suit_ros/node_probe.py): what it counts."""
from __future__ import annotations

import pytest

from suit_ros.node_probe import _summary


def test_rate_and_latency_are_counted_over_the_playback():
    """Rate from the first cloud to the last detections; latency per answered cloud."""
    clouds = {k: 10.0 + 0.1 * k for k in range(10)}
    dets = {k: t + 0.05 + 0.01 * (k == 9) for k, t in clouds.items() if k != 4}
    out = _summary(clouds, dets, {'model_ms_p50': '40.0', 'convert_ms_p50': '2.0',
                                  'publish_ms_p50': '2.0', 'dropped_frames': '1'})
    assert out['frames_in'] == 10 and out['frames_out'] == 9 and out['dropped'] == 1
    assert out['rate_hz'] == pytest.approx(9 / (0.9 + 0.06))
    assert out['latency_ms_p50'] == pytest.approx(50.0)
    assert out['overhead_pct'] == pytest.approx(10.0)
    assert _summary({}, {}, {})['rate_hz'] == 0.0
