"""SUITDetector: every temporal variant trains and streams; training reduces every loss."""
from __future__ import annotations

import math

from modelkit import frame, small_config
import pytest
import torch

from suit_ros.model.detector import SUITDetector
from suit_ros.model.streaming import StreamingDetector


@pytest.mark.parametrize('temporal', ['none', 'dense', 'sparse', 'sparse_velocity', 'suit'])
def test_variants_train_and_stream(temporal):
    torch.manual_seed(0)
    model = SUITDetector(small_config(temporal))
    losses = model.forward_sequence([[frame(0), frame(1), frame(2)]])
    assert set(losses) == {'hm_loss', 'loc_loss', 'geo_loss', 'distill_loss', 'loss'}
    assert torch.isfinite(losses['loss'])
    losses['loss'].backward()
    runner = StreamingDetector(model)
    used = [runner.step(frame(t).points[:, :4], frame(t).stamp_ns,
                        frame(t).pose).used_memory for t in range(3)]
    assert used == [False] + [temporal != 'none'] * 2


@pytest.mark.slow
def test_optimisation_reduces_every_loss():
    torch.manual_seed(0)
    model = SUITDetector(small_config('suit'))
    batch = [[frame(t, seed=1) for t in range(3)]]
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    first = {k: float(v) for k, v in model.forward_sequence(batch).items()}
    for _ in range(25):
        losses = model.forward_sequence(batch)
        opt.zero_grad()
        losses['loss'].backward()
        opt.step()
    last = {k: float(v) for k, v in model.forward_sequence(batch).items()}
    for k in ('hm_loss', 'loc_loss', 'geo_loss'):
        assert last[k] < first[k], (k, first[k], last[k])
    assert math.isfinite(last['loss'])

