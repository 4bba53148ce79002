"""How much of a carry term's rows hold something: `suit_carry` over 20 demo frames; per frame
(last 6 printed) the rows of the carry term gated to the cells without returns, the non-zero
ones, and for each (all rows, non-zero rows) the cells touched, the carry head's needed cells
(within two cells, without returns) and the cells feeding its first layer. Run it on a tree
before the pruning (commit 4097285) to see the full windows.
Usage: python term_rows.py
"""
import torch
import torch.nn.functional as F

from suit_ros.checkpoint import load_model_as
from suit_ros.data.sequences import synthetic_sequence
from suit_ros.evaluate import step_inputs
import suit_ros.model.detector as D
from suit_ros.model.streaming import StreamingDetector
from suit_ros.tracking import TrackerConfig

torch.set_num_threads(1)
frames = synthetic_sequence('demo-real', 7, 20, sensor='sim32')
runner = StreamingDetector(load_model_as('suit_carry', None), 'cpu', tracker=TrackerConfig())
original = D.SUITDetector.predict
stats = []


def predict(self, current, past, fused, observed):  # type: ignore[no-untyped-def]
    """The model's predict, counting the carry term's rows first."""
    if isinstance(past, D.BranchTerms):
        term = D.gate_past(past.carry, observed)
        B, _, H, W = current.shape

        def cells(index):  # type: ignore[no-untyped-def]
            touched = torch.zeros(B * H * W, dtype=torch.bool)
            touched[index] = True
            near = F.max_pool2d(touched.view(B, 1, H, W).float(), 5, 1, 2)[:, 0] > 0
            needed = near & ~observed
            feed = F.max_pool2d(needed[:, None].float(), 3, 1, 1)[:, 0] > 0
            return int(touched.sum()), int(needed.sum()), int(feed.sum())
        live = term.values.abs().amax(1) > 0
        stats.append((len(term.index), int(live.sum()), cells(term.index),
                      cells(term.index[live])))
    return original(self, current, past, fused, observed)


D.SUITDetector.predict = predict
for f in frames:
    runner.step(*step_inputs(f))
print('rows, non-zero rows, (touched, needed, feeding) of all rows, of the non-zero ones')
for s in stats[-6:]:
    print(s)
