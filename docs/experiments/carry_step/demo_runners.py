"""The setup the step scripts of this folder share: THREADS and FRAMES from the command line,
the demo drive's step inputs, and streaming detectors (tracker on, precision auto) by name.
"""
import sys
from typing import Any

import torch

from suit_ros.checkpoint import load_model_as
from suit_ros.data.sim import preset
from suit_ros.data.sim.scene import Simulation, to_frame
from suit_ros.evaluate import step_inputs
from suit_ros.heap import keep_freed_memory
from suit_ros.model.streaming import StreamingDetector
from suit_ros.tracking import TrackerConfig


def demo_runners(models: dict[str, tuple[str, str | None]]
                 ) -> tuple[int, int, list[Any], dict[str, StreamingDetector]]:
    """``(threads, frames, step inputs, runners)``; ``models``: name -> (shipped checkpoint
    name, temporal mode or None for the checkpoint's own)."""
    keep_freed_memory()
    threads, n = int(sys.argv[1]), int(sys.argv[2])
    torch.set_num_threads(threads)
    sim = Simulation(preset('demo-real', frames=n), 7)
    inputs = [step_inputs(to_frame(sim.render(k), 7)) for k in range(n)]
    runners = {k: StreamingDetector(
        load_model_as(f'suit_ros/checkpoints/{c}.safetensors', t), 'cpu', precision='auto',
        tracker=TrackerConfig()) for k, (c, t) in models.items()}
    return threads, n, inputs, runners
