"""Significant sampling and its relaxation windows."""
from __future__ import annotations

from modelkit import GRID, peaks_heatmap
import numpy as np
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



def _memory(xy, probs, ages=None, P=9):
    """A sparse memory of one frame: samples at metric centres ``xy`` (window of ``P`` cells
    around each, 1 m boxes), centre probability ``probs``."""
    from suit_ros.model.memory import SparseMemory
    xy = torch.tensor(xy, dtype=torch.float32)
    M = len(xy)
    offsets = torch.linspace(-0.4, 0.4, P)[None, :, None].expand(M, P, 2)
    p = torch.tensor(probs, dtype=torch.float32)[:, None].expand(M, P).clone()
    boxes = torch.cat([xy, torch.zeros(M, 1), torch.ones(M, 3), torch.zeros(M, 1)], 1)
    return SparseMemory(torch.zeros(M, dtype=torch.long), xy[:, None] + offsets,
                        torch.randn(M, P, 4), p, torch.ones(M, P, dtype=torch.bool), boxes,
                        torch.zeros(M, 2), [0], np.eye(4)[None], 3,
                        None if ages is None else torch.tensor(ages))


@pytest.mark.parametrize('grad', [True, False])
def test_keep_carried_keeps_unseen_objects_until_their_age_runs_out(grad):
    """A carried sample survives where the input has no returns and no seen detection covers
    it, up to ``carry_s``; a seen detection replaces it; a place seen empty drops it; a
    detection at an unseen place is not carried further (it cannot keep itself alive). In
    training (the tensor code) and at inference (a compiled pass)."""
    from suit_ros.model.sampling import _keep_carried_compiled, keep_carried
    cfg = SamplingConfig(carry_s=0.35)
    ms = 1_000_000
    observed = torch.zeros(1, GRID.H, GRID.W, dtype=torch.bool)
    seen_xy = (4.1, 4.1)
    c, r = torch.floor(GRID.xy_to_cell(torch.tensor(seen_xy))).long().tolist()
    observed[0, r - 3:r + 4, c - 3:c + 4] = True                     # returns around (4, 4)
    empty_xy = (-10.1, 10.1)                                         # seen, nothing there
    c, r = torch.floor(GRID.xy_to_cell(torch.tensor(empty_xy))).long().tolist()
    observed[0, r - 2:r + 3, c - 2:c + 3] = True
    new = _memory([seen_xy, (-5.0, -5.0)], [0.3, 0.9])               # seen; made by the memory
    carried = _memory([(4.3, 4.2), (-5.2, -5.1), (12.0, -8.0), (15.0, 3.0), empty_xy,
                       (40.0, 0.0)],
                      [0.9, 0.2, 0.5, 0.5, 0.8, 0.8],
                      ages=[100 * ms, 100 * ms, 350 * ms, 351 * ms, 100 * ms, 100 * ms])
    with torch.set_grad_enabled(grad):
        out = keep_carried(new, carried, observed, cfg, GRID)
        # (at inference the compiled pass answers, not the tensor code)
        assert (_keep_carried_compiled(new, carried, observed, cfg, GRID, False) is None) == grad
    centres = {tuple(round(v, 1) for v in b[:2].tolist()): int(a)
               for b, a in zip(out.boxes, out.age())}
    assert centres == {seen_xy: 0,               # seen now: the new sample, age 0
                       (-5.2, -5.1): 100 * ms,   # the carried one wins over the memory's own
                       (12.0, -8.0): 350 * ms}   # unseen, age at the limit
    # (15, 3): too old; the seen-empty place and the one off the map (40, 0): dropped
    assert out.features.shape[1:] == new.features.shape[1:]


def test_cell_flags_outside_the_map_are_false():
    from suit_ros.model.sampling import cell_flags
    flags = torch.ones(1, GRID.H, GRID.W, dtype=torch.bool)
    xy = torch.tensor([[0.0, 0.0], [GRID.W * GRID.cell, 0.0], [0.0, -30.0]])
    assert cell_flags(flags, torch.zeros(3, dtype=torch.long), xy, GRID).tolist() == [
        True, False, False]


def test_the_coarse_top_k_of_one_frame_is_that_of_a_batch():
    """A node's one frame takes a shorter way through the coarse top-K: the same cells,
    scores and order as the same frame in a batch of two; nothing when no cell reaches alpha."""
    from suit_ros.model.sampling import coarse_topk
    g = torch.Generator().manual_seed(1)
    prob = torch.rand(2, 20, 30, generator=g) ** 4
    b, cells, scores = coarse_topk(prob, 0.3, 25)
    one = coarse_topk(prob[1:], 0.3, 25)
    mine = b == 1
    assert torch.equal(one[0], torch.zeros(int(mine.sum()), dtype=torch.long))
    assert torch.equal(one[1], cells[mine]) and torch.equal(one[2], scores[mine])
    assert 0 < len(one[2]) <= 25 and (one[2] >= 0.3).all()
    empty = coarse_topk(prob[:1] * 0, 0.3, 25)
    assert all(len(t) == 0 for t in empty) and empty[1].shape == (0, 2)
