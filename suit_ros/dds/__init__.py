"""DDS settings that ship with suit_ros: a Fast DDS profile for publishers of large messages.

See ``fastdds_large_data.xml`` beside this file for what it sets and why.
"""
from __future__ import annotations

from collections.abc import MutableMapping
from pathlib import Path

PROFILE_VARIABLES = ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE')
LARGE_DATA_PROFILE = Path(__file__).with_name('fastdds_large_data.xml')


def use_large_data_profile(env: MutableMapping[str, str]) -> str | None:
    """Point ``env`` at the large-data profile unless the user chose a profile already.

    Call it on ``os.environ`` before ``rclpy.init`` in a process that publishes point clouds
    (the participant reads the variable when it is created), or on a child's environment.

    :return: the profile path set, or None when a profile variable was already set.
    """
    if any(env.get(name) for name in PROFILE_VARIABLES):
        return None
    env['FASTRTPS_DEFAULT_PROFILES_FILE'] = str(LARGE_DATA_PROFILE)
    return str(LARGE_DATA_PROFILE)
