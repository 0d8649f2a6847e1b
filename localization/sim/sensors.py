"""The simulated sensors: a Hokuyo-like lidar (exact ray casting + noise) and wheel odometry
(noise, scale and bias) derived from the true trajectory."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from localization.core.geometry import compose, integrate_twist
from localization.core.occupancy_map import OccupancyMap
from localization.core.raycast.exact import ExactRayCaster
from localization.sim.config import PHYSICS_RATE_HZ, SimConfig, SimulationError
from localization.sim.trajectory import Trajectory

# ============================================================================================
# 4. Lidar
# ============================================================================================


class Lidar:
    """A Hokuyo UST-10LX-like planar lidar at ``offset_x`` ahead of base_link.

    Each beam's range is the exact ray-cast distance from the laser to the first cell that is
    not known free (``ExactRayCaster``), plus Gaussian noise::

        z = clip(d + N(0, σ²), range_min, range_max)

    Rays that hit nothing within ``range_max`` read ``range_max`` (as the racecar simulator).
    """

    def __init__(self, occupancy_map: OccupancyMap, cfg: SimConfig, rng: np.random.Generator):
        self.angles = np.linspace(cfg.angle_min, cfg.angle_max, cfg.num_beams)
        self.angle_increment = (cfg.angle_max - cfg.angle_min) / max(cfg.num_beams - 1, 1)
        self.cfg = cfg
        self.offset = np.array([cfg.car.laser_offset_x, 0.0, 0.0])
        self.caster = ExactRayCaster(occupancy_map, cfg.range_max)
        self.rng = rng

    def scan(self, base_poses, batch: int = 64) -> np.ndarray:
        """Ranges (M, num_beams) float32 for M base_link poses (cast ``batch`` scans at a time)."""
        base_poses = np.atleast_2d(base_poses)
        out = np.empty((len(base_poses), self.angles.size), dtype=np.float32)
        for a in range(0, len(base_poses), batch):
            laser = compose(base_poses[a:a + batch], self.offset)
            d = self.caster.cast(laser, self.angles)
            z = d + self.rng.standard_normal(d.shape) * self.cfg.range_noise
            out[a:a + batch] = np.clip(z, self.cfg.range_min, self.cfg.range_max)
        return out


# ============================================================================================
# 5. Odometry
# ============================================================================================


@dataclass
class OdometryStream:
    t: np.ndarray  # (M,) seconds
    twist: np.ndarray  # (M, 3) reported vx, vy, ωz
    pose: np.ndarray  # (M, 3) reported odom pose (integrated from the reported twist)
    true_twist: np.ndarray  # (M, 3)


def odometry_from_trajectory(traj: Trajectory, cfg: SimConfig, rng: np.random.Generator) -> OdometryStream:
    """Odometry messages at ``odom_rate``: message k reports the twist over the period that
    ends at its stamp (the convention of the localizer: the twist of message k times the
    time since message k−1 is the motion between them).

    True twist over the period = mean of the physics-step twists (v, 0, w). Reported::

        vx = speed_scale · v̄ + N(0, k²)
        vy =                 N(0, k²)            k = odom_noise (Table 1 of the lab report)
        ωz = w̄ + yaw_rate_bias + N(0, k²)

    and the odometry pose integrates the *reported* twist from (0, 0, 0) in frame ``odom``."""
    per = PHYSICS_RATE_HZ / cfg.odom_rate
    if abs(per - round(per)) > 1e-9:
        raise SimulationError(f"odom_rate must divide {PHYSICS_RATE_HZ} Hz, got {cfg.odom_rate}")
    per = int(round(per))
    n_steps = len(traj.v)
    m = n_steps // per + 1  # message 0 at t = 0 (standing), then one every ``per`` steps
    true_twist = np.zeros((m, 3))
    if m > 1:
        true_twist[1:, 0] = traj.v[:(m - 1) * per].reshape(m - 1, per).mean(axis=1)
        true_twist[1:, 2] = traj.w[:(m - 1) * per].reshape(m - 1, per).mean(axis=1)
    noise = rng.standard_normal((m, 3)) * cfg.odom_noise
    twist = true_twist * np.array([cfg.speed_scale, 1.0, 1.0]) + noise
    twist[:, 2] += cfg.yaw_rate_bias
    period = 1.0 / cfg.odom_rate
    pose = np.zeros((m, 3))
    for k in range(1, m):
        pose[k] = compose(pose[k - 1], integrate_twist(*twist[k], period))
    return OdometryStream(np.arange(m) * per / PHYSICS_RATE_HZ, twist, pose, true_twist)
