"""What determines a simulated recording: ``SimConfig`` (its digest keys the caches), the bag's
time base and the physics rate."""
from __future__ import annotations

import hashlib
import math
from dataclasses import asdict, dataclass, field, replace

from localization.sim.perturb import MapPerturbation
from localization.sim.vehicle import CarModel, DiffDriveModel, SimulationError

__all__ = ["DIFFERENTIAL_ROUTE", "DIFFERENTIAL_START", "PHYSICS_RATE_HZ", "SENSOR_START_DELAY_NS", "T0_NS",
           "CarModel", "DiffDriveModel", "SimConfig", "SimulationError", "differential_trial"]

#: Bag time of the first message (ns). The static transform and the initial pose are stamped
#: here; simulated time 0 (the first /odom, /scan and /tf) is ``SENSOR_START_DELAY_NS`` later,
#: so every player delivers them first.
T0_NS = 1_700_000_000 * 1_000_000_000
SENSOR_START_DELAY_NS = 1_000_000

PHYSICS_RATE_HZ = 200  # 5 ms: a common multiple of the 40 Hz scan and 50 Hz odometry periods




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
    speed: float = 2.0  # cruise speed (m/s), at most car.max_speed
    duration: float | None = None  # seconds; None: until the end of an open route
    seed: int = 0
    # odometry
    odom_rate: float = 50.0
    # std of the Gaussian noise added to each of vx, vy (m/s) and ωz (rad/s); a differential base's odometry
    # (wheel encoders) reports vy = 0 exactly and gets it on vx and ωz only
    odom_noise: float = 0.0
    speed_scale: float = 1.0  # reported vx = speed_scale · true vx (+ noise): e.g. 0.95 runs 5 % short
    yaw_rate_scale: float = 1.0  # reported ωz = yaw_rate_scale · true ωz + yaw_rate_bias (+ noise)
    yaw_rate_bias: float = 0.0  # rad/s added to the reported ωz
    odom_latency: float = 0.0  # s: the message stamped t reports the twist of the period ending at t − latency
    # lidar
    scan_rate: float = 40.0
    num_beams: int = 1081
    angle_min: float = -0.75 * math.pi  # -2.356 rad
    angle_max: float = 0.75 * math.pi
    range_min: float = 0.02
    range_max: float = 10.0
    range_noise: float = 0.01  # std (m) of the Gaussian range noise
    range_scale: float = 1.0  # reported range = range_scale · true range (+ noise)
    sweep: bool = False  # beam i measured at stamp + i · time_increment while the car moves (UST-10LX)
    laser_offset: tuple = (0.275, 0.0, 0.0)  # laser pose (x, y, yaw) in base_link (m, m, rad)
    # ground truth and initial pose
    initial_pose: bool = True  # record /initialpose
    initial_offset: tuple = (0.3, 0.4, 0.2)  # /initialpose = true start + this (map frame dx, dy, dyaw)
    initial_std: tuple = (0.5, 0.2)  # std (m, rad) written into the /initialpose covariance
    # robustness tests: teleport the car
    kidnap_at: float | None = None  # seconds after the start
    kidnap_to: tuple | None = None  # (x, y, yaw)
    car: CarModel | DiffDriveModel = field(default_factory=CarModel)  # the vehicle (its kinematics and follower)
    # the world the lidar sees: None, the map itself; else the map perturbed (``perturb_map``: boxes, people,
    # glass, scale), with the planned trajectory kept clear
    world: MapPerturbation | None = None

    def key(self) -> str:
        """Stable digest of the configuration (for caches)."""
        items = asdict(self)
        if items["world"] is None:  # the unperturbed world keeps the digests recorded before the field existed
            del items["world"]
        text = repr(sorted(items.items()))
        return hashlib.sha1(text.encode()).hexdigest()[:16]


#: A differential base's drive in the Stata basement (map frame, m): from the diagonal corridor
#: south-west, a U-turn on the spot, back north-east past the start, a turn on the spot to the north,
#: north, a turn on the spot to the west into the y = 25.7 corridor
DIFFERENTIAL_START = (-6.6, 20.5, -2.24)
DIFFERENTIAL_ROUTE = (DIFFERENTIAL_START[:2], (-9.0, 17.8), (-5.9, 21.2), (-5.6, 23.6), (-6.6, 25.5), (-10.0, 25.7))


def differential_trial(**changes) -> SimConfig:
    """The differential-drive trial: a Pioneer-like base (``DiffDriveModel``) at 0.6 m/s with turns on
    the spot, wheel-encoder odometry at 20 Hz (ticks, wheel slip), a 10 Hz lidar; ``changes`` override
    any field."""
    cfg = SimConfig(start=DIFFERENTIAL_START, waypoints=DIFFERENTIAL_ROUTE, speed=0.6, seed=7, odom_rate=20.0,
                    scan_rate=10.0, car=DiffDriveModel(), initial_offset=(0.1, -0.1, 0.05), initial_std=(0.2, 0.1))
    return replace(cfg, **changes)
