"""Dead reckoning: the odometry's poses from its reported twists (with a speed scale a, a yaw-rate
scale b and bias c), at any query time, and the noise model of its motion between two scans
(package doc, steps 1 and 3)."""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from localization.core.geometry import compose, integrate_twists, wrap_angle


def odometry_chain(odom_t, twist, a=1.0, b=1.0, c=0.0) -> np.ndarray:
    """Odometry poses (M, 3) at the stamps, from 0 at the first: twist k (corrected: a·(vx, vy),
    b·ωz + c) held over (t_{k−1}, t_k], composed in closed form (θ_k = Σ dθ, p_k = Σ R(θ_{j−1}) d_j)."""
    t = np.asarray(odom_t, dtype=float)
    tw = np.asarray(twist, dtype=float).reshape(-1, 3)
    M = len(t)
    poses = np.zeros((M, 3))
    if M < 2:
        return poses
    steps = integrate_twists(a * tw[1:, 0], a * tw[1:, 1], b * tw[1:, 2] + c, np.diff(t))
    th = np.concatenate([[0.0], np.cumsum(steps[:, 2])])
    cs, sn = np.cos(th[:-1]), np.sin(th[:-1])
    poses[1:, 0] = np.cumsum(cs * steps[:, 0] - sn * steps[:, 1])
    poses[1:, 1] = np.cumsum(sn * steps[:, 0] + cs * steps[:, 1])
    poses[:, 2] = wrap_angle(th)
    return poses


def odometry_chain_loop(odom_t, twist, a=1.0, b=1.0, c=0.0) -> np.ndarray:
    """Reference of ``odometry_chain``: the same composition one step at a time (tests)."""
    t = np.asarray(odom_t, dtype=float)
    tw = np.asarray(twist, dtype=float).reshape(-1, 3)
    poses = np.zeros((len(t), 3))
    for k in range(1, len(t)):
        step = integrate_twists(a * tw[k, 0], a * tw[k, 1], b * tw[k, 2] + c, t[k] - t[k - 1])
        poses[k] = compose(poses[k - 1], step)
    return poses


def odometry_inputs(odom_t, twist, query_t):
    """The stamps (M,), twists (M, 3) and query times as float arrays (dead reckoning's inputs)."""
    return (np.asarray(odom_t, dtype=float), np.asarray(twist, dtype=float).reshape(-1, 3),
            np.asarray(query_t, dtype=float))


def dead_reckon(odom_t, twist, query_t, a=1.0, b=1.0, c=0.0, chain=None) -> np.ndarray:
    """Odometry pose (odom frame, 0 at the first stamp) at ``query_t`` (odometry clock): the chain
    at the stamp before, moved on by the twist of the period holding the query (beyond the last
    stamp the last twist goes on, before the first one the first period's twist is run backwards:
    a robot already moving when the bag starts). ``chain``: ``odometry_chain`` of the same
    (a, b, c), when already computed."""
    t, tw, q = odometry_inputs(odom_t, twist, query_t)
    M = len(t)
    if M < 2:
        return np.zeros(q.shape + (3,))
    poses = odometry_chain(t, tw, a, b, c) if chain is None else chain
    k = np.clip(np.searchsorted(t, q, side="left"), 1, M - 1)  # the period (t_{k-1}, t_k] holding q
    dt = q - t[k - 1]  # < 0 only before the first stamp
    return compose(poses[k - 1], integrate_twists(a * tw[k, 0], a * tw[k, 1], b * tw[k, 2] + c, dt))


def odometry_twist_at(odom_t, twist, query_t) -> np.ndarray:
    """The reported twist (…, 3) of the period holding each query time (the last one beyond)."""
    t = np.asarray(odom_t, dtype=float)
    tw = np.asarray(twist, dtype=float).reshape(-1, 3)
    if len(t) < 2:
        return np.zeros(np.shape(query_t) + (3,)) if len(t) == 0 else np.broadcast_to(tw[0], np.shape(query_t) + (3,))
    k = np.clip(np.searchsorted(t, np.asarray(query_t, dtype=float), side="left"), 1, len(t) - 1)
    return tw[k]


@dataclass(frozen=True)
class OdometryNoise:
    """Standard deviation of the odometry's motion between two scans (package doc, step 3)."""

    xy_per_m: float = 0.05  # m per m travelled
    xy_per_rad: float = 0.02  # m per rad turned
    xy_per_sqrt_s: float = 0.01  # m per √s
    theta_per_rad: float = 0.05  # rad per rad turned
    theta_per_m: float = 0.05  # rad per m travelled
    theta_per_sqrt_s: float = 0.01  # rad per √s
    along: float = 1.0  # multiplies σ of dx (the odometry's own forward axis) ...
    across: float = 1.0  # ... and of dy

    def scaled(self, x: float, y: float, theta: float) -> "OdometryNoise":
        """The same model with σ_x × x, σ_y × y and every heading term × theta."""
        return replace(self, along=self.along * x, across=self.across * y, theta_per_rad=self.theta_per_rad * theta,
                       theta_per_m=self.theta_per_m * theta, theta_per_sqrt_s=self.theta_per_sqrt_s * theta)

    def sigmas(self, delta, dt) -> np.ndarray:
        """(…, 3) σ of (dx, dy, dθ) for relative motions ``delta`` (…, 3) over ``dt`` (…) s."""
        d = np.asarray(delta, dtype=float)
        s = np.hypot(d[..., 0], d[..., 1])
        r = np.abs(d[..., 2])
        root = np.sqrt(np.clip(np.asarray(dt, dtype=float), 0.0, None))
        sxy = self.xy_per_m * s + self.xy_per_rad * r + self.xy_per_sqrt_s * root + 1e-4
        sth = self.theta_per_rad * r + self.theta_per_m * s + self.theta_per_sqrt_s * root + 1e-4
        return np.stack([sxy * self.along, sxy * self.across, sth], axis=-1)
