"""One harness for everything that drives the node from outside: start it in its own process,
a probe node in a private rclpy context that spins only against deadlines, a bag player
process, and the orderly stop of all three. The demo, the node benchmark, the scripts and the
integration tests use it; every process it starts runs on this machine's private graph
(:func:`suit_ros.rosenv.local_ros_env`).
"""
from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
import contextlib
import subprocess
import sys
import time

from suit_ros.errors import SuitRosError


def ros_env() -> dict[str, str]:
    """Environment for child processes: DDS on localhost, this run's domain."""
    from suit_ros.rosenv import local_ros_env
    return local_ros_env()


def start_node(checkpoint: str, *params: str, env: dict[str, str] | None = None,
               quiet: bool = False, cmd: list[str] | None = None) -> subprocess.Popen[str]:
    """The detector node in its own process (``params``: ``name:=value``; every other
    parameter at its default); its output is kept for :func:`stop` unless ``quiet``.

    :param cmd: the executable (default: this interpreter's ``suit_ros.node``; the tests also
        run the colcon install's ``detector``).
    """
    args = (cmd or [sys.executable, '-m', 'suit_ros.node']) + [
        '--ros-args', '-p', f'checkpoint:={checkpoint}']
    for p in params:
        args += ['-p', p]
    out = subprocess.DEVNULL if quiet else subprocess.PIPE
    return subprocess.Popen(args, env=env or ros_env(), stdout=out,
                            stderr=subprocess.STDOUT, text=True)


def start_player(bag: str, *options: str, env: dict[str, str] | None = None,
                 quiet: bool = True) -> subprocess.Popen[str]:
    """``suit-ros play BAG OPTIONS`` in its own process (it sets the large-data Fast DDS
    profile for itself)."""
    out = subprocess.DEVNULL if quiet else subprocess.PIPE
    return subprocess.Popen([sys.executable, '-m', 'suit_ros.cli', 'play', bag, *options],
                            env=env or ros_env(), stdout=out, stderr=subprocess.STDOUT,
                            text=True)


def stop(proc: subprocess.Popen[str]) -> str:
    """Terminate a process (kill after 10 s) and return its output."""
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(10)
    return proc.stdout.read() if proc.stdout else ''


class Probe:
    """A node in this process with its own Context; spins only against deadlines."""

    def __init__(self, name: str = 'probe') -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        self.ctx = Context()
        rclpy.init(context=self.ctx)
        self.node = rclpy.create_node(name, context=self.ctx)
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)

    def spin_until(self, cond: Callable[[], bool], timeout: float, step: float = 0.05) -> bool:
        """Spin until ``cond()`` or the timeout; return ``cond()``."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if cond():
                return True
            self.ex.spin_once(timeout_sec=step)
        return cond()

    def spin_for(self, seconds: float, step: float = 0.05) -> None:
        """Spin for a fixed time."""
        self.spin_until(lambda: False, seconds, step)

    def spin_while_running(self, proc: subprocess.Popen[str], timeout: float,
                           step: float = 0.02) -> float:
        """Spin while ``proc`` runs (at most ``timeout``); :return: the seconds spun."""
        t0 = time.monotonic()
        self.spin_until(lambda: proc.poll() is not None, timeout, step)
        return time.monotonic() - t0

    def close(self) -> None:
        """Shut the context down."""
        from rclpy.utilities import try_shutdown
        self.ex.shutdown()
        self.node.destroy_node()
        try_shutdown(context=self.ctx)


def wait_ready(probe: Probe, node: subprocess.Popen[str], ready: Callable[[], bool],
               timeout: float) -> None:
    """Spin until ``ready()`` (for example: the node's first diagnostics arrived).

    :raises SuitRosError: the node exited (with its output) or did not come up in time.
    """
    end = time.monotonic() + timeout
    while not ready():
        probe.ex.spin_once(timeout_sec=0.1)
        if node.poll() is not None:
            raise SuitRosError(f'the detector node exited:\n{stop(node)[-3000:]}')
        if time.monotonic() > end:
            raise SuitRosError(f'the detector node did not come up in {timeout:.0f} s')


@contextlib.contextmanager
def node_and_probe(checkpoint: str, *params: str, name: str = 'probe',
                   quiet: bool = False, log: Callable[[str], None] | None = None
                   ) -> Iterator[tuple[subprocess.Popen[str], Probe]]:
    """A detector node in its own process and a probe in this one; both closed afterwards
    (the node's output handed to ``log`` when given)."""
    node = start_node(checkpoint, *params, quiet=quiet)
    probe = Probe(name)
    try:
        yield node, probe
    finally:
        probe.close()
        text = stop(node)
        if log is not None:
            log(text[-3000:])


def play_into(probe: Probe, bag: str, options: Sequence[str], timeout: float,
              settle_s: float = 2.5) -> float:
    """Play a bag while the probe spins, then spin ``settle_s`` more for the last outputs;
    :return: the playing time (s)."""
    player = start_player(bag, *options)
    try:
        played = probe.spin_while_running(player, timeout)
        probe.spin_for(settle_s)
    finally:
        stop(player)
    return played

