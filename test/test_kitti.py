"""The KITTI-format reader on tiny datasets the tests write (object and tracking layouts).

Boxes are checked against an independent implementation of the KITTI devkit's formulas
(``computeBox3D`` corners in the rectified camera frame, moved to the Velodyne frame by solving
``R0_rect @ Tr_velo_to_cam``), not against the reader's own conversion.
"""
from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from suit_ros.data.kitti import (
    KittiReader,
    camera_boxes_to_lidar,
    camera_fov_run,
    in_camera_fov,
    map_kitti_class,
    oxts_poses,
    read_calib,
    read_velodyne,
)
from suit_ros.data.sequences import ClipSampler, kitti_sequences
from suit_ros.errors import DatasetError
from suit_ros.evaluate import ModelRun
from suit_ros.structures import Detections

# KITTI's nominal axes: camera x = -velo y, camera y = -velo z, camera z = velo x.
NOMINAL = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
P2 = np.array([[700.0, 0.0, 600.0, 45.0], [0.0, 700.0, 180.0, -0.3], [0.0, 0.0, 1.0, 0.005]])


def make_calib(yaw=0.03, ry_rect=0.04, tilt=(0.0, 0.0)):
    """R0_rect (3, 3) and Tr_velo_to_cam (3, 4): non-trivial rotations, optionally tilted."""
    R0 = Rotation.from_euler('y', ry_rect).as_matrix()
    R_velo = Rotation.from_euler('zyx', [yaw, tilt[0], tilt[1]]).as_matrix()
    Tr = np.c_[NOMINAL @ R_velo.T, [-0.02, -0.07, -0.3]]
    return R0, Tr


def calib_text(R0, Tr, tracking=False, Tr_imu=None):
    rows = [('P0', P2), ('P1', P2), ('P2', P2), ('P3', P2),
            ('R_rect' if tracking else 'R0_rect', R0),
            ('Tr_velo_cam' if tracking else 'Tr_velo_to_cam', Tr)]
    if Tr_imu is not None:
        rows.append(('Tr_imu_velo' if tracking else 'Tr_imu_to_velo', Tr_imu))
    sep = ' ' if tracking else ': '
    return '\n'.join(k + sep + ' '.join(f'{v:.12e}' for v in np.ravel(m)) for k, m in rows) + '\n'


def velo_from_rect(R0, Tr):
    """Devkit rule: x_rect = R0_rect * Tr_velo_to_cam * x_velo, solved for x_velo."""
    M = np.eye(4)
    M[:3, :3] = R0
    T = np.eye(4)
    T[:3] = Tr
    return np.linalg.inv(M @ T)


def devkit_corners(h, w, length, loc, ry):
    """computeBox3D of the KITTI object devkit: ``(8, 3)`` corners in the rectified frame."""
    R = np.array([[np.cos(ry), 0, np.sin(ry)], [0, 1, 0], [-np.sin(ry), 0, np.cos(ry)]])
    x = [length / 2, length / 2, -length / 2, -length / 2] * 2
    y = [0, 0, 0, 0, -h, -h, -h, -h]
    z = [w / 2, -w / 2, -w / 2, w / 2] * 2
    return (R @ np.array([x, y, z])).T + np.asarray(loc)


def box_corners(box):
    """``(8, 3)`` corners of an upright ``x y z l w h yaw`` box."""
    x, y, z, length, w, h, yaw = box
    sx, sy, sz = np.meshgrid([-1, 1], [-1, 1], [-1, 1], indexing='ij')
    local = np.c_[sx.ravel() * length / 2, sy.ravel() * w / 2, sz.ravel() * h / 2]
    c, s = np.cos(yaw), np.sin(yaw)
    return local @ np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]]) + [x, y, z]


def to_velo(T, xyz):
    return (np.c_[xyz, np.ones(len(xyz))] @ T.T)[:, :3]


def points_in_camera_box(rng, n, h, w, length, loc, ry, T):
    """``n`` Velodyne points strictly inside a camera-frame box (5 % away from its faces)."""
    u = rng.uniform(-0.45, 0.45, (n, 3))
    local = np.c_[u[:, 0] * length, (u[:, 1] - 0.5) * h, u[:, 2] * w]
    R = np.array([[np.cos(ry), 0, np.sin(ry)], [0, 1, 0], [-np.sin(ry), 0, np.cos(ry)]])
    return to_velo(T, local @ R.T + np.asarray(loc))


def label_line(kind, h, w, length, loc, ry, prefix=''):
    return (f'{prefix}{kind} 0.00 0 -1.57 100.0 150.0 200.0 250.0 {h:.2f} {w:.2f} '
            f'{length:.2f} {loc[0]:.6f} {loc[1]:.6f} {loc[2]:.6f} {ry:.6f}')


# (type, h, w, l, location (bottom centre, rect camera), ry, points inside)
OBJECTS = [('Car', 1.5, 1.7, 4.2, (1.0, 1.6, 12.0), 0.3, 60),
           ('Van', 2.1, 1.9, 5.0, (-4.0, 1.7, 20.0), -1.2, 40),
           ('Pedestrian', 1.8, 0.6, 0.7, (3.0, 1.7, 8.0), 2.5, 25),
           ('Cyclist', 1.7, 0.6, 1.8, (-2.5, 1.6, 15.0), 1.0, 30),
           ('Truck', 3.2, 2.5, 9.0, (6.0, 1.8, 30.0), 0.1, 50),
           ('Person_sitting', 1.1, 0.6, 0.8, (0.0, 1.7, 6.0), 0.0, 10),
           ('Tram', 3.5, 2.6, 15.0, (-9.0, 1.8, 35.0), 0.0, 20),
           ('Misc', 1.0, 1.0, 1.0, (2.0, 1.7, 25.0), 0.0, 5)]
EXPECTED_LABELS = [0, 0, 2, 3, 1, 2]      # car, car, pedestrian, cyclist, truck, pedestrian


def write_object_frame(root, name, rng, R0, Tr, objects=OBJECTS):
    T = velo_from_rect(R0, Tr)
    chunks = [np.c_[rng.uniform(-40, 40, (300, 2)), rng.uniform(-2.6, -2.5, 300)]]  # ground
    lines = []
    for kind, h, w, length, loc, ry, n in objects:
        chunks.append(points_in_camera_box(rng, n, h, w, length, loc, ry, T))
        lines.append(label_line(kind, h, w, length, loc, ry))
    lines.append('DontCare -1 -1 -10 500.0 150.0 540.0 190.0 -1 -1 -1 -1000 -1000 -1000 -10')
    xyz = np.concatenate(chunks)
    pts = np.c_[xyz, rng.uniform(0, 1, len(xyz))].astype(np.float32)
    for d in ('velodyne', 'label_2', 'calib'):
        (root / d).mkdir(parents=True, exist_ok=True)
    pts.tofile(root / 'velodyne' / f'{name}.bin')
    (root / 'label_2' / f'{name}.txt').write_text('\n'.join(lines) + '\n')
    (root / 'calib' / f'{name}.txt').write_text(calib_text(R0, Tr))
    return pts


@pytest.fixture(scope='module')
def object_root(tmp_path_factory):
    root = tmp_path_factory.mktemp('kitti_object')
    rng = np.random.default_rng(0)
    R0, Tr = make_calib()
    write_object_frame(root / 'training', '000000', rng, R0, Tr)
    write_object_frame(root / 'training', '000001', rng, *make_calib(-0.05, 0.02))
    return root


def test_boxes_match_devkit_corners(object_root):
    R0, Tr = make_calib()
    T = velo_from_rect(R0, Tr)
    seqs = KittiReader(object_root).sequences()
    assert [s.sequence_id for s in seqs] == ['000000', '000001'] and len(seqs[0]) == 1
    frame = seqs[0][0]
    assert frame.gt is not None and frame.frame_id == 'velodyne'
    kept = [o for o in OBJECTS if map_kitti_class(o[0]) is not None]
    assert len(frame.gt) == len(kept)
    for box, (_, h, w, length, loc, ry, _) in zip(frame.gt.boxes, kept):
        theirs = to_velo(T, devkit_corners(h, w, length, loc, ry))
        ours = box_corners(box)
        dist = np.linalg.norm(theirs[:, None] - ours[None], axis=2)
        assert dist.min(1).max() < 1e-4 and dist.min(0).max() < 1e-4
        np.testing.assert_allclose(box[3:6], [length, w, h], atol=1e-6)


def test_yaw_is_minus_ry_minus_half_pi_for_nominal_axes(tmp_path):
    R0, Tr = make_calib(yaw=0.0, ry_rect=0.0)
    (tmp_path / 'calib.txt').write_text(calib_text(R0, Tr))
    calib = read_calib(tmp_path / 'calib.txt')
    ry = np.array([-3.0, -1.0, 0.0, 0.5, 2.0, 3.1])
    boxes = camera_boxes_to_lidar(np.ones((6, 3)), np.zeros((6, 3)), ry, calib)
    np.testing.assert_allclose(np.cos(boxes[:, 6] - (-ry - np.pi / 2)), 1.0, atol=1e-9)
    assert (np.abs(boxes[:, 6]) <= np.pi).all()
    # the centre is lifted by h / 2 (camera y points down): z_velo + 1 for h = 2
    lifted = camera_boxes_to_lidar([[2.0, 1.0, 1.0]], [[0.0, 1.0, 10.0]], [0.0], calib)
    bottom = to_velo(velo_from_rect(R0, Tr), [[0.0, 1.0, 10.0]])[0]
    np.testing.assert_allclose(lifted[0, :3], bottom + [0.0, 0.0, 1.0], atol=1e-9)


@pytest.mark.parametrize('tilt', [(0.01, 0.0), (0.0, -0.015), (0.012, 0.008)])
def test_tilted_calibration_corners_within_tilt(tmp_path, tilt):
    """With a tilted LiDAR the upright LiDAR box can only approximate the camera box: the
    centre stays exact and the corners move by at most the tilt times the half-diagonal."""
    R0, Tr = make_calib(tilt=tilt)
    write_object_frame(tmp_path, '000007', np.random.default_rng(1), R0, Tr, OBJECTS[:1])
    frame = KittiReader(tmp_path).sequences()[0][0]
    assert frame.gt is not None
    _, h, w, length, loc, ry, _ = OBJECTS[0]
    theirs = to_velo(velo_from_rect(R0, Tr), devkit_corners(h, w, length, loc, ry))
    np.testing.assert_allclose(frame.gt.boxes[0, :3], theirs.mean(0), atol=1e-5)
    dist = np.linalg.norm(theirs[:, None] - box_corners(frame.gt.boxes[0])[None], axis=2)
    bound = 1.1 * np.hypot(*tilt) * 0.5 * np.linalg.norm([length, w, h]) + 1e-4
    assert 1e-4 < dist.min(1).max() <= bound


def test_num_points_classes_points_and_extrinsic(object_root):
    frame = KittiReader(object_root).sequences()[0][0]
    assert frame.gt is not None and frame.num_points is not None
    kept = [o for o in OBJECTS if map_kitti_class(o[0]) is not None]
    assert frame.num_points.tolist() == [o[6] for o in kept]
    assert frame.gt.labels.tolist() == EXPECTED_LABELS
    # the tram and the misc object: labelled, not a class here: ignore boxes (a box on one is
    # no false positive), in the Velodyne frame (x forward: the camera's z)
    assert frame.ignore_boxes is not None and len(frame.ignore_boxes) == 2
    np.testing.assert_allclose(frame.ignore_boxes[:, 3], [15.0, 1.0])      # their lengths
    assert frame.ignore_boxes[0, 0] > 30.0 and frame.ignore_boxes[1, 0] > 20.0
    # the object layout has single frames: no velocity is known (NaN, not standing still)
    assert np.isnan(frame.gt.velocities).all() and (frame.gt.scores == 1).all()
    raw = np.fromfile(object_root / 'training/velodyne/000000.bin', np.float32).reshape(-1, 4)
    assert frame.points.shape == (len(raw), 5) and frame.points.dtype == np.float32
    np.testing.assert_array_equal(frame.points[:, :4], raw)      # reflectance not scaled
    assert (frame.points[:, 4] == 0).all()
    np.testing.assert_array_equal(frame.pose, np.eye(4))
    expected = np.eye(4)
    expected[2, 3] = 1.73
    np.testing.assert_array_equal(frame.T_base_lidar, expected)
    assert [map_kitti_class(t) for t in ('Tram', 'Misc', 'DontCare', 'Person_sitting',
                                         'Person')] == [None, None, None, 'pedestrian',
                                                        'pedestrian']
    # kitti_sequences: the same frames, optionally cropped to the camera's view for training
    cropped = kitti_sequences(object_root, fov_points_only=True, ids=['000000'])
    assert len(cropped) == 1
    small = cropped[0][0]
    calib = read_calib(object_root / 'training/calib/000000.txt')
    assert in_camera_fov(small.points[:, :3], calib).all()
    assert 0 < len(small.points) < len(frame.points)
    assert small.num_points is not None and small.num_points.tolist() == [o[6] for o in kept]
    clips = ClipSampler(kitti_sequences(object_root), [1], 0).batch(3)
    assert all(len(c) == 1 and c[0].sequence_id in ('000000', '000001') for c in clips)


def test_camera_fov_against_projection(object_root):
    calib = read_calib(object_root / 'training/calib/000000.txt')
    R0, Tr = make_calib()
    rng = np.random.default_rng(3)
    xyz = np.c_[rng.uniform(-60, 60, (2000, 2)), rng.uniform(-3, 2, 2000)]
    T = np.linalg.inv(velo_from_rect(R0, Tr))
    rect = to_velo(T, xyz)
    img = np.c_[rect, np.ones(len(rect))] @ P2.T
    expected = (img[:, 2] > 0) & (img[:, 0] / img[:, 2] >= 0) & (img[:, 0] / img[:, 2] < 1242)
    np.testing.assert_array_equal(in_camera_fov(xyz, calib), expected)
    assert 200 < expected.sum() < 1800
    assert in_camera_fov([[20.0, 0.0, 0.0]], calib).all()
    assert not in_camera_fov([[-20.0, 0.0, 0.0], [1.0, 20.0, 0.0]], calib).any()
    narrow = in_camera_fov(xyz, calib, image_width=600)
    assert narrow.sum() < expected.sum() and not (narrow & ~expected).any()


def test_evaluation_scores_only_the_camera_view(object_root):
    seqs = kitti_sequences(object_root, ids=['000000'])
    frame = seqs[0][0]
    assert frame.gt is not None
    behind = frame.gt.boxes[:1].copy()
    behind[0, 0] = -15.0                       # a car behind the camera: nobody labelled it
    boxes = np.concatenate([frame.gt.boxes, behind])
    scores = np.r_[np.full(len(frame.gt), 0.5), 0.9]
    det = Detections(boxes, np.zeros((len(boxes), 2)), scores, np.r_[frame.gt.labels, 0])
    run = ModelRun([frame.gt], [det], [frame.num_points], [0.01], [0], {})
    assert run.evaluate(('car', 'truck', 'pedestrian', 'cyclist')).class_ap['car'] < 0.9
    scored = camera_fov_run(run, seqs)
    assert len(scored.det[0]) == len(frame.gt) and len(scored.gt[0]) == len(frame.gt)
    result = scored.evaluate(('car', 'truck', 'pedestrian', 'cyclist'))
    assert result.class_ap['car'] == pytest.approx(1.0)
    # each detection's carried flag goes with it: the published cut stays consistent
    run.carried = [np.r_[np.zeros(len(frame.gt), bool), True]]
    scored = camera_fov_run(run, seqs)
    assert scored.carried[0].tolist() == [False] * len(frame.gt)
    published = scored.published([0.5] * 4, [0.5] * 4)
    assert len(published[0]) == (scores[:-1] >= 0.5).sum()
    with pytest.raises(ValueError, match='frames'):
        camera_fov_run(run, seqs * 2)


@pytest.mark.slow
def test_report_runs_on_a_kitti_folder(object_root, tmp_path):
    """``suit-ros report --kitti`` with the shipped checkpoint: the camera view is scored and
    the published cut, the missed objects and the false positives follow it."""
    from suit_ros.cli import main
    assert main(['report', '--kitti', str(object_root / 'training'), '--out',
                 str(tmp_path / 'r'), '--pictures', '0']) == 0
    report = json.loads((tmp_path / 'r' / 'report.json').read_text())
    assert report['frames'] == 2 and 'camera field of view' in report['source']
    gt = sum(c['published']['gt'] for c in report['classes'].values())
    found = sum(c['published']['tp'] for c in report['classes'].values())
    assert gt > 0 and len(report['missed']) == gt - found
    # object frames are single scans: the report says the model read them with one sweep
    assert report['frames_by_input_sweeps'] == {'1': 2}
    assert any(n.startswith('2 of 2 frames read with fewer than 3 sweeps (2 with 1')
               for n in report['notes'])


def write_tracking(root, rng, frames=5):
    """Sequence 0000: the ego drives east and turns; car track 3 moves at 4 m/s east and 1 m/s
    north; pedestrian track 5 appears in one frame only."""
    R0, Tr = make_calib()
    Tr_imu = np.c_[Rotation.from_euler('z', 0.02).as_matrix(), [-0.81, 0.32, -0.8]]
    T_imu = np.eye(4)
    T_imu[:3] = Tr_imu
    lat0, lon0, alt = 49.0, 8.4, 110.0
    scale = np.cos(np.deg2rad(lat0))
    oxts, poses = [], []
    for k in range(frames):
        east, yaw = 1.2 * k, 0.3 + 0.05 * k
        lon = lon0 + np.rad2deg(east / (scale * 6378137.0))
        oxts.append(f'{lat0} {lon} {alt + 0.1 * k} 0.01 -0.02 {yaw} ' + ' '.join(['0'] * 24))
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler('ZYX', [yaw, -0.02, 0.01]).as_matrix()
        T[:3, 3] = [east, 0.0, 0.1 * k]
        poses.append(T @ np.linalg.inv(T_imu))
    T_cam = np.linalg.inv(velo_from_rect(R0, Tr))
    lines = []
    for k in range(frames):
        objects = [(3, 'Car', 1.5, 1.7, 4.2, np.array([10 + 0.4 * k, 3 + 0.1 * k, 0.8]))]
        if k == 2:
            objects.append((5, 'Pedestrian', 1.8, 0.6, 0.7, np.array([6.0, 8.0, 0.9])))
        for tid, kind, h, w, length, c_odom in objects:
            c_velo = to_velo(np.linalg.inv(poses[k]), c_odom[None])
            c_rect = to_velo(T_cam, c_velo)[0] + [0.0, h / 2, 0.0]
            lines.append(label_line(kind, h, w, length, c_rect, 0.2, prefix=f'{k} {tid} '))
        lines.append(f'{k} -1 DontCare -1 -1 -10 1 1 2 2 -1 -1 -1 -1000 -1000 -1000 -10')
        (root / 'velodyne/0000').mkdir(parents=True, exist_ok=True)
        xyz = rng.uniform(-30, 30, (200, 3))
        np.c_[xyz, rng.uniform(0, 1, 200)].astype(np.float32).tofile(
            root / f'velodyne/0000/{k:06d}.bin')
    for d in ('label_02', 'calib', 'oxts'):
        (root / d).mkdir(exist_ok=True)
    (root / 'label_02/0000.txt').write_text('\n'.join(lines) + '\n')
    (root / 'calib/0000.txt').write_text(calib_text(R0, Tr, tracking=True, Tr_imu=Tr_imu))
    (root / 'oxts/0000.txt').write_text('\n'.join(oxts) + '\n')
    return np.array(poses)


def test_tracking_layout_poses_and_velocities(tmp_path):
    poses = write_tracking(tmp_path / 'training', np.random.default_rng(4))
    seqs = KittiReader(tmp_path).sequences()
    assert len(seqs) == 1 and len(seqs[0]) == 5 and seqs[0].sequence_id == '0000'
    frames = list(seqs[0])
    for k, f in enumerate(frames):
        assert f.stamp_ns == k * 100_000_000 and f.gt is not None
        # odometry frame: origin at the first IMU position, axes east, north, up
        np.testing.assert_allclose(f.pose, poses[k], atol=1e-6)
        car = int(np.flatnonzero(f.instance_ids == 3)[0])
        v_lidar = poses[k][:3, :3].T @ np.array([4.0, 1.0, 0.0])
        np.testing.assert_allclose(f.gt.velocities[car], v_lidar[:2], atol=1e-3)
    ped = frames[2]
    assert ped.gt is not None and ped.instance_ids is not None
    assert sorted(ped.instance_ids.tolist()) == [3, 5]
    # seen in one frame only: its velocity is unknown
    assert np.isnan(ped.gt.velocities[ped.instance_ids.tolist().index(5)]).all()
    # training samples clips straight from the lazily read sequences
    clips = ClipSampler(kitti_sequences(tmp_path, fov_points_only=True), [3], 0).batch(2)
    assert [len(c) for c in clips] == [3, 3]
    assert all(c[1].stamp_ns - c[0].stamp_ns == 100_000_000 for c in clips)
    # oxts_poses on its own: translations from the Mercator projection
    calib = read_calib(tmp_path / 'training/calib/0000.txt')
    assert calib.Tr_imu_to_velo is not None
    direct = oxts_poses(tmp_path / 'training/oxts/0000.txt', calib.Tr_imu_to_velo)
    np.testing.assert_allclose(direct, np.stack([f.pose for f in frames]), atol=1e-12)


def test_malformed_inputs_say_what_is_wrong(tmp_path, object_root):
    with pytest.raises(DatasetError, match='velodyne/ label_2/ calib/'):
        KittiReader(tmp_path / 'nowhere')
    root = tmp_path / 'bad'
    write_object_frame(root, '000000', np.random.default_rng(2), *make_calib(), OBJECTS[:2])
    label = root / 'label_2/000000.txt'
    good = label.read_text()

    def fails(match, **kwargs):
        with pytest.raises(DatasetError, match=match):
            KittiReader(root, **kwargs).sequences()[0][0]

    label.write_text('Car 0.0 0 1.0 1 2 3\n')
    fails(r'000000.txt:1: 7 fields, expected 15')
    label.write_text(good.replace('Van', 'Bus'))
    fails(r"000000.txt:2: unknown object type 'Bus'")
    label.write_text(good.replace('1.50', 'tall'))
    fails(r'000000.txt:1: a field is not a number')
    label.write_text(good.replace('12.000000', 'nan'))
    fails('non-finite')
    label.unlink()
    fails('missing label file .*testing split has no labels')
    label.write_text(good)
    calib = root / 'calib/000000.txt'
    text = calib.read_text()
    calib.write_text('\n'.join(x for x in text.splitlines() if not x.startswith('Tr_velo')))
    fails('has no Tr_velo_to_cam or Tr_velo_cam line')
    calib.write_text(text.replace('R0_rect:', 'R0_rect: 1.0'))
    fails('R0_rect has 10 values, expected 9')
    calib.unlink()
    fails('missing calibration file')
    calib.write_text(text)
    scan = root / 'velodyne/000000.bin'
    pts = np.fromfile(scan, np.float32).reshape(-1, 4)
    np.r_[pts.ravel(), 1.0].astype(np.float32).tofile(scan)
    fails('not a multiple of 16')
    (pts * [1, 1, 1, 255]).astype(np.float32).tofile(scan)
    fails('reflectance up to .* intensity_scale=255')
    frame = KittiReader(root, intensity_scale=255.0).sequences()[0][0]
    assert 0.5 < frame.points[:, 3].max() <= 1.0
    with pytest.raises(DatasetError, match=r'no scan in .* \(first: 000009.bin\)'):
        KittiReader(root, ids=['000000', '000009']).sequences()
    scan.unlink()
    with pytest.raises(DatasetError, match='missing LiDAR file'):
        read_velodyne(scan)
    track = tmp_path / 'track'
    write_tracking(track, np.random.default_rng(5), frames=2)
    (track / 'oxts/0000.txt').unlink()
    with pytest.raises(DatasetError, match='needs oxts/'):
        KittiReader(track).sequences()


@pytest.mark.slow
def test_eval_cli_on_kitti_format(object_root, tmp_path, capsys):
    from suit_ros.cli import main
    assert main(['eval', '--kitti', str(object_root), '--json-out',
                 str(tmp_path / 'm.json')]) == 0
    out = capsys.readouterr().out
    assert 'mAP' in out
    summary = json.loads((tmp_path / 'm.json').read_text())['summary']
    assert summary['frames'] == 2 and 'camera field of view' in summary['scored_region']
    (tmp_path / 'val.txt').write_text('000001\n')
    assert main(['eval', '--kitti', str(object_root), '--kitti-ids', str(tmp_path / 'val.txt'),
                 '--json-out', str(tmp_path / 'v.json')]) == 0
    assert json.loads((tmp_path / 'v.json').read_text())['summary']['frames'] == 1
    assert main(['eval', '--kitti', str(tmp_path / 'missing')]) == 1
    err = capsys.readouterr().err
    assert 'suit-ros eval: error:' in err and 'does not exist' in err
    assert main(['eval', '--kitti', str(object_root), '--kitti-ids', 'nope.txt']) == 1
    assert 'cannot read --kitti-ids nope.txt' in capsys.readouterr().err
    assert main(['eval', '--kitti', str(object_root), '--tracker', '--json-out',
                 str(tmp_path / 'f.json')]) == 0
    assert json.loads((tmp_path / 'f.json').read_text())['summary']['frames'] == 2
    assert main(['eval', '--kitti', str(object_root), '--tracker',
                 '--history', '2']) == 1
    assert 'drop --history' in capsys.readouterr().err
