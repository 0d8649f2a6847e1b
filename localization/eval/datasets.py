"""The evaluation data sets: simulated Stata basement trials (generated on demand, cached) and
the real RSS 2022 bags (read from the shared data directory).

Simulated trials follow the reference lab report's Table 1: three drives starting in the
diagonal corridor in front of room 32-044 at odometry noise 0, 0.3 and 0.6, plus a longer loop
around the basement with noisy *and* biased odometry. They are never committed: ``sim_bag(name)``
records them with ``localization.simulator`` the first time and reuses them afterwards, from

    $LOCALIZATION_CACHE_DIR/sim/<name>-<key>/bag      (default ~/.cache/localization)

where ``key`` digests the trial's full ``SimConfig``, the map's content and the simulator's code
(``simulator.code_version()``): change any of them and the bag is recorded anew.
"""
from __future__ import annotations

import json
import os
import shutil
import tempfile
from dataclasses import asdict, dataclass, replace
from pathlib import Path

from localization.core.occupancy_map import load_map
from localization.core.paths import cache_dir, shared_dir
from localization.sim import CarModel, SimConfig, code_version, record

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
    # time-correct localization (issue 10): fast driving, odometry latency, sweep timing, calibration
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
    start: tuple  # approximate start pose of base_link (x, y, yaw), good to a few decimetres
    duration: float  # seconds
    scan_topic: str = "/scan"
    odom_topic: str = "/vesc/odom"


REAL_BAGS = {b.name: b for b in (
    RealBag("bag1", "localization_bag1_2022-03-29-19-23-29.bag", "basement_fixed", (0.8, -0.3, 1.26), 7.0),
    RealBag("bag2", "localization_bag2_2022-03-29-19-24-34.bag", "basement_fixed", (1.2, -1.2, 1.79), 8.7),
    RealBag("bag3", "localization_bag3.bag", "basement_fixed", (1.3, 0.2, 1.59), 5.4),
)}


# --------------------------------------------------------------------------------------------
# Locations
# --------------------------------------------------------------------------------------------


def real_bag_path(name: str) -> Path:
    bag = REAL_BAGS[name]
    return shared_dir() / "bags" / "rss2022" / bag.filename


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
    suffix = "" if not overrides else "-" + "-".join(f"{k}{v}" for k, v in sorted(overrides.items()))
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
        summary = {"name": name, "overrides": overrides, "config": _jsonable(asdict(cfg)),
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
    if isinstance(obj, dict):
        return {k: _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    return obj
