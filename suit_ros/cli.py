"""The ``suit-ros`` command line: one entry point, one module per subcommand.

Each subcommand lives in its own module, which defines ``configure_parser(parser)`` and
``run(args) -> int``. Modules are imported only when their subcommand runs, so ``suit-ros info``
does not pay for importing torch twice and a broken optional dependency breaks one command only.
"""
from __future__ import annotations

import argparse
from collections.abc import Sequence
import importlib
import sys

from suit_ros import __version__
from suit_ros.errors import SuitRosError

# name -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    'info': ('suit_ros.info', 'print versions of python, numpy, torch, rclpy, the RMW, devices'),
    'simulate': ('suit_ros.data.simulate_cli', 'write a synthetic LiDAR driving bag'),
    'train': ('suit_ros.train', 'train the detector (single-frame or SUIT)'),
    'eval': ('suit_ros.evaluate_cli', 'nuScenes-style mAP/NDS of detections against GT'),
    'report': ('suit_ros.report', 'what the node publishes on a labelled dataset: recall, '
               'precision, AP, headings, pictures'),
    'choose-thresholds': ('suit_ros.thresholds_cli', 'choose the per-class thresholds the node '
                          'publishes at (synthetic tune split) and store them'),
    'outage': ('suit_ros.outage', 'recall through sensor outages: what the memory carries'),
    'compare': ('suit_ros.compare', 'checkpoints and variants on the validation drives, '
                'paired intervals (--ablation: docs/results.md)'),
    'detect-bag': ('suit_ros.detect_bag', 'run the detector over a bag and write a bag'),
    'play': ('suit_ros.play', 'publish a bag into the live ROS graph'),
    'bench': ('suit_ros.bench', 'benchmark latency, memory and scaling'),
    'demo': ('suit_ros.demo', 'simulate, detect over DDS, evaluate and draw: the quick start'),
}


def build_parser() -> argparse.ArgumentParser:
    """Build the top-level parser with every available subcommand."""
    parser = argparse.ArgumentParser(
        prog='suit-ros', description='SUIT multi-frame LiDAR 3D detection for ROS 2.')
    parser.add_argument('--version', action='version', version=f'suit-ros {__version__}')
    sub = parser.add_subparsers(dest='command', metavar='COMMAND')
    for name, (module_name, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(_module=module_name)
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            if exc.name is not None and exc.name.startswith('suit_ros'):
                p.set_defaults(_unavailable=f'{name} is not available in this build')
                continue
            raise
        module.configure_parser(p)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the CLI; return the process exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    if getattr(args, '_unavailable', None):
        print(f'suit-ros: {args._unavailable}', file=sys.stderr)
        return 2
    module = importlib.import_module(args._module)
    try:
        return int(module.run(args) or 0)
    except SuitRosError as exc:
        print(f'suit-ros {args.command}: error: {exc}', file=sys.stderr)
        return 1
    except OSError as exc:      # a file or folder the command could not read or write
        print(f'suit-ros {args.command}: error: {exc}', file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f'suit-ros {args.command}: interrupted', file=sys.stderr)
        return 130


if __name__ == '__main__':
    sys.exit(main())
