"""The streaming detector: reset rules with the tracker, candidates and literal modes."""
from __future__ import annotations

from modelkit import frame, small_config
import pytest
import torch

from suit_ros.model.detector import SUITDetector
from suit_ros.model.streaming import StreamingDetector


def carry_branch_model() -> SUITDetector:
    """A small SUIT model with a carry branch whose projection is not zero, carrying up to 3
    frames, sampling at a low alpha (seeded)."""
    from dataclasses import replace
    torch.manual_seed(0)
    cfg = replace(small_config('suit'), fusion_gate='carry_branch',
                  sampling=replace(small_config().sampling, carry_s=0.35, alpha=0.01, top_k=5))
    model = SUITDetector(cfg).eval()
    with torch.no_grad():
        model.carry.past.weight.normal_(0, 0.2)
    return model


def test_tracker_in_the_stream_follows_the_reset_rules():
    from suit_ros.tracking import TrackerConfig
    torch.manual_seed(0)
    model = SUITDetector(small_config('suit'))
    K = len(model.cfg.class_names)
    filt = TrackerConfig(birth_score=0.0)         # an untrained head is never confident
    runner = StreamingDetector(model, score_thresholds=[0.0] * K, tracker=filt)
    f = frame(0)
    r1 = runner.step(f.points, int(1e9), f.pose)
    assert len(r1.detections) > 0 and (r1.track_ids > 0).all()
    assert len(set(r1.track_ids.tolist())) == len(r1.detections)
    r2 = runner.step(f.points, int(1.1e9), f.pose)
    assert set(r2.track_ids.tolist()) & set(r1.track_ids.tolist())
    assert runner.tracks is not None and 'tracking' in r2.timings
    tracks = runner.tracks
    runner.reset('drop memory', sweeps=False)     # the feature memory only: tracks stay
    assert len(tracks) > 0
    runner.set_tracker(filt)              # unchanged settings keep the tracks
    assert runner.tracks is tracks
    # a change of how clouds are read keeps the tracks, memory and sweeps go; a frame with
    # no pose after it still ends them (no odometry frame to carry them in)
    runner.step(f.points, int(1.15e9), f.pose)
    runner.reset('input settings', tracks=False)
    assert len(tracks) > 0
    runner.step(f.points, int(1.17e9), None)
    assert len(tracks) == 0 and runner.last_reset_reason == 'no pose'
    runner.step(f.points, int(1.18e9), f.pose)
    assert len(tracks) > 0
    runner.reset('test')
    assert len(tracks) == 0
    r3 = runner.step(f.points, int(1.2e9), None)  # no pose: no odometry frame to track in
    assert len(r3.detections) and not r3.track_ids.any()
    runner.set_tracker(None)
    r4 = runner.step(f.points, int(1.3e9), f.pose)
    assert runner.tracks is None and not r4.track_ids.any()


def test_a_sweep_added_without_a_step_feeds_the_next_input_only():
    """add_sweep (a cloud the node skipped) changes the next input's sweeps and nothing else:
    the memory, the tracks and the detections of the stream are the model's alone."""
    from dataclasses import replace

    import numpy as np

    from suit_ros.evaluate import run_model
    from suit_ros.tracking import TrackerConfig
    torch.manual_seed(0)
    model = SUITDetector(replace(small_config('suit'), sweeps=3))
    runner = StreamingDetector(model, tracker=TrackerConfig(birth_score=0.0))
    frames = [frame(t) for t in range(5)]
    runner.step(frames[0].points, frames[0].stamp_ns, frames[0].pose)
    memory, tracks = runner.memory, runner.tracks
    assert tracks is not None
    n_tracks = len(tracks)
    runner.add_sweep(frames[1].points, frames[1].stamp_ns, frames[1].pose)
    assert runner.memory is memory and runner.tracks is tracks and len(tracks) == n_tracks
    runner.add_sweep(frames[2].points, frames[2].stamp_ns, None)     # no pose: not buffered
    assert len(runner.sweeps) == 2
    r = runner.step(frames[3].points, frames[3].stamp_ns, frames[3].pose)
    assert runner.sweeps.last_lags_s == pytest.approx((0.0, 0.2, 0.3))
    assert r.used_memory and r.model_points == 3 * len(frames[3].points)
    with pytest.raises(ValueError, match='points must be'):
        runner.add_sweep(np.zeros((3, 2), np.float32), frames[4].stamp_ns, frames[4].pose)
    # evaluation runs a node too slow for its sensor the same way
    seqs = [frames]
    every = run_model(model, seqs, run_every=2)
    assert [g.boxes[0, 0] for g in every.gt] == [frames[t].gt.boxes[0, 0] for t in (0, 2, 4)]
    dropped = run_model(model, seqs, run_every=2, buffer_skipped=False)
    assert len(dropped.det) == 3
    assert not np.array_equal(every.det[1].scores, dropped.det[1].scores)
    # a memory older than max_gap_s is dropped, as the node's pipeline does (sweeps kept)
    assert every.used_memory == [False, True, True]
    stale = run_model(model, seqs, run_every=2, max_gap_s=0.15)
    assert stale.used_memory == [False, False, False]
    assert run_model(model, seqs, max_gap_s=0.05).used_memory[1:] == [True] * 4  # run_every 1


def test_streaming_candidates_and_literal_modes():
    from suit_ros.config import model_config_from_dict
    from suit_ros.errors import ConfigError
    runner = StreamingDetector(SUITDetector(small_config('none')), candidates=7)
    assert runner.candidates == 7
    runner.set_thresholds(candidates=None)
    assert runner.candidates == runner.cfg.head.top_k == 500
    with pytest.raises(ValueError, match='candidates'):
        runner.set_thresholds(candidates=0)
    with pytest.raises(ConfigError, match='head.nms must be one of'):
        model_config_from_dict({'head': {'nms': 'iou'}})
    assert model_config_from_dict({'sweeps': 3}).sweeps == 3
    with pytest.raises(ConfigError, match='sweeps'):
        model_config_from_dict({'sweeps': 0})



def test_carried_boxes_are_published_at_the_carry_thresholds():
    """With a carry branch, the boxes decoded where the cloud has no returns are marked
    ``carried`` and cut at the carry thresholds, the others at the score thresholds."""
    import numpy as np
    model = carry_branch_model()
    with torch.no_grad():
        model.carry.head.heatmap[-1].bias.add_(3.0)     # carried boxes among the candidates
    K = len(model.cfg.class_names)

    def run(thresholds, carry):
        runner = StreamingDetector(model)
        runner.set_thresholds(thresholds, max_detections=40, candidates=80,
                              carry_thresholds=carry)
        out = []
        for t in range(4):
            f = frame(t)
            pts = f.points if t < 2 else f.points[f.points[:, 0] < 0]      # x > 0 lost
            res = runner.step(pts, f.stamp_ns, f.pose)
            assert res.carried.shape == (len(res.detections),)
            out.append(res)
        return out

    only_seen = run([0.0] * K, [1.01] * K)
    assert not any(r.carried.any() for r in only_seen)
    assert sum(len(r.detections) for r in only_seen) > 0
    assert not any(r.held.any() for r in only_seen)
    only_carried = run([1.01] * K, [0.0] * K)
    assert all(r.carried.all() for r in only_carried)
    assert all((r.held == 1).all() for r in only_carried)          # carried, not coasted
    assert sum(len(r.detections) for r in only_carried[2:]) > 0
    assert not any(len(r.detections) for r in only_carried[:1])     # no memory yet
    assert np.all([r.used_memory for r in only_carried[1:]])


@pytest.mark.parametrize('temporal', ['suit', 'sparse_velocity', 'sparse', 'suit carrying'])
def test_a_memory_with_no_sample_fuses_nothing(temporal):
    """A scene where no cell scores alpha or more leaves the sparse memory empty (the shipped
    SUIT model keeps cells scoring 0.2 or more: an empty road); the next step fuses nothing
    and gives what a step with the memory dropped gives (this crashed GeoNet's reshape); with
    a carry branch the step runs."""
    from dataclasses import replace
    torch.manual_seed(0)
    cfg = small_config(temporal.split()[0])
    carry = {'fusion_gate': 'carry_branch', 'sampling': replace(cfg.sampling, carry_s=0.35)}
    cfg = replace(cfg, **carry) if temporal.endswith('carrying') else cfg
    model = SUITDetector(replace(cfg, sampling=replace(cfg.sampling, alpha=0.999))).eval()
    K = len(model.cfg.class_names)
    empty = StreamingDetector(model, score_thresholds=[0.0] * K)
    dropped = StreamingDetector(model, score_thresholds=[0.0] * K)
    for t in range(3):
        f = frame(t)
        dropped.reset('memory dropped', sweeps=False)
        a = empty.step(f.points, f.stamp_ns, f.pose)
        b = dropped.step(f.points, f.stamp_ns, f.pose)
        assert len(a.detections) > 0
        if temporal.endswith('carrying'):
            # the carry decoding (boxes where the cloud has no returns cut apart) still
            # applies with nothing carried, so only the step itself is checked
            continue
        assert torch.equal(torch.from_numpy(a.detections.boxes),
                           torch.from_numpy(b.detections.boxes)), t
    assert empty.memory is not None and len(empty.memory.batch_index) == 0


def test_the_past_term_goes_beside_only_where_torch_leaves_a_core(monkeypatch):
    """By default the second thread is used where torch's threads leave the process a core
    (the node's one thread on two cores), not where the encoder's threads take every core;
    an explicit choice stands either way."""
    import suit_ros.model.streaming as streaming
    model = SUITDetector(small_config())
    auto = StreamingDetector(model)
    threads = torch.get_num_threads()
    monkeypatch.setattr(streaming, '_usable_cores', lambda: 2)
    try:
        torch.set_num_threads(1)
        assert auto.uses_beside()
        torch.set_num_threads(2)
        assert not auto.uses_beside()
        assert StreamingDetector(model, beside=True).uses_beside()
        torch.set_num_threads(1)
        assert not StreamingDetector(model, beside=False).uses_beside()
    finally:
        torch.set_num_threads(threads)


def test_the_past_term_beside_the_encoder_gives_the_same_steps():
    """The past term computed in a second thread while the encoder runs (``beside``) gives
    the serial step's boxes, scores, memory and carried flags bit for bit, frame by frame (a
    carry branch, a lost half of the sweep, a frame without a pose); an error there reaches
    the caller, and the next step runs."""
    import numpy as np
    model = carry_branch_model()
    with torch.no_grad():
        model.fusion.past.weight.normal_(0, 0.2)
    threads = torch.get_num_threads()
    serial = StreamingDetector(model, beside=False)
    beside = StreamingDetector(model, beside=True)
    assert not serial.beside and beside.beside
    for t in range(6):
        f = frame(t)
        pts = f.points if t not in (3, 4) else f.points[f.points[:, 0] < 0]
        pose = None if t == 5 else f.pose
        a, b = serial.step(pts, f.stamp_ns, pose), beside.step(pts, f.stamp_ns, pose)
        assert np.array_equal(a.detections.boxes, b.detections.boxes)
        assert np.array_equal(a.detections.scores, b.detections.scores)
        assert np.array_equal(a.carried, b.carried)
        assert a.used_memory == b.used_memory and a.memory_bytes == b.memory_bytes
        assert (a.used_memory, t) != (False, 2)            # the memory was fused
    assert beside._worker is not None                    # the second thread ran
    # its small work on one torch thread; the step's own thread keeps its count
    assert beside._worker.submit(torch.get_num_threads).result() == 1
    assert torch.get_num_threads() == threads
    # stepped from another thread (the node's model thread after a warm-up in its main
    # one), the second thread is started again by the thread that steps
    import threading
    first = beside._worker
    stepper = threading.Thread(target=lambda: [beside.step(frame(t).points, frame(t).stamp_ns,
                                                           frame(t).pose) for t in (6, 7)])
    stepper.start()
    stepper.join()
    assert beside._worker is not first and beside._worker_owner == stepper.ident
    beside.close()
    assert beside._worker is None

    def broken(*args):
        raise RuntimeError('past term failed')
    beside.model.past_term = broken
    with pytest.raises(RuntimeError, match='past term failed'):
        beside.step(frame(8).points, frame(8).stamp_ns, frame(8).pose)
    del beside.model.past_term
    # the memory of frame 7 is still there, and fused again (the second thread started anew)
    assert beside.step(frame(9).points, frame(9).stamp_ns, frame(9).pose).used_memory


def test_training_reads_the_carry_head_where_inference_does():
    """A carry branch's head answers, in training as in inference, at the cells without returns
    within two cells of the carry term, and the model's own head everywhere else: training
    optimises the path the node runs (it took the carry head at every unobserved cell)."""
    from dataclasses import replace

    from suit_ros.model.detector import carry_cells, frame_points
    model = carry_branch_model()
    with torch.no_grad():                           # the two heads differ, as after training
        for p in model.carry.head.parameters():
            p.add_(torch.randn_like(p) * 0.2)
    memory, checked = None, 0
    with torch.no_grad():
        for t in range(4):
            f = frame(t)
            pts = f.points if t < 2 else f.points[f.points[:, 0] < 0]      # x > 0 lost
            f = replace(f, points=pts)
            cur, obs = model.encode_observed([frame_points(f, torch.device('cpu'))])
            past, aux = model.past_term(memory, f.pose[None], [f.stamp_ns])
            fused = model.fuse(cur, past, obs)
            infer = model.predict(cur, past, fused, obs)
            if past is not None:
                model.training = True               # the flag alone: batch norms stay as they are
                try:
                    train = model.predict(cur, past, fused, obs)
                finally:
                    model.training = False
                for k in ('heatmap', 'reg', 'height', 'dim', 'rot', 'vel'):
                    if k in infer:
                        torch.testing.assert_close(train[k], infer[k], atol=1e-5, rtol=1e-5)
                use = carry_cells(past.carry_gated, obs)
                own = infer['own.heatmap']
                assert use.any() and not torch.equal(infer['heatmap'][use.expand_as(own)],
                                                     own[use.expand_as(own)])
                assert torch.equal(infer['heatmap'][~use.expand_as(own)],
                                   own[~use.expand_as(own)])
                checked += 1
            memory = model.sample_memory(fused, infer, f.pose[None], [f.stamp_ns],
                                         model.carried(memory, aux, f.pose[None],
                                                       [f.stamp_ns]), obs)
    assert checked >= 2
