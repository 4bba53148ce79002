"""A synthetic drive recorded as a rosbag2 bag (what ``suit-ros simulate`` writes)."""
from __future__ import annotations

import collections
import os
import sys
from typing import Any

import numpy as np
from numpy.typing import NDArray

from suit_ros import CLASS_NAMES


def write_bag(path: str | os.PathLike[str], config: Any, seed: int, storage: str = 'mcap',
              progress: bool = False, densify: float = 1.0) -> dict[str, Any]:
    """Simulate and write ``/points``, ``/odom``, ``/gt/objects``, ``/tf_static``.

    Clouds are recorded at their stamp + one sweep period (when a driver would publish the
    finished sweep), odometry and GT at their stamps. :return: a summary.

    :param densify: > 1: each cloud gets that many times its points, jittered copies (3 cm)
        beside their originals so the scan order stays, as a denser sensor would publish (a
        64-beam drive x 2.3 has the size of a 128-beam one); for load tests, since the GT's
        ``num_points`` still count the original returns.
    """
    if not densify >= 1.0:
        raise ValueError(f'densify must be >= 1, not {densify}')
    dense_rng = np.random.default_rng([seed, 1])
    from tqdm import tqdm  # type: ignore[import-untyped]

    from suit_ros.data.bag import open_writer
    from suit_ros.data.sim.scene import Simulation
    from suit_ros.msg_adapters.classes import MessageClasses
    from suit_ros.msg_adapters.detections import detections_to_pointcloud2
    from suit_ros.msg_adapters.odometry import matrix_to_quaternion
    from suit_ros.msg_adapters.pointcloud2 import array_to_pointcloud2
    sim = Simulation(config, seed)
    period_ns = int(round(1e9 / config.lidar.rate_hz))
    points_per_frame = []
    objects: collections.Counter[str] = collections.Counter()
    with open_writer(path, storage) as bag:
        C = MessageClasses.from_rosbags(bag.store)
        t = bag.store.types
        T = sim.T_base_lidar
        q = matrix_to_quaternion(T[:3, :3])
        tf = t['geometry_msgs/msg/TransformStamped'](
            header=C.header(0, 'base_link'), child_frame_id='lidar',
            transform=t['geometry_msgs/msg/Transform'](
                translation=C.Vector3(x=T[0, 3], y=T[1, 3], z=T[2, 3]),
                rotation=C.Quaternion(x=q[0], y=q[1], z=q[2], w=q[3])))
        from suit_ros.data.sim.scene import START_NS
        bag.write('/tf_static', 'tf2_msgs/msg/TFMessage', START_NS - period_ns,
                  t['tf2_msgs/msg/TFMessage'](transforms=[tf]))
        Odom = t['nav_msgs/msg/Odometry']
        cov = np.zeros(36)
        bar = tqdm(range(config.frames), desc='simulate', unit='frame', disable=not progress,
                   file=sys.stderr)
        for k in bar:
            f = sim.render(k)
            for stamp, Tb, tw in f.odometry:
                qb = matrix_to_quaternion(Tb[:3, :3])
                msg = Odom(header=C.header(stamp, 'odom'), child_frame_id='base_link',
                           pose=t['geometry_msgs/msg/PoseWithCovariance'](
                               pose=C.Pose(position=C.Point(x=Tb[0, 3], y=Tb[1, 3], z=Tb[2, 3]),
                                           orientation=C.Quaternion(x=qb[0], y=qb[1], z=qb[2],
                                                                    w=qb[3])),
                               covariance=cov),
                           twist=t['geometry_msgs/msg/TwistWithCovariance'](
                               twist=t['geometry_msgs/msg/Twist'](
                                   linear=C.Vector3(x=tw[0], y=tw[1], z=0.0),
                                   angular=C.Vector3(x=0.0, y=0.0, z=tw[2])),
                               covariance=cov))
                bag.write('/odom', 'nav_msgs/msg/Odometry', stamp, msg)
            header = C.header(f.stamp_ns, 'lidar')
            cloud = f.cloud if densify == 1.0 else densified(f.cloud, densify, dense_rng)
            bag.write('/points', 'sensor_msgs/msg/PointCloud2', f.stamp_ns + period_ns,
                      array_to_pointcloud2(cloud, header, C, is_dense=True))
            gt = f.gt
            bag.write('/gt/objects', 'sensor_msgs/msg/PointCloud2', f.stamp_ns + period_ns,
                      detections_to_pointcloud2(gt.boxes, gt.velocities, gt.scores, gt.labels,
                                                header, C, {'num_points': f.num_points,
                                                            'instance_id': f.instance_ids}))
            points_per_frame.append(len(cloud))
            seen = f.num_points > 0
            objects.update(CLASS_NAMES[int(lab)] for lab in gt.labels[seen])
    n = config.frames
    return {'frames': n, 'points_per_frame_mean': float(np.mean(points_per_frame)),
            'objects_per_frame': {c: objects[c] / n for c in CLASS_NAMES}}


def densified(cloud: NDArray[Any], factor: float, rng: np.random.Generator) -> NDArray[Any]:
    """``factor`` x the points of a cloud: every original point, and ``factor - 1`` x as many
    copies of points drawn at random, each jittered by 3 cm in x, y and z and placed right
    after its original (scan order kept, as a denser sensor publishes). ``cloud``: a
    structured array with x, y, z fields, or ``(N, >= 3)`` with x, y, z first."""
    n = len(cloud)
    extra = rng.integers(0, n, max(int(n * factor) - n, 0))
    idx = np.r_[np.arange(n), extra]
    order = np.argsort(idx, kind='stable')          # originals first within each point
    out: NDArray[Any] = cloud[idx[order]].copy()
    copy = order >= n
    jitter = rng.normal(0, 0.03, (int(copy.sum()), 3))
    if out.dtype.names:
        for i, k in enumerate(('x', 'y', 'z')):
            out[k][copy] += jitter[:, i].astype(out.dtype[k])
    else:
        out[copy, :3] += jitter.astype(out.dtype)
    return out
