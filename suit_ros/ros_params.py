"""The detector's parameters as ROS parameters: descriptors with ranges and choices, declared
and read in one place (:class:`~suit_ros.params.DetectorParams` owns names, defaults, ranges
and the read-only flags)."""
from __future__ import annotations

import os

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.node import Node

from suit_ros.errors import ConfigError, SuitRosError
from suit_ros.params import RENAMED, DetectorParams, parameter_descriptions, renamed_message


def descriptor(name: str) -> ParameterDescriptor:
    """The ParameterDescriptor of a :class:`DetectorParams` field."""
    m = parameter_descriptions()[name]
    d = ParameterDescriptor(description=m['description'], read_only=m['read_only'])
    if m['choices']:
        d.additional_constraints = 'one of: ' + ', '.join(m['choices'])
    if m['lo'] is not None:
        if isinstance(getattr(DetectorParams, name), int):
            d.integer_range = [IntegerRange(from_value=int(m['lo']), to_value=int(m['hi']),
                                            step=1)]
        else:
            d.floating_point_range = [FloatingPointRange(
                from_value=float(m['lo']), to_value=float(m['hi']), step=0.0)]
    return d


def declare_detector_parameters(node: Node) -> DetectorParams:
    """Declare every detector parameter on ``node`` and read them (not yet checked against
    the model's classes: :meth:`DetectorParams.validate`).

    :raises SuitRosError: a value of the wrong type or out of range, or a parameter given
        under a name it no longer has (rclpy would ignore it: the user's setting would be lost
        without a word).
    """
    old = sorted(_overrides(node) & set(RENAMED))
    if old:
        raise SuitRosError('renamed parameter(s): ' + '; '.join(map(renamed_message, old)))
    for name, value in DetectorParams().ros_values().items():
        try:
            node.declare_parameter(name, value, descriptor(name))
        except InvalidParameterTypeException as exc:
            kind = type(value).__name__
            hint = ' (a float needs a decimal point: 0.0, not 0)' if kind == 'float' else ''
            raise SuitRosError(f'parameter {name} must be a {kind}{hint}: {exc}') from exc
        except InvalidParameterValueException as exc:   # outside the descriptor's range
            m = parameter_descriptions()[name]
            allowed = (f'within {m["lo"]}..{m["hi"]}' if m['lo'] is not None
                       else 'one of ' + ', '.join(m['choices']) if m['choices'] else 'valid')
            raise SuitRosError(f'parameter {name} must be {allowed}: {exc}') from exc
    try:
        return DetectorParams.from_mapping(
            {n: node.get_parameter(n).value for n in parameter_descriptions()})
    except ConfigError as exc:
        raise SuitRosError(f'invalid parameters: {exc}') from exc


def _overrides(node: Node) -> set[str]:
    """The names of the parameters the launch gave ``node``."""
    # rclpy keeps them here; it has no public reader for them
    return set(getattr(node, '_parameter_overrides', {}))


def ignored_overrides(node: Node) -> list[str]:
    """The parameters the launch gave ``node`` that it never declared: rclpy drops them
    without a word (a misspelt name, a parameter of another node under ``/**``). Call it once
    every parameter is declared (the QoS overrides are declared with their endpoints)."""
    return sorted(name for name in _overrides(node) if not node.has_parameter(name))


def torch_threads(requested: int) -> int:
    """Torch threads for ``threads`` (0: every core this process may use but one)."""
    if requested > 0:
        return requested
    return max(1, len(os.sched_getaffinity(0)) - 1)


def limit_threads(threads: int) -> str:
    """Bound the process's compute threads to ``threads``: torch's, and numpy's BLAS pool,
    whose idle workers spin (``sched_yield``) after each large product: on a 2-core machine
    they took a core the ``threads`` parameter left to DDS (the node at 114k points used 1.6
    cores, 0.56 with them bound). Returns what was set, for the log."""
    import torch
    torch.set_num_threads(threads)
    try:
        from threadpoolctl import threadpool_info, threadpool_limits
    except ImportError:         # an install without it: torch bound, BLAS as it comes
        return f'{threads} torch threads (BLAS threads not bound: no threadpoolctl)'
    import numpy  # noqa: F401 - loaded: the limit reaches only libraries loaded already
    threadpool_limits(limits=threads, user_api='blas')   # for the process's lifetime
    found = [p for p in threadpool_info() if p['user_api'] == 'blas']
    return (f'{threads} torch threads, BLAS threads {threads}' if found
            else f'{threads} torch threads (no BLAS library found to bound)')
