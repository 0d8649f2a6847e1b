"""The physics loop: the vehicle follows its route at ``PHYSICS_RATE_HZ``; the true trajectory."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from localization.core.geometry import compose, integrate_twist, integrate_twists
from localization.core.occupancy_map import OccupancyMap
from localization.sim.config import PHYSICS_RATE_HZ, SimConfig, SimulationError

# ============================================================================================
# 3. The physics loop
# ============================================================================================


@dataclass
class Trajectory:
    """The true motion at the physics rate: step i covers [t[i], t[i] + dt)."""

    t: np.ndarray  # (K+1,) seconds since the start
    poses: np.ndarray  # (K+1, 3) true base_link pose at t
    v: np.ndarray  # (K,) speed during step i
    w: np.ndarray  # (K,) yaw rate during step i
    steer: np.ndarray  # (K,)
    min_clearance: float  # smallest distance (m) from a collision circle centre to a wall
    route_length: float
    kidnapped_at_step: int | None = None

    def pose_at(self, t) -> np.ndarray:
        """True pose (..., 3) at any times ``t`` (s): the constant-twist arc of the physics step
        holding t, from its start pose (clamped to the trajectory's span)."""
        t = np.asarray(t, dtype=float)
        dt = 1.0 / PHYSICS_RATE_HZ
        i = np.clip(np.floor(t / dt + 1e-9).astype(np.int64), 0, len(self.v) - 1)
        tau = np.clip(t - self.t[i], 0.0, dt)
        return compose(self.poses[i], integrate_twists(self.v[i], 0.0, self.w[i], tau))


def clearance_grid(occupancy_map: OccupancyMap) -> np.ndarray:
    """Per-cell distance (m) to the nearest cell that is not known free (walls and unknown)."""
    from scipy.ndimage import distance_transform_edt
    return distance_transform_edt(np.pad(occupancy_map.free, 1, constant_values=False))[1:-1, 1:-1] \
        * occupancy_map.resolution


def clearance_at(occupancy_map: OccupancyMap, grid: np.ndarray, xy) -> np.ndarray:
    cr = occupancy_map.world_to_grid(np.asarray(xy, dtype=float))
    inside = occupancy_map.in_bounds(cr)
    out = np.zeros(cr.shape[:-1])
    out[inside] = grid[cr[..., 1][inside], cr[..., 0][inside]]
    return out


def simulate_trajectory(cfg: SimConfig, occupancy_map: OccupancyMap) -> Trajectory:
    """Drive the route with the vehicle's follower (the car: pure pursuit and the Ackermann model;
    the differential base: turns on the spot and straight legs) at ``PHYSICS_RATE_HZ``.

    Raises ``SimulationError`` when the vehicle would leave free space (a collision circle comes
    closer than its radius to a wall or to unknown space)."""
    car = cfg.car
    dt = 1.0 / PHYSICS_RATE_HZ
    if not cfg.waypoints:
        raise SimulationError("no route: give waypoints (or a named trial)")
    follower = car.follower(cfg.waypoints, closed=cfg.closed)
    follower.reset_to_nearest(cfg.start[:2])
    max_steps = int(round((cfg.duration if cfg.duration is not None else 3600.0) * PHYSICS_RATE_HZ))
    kidnap_step = None if cfg.kidnap_at is None else int(round(cfg.kidnap_at * PHYSICS_RATE_HZ))
    if kidnap_step is not None and cfg.kidnap_to is None:
        raise SimulationError("kidnap_at needs kidnap_to (x, y, yaw)")
    clear = clearance_grid(occupancy_map)

    pose = np.asarray(cfg.start, dtype=float).copy()
    v, u = 0.0, 0.0  # speed and the second input (steering angle or yaw rate)
    poses, vs, ws, steers = [pose.copy()], [], [], []
    min_clear = math.inf
    for i in range(max_steps):
        if i == kidnap_step:
            pose = np.asarray(cfg.kidnap_to, dtype=float).copy()
            poses[-1] = pose.copy()  # the truth jumps at this instant
            follower.reset_to_nearest(pose[:2])
        v_cmd, u_cmd = follower.control(pose, v, car, cfg.speed)
        v, u = car.limit(v, u, v_cmd, u_cmd, dt)
        w = car.yaw_rate(v, u)
        pose = compose(pose, integrate_twist(v, 0.0, w, dt))
        poses.append(pose.copy())
        vs.append(v)
        ws.append(w)
        steers.append(car.steering(u))
        c = float(clearance_at(occupancy_map, clear, car.footprint_points(pose)).min())
        min_clear = min(min_clear, c)
        if c < car.radius:
            raise SimulationError(f"the car hits a wall at t={(i + 1) * dt:.2f} s, pose "
                                  f"({pose[0]:.2f}, {pose[1]:.2f}, {pose[2]:.2f}): the route passes too close "
                                  f"to a wall or unknown space")
        if cfg.duration is None and not follower.closed and follower.distance_to_end() < 0.15 and v < 0.05:
            break
    else:
        if cfg.duration is None:
            raise SimulationError("the car did not reach the end of the route within an hour")
    t = np.arange(len(poses)) * dt
    return Trajectory(t, np.array(poses), np.array(vs), np.array(ws), np.array(steers), min_clear,
                      follower.length, kidnap_step)
