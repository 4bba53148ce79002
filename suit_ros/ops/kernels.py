"""Compiled per-point loops (numba): the work that grows with the points of a sweep.

A 64-beam sensor puts about 115k points in a sweep and the model reads three sweeps, so every
pass over the model input touches 340k points. In numpy or torch each step of such a pass
(a mask, a gather, a product, a scatter) writes a temporary of the whole cloud; here one loop
does the step's work in a single pass, without temporaries. Each kernel computes what the
array code it replaces computed, in the same float32 operations and order (the tests compare
them), so outputs do not change:

- :func:`transform_sweep`: a sweep moved into base_link and tagged with its time lag
  (:func:`suit_ros.model.sweeps.accumulate_sweeps`);
- :func:`pillar_max`: dynamic pillarization and the folded pillar encoder's per-pillar max
  (:class:`suit_ros.model.pillars.PillarEncoder`, inference);
- :func:`bucket_points`: the points in marked cells of a coarse grid, sorted by cell
  (:class:`suit_ros.ops.geometry.CellIndex`, used by the box point counts and the tracker);
- :func:`distinct_values`: the distinct time lags of a model input.

Compiled on first use and cached on disk beside this module (or in numba's user cache when
the package folder is read-only); :func:`warm_up` compiles them all, as the node does at start.
"""
from __future__ import annotations

from typing import Any

import numba
import numpy as np
from numpy.typing import NDArray

# ``contract`` lets LLVM fuse a multiply and an add into one FMA: the per-point product of the
# pillar encoder then rounds as torch's float32 matmul does on this CPU (the tests compare)
_jit = numba.njit(cache=True, nogil=True)
_jit_fma = numba.njit(cache=True, nogil=True, fastmath={'contract'})


@_jit
def transform_sweep(src: Any, R: Any, t: Any, lag: Any, out: Any) -> None:  # pragma: no cover
    """``out[:, :3] = src[:, :3] @ R.T + t``, intensity copied, ``out[:, 4]`` the sweep's lag
    (added to the point's own lag when ``src`` has a fifth column). All float32."""
    n = src.shape[0]
    has_lag = src.shape[1] == 5
    for i in range(n):
        x = src[i, 0]
        y = src[i, 1]
        z = src[i, 2]
        for r in range(3):
            out[i, r] = (x * R[r, 0] + y * R[r, 1] + z * R[r, 2]) + t[r]
        out[i, 3] = src[i, 3]
        out[i, 4] = src[i, 4] + lag if has_lag else lag


@_jit
def _pillar_ids(points: Any, lo: Any, hi: Any, size: Any, nx: int, ny: int
                ) -> tuple[Any, Any]:  # pragma: no cover
    """Each point's pillar (-1 out of range; pillars numbered in order of first appearance)
    and each pillar's cell ``iy * nx + ix``."""
    n = points.shape[0]
    cell_pillar = np.full(nx * ny, -1, np.int64)
    pid = np.empty(n, np.int64)
    U = 0
    for i in range(n):
        x = points[i, 0]
        y = points[i, 1]
        z = points[i, 2]
        if (x >= lo[0] and x < hi[0] and y >= lo[1] and y < hi[1]
                and z >= lo[2] and z < hi[2]):
            ix = min(int((x - lo[0]) / size), nx - 1)
            iy = min(int((y - lo[1]) / size), ny - 1)
            k = iy * nx + ix
            p = cell_pillar[k]
            if p < 0:
                p = U
                cell_pillar[k] = p
                U += 1
            pid[i] = p
        else:
            pid[i] = -1
    cells = np.empty(U, np.int64)
    for k in range(nx * ny):
        if cell_pillar[k] >= 0:
            cells[cell_pillar[k]] = k
    return pid, cells


@_jit_fma
def _pillar_reduce(points: Any, pid: Any, U: int, A: Any) -> tuple[Any, Any]:  # pragma: no cover
    """Per pillar: the mean of its points' xyz and the max over its points of ``p @ A``."""
    n, F = points.shape
    C = A.shape[1]
    count = np.zeros(U, np.float32)
    mean = np.zeros((U, 3), np.float32)
    top = np.full((U, C), -np.inf, np.float32)
    z = np.empty(C, np.float32)
    for i in range(n):
        p = pid[i]
        if p < 0:
            continue
        count[p] += np.float32(1.0)
        for j in range(3):
            mean[p, j] += points[i, j]
        for c in range(C):
            z[c] = np.float32(0.0)
        for f in range(F):
            v = points[i, f]
            for c in range(C):
                z[c] += v * A[f, c]
        row = top[p]
        for c in range(C):
            row[c] = max(row[c], z[c])
    for p in range(U):
        for j in range(3):
            mean[p, j] = mean[p, j] / count[p]
    return mean, top


def pillar_max(points: NDArray[np.float32], point_range: tuple[float, ...], size: float,
               nx: int, ny: int, A: NDArray[np.float32]
               ) -> tuple[NDArray[np.int64], NDArray[np.float32], NDArray[np.float32]]:
    """Pillarize one cloud and reduce it per pillar, in two passes over its points.

    :param points: ``(N, F)`` float32, x, y, z first.
    :param point_range: x0, y0, z0, x1, y1, z1; a point is in range when ``lo <= p < hi``.
    :param A: ``(F, C)`` float32, the per-point linear map.
    :return: each occupied pillar's cell ``iy * nx + ix`` ``(U,)``, its points' mean xyz
        ``(U, 3)`` and ``max_i points[i] @ A`` over its points ``(U, C)``, pillars in order
        of first appearance.
    """
    r = np.asarray(point_range, np.float32)
    pts = np.ascontiguousarray(points, np.float32)
    pid, cells = _pillar_ids(pts, r[:3], r[3:], np.float32(size), int(nx), int(ny))
    mean, top = _pillar_reduce(pts, pid, len(cells), np.ascontiguousarray(A, np.float32))
    return cells, mean, top


@_jit
def _bucket(x: Any, y: Any, inv_cell: Any, origin: Any, shape: Any, marked: Any,
            z: Any, zlo: Any, zhi: Any, use_z: bool) -> tuple[Any, Any]:  # pragma: no cover
    n = x.shape[0]
    flat = np.empty(n, np.int64)
    m = 0
    idx = np.empty(n, np.int64)
    counts = np.zeros(shape[0] * shape[1] + 1, np.int64)
    for i in range(n):
        if use_z and not (z[i] > zlo and z[i] < zhi):
            continue
        ix = np.int64(np.floor(x[i] * inv_cell)) - origin[0]
        iy = np.int64(np.floor(y[i] * inv_cell)) - origin[1]
        if ix < 0 or ix >= shape[0] or iy < 0 or iy >= shape[1]:
            continue
        k = ix * shape[1] + iy
        if not marked[k]:
            continue
        idx[m] = i
        flat[m] = k
        counts[k + 1] += 1
        m += 1
    # a counting sort by cell, stable (points of a cell in cloud order)
    for k in range(1, counts.shape[0]):
        counts[k] += counts[k - 1]
    order = np.empty(m, np.int64)
    keys = np.empty(m, np.int64)
    for j in range(m):
        k = flat[j]
        pos = counts[k]
        order[pos] = idx[j]
        keys[pos] = k
        counts[k] = pos + 1
    return order, keys


def bucket_points(xy: NDArray[np.floating[Any]], cell: float, origin: NDArray[np.int64],
                  shape: NDArray[np.int64], marked: NDArray[np.bool_],
                  z_range: tuple[float, float] | None = None, z_column: int = 2
                  ) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """The points whose cell ``floor(xy / cell) - origin`` lies in the grid ``shape`` and is
    ``marked`` (row-major flat index ``ix * shape[1] + iy``), sorted by cell, stably.

    :param xy: ``(N, >= 2)`` float32 or float64 points; the product ``xy * (1 / cell)`` is
        taken in their dtype, as numpy does.
    :param z_range: keep only points with ``lo < p[:, z_column] < hi``.
    :return: the points' indices into ``xy`` and their cells, both ``(K,)``.
    """
    p = np.asarray(xy)
    if p.dtype not in (np.float32, np.float64):
        p = p.astype(np.float64)
    use_z = z_range is not None
    zlo, zhi = z_range if z_range is not None else (0.0, 0.0)
    z = p[:, z_column] if use_z else p[:, 0]
    dt = p.dtype.type
    return _bucket(p[:, 0], p[:, 1], dt(1.0 / cell), np.asarray(origin, np.int64),
                   np.asarray(shape, np.int64), np.ascontiguousarray(marked, np.bool_),
                   z, dt(zlo), dt(zhi), use_z)


@_jit
def _distinct(values: Any, limit: int) -> Any:  # pragma: no cover
    found = np.empty(limit, values.dtype)
    m = 0
    for i in range(values.shape[0]):
        v = values[i]
        if v != v:
            continue
        seen = False
        for j in range(m):
            if found[j] == v:
                seen = True
                break
        if not seen:
            if m == limit:
                return found[:0]
            found[m] = v
            m += 1
    return np.sort(found[:m])


def distinct_values(values: NDArray[Any], limit: int = 64) -> NDArray[Any]:
    """``np.unique(values)`` (NaNs left out) in one pass when there are at most ``limit``
    distinct values (a model input's time lags: one per sweep); ``np.unique`` otherwise."""
    v = np.asarray(values)
    if len(v) == 0:
        return v[:0]
    out: NDArray[Any] = _distinct(v, limit)
    if len(out) == 0:
        out = np.unique(v[~np.isnan(v)]) if v.dtype.kind == 'f' else np.unique(v)
    return out


def warm_up() -> None:
    """Compile (or load from the cache) every kernel for the dtypes the node uses."""
    pts = np.zeros((2, 5), np.float32)
    transform_sweep(pts[:, :4], np.eye(3, dtype=np.float32), np.zeros(3, np.float32),
                    np.float32(0.0), pts.copy())
    transform_sweep(pts, np.eye(3, dtype=np.float32), np.zeros(3, np.float32),
                    np.float32(0.0), pts.copy())
    pillar_max(pts, (-1.0, -1.0, -1.0, 1.0, 1.0, 1.0), 0.5, 4, 4, np.zeros((5, 2), np.float32))
    marked = np.ones(4, bool)
    for arr in (pts, pts.astype(np.float64)):
        bucket_points(arr, 1.0, np.zeros(2, np.int64), np.array([2, 2]), marked)
        bucket_points(arr, 1.0, np.zeros(2, np.int64), np.array([2, 2]), marked, (0.0, 1.0))
    distinct_values(pts[:, 4])
