"""The Argoverse 2 reader on small AV2-layout logs the tests write themselves."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.feather as feather
import pytest

from suit_ros.data.av2 import EGO_HEIGHT_M, Av2Sequence, av2_sequences, find_logs
from suit_ros.errors import DatasetError
from suit_ros.evaluate import drop_ignored, run_model
from suit_ros.structures import Detections

T0 = 315966265259836000
DT = 100_000_000                       # 10 Hz


def _quat_z(yaw: float) -> tuple[float, float, float, float]:
    return np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)


def _write(path: Path, columns: dict[str, object]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    feather.write_feather(pa.table(columns), str(path))


def write_log(root: Path, sweeps: int = 3, ego_speed: float = 5.0,
              car_speed: float = 10.0, points: int = 2000) -> Path:
    """A log under ``root/sensor/val/<id>``: the ego drives along x at ``ego_speed``, a car
    ahead drives along +x at ``car_speed`` (city frame), a pedestrian stands, a parked bicycle
    (ignored), a bollard (background). Annotations at every sweep stamp and two more."""
    log = root / 'sensor' / 'val' / '0000-test-log'
    rng = np.random.default_rng(0)
    ann: dict[str, list[object]] = {k: [] for k in (
        'timestamp_ns', 'track_uuid', 'category', 'length_m', 'width_m', 'height_m', 'qw',
        'qx', 'qy', 'qz', 'tx_m', 'ty_m', 'tz_m', 'num_interior_pts')}
    poses: dict[str, list[object]] = {k: [] for k in (
        'timestamp_ns', 'qw', 'qx', 'qy', 'qz', 'tx_m', 'ty_m', 'tz_m')}
    for k in range(-1, sweeps + 1):
        stamp = T0 + k * DT
        ego_x = 100.0 + ego_speed * k * 0.1
        for name, v in zip(('qw', 'qx', 'qy', 'qz'), _quat_z(0.0)):
            poses[name].append(v)
        poses['timestamp_ns'].append(stamp)
        poses['tx_m'].append(ego_x)
        poses['ty_m'].append(50.0)
        poses['tz_m'].append(10.0)
        car_x = 120.0 + car_speed * k * 0.1 - ego_x           # egovehicle frame
        for uuid, cat, size, xyz, yaw in (
                ('car-1', 'REGULAR_VEHICLE', (4.5, 1.9, 1.6), (car_x, 0.0, 0.45), 0.0),
                ('ped-1', 'PEDESTRIAN', (0.6, 0.6, 1.75), (108.0 - ego_x, 5.0, 0.5), np.pi / 2),
                ('bike-1', 'BICYCLE', (1.7, 0.6, 1.0), (-6.0, -6.0, 0.15), 0.3),
                ('bollard-1', 'BOLLARD', (0.3, 0.3, 0.9), (5.0, -5.0, 0.1), 0.0)):
            ann['timestamp_ns'].append(stamp)
            ann['track_uuid'].append(uuid)
            ann['category'].append(cat)
            for name, v in zip(('length_m', 'width_m', 'height_m'), size):
                ann[name].append(v)
            for name, v in zip(('qw', 'qx', 'qy', 'qz'), _quat_z(yaw)):
                ann[name].append(v)
            for name, v in zip(('tx_m', 'ty_m', 'tz_m'), xyz):
                ann[name].append(v)
            ann['num_interior_pts'].append(0)
        if 0 <= k < sweeps:
            xyz = np.concatenate([rng.uniform([-40, -40, -0.4], [40, 40, -0.3], (points, 3)),
                                  rng.uniform([car_x - 2, -0.8, 0.0], [car_x + 2, 0.8, 1.0],
                                              (50, 3))]).astype(np.float16)
            n = len(xyz)
            _write(log / 'sensors' / 'lidar' / f'{stamp}.feather', {
                'x': xyz[:, 0], 'y': xyz[:, 1], 'z': xyz[:, 2],
                'intensity': rng.integers(0, 256, n).astype(np.uint8),
                'laser_number': rng.integers(0, 64, n).astype(np.uint8),
                'offset_ns': np.zeros(n, np.int32)})
    _write(log / 'annotations.feather', ann)
    _write(log / 'city_SE3_egovehicle.feather', poses)
    _write(log / 'calibration' / 'egovehicle_SE3_sensor.feather', {
        'sensor_name': ['up_lidar'], 'qw': [1.0], 'qx': [0.0], 'qy': [0.0], 'qz': [0.0],
        'tx_m': [1.35], 'ty_m': [0.0], 'tz_m': [1.64]})
    return log


def test_reads_points_gt_classes_poses_and_velocities(tmp_path: Path) -> None:
    log = write_log(tmp_path)
    (seq,) = av2_sequences(tmp_path)
    assert len(seq) == 3 and seq.sequence_id == log.name
    f = seq[1]
    assert f.points.shape[1] == 5 and f.points.dtype == np.float32
    assert 0.0 <= f.points[:, 3].min() and f.points[:, 3].max() <= 1.0      # 0..255 -> 0..1
    assert (f.points[:, 4] == 0).all()
    assert f.stamp_ns == T0 + DT
    # the egovehicle frame is lifted to base_link by the rear-axle height
    np.testing.assert_allclose(f.T_base_lidar[2, 3], EGO_HEIGHT_M)
    np.testing.assert_allclose(f.pose[:3, 3], [100.5, 50.0, 10.0])
    # car and pedestrian are objects; the bicycle is ignored; the bollard is background
    assert f.gt is not None and sorted(f.gt.labels.tolist()) == [0, 2]
    assert f.ignore_boxes is not None and len(f.ignore_boxes) == 1
    np.testing.assert_allclose(f.ignore_boxes[0, :2], [-6.0, -6.0], atol=1e-5)
    car = f.gt.labels == 0
    np.testing.assert_allclose(f.gt.velocities[car][0], [10.0, 0.0], atol=1e-6)  # absolute
    np.testing.assert_allclose(f.gt.velocities[~car][0], [-0.0, 0.0], atol=1e-6)
    ped = f.gt.boxes[~car][0]
    np.testing.assert_allclose(ped[6], np.pi / 2, atol=1e-6)                # yaw from quat
    assert f.num_points is not None and f.num_points[car][0] >= 50
    # each object keeps one id (its track) over the sweeps, as a tracking dataset's
    ids = [dict(zip(g.gt.labels.tolist(), g.instance_ids.tolist())) for g in seq]
    assert ids[0] == ids[1] == ids[2] and 0 not in ids[0].values()
    assert len(set(ids[0].values())) == 2


def test_an_object_annotated_twice_is_one_object(tmp_path: Path) -> None:
    """Two track ids with one category and one box (as a car of the real dev log has) are one
    GT box; a car of the same size next to it, or the same box turned by 10 degrees, stays."""
    from suit_ros.data.av2 import first_of_duplicates
    write_log(tmp_path)
    path = tmp_path / 'sensor/val/0000-test-log/annotations.feather'
    t = feather.read_table(str(path)).to_pydict()
    rows = [i for i, c in enumerate(t['category']) if c == 'REGULAR_VEHICLE']
    for i in rows:                         # a second track id on the same car at every stamp
        for k in t:
            t[k].append(f'{t[k][i]}-again' if k == 'track_uuid' else t[k][i])
    feather.write_feather(pa.table(t), str(path))
    (seq,) = av2_sequences(tmp_path)
    f = seq[1]
    assert f.gt is not None and sorted(f.gt.labels.tolist()) == [0, 2]
    np.testing.assert_allclose(f.gt.velocities[f.gt.labels == 0][0], [10.0, 0.0], atol=1e-6)
    box = np.array([10.0, 2.0, 0.5, 4.5, 1.9, 1.6, 0.3])
    beside, turned, flipped = box.copy(), box.copy(), box.copy()
    beside[1] += 2.2
    turned[6] += np.deg2rad(10)
    flipped[6] += np.pi                    # the same box with its heading the other way
    boxes = np.stack([box, box, beside, turned, flipped, box])
    keys = ['car', 'car', 'car', 'car', 'car', 'pedestrian']
    assert first_of_duplicates(boxes, keys).tolist() == [True, False, True, True, False, True]
    assert first_of_duplicates(np.zeros((0, 7)), []).tolist() == []


def test_velocity_in_the_egovehicle_frame_when_the_ego_turns(tmp_path: Path) -> None:
    write_log(tmp_path)
    path = tmp_path / 'sensor/val/0000-test-log/city_SE3_egovehicle.feather'
    t = feather.read_table(str(path)).to_pydict()
    qw, _, _, qz = _quat_z(np.pi / 2)          # the ego faces city +y: city +x is ego -y
    t['qw'] = [qw] * len(t['qw'])
    t['qz'] = [qz] * len(t['qz'])
    feather.write_feather(pa.table(t), str(path))
    (seq,) = av2_sequences(tmp_path)
    gt, _, _ = seq.labelled(T0 + DT)
    # the car moves +5 m/s along ego x relative to the ego, which moves along city +x (ego -y)
    # at 5 m/s: (5, 5) in the city, (5, -5) in the egovehicle frame
    np.testing.assert_allclose(gt.velocities[gt.labels == 0][0], [5.0, -5.0], atol=1e-6)


def test_an_object_annotated_once_has_an_unknown_velocity(tmp_path: Path) -> None:
    """A track annotated at one stamp only has no velocity (NaN, as the nuScenes devkit says),
    not 0: a standing target would teach the velocity head, and score its error, as if the
    object stood still."""
    write_log(tmp_path)
    path = tmp_path / 'sensor/val/0000-test-log/annotations.feather'
    t = feather.read_table(str(path)).to_pydict()
    i = next(i for i, (c, s) in enumerate(zip(t['category'], t['timestamp_ns']))
             if c == 'REGULAR_VEHICLE' and s == T0 + DT)
    for k in t:                            # a second car, seen at this one stamp
        t[k].append('car-once' if k == 'track_uuid' else
                    t[k][i] + 10.0 if k == 'ty_m' else t[k][i])
    feather.write_feather(pa.table(t), str(path))
    (seq,) = av2_sequences(tmp_path)
    gt, _, _ = seq.labelled(T0 + DT)
    cars = gt.velocities[gt.labels == 0]
    assert len(cars) == 2
    np.testing.assert_allclose(cars[0], [10.0, 0.0], atol=1e-6)
    assert np.isnan(cars[1]).all()


def test_find_logs_accepts_dataset_split_and_log_folders(tmp_path: Path) -> None:
    log = write_log(tmp_path)
    for root in (tmp_path, tmp_path / 'sensor', tmp_path / 'sensor' / 'val', log):
        assert find_logs(root) == [log]


def test_clear_errors_for_wrong_folders_and_corrupt_files(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match='not a folder'):
        find_logs(tmp_path / 'nope')
    (tmp_path / 'empty').mkdir()
    with pytest.raises(DatasetError, match='no Argoverse 2 log'):
        find_logs(tmp_path / 'empty')
    log = write_log(tmp_path / 'a')
    (log / 'annotations.feather').write_bytes(b'not arrow at all')
    with pytest.raises(DatasetError, match='not a readable feather'):
        Av2Sequence(log)
    log = write_log(tmp_path / 'b')
    (log / 'city_SE3_egovehicle.feather').unlink()
    with pytest.raises(DatasetError, match='missing .*city_SE3_egovehicle'):
        Av2Sequence(log)
    log = write_log(tmp_path / 'c')
    _write(log / 'annotations.feather', {'timestamp_ns': [T0]})
    with pytest.raises(DatasetError, match='lacks the column'):
        Av2Sequence(log)


def test_drop_ignored_keeps_detections_near_real_objects() -> None:
    gt = Detections(np.array([[10.0, 0, 0, 0.6, 0.6, 1.7, 0]]), np.zeros((1, 2)), np.ones(1),
                    np.array([2]))
    ignore = np.array([[0.0, 0, 0, 1.7, 0.6, 1.0, 0], [10.5, 0, 0, 1.7, 0.6, 1.0, 0]])
    det = Detections(np.array([[0.5, 0, 0, 0.6, 0.6, 1.7, 0],     # on the parked bicycle
                               [10.2, 0, 0, 0.6, 0.6, 1.7, 0],    # the pedestrian beside one
                               [20.0, 0, 0, 0.6, 0.6, 1.7, 0]]),  # a false positive
                     np.zeros((3, 2)), np.array([0.9, 0.8, 0.7]), np.array([2, 2, 2]))
    kept = drop_ignored(det, gt, ignore)
    np.testing.assert_allclose(kept.boxes[:, 0], [10.2, 20.0])
    # only a scored object of the box's own class vouches for it: a cyclist box on the
    # bicycle beside the pedestrian is on an ignored thing (it counted as a false positive),
    # and so is a pedestrian box there when the pedestrian has no returns (not scored)
    cyclist = Detections(det.boxes[1:2], np.zeros((1, 2)), np.array([0.8]), np.array([1]))
    assert len(drop_ignored(cyclist, gt, ignore)) == 0
    assert len(drop_ignored(det, gt, ignore, num_points=np.array([0], np.uint32))) == 1
    assert len(drop_ignored(det, gt, ignore, num_points=np.array([5], np.uint32))) == 2


@pytest.mark.slow
def test_model_runs_over_an_av2_log(tmp_path: Path) -> None:
    from suit_ros.checkpoint import default_checkpoint_path, load_checkpoint
    write_log(tmp_path)
    model, cfg, _ = load_checkpoint(default_checkpoint_path())
    seqs = av2_sequences(tmp_path, cfg.class_names)
    run = run_model(model, seqs)
    assert len(run.det) == 3 and len(run.ignore) == 3
    result = run.evaluate(cfg.class_names)
    assert result.num_gt['car'] == 3 and result.num_frames == 3


@pytest.mark.slow
def test_eval_runs_the_model_as_an_overloaded_node_does(tmp_path: Path, capsys) -> None:
    """``eval --run-every 2``: the model runs on sweeps 0, 2, 4 (the others feed its sweeps),
    only those are scored; a value it cannot honour is refused with a message."""
    import json

    from suit_ros.cli import main
    write_log(tmp_path / 'data', sweeps=5)
    out = tmp_path / 'every2.json'
    assert main(['eval', '--av2', str(tmp_path / 'data'), '--run-every', '2', '--tracker',
                 '--json-out', str(out)]) == 0
    assert json.loads(out.read_text())['summary']['frames'] == 3
    assert main(['eval', '--av2', str(tmp_path / 'data'), '--run-every', '0']) == 1
    assert '--run-every must be at least 1' in capsys.readouterr().err
    assert main(['eval', '--av2', str(tmp_path / 'data'), '--run-every', '2',
                 '--history', '2']) == 1
    assert 'without --history' in capsys.readouterr().err
    with pytest.raises(ValueError, match='run_every'):
        run_model(None, [], run_every=0)


@pytest.mark.slow
def test_a_training_config_can_train_on_av2_logs(tmp_path: Path) -> None:
    from suit_ros.checkpoint import load_checkpoint
    from suit_ros.train import TrainConfig, train
    write_log(tmp_path / 'data', sweeps=3)
    repo = Path(__file__).resolve().parents[1]
    tc = TrainConfig(model_config=str(repo / 'params/model_cpu.yaml'), dataset='av2',
                     dataset_paths=(str(tmp_path / 'data'),), temporal='suit', steps=2,
                     batch_size=1, clip_lengths=(2,), checkpoint_every=1, eval_at_end=False)
    metrics = train(tc, tmp_path / 'run')
    assert metrics['steps'] == 2
    _, cfg, _ = load_checkpoint(tmp_path / 'run' / 'model.safetensors')
    assert cfg.temporal == 'suit'
