"""Inference copies: folded batch norms, bfloat16, the precision choice."""
from __future__ import annotations

from modelkit import cloud_in_grid, small_config
import numpy as np
import pytest
import torch

from suit_ros.model.detector import SUITDetector
from suit_ros.model.streaming import StreamingDetector


def test_inference_copy_folds_batch_norms_exactly():
    from suit_ros.model.inference import fold_batchnorm, inference_copy
    torch.manual_seed(0)
    model = SUITDetector(small_config())
    # non-trivial running statistics and affine parameters, as after training
    for m in model.modules():
        if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
            m.running_mean.uniform_(-0.5, 0.5)
            m.running_var.uniform_(0.5, 2.0)
            m.weight.data.uniform_(0.5, 1.5)
            m.bias.data.uniform_(-0.2, 0.2)
    model.eval()
    before = {k: v.clone() for k, v in model.state_dict().items()}
    fast = inference_copy(model)
    n_bn = sum(isinstance(m, torch.nn.modules.batchnorm._BatchNorm) for m in model.modules())
    assert n_bn > 0 and not any(isinstance(m, torch.nn.modules.batchnorm._BatchNorm)
                                for m in fast.modules())
    assert all(torch.equal(before[k], v) for k, v in model.state_dict().items())  # untouched
    convs = [m for m in fast.modules() if isinstance(m, torch.nn.Conv2d)]
    assert convs and all(m.weight.is_contiguous(memory_format=torch.channels_last)
                         for m in convs)                     # NHWC for oneDNN
    assert all(m.weight.is_contiguous() for m in inference_copy(model, channels_last=False)
               .modules() if isinstance(m, torch.nn.Conv2d))
    pts = cloud_in_grid(0)
    with torch.no_grad():
        a = model.encode([torch.from_numpy(pts)])
        b = fast.encode([torch.from_numpy(pts)])
        assert torch.allclose(a, b, atol=1e-4, rtol=1e-4)
        pa, pb = model.head(a), fast.head(b)
        for k in pa:
            assert torch.allclose(pa[k], pb[k], atol=1e-4, rtol=1e-4), k
    with pytest.raises(ValueError, match='eval mode'):
        fold_batchnorm(SUITDetector(small_config()).train())


def test_bfloat16_inference_copy_wraps_the_convolutions_and_keeps_float32_outputs():
    from suit_ros.model.inference import Cast, inference_copy
    torch.manual_seed(0)
    model = SUITDetector(small_config()).eval()
    fast = inference_copy(model, precision='bfloat16')
    assert isinstance(fast.backbone, Cast) and isinstance(fast.head.shared, Cast)
    assert isinstance(fast.fusion.current, Cast)
    assert all(p.dtype == torch.bfloat16 for p in fast.backbone.parameters())
    # the final 1x1 projections, the pillar encoder and GeoNet stay float32
    assert fast.head.heatmap[-1].weight.dtype == torch.float32
    assert fast.head.regression[-1].weight.dtype == torch.float32
    assert all(p.dtype == torch.float32 for p in fast.pillars.parameters())
    assert all(p.dtype == torch.float32 for p in fast.geonet.parameters())
    assert all(p.dtype == torch.float32 for p in model.parameters())        # untouched
    pts = cloud_in_grid(1)
    with torch.no_grad():
        a = model.encode([torch.from_numpy(pts)])
        b = fast.encode([torch.from_numpy(pts)])
        assert b.dtype == torch.bfloat16                 # handed on to the fusion as it is
        # bfloat16 keeps 8 significant bits: relative error about 2^-8 per layer
        assert (a - b.float()).abs().max() <= 0.05 * a.abs().max()
        fused = fast.fuse(b, None)
        assert fused.dtype == torch.bfloat16             # the head takes it as it is
        pa, pb = model.head(model.fuse(a, None)), fast.head(fused)
        for k in pa:
            assert pb[k].dtype == torch.float32
            assert (pa[k] - pb[k]).abs().max() <= 0.05 * pa[k].abs().max() + 1e-3, k
        # the memory holds float32 features, and the next frame's past term fuses in bfloat16
        memory = fast.sample_memory(fused, pb, np.eye(4)[None], [0])
        assert memory.num_samples > 0 and memory.features.dtype == torch.float32
        past, _ = fast.past_term(memory, np.eye(4)[None], [100_000_000])
        assert past is not None and past.values.dtype == torch.float32
        assert fast.fuse(b, past).dtype == torch.bfloat16
    with pytest.raises(ValueError, match='precision'):
        inference_copy(model, precision='float16')


def test_bfloat16_inference_copy_wraps_the_carry_head_too():
    from dataclasses import replace

    from suit_ros.model.inference import Cast, inference_copy
    torch.manual_seed(0)
    model = SUITDetector(replace(small_config(), fusion_gate='carry_branch')).eval()
    fast = inference_copy(model, precision='bfloat16')
    assert isinstance(fast.head.shared, Cast) and isinstance(fast.carry.head.shared, Cast)
    assert fast.carry.head.heatmap[-1].weight.dtype == torch.float32
    assert fast.carry.past.weight.dtype == torch.float32
    with torch.no_grad():
        b = fast.encode([torch.from_numpy(cloud_in_grid(1))])
        pa, pb = model.carry.head(model.fuse(b.float(), None)), fast.carry.head(fast.fuse(b, None))
    for k in pa:
        assert (pa[k] - pb[k]).abs().max() <= 0.05 * pa[k].abs().max() + 1e-3, k


def test_precision_auto_follows_the_cpu_flags(tmp_path, monkeypatch):
    from suit_ros.model import inference
    amx = tmp_path / 'amx'
    amx.write_text('processor\t: 0\nflags\t\t: fpu avx2 avx512f amx_bf16 amx_tile\n')
    plain = tmp_path / 'plain'
    plain.write_text('processor\t: 0\nflags\t\t: fpu avx2 avx512f avx512bw\n')
    assert inference.cpu_has_bf16_units(str(amx))
    assert not inference.cpu_has_bf16_units(str(plain))
    assert not inference.cpu_has_bf16_units(str(tmp_path / 'missing'))
    for has_units, want in ((True, 'bfloat16'), (False, 'float32')):
        monkeypatch.setattr(inference, 'cpu_has_bf16_units', lambda h=has_units: h)
        assert inference.resolve_precision('auto', 'cpu') == want
    assert inference.resolve_precision('auto', 'cuda') == 'float32'
    assert inference.resolve_precision('bfloat16', 'cpu') == 'bfloat16'
    with pytest.raises(ValueError, match='precision'):
        inference.resolve_precision('half', 'cpu')
    runner = StreamingDetector(SUITDetector(small_config()), precision='bfloat16')
    assert runner.precision == 'bfloat16'



@pytest.mark.parametrize('precision', ['float32', 'bfloat16'])
def test_an_identity_current_conv_is_skipped_with_the_same_values(precision):
    """A fusion whose W1 is still the identity (never trained) skips the conv in an inference
    copy, with the conv's values bit for bit; a trained W1 keeps it."""
    from suit_ros.model.fusion import PastTerm
    from suit_ros.model.inference import inference_copy
    torch.manual_seed(0)
    model = SUITDetector(small_config()).eval()
    fast = inference_copy(model, precision=precision)
    assert fast.fusion.identity_current
    current = torch.randn(1, model.backbone.out_channels, 32, 32).contiguous(
        memory_format=torch.channels_last)
    if precision == 'bfloat16':
        current = current.to(torch.bfloat16)
    C = current.shape[1]
    term = PastTerm(torch.tensor([0, 5, 5, 700]), torch.randn(4, C), (1, C, 32, 32))
    with torch.no_grad():
        skipped = fast.fusion(current, term)
        fast.fusion.identity_current = False
        conv = fast.fusion(current, term)
    assert skipped.dtype == conv.dtype and torch.equal(skipped, conv)
    assert skipped.is_contiguous(memory_format=torch.channels_last)
    with torch.no_grad():
        model.fusion.current.weight[0, 1] += 0.1
    assert not inference_copy(model, precision=precision).fusion.identity_current


def _trained_fusion(model: SUITDetector) -> SUITDetector:
    """W1 moved off the identity, a bias, W2 (and a carry branch's) non-zero: as after training."""
    with torch.no_grad():
        model.fusion.current.weight.add_(0.2 * torch.randn_like(model.fusion.current.weight))
        model.fusion.current.bias.uniform_(-0.3, 0.3)
        model.fusion.past.weight.normal_(0, 0.3)
        if model.carry is not None:
            model.carry.past.weight.normal_(0, 0.3)
            model.carry.head.heatmap[-1].bias.add_(3.0)     # carried boxes among the outputs
    return model.eval()


@pytest.mark.parametrize('precision', ['float32', 'bfloat16'])
@pytest.mark.parametrize('carry', [False, True])
def test_the_heads_read_the_fused_map_through_w1_as_on_the_formed_map(monkeypatch, precision,
                                                                       carry):
    """An inference copy of a model whose fusion was trained composes its heads' first layer
    with W1 (HeadFold) and never forms the fused map: over a stream with a memory (and a
    carry branch reading a lost half of the cloud), the detections, their scores and the
    memory's features are those of the formed map to rounding."""
    from dataclasses import replace

    from modelkit import frame

    from suit_ros.model import inference
    from suit_ros.model.fusion import FoldedFused, PastTerm
    torch.manual_seed(0)
    cfg = small_config('suit')
    if carry:
        cfg = replace(cfg, fusion_gate='carry_branch',
                      sampling=replace(cfg.sampling, carry_s=0.35, alpha=0.01, top_k=5))
    model = _trained_fusion(SUITDetector(cfg))
    K = len(cfg.class_names)

    def run(fold: bool) -> list:
        with monkeypatch.context() as m:
            if not fold:
                m.setattr(inference, 'fold_fusion', lambda model: 0)
            runner = StreamingDetector(model, precision=precision, score_thresholds=[0.05] * K)
        folded = runner.model.head.fold is not None
        assert folded == fold and (runner.model.carry is None
                                   or (runner.model.carry.head.fold is not None) == fold)
        out = []
        for t in range(4):
            f = frame(t)
            pts = f.points if t < 2 or not carry else f.points[f.points[:, 0] < 0]
            res = runner.step(pts, f.stamp_ns, f.pose)
            out.append((res, runner.memory))
        return out

    tol = 1e-4 if precision == 'float32' else 3e-2
    # the stream in float32 (in bfloat16 an untrained head's near-tied boxes come and go with
    # rounding: the maps are compared below)
    for (a, ma), (b, mb) in zip(*(run(fold) for fold in (True, False)) if precision == 'float32'
                                else ()):
        da, db = a.detections, b.detections
        assert len(da) == len(db) > 0 and a.carried.sum() == b.carried.sum()
        np.testing.assert_allclose(np.sort(da.scores), np.sort(db.scores), atol=tol)
        # order-free (rounding may swap boxes whose scores tie): each box has its twin
        for x, y in ((da, db), (db, da)):
            for box, label in zip(x.boxes, x.labels):
                twin = np.abs(y.boxes[y.labels == label] - box).max(axis=1).min()
                assert twin <= 20 * tol, (box, twin)
        torch.testing.assert_close(ma.features, mb.features, atol=10 * tol, rtol=tol)
    assert not carry or any(r.carried.any() for r, _ in run(True))
    # the maps themselves: the head on the map not formed (and at cells, as a carry head
    # reads it) against the head on the formed map, with a past term reaching the map's edge
    fast = inference.inference_copy(model, precision=precision)
    f0, f1 = frame(0), frame(1)
    with torch.no_grad():
        c0 = fast.encode([torch.from_numpy(f0.points)])
        fused0 = fast.fuse(c0, None)
        assert isinstance(fused0, FoldedFused)
        memory = fast.sample_memory(fused0, fast.head(fused0), f0.pose[None], [f0.stamp_ns])
        past, _ = fast.past_term(memory, f1.pose[None], [f1.stamp_ns])
        own = past.own if carry else past
        index = own.index.clone()
        index[:3] = torch.tensor([0, fast.grid.W - 1, fast.grid.H * fast.grid.W - 1])
        own = PastTerm(index, own.values, own.shape)      # cells moved: not distinct now
        c1 = fast.encode([torch.from_numpy(f1.points)])
        folded = FoldedFused(c1, own, fast.fusion)
        formed = folded.dense()
        want, got = fast.head(formed), fast.head(folded)
        needed = torch.rand(1, fast.grid.H, fast.grid.W) < 0.05
        needed[0, 0, 0] = needed[0, -1, -1] = True
        at_got = fast.head.forward_at(folded, needed, want)
        at_want = fast.head.forward_at(formed, needed, want)
    for k in want:
        scale = want[k].abs().max()
        assert (got[k] - want[k]).abs().max() <= tol * scale + tol, k
        assert (at_got[k] - at_want[k]).abs().max() <= tol * scale + tol, k


def test_a_fold_equals_the_formed_map_over_a_batch_at_the_edges(monkeypatch):
    """HeadFold and FoldedFused.rows on a batch of two: past rows at the corners, on the last
    row of the first map and the first of the second, one cell repeated, equal the head's
    first layer on the formed map (the whole map and gathered at cells) and its rows."""
    from suit_ros.model.fusion import FoldedFused, PastTerm, TemporalFusion
    from suit_ros.model.head import HeadFold, _neighbourhoods
    from suit_ros.ops.kernels import add_tap_spread_dense as spread_dense
    torch.manual_seed(0)
    B, C, hc, H, W = 2, 6, 5, 7, 9
    fusion = TemporalFusion(C).eval()
    with torch.no_grad():
        fusion.current.weight.normal_(0, 0.5)
        fusion.current.bias.uniform_(-1, 1)
    shared = torch.nn.Sequential(torch.nn.Conv2d(C, hc, 3, padding=1), torch.nn.ReLU())
    fold = HeadFold(shared, fusion.current, H, W)
    index = torch.tensor([0, W - 1, H * W - W, H * W - 1, H * W, 2 * H * W - 1, 3 * W + 4,
                          3 * W + 4, H * W + 2 * W])
    past = PastTerm(index, torch.randn(len(index), C), (B, C, H, W))
    current = torch.randn(B, C, H, W)
    folded = FoldedFused(current, past, fusion)
    with torch.no_grad():
        formed = folded.dense()
        want = shared(formed)
        torch.testing.assert_close(fold.dense(folded), want, atol=1e-5, rtol=1e-5)
        cells = torch.nonzero(torch.ones(B, H, W, dtype=torch.bool))
        torch.testing.assert_close(fold.at(folded, cells),
                                   want.permute(0, 2, 3, 1).reshape(-1, hc), atol=1e-5,
                                   rtol=1e-5)
        flat = torch.arange(B * H * W)
        torch.testing.assert_close(folded.rows(flat),
                                   formed.permute(0, 2, 3, 1).reshape(-1, C), atol=1e-5,
                                   rtol=1e-5)
        rows = formed.permute(0, 2, 3, 1).reshape(-1, C)
        assert _neighbourhoods(rows, cells, H, W).shape == (B * H * W, 9 * C)
        # a cell asked twice: both rows (the compiled pass takes each cell once)
        twice = torch.cat([cells[:4], cells[2:3]])
        torch.testing.assert_close(fold.at(folded, twice), want.permute(0, 2, 3, 1).reshape(
            -1, hc)[[0, 1, 2, 3, 2]], atol=1e-5, rtol=1e-5)
        # a channels-last map (an inference copy's): the compiled spread into the whole map
        from suit_ros.ops import kernels
        calls = []
        monkeypatch.setattr(kernels, 'add_tap_spread_dense',
                            lambda *a: calls.append(1) or spread_dense(*a))
        last = FoldedFused(current.contiguous(memory_format=torch.channels_last), past, fusion)
        torch.testing.assert_close(fold.dense(last), want, atol=1e-5, rtol=1e-5)
        assert calls                                   # the compiled pass ran
        lone = FoldedFused(last.current, None, fusion)
        torch.testing.assert_close(fold.dense(lone), shared(lone.dense()), atol=1e-5,
                                   rtol=1e-5)
        # no past term: the edge correction alone
        bare = FoldedFused(current, None, fusion)
        torch.testing.assert_close(fold.at(bare, cells[::5]), shared(bare.dense()).permute(
            0, 2, 3, 1).reshape(-1, hc)[::5], atol=1e-5, rtol=1e-5)
    # with autograd the tensor path (not the compiled pass) gives the same rows
    graph = FoldedFused(current.clone().requires_grad_(), past, fusion)
    torch.testing.assert_close(fold.at(graph, cells).detach(),
                               want.permute(0, 2, 3, 1).reshape(-1, hc), atol=1e-5, rtol=1e-5)


def test_no_fold_where_it_saves_nothing_or_cannot_hold():
    """A W1 still the identity (skipped already) and a dense memory are not folded; a head
    whose first layer is not a plain 3x3 conv followed by one ReLU is refused."""
    from suit_ros.model.head import HeadFold
    from suit_ros.model.inference import inference_copy
    torch.manual_seed(0)
    assert inference_copy(SUITDetector(small_config('suit')).eval()).head.fold is None
    dense = _trained_fusion(SUITDetector(small_config('dense')))
    assert inference_copy(dense).head.fold is None
    assert inference_copy(_trained_fusion(SUITDetector(small_config('suit')))).head.fold
    model = SUITDetector(small_config('suit'))
    C = model.fusion.current.out_channels
    relu = torch.nn.ReLU()
    for bad in (torch.nn.Sequential(torch.nn.Conv2d(C, 32, 1), relu),
                torch.nn.Sequential(torch.nn.Conv2d(C, 32, 3, padding=1)),
                torch.nn.Sequential(torch.nn.Conv2d(C, 32, 3, padding=2, dilation=2), relu),
                torch.nn.Sequential(torch.nn.Conv2d(C, 32, 3, padding=1,
                                                    padding_mode='reflect'), relu)):
        with pytest.raises(ValueError, match='3x3'):
            HeadFold(bad, model.fusion.current, 8, 8)


def test_the_regression_read_where_decoded_gives_the_boxes_of_the_whole_maps():
    """An inference copy runs the regression branch only at the cells it decodes and samples
    (a carry head's rows where it answered): over a stream with a memory and a lost half of
    the cloud, its boxes (carried ones among them) and its memory's boxes are those of the
    same copy with the whole maps; the maps rebuilt from its outputs are the head's."""
    from dataclasses import replace

    from modelkit import frame

    from suit_ros.model.head import CARRY_CELLS, SHARED
    torch.manual_seed(0)
    cfg = small_config('suit')
    cfg = replace(cfg, fusion_gate='carry_branch',
                  sampling=replace(cfg.sampling, carry_s=0.35, alpha=0.01, top_k=5))
    model = _trained_fusion(SUITDetector(cfg))
    K = len(cfg.class_names)
    runs = []
    for lazy in (True, False):
        runner = StreamingDetector(model, score_thresholds=[0.05] * K)
        assert runner.model.lazy_regression
        runner.model.lazy_regression = lazy
        out = []
        for t in range(5):
            f = frame(t)
            pts = f.points if t < 2 else f.points[f.points[:, 0] < 0]
            res = runner.step(pts, f.stamp_ns, f.pose)
            out.append((res, runner.memory))
        runs.append(out)
    for (a, ma), (b, mb) in zip(*runs):
        assert len(a.detections) == len(b.detections) > 0
        np.testing.assert_array_equal(a.carried, b.carried)
        np.testing.assert_allclose(a.detections.boxes, b.detections.boxes, atol=1e-4)
        np.testing.assert_allclose(a.detections.scores, b.detections.scores, atol=1e-5)
        torch.testing.assert_close(ma.boxes, mb.boxes, atol=1e-4, rtol=1e-4)
    assert sum(int(r.carried.sum()) for r, _ in runs[0]) > 0
    # the outputs themselves: a carry head's rows where it answered, the maps rebuilt
    fast = runner.model
    with torch.no_grad():
        f0 = frame(0)
        c0, o0 = fast.encode_observed([torch.from_numpy(f0.points)])
        p0 = fast.predict(c0, None, fast.fuse(c0, None, o0), o0)
        assert SHARED not in p0 and 'offset' in p0          # lazy off on this copy
        fast.lazy_regression = True
        lazy = fast.predict(c0, None, fast.fuse(c0, None, o0), o0)
        assert SHARED in lazy and 'offset' not in lazy and CARRY_CELLS not in lazy
        for k, v in fast.head.dense_outputs(lazy).items():
            torch.testing.assert_close(v, p0[k], atol=1e-5, rtol=1e-5)


def test_one_thread_runs_a_block_on_one_torch_thread_and_puts_the_count_back():
    """The step's small work runs on one torch thread; the count comes back after the block,
    also when it raises; disabled, or at one thread already, nothing changes."""
    from suit_ros.model.inference import one_thread
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        with one_thread():
            assert torch.get_num_threads() == 1
        assert torch.get_num_threads() == 2
        with pytest.raises(ValueError), one_thread():
            raise ValueError('inside')
        assert torch.get_num_threads() == 2
        with one_thread(enabled=False):
            assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
