"""End-to-end node latency through DDS: the demo bag played into a detector process."""
from __future__ import annotations

import os
import time
from typing import Any

import numpy as np


def node_latency(checkpoint: str = '', rate: float = 1.0, frames: int = 100,
                 seed: int = 7, workdir: str = 'out/demo', threads: int = 0,
                 precision: str = 'auto', sensor: str = 'sim32', densify: float = 1.0
                 ) -> dict[str, Any]:
    """Play the demo drive (as ``sensor`` sees it, ``densify`` x its points) at ``rate`` x
    10 Hz into a fresh node; measure cloud-received -> detections-received latency at a probe
    (and the node's own, from its diagnostics: stamp or receipt -> published), the output
    rate, drops, the node's overhead and its CPU use (cores: the process's CPU time over the
    playback).

    :param threads: the node's ``threads`` parameter (0: its default, all cores but one).
    :param precision: the node's ``precision`` parameter.
    """
    from suit_ros.checkpoint import default_checkpoint_path
    from suit_ros.harness import node_and_probe, play_into, wait_ready
    from suit_ros.rosenv import local_ros_env
    os.environ.update(local_ros_env())
    bag = demo_bag(workdir, seed, frames, sensor, densify=densify)
    ckpt = checkpoint or str(default_checkpoint_path())
    with node_and_probe(ckpt, f'threads:={threads}', f'precision:={precision}',
                        name='suit_ros_bench_probe', quiet=True) as (node, probe):
        rec = OutputRecorder(probe.node)
        wait_ready(probe, node, lambda: bool(rec.diags), 90)
        rec.pid = node.pid
        before = cpu_jiffies()
        play_into(probe, bag, ['--rate', str(rate), '--start-delay', '1.0',
                               '--wait-subscribers', '20', '--topics', '/points', '/odom'],
                  120, settle_s=0.0)
        probe.spin_for(2.5)
        after = cpu_jiffies()
    return {'node_threads': threads, 'node_precision': precision, 'sensor': sensor,
            'densify': densify, 'cpu_cores': rec.cores,
            # the share of the machine's CPU time the hypervisor gave to others (a virtual
            # machine's steal): above a few percent the node's tail latency is not its own
            'cpu_steal_pct': steal_pct(before, after), **_summary(rec.clouds,
                                               {k: t for k, (t, _) in rec.dets.items()},
                                               rec.diags[-1] if rec.diags else {})}


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
        # set to the detector's process id: its CPU time is read at the first cloud and at
        # each detections message (the playback window, not the player's start-up)
        self.pid: int | None = None
        self._first_cpu: tuple[float, float] | None = None
        self._last_cpu: tuple[float, float] | None = None
        probe.create_subscription(PointCloud2, '/points', self._on_cloud,
                                  QoSProfile(depth=10,
                                             reliability=QoSReliabilityPolicy.RELIABLE))
        probe.create_subscription(PointCloud2, '/detector/detections', self._on_detections, 50)
        probe.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics, 10)

    @staticmethod
    def _key(m: Any) -> int:
        return int(m.header.stamp.sec) * 10**9 + int(m.header.stamp.nanosec)

    @property
    def cores(self) -> float:
        """The detector's CPU use (cores) from the first cloud to the last detections."""
        if self._first_cpu is None or self._last_cpu is None:
            return float('nan')
        (t0, c0), (t1, c1) = self._first_cpu, self._last_cpu
        return (c1 - c0) / max(t1 - t0, 1e-9)

    def _cpu_sample(self) -> tuple[float, float] | None:
        return None if self.pid is None else (time.monotonic(), process_cpu_s(self.pid))

    def _on_cloud(self, m: Any) -> None:
        self.clouds.setdefault(self._key(m), time.monotonic())
        if self._first_cpu is None:
            self._first_cpu = self._cpu_sample()

    def _on_detections(self, m: Any) -> None:
        from suit_ros.msg_adapters.detections import pointcloud2_to_detections
        received = time.monotonic()
        self.dets.setdefault(self._key(m), (received, pointcloud2_to_detections(m)))
        self._last_cpu = self._cpu_sample()

    def _on_diagnostics(self, m: Any) -> None:
        self.diags.append({kv.key: kv.value for kv in m.status[0].values})


def demo_bag(workdir: str, seed: int, frames: int, sensor: str = 'sim32',
             progress: bool = False, densify: float = 1.0) -> str:
    """The demo drive's bag as ``sensor`` sees it, ``densify`` x its points (written once,
    then reused)."""
    from suit_ros.data.sim import preset
    from suit_ros.data.sim.recording import write_bag
    bag = os.path.join(workdir, f'demo-seed{seed}-{frames}f'
                       + ('' if sensor == 'sim32' else f'-{sensor}')
                       + ('' if densify == 1.0 else f'-x{densify:g}'))
    if not os.path.exists(bag):
        os.makedirs(workdir, exist_ok=True)
        if progress:
            print(f'[demo] simulating {frames} frames into {bag} ...', flush=True)
        write_bag(bag, preset('demo-real', frames=frames, sensor=sensor), seed, 'mcap',
                  progress=progress, densify=densify)
    return bag


def cpu_jiffies() -> tuple[int, int]:
    """The machine's steal and total CPU time so far (jiffies, ``/proc/stat``; zeros
    elsewhere)."""
    try:
        with open('/proc/stat', encoding='ascii') as f:
            fields = [int(v) for v in f.readline().split()[1:]]
    except (OSError, ValueError):
        return 0, 0
    return (fields[7] if len(fields) > 7 else 0), sum(fields[:8])


def steal_pct(before: tuple[int, int], after: tuple[int, int]) -> float:
    """Steal over the window between two :func:`cpu_jiffies` readings, percent of all CPU
    time (nan when unknown)."""
    total = after[1] - before[1]
    return 100.0 * (after[0] - before[0]) / total if total > 0 else float('nan')


def process_cpu_s(pid: int) -> float:
    """User + system CPU seconds a process has used (Linux ``/proc``; nan elsewhere)."""
    try:
        with open(f'/proc/{pid}/stat', encoding='ascii') as f:
            fields = f.read().rsplit(')', 1)[1].split()
    except OSError:
        return float('nan')
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


def _summary(clouds: dict[int, float], dets: dict[int, float], last: dict[str, str]
             ) -> dict[str, Any]:
    """Frames, rate (from the first cloud to the last detections), latency at the probe
    (cloud received -> detections received), the node's model time and its overhead."""
    lat = [dets[s] - clouds[s] for s in dets if s in clouds]
    span = max(dets.values()) - min(clouds.values()) if dets and clouds else 0.0
    model = float(last.get('model_ms_p50', 'nan'))
    overhead = sum(float(last.get(k, 'nan')) for k in ('convert_ms_p50', 'publish_ms_p50')) \
        + float(last.get('buffer_ms_p50', 0.0)) + float(last.get('markers_ms_p50', 0.0))
    return {'frames_in': len(clouds), 'frames_out': len(dets),
            'dropped': int(last.get('dropped_frames', -1)),
            # skipped clouds the node still took into the model's sweeps; the last input's
            'sweeps_only': int(last.get('frames_sweeps_only', -1)),
            'input_sweeps': last.get('input_sweeps', 'n/a'),
            'rate_hz': len(dets) / span if span > 0 else 0.0,
            'latency_ms_p50': float(np.median(lat)) * 1e3 if lat else float('nan'),
            'latency_ms_p95': float(np.percentile(lat, 95)) * 1e3 if lat else float('nan'),
            'node_latency_ms_p50': float(last.get('latency_ms_p50', 'nan')),
            'node_latency_ms_p95': float(last.get('latency_ms_p95', 'nan')),
            # from the header stamp, or from receipt when the stamps are off the node clock
            # (the demo bag's are from 2023): then the transport is not in it
            'node_latency_from': ('stamp' if last.get('latency_reference') == 'header stamp'
                                  else 'receipt'),
            'model_ms_p50': model, 'overhead_pct': 100.0 * overhead / model if model else 0.0}
