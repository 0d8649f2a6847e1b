"""Running a replay: the bag's messages through the ``Localizer`` in bag-time order, collecting estimates,
truth, agreement, timing and the yardstick (``localization.eval.replay``, the package's docstring)."""
from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

import numpy as np

from localization.bags import BagError, open_bag
from localization.core.geometry import yaw_of
from localization.core.localizer import Localizer
from localization.core.occupancy_map import MapError, OccupancyMap
from localization.core.occupancy_map import load_map as load_occupancy_map
from localization.core.parameters import Parameters
from localization.core.paths import find_map, is_map_name, map_not_found
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
    reference_problem: str | None = None  # why the yardstick could not be computed (reference asked for)
    corrected_t: np.ndarray = field(default_factory=lambda: np.zeros(0))  # s, scan clock: each correction's scan time
    corrected_poses: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # every sensor-corrected estimate
    scan_t: np.ndarray = field(default_factory=lambda: np.zeros(0))  # s, scan clock: each scan's time
    scan_poses: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # the estimate at each scan's time
    laser_source: str = "parameters"  # where the laser mount came from: "parameters" or "tf" (the bag's TF)
    laser_offset: tuple = ()  # (x m, y m, yaw rad): the laser mount used
    # a simulated perturbed world's truth in the world frame (WORLD_TRUTH_TOPIC; truth_* is the map frame's)
    world_truth_t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    world_truth_poses: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    costs: list = field(default_factory=list)  # core.cost.UpdateCost of each scan through the pipeline

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
                                                 params.laser_offset_yaw), costs=log.costs)
    if world_truth is not None and world_truth[1]:
        wt = np.asarray(world_truth[1], dtype=float)
        order = np.argsort(wt, kind="stable")
        res.world_truth_t, res.world_truth_poses = wt[order], np.asarray(world_truth[2], dtype=float)[order]
    if opts.reference or (opts.reference is None and not res.has_truth):
        res.reference, res.reference_problem = _reference(opts, res, occupancy_map, params, scan_topic)
        res.wall_time = time.perf_counter() - t_wall0
    return res


def _reference(opts: ReplayOptions, res: ReplayResult, occupancy_map, params: Parameters, scan_topic: str):
    """The yardstick of the replayed bag (``localization.eval.reference``): (track or None, why not).
    Its own "nothing to score" lines are kept so that a yardstick with no scored scan can say why."""
    from localization.eval.progress import busy
    from localization.eval.reference import reference_for_bag
    said: list = []
    try:
        with busy("reference track", enabled=opts.progress) as say:  # the pass after the replay's bar
            def note(line: str) -> None:
                said.append(line)
                if opts.progress:
                    say(line)
            ref = reference_for_bag(
                opts.bag, occupancy_map, scan_topic,
                (params.laser_offset_x, params.laser_offset_y, params.laser_offset_yaw),
                odom_topic=opts.odom_topic or opts.params.odom_topic, odom_frame=params.odom_frame,
                base_frame=params.base_frame,
                initial_pose=res.initial_pose, range_scale=params.lidar_scale_to_map_scale,
                wall_depth=params.map_wall_depth, scan_stamp=params.scan_stamp,
                scan_stamp_offset=params.scan_stamp_offset, log=note)
    except (BagError, ValueError) as exc:
        return None, f"the yardstick could not start: {exc}"
    why = [line.split(":", 1)[1].strip() for line in said if line.startswith("reference track:")]
    return ref, (why[-1] if why else None)


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
