"""The memory moved by ego motion and fused by equation (11)."""
from __future__ import annotations

from dataclasses import replace

from modelkit import GRID, frame, small_config
import numpy as np
import pytest
import torch

from suit_ros.model.detector import SUITDetector
from suit_ros.model.fusion import sparse_past_term
from suit_ros.model.memory import SparseMemory, transform_sample_positions
from suit_ros.model.streaming import StreamingDetector
from suit_ros.ops.geometry import ego_transform, pose_from_xyz_rpy, se3_inverse


def test_ego_transform_static_object_lands_on_same_cell():
    world_xy = np.array([8.3, -4.1])
    p0 = pose_from_xyz_rpy((0, 0, 1.8), (0, 0, 0.0))
    p1 = pose_from_xyz_rpy((2.0, 0.5, 1.8), (0, 0, 0.3))
    in0 = (se3_inverse(p0) @ np.r_[world_xy, 0, 1])[:2]
    in1 = (se3_inverse(p1) @ np.r_[world_xy, 0, 1])[:2]
    mem = SparseMemory(torch.zeros(1, dtype=torch.long),
                       torch.tensor(in0, dtype=torch.float32)[None, None], torch.zeros(1, 1, 4),
                       torch.ones(1, 1), torch.ones(1, 1, dtype=torch.bool),
                       torch.tensor([[in0[0], in0[1], -1.8, 1, 1, 1, 0]], dtype=torch.float32),
                       torch.zeros(1, 2), [0], p0[None], 1)
    moved = transform_sample_positions(mem, ego_transform(p1, p0)[None])[0, 0]
    np.testing.assert_allclose(moved.numpy(), in1, atol=1e-5)
    assert torch.equal(torch.floor(GRID.xy_to_cell(moved)),
                       torch.floor(GRID.xy_to_cell(torch.tensor(in1, dtype=torch.float32))))


@pytest.mark.parametrize('dt', [0.1, 0.05])
def test_fusion_equation_11_single_sample(dt):
    C = 4
    proj = torch.nn.Linear(C, C, bias=False)
    with torch.no_grad():
        proj.weight.copy_(torch.eye(C) * 2.0)
    f = torch.tensor([[[1.0, 2.0, 3.0, 4.0]]])
    pos = torch.tensor([[[5.2, -3.3]]])
    vel_bins = torch.tensor([[0.0, 0.0], [10.0, 0.0]])
    disp = (vel_bins * dt)[None]                                    # (1, 2, 2)
    q = torch.tensor([[0.25, 0.75]])
    out = sparse_past_term(f, torch.tensor([[0.8]]), torch.ones(1, 1, dtype=torch.bool), pos,
                           torch.zeros(1, dtype=torch.long), disp, q, proj, GRID, 1)
    expect = torch.zeros(1, C, GRID.H, GRID.W)
    for k in range(2):
        c, r = torch.floor(GRID.xy_to_cell(pos[0, 0] + disp[0, k])).long().tolist()
        expect[0, :, r, c] += 0.8 * q[0, k] * 2.0 * f[0, 0]
    torch.testing.assert_close(out.dense(), expect)
    # the term's rows are the cells the memory puts something in: two bins, two cells (the
    # window spanning the 1 m displacement holds more, adding nothing); a bin pruned to zero
    # weight puts nothing
    assert sorted(out.index.tolist()) == sorted(
        (expect[0].abs().sum(0).flatten() > 0).nonzero()[:, 0].tolist())
    assert len(out.index) == 2
    pruned = sparse_past_term(f, torch.tensor([[0.8]]), torch.ones(1, 1, dtype=torch.bool), pos,
                              torch.zeros(1, dtype=torch.long), disp, q, proj, GRID, 1,
                              prune=0.5)
    assert len(pruned.index) == 1
    # added in place: only the touched rows of a channels-last map, a dense add otherwise
    base = torch.randn(1, C, GRID.H, GRID.W)
    for x in (base.clone(), base.clone().contiguous(memory_format=torch.channels_last)):
        assert out.add_to(x) is x
        torch.testing.assert_close(x, base + expect)
    with pytest.raises(ValueError, match='shape'):
        out.add_to(torch.zeros(2, C, GRID.H, GRID.W))


def test_sparse_past_term_in_place_add_has_the_dense_gradients():
    """Training adds the sparse term in place into the channels-last conv output: W2, the
    features and the current conv get the same gradients as with a dense add."""
    torch.manual_seed(0)
    C, M, P = 6, 5, 9
    conv = torch.nn.Conv2d(C, C, 1)
    proj = torch.nn.Linear(C, C, bias=False)
    feats = torch.randn(M, P, C, requires_grad=True)
    pos = torch.rand(M, P, 2) * 30 - 15
    disp = torch.randn(M, 3, 2)
    q = torch.softmax(torch.randn(M, 3), 1)
    probs = torch.rand(M, P)
    x = torch.randn(1, C, GRID.H, GRID.W).contiguous(memory_format=torch.channels_last)
    weight = torch.randn(1, C, GRID.H, GRID.W)
    grads = []
    for sparse in (True, False):
        for t in (conv.weight, proj.weight, feats):
            t.grad = None
        term = sparse_past_term(feats, probs, torch.ones(M, P, dtype=torch.bool), pos,
                                torch.zeros(M, dtype=torch.long), disp, q, proj, GRID, 1)
        out = conv(x)
        assert out.is_contiguous(memory_format=torch.channels_last)
        fused = term.add_to(out) if sparse else out + term.dense()
        (fused * weight).sum().backward()
        grads.append([t.grad.clone() for t in (conv.weight, proj.weight, feats)])
    for a, b in zip(*grads):
        torch.testing.assert_close(a, b)
    assert grads[0][1].abs().sum() > 0


def test_memory_size_constant_over_frames_and_reset():
    torch.manual_seed(0)
    runner = StreamingDetector(SUITDetector(small_config('suit')))
    f = frame(0)
    sizes = {}
    for t in range(10):
        r = runner.step(f.points, int(1e9 + t * 1e8), f.pose)
        sizes[t + 1] = r.memory_bytes
    assert sizes[2] == sizes[10] > 0
    assert runner.memory.num_samples <= runner.cfg.sampling.top_k
    runner.reset('test')
    assert runner.memory_bytes == 0
    assert not runner.step(f.points, int(3e9), f.pose).used_memory
    # time going backwards or a missing pose never fuses the memory
    assert not runner.step(f.points, int(2e9), f.pose).used_memory
    assert not runner.step(f.points, int(2.1e9), None).used_memory
    assert runner.memory is None and len(runner.sweeps) == 0
    dense = StreamingDetector(SUITDetector(small_config('dense')))
    for t in range(2):
        d = dense.step(f.points, int(1e9 + t * 1e8), f.pose)
    assert d.memory_bytes > sizes[10]



def test_the_unobserved_gate_adds_the_past_only_where_the_input_has_no_returns():
    """``fusion_gate: unobserved``: the past term enters the head cells without returns within
    ``fusion_gate_radius`` cells, nowhere else; without the gate the model is unchanged."""
    from suit_ros.model.detector import gate_past
    from suit_ros.model.fusion import PastTerm
    torch.manual_seed(0)
    cfg = replace(small_config('suit'), fusion_gate='unobserved', fusion_gate_radius=1)
    model = SUITDetector(cfg).eval()
    pts = torch.from_numpy(np.array([[0.1, 0.1, 0.5, 0.5, 0.0]] * 5, np.float32))
    with torch.no_grad():
        current, observed = model.encode_observed([pts])
    H, W = observed.shape[1:]
    assert observed.sum() == 9                     # the occupied cell and its 8 neighbours
    r, c = (torch.nonzero(observed[0])[4]).tolist()
    index = torch.tensor([r * W + c, 0])           # one observed cell, one far corner
    term = PastTerm(index, torch.ones(2, current.shape[1]), (1, current.shape[1], H, W))
    kept = gate_past(term, observed)
    assert kept.index.tolist() == [0]
    dense = gate_past(term.dense(), observed)
    assert dense[0, :, r, c].abs().sum() == 0 and dense[0, :, 0, 0].sum() == current.shape[1]
    plain = SUITDetector(small_config('suit'))
    assert plain.encode_observed([pts])[1] is None
    with pytest.raises(ValueError, match='fusion_gate'):
        replace(cfg, fusion_gate='maybe')


def test_moved_memory_puts_a_static_object_where_the_new_frame_sees_it():
    """A carried sample of a parked car: cells and box centre land on the car's position in
    the new frame, the heading turns with the ego, velocities rotate, the age grows; an object
    shift (GeoNet's displacement) adds on top."""
    from suit_ros.model.memory import moved_memory
    world = np.array([8.3, -4.1, 0.0, 1.0])
    p0 = pose_from_xyz_rpy((0, 0, 1.8), (0, 0, 0.0))
    p1 = pose_from_xyz_rpy((2.0, 0.5, 1.8), (0, 0, 0.3))
    in0, in1 = (se3_inverse(p0) @ world)[:3], (se3_inverse(p1) @ world)[:3]
    mem = SparseMemory(torch.zeros(1, dtype=torch.long),
                       torch.tensor(in0[:2], dtype=torch.float32)[None, None],
                       torch.ones(1, 1, 4), torch.ones(1, 1), torch.ones(1, 1, dtype=torch.bool),
                       torch.tensor([[*in0, 4.5, 1.9, 1.6, 0.2]], dtype=torch.float32),
                       torch.tensor([[1.0, 0.0]]), [0], p0[None], 1)
    T = ego_transform(p1, p0)[None]
    positions = transform_sample_positions(mem, T)
    shift = torch.tensor([[0.5, -0.25]])
    moved = moved_memory(mem, positions, shift, T, p1[None], [100])
    np.testing.assert_allclose(moved.boxes[0, :3].numpy(), in1 + [0.5, -0.25, 0], atol=1e-4)
    np.testing.assert_allclose(moved.cell_xy[0, 0].numpy(), in1[:2] + [0.5, -0.25], atol=1e-4)
    assert moved.boxes[0, 6].item() == pytest.approx(0.2 - 0.3, abs=1e-5)
    np.testing.assert_allclose(moved.velocities[0].numpy(), [np.cos(-0.3), np.sin(-0.3)],
                               atol=1e-5)
    assert moved.age().tolist() == [100] and moved.stamps_ns == [100]     # ns since seen
    again = moved_memory(moved, positions, shift * 0, T, p1[None], [250])
    assert again.age().tolist() == [250]
    same = moved_memory(again, positions, shift * 0, T, p1[None], [250])  # a repeated stamp
    assert same.age().tolist() == [251]


@pytest.mark.parametrize('rate_hz', [10, 20])
def test_the_carry_holds_an_object_through_empty_frames_then_lets_it_go(rate_hz):
    """Streaming with ``carry_s``: a sample whose returns vanish (the object's sector lost)
    stays in the memory with a growing age (nanoseconds) for ``carry_s`` seconds whatever the
    sensor's rate (3 frames at 10 Hz, 7 at 20 Hz), then is dropped; training through such a
    clip reaches W2 and GeoNet."""
    torch.manual_seed(0)
    cfg = replace(small_config('suit'), fusion_gate='unobserved', fusion_gate_radius=1,
                  sampling=replace(small_config().sampling, carry_s=0.35, alpha=0.01,
                                   top_k=3))
    model = SUITDetector(cfg).eval()
    sd = StreamingDetector(model)
    f = frame(0)
    frame_ns, never = 1_000_000_000 // rate_hz, 350_000_001     # a frame; past the limit
    held = 350_000_000 // frame_ns                               # frames carried
    ages = []
    for t in range(held + 3):
        pts = f.points if t == 0 else f.points[np.abs(f.points[:, 1]) > 30]   # all lost
        sd.step(pts[:, :4], int(1e9 + t * frame_ns), f.pose)
        ages.append(sorted(sd.memory.age().tolist()))
    seen = ages[0].count(0)
    assert seen > 0
    # held with a growing age while nothing is seen (beside them: samples the memory made
    # itself in the empty frame, given an age past the limit at once, never carried on)
    for t in range(1, held + 1):
        assert ages[t].count(t * frame_ns) == seen
    assert set(ages[held + 1]) <= {never} and set(ages[held + 2]) <= {never}   # too old
    if rate_hz == 10:
        model.train()
        losses = model.forward_sequence([[frame(t) for t in range(3)]])
        losses['loss'].backward()
        assert model.fusion.past.weight.grad is not None


def test_the_output_gate_keeps_the_observed_cells_as_the_current_frame_alone():
    """``fusion_gate: unobserved_output``: a past term next to observed cells reaches their
    outputs through the head's receptive field with the input gate only; with the output gate
    those cells decode exactly as without a memory, the unobserved ones still see the past."""
    from suit_ros.model.fusion import PastTerm
    torch.manual_seed(0)
    pts = torch.from_numpy(np.array([[0.1, 0.1, 0.5, 0.5, 0.0]] * 5, np.float32))
    outs = {}
    for gate in ('unobserved', 'unobserved_output'):
        torch.manual_seed(0)
        model = SUITDetector(replace(small_config('suit'), fusion_gate=gate)).eval()
        with torch.no_grad():
            current, observed = model.encode_observed([pts])
            H, W = observed.shape[1:]
            r, c = torch.nonzero(observed[0])[0].tolist()
            near = torch.tensor([(r - 1) * W + c, (r - 2) * W + c])   # unobserved, next to it
            past = PastTerm(near, torch.full((2, current.shape[1]), 5.0),
                            (1, current.shape[1], H, W))
            fused = model.fuse(current, past, observed)
            preds = model.predict(current, past, fused, observed)
            alone = model.head(model.fusion(current, None))
        outs[gate] = (preds['heatmap'], alone['heatmap'], observed)
    hm, alone, obs = outs['unobserved']
    assert not torch.allclose(hm[0, :, obs[0]], alone[0, :, obs[0]])        # leaks in
    hm, alone, obs = outs['unobserved_output']
    assert torch.equal(hm[0, :, obs[0]], alone[0, :, obs[0]])
    assert not torch.allclose(hm[0, :, ~obs[0]], alone[0, :, ~obs[0]])


def _stream(model, clouds):
    """Run ``model`` frame by frame over ``(points, frame)`` pairs; per frame its predictions,
    observed cells and memory."""
    memory, out = None, []
    with torch.no_grad():
        for pts, f in clouds:
            poses, stamps = f.pose[None], [f.stamp_ns]
            current, observed = model.encode_observed([torch.from_numpy(pts)])
            past, aux = model.past_term(memory, poses, stamps)
            fused = model.fuse(current, past, observed)
            preds = model.predict(current, past, fused, observed)
            memory = model.sample_memory(fused, preds, poses, stamps,
                                         model.carried(memory, aux, poses, stamps), observed)
            # an inference copy reads its regression where decoded: the maps, to compare
            out.append(({**preds, **model.head.dense_outputs(preds)}, observed, memory))
    return out


def test_the_carry_branch_decodes_observed_cells_as_the_model_without_it(tmp_path):
    """``fusion_gate: carry_branch``: over a stream whose object's side is lost for three
    frames, the observed cells' outputs and the model's own memory equal those of the model
    without a gate or a carry, whatever the carry branch's weights; the unobserved cells are
    the carry head's, and the carried samples reach them. A checkpoint without a carry branch
    starts its head as the model's own."""
    from suit_ros.checkpoint import load_weights_into, save_checkpoint
    torch.manual_seed(0)
    cfg = replace(small_config('suit'), fusion_gate='carry_branch',
                  sampling=replace(small_config().sampling, carry_s=0.35, alpha=0.01, top_k=5))
    branch = SUITDetector(cfg).eval()
    plain = SUITDetector(replace(cfg, fusion_gate='none',
                                 sampling=replace(cfg.sampling, carry_s=0.0))).eval()
    torch.manual_seed(1)
    with torch.no_grad():
        for p in plain.parameters():
            p.add_(torch.randn_like(p) * 0.02)
    path = save_checkpoint(tmp_path / 'plain.safetensors', plain, plain.cfg)
    assert load_weights_into(branch, path) == ['carry.past.weight']
    assert torch.equal(branch.carry.head.heatmap[-1].weight, plain.head.heatmap[-1].weight)
    with torch.no_grad():
        branch.carry.past.weight.normal_(0, 0.2)
        for p in branch.carry.head.parameters():
            p.add_(torch.randn_like(p) * 0.05)
    clouds = []
    for t in range(6):
        f = frame(t)
        pts = f.points if t < 2 or t > 4 else f.points[f.points[:, 0] < 0]   # x > 0 lost
        clouds.append((pts, f))
    ref, got = _stream(plain, clouds), _stream(branch, clouds)
    carried_seen = 0
    for (rp, _, rm), (bp, obs, bm) in zip(ref, got):
        seen = obs[0]
        for key in rp:
            assert torch.equal(bp[key][0, :, seen], rp[key][0, :, seen]), key
            assert torch.equal(bp.get('own.' + key, bp[key]), rp[key])
        own = bm.select(torch.nonzero(bm.owned())[:, 0])
        assert torch.equal(own.features, rm.features) and torch.equal(own.cell_xy, rm.cell_xy)
        carried_seen += int((~bm.owned()).sum())
    assert carried_seen > 0
    # the lost frames: the unobserved cells differ from the plain model's
    bp, obs, _ = got[3]
    assert not torch.allclose(bp['heatmap'][0, :, ~obs[0]], ref[3][0]['heatmap'][0, :, ~obs[0]])
    # the carry branch trains; the rest can stay frozen
    branch.train()
    losses = branch.forward_sequence([[frame(t) for t in range(3)]])
    losses['loss'].backward()
    assert branch.carry.past.weight.grad is not None
    assert branch.carry.head.heatmap[-1].weight.grad is not None
    branch.eval()
    _check_decode(branch, plain, got[3], ref[3])


def _check_decode(branch, plain, got, ref):
    """``SUITDetector.decode``: the boxes at observed cells are the head's, in order; a box
    at an unobserved cell is marked carried, and none stands within ``head.carry_nms_radius``
    of a surer box of its class; without a carry branch nothing is carried."""
    (bp, obs, _), (rp, _, _) = got, ref
    # a random heatmap (the random carry head's is surer than any observed cell), so that the
    # candidates hold both kinds of cells
    torch.manual_seed(2)
    bp = {**bp, 'heatmap': torch.randn_like(bp['heatmap'])}
    thr = torch.zeros(len(branch.cfg.class_names))
    with torch.no_grad():
        out = branch.decode(bp, obs, 300, thr, 0.2, 300)
        head = branch.head.decode(bp, 300, thr, 'rotated', 0.2, None, 300)[0]
        plain_out = plain.decode(rp, obs, 200, thr, 0.2, 200)
    cells = out['cells']
    assert torch.equal(out['carried'], ~obs[0, cells[:, 1], cells[:, 0]])
    assert 0 < int(out['carried'].sum()) < len(cells)
    at_seen = obs[0, head['cells'][:, 1], head['cells'][:, 0]]
    assert torch.equal(out['boxes'][~out['carried']], head['boxes'][at_seen])
    assert int((~at_seen).sum()) > int(out['carried'].sum())      # some carried boxes went
    radius = torch.tensor(branch.cfg.head.carry_nms_radius)
    xy, lab, sc = out['boxes'][:, :2], out['labels'], out['scores']
    for i in torch.nonzero(out['carried'])[:, 0]:
        surer = (sc > sc[i]) & (lab == lab[i])
        assert not bool(((xy[surer] - xy[i]).norm(dim=1) < radius[lab[i]]).any())
    assert not bool(plain_out['carried'].any())
    assert torch.equal(plain_out['boxes'], plain.head.decode(rp, 200, thr, 'rotated', 0.2, None,
                                                             200)[0]['boxes'])


def test_a_carry_branch_on_a_single_frame_base_decodes_its_seen_cells_as_the_base():
    """A carry branch on a model whose own fusion never trained (W1 the identity, own W2
    zero: docs/experiments/memory_carry, run 10): the observed cells' outputs are the
    single-frame model's; the inference copy skips the identity conv and the zero own term
    with the same values as computing them."""
    from suit_ros.model.inference import inference_copy
    torch.manual_seed(0)
    cfg = replace(small_config('suit'), fusion_gate='carry_branch',
                  sampling=replace(small_config().sampling, carry_s=0.35, alpha=0.01, top_k=5))
    branch = SUITDetector(cfg).eval()
    single = SUITDetector(replace(cfg, temporal='none', fusion_gate='none',
                                  sampling=replace(cfg.sampling, carry_s=0.0))).eval()
    single.load_state_dict({k: v for k, v in branch.state_dict().items()
                            if k in single.state_dict()})
    with torch.no_grad():
        branch.carry.past.weight.normal_(0, 0.2)
    clouds = []
    for t in range(6):
        f = frame(t)
        pts = f.points if t < 2 or t > 4 else f.points[f.points[:, 0] < 0]   # x > 0 lost
        clouds.append((pts, f))
    fast = inference_copy(branch)
    assert fast.fusion.identity_current and fast.fusion.zero_past
    slow = inference_copy(branch)
    slow.fusion.identity_current = slow.fusion.zero_past = False
    got, ref, base = _stream(fast, clouds), _stream(slow, clouds), _stream(single, clouds)
    for (gp, obs, gm), (rp, _, rm), (sp, _, _) in zip(got, ref, base):
        for key in gp:
            assert torch.equal(gp[key], rp[key]), key
        for key in sp:
            seen = obs[0]
            torch.testing.assert_close(gp[key][0, :, seen], sp[key][0, :, seen],
                                       rtol=1e-4, atol=1e-4)
        assert torch.equal(gm.features, rm.features)


def test_the_window_and_the_triples_give_the_same_past_terms():
    """The past term's two ways (the per-sample window of training, the weighted triples of
    inference) give the same maps, on a batch of two with samples at the map's edge, pruned
    bins and a projection of a subset of the samples (a carry branch's own term)."""
    from suit_ros.model.fusion import _triple_terms, _window_terms, sparse_past_terms
    torch.manual_seed(4)
    M, P, K, C, B = 7, 9, 5, 6, 2
    feats = torch.randn(M, P, C)
    positions = torch.rand(M, P, 2) * 40 - 20
    positions[0] = torch.tensor([GRID.point_range[0] + 0.05, 0.0])          # on the map's edge
    disp = torch.randn(M, K, 2) * 1.5
    q0 = torch.softmax(torch.randn(M, K), 1)
    q = q0 * (q0 >= 0.15)
    probs = torch.rand(M, P)
    mask = torch.rand(M, P) > 0.2
    batch_index = torch.tensor([0, 1, 0, 1, 1, 0, 0])
    own, carry = torch.nn.Linear(C, C, bias=False), torch.nn.Linear(C, C + 2, bias=False)
    projections = [(own, torch.tensor([1, 4, 5])), (carry, None)]
    shapes = [(B, C, GRID.H, GRID.W), (B, C + 2, GRID.H, GRID.W)]
    cells = torch.floor(GRID.xy_to_cell(positions[:, :, None, :] + disp[:, None])).long()
    w = (probs * mask)[:, :, None] * q[:, None, :]
    with torch.no_grad():
        window = _window_terms(feats, positions, batch_index, projections, GRID, shapes,
                               cells, w)
        # on the CPU without autograd: the compiled pass, each cell's sum projected once
        triples = sparse_past_terms(feats, probs, mask, positions, batch_index, disp, q0,
                                    projections, GRID, B, prune=0.15)
    with torch.enable_grad():               # the tensor code (autograd on)
        tensors = _triple_terms(feats, positions, batch_index, projections, GRID, shapes,
                                cells, w)
        assert all(torch.equal(a.index, b.index) and torch.equal(a.values, b.values)
                   for a, b in zip(tensors, sparse_past_terms(
                       feats, probs, mask, positions, batch_index, disp, q0, projections,
                       GRID, B, prune=0.15)))
    for a, b, c in zip(window, triples, tensors):
        torch.testing.assert_close(a.dense(), b.dense(), atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(c.dense().detach(), b.dense(), atol=1e-5, rtol=1e-5)
        assert torch.equal(b.index, c.index)                   # the same cells, in order
        assert b.distinct and c.distinct
        some = torch.cat([b.index[::2], torch.tensor([0, 5, b.index[-1] + 1])])
        plain = type(b)(b.index, b.values, b.shape)           # read as if it had repeats
        assert torch.equal(b.at(some), plain.at(some))
        assert b.dense().abs().sum() > 0
        assert len(torch.unique(b.index)) == len(b.index)      # one row per cell touched
    with torch.no_grad():                   # a subset with no sample: no row
        none = sparse_past_terms(feats, probs, mask, positions, batch_index, disp, q0,
                                 [(own, torch.zeros(0, dtype=torch.long)), (carry, None)],
                                 GRID, B, prune=0.15)
    assert len(none[0].index) == 0 and none[0].values.shape == (0, C)
    assert torch.equal(none[1].index, triples[1].index)
