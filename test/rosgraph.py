"""Helpers for tests over real DDS: the library's harness (:mod:`suit_ros.harness`: the node's
process, a probe in a private rclpy context, bounded spinning) and what only tests need."""
from __future__ import annotations

from collections.abc import Callable, Iterator
import contextlib
from pathlib import Path
import subprocess
from typing import Any

from suit_ros.harness import Probe, ros_env, start_node, stop  # noqa: F401 - for the tests

REPO = Path(__file__).resolve().parents[1]


@contextlib.contextmanager
def running_node(checkpoint: str, make_probe: Callable[[], Any], *params: str
                 ) -> Iterator[tuple[subprocess.Popen[str], Any]]:
    """A detector node in its own process and a probe (with ``ready(proc)`` and a ``p``
    :class:`Probe`) that waited for it; both closed afterwards (the node's log printed)."""
    proc = start_node(checkpoint, *params)
    probe = make_probe()
    try:
        probe.ready(proc)
        yield proc, probe
    finally:
        probe.p.close()
        print(stop(proc)[-3000:])


def diag_values(msg: Any) -> dict[str, str]:
    """KeyValues of the detector's DiagnosticStatus."""
    for st in msg.status:
        if st.name.endswith(': suit_ros detector'):
            return {kv.key: kv.value for kv in st.values}
    return {}


def synthetic_bag(directory: Path, frames: int, seed: int, storage: str = 'mcap',
                  distorted: bool = False) -> Path:
    """A small synthetic bag (16 beams) for integration tests; ``distorted``: each sweep cast
    over its turn from the moving vehicle, with its returns' times (as a real spinning
    sensor's driver publishes it)."""
    from dataclasses import replace

    from suit_ros.data.sim import preset
    from suit_ros.data.sim.recording import write_bag
    path = directory / 'bag'
    cfg = preset('test', frames=frames)
    if distorted:
        cfg = replace(cfg, lidar=replace(cfg.lidar, motion_distortion=True))
    write_bag(path, cfg, seed, storage)
    return path


def node_checkpoint(directory: Path) -> str:
    """The shipped checkpoint, or (before one is trained) an untrained real model."""
    from suit_ros.checkpoint import default_checkpoint_path, save_checkpoint
    if default_checkpoint_path().exists():
        return str(default_checkpoint_path())
    from suit_ros.config import ModelConfig
    from suit_ros.model.detector import SUITDetector
    path = directory / 'untrained.safetensors'
    save_checkpoint(path, SUITDetector(ModelConfig()), ModelConfig())
    return str(path)
