"""The quick-start demo end to end (a short drive): node, player and recorder over DDS."""
from __future__ import annotations

import subprocess
import sys

import pytest
from rosgraph import REPO, ros_env

pytestmark = pytest.mark.ros


@pytest.mark.slow
def test_demo_runs_and_reports(tmp_path):
    from suit_ros.checkpoint import default_checkpoint_path, save_checkpoint
    ckpt = default_checkpoint_path()
    if not ckpt.exists():
        from suit_ros.config import ModelConfig
        from suit_ros.model.detector import SUITDetector
        ckpt = tmp_path / 'untrained.safetensors'
        save_checkpoint(ckpt, SUITDetector(ModelConfig()), ModelConfig())
    proc = subprocess.run([sys.executable, '-m', 'suit_ros.cli', 'demo', '--out',
                           str(tmp_path / 'demo'), '--frames', '15', '--rate', '0.5',
                           '--checkpoint', str(ckpt)], cwd=REPO, env=ros_env(),
                          capture_output=True, text=True, timeout=240)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out
    assert 'frames in 15' in out and 'latency' in out and 'mAP' in out and 'NDS' in out
    assert 'published boxes per frame' in out and 'precision' in out
    # whether or not the node kept up, the last input held the last three clouds
    assert ckpt != default_checkpoint_path() or 'last input: 3 over 0.20 s' in out, out
    assert (tmp_path / 'demo' / 'bev.png').stat().st_size > 10_000
