"""What the scripts of this folder share: a checkpoint by shipped name or path, with its
class names and published thresholds, and a table cell of recall / precision (GT) at a
threshold."""
from typing import Any

from suit_ros.checkpoint import load_checkpoint, published_thresholds


def checkpoint(name: str) -> tuple[Any, tuple[str, ...], list[float]]:
    """``(model, class names, published thresholds)`` of a shipped name or a path."""
    model, cfg, meta = load_checkpoint(name if name.endswith('.safetensors')
                                       else f'suit_ros/checkpoints/{name}.safetensors')
    names = tuple(cfg.class_names)
    return model, names, published_thresholds(meta, names)


def cell(a: dict[str, Any]) -> str:
    """``recall / precision (GT)`` of a class's counts at a threshold (``ClassCounts.at``)."""
    return f"{a['recall']:.3f} / {a['precision']:.3f} ({a['gt']})"
