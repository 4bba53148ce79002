"""3D detections <-> the custom-field PointCloud2, and -> visualization_msgs/MarkerArray.

The PointCloud2 has one point per box with fields (FLOAT32) ``x y z length width height yaw vx
vy score`` and ``label`` (UINT8, index into the class names); GT adds ``num_points`` and
``instance_id`` (UINT32).
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .classes import MessageClasses
from .errors import PointCloudError
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


def detections_to_array(boxes: NDArray[Any], velocities: NDArray[Any], scores: NDArray[Any],
                        labels: NDArray[Any], extra_fields: dict[str, NDArray[Any]] | None = None
                        ) -> NDArray[Any]:
    """The structured array behind the detections cloud."""
    b = np.asarray(boxes, np.float32).reshape(-1, 7)
    n = len(b)
    arr = np.zeros(n, detection_dtype(bool(extra_fields)))
    for i, name in enumerate(FLOAT_FIELDS[:7]):
        arr[name] = b[:, i]
    v = np.asarray(velocities, np.float32).reshape(n, 2)
    arr['vx'], arr['vy'] = v[:, 0], v[:, 1]
    arr['score'] = np.asarray(scores, np.float32).reshape(n)
    lab = np.asarray(labels).reshape(n)
    if n and (lab.min() < 0 or lab.max() > 255):
        raise PointCloudError('labels must be within 0..255 to fit the UINT8 label field')
    arr['label'] = lab.astype(np.uint8)
    for name in GT_FIELDS if extra_fields else ():
        arr[name] = np.asarray(extra_fields[name] if extra_fields else 0, np.uint32)
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
                              classes: MessageClasses, min_arrow_speed: float = 0.2) -> Any:
    """A MarkerArray: DELETEALL, then per box a CUBE, a TEXT label and a velocity ARROW.

    Namespaces are ``<class>/box``, ``<class>/label``, ``<class>/velocity``; ids are unique per
    namespace; every marker carries ``header``.
    """
    C = classes
    b = np.asarray(boxes, np.float64).reshape(-1, 7)
    v = np.asarray(velocities, np.float64).reshape(-1, 2)
    s = np.asarray(scores, np.float64).reshape(-1)
    lab = np.asarray(labels, np.int64).reshape(-1)
    markers = [C.Marker(header=header, ns='', id=0, action=DELETEALL)]
    zero = C.Duration(sec=0, nanosec=0)
    half = b[:, 6] * 0.5
    qz, qw = np.sin(half), np.cos(half)
    speed = np.hypot(v[:, 0], v[:, 1])
    ident = C.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)
    white = C.ColorRGBA(r=1.0, g=1.0, b=1.0, a=1.0)
    for i in range(len(b)):
        k = int(lab[i])
        name = class_names[k] if 0 <= k < len(class_names) else f'class{k}'
        r, g, bl = PALETTE[k % len(PALETTE)]
        x, y, z, length, width, height = (float(t) for t in b[i, :6])
        pose = C.Pose(position=C.Point(x=x, y=y, z=z),
                      orientation=C.Quaternion(x=0.0, y=0.0, z=float(qz[i]), w=float(qw[i])))
        markers.append(C.Marker(
            header=header, ns=f'{name}/box', id=i, type=CUBE, action=ADD, pose=pose,
            scale=C.Vector3(x=length, y=width, z=height),
            color=C.ColorRGBA(r=r, g=g, b=bl, a=0.45), lifetime=zero))
        markers.append(C.Marker(
            header=header, ns=f'{name}/label', id=i, type=TEXT_VIEW_FACING, action=ADD,
            pose=C.Pose(position=C.Point(x=x, y=y, z=z + height / 2 + 0.5), orientation=ident),
            scale=C.Vector3(x=0.0, y=0.0, z=0.8), color=white,
            text=f'{name} {s[i]:.2f}', lifetime=zero))
        if speed[i] >= min_arrow_speed:
            heading = math.atan2(v[i, 1], v[i, 0])
            markers.append(C.Marker(
                header=header, ns=f'{name}/velocity', id=i, type=ARROW, action=ADD,
                pose=C.Pose(position=C.Point(x=x, y=y, z=z + height / 2),
                            orientation=C.Quaternion(x=0.0, y=0.0, z=math.sin(heading / 2),
                                                     w=math.cos(heading / 2))),
                scale=C.Vector3(x=float(speed[i]), y=0.2, z=0.2),
                color=C.ColorRGBA(r=r, g=g, b=bl, a=1.0), lifetime=zero))
    return C.MarkerArray(markers=markers)
