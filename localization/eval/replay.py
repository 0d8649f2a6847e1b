"""``localization-replay``: run the localizer over a recorded bag as fast as the CPU allows.

Usage::

    localization-replay BAG --map MAP.yaml [--params FILE] [--out DIR] [--initial-pose X,Y,YAW]
                        [--global] [--seed N] [--scan-topic T] [--odom-topic T] [--truth-topic T]
                        [--particles N] [-p NAME=VALUE ...] [--no-plots] [--progress/--no-progress]

``BAG``: a rosbag2 directory (sqlite3 or MCAP), a bare ``.db3`` / ``.mcap`` file, or a ROS 1
``.bag``. Every scan, odometry and initial-pose message goes, in bag-time order, through exactly
what the node does with it: the duck-typed converters of ``localization.conversions`` and the
``Localizer`` (``on_odometry``, ``on_scan``, ``set_initial_pose``), fed by the one loop the tuner
and the benchmarks use too (``localization.eval.feed``). Stamps come from the messages, so the
result does not depend on how fast the replay runs.

Initial pose: ``--initial-pose``, else every ``/initialpose`` message of the bag (as the node
would receive it), else global localization (``--global`` forces it).

Ground truth (optional): TF ``map -> base_link`` on ``/tf`` (what ``localization-simulate``
records, like the racecar simulator), or ``--truth-topic`` carrying nav_msgs/Odometry,
geometry_msgs/PoseStamped, PoseWithCovarianceStamped or tf2_msgs/TFMessage. A simulated bag's /tf is
the truth in the map frame (``localization.sim.perturb``: q = c + (p − c) / s, what the map shows where
the car is); a bag drawn from a perturbed world also carries the world-frame truth on ``/truth/world``,
scored as the second figure ``world_ct_error_m``.

Outputs in ``--out`` (default: a new ``replay-<bag>-<time>`` folder in the current directory):

- ``poses.csv``: ``t,x,y,theta``, one row per estimate the node would publish: the pose carried to
  each odometry message's time, and a sensor-corrected estimate when it is newer than the row
  before (t, scan clock, never goes backwards);
- ``corrections.csv``: ``t,x,y,theta``, every sensor-corrected estimate at its scan's time;
- ``metrics.json``: CT error statistics, heading error, time to converge and false recoveries
  (``metrics.false_recoveries``) (with truth; ``world_ct_error_m`` against the world-frame truth),
  scan–map agreement, update timing, effective update rate (see ``localization.metrics``);
- ``agreement.csv`` (and ``errors.csv`` with truth): the time series behind the figures (agreement
  of the estimate at each scan's time, t = that time on the scan clock, ``localization.eval.feed``);
- ``trajectory.png`` (map, truth, estimate) and ``error.png`` (errors and agreement vs time);
- with a reference track (``--reference``; by default when the bag has no ground truth): the
  estimate at each scan's time scored against every scan matched to the map
  (``localization.eval.reference``; ``published_*``: the poses as published, interpolated):
  ``reference_error_m``, ``along_track_error_m``, ``cross_track_error_m``, ``best_lag_s`` ... in
  metrics.json, and ``reference.png`` (along/cross-track error vs time).

Exit status: 0 success; 1 when the bag, map, parameters or a topic are missing or unusable
(one line ``localization-replay: error: ...`` on stderr); 2 bad command-line arguments.
"""
from __future__ import annotations

import csv
import json
import math
import sys
import time
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

import numpy as np

from localization.bags import BagError, open_bag
from localization.core.geometry import wrap_angle, yaw_of
from localization.core.localizer import Localizer
from localization.core.occupancy_map import MapError, OccupancyMap
from localization.core.occupancy_map import load_map as load_occupancy_map
from localization.core.parameters import Parameters
from localization.core.paths import find_map, is_map_name, map_not_found
from localization.eval import metrics as M
from localization.eval.feed import START_FROM_EVENTS, START_GLOBAL, Feeder, InitialPose, make_scorer
from localization.ros.conversions import (
    pose_from_msg,
    pose_from_pose_with_covariance,
    scan_from_msg,
    stamp_to_sec,
    twist_from_odometry,
)
from localization.sim.recorder import WORLD_TRUTH_TOPIC

PROG = "localization-replay"

LASER_SCAN = "sensor_msgs/msg/LaserScan"
ODOMETRY = "nav_msgs/msg/Odometry"
POSE_COV = "geometry_msgs/msg/PoseWithCovarianceStamped"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
TRUTH_TYPES = (ODOMETRY, POSE_STAMPED, POSE_COV, TF_MESSAGE)


class ReplayError(RuntimeError):
    """A replay that cannot run: the message is one line saying what is wrong."""


@dataclass
class ReplayOptions:
    bag: Path
    map: str
    params: Parameters = field(default_factory=Parameters)
    initial_pose: tuple | None = None
    force_global: bool = False
    scan_topic: str | None = None  # default: params.scan_topic
    odom_topic: str | None = None  # default: params.odom_topic
    truth_topic: str | None = None  # default: /tf when it holds map -> base_link
    truth_frames: tuple = ("map", "base_link")
    progress: bool = False
    label: str = ""
    reference: bool | None = None  # score against a scan-matched reference track; None: when there is no truth
    on_scan: object | None = None  # called as on_scan(scan, localizer) after each scan (export.ReplayRecorder)
    log: object | None = None  # log(line) for the odometry source and laser mount notes; None: one line on stderr


@dataclass
class ReplayResult:
    options: ReplayOptions
    bag_path: Path
    map_path: Path
    occupancy_map: OccupancyMap
    est_t: np.ndarray
    est_poses: np.ndarray
    truth_t: np.ndarray
    truth_poses: np.ndarray
    agreement_t: np.ndarray
    agreement: np.ndarray
    sensor_times: list
    motion_times: list
    filter_time: float  # seconds spent inside on_scan / on_odometry
    wall_time: float  # the whole replay (reading, filtering, scoring)
    bag_duration: float
    counts: dict
    initial_pose_source: str
    initial_pose: np.ndarray | None
    init_t: float | None  # stamp of the (first) initialisation: convergence is timed from here
    scan_topic: str
    odom_topic: str
    truth_source: str | None
    health: np.ndarray = field(default_factory=lambda: np.zeros(0))  # Localizer.health (scan-map agreement)
    particles_t: np.ndarray = field(default_factory=lambda: np.zeros(0))  # after each sensor update
    particles: np.ndarray = field(default_factory=lambda: np.zeros(0))  # particle count (adaptive_particles)
    reference: object | None = None  # localization.eval.reference.ReferenceTrack, when computed
    corrected_t: np.ndarray = field(default_factory=lambda: np.zeros(0))  # s, scan clock: each correction's scan time
    corrected_poses: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # every sensor-corrected estimate
    scan_t: np.ndarray = field(default_factory=lambda: np.zeros(0))  # s, scan clock: each scan's time
    scan_poses: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # the estimate at each scan's time
    laser_source: str = "parameters"  # where the laser mount came from: "parameters" or "tf" (the bag's TF)
    laser_offset: tuple = ()  # (x m, y m, yaw rad): the laser mount used
    # a simulated perturbed world's truth in the world frame (WORLD_TRUTH_TOPIC; truth_* is the map frame's)
    world_truth_t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    world_truth_poses: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    @property
    def has_truth(self) -> bool:
        return len(self.truth_t) > 0


# --------------------------------------------------------------------------------------------
# Running
# --------------------------------------------------------------------------------------------


def _strip(frame: str) -> str:
    return frame[1:] if frame.startswith("/") else frame


class _Progress:
    """The replay's progress bar on stderr (tqdm, ``localization.eval.progress``), in seconds of bag time."""

    def __init__(self, enabled: bool, start_ns: int, end_ns: int, label: str):
        from localization.eval.progress import progress_bar
        self.start, self.span = start_ns, max(end_ns - start_ns, 1)
        self.done = 0.0
        self.bar = progress_bar(total=round(self.span * 1e-9, 1), desc=label, unit="s", enabled=enabled,
                                bar_format="{desc} {percentage:3.0f}%|{bar}| {n:.1f}/{total:.1f} s of bag "
                                           "[{elapsed}<{remaining}]")

    def update(self, t_ns: int) -> None:
        frac = min(max((t_ns - self.start) / self.span, 0.0), 1.0)
        step = round(frac * self.span * 1e-9, 1) - self.done
        if step > 0:
            self.bar.update(step)
            self.done += step

    def close(self) -> None:
        self.bar.close()


def load_map(name_or_path) -> OccupancyMap:
    """The map to localize in; ReplayError (one line) when it is missing or unreadable: a bare map name no
    maps folder has names every folder searched and the maps available."""
    if is_map_name(name_or_path) and find_map(str(name_or_path)) is None:
        raise ReplayError(map_not_found(str(name_or_path)))
    try:
        return load_occupancy_map(name_or_path)
    except MapError as exc:
        raise ReplayError(str(exc)) from None


def _check_topic(infos: dict, topic: str, wanted: tuple, what: str, option: str, bag_path) -> None:
    if topic not in infos:
        same = [n for n, i in infos.items() if i.msgtype in wanted]
        hint = f" ({what} topics there: {', '.join(same)}; use {option})" if same else f" (it has no {what} topic)"
        raise ReplayError(f"{what} topic {topic} not in bag {bag_path}{hint}")
    info = infos[topic]
    if info.msgtype not in wanted:
        raise ReplayError(f"topic {topic} in {bag_path} has type {info.msgtype}, expected {' or '.join(wanted)}")
    if info.count == 0:
        raise ReplayError(f"no {what} messages on {topic} in bag {bag_path}")


def tf_odometry(infos: dict, odom_topic: str) -> bool:
    """Whether a bag's odometry comes from TF: it has no ``odom_topic`` at all but has ``/tf``
    (``tf2_msgs/msg/TFMessage`` or ROS 1's ``tf/msg/tfMessage``), read as ``datasets.bag_odometry`` reads it."""
    from localization.bags.tf import TF_TYPES
    return odom_topic not in infos and "/tf" in infos and infos["/tf"].msgtype in TF_TYPES


def check_topics(infos: dict, bag_path, scan_topic: str, odom_topic: str, truth_topic: str | None,
                 init_topic: str, bag_initial_pose: bool) -> tuple[str | None, bool]:
    """Check a bag's scan and odometry topics (ReplayError naming the alternatives) and the truth
    topic (given, else ``/tf`` when the bag has it); returns (truth topic or None, whether the bag's
    initial poses are used: ``bag_initial_pose`` and the bag has some). A bag without ``odom_topic``
    but with ``/tf`` passes (``tf_odometry``): its odometry is read from TF odom → base_link."""
    _check_topic(infos, scan_topic, (LASER_SCAN,), "scan", "--scan-topic", bag_path)
    if not tf_odometry(infos, odom_topic):
        _check_topic(infos, odom_topic, (ODOMETRY,), "odometry", "--odom-topic", bag_path)
    if truth_topic is not None:
        if truth_topic not in infos:
            raise ReplayError(f"truth topic {truth_topic} not in bag {bag_path}")
        if infos[truth_topic].msgtype not in TRUTH_TYPES:
            raise ReplayError(f"truth topic {truth_topic} has type {infos[truth_topic].msgtype}, expected one "
                              f"of {', '.join(TRUTH_TYPES)}")
    elif "/tf" in infos and infos["/tf"].msgtype == TF_MESSAGE:
        truth_topic = "/tf"
    use_bag_init = (bag_initial_pose and init_topic in infos and infos[init_topic].msgtype == POSE_COV
                    and infos[init_topic].count > 0)
    return truth_topic, use_bag_init


def _stderr(line: str) -> None:
    print(f"{PROG}: {line}", file=sys.stderr, flush=True)


def laser_mount_params(bag, scan_topic: str, params: Parameters, log=None) -> tuple[Parameters, str]:
    """As the node does with ``laser_pose_from_tf``: the laser mount from the bag's TF (base_frame →
    the scan's frame, ``bags.tf.laser_mount_from_bag``) replaces laser_offset_x/y/yaw when the bag
    carries it; returns (parameters, "tf" or "parameters"). ``bag``: a path or an open reader."""
    from localization.bags.tf import laser_mount_from_bag
    if not params.laser_pose_from_tf:
        return params, "parameters"
    mount = laser_mount_from_bag(bag, scan_topic, params.base_frame)
    if mount is None:
        return params, "parameters"
    if log is not None:
        log(mount.describe() + f" (laser_offset_* {params.laser_offset_x:.3f}, {params.laser_offset_y:.3f}, "
            f"{params.laser_offset_yaw:.3f} not used)")
    x, y, yaw = (float(v) for v in mount.pose)
    return Parameters(dict(params), laser_offset_x=x, laser_offset_y=y, laser_offset_yaw=yaw), "tf"


def run_replay(opts: ReplayOptions) -> ReplayResult:
    """Replay a bag through the Localizer; collect estimates, truth, agreement and timing."""
    t_wall0 = time.perf_counter()
    params = opts.params
    say = opts.log if opts.log is not None else _stderr
    occupancy_map = load_map(opts.map)
    map_path = occupancy_map.source
    scan_topic = opts.scan_topic or params.scan_topic
    odom_topic = opts.odom_topic or params.odom_topic
    init_topic = params.initialpose_topic
    parent, child = (_strip(f) for f in opts.truth_frames)

    try:
        bag = open_bag(opts.bag)
    except BagError as exc:
        raise ReplayError(str(exc)) from None
    with bag:
        infos = bag.topic_infos
        truth_topic, use_bag_initialpose = check_topics(
            infos, bag.path, scan_topic, odom_topic, opts.truth_topic, init_topic,
            bag_initial_pose=opts.initial_pose is None and not opts.force_global)
        odometry = None
        if tf_odometry(infos, odom_topic):
            from localization.eval.datasets import bag_odometry
            try:
                odometry = bag_odometry(bag.path, odom_topic, params.odom_frame, params.base_frame)
            except BagError as exc:
                raise ReplayError(str(exc)) from None
            say(f"no odometry topic {odom_topic} in the bag: odometry from {odometry.source} "
                f"({len(odometry.messages)} twists)")
        params, laser_source = laser_mount_params(bag, scan_topic, params, say)
        if opts.initial_pose is not None:
            init_source = "--initial-pose"
        elif opts.force_global:
            init_source = "global (--global)"
        elif use_bag_initialpose:
            init_source = f"{init_topic} in the bag"
        else:
            init_source = "global (no initial pose given or in the bag)"

        localizer = Localizer(params)
        localizer.set_map(occupancy_map)
        world_truth = None  # (topic, stamps, poses): a perturbed world's truth in the world frame
        if truth_topic is not None and truth_topic != WORLD_TRUTH_TOPIC and WORLD_TRUTH_TOPIC in infos \
                and infos[WORLD_TRUTH_TOPIC].msgtype == POSE_STAMPED:
            world_truth = (WORLD_TRUTH_TOPIC, [], [])
        topics = [scan_topic] + ([odom_topic] if odometry is None else []) \
            + ([init_topic] if use_bag_initialpose else []) + ([truth_topic] if truth_topic else []) \
            + ([WORLD_TRUTH_TOPIC] if world_truth else [])
        progress = _Progress(opts.progress, bag.start_ns, bag.end_ns, opts.label or bag_label(opts.bag))
        bag_duration = (bag.end_ns - bag.start_ns) * 1e-9
        if use_bag_initialpose:
            start = START_FROM_EVENTS
        elif opts.initial_pose is not None and not opts.force_global:
            start = tuple(float(v) for v in opts.initial_pose)
        else:
            start = START_GLOBAL
        feeder = Feeder(localizer, make_scorer(occupancy_map, params))
        truth_t, truth_poses = [], []
        events = bag_events(bag, topics, scan_topic, odom_topic, init_topic if use_bag_initialpose else None,
                            truth_topic, (parent, child), truth_t, truth_poses, progress=progress.update,
                            odometry=odometry, world_truth=world_truth)
        try:
            log = feeder.run(events, start, on_scan=opts.on_scan)
        except BagError as exc:
            raise ReplayError(str(exc)) from None
        finally:
            progress.close()

    counts = log.counts
    if counts["scans"] == 0:
        raise ReplayError(f"no scan messages on {scan_topic} in bag {opts.bag}")
    if counts["odometry"] == 0:
        raise ReplayError(f"no odometry messages on {odom_topic} in bag {opts.bag}")
    if odometry is not None:
        odom_topic = odometry.source
    truth_t_arr = np.asarray(truth_t, dtype=float)
    truth_p_arr = np.asarray(truth_poses, dtype=float).reshape(-1, 3)
    order = np.argsort(truth_t_arr, kind="stable")
    counts["recoveries"] = localizer.recoveries
    counts["refused_jumps"] = localizer.refused_jumps
    est_t, est_poses = log.estimates()
    corrected_t, corrected_poses = log.corrections()
    scan_t, scan_poses = log.scan_track()
    res = ReplayResult(
        options=opts, bag_path=Path(opts.bag), map_path=map_path, occupancy_map=occupancy_map,
        est_t=est_t, est_poses=est_poses, truth_t=truth_t_arr[order], truth_poses=truth_p_arr[order],
        agreement_t=np.asarray(log.agreement_t, dtype=float), agreement=np.asarray(log.agreement, dtype=float),
        sensor_times=log.sensor_times, motion_times=log.motion_times, filter_time=log.filter_time,
        wall_time=time.perf_counter() - t_wall0, bag_duration=bag_duration, counts=counts,
        initial_pose_source=init_source, initial_pose=log.initial_pose, init_t=log.init_t, scan_topic=scan_topic,
        odom_topic=odom_topic,
        truth_source=(f"{truth_topic} ({parent} -> {child})" if truth_topic == "/tf" else truth_topic)
        if len(truth_t) else None,
        health=np.asarray(log.health, dtype=float),
        particles_t=np.asarray(log.particles_t, dtype=float), particles=np.asarray(log.particles, dtype=float),
        corrected_t=corrected_t, corrected_poses=corrected_poses, scan_t=scan_t, scan_poses=scan_poses,
        laser_source=laser_source, laser_offset=(params.laser_offset_x, params.laser_offset_y,
                                                 params.laser_offset_yaw))
    if world_truth is not None and world_truth[1]:
        wt = np.asarray(world_truth[1], dtype=float)
        order = np.argsort(wt, kind="stable")
        res.world_truth_t, res.world_truth_poses = wt[order], np.asarray(world_truth[2], dtype=float)[order]
    if opts.reference or (opts.reference is None and not res.has_truth):
        from localization.eval.progress import busy
        from localization.eval.reference import reference_for_bag
        try:
            with busy("reference track", enabled=opts.progress) as say:  # the pass after the replay's bar
                res.reference = reference_for_bag(
                    opts.bag, occupancy_map, scan_topic,
                    (params.laser_offset_x, params.laser_offset_y, params.laser_offset_yaw),
                    odom_topic=opts.odom_topic or opts.params.odom_topic, odom_frame=params.odom_frame,
                    base_frame=params.base_frame,
                    initial_pose=log.initial_pose, range_scale=params.lidar_scale_to_map_scale,
                    wall_depth=params.map_wall_depth, scan_stamp=params.scan_stamp,
                    scan_stamp_offset=params.scan_stamp_offset,
                    log=say if opts.progress else None)
        except BagError as exc:
            raise ReplayError(str(exc)) from None
        res.wall_time = time.perf_counter() - t_wall0
    return res


def bag_events(bag, topics, scan_topic: str, odom_topic: str, init_topic: str | None, truth_topic: str | None,
               truth_frames: tuple, truth_t: list, truth_poses: list, progress=None, odometry=None,
               world_truth=None):
    """A bag's filter input in bag-time order, converted as the node converts it: ``TwistData``
    (odometry), ``ScanData`` (scans), ``InitialPose`` (``init_topic``; None: not read); the truth
    (``truth_topic``, ``truth_frames`` = (parent, child)) is collected into ``truth_t`` /
    ``truth_poses`` on the way; ``progress(t_ns)`` per message. ``odometry``: a
    ``datasets.BagOdometry`` (odometry from TF) whose twists are merged in at their record times
    (each before a message recorded at the same time), instead of ``odom_topic``. ``world_truth``:
    (topic, stamps list, poses list) filled from a second truth topic (``WORLD_TRUTH_TOPIC``)."""
    parent, child = truth_frames
    twists = [] if odometry is None else odometry.messages
    rec = np.zeros(0, dtype=np.int64) if odometry is None else np.asarray(odometry.record_ns, dtype=np.int64)
    order = np.argsort(rec, kind="stable")
    j = 0
    for m in bag.messages(topics):
        if progress is not None:
            progress(m.t_ns)
        while j < len(order) and rec[order[j]] <= m.t_ns:
            yield twists[order[j]]
            j += 1
        if m.topic == truth_topic:
            _collect_truth(m.msg, m.msgtype, parent, child, truth_t, truth_poses)
        elif world_truth is not None and m.topic == world_truth[0]:
            _collect_truth(m.msg, m.msgtype, parent, child, world_truth[1], world_truth[2])
        if m.topic == scan_topic:
            yield scan_from_msg(m.msg)
        elif m.topic == odom_topic:
            yield twist_from_odometry(m.msg)
        elif init_topic is not None and m.topic == init_topic:
            pc = pose_from_pose_with_covariance(m.msg)
            yield InitialPose(pc.stamp, np.asarray(pc.pose, dtype=float), pc.covariance)
    while j < len(order):
        yield twists[order[j]]
        j += 1


def _collect_truth(msg, msgtype: str, parent: str, child: str, out_t: list, out_p: list) -> None:
    if msgtype == TF_MESSAGE:
        for tf in msg.transforms:
            if _strip(tf.header.frame_id) == parent and _strip(tf.child_frame_id) == child:
                tr = tf.transform.translation
                out_t.append(stamp_to_sec(tf.header.stamp))
                out_p.append((float(tr.x), float(tr.y), yaw_of(tf.transform.rotation)))
    elif msgtype == ODOMETRY or msgtype == POSE_COV:
        out_t.append(stamp_to_sec(msg.header.stamp))
        out_p.append(tuple(pose_from_msg(msg.pose.pose)))
    elif msgtype == POSE_STAMPED:
        out_t.append(stamp_to_sec(msg.header.stamp))
        out_p.append(tuple(pose_from_msg(msg.pose)))


# --------------------------------------------------------------------------------------------
# Metrics and outputs
# --------------------------------------------------------------------------------------------


def compute_metrics(res: ReplayResult) -> dict:
    p = res.options.params
    out = {
        "bag": str(res.bag_path),
        "map": str(res.map_path),
        "scan_topic": res.scan_topic,
        "odom_topic": res.odom_topic,
        "num_particles": p.num_particles,
        "num_beams_per_particle": p.num_beams_per_particle,
        "ray_caster": p.ray_caster,
        "random_seed": p.random_seed,
        "initial_pose_source": res.initial_pose_source,
        "initial_pose": None if res.initial_pose is None else [float(v) for v in res.initial_pose],
        "estimates": int(len(res.est_t)),
        **{k: int(v) for k, v in res.counts.items()},
        "bag_duration_s": res.bag_duration,
        "wall_time_s": res.wall_time,
        "realtime_factor": res.bag_duration / res.wall_time if res.wall_time > 0 else None,
        "sensor_update_ms": M.timing_stats(res.sensor_times),
        "motion_update_ms": M.timing_stats(res.motion_times),
        # sensor updates per second of filter time (all on_scan + on_odometry calls): the scan
        # rate this filter could keep up with live on this CPU
        "effective_update_rate_hz": (res.counts["sensor_updates"] / res.filter_time) if res.filter_time > 0 else None,
        "scan_map_agreement": M.agreement_stats(res.agreement),
        "agreement_tolerance_m": M.AGREEMENT_TOLERANCE_M,
        "max_jump_m": M.max_jump(res.est_poses),
        "has_truth": res.has_truth,
        "truth_source": res.truth_source,
        "laser_source": res.laser_source,
        "laser_offset": [float(v) for v in (res.laser_offset or (p.laser_offset_x, p.laser_offset_y,
                                                                  p.laser_offset_yaw))],
        "health": M.agreement_stats(res.health),  # the filter's own health figure (fast average)
        "sensor_model": p.sensor_model,
        "adaptive_particles": p.adaptive_particles,
        # particle count over the sensor updates (changes with adaptive_particles and global spreads)
        "particles": ({"min": int(res.particles.min()), "median": float(np.median(res.particles)),
                       "mean": float(res.particles.mean()), "max": int(res.particles.max())}
                      if res.particles.size else None),
    }
    if res.has_truth:
        cmp = M.compare_to_truth(res.est_t, res.est_poses, res.truth_t, res.truth_poses)
        out["ct_error_m"] = M.error_stats(cmp.ct_error)
        out["heading_error_mean_abs_rad"] = float(cmp.heading_error.mean()) if cmp.heading_error.size else None
        t_start = res.init_t if res.init_t is not None else (float(res.est_t[0]) if len(res.est_t) else None)
        out["time_to_converge_s"] = M.time_to_converge(cmp.t, cmp.ct_error, M.CONVERGENCE_THRESHOLD_M, t_start)
        if res.initial_pose is not None and len(res.truth_t):
            truth0 = M.interpolate_poses([res.init_t], res.truth_t, res.truth_poses)[0]
            if np.all(np.isfinite(truth0)):
                out["initial_pose_error_m"] = float(np.hypot(*(np.asarray(res.initial_pose)[:2] - truth0[:2])))
                out["initial_pose_heading_error_rad"] = float(abs(wrap_angle(res.initial_pose[2] - truth0[2])))
        out["converge_threshold_m"] = M.CONVERGENCE_THRESHOLD_M
        out["scored_estimates"] = int(cmp.t.size)
        # switches to a place > 1 m from the (map-frame) truth after the first second
        out["false_recoveries"] = M.false_recoveries(cmp.t, cmp.ct_error, t_start=t_start)
        if len(res.world_truth_t):  # a perturbed world: the error against the car's pose in the world as well
            world = M.compare_to_truth(res.est_t, res.est_poses, res.world_truth_t, res.world_truth_poses)
            out["world_ct_error_m"] = M.error_stats(world.ct_error)
        from localization.eval.reference import truth_decomposition  # along-/cross-track vs truth
        out.update(truth_decomposition(res.est_t, res.est_poses, res.truth_t, res.truth_poses))
    if res.reference is not None:
        from localization.eval.reference import reference_metrics
        # the reference is per scan, at the scan's time: compared with the estimate at that time
        out.update(reference_metrics(res.reference, res.scan_t, res.scan_poses,
                                     res.truth_t if res.has_truth else None, res.truth_poses))
        published = reference_metrics(res.reference, res.est_t, res.est_poses)  # the poses as published
        out["published_reference_error_m"] = published["reference_error_m"]
        out["published_along_track_error_m"] = published["along_track_error_m"]
    return out


def bag_label(bag) -> str:
    """A short name for a bag path (the folder's parent for the cache's ``<trial>-<key>/bag``)."""
    p = Path(bag).expanduser().resolve()
    return p.parent.name if p.name == "bag" and p.parent.name else p.name


def default_out_dir(bag: Path) -> Path:
    stem = bag_label(bag) or "bag"
    stem = stem.rsplit(".", 1)[0] if Path(stem).suffix in (".bag", ".db3", ".mcap") else stem
    base = Path.cwd() / f"replay-{stem}-{datetime.now().strftime('%Y%m%d-%H%M%S')}"
    out, k = base, 1
    while out.exists():
        k += 1
        out = Path(f"{base}-{k}")
    return out


def _write_poses(path: Path, stamps, poses) -> Path:
    """One pose per row: t (s, scan clock), x, y (m), theta (rad)."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t", "x", "y", "theta"])
        for t, (x, y, th) in zip(stamps, poses):
            w.writerow([f"{t:.6f}", f"{x:.5f}", f"{y:.5f}", f"{th:.6f}"])
    return path


def write_outputs(res: ReplayResult, metrics: dict, out_dir: Path, plots: bool = True) -> dict:
    """poses.csv, corrections.csv, metrics.json, agreement.csv, errors.csv (with truth), trajectory.png, error.png."""
    out_dir = Path(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ReplayError(f"cannot create output folder {out_dir}: {exc}") from None
    files = {}
    files["poses"] = _write_poses(out_dir / "poses.csv", res.est_t, res.est_poses)
    files["corrections"] = _write_poses(out_dir / "corrections.csv", res.corrected_t, res.corrected_poses)
    with open(out_dir / "agreement.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t", "agreement"])
        for t, a in zip(res.agreement_t, res.agreement):
            w.writerow([f"{t:.6f}", f"{a:.4f}"])
    cmp = None
    if res.has_truth:
        cmp = M.compare_to_truth(res.est_t, res.est_poses, res.truth_t, res.truth_poses)
        with open(out_dir / "errors.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["t", "ct_error", "heading_error"])
            for t, e, h in zip(cmp.t, cmp.ct_error, cmp.heading_error):
                w.writerow([f"{t:.6f}", f"{e:.5f}", f"{h:.6f}"])
    (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
    files["metrics"] = out_dir / "metrics.json"
    if plots:
        from localization.eval.plots import plot_errors, plot_trajectory
        from localization.eval.reference import track_errors
        title = res.options.label or bag_label(res.bag_path)
        files["trajectory"] = plot_trajectory(out_dir / "trajectory.png", res.occupancy_map, res.est_poses,
                                              res.truth_poses if res.has_truth else None, res.initial_pose,
                                              title=title, reference_poses=None if res.reference is None
                                              else res.reference.good_track()[1])
        t0 = res.init_t if res.init_t is not None else (
            float(res.est_t[0]) if len(res.est_t) else (float(res.agreement_t[0]) if len(res.agreement_t) else 0.0))
        files["error"] = plot_errors(out_dir / "error.png", t0,
                                     cmp.t if cmp is not None else None, cmp.ct_error if cmp is not None else None,
                                     cmp.heading_error if cmp is not None else None,
                                     res.agreement_t, res.agreement, title=title,
                                     particles_t=res.particles_t, particles=res.particles,
                                     track=track_errors(res.est_t, res.est_poses, res.truth_t, res.truth_poses)
                                     if res.has_truth else None)
        if res.reference is not None:
            from localization.eval.reference import plot_reference
            files["reference"] = plot_reference(out_dir / "reference.png", res.reference, res.est_t, res.est_poses,
                                                 t0, title=title)
    return files


def _fmt(v, spec=".3f", unit=""):
    return "n/a" if v is None else f"{v:{spec}}{unit}"


def summary_table(metrics: dict, out_dir: Path | None = None) -> str:
    m = metrics
    rows = [("bag", m["bag"]),
            ("initial pose", m["initial_pose_source"]),
            ("messages", f"{m['scans']} scans, {m['odometry']} odometry -> {m['estimates']} estimates "
                         f"({m['sensor_updates']} sensor updates)")]
    if m.get("has_truth"):
        ct = m["ct_error_m"]
        rows += [("CT error (m)", f"mean {_fmt(ct['mean'])}  median {_fmt(ct['median'])}  p95 {_fmt(ct['p95'])}  "
                                  f"max {_fmt(ct['max'])}  rms {_fmt(ct['rms'])}"),
                 ("heading error", "mean |err| " + _fmt(
                     None if m["heading_error_mean_abs_rad"] is None else math.degrees(m["heading_error_mean_abs_rad"]),
                     ".2f", " deg")),
                 ("converged", ("never" if m["time_to_converge_s"] is None else "at the first estimate"
                                if m["time_to_converge_s"] < 0.05 else f"after {m['time_to_converge_s']:.2f} s")
                  + f" (below {m['converge_threshold_m']} m for good, from the initial pose"
                  + (f" {m['initial_pose_error_m']:.2f} m / {m['initial_pose_heading_error_rad']:.2f} rad off)"
                     if "initial_pose_error_m" in m else ")"))]
    if m.get("reference_error_m") is not None:
        r, al, cr = m["reference_error_m"], m["along_track_error_m"], m["cross_track_error_m"]
        rows += [("vs reference track", f"median {_fmt(r['median'])}  p95 {_fmt(r['p95'])}  max {_fmt(r['max'])} m "
                                        f"({m['reference_scored']} scans scored, {m['reference_ambiguous']} ambiguous, "
                                        f"{m['reference_low_score']} unmatched/low score)"),
                 ("along / cross track", f"along mean {_fmt(al['mean'])} median {_fmt(al['median'])}; "
                                         f"cross mean {_fmt(cr['mean'])} median {_fmt(cr['median'])} m; "
                                         f"best lag {_fmt(m['best_lag_s'], '.3f', ' s')}")]
        if m.get("reference_vs_truth_m"):
            rows.append(("reference vs truth", f"median {_fmt(m['reference_vs_truth_m']['median'], '.4f')} m"))
    if m.get("truth_along_track_error_m") is not None:
        al, cr = m["truth_along_track_error_m"], m["truth_cross_track_error_m"]
        rows.append(("along / cross vs truth", f"along mean {_fmt(al['mean'])} median {_fmt(al['median'])}; "
                                               f"cross mean {_fmt(cr['mean'])} median {_fmt(cr['median'])} m"))
    ag = m["scan_map_agreement"]
    rows += [("scan-map agreement", f"median {_fmt(ag['median'])}  mean {_fmt(ag['mean'])}  p05 {_fmt(ag['p05'])}"),
             ("filter health", f"median {_fmt((m.get('health') or {}).get('median'))}  "
                               f"min {_fmt((m.get('health') or {}).get('min'))}; "
                               f"{m.get('recoveries', 0)} recoveries (switches and re-spreads), "
                               f"{m.get('refused_jumps', 0)} updates undone (a jump to a worse fit)"),
             ("max jump", f"{m['max_jump_m']:.3f} m between consecutive estimates"),
             ("sensor update", f"median {_fmt(m['sensor_update_ms']['median_ms'], '.1f')} ms, "
                               f"p95 {_fmt(m['sensor_update_ms']['p95_ms'], '.1f')} ms "
                               + ("(adaptive particles" if m.get("adaptive_particles")
                                  else f"({m['num_particles']} particles")
                               + f" x {m['num_beams_per_particle']} beams, "
                               + (f"{m['ray_caster']})" if m.get("sensor_model", "beam") == "beam"
                                  else f"{m['sensor_model']})")),
             ("particles", "n/a" if not m.get("particles") else
              f"min {m['particles']['min']}  median {m['particles']['median']:.0f}  max {m['particles']['max']}"
              + (" (adaptive, KLD)" if m.get("adaptive_particles") else "")),
             ("motion update", f"median {_fmt(m['motion_update_ms']['median_ms'], '.2f')} ms, "
                               f"p95 {_fmt(m['motion_update_ms']['p95_ms'], '.2f')} ms"),
             ("update rate", f"{_fmt(m['effective_update_rate_hz'], '.1f')} Hz effective; "
                             f"{_fmt(m['realtime_factor'], '.2f')}x real time "
                             f"({m['bag_duration_s']:.1f} s of bag in {m['wall_time_s']:.1f} s)")]
    if out_dir is not None:
        rows.append(("outputs", str(out_dir)))
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in rows)
