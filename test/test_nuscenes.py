"""The nuScenes-format reader against nuscenes-devkit reading the same tiny on-disk dataset."""
from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from suit_ros.data.nuscenes import NuScenesReader, map_category
from suit_ros.errors import DatasetError

VERSION = 'v1.0-mini'


def quat_wxyz(yaw, pitch=0.0, roll=0.0):
    x, y, z, w = Rotation.from_euler('zyx', [yaw, pitch, roll]).as_quat()
    return [w, x, y, z]


def build_dataset(root, rng):
    tables = {k: [] for k in ('category', 'attribute', 'visibility', 'instance', 'sensor',
                              'calibrated_sensor', 'ego_pose', 'log', 'scene', 'sample',
                              'sample_data', 'sample_annotation', 'map')}
    tables['sensor'].append({'token': 'sens_lidar', 'channel': 'LIDAR_TOP',
                             'modality': 'lidar'})
    tables['calibrated_sensor'].append({'token': 'cal_lidar', 'sensor_token': 'sens_lidar',
                                        'translation': [0.94, 0.0, 1.84],
                                        'rotation': quat_wxyz(-1.57, 0.01, -0.005),
                                        'camera_intrinsic': []})
    cats = ['vehicle.car', 'human.pedestrian.adult', 'vehicle.bus.rigid', 'movable_object.barrier',
            'vehicle.bicycle']
    for c in cats:
        tables['category'].append({'token': f'cat_{c}', 'name': c, 'description': ''})
    tables['visibility'].append({'token': '4', 'level': 'v80-100', 'description': ''})
    tables['log'].append({'token': 'log0', 'logfile': '', 'vehicle': 'v', 'date_captured': '',
                          'location': 'singapore-onenorth'})
    tables['map'].append({'token': 'map0', 'log_tokens': ['log0'], 'category': 'semantic_prior',
                          'filename': ''})
    (root / 'samples/LIDAR_TOP').mkdir(parents=True)
    (root / 'sweeps/LIDAR_TOP').mkdir(parents=True)
    for s in range(2):
        samples = [f's{s}_{k}' for k in range(3)]
        tables['scene'].append({'token': f'scene{s}', 'log_token': 'log0', 'nbr_samples': 3,
                                'first_sample_token': samples[0],
                                'last_sample_token': samples[-1], 'name': f'scene-{s:04d}',
                                'description': ''})
        prev_sd = ''
        sd_records = []
        for k, tok in enumerate(samples):
            t_key = 1_600_000_000_000_000 + s * 100_000_000 + k * 500_000
            tables['sample'].append({'token': tok, 'timestamp': t_key, 'scene_token': f'scene{s}',
                                     'prev': samples[k - 1] if k else '',
                                     'next': samples[k + 1] if k < 2 else ''})
            for j in (2, 1, 0):          # two sweeps, then the keyframe
                t = t_key - j * 50_000
                sd_tok = f'sd_{tok}_{j}'
                ep = f'ep_{sd_tok}'
                tables['ego_pose'].append({'token': ep, 'timestamp': t,
                                           'translation': [100 + 5 * k + 0.1 * j * rng.random(),
                                                           200 + s, 0.1 * rng.random()],
                                           'rotation': quat_wxyz(0.3 + 0.05 * k - 0.01 * j)})
                key = j == 0
                folder = 'samples' if key else 'sweeps'
                fname = f'{folder}/LIDAR_TOP/{sd_tok}.pcd.bin'
                pts = np.c_[rng.uniform(-30, 30, (400, 3)), rng.uniform(0, 255, 400),
                            rng.integers(0, 32, 400)].astype(np.float32)
                pts[:5, :2] = 0.3                              # close points (removed)
                pts.tofile(root / fname)
                rec = {'token': sd_tok, 'sample_token': tok, 'ego_pose_token': ep,
                       'calibrated_sensor_token': 'cal_lidar', 'timestamp': t,
                       'fileformat': 'pcd', 'is_key_frame': key, 'height': 0, 'width': 0,
                       'filename': fname, 'prev': prev_sd, 'next': ''}
                if sd_records:
                    sd_records[-1]['next'] = sd_tok
                sd_records.append(rec)
                prev_sd = sd_tok
        tables['sample_data'] += sd_records
        for i, cat in enumerate(cats):
            inst = f'inst{s}_{i}'
            ann_tokens = [f'ann_{inst}_{k}' for k in range(3)]
            n_ann = 3 if i != 1 else 1                          # an isolated annotation
            tables['instance'].append({'token': inst, 'category_token': f'cat_{cat}',
                                       'nbr_annotations': n_ann,
                                       'first_annotation_token': ann_tokens[0],
                                       'last_annotation_token': ann_tokens[n_ann - 1]})
            for k in range(n_ann):
                tables['sample_annotation'].append({
                    'token': ann_tokens[k], 'sample_token': f's{s}_{k}', 'instance_token': inst,
                    'visibility_token': '4', 'attribute_tokens': [],
                    'translation': [110 + 3 * i + 1.5 * k, 195 + 2 * i, 1.0],
                    'size': [1.9, 4.5, 1.6], 'rotation': quat_wxyz(0.1 * i + 0.02 * k),
                    'prev': ann_tokens[k - 1] if k else '',
                    'next': ann_tokens[k + 1] if k < n_ann - 1 else '',
                    'num_lidar_pts': 10 + i, 'num_radar_pts': 0})
    (root / VERSION).mkdir()
    for name, rows in tables.items():
        (root / VERSION / f'{name}.json').write_text(json.dumps(rows))


@pytest.fixture(scope='module')
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp('nuscenes')
    build_dataset(root, np.random.default_rng(0))
    return root


@pytest.mark.slow
def test_reader_agrees_with_devkit(dataset):
    from nuscenes.nuscenes import NuScenes
    from nuscenes.utils.data_classes import LidarPointCloud
    nusc = NuScenes(VERSION, str(dataset), verbose=False)
    reader = NuScenesReader(dataset, VERSION, sweeps=3)
    frames = {f.stamp_ns: f for scene in reader.scenes() for f in reader.sequence(scene)}
    assert len(frames) == 6
    for sample in nusc.sample:
        sd_tok = sample['data']['LIDAR_TOP']
        pc, times = LidarPointCloud.from_file_multisweep(nusc, sample, 'LIDAR_TOP', 'LIDAR_TOP',
                                                         nsweeps=3)
        f = frames[nusc.get('sample_data', sd_tok)['timestamp'] * 1000]
        np.testing.assert_allclose(f.points[:, :3], pc.points[:3].T, atol=1e-3)
        np.testing.assert_allclose(f.points[:, 4], times[0], atol=1e-6)
        np.testing.assert_allclose(f.points[:, 3], pc.points[3] / 255.0, atol=1e-6)
        _, boxes, _ = nusc.get_sample_data(sd_tok)
        ours = {}
        for b in boxes:
            cls = map_category(b.name)
            if cls is None:
                continue
            ann = nusc.get('sample_annotation', b.token)
            v = nusc.box_velocity(b.token)
            ego = nusc.get('ego_pose', nusc.get('sample_data', sd_tok)['ego_pose_token'])
            cal = nusc.get('calibrated_sensor',
                           nusc.get('sample_data', sd_tok)['calibrated_sensor_token'])
            from pyquaternion import Quaternion
            v_l = Quaternion(cal['rotation']).inverse.rotate(
                Quaternion(ego['rotation']).inverse.rotate(v))     # NaN (unknown) stays NaN
            yaw = b.orientation.yaw_pitch_roll[0]
            ours[ann['num_lidar_pts']] = (b.center, b.wlh, yaw, v_l[:2])
        assert len(ours) == len(f.gt)
        for k, num in enumerate(f.num_points):
            center, wlh, yaw, vel = ours[int(num)]
            np.testing.assert_allclose(f.gt.boxes[k, :3], center, atol=1e-4)
            np.testing.assert_allclose(f.gt.boxes[k, 3:6], [wlh[1], wlh[0], wlh[2]], atol=1e-5)
            assert np.cos(f.gt.boxes[k, 6] - yaw) == pytest.approx(1.0, abs=1e-5)
            np.testing.assert_allclose(f.gt.velocities[k], vel, atol=1e-4)


def test_keyframes_take_the_models_sweeps(dataset):
    """A keyframe input holds the keyframe and the sweeps before it, as many as asked (the
    model's count), as they come; fewer than one is refused."""
    def lags(sweeps):
        reader = NuScenesReader(dataset, VERSION, sweeps=sweeps)
        later = list(reader.sequence(reader.scenes()[0]))[1]
        return sorted(set(np.round(later.points[:, 4].astype(float), 3).tolist()))
    assert lags(2) == [0.0, 0.05]
    assert lags(3) == [0.0, 0.05, 0.1]
    with pytest.raises(DatasetError, match='sweeps'):
        NuScenesReader(dataset, VERSION, sweeps=0)


def test_class_mapping_and_errors(tmp_path, dataset):
    assert map_category('vehicle.bus.bendy') == 'truck'
    assert map_category('human.pedestrian.construction_worker') == 'pedestrian'
    assert map_category('vehicle.motorcycle') == 'cyclist'
    assert map_category('movable_object.trafficcone') is None
    with pytest.raises(DatasetError, match='does not exist'):
        NuScenesReader(tmp_path, VERSION)
    reader = NuScenesReader(dataset, VERSION, sweeps=1)
    first = next(reader.sequence(reader.scenes()[0]))
    assert (first.points[:, 4] == 0).all() and set(first.gt.labels.tolist()) <= {0, 1, 2, 3}


def test_eval_cli_on_nuscenes_format(dataset, tmp_path, capsys):
    from suit_ros.cli import main
    assert main(['eval', '--nuscenes', str(dataset), '--version', VERSION, '--sweeps', '2',
                 '--json-out', str(tmp_path / 'm.json')]) == 0
    out = capsys.readouterr().out
    assert 'mAP' in out and json.loads((tmp_path / 'm.json').read_text())['summary']['frames'] == 6
    # tracked as the node tracks, over keyframes 0.5 s apart (tracker_for)
    assert main(['eval', '--nuscenes', str(dataset), '--version', VERSION, '--sweeps', '2',
                 '--tracker', '--json-out', str(tmp_path / 't.json')]) == 0
    assert json.loads((tmp_path / 't.json').read_text())['summary']['frames'] == 6


def test_eval_and_report_read_nuscenes_with_the_checkpoints_sweeps(dataset, tmp_path,
                                                                   monkeypatch):
    """``eval --nuscenes`` without ``--sweeps`` and ``report --nuscenes`` read each keyframe
    with the checkpoint's count of sweeps (3 for the shipped model, not nuScenes recipes' 10),
    and track over the keyframes with the gap widened (tracker_for); ``--sweeps 0`` is
    refused."""
    from suit_ros.cli import main
    import suit_ros.data.nuscenes as nus
    import suit_ros.evaluate as ev
    counts, gaps = [], []
    reader_init, widen = nus.NuScenesReader.__init__, ev.tracker_for

    def spy_init(self, root, version='v1.0-mini', sweeps=3, *a, **k):
        counts.append(sweeps)
        reader_init(self, root, version, sweeps, *a, **k)

    def spy_widen(seqs, config=None):
        out = widen(seqs, config)
        gaps.append(out.max_gap_s)
        return out
    monkeypatch.setattr(nus.NuScenesReader, '__init__', spy_init)
    monkeypatch.setattr(ev, 'tracker_for', spy_widen)
    assert main(['eval', '--nuscenes', str(dataset), '--version', VERSION, '--tracker',
                 '--json-out', str(tmp_path / 'e.json')]) == 0
    assert counts == [3] and gaps == [pytest.approx(1.25)]
    assert main(['report', '--nuscenes', str(dataset), '--version', VERSION,
                 '--out', str(tmp_path / 'report')]) == 0
    assert counts == [3, 3] and gaps == [pytest.approx(1.25)] * 2
    report = json.loads((tmp_path / 'report' / 'report.json').read_text())
    # keyframes come with their sweeps (counted by their time lags), but a scene's first
    # keyframe has none before it
    by = report.get('frames_by_input_sweeps', {})
    assert sum(by.values()) == report['frames'] and by.get('3', 0) >= 1
    # the scenes were recorded in Singapore: the report runs them as the node set for
    # left-hand traffic would (--traffic-side auto, the default), or as told
    assert 'traffic side left in 2 of 2 sequences' in \
        (tmp_path / 'report' / 'report.md').read_text()
    assert main(['report', '--nuscenes', str(dataset), '--version', VERSION, '--pictures', '0',
                 '--traffic-side', 'right', '--out', str(tmp_path / 'right')]) == 0
    assert 'traffic side left' not in (tmp_path / 'right' / 'report.md').read_text()
    assert main(['eval', '--nuscenes', str(dataset), '--version', VERSION,
                 '--sweeps', '0']) != 0


def test_parked_bicycles_are_ignored_and_objects_keep_their_ids(dataset, tmp_path):
    """A bicycle without a rider (``cycle.without_rider``) is neither a cyclist nor a false
    positive (an ignore box, as the Argoverse 2 reader's parked bicycles); one with a rider
    is a cyclist. A stroller is no pedestrian (the devkit's four pedestrian subclasses). Each
    object keeps one instance id over its keyframes."""
    import shutil
    root = tmp_path / 'ns'
    shutil.copytree(dataset, root)
    tables = root / VERSION
    anns = json.loads((tables / 'sample_annotation.json').read_text())
    for a in anns:
        if a['instance_token'] == 'inst0_4':
            a['attribute_tokens'] = ['attr_rider']
        if a['instance_token'] == 'inst1_4':
            a['attribute_tokens'] = ['attr_parked']
    (tables / 'sample_annotation.json').write_text(json.dumps(anns))
    # scene 1's adult is a stroller there: an ignore box too
    cats = json.loads((tables / 'category.json').read_text())
    cats.append({'token': 'cat_stroller', 'name': 'human.pedestrian.stroller',
                 'description': ''})
    (tables / 'category.json').write_text(json.dumps(cats))
    insts = json.loads((tables / 'instance.json').read_text())
    for i in insts:
        if i['token'] == 'inst1_1':
            i['category_token'] = 'cat_stroller'
    (tables / 'instance.json').write_text(json.dumps(insts))
    (tables / 'attribute.json').write_text(json.dumps([
        {'token': 'attr_rider', 'name': 'cycle.with_rider', 'description': ''},
        {'token': 'attr_parked', 'name': 'cycle.without_rider', 'description': ''}]))
    reader = NuScenesReader(root, VERSION, sweeps=1)
    cyclist = list(reader.class_names).index('cyclist')
    scene0, scene1 = (list(reader.sequence(s)) for s in reader.scenes())
    assert all((f.gt.labels == cyclist).sum() == 1 for f in scene0)
    pedestrian = list(reader.class_names).index('pedestrian')
    assert all((f.gt.labels == cyclist).sum() == 0 for f in scene1)
    assert [len(f.ignore_boxes) for f in scene1] == [2, 1, 1]      # the stroller: frame 0
    assert not any((f.gt.labels == pedestrian).any() for f in scene1)
    ids = [dict(zip(f.num_points.tolist(), f.instance_ids.tolist())) for f in scene0]
    assert ids[0][10] == ids[1][10] == ids[2][10] != 0          # the car, over 3 keyframes
    assert len(set(ids[0].values())) == len(ids[0])
    assert map_category('human.pedestrian.stroller') is None
    assert map_category('human.pedestrian.wheelchair') is None


def test_scenes_keep_to_the_side_of_their_log_location(dataset, tmp_path):
    """Singapore logs keep left, Boston logs right, and a dataset without a log table right."""
    import json
    import shutil

    from suit_ros.data.nuscenes import NuScenesReader
    from suit_ros.data.sequences import nuscenes_scenes
    seqs, sides = nuscenes_scenes(dataset, VERSION)
    assert len(seqs) == 2 and sides == ['left', 'left']
    copy = tmp_path / 'boston'
    shutil.copytree(dataset, copy)
    log = copy / VERSION / 'log.json'
    rows = json.loads(log.read_text())
    rows[0]['location'] = 'boston-seaport'
    log.write_text(json.dumps(rows))
    reader = NuScenesReader(copy, VERSION)
    assert [reader.traffic_side(s) for s in reader.scenes()] == ['right', 'right']
    log.unlink()
    reader = NuScenesReader(copy, VERSION)
    assert [reader.traffic_side(s) for s in reader.scenes()] == ['right', 'right']
