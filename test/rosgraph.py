"""Helpers for tests over real DDS: processes, a private rclpy context, bounded spinning."""
from __future__ import annotations

from collections.abc import Callable, Iterator
import contextlib
from pathlib import Path
import subprocess
import sys
import time
from typing import Any

REPO = Path(__file__).resolve().parents[1]


def ros_env() -> dict[str, str]:
    """Environment for child processes: DDS on localhost, this run's domain."""
    from suit_ros.rosenv import local_ros_env
    return local_ros_env()


def start_node(checkpoint: str, *params: str, cmd: list[str] | None = None
               ) -> subprocess.Popen[str]:
    """Start the detector node in its own process (every other parameter at its default)."""
    args = (cmd or [sys.executable, '-m', 'suit_ros.node']) + [
        '--ros-args', '-p', f'checkpoint:={checkpoint}']
    for p in params:
        args += ['-p', p]
    return subprocess.Popen(args, env=ros_env(), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)


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


def stop(proc: subprocess.Popen[str]) -> str:
    """Terminate a process and return its output."""
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
    return proc.stdout.read() if proc.stdout else ''


class Probe:
    """A node in the test process with its own Context; spins only against deadlines."""

    def __init__(self, name: str = 'probe') -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        self.ctx = Context()
        rclpy.init(context=self.ctx)
        self.node = rclpy.create_node(name, context=self.ctx)
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)

    def spin_until(self, cond: Callable[[], bool], timeout: float) -> bool:
        """Spin until ``cond()`` or the timeout; return ``cond()``."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if cond():
                return True
            self.ex.spin_once(timeout_sec=0.05)
        return cond()

    def spin_for(self, seconds: float) -> None:
        """Spin for a fixed time."""
        self.spin_until(lambda: False, seconds)

    def close(self) -> None:
        """Shut the context down."""
        import rclpy
        self.ex.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.ctx)


def diag_values(msg: Any) -> dict[str, str]:
    """KeyValues of the detector's DiagnosticStatus."""
    for st in msg.status:
        if st.name == 'suit_ros: detector':
            return {kv.key: kv.value for kv in st.values}
    return {}


def synthetic_bag(directory: Path, frames: int, seed: int, storage: str = 'mcap') -> Path:
    """A small synthetic bag (16 beams) for integration tests."""
    from suit_ros.data.sim import preset
    from suit_ros.data.simulate_cli import write_bag
    path = directory / 'bag'
    write_bag(path, preset('test', frames=frames), seed, storage)
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
