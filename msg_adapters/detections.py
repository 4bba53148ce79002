"""3D detections <-> the custom-field PointCloud2, and -> visualization_msgs/MarkerArray.

The PointCloud2 has one point per box with fields (FLOAT32) ``x y z length width height yaw vx
vy score`` and ``label`` (UINT8, index into the class names); GT adds ``num_points`` and
``instance_id`` (UINT32); the node's detections add ``held`` (UINT8, in the byte after
``label``: 0 a box decoded from what the current cloud shows, 1 one a carry branch holds where
the cloud has no returns, 2 one the tracker coasts with no detection this frame),
``num_points`` (UINT32: the current cloud's returns inside the box; 0 for a held box, and
also for a box seen now whose returns lie on its faces just outside it) and, from the
tracker, ``track_id`` (UINT32, the same object keeps its id across frames; 0:
not tracked) and ``vel_std`` (FLOAT32, m/s: the standard deviation of ``vx`` and of ``vy``,
the tracker's for a tracked box, the measurement's for one no track took; NaN where the
velocity is NaN).
"""
from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from .builders import MessageFactory, message_factory
from .classes import MessageClasses
from .errors import MessageError, PointCloudError
from .pointcloud2 import array_to_pointcloud2, pointcloud2_to_array

FLOAT_FIELDS = ('x', 'y', 'z', 'length', 'width', 'height', 'yaw', 'vx', 'vy', 'score')
GT_FIELDS = ('num_points', 'instance_id')
TRACK_FIELD = 'track_id'
VEL_STD_FIELD = 'vel_std'
HELD_FIELD = 'held'
HELD_SEEN, HELD_CARRIED, HELD_COASTED = 0, 1, 2     # the held field's values
HELD_WORDS = {HELD_CARRIED: ' carried', HELD_COASTED: ' coasted'}   # in a box's marker text
# class colours (RGBA) by label index; cycles for more classes
PALETTE = ((0.12, 0.47, 0.71), (1.0, 0.5, 0.05), (0.17, 0.63, 0.17), (0.84, 0.15, 0.16),
           (0.58, 0.4, 0.74), (0.55, 0.34, 0.29), (0.89, 0.47, 0.76), (0.5, 0.5, 0.5))
# visualization_msgs/Marker constants
ARROW, CUBE, LINE_LIST, TEXT_VIEW_FACING = 0, 1, 5, 9
ADD, DELETEALL = 0, 3


MARKER_LIFETIME_S = 1.0     # a marker's life when no later array deletes it (s)

def detection_dtype(with_gt: bool, with_track: bool = False, with_points: bool = False,
                    with_vel_std: bool = False, with_held: bool = False) -> np.dtype[Any]:
    """Structured dtype of the detections cloud (4-byte aligned): after the common ones
    (``held`` in the byte after ``label``, where padding was), GT fields (or ``num_points``
    alone), then ``track_id``, then ``vel_std``."""
    names = list(FLOAT_FIELDS) + ['label']
    formats: list[str] = ['<f4'] * len(FLOAT_FIELDS) + ['u1']
    offsets = [4 * i for i in range(len(FLOAT_FIELDS))] + [40]
    if with_held:
        names.append(HELD_FIELD)
        formats.append('u1')
        offsets.append(41)
    size = 44
    if with_gt:
        names += list(GT_FIELDS)
        formats += ['<u4', '<u4']
        offsets += [size, size + 4]
        size += 8
    elif with_points:
        names.append(GT_FIELDS[0])
        formats.append('<u4')
        offsets.append(size)
        size += 4
    if with_track:
        names.append(TRACK_FIELD)
        formats.append('<u4')
        offsets.append(size)
        size += 4
    if with_vel_std:
        names.append(VEL_STD_FIELD)
        formats.append('<f4')
        offsets.append(size)
        size += 4
    return np.dtype({'names': names, 'formats': formats, 'offsets': offsets, 'itemsize': size})


def _box_inputs(boxes: NDArray[Any], velocities: NDArray[Any], scores: NDArray[Any],
                   labels: NDArray[Any]) -> tuple[NDArray[np.float64], NDArray[np.float64],
                                                  NDArray[np.float64], NDArray[np.int64]]:
    """Boxes ``(N, 7)``, velocities ``(N, 2)``, scores ``(N,)``, labels ``(N,)``, checked."""
    b = np.asarray(boxes, np.float64).reshape(-1, 7)
    n = len(b)
    v = np.asarray(velocities, np.float64)
    s = np.asarray(scores, np.float64).reshape(-1)
    lab = np.asarray(labels, np.int64).reshape(-1)
    if v.size != 2 * n or len(s) != n or len(lab) != n:
        raise MessageError(f'{n} boxes need (N, 2) velocities, N scores and N labels; got '
                           f'{v.shape}, {s.shape}, {lab.shape}')
    return b, v.reshape(n, 2), s, lab


def detections_to_array(boxes: NDArray[Any], velocities: NDArray[Any], scores: NDArray[Any],
                        labels: NDArray[Any], extra_fields: dict[str, NDArray[Any]] | None = None,
                        track_ids: NDArray[Any] | None = None,
                        num_points: NDArray[Any] | None = None,
                        vel_std: NDArray[Any] | None = None,
                        held: NDArray[Any] | None = None) -> NDArray[Any]:
    """The structured array behind the detections cloud (see :func:`detection_dtype`)."""
    b, v, s, lab = _box_inputs(boxes, velocities, scores, labels)
    n = len(b)
    arr = np.zeros(n, detection_dtype(bool(extra_fields), track_ids is not None,
                                      num_points is not None, vel_std is not None,
                                      held is not None))
    if held is not None:
        how = np.asarray(held).reshape(-1)
        if len(how) != n:
            raise MessageError(f'{len(how)} held flags for {n} boxes')
        if n and (how.min() < HELD_SEEN or how.max() > HELD_COASTED):
            raise PointCloudError(f'held must be {HELD_SEEN} (seen), {HELD_CARRIED} (carried) '
                                  f'or {HELD_COASTED} (coasted)')
        arr[HELD_FIELD] = how.astype(np.uint8)
    if vel_std is not None:
        std = np.asarray(vel_std, np.float64).reshape(-1)
        if len(std) != n:
            raise MessageError(f'{len(std)} velocity standard deviations for {n} boxes')
        if np.isinf(std).any() or (std < 0).any():        # NaN: unknown (a NaN velocity)
            raise PointCloudError('velocity standard deviations must be >= 0 and finite (NaN: '
                                  'unknown)')
        arr[VEL_STD_FIELD] = std
    for name, what, values in ((TRACK_FIELD, 'track ids', track_ids),
                               (GT_FIELDS[0], 'point counts', num_points)):
        if values is None or (extra_fields and name != TRACK_FIELD):
            continue                      # GT fields carry their own num_points
        ids = np.asarray(values).reshape(-1)
        if len(ids) != n:
            raise MessageError(f'{len(ids)} {what} for {n} boxes')
        if n and (ids.min() < 0 or ids.max() > np.iinfo(np.uint32).max):
            raise PointCloudError(f'{what} must fit the UINT32 {name} field')
        arr[name] = ids.astype(np.uint32)
    for i, name in enumerate(FLOAT_FIELDS[:7]):
        arr[name] = b[:, i]
    arr['vx'], arr['vy'], arr['score'] = v[:, 0], v[:, 1], s
    if n and (lab.min() < 0 or lab.max() > 255):
        raise PointCloudError('labels must be within 0..255 to fit the UINT8 label field')
    arr['label'] = lab.astype(np.uint8)
    if extra_fields:
        missing = [k for k in GT_FIELDS if k not in extra_fields]
        if missing:
            raise MessageError(f'extra_fields needs {list(GT_FIELDS)}; {missing} missing')
        for name in GT_FIELDS:
            values = np.asarray(extra_fields[name]).reshape(-1)
            if len(values) != n:
                raise MessageError(f'extra field {name!r} has {len(values)} values for {n} boxes')
            arr[name] = values.astype(np.uint32)
    return arr


def detections_to_pointcloud2(boxes: NDArray[Any], velocities: NDArray[Any],
                              scores: NDArray[Any], labels: NDArray[Any], header: Any,
                              classes: MessageClasses,
                              extra_fields: dict[str, NDArray[Any]] | None = None,
                              track_ids: NDArray[Any] | None = None,
                              num_points: NDArray[Any] | None = None,
                              vel_std: NDArray[Any] | None = None,
                              held: NDArray[Any] | None = None) -> Any:
    """Build the detections (or GT, with ``extra_fields``) PointCloud2; ``track_ids`` adds the
    ``track_id`` field, ``num_points`` the ``num_points`` field, ``vel_std`` the ``vel_std``
    field, ``held`` the ``held`` field."""
    arr = detections_to_array(boxes, velocities, scores, labels, extra_fields, track_ids,
                              num_points, vel_std, held)
    return array_to_pointcloud2(arr, header, classes)   # is_dense: every x y z finite


def pointcloud2_to_detections(msg: Any) -> dict[str, NDArray[Any]]:
    """Read a detections/GT cloud: ``boxes (N, 7)``, ``velocities (N, 2)``, ``scores``,
    ``labels`` (int64), ``num_points``/``instance_id``/``track_id`` (uint32) and ``vel_std``
    (float32) when present."""
    arr = pointcloud2_to_array(msg).reshape(-1)
    names = set(arr.dtype.names or ())
    missing = [n for n in FLOAT_FIELDS + ('label',) if n not in names]
    if missing:
        raise PointCloudError(f'not a detections cloud: missing field(s) {missing}')
    out = {'boxes': np.stack([arr[n].astype(np.float32) for n in FLOAT_FIELDS[:7]], 1)
           .reshape(-1, 7),
           'velocities': np.stack([arr['vx'], arr['vy']], 1).astype(np.float32).reshape(-1, 2),
           'scores': arr['score'].astype(np.float32),
           'labels': arr['label'].astype(np.int64)}
    for n in GT_FIELDS + (TRACK_FIELD,):
        if n in names:
            out[n] = arr[n].astype(np.uint32)
    if VEL_STD_FIELD in names:
        out[VEL_STD_FIELD] = arr[VEL_STD_FIELD].astype(np.float32)
    if HELD_FIELD in names:
        out[HELD_FIELD] = arr[HELD_FIELD].astype(np.uint8)
    return out


# the 12 edges of a box as pairs of corner indices (corners: bottom 0-3, top 4-7, same order)
BOX_EDGES = np.array([[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4],
                      [0, 4], [1, 5], [2, 6], [3, 7]])


def box_corners(boxes: NDArray[np.float64]) -> NDArray[np.float64]:
    """Corners ``(N, 8, 3)`` of boxes ``(N, 7)``: bottom face counter-clockwise from
    (+length/2, +width/2) in the box frame, then the top face in the same order."""
    b = np.asarray(boxes, np.float64).reshape(-1, 7)
    local = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], np.float64) * 0.5
    xy = local[None] * b[:, None, 3:5]                               # (N, 4, 2)
    c, s = np.cos(b[:, 6])[:, None], np.sin(b[:, 6])[:, None]
    x = b[:, None, 0] + c * xy[..., 0] - s * xy[..., 1]
    y = b[:, None, 1] + s * xy[..., 0] + c * xy[..., 1]
    z0 = np.repeat((b[:, 2] - b[:, 5] * 0.5)[:, None], 4, 1)
    z1 = z0 + b[:, 5:6]
    bottom = np.stack([x, y, z0], -1)
    top = np.stack([x, y, z1], -1)
    return np.concatenate([bottom, top], 1)


def detections_to_markerarray(boxes: NDArray[Any], velocities: NDArray[Any],
                              scores: NDArray[Any], labels: NDArray[Any], header: Any,
                              class_names: tuple[str, ...] | list[str],
                              classes: MessageClasses, min_arrow_speed: float = 0.2,
                              factory: MessageFactory | None = None,
                              line_width: float = 0.08,
                              track_ids: NDArray[Any] | None = None,
                              lifetime_s: float = MARKER_LIFETIME_S,
                              held: NDArray[Any] | None = None) -> Any:
    """A MarkerArray: DELETEALL, one LINE_LIST per class, one TEXT label per box.

    The LINE_LIST of a class (namespace ``<class>/boxes``, id 0, coloured by class from
    :data:`PALETTE`, ``scale.x`` the line width) holds the 12 edges of each of its boxes
    (24 points per box, in the order of :func:`box_corners` and :data:`BOX_EDGES`) followed by
    one velocity segment per box moving at ``min_arrow_speed`` m/s or more: from the centre of
    the box's top face to where it will be in one second. The text (namespace
    ``<class>/labels``, id the box index) reads ``'<class> <score:.2f>'`` above the box, and
    ``' #<track id>'`` after it for a tracked box (``track_ids`` given, id > 0), then
    ``' carried'`` or ``' coasted'`` for a box held where the cloud shows nothing (``held``
    given: the detections cloud's field).
    The next array's DELETEALL clears them, and each lives ``lifetime_s`` (1 s: ten frames at
    10 Hz), so that boxes do not stay in a viewer when no array follows (the input stopped, a
    frame failed, the node ended); every marker carries ``header``.

    Sub-messages equal between markers (the header, the lifetime, colours, the identity pose)
    are shared objects: treat the result as read-only.

    :param boxes: ``(N, 7)`` x, y, z, length, width, height, yaw in ``header.frame_id``.
    :param velocities: ``(N, 2)`` vx, vy in m/s.
    :param scores: ``(N,)``; ``labels``: ``(N,)`` indices into ``class_names``.
    :param classes: which message classes to build (rclpy or rosbags).
    :param factory: how to build them; default :func:`message_factory` ``(classes)``.
    """
    C = classes
    f = factory or message_factory(classes)
    b, v, s, lab = _box_inputs(boxes, velocities, scores, labels)
    if not lifetime_s >= 0:
        raise ValueError(f'lifetime_s must be >= 0 (0: until deleted), got {lifetime_s}')
    sec, nanosec = divmod(int(round(lifetime_s * 1e9)), 1_000_000_000)
    lifetime = C.Duration(sec=sec, nanosec=nanosec)
    ident = f.pose(f.point(0.0, 0.0, 0.0), f.quaternion(0.0, 0.0, 0.0, 1.0))
    markers = [f.marker(header, '', 0, LINE_LIST, DELETEALL, ident, f.vector3(0.0, 0.0, 0.0),
                        f.color(0.0, 0.0, 0.0, 0.0), lifetime)]
    if not len(b):
        return C.MarkerArray(markers=markers)
    corners = box_corners(b)
    edges = corners[:, BOX_EDGES.reshape(-1)]                         # (N, 24, 3)
    top = b[:, :3].copy()
    top[:, 2] += b[:, 5] * 0.5
    moving = np.hypot(v[:, 0], v[:, 1]) >= min_arrow_speed
    white = f.color(1.0, 1.0, 1.0, 1.0)
    text_scale = f.vector3(0.0, 0.0, 0.8)
    names = {k: class_names[k] if 0 <= k < len(class_names) else f'class{k}'
             for k in set(lab.tolist())}
    for k in sorted(names):
        idx = np.flatnonzero(lab == k)
        ends = [edges[idx].reshape(-1, 3)]
        go = idx[moving[idx]]
        if len(go):
            seg = np.stack([top[go], top[go] + np.c_[v[go], np.zeros(len(go))]], 1)
            ends.append(seg.reshape(-1, 3))
        points = [f.point(x, y, z) for x, y, z in np.concatenate(ends).tolist()]
        r, g, bl = PALETTE[k % len(PALETTE)]
        markers.append(f.marker(header, f'{names[k]}/boxes', 0, LINE_LIST, ADD, ident,
                                f.vector3(line_width, 0.0, 0.0), f.color(r, g, bl, 1.0),
                                lifetime, points=points))
    z_text = (top[:, 2] + 0.5).tolist()
    ids = (np.zeros(len(b), np.int64) if track_ids is None
           else np.asarray(track_ids, np.int64).reshape(-1))
    if len(ids) != len(b):
        raise MessageError(f'{len(ids)} track ids for {len(b)} boxes')
    how = (np.zeros(len(b), np.int64) if held is None
           else np.asarray(held, np.int64).reshape(-1))
    if len(how) != len(b):
        raise MessageError(f'{len(how)} held flags for {len(b)} boxes')
    for i, (x, y, z, k, score, tid, h) in enumerate(zip(
            b[:, 0].tolist(), b[:, 1].tolist(), z_text, lab.tolist(), s.tolist(), ids.tolist(),
            how.tolist())):
        text = (f'{names[k]} {score:.2f}' + (f' #{tid}' if tid > 0 else '')
                + HELD_WORDS.get(h, ''))
        markers.append(f.marker(header, f'{names[k]}/labels', i, TEXT_VIEW_FACING, ADD,
                                f.pose(f.point(x, y, z), ident.orientation), text_scale, white,
                                lifetime, text))
    return C.MarkerArray(markers=markers)
