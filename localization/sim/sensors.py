"""The simulated sensors: a Hokuyo-like lidar (exact ray casting + noise) and wheel odometry
(noise, scale and bias; a differential base: wheel encoders) derived from the true trajectory."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from localization.core.geometry import compose, integrate_twist
from localization.core.occupancy_map import OccupancyMap
from localization.core.raycast.exact import ExactRayCaster
from localization.sim.config import PHYSICS_RATE_HZ, SimConfig, SimulationError
from localization.sim.trajectory import Trajectory
from localization.sim.vehicle import DiffDriveModel

# ============================================================================================
# 4. Lidar
# ============================================================================================


class Lidar:
    """A Hokuyo UST-10LX-like planar lidar at ``cfg.laser_offset`` (x, y, yaw) in base_link.

    Each beam's range is the exact ray-cast distance from the laser to the first cell that is
    not known free (``ExactRayCaster``), scaled and with Gaussian noise::

        z = clip(s · d + N(0, σ²), range_min, range_max)           s = range_scale

    Rays that hit nothing within ``range_max`` read ``range_max`` (as the racecar simulator).

    Sweep timing (``cfg.sweep``): the mirror turns once per scan period, so beam i is measured at
    ``stamp + i · Δt`` with ``Δt = (angle_increment / 2π) / scan_rate`` (1081 beams over 270° at
    40 Hz: 17.36 µs, 18.75 ms for the sweep); each beam is cast from the true laser pose at its
    own time (``scan_swept``). The header stamp is the first beam's time (the LaserScan convention).
    """

    def __init__(self, occupancy_map: OccupancyMap, cfg: SimConfig, rng: np.random.Generator):
        self.angles = np.linspace(cfg.angle_min, cfg.angle_max, cfg.num_beams)
        self.angle_increment = (cfg.angle_max - cfg.angle_min) / max(cfg.num_beams - 1, 1)
        self.time_increment = (self.angle_increment / (2.0 * math.pi)) / cfg.scan_rate if cfg.sweep else 0.0
        self.cfg = cfg
        self.offset = np.asarray(cfg.laser_offset, dtype=float)
        self.caster = ExactRayCaster(occupancy_map, cfg.range_max)
        self.rng = rng

    def _measure(self, d: np.ndarray) -> np.ndarray:
        z = d * self.cfg.range_scale + self.rng.standard_normal(d.shape) * self.cfg.range_noise
        return np.clip(z, self.cfg.range_min, self.cfg.range_max)

    def scan(self, base_poses, batch: int = 64) -> np.ndarray:
        """Ranges (M, num_beams) float32 for M base_link poses, every beam at once (cast
        ``batch`` scans at a time)."""
        base_poses = np.atleast_2d(base_poses)
        out = np.empty((len(base_poses), self.angles.size), dtype=np.float32)
        for a in range(0, len(base_poses), batch):
            laser = compose(base_poses[a:a + batch], self.offset)
            out[a:a + batch] = self._measure(self.caster.cast(laser, self.angles))
        return out

    def beam_times(self, stamps) -> np.ndarray:
        """(M, num_beams) time of each beam of the scans stamped ``stamps`` (first beam)."""
        return np.asarray(stamps, dtype=float)[:, None] + np.arange(self.angles.size) * self.time_increment

    def scan_swept(self, traj: Trajectory, stamps, batch: int = 32) -> np.ndarray:
        """Ranges (M, num_beams) float32 of scans stamped ``stamps`` (s), each beam cast from the
        true laser pose at its own time (``beam_times``) along ``traj``."""
        stamps = np.asarray(stamps, dtype=float)
        out = np.empty((len(stamps), self.angles.size), dtype=np.float32)
        for a in range(0, len(stamps), batch):
            laser = compose(traj.pose_at(self.beam_times(stamps[a:a + batch])), self.offset)
            angles = np.broadcast_to(self.angles, laser.shape[:-1])
            d = self.caster.cast_rays(laser.reshape(-1, 3), angles.ravel()).reshape(laser.shape[:-1])
            out[a:a + batch] = self._measure(d)
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
    time since message k−1 is the motion between them) — or, with ``odom_latency`` L, the
    period ending at t_k − L (the twist reported late; the car stands before t = 0).

    True twist over the period (a, b] = mean of the physics-step twists (v, 0, w) over it
    (an exact integral of the piecewise-constant speed and yaw rate). Reported::

        vx = speed_scale · v̄ + N(0, k²)
        vy =                 N(0, k²)            k = odom_noise (Table 1 of the lab report)
        ωz = yaw_rate_scale · w̄ + yaw_rate_bias + N(0, k²)

    and the odometry pose integrates the *reported* twist from (0, 0, 0) in frame ``odom``.

    A differential base (``cfg.car`` a ``DiffDriveModel``) measures its wheels instead
    (``wheel_odometry``): v̄ and w̄ above become the twist its encoders report, vy is 0."""
    per = PHYSICS_RATE_HZ / cfg.odom_rate
    if abs(per - round(per)) > 1e-9:
        raise SimulationError(f"odom_rate must divide {PHYSICS_RATE_HZ} Hz, got {cfg.odom_rate}")
    per = int(round(per))
    n_steps = len(traj.v)
    m = n_steps // per + 1  # message 0 at t = 0 (standing), then one every ``per`` steps
    t = np.arange(m) * per / PHYSICS_RATE_HZ
    true_twist = np.zeros((m, 3))
    if cfg.odom_latency == 0.0:
        if m > 1:
            true_twist[1:, 0] = traj.v[:(m - 1) * per].reshape(m - 1, per).mean(axis=1)
            true_twist[1:, 2] = traj.w[:(m - 1) * per].reshape(m - 1, per).mean(axis=1)
    else:
        period = 1.0 / cfg.odom_rate
        b = t - cfg.odom_latency
        for col, rate in ((0, traj.v), (2, traj.w)):
            true_twist[:, col] = (_integral(traj, rate, b) - _integral(traj, rate, b - period)) / period
    measured = true_twist
    if isinstance(cfg.car, DiffDriveModel):
        measured = wheel_odometry(traj, cfg, t, rng)
    noise = rng.standard_normal((m, 3)) * cfg.odom_noise
    if isinstance(cfg.car, DiffDriveModel):
        noise[:, 1] = 0.0  # wheel encoders cannot see sideways motion
    twist = measured * np.array([cfg.speed_scale, 1.0, cfg.yaw_rate_scale]) + noise
    twist[:, 2] += cfg.yaw_rate_bias
    period = 1.0 / cfg.odom_rate
    pose = np.zeros((m, 3))
    for k in range(1, m):
        pose[k] = compose(pose[k - 1], integrate_twist(*twist[k], period))
    return OdometryStream(t, twist, pose, true_twist)


def wheel_odometry(traj: Trajectory, cfg: SimConfig, t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The twist (M, 3) a differential base's wheel-odometry driver reports at stamps ``t``: each
    wheel's angle φ(τ) = ∫ φ̇ dτ (``DiffDriveModel.wheel_rates`` of the true v, ω) at τ = t − latency,
    plus wheel slip (a random walk: variance ``wheel_slip``² per radian the wheel turns), counted in
    whole encoder ticks; message k reports the tick differences over its period::

        n(τ) = floor((φ(τ) + slip(τ)) · ticks / 2π),   Δφ_k = (n(τ_k) − n(τ_k − T)) · 2π / ticks
        (vx, ωz) = twist_from_wheels(Δφ_L, Δφ_R, T),   vy = 0"""
    base: DiffDriveModel = cfg.car
    period = 1.0 / cfg.odom_rate
    tau = np.asarray(t, dtype=float) - cfg.odom_latency
    tick = 2.0 * math.pi / base.encoder_ticks
    out = np.zeros((len(tau), 3))
    deltas = []
    for rate in base.wheel_rates(traj.v, traj.w):
        angle = _integral(traj, rate, tau)  # at each stamp (the wheel stands before the start)
        slip = np.cumsum(rng.standard_normal(len(tau)) * base.wheel_slip * np.sqrt(np.abs(np.diff(angle, prepend=0.0))))
        ticks = np.floor((angle + slip) / tick)
        before = np.concatenate([[0.0], ticks[:-1]])
        deltas.append((ticks - before) * tick)
    out[:, 0], out[:, 2] = base.twist_from_wheels(deltas[0], deltas[1], period)
    return out


def _integral(traj: Trajectory, rate: np.ndarray, t) -> np.ndarray:
    """∫_0^t rate dt' of a piecewise-constant per-step rate (0 before the start, the last value
    held after the end)."""
    dt = 1.0 / PHYSICS_RATE_HZ
    cum = np.concatenate([[0.0], np.cumsum(rate) * dt])
    t = np.maximum(np.asarray(t, dtype=float), 0.0)
    i = np.minimum(np.floor(t / dt).astype(np.int64), len(rate) - 1)
    return cum[i] + rate[i] * (t - i * dt)
