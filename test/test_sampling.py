"""Significant sampling and its relaxation windows."""
from __future__ import annotations

from modelkit import GRID, peaks_heatmap
import pytest
import torch

from suit_ros.config import SamplingConfig
from suit_ros.model.sampling import Samples, relaxation_window, significant_sampling


def test_significant_sampling_one_sample_per_object():
    cells = [(10, 10), (30, 12), (40, 50), (12, 14)]                 # separated objects
    logits = peaks_heatmap(cells)

    def decode(b, c):   # a perfect regressor: every cell points at its object's centre
        xy = GRID.cell_to_xy(c)
        ctr = GRID.cell_to_xy(torch.tensor(cells))
        nearest = torch.cdist(xy, ctr).argmin(1)
        boxes = torch.cat([ctr[nearest], torch.zeros(len(c), 1),
                           torch.tensor([[1.0, 1.0, 1.5, 0.0]]).expand(len(c), 4)], 1)
        return boxes, torch.zeros(len(c), 2)
    s = significant_sampling(logits, decode, SamplingConfig(alpha=0.1, top_k=200), GRID)
    assert sorted(map(tuple, s.cells.tolist())) == sorted(cells)
    coarse = (torch.sigmoid(logits).amax(1) >= 0.1).sum().item()
    assert coarse > len(cells)                          # NMS did the reduction
    few = significant_sampling(logits, decode, SamplingConfig(alpha=0.1, top_k=3), GRID)
    assert len(few.cells) <= 3


@pytest.mark.parametrize('relax,cell,count', [
    ('square', (20, 20), 9), ('square', (0, 0), 4), ('circle', (20, 20), 5),
    ('rectangle', (20, 20), 3)])
def test_relaxation_windows(relax, cell, count):
    xy = GRID.cell_to_xy(torch.tensor([cell]))[0]
    box = torch.tensor([[xy[0], xy[1], 0.0, 2.0, 0.5, 1.5, 0.0]])     # 2.5 cells along x
    s = Samples(torch.zeros(1, dtype=torch.long), torch.tensor([cell]), torch.ones(1), box,
                torch.zeros(1, 2))
    cfg = SamplingConfig(relaxation=relax, window=3, radius=1.0)
    cells, mask = relaxation_window(s, cfg, GRID)
    assert int(mask.sum()) == count
    chosen = {tuple(c) for c in cells[0][mask[0]].tolist()}
    assert cell in chosen
    if relax == 'rectangle':
        assert chosen == {(cell[0] - 1, cell[1]), cell, (cell[0] + 1, cell[1])}

