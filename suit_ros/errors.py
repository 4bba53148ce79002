"""The package's exceptions: each says what was wrong and what to do about it."""


class SuitRosError(Exception):
    """Base class of every error this package raises on purpose."""


class ConfigError(SuitRosError, ValueError):
    """A configuration file or parameter is invalid (unknown key, wrong type, out of range)."""


class CheckpointError(SuitRosError):
    """A checkpoint is missing, corrupt, foreign, or does not match the requested config."""


class BagError(SuitRosError):
    """A rosbag2 file cannot be read or lacks the topics a command needs."""


class DatasetError(SuitRosError):
    """A dataset on disk is missing files or is in a format this package does not read."""
