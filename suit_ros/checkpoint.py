"""Checkpoints: safetensors weights + JSON metadata (config, class names, metrics, code version).

Nothing here unpickles: a pickle or ``torch.save`` archive is refused with a message that says
what it is and what to do.
"""
from __future__ import annotations

import datetime
import json
import os
from pathlib import Path
import stat
import subprocess
from typing import Any

import torch

from suit_ros import __version__
from suit_ros.config import SPARSE_MEMORIES, ModelConfig, TemporalMode, model_config_from_dict
from suit_ros.errors import CheckpointError, ConfigError

FORMAT = 'suit_ros/1'
# the node's default since 2026-12-08: SUIT with a carry branch (docs/experiments/
# carry_node_default); suit_default is its base, without the carry
DEFAULT_NAME = 'suit_carry.safetensors'


def default_checkpoint_path() -> Path:
    """The checkpoint shipped with the package (used when none is given)."""
    return Path(__file__).resolve().parent / 'checkpoints' / DEFAULT_NAME


def shipped_checkpoints() -> list[str]:
    """The names of the checkpoints shipped with the package (``suit_carry``, ...)."""
    return sorted(p.stem for p in default_checkpoint_path().parent.glob('*.safetensors'))


def resolve_checkpoint(path: str | os.PathLike[str]) -> Path:
    """``path`` itself when it is a file; else a shipped checkpoint named so (``suit_carry``
    or ``suit_carry.safetensors``; '' is the default one); else ``path`` (whose reading then
    says that it does not exist)."""
    p = Path(path)
    if os.fspath(path) == '':
        return default_checkpoint_path()
    if p.is_file() or p.parent != Path('.'):
        return p
    shipped = default_checkpoint_path().parent / (p.stem + '.safetensors')
    return shipped if p.suffix in ('', '.safetensors') and shipped.is_file() else p


def code_version() -> str:
    """``suit_ros.__version__`` plus ``git describe`` when run from a checkout."""
    try:
        described = subprocess.run(
            ['git', 'describe', '--always', '--dirty'], cwd=Path(__file__).parent,
            capture_output=True, text=True, timeout=5, check=False).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        described = ''
    return f'{__version__}+{described}' if described else __version__


def save_checkpoint(path: str | os.PathLike[str], model: torch.nn.Module, config: ModelConfig,
                    metrics: dict[str, Any] | None = None,
                    extra: dict[str, Any] | None = None) -> Path:
    """Write the model's weights and metadata to a ``.safetensors`` file (atomically)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    meta = {
        'format': FORMAT,
        'config': config.to_dict(),
        'class_names': list(config.class_names),
        'metrics': metrics or {},
        'code_version': code_version(),
        'created': datetime.datetime.now(datetime.timezone.utc).isoformat(timespec='seconds'),
        'extra': extra or {},
    }
    _write(path, state, meta)
    return path


def _write(path: Path, state: dict[str, torch.Tensor], meta: dict[str, Any]) -> None:
    """The tensors and metadata into ``path``, whole or not at all (:func:`durable_replace`).
    Written by Python's own open, so a new file gets the umask's mode (safetensors' file
    writer makes 0600); a replaced file's mode is kept: readable by whom it was before."""
    from safetensors.torch import save

    from suit_ros.outputs import durable_replace
    tmp = path.with_suffix(path.suffix + '.tmp')
    tmp.unlink(missing_ok=True)             # one left by a crash keeps its own mode
    tmp.write_bytes(save(state, metadata={'suit_ros': json.dumps(meta)}))
    if path.is_file():
        os.chmod(tmp, stat.S_IMODE(path.stat().st_mode))
    durable_replace(tmp, path)


def _sniff(path: Path) -> None:
    """Refuse pickles and torch.save archives before any parser sees them.

    A safetensors file starts with its JSON header's length (8 bytes, little endian) followed by
    ``{``; that is checked first, because the length's low byte may be anything, 0x80 (a pickle's
    first byte) included.
    """
    size = path.stat().st_size
    with open(path, 'rb') as f:
        head = f.read(9)
    if len(head) == 9 and head[8:9] == b'{' and 8 + int.from_bytes(head[:8], 'little') <= size:
        return
    if head[:1] == b'\x80' or head[:2] == b'PK':
        kind = 'a pickle' if head[:1] == b'\x80' else 'a torch.save (zip/pickle) archive'
        raise CheckpointError(
            f'{path} is {kind}, not a suit_ros checkpoint. Pickles can run code when loaded, so '
            'suit_ros refuses them; export the weights to safetensors (suit-ros train writes '
            'them) and pass that file.')
    if len(head) < 8:
        raise CheckpointError(f'{path} is too short to be a checkpoint ({len(head)} bytes)')


def read_metadata(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Return a checkpoint's metadata without loading its tensors."""
    from safetensors import safe_open
    path = resolve_checkpoint(path)
    if path.is_dir():
        raise CheckpointError(f'checkpoint {path} is a folder: give the .safetensors file in '
                              'it (a training run writes model.safetensors)')
    if not path.is_file():
        raise CheckpointError(f'checkpoint {path} does not exist; train one with '
                              '`suit-ros train`, pass a path, or name a shipped one: '
                              + ', '.join(shipped_checkpoints()))
    _sniff(path)
    try:
        with safe_open(str(path), framework='pt') as f:
            raw = (f.metadata() or {}).get('suit_ros')
    except Exception as exc:  # safetensors raises several types for corrupt headers
        raise CheckpointError(f'{path} is not a valid safetensors file ({exc}); it may be '
                              'truncated or corrupt') from exc
    if raw is None:
        raise CheckpointError(f'{path} is a safetensors file but not a suit_ros checkpoint '
                              '(no suit_ros metadata)')
    try:
        meta = json.loads(raw)
    except json.JSONDecodeError as exc:
        raise CheckpointError(f'{path}: corrupt suit_ros metadata ({exc})') from exc
    if not isinstance(meta, dict):
        raise CheckpointError(f'{path}: corrupt suit_ros metadata (a JSON '
                              f'{type(meta).__name__}, not an object)')
    if meta.get('format') != FORMAT:
        raise CheckpointError(f'{path}: unsupported checkpoint format {meta.get("format")!r} '
                              f'(this suit_ros reads {FORMAT})')
    return dict(meta)


def published_thresholds(meta: dict[str, Any], class_names: tuple[str, ...] | list[str],
                         carried: bool = False) -> list[float]:
    """The per-class score thresholds the node publishes at: the checkpoint's
    ``publish_thresholds`` (chosen for the published output, ``suit-ros choose-thresholds``),
    else its decoding threshold (``head.score_threshold``, the low one AP evaluation uses).

    :param carried: those of the boxes a carry branch decodes where the input has no returns
        (``carry_publish_thresholds``; where the checkpoint has none, the others)."""
    stored = _thresholds(meta, 'publish_thresholds')
    if carried:
        stored = {**stored, **_thresholds(meta, 'carry_publish_thresholds')}
    config = meta.get('config') if isinstance(meta.get('config'), dict) else {}
    head = config.get('head', {}) if isinstance(config, dict) else {}
    decode = float(head.get('score_threshold', 0.1)) if isinstance(head, dict) else 0.1
    return [stored.get(c, decode) for c in class_names]


def _thresholds(meta: dict[str, Any], key: str) -> dict[str, float]:
    """``meta[key]``: class name -> a score in 0..1 (absent: none).

    :raises CheckpointError: anything else (a hand-edited file)."""
    raw = meta.get(key) or {}
    try:
        if not isinstance(raw, dict):
            raise TypeError(f'a {type(raw).__name__}')
        out = {str(k): float(v) for k, v in raw.items()}
        bad = {k: v for k, v in out.items() if not 0.0 <= v <= 1.0}
        if bad:
            raise ValueError(f'outside 0..1: {bad}')
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"the checkpoint's {key} must map class names to scores in "
                              f'0..1, not {raw!r} ({exc}); rewrite them with suit-ros '
                              'choose-thresholds --write') from exc
    return out


def update_metadata(path: str | os.PathLike[str], **changes: Any) -> Path:
    """Rewrite a checkpoint with the same tensors and its metadata updated (atomically)."""
    from safetensors.torch import load_file
    path = resolve_checkpoint(path)         # a shipped one by name, as read_metadata takes it
    meta = read_metadata(path)
    meta.update(changes)
    state = load_file(str(path), device='cpu')
    _write(path, state, meta)
    return path


def load_checkpoint(path: str | os.PathLike[str], device: torch.device | str | None = None,
                    expect_config: ModelConfig | None = None,
                    expect_classes: tuple[str, ...] | list[str] | None = None,
                    ) -> tuple[Any, ModelConfig, dict[str, Any]]:
    """Load a checkpoint into a fresh SUITDetector.

    :param expect_config: when given, the checkpoint's config must equal it (the keys that
        differ are listed in the error).
    :param expect_classes: when given, the class names must match, in order.
    :return: ``(model, config, metadata)``; the model is in eval mode on ``device``.
    """
    from safetensors.torch import load_file

    from suit_ros.model.detector import SUITDetector
    path = resolve_checkpoint(path)
    meta = read_metadata(path)
    try:
        cfg = model_config_from_dict(meta['config'], f'{path} (embedded config)')
    except (ConfigError, KeyError, TypeError) as exc:
        raise CheckpointError(f'{path}: embedded config is invalid: {exc}') from exc
    if expect_config is not None and cfg != expect_config:
        diff = ', '.join(cfg.diff(expect_config)) or '?'
        raise CheckpointError(f'{path} was trained with a different model config '
                              f'(differs in: {diff}); use the config stored in the checkpoint '
                              'or retrain')
    if expect_classes is not None and tuple(expect_classes) != tuple(cfg.class_names):
        raise CheckpointError(f'{path} detects classes {list(cfg.class_names)}, but '
                              f'{list(expect_classes)} were expected')
    try:
        state = load_file(str(path), device='cpu')
    except Exception as exc:
        raise CheckpointError(f'{path}: cannot read tensors ({exc}); the file is corrupt') from exc
    try:
        model = SUITDetector(cfg)
    except Exception as exc:  # noqa: BLE001 - a config that passed its checks but builds nothing
        raise CheckpointError(f'{path}: cannot build the model from its embedded config '
                              f'({type(exc).__name__}: {exc})') from exc
    missing, unexpected = _check_keys(model, state)
    if missing or unexpected:
        raise CheckpointError(
            f'{path} does not match the model built from its config: missing tensors '
            f'{missing[:5]}{"..." if len(missing) > 5 else ""}, unexpected {unexpected[:5]}')
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        raise CheckpointError(f'{path}: tensor shapes do not match the config ({exc})') from exc
    if device is not None:
        model = model.to(device)
    return model.eval(), cfg, meta


def load_model_as(path: str | os.PathLike[str], temporal: TemporalMode | None = None,
                  device: torch.device | str | None = None) -> Any:
    """A checkpoint's model (eval mode), or its weights in another temporal mode (the
    modules that mode lacks are left out: the single-frame or zero-displacement baselines of
    a SUIT checkpoint)."""
    from dataclasses import replace

    from suit_ros.model.detector import SUITDetector
    model, cfg, _ = load_checkpoint(path, device)
    if temporal is None or temporal == cfg.temporal:
        return model
    if temporal in SPARSE_MEMORIES:
        new = replace(cfg, temporal=temporal)
    else:
        # carrying needs a sparse memory: the dense or single-frame variant of a carrying
        # checkpoint (suit_carry) is its base model
        new = replace(cfg, temporal=temporal, sampling=replace(cfg.sampling, carry_s=0.0),
                      fusion_gate='none' if cfg.fusion_gate == 'carry_branch'
                      else cfg.fusion_gate)
    other = SUITDetector(new)
    other.load_state_dict(model.state_dict(), strict=False)
    return other.to(model.device).eval()


def _check_keys(model: torch.nn.Module, state: dict[str, torch.Tensor]
                ) -> tuple[list[str], list[str]]:
    own = set(model.state_dict())
    return sorted(own - set(state)), sorted(set(state) - own)


def load_weights_into(model: torch.nn.Module, path: str | os.PathLike[str]) -> list[str]:
    """Initialise ``model`` from a checkpoint's shared tensors (stage-2 fine-tuning).

    Tensors present in both with equal shapes are copied; the model's own extra modules (the
    temporal path) keep their initialisation. Pillar weights learned at another
    ``pillars.time_scale`` are rescaled so the copied encoder computes the same features.
    :return: the names that were not initialised.
    """
    from safetensors.torch import load_file

    from suit_ros.model.pillars import PillarEncoder
    path = resolve_checkpoint(path)         # a shipped one by name (init_from: suit_default)
    meta = read_metadata(path)
    state = load_file(str(path), device='cpu')
    own = model.state_dict()
    shared = {k: v for k, v in state.items() if k in own and own[k].shape == v.shape}
    if not shared:
        raise CheckpointError(f'{path} shares no tensors with this model')
    model.load_state_dict(shared, strict=False)
    carry_head = getattr(getattr(model, 'carry', None), 'head', None)
    head = getattr(model, 'head', None)
    if (isinstance(carry_head, torch.nn.Module) and isinstance(head, torch.nn.Module)
            and not any(k.startswith('carry.head.') for k in shared)):
        # a carry branch's head starts as the model's own (fusion_gate: carry_branch)
        carry_head.load_state_dict(head.state_dict())
        shared.update({f'carry.head.{k}': v for k, v in head.state_dict().items()})
    pillars = getattr(model, 'pillars', None)
    if isinstance(pillars, PillarEncoder) and 'pillars.linear.weight' in shared:
        config = meta.get('config')
        pillar_cfg = config.get('pillars', {}) if isinstance(config, dict) else {}
        pillars.rescale_time_weights(float(pillar_cfg.get('time_scale', 1.0)))
    return sorted(set(own) - set(shared))
