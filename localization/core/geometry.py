"""Planar pose helpers: angle wrapping, pose composition, yaw <-> quaternion.

Poses are ``[x, y, theta]`` rows; every function accepts one pose ``(3,)`` or a stack ``(N, 3)``.
"""
from __future__ import annotations

import math

import numpy as np


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
    dth = wz * dt
    if abs(dth) < 1e-6:
        c, s = 1.0 - dth * dth / 6.0, 0.5 * dth  # sin(x)/x and (1 - cos x)/x, to second order
        return np.array([vx * dt * c - vy * dt * s, vx * dt * s + vy * dt * c, dth])
    a, b = math.sin(dth) / wz, (1.0 - math.cos(dth)) / wz
    return np.array([vx * a - vy * b, vx * b + vy * a, dth])


def integrate_twists(vx, vy, wz, dt) -> np.ndarray:
    """``integrate_twist`` for arrays (broadcast): displacements of shape (..., 3)."""
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
