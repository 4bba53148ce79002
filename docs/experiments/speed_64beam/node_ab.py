import os, sys
from suit_ros.node_probe import node_latency
os.environ['PYTHONPATH'] = sys.argv[1]
r = node_latency(rate=1.0, sensor=sys.argv[2] if len(sys.argv) > 2 else 'hdl64e', workdir='/tmp/exp/nodebench')
print({k: round(v, 2) if isinstance(v, float) else v for k, v in r.items()})
