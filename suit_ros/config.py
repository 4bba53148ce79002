"""Typed model configuration: dataclasses with the paper's defaults, loaded from YAML strictly.

Unknown keys, wrong types and out-of-range values are errors that name the key and the file.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields, is_dataclass
import os
import typing
from typing import Any, Literal, get_args

import yaml

from suit_ros import CLASS_NAMES
from suit_ros.errors import ConfigError
from suit_ros.params import GroundParam, OverhangParam

TemporalMode = Literal['none', 'dense', 'sparse', 'sparse_velocity', 'suit']
Relaxation = Literal['square', 'circle', 'rectangle']
NmsKind = Literal['rotated', 'circle']
TEMPORAL_MODES: tuple[str, ...] = get_args(TemporalMode)
# the temporal modes whose memory is sparse (sampled cells, which a carry can keep)
SPARSE_MEMORIES: tuple[TemporalMode, ...] = ('sparse', 'sparse_velocity', 'suit')
# where the memory's past term enters the fused map: everywhere (the paper), or only at head
# cells whose neighbourhood has no return in the current input (the memory fills what the
# sweeps do not see: occlusion, a lost sector; what is seen now is left as the sweep shows it)
# unobserved: the memory's past term enters only the head cells without returns;
# unobserved_output: also the head's outputs at cells with returns are the current frame's
# alone (the head run again without the past term), so the memory cannot move them;
# carry_branch: the observed cells decode exactly as without a gate (the model's own past
# term, everywhere, and its head), the unobserved cells through a second past projection and
# head of their own (``carry.past``, ``carry.head``), trained to read what the memory carries
FusionGate = Literal['none', 'unobserved', 'unobserved_output', 'carry_branch']
FUSION_GATES: tuple[str, ...] = get_args(FusionGate)
RELAXATIONS: tuple[str, ...] = get_args(Relaxation)


@dataclass(frozen=True)
class PillarConfig:
    """Dynamic pillarization and the PointNet pillar encoder."""

    point_range: tuple[float, float, float, float, float, float] = (
        -51.2, -51.2, -3.0, 51.2, 51.2, 3.0)
    pillar_size: float = 0.4
    in_channels: int = 5          # x, y, z, intensity (0..1), time_lag (s)
    channels: int = 32
    # the time lag is multiplied by this (1/s) before the encoder's linear layer: at 1 a lag of
    # 0.2 s weighs 1/40 of a metre-scale coordinate and its weight learns slowly (Adam moves
    # every weight at the same rate); 10 = the lag in 100 ms units
    time_scale: float = 1.0
    # at most about this many points per pillar (0: all): a denser pillar keeps a
    # deterministic pseudo-random subset of this expected size, as PointPillars caps its
    # pillars; the near field of a 64-beam sensor holds hundreds of points per pillar
    max_points_per_pillar: int = 0
    # keep: every return; drop: the returns that hang over a gap in their column (canopies,
    # awnings) removed before the encoder, in training and inference (suit_ros/overhang.py)
    overhang: OverhangParam = 'keep'
    # with overhang: drop, the gap that splits a column's returns grows to this many metres per
    # metre of range where that is more than 0.5 m (0: 0.5 m at every range); far rings are
    # further apart than 0.5 m, so a fixed gap cuts a far truck's side into floating stacks
    overhang_gap_per_m: float = 0.0
    # the input's height reference the model was trained on (suit_ros/ground.py): as_given,
    # or local (leveled to the ground around each point, GT boxes with it); what the node's
    # `ground: checkpoint` runs the model with
    ground: GroundParam = 'as_given'


@dataclass(frozen=True)
class BackboneConfig:
    """2D BEV backbone (strided blocks) and neck (upsample + concatenate)."""

    layer_nums: tuple[int, ...] = (1, 2, 2)
    layer_strides: tuple[int, ...] = (2, 2, 2)
    num_filters: tuple[int, ...] = (32, 64, 128)
    upsample_strides: tuple[int, ...] = (1, 2, 4)
    num_upsample_filters: tuple[int, ...] = (32, 32, 32)


@dataclass(frozen=True)
class HeadConfig:
    """CenterHead: targets, losses and decoding (CenterPoint's defaults)."""

    head_channels: int = 32
    min_overlap: float = 0.1
    min_radius: int = 2
    # CenterPoint's nuScenes weights; the shipped recipe (params/model_cpu.yaml) sets velocity 1.0
    code_weights: tuple[float, ...] = (1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 0.2, 0.2)
    loc_weight: float = 0.25
    max_objects: int = 500
    top_k: int = 500              # heatmap peaks kept before the score threshold and NMS
    score_threshold: float = 0.1
    nms: NmsKind = 'rotated'      # 'rotated' (BEV IoU) or 'circle'
    nms_iou_threshold: float = 0.2
    circle_nms_radius: tuple[float, ...] = (2.0, 3.0, 0.5, 0.75)   # metres, per class
    # a box of the carry branch goes when a surer one of its class is this near (metres)
    carry_nms_radius: tuple[float, ...] = (2.5, 3.5, 1.0, 1.5)
    max_detections: int = 200
    yaw_velocity_min_speed: float = 1.0   # m/s: faster boxes face their velocity (0: off)


MAX_CARRY_S = 2.5      # seconds: no model carries further than it was trained to (0.8 s)


@dataclass(frozen=True)
class SamplingConfig:
    """Significant sampling (paper section IV-A): alpha, K, refined NMS, relaxation."""

    alpha: float = 0.1            # coarse: keep cells with max-class score >= alpha
    top_k: int = 200              # K
    nms_iou_threshold: float = 0.1   # refined: suppress overlapping decoded boxes
    relaxation: Relaxation = 'square'
    window: int = 3               # Hs = Ws for square; window bound for circle / rectangle
    radius: float = 1.5           # rho in cells, for circle
    carry_s: float = 0.0          # seconds a sample outlives its object's returns (0: off)


@dataclass(frozen=True)
class GeoNetConfig:
    """GeoNet: object-centric displacement distribution over an Hw x Hw window of bins.

    Bins are velocities ``k * velocity_step`` (k = -(Hw//2)..Hw//2 per axis); the displacement
    of a bin is its velocity times the real time gap between the two frames.
    """

    bins: int = 7                 # Hw = Ww
    velocity_step: float = 5.0    # m/s between bins: 7 bins cover -15..15 m/s
    channels: int = 32
    prune_probability: float = 1e-3   # inference only: skip bins below this probability
    velocity_input: bool = False  # append the head's velocity at the sample to the patch


@dataclass(frozen=True)
class ModelConfig:
    """The whole detector."""

    class_names: tuple[str, ...] = CLASS_NAMES
    temporal: TemporalMode = 'suit'
    pillars: PillarConfig = field(default_factory=PillarConfig)
    backbone: BackboneConfig = field(default_factory=BackboneConfig)
    head: HeadConfig = field(default_factory=HeadConfig)
    sampling: SamplingConfig = field(default_factory=SamplingConfig)
    geonet: GeoNetConfig = field(default_factory=GeoNetConfig)
    geo_loss_weight: float = 1.0
    sweeps: int = 1               # LiDAR sweeps per input (current + previous), model frame
    fusion_gate: FusionGate = 'none'
    fusion_gate_radius: int = 1   # head cells around a return that count as observed

    def __post_init__(self) -> None:
        validate(self)

    @property
    def out_stride(self) -> int:
        """Stride of the head map relative to the pillar grid."""
        return int(self.backbone.layer_strides[0])

    def to_dict(self) -> dict[str, Any]:
        """Return a plain dict (YAML/JSON-serialisable)."""
        return typing.cast(dict[str, Any], _plain(asdict(self)))

    def diff(self, other: ModelConfig) -> list[str]:
        """Return the dotted keys whose values differ between two configs."""
        return _diff(self.to_dict(), other.to_dict(), '')


def validate(cfg: ModelConfig) -> None:
    """Raise ConfigError when a value is out of its range."""
    def bad(msg: str) -> ConfigError:
        return ConfigError(f'invalid model config: {msg}')
    if cfg.temporal not in TEMPORAL_MODES:
        raise bad(f'temporal must be one of {TEMPORAL_MODES}, got {cfg.temporal!r}')
    if cfg.fusion_gate not in FUSION_GATES or not 0 <= cfg.fusion_gate_radius <= 8:
        raise bad(f'fusion_gate must be one of {FUSION_GATES} and fusion_gate_radius within '
                  f'0..8, got {cfg.fusion_gate!r} and {cfg.fusion_gate_radius}')
    if not 0 <= cfg.sampling.carry_s <= MAX_CARRY_S:
        raise bad(f'sampling.carry_s must be within 0..{MAX_CARRY_S} s, got '
                  f'{cfg.sampling.carry_s}')
    if cfg.sampling.carry_s and (cfg.fusion_gate == 'none'
                                 or cfg.temporal not in SPARSE_MEMORIES):
        raise bad('sampling.carry_s needs a sparse memory and a fusion_gate (unobserved, '
                  'unobserved_output or carry_branch): a sample is carried only where the '
                  'current input has no returns')
    if cfg.fusion_gate == 'carry_branch' and cfg.temporal not in SPARSE_MEMORIES:
        raise bad(f'fusion_gate carry_branch needs a sparse memory, not temporal '
                  f'{cfg.temporal!r}')
    if not cfg.class_names or len(set(cfg.class_names)) != len(cfg.class_names):
        raise bad('class_names must be a non-empty list of unique names')
    r = cfg.pillars.point_range
    if len(r) != 6 or not (r[0] < r[3] and r[1] < r[4] and r[2] < r[5]):
        raise bad(f'point_range must be (x0, y0, z0, x1, y1, z1) with x0 < x1 ...: {r}')
    if cfg.pillars.pillar_size <= 0:
        raise bad('pillars.pillar_size must be > 0')
    if not 0 <= cfg.pillars.max_points_per_pillar <= 10_000:
        raise bad('pillars.max_points_per_pillar must be within 0..10000 (0: no cap)')
    if not 0 <= cfg.pillars.overhang_gap_per_m < 1:
        raise bad('pillars.overhang_gap_per_m must be within [0, 1) (0: a 0.5 m gap at every '
                  f'range), got {cfg.pillars.overhang_gap_per_m}')
    if not cfg.pillars.time_scale > 0:
        raise bad(f'pillars.time_scale must be > 0, got {cfg.pillars.time_scale}')
    for extent in (r[3] - r[0], r[4] - r[1]):
        cells = extent / cfg.pillars.pillar_size
        if abs(cells - round(cells)) > 1e-6:
            raise bad('point_range extent must be a multiple of pillar_size')
        total_stride = 1
        for s in cfg.backbone.layer_strides:
            total_stride *= s
        if round(cells) % total_stride:
            raise bad(f'pillar grid ({round(cells)}) must be divisible by the backbone '
                      f'strides product ({total_stride})')
    b = cfg.backbone
    n = len(b.layer_nums)
    if not (len(b.layer_strides) == len(b.num_filters) == len(b.upsample_strides)
            == len(b.num_upsample_filters) == n):
        raise bad('backbone lists must all have the same length')
    stride = 1
    for s, u in zip(b.layer_strides, b.upsample_strides):
        stride *= s
        if stride // u != b.layer_strides[0] or stride % u:
            raise bad('backbone: every upsampled block must land on the first block stride')
    if cfg.head.nms not in ('rotated', 'circle'):
        raise bad(f"head.nms must be 'rotated' or 'circle', got {cfg.head.nms!r}")
    if len(cfg.head.code_weights) != 10:
        raise bad('head.code_weights needs 10 values (offset 2, z, size 3, rot 2, vel 2)')
    if len(cfg.head.circle_nms_radius) != len(cfg.class_names):
        raise bad('head.circle_nms_radius needs one radius per class')
    if len(cfg.head.carry_nms_radius) != len(cfg.class_names):
        raise bad('head.carry_nms_radius needs one radius per class')
    sc = cfg.sampling
    if not 0.0 < sc.alpha < 1.0:
        raise bad('sampling.alpha must be in (0, 1)')
    if sc.top_k < 1:
        raise bad('sampling.top_k must be >= 1')
    if sc.relaxation not in RELAXATIONS:
        raise bad(f'sampling.relaxation must be one of {RELAXATIONS}')
    if sc.window < 1 or sc.window % 2 == 0:
        raise bad('sampling.window must be odd and >= 1')
    if cfg.geonet.bins < 1 or cfg.geonet.bins % 2 == 0:
        raise bad('geonet.bins must be odd and >= 1')
    if cfg.geonet.velocity_step <= 0:
        raise bad('geonet.velocity_step must be > 0')
    if not 1 <= cfg.sweeps <= 20:
        raise bad('sweeps must be within 1..20')
    if cfg.head.top_k < 1:
        raise bad('head.top_k must be >= 1')
    if cfg.head.yaw_velocity_min_speed < 0:
        raise bad('head.yaw_velocity_min_speed must be >= 0')


def _plain(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def _diff(a: Any, b: Any, prefix: str) -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        out: list[str] = []
        for key in sorted(set(a) | set(b)):
            out += _diff(a.get(key), b.get(key), f'{prefix}{key}.')
        return [k.rstrip('.') for k in out]
    return [] if a == b else [prefix]


def _coerce(cls: type, data: Any, where: str, source: str) -> Any:
    """Build dataclass ``cls`` from a mapping, strictly."""
    if not isinstance(data, dict):
        raise ConfigError(f'{source}: {where or "top level"} must be a mapping')
    hints = typing.get_type_hints(cls)
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise ConfigError(f'{source}: unknown key(s) {", ".join(where + k for k in unknown)}; '
                          f'allowed: {", ".join(sorted(known))}')
    kwargs: dict[str, Any] = {}
    for name, value in data.items():
        kwargs[name] = _convert(hints[name], value, f'{where}{name}', source)
    return cls(**kwargs)


def _convert(hint: Any, value: Any, key: str, source: str) -> Any:
    origin = typing.get_origin(hint)
    if isinstance(hint, type) and is_dataclass(hint):
        return _coerce(hint, value, key + '.', source)
    if origin is Literal:
        if value not in get_args(hint):
            raise ConfigError(f'{source}: {key} must be one of {list(get_args(hint))}, '
                              f'got {value!r}')
        return value
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f'{source}: {key} must be a list, got {value!r}')
        args = typing.get_args(hint)
        item = args[0]
        if len(args) != 2 or args[1] is not Ellipsis:
            if len(value) != len(args):
                raise ConfigError(f'{source}: {key} needs {len(args)} values, got {len(value)}')
        return tuple(_convert(item, v, key, source) for v in value)
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f'{source}: {key} must be a number, got {value!r}')
        return float(value)
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f'{source}: {key} must be an integer, got {value!r}')
        return value
    if hint is str:
        if not isinstance(value, str):
            raise ConfigError(f'{source}: {key} must be a string, got {value!r}')
        return value
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(f'{source}: {key} must be true or false, got {value!r}')
        return value
    return value


def dataclass_from_dict(cls: type, data: Any, source: str) -> Any:
    """Build any config dataclass from a mapping, strictly (unknown keys are errors)."""
    return _coerce(cls, data, '', source)


# experiment settings that were tried and not shipped (docs/experiments, reproducible from
# commit 44202bd): a config (or a checkpoint's embedded one) may still name them at the value
# that meant "off"; any other value is refused
RETIRED = {('pillars', 'time_channels'): False, ('memory_stride',): 1}

# the carry's lifetime was once counted in frames (``sampling.carry_frames``), so a 20 Hz
# sensor held a sample half as long as the 10 Hz drives it was trained on, and a node that
# skipped clouds under load twice as long. A config (or a checkpoint's embedded one) that
# names it gets ``carry_s`` = (frames + 0.5) x 0.1 s: exactly as many frames at 10 Hz, the
# rate every model was trained at, whatever the jitter of the stamps.
LEGACY_FRAME_S = 0.1


def carry_in_seconds(data: dict[str, Any], source: str) -> dict[str, Any]:
    """``data`` (a model config mapping) with a legacy ``sampling.carry_frames`` read as
    ``carry_s`` (see above); every other key as it is."""
    sampling = data.get('sampling')
    if not isinstance(sampling, dict) or 'carry_frames' not in sampling:
        return data
    sampling = dict(sampling)
    frames = sampling.pop('carry_frames')
    if 'carry_s' in sampling:
        raise ConfigError(f'{source}: sampling.carry_frames and sampling.carry_s both given; '
                          'keep carry_s (seconds)')
    if isinstance(frames, bool) or not isinstance(frames, int) or frames < 0:
        raise ConfigError(f'{source}: sampling.carry_frames must be a whole number of frames '
                          f'>= 0, not {frames!r} (or give sampling.carry_s in seconds)')
    sampling['carry_s'] = round((frames + 0.5) * LEGACY_FRAME_S, 6) if frames else 0.0
    return {**data, 'sampling': sampling}


def model_config_from_dict(data: dict[str, Any], source: str = '<dict>') -> ModelConfig:
    """Build a ModelConfig from a (possibly partial) mapping; missing keys take defaults."""
    data = carry_in_seconds(dict(data), source)
    for path, off in RETIRED.items():
        holder: Any = data
        for key in path[:-1]:
            holder = holder.get(key) if isinstance(holder, dict) else None
        if not isinstance(holder, dict) or path[-1] not in holder:
            continue
        if holder[path[-1]] != off:
            raise ConfigError(f'{source}: {".".join(path)} was an experiment that is no longer '
                              f'supported (only {off!r}); see docs/experiments at commit '
                              '44202bd to reproduce it')
        holder = dict(holder)
        del holder[path[-1]]
        if len(path) == 1:
            data = holder
        else:
            data[path[0]] = holder
    return typing.cast(ModelConfig, _coerce(ModelConfig, data, '', source))


def load_model_config(path: str | os.PathLike[str]) -> ModelConfig:
    """Load a model config YAML (optionally nested under a top-level ``model:`` key).

    ``_base_: other.yaml`` (relative to the file) starts from that file's settings; the keys
    given here override it, nested mappings key by key (as mmdetection3d's configs do).
    """
    return model_config_from_dict(_read_config(os.fspath(path), ()), os.fspath(path))


def _read_config(path: str, seen: tuple[str, ...]) -> dict[str, Any]:
    if path in seen:
        raise ConfigError(f'model config {path}: _base_ cycle ({" -> ".join(seen + (path,))})')
    try:
        with open(path, encoding='utf-8') as f:
            data = yaml.safe_load(f)
    except FileNotFoundError as exc:
        raise ConfigError(f'model config {path} does not exist') from exc
    except yaml.YAMLError as exc:
        raise ConfigError(f'model config {path} is not valid YAML: {exc}') from exc
    data = data or {}
    if not isinstance(data, dict):
        raise ConfigError(f'model config {path}: expected a mapping')
    base = data.pop('_base_', None)
    if isinstance(data, dict) and set(data) == {'model'}:
        data = data['model'] or {}
    if isinstance(data, dict):      # each file's own: a child's carry_s overrides a base's
        data = carry_in_seconds(data, path)     # carry_frames
    if base is None:
        return dict(data)
    parent = _read_config(os.path.join(os.path.dirname(path), str(base)), seen + (path,))
    return _merged(parent, data)


def _merged(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merged(out[k], v) if isinstance(v, dict) and isinstance(out.get(k),
                                                                        dict) else v
    return out
