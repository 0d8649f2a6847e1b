"""Pose-track arithmetic the stages share: differences of poses, a track's own twist and its direction
of travel."""
from __future__ import annotations

import numpy as np

from localization.core.geometry import relative, wrap_angle
from localization.eval.reference.constants import STANDSTILL_SPEED


def relative_difference(a, b) -> np.ndarray:
    """a − b for poses (…, 3), the angle wrapped."""
    d = np.asarray(a, dtype=float) - np.asarray(b, dtype=float)
    d[..., 2] = wrap_angle(d[..., 2])
    return d


def track_twists(t, poses) -> np.ndarray:
    """Base-frame twist (K, 3: v_x, v_y, ω) of a pose track at each entry, from its neighbours
    (central differences; one-sided at the ends): X_{k−1}⁻¹ ⊕ X_{k+1} / (t_{k+1} − t_{k−1})."""
    t = np.asarray(t, dtype=float)
    p = np.asarray(poses, dtype=float).reshape(-1, 3)
    K = len(t)
    if K < 2:
        return np.zeros((K, 3))
    i0, i1 = np.clip(np.arange(K) - 1, 0, K - 1), np.clip(np.arange(K) + 1, 0, K - 1)
    dt = np.where(t[i1] > t[i0], t[i1] - t[i0], np.inf)
    return relative(p[i0], p[i1]) / dt[:, None]


def travel_directions(t, poses, standstill: float = STANDSTILL_SPEED) -> tuple[np.ndarray, np.ndarray]:
    """Unit direction of travel (K, 2) and speed (K,) of a pose track (central differences;
    the heading where the speed is below ``standstill``)."""
    t = np.asarray(t, dtype=float)
    p = np.asarray(poses, dtype=float).reshape(-1, 3)
    K = len(t)
    d = np.stack([np.cos(p[:, 2]), np.sin(p[:, 2])], axis=1) if K else np.zeros((0, 2))
    speed = np.zeros(K)
    if K >= 2:
        i0 = np.clip(np.arange(K) - 1, 0, K - 1)
        i1 = np.clip(np.arange(K) + 1, 0, K - 1)
        dt = t[i1] - t[i0]
        dxy = p[i1, :2] - p[i0, :2]
        with np.errstate(invalid="ignore", divide="ignore"):
            vel = dxy / dt[:, None]
        speed = np.where(dt > 0, np.hypot(vel[:, 0], vel[:, 1]), 0.0)
        moving = speed > standstill
        d[moving] = vel[moving] / speed[moving, None]
    return d, speed
