"""Compare two `same_outputs.py` files: how many arrays differ, the largest float difference.

Usage: python compare_outputs.py BEFORE.npz AFTER.npz [NAME ...]
"""
import sys

import numpy as np

a, b = np.load(sys.argv[1]), np.load(sys.argv[2])
names = sys.argv[3:]
keys = [k for k in b.files if not names or k.split('/')[0] in names]
differ, worst = 0, 0.0
for k in keys:
    x, y = a[k], b[k]
    if x.shape != y.shape:
        print('shape', k, x.shape, y.shape)
        differ += 1
    elif x.dtype.kind == 'f':
        d = float(np.abs(x - y).max()) if x.size else 0.0
        worst = max(worst, d)
        differ += d > 0
    elif not np.array_equal(x, y):
        print('differs', k)
        differ += 1
print(f'{len(keys)} arrays, {differ} differ, largest float difference {worst:g}')
