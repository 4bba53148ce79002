"""The frame generator: the world, the ego drive and the actors rendered into LiDAR sweeps.

The cloud of frame ``k`` is stamped at its sweep start ``t_k = k / rate``; GT boxes are at that
instant. With ``motion_distortion`` off (default) the whole sweep is cast at ``t_k``; with it on,
the sweep is cast in 10 azimuth sectors, each from the ego and actor poses at its firing time
and expressed in the LiDAR frame of that time (what a real driver reports).
"""
from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from suit_ros.data.sim.actors import Actor, make_actors, make_ego
from suit_ros.data.sim.config import SimConfig
from suit_ros.data.sim.lidar import GROUND, RangeImage, cast, ray_directions
from suit_ros.data.sim.world import REFLECTIVITY, build_world
from suit_ros.ops.geometry import pose_from_xyz_rpy, se3_inverse, transform_boxes
from suit_ros.structures import Detections, Frame

START_NS = 1_700_000_000 * 10**9          # a fixed epoch: same seed, same stamps
POINT_DTYPE = np.dtype({'names': ['x', 'y', 'z', 'intensity', 'time', 'ring'],
                        'formats': ['<f4', '<f4', '<f4', '<f4', '<f4', '<u2'],
                        'offsets': [0, 4, 8, 12, 16, 20], 'itemsize': 24})
SECTORS = 10


@dataclass
class SimFrame:
    """One LiDAR frame of a simulated drive, with everything a bag or a test needs."""

    index: int
    stamp_ns: int
    cloud: NDArray[np.void]                 # (N,) POINT_DTYPE, LiDAR frame
    T_odom_base: NDArray[np.float64]        # (4, 4) at stamp
    T_base_lidar: NDArray[np.float64]       # (4, 4)
    gt: Detections                          # LiDAR frame, absolute velocities
    num_points: NDArray[np.uint32]
    instance_ids: NDArray[np.uint32]
    surface: NDArray[np.int64]              # per point: -1 ground, else box id (see boxes)
    boxes_world: NDArray[np.float64]        # (S + A, 7) the boxes ``surface`` indexes
    odometry: list[tuple[int, NDArray[np.float64], NDArray[np.float64]]] = field(
        default_factory=list)               # (stamp_ns, T_odom_base, twist [vx, vy, wz])

    @property
    def T_odom_lidar(self) -> NDArray[np.float64]:  # noqa: N802 - ROS naming T_a_b
        """The LiDAR's pose at the stamp."""
        return self.T_odom_base @ self.T_base_lidar


def base_pose(ego: Actor, t: float) -> NDArray[np.float64]:
    """``T_odom_base`` of the ego at time ``t``."""
    x, y, yaw, _, _ = ego.state(t)
    return pose_from_xyz_rpy((x, y, 0.0), (0.0, 0.0, yaw))


def ego_twist(ego: Actor, t: float, h: float = 0.01) -> NDArray[np.float64]:
    """Body twist ``[vx, vy, wz]`` in base_link at ``t`` (central difference of the yaw)."""
    x, y, yaw, vx, vy = ego.state(t)
    yaw_a, yaw_b = ego.state(max(t - h, 0.0))[2], ego.state(t + h)[2]
    wz = float(np.angle(np.exp(1j * (yaw_b - yaw_a)))) / (t + h - max(t - h, 0.0))
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([c * vx + s * vy, -s * vx + c * vy, wz])


class Simulation:
    """A seeded drive: build once, render frames on demand."""

    def __init__(self, cfg: SimConfig, seed: int) -> None:
        self.cfg = cfg.validate()
        self.seed = seed
        rng = np.random.default_rng([seed, 0x5017])
        self.duration = cfg.frames / cfg.lidar.rate_hz + 1.0
        self.world = build_world(cfg, rng)
        self.ego = make_ego(self.world, cfg, rng, self.duration)
        self.actors = make_actors(self.world, cfg, rng, self.duration, self.ego)
        self.noise_rng = np.random.default_rng([seed, 0xA11D])
        self.dirs = ray_directions(cfg.lidar)
        self.T_base_lidar = pose_from_xyz_rpy(cfg.lidar.extrinsic_xyz, cfg.lidar.extrinsic_rpy)
        self.static_materials = self.world.materials

    def actor_boxes(self, t: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """World boxes ``(A, 7)`` and velocities ``(A, 2)`` of every actor at ``t``."""
        out = [a.box(t) for a in self.actors]
        return np.array([b for b, _ in out]), np.array([v for _, v in out])

    def render(self, k: int) -> SimFrame:
        """Render frame ``k``."""
        lc = self.cfg.lidar
        period = 1.0 / lc.rate_hz
        t = k * period
        B, C = self.dirs.shape[:2]
        image = RangeImage(np.full((B, C), np.inf), np.full((B, C), -2, np.int64),
                           np.zeros((B, C)))
        S = len(self.world.boxes)
        sectors = SECTORS if lc.motion_distortion else 1
        bounds = np.linspace(0, C, sectors + 1).astype(int)
        T_world_lidar_sector = []
        for j in range(sectors):
            tj = t + (bounds[j] + bounds[j + 1]) / 2 / C * period if sectors > 1 else t
            T_wl = base_pose(self.ego, tj) @ self.T_base_lidar
            T_world_lidar_sector.append(T_wl)
            origin = T_wl[:3, 3]
            near = np.hypot(*(self.world.boxes[:, :2] - origin[:2]).T) < lc.max_range + 30
            actor_boxes, _ = self.actor_boxes(tj)
            boxes = np.concatenate([self.world.boxes, actor_boxes])
            cand = np.concatenate([near, np.hypot(*(actor_boxes[:, :2] - origin[:2]).T)
                                   < lc.max_range + 15])
            idx = np.nonzero(cand)[0]
            sub = RangeImage(image.rng[:, bounds[j]:bounds[j + 1]].copy(),
                             np.full((B, bounds[j + 1] - bounds[j]), -2, np.int64),
                             np.zeros((B, bounds[j + 1] - bounds[j])))
            cast(self.dirs[:, bounds[j]:bounds[j + 1]], origin, T_wl[:3, :3], boxes[idx],
                 slice(None), lc.max_range, sub)
            hit = np.where(sub.hit >= 0, idx[np.clip(sub.hit, 0, None)], sub.hit)
            image.rng[:, bounds[j]:bounds[j + 1]] = sub.rng
            image.hit[:, bounds[j]:bounds[j + 1]] = hit
            image.cos[:, bounds[j]:bounds[j + 1]] = sub.cos
        # returns: range limits, dropout, noise; points in column (firing) order
        rng = self.noise_rng
        valid = np.isfinite(image.rng) & (image.rng >= lc.min_range) & (image.rng <= lc.max_range)
        valid &= rng.random(image.rng.shape) >= lc.dropout
        r = image.rng + rng.normal(0.0, lc.range_noise, image.rng.shape)
        order_b, order_c = np.nonzero(valid.T)[::-1]          # column-major: c outer, b inner
        rr = r[order_b, order_c]
        xyz = self.dirs[order_b, order_c] * rr[:, None]
        surface = image.hit[order_b, order_c]
        actor_mat = np.array([a.material for a in self.actors], np.int64)
        mat = np.where(surface == GROUND, 0,
                       np.where(surface < S, self.static_materials[np.clip(surface, 0, S - 1)],
                                actor_mat[np.clip(surface - S, 0, len(self.actors) - 1)]))
        refl = REFLECTIVITY[mat]
        inten = refl * (0.3 + 0.7 * image.cos[order_b, order_c]) * lc.intensity_max
        inten *= np.exp(-rr / 400.0) * (1.0 + rng.normal(0.0, 0.05, len(rr)))
        cloud = np.zeros(len(rr), POINT_DTYPE)
        cloud['x'], cloud['y'], cloud['z'] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
        cloud['intensity'] = np.clip(inten, 0, lc.intensity_max)
        cloud['ring'] = order_b
        cloud['time'] = order_c / C * period
        # ground truth at the stamp, in the LiDAR frame
        T_ob = base_pose(self.ego, t)
        T_ol = T_ob @ self.T_base_lidar
        actor_boxes, actor_vel = self.actor_boxes(t)
        T_lo = se3_inverse(T_ol)
        boxes_l, vel_l = transform_boxes(T_lo, actor_boxes, actor_vel)
        assert vel_l is not None
        origin = T_ol[:3, 3]
        rel = actor_boxes[:, :2] - origin[:2]
        dist = np.hypot(rel[:, 0], rel[:, 1])
        cs, sn = np.cos(actor_boxes[:, 6]), np.sin(actor_boxes[:, 6])
        sensor_inside = ((np.abs(rel[:, 0] * cs + rel[:, 1] * sn) < actor_boxes[:, 3] / 2)
                         & (np.abs(-rel[:, 0] * sn + rel[:, 1] * cs) < actor_boxes[:, 4] / 2))
        keep = (dist <= lc.max_range) & ~sensor_inside
        boxes_l, vel_l = boxes_l[keep], vel_l[keep]
        labels = np.array([a.label for a in self.actors], np.int64)[keep]
        ids = np.array([a.instance_id for a in self.actors], np.uint32)[keep]
        num = count_points_in_boxes(xyz, boxes_l)
        gt = Detections(boxes_l, vel_l, np.ones(len(boxes_l), np.float32), labels)
        odometry = []
        odom_period = 1.0 / self.cfg.odom_rate_hz
        first = -1.0 * period if k == 0 else t
        n0 = int(np.ceil(first / odom_period - 1e-9))
        n1 = int(np.ceil((t + period) / odom_period - 1e-9))
        for n in range(n0, n1):
            ts = max(n * odom_period, -period)
            T = base_pose(self.ego, max(ts, 0.0))
            if ts < 0:   # before the drive starts the ego stands still at its start pose
                tw = np.zeros(3)
            else:
                tw = ego_twist(self.ego, ts)
            if self.cfg.odom_noise > 0:
                T = T @ pose_from_xyz_rpy(rng.normal(0, self.cfg.odom_noise, 3) * [1, 1, 0],
                                          (0, 0, rng.normal(0, self.cfg.odom_noise)))
            odometry.append((START_NS + int(round(ts * 1e9)), T, tw))
        return SimFrame(k, START_NS + int(round(t * 1e9)), cloud, T_ob, self.T_base_lidar, gt,
                        num, ids, surface, np.concatenate([self.world.boxes, actor_boxes]),
                        odometry)


def points_in_boxes(xyz: NDArray[np.floating], boxes: NDArray[np.floating]) -> NDArray[np.bool_]:
    """``(N, M)`` membership of points in ``(M, 7)`` yaw-rotated boxes (closed intervals)."""
    if len(boxes) == 0:
        return np.zeros((len(xyz), 0), bool)
    d = np.asarray(xyz, np.float64)[:, None, :] - np.asarray(boxes, np.float64)[None, :, :3]
    c, s = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    along = d[..., 0] * c + d[..., 1] * s
    across = -d[..., 0] * s + d[..., 1] * c
    return ((np.abs(along) <= boxes[:, 3] / 2) & (np.abs(across) <= boxes[:, 4] / 2)
            & (np.abs(d[..., 2]) <= boxes[:, 5] / 2))


def count_points_in_boxes(xyz: NDArray[np.floating], boxes: NDArray[np.floating]
                          ) -> NDArray[np.uint32]:
    """Number of points inside each ``(M, 7)`` box (same rule as :func:`points_in_boxes`),
    testing only the points within each box's bounding square."""
    xyz = np.asarray(xyz, np.float64)
    out = np.zeros(len(boxes), np.uint32)
    if len(xyz) == 0:
        return out
    order = np.argsort(xyz[:, 0], kind='stable')
    xs = xyz[order, 0]
    for i, box in enumerate(np.asarray(boxes, np.float64)):
        r = 0.5 * np.hypot(box[3], box[4])
        lo, hi = np.searchsorted(xs, [box[0] - r, box[0] + r])
        cand = xyz[order[lo:hi]]
        cand = cand[np.abs(cand[:, 1] - box[1]) <= r]
        out[i] = points_in_boxes(cand, box[None]).sum()
    return out


def simulate(cfg: SimConfig, seed: int) -> Iterator[SimFrame]:
    """Yield the frames of a seeded drive in order."""
    sim = Simulation(cfg, seed)
    for k in range(cfg.frames):
        yield sim.render(k)


def to_frame(f: SimFrame, seed: int, intensity_max: float = 255.0) -> Frame:
    """A SimFrame as a sensor Frame (LiDAR frame, intensity scaled to 0..1, time lag 0)."""
    c = f.cloud
    pts = np.stack([c['x'], c['y'], c['z'], c['intensity'] / intensity_max,
                    np.zeros(len(c), np.float32)], 1).astype(np.float32)
    return Frame(pts, f.T_odom_lidar, f.stamp_ns, 'lidar', f.gt, f.num_points, f.instance_ids,
                 f'sim-{seed}', f.T_base_lidar.copy())


def sim_frames(cfg: SimConfig, seed: int) -> Iterator[Frame]:
    """Yield the sensor frames of a seeded drive."""
    for f in simulate(cfg, seed):
        yield to_frame(f, seed, cfg.lidar.intensity_max)
