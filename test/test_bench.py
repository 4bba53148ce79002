"""The node benchmark (suit_ros/node_probe.py): what it counts, and a live node measured."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest
from rosgraph import REPO, ros_env

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


@pytest.mark.slow
@pytest.mark.ros
def test_the_node_benchmark_measures_a_live_node(tmp_path):
    """A 20-frame drive at 10 Hz into the node over DDS: every cloud seen, the node's CPU read
    over the playback (not the player's start-up), the rate near 10 Hz."""
    code = ('import json; from suit_ros.node_probe import node_latency; '
            f'print(json.dumps(node_latency(frames=20, workdir={str(tmp_path)!r})))')
    proc = subprocess.run([sys.executable, '-c', code], cwd=REPO, env=ros_env(),
                          capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    r = json.loads(proc.stdout.strip().splitlines()[-1])
    assert r['frames_in'] == 20 and r['frames_out'] >= 18
    assert 0.05 < r['cpu_cores'] < 2.5
    assert 6.0 < r['rate_hz'] < 14.0
    assert 0 < r['latency_ms_p50'] <= r['latency_ms_p95'] < 1000
