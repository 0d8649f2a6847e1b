"""One bag's replay and its score (the formula is in ``localization.eval.tuning``): the bag read into
memory once per worker, replayed through the core (``Feeder.run`` → ``Localizer``) and scored against
its ground truth, its reference track or the scan–map agreement."""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from localization.bags import BagError, open_bag
from localization.core.localizer import Localizer
from localization.core.localizer.health import AgreementScorer
from localization.core.occupancy_map import OccupancyMap
from localization.core.odometry import TwistData
from localization.core.parameters import Parameters
from localization.core.scan import ScanData
from localization.eval import metrics as M
from localization.eval.feed import START_FROM_EVENTS, START_GLOBAL, Feeder, FeedLog, InitialPose, make_scorer
from localization.eval.replay import ReplayError, bag_events, check_topics

LOST_FINAL_ERROR_M = 1.0  # m: a last estimate further than this from the truth counts as lost
NO_ESTIMATE_ERROR_M = 10.0  # m: the error of a bag that produced no estimate at all
MIN_REFERENCE_MATCHES = 10  # good scan matches a reference track needs to be used


# --------------------------------------------------------------------------------------------
# Bags, read once per worker
# --------------------------------------------------------------------------------------------


@dataclass
class BagData:
    """One bag's filter input in stamp order (TwistData, ScanData, InitialPose) and its truth."""

    path: Path
    label: str
    events: list
    duration: float  # s of bag time
    truth_t: np.ndarray
    truth_poses: np.ndarray
    initial_pose_source: str
    start_pose: tuple | None = None  # given initial pose (applied at the first input), else None
    reference: tuple | None = None  # (t (K,), poses (K, 3)): the good matches of the reference track

    @property
    def has_truth(self) -> bool:
        return len(self.truth_t) > 0


def load_bag(path, *, scan_topic: str = "/scan", odom_topic: str = "/odom", initialpose_topic: str = "/initialpose",
             initial_pose=None, truth_topic: str | None = None, truth_frames=("map", "base_link")) -> BagData:
    """Read a bag into memory (raises ReplayError, one line). Initial pose: ``initial_pose``, else the
    bag's ``/initialpose`` messages (fed where they occur), else global localization."""
    from localization.eval.replay import bag_label

    parent, child = (f.lstrip("/") for f in truth_frames)
    try:
        bag = open_bag(path)
    except BagError as exc:
        raise ReplayError(str(exc)) from None
    with bag:
        truth_topic, use_bag_init = check_topics(bag.topic_infos, bag.path, scan_topic, odom_topic, truth_topic,
                                                 initialpose_topic, bag_initial_pose=initial_pose is None)
        topics = [scan_topic, odom_topic] + ([initialpose_topic] if use_bag_init else []) \
            + ([truth_topic] if truth_topic else [])
        truth_t: list = []
        truth_p: list = []
        try:
            events = list(bag_events(bag, topics, scan_topic, odom_topic, initialpose_topic if use_bag_init else None,
                                     truth_topic, (parent, child), truth_t, truth_p))
        except BagError as exc:
            raise ReplayError(str(exc)) from None
        duration = (bag.end_ns - bag.start_ns) * 1e-9
    if not any(isinstance(e, ScanData) for e in events):
        raise ReplayError(f"no scan messages on {scan_topic} in bag {path}")
    tt = np.asarray(truth_t, dtype=float)
    order = np.argsort(tt, kind="stable")
    source = ("given" if initial_pose is not None else f"{initialpose_topic} in the bag" if use_bag_init
              else "global localization")
    return BagData(Path(path), bag_label(path), events, duration, tt[order],
                   np.asarray(truth_p, dtype=float).reshape(-1, 3)[order], source,
                   tuple(float(v) for v in initial_pose) if initial_pose is not None else None)


# --------------------------------------------------------------------------------------------
# One replay, its score
# --------------------------------------------------------------------------------------------


@dataclass
class ScoreWeights:
    lost_penalty: float = 1.0  # added to a bag's score when the filter got lost
    time_weight: float = 1.0  # per unit of (filter time / bag duration) above 1
    max_realtime: float = 5.0  # a bag whose filter time exceeds this many times its duration is cut (lost)


@dataclass
class BagScore:
    bag: str
    score: float
    error: float  # m against truth, or the truth-free figure (see ``source``)
    source: str  # "truth" or the truth-free scorer's name
    lost: bool
    recoveries: int
    final_error: float | None  # m against truth
    realtime_ratio: float  # filter time / bag duration
    filter_time: float  # s
    cut: bool  # stopped early for being too slow


def _quiet_logger() -> logging.Logger:
    log = logging.getLogger("localization.tune.filter")
    log.propagate = False
    if not log.handlers:
        log.addHandler(logging.NullHandler())
    return log


def replay_bag(bag: BagData, occupancy_map: OccupancyMap, params: Parameters, *, max_filter_time: float = math.inf,
               scorer: AgreementScorer | None = None) -> tuple[FeedLog, Localizer]:
    """Feed one bag to a fresh Localizer through ``Feeder.run`` (as localization-replay does): its
    initial poses, else ``bag.start_pose``, else global localization. Returns (FeedLog, localizer);
    with a ``scorer`` the log holds each scan's agreement at the scan's time; ``log.cut`` when the
    filter time exceeded ``max_filter_time``."""
    localizer = Localizer(params, logger=_quiet_logger())
    localizer.set_map(occupancy_map)
    if any(isinstance(e, InitialPose) for e in bag.events):
        start = START_FROM_EVENTS
    else:
        start = bag.start_pose if bag.start_pose is not None else START_GLOBAL
    log = Feeder(localizer, scorer).run(bag.events, start, max_filter_time=max_filter_time)
    return log, localizer


def score_without_truth(bag: BagData, est_t: np.ndarray, est_poses: np.ndarray,
                        agreement: list) -> tuple[float, str, float | None]:
    """The error figure of a bag without ground truth: (error, source, final error).

    With a reference track (``bag.reference``): the mean position error (m) of the estimates
    (``est_t``, ``est_poses``: the estimate at each scan's time) against it, and the last one.
    Without: 1 − median scan–map agreement of the estimates (0 = every beam endpoint on a wall; a
    lost filter scores near 1; ``agreement`` is then filled by the replay).
    """
    if bag.reference is not None:
        from localization.eval.reference import track_errors

        err = track_errors(est_t, est_poses, *bag.reference).position
        if err.size:
            return float(err.mean()), "reference", float(err[-1])
        return NO_ESTIMATE_ERROR_M, "reference", None
    if not agreement:
        return 1.0, "agreement", None
    return float(1.0 - np.median(agreement)), "agreement", None


def build_bag_reference(bag: BagData, occupancy_map: OccupancyMap, params: Parameters) -> tuple | None:
    """The reference track of a bag (good matches only): its scans matched to the map along its
    odometry (``localization.eval.reference``, independent of the filter), from the bag's start
    pose or first initial pose (else a global search), with ``params``' laser mount, range scale
    and scan stamp convention; None when fewer than MIN_REFERENCE_MATCHES matches are good."""
    from localization.eval.reference import build_reference

    scans = [e for e in bag.events if isinstance(e, ScanData)]
    odometry = [e for e in bag.events if isinstance(e, TwistData)]
    first = next((e.pose for e in bag.events if isinstance(e, InitialPose)), None)
    start = bag.start_pose if bag.start_pose is not None else first
    ref = build_reference(scans, occupancy_map, (params.laser_offset_x, params.laser_offset_y, params.laser_offset_yaw),
                          (np.array([e.stamp for e in odometry], dtype=float),
                           np.array([(e.vx, e.vy, e.wz) for e in odometry], dtype=float).reshape(-1, 3)),
                          start, range_scale=params.lidar_scale_to_map_scale, wall_depth=params.map_wall_depth,
                          scan_stamp=params.scan_stamp,
                          scan_stamp_offset=params.scan_stamp_offset)
    t, poses = ref.good_track()
    if len(t) < MIN_REFERENCE_MATCHES:
        return None
    return np.asarray(t, dtype=float), np.asarray(poses, dtype=float)


def evaluate_bag(bag: BagData, occupancy_map: OccupancyMap, params: Parameters, weights: ScoreWeights | None = None,
                 scorer: AgreementScorer | None = None) -> BagScore:
    """Replay ``bag`` with ``params`` and score it (see the module docstring)."""
    w = weights or ScoreWeights()
    duration = max(bag.duration, 1e-3)
    need_agreement = not bag.has_truth and bag.reference is None
    if need_agreement and scorer is None:
        scorer = make_scorer(occupancy_map, params)
    log, localizer = replay_bag(bag, occupancy_map, params, max_filter_time=w.max_realtime * duration,
                                scorer=scorer if need_agreement else None)
    cut = log.cut
    est_t, est_poses = log.estimates()
    final_error = None
    if bag.has_truth:
        source = "truth"
        cmp = M.compare_to_truth(est_t, est_poses, bag.truth_t, bag.truth_poses)
        if cmp.ct_error.size:
            error = float(cmp.ct_error.mean())
            final_error = float(cmp.ct_error[-1])
        else:
            error = NO_ESTIMATE_ERROR_M
    else:
        error, source, final_error = score_without_truth(bag, *log.scan_track(), log.agreement)
    if not len(est_t) and bag.has_truth:
        error = NO_ESTIMATE_ERROR_M
    rho = log.filter_time / duration
    if cut:  # the rest of the bag would have taken at least as long per second
        rho = max(rho, w.max_realtime)
    lost = bool(localizer.recoveries > 0 or cut or not len(est_t)
                or (final_error is not None and final_error > LOST_FINAL_ERROR_M))
    score = error + w.lost_penalty * lost + w.time_weight * max(0.0, rho - 1.0)
    return BagScore(bag=bag.label, score=float(score), error=float(error), source=source, lost=lost,
                    recoveries=int(localizer.recoveries), final_error=final_error, realtime_ratio=float(rho),
                    filter_time=float(log.filter_time), cut=cut)
