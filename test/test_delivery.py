"""Delivery with every default: a 100-frame bag of ~1.2 MB clouds played into the node.

Separate processes over real DDS: the detector (every parameter at its default, no QoS
override), ``suit-ros play`` (which uses the shipped large-data Fast DDS profile for itself),
and a probe. Run once with the player's default reliable publishers and once with best-effort
publishers, as LiDAR drivers use.
"""
from __future__ import annotations

import re
import subprocess
import sys

import pytest
from rosgraph import Probe, diag_values, node_checkpoint, ros_env, start_node, stop

pytestmark = [pytest.mark.ros, pytest.mark.slow]

FRAMES = 100


@pytest.fixture(scope='module')
def big_bag(tmp_path_factory):
    from suit_ros.data.sim import preset
    from suit_ros.data.sim.recording import write_bag
    path = tmp_path_factory.mktemp('big') / 'bag'
    write_bag(path, preset('demo', frames=FRAMES), 7, 'mcap')
    return path


@pytest.fixture(scope='module')
def checkpoint(tmp_path_factory):
    return node_checkpoint(tmp_path_factory.mktemp('ckpt'))


@pytest.mark.parametrize('reliability', ['reliable', 'best_effort'])
def test_default_node_gets_the_clouds_of_a_played_bag(big_bag, checkpoint, reliability):
    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import PointCloud2
    node = start_node(checkpoint)
    probe = Probe()
    dets, diags = [], []
    probe.node.create_subscription(PointCloud2, '/detector/detections', dets.append, 200)
    probe.node.create_subscription(DiagnosticArray, '/diagnostics',
                                   lambda m: diags.append(diag_values(m)), 50)
    player_out = ''
    try:
        assert probe.spin_until(lambda: bool(diags) or node.poll() is not None, 90.0)
        assert node.poll() is None, stop(node)
        player = subprocess.Popen(
            [sys.executable, '-m', 'suit_ros.cli', 'play', str(big_bag), '--topics', '/points',
             '/odom', '--wait-subscribers', '20', '--start-delay', '1.5',
             '--reliability', reliability],
            env=ros_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        probe.spin_until(lambda: player.poll() is not None, 120.0)
        player_out = stop(player)
        n = len(diags)

        def settled() -> bool:      # the node has published every cloud it took
            if len(diags) < n + 2:
                return False
            a, b = diags[-2], diags[-1]
            return (a['frames_in'] == b['frames_in'] and len(dets) == int(b['frames_out'])
                    and int(b['frames_out']) + int(b['dropped_frames']) == int(b['frames_in']))
        probe.spin_until(settled, 60.0)
    finally:
        probe.close()
        node_out = stop(node)
    last = diags[-1]
    frames_in, frames_out = int(last['frames_in']), int(last['frames_out'])
    dropped = int(last['dropped_frames'])
    print(f'{reliability} publisher: node received {frames_in}/{FRAMES}, processed '
          f'{frames_out}, dropped (busy) {dropped}, lost before the callback '
          f'{last["lost_before_callback"]}, reader delay p50/max {last["reader_delay_ms_p50"]}/'
          f'{last["reader_delay_ms_max"]} ms, detections at the probe {len(dets)}; '
          f'subscription {last["points_reliability"]}; {player_out.strip().splitlines()[-1]}')
    assert 'large-data' in player_out or 'fastdds_large_data' in player_out, player_out
    expected = 'reliable' if reliability == 'reliable' else 'best_effort'
    assert last['points_reliability'] == expected, node_out[-2000:]
    from suit_ros.model.inference import resolve_precision
    # the default precision (auto) as this machine resolves it, reported in diagnostics
    assert last['model_precision'] == resolve_precision('auto', last['model_device'])
    # ground and overhang: checkpoint (the defaults), as the shipped checkpoint was trained
    from suit_ros.checkpoint import default_checkpoint_path, read_metadata
    pillars = read_metadata(default_checkpoint_path())['config']['pillars']
    assert last['model_ground'] == pillars.get('ground', 'as_given')
    assert last['model_overhang'] == pillars.get('overhang', 'keep')
    assert frames_in >= 0.95 * FRAMES, node_out[-2000:]
    # whatever was lost is counted: by the publisher's sequence numbers
    assert frames_in + int(last['lost_before_callback']) >= FRAMES - 1, node_out[-2000:]
    assert frames_out + dropped == frames_in
    assert len(dets) == frames_out
    # the node bounds numpy's BLAS pool to its threads as it does torch's (idle, its workers
    # spun on the core left to DDS: the node at 114k points took 1.6 cores)
    assert re.search(r'\d+ torch threads, BLAS threads \d+', node_out), node_out[-2000:]
