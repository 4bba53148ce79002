"""A/B: the same model stepping the same demo frames in two source trees (git worktrees),
frame by frame in turn; prints each tree's stage medians (frames 5+), the total ratio and the
largest box difference over the frames whose box counts agree.

Usage: THREADS=1 python ab.py MODEL FRAMES TREE_A TREE_B [SENSOR]
"""
import json
import os
import subprocess
import sys

import numpy as np

name, n, trees = sys.argv[1], int(sys.argv[2]), sys.argv[3:5]
sensor = sys.argv[5] if len(sys.argv) > 5 else 'sim32'
worker = os.path.join(os.path.dirname(os.path.abspath(__file__)), 'worker.py')
procs = []
for tree in trees:
    p = subprocess.Popen([sys.executable, worker, name, str(n), sensor], cwd=tree,
                         env=dict(os.environ, PYTHONPATH=tree), stdin=subprocess.PIPE,
                         stdout=subprocess.PIPE, text=True)
    assert p.stdout is not None and p.stdout.readline().strip() == 'ready'
    procs.append(p)
times: list[dict[str, list[float]]] = [{} for _ in trees]
worst, same = 0.0, 0
for i in range(n):
    outs = []
    for k, p in enumerate(procs):
        assert p.stdin is not None and p.stdout is not None
        p.stdin.write(f'{i}\n')
        p.stdin.flush()
        out = json.loads(p.stdout.readline())
        outs.append(out)
        if i >= 4:
            for key, v in out['t'].items():
                times[k].setdefault(key, []).append(v)
    a, b = outs
    if len(a['scores']) != len(b['scores']):
        print('frame', i, 'box counts', len(a['scores']), len(b['scores']))
        continue
    same += 1
    if a['scores']:
        worst = max(worst, float(np.abs(np.array(a['boxes']) - np.array(b['boxes'])).max()))
for tree, t in zip(trees, times):
    print(tree, ' '.join(f'{key} {np.median(v):.1f}' for key, v in t.items()))
print(f"total B/A {np.median(times[1]['total']) / np.median(times[0]['total']):.3f}; "
      f'frames with equal box counts {same} of {n}; largest box difference {worst:.2g}')
for p in procs:
    assert p.stdin is not None
    p.stdin.close()
    p.wait()
