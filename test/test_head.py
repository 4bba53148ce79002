"""CenterHead: Gaussian targets, target/decode round trip, headings decoded from velocity."""
from __future__ import annotations

import math

from modelkit import GRID
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from suit_ros.model.grid import BEVGrid
from suit_ros.model.head import CenterHead, draw_gaussian, gaussian_radius


def test_gaussian_radius_formula():
    # CornerNet's rule as CenterPoint applies it: the larger root of each of the three
    # quadratics, with the published "(b + sqrt(b^2 - 4ac)) / 2" normalisation (not / 2a)
    for h, w in [(5.6, 2.4), (1.0, 1.0), (14.0, 3.5)]:
        cands = []
        for a, b, c in [(1, h + w, w * h * 0.9 / 1.1), (4, 2 * (h + w), 0.9 * w * h),
                        (0.4, -0.2 * (h + w), -0.9 * w * h)]:
            root = max(np.roots([a, -b, c]).real)            # the true quadratic root
            cands.append(root * a)                           # == (b + sqrt(...)) / 2
        assert gaussian_radius(h, w, 0.1) == pytest.approx(min(cands), rel=1e-9)
    assert gaussian_radius(4.0, 2.0, 0.1) < 4.0


def test_draw_gaussian_peak_and_clipping():
    hm = torch.zeros(10, 10)
    draw_gaussian(hm, 0, 9, 2)
    assert hm[9, 0] == 1.0 and hm.max() == 1.0 and (hm > 0).sum() == 9   # 3x3 quarter left


def test_targets_decode_round_trip():
    head = CenterHead(8, 4, GRID)
    boxes = torch.tensor([[3.3, -7.1, -0.9, 4.5, 1.9, 1.6, 0.7],
                          [-10.2, 4.4, -0.8, 0.7, 0.6, 1.8, -2.5],
                          [15.0, 15.0, -0.5, 11.0, 2.9, 3.3, 3.0]])
    vel = torch.tensor([[5.0, -1.0], [0.5, 0.5], [0.0, 12.0]])
    labels = torch.tensor([0, 2, 1])
    tgt = head.build_targets([boxes], [vel], [labels])
    assert tgt['mask'].sum() == 3
    # predictions equal to the targets: logits +/- large, regression maps written at centres
    preds = {'heatmap': torch.where(tgt['heatmap'] == 1, 10.0, -10.0)}
    reg = torch.zeros(1, 10, GRID.H, GRID.W)
    for k in range(3):
        idx = tgt['index'][0, k]
        reg[0, :, idx // GRID.W, idx % GRID.W] = tgt['reg'][0, k]
    from suit_ros.model.head import REG_SLICES
    for name, (a, b) in REG_SLICES.items():
        preds[name] = reg[:, a:b]
    out = head.decode(preds, k=10, score_threshold=0.5)[0]
    order = torch.argsort(out['labels'])
    torch.testing.assert_close(out['boxes'][order], boxes[[0, 2, 1]], atol=1e-4, rtol=0)
    torch.testing.assert_close(out['velocities'][order], vel[[0, 2, 1]])
    assert out['labels'][order].tolist() == [0, 1, 2]


def test_decode_turns_moving_boxes_to_face_their_velocity():
    grid = BEVGrid((-25.6, -25.6, -3.0, 25.6, 25.6, 3.0), 0.4, 2)
    preds = {'heatmap': torch.full((1, 1, grid.H, grid.W), -10.0),
             'offset': torch.zeros(1, 2, grid.H, grid.W), 'z': torch.zeros(1, 1, grid.H, grid.W),
             'size': torch.zeros(1, 3, grid.H, grid.W), 'rot': torch.zeros(1, 2, grid.H, grid.W),
             'vel': torch.zeros(1, 2, grid.H, grid.W)}
    preds['rot'][0, 1] = 1.0                                      # yaw 0 everywhere
    for col, vx in ((10, -5.0), (20, -0.5), (30, 5.0)):          # backwards fast/slow, forwards
        preds['heatmap'][0, 0, 5, col] = 5.0
        preds['vel'][0, 0, 5, col] = vx
    yaws = {}
    for min_speed in (1.0, 0.0):
        head = CenterHead(8, 1, grid, 8, yaw_velocity_min_speed=min_speed)
        out = head.decode(preds, 10, 0.5, 'circle', 0.2, torch.tensor([0.1]), 10)[0]
        yaws[min_speed] = {int(c): float(y) for c, y in zip(out['cells'][:, 0],
                                                             out['boxes'][:, 6])}
    assert yaws[1.0][10] == pytest.approx(-math.pi) or yaws[1.0][10] == pytest.approx(math.pi)
    assert yaws[1.0][20] == 0.0 and yaws[1.0][30] == 0.0        # slow or forwards: untouched
    assert set(yaws[0.0].values()) == {0.0}                       # disabled



@pytest.mark.parametrize('copy', [None, 'float32', 'bfloat16'])
def test_the_head_at_cells_equals_the_head_where_it_is_read(copy):
    """A carry branch's head runs only at the cells it is read at: there it gives the full
    map's values (the map's edges included), elsewhere the given maps; on the training module
    and on inference copies (folded norms, bfloat16 casts)."""
    from suit_ros.model.inference import inference_copy
    torch.manual_seed(0)
    head = CenterHead(16, 4, GRID, head_channels=8).eval()
    for m in head.modules():
        if isinstance(m, torch.nn.BatchNorm2d):        # statistics that are not the identity
            m.running_mean.uniform_(-0.5, 0.5)
            m.running_var.uniform_(0.5, 2.0)
    if copy is not None:               # as in a detector's inference copy (its head attribute)
        holder = torch.nn.Module()
        holder.head = head
        head = inference_copy(holder, precision=copy).head
    H, W = 70, 45
    x = torch.randn(2, 16, H, W)
    if copy is not None:
        x = x.contiguous(memory_format=torch.channels_last)
    if copy == 'bfloat16':
        x = x.to(torch.bfloat16)
    needed = torch.rand(2, H, W) < 0.05
    needed[0, 0, 0] = needed[0, 69, 44] = needed[1, 69, 0] = needed[1, 0, 44] = True  # corners
    with torch.no_grad():
        full = head(x)
        elsewhere = {k: torch.full_like(v, 7.0) for k, v in full.items()}
        got = head.forward_at(x, needed, elsewhere)
    tol = {'rtol': 2e-2, 'atol': 2e-2} if copy == 'bfloat16' else {'rtol': 1e-5, 'atol': 1e-5}
    for k in full:
        assert got[k].shape == full[k].shape and got[k].dtype == full[k].dtype
        g, w = got[k].permute(0, 2, 3, 1), full[k].permute(0, 2, 3, 1)
        torch.testing.assert_close(g[needed], w[needed], **tol)
        assert (g[~needed] == 7.0).all()
    nothing = head.forward_at(x, torch.zeros_like(needed), elsewhere)
    assert all(torch.equal(nothing[k], elsewhere[k]) for k in elsewhere)


def test_an_unknown_velocity_is_no_target():
    """A GT box whose velocity is NaN (a real dataset's isolated annotation) is found and sized
    as any other, but its velocity is left out of the loss: not taught as standing still, and
    no NaN reaches the loss or the gradients."""
    head = CenterHead(8, 4, GRID)
    boxes = torch.tensor([[3.3, -7.1, -0.9, 4.5, 1.9, 1.6, 0.7],
                          [-10.2, 4.4, -0.8, 4.5, 1.9, 1.6, -2.5]])
    labels = torch.tensor([0, 0])
    known = head.build_targets([boxes], [torch.tensor([[5.0, -1.0], [3.0, 3.0]])], [labels])
    unknown = head.build_targets([boxes], [torch.tensor([[5.0, -1.0], [math.nan, math.nan]])],
                                 [labels])
    assert known['vel_known'][0, :2].tolist() == [True, True]
    assert unknown['vel_known'][0, :2].tolist() == [True, False]
    assert torch.isfinite(unknown['reg']).all()
    torch.manual_seed(0)
    preds = {'heatmap': torch.randn(1, 4, GRID.H, GRID.W, requires_grad=True)}
    reg = torch.randn(1, 10, GRID.H, GRID.W, requires_grad=True)
    from suit_ros.model.head import REG_SLICES
    for name, (a, b) in REG_SLICES.items():
        preds[name] = reg[:, a:b]
    loss_known, loss_unknown = head.loss(preds, known), head.loss(preds, unknown)
    assert torch.isfinite(loss_unknown['loss'])
    # the velocity term is the mean over the known velocity alone; the rest is unchanged
    w = head.code_weights
    def term(tgt, k, ch):
        idx = tgt['index'][0, k]
        at = reg.detach()[0, ch, idx // GRID.W, idx % GRID.W]
        return float((at - tgt['reg'][0, k, ch]).abs())
    vel_known = sum(float(w[c]) * (term(known, 0, c) + term(known, 1, c)) / 2 for c in (8, 9))
    vel_unknown = sum(float(w[c]) * term(unknown, 0, c) for c in (8, 9))
    assert float((loss_known['loc_loss'] - loss_unknown['loc_loss']).detach()) == pytest.approx(
        vel_known - vel_unknown, rel=1e-4, abs=1e-5)
    loss_unknown['loss'].backward()
    assert reg.grad is not None and torch.isfinite(reg.grad).all()
    idx = unknown['index'][0, 1]
    cell = reg.grad[0, :, idx // GRID.W, idx % GRID.W]
    assert (cell[8:10] == 0).all() and (cell[:8] != 0).any()


def test_a_score_on_an_ignored_thing_costs_nothing():
    """Cells inside an ignore box (a parked bicycle on a real dataset) are no negatives: a
    confident score there costs what no score does; outside one it costs."""
    head = CenterHead(8, 4, GRID)
    car = torch.tensor([[3.3, -7.1, -0.9, 4.5, 1.9, 1.6, 0.7]])
    bike = torch.tensor([[-10.0, 6.0, -0.9, 1.7, 0.6, 1.0, 0.4]])
    args = ([car], [torch.zeros(1, 2)], [torch.tensor([0])])
    plain = head.build_targets(*args)
    ignored = head.build_targets(*args, ignore=[bike])
    assert 'hm_ignore' not in plain and ignored['hm_ignore'].shape == (1, GRID.H, GRID.W)
    col, row = (int(v) for v in GRID.xy_to_cell(bike[0, :2]))
    assert ignored['hm_ignore'][0, row, col] and ignored['hm_ignore'][0].sum() >= 2
    assert not ignored['hm_ignore'][0, row, col + 10]
    quiet = torch.full((1, 4, GRID.H, GRID.W), -9.0)

    def hm(logits, tgt):
        preds = {'heatmap': logits}
        for name, (a, b) in __import__('suit_ros.model.head', fromlist=['REG_SLICES']) \
                .REG_SLICES.items():
            preds[name] = torch.zeros(1, b - a, GRID.H, GRID.W)
        return float(head.loss(preds, tgt)['hm_loss'])
    on_bike, beside = quiet.clone(), quiet.clone()
    on_bike[0, 3, row, col] = 5.0              # a cyclist box on the parked bicycle
    beside[0, 3, row, col + 10] = 5.0
    assert hm(on_bike, ignored) == pytest.approx(hm(quiet, ignored), abs=1e-6)
    assert hm(on_bike, plain) > hm(quiet, plain) + 1.0
    assert hm(beside, ignored) > hm(quiet, ignored) + 1.0


@pytest.mark.parametrize('r', [1, 2])
def test_dilated_cells_are_what_a_max_pool_of_their_map_marks(r):
    """The sparse neighbourhood the carry head is read in equals the dense max pool it
    replaced, edges and a batch of two included, repeats in the input allowed."""
    from suit_ros.model.head import dilated_cells
    g = torch.Generator().manual_seed(r)
    B, H, W = 2, 9, 13
    flat = torch.randint(0, B * H * W, (25,), generator=g)
    flat = torch.cat([flat, flat[:5], torch.tensor([0, H * W - 1, B * H * W - 1, W - 1])])
    marked = torch.zeros(B * H * W)
    marked[flat] = 1
    want = torch.nonzero(F.max_pool2d(marked.view(B, 1, H, W), 2 * r + 1, 1, r).reshape(-1) > 0)
    assert dilated_cells(flat, H, W, r).tolist() == want[:, 0].tolist()
    assert len(dilated_cells(flat[:0], H, W, r)) == 0


@pytest.mark.parametrize('dtype', [torch.float32, torch.bfloat16])
def test_compiled_neighbourhoods_equal_the_tensor_gather(dtype):
    """The compiled gather of 3 x 3 neighbourhoods (inference) and the tensor one (autograd)
    give the same values bit for bit, on a batch of two, at the map's edges and corners, from
    the map's rows and from some of them through a ``where`` map; a bfloat16 map's come back
    as float32, exactly; a cell off the map is refused, not read."""
    from suit_ros.model.head import _neighbourhoods
    torch.manual_seed(3)
    B, H, W, C = 2, 6, 5, 7
    full = torch.randn(B * H * W, C).to(dtype)
    cells = torch.tensor([[0, 0, 0], [0, 5, 4], [1, 0, 4], [1, 5, 0], [1, 2, 3], [0, 3, 1]])
    picked = torch.tensor([3, 17, 40, 41, 59, 22, 11, 8])
    where = torch.full((B * H * W,), len(picked), dtype=torch.long)
    where[picked] = torch.arange(len(picked))
    some = torch.cat([full[picked], torch.zeros(1, C, dtype=dtype)])
    for rows, at in ((full, None), (some, where)):
        fast = _neighbourhoods(rows, cells, H, W, at)
        slow = _neighbourhoods(rows.clone().float().requires_grad_(), cells, H, W, at)
        assert fast.dtype == torch.float32 and fast.shape == (len(cells), 9 * C)
        assert torch.equal(fast, slow.detach())
    # -1 in the where map: a cell the rows do not hold reads as zero, both ways
    holes = where.clone()
    holes[holes == len(picked)] = -1
    for rows in (some[:-1], some[:-1].clone().float().requires_grad_()):
        got = _neighbourhoods(rows, cells, H, W, holes)
        assert torch.equal(got.detach(), _neighbourhoods(some, cells, H, W, where))
    assert torch.equal(_neighbourhoods(full, cells[:0], H, W), torch.zeros(0, 9 * C))
    with pytest.raises(IndexError, match='where map'):
        _neighbourhoods(some, torch.tensor([[2, 0, 0]]), H, W, where)


def test_gathered_weights_kept_on_a_copy_follow_its_weights():
    """An inference copy keeps its head layers', its fusion's and GeoNet's weights as the
    gathered products take them; a load of other weights (or an in-place update) is seen at
    the next call, not served from what was kept."""
    from suit_ros.model.fusion import TemporalFusion
    from suit_ros.model.geonet import GeoNet
    from suit_ros.model.head import _at_cells
    torch.manual_seed(5)
    H, W, C = 6, 7, 4
    stack = torch.nn.Sequential(torch.nn.Conv2d(C, 5, 3, padding=1), torch.nn.ReLU(),
                                torch.nn.Conv2d(5, 3, 1)).eval()
    stack.__dict__['gathered_cache'] = {}
    rows = torch.randn(H * W, C)
    cells = torch.tensor([[0, 0, 0], [0, 3, 4], [0, 5, 6]])
    fusion = TemporalFusion(C)
    fusion.__dict__['gathered_cache'] = {}
    geo = GeoNet(C, 3, bins=3, channels=4).eval()
    geo.as_products()
    patches = torch.randn(2, C, 3, 3)
    other = {k: v + 0.5 for k, v in stack.state_dict().items()}
    with torch.no_grad():
        before = _at_cells(stack, rows, cells, H, W)
        assert torch.equal(before, _at_cells(stack, rows, cells, H, W))   # served as kept
        stack.load_state_dict(other)
        after = _at_cells(stack, rows, cells, H, W)
        fresh = _at_cells(torch.nn.Sequential(*stack), rows, cells, H, W)  # nothing kept
        assert not torch.allclose(before, after) and torch.equal(after, fresh)
        w_before = fusion.current_weights(torch.float32)[0].clone()
        fusion.current.weight.mul_(2.0)
        torch.testing.assert_close(fusion.current_weights(torch.float32)[0], 2 * w_before)
        kept = geo(patches)
        geo.net[0].weight.add_(0.3)
        moved = geo(patches)
        assert not torch.allclose(kept, moved)
        torch.testing.assert_close(moved, geo.net(patches).flatten(1))
