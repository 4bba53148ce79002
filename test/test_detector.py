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



def test_unknown_gt_velocities_train_without_nan():
    """Real datasets' isolated annotations have no velocity (NaN): a training step stays
    finite, and GeoNet's loss leaves out the samples on such a box instead of teaching them
    zero motion."""
    from suit_ros.model.detector import assign_velocities
    from suit_ros.structures import Detections
    torch.manual_seed(0)
    model = SUITDetector(small_config('suit'))
    frames = [frame(t) for t in range(3)]
    for f in frames:
        assert f.gt is not None
        vel = f.gt.velocities.copy()
        vel[0] = float('nan')                  # the moving car's motion is unknown
        f.gt = Detections(f.gt.boxes, vel, f.gt.scores, f.gt.labels)
    seen = []
    loss = model.geonet.loss

    def spy(logits, velocities, valid=None):
        seen.append((len(logits), velocities.detach().clone(), valid))
        return loss(logits, velocities, valid)
    model.geonet.loss = spy
    losses = model.forward_sequence([frames])
    assert all(torch.isfinite(v) for v in losses.values()), losses
    # GeoNet is taught only where the motion is known: no NaN target reaches its loss
    assert seen and all(torch.isfinite(v).all() for _, v, _ in seen)
    assert all(n == len(v) for n, v, _ in seen)
    losses['loss'].backward()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)
    centres = torch.tensor([[5.0, 3.0], [-8.0, -6.0], [20.0, 20.0]])
    vel, valid = assign_velocities(centres, torch.zeros(3, dtype=torch.long), frames[:1])
    assert valid.tolist() == [True, True, False]
    assert torch.isnan(vel[0]).all() and vel[1:].tolist() == [[0.0, 0.0], [0.0, 0.0]]
