"""The frame generator: the world, the ego drive and the actors rendered into LiDAR sweeps.

The cloud of frame ``k`` is stamped at its sweep start ``t_k = k / rate``; GT boxes are at that
instant. With ``motion_distortion`` off (default) the whole sweep is cast at ``t_k``; with it on,
the sweep is cast in 10 azimuth sectors, each from the ego and actor poses at its firing time
and expressed in the LiDAR frame of that time (what a real driver reports).
"""
from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from suit_ros.data.sim.actors import Actor, Trajectories, dress_actors, make_actors, make_ego
from suit_ros.data.sim.bodies import ego_body
from suit_ros.data.sim.bystanders import place_at_fronts, place_bystanders
from suit_ros.data.sim.clutter import CLUTTER_ID, StaticScene, furnish
from suit_ros.data.sim.config import Realism, SimConfig
from suit_ros.data.sim.lidar import GROUND, Porosity, RangeImage, cast, ray_directions
from suit_ros.data.sim.parked_rows import park_rows
from suit_ros.data.sim.world import REFLECTIVITY, build_world
from suit_ros.ops.geometry import (  # noqa: F401 - points_in_boxes: re-exported
    count_points_in_boxes,
    points_in_boxes,
    pose_from_xyz_rpy,
    se3_inverse,
    transform_boxes,
)
from suit_ros.structures import Detections, Frame, object_returns

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
    # detailed world only (empty in the box world): clutter footprints (K, 7) in the LiDAR
    # frame, their types (ids into clutter.CLUTTER_TYPES)
    clutter_boxes: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 7)))
    clutter_types: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    surface_instance: NDArray[np.uint32] | None = None     # per point its actor (0: none)

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


@dataclass
class _Surfaces:
    """The detailed world's surfaces: static parts, then the ego's parts, then every actor's
    parts, with what a LiDAR sees of each ``(N,)``."""

    static: NDArray[np.float64]              # (S, 7) world
    ego: NDArray[np.float64]                 # (E, 7) base_link
    actor_parts: NDArray[np.float64]         # (P, 7) in their actor's frame
    actor_owner: NDArray[np.int64]           # (P,) actor index
    swing: NDArray[np.float64]               # (P,) walking swing amplitude (m)
    stride: NDArray[np.float64]              # (P,) metres per swing cycle
    reflectivity: NDArray[np.float64]
    return_prob: NDArray[np.float64]
    porosity: NDArray[np.float64]
    instance: NDArray[np.uint32]             # actor instance id per surface (0: not an actor)


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
        self.scene: StaticScene | None = None
        self.surfaces: _Surfaces | None = None
        self.trajectories: Trajectories | None = None
        if cfg.realism is not None:
            self._build_detailed(cfg.realism)

    def _build_detailed(self, realism: Realism) -> None:
        """Dress the actors, furnish the streets and lay out the surface table."""
        rng = np.random.default_rng([self.seed, 0xDE7A])
        dress_actors(self.actors, realism, rng)
        self.scene = furnish(self.world, self.cfg, realism, rng)
        taken = place_bystanders(self.actors, self.scene, self.world, realism.bystanders,
                                 np.random.default_rng([self.seed, 0xB757]))
        place_at_fronts(self.actors, self.scene, self.world, realism.at_fronts,
                        np.random.default_rng([self.seed, 0xF407]), taken)
        self.actors += park_rows(self.actors, self.ego, self.world, realism,
                                 np.random.default_rng([self.seed, 0x9A2C]))
        self.trajectories = Trajectories.sample(self.actors)
        ego = ego_body(self.ego.size) if realism.ego_body else None
        bodies = [a.body for a in self.actors if a.body is not None]
        if len(bodies) != len(self.actors):
            raise RuntimeError('every actor of the detailed world needs a body (dress_actors)')
        empty = np.zeros((0, 7))
        looks = [(self.scene.reflectivity, self.scene.return_prob, self.scene.porosity)]
        if ego is not None:
            looks.append((ego.reflectivity, ego.return_prob, ego.porosity))
        looks += [(b.reflectivity, b.return_prob, b.porosity) for b in bodies]
        counts = [len(b.parts) for b in bodies]
        owner = np.repeat(np.arange(len(bodies)), counts)
        n_fixed = len(self.scene.parts) + (0 if ego is None else len(ego.parts))
        self.surfaces = _Surfaces(
            self.scene.parts, empty if ego is None else ego.parts,
            np.concatenate([b.parts for b in bodies]) if bodies else empty, owner,
            np.concatenate([b.swing for b in bodies]) if bodies else np.zeros(0),
            np.repeat([b.stride for b in bodies], counts),
            np.concatenate([look[0] for look in looks]),
            np.concatenate([look[1] for look in looks]),
            np.concatenate([look[2] for look in looks]),
            np.concatenate([np.zeros(n_fixed, np.uint32),
                            np.array([a.instance_id for a in self.actors], np.uint32)[owner]]))

    def actor_boxes(self, t: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """World boxes ``(A, 7)`` and velocities ``(A, 2)`` of every actor at ``t``."""
        if self.trajectories is not None:
            x, y, yaw, vx, vy, _ = self.trajectories.at(t)
            size = np.array([a.size for a in self.actors]).reshape(-1, 3)
            return (np.stack([x, y, size[:, 2] / 2, size[:, 0], size[:, 1], size[:, 2], yaw], 1),
                    np.stack([vx, vy], 1))
        out = [a.box(t) for a in self.actors]
        return (np.array([b for b, _ in out]).reshape(-1, 7),
                np.array([v for _, v in out]).reshape(-1, 2))

    def render(self, k: int) -> SimFrame:
        """Render frame ``k``: cast the sweep, turn hits into returns, label them."""
        period = 1.0 / self.cfg.lidar.rate_hz
        t = k * period
        image = self._cast_sweep(t, k)
        cloud, xyz, surface = self._returns(image, k)
        T_ob = base_pose(self.ego, t)
        T_ol = T_ob @ self.T_base_lidar
        actor_boxes, actor_vel = self.actor_boxes(t)
        owner = self._owners(surface)
        gt, num, ids = self._ground_truth(T_ol, actor_boxes, actor_vel, xyz, owner)
        frame = SimFrame(k, START_NS + int(round(t * 1e9)), cloud, T_ob, self.T_base_lidar, gt,
                         num, ids, surface, self._surface_boxes(t, actor_boxes),
                         self._odometry(k), surface_instance=owner)
        if self.surfaces is not None:
            frame.clutter_boxes, frame.clutter_types = self._clutter(T_ol)
        return frame

    def _owners(self, surface: NDArray[np.int64]) -> NDArray[np.uint32]:
        """Per return the actor (instance id) whose surface it is on, 0 for none."""
        if self.surfaces is not None:
            owner = np.where(surface >= 0, self.surfaces.instance[surface.clip(0)], 0)
        else:
            S = len(self.world.boxes)
            actor_ids = np.array([a.instance_id for a in self.actors] or [0], np.int64)
            owner = np.where(surface >= S, actor_ids[(surface - S).clip(0, len(actor_ids) - 1)],
                             0)
        return np.asarray(owner, np.uint32)

    # ------------------------------------------------------------------ casting
    def _cast_sweep(self, t: float, k: int) -> RangeImage:
        """The range image of the sweep starting at ``t``: one cast, or with motion distortion
        one per azimuth sector from the poses at its firing time."""
        lc = self.cfg.lidar
        period = 1.0 / lc.rate_hz
        B, C = self.dirs.shape[:2]
        image = RangeImage(np.full((B, C), np.inf), np.full((B, C), -2, np.int64),
                           np.zeros((B, C)))
        sectors = SECTORS if lc.motion_distortion else 1
        bounds = np.linspace(0, C, sectors + 1).astype(int)
        ray_u = None
        if self.surfaces is not None:
            ray_u = np.random.default_rng([self.seed, 0x9A55, k]).random((B, C))
        for j in range(sectors):
            c0, c1 = int(bounds[j]), int(bounds[j + 1])
            tj = t + (c0 + c1) / 2 / C * period if sectors > 1 else t
            T_wl = base_pose(self.ego, tj) @ self.T_base_lidar
            boxes, idx, porosity = self._sector_surfaces(tj, T_wl[:3, 3])
            sub = RangeImage(image.rng[:, c0:c1].copy(), np.full((B, c1 - c0), -2, np.int64),
                             np.zeros((B, c1 - c0)))
            exact = self.cfg.exact_sector_columns
            cast(self.dirs[:, c0:c1], T_wl[:3, 3], T_wl[:3, :3], boxes, slice(None),
                 lc.max_range, sub, first_column=c0 if exact else 0,
                 sweep_columns=C if exact else None,
                 porosity=None if porosity is None or ray_u is None
                 else Porosity(porosity, ray_u[:, c0:c1]))
            image.rng[:, c0:c1] = sub.rng
            image.hit[:, c0:c1] = np.where(sub.hit >= 0, idx[np.clip(sub.hit, 0, None)], sub.hit)
            image.cos[:, c0:c1] = sub.cos
        return image

    def _sector_surfaces(self, t: float, origin: NDArray[np.float64]
                         ) -> tuple[NDArray[np.float64], NDArray[np.int64],
                                    NDArray[np.float64] | None]:
        """Boxes near ``origin`` at time ``t``, their surface ids and (detailed world) their
        porosity."""
        reach = self.cfg.lidar.max_range
        if self.surfaces is None:
            near = np.hypot(*(self.world.boxes[:, :2] - origin[:2]).T) < reach + 30
            actor_boxes, _ = self.actor_boxes(t)
            boxes = np.concatenate([self.world.boxes, actor_boxes])
            cand = np.concatenate([near, np.hypot(*(actor_boxes[:, :2] - origin[:2]).T)
                                   < reach + 15])
            idx = np.nonzero(cand)[0]
            return boxes[idx], idx, None
        boxes = self._surface_boxes(t)
        extent = 0.5 * np.hypot(boxes[:, 3], boxes[:, 4])
        idx = np.nonzero(np.hypot(*(boxes[:, :2] - origin[:2]).T) - extent < reach)[0]
        return boxes[idx], idx, self.surfaces.porosity[idx]

    def _surface_boxes(self, t: float, actor_boxes: NDArray[np.float64] | None = None
                       ) -> NDArray[np.float64]:
        """World boxes of every surface at ``t`` (what ``SimFrame.surface`` indexes)."""
        if self.surfaces is None or self.trajectories is None:
            assert actor_boxes is not None
            return np.concatenate([self.world.boxes, actor_boxes])
        sf = self.surfaces
        x, y, yaw, _, _, travelled = self.trajectories.at(t)
        o = sf.actor_owner
        local = sf.actor_parts
        lx = local[:, 0] + sf.swing * np.sin(2 * np.pi * travelled[o] / sf.stride)
        parts = _place_boxes(local, lx, x[o], y[o], yaw[o])
        T = base_pose(self.ego, t)
        ego = _place_boxes(sf.ego, sf.ego[:, 0], np.full(len(sf.ego), T[0, 3]),
                           np.full(len(sf.ego), T[1, 3]),
                           np.full(len(sf.ego), np.arctan2(T[1, 0], T[0, 0])))
        return np.concatenate([sf.static, ego, parts])

    # ------------------------------------------------------------------ returns and labels
    def _returns(self, image: RangeImage, k: int
                 ) -> tuple[NDArray[np.void], NDArray[np.float64], NDArray[np.int64]]:
        """Points from the range image: range limits, dropout, noise, intensity; in column
        (firing) order. Returns the cloud, its xyz and each point's surface id."""
        lc = self.cfg.lidar
        C = self.dirs.shape[1]
        rng = self.noise_rng
        valid = np.isfinite(image.rng) & (image.rng >= lc.min_range) & (image.rng <= lc.max_range)
        valid &= rng.random(image.rng.shape) >= lc.dropout
        if self.surfaces is not None:       # glass, dark paint, tyres: hits without a return
            kept = np.random.default_rng([self.seed, 0x7E7, k]).random(image.rng.shape)
            valid &= (image.hit < 0) | (kept < self.surfaces.return_prob[image.hit.clip(0)])
        r = image.rng + rng.normal(0.0, lc.range_noise, image.rng.shape)
        order_b, order_c = np.nonzero(valid.T)[::-1]          # column-major: c outer, b inner
        rr = r[order_b, order_c]
        xyz = self.dirs[order_b, order_c] * rr[:, None]
        surface = image.hit[order_b, order_c]
        refl = self._reflectivity(surface)
        inten = refl * (0.3 + 0.7 * image.cos[order_b, order_c]) * lc.intensity_max
        inten *= np.exp(-rr / 400.0) * (1.0 + rng.normal(0.0, 0.05, len(rr)))
        cloud = np.zeros(len(rr), POINT_DTYPE)
        cloud['x'], cloud['y'], cloud['z'] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
        cloud['intensity'] = np.clip(inten, 0, lc.intensity_max)
        cloud['ring'] = order_b
        # each return's firing time after the stamp; a sweep cast at one instant has none
        cloud['time'] = order_c / C * (1.0 / lc.rate_hz) if lc.motion_distortion else 0.0
        return cloud, xyz, surface

    def _reflectivity(self, surface: NDArray[np.int64]) -> NDArray[np.float64]:
        """Reflectivity (0..1) of each point's surface."""
        if self.surfaces is not None:
            return np.where(surface == GROUND, REFLECTIVITY[0],
                            self.surfaces.reflectivity[surface.clip(0)])
        S = len(self.world.boxes)
        actor_mat = np.array([a.material for a in self.actors] or [0], np.int64)
        mat = np.where(surface == GROUND, 0,
                       np.where(surface < S, self.static_materials[np.clip(surface, 0, S - 1)],
                                actor_mat[np.clip(surface - S, 0, len(actor_mat) - 1)]))
        out: NDArray[np.float64] = REFLECTIVITY[mat]
        return out

    def _ground_truth(self, T_ol: NDArray[np.float64], actor_boxes: NDArray[np.float64],
                      actor_vel: NDArray[np.float64], xyz: NDArray[np.float64],
                      owner: NDArray[np.uint32]
                      ) -> tuple[Detections, NDArray[np.uint32], NDArray[np.uint32]]:
        """GT in the LiDAR frame (actors within range, not the one the sensor sits in), the
        number of returns of each object and the instance ids.

        An object's returns are those in its box at the stamp, or its own (the returns cast
        on it, ``owner``) where there are more (:func:`~suit_ros.structures.object_returns`):
        a visible object counted 0 was trained as background and left unscored."""
        lc = self.cfg.lidar
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
        num = object_returns(xyz, boxes_l, owner, ids)
        gt = Detections(boxes_l, vel_l, np.ones(len(boxes_l), np.float32), labels)
        return gt, num, ids

    def _clutter(self, T_ol: NDArray[np.float64]
                 ) -> tuple[NDArray[np.floating[Any]], NDArray[np.int64]]:
        """Clutter objects within range, LiDAR frame, with their types; the ego's body last."""
        assert self.scene is not None and self.cfg.realism is not None
        objects, types = self.scene.objects, self.scene.types
        near = np.hypot(*(objects[:, :2] - T_ol[:2, 3]).T) <= self.cfg.lidar.max_range
        boxes, _ = transform_boxes(se3_inverse(T_ol), objects[near])
        types = types[near]
        if self.cfg.realism.ego_body:
            size = self.ego.size
            ego_box = np.array([[0.0, 0.0, size[2] / 2, *size, 0.0]])
            ego_l, _ = transform_boxes(se3_inverse(self.T_base_lidar), ego_box)
            boxes = np.concatenate([boxes, ego_l])
            types = np.append(types, CLUTTER_ID['ego_body'])
        return boxes, np.asarray(types, np.int64)

    def _odometry(self, k: int) -> list[tuple[int, NDArray[np.float64], NDArray[np.float64]]]:
        """Odometry messages from the previous sweep's stamp (exclusive) to this one's end."""
        period = 1.0 / self.cfg.lidar.rate_hz
        t = k * period
        rng = self.noise_rng
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
        return odometry


def _place_boxes(local: NDArray[np.float64], lx: NDArray[np.float64], x: NDArray[np.float64],
                 y: NDArray[np.float64], yaw: NDArray[np.float64]) -> NDArray[np.float64]:
    """Boxes ``(P, 7)`` given in their owner's frame (x replaced by ``lx``) placed in the world
    at the owners' ``x, y, yaw`` ``(P,)``."""
    c, s = np.cos(yaw), np.sin(yaw)
    out = local.copy()
    out[:, 0] = x + c * lx - s * local[:, 1]
    out[:, 1] = y + s * lx + c * local[:, 1]
    out[:, 6] = yaw + local[:, 6]
    return out


def simulate(cfg: SimConfig, seed: int) -> Iterator[SimFrame]:
    """Yield the frames of a seeded drive in order."""
    sim = Simulation(cfg, seed)
    for k in range(cfg.frames):
        yield sim.render(k)


def to_frame(f: SimFrame, seed: int, intensity_max: float = 255.0) -> Frame:
    """A SimFrame as a sensor Frame (LiDAR frame, intensity scaled to 0..1, time lag 0; the
    returns' firing times when the sweep was cast over time)."""
    c = f.cloud
    pts = np.stack([c['x'], c['y'], c['z'], c['intensity'] / intensity_max,
                    np.zeros(len(c), np.float32)], 1).astype(np.float32)
    times = None if len(c) and not c['time'].any() else np.array(c['time'], np.float32)
    return Frame(pts, f.T_odom_lidar, f.stamp_ns, 'lidar', f.gt, f.num_points, f.instance_ids,
                 f'sim-{seed}', f.T_base_lidar.copy(), times=times,
                 owners=None if f.surface_instance is None else f.surface_instance.copy())


def sim_frames(cfg: SimConfig, seed: int) -> Iterator[Frame]:
    """Yield the sensor frames of a seeded drive."""
    for f in simulate(cfg, seed):
        yield to_frame(f, seed, cfg.lidar.intensity_max)
