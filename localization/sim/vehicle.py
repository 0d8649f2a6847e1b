"""The simulated vehicles and their route followers: the car (Ackermann kinematics, ``CarModel``,
pure pursuit ``RouteFollower``) and a differential-drive base (``DiffDriveModel``, turning on the
spot between straight legs ``TurnAndDriveFollower``).

A vehicle works on a state (v, u): the speed v and its second input u (the car: the steering angle
δ; the differential base: the yaw rate ω). Both offer ``limit`` (apply the command limits over a
step), ``yaw_rate(v, u)``, ``steering(u)`` (the steering angle recorded), ``footprint_points``,
``radius`` and ``follower(waypoints, closed)`` (their route follower)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from localization.core.geometry import compose, integrate_twist, wrap_angle


def _toward(current: float, cmd: float, bound: float, rate: float, dt: float) -> float:
    """``current`` moved toward the command clipped to ±``bound``, by at most ``rate`` · dt."""
    cmd = float(np.clip(cmd, -bound, bound))
    return current + float(np.clip(cmd - current, -rate * dt, rate * dt))


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
    |δ| ≤ max_steer, |dv/dt| ≤ max_accel, |dδ/dt| ≤ max_steer_rate. With a finite
    ``max_lateral_accel`` the route follower also plans its speed so that v² κ ≤ max_lateral_accel
    on the route ahead (needed at 6–8 m/s; ``inf``, the default, keeps the slow trials' speed law).
    """

    wheelbase: float = 0.325  # m
    max_speed: float = 8.0  # m/s (an F1TENTH car on a long straight)
    max_steer: float = 0.34  # rad
    max_accel: float = 3.0  # m/s²
    max_steer_rate: float = 3.2  # rad/s
    max_lateral_accel: float = math.inf  # m/s² (v² κ); inf: no speed planning for curvature
    radius: float = 0.18  # collision circles of this radius at the rear and front axle (m)

    def yaw_rate(self, v: float, steer: float) -> float:
        """θ̇ = v tan(δ) / L."""
        return v * math.tan(steer) / self.wheelbase

    def limit(self, v: float, steer: float, v_cmd: float, steer_cmd: float, dt: float) -> tuple[float, float]:
        """Apply the speed, steering, acceleration and steering-rate limits to a command."""
        return (_toward(v, v_cmd, self.max_speed, self.max_accel, dt),
                _toward(steer, steer_cmd, self.max_steer, self.max_steer_rate, dt))

    def step(self, pose, v: float, steer: float, dt: float) -> np.ndarray:
        """Pose after driving (v, δ) for dt: the constant-twist arc (v, 0, v tan δ / L) from pose
        (``geometry.integrate_twist``)."""
        return compose(pose, integrate_twist(v, 0.0, self.yaw_rate(v, steer), dt))

    def footprint_points(self, pose) -> np.ndarray:
        """Centres (2, 2) of the collision circles: rear axle and front axle."""
        x, y, th = pose
        return np.array([[x, y], [x + self.wheelbase * math.cos(th), y + self.wheelbase * math.sin(th)]])

    def steering(self, steer: float) -> float:
        """The steering angle recorded in the trajectory (the car's second input is δ itself)."""
        return steer

    def follower(self, waypoints, closed: bool = False) -> "RouteFollower":
        return RouteFollower(waypoints, closed=closed)


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

    With a finite ``car.max_lateral_accel`` a_lat, also the planned speed at the nearest path
    point (``speed_profile``): the route's curvature κ_i (heading change over ±1 m), the cornering
    limit sqrt(a_lat / κ_i), and a backward pass so the car can brake in time (at 0.8 a_max)::

        v_i = min(sqrt(a_lat / κ_i), sqrt(v_{i+1}² + 2 · 0.8 a_max · Δs))
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
        self._profile: tuple[tuple[float, float], np.ndarray] | None = None

    def speed_profile(self, car: CarModel, window_m: float = 1.0) -> np.ndarray:
        """Planned speed limit (m/s) at every path point for ``car`` (inf everywhere without a
        lateral-acceleration limit)."""
        key = (car.max_lateral_accel, car.max_accel)
        if self._profile is not None and self._profile[0] == key:
            return self._profile[1]
        n = len(self.path)
        if not math.isfinite(car.max_lateral_accel):
            limit = np.full(n, math.inf)
        else:
            d = np.diff(self.path, axis=0, append=self.path[:1] if self.closed else self.path[-1:])
            if not self.closed:
                d[-1] = d[-2]
            heading = np.arctan2(d[:, 1], d[:, 0])
            m = max(1, int(round(window_m / self.spacing)))
            k = np.arange(n)
            ahead, behind = k + m, k - m
            if self.closed:
                ahead, behind = ahead % n, behind % n
            else:
                ahead, behind = np.minimum(ahead, n - 1), np.maximum(behind, 0)
            kappa = np.abs(wrap_angle(heading[ahead] - heading[behind])) / (2 * m * self.spacing)
            limit = np.sqrt(car.max_lateral_accel / np.maximum(kappa, 1e-9))
            brake = 0.8 * car.max_accel
            for _ in range(2 if self.closed else 1):  # a loop: the wrap-around needs a second pass
                for i in range(n - 2, -1, -1) if not self.closed else range(n - 1, -1, -1):
                    j = (i + 1) % n
                    limit[i] = min(limit[i], math.sqrt(limit[j] ** 2 + 2.0 * brake * self.spacing))
        self._profile = (key, limit)
        return limit

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
        if math.isfinite(car.max_lateral_accel):
            v_cmd = min(v_cmd, float(self.speed_profile(car)[self.index]))
        return v_cmd, steer


# ============================================================================================
# 1b. Differential drive
# ============================================================================================


@dataclass(frozen=True)
class DiffDriveModel:
    """A differential-drive base (Pioneer 3-DX-like), reference point the wheel axle's centre
    (= base_link). Inputs: speed v and yaw rate ω; the wheels turn at::

        ẋ = v cos θ,   ẏ = v sin θ,   θ̇ = ω
        φ̇_R = (v + ω b/2) / r_w,   φ̇_L = (v − ω b/2) / r_w       b = track, r_w = wheel radius

    so it turns on the spot (v = 0, ω ≠ 0) and never moves sideways. Limits: |v| ≤ max_speed,
    |ω| ≤ max_yaw_rate, |dv/dt| ≤ max_accel, |dω/dt| ≤ max_yaw_accel. Wheel encoders
    (``sensors.odometry_from_trajectory``): ``encoder_ticks`` per wheel revolution, and wheel slip as a
    random walk of each wheel's measured angle, variance ``wheel_slip``² per radian the wheel turns
    (rad/√rad)."""

    track: float = 0.33  # m between the wheels
    wheel_radius: float = 0.0975  # m
    max_speed: float = 0.7  # m/s
    max_yaw_rate: float = 1.2  # rad/s
    max_accel: float = 1.0  # m/s²
    max_yaw_accel: float = 3.0  # rad/s²
    radius: float = 0.26  # collision circle about base_link (m)
    encoder_ticks: int = 2000  # per wheel revolution
    wheel_slip: float = 0.01  # rad/√rad: std of a wheel's measured angle error per √(radian turned)

    def yaw_rate(self, v: float, w: float) -> float:
        """θ̇ = ω (the second input is the yaw rate itself)."""
        return w

    def steering(self, w: float) -> float:
        """No steering angle: 0."""
        return 0.0

    def limit(self, v: float, w: float, v_cmd: float, w_cmd: float, dt: float) -> tuple[float, float]:
        """Apply the speed, yaw-rate and acceleration limits to a command (v_cmd, ω_cmd)."""
        return (_toward(v, v_cmd, self.max_speed, self.max_accel, dt),
                _toward(w, w_cmd, self.max_yaw_rate, self.max_yaw_accel, dt))

    def step(self, pose, v: float, w: float, dt: float) -> np.ndarray:
        """Pose after driving (v, ω) for dt: the constant-twist arc."""
        return compose(pose, integrate_twist(v, 0.0, w, dt))

    def wheel_rates(self, v, w):
        """(φ̇_L, φ̇_R) in rad/s for speed v and yaw rate ω (arrays broadcast)."""
        v, w = np.asarray(v, dtype=float), np.asarray(w, dtype=float)
        return (v - 0.5 * self.track * w) / self.wheel_radius, (v + 0.5 * self.track * w) / self.wheel_radius

    def twist_from_wheels(self, d_left, d_right, dt: float):
        """(v, ω) from the wheels' angle changes over dt (what a wheel-odometry driver reports)::

            v = r_w (Δφ_R + Δφ_L) / (2 dt),   ω = r_w (Δφ_R − Δφ_L) / (b dt)"""
        d_left, d_right = np.asarray(d_left, dtype=float), np.asarray(d_right, dtype=float)
        return (self.wheel_radius * (d_right + d_left) / (2.0 * dt),
                self.wheel_radius * (d_right - d_left) / (self.track * dt))

    def footprint_points(self, pose) -> np.ndarray:
        """Centre (1, 2) of the collision circle: base_link."""
        return np.asarray(pose, dtype=float)[None, :2]

    def follower(self, waypoints, closed: bool = False) -> "TurnAndDriveFollower":
        return TurnAndDriveFollower(waypoints, closed=closed)


class TurnAndDriveFollower:
    """A differential base's way along a waypoint route: turn on the spot to face the next waypoint,
    drive straight to it, stop; repeat. While turning (e_θ = bearing to the waypoint − θ)::

        v = 0,   ω = sign(e_θ) · min(ω_max, k_turn |e_θ|, sqrt(2 · 0.5 α_max |e_θ|))

    until |e_θ| < turn_tolerance and |ω| is small; while driving, pure pursuit onto the leg from the
    previous waypoint (goal ``lookahead`` ahead on the leg, capped at the waypoint)::

        v = min(speed, sqrt(2 · 0.5 a_max · d)),   ω = 2 v sin(α) / L_d         d = distance to the waypoint

    and the waypoint is reached within ``arrive_tolerance``. Legs shorter than that are skipped.
    """

    def __init__(self, waypoints, closed: bool = False, lookahead: float = 0.6, k_turn: float = 3.0,
                 turn_tolerance: float = 0.01, arrive_tolerance: float = 0.03):
        pts = np.asarray(waypoints, dtype=float).reshape(-1, 2)
        if len(pts) < 2:
            raise SimulationError("a route needs at least two waypoints")
        self.closed = bool(closed)
        self.points = pts
        legs = np.hypot(*np.diff(np.vstack([pts, pts[:1]]) if self.closed else pts, axis=0).T)
        self.length = float(legs.sum())
        self.lookahead = lookahead
        self.k_turn = k_turn
        self.turn_tolerance = turn_tolerance
        self.arrive_tolerance = arrive_tolerance
        self.target = 0  # index of the waypoint driven to
        self.leg_start = pts[0].copy()
        self.turning = True
        self.done = False
        self.travelled = 0.0

    def reset_to_nearest(self, xy) -> None:
        """Drive (after turning) to the waypoint nearest to ``xy`` (start, or after a kidnapping)."""
        xy = np.asarray(xy, dtype=float)[:2]
        self.target = int(np.argmin(np.hypot(*(self.points - xy).T)))
        if np.hypot(*(self.points[self.target] - xy)) < self.arrive_tolerance:
            self._advance()
        self.leg_start = xy.copy()
        self.turning = True

    def _advance(self) -> None:
        nxt = self.target + 1
        if nxt >= len(self.points):
            if not self.closed:
                self.done = True
                return
            nxt = 0
        self.target = nxt

    def distance_to_end(self) -> float:
        if self.closed:
            return math.inf
        if self.done:
            return 0.0
        rest = np.hypot(*np.diff(self.points[self.target:], axis=0).T).sum() if self.target + 1 < len(self.points) \
            else 0.0
        return float(rest + np.hypot(*(self.points[self.target] - self.leg_start)))

    def control(self, pose, v: float, base: DiffDriveModel, speed: float) -> tuple[float, float]:
        """(v_cmd, ω_cmd) for the current pose and speed."""
        x, y, th = pose
        if self.done:
            return 0.0, 0.0
        goal = self.points[self.target]
        dist = math.hypot(goal[0] - x, goal[1] - y)
        if not self.turning and (dist < self.arrive_tolerance or self._passed(x, y)) and abs(v) < 0.02:
            self.travelled += math.hypot(*(goal - self.leg_start))
            self.leg_start = goal.copy()
            self._advance()
            self.turning = True
            if self.done:
                return 0.0, 0.0
            goal = self.points[self.target]
            dist = math.hypot(goal[0] - x, goal[1] - y)
        if self.turning:
            err = wrap_angle(math.atan2(goal[1] - y, goal[0] - x) - th)
            rate = min(base.max_yaw_rate, self.k_turn * abs(err), math.sqrt(base.max_yaw_accel * abs(err)))
            if abs(err) < self.turn_tolerance:
                self.turning = False
            else:
                return 0.0, math.copysign(rate, err)
        if self._passed(x, y):
            return 0.0, 0.0  # overshot the waypoint: stop there
        # pure pursuit onto the leg leg_start -> goal
        leg = goal - self.leg_start
        length = max(float(np.hypot(*leg)), 1e-9)
        along = float(np.dot(np.array([x, y]) - self.leg_start, leg) / length)
        ahead = min(along + self.lookahead, length)
        target = self.leg_start + leg * (ahead / length)
        alpha = wrap_angle(math.atan2(target[1] - y, target[0] - x) - th)
        ld = max(math.hypot(target[0] - x, target[1] - y), 1e-6)
        v_cmd = min(speed, math.sqrt(base.max_accel * max(dist - 0.5 * self.arrive_tolerance, 0.0)))
        return v_cmd, 2.0 * v_cmd * math.sin(alpha) / ld

    def _passed(self, x: float, y: float) -> bool:
        """The robot is beyond the current waypoint along its leg."""
        leg = self.points[self.target] - self.leg_start
        length = float(np.hypot(*leg))
        return length > 0 and float(np.dot(np.array([x, y]) - self.leg_start, leg)) / length >= length
