"""The node over DDS (`suit_ros.node_probe.node_latency`, as `suit-ros bench` runs it) from two
source trees in turn: latency at a subscriber and CPU, per size, REPS times each.

Usage: [MARKERS=1] python ab_node.py BASE_TREE WORK_TREE REPS [SIZE ...]   (sizes: 37k 114k
260k; default 37k 114k; from a tree whose .venv has rclpy; MARKERS=1: a markers subscriber)
"""
import json
import os
import subprocess
import sys

SIZES = {'37k': ('sim32', 1.0), '114k': ('hdl64e', 1.0), '260k': ('hdl64e', 2.3)}
# MARKERS=1 in the environment: the probe also subscribes to the node's markers (as a viewer
# does), so that the node builds them
PATCH = ('import suit_ros.node_probe as P; from visualization_msgs.msg import MarkerArray; '
         'init = P.OutputRecorder.__init__; '
         'P.OutputRecorder.__init__ = lambda self, probe: (init(self, probe), '
         'probe.create_subscription(MarkerArray, "/detector/markers", lambda m: None, 10))'
         '[0]; ') if os.environ.get('MARKERS') == '1' else ''
CODE = PATCH + ('import json, sys; from suit_ros.node_probe import node_latency; '
        'r = node_latency("", rate=1.0, frames=int(sys.argv[3]), threads=0, '
        'precision="auto", sensor=sys.argv[1], densify=float(sys.argv[2])); '
        'print("RESULT " + json.dumps(r))')
base, work, reps = sys.argv[1], sys.argv[2], int(sys.argv[3])
for size in sys.argv[4:] or ['37k', '114k']:
    sensor, dense = SIZES[size]
    for rep in range(reps):
        for tree in (base, work):
            frames = '60' if size == '260k' else '100'
            out = subprocess.run([sys.executable, '-c', CODE, sensor, str(dense), frames],
                                 cwd=tree,
                                 env=dict(os.environ, PYTHONPATH=tree), capture_output=True,
                                 text=True, check=True).stdout
            r = json.loads(next(line for line in out.splitlines()
                                if line.startswith('RESULT '))[7:])
            keys = ('latency_ms_p50', 'latency_ms_p95', 'model_ms_p50', 'cpu_cores', 'frames_out')
            print(size, rep, os.path.basename(tree.rstrip('/')),
                  ' '.join(f'{k} {r.get(k)}' for k in keys), flush=True)
