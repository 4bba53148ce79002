"""Motion distortion: a spinning LiDAR's sweep, taken while the vehicle moves, put back into the
instant of its stamp.

A spinning sensor takes a sweep over one turn (0.1 s at 10 Hz) and reports every return in its
frame at the moment it was taken. At 10 m/s the vehicle moves 1 m during a sweep, so what the
sensor saw last sits up to 1 m behind where it was at the stamp, and an object at the seam of
the sweep shows twice. Most drivers publish the sweep that way, with each return's time in a
field (Velodyne ``time``, Ouster ``t``, Hesai ``timestamp``, Livox ``offset_time``). The GT of
the synthetic world and of every dataset is at the stamp, and so is the pose the node stacks
sweeps with.

``deskew: true`` (the node's default) moves each return to where it would have been seen from
the sensor's pose at the stamp: the vehicle's motion over the sweep is read from the odometry
buffer (:func:`twist_from_poses`: constant velocity over the sweep, the poses around it
interpolated; when the odometry does not reach the end of the sweep yet, the motion of the
same span before its newest pose) and applied per return (:func:`deskew`, one compiled pass).
What moves by itself (another car) keeps its own smear: only the ego's motion is known.
A cloud deskewed upstream that still carries its times (Autoware's distortion corrector keeps
``time_stamp``; Argoverse 2's sweeps are compensated and keep ``offset_ns``, which is not
looked for) would be moved twice: set ``deskew: false`` for it.

Times come from the cloud (:func:`relative_times`): an integer field counts nanoseconds, a
float field seconds; values more than a day from zero are absolute (epoch) and are taken
relative to the cloud's stamp, as are smaller ones that only against the stamp make one sweep
(a clock that started near zero: simulation time). A sweep whose times span more than
:data:`MAX_SPAN_S` or are not finite is not deskewed, and the diagnostics say why; so is one
whose odometry jumps (:func:`implausible`, :func:`uneven`).

What it is worth on the synthetic drives (3 of 4 sensors sweep with distortion, the ego at up
to 13 m/s): docs/experiments/deskew.
"""
from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from suit_ros.msg_adapters.errors import PoseLookupError
from suit_ros.msg_adapters.odometry import PoseBuffer
from suit_ros.ops.kernels import deskew_points

# the per-point time fields drivers write, tried in this order when ``time_field`` is ''
# (Velodyne, Ouster, Hesai and Robosense, Autoware's nebula, Livox)
TIME_FIELDS = ('time', 't', 'timestamp', 'time_stamp', 'offset_time')
MAX_SPAN_S = 0.5          # a sweep's times span at most this (a 2 Hz sensor), else not a sweep
ABSOLUTE_S = 86_400.0     # values further from zero than a day are epoch times
MIN_MOTION_SPAN_S = 0.02  # the odometry must cover at least this much of the sweep's span
ABSOLUTE_NS = 1e15        # float values beyond this are epoch nanoseconds (Livox writes them)
MAX_SPEED = 70.0          # m/s: odometry moving faster over a sweep jumped (a relocalisation)
MAX_TURN = 3.0            # rad/s: the same for turning
# the two halves of the sweep's window may differ by at most this much (a car braking at 1 g
# changes speed 0.5 m/s in 50 ms): a smaller odometry step (a 0.3 m relocalisation in a 0.1 s
# sweep reads as 6 m/s, well under MAX_SPEED) would otherwise warp the cloud by its size
MAX_SPEED_CHANGE = 3.0    # m/s
MAX_TURN_CHANGE = 1.0     # rad/s


def relative_times(values: NDArray[Any], stamp_ns: int) -> tuple[NDArray[np.float32] | None,
                                                                   str]:
    """Each return's time relative to the cloud stamp (s), from a time field's values.

    :param values: the field as read (integers: nanoseconds; floats: seconds), absolute
        (epoch) or relative to the stamp.
    :return: ``(times, '')``, or ``(None, why)`` when they cannot be a sweep's.
    """
    v = np.asarray(values)
    if not len(v):
        return np.zeros(0, np.float32), ''
    if np.issubdtype(v.dtype, np.integer):
        ns = v.astype(np.int64)
        absolute = max(abs(int(ns.min())), abs(int(ns.max()))) * 1e-9 > ABSOLUTE_S
        rel = ((ns - stamp_ns) if absolute else ns).astype(np.float64) * 1e-9
    else:
        first, last = float(v.min()), float(v.max())       # NaN comes through both
        if not (np.isfinite(first) and np.isfinite(last)):
            return None, 'times not finite'
        top = max(abs(first), abs(last))
        absolute = top > ABSOLUTE_S
        if absolute and v.dtype.itemsize < 8:
            return None, (f'absolute times in a {v.dtype.itemsize * 8}-bit float field '
                          '(too coarse to place a return within the sweep)')
        if top > ABSOLUTE_NS:                              # epoch nanoseconds in a float
            rel = (v.astype(np.float64) - float(stamp_ns)) * 1e-9
        else:
            rel = v.astype(np.float64) - stamp_ns * 1e-9 if absolute else v
    why = _not_a_sweep(rel)
    if why and not absolute:
        # absolute times of a clock that started near zero (simulation time, a bag replayed
        # from 0) read as relative ones: taken against the stamp they may be one sweep
        if np.issubdtype(v.dtype, np.integer):
            rel_abs = (v.astype(np.int64) - stamp_ns).astype(np.float64) * 1e-9
        else:
            rel_abs = v.astype(np.float64) - stamp_ns * 1e-9
        if not _not_a_sweep(rel_abs):
            rel, why = rel_abs, ''
    if why:
        return None, why
    return np.asarray(rel, np.float32), ''


def _not_a_sweep(rel: NDArray[Any]) -> str:
    """Why times relative to the stamp (s) are not one sweep's ('' when they are)."""
    lo, hi = float(rel.min()), float(rel.max())
    if hi - lo > MAX_SPAN_S or max(abs(lo), abs(hi)) > 2 * MAX_SPAN_S:
        return (f'times from {lo:+.3f} to {hi:+.3f} s of the stamp: not one sweep '
                f'(at most {MAX_SPAN_S} s)')
    return ''


def rotation_vector(R: NDArray[np.float64]) -> NDArray[np.float64]:
    """Axis times angle of a rotation matrix (ill-conditioned near half a turn, which a
    vehicle does not turn in a sweep)."""
    w = 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    sin = float(np.linalg.norm(w))
    angle = float(np.arctan2(sin, 0.5 * (np.trace(R) - 1.0)))
    return w * (angle / sin) if sin > 1e-12 else w


def arc_matrix(w: NDArray[np.float64]) -> NDArray[np.float64]:
    """The matrix that takes a constant twist's linear part to its translation after turning
    by the rotation vector ``w`` (SE(3)'s exponential: ``I + (1 - cos a) / a K + (a - sin a) /
    a K^2``, K the unit axis' cross product)."""
    a = float(np.linalg.norm(w))
    if a < 1e-12:
        return np.eye(3)
    k = w / a
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    out: NDArray[np.float64] = np.eye(3) + (1 - np.cos(a)) / a * K + (a - np.sin(a)) / a * K @ K
    return out


def body_twist(T_a: NDArray[np.float64], T_b: NDArray[np.float64], dt: float
               ) -> NDArray[np.float64]:
    """``(6,)`` angular (rad/s) then linear (m/s) velocity, in the body frame, that moves pose
    ``T_a`` to ``T_b`` in ``dt`` seconds (constant velocity: SE(3)'s logarithm)."""
    D = np.linalg.solve(T_a, T_b)
    w = rotation_vector(D[:3, :3])
    out: NDArray[np.float64] = np.concatenate([w, np.linalg.solve(arc_matrix(w), D[:3, 3])]) / dt
    return out


def implausible(twist: NDArray[np.float64]) -> str:
    """Why a twist cannot be a vehicle's over a sweep ('' when it can): an odometry jump
    (relocalisation) inside the window would otherwise warp the whole cloud."""
    speed, turn = sweep_speed(twist), float(np.linalg.norm(twist[:3]))
    if speed > MAX_SPEED or turn > MAX_TURN or not np.isfinite(twist).all():
        return (f'odometry moved at {speed:.0f} m/s, turned at {turn:.1f} rad/s over the '
                f'sweep (a jump: at most {MAX_SPEED:g} m/s, {MAX_TURN:g} rad/s)')
    return ''


def motion_window(poses: PoseBuffer, start_ns: int, end_ns: int) -> tuple[int, int] | None:
    """The span ``(a, b)`` (ns) of the buffered odometry that tells the vehicle's motion over a
    sweep from ``start_ns`` to ``end_ns``: the sweep's own; where the buffer ends before the
    sweep does (odometry arrives later than the cloud), the same span before its newest pose;
    None when the buffer holds less than :data:`MIN_MOTION_SPAN_S` of it."""
    span = poses.span()
    if span is None or len(poses) < 2:
        return None
    first, last = span
    b = min(end_ns, last)
    a = max(first, b - max(end_ns - start_ns, int(MIN_MOTION_SPAN_S * 1e9)))
    return (a, b) if (b - a) * 1e-9 >= MIN_MOTION_SPAN_S else None


def _twist(poses: PoseBuffer, a: int, b: int) -> NDArray[np.float64] | None:
    try:
        return body_twist(poses.lookup(a), poses.lookup(b), (b - a) * 1e-9)
    except PoseLookupError:
        return None


def twist_from_poses(poses: PoseBuffer, start_ns: int, end_ns: int) -> NDArray[np.float64] | None:
    """The vehicle's twist over a sweep from ``start_ns`` to ``end_ns`` (base_link, see
    :func:`body_twist`) over its :func:`motion_window`, or None when the buffer holds too
    little motion to tell."""
    window = motion_window(poses, start_ns, end_ns)
    return None if window is None else _twist(poses, *window)


def uneven(poses: PoseBuffer, window: tuple[int, int]) -> str:
    """Why the odometry over a sweep's :func:`motion_window` is not one steady motion ('' when
    it is): its two halves differ by more than :data:`MAX_SPEED_CHANGE` or
    :data:`MAX_TURN_CHANGE`, a step (relocalisation) too small for :func:`implausible`."""
    a, b = window
    mid = (a + b) // 2
    first, second = _twist(poses, a, mid), _twist(poses, mid, b)
    if first is None or second is None:
        return ''
    speed = float(np.linalg.norm(first[3:] - second[3:]))
    turn = float(np.linalg.norm(first[:3] - second[:3]))
    if speed > MAX_SPEED_CHANGE or turn > MAX_TURN_CHANGE:
        return (f'odometry changed by {speed:.1f} m/s, {turn:.2f} rad/s within the sweep (a '
                f'jump: at most {MAX_SPEED_CHANGE:g} m/s, {MAX_TURN_CHANGE:g} rad/s)')
    return ''


def deskew(points: NDArray[np.float32], times: NDArray[np.float32],
           twist: NDArray[np.float64], T_base_lidar: NDArray[np.float64]) -> NDArray[np.float32]:
    """The returns ``(N, >= 3)`` (LiDAR frame, each taken ``times`` s after the stamp) in the
    LiDAR frame at the stamp, for a vehicle moving with ``twist`` (:func:`body_twist`); a new
    array, other columns as they were."""
    if len(times) != len(points):
        raise ValueError(f'deskew: {len(times)} times for {len(points)} points')
    R, t = T_base_lidar[:3, :3], T_base_lidar[:3, 3]
    w_b, v_b = twist[:3], twist[3:]
    # the same motion seen from the sensor: the twist moved by the extrinsic
    w = R.T @ w_b
    v = R.T @ (v_b + np.cross(w_b, t))
    out = np.array(points, np.float32, order='C', copy=True)
    deskew_points(out, np.ascontiguousarray(times, np.float32), w, v)
    return out


def deskew_sweep(points: NDArray[Any], times: NDArray[np.float32], stamp_ns: int,
                 poses: PoseBuffer, T_base_lidar: NDArray[np.float64]
                 ) -> tuple[NDArray[Any], NDArray[np.float64] | None, str]:
    """A sweep's returns moved to the sensor's pose at ``stamp_ns`` by the motion the odometry
    ``poses`` (base_link) show over the sweep (:func:`twist_from_poses`), that motion and ''; or
    the points as they are (any dtype), None and why: a sweep at the stamp's instant, odometry
    that cannot tell, or a motion no vehicle makes (:func:`implausible`, :func:`uneven`)."""
    if not len(times) or not times.any():
        return points, None, 'sweep at one instant'
    lo, hi = float(times.min()), float(times.max())
    start = stamp_ns + int(round(min(lo, 0.0) * 1e9))
    end = stamp_ns + int(round(max(hi, 0.0) * 1e9))
    window = motion_window(poses, start, end)
    twist = None if window is None else _twist(poses, *window)
    if window is None or twist is None:
        return points, None, 'no odometry over the sweep'
    why = implausible(twist) or uneven(poses, window)
    if why:
        return points, None, why
    return deskew(points, times, twist, T_base_lidar), twist, ''


def sweep_speed(twist: NDArray[np.float64]) -> float:
    """The vehicle's speed (m/s) in a twist."""
    return float(np.linalg.norm(twist[3:]))
