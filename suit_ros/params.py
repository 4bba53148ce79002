"""The detector's parameters: one typed set with one set of defaults.

:class:`DetectorParams` is the single owner of every setting of the ``detector`` node and of
``suit-ros detect-bag``: the node declares its ROS parameters from it (names, defaults,
descriptions, ranges, read-only flags), ``detect-bag`` loads the same YAML into it, and
``params/detector.yaml`` and the README's parameter table are generated from it (``python -m
suit_ros.params > params/detector.yaml``, ``python -m suit_ros.params --markdown``; tests
check that both are up to date).
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
import math
import sys
import textwrap
from typing import Any, Literal, get_args

from suit_ros.errors import ConfigError

PointsQoS = Literal['auto', 'sensor_data', 'reliable']
Device = Literal['auto', 'cpu', 'cuda']
PrecisionParam = Literal['auto', 'float32', 'bfloat16']
GroundParam = Literal['as_given', 'local']       # suit_ros.ground.GroundMode
OverhangParam = Literal['keep', 'drop']          # suit_ros.overhang.OverhangMode
OverhangChoice = Literal['checkpoint', 'keep', 'drop']   # the node's: 'checkpoint' as it says
GroundChoice = Literal['checkpoint', 'as_given', 'local']   # the node's: 'checkpoint' as it says
BoxFitParam = Literal['off', 'faces']             # suit_ros.box_fit.BoxFitMode
TrafficSide = Literal['right', 'left']
TrafficSideParam = Literal['auto', 'right', 'left']   # auto: suit_ros.traffic_side
Vector3 = tuple[float, float, float]


def _spec(description: str, *, read_only: bool = False, lo: float | None = None,
          hi: float | None = None, choices: tuple[str, ...] = (), length: int = 0
          ) -> dict[str, Any]:
    """Field metadata: what the node's ParameterDescriptor and the YAML comments say."""
    return {'description': description, 'read_only': read_only, 'lo': lo, 'hi': hi,
            'choices': choices, 'length': length}


# parameters renamed in a release: old name -> new name (an old YAML fails with a pointer),
# and what changed besides the name
RENAMED = {'velocity_filter': 'tracking', 'coast_frames': 'coast_s'}
RENAMED_NOTES = {'coast_frames': 'seconds: 0.5 is 5 frames at 10 Hz'}


def renamed_message(old: str) -> str:
    """``'<old> is now <new>'`` for a renamed parameter, with what else changed."""
    note = RENAMED_NOTES.get(old)
    return f'{old} is now {RENAMED[old]}' + (f' ({note})' if note else '')


@dataclass(frozen=True)
class DetectorParams:
    """Every setting of the detector node and ``detect-bag`` (defaults are the node's)."""

    checkpoint: str = field(default='', metadata=_spec(
        'model checkpoint: a .safetensors path or a shipped one by name (suit_carry: SUIT '
        'that holds objects through lost returns, docs/outage; suit_default: the same '
        'without the carry, a shorter step; centerpoint_single); empty: suit_carry',
        read_only=True))
    device: Device = field(default='auto', metadata=_spec(
        'auto | cpu | cuda', read_only=True, choices=get_args(Device)))
    threads: int = field(default=0, metadata=_spec(
        'torch and BLAS CPU threads; 0: all cores but one, so DDS I/O keeps a core',
        read_only=True, lo=0, hi=256))
    precision: PrecisionParam = field(default='auto', metadata=_spec(
        'auto | float32 | bfloat16: bfloat16 runs the backbone and head convolutions in '
        'bfloat16; auto: bfloat16 on a CPU with bfloat16 units (AMX, AVX512-BF16), else '
        'float32', read_only=True, choices=get_args(PrecisionParam)))
    points_topic: str = field(default='/points', metadata=_spec(
        'input PointCloud2 topic (or remap)', read_only=True))
    odom_topic: str = field(default='/odom', metadata=_spec(
        'input Odometry topic (or remap)', read_only=True))
    points_qos: PointsQoS = field(default='auto', metadata=_spec(
        'points reliability: auto (reliable when every publisher offers it, else best '
        'effort; re-checked as publishers come and go) | sensor_data | reliable',
        read_only=True, choices=get_args(PointsQoS)))
    score_thresholds: tuple[float, ...] = field(default=(0.0,), metadata=_spec(
        'published boxes: per-class score thresholds on the final (tracked) scores; one '
        "value: all classes, carried boxes too; [0.0]: the checkpoint's published ones "
        '(with a carry branch, its own for boxes held where the cloud shows nothing)'))
    nms_iou_threshold: float = field(default=0.2, metadata=_spec(
        'BEV IoU NMS threshold', lo=0.0, hi=1.0))
    max_detections: int = field(default=200, metadata=_spec(
        'detections per frame', lo=1, hi=1000))
    candidates: int = field(default=500, metadata=_spec(
        'heatmap peaks kept before the score threshold and NMS (busy scenes need hundreds)',
        lo=1, hi=10000))
    tracking: bool = field(default=True, metadata=_spec(
        "track detections over frames (constant-velocity Kalman tracks, odometry frame): "
        "velocities filtered, scores smoothed, vehicle headings settled, track ids "
        "published (renamed from velocity_filter); false: the model's one-frame output"))
    track_score_mix: float = field(default=0.7, metadata=_spec(
        "with tracking: a tracked detection's score is (1 - mix) x its own + mix x its "
        "track's running score; 0: the model's scores", lo=0.0, hi=1.0))
    coast_s: float = field(default=0.5, metadata=_spec(
        'with tracking: a confident track that gets no detection is published where it is '
        'predicted, with its running score and num_points 0, for up to this many seconds '
        "since its last detection while no ray of the cloud passed through its box (a lost "
        "sector, an occluder's shadow; docs/experiments/coast; in whole frames, about the same "
        'time at any sensor rate; renamed from coast_frames: 5 frames); 0.0: off', lo=0.0,
        hi=0.6))
    ground: GroundChoice = field(default='checkpoint', metadata=_spec(
        "checkpoint | as_given | local: the input's heights as the checkpoint's config says "
        "(the shipped ones: local), as base_link has them, or leveled to the ground estimated "
        "around each point "
        '(sloped roads, an extrinsic height a little off; boxes put back on the road); a '
        'change resets the memory',
        choices=get_args(GroundChoice)))
    overhang: OverhangChoice = field(default='checkpoint', metadata=_spec(
        'checkpoint | keep | drop: the returns that hang over a gap in their column '
        "(canopies, awnings, signal arms over the objects) as the checkpoint's config says, "
        'kept, or dropped before the model; a change resets the memory',
        choices=get_args(OverhangChoice)))
    box_fit: BoxFitParam = field(default='off', metadata=_spec(
        'off | faces: car boxes as the model places them, or moved toward the sensor onto the '
        'returns of the faces it sees (real LiDAR: the shipped models place parked cars about '
        '0.6 m too far; docs/experiments/box_fit)', choices=get_args(BoxFitParam)))
    traffic_side: TrafficSideParam = field(default='right', metadata=_spec(
        'auto | right | left: the side of the road traffic keeps to. The shipped models learnt '
        "a vehicle's front from the side of the road in right-hand traffic (left-hand: half "
        'the car headings flipped, docs/experiments/either_way); left mirrors the cloud, the '
        'odometry and the extrinsic across the x-z plane before the model and its boxes back, '
        'so it sees right-hand traffic; auto starts right (or goes on from the side in use) '
        'and takes the side the oncoming vehicles pass on (suit_ros/traffic_side.py; needs '
        'tracking and odometry); a change of the side in use resets the memory and the tracks',
        choices=get_args(TrafficSideParam)))
    min_range: float = field(default=1.0, metadata=_spec(
        'drop points closer than this (m, xy, LiDAR frame)', lo=0.0, hi=50.0))
    max_range: float = field(default=80.0, metadata=_spec(
        'drop points farther than this (m, xy, LiDAR frame)', lo=1.0, hi=500.0))
    intensity_field: str = field(default='', metadata=_spec(
        "intensity field: '' the first of intensity, i, reflectivity; 'none' no intensity "
        '(the model works from geometry); or a field name'))
    intensity_scale: float = field(default=255.0, metadata=_spec(
        'intensity / scale -> 0..1 (255: Velodyne-style 0..255; 1: 0..1 reflectance)',
        lo=1e-6, hi=1e6))
    deskew: bool = field(default=True, metadata=_spec(
        "move each return to where the sensor was at the cloud's stamp: the odometry's motion "
        'over the sweep applied by the per-point time field (a spinning LiDAR on a moving '
        'vehicle; docs/experiments/deskew); no time field: as given; false for a cloud '
        'deskewed upstream'))
    time_field: str = field(default='', metadata=_spec(
        "deskew's per-point time field: '' the first of time, t, timestamp, time_stamp, "
        'offset_time; or a field name (integers: ns, floats: s; relative to the stamp or '
        'absolute)'))
    extrinsic_xyz: Vector3 = field(default=(0.9, 0.0, 1.8), metadata=_spec(
        'base_link -> LiDAR translation (m); a change resets the memory', length=3))
    extrinsic_rpy: Vector3 = field(default=(0.0, 0.0, 0.0), metadata=_spec(
        'base_link -> LiDAR roll pitch yaw (rad); a change resets the memory', length=3))
    ego_box_min: Vector3 = field(default=(0.0, 0.0, 0.0), metadata=_spec(
        'ego-vehicle crop box, min corner in base_link (m): points inside are dropped; '
        'disabled while any max <= min', length=3))
    ego_box_max: Vector3 = field(default=(0.0, 0.0, 0.0), metadata=_spec(
        'ego-vehicle crop box, max corner in base_link (m)', length=3))
    min_points: int = field(default=1000, metadata=_spec(
        'warn when fewer points than this remain after filtering', lo=0, hi=10_000_000))
    odom_buffer_s: float = field(default=10.0, metadata=_spec(
        'odometry kept for pose lookups (s)', lo=0.1, hi=600.0))
    odom_tolerance_s: float = field(default=0.15, metadata=_spec(
        'max time of a cloud stamp outside the odometry buffer for a pose (s)',
        lo=0.0, hi=5.0))
    odom_wait_s: float = field(default=0.1, metadata=_spec(
        'wait up to this long for odometry covering the cloud stamp before running with '
        'the nearest pose or single-frame (s)', lo=0.0, hi=5.0))
    max_gap_s: float = field(default=0.5, metadata=_spec(
        'reset the memory after a longer gap between cloud stamps (the one staleness '
        'threshold)', lo=0.01, hi=60.0))
    max_pose_jump_m: float = field(default=5.0, metadata=_spec(
        'reset the memory when the pose moves farther between two clouds than this per 0.1 s '
        'of their gap, and at least this (m; 5: 50 m/s, so a cloud dropped at highway speed '
        'is no jump)',
        lo=0.1, hi=1000.0))
    max_stamp_skew_s: float = field(default=1.0, metadata=_spec(
        'stamps farther than this from the node clock: latency is measured from the '
        'receive time instead, and odometry stamped further ahead of the clock is refused (s)',
        lo=0.0, hi=1e9))
    stale_periods: float = field(default=3.0, metadata=_spec(
        'diagnostics WARN when no cloud arrived for this many expected input periods',
        lo=1.0, hi=1000.0))
    input_timeout_s: float = field(default=1.0, metadata=_spec(
        'diagnostics ERROR when no cloud arrived for this long (s); before the first cloud '
        'WARN for this and 10 s more', lo=0.05, hi=3600.0))
    diagnostics_period_s: float = field(default=1.0, metadata=_spec(
        'diagnostics publishing period (s)', read_only=True, lo=0.05, hi=60.0))

    # ------------------------------------------------------------------ checks
    def validate(self, num_classes: int | None = None) -> DetectorParams:
        """Raise ConfigError naming the first invalid setting; return self.

        :param num_classes: the model's class count, to check ``score_thresholds``.
        """
        for f in fields(self):
            value = getattr(self, f.name)
            m = f.metadata
            if m['choices'] and value not in m['choices']:
                raise ConfigError(f'{f.name} must be one of {", ".join(m["choices"])}, '
                                  f'not {value!r}')
            if m['length'] and (len(value) != m['length']
                                or not all(math.isfinite(v) for v in value)):
                raise ConfigError(f'{f.name} needs {m["length"]} finite numbers, got '
                                  f'{list(value)}')
            if m['lo'] is not None and not m['lo'] <= value <= m['hi']:
                raise ConfigError(f'{f.name} must be within {m["lo"]}..{m["hi"]}, '
                                  f'not {value}')
        thr = self.score_thresholds
        # without the model's class count (before a checkpoint is loaded) any count is taken
        # here; the caller checks it again with the count
        count_ok = len(thr) >= 1 if num_classes is None else len(thr) in (1, num_classes)
        if not count_ok or any(not 0.0 <= v <= 1.0 for v in thr):
            sizes = 'one or more' if num_classes is None else f'1 or {num_classes}'
            raise ConfigError(f'score_thresholds needs {sizes} values within 0..1, got '
                              f'{list(thr)}')
        if self.min_range >= self.max_range:
            raise ConfigError(f'min_range ({self.min_range}) must be below max_range '
                              f'({self.max_range})')
        return self

    @property
    def ego_box_enabled(self) -> bool:
        """Whether the ego crop box is a real box."""
        return all(hi > lo for lo, hi in zip(self.ego_box_min, self.ego_box_max))

    def ground_mode(self) -> GroundParam | None:
        """``ground`` for :class:`~suit_ros.model.streaming.StreamingDetector` (None: the
        checkpoint's)."""
        return None if self.ground == 'checkpoint' else self.ground

    def overhang_mode(self) -> OverhangParam | None:
        """``overhang`` for :class:`~suit_ros.model.streaming.StreamingDetector` (None: the
        checkpoint's)."""
        return None if self.overhang == 'checkpoint' else self.overhang

    def class_thresholds(self, num_classes: int) -> list[float] | None:
        """Per-class thresholds for ``StreamingDetector.set_thresholds`` (None: default)."""
        thr = list(self.score_thresholds)
        if thr == [0.0]:
            return None
        return thr * num_classes if len(thr) == 1 else thr

    # ------------------------------------------------------------------ conversions
    def updated(self, values: Mapping[str, Any]) -> DetectorParams:
        """A copy with ``values`` (ROS parameter values or YAML) applied; unknown keys fail."""
        known = {f.name: f for f in fields(self)}
        unknown = sorted(set(values) - set(known))
        if unknown:
            renamed = ''.join(f'; {renamed_message(old)}' for old in unknown if old in RENAMED)
            raise ConfigError(f'unknown detector parameter(s) {unknown}{renamed}; known: '
                              f'{sorted(known)}')
        changes = {}
        for name, value in values.items():
            default = getattr(DetectorParams, name)
            changes[name] = _coerce(name, value, default)
        return replace(self, **changes)

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any]) -> DetectorParams:
        """Defaults updated with ``values`` (strict)."""
        return cls().updated(values)

    @classmethod
    def from_yaml(cls, path: str) -> DetectorParams:
        """Read a node parameter file (``detector: ros__parameters:`` layout or flat)."""
        import yaml
        try:
            with open(path, encoding='utf-8') as f:
                data = yaml.safe_load(f) or {}
        except OSError as exc:
            raise ConfigError(f'cannot read the parameter file {path}: '
                              f'{exc.strerror or exc}') from exc
        except yaml.YAMLError as exc:
            raise ConfigError(f'{path} is not valid YAML: {exc}') from exc
        if not isinstance(data, dict):
            raise ConfigError(f'{path}: expected a mapping')
        for key in ('detector', '/detector', '/**'):
            if isinstance(data.get(key), dict) and 'ros__parameters' in data[key]:
                data = data[key]['ros__parameters']
                break
        return cls.from_mapping(data)

    def ros_values(self) -> dict[str, Any]:
        """Name -> value as a ROS parameter (tuples as lists)."""
        return {f.name: (list(v) if isinstance(v := getattr(self, f.name), tuple) else v)
                for f in fields(self)}


def _coerce(name: str, value: Any, default: Any) -> Any:
    """``value`` in the type of ``default``; ConfigError when it cannot be."""
    try:
        if isinstance(default, tuple):
            return tuple(float(v) for v in value)
        if isinstance(default, bool) or isinstance(default, str):
            if not isinstance(value, type(default)):
                raise TypeError
            return value
        if isinstance(default, int):
            if isinstance(value, bool) or int(value) != value:
                raise TypeError
            return int(value)
        if isinstance(value, bool):
            raise TypeError
        return float(value)
    except (TypeError, ValueError, OverflowError) as exc:     # OverflowError: int(inf)
        raise ConfigError(f'{name} must be {_kind(default)}, got {value!r}') from exc


def _kind(default: Any) -> str:
    if isinstance(default, tuple):
        return 'a list of numbers'
    return {str: 'a string', int: 'an integer', float: 'a number'}.get(type(default), 'valid')


def parameter_descriptions() -> dict[str, dict[str, Any]]:
    """Name -> field metadata (description, read_only, lo, hi, choices, length)."""
    return {f.name: dict(f.metadata) for f in fields(DetectorParams)}


def runtime_parameters() -> tuple[str, ...]:
    """Names that can change while the node runs."""
    return tuple(n for n, m in parameter_descriptions().items() if not m['read_only'])


def render_yaml() -> str:
    """``params/detector.yaml``: every parameter with its default and description."""
    lines = ['# Parameters of the suit_ros detector node, generated from suit_ros/params.py',
             '# (python -m suit_ros.params > params/detector.yaml). Use with',
             '#   ros2 run suit_ros detector --ros-args --params-file params/detector.yaml',
             '#   suit-ros detect-bag IN OUT --params params/detector.yaml',
             '# read-only: fixed at start; the others can change at runtime',
             '# (ros2 param set /detector <name> <value>).',
             'detector:', '  ros__parameters:']
    for name, value in DetectorParams().ros_values().items():
        m = parameter_descriptions()[name]
        text = ('read-only; ' if m['read_only'] else '') + m['description']
        lines += textwrap.wrap(text, 95, initial_indent='    # ', subsequent_indent='    # ')
        lines.append(f'    {name}: {_yaml_value(value)}')
    return '\n'.join(lines) + '\n'


README_BEGIN = '<!-- parameters: generated by `python -m suit_ros.params --markdown` -->'
README_END = '<!-- end of parameters -->'


def render_markdown() -> str:
    """The README's parameter table (between :data:`README_BEGIN` and :data:`README_END`;
    a test checks that the README holds what this generates)."""
    lines = [README_BEGIN, '', '| name | default | runtime | meaning |', '|---|---|---|---|']
    for name, value in DetectorParams().ros_values().items():
        m = parameter_descriptions()[name]
        text = m['description'].replace('|', 'or')
        lines.append(f'| `{name}` | `{_yaml_value(value)}` | '
                     f'{"read-only" if m["read_only"] else "yes"} | {text} |')
    return '\n'.join(lines + ['', README_END]) + '\n'


def _yaml_value(value: Any) -> str:
    if isinstance(value, list):
        return '[' + ', '.join(_yaml_value(v) for v in value) + ']'
    if isinstance(value, str):
        return f"'{value}'"
    if isinstance(value, bool):
        return 'true' if value else 'false'
    return repr(value)


if __name__ == '__main__':
    sys.stdout.write(render_markdown() if '--markdown' in sys.argv[1:] else render_yaml())
