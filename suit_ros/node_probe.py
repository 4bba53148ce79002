"""End-to-end node latency through DDS: the demo bag played into a detector process."""
from __future__ import annotations

import os
import subprocess
import sys
import time
from typing import Any

import numpy as np


def node_latency(checkpoint: str = '', rate: float = 1.0, frames: int = 100,
                 seed: int = 7, workdir: str = 'out/demo', threads: int = 0,
                 precision: str = 'auto', sensor: str = 'sim32') -> dict[str, Any]:
    """Play the demo drive (as ``sensor`` sees it) at ``rate`` x 10 Hz into a fresh node;
    measure cloud-received -> detections-received latency at a probe, the output rate, drops,
    the node's overhead and its CPU use (cores: the process's CPU time over the playback).

    :param threads: the node's ``threads`` parameter (0: its default, all cores but one).
    :param precision: the node's ``precision`` parameter.
    """
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.utilities import try_shutdown

    from suit_ros.checkpoint import default_checkpoint_path
    from suit_ros.rosenv import local_ros_env
    env = local_ros_env()
    os.environ.update(env)
    bag = demo_bag(workdir, seed, frames, sensor)
    ckpt = checkpoint or str(default_checkpoint_path())
    node = subprocess.Popen([sys.executable, '-m', 'suit_ros.node', '--ros-args', '-p',
                             f'checkpoint:={ckpt}', '-p', f'threads:={threads}', '-p',
                             f'precision:={precision}'],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    ctx = Context()
    rclpy.init(context=ctx)
    probe = rclpy.create_node('suit_ros_bench_probe', context=ctx)
    rec = OutputRecorder(probe)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(probe)
    try:
        end = time.monotonic() + 90
        while not rec.diags and time.monotonic() < end:
            ex.spin_once(timeout_sec=0.1)
        player = subprocess.Popen([sys.executable, '-m', 'suit_ros.cli', 'play', bag,
                                   '--rate', str(rate), '--start-delay', '1.0',
                                   '--wait-subscribers', '20',
                                   '--topics', '/points', '/odom'],
                                  env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        t0, cpu0 = time.monotonic(), process_cpu_s(node.pid)
        while player.poll() is None and time.monotonic() < end + 120:
            ex.spin_once(timeout_sec=0.02)
        t_play = time.monotonic() - t0
        cores = (process_cpu_s(node.pid) - cpu0) / max(t_play, 1e-9)
        settle = time.monotonic() + 2.5
        while time.monotonic() < settle:
            ex.spin_once(timeout_sec=0.05)
    finally:
        ex.shutdown()
        probe.destroy_node()
        try_shutdown(context=ctx)
        node.terminate()
        node.wait(10)
    return {'node_threads': threads, 'node_precision': precision, 'sensor': sensor,
            'cpu_cores': cores, **_summary(rec.clouds, {k: t for k, (t, _) in rec.dets.items()},
                       rec.diags[-1] if rec.diags else {}, t_play)}


class OutputRecorder:
    """What a probe node sees of a running detector: when each input cloud and each
    detections message arrived (monotonic s, by header stamp; detections parsed) and the
    detector's diagnostics values. The demo and the node benchmark record with it."""

    def __init__(self, probe: Any) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.qos import QoSProfile, QoSReliabilityPolicy
        from sensor_msgs.msg import PointCloud2
        self.clouds: dict[int, float] = {}
        self.dets: dict[int, tuple[float, dict[str, Any]]] = {}
        self.diags: list[dict[str, str]] = []
        probe.create_subscription(PointCloud2, '/points', self._on_cloud,
                                  QoSProfile(depth=10,
                                             reliability=QoSReliabilityPolicy.RELIABLE))
        probe.create_subscription(PointCloud2, '/detector/detections', self._on_detections, 50)
        probe.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics, 10)

    @staticmethod
    def _key(m: Any) -> int:
        return int(m.header.stamp.sec) * 10**9 + int(m.header.stamp.nanosec)

    def _on_cloud(self, m: Any) -> None:
        self.clouds.setdefault(self._key(m), time.monotonic())

    def _on_detections(self, m: Any) -> None:
        from suit_ros.msg_adapters.detections import pointcloud2_to_detections
        received = time.monotonic()
        self.dets.setdefault(self._key(m), (received, pointcloud2_to_detections(m)))

    def _on_diagnostics(self, m: Any) -> None:
        self.diags.append({kv.key: kv.value for kv in m.status[0].values})


def demo_bag(workdir: str, seed: int, frames: int, sensor: str = 'sim32') -> str:
    """The demo drive's bag as ``sensor`` sees it (written once, then reused)."""
    from suit_ros.data.sim import preset
    from suit_ros.data.simulate_cli import write_bag
    name = f'demo-seed{seed}-{frames}f' + ('' if sensor == 'sim32' else f'-{sensor}')
    bag = os.path.join(workdir, name)
    if not os.path.exists(bag):
        os.makedirs(workdir, exist_ok=True)
        write_bag(bag, preset('demo-real', frames=frames, sensor=sensor), seed, 'mcap')
    return bag


def process_cpu_s(pid: int) -> float:
    """User + system CPU seconds a process has used (Linux ``/proc``; nan elsewhere)."""
    try:
        fields = open(f'/proc/{pid}/stat', encoding='ascii').read().rsplit(')', 1)[1].split()
    except OSError:
        return float('nan')
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


def _summary(clouds: dict[int, float], dets: dict[int, float], last: dict[str, str],
             t_play: float) -> dict[str, Any]:
    """Frames, rate, latency at the probe (cloud received -> detections received), the
    node's model time and its overhead."""
    lat = [dets[s] - clouds[s] for s in dets if s in clouds]
    model = float(last.get('model_ms_p50', 'nan'))
    overhead = sum(float(last.get(k, 'nan')) for k in ('convert_ms_p50', 'publish_ms_p50'))
    return {'frames_in': len(clouds), 'frames_out': len(dets),
            'dropped': int(last.get('dropped_frames', -1)),
            'rate_hz': len(dets) / max(t_play - 1.0, 1e-9),
            'latency_ms_p50': float(np.median(lat)) * 1e3 if lat else float('nan'),
            'latency_ms_p95': float(np.percentile(lat, 95)) * 1e3 if lat else float('nan'),
            'model_ms_p50': model, 'overhead_pct': 100.0 * overhead / model if model else 0.0}
