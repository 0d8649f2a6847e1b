"""The evaluation data sets: simulated Stata basement trials (generated on demand, cached), the
real RSS 2022 RACECAR bags and the real Pioneer 3-DX bags (read from the shared data directory),
and what a bag says about its robot: its odometry (an Odometry topic, else TF odom → base_link)
and its laser mount (TF base_link → the scan's frame).

Simulated trials follow the reference lab report's Table 1: three drives starting in the
diagonal corridor in front of room 32-044 at odometry noise 0, 0.3 and 0.6, plus a longer loop
around the basement with noisy *and* biased odometry. They are never committed: ``sim_bag(name)``
records them with ``localization.simulator`` the first time and reuses them afterwards, from

    $LOCALIZATION_CACHE_DIR/sim/<name>-<key>/bag      (default ~/.cache/localization)

where ``key`` digests the trial's full ``SimConfig`` (its ``world`` too: a perturbed world's recording has
its own key), the map's content and the simulator's code (``simulator.code_version()``): change any of
them and the bag is recorded anew. ``<name>`` carries the overrides (a perturbed world by its
``MapPerturbation.label()``).
"""
from __future__ import annotations

import json
import os
import shutil
import tempfile
from dataclasses import asdict, dataclass, is_dataclass, replace
from pathlib import Path

import numpy as np

from localization.core.occupancy_map import load_map
from localization.core.paths import cache_dir, shared_dir
from localization.sim import CarModel, MapPerturbation, SimConfig, code_version, record

# Corridor centre lines of stata_basement (map frame, metres), measured on the map's clearance.
_DIAGONAL_SW = ((-8.45, 18.4), (-10.4, 16.3), (-12.5, 14.5), (-13.9, 12.4), (-15.2, 10.5), (-16.2, 9.5),
                (-17.3, 8.4), (-18.9, 6.3), (-19.6, 3.1))
_BOTTOM_WEST = ((-20.6, -0.6), (-26.0, -0.5), (-35.0, -0.4), (-42.0, -0.6), (-48.0, -0.8))
_BOTTOM_EAST = ((-18.2, -0.6), (-12.0, -0.9), (-5.0, -1.2), (2.0, -1.0), (10.0, -0.7), (18.0, -0.8))
_NORTH_EAST = ((-5.75, 22.3), (-5.6, 23.6), (-6.6, 25.5), (-9.0, 25.75), (-12.0, 25.7), (-18.0, 25.75),
               (-20.5, 25.5), (-20.3, 28.0), (-20.3, 31.0), (-20.9, 33.6), (-22.5, 34.1), (-26.0, 34.1),
               (-32.0, 34.1), (-40.0, 34.05), (-46.0, 34.1))
_LOOP = (_DIAGONAL_SW + ((-20.6, -0.6), (-26.0, -0.5), (-35.0, -0.4), (-45.0, -0.7), (-52.0, -0.8),
                         (-55.2, -1.2), (-54.8, 3.0), (-54.8, 10.0), (-54.9, 20.0), (-54.7, 30.0),
                         (-55.2, 34.4), (-50.0, 34.1), (-45.0, 34.1), (-35.0, 34.1), (-25.0, 34.1),
                         (-20.0, 34.4), (-20.3, 30.0), (-20.3, 27.5), (-20.5, 25.5), (-17.0, 25.75),
                         (-12.0, 25.7), (-8.0, 25.75), (-5.2, 25.0), (-4.6, 23.5), (-5.3, 21.9), (-6.6, 20.5)))


@dataclass(frozen=True)
class SimTrial:
    name: str
    title: str
    odom_noise: float
    config: SimConfig


SIM_TRIALS = {t.name: t for t in (
    SimTrial("trial1_noise0", "Trial 1: from (-6, 20) south-west down the diagonal corridor, west along the "
             "bottom corridor; no odometry noise", 0.0,
             SimConfig(start=(-6.0, 20.0, -2.24), waypoints=_DIAGONAL_SW + _BOTTOM_WEST, speed=1.6, seed=1,
                       odom_noise=0.0)),
    SimTrial("trial2_noise0.3", "Trial 2: from (-6.4, 20.3) north-east, west along the y=25.7 corridor, north, "
             "west along the top corridor; odometry noise 0.3", 0.3,
             SimConfig(start=(-6.4, 20.3, 0.9), waypoints=_NORTH_EAST, speed=1.6, seed=2, odom_noise=0.3)),
    SimTrial("trial3_noise0.6", "Trial 3: from (-6.5, 19.3) south-west down the diagonal corridor, east along the "
             "bottom corridor; odometry noise 0.6", 0.6,
             SimConfig(start=(-6.5, 19.3, -2.24), waypoints=_DIAGONAL_SW + _BOTTOM_EAST, speed=1.6, seed=3,
                       odom_noise=0.6)),
    SimTrial("loop_noise0.3_biased", "Loop around the basement (diagonal, bottom, west, top corridors and back); "
             "odometry noise 0.3, speed 5 % short, yaw-rate bias 0.05 rad/s", 0.3,
             SimConfig(start=(-6.6, 20.5, -2.24), waypoints=_LOOP, closed=True, duration=75.0, speed=2.5, seed=4,
                       odom_noise=0.3, speed_scale=0.95, yaw_rate_bias=0.05)),
    # time-correct localization: fast driving, odometry latency, sweep timing, calibration
    SimTrial("fast", "Fast: the basement loop (diagonal, bottom, west, top corridors) at up to 7 m/s on the "
             "straights; odometry 40 ms late, noise 0.3; lidar sweep timing", 0.3,
             SimConfig(start=(-6.6, 20.5, -2.24), waypoints=_LOOP[:-3], speed=7.0, seed=5, odom_noise=0.3,
                       odom_latency=0.04, sweep=True, car=CarModel(max_lateral_accel=6.0))),
    SimTrial("calibration", "Calibration: the basement loop at 2–4 m/s (turns, speed changes) with known odometry "
             "latency 30 ms, speed scale 0.95, yaw-rate scale 1.04 and bias 0.03 rad/s, laser at "
             "(0.30, 0.02, 0.015), range scale 1.01; lidar sweep timing", 0.1,
             SimConfig(start=(-6.6, 20.5, -2.24), waypoints=_LOOP[:-3], speed=4.0, seed=6, odom_noise=0.1,
                       odom_latency=0.03, speed_scale=0.95, yaw_rate_scale=1.04, yaw_rate_bias=0.03,
                       laser_offset=(0.30, 0.02, 0.015), range_scale=1.01, sweep=True,
                       car=CarModel(max_lateral_accel=6.0))),
)}

#: The reference report's three trials, in its order.
REPORT_TRIALS = ("trial1_noise0", "trial2_noise0.3", "trial3_noise0.6")


@dataclass(frozen=True)
class RealBag:
    name: str
    filename: str
    map: str
    start: tuple | None  # approximate start pose of base_link (x, y, yaw), good to a few decimetres; None: global
    duration: float  # seconds
    scan_topic: str = "/scan"
    odom_topic: str = "/vesc/odom"  # absent from the bag: odometry from TF odom_frame -> base_frame
    folder: str = "rss2022"  # under <shared>/bags
    params: str = "real_params.yaml"  # the robot's parameter file in config/
    odom_frame: str = "odom"
    base_frame: str = "base_link"
    scan_stamp: str = "last_beam"  # which beam the scan stamps describe (calibration.check_scan_stamps on the bag)


#: The MIT RACECAR, Stata basement (Hokuyo UST-10LX-class: 1081 beams, 30 m, 40 Hz; VESC odometry 50 Hz).
REAL_BAGS = {b.name: b for b in (
    RealBag("bag1", "localization_bag1_2022-03-29-19-23-29.bag", "basement_fixed", (0.8, -0.3, 1.26), 7.0),
    RealBag("bag2", "localization_bag2_2022-03-29-19-24-34.bag", "basement_fixed", (1.2, -1.2, 1.79), 8.7),
    RealBag("bag3", "localization_bag3.bag", "basement_fixed", (1.3, 0.2, 1.59), 5.4),
)}

#: A Pioneer 3-DX, University of Birmingham (URG-04LX: 512-726 beams, 5.6 m, 10 Hz; odometry 10 Hz;
#: lgfloor2 has odometry only as TF). trace0's start pose was fitted on its first 30 s.
PIONEER_BAGS = {b.name: b for b in (
    RealBag("trace0", "trace0.bag", "lgfloor", (30.47, 17.14, 2.217), 96.0, "/base_scan", "/odom", "uob_pioneer",
            "pioneer_params.yaml"),
    RealBag("trace1", "trace1.bag", "lgfloor", None, 91.0, "/base_scan", "/odom", "uob_pioneer",
            "pioneer_params.yaml"),
    RealBag("lgfloor2", "lgfloor2.bag", "lgfloor", None, 163.0, "/base_scan", "/odom", "uob_pioneer",
            "pioneer_params.yaml", scan_stamp="first_beam"),
)}


# --------------------------------------------------------------------------------------------
# Locations
# --------------------------------------------------------------------------------------------


def real_bag(name: str) -> RealBag:
    """A real bag by name (``REAL_BAGS`` or ``PIONEER_BAGS``)."""
    try:
        return REAL_BAGS[name] if name in REAL_BAGS else PIONEER_BAGS[name]
    except KeyError:
        raise KeyError(f"unknown real bag {name!r}; known: {', '.join([*REAL_BAGS, *PIONEER_BAGS])}") from None


def real_bag_path(name: str) -> Path:
    bag = real_bag(name)
    return shared_dir() / "bags" / bag.folder / bag.filename


# --------------------------------------------------------------------------------------------
# What a bag says about its robot: scans, odometry, laser mount
# --------------------------------------------------------------------------------------------


ODOMETRY_TYPE = "nav_msgs/msg/Odometry"


@dataclass
class BagOdometry:
    """A bag's odometry as the twist stream the core takes (stamps on the bag's clock).

    ``source``: ``"<topic>"`` or ``"/tf <odom> -> <base>"``; ``record_ns`` (M,): the bag's record
    time of each entry (to feed it in bag order with the scans); ``messages``: ``TwistData``."""

    source: str
    messages: list
    record_ns: np.ndarray

    @property
    def stamps(self) -> np.ndarray:
        return np.array([m.stamp for m in self.messages], dtype=float)

    @property
    def twists(self) -> np.ndarray:
        """(M, 3): v_x, v_y, ω_z."""
        return np.array([[m.vx, m.vy, m.wz] for m in self.messages], dtype=float).reshape(-1, 3)

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """Stamps (M,) and twists (M, 3), in stamp order."""
        t, tw = self.stamps, self.twists
        order = np.argsort(t, kind="stable")
        return t[order], tw[order]


def bag_odometry(bag_path, odom_topic: str = "/odom", odom_frame: str = "odom",
                 base_frame: str = "base_link") -> BagOdometry:
    """The bag's odometry: nav_msgs/Odometry on ``odom_topic`` when the bag has it, else TF
    ``odom_frame → base_frame`` differentiated into twists at the TF rate (the stream of
    ``bags.tf.odometry_from_tf``).
    Raises BagError (one line) when the bag has neither."""
    from localization.bags import BagError, open_bag
    from localization.bags.tf import moving_edge, read_tf, tf_poses, twists_from_poses
    from localization.core.odometry import TwistData
    from localization.ros.conversions import twist_from_odometry

    with open_bag(bag_path) as bag:
        info = bag.topic_infos.get(odom_topic)
        if info is not None and info.msgtype == ODOMETRY_TYPE:
            msgs, rec = [], []
            for m in bag.messages([odom_topic]):
                msgs.append(twist_from_odometry(m.msg))
                rec.append(m.t_ns)
            return BagOdometry(odom_topic, msgs, np.asarray(rec, dtype=np.int64))
        try:
            tree = read_tf(bag)
            t, poses = tf_poses(tree, odom_frame, base_frame)
            record = moving_edge(tree, odom_frame, base_frame).record_ns
        except BagError as exc:
            raise BagError(f"no odometry in bag {bag.path}: no {ODOMETRY_TYPE} on {odom_topic} and {exc}") from None
    tt, tw = twists_from_poses(t, poses)
    rec = record[np.clip(np.searchsorted(t, tt, side="left"), 0, max(len(t) - 1, 0))]  # t is in stamp order
    msgs = [TwistData(stamp=float(s), vx=float(v[0]), vy=float(v[1]), wz=float(v[2]), frame_id=odom_frame.lstrip("/"))
            for s, v in zip(tt, tw)]
    return BagOdometry(f"/tf {odom_frame.lstrip('/')} -> {base_frame.lstrip('/')}", msgs, rec)


def bag_laser_mount(bag_path, scan_topic: str, fallback, base_frame: str = "base_link", log=None) -> tuple:
    """The laser's (x, y, yaw) in ``base_frame`` from the bag's TF (``bags.tf.laser_mount_from_bag``,
    as the node looks it up), else ``fallback`` (the laser_offset_* parameters); with ``log``, one
    line saying which was used."""
    from localization.bags.tf import laser_mount_from_bag
    mount = laser_mount_from_bag(bag_path, scan_topic, base_frame)
    if mount is None:
        if log:
            log(f"no {base_frame} -> laser transform in the bag's TF: laser pose from laser_offset_* "
                f"({', '.join(f'{v:.3f}' for v in fallback)})")
        return tuple(float(v) for v in fallback)
    if log:
        log(mount.describe())
    if not mount.upright and log:
        log("the lidar is mounted upside down: its scan is mirrored, which this package does not model")
    return tuple(float(v) for v in mount.pose)


def read_scans(bag_path, scan_topic: str) -> list:
    """Every sensor_msgs/LaserScan on ``scan_topic`` as ``ScanData`` (raises BagError without the topic)."""
    from localization.bags import BagError, open_bag
    from localization.ros.conversions import scan_from_msg
    with open_bag(bag_path) as bag:
        if scan_topic not in bag.topic_infos:
            raise BagError(f"scan topic {scan_topic} not in bag {bag_path}")
        return [scan_from_msg(m.msg) for m in bag.messages([scan_topic])]


# --------------------------------------------------------------------------------------------
# Simulated bags
# --------------------------------------------------------------------------------------------


def trial_config(name: str, **overrides) -> SimConfig:
    """The ``SimConfig`` of a named trial, with field overrides (e.g. ``duration=20``)."""
    try:
        cfg = SIM_TRIALS[name].config
    except KeyError:
        raise KeyError(f"unknown trial {name!r}; known: {', '.join(SIM_TRIALS)}") from None
    return replace(cfg, **overrides) if overrides else cfg


def cache_key(cfg: SimConfig) -> str:
    import hashlib

    h = hashlib.sha1(cfg.key().encode())
    h.update(code_version().encode())
    h.update(load_map(cfg.map).digest.encode())
    return h.hexdigest()[:16]


def sim_bag(name: str, *, cache: Path | None = None, log=None, **overrides) -> Path:
    """Path of the recorded bag of trial ``name`` (overrides: ``SimConfig`` fields), recording it
    into the cache first if needed. Safe against concurrent callers (atomic rename)."""
    cfg = trial_config(name, **overrides)
    suffix = "" if not overrides else "-" + "-".join(
        f"{k}{v.label() if isinstance(v, MapPerturbation) else v}" for k, v in sorted(overrides.items()))
    root = Path(cache) if cache is not None else cache_dir()
    entry = root / "sim" / f"{name}{suffix}-{cache_key(cfg)}"
    bag = entry / "bag"
    if (bag / "metadata.yaml").is_file():
        return bag
    entry.parent.mkdir(parents=True, exist_ok=True)
    if log:
        log(f"recording simulated trial {name} into {entry} ...")
    tmp = Path(tempfile.mkdtemp(prefix=entry.name + ".tmp-", dir=entry.parent))
    try:
        rec = record(cfg, tmp / "bag")
        summary = {"name": name, "overrides": _jsonable(overrides), "config": _jsonable(asdict(cfg)),
                   "duration_s": rec.duration, "scans": int(len(rec.scan_t)),
                   "odometry": int(len(rec.odometry.t)), "min_clearance_m": rec.trajectory.min_clearance}
        (tmp / "config.json").write_text(json.dumps(summary, indent=2))
        try:
            os.rename(tmp, entry)
        except OSError:  # another process finished first: use its bag
            if not (bag / "metadata.yaml").is_file():
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return bag


def _jsonable(obj):
    if is_dataclass(obj) and not isinstance(obj, type):
        return _jsonable(asdict(obj))
    if isinstance(obj, dict):
        return {k: _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    return obj
