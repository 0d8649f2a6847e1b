"""A whole simulated recording (``simulate``) and writing it as a rosbag2 bag (``record``).

The ground truth is in the map's frame (``perturb.world_to_map``: q = c + (p − c) / s, heading unchanged):
``Recording.truth_poses`` and the bag's /tf map → base_link say where the map shows what the car sees;
``Recording.world_truth_poses`` (and, in a perturbed world, ``WORLD_TRUTH_TOPIC``) where the car is in the
world. Without a scale error the two are the same poses, bit for bit; the bag of the unperturbed world
(``SimConfig.world`` None) has no world topic."""
from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from localization.bags import (
    BagWriter,
    make_header,
    make_laser_scan,
    make_odometry,
    make_pose,
    make_tf_message,
    make_transform_stamped,
)
from localization.core.geometry import wrap_angle
from localization.core.occupancy_map import OccupancyMap, load_map
from localization.sim.config import PHYSICS_RATE_HZ, SENSOR_START_DELAY_NS, T0_NS, SimConfig, SimulationError
from localization.sim.perturb import perturb_map, scale_centre, world_to_map
from localization.sim.sensors import Lidar, OdometryStream, odometry_from_trajectory
from localization.sim.trajectory import Trajectory, simulate_trajectory

#: Topic of the world-frame truth (geometry_msgs/msg/PoseStamped, frame ``WORLD_FRAME``) in the bag of a
#: perturbed world; /tf map -> base_link carries the truth in the map frame.
WORLD_TRUTH_TOPIC = "/truth/world"
WORLD_FRAME = "world"

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
    scan_time_increment: float  # s between beams (0: the whole scan at its stamp)
    truth_t: np.ndarray  # times of the /tf ground truth (every odom and scan stamp)
    truth_poses: np.ndarray  # (T, 3) the truth in the map frame: where the map shows what the car sees
    initial_pose: np.ndarray | None  # what /initialpose says
    world_truth_poses: np.ndarray | None = None  # (T, 3) the car's pose in the world (None: as truth_poses)
    scale_centre: np.ndarray | None = None  # c of world_to_map (None: no scale error)

    def __post_init__(self):
        if self.world_truth_poses is None:
            self.world_truth_poses = self.truth_poses

    @property
    def duration(self) -> float:
        return float(self.trajectory.t[-1])


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
    world = occupancy_map
    if cfg.world is not None:  # the scans come from the perturbed world; the route stays planned on the map
        world = perturb_map(occupancy_map, cfg.world, keep_free=traj.poses[:, :2])
    lidar = Lidar(world, cfg, scan_rng)
    if cfg.sweep:
        ranges = lidar.scan_swept(traj, traj.t[scan_steps])
    else:
        ranges = lidar.scan(traj.poses[scan_steps])

    odom_steps = np.rint(odom.t * PHYSICS_RATE_HZ).astype(int)
    truth_steps = np.union1d(scan_steps, odom_steps)
    initial = None
    if cfg.initial_pose:
        initial = np.asarray(cfg.start, dtype=float) + np.asarray(cfg.initial_offset, dtype=float)
        initial[2] = wrap_angle(initial[2])
    world_truth = traj.poses[truth_steps]
    truth, centre = world_truth, None
    if cfg.world is not None and cfg.world.scale != 1.0:  # the map frame: q = c + (p − c) / s
        centre = scale_centre(occupancy_map, traj.poses[:, :2])
        truth = world_to_map(world_truth, cfg.world.scale, centre)
    return Recording(cfg, traj, odom, traj.t[scan_steps], ranges, lidar.angle_increment, lidar.time_increment,
                     traj.t[truth_steps], truth, initial, world_truth, centre)


# ============================================================================================
# 6. Writing the bag
# ============================================================================================


def _ns(t: float) -> int:
    return T0_NS + SENSOR_START_DELAY_NS + int(round(t * 1e9))


def write_bag(rec: Recording, path, storage: str = "sqlite3", overwrite: bool = False) -> Path:
    """Write the recording as a rosbag2 bag at ``path`` (a new directory)."""
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
        T = ts.types
        w.add_topic("/tf_static", "tf2_msgs/msg/TFMessage")
        w.add_topic("/tf", "tf2_msgs/msg/TFMessage")
        w.add_topic("/odom", "nav_msgs/msg/Odometry")
        w.add_topic("/scan", "sensor_msgs/msg/LaserScan", qos="sensor_data")
        world_topic = cfg.world is not None  # a perturbed world: its truth beside the map frame's
        if world_topic:
            w.add_topic(WORLD_TRUTH_TOPIC, "geometry_msgs/msg/PoseStamped")
        w.write("/tf_static", T0_NS, make_tf_message(ts, [make_transform_stamped(
            ts, T0_NS, "base_link", "laser", x=cfg.laser_offset[0], y=cfg.laser_offset[1],
            yaw=cfg.laser_offset[2])]))
        x, y, th = rec.truth_poses[0]  # the car waits at its start pose until the sensors start
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
                if world_topic:
                    w.write(WORLD_TRUTH_TOPIC, t_ns, T["geometry_msgs/msg/PoseStamped"](
                        header=make_header(ts, t_ns, WORLD_FRAME), pose=make_pose(ts, *rec.world_truth_poses[k])))
            elif topic == "/odom":
                (x, y, th), (vx, vy, wz) = odom.pose[k], odom.twist[k]
                w.write("/odom", t_ns, make_odometry(ts, t_ns, "odom", "base_link", x, y, th, vx, vy, wz))
            else:
                w.write("/scan", t_ns, make_laser_scan(
                    ts, t_ns, "laser", rec.scan_ranges[k], angle_min=cfg.angle_min, angle_max=cfg.angle_max,
                    angle_increment=rec.scan_angle_increment, range_min=cfg.range_min, range_max=cfg.range_max,
                    time_increment=rec.scan_time_increment, scan_time=1.0 / cfg.scan_rate))
    return Path(path)


def make_pose_with_covariance(typestore, t_ns: int, frame_id: str, pose, std=(0.5, 0.2)):
    """``geometry_msgs/msg/PoseWithCovarianceStamped`` (what RViz's "2D Pose Estimate" sends)."""
    T = typestore.types
    cov = np.zeros(36)
    cov[0] = cov[7] = float(std[0]) ** 2
    cov[35] = float(std[1]) ** 2
    p = make_pose(typestore, *pose[:3])
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
    package = Path(__file__).resolve().parents[1]
    for name in ("sim/config.py", "sim/vehicle.py", "sim/trajectory.py", "sim/sensors.py", "sim/recorder.py",
                 "sim/perturb.py", "core/raycast/exact.py", "core/geometry.py", "bags/writer.py"):
        try:
            h.update((package / name).read_bytes())
        except OSError:
            pass
    return h.hexdigest()[:12]
