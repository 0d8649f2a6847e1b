"""Planar pose helpers: angle wrapping, pose composition, yaw <-> quaternion.

Poses are ``[x, y, theta]`` rows; every function accepts one pose ``(3,)`` or a stack ``(N, 3)``.

The filter calls ``compose``, ``relative`` and ``integrate_twists`` many times per scan on one pose or a
few: there numpy's per-call cost is most of the time, so one pose goes through Python floats and the
arrays of ``integrate_twists`` (and a stack composed with one pose) through compiled loops, with the
numpy code's arithmetic in the same order (``compose_numpy``, ``integrate_twists_numpy`` and ``relative``'s
numpy code, which takes stacks, are the references, asserted equal in ``test/test_geometry_motion.py``).
"""
from __future__ import annotations

import math

import numpy as np

try:  # numba is pinned; the numpy code serves without it
    from numba import njit
except ImportError:  # pragma: no cover
    njit = None

TWO_PI = 2.0 * math.pi


def _one_pose(a):
    """[x, y, θ] as three Python floats when ``a`` is one float64 pose with a finite heading (math.cos would
    refuse an infinite one), else None: numpy takes it."""
    if type(a) is np.ndarray and a.shape == (3,) and a.dtype == np.float64:
        a = a.tolist()
    elif not (type(a) in (list, tuple) and len(a) == 3 and all(type(v) is float for v in a)):
        return None
    return a if not math.isinf(a[2]) else None


def _wrap(theta: float) -> float:
    """``wrap_angle`` of one float (Python's float modulo is numpy's remainder)."""
    wrapped = (theta + math.pi) % TWO_PI - math.pi
    return wrapped + TWO_PI if wrapped <= -math.pi else wrapped


def wrap_angle(theta):
    """Wrap angles to (-pi, pi]."""
    wrapped = np.remainder(np.asarray(theta, dtype=float) + np.pi, 2.0 * np.pi) - np.pi
    # remainder maps +pi to -pi; the convention here is (-pi, pi].
    return np.where(wrapped <= -np.pi, wrapped + 2.0 * np.pi, wrapped)


def compose(pose, delta):
    """Pose composition ``pose ⊕ delta``: apply ``delta`` (expressed in the frame of ``pose``).

        x' = x + cos(θ) dx - sin(θ) dy
        y' = y + sin(θ) dx + cos(θ) dy
        θ' = θ + dθ
    """
    a, d = _one_pose(pose), _one_pose(delta)
    if a is not None and d is not None:
        return np.array(compose_floats(a, d))
    if _compose_kernel is not None and (a is not None or d is not None):  # a stack and one pose
        pose, delta = np.asarray(pose, dtype=float), np.asarray(delta, dtype=float)
        if max(pose.ndim, delta.ndim) == 2 and pose.shape[-1] == delta.shape[-1] == 3:
            # C-contiguous and writable: the one signature the compiled loop is cached for
            pose, delta = (np.require(v, requirements=("C", "W")).reshape(-1, 3) for v in (pose, delta))
            out = np.empty((len(delta) if a is not None else len(pose), 3))  # the stack's rows
            _compose_kernel(pose, delta, out)
            return out
    return compose_numpy(pose, delta)


def compose_floats(pose, delta) -> tuple[float, float, float]:
    """``compose`` of one pose and one delta given as three floats each (a finite heading), as three floats."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return pose[0] + c * delta[0] - s * delta[1], pose[1] + s * delta[0] + c * delta[1], _wrap(pose[2] + delta[2])


def compose_numpy(pose, delta):
    """``compose`` in numpy (any broadcast shapes): the reference of the other paths."""
    pose = np.asarray(pose, dtype=float)
    delta = np.asarray(delta, dtype=float)
    c, s = np.cos(pose[..., 2]), np.sin(pose[..., 2])
    out = np.empty(np.broadcast_shapes(pose.shape, delta.shape))
    out[..., 0] = pose[..., 0] + c * delta[..., 0] - s * delta[..., 1]
    out[..., 1] = pose[..., 1] + s * delta[..., 0] + c * delta[..., 1]
    out[..., 2] = wrap_angle(pose[..., 2] + delta[..., 2])
    return out


def relative(pose_from, pose_to):
    """The delta ``d`` with ``compose(pose_from, d) == pose_to`` (``pose_from ⊖ pose_to``)."""
    a, b = _one_pose(pose_from), _one_pose(pose_to)
    if a is not None and b is not None:
        c, s = math.cos(a[2]), math.sin(a[2])
        dx, dy = b[0] - a[0], b[1] - a[1]
        return np.array([c * dx + s * dy, -s * dx + c * dy, _wrap(b[2] - a[2])])
    a = np.asarray(pose_from, dtype=float)
    b = np.asarray(pose_to, dtype=float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    dx, dy = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1]
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = c * dx + s * dy
    out[..., 1] = -s * dx + c * dy
    out[..., 2] = wrap_angle(b[..., 2] - a[..., 2])
    return out


def inverse(pose):
    """The inverse transform of ``pose``: ``compose(pose, inverse(pose)) == 0``."""
    pose = np.asarray(pose, dtype=float)
    return relative(pose, np.zeros_like(pose))


def integrate_twist(vx: float, vy: float, wz: float, dt: float) -> np.ndarray:
    """Robot-frame displacement [dx, dy, dθ] after driving a constant twist (vx, vy, ωz) for dt
    (the planar velocity turns with the heading)::

        dθ = ωz dt
        dx = vx sin(dθ)/ωz − vy (1 − cos dθ)/ωz        (→ vx dt − vy ωz dt²/2  as ωz → 0)
        dy = vx (1 − cos dθ)/ωz + vy sin(dθ)/ωz        (→ vy dt + vx ωz dt²/2  as ωz → 0)
    """
    return np.array(integrate_twist_floats(vx, vy, wz, dt))


def integrate_twist_floats(vx: float, vy: float, wz: float, dt: float) -> tuple[float, float, float]:
    """``integrate_twist`` as three floats (no array: for loops over a few pieces)."""
    dth = wz * dt
    if abs(dth) < 1e-6:
        c, s = 1.0 - dth * dth / 6.0, 0.5 * dth  # sin(x)/x and (1 - cos x)/x, to second order
        return vx * dt * c - vy * dt * s, vx * dt * s + vy * dt * c, dth
    a, b = math.sin(dth) / wz, (1.0 - math.cos(dth)) / wz
    return vx * a - vy * b, vx * b + vy * a, dth


def integrate_twists(vx, vy, wz, dt) -> np.ndarray:
    """``integrate_twist`` for arrays (broadcast): displacements of shape (..., 3)."""
    arrays = [np.asarray(v, dtype=float) for v in (vx, vy, wz, dt)]
    shapes = {a.shape for a in arrays if a.ndim}
    if _integrate_twists_kernel is None or len(shapes) != 1 or len(next(iter(shapes))) != 1:
        return integrate_twists_numpy(*arrays)  # all scalars, or shapes numpy broadcasts
    n = next(iter(shapes))[0]
    out = np.empty((n, 3))
    _integrate_twists_kernel(*(np.full(n, a) if a.ndim == 0 else np.require(a, requirements=("C", "W"))
                               for a in arrays), out)
    return out


def integrate_twists_numpy(vx, vy, wz, dt) -> np.ndarray:
    """``integrate_twists`` in numpy: the reference of its compiled loop."""
    vx, vy, wz, dt = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (vx, vy, wz, dt)))
    dth = wz * dt
    small = np.abs(dth) < 1e-6
    w = np.where(small, 1.0, wz)
    a = np.where(small, dt * (1.0 - dth * dth / 6.0), np.sin(dth) / w)  # sin(dθ)/ωz
    b = np.where(small, dt * 0.5 * dth, (1.0 - np.cos(dth)) / w)  # (1 − cos dθ)/ωz
    return np.stack([vx * a - vy * b, vx * b + vy * a, dth], axis=-1)


def yaw_to_quaternion(yaw):
    """Quaternion ``(x, y, z, w)`` of a rotation by ``yaw`` about z."""
    half = 0.5 * np.asarray(yaw, dtype=float)
    zeros = np.zeros_like(half)
    return np.stack([zeros, zeros, np.sin(half), np.cos(half)], axis=-1)


def quaternion_to_yaw(x, y, z, w):
    """Yaw (rotation about z) of a quaternion; exact for planar rotations."""
    return np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def yaw_of(q) -> float:
    """Yaw of any quaternion object with ``x, y, z, w`` fields (a ROS or rosbags message)."""
    return float(quaternion_to_yaw(q.x, q.y, q.z, q.w))


def circular_mean(angles, weights=None):
    """atan2 of the (weighted) summed sines and cosines."""
    angles = np.asarray(angles, dtype=float)
    if weights is None:
        return float(np.arctan2(np.sin(angles).sum(), np.cos(angles).sum()))
    return float(np.arctan2(np.dot(weights, np.sin(angles)), np.dot(weights, np.cos(angles))))


if njit is not None:
    @njit(cache=True, nogil=True)
    def _compose_kernel(pose, delta, out):  # pragma: no cover - compiled
        """``compose_numpy`` of (N, 3) with (1, 3) rows, or (1, 3) with (N, 3), into ``out`` (N, 3)."""
        for i in range(out.shape[0]):
            p = pose[i if pose.shape[0] > 1 else 0]
            d = delta[i if delta.shape[0] > 1 else 0]
            c = math.cos(p[2])
            s = math.sin(p[2])
            out[i, 0] = p[0] + c * d[0] - s * d[1]
            out[i, 1] = p[1] + s * d[0] + c * d[1]
            w = (p[2] + d[2] + math.pi) % TWO_PI - math.pi
            out[i, 2] = w + TWO_PI if w <= -math.pi else w

    @njit(cache=True, nogil=True)
    def _integrate_twists_kernel(vx, vy, wz, dt, out):  # pragma: no cover - compiled
        """``integrate_twists_numpy`` of four 1-D arrays of N into ``out`` (N, 3)."""
        for i in range(out.shape[0]):
            dth = wz[i] * dt[i]
            if abs(dth) < 1e-6:
                a = dt[i] * (1.0 - dth * dth / 6.0)
                b = dt[i] * 0.5 * dth
            else:
                a = math.sin(dth) / wz[i]
                b = (1.0 - math.cos(dth)) / wz[i]
            out[i, 0] = vx[i] * a - vy[i] * b
            out[i, 1] = vx[i] * b + vy[i] * a
            out[i, 2] = dth
else:  # pragma: no cover
    _compose_kernel = _integrate_twists_kernel = None
