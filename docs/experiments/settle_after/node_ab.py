"""The node through DDS at 10 Hz on the demo drive (37k points; `suit-ros bench`'s node run):
latency at a subscriber and in the node, p50, CPU cores. Run in two trees in turn.

Usage: python node_ab.py CHECKPOINT
"""
import sys

from suit_ros.node_probe import node_latency

v = node_latency(sys.argv[1], rate=1.0, frames=100)
print(f"{sys.argv[1]}: subscriber p50 {v['latency_ms_p50']:.1f} p95 {v['latency_ms_p95']:.1f} ms, "
      f"node p50 {v['node_latency_ms_p50']:.1f} p95 {v['node_latency_ms_p95']:.1f} ms, model "
      f"{v['model_ms_p50']:.1f} ms, CPU {v.get('cpu_cores', float('nan')):.2f} cores, "
      f"{v['frames_out']}/{v['frames_in']} out", flush=True)
