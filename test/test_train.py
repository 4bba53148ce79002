"""Training: augmentation consistency, a tiny real run with resume, and gloo DDP gradients."""
from __future__ import annotations

from dataclasses import replace
import os
from pathlib import Path
import socket
import time

import numpy as np
import pytest
import torch

from suit_ros.data.augment import Augmentation, apply_clip
from suit_ros.ops.geometry import ego_transform, pose_from_xyz_rpy, se3_inverse, transform_boxes
from suit_ros.structures import Detections, Frame
from suit_ros.train import TrainConfig, load_train_config

REPO = Path(__file__).resolve().parents[1]


def two_frames():
    world = np.array([[12.0, 5.0, 0.8, 4.5, 1.9, 1.6, 0.3]])
    vel_w = np.array([[3.0, -1.0]])
    frames = []
    for k, pose in enumerate([pose_from_xyz_rpy((0, 0, 1.8), (0, 0, 0.1)),
                              pose_from_xyz_rpy((1.2, 0.2, 1.8), (0, 0, 0.14))]):
        b, v = transform_boxes(se3_inverse(pose), world, vel_w)
        pts = np.c_[b[:, :3], [[0.5, 0.0]]].astype(np.float32)
        frames.append(Frame(pts, pose, k, 'lidar', Detections(b, v, np.ones(1), [0])))
    return frames


@pytest.mark.parametrize('aug', [Augmentation(False, 0.3, 1.0), Augmentation(True, -0.5, 1.04),
                                 Augmentation(True, 0.0, 0.95),
                                 Augmentation(False, 0.2, 1.0, tilt=(0.03, -0.04), lift=0.25)])
def test_augmentation_keeps_static_objects_consistent(aug):
    f0, f1 = apply_clip(two_frames(), aug)
    moved, _ = transform_boxes(ego_transform(f1.pose, f0.pose), f0.gt.boxes)
    np.testing.assert_allclose(moved[:, :6], f1.gt.boxes[:, :6], atol=1e-4)
    assert np.cos(moved[0, 6] - f1.gt.boxes[0, 6]) == pytest.approx(1.0, abs=1e-6)
    # points move with the boxes; velocities rotate (and flip) and scale with the scene
    np.testing.assert_allclose(f0.points[:, :3], f0.gt.boxes[:, :3], atol=1e-4)
    raw = two_frames()[0]
    R = aug.matrix[:2, :2] * aug.scale
    np.testing.assert_allclose(f0.gt.velocities, raw.gt.velocities @ R.T, atol=1e-5)
    # ignore boxes (a real dataset's parked bicycles) go with the GT, as the same box would
    frames = [replace(f, ignore_boxes=f.gt.boxes.astype(np.float32)) for f in two_frames()]
    for f in apply_clip(frames, aug):
        np.testing.assert_allclose(f.ignore_boxes, f.gt.boxes, atol=1e-4)


def test_a_mirrored_drive_is_a_left_hand_drive_of_the_same_objects():
    """``mirror_world`` (compare's ``mirrored``): the odometry frame mirrored too, so every pose
    stays a rotation, static objects still map through the poses, a box's heading and velocity
    mirror with it, the points stay in their boxes, and twice gives the frame back."""
    from suit_ros.data.augment import mirror_world
    from suit_ros.ops.geometry import yaw_of
    raw = two_frames()
    f0, f1 = (mirror_world(f) for f in raw)
    for f, r in ((f0, raw[0]), (f1, raw[1])):
        assert np.linalg.det(f.pose[:3, :3]) == pytest.approx(1.0)
        assert yaw_of(f.pose) == pytest.approx(-yaw_of(r.pose))
        assert f.pose[1, 3] == pytest.approx(-r.pose[1, 3])
        np.testing.assert_allclose(f.points[:, :3], f.gt.boxes[:, :3], atol=1e-4)
        back = mirror_world(f)
        np.testing.assert_array_equal(back.points, r.points)
        np.testing.assert_allclose(back.pose, r.pose)
        np.testing.assert_allclose(back.gt.boxes, r.gt.boxes)
        np.testing.assert_allclose(back.gt.velocities, r.gt.velocities)
    moved, vel = transform_boxes(ego_transform(f1.pose, f0.pose), f0.gt.boxes,
                                 f0.gt.velocities)
    np.testing.assert_allclose(moved[:, :6], f1.gt.boxes[:, :6], atol=1e-4)
    assert np.cos(moved[0, 6] - f1.gt.boxes[0, 6]) == pytest.approx(1.0, abs=1e-6)
    np.testing.assert_allclose(vel, f1.gt.velocities, atol=1e-6)
    # in the odometry frame: the world's velocity (3, -1) and heading 0.3 mirrored
    world_yaw = f0.gt.boxes[0, 6] + yaw_of(f0.pose)
    assert np.cos(world_yaw + 0.3) == pytest.approx(1.0, abs=1e-6)
    np.testing.assert_allclose(f0.pose[:2, :2] @ f0.gt.velocities[0], [3.0, 1.0], atol=1e-6)
    # a mounting off the centre line and turned, and ignore boxes: the model's input (sweeps
    # accumulated in base_link) of the mirrored drive is the mirrored input of the drive
    from suit_ros.model.sweeps import model_frame
    mount = pose_from_xyz_rpy((1.1, 0.4, 1.6), (0.0, 0.02, 0.15))
    raw = [replace(f, T_base_lidar=mount, ignore_boxes=f.gt.boxes.astype(np.float32) + 0.5)
           for f in two_frames()]
    ours = model_frame([mirror_world(f) for f in raw], 1, 2)
    theirs = mirror_world(model_frame(raw, 1, 2))
    assert len(ours.points) == 2
    np.testing.assert_allclose(ours.points, theirs.points, atol=1e-5)
    np.testing.assert_allclose(ours.pose, theirs.pose, atol=1e-9)
    np.testing.assert_allclose(ours.gt.boxes, theirs.gt.boxes, atol=1e-6)
    np.testing.assert_allclose(ours.gt.velocities, theirs.gt.velocities, atol=1e-6)
    np.testing.assert_allclose(ours.ignore_boxes, theirs.ignore_boxes, atol=1e-5)


def test_tilt_lift_and_dropout_draws():
    from suit_ros.data.augment import apply, draw
    rng = np.random.default_rng(0)
    plain = [draw(np.random.default_rng(1)) for _ in range(3)]
    assert all(a.tilt == (0.0, 0.0) and a.lift == 0.0 and a.point_dropout == 0.0 for a in plain)
    augs = [draw(rng, tilt_deg=1.5, lift_m=0.3, point_dropout=0.3) for _ in range(400)]
    tilts = np.array([a.tilt for a in augs])
    assert 0.015 < np.std(tilts) < 0.035 and np.abs(tilts).max() <= np.deg2rad(3.75) + 1e-9
    assert max(abs(a.lift) for a in augs) <= 0.3
    assert 0.35 < np.mean([a.point_dropout > 0 for a in augs]) < 0.65
    # the ground plane (z = 0) is tilted and lifted: its height at 40 m ahead follows the pitch
    ground = Frame(np.array([[40.0, 0, 0, 0.5, 0], [0, 0, 0, 0.5, 0]], np.float32), np.eye(4),
                   0)
    out = apply(ground, Augmentation(False, 0.0, 1.0, tilt=(0.0, 0.02), lift=0.1))
    assert out.points[0, 2] == pytest.approx(-40 * np.sin(0.02) + 0.1, abs=1e-4)
    assert out.points[1, 2] == pytest.approx(0.1, abs=1e-6)
    many = Frame(np.random.default_rng(2).uniform(-30, 30, (10000, 5)).astype(np.float32),
                 np.eye(4), 0)
    kept = len(apply(many, Augmentation(False, 0.0, 1.0, point_dropout=0.3)).points)
    assert 6500 < kept < 7500


def test_train_config_strict(tmp_path):
    from suit_ros.errors import ConfigError
    (tmp_path / 'bad.yaml').write_text('stepz: 3\n')
    with pytest.raises(ConfigError, match='stepz'):
        load_train_config(tmp_path / 'bad.yaml')
    assert load_train_config(REPO / 'params/train_single.yaml').temporal == 'none'
    street = load_train_config(REPO / 'docs/experiments/street/configs/train_suit_street.yaml')
    assert (street.preset, street.tilt_deg, street.point_dropout) == ('train-street', 1.5, 0.3)
    (tmp_path / 'neg.yaml').write_text('train_first_sequence: -1\n')
    with pytest.raises(ConfigError, match='train_first_sequence'):
        load_train_config(tmp_path / 'neg.yaml')
    (tmp_path / 'ovh.yaml').write_text('overhead_probability: 1.5\n')
    with pytest.raises(ConfigError, match='overhead_probability'):
        load_train_config(tmp_path / 'ovh.yaml')
    (tmp_path / 'ground.yaml').write_text('ground: flat\n')
    with pytest.raises(ConfigError, match='ground'):
        load_train_config(tmp_path / 'ground.yaml')
    assert load_train_config(
        REPO / 'docs/experiments/ground/configs/train_suit_ground14.yaml').ground == 'local'
    mix = load_train_config(REPO / 'params/train_suit_street_mix.yaml')
    assert (mix.preset, mix.more_presets) == ('train-ends-all', ('train-street-ends',))
    (tmp_path / 'world.yaml').write_text('more_presets: [train-streets]\n')
    with pytest.raises(ConfigError, match=r'unknown synthetic world.*train-streets'):
        load_train_config(tmp_path / 'world.yaml')
    (tmp_path / 'mixbag.yaml').write_text('dataset: bags\nmore_presets: [train-real]\n')
    with pytest.raises(ConfigError, match='more_presets are synthetic'):
        load_train_config(tmp_path / 'mixbag.yaml')
    # values that crashed a run after its first step (a modulo by zero, an empty batch)
    for text, match in (('checkpoint_every: 0\n', 'checkpoint_every must be at least 1'),
                        ('batch_size: 0\n', 'batch_size must be at least 1'),
                        ('clip_lengths: []\n', 'clip_lengths must list one or more')):
        (tmp_path / 'zero.yaml').write_text(text)
        with pytest.raises(ConfigError, match=match):
            load_train_config(tmp_path / 'zero.yaml')


def test_more_presets_add_the_same_drives_in_another_world(tmp_path):
    """``more_presets``: the training set holds the config's drives once per world, the
    extra world's drives after the first's, each the drive its world would give alone."""
    from suit_ros.data.sim.config import PRESETS
    from suit_ros.train import TrainConfig, training_sequences
    assert 'train-street-ends' in PRESETS
    tc = TrainConfig(preset='train-ends-all', more_presets=('train-street-ends',),
                     train_sequences=1, train_frames=2, train_first_sequence=0,
                     cache_dir=str(tmp_path))
    data = training_sequences(tc, ('car', 'truck', 'pedestrian', 'cyclist'))
    assert len(data) == 2
    plain, street = data
    assert len(plain) == len(street) == 2
    # the same drive (ego path, actors) in two worlds: the poses agree, the returns do not
    np.testing.assert_allclose(plain[1].pose, street[1].pose)
    assert len(plain[1].points) != len(street[1].points)


def test_training_clips_are_leveled_when_the_config_asks():
    """``ground: local``: a clip on a road 0.5 m below base_link's ground reaches the model
    leveled, its GT lowered with it; without a ground (as_given) the clip is untouched."""
    from suit_ros.ground import LocalGround
    from suit_ros.structures import Detections
    from suit_ros.train import _augmented
    rng = np.random.default_rng(0)
    clip = []
    for t in range(2):
        xy = rng.uniform(-40, 40, (20000, 2))
        pts = np.c_[xy, rng.normal(-0.5, 0.02, 20000), np.full(20000, 0.3),
                    np.zeros(20000)].astype(np.float32)
        gt = Detections(np.array([[10.0 + t, 2.0, 0.3, 4.5, 1.9, 1.6, 0.0]]),
                        np.array([[10.0, 0.0]]), np.ones(1), np.zeros(1, np.int64))
        clip.append(Frame(pts, np.eye(4), t, 'base_link', gt))
    tc = TrainConfig(augment=False, ground='local')
    assert _augmented([clip], tc, rng)[0] is clip
    out = _augmented([clip], tc, rng, LocalGround((-51.2, -51.2, -3.0, 51.2, 51.2, 3.0)))[0]
    for o, c in zip(out, clip):
        assert abs(float(np.median(o.points[:, 2]))) < 0.05
        assert o.gt is not None and o.gt.boxes[0, 2] == pytest.approx(0.8, abs=0.06)
        assert c.gt is not None and c.gt.boxes[0, 2] == pytest.approx(0.3)


def test_fresh_window_of_training_drives_follows_the_first_ones():
    from suit_ros.data.sequences import split_drives
    first, fresh = split_drives('train', 288), split_drives('train', 288, first=288)
    assert split_drives('train', 576) == first + fresh       # seeds and sensor cycle continue
    assert not {s for s, _ in fresh} & {s for s, _ in first}
    held = {s for split in ('val', 'heldout') for s, _ in split_drives(split, 16)}
    assert not {s for s, _ in fresh} & held
    assert load_train_config(REPO / 'params/train_suit_fresh.yaml').train_first_sequence == 288
    with pytest.raises(ValueError, match='first'):
        split_drives('train', 2, first=-1)


def _small_world(seqs):
    """``synthetic_sequence`` on the small test world (whatever preset a config names)."""
    orig = seqs.synthetic_sequence
    return (lambda name, seed, frames, cache_dir=None, sensor='sim32',
            points_dtype=np.float32, rate_hz=None:
            orig('test', seed, frames, cache_dir, points_dtype=points_dtype, rate_hz=rate_hz))


def tiny(tmp_path, **kw) -> TrainConfig:
    return replace(TrainConfig(model_config=str(REPO / 'params/model_cpu.yaml'),
                               train_sequences=1, train_frames=4, val_sequences=1,
                               val_frames=3, cache_dir=str(tmp_path / 'cache'), steps=4,
                               checkpoint_every=2, batch_size=1, clip_lengths=(2,)), **kw)


@pytest.mark.slow
def test_tiny_training_run_writes_loadable_checkpoint_and_resumes(tmp_path, monkeypatch):
    from suit_ros.checkpoint import load_checkpoint
    import suit_ros.data.sequences as seqs
    from suit_ros.train import train
    monkeypatch.setattr(seqs, 'synthetic_sequence', _small_world(seqs))
    # an interrupted run (time budget) ...
    metrics = train(tiny(tmp_path, temporal='suit', max_minutes=1e-6), tmp_path / 'run')
    assert metrics['steps'] == 1 and 'mAP' in metrics
    model, cfg, meta = load_checkpoint(tmp_path / 'run' / 'model.safetensors')
    assert cfg.temporal == 'suit' and meta['metrics']['steps'] == 1
    state = torch.load(tmp_path / 'run' / 'last.pt', weights_only=True)
    assert state['step'] == 1 and state['train_config']['max_minutes'] == 1e-6
    from suit_ros.errors import ConfigError
    # a new run into it would overwrite its snapshot: refused; so is a resume that changes
    # more than the budget
    with pytest.raises(ConfigError, match='holds a training run'):
        train(tiny(tmp_path, temporal='suit'), tmp_path / 'run')
    with pytest.raises(ConfigError, match=r'other settings: lr 0.002 -> 0.01\. A resumed'):
        train(tiny(tmp_path, temporal='suit', lr=0.01), tmp_path / 'run', resume=True)
    # rows logged after the last snapshot (a kill), one cut short: dropped on resume
    with open(tmp_path / 'run' / 'log.csv', 'a', encoding='utf-8') as f:
        f.write('2,0.5,0.001,1.0,1.0,1.0,0.0,0.0\n3,0.7,0.0')
    # ... resumes where it stopped
    metrics = train(tiny(tmp_path, temporal='suit', steps=4), tmp_path / 'run', resume=True)
    assert metrics['steps'] == 4
    rows = (tmp_path / 'run' / 'log.csv').read_text().strip().splitlines()
    assert rows[0].startswith('step') and [r.split(',')[0] for r in rows[1:]] == \
        ['1', '2', '3', '4']
    # resumed again (a recipe resumed as a whole): finished, its model left as it is
    written = (tmp_path / 'run' / 'model.safetensors').stat().st_mtime_ns
    again = train(tiny(tmp_path, temporal='suit', steps=4), tmp_path / 'run', resume=True)
    assert again['steps'] == 4
    assert (tmp_path / 'run' / 'model.safetensors').stat().st_mtime_ns == written
    # a last.pt cut short (killed while saving, before saves were atomic) is named
    data = (tmp_path / 'run' / 'last.pt').read_bytes()
    (tmp_path / 'run' / 'last.pt').write_bytes(data[:len(data) // 3])
    with pytest.raises(ConfigError, match='cannot resume from'):
        train(tiny(tmp_path, temporal='suit', steps=8), tmp_path / 'run', resume=True)
    # a last.pt torch reads without pickle but that is no run's state: named, nothing loaded
    for foreign, match in (([1, 2, 3], 'it holds a list'),
                           ({'model': {}, 'step': 1}, 'it holds no optimizer, torch_rng')):
        torch.save(foreign, tmp_path / 'run' / 'last.pt')
        with pytest.raises(ConfigError, match=match):
            train(tiny(tmp_path, temporal='suit', steps=8), tmp_path / 'run', resume=True)
    # a trained model without last.pt (a copied or cleaned run): a new run there, resumed or
    # not, would overwrite it
    (tmp_path / 'run' / 'last.pt').unlink()
    for resume in (False, True):
        with pytest.raises(ConfigError, match=r'holds a trained model \(model.safetensors'):
            train(tiny(tmp_path, temporal='suit'), tmp_path / 'run', resume=resume)
    assert (tmp_path / 'run' / 'model.safetensors').stat().st_mtime_ns == written
    # a model of another class set on the synthetic world (its labels index these four)
    two = tmp_path / 'two.yaml'
    import yaml

    from suit_ros.config import load_model_config
    cfg = load_model_config(REPO / 'params/model_cpu.yaml').to_dict()
    cfg['class_names'] = ['car', 'pedestrian']
    cfg['head']['circle_nms_radius'] = cfg['head']['circle_nms_radius'][:2]
    cfg['head']['carry_nms_radius'] = cfg['head']['carry_nms_radius'][:2]
    two.write_text(yaml.safe_dump({'model': cfg}))
    with pytest.raises(ConfigError, match=r"but the synthetic world labels \['car', 'truck'"):
        train(tiny(tmp_path, temporal='suit', model_config=str(two)), tmp_path / 'run2')


@pytest.mark.slow
def test_a_resumed_run_trains_what_the_run_would_have(tmp_path, monkeypatch):
    """Killed after its snapshot at step 2 and resumed, a run draws the clips and the
    augmentation it would have drawn, and ends with the same weights as one run through
    (it drew afresh from the step before)."""
    from safetensors.torch import load_file

    import suit_ros.data.sequences as seqs
    import suit_ros.train as train_mod
    monkeypatch.setattr(seqs, 'synthetic_sequence', _small_world(seqs))
    torch.set_num_threads(1)               # one thread: the same sums in the same order
    cfg = tiny(tmp_path, temporal='suit', eval_at_end=False, train_frames=8,
               clip_lengths=(2, 3))
    train_mod.train(cfg, tmp_path / 'whole')
    optimise, calls = train_mod._optimise, []

    def killed_at_step_3(*args, **kw):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return optimise(*args, **kw)
    monkeypatch.setattr(train_mod, '_optimise', killed_at_step_3)
    with pytest.raises(KeyboardInterrupt):
        train_mod.train(cfg, tmp_path / 'cut')
    monkeypatch.setattr(train_mod, '_optimise', optimise)
    assert torch.load(tmp_path / 'cut' / 'last.pt', weights_only=True)['step'] == 2
    train_mod.train(cfg, tmp_path / 'cut', resume=True)
    whole = load_file(tmp_path / 'whole' / 'model.safetensors')
    cut = load_file(tmp_path / 'cut' / 'model.safetensors')
    assert whole.keys() == cut.keys()
    assert all(torch.equal(whole[k], cut[k]) for k in whole)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


def _ddp_worker(rank, world, port, out):
    import torch.distributed as dist
    from torch.nn.parallel import DistributedDataParallel

    from suit_ros.config import BackboneConfig, ModelConfig, PillarConfig
    from suit_ros.model.detector import SUITDetector
    os.environ.update(MASTER_ADDR='127.0.0.1', MASTER_PORT=str(port))
    dist.init_process_group('gloo', rank=rank, world_size=world)
    torch.manual_seed(0)
    torch.set_num_threads(1)
    cfg = ModelConfig(pillars=PillarConfig(point_range=(-25.6, -25.6, -3, 25.6, 25.6, 3),
                                           channels=8),
                      backbone=BackboneConfig(num_filters=(8, 8, 8),
                                              num_upsample_filters=(8, 8, 8)))
    model = DistributedDataParallel(SUITDetector(cfg), find_unused_parameters=True)
    frames = two_frames()
    rng = np.random.default_rng(rank)                 # each rank sees different data
    for f in frames:
        f.points = np.c_[rng.uniform(-20, 20, (500, 2)), rng.uniform(-2, 0, (500, 1)),
                         rng.uniform(0, 1, (500, 1)), np.zeros((500, 1))].astype(np.float32)
    loss = model([frames])['loss']
    loss.backward()
    grads = torch.cat([p.grad.flatten() for p in model.parameters() if p.grad is not None])
    torch.save({'grads': grads, 'loss': loss.detach()}, out / f'rank{rank}.pt')
    dist.barrier()                  # as train() does: no rank tears down while its peer talks
    dist.destroy_process_group()


@pytest.mark.slow
def test_distributed_gradients_agree_across_ranks(tmp_path):
    import torch.multiprocessing as mp
    mp.spawn(_ddp_worker, args=(2, _free_port(), tmp_path), nprocs=2, join=True)
    r0 = torch.load(tmp_path / 'rank0.pt', weights_only=True)
    r1 = torch.load(tmp_path / 'rank1.pt', weights_only=True)
    assert not torch.equal(r0['loss'], r1['loss'])           # different data per rank
    torch.testing.assert_close(r0['grads'], r1['grads'])     # all-reduced gradients agree


def _budget_worker(rank, world, port, tmp_path, cfg):
    import time

    import suit_ros.data.sequences as seqs
    import suit_ros.train as train_mod
    os.environ.update(MASTER_ADDR='127.0.0.1', MASTER_PORT=str(port), RANK=str(rank),
                      WORLD_SIZE=str(world))
    seqs.synthetic_sequence = _small_world(seqs)
    if rank == 1:                          # this rank's clock runs at half speed
        real = time.monotonic
        time.monotonic = lambda: real() * 0.5
    metrics = train_mod.train(cfg, tmp_path / 'run', device='cpu', threads=1)
    (tmp_path / f'rank{rank}.json').write_text(str(metrics['steps']))


@pytest.mark.slow
def test_distributed_ranks_agree_when_the_time_budget_ends(tmp_path, monkeypatch):
    """With ``max_minutes`` each rank used to read its own clock: the first to reach the budget
    stopped while the others began another step and waited in its gradient exchange for good
    (and each set its own learning rate). The ranks now take the furthest progress of all:
    they stop after the same step."""
    import torch.multiprocessing as mp

    import suit_ros.data.sequences as seqs
    from suit_ros.train import training_sequences
    monkeypatch.setattr(seqs, 'synthetic_sequence', _small_world(seqs))
    cfg = tiny(tmp_path, temporal='suit', steps=10_000, max_minutes=0.05, eval_at_end=False,
               checkpoint_every=10_000)
    from suit_ros.config import load_model_config
    training_sequences(cfg, load_model_config(cfg.model_config).class_names)  # cache once
    ctx = mp.spawn(_budget_worker, args=(2, _free_port(), tmp_path, cfg), nprocs=2,
                   join=False)
    deadline = time.monotonic() + 240
    while not ctx.join(timeout=5):
        if time.monotonic() > deadline:
            for p in ctx.processes:
                p.kill()
            pytest.fail('the ranks did not finish: one waits for the other')
    steps = [int((tmp_path / f'rank{r}.json').read_text()) for r in range(2)]
    assert steps[0] == steps[1] >= 1          # (a loaded machine may make one step in 3 s)


@pytest.mark.slow
def test_one_cycle_matches_torch_and_ends_annealed():
    import torch

    from suit_ros.train import one_cycle
    opt = torch.optim.AdamW([torch.nn.Parameter(torch.zeros(1))], lr=1e-3, betas=(0.95, 0.99))
    sched = torch.optim.lr_scheduler.OneCycleLR(
        opt, max_lr=1e-3, total_steps=101, pct_start=0.3, base_momentum=0.85,
        max_momentum=0.95, div_factor=10.0, final_div_factor=100.0)
    for k in range(101):
        lr, beta1 = one_cycle(k / 100, 1e-3)
        # torch puts the peak at step round(0.3 * 101) - 1; ours at progress 0.3 exactly
        assert lr == pytest.approx(sched.get_last_lr()[0], rel=0.08, abs=2e-5)
        assert beta1 == pytest.approx(opt.param_groups[0]['betas'][0], abs=0.01)
        opt.step()
        sched.step()
    assert one_cycle(1.0, 1e-3) == pytest.approx((1e-6, 0.95))
    assert one_cycle(0.0, 1e-3) == pytest.approx((1e-4, 0.95))
    assert one_cycle(0.3, 1e-3)[0] == pytest.approx(1e-3)


def test_frozen_base_and_distillation_train_only_the_temporal_part():
    """With pillars and backbone frozen no gradient reaches them and the encoder builds no
    graph; the distillation term is zero for a student equal to its teacher on frames without
    a memory, positive once the student's head moves, and skipped on outage frames."""
    from suit_ros.config import load_model_config
    from suit_ros.model.detector import SUITDetector
    from suit_ros.model.distill import Distiller
    from suit_ros.train import freeze
    torch.manual_seed(0)
    cfg = replace(load_model_config(REPO / 'params/model_cpu.yaml'), temporal='suit')
    model = SUITDetector(cfg)
    assert freeze(SUITDetector(cfg), ('fusion.current',))[0].weight.requires_grad is False
    frozen = freeze(model, ('pillars', 'backbone'))
    assert frozen == [model.pillars, model.backbone]
    distiller = Distiller(model.head, model.fusion.current, 1.0)
    model.eval()                   # as with frozen_batchnorm: the head's statistics stay
    noise = np.random.default_rng(0).normal(0, 0.3, (50, 5)) * [1, 1, 1, 0, 0]
    frames = [replace(f, points=(np.tile(f.points, (50, 1)) + noise).astype(np.float32))
              for f in two_frames()]
    points = [torch.from_numpy(frames[0].points)]
    assert not model.encode(points).requires_grad
    current = model.encode(points)
    preds = model.head(model.fusion(current, None))
    zero = distiller.loss(current, preds, torch.tensor([True]))
    assert float(zero.detach()) == pytest.approx(0.0, abs=1e-10)
    with torch.no_grad():
        model.head.heatmap[-1].bias.add_(1.0)
    preds = model.head(model.fusion(current, None))
    moved = distiller.loss(current, preds, torch.tensor([True]))
    assert float(moved.detach()) > 1e-4 and moved.requires_grad
    assert float(distiller.loss(current, preds, torch.tensor([False]))) == 0.0
    losses = model.forward_sequence([frames], [[False, True]], distiller)
    losses['loss'].backward()
    assert all(p.grad is None for m in frozen for p in m.parameters())
    assert any(p.grad is not None for p in model.head.parameters())
    assert float(losses['distill_loss']) > 0


def test_a_resume_compares_the_settings_both_runs_have():
    """A setting a later release adds is no difference (a run saved before it resumes); a
    changed one is named, dotted inside the model config."""
    from suit_ros.train import _differences
    before = {'lr': 1e-3, 'pillars': {'ground': 'local', 'size': 0.4}}
    now = {'lr': 1e-3, 'new_option': 0.0, 'pillars': {'ground': 'local', 'size': 0.4,
                                                      'added': True}}
    assert _differences(before, now) == []
    now['pillars']['ground'] = 'as_given'
    now['lr'] = 2e-3
    assert _differences(before, now) == ['lr', 'pillars.ground']
    # a run saved while the carry counted frames: compared in seconds
    from suit_ros.train import _model_differences
    old = {'sampling': {'carry_frames': 8, 'alpha': 0.2}}
    assert _model_differences(old, {'sampling': {'carry_s': 0.85, 'alpha': 0.2}}, 'last.pt') == []
    assert _model_differences(old, {'sampling': {'carry_s': 2.0, 'alpha': 0.2}}, 'last.pt') == [
        'sampling.carry_s']


def test_clips_longer_than_the_carry_are_warned_of():
    """With carry_gt (or outages) a clip that spans longer than ``carry_s`` asks the memory
    for objects it has let go: at 2 Hz (bags, nuScenes keyframes) an 8-frame clip spans 3.5 s
    against 0.85 s; at 10 Hz it spans 0.7 s, no warning; without carry_gt or a carry none."""
    from suit_ros.train import TrainConfig, carry_span_warning

    def drive(gap_ns):
        return [[Frame(np.zeros((1, 5), np.float32), np.eye(4), i * gap_ns)
                 for i in range(10)]]
    tc = TrainConfig(carry_gt=True)
    line = carry_span_warning(drive(500_000_000), [8], 0.85, tc)
    assert '8 frames 0.50 s apart span 3.50 s' in line and 'sampling.carry_s' in line
    assert carry_span_warning(drive(100_000_000), [8], 0.85, tc) == ''
    assert carry_span_warning(drive(500_000_000), [8], 0.0, tc) == ''
    assert carry_span_warning(drive(500_000_000), [8], 0.85, TrainConfig()) == ''
