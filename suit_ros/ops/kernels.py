"""Compiled loops (numba): the work that grows with the points of a sweep, and small work.

A 64-beam sensor puts about 115k points in a sweep and the model reads three sweeps, so every
pass over the model input touches 340k points. In numpy or torch each step of such a pass
(a mask, a gather, a product, a scatter) writes a temporary of the whole cloud; here one loop
does the step's work without them. The same goes for the small work of a step that the
memory and the heads do at a few hundred cells or boxes, where each tensor operation's fixed
cost, not its arithmetic, was the time. Each kernel computes what the array code it replaced
computed, in the same floating-point operations and order (test/test_kernels.py compares
them bit for bit), except where a kernel says otherwise (:func:`add_tap_spread`,
:func:`sum_triples`, :func:`move_cells` and :func:`move_boxes` sum in another order;
:func:`add_tap_spread_dense_bf16` rounds each sum to bfloat16 where ``index_add_`` rounds the
addend first, and the dense spreads add the edge correction after the taps, the tensor code
before; :func:`greedy_bev_nms` and :func:`suppress_near_kernel` measure centre
distances in float64, where the tensor code's ``cdist`` could round a distance at its
threshold the other way):

- :func:`in_range`: the node's range filter of an incoming cloud;
- :func:`deskew_points`: a sweep's returns moved to where the sensor was at its stamp
  (:mod:`suit_ros.deskew`);
- :func:`transform_sweep`: a sweep moved into base_link and tagged with its time lag
  (:func:`suit_ros.model.sweeps.accumulate_sweeps`);
- :func:`pillar_max`: dynamic pillarization and the folded pillar encoder's per-pillar max
  and mean (:class:`suit_ros.model.pillars.PillarEncoder`, inference), and
  :func:`pillar_features`: its pillar features written into the pseudo-image;
- :func:`count_in_box_cells`: the points inside each box (the node's ``num_points``) and
  :func:`sweep_histograms_by_cell`: each vehicle's returns along its heading, per sweep (the
  tracker's velocity reading, :func:`suit_ros.tracking.sweep_velocities`), each in one pass
  over the points, every point tested against the boxes of its grid cell
  (:meth:`suit_ros.ops.geometry.CellIndex.box_lists`);
- :func:`distinct_values`: the distinct time lags of a model input;
- :func:`azimuth_counts`: a cloud's returns per azimuth bin (the node's sector-gap check,
  :mod:`suit_ros.coverage`; float64 angles, tested against numpy's in float64);
- :func:`paired_bev_iou`: rotated BEV IoU of box pairs, a loop per pair instead of some 60
  tensor operations, and :func:`greedy_bev_nms`: the greedy rotated-IoU NMS of the head and
  of the significance sampling in one pass, the IoU computed only for the pairs it reads;
  :func:`suppress_near_kernel`: the carried boxes dropped near surer ones;
- :func:`gather_taps` (and :func:`gather_taps_bf16`): the 3 x 3 neighbourhoods of a few
  hundred cells of a BEV map, where the heads run as gathered products (float32 out, a
  bfloat16 map's values exactly), :func:`dilate_flat_cells`: the cells around them (less
  the observed ones: those a carry head answers), :func:`feeding_map`: the cells that feed
  those, and :func:`add_tap_spread` (:func:`add_tap_spread_dense` and
  :func:`add_tap_spread_dense_bf16` over a whole map): a sparse past term through a 3 x 3
  layer at those cells;
- :func:`sum_triples`: the sparse past term's weighted features summed per destination cell
  (projected afterwards, once per cell: the same sums up to float rounding);
  :func:`move_cells` and :func:`move_boxes`: a memory's samples moved by ego motion;
  :func:`flags_at`: a flag map read at metric positions; :func:`carry_selection`: which
  samples, this frame's and the carried ones, the next memory keeps; :func:`pool_occupancy`:
  the head cells with returns, grown by the gate's radius;
- :func:`height_histograms` and :func:`level_heights`: the local ground under a model input
  and the input leveled to it (:mod:`suit_ros.ground`, ``ground: local``; new computations,
  tested against numpy);
- :func:`overhang_keep`: the returns that hang over the street, left out of a model input
  (:mod:`suit_ros.overhang`, ``overhang: drop``; tested against numpy).

Compiled on first use (:func:`compiled`) and cached on disk; :func:`warm_up` compiles the
types a detector step uses, as the node does at start.
"""
from __future__ import annotations

from collections.abc import Callable
import math
from typing import Any, TypeVar, cast

import numba
import numpy as np
from numpy.typing import NDArray

F = TypeVar('F', bound=Callable[..., Any])


def compiled(fastmath: set[str] | None = None) -> Callable[[F], F]:
    """``numba.njit`` (GIL released), cached on disk where numba finds a writable place
    (beside the module, or the user's cache folder; ``NUMBA_CACHE_DIR`` chooses one); where
    none is (a read-only install and home), compiled in each process instead of failing.

    :param fastmath: LLVM fast-math flags; ``{'contract'}`` lets a multiply and an add fuse
        into one FMA, which is how the float32 matmul rounds on this CPU (the tests compare).
    """
    def wrap(fn: F) -> F:
        try:
            return cast(F, numba.njit(cache=True, nogil=True, fastmath=fastmath or False)(fn))
        except RuntimeError:                  # "cannot cache function ...: no locator"
            return cast(F, numba.njit(cache=False, nogil=True, fastmath=fastmath or False)(fn))
    return wrap


_jit = compiled()
_jit_fma = compiled({'contract'})


@_jit_fma
def transform_sweep(src: Any, R: Any, t: Any, lag: Any, out: Any) -> None:  # pragma: no cover
    """``out[:, :3] = src[:, :3] @ R.T + t``, intensity copied, ``out[:, 4]`` the sweep's lag
    (added to the point's own lag when ``src`` has a fifth column). All float32; the product
    is a chain of FMAs from zero, as the float32 matmul computes it, then ``t`` is added."""
    n = src.shape[0]
    has_lag = src.shape[1] == 5
    for i in range(n):
        x = src[i, 0]
        y = src[i, 1]
        z = src[i, 2]
        for r in range(3):
            out[i, r] = (((np.float32(0.0) + x * R[r, 0]) + y * R[r, 1]) + z * R[r, 2]) + t[r]
        out[i, 3] = src[i, 3]
        out[i, 4] = src[i, 4] + lag if has_lag else lag


@_jit
def _pillar_ids(points: Any, lo: Any, hi: Any, size: Any, nx: int, ny: int, keep: Any
                ) -> tuple[Any, Any]:  # pragma: no cover
    """Each point's pillar (-1 out of range, or not kept where ``keep`` has entries; pillars
    numbered in order of first appearance) and each pillar's cell ``iy * nx + ix``."""
    n = points.shape[0]
    masked = keep.shape[0] > 0
    cell_pillar = np.full(nx * ny, -1, np.int32)
    pid = np.empty(n, np.int32)
    U = 0
    l0, l1, l2, h0, h1, h2 = lo[0], lo[1], lo[2], hi[0], hi[1], hi[2]     # once, not per point
    for i in range(n):
        x = points[i, 0]
        y = points[i, 1]
        z = points[i, 2]
        pid[i] = -1
        if masked and not keep[i]:
            continue
        if x >= l0 and x < h0 and y >= l1 and y < h1 and z >= l2 and z < h2:
            k = min(int((y - l1) / size), ny - 1) * nx + min(int((x - l0) / size), nx - 1)
            if cell_pillar[k] < 0:
                cell_pillar[k] = U
                U += 1
            pid[i] = cell_pillar[k]
    cells = np.empty(U, np.int64)
    for k in range(nx * ny):
        if cell_pillar[k] >= 0:
            cells[cell_pillar[k]] = k
    return pid, cells


@_jit_fma
def _pillar_reduce(points: Any, pid: Any, U: int, A: Any) -> tuple[Any, Any]:  # pragma: no cover
    """Per pillar: the mean of its points' xyz and the max over its points of ``p @ A``.

    The five features of a point are summed in their order, as a matmul does; the loop over
    the ``C`` outputs is innermost, so it runs in SIMD lanes (``contract`` fuses only the
    multiply-adds of that sum).
    """
    n = points.shape[0]
    C = A.shape[1]
    count = np.zeros(U, np.float32)
    mean = np.zeros((U, 3), np.float32)
    top = np.full(U * C, -np.inf, np.float32)
    a = A.ravel()
    for i in range(n):
        p = pid[i]
        if p < 0:
            continue
        count[p] += np.float32(1.0)
        x0 = points[i, 0]
        x1 = points[i, 1]
        x2 = points[i, 2]
        x3 = points[i, 3]
        x4 = points[i, 4]
        mean[p, 0] += x0
        mean[p, 1] += x1
        mean[p, 2] += x2
        base = p * C
        for c in range(C):
            v = ((((np.float32(0.0) + x0 * a[c]) + x1 * a[C + c]) + x2 * a[2 * C + c])
                 + x3 * a[3 * C + c]) + x4 * a[4 * C + c]
            if v > top[base + c]:
                top[base + c] = v
    for p in range(U):
        for j in range(3):
            mean[p, j] = mean[p, j] / count[p]
    return mean, top.reshape(U, C)


@_jit_fma
def _mean_product(mean: Any, B: Any) -> Any:  # pragma: no cover
    """``mean @ B`` for ``(U, 3)`` and ``(3, C)`` float32, each entry a chain of FMAs from
    zero over the three terms, as the float32 matmul computes it."""
    U = mean.shape[0]
    C = B.shape[1]
    out = np.empty((U, C), np.float32)
    for p in range(U):
        m0 = mean[p, 0]
        m1 = mean[p, 1]
        m2 = mean[p, 2]
        for c in range(C):
            out[p, c] = ((np.float32(0.0) + m0 * B[0, c]) + m1 * B[1, c]) + m2 * B[2, c]
    return out


@_jit
def _pillar_features(top: Any, mm: Any, cells: Any, nx: int, ny: int, lo: Any, size: Any,
                     wx: Any, wy: Any, bias: Any, rows: Any, offset: int, occupied: Any,
                     to_bfloat16: bool) -> None:  # pragma: no cover
    """The folded encoder's pillar features, written into the pseudo-image: for pillar ``p``
    at cell ``k``, ``relu(top - (mm + cx * wx + cy * wy - bias))`` (each operation rounded to
    float32 in that order; ``cx``, ``cy`` the pillar's centre) into ``rows[offset + k]``,
    as float32 or as bfloat16 bits (round to nearest even); ``occupied[offset + k]`` where a
    value is not zero (when ``occupied`` has entries). No contraction: each product is
    rounded before its sum, as the tensor code computes it."""
    U = top.shape[0]
    C = top.shape[1]
    half = np.float32(0.5)
    mark = occupied.shape[0] > 0
    for p in range(U):
        k = cells[p]
        cx = (np.float32(k % nx) + half) * size + lo[0]
        cy = (np.float32((k // nx) % ny) + half) * size + lo[1]
        row = offset + k
        any_set = False
        for c in range(C):
            per = ((mm[p, c] + cx * wx[c]) + cy * wy[c]) - bias[c]
            v = max(np.float32(0.0), top[p, c] - per)       # ReLU (-0 and NaN give 0)
            if to_bfloat16:
                bits = np.float32(v).view(np.uint32)
                b = np.uint16((bits + np.uint32(0x7FFF) + ((bits >> np.uint32(16))
                                                           & np.uint32(1))) >> np.uint32(16))
                rows[row, c] = b
                any_set = any_set or b != 0
            else:
                rows[row, c] = v
                any_set = any_set or v != 0
        if mark:
            occupied[row] = any_set


def pillar_max(points: NDArray[np.float32], point_range: tuple[float, ...], size: float,
               nx: int, ny: int, A: NDArray[np.float32], keep: NDArray[np.bool_] | None = None
               ) -> tuple[NDArray[np.int64], NDArray[np.float32], NDArray[np.float32]]:
    """Pillarize one cloud and reduce it per pillar, in two passes over its points.

    :param points: ``(N, 5)`` float32: x, y, z, intensity, time lag.
    :param point_range: x0, y0, z0, x1, y1, z1; a point is in range when ``lo <= p < hi``.
    :param A: ``(5, C)`` float32, the per-point linear map.
    :param keep: ``(N,)`` bool: only these points (the same result as ``points[keep]``).
    :return: each occupied pillar's cell ``iy * nx + ix`` ``(U,)``, its points' mean xyz
        ``(U, 3)`` and ``max_i points[i] @ A`` over its points ``(U, C)``, pillars in order
        of first appearance.
    """
    r = np.asarray(point_range, np.float32)
    pts = np.ascontiguousarray(points, np.float32)
    if pts.ndim != 2 or pts.shape[1] != 5 or A.shape[0] != 5:
        raise ValueError(f'pillar_max takes (N, 5) points and a (5, C) map, got {pts.shape} '
                         f'and {A.shape}')
    if keep is not None and len(keep) != len(pts):
        raise ValueError(f'pillar_max: {len(keep)} keep flags for {len(pts)} points')
    pid, cells = _pillar_ids(pts, r[:3], r[3:], np.float32(size), int(nx), int(ny),
                             np.zeros(0, np.bool_) if keep is None else keep)
    mean, top = _pillar_reduce(pts, pid, len(cells), np.ascontiguousarray(A, np.float32))
    return cells, mean, top


def as_float(points: NDArray[Any]) -> NDArray[np.floating[Any]]:
    """``points`` as the kernels take them: float32 or float64 as they are, anything else
    (float16 training drives, integers) as float64."""
    p = np.asarray(points)
    return p if p.dtype in (np.float32, np.float64) else p.astype(np.float64)


@_jit
def _distinct(values: Any, limit: int) -> Any:  # pragma: no cover
    found = np.empty(limit, values.dtype)
    m = 0
    last = values[0]
    for i in range(values.shape[0]):
        v = values[i]
        if v != v or (v == last and m > 0):       # NaN; the value just seen (runs of one lag)
            continue
        last = v
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


def pillar_features(top: NDArray[np.float32], mean: NDArray[np.float32],
                    cells: NDArray[np.int64], W: NDArray[np.float32],
                    bias: NDArray[np.float32] | None, grid: tuple[float, float, float, int, int],
                    rows: NDArray[Any], offset: int,
                    occupied: NDArray[np.bool_] | None = None) -> None:
    """The folded pillar encoder's output for :func:`pillar_max`'s pillars, written into the
    pseudo-image (:meth:`suit_ros.model.pillars.PillarEncoder._per_pillar`, then the ReLU of
    the max minus it, then the canvas dtype), in one pass and no temporaries but one product.

    :param W: ``(C, 5 + 5)`` float32, the folded linear map (its columns 5-7 weigh a pillar's
        mean xyz, 8-9 its centre x and y).
    :param grid: ``(x0, y0, pillar size, nx, ny)``.
    :param rows: ``(B * ny * nx, C)`` float32, or uint16 holding bfloat16 bits.
    :param offset: the first row of this cloud's image; ``occupied`` ``(B * ny * nx,)`` gets
        which cells have a non-zero feature.
    """
    C5 = W.shape[1] - 5
    B = np.ascontiguousarray(W[:, C5:C5 + 3].T, np.float32)
    wx = np.ascontiguousarray(W[:, C5 + 3], np.float32)
    wy = np.ascontiguousarray(W[:, C5 + 4], np.float32)
    b = (np.zeros(W.shape[0], np.float32) if bias is None
         else np.ascontiguousarray(bias, np.float32))
    x0, y0, size, nx, ny = grid
    if rows.dtype not in (np.float32, np.uint16) or rows.shape[1] != W.shape[0]:
        raise ValueError(f'pillar_features writes (cells, {W.shape[0]}) float32 or bfloat16 '
                         f'bits, got {rows.dtype} {rows.shape}')
    # the compiled loop does not check its indices: everything it writes must exist
    U = len(cells)
    if (top.shape != (U, W.shape[0]) or mean.shape != (U, 3) or offset < 0
            or offset + int(nx) * int(ny) > rows.shape[0]
            or (occupied is not None and len(occupied) != rows.shape[0])
            or (U and (int(cells.min()) < 0 or int(cells.max()) >= int(nx) * int(ny)))):
        raise ValueError(f'pillar_features: {U} pillars, top {top.shape}, mean {mean.shape}, '
                         f'offset {offset} + {nx}x{ny} cells, image {rows.shape}, occupied '
                         f'{None if occupied is None else occupied.shape}: inconsistent')
    _pillar_features(top, _mean_product(np.ascontiguousarray(mean, np.float32), B),
                     cells, int(nx), int(ny), np.array([x0, y0], np.float32), np.float32(size),
                     wx, wy, b, rows, int(offset),
                     np.zeros(0, np.bool_) if occupied is None else occupied,
                     rows.dtype == np.uint16)


@numba.njit(inline='always', nogil=True)
def _iou_scratch() -> Any:  # pragma: no cover
    """:func:`_bev_iou`'s scratch: candidate points, their angles, the two boxes' corners, and
    the corners' signs along length and width."""
    return (np.empty((24, 2), np.float64), np.empty(24, np.float64),
            np.empty((2, 4, 2), np.float64), np.array([1.0, -1.0, -1.0, 1.0]),
            np.array([1.0, 1.0, -1.0, -1.0]))


@numba.njit(inline='always', nogil=True)
def _bev_iou(a: Any, b: Any, pts: Any, ang: Any, corners: Any, sx: Any, sy: Any
             ) -> Any:  # pragma: no cover
    """The rotated BEV IoU of two float32 boxes (:func:`paired_bev_iou`), in the scratch
    arrays given."""
    for m in range(2):
        bx = a if m == 0 else b
        x = np.float64(bx[0])
        y = np.float64(bx[1])
        hl = np.float64(bx[3]) * 0.5
        hw = np.float64(bx[4]) * 0.5
        c = np.cos(np.float64(bx[6]))
        s = np.sin(np.float64(bx[6]))
        for i in range(4):
            dx = sx[i] * hl
            dy = sy[i] * hw
            corners[m, i, 0] = x + c * dx - s * dy
            corners[m, i, 1] = y + s * dx + c * dy
    n = 0
    for m in range(2):                    # corners of box m inside the other box
        ot = b if m == 0 else a
        ox = np.float64(ot[0])
        oy = np.float64(ot[1])
        c = np.cos(np.float64(ot[6]))
        s = np.sin(np.float64(ot[6]))
        half_l = np.float64(ot[3]) * 0.5 + 1e-6
        half_w = np.float64(ot[4]) * 0.5 + 1e-6
        for i in range(4):
            d0 = corners[m, i, 0] - ox
            d1 = corners[m, i, 1] - oy
            if abs(d0 * c + d1 * s) <= half_l and abs(d1 * c - d0 * s) <= half_w:
                pts[n, 0] = corners[m, i, 0]
                pts[n, 1] = corners[m, i, 1]
                n += 1
    for i in range(4):                    # edge i of a against edge j of b
        i1 = (i + 1) % 4
        r0 = corners[0, i1, 0] - corners[0, i, 0]
        r1 = corners[0, i1, 1] - corners[0, i, 1]
        for j in range(4):
            j1 = (j + 1) % 4
            v0 = corners[1, j1, 0] - corners[1, j, 0]
            v1 = corners[1, j1, 1] - corners[1, j, 1]
            denom = r0 * v1 - r1 * v0
            if abs(denom) < 1e-12:
                continue
            q0 = corners[1, j, 0] - corners[0, i, 0]
            q1 = corners[1, j, 1] - corners[0, i, 1]
            t = (q0 * v1 - q1 * v0) / denom
            u = (q0 * r1 - q1 * r0) / denom
            if t >= 0.0 and t <= 1.0 and u >= 0.0 and u <= 1.0:
                pts[n, 0] = corners[0, i, 0] + t * r0
                pts[n, 1] = corners[0, i, 1] + t * r1
                n += 1
    inter = 0.0
    if n >= 3:
        mx = 0.0
        my = 0.0
        for i in range(n):
            mx += pts[i, 0]
            my += pts[i, 1]
        mx /= n
        my /= n
        for i in range(n):
            ang[i] = np.arctan2(pts[i, 1] - my, pts[i, 0] - mx)
        order = np.argsort(ang[:n])
        acc = 0.0
        for i in range(n):
            p = order[i]
            q = order[(i + 1) % n]
            acc += pts[p, 0] * pts[q, 1] - pts[p, 1] * pts[q, 0]
        inter = 0.5 * abs(acc)
    area_a = np.float64(a[3] * a[4])
    area_b = np.float64(b[3] * b[4])
    union = area_a + area_b - inter
    iou = inter / (union if union > 1e-9 else 1e-9)
    return np.float32(min(max(iou, 0.0), 1.0))


@_jit
def paired_bev_iou(boxes_a: Any, boxes_b: Any) -> Any:  # pragma: no cover
    """Rotated BEV IoU of each pair ``(boxes_a[k], boxes_b[k])`` of ``(K, 7)`` float32 boxes,
    as :func:`suit_ros.ops.iou.paired_bev_iou` computes it (float64 geometry, float32
    result): the intersection polygon from the corners of each box inside the other (1e-6 m
    tolerance) and the crossings of their edges (edges closer to parallel than 1e-12 m^2 do
    not cross), ordered by angle around the candidates' mean, shoelace area. Sums are
    taken in order, so a value may differ from the tensor code's in the last bits of the
    float64 geometry (the tests bound it)."""
    K = boxes_a.shape[0]
    out = np.empty(K, np.float32)
    pts, ang, corners, sx, sy = _iou_scratch()
    for k in range(K):
        out[k] = _bev_iou(boxes_a[k], boxes_b[k], pts, ang, corners, sx, sy)
    return out


@_jit
def greedy_bev_nms(boxes: Any, group: Any, iou_threshold: Any, min_distance: float
                   ) -> Any:  # pragma: no cover
    """Greedy NMS of ``(N, 7)`` float32 boxes given in descending score order: which stay
    (``(N,)`` bool). A kept box drops each later box of its ``group`` (``(N,)`` int64: the
    class, or the frame) whose centre lies closer than ``min_distance`` metres, or whose
    rotated BEV IoU with it (:func:`paired_bev_iou`, float32) exceeds ``iou_threshold``
    (float32); the IoU is computed only for pairs whose circumscribed circles meet, and only
    for boxes not dropped already: the kept set of :func:`suit_ros.ops.nms.rotated_suppression`
    and :func:`~suit_ros.ops.nms.greedy_suppression`, in one pass (distances in float64)."""
    N = boxes.shape[0]
    keep = np.zeros(N, np.bool_)
    removed = np.zeros(N, np.bool_)
    r = np.empty(N, np.float64)
    for i in range(N):
        r[i] = 0.5 * math.hypot(np.float64(boxes[i, 3]), np.float64(boxes[i, 4]))
    pts, ang, corners, sx, sy = _iou_scratch()
    for i in range(N):
        if removed[i]:
            continue
        keep[i] = True
        for j in range(i + 1, N):
            if removed[j] or group[j] != group[i]:
                continue
            dx = np.float64(boxes[j, 0]) - np.float64(boxes[i, 0])
            dy = np.float64(boxes[j, 1]) - np.float64(boxes[i, 1])
            d = math.sqrt(dx * dx + dy * dy)
            if d < min_distance:
                removed[j] = True
            elif d < r[i] + r[j] and _bev_iou(boxes[i], boxes[j], pts, ang, corners, sx,
                                               sy) > iou_threshold:
                removed[j] = True
    return keep


@_jit
def suppress_near_kernel(xy: Any, labels: Any, movable: Any, radius: Any
                         ) -> Any:  # pragma: no cover
    """:func:`suit_ros.ops.nms.suppress_near` in one pass: boxes in descending score order,
    ``xy`` ``(N, 2)`` float64 centres, ``labels`` ``(N,)`` int64, ``movable`` ``(N,)`` bool,
    ``radius`` ``(N,)`` float64 (each box's class radius); a movable box goes when an earlier
    box of its class that stays lies closer than its radius. Returns ``(N,)`` bool."""
    N = xy.shape[0]
    keep = np.ones(N, np.bool_)
    for i in range(N):
        if not movable[i]:
            continue
        for j in range(i):
            if keep[j] and labels[j] == labels[i]:
                dx = xy[i, 0] - xy[j, 0]
                dy = xy[i, 1] - xy[j, 1]
                if math.sqrt(dx * dx + dy * dy) < radius[i]:
                    keep[i] = False
                    break
    return keep


@numba.njit(inline='always', nogil=True)
def _tap_row(cells: Any, m: int, t: int, H: int, W: int, where: Any,
             rows: int) -> Any:  # pragma: no cover
    """The row of tap ``t`` (row-major 3 x 3) of cell ``m`` (b, y, x): -1 off the map, or for
    a cell the rows do not hold (-1 in ``where``)."""
    y = cells[m, 1] + t // 3 - 1
    x = cells[m, 2] + t % 3 - 1
    if y < 0 or y >= H or x < 0 or x >= W:
        return -1
    r = (cells[m, 0] * H + y) * W + x
    if r < 0:
        raise IndexError('gather_taps: a cell of a negative frame')
    if len(where):
        if r >= len(where):
            raise IndexError('gather_taps: a cell lies outside the where map')
        r = where[r]
        if r < 0:                       # a cell the rows do not hold: zero, as off the map
            return -1
    if r < 0 or r >= rows:
        raise IndexError('gather_taps: a tap reads a row the map does not have')
    return r


@_jit
def gather_taps(rows: Any, cells: Any, H: int, W: int, where: Any,
                out: Any) -> None:  # pragma: no cover
    """The 3 x 3 neighbourhoods of ``cells`` ``(M, 3)`` int64 (b, y, x) of a map given as its
    ``(R, C)`` float32 rows (row ``(b * H + y) * W + x``, or ``where`` of it when ``where``
    is not empty; -1 there: a cell the rows do not hold, read as zero), written into ``out``
    ``(M, 9 C)`` (row-major taps), zero off the map as a padded convolution has it
    (:func:`suit_ros.model.head._neighbourhoods`)."""
    C = rows.shape[1]
    for m in range(cells.shape[0]):
        for t in range(9):
            r = _tap_row(cells, m, t, H, W, where, rows.shape[0])
            for c in range(C):
                out[m, t * C + c] = rows[r, c] if r >= 0 else np.float32(0.0)


@_jit
def gather_taps_bf16(rows: Any, cells: Any, H: int, W: int, where: Any,
                     out: Any) -> None:  # pragma: no cover
    """:func:`gather_taps` of bfloat16 rows given as their ``uint16`` bits, written as the
    ``uint32`` bits of the same values in float32 (exact: bfloat16 is float32's upper half)."""
    C = rows.shape[1]
    for m in range(cells.shape[0]):
        for t in range(9):
            r = _tap_row(cells, m, t, H, W, where, rows.shape[0])
            for c in range(C):
                out[m, t * C + c] = np.uint32(rows[r, c]) << np.uint32(16) if r >= 0 \
                    else np.uint32(0)


@_jit
def dilate_flat_cells(flat: Any, H: int, W: int, r: int, skip: Any) -> Any:  # pragma: no cover
    """The sorted flat cells ``(b * H + y) * W + x`` within ``r`` cells (a square) of the
    cells ``flat`` (``(N,)`` int64, repeats allowed) on their ``(B, H, W)`` map (B: the last
    frame they name, or ``skip``'s), marked on a scratch map and read back in order; less the
    cells ``skip`` (``(B * H * W,)`` bool; empty: none) marks."""
    if len(flat) == 0:
        return np.zeros(0, np.int64)
    HW = H * W
    top = 0
    for f in flat:
        if f < 0 or (len(skip) and f >= len(skip)):
            raise IndexError('dilate_flat_cells: a cell lies off the map')
        top = max(top, f)
    mark = np.zeros(len(skip) if len(skip) else (top // HW + 1) * HW, np.bool_)
    for f in flat:
        b = f // HW
        y = f // W % H
        x = f % W
        for yy in range(max(y - r, 0), min(y + r + 1, H)):
            for xx in range(max(x - r, 0), min(x + r + 1, W)):
                c = (b * H + yy) * W + xx
                if not (len(skip) and skip[c]):
                    mark[c] = True
    return np.nonzero(mark)[0].astype(np.int64)


@_jit
def feeding_map(needed: Any, B: int, H: int, W: int) -> Any:  # pragma: no cover
    """For the sorted distinct flat cells ``needed`` ``(M,)`` of a ``(B, H, W)`` map, where a
    3 x 3 layer over a 3 x 3 layer is read (:meth:`suit_ros.model.head.CenterHead.forward_at`):
    their ``(M, 3)`` (b, y, x) rows, the sorted flat cells that feed them (within one cell),
    those as ``(F, 3)`` rows, and the ``(B * H * W,)`` map of each cell's row among the
    feeding ones (-1: not feeding)."""
    HW = H * W
    cells = np.empty((len(needed), 3), np.int64)
    where = np.full(B * HW, -1, np.int64)
    for i in range(len(needed)):
        f = needed[i]
        if f < 0 or f >= B * HW:
            raise IndexError('feeding_map: a needed cell lies off the map')
        b = f // HW
        y = f // W % H
        x = f % W
        cells[i, 0] = b
        cells[i, 1] = y
        cells[i, 2] = x
        for yy in range(max(y - 1, 0), min(y + 2, H)):
            for xx in range(max(x - 1, 0), min(x + 2, W)):
                where[(b * H + yy) * W + xx] = 0
    F = 0
    for f in range(B * HW):
        if where[f] == 0:
            F += 1
    flat = np.empty(F, np.int64)
    feeding = np.empty((F, 3), np.int64)
    n = 0
    for f in range(B * HW):
        if where[f] == 0:
            where[f] = n
            flat[n] = f
            feeding[n, 0] = f // HW
            feeding[n, 1] = f // W % H
            feeding[n, 2] = f % W
            n += 1
    return cells, flat, feeding, where


@numba.njit(inline='always', nogil=True)
def _bf16_add(bits: Any, value: Any, scratch: Any, view: Any) -> Any:  # pragma: no cover
    """``bits`` (a bfloat16's uint16) plus the float32 ``value``, rounded to the nearest
    bfloat16 (ties to even; NaN stays NaN), as bits (``scratch``/``view``: one uint32 and its
    float32 view)."""
    scratch[0] = np.uint32(bits) << np.uint32(16)
    view[0] = view[0] + value
    u = scratch[0]
    if view[0] != view[0]:
        return np.uint16(0x7FC0)
    u = u + np.uint32(0x7FFF) + ((u >> np.uint32(16)) & np.uint32(1))
    return np.uint16(u >> np.uint32(16))


@numba.njit(inline='always', nogil=True)
def _add_f32(out: Any, row: int, c: int, value: Any, scratch: Any,
             view: Any) -> None:  # pragma: no cover
    out[row, c] += value


@numba.njit(inline='always', nogil=True)
def _add_bf16(out: Any, row: int, c: int, value: Any, scratch: Any,
              view: Any) -> None:  # pragma: no cover
    out[row, c] = _bf16_add(out[row, c], value, scratch, view)


@numba.njit(inline='always', nogil=True)
def _add_at(out: Any, cell: int, lookup: Any, values: Any, add: Any, scratch: Any,
            view: Any) -> None:  # pragma: no cover
    """``values`` ``(hc,)`` added with ``add`` to the row of ``out`` at flat ``cell``: the
    cell itself, or ``lookup``'s row for it (-1: none) when ``lookup`` is not empty."""
    row = lookup[cell] if len(lookup) else cell
    if row >= out.shape[0]:
        raise IndexError('add_tap_spread: the lookup names a row out does not have')
    if row >= 0:
        for c in range(out.shape[1]):
            add(out, row, c, values[c], scratch, view)


@numba.njit(inline='always', nogil=True)
def _spread(out: Any, spread: Any, index: Any, edge_index: Any, edge_values: Any, lookup: Any,
            H: int, W: int, add: Any) -> None:  # pragma: no cover
    """The loop of :func:`add_tap_spread` (``lookup`` empty: the rows of ``out`` are the map's
    cells), adding with ``add``."""
    HW = H * W
    n = len(lookup) if len(lookup) else out.shape[0]
    scratch = np.zeros(1, np.uint32)
    view = scratch.view(np.float32)
    for r in range(len(index)):
        f = index[r]
        if f < 0 or f >= n:
            raise IndexError('add_tap_spread: an input row lies off the map')
        b = f // HW
        y = f // W % H
        x = f % W
        for t in range(9):
            ty = y - (t // 3 - 1)
            tx = x - (t % 3 - 1)
            if ty < 0 or ty >= H or tx < 0 or tx >= W:
                continue
            _add_at(out, (b * H + ty) * W + tx, lookup, spread[r, t], add, scratch, view)
    for b in range(n // HW):
        for e in range(len(edge_index)):
            _add_at(out, b * HW + edge_index[e], lookup, edge_values[e], add, scratch, view)


@_jit
def add_tap_spread(out: Any, spread: Any, index: Any, edge_index: Any, edge_values: Any,
                   lookup: Any, H: int, W: int) -> None:  # pragma: no cover
    """Add to ``out`` ``(M, hc)`` float32 rows of a 3 x 3 layer's pre-activation, at the cells
    ``lookup`` maps to them (``(B * H * W,)``: a cell's row of ``out``, -1 for none), what a
    sparse input term gives there: each input row ``r`` at flat cell ``index[r]`` feeds, by
    its tap ``t`` (row-major, ``spread`` ``(R, 9, hc)``: the taps' products with it), the
    output cell ``(y - (t // 3 - 1), x - (t % 3 - 1))``; and the edge correction
    ``edge_values`` ``(E, hc)`` at the cells ``edge_index`` of every frame
    (:meth:`suit_ros.model.head.HeadFold.at`)."""
    _spread(out, spread, index, edge_index, edge_values, lookup, H, W, _add_f32)


@_jit
def add_tap_spread_dense(out: Any, spread: Any, index: Any, edge_index: Any, edge_values: Any,
                         H: int, W: int) -> None:  # pragma: no cover
    """:func:`add_tap_spread` into a whole ``(B * H * W, hc)`` float32 map's rows
    (channels-last; row = flat cell) (:meth:`suit_ros.model.head.HeadFold.dense`)."""
    _spread(out, spread, index, edge_index, edge_values, np.zeros(0, np.int64), H, W, _add_f32)


@_jit
def add_tap_spread_dense_bf16(out: Any, spread: Any, index: Any, edge_index: Any,
                              edge_values: Any, H: int, W: int) -> None:  # pragma: no cover
    """:func:`add_tap_spread_dense` into a bfloat16 map given as its ``uint16`` bits, each
    added value rounded to bfloat16 (to nearest, ties to even) as it is added."""
    _spread(out, spread, index, edge_index, edge_values, np.zeros(0, np.int64), H, W,
            _add_bf16)


@_jit
def sum_triples(positions: Any, displacements: Any, probs: Any, mask: Any, q: Any, prune: Any,
                origin: Any, cell: Any, batch_index: Any, features: Any, member: Any, H: int,
                W: int) -> Any:  # pragma: no cover
    """The sparse past term's weighted sums before its projection
    (:func:`suit_ros.model.fusion.sparse_past_terms`, pruned bins): every (sample m, cell p,
    bin k) of weight ``w = probs[m, p] * mask[m, p] * q[m, k]`` (``q`` below ``prune``: 0) over
    0, whose destination ``floor((positions[m, p] + displacements[m, k] - origin) / cell)``
    (col, row; float32, as the tensor code) lies on the ``H x W`` map, adds
    ``w * features[m, p]`` to its flat cell ``(b * H + row) * W + col``; per subset ``s``
    (``member`` ``(S, M)`` bool: the samples it takes) the cells it touches in increasing order
    and their sums. Sums run over the triples in (m, p, k) order per cell.

    :return: flat cells ``(R,)`` int64, sums ``(R, C)`` float32 and ``(S,)`` counts (the
        subsets' rows one after another).
    """
    M, P, _ = positions.shape
    K = q.shape[1]
    C = features.shape[2]
    S = member.shape[0]
    zero = np.float32(0.0)
    one = np.float32(1.0)
    flat = np.empty(M * P * K, np.int64)
    who = np.empty((M * P * K, 2), np.int64)
    weight = np.empty(M * P * K, np.float32)
    n = 0
    for m in range(M):
        for p in range(P):
            pw = probs[m, p] * (one if mask[m, p] else zero)
            for k in range(K):
                qk = q[m, k] * (one if q[m, k] >= prune else zero)
                w = pw * qk
                if not w > 0:
                    continue
                col = np.floor((positions[m, p, 0] + displacements[m, k, 0] - origin[0]) / cell)
                row = np.floor((positions[m, p, 1] + displacements[m, k, 1] - origin[1]) / cell)
                if 0 <= col < W and 0 <= row < H:
                    flat[n] = (batch_index[m] * H + int(row)) * W + int(col)
                    who[n, 0] = m
                    who[n, 1] = p
                    weight[n] = w
                    n += 1
    # in (m, p, k) order within a cell: the position breaks ties, so the sort needs no
    # stability (numba's mergesort took three times its quicksort here)
    key = np.empty(n, np.int64)
    for i in range(n):
        key[i] = flat[i] * n + i
    order = np.argsort(key)
    counts = np.zeros(S, np.int64)
    total = 0
    for s in range(S):
        last = -1
        for i in order:
            if member[s, who[i, 0]] and flat[i] != last:
                last = flat[i]
                counts[s] += 1
        total += counts[s]
    out_flat = np.empty(total, np.int64)
    sums = np.zeros((total, C), np.float32)
    r = -1
    for s in range(S):
        last = -1
        for i in order:
            m = who[i, 0]
            if not member[s, m]:
                continue
            if flat[i] != last:
                last = flat[i]
                r += 1
                out_flat[r] = last
            p = who[i, 1]
            for c in range(C):
                sums[r, c] += weight[i] * features[m, p, c]
    return out_flat, sums, counts


@_jit
def pool_occupancy(occupied: Any, B: int, ny: int, nx: int, stride: int,
                   radius: int) -> Any:  # pragma: no cover
    """:func:`suit_ros.model.grid.pooled_occupancy` of ``(B * ny * nx,)`` bool pillars: the
    ``(B, ny // stride, nx // stride)`` head cells holding an occupied pillar, grown by
    ``radius`` cells (a square, clipped at the map's edge)."""
    H = ny // stride
    W = nx // stride
    coarse = np.zeros((B, H, W), np.bool_)
    for b in range(B):
        for y in range(H * stride):
            base = (b * ny + y) * nx
            row = y // stride
            for x in range(W * stride):
                if occupied[base + x]:
                    coarse[b, row, x // stride] = True
    if radius == 0:
        return coarse
    # grown along rows, then along columns: a sliding count of the cells in the window
    wide = np.zeros((B, H, W), np.bool_)
    for b in range(B):
        for y in range(H):
            count = 0
            for x in range(min(radius, W)):
                count += coarse[b, y, x]
            for x in range(W):
                if x + radius < W:
                    count += coarse[b, y, x + radius]
                if x - radius - 1 >= 0:
                    count -= coarse[b, y, x - radius - 1]
                wide[b, y, x] = count > 0
    out = np.zeros((B, H, W), np.bool_)
    counts = np.zeros(W, np.int64)          # per column, row by row (in memory order)
    for b in range(B):
        counts[:] = 0
        for y in range(min(radius, H)):
            for x in range(W):
                counts[x] += wide[b, y, x]
        for y in range(H):
            if y + radius < H:
                for x in range(W):
                    counts[x] += wide[b, y + radius, x]
            if y - radius - 1 >= 0:
                for x in range(W):
                    counts[x] -= wide[b, y - radius - 1, x]
            for x in range(W):
                out[b, y, x] = counts[x] > 0
    return out


@_jit
def flags_at(flags: Any, batch_index: Any, xy: Any, origin: Any, cell: Any,
             invert: bool = False) -> Any:  # pragma: no cover
    """``flags[b, row, col]`` (``(B, H, W)`` bool; with ``invert`` its negation) at the cells
    of metric positions ``xy`` ``(M, 2)`` float32 (``floor((xy - origin) / cell)``, float32 as
    the tensor code), False off the map (:func:`suit_ros.model.sampling.cell_flags`)."""
    B, H, W = flags.shape
    out = np.zeros(xy.shape[0], np.bool_)
    for m in range(xy.shape[0]):
        col = np.floor((xy[m, 0] - origin[0]) / cell)
        row = np.floor((xy[m, 1] - origin[1]) / cell)
        b = batch_index[m]
        if b < 0 or b >= B:
            raise IndexError('flags_at: a position of a frame the flags do not have')
        if 0 <= col < W and 0 <= row < H:
            out[m] = flags[b, int(row), int(col)] != invert
    return out


@_jit
def carry_selection(observed: Any, new_index: Any, new_xy: Any, new_probs: Any, new_boxes: Any,
                    old_index: Any, old_xy: Any, old_probs: Any, old_boxes: Any, old_ages: Any,
                    max_age: int, keep_new: bool, origin: Any, cell: Any,
                    iou_threshold: Any, min_distance: float) -> Any:  # pragma: no cover
    """The next memory's samples from this frame's (``new_*``) and the carried ones
    (``old_*``), as :func:`suit_ros.model.sampling.keep_carried`'s tensor code picks them:
    each sample's centre cell (``*_xy`` ``(M, P, 2)`` float32, the window's middle cell) read
    in ``observed`` (``(B, H, W)`` bool, :func:`flags_at`); a carried sample stays a
    candidate where its centre is on the map without returns and its age (nanoseconds) is at
    most ``max_age``; each candidate's priority is its tier (a new sample seen now, or every
    new one with ``keep_new``: 2; a carried one: 1; a new one unseen: 0) plus its centre
    probability (float32), and :func:`greedy_bev_nms` over the frame keeps one per object
    in that order (stable; the priorities are finite: probabilities). Returns the kept
    samples as rows of the new ones followed by all the carried ones ``(K,)`` int64, in
    priority order, and whether each new sample's centre has returns ``(N,)`` bool."""
    N = new_index.shape[0]
    R = old_index.shape[0]
    c = new_xy.shape[1] // 2
    seen = flags_at(observed, new_index, new_xy[:, c, :], origin, cell)
    unseen = flags_at(observed, old_index, old_xy[:, c, :], origin, cell, True)
    rows = np.empty(N + R, np.int64)
    for i in range(N):
        rows[i] = i
    T = N
    for j in range(R):
        if unseen[j] and old_ages[j] <= max_age:
            rows[T] = N + j
            T += 1
    rows = rows[:T]
    priority = np.empty(T, np.float32)
    group = np.empty(T, np.int64)
    boxes = np.empty((T, 7), np.float32)
    for t in range(T):
        r = rows[t]
        if r < N:
            tier = np.float32(2.0) if seen[r] or keep_new else np.float32(0.0)
            priority[t] = tier + np.float32(new_probs[r, c])
            group[t] = new_index[r]
            boxes[t] = new_boxes[r]
        else:
            priority[t] = np.float32(1.0) + np.float32(old_probs[r - N, c])
            group[t] = old_index[r - N]
            boxes[t] = old_boxes[r - N]
    order = np.argsort(-priority, kind='mergesort')      # descending, ties in row order
    keep = greedy_bev_nms(boxes[order], group[order], iou_threshold, min_distance)
    return rows[order][keep], seen


@_jit
def move_cells(cell_xy: Any, z: Any, T: Any, batch_index: Any, out: Any
               ) -> None:  # pragma: no cover
    """Memory sample cells ``(M, P, 2)`` float32 lifted to 3D at their sample's height ``z``
    ``(M,)``, moved by their frame's ``T`` ``(B, 4, 4)`` float64 and projected back to BEV,
    written into ``out`` ``(M, P, 2)`` float32 (float64 arithmetic;
    :func:`suit_ros.model.memory.transform_sample_positions`)."""
    for m in range(cell_xy.shape[0]):
        b = batch_index[m]
        if b < 0 or b >= T.shape[0]:
            raise IndexError('move_cells: a sample of a frame without a transform')
        h = np.float64(z[m])
        for p in range(cell_xy.shape[1]):
            x = np.float64(cell_xy[m, p, 0])
            y = np.float64(cell_xy[m, p, 1])
            for i in range(2):
                out[m, p, i] = np.float32(T[b, i, 0] * x + T[b, i, 1] * y + T[b, i, 2] * h
                                          + T[b, i, 3])


@_jit
def move_boxes(boxes: Any, velocities: Any, shift: Any, T: Any, batch_index: Any,
               out_boxes: Any, out_velocities: Any) -> None:  # pragma: no cover
    """Memory samples' boxes ``(M, 7)`` and velocities ``(M, 2)`` (float32) moved into the
    current frame by their frame's ``T`` ``(B, 4, 4)`` float64 (the centres in float64), the
    boxes' centres further by ``shift`` ``(M, 2)`` (:func:`suit_ros.model.memory.
    moved_memory`)."""
    for m in range(boxes.shape[0]):
        b = batch_index[m]
        if b < 0 or b >= T.shape[0]:
            raise IndexError('move_boxes: a sample of a frame without a transform')
        x = np.float64(boxes[m, 0])
        y = np.float64(boxes[m, 1])
        h = np.float64(boxes[m, 2])
        for k in range(7):
            out_boxes[m, k] = boxes[m, k]
        for i in range(3):
            v = T[b, i, 0] * x + T[b, i, 1] * y + T[b, i, 2] * h + T[b, i, 3]
            out_boxes[m, i] = np.float32(v)
        # the shift, the turn and the velocities' rotation in float32, as the tensor code
        out_boxes[m, 0] = out_boxes[m, 0] + np.float32(shift[m, 0])
        out_boxes[m, 1] = out_boxes[m, 1] + np.float32(shift[m, 1])
        out_boxes[m, 6] = boxes[m, 6] + np.float32(np.arctan2(T[b, 1, 0], T[b, 0, 0]))
        vx = velocities[m, 0]
        vy = velocities[m, 1]
        out_velocities[m, 0] = np.float32(T[b, 0, 0]) * vx + np.float32(T[b, 0, 1]) * vy
        out_velocities[m, 1] = np.float32(T[b, 1, 0]) * vx + np.float32(T[b, 1, 1]) * vy


@_jit
def rectangle_cells(lo: Any, hi: Any, width: int, origin: Any, cell: float, oriented: Any,
                    margin: float) -> Any:  # pragma: no cover
    """The cells of a coarse grid each rectangle touches (:class:`suit_ros.ops.geometry.
    CellIndex`): rectangle ``k`` spans the grid cells ``lo[k]`` to ``hi[k]`` (``(M, 2)``
    int64, from the grid's ``origin``), row-major flat ``row * width + col``; with
    ``oriented`` ``(M, 5)`` float64 (centre x, y, half length, half width, yaw; empty: none)
    only those whose centre lies within ``margin`` of the rotated rectangle. Returns the flat
    cells and their rectangle's index, rectangle by rectangle, rows then columns."""
    M = lo.shape[0]
    total = 0
    for k in range(M):
        total += (hi[k, 0] - lo[k, 0] + 1) * (hi[k, 1] - lo[k, 1] + 1)
    flat = np.empty(total, np.int64)
    owner = np.empty(total, np.int64)
    n = 0
    for k in range(M):
        if len(oriented):
            cx = oriented[k, 0]
            cy = oriented[k, 1]
            hl = oriented[k, 2] + margin
            hw = oriented[k, 3] + margin
            c = np.cos(oriented[k, 4])
            s = np.sin(oriented[k, 4])
        for row in range(lo[k, 0], hi[k, 0] + 1):
            for col in range(lo[k, 1], hi[k, 1] + 1):
                if len(oriented):
                    dx = (row + origin[0] + 0.5) * cell - cx
                    dy = (col + origin[1] + 0.5) * cell - cy
                    if abs(dx * c + dy * s) > hl or abs(-dx * s + dy * c) > hw:
                        continue
                flat[n] = row * width + col
                owner[n] = k
                n += 1
    return flat[:n], owner[:n]


@numba.njit(inline='always', nogil=True)
def _in_range(points: Any, times: Any, r_min: Any, r_max: Any) -> Any:  # pragma: no cover
    """The rows of ``points`` (and of ``times`` when it has one per point) in range."""
    n, c = points.shape
    timed = times.shape[0] == n
    out = np.empty((n, c), np.float32)
    out_t = np.empty(n if timed else 0, np.float32)
    m = 0
    for i in range(n):
        r = np.hypot(points[i, 0], points[i, 1])
        if r >= r_min and r <= r_max:
            for j in range(c):
                out[m, j] = points[i, j]
            if timed:
                out_t[m] = times[i]
            m += 1
    return out[:m], out_t[:m]


@_jit
def in_range(points: Any, r_min: Any, r_max: Any) -> Any:  # pragma: no cover
    """The rows of ``(N, 4)`` float32 ``points`` whose horizontal range ``hypot(x, y)``
    (float32) lies in ``[r_min, r_max]`` (float32), copied in order: one pass for
    ``points[(r >= r_min) & (r <= r_max)]`` (the node's range filter)."""
    return _in_range(points, np.empty(0, np.float32), r_min, r_max)[0]


@_jit
def in_range_times(points: Any, times: Any, r_min: Any, r_max: Any) -> Any:  # pragma: no cover
    """:func:`in_range` of ``(N, C)`` points and the same rows of their ``(N,)`` float32 times
    (deskew's): ``(points, times)``."""
    if times.shape[0] != points.shape[0]:
        raise ValueError('in_range_times needs one time per point')
    return _in_range(points, times, r_min, r_max)


@_jit
def azimuth_counts(xyz: Any, bins: int) -> Any:  # pragma: no cover
    """Returns per azimuth bin of ``(N, >= 2)`` points: bin ``k`` holds the angles (about
    +z, counter-clockwise from +x, ``0 .. 2 pi``) in ``[k, k + 1) * 2 pi / bins``, the angle
    ``atan2(y, x) mod 2 pi`` in float64 (an angle that rounds to 2 pi goes to the last
    bin); a point with a NaN coordinate counts nowhere."""
    counts = np.zeros(bins, np.int64)
    two_pi = 2.0 * np.pi
    scale = bins / two_pi
    for i in range(xyz.shape[0]):
        a = math.atan2(np.float64(xyz[i, 1]), np.float64(xyz[i, 0]))
        if a != a:
            continue
        if a < 0.0:
            a += two_pi
        k = int(a * scale)
        counts[min(k, bins - 1)] += 1
    return counts


@_jit
def deskew_points(points: Any, times: Any, w: Any, v: Any) -> None:  # pragma: no cover
    """Move each return of ``(N, >= 3)`` float32 ``points`` (in place), taken ``times[i]``
    seconds after the stamp by a sensor moving with the constant twist ``w`` (rad/s), ``v``
    (m/s) (float64, in the sensor's frame at the stamp), into the sensor's frame at the stamp:
    ``exp(t [w, v]) p`` (SE(3): the rotation by Rodrigues' formula, the translation along the
    arc; new computation, tested against numpy in test/test_deskew.py)."""
    speed = np.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    kx, ky, kz = 0.0, 0.0, 1.0
    if speed > 0.0:
        kx, ky, kz = w[0] / speed, w[1] / speed, w[2] / speed
    # k x v and k x (k x v): the arc's bend of the translation
    ax, ay, az = ky * v[2] - kz * v[1], kz * v[0] - kx * v[2], kx * v[1] - ky * v[0]
    bx, by, bz = ky * az - kz * ay, kz * ax - kx * az, kx * ay - ky * ax
    longest = 0.0
    for i in range(times.shape[0]):
        longest = max(longest, abs(float(times[i])))
    # a sweep's turn (under 0.2 rad): cos and sin by their series, within 1e-8 (the branch
    # is the same for every return)
    series = speed * longest < 0.2
    for i in range(points.shape[0]):
        t = float(times[i])
        x, y, z = float(points[i, 0]), float(points[i, 1]), float(points[i, 2])
        a = speed * t
        a2 = a * a
        if series:
            c = 1.0 - a2 * (0.5 - a2 * (1.0 / 24.0 - a2 / 720.0))
            s = a * (1.0 - a2 * (1.0 / 6.0 - a2 * (1.0 / 120.0 - a2 / 5040.0)))
            f1 = speed * t * t * (0.5 - a2 * (1.0 / 24.0 - a2 / 720.0))
            f2 = speed * speed * t * t * t * (1.0 / 6.0 - a2 * (1.0 / 120.0 - a2 / 5040.0))
        else:
            c, s = np.cos(a), np.sin(a)
            f1 = (1.0 - c) / speed
            f2 = (a - s) / speed
        d = (kx * x + ky * y + kz * z) * (1.0 - c)
        cx, cy, cz = ky * z - kz * y, kz * x - kx * z, kx * y - ky * x
        points[i, 0] = x * c + cx * s + kx * d + t * v[0] + f1 * ax + f2 * bx
        points[i, 1] = y * c + cy * s + ky * d + t * v[1] + f1 * ay + f2 * by
        points[i, 2] = z * c + cz * s + kz * d + t * v[2] + f1 * az + f2 * bz


@numba.njit(inline='always', nogil=True)
def _grid_cell(x: Any, y: Any, inv_cell: Any, o0: int, o1: int, s0: int,
               s1: int) -> int:  # pragma: no cover
    """The flat cell ``ix * s1 + iy`` of ``floor((x, y) * inv_cell) - (o0, o1)`` (the product
    in the points' dtype, as numpy computes it), or -1 outside the ``(s0, s1)`` grid or not
    finite. The grid's origin and shape come as scalars: read from their arrays once per
    call of a kernel, not once per point (8x faster than indexing them here)."""
    x = x * inv_cell
    y = y * inv_cell
    if not (abs(x) < 1e15 and abs(y) < 1e15):
        return -1
    ix = np.int64(np.floor(x)) - o0
    iy = np.int64(np.floor(y)) - o1
    if ix < 0 or ix >= s0 or iy < 0 or iy >= s1:
        return -1
    return int(ix * s1 + iy)


@_jit
def count_in_box_cells(xyz: Any, inv_cell: Any, origin: Any, shape: Any, cell_start: Any,
                       cell_boxes: Any, boxes: Any, cos: Any, sin: Any) -> Any:  # pragma: no cover
    """Per box, how many points lie inside it (the rule and float64 arithmetic of
    :func:`suit_ros.ops.geometry.points_in_boxes`; ``cos``/``sin`` of the yaws given, computed
    by numpy), in one pass over the points without bucketing them: each point is tested
    against the boxes listed for its grid cell (``cell_boxes[cell_start[k]:cell_start[k +
    1]]``, :meth:`suit_ros.ops.geometry.CellIndex.box_lists`)."""
    M = boxes.shape[0]
    out = np.zeros(M, np.uint32)
    o0, o1, s0, s1 = origin[0], origin[1], shape[0], shape[1]
    for i in range(xyz.shape[0]):
        k = _grid_cell(xyz[i, 0], xyz[i, 1], inv_cell, o0, o1, s0, s1)
        if k < 0:
            continue
        for j in range(cell_start[k], cell_start[k + 1]):
            b = cell_boxes[j]
            dx = np.float64(xyz[i, 0]) - boxes[b, 0]
            dy = np.float64(xyz[i, 1]) - boxes[b, 1]
            dz = np.float64(xyz[i, 2]) - boxes[b, 2]
            if (abs(dx * cos[b] + dy * sin[b]) <= boxes[b, 3] / 2
                    and abs(-dx * sin[b] + dy * cos[b]) <= boxes[b, 4] / 2
                    and abs(dz) <= boxes[b, 5] / 2):
                out[b] += 1
    return out


@_jit
def sweep_histograms_by_cell(pts: Any, inv_cell: Any, origin: Any, shape: Any, zlo: Any,
                             zhi: Any, cell_start: Any, cell_boxes: Any, geometry: Any,
                             lags: Any, bin_m: Any, n_bins: Any
                             ) -> tuple[Any, Any]:  # pragma: no cover
    """Per box, the histograms along its heading of its returns, one per sweep (row 0 the
    current sweep, row ``1 + l`` the sweep of lag ``lags[l]``), for
    :func:`suit_ros.tracking.sweep_velocities`, in one pass over the points with
    ``zlo < z < zhi``, each tested against the boxes listed for its grid cell (as
    :func:`count_in_box_cells`).

    float32 arithmetic throughout, as numpy computes a float32 cloud against float scalars:
    ``geometry`` is ``(M, 7)`` float32: centre x, y, cos, sin, half the search length, half
    the width plus margin, the top (centre z + half height + margin).
    :return: ``(M, 1 + L, width)`` counts and each box's histogram length (its ``n_bins``,
        or more where a bin rounded up past it, as ``np.bincount`` would return).
    """
    M = geometry.shape[0]
    L = lags.shape[0]
    width = (n_bins.max() if M else 0) + 2
    out = np.zeros((M, L + 1, width), np.float64)
    length = n_bins.copy()
    o0, o1, s0, s1 = origin[0], origin[1], shape[0], shape[1]
    for i in range(pts.shape[0]):
        z = pts[i, 2]
        if not (z > zlo and z < zhi):
            continue
        k = _grid_cell(pts[i, 0], pts[i, 1], inv_cell, o0, o1, s0, s1)
        if k < 0:
            continue
        lag = pts[i, 4]
        row = 0
        valid = lag == 0
        for q in range(L):
            if lags[q] == lag:
                row = 1 + q
                valid = True
        if not valid:
            continue
        for j in range(cell_start[k], cell_start[k + 1]):
            b = cell_boxes[j]
            dx = pts[i, 0] - geometry[b, 0]
            dy = pts[i, 1] - geometry[b, 1]
            c = geometry[b, 2]
            s = geometry[b, 3]
            half = geometry[b, 4]
            u = dx * c + dy * s
            if abs(u) < half and abs(-dx * s + dy * c) < geometry[b, 5] and z < geometry[b, 6]:
                h = min(np.int64((u + half) / bin_m), width - 1)
                out[b, row, h] += 1.0
                length[b] = max(length[b], h + 1)
    return out, length


GROUND_BIN_M = 0.05     # the ground estimate's height bin (m)


@_jit
def height_histograms(points: Any, x0: float, y0: float, cell: float, nx: int, ny: int,
                      zlo: float, n_bins: int) -> Any:  # pragma: no cover
    """Per cell of an ``(ny, nx)`` grid of ``cell`` m from ``(x0, y0)``, a histogram of its
    points' heights in ``GROUND_BIN_M`` bins from ``zlo`` (points outside the grid or the band
    left out; :class:`suit_ros.ground.LocalGround`)."""
    out = np.zeros((nx * ny, n_bins), np.int32)
    inv = 1.0 / cell
    for i in range(points.shape[0]):
        fx = (points[i, 0] - x0) * inv
        fy = (points[i, 1] - y0) * inv
        fz = (points[i, 2] - zlo) * (1.0 / GROUND_BIN_M)
        if not (fx >= 0 and fx < nx and fy >= 0 and fy < ny and fz >= 0 and fz < n_bins):
            continue
        out[int(fy) * nx + int(fx), int(fz)] += 1
    return out


@_jit
def level_heights(points: Any, ground: Any, x0: float, y0: float, cell: float,
                  out: Any) -> None:  # pragma: no cover
    """``out = points`` with z minus the ground under each point: bilinear between the cell
    centres of ``ground`` ``(ny, nx)`` (at least 2 x 2), clamped at the grid's edge; a point
    with a coordinate that is not finite keeps its z."""
    ny, nx = ground.shape
    inv = 1.0 / cell
    umax = nx - 1.0
    vmax = ny - 1.0
    ncol = points.shape[1]
    for i in range(points.shape[0]):
        px = points[i, 0]
        py = points[i, 1]
        pz = points[i, 2]
        out[i, 0] = px
        out[i, 1] = py
        if ncol == 5:                                   # a model input: the common case
            out[i, 3] = points[i, 3]
            out[i, 4] = points[i, 4]
        else:
            for j in range(3, ncol):
                out[i, j] = points[i, j]
        u = (px - x0) * inv - 0.5
        v = (py - y0) * inv - 0.5
        if not (abs(u) < 1e9 and abs(v) < 1e9):        # NaN or infinite
            out[i, 2] = pz
            continue
        u = min(max(u, 0.0), umax)
        v = min(max(v, 0.0), vmax)
        ix = min(int(u), nx - 2)
        iy = min(int(v), ny - 2)
        a = u - ix
        b = v - iy
        g = ((1 - a) * (1 - b) * ground[iy, ix] + a * (1 - b) * ground[iy, ix + 1]
             + (1 - a) * b * ground[iy + 1, ix] + a * b * ground[iy + 1, ix + 1])
        out[i, 2] = pz - g


OVERHANG_BIN_M = 0.1     # the overhang filter's height bin (m); 64 bins a column at most


@_jit
def overhang_keep(points: Any, x0: float, y0: float, size: float, nx: int, ny: int,
                  zlo: float, n_bins: int, gap_bins: int, b_float: int,
                  gap_bins_per_m: float) -> Any:  # pragma: no cover
    """Which points to keep when the returns that hang are dropped
    (:class:`suit_ros.overhang.Overhang`): per column of a ``(ny, nx)`` grid of ``size`` m
    from ``(x0, y0)``, its occupied ``OVERHANG_BIN_M`` height bins from ``zlo`` (``n_bins``
    <= 64, one bit each) split into stacks at every ``max(gap_bins, round(gap_bins_per_m *
    r))`` empty bins in a row, ``r`` the column centre's distance from the origin; a point is
    dropped when its stack starts at bin ``b_float`` or higher. Points outside the grid or the
    bins (or not finite) are kept. :return: ``(N,)`` bool, and the number dropped."""
    n = points.shape[0]
    occ = np.zeros(nx * ny, np.uint64)
    cell = np.full(n, -1, np.int64)
    level = np.zeros(n, np.int64)
    inv = 1.0 / size
    inv_bin = 1.0 / OVERHANG_BIN_M
    one = np.uint64(1)
    high = False
    for i in range(n):
        fx = (points[i, 0] - x0) * inv
        fy = (points[i, 1] - y0) * inv
        fz = (points[i, 2] - zlo) * inv_bin
        if not (fx >= 0 and fx < nx and fy >= 0 and fy < ny and fz >= 0 and fz < n_bins):
            continue
        c = int(fy) * nx + int(fx)
        b = int(fz)
        cell[i] = c
        level[i] = b
        occ[c] |= one << np.uint64(b)
        if b >= b_float:
            high = True
    keep = np.ones(n, np.bool_)
    if not high:
        return keep, 0
    # per column, the bins whose stack starts at b_float or higher (one bit each); built
    # for the columns a high point is in
    floating = np.zeros(nx * ny, np.uint64)
    done = np.zeros(nx * ny, np.bool_)
    dropped = 0
    for i in range(n):
        c = cell[i]
        if c < 0 or level[i] < b_float:
            continue
        if not done[c]:
            done[c] = True
            bits = occ[c]
            gap = gap_bins
            if gap_bins_per_m > 0:
                rx = x0 + ((c % nx) + 0.5) * size
                ry = y0 + ((c // nx) + 0.5) * size
                gap = max(gap_bins, int(round(gap_bins_per_m * np.sqrt(rx * rx + ry * ry))))
            start = -1
            last = -n_bins - 1
            mask = np.uint64(0)
            for b in range(n_bins):
                if (bits >> np.uint64(b)) & one:
                    if b - last - 1 >= gap:
                        start = b
                    last = b
                    if start >= b_float:
                        mask |= one << np.uint64(b)
            floating[c] = mask
        if (floating[c] >> np.uint64(level[i])) & one:
            keep[i] = False
            dropped += 1
    return keep, dropped


@_jit
def rays_through(points: Any, o: Any, u: Any, cos_half: Any, near: Any, low: Any,
                 high: Any) -> Any:  # pragma: no cover
    """Per box ``m``: whether a return's ray (from ``o``) passed through it: on its bearings
    (unit direction ``u[m]``, within the half-angle whose cosine is ``cos_half[m]``), at or
    beyond its nearest range ``near[m]``, and at that range between heights ``low[m]`` and
    ``high[m]`` (relative to ``o``). One pass over the points, stopping when every box is hit
    (see :func:`suit_ros.tracking.unseen`)."""
    M = near.shape[0]
    hit = np.zeros(M, np.bool_)
    left = M
    for i in range(points.shape[0]):
        x = points[i, 0] - o[0]
        y = points[i, 1] - o[1]
        r = np.sqrt(x * x + y * y)
        if r <= 0.0:
            continue
        dz = points[i, 2] - o[2]
        for m in range(M):
            if hit[m] or r < near[m] or x * u[m, 0] + y * u[m, 1] < r * cos_half[m]:
                continue
            z = dz * near[m] / r
            if low[m] <= z <= high[m]:
                hit[m] = True
                left -= 1
        if left == 0:
            break
    return hit


def warm_up() -> None:
    """Compile (or load from the cache) every kernel for the argument types of the node's
    step: float32 clouds of 4 (the sensor's) and 5 columns (the model input), xyz slices of
    them, float64 boxes. (A test checks that a step after this compiles nothing more.)"""
    sweep = np.zeros((4, 4), np.float32)
    model_input = np.zeros((4, 5), np.float32)
    R, t, lag = np.eye(3, dtype=np.float32), np.zeros(3, np.float32), np.float32(0.0)
    in_range(sweep, np.float32(1.0), np.float32(2.0))
    in_range_times(sweep, np.zeros(4, np.float32), np.float32(1.0), np.float32(2.0))
    deskew_points(sweep, np.zeros(4, np.float32), np.zeros(3), np.zeros(3))
    transform_sweep(sweep, R, t, lag, model_input)
    transform_sweep(model_input, R, t, lag, model_input.copy())
    cells, mean, top = pillar_max(model_input, (-1.0, -1.0, -1.0, 1.0, 1.0, 1.0), 0.5, 4, 4,
                                  np.zeros((5, 2), np.float32))
    pillar_max(model_input, (-1.0, -1.0, -1.0, 1.0, 1.0, 1.0), 0.5, 4, 4,
               np.zeros((5, 2), np.float32), np.ones(4, np.bool_))
    W = np.zeros((2, 10), np.float32)
    for rows in (np.zeros((16, 2), np.float32), np.zeros((16, 2), np.uint16)):
        for occupied in (None, np.zeros(16, bool)):
            pillar_features(top, mean, cells, W, W[:, 0], (-1.0, -1.0, 0.5, 4, 4), rows, 0,
                            occupied)
    origin, shape = np.zeros(2, np.int64), np.array([2, 2])
    start, owners = np.array([0, 1, 1, 1, 1]), np.zeros(1, np.int64)
    for xyz in (sweep[:, :3], model_input):
        count_in_box_cells(xyz, np.float32(0.5), origin, shape, start, owners, np.ones((1, 7)),
                           np.ones(1), np.zeros(1))
    sweep_histograms_by_cell(model_input, np.float32(0.5), origin, shape, np.float32(0.3),
                             np.float32(5.0), start, owners, np.ones((1, 7), np.float32),
                             np.ones(1, np.float32), np.float32(0.1), np.ones(1, np.int64))
    distinct_values(model_input[:, 4])
    azimuth_counts(sweep[:, :3], 72)
    height_histograms(model_input, -1.0, -1.0, 1.0, 2, 2, -1.0, 4)
    level_heights(model_input, np.zeros((2, 2), np.float32), -1.0, -1.0, 1.0,
                  model_input.copy())
    overhang_keep(model_input, -1.0, -1.0, 0.5, 4, 4, -1.0, 20, 5, 10, 0.5)
    paired_bev_iou(np.ones((1, 7), np.float32), np.ones((1, 7), np.float32))
    greedy_bev_nms(np.ones((1, 7), np.float32), np.zeros(1, np.int64), np.float32(0.5), 0.0)
    suppress_near_kernel(np.zeros((1, 2)), np.zeros(1, np.int64), np.ones(1, np.bool_),
                         np.ones(1))
    cells1 = np.zeros((1, 3), np.int64)
    for skip in (np.zeros(0, np.bool_), np.zeros(4, np.bool_)):
        dilate_flat_cells(np.zeros(1, np.int64), 2, 2, 1, skip)
    for band in (np.zeros((0, 5)), np.ones((1, 5))):
        rectangle_cells(np.zeros((1, 2), np.int64), np.ones((1, 2), np.int64), 2,
                        np.zeros(2, np.int64), 2.0, band, 1.0)
    add_tap_spread(np.zeros((1, 2), np.float32), np.zeros((1, 9, 2), np.float32),
                   np.zeros(1, np.int64), np.zeros(1, np.int64), np.zeros((1, 2), np.float32),
                   np.zeros(1, np.int64), 1, 1)
    for dense, spread_into in ((np.zeros((1, 2), np.float32), add_tap_spread_dense),
                               (np.zeros((1, 2), np.uint16), add_tap_spread_dense_bf16)):
        spread_into(dense, np.zeros((1, 9, 2), np.float32), np.zeros(1, np.int64),
                    np.zeros(1, np.int64), np.zeros((1, 2), np.float32), 1, 1)
    f32 = np.zeros((1, 1, 2), np.float32)
    sum_triples(f32, f32, np.zeros((1, 1), np.float32), np.ones((1, 1), np.bool_),
                np.zeros((1, 1), np.float32), np.float32(0.1), np.zeros(2, np.float32),
                np.float32(1.0), np.zeros(1, np.int64), f32, np.ones((1, 1), np.bool_), 1, 1)
    pool_occupancy(np.zeros(4, np.bool_), 1, 2, 2, 2, 1)
    feeding_map(np.zeros(1, np.int64), 1, 2, 2)
    flags_at(np.zeros((1, 2, 2), np.bool_), np.zeros(1, np.int64), np.zeros((1, 2), np.float32),
             np.zeros(2, np.float32), np.float32(1.0))
    f32c = np.zeros((1, 3, 2), np.float32)
    carry_selection(np.zeros((1, 2, 2), np.bool_), np.zeros(1, np.int64), f32c,
                    np.zeros((1, 3), np.float32), np.ones((1, 7), np.float32),
                    np.zeros(1, np.int64), f32c, np.zeros((1, 3), np.float32),
                    np.ones((1, 7), np.float32), np.zeros(1, np.int64), 8, True,
                    np.zeros(2, np.float32), np.float32(1.0), np.float32(0.1), 0.5)
    T1 = np.eye(4)[None]
    move_cells(np.zeros((1, 1, 2), np.float32), np.zeros(1, np.float32), T1,
               np.zeros(1, np.int64), np.zeros((1, 1, 2), np.float32))
    move_boxes(np.zeros((1, 7), np.float32), np.zeros((1, 2), np.float32),
               np.zeros((1, 2), np.float32), T1, np.zeros(1, np.int64),
               np.zeros((1, 7), np.float32), np.zeros((1, 2), np.float32))
    for where in (np.zeros(0, np.int64), np.zeros(1, np.int64)):
        gather_taps(np.zeros((1, 2), np.float32), cells1, 1, 1, where,
                    np.zeros((1, 18), np.float32))
        gather_taps_bf16(np.zeros((1, 2), np.uint16), cells1, 1, 1, where,
                         np.zeros((1, 18), np.uint32))
    one = np.ones(1)
    rays_through(model_input, np.zeros(3), np.ones((1, 2)), one, one, one, one)
