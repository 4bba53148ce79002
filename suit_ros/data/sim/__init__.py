"""The embedded synthetic LiDAR world: town layout, actors, ego drive, ray-cast LiDAR, GT.

``simulate(config, seed)`` yields :class:`SimFrame` s; ``sim_frames(config, seed)`` yields
model-ready :class:`suit_ros.structures.Frame` s;
:func:`suit_ros.data.sim.recording.write_bag` writes a rosbag2 bag.
"""
from suit_ros.data.sim.config import PRESETS, LidarConfig, Realism, SimConfig, preset
from suit_ros.data.sim.scene import SimFrame, sim_frames, simulate

__all__ = ['LidarConfig', 'PRESETS', 'Realism', 'SimConfig', 'SimFrame', 'preset', 'sim_frames',
           'simulate']
