"""What the probes of this page share: which pedestrians of a validation drive stand at a front."""
import numpy as np

from suit_ros import CLASS_NAMES
from suit_ros.data.sim import preset
from suit_ros.data.sim.scene import Simulation

PED = CLASS_NAMES.index('pedestrian')


def at_fronts(seed: int, sensor: str, frames: int = 40) -> set[int]:
    """The instance ids of the pedestrians that ``val-fronts`` moves in front of a building
    (those that stand elsewhere than in the same drive of ``val-street-ends``)."""
    plain = Simulation(preset('val-street-ends', sensor=sensor, frames=frames), seed).actors
    there = Simulation(preset('val-fronts', sensor=sensor, frames=frames), seed).actors
    return {b.instance_id for a, b in zip(plain, there)
            if b.label == PED and not np.array_equal(a.poly, b.poly)}
