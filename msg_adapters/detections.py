"""3D detections <-> the custom-field PointCloud2, and -> visualization_msgs/MarkerArray.

The PointCloud2 has one point per box with fields (FLOAT32) ``x y z length width height yaw vx
vy score`` and ``label`` (UINT8, index into the class names); GT adds ``num_points`` and
``instance_id`` (UINT32).
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
# class colours (RGBA) by label index; cycles for more classes
PALETTE = ((0.12, 0.47, 0.71), (1.0, 0.5, 0.05), (0.17, 0.63, 0.17), (0.84, 0.15, 0.16),
           (0.58, 0.4, 0.74), (0.55, 0.34, 0.29), (0.89, 0.47, 0.76), (0.5, 0.5, 0.5))
# visualization_msgs/Marker constants
ARROW, CUBE, TEXT_VIEW_FACING = 0, 1, 9
ADD, DELETEALL = 0, 3


def detection_dtype(with_gt: bool) -> np.dtype[Any]:
    """Structured dtype of the detections cloud (4-byte aligned)."""
    names = list(FLOAT_FIELDS) + ['label']
    formats: list[str] = ['<f4'] * len(FLOAT_FIELDS) + ['u1']
    offsets = [4 * i for i in range(len(FLOAT_FIELDS))] + [40]
    size = 44
    if with_gt:
        names += list(GT_FIELDS)
        formats += ['<u4', '<u4']
        offsets += [44, 48]
        size = 52
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
                        labels: NDArray[Any], extra_fields: dict[str, NDArray[Any]] | None = None
                        ) -> NDArray[Any]:
    """The structured array behind the detections cloud (see :func:`detection_dtype`)."""
    b, v, s, lab = _box_inputs(boxes, velocities, scores, labels)
    n = len(b)
    arr = np.zeros(n, detection_dtype(bool(extra_fields)))
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
                              extra_fields: dict[str, NDArray[Any]] | None = None) -> Any:
    """Build the detections (or GT, with ``extra_fields``) PointCloud2."""
    arr = detections_to_array(boxes, velocities, scores, labels, extra_fields)
    return array_to_pointcloud2(arr, header, classes, is_dense=True)


def pointcloud2_to_detections(msg: Any) -> dict[str, NDArray[Any]]:
    """Read a detections/GT cloud: ``boxes (N, 7)``, ``velocities (N, 2)``, ``scores``,
    ``labels`` (int64), and ``num_points``/``instance_id`` when present."""
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
    for n in GT_FIELDS:
        if n in names:
            out[n] = arr[n].astype(np.uint32)
    return out


def detections_to_markerarray(boxes: NDArray[Any], velocities: NDArray[Any],
                              scores: NDArray[Any], labels: NDArray[Any], header: Any,
                              class_names: tuple[str, ...] | list[str],
                              classes: MessageClasses, min_arrow_speed: float = 0.2,
                              factory: MessageFactory | None = None) -> Any:
    """A MarkerArray: DELETEALL, then per box a CUBE, a TEXT label and a velocity ARROW.

    The cube is oriented by the yaw and coloured by class (:data:`PALETTE`), the text reads
    ``'<class> <score:.2f>'`` above the box, the arrow (only when the speed is at least
    ``min_arrow_speed`` m/s) starts at the top of the box, points along the velocity and is as
    long as the speed in m/s. Namespaces are ``<class>/box``, ``<class>/label`` and
    ``<class>/velocity``, ids the box index (unique per namespace), ``lifetime`` 0 (the next
    array's DELETEALL clears them); every marker carries ``header``.

    Sub-messages that are equal between markers (the header, colours, lifetime, the text's
    orientation and scale) are shared objects: treat the result as read-only.

    :param boxes: ``(N, 7)`` x, y, z, length, width, height, yaw in ``header.frame_id``.
    :param velocities: ``(N, 2)`` vx, vy in m/s.
    :param scores: ``(N,)``; ``labels``: ``(N,)`` indices into ``class_names``.
    :param classes: which message classes to build (rclpy or rosbags).
    :param factory: how to build them; default :func:`message_factory` ``(classes)``.
    """
    C = classes
    f = factory or message_factory(classes)
    b, v, s, lab = _box_inputs(boxes, velocities, scores, labels)
    lifetime = C.Duration(sec=0, nanosec=0)
    ident = f.quaternion(0.0, 0.0, 0.0, 1.0)
    clear = f.color(0.0, 0.0, 0.0, 0.0)
    markers = [f.marker(header, '', 0, CUBE, DELETEALL, f.pose(f.point(0.0, 0.0, 0.0), ident),
                        f.vector3(0.0, 0.0, 0.0), clear, lifetime)]
    if not len(b):
        return C.MarkerArray(markers=markers)
    white = f.color(1.0, 1.0, 1.0, 1.0)
    text_scale = f.vector3(0.0, 0.0, 0.8)
    half_yaw = b[:, 6] * 0.5
    heading_half = np.arctan2(v[:, 1], v[:, 0]) * 0.5
    speed = np.hypot(v[:, 0], v[:, 1])
    top = b[:, 2] + b[:, 5] * 0.5
    columns = (b[:, 0], b[:, 1], b[:, 2], b[:, 3], b[:, 4], b[:, 5], np.sin(half_yaw),
               np.cos(half_yaw), top, top + 0.5, speed, np.sin(heading_half),
               np.cos(heading_half))
    rows = zip(*(c.tolist() for c in columns), lab.tolist(), s.tolist())
    styles: dict[int, tuple[str, str, str, str, Any, Any]] = {}
    for i, (x, y, z, length, width, height, qz, qw, z_top, z_text, speed_i, hz, hw, k,
            score) in enumerate(rows):
        style = styles.get(k)
        if style is None:
            name = class_names[k] if 0 <= k < len(class_names) else f'class{k}'
            r, g, bl = PALETTE[k % len(PALETTE)]
            style = styles[k] = (name, f'{name}/box', f'{name}/label', f'{name}/velocity',
                                 f.color(r, g, bl, 0.45), f.color(r, g, bl, 1.0))
        name, ns_box, ns_label, ns_velocity, box_color, arrow_color = style
        markers.append(f.marker(
            header, ns_box, i, CUBE, ADD,
            f.pose(f.point(x, y, z), f.quaternion(0.0, 0.0, qz, qw)),
            f.vector3(length, width, height), box_color, lifetime))
        markers.append(f.marker(
            header, ns_label, i, TEXT_VIEW_FACING, ADD, f.pose(f.point(x, y, z_text), ident),
            text_scale, white, lifetime, f'{name} {score:.2f}'))
        if speed_i >= min_arrow_speed:
            markers.append(f.marker(
                header, ns_velocity, i, ARROW, ADD,
                f.pose(f.point(x, y, z_top), f.quaternion(0.0, 0.0, hz, hw)),
                f.vector3(speed_i, 0.2, 0.2), arrow_color, lifetime))
    return C.MarkerArray(markers=markers)
