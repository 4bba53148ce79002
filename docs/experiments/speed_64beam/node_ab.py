#!/usr/bin/env python3
"""The node over DDS at 10 Hz (every default) on the demo drive as an hdl64e sees it, the
harness of this commit driving the node of another: ``node_ab.py PYTHONPATH [SENSOR]``, run
from a folder without a ``suit_ros`` in it (the node's ``python -m`` puts the working folder
first), PYTHONPATH a worktree of the other commit (empty: this one)."""
import os
import sys

from suit_ros.node_probe import node_latency

os.environ['PYTHONPATH'] = sys.argv[1]
r = node_latency(rate=1.0, sensor=sys.argv[2] if len(sys.argv) > 2 else 'hdl64e',
                 workdir='/tmp/exp/nodebench')
print({k: round(v, 2) if isinstance(v, float) else v for k, v in r.items()})
