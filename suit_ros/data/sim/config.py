"""Configuration of the synthetic world and its LiDAR (dataclasses and named presets)."""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from suit_ros.errors import ConfigError


@dataclass(frozen=True)
class LidarConfig:
    """A spinning multi-beam LiDAR.

    :param beams: 16, 32, 64 or 128 evenly spread over ``fov_down..fov_up`` degrees, unless
        ``elevations`` lists the beam angles explicitly (degrees).
    :param extrinsic_xyz: LiDAR position in base_link (m); ``extrinsic_rpy``: its orientation.
    """

    beams: int = 32
    fov_down: float = -30.0
    fov_up: float = 10.0
    elevations: tuple[float, ...] | None = None
    azimuth_resolution: float = 0.2       # degrees
    rate_hz: float = 10.0
    max_range: float = 100.0
    min_range: float = 1.0
    range_noise: float = 0.02             # m, 1 sigma
    dropout: float = 0.05                 # probability a return is lost
    motion_distortion: bool = False       # cast each column from the pose at its firing time
    extrinsic_xyz: tuple[float, float, float] = (0.9, 0.0, 1.8)
    extrinsic_rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)
    intensity_max: float = 255.0          # the sensor's intensity convention: 0..intensity_max

    def beam_elevations(self) -> NDArray[np.float64]:
        """Beam elevation angles in radians, ascending; ring ``i`` is ``elevations[i]``."""
        if self.elevations is not None:
            degrees = np.sort(np.asarray(self.elevations, np.float64))
        else:
            degrees = np.linspace(self.fov_down, self.fov_up, self.beams)
        out: NDArray[np.float64] = np.radians(degrees)
        return out

    @property
    def columns(self) -> int:
        """Azimuth columns per sweep."""
        return int(round(360.0 / self.azimuth_resolution))


@dataclass(frozen=True)
class Realism:
    """The detailed world: actors built from parts, street clutter as negatives, ego returns.

    :param clutter: density of street furniture (hedges, fences, guardrails, bicycles, benches,
        bollards, signs, cones, barriers, curbs, verges) relative to the preset's; 0: none.
    :param glass_porosity: probability that a ray passes through vehicle glass.
    :param glass_return: probability that a ray stopped by glass gives a return.
    :param dark_paint: fraction of vehicles with dark paint (low reflectivity, fewer returns).
    :param hedge_porosity: range of the pass-through probability of hedges, bushes, canopies.
    :param ego_body: cast the ego vehicle's own body (hood, roof, mirrors) near the sensor.
    :param street_objects: density of the pedestrian-sized street objects that real sweeps
        are full of and the detector took for pedestrians (trash cans, hydrants, parking
        meters, utility boxes, planters, slim street trees and lamp posts, facade columns,
        bus shelters), relative to one per 8 m of sidewalk; 0 (default): none, and the world is
        byte for byte the one before they existed.
    :param real_car_ends: fraction of passenger cars whose ends are shaped as real cars' are
        (a set-back body over a dark bumper, seats behind the glass:
        :func:`~suit_ros.data.sim.bodies.car_body`), drawn from each car's id so that the
        rest of the world is unchanged; 0 (default): none, the world byte for byte as before.
    :param bystanders: share of pedestrians (drawn from their ids) that stand beside a street
        object or a parked vehicle near their start, as real ones wait at a post, a meter or
        a car door (:mod:`~suit_ros.data.sim.bystanders`); 0 (default): none, the world byte
        for byte as before.
    :param dark_tops: share of passenger cars (drawn from their ids) seen only below the belt:
        glass that returns nothing, a roof that returns one hit in six, dim seats behind the
        glass (:func:`~suit_ros.data.sim.bodies.car_body`); 0 (default): none, the world byte
        for byte as before.
    :param parked_rows: about the share of the kerbs near the ego's path lined with rows of
        parked cars, as city streets are (:mod:`~suit_ros.data.sim.parked_rows`); 0 (default):
        none, the world byte for byte as before.
    :param real_car_roofs: share of passenger cars (drawn from their ids) whose greenhouse
        sits as on real cars: a raked windscreen that returns little, the roof from near the
        middle back to the rear (:func:`~suit_ros.data.sim.bodies.car_body`), so the car's
        own returns say which end is its front; 0 (default): none, the world byte for byte
        as before.
    :param at_fronts: share of pedestrians (drawn from their ids; not the bystanders) that
        stand on the sidewalk close in front of a building or a lot wall, 0.1-0.5 m off it, as
        real ones wait at a door or look in a shop window
        (:func:`~suit_ros.data.sim.bystanders.place_at_fronts`; the world's walkers keep 1.5 m
        or more off the building line); 0 (default): none, the world byte for byte as before.
    :param parked_reversed: share of those row cars parked against their side's traffic, as on
        one-way streets and in cities where cars park either way (0.15, the default, the world
        as it was; at 0.5 the side of the road says nothing of a parked car's heading).
    """

    clutter: float = 1.0
    glass_porosity: float = 0.6
    glass_return: float = 0.5
    dark_paint: float = 0.25
    hedge_porosity: tuple[float, float] = (0.25, 0.6)
    ego_body: bool = True
    street_objects: float = 0.0
    real_car_ends: float = 0.0
    bystanders: float = 0.0
    dark_tops: float = 0.0
    parked_rows: float = 0.0
    parked_reversed: float = 0.15
    real_car_roofs: float = 0.0
    at_fronts: float = 0.0


@dataclass(frozen=True)
class SimConfig:
    """What a simulated drive contains.

    :param frames: number of LiDAR frames (sweeps) to produce.
    """

    frames: int = 100
    block: float = 70.0                   # road grid spacing (m)
    grid_half: int = 5                    # intersections from the centre to the edge
    lanes_per_direction: int = 2
    lane_width: float = 3.5
    sidewalk_width: float = 3.0
    moving_vehicles: int = 45
    parked_vehicles: int = 30
    pedestrians: int = 45
    cyclists: int = 12
    truck_fraction: float = 0.15
    ego_max_speed: float = 13.0
    odom_rate_hz: float = 50.0
    odom_noise: float = 0.0               # m / rad noise on recorded odometry
    lidar: LidarConfig = field(default_factory=LidarConfig)
    realism: Realism | None = None        # None: the box world (every actor one cuboid)
    exact_sectors: bool = True            # see below

    # ``exact_sectors``: with motion distortion, find each box's columns in the sector being
    # cast. False reproduces the sweeps generated before it existed, where boxes were looked
    # up in the wrong columns and most were missed (ground only in most sectors); set it for
    # any new data. The detailed world (``realism``) always casts exactly.

    def validate(self) -> SimConfig:
        """Raise ConfigError on out-of-range values; return self."""
        lc = self.lidar
        if self.frames < 1:
            raise ConfigError('frames must be >= 1')
        if lc.elevations is None and lc.beams not in (16, 32, 64, 128):
            raise ConfigError(f'beams must be 16, 32, 64 or 128 (or give elevations), '
                              f'got {lc.beams}')
        if not 0.01 <= lc.azimuth_resolution <= 5.0:
            raise ConfigError('azimuth_resolution must be within 0.01..5 degrees')
        if abs(360.0 / lc.azimuth_resolution - lc.columns) > 1e-6:
            raise ConfigError('azimuth_resolution must divide 360 degrees')
        if not 1.0 <= lc.rate_hz <= 50.0:
            raise ConfigError('rate_hz must be within 1..50')
        if not 10.0 <= lc.max_range <= 300.0:
            raise ConfigError('max_range must be within 10..300 m')
        if not 0.0 <= lc.dropout < 1.0:
            raise ConfigError('dropout must be in [0, 1)')
        if lc.intensity_max <= 0:
            raise ConfigError('intensity_max must be > 0')
        if self.realism is not None:
            _validate_realism(self.realism)
        return self

    @property
    def exact_sector_columns(self) -> bool:
        """Whether sector casting looks boxes up in the right columns (see ``exact_sectors``)."""
        return self.exact_sectors or self.realism is not None


def _validate_realism(r: Realism) -> None:
    """Raise ConfigError on out-of-range realism values."""
    if r.clutter < 0:
        raise ConfigError(f'realism.clutter must be >= 0 (0: no clutter), got {r.clutter}')
    for name in ('glass_porosity', 'glass_return', 'dark_paint', 'real_car_ends', 'bystanders',
                 'dark_tops', 'parked_rows', 'parked_reversed', 'real_car_roofs', 'at_fronts'):
        value = getattr(r, name)
        if not 0.0 <= value <= 1.0:
            raise ConfigError(f'realism.{name} is a probability in [0, 1], got {value}')
    lo, hi = r.hedge_porosity
    if not 0.0 <= lo <= hi < 1.0:
        raise ConfigError('realism.hedge_porosity must be (low, high) with 0 <= low <= high < 1, '
                          f'got {r.hedge_porosity}')


def _hdl64e_elevations() -> tuple[float, ...]:
    """HDL-64E S2: an upper block of 32 lasers from +2 deg down in 1/3 deg steps and a lower
    block of 32 from -8.83 deg down in 1/2 deg steps (datasheet: +2 to -24.9 deg)."""
    upper = [2.0 - k / 3.0 for k in range(32)]
    lower = [-8.83 - 0.5 * k for k in range(32)]
    return tuple(round(v, 4) for v in upper + lower)


# Real sensors (beam tables and mounting heights; public datasheets, see docs/sensors.md).
# Intensity conventions: Velodyne 0..255 calibrated reflectivity, KITTI reflectance 0..1,
# Ouster's 8-bit reflectivity channel 0..255. Motion distortion on: real spinning sensors
# report each column at its firing pose.
SENSORS: dict[str, LidarConfig] = {
    'sim32': LidarConfig(),
    'hdl32e': LidarConfig(beams=32, fov_down=-30.67, fov_up=10.67, azimuth_resolution=0.16,
                          range_noise=0.02, dropout=0.08, motion_distortion=True,
                          extrinsic_xyz=(0.94, 0.0, 1.84), max_range=100.0),
    'hdl64e': LidarConfig(elevations=_hdl64e_elevations(), azimuth_resolution=0.18,
                          range_noise=0.02, dropout=0.06, motion_distortion=True,
                          extrinsic_xyz=(0.76, 0.0, 1.73), intensity_max=1.0, max_range=120.0),
    'vlp16': LidarConfig(beams=16, fov_down=-15.0, fov_up=15.0, azimuth_resolution=0.2,
                         range_noise=0.03, dropout=0.05, motion_distortion=True,
                         extrinsic_xyz=(0.8, 0.0, 1.6), max_range=100.0),
    'os1-64': LidarConfig(beams=64, fov_down=-22.5, fov_up=22.5, azimuth_resolution=0.3515625,
                          range_noise=0.03, dropout=0.05, motion_distortion=True,
                          extrinsic_xyz=(0.8, 0.0, 1.8), max_range=120.0),
    'os1-128': LidarConfig(beams=128, fov_down=-22.5, fov_up=22.5,
                           azimuth_resolution=0.3515625, range_noise=0.03, dropout=0.05,
                           motion_distortion=True, extrinsic_xyz=(0.8, 0.0, 1.8),
                           max_range=120.0),
}


PRESETS: dict[str, SimConfig] = {
    'demo': SimConfig(frames=100),
    'train': SimConfig(frames=60),
    'val': SimConfig(frames=40),
    'test': SimConfig(frames=8, moving_vehicles=20, parked_vehicles=10, pedestrians=15,
                      cyclists=5, lidar=LidarConfig(beams=16, azimuth_resolution=0.4)),
}
# the same drives in the detailed world (actors from parts, clutter, ego returns)
PRESETS.update({f'{name}-real': replace(cfg, realism=Realism())
                for name, cfg in list(PRESETS.items())})
# the detailed world with the street objects of real sidewalks (issue 20: what real false
# positives sit on); training only, so the validation drives stay what they were
PRESETS['train-street'] = replace(PRESETS['train-real'], realism=Realism(street_objects=1.0))
PRESETS['val-street'] = replace(PRESETS['val-real'], realism=Realism(street_objects=1.0))
# half the passenger cars with the ends of real ones (docs/experiments/box_fit, run 18)
PRESETS['train-ends'] = replace(PRESETS['train-real'], realism=Realism(real_car_ends=0.5))
PRESETS['val-ends'] = replace(PRESETS['val-real'], realism=Realism(real_car_ends=0.5))
# every passenger car with the ends of real ones (run 19)
PRESETS['train-ends-all'] = replace(PRESETS['train-real'], realism=Realism(real_car_ends=1.0))
PRESETS['val-ends-all'] = replace(PRESETS['val-real'], realism=Realism(real_car_ends=1.0))
# and the street objects of real sidewalks (run 20: what the real false positives sit on)
PRESETS['train-street-ends'] = replace(PRESETS['train-real'],
                                       realism=Realism(real_car_ends=1.0, street_objects=1.0))
PRESETS['val-street-ends'] = replace(PRESETS['val-real'],
                                     realism=Realism(real_car_ends=1.0, street_objects=1.0))
# and half the pedestrians standing beside street objects and parked cars (run 23)
PRESETS['train-bystanders'] = replace(
    PRESETS['train-real'], realism=Realism(real_car_ends=1.0, street_objects=1.0, bystanders=0.5))
PRESETS['val-bystanders'] = replace(
    PRESETS['val-real'], realism=Realism(real_car_ends=1.0, street_objects=1.0, bystanders=0.5))
# or with half the passenger cars seen only below the belt (run 24)
PRESETS['train-dark-tops'] = replace(
    PRESETS['train-real'], realism=Realism(real_car_ends=1.0, street_objects=1.0, dark_tops=0.5))
PRESETS['val-dark-tops'] = replace(
    PRESETS['val-real'], realism=Realism(real_car_ends=1.0, street_objects=1.0, dark_tops=0.5))
# or with the kerbs lined with rows of parked cars (docs/experiments/parked_rows)
PRESETS['train-parked-rows'] = replace(
    PRESETS['train-real'], realism=Realism(real_car_ends=1.0, street_objects=1.0,
                                           parked_rows=0.5))
PRESETS['val-parked-rows'] = replace(
    PRESETS['val-real'], realism=Realism(real_car_ends=1.0, street_objects=1.0, parked_rows=0.5))
# and half the row cars parked against their side's traffic (docs/experiments/either_way)
PRESETS['train-parked-either'] = replace(
    PRESETS['train-real'], realism=Realism(real_car_ends=1.0, street_objects=1.0,
                                           parked_rows=0.5, parked_reversed=0.5))
PRESETS['val-parked-either'] = replace(
    PRESETS['val-real'], realism=Realism(real_car_ends=1.0, street_objects=1.0, parked_rows=0.5,
                                         parked_reversed=0.5))
# and half the pedestrians standing close in front of buildings and walls, as real ones do
# (docs/experiments/at_fronts: the real dev pedestrian at 13 m stands within 1.5 m of a facade)
PRESETS['train-fronts'] = replace(
    PRESETS['train-real'], realism=Realism(real_car_ends=1.0, street_objects=1.0, at_fronts=0.5))
PRESETS['val-fronts'] = replace(
    PRESETS['val-real'], realism=Realism(real_car_ends=1.0, street_objects=1.0, at_fronts=0.5))
# every passenger car with a real car's greenhouse: rear pillars, a compact back, a raked
# screen, the roof back to the tailgate (docs/experiments/car_front: a car's own front and back)
_ROOFS = Realism(real_car_ends=1.0, real_car_roofs=1.0)
PRESETS['train-ends-roofs'] = replace(PRESETS['train-real'], realism=_ROOFS)
PRESETS['val-ends-roofs'] = replace(PRESETS['val-real'], realism=_ROOFS)
PRESETS['train-street-roofs'] = replace(PRESETS['train-real'],
                                        realism=replace(_ROOFS, street_objects=1.0))
PRESETS['val-street-roofs'] = replace(PRESETS['val-real'],
                                      realism=replace(_ROOFS, street_objects=1.0))
PRESETS['train-parked-roofs'] = replace(
    PRESETS['train-real'], realism=replace(_ROOFS, street_objects=1.0, parked_rows=0.5,
                                           parked_reversed=0.5))
PRESETS['val-parked-roofs'] = replace(
    PRESETS['val-real'], realism=replace(_ROOFS, street_objects=1.0, parked_rows=0.5,
                                         parked_reversed=0.5))


def preset(name: str, sensor: str | None = None, **overrides: object) -> SimConfig:
    """A named preset with optional field overrides.

    ``demo``, ``train``, ``val``, ``test`` are the box world; ``demo-real``, ``train-real``,
    ``val-real``, ``test-real`` the same drives in the detailed world (:class:`Realism`).

    :param sensor: a real-sensor model from :data:`SENSORS` replacing the preset's LiDAR.
    """
    if name not in PRESETS:
        raise ConfigError(f'unknown preset {name!r}; choose from {", ".join(PRESETS)}')
    cfg = PRESETS[name]
    if sensor is not None:
        if sensor not in SENSORS:
            raise ConfigError(f'unknown sensor {sensor!r}; choose from {", ".join(SENSORS)}')
        cfg = replace(cfg, lidar=SENSORS[sensor])
    lidar_keys = {k: v for k, v in overrides.items() if k in LidarConfig.__dataclass_fields__}
    other = {k: v for k, v in overrides.items() if k not in lidar_keys}
    if lidar_keys:
        cfg = replace(cfg, lidar=replace(cfg.lidar, **lidar_keys))  # type: ignore[arg-type]
    return replace(cfg, **other).validate()  # type: ignore[arg-type]
