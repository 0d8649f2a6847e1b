"""``localization-simulate``: a 2D MIT RACECAR simulator that records rosbag2 bags.

The simulated car drives a route through a map_server map and everything it "publishes" is
written to a rosbag2 bag (sqlite3 or MCAP, with ``rosbags``) that ``ros2 bag play`` and
``localization-replay`` can play:

============== ================================ ===========================================
topic          type                             what
============== ================================ ===========================================
/scan          sensor_msgs/msg/LaserScan        Hokuyo-like lidar, 1081 beams over 270°, 40 Hz
/odom          nav_msgs/msg/Odometry            odom -> base_link at 50 Hz: (noisy) twist and
                                                the pose integrated from it
/tf            tf2_msgs/msg/TFMessage           ground truth map -> base_link, stamped like
                                                every /scan and /odom message
/tf_static     tf2_msgs/msg/TFMessage           base_link -> laser (latched)
/initialpose   geometry_msgs/msg/                optional: the true start pose plus an offset
               PoseWithCovarianceStamped
============== ================================ ===========================================

The pieces, each next to its math (PythonRobotics style):

1. ``CarModel``: Ackermann (kinematic bicycle) model about the rear axle centre (= base_link).
2. ``RouteFollower``: pure pursuit along a waypoint route, speed reduced in turns.
3. ``simulate_trajectory``: the physics loop at 200 Hz (controls constant within a step).
4. ``Lidar``: exact ray casting in the map + Gaussian range noise.
5. ``odometry_from_trajectory``: twist averaged over each odometry period, noise and bias added,
   odometry pose integrated from the reported twist (as a wheel-odometry driver would).
6. ``write_bag``: messages built with ``localization.bag_io`` and written in time order.

Everything is deterministic given ``SimConfig.seed``. The trajectory does not depend on the
sensors (the controller follows waypoints, it does not look at the lidar), so the scans are ray
cast afterwards, many at once.

A "kidnapping" (``kidnap_at`` / ``kidnap_to``) teleports the car mid-run: the ground truth
jumps, the odometry does not notice (a teleport is not motion), and the controller continues
along the route from the point nearest to the new pose.
"""
from __future__ import annotations

import argparse
import hashlib
import math
import sys
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from .geometry import compose, wrap_angle
from .occupancy_map import MapError, OccupancyMap, resolve_map_path

PROG = "localization-simulate"

#: Bag time of the first message (ns). The static transform and the initial pose are stamped
#: here; simulated time 0 (the first /odom, /scan and /tf) is ``SENSOR_START_DELAY_NS`` later,
#: so every player delivers them first.
T0_NS = 1_700_000_000 * 1_000_000_000
SENSOR_START_DELAY_NS = 1_000_000

PHYSICS_RATE_HZ = 200  # 5 ms: a common multiple of the 40 Hz scan and 50 Hz odometry periods


class SimulationError(RuntimeError):
    """The simulation cannot run as configured (bad route, car hits a wall, ...)."""


# ============================================================================================
# 1. Ackermann kinematics
# ============================================================================================


@dataclass(frozen=True)
class CarModel:
    """Kinematic bicycle model of the MIT RACECAR, reference point the rear axle centre.

    State (x, y, θ) and speed v; the input is the front-wheel steering angle δ::

        ẋ = v cos θ
        ẏ = v sin θ
        θ̇ = v tan(δ) / L                  L = wheelbase

    With v and δ constant over a step dt the car drives an arc of curvature κ = tan(δ)/L,
    integrated exactly (``step``). Commands are limited like the real car: |v| ≤ max_speed,
    |δ| ≤ max_steer, |dv/dt| ≤ max_accel, |dδ/dt| ≤ max_steer_rate.
    """

    wheelbase: float = 0.325  # m
    max_speed: float = 4.0  # m/s
    max_steer: float = 0.34  # rad
    max_accel: float = 3.0  # m/s²
    max_steer_rate: float = 3.2  # rad/s
    laser_offset_x: float = 0.275  # lidar ahead of the rear axle (m)
    radius: float = 0.18  # collision circles of this radius at the rear and front axle (m)

    def yaw_rate(self, v: float, steer: float) -> float:
        """θ̇ = v tan(δ) / L."""
        return v * math.tan(steer) / self.wheelbase

    def limit(self, v: float, steer: float, v_cmd: float, steer_cmd: float, dt: float) -> tuple[float, float]:
        """Apply the speed, steering, acceleration and steering-rate limits to a command."""
        v_cmd = float(np.clip(v_cmd, -self.max_speed, self.max_speed))
        steer_cmd = float(np.clip(steer_cmd, -self.max_steer, self.max_steer))
        v_new = v + float(np.clip(v_cmd - v, -self.max_accel * dt, self.max_accel * dt))
        steer_new = steer + float(np.clip(steer_cmd - steer, -self.max_steer_rate * dt, self.max_steer_rate * dt))
        return v_new, steer_new

    @staticmethod
    def arc(v: float, w: float, dt: float) -> np.ndarray:
        """Robot-frame displacement [dx, dy, dθ] after driving speed v, yaw rate w for dt::

            dθ = w dt
            dx = v sin(dθ) / w            (→ v dt       as w → 0)
            dy = v (1 − cos(dθ)) / w      (→ v w dt²/2  as w → 0)
        """
        dth = w * dt
        if abs(dth) < 1e-9:
            return np.array([v * dt, 0.5 * v * dth * dt, dth])
        return np.array([v * math.sin(dth) / w, v * (1.0 - math.cos(dth)) / w, dth])

    def step(self, pose, v: float, steer: float, dt: float) -> np.ndarray:
        """Pose after driving (v, δ) for dt: pose ⊕ arc(v, v tan δ / L, dt)."""
        return compose(pose, self.arc(v, self.yaw_rate(v, steer), dt))

    def footprint_points(self, pose) -> np.ndarray:
        """Centres (2, 2) of the collision circles: rear axle and front axle."""
        x, y, th = pose
        return np.array([[x, y], [x + self.wheelbase * math.cos(th), y + self.wheelbase * math.sin(th)]])


# ============================================================================================
# 2. Pure pursuit route follower
# ============================================================================================


def densify(waypoints, spacing: float = 0.05, closed: bool = False) -> np.ndarray:
    """Points every ``spacing`` metres along the polyline through ``waypoints`` (closed: back
    to the first)."""
    pts = np.asarray(waypoints, dtype=float).reshape(-1, 2)
    if closed:
        pts = np.vstack([pts, pts[:1]])
    out = [pts[:1]]
    for a, b in zip(pts[:-1], pts[1:]):
        n = max(1, int(math.ceil(np.hypot(*(b - a)) / spacing)))
        out.append(a + (b - a) * (np.arange(1, n + 1)[:, None] / n))
    path = np.vstack(out)
    if closed:
        path = path[:-1]  # the last point is the first again
    return path


class RouteFollower:
    """Pure pursuit (Coulter 1992) along a waypoint route.

    Each step: find the path point nearest to the rear axle (searching a little ahead of the
    last one, so the car never skips a loop), take the goal point ``Ld`` further along the
    path, and steer onto the circle through the rear axle and the goal::

        Ld = lookahead_min + lookahead_gain · v
        α  = atan2(goal_y − y, goal_x − x) − θ          (goal bearing in the car frame)
        δ  = atan(2 L sin(α) / Ld)

    Speed: ``speed`` on straights, reduced in turns and to a stop at the end of an open route::

        v_cmd = speed · (1 − turn_slowdown · |δ| / max_steer)
        v_cmd = min(v_cmd, sqrt(2 · a_max · distance_to_end))
    """

    def __init__(self, waypoints, closed: bool = False, lookahead_min: float = 0.9, lookahead_gain: float = 0.3,
                 turn_slowdown: float = 0.5, spacing: float = 0.05):
        pts = np.asarray(waypoints, dtype=float).reshape(-1, 2)
        if len(pts) < 2:
            raise SimulationError("a route needs at least two waypoints")
        self.closed = bool(closed)
        self.path = densify(pts, spacing, self.closed)
        seg = np.hypot(*np.diff(self.path, axis=0, append=self.path[:1] if self.closed else self.path[-1:]).T)
        self.s = np.concatenate([[0.0], np.cumsum(seg)])[:len(self.path)]  # arc length of each point
        self.length = float(self.s[-1] + (seg[-1] if self.closed else 0.0))
        self.spacing = spacing
        self.lookahead_min = lookahead_min
        self.lookahead_gain = lookahead_gain
        self.turn_slowdown = turn_slowdown
        self.index = 0
        self.travelled = 0.0  # arc length progressed along the route (grows past ``length`` on loops)

    def reset_to_nearest(self, xy) -> None:
        """Continue from the route point nearest to ``xy`` (start, or after a kidnapping)."""
        self.index = int(np.argmin(np.hypot(*(self.path - np.asarray(xy, dtype=float)[:2]).T)))

    def _nearest_ahead(self, xy, window_m: float = 3.0) -> int:
        n = len(self.path)
        k = np.arange(self.index, self.index + int(window_m / self.spacing) + 1)
        k = k % n if self.closed else k[k < n]
        return int(k[np.argmin(np.hypot(*(self.path[k] - xy).T))])

    def _point_ahead(self, index: int, distance: float) -> tuple[np.ndarray, float]:
        """The path point ``distance`` metres after ``index`` (clamped at the end of an open
        route) and the distance actually available."""
        steps = int(round(distance / self.spacing))
        if self.closed:
            return self.path[(index + steps) % len(self.path)], distance
        j = min(index + steps, len(self.path) - 1)
        return self.path[j], self.s[j] - self.s[index]

    def distance_to_end(self) -> float:
        return math.inf if self.closed else float(self.s[-1] - self.s[self.index])

    def control(self, pose, v: float, car: CarModel, speed: float) -> tuple[float, float]:
        """(v_cmd, δ_cmd) for the current pose and speed."""
        x, y, th = pose
        new = self._nearest_ahead(np.array([x, y]))
        step = (new - self.index) % len(self.path) if self.closed else new - self.index
        self.travelled += step * self.spacing
        self.index = new
        ld = self.lookahead_min + self.lookahead_gain * abs(v)
        goal, _ = self._point_ahead(self.index, ld)
        alpha = wrap_angle(math.atan2(goal[1] - y, goal[0] - x) - th)
        dist = max(math.hypot(goal[0] - x, goal[1] - y), 1e-6)
        steer = math.atan2(2.0 * car.wheelbase * math.sin(alpha), dist)
        steer = float(np.clip(steer, -car.max_steer, car.max_steer))
        v_cmd = speed * (1.0 - self.turn_slowdown * abs(steer) / car.max_steer)
        if not self.closed:
            v_cmd = min(v_cmd, math.sqrt(2.0 * car.max_accel * 0.5 * max(self.distance_to_end() - 0.05, 0.0)))
        return v_cmd, steer


# ============================================================================================
# Configuration
# ============================================================================================


@dataclass(frozen=True)
class SimConfig:
    """Everything that determines a simulated recording (and so its cache key)."""

    map: str = "stata_basement"  # map name (in the maps dir) or YAML path
    start: tuple = (-6.6, 20.5, -2.24)  # true start pose of base_link (x, y, yaw)
    waypoints: tuple = ()  # route ((x, y), ...); the car drives from ``start`` through these
    closed: bool = False  # route is a loop: keep driving until ``duration``
    speed: float = 2.0  # cruise speed (m/s)
    duration: float | None = None  # seconds; None: until the end of an open route
    seed: int = 0
    # odometry
    odom_rate: float = 50.0
    odom_noise: float = 0.0  # std of the Gaussian noise added to each of vx, vy (m/s) and ωz (rad/s)
    speed_scale: float = 1.0  # reported vx = speed_scale · true vx (+ noise): e.g. 0.95 runs 5 % short
    yaw_rate_bias: float = 0.0  # rad/s added to the reported ωz
    # lidar
    scan_rate: float = 40.0
    num_beams: int = 1081
    angle_min: float = -0.75 * math.pi  # -2.356 rad
    angle_max: float = 0.75 * math.pi
    range_min: float = 0.02
    range_max: float = 10.0
    range_noise: float = 0.01  # std (m) of the Gaussian range noise
    # ground truth and initial pose
    initial_pose: bool = True  # record /initialpose
    initial_offset: tuple = (0.3, 0.4, 0.2)  # /initialpose = true start + this (map frame dx, dy, dyaw)
    initial_std: tuple = (0.5, 0.2)  # std (m, rad) written into the /initialpose covariance
    # robustness tests: teleport the car
    kidnap_at: float | None = None  # seconds after the start
    kidnap_to: tuple | None = None  # (x, y, yaw)
    car: CarModel = field(default_factory=CarModel)

    def key(self) -> str:
        """Stable digest of the configuration (for caches)."""
        text = repr(sorted(asdict(self).items()))
        return hashlib.sha1(text.encode()).hexdigest()[:16]


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
    """Drive the route with pure pursuit and the Ackermann model at ``PHYSICS_RATE_HZ``.

    Raises ``SimulationError`` when the car would leave free space (a collision circle comes
    closer than its radius to a wall or to unknown space)."""
    car = cfg.car
    dt = 1.0 / PHYSICS_RATE_HZ
    if not cfg.waypoints:
        raise SimulationError("no route: give waypoints (or a named trial)")
    follower = RouteFollower(cfg.waypoints, closed=cfg.closed)
    follower.reset_to_nearest(cfg.start[:2])
    max_steps = int(round((cfg.duration if cfg.duration is not None else 3600.0) * PHYSICS_RATE_HZ))
    kidnap_step = None if cfg.kidnap_at is None else int(round(cfg.kidnap_at * PHYSICS_RATE_HZ))
    if kidnap_step is not None and cfg.kidnap_to is None:
        raise SimulationError("kidnap_at needs kidnap_to (x, y, yaw)")
    clear = clearance_grid(occupancy_map)

    pose = np.asarray(cfg.start, dtype=float).copy()
    v, steer = 0.0, 0.0
    poses, vs, ws, steers = [pose.copy()], [], [], []
    min_clear = math.inf
    for i in range(max_steps):
        if i == kidnap_step:
            pose = np.asarray(cfg.kidnap_to, dtype=float).copy()
            poses[-1] = pose.copy()  # the truth jumps at this instant
            follower.reset_to_nearest(pose[:2])
        v_cmd, steer_cmd = follower.control(pose, v, car, cfg.speed)
        v, steer = car.limit(v, steer, v_cmd, steer_cmd, dt)
        w = car.yaw_rate(v, steer)
        pose = compose(pose, car.arc(v, w, dt))
        poses.append(pose.copy())
        vs.append(v)
        ws.append(w)
        steers.append(steer)
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
        from .ray_casting import ExactRayCaster
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
        pose[k] = compose(pose[k - 1], _twist_arc(*twist[k], period))
    return OdometryStream(np.arange(m) * per / PHYSICS_RATE_HZ, twist, pose, true_twist)


def _twist_arc(vx, vy, wz, dt) -> np.ndarray:
    """Robot-frame displacement of a constant twist (vx, vy, ωz) over dt (rotate the planar
    velocity with the heading: the arc formula of ``CarModel.arc`` for both components)."""
    dth = wz * dt
    if abs(dth) < 1e-9:
        return np.array([vx * dt - 0.5 * vy * dth * dt, vy * dt + 0.5 * vx * dth * dt, dth])
    a, b = math.sin(dth) / wz, (1.0 - math.cos(dth)) / wz
    return np.array([vx * a - vy * b, vx * b + vy * a, dth])


# ============================================================================================
# The whole recording
# ============================================================================================


@dataclass
class Recording:
    cfg: SimConfig
    trajectory: Trajectory
    odometry: OdometryStream
    scan_t: np.ndarray  # (S,) seconds
    scan_ranges: np.ndarray  # (S, beams) float32
    scan_angle_increment: float
    truth_t: np.ndarray  # times of the /tf ground truth (every odom and scan stamp)
    truth_poses: np.ndarray
    initial_pose: np.ndarray | None  # what /initialpose says

    @property
    def duration(self) -> float:
        return float(self.trajectory.t[-1])


def load_map(name_or_path) -> OccupancyMap:
    path = resolve_map_path(name_or_path)
    return OccupancyMap.from_yaml(path)


def simulate(cfg: SimConfig, occupancy_map: OccupancyMap | None = None) -> Recording:
    """Run the simulation (no files written)."""
    occupancy_map = occupancy_map if occupancy_map is not None else load_map(cfg.map)
    if not occupancy_map.is_free(np.asarray(cfg.start[:2], dtype=float)):
        raise SimulationError(f"start pose {tuple(cfg.start)} is not in free space of map {cfg.map}")
    odom_rng, scan_rng = (np.random.default_rng(s) for s in np.random.SeedSequence(cfg.seed).spawn(2))
    traj = simulate_trajectory(cfg, occupancy_map)
    odom = odometry_from_trajectory(traj, cfg, odom_rng)

    per = PHYSICS_RATE_HZ / cfg.scan_rate
    if abs(per - round(per)) > 1e-9:
        raise SimulationError(f"scan_rate must divide {PHYSICS_RATE_HZ} Hz, got {cfg.scan_rate}")
    scan_steps = np.arange(0, len(traj.t), int(round(per)))
    lidar = Lidar(occupancy_map, cfg, scan_rng)
    ranges = lidar.scan(traj.poses[scan_steps])

    odom_steps = np.rint(odom.t * PHYSICS_RATE_HZ).astype(int)
    truth_steps = np.union1d(scan_steps, odom_steps)
    initial = None
    if cfg.initial_pose:
        initial = np.asarray(cfg.start, dtype=float) + np.asarray(cfg.initial_offset, dtype=float)
        initial[2] = wrap_angle(initial[2])
    return Recording(cfg, traj, odom, traj.t[scan_steps], ranges, lidar.angle_increment,
                     traj.t[truth_steps], traj.poses[truth_steps], initial)


# ============================================================================================
# 6. Writing the bag
# ============================================================================================


def _ns(t: float) -> int:
    return T0_NS + SENSOR_START_DELAY_NS + int(round(t * 1e9))


def write_bag(rec: Recording, path, storage: str = "sqlite3", overwrite: bool = False) -> Path:
    """Write the recording as a rosbag2 bag at ``path`` (a new directory)."""
    from .bag_io import BagWriter, make_laser_scan, make_odometry, make_tf_message, make_transform_stamped
    cfg = rec.cfg
    events = []  # (t_ns, order, topic, builder)
    for k, t in enumerate(rec.odometry.t):
        events.append((_ns(t), 1, "/odom", k))
    for k, t in enumerate(rec.scan_t):
        events.append((_ns(t), 2, "/scan", k))
    for k, t in enumerate(rec.truth_t):
        events.append((_ns(t), 0, "/tf", k))
    events.sort(key=lambda e: (e[0], e[1]))

    with BagWriter(path, storage=storage, overwrite=overwrite) as w:
        ts = w.typestore
        w.add_topic("/tf_static", "tf2_msgs/msg/TFMessage")
        w.add_topic("/tf", "tf2_msgs/msg/TFMessage")
        w.add_topic("/odom", "nav_msgs/msg/Odometry")
        w.add_topic("/scan", "sensor_msgs/msg/LaserScan", qos="sensor_data")
        w.write("/tf_static", T0_NS, make_tf_message(ts, [make_transform_stamped(
            ts, T0_NS, "base_link", "laser", x=cfg.car.laser_offset_x)]))
        x, y, th = rec.trajectory.poses[0]  # the car waits at its start pose until the sensors start
        w.write("/tf", T0_NS, make_tf_message(ts, [make_transform_stamped(ts, T0_NS, "map", "base_link",
                                                                          x=x, y=y, yaw=th)]))
        if rec.initial_pose is not None:
            w.add_topic("/initialpose", "geometry_msgs/msg/PoseWithCovarianceStamped")
            w.write("/initialpose", T0_NS, make_pose_with_covariance(ts, T0_NS, "map", rec.initial_pose,
                                                                      cfg.initial_std))
        odom = rec.odometry
        for t_ns, _, topic, k in events:
            if topic == "/tf":
                x, y, th = rec.truth_poses[k]
                w.write("/tf", t_ns, make_tf_message(ts, [make_transform_stamped(ts, t_ns, "map", "base_link",
                                                                                  x=x, y=y, yaw=th)]))
            elif topic == "/odom":
                (x, y, th), (vx, vy, wz) = odom.pose[k], odom.twist[k]
                w.write("/odom", t_ns, make_odometry(ts, t_ns, "odom", "base_link", x, y, th, vx, vy, wz))
            else:
                w.write("/scan", t_ns, make_laser_scan(
                    ts, t_ns, "laser", rec.scan_ranges[k], angle_min=cfg.angle_min, angle_max=cfg.angle_max,
                    angle_increment=rec.scan_angle_increment, range_min=cfg.range_min, range_max=cfg.range_max,
                    scan_time=1.0 / cfg.scan_rate))
    return Path(path)


def make_pose_with_covariance(typestore, t_ns: int, frame_id: str, pose, std=(0.5, 0.2)):
    """``geometry_msgs/msg/PoseWithCovarianceStamped`` (what RViz's "2D Pose Estimate" sends)."""
    from .bag_io import make_header, quaternion_from_yaw
    T = typestore.types
    qx, qy, qz, qw = quaternion_from_yaw(float(pose[2]))
    cov = np.zeros(36)
    cov[0] = cov[7] = float(std[0]) ** 2
    cov[35] = float(std[1]) ** 2
    p = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=float(pose[0]), y=float(pose[1]), z=0.0),
                                    orientation=T["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw))
    return T["geometry_msgs/msg/PoseWithCovarianceStamped"](
        header=make_header(typestore, t_ns, frame_id),
        pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=p, covariance=cov))


def record(cfg: SimConfig, path, storage: str = "sqlite3", overwrite: bool = False,
           occupancy_map: OccupancyMap | None = None) -> Recording:
    """Simulate and write the bag; returns the recording (truth, odometry, scans)."""
    rec = simulate(cfg, occupancy_map)
    write_bag(rec, path, storage, overwrite)
    return rec


def code_version() -> str:
    """Digest of the code that determines a recording's content (for caches)."""
    h = hashlib.sha1()
    here = Path(__file__).resolve().parent
    for name in ("simulator.py", "ray_casting.py", "geometry.py", "bag_io.py"):
        try:
            h.update((here / name).read_bytes())
        except OSError:
            pass
    return h.hexdigest()[:12]


# ============================================================================================
# Command line
# ============================================================================================


def _floats(text: str, n: int | None = None) -> tuple:
    try:
        vals = tuple(float(v) for v in text.replace(" ", "").split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None
    if n is not None and len(vals) != n:
        raise argparse.ArgumentTypeError(f"expected {n} comma-separated numbers, got {text!r}")
    return vals


def _pose(text):
    return _floats(text, 3)


def _waypoints(text: str) -> tuple:
    """``"x,y;x,y;..."`` or a file with one ``x, y`` (or ``x y``) per line."""
    p = Path(text)
    if p.is_file():
        rows = [line.split("#")[0].replace(",", " ").split() for line in p.read_text().splitlines()]
        pts = [tuple(float(v) for v in r[:2]) for r in rows if len(r) >= 2]
    else:
        try:
            pts = [_floats(item, 2) for item in text.split(";") if item.strip()]
        except argparse.ArgumentTypeError:
            raise argparse.ArgumentTypeError(f"waypoints must be 'x,y;x,y;...' or a file, got {text!r}") from None
    if len(pts) < 2:
        raise argparse.ArgumentTypeError("a route needs at least two waypoints")
    return tuple(pts)


def build_parser() -> argparse.ArgumentParser:
    from .datasets import SIM_TRIALS
    ap = argparse.ArgumentParser(
        prog=PROG, description="Simulate the MIT RACECAR driving a route in a map and record a rosbag2 bag "
                               "(/scan, /odom, ground truth /tf, /tf_static, /initialpose).",
        epilog=f"trials: {', '.join(SIM_TRIALS)}. Example: {PROG} out_bag --trial trial2_noise0.3. "
               "Values starting with '-' need '=': --start=-6.0,20.0,-2.24")
    ap.add_argument("out", type=Path, help="bag directory to write (must not exist unless --overwrite)")
    ap.add_argument("--trial", choices=sorted(SIM_TRIALS), help="start from a predefined trial "
                    "(route, start, speed, noise); other options override it")
    ap.add_argument("--map", help="map name or YAML (default stata_basement)")
    ap.add_argument("--start", type=_pose, metavar="X,Y,YAW", help="true start pose")
    ap.add_argument("--waypoints", type=_waypoints, metavar="'X,Y;X,Y;...'|FILE", help="route to drive")
    ap.add_argument("--closed", action="store_true", default=None, help="the route is a loop (needs --duration)")
    ap.add_argument("--speed", type=float, help="cruise speed m/s (max 4)")
    ap.add_argument("--duration", type=float, help="seconds (default: until the end of the route)")
    ap.add_argument("--seed", type=int)
    ap.add_argument("--odom-noise", type=float, metavar="K", help="std of the noise on vx, vy (m/s) and wz (rad/s)")
    ap.add_argument("--speed-scale", type=float, help="odometry speed scale bias (e.g. 0.95)")
    ap.add_argument("--yaw-rate-bias", type=float, help="odometry yaw-rate bias (rad/s)")
    ap.add_argument("--range-noise", type=float, help="lidar range noise std (m), default 0.01")
    ap.add_argument("--no-initialpose", action="store_true", help="do not record /initialpose")
    ap.add_argument("--initial-offset", type=_pose, metavar="DX,DY,DYAW",
                    help="/initialpose = true start + offset (map frame), default 0.3,0.4,0.2")
    ap.add_argument("--kidnap-at", type=float, metavar="T", help="teleport the car T seconds after the start")
    ap.add_argument("--kidnap-to", type=_pose, metavar="X,Y,YAW", help="where to teleport it")
    ap.add_argument("--storage", choices=("sqlite3", "mcap"), default="sqlite3")
    ap.add_argument("--overwrite", action="store_true")
    return ap


def config_from_args(args) -> SimConfig:
    from .datasets import SIM_TRIALS
    cfg = SIM_TRIALS[args.trial].config if args.trial else SimConfig()
    changes = {}
    for name, attr in (("map", "map"), ("start", "start"), ("waypoints", "waypoints"), ("closed", "closed"),
                       ("speed", "speed"), ("duration", "duration"), ("seed", "seed"),
                       ("odom_noise", "odom_noise"), ("speed_scale", "speed_scale"),
                       ("yaw_rate_bias", "yaw_rate_bias"), ("range_noise", "range_noise"),
                       ("initial_offset", "initial_offset"), ("kidnap_at", "kidnap_at"),
                       ("kidnap_to", "kidnap_to")):
        value = getattr(args, name)
        if value is not None:
            changes[attr] = value
    if args.no_initialpose:
        changes["initial_pose"] = False
    cfg = replace(cfg, **changes)
    if not cfg.waypoints:
        raise SimulationError("no route: give --trial or --waypoints")
    if cfg.closed and cfg.duration is None:
        raise SimulationError("a closed route needs --duration")
    if (cfg.kidnap_at is None) != (cfg.kidnap_to is None):
        raise SimulationError("--kidnap-at and --kidnap-to go together")
    if not 0 < cfg.speed <= cfg.car.max_speed:
        raise SimulationError(f"--speed must be in (0, {cfg.car.max_speed}] m/s")
    return cfg


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        cfg = config_from_args(args)
        rec = record(cfg, args.out, storage=args.storage, overwrite=args.overwrite)
    except (SimulationError, MapError, ValueError, OSError) as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 1
    traj = rec.trajectory
    dist = float(np.sum(np.abs(traj.v)) / PHYSICS_RATE_HZ)
    print(f"wrote {args.out}: {rec.duration:.1f} s, {dist:.1f} m driven, {len(rec.scan_t)} scans, "
          f"{len(rec.odometry.t)} odometry, min wall clearance {traj.min_clearance:.2f} m")
    return 0


if __name__ == "__main__":
    sys.exit(main())
