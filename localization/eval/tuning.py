"""Tuning the filter from recorded bags with Optuna: the search space, the objective, the study.

A *trial* draws one value per entry of the search space (a YAML file naming parameters of the
table, ``config/tune_space.yaml``), lays them over the starting parameters, replays every bag
through the core (``Feeder.run`` → ``Localizer``, the loop ``localization-replay`` uses; the
messages read once per worker) and scores it.
For bag b::

    s_b = e_b + P_lost · [lost_b] + W_time · max(0, ρ_b − 1)

    e_b     mean position (CT) error (m) of the published estimates against the bag's ground truth
            (``/tf`` map → base_link, what simulated bags carry); without truth (``score_without_truth``)
            the mean position error (m) of the estimate at each scan's time (``FeedLog.scan_track``, as
            in localization-replay's reference figures) against the bag's reference track — every scan
            matched to the map by the correlative scan matcher (``localization.eval.reference``), built once per bag
            before the study from the bag's scans and odometry alone — or, when no reference can
            be built, 1 − median scan–map agreement of the estimate at each scan's time (in [0, 1], not
            metres; ``feed.make_scorer`` of the starting parameters: their laser mount and lidar range
            scale, as localization-replay scores)
    lost_b  the filter re-spread its particles (recoveries > 0), or the last scored estimate is more
            than ``LOST_FINAL_ERROR_M`` (1 m) from the truth (or reference), or the bag was cut for
            being too slow
    ρ_b     filter time / bag duration (the time spent inside the Localizer; > 1: slower than real
            time on this machine)
    P_lost  ``lost_penalty`` (default 1.0), W_time ``time_weight`` (default 1.0 per real time over)

and the trial's value is the mean of s_b over the bags (minimised). After each bag the running
mean is reported to Optuna (step = bag index), so a pruner stops hopeless trials after the first
bag. Every random draw of the filter uses the same ``seed`` in every trial, so two parameter sets
meet the same luck.

The study lives in Optuna storage: a journal file (``JournalStorage`` + ``JournalFileBackend``) by
default, or any Optuna storage URL (``sqlite:///…``, ``postgresql://…``), so worker processes on
one machine (``run_workers``) and on several machines (the same command, the same URL) share one
study; running again with the same study name continues it.
"""
from __future__ import annotations

import logging
import math
import multiprocessing
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from localization.bags import BagError, open_bag
from localization.core.health import AgreementScorer
from localization.core.localizer import Localizer
from localization.core.occupancy_map import OccupancyMap
from localization.core.odometry import TwistData
from localization.core.parameters import BY_NAME, ParameterError, Parameters
from localization.core.paths import config_dir, resolve_params_path
from localization.core.scan import ScanData
from localization.eval import metrics as M
from localization.eval.feed import START_FROM_EVENTS, START_GLOBAL, Feeder, FeedLog, InitialPose, make_scorer
from localization.eval.replay import ReplayError, bag_events, check_topics, load_map

LOST_FINAL_ERROR_M = 1.0  # m: a last estimate further than this from the truth counts as lost
NO_ESTIMATE_ERROR_M = 10.0  # m: the error of a bag that produced no estimate at all
MIN_REFERENCE_MATCHES = 10  # good scan matches a reference track needs to be used
DEFAULT_STUDY = "localization-tune"
BASELINE_ATTR = "baseline"  # user attribute of the enqueued trial that evaluates the starting parameters
DUPLICATE_ATTR = "repeat_of"  # user attribute of a trial whose parameters an earlier trial evaluated: its number


class TuneError(RuntimeError):
    """A tuning run that cannot start: the message is one line saying what is wrong."""


class SpaceError(TuneError):
    """A search space file that cannot be used (unreadable, unknown parameter, bad range)."""


# --------------------------------------------------------------------------------------------
# Search space
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SpaceEntry:
    """One tuned parameter: a range [low, high] (``log``: sampled uniformly in log; ``step``: on a
    grid) or a list of ``choices``. Integer parameters of the table sample integers."""

    name: str
    low: float | int | None = None
    high: float | int | None = None
    log: bool = False
    step: float | int | None = None
    choices: tuple | None = None

    @property
    def is_int(self) -> bool:
        d = BY_NAME[self.name].default
        return isinstance(d, int) and not isinstance(d, bool)

    def suggest(self, trial):
        if self.choices is not None:
            return trial.suggest_categorical(self.name, list(self.choices))
        if self.is_int:
            return trial.suggest_int(self.name, int(self.low), int(self.high), step=int(self.step or 1), log=self.log)
        return trial.suggest_float(self.name, float(self.low), float(self.high), step=self.step, log=self.log)


def default_space_path() -> Path:
    return config_dir() / "tune_space.yaml"


def _number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _entry(name: str, spec, where: str) -> SpaceEntry:
    if name not in BY_NAME:
        raise SpaceError(f"{where}: unknown parameter {name!r} (not in the parameter table, "
                         "localization/core/parameters.py)")
    p = BY_NAME[name]

    def ok(value) -> bool:
        if isinstance(p.default, float) and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if type(value) is not type(p.default):
            return False
        return p.check is None or p.check(value)

    if isinstance(spec, list):
        spec = {"choices": spec}
    if not isinstance(spec, dict):
        raise SpaceError(f"{where}: {name}: expected {{low: A, high: B}} or {{choices: [...]}}, got {spec!r}")
    unknown = set(spec) - {"low", "high", "log", "step", "choices"}
    if unknown:
        raise SpaceError(f"{where}: {name}: unknown key(s) {', '.join(sorted(map(str, unknown)))} "
                         "(use low, high, log, step or choices)")
    if "choices" in spec:
        choices = spec["choices"]
        if set(spec) != {"choices"} or not isinstance(choices, list) or not choices:
            raise SpaceError(f"{where}: {name}: choices must be a non-empty list, alone")
        bad = [c for c in choices if not ok(c)]
        if bad:
            raise SpaceError(f"{where}: {name}: choice {bad[0]!r} is not valid ({name} must be {p.rule or 'valid'})")
        return SpaceEntry(name, choices=tuple(choices))
    if isinstance(p.default, (bool, str)):
        raise SpaceError(f"{where}: {name} is not numeric: give it {{choices: [...]}}")
    if "low" not in spec or "high" not in spec:
        raise SpaceError(f"{where}: {name}: needs both low and high")
    low, high, log, step = spec["low"], spec["high"], spec.get("log", False), spec.get("step")
    if not (_number(low) and _number(high)):
        raise SpaceError(f"{where}: {name}: low and high must be finite numbers, got {low!r}, {high!r}")
    if not low < high:
        raise SpaceError(f"{where}: {name}: low ({low}) must be below high ({high})")
    if not isinstance(log, bool):
        raise SpaceError(f"{where}: {name}: log must be true or false, got {log!r}")
    if log and low <= 0:
        raise SpaceError(f"{where}: {name}: a log range needs low > 0, got {low}")
    if step is not None and not (_number(step) and step > 0):
        raise SpaceError(f"{where}: {name}: step must be a positive number, got {step!r}")
    if log and step is not None and not isinstance(p.default, int):
        raise SpaceError(f"{where}: {name}: give log or step, not both")
    is_int = isinstance(p.default, int)
    if is_int and not all(float(v).is_integer() for v in (low, high, step or 1)):
        raise SpaceError(f"{where}: {name} is an integer parameter: low, high and step must be integers")
    if is_int and log and step not in (None, 1):
        raise SpaceError(f"{where}: {name}: give log or step, not both")
    for v in (low, high):
        if not ok(int(v) if is_int else v):
            raise SpaceError(f"{where}: {name}: {v} is out of the parameter's range ({name} must be {p.rule})")
    return SpaceEntry(name, int(low) if is_int else float(low), int(high) if is_int else float(high), log,
                      (int(step) if is_int else float(step)) if step is not None else None)


def load_space(path=None) -> list[SpaceEntry]:
    """The search space of a YAML file (default ``config/tune_space.yaml``; a bare name is looked up
    in the package's config/): ``name: {low: A, high: B[, log: true][, step: S]}`` or
    ``name: {choices: [...]}`` per parameter. Raises SpaceError (one line)."""
    import yaml

    path = default_space_path() if path is None else resolve_params_path(path)
    try:
        doc = yaml.safe_load(Path(path).read_text())
    except FileNotFoundError:
        raise SpaceError(f"search space file not found: {path}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SpaceError(f"cannot read search space file {path}: {exc}") from None
    except yaml.YAMLError as exc:
        first = " ".join(str(exc).split())
        raise SpaceError(f"search space file {path} is not valid YAML: {first}") from None
    if not isinstance(doc, dict) or not doc:
        raise SpaceError(f"search space file {path}: expected a mapping of parameter names to ranges")
    return [_entry(str(name), spec, str(path)) for name, spec in doc.items()]


def space_from_dict(doc: dict, where: str = "search space") -> list[SpaceEntry]:
    return [_entry(str(name), spec, where) for name, spec in doc.items()]


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


# --------------------------------------------------------------------------------------------
# The objective and the study
# --------------------------------------------------------------------------------------------


@dataclass
class TuneConfig:
    """Everything a worker process needs (picklable)."""

    bags: list  # paths
    map: str
    start: dict  # starting parameter values (the complete table)
    space: list  # SpaceEntry
    storage: str  # an Optuna storage URL, or a journal file path
    study: str = DEFAULT_STUDY
    seed: int = 0
    weights: ScoreWeights = field(default_factory=ScoreWeights)
    initial_poses: list | None = None  # per bag: (x, y, yaw) or None
    scan_topic: str | None = None  # default: the start parameters' scan_topic
    odom_topic: str | None = None
    prune: bool = True
    timeout: float | None = None
    references: list | None = None  # per bag: (t, poses) of its reference track, or None (see prepare_references)


def make_storage(url: str):
    """An Optuna storage: a URL (``sqlite:///f.db``, ``postgresql://…``) as Optuna reads it, anything
    else a journal file (created on first use; safe for processes sharing the file)."""
    import optuna
    from optuna.storages.journal import JournalFileBackend, JournalStorage

    if "://" in str(url):
        try:
            return optuna.storages.get_storage(str(url))
        except Exception as exc:  # noqa: BLE001 - any driver/connection problem: one line
            raise TuneError(f"cannot open study storage {url}: {' '.join(str(exc).split())[:300]}") from None
    path = Path(url).expanduser()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        return JournalStorage(JournalFileBackend(str(path)))
    except OSError as exc:
        raise TuneError(f"cannot open study journal {path}: {exc}") from None


def make_study(cfg: TuneConfig, worker: int = 0):
    import optuna

    storage = make_storage(cfg.storage)
    # a resumed study seeds its sampler past the trials it has: the same seed again would draw the
    # same first (random) parameter sets again
    done = _finished_trials(storage, cfg.study)
    sampler = optuna.samplers.TPESampler(seed=cfg.seed + 1000 * worker + 100_003 * done, constant_liar=True)
    pruner = (optuna.pruners.PercentilePruner(75.0, n_startup_trials=5, n_warmup_steps=0) if cfg.prune
              else optuna.pruners.NopPruner())
    return optuna.create_study(storage=storage, study_name=cfg.study, direction="minimize",
                               sampler=sampler, pruner=pruner, load_if_exists=True)


def _finished_trials(storage, study_name: str) -> int:
    """Finished trials of a study in ``storage`` (0 when there is no such study yet)."""
    try:
        study_id = storage.get_study_id_from_name(study_name)
    except KeyError:
        return 0
    return sum(t.state.is_finished() for t in storage.get_all_trials(study_id, deepcopy=False))


def _n_finished(study) -> int:
    return sum(t.state.is_finished() for t in study.get_trials(deepcopy=False))


def earlier_trial_with(study, params: dict, number: int):
    """A complete trial before ``number`` that evaluated exactly ``params`` (None if there is none)."""
    import optuna

    for t in study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,)):
        if t.number != number and t.params == params and DUPLICATE_ATTR not in t.user_attrs:
            return t
    return None


def start_values(cfg: TuneConfig) -> dict:
    """The starting parameters' values of the tuned names (the baseline trial's parameters). A start
    value Optuna cannot record in the entry's distribution (not among the choices, <= 0 on a log
    range) is not a trial parameter: the baseline uses it as is."""
    out = {}
    for e in cfg.space:
        v = cfg.start[e.name]
        if (e.choices is not None and v not in e.choices) or (e.choices is None and e.log and not v > 0):
            continue
        out[e.name] = v
    return out


def enqueue_baseline(study, cfg: TuneConfig) -> None:
    """Evaluate the starting parameters first (once per study: again only if it failed)."""
    import optuna

    live = (optuna.trial.TrialState.COMPLETE, optuna.trial.TrialState.RUNNING, optuna.trial.TrialState.WAITING)
    if any(t.user_attrs.get(BASELINE_ATTR) for t in study.get_trials(deepcopy=False, states=live)):
        return
    study.enqueue_trial(start_values(cfg), user_attrs={BASELINE_ATTR: True}, skip_if_exists=True)


def prepare_references(cfg: TuneConfig, log=None) -> list:
    """The reference track of every bag without ground truth (None for the others), stored in
    ``cfg.references`` so every worker scores against the same one. A bag whose reference cannot
    be built is scored by scan–map agreement (``log`` says so)."""
    start = Parameters(dict(cfg.start, random_seed=cfg.seed))
    occupancy_map = load_map(cfg.map)
    poses = cfg.initial_poses or [None] * len(cfg.bags)
    refs = []
    for path, pose in zip(cfg.bags, poses):
        bag = load_bag(path, scan_topic=cfg.scan_topic or start.scan_topic,
                       odom_topic=cfg.odom_topic or start.odom_topic, initialpose_topic=start.initialpose_topic,
                       initial_pose=pose)
        ref = None
        if not bag.has_truth:
            try:
                ref = build_bag_reference(bag, occupancy_map, start)
            except Exception as exc:  # noqa: BLE001 - the matcher failing must not stop the tuning
                ref = None
                if log:
                    log(f"{bag.label}: no reference track ({' '.join(str(exc).split())[:200]})")
            if ref is None and log:
                log(f"{bag.label}: no ground truth and no usable reference track: scored by scan-map agreement")
            elif log:
                log(f"{bag.label}: no ground truth: scored against a reference track of {len(ref[0])} scan matches")
        refs.append(ref)
    cfg.references = refs
    return refs


def check_bags(cfg: TuneConfig) -> None:
    """Every bag opens and has the scan and odometry topics (ReplayError, one line, otherwise)."""
    start = Parameters(cfg.start)
    for path in cfg.bags:
        try:
            bag = open_bag(path)
        except BagError as exc:
            raise ReplayError(str(exc)) from None
        with bag:
            check_topics(bag.topic_infos, bag.path, cfg.scan_topic or start.scan_topic,
                         cfg.odom_topic or start.odom_topic, None, start.initialpose_topic, bag_initial_pose=False)


class Objective:
    """``objective(trial) -> mean score``; reads the bags and the map once."""

    def __init__(self, cfg: TuneConfig):
        self.cfg = cfg
        start = Parameters(cfg.start)
        self.map = load_map(cfg.map)
        scan_topic = cfg.scan_topic or start.scan_topic
        odom_topic = cfg.odom_topic or start.odom_topic
        poses = cfg.initial_poses or [None] * len(cfg.bags)
        self.bags = [load_bag(b, scan_topic=scan_topic, odom_topic=odom_topic,
                              initialpose_topic=start.initialpose_topic, initial_pose=p)
                     for b, p in zip(cfg.bags, poses)]
        for bag, ref in zip(self.bags, cfg.references or [None] * len(self.bags)):
            bag.reference = ref
        # truth-free scoring always projects scans with the starting laser mount and range scale (tuned
        # values must not move the yardstick)
        self.scorer = make_scorer(self.map, start)

    def params_of(self, values: dict) -> Parameters:
        merged = dict(self.cfg.start)
        merged.update(values)
        merged["random_seed"] = self.cfg.seed
        return Parameters(merged)

    def __call__(self, trial) -> float:
        import optuna

        fixed = start_values(self.cfg) if trial.user_attrs.get(BASELINE_ATTR) else None
        values = {e.name: e.suggest(trial) for e in self.cfg.space if fixed is None or e.name in fixed}
        try:
            params = self.params_of(values)
        except ParameterError as exc:  # e.g. every alpha zero: no score
            trial.set_user_attr("invalid", str(exc))
            raise optuna.TrialPruned(str(exc)) from None
        trial.set_user_attr("worker_pid", os.getpid())
        same = earlier_trial_with(trial.study, trial.params, trial.number)
        if same is not None:  # evaluated already (a resumed or shared study): its value, not a re-run
            for key, value in same.user_attrs.items():
                if key not in (BASELINE_ATTR, "worker_pid"):
                    trial.set_user_attr(key, value)
            trial.set_user_attr(DUPLICATE_ATTR, same.number)
            trial.set_user_attr("wall_s", 0.0)
            return float(same.value)
        t0 = time.perf_counter()
        scores = []
        for k, bag in enumerate(self.bags):
            s = evaluate_bag(bag, self.map, params, self.cfg.weights, self.scorer)
            scores.append(s.score)
            trial.set_user_attr(f"error_{k}", s.error)
            trial.set_user_attr(f"source_{k}", s.source)
            trial.set_user_attr(f"lost_{k}", s.lost)
            trial.set_user_attr(f"realtime_{k}", s.realtime_ratio)
            running = float(np.mean(scores))
            trial.report(running, k)
            if (self.cfg.prune and k + 1 < len(self.bags) and not trial.user_attrs.get(BASELINE_ATTR)
                    and trial.should_prune()):
                trial.set_user_attr("wall_s", time.perf_counter() - t0)
                raise optuna.TrialPruned(f"pruned after bag {k + 1}: {running:.4f}")
        trial.set_user_attr("wall_s", time.perf_counter() - t0)
        trial.set_user_attr("mean_error", float(np.mean([trial.user_attrs[f"error_{k}"]
                                                          for k in range(len(self.bags))])))
        return float(np.mean(scores))


def _quiet_optuna() -> None:
    import warnings

    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    warnings.filterwarnings("ignore", category=optuna.exceptions.ExperimentalWarning)
    # the baseline trial evaluates the starting values even outside the space's ranges: expected
    warnings.filterwarnings("ignore", message="Fixed parameter .* is out of range")


class GracefulStop:
    """Ctrl-C / SIGTERM as a graceful stop: the running trial finishes and is stored, then
    ``study.stop()``. (A KeyboardInterrupt raised at an arbitrary point could leave the journal
    file's lock behind, and the next writer would wait for it to go stale.) Use as a context
    manager in the main thread; it is also the study callback that stops the study."""

    def __init__(self):
        self.requested = False
        self._previous = {}

    def __enter__(self) -> "GracefulStop":
        import signal
        import threading
        if threading.current_thread() is threading.main_thread():
            for s in (signal.SIGINT, signal.SIGTERM):
                self._previous[s] = signal.signal(s, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        import signal
        for s, handler in self._previous.items():
            signal.signal(s, handler)

    def _handle(self, signum, frame) -> None:  # noqa: ARG002
        self.requested = True

    def __call__(self, study, trial) -> None:  # noqa: ARG002 - an Optuna callback
        if self.requested:
            study.stop()


def run_worker(cfg: TuneConfig, worker: int, n_trials: int, callbacks=()) -> int:
    """Run ``n_trials`` trials of the study in this process; returns how many ran. Raises
    KeyboardInterrupt after a graceful stop on Ctrl-C / SIGTERM."""
    _quiet_optuna()
    objective = Objective(cfg)
    study = make_study(cfg, worker)
    before = len(study.get_trials(deepcopy=False))
    with GracefulStop() as stop:
        # a trial that raises is recorded as failed (Optuna logs its traceback) and the study goes on
        study.optimize(objective, n_trials=n_trials, timeout=cfg.timeout, callbacks=[*callbacks, stop],
                       catch=(Exception,))
    if stop.requested:
        raise KeyboardInterrupt
    return len(study.get_trials(deepcopy=False)) - before


def _worker_main(cfg: TuneConfig, worker: int, n_trials: int, progress: bool) -> None:
    callbacks = [print_trial] if progress else []
    try:
        run_worker(cfg, worker, n_trials, callbacks)
    except KeyboardInterrupt:
        pass


def _stderr(line: str) -> None:
    import sys

    sys.stderr.write(line + "\n")
    sys.stderr.flush()


def print_trial(study, trial) -> None:
    """A one-line report per finished trial on stderr."""
    import sys

    import optuna

    state = trial.state
    value = (f"{trial.value:.4f}" if state == optuna.trial.TrialState.COMPLETE and trial.value is not None
             else state.name.lower())
    try:
        best = f"{study.best_value:.4f}"
    except ValueError:
        best = "n/a"
    wall = trial.user_attrs.get("wall_s")
    sys.stderr.write(f"trial {trial.number:4d}: {value:>8} (best {best})"
                     + (f" {wall:.1f} s" if wall is not None else "")
                     + (" [baseline]" if trial.user_attrs.get(BASELINE_ATTR) else "")
                     + (f" [same parameters as trial {trial.user_attrs[DUPLICATE_ATTR]}: not re-run]"
                        if DUPLICATE_ATTR in trial.user_attrs else "") + "\n")
    sys.stderr.flush()


def split_trials(n_trials: int, jobs: int) -> list[int]:
    """``n_trials`` spread over ``jobs`` workers (exactly n_trials in all)."""
    return [n_trials // jobs + (1 if k < n_trials % jobs else 0) for k in range(jobs)]


def run_workers(cfg: TuneConfig, n_trials: int, jobs: int = 1, progress: bool = False, bar: bool = False):
    """Create (or load) the study, queue the baseline, run ``n_trials`` trials over ``jobs`` worker
    processes (each its own Python: the filter is CPU-bound) and return the study. ``progress``:
    what happens on stderr (reference tracks, then one line per trial, or with ``bar`` a tqdm bar
    of the trials instead of the lines)."""
    from localization.eval.progress import busy, progress_bar
    _quiet_optuna()
    study = make_study(cfg)
    if cfg.references is None:
        with busy("reference tracks", enabled=progress and bar) as say:
            prepare_references(cfg, log=say if progress else None)
    enqueue_baseline(study, cfg)
    shares = [n for n in split_trials(n_trials, max(1, jobs)) if n > 0]
    lines = progress and not bar
    trials_bar = progress_bar(total=n_trials, desc="trials", unit="trial", enabled=progress and bar)
    before = _n_finished(study)
    if len(shares) <= 1:
        try:
            run_worker(cfg, 0, n_trials, ([print_trial] if lines else []) + [_BarCallback(trials_bar)])
        finally:
            trials_bar.close()
        return study
    ctx = multiprocessing.get_context("spawn")
    procs = [ctx.Process(target=_worker_main, args=(cfg, k, n, lines), name=f"tune-worker-{k}")
             for k, n in enumerate(shares)]
    for p in procs:
        p.start()
    with GracefulStop() as stop:  # the workers get the signal too and stop after their running trial
        for p in procs:
            while p.is_alive():
                p.join(1.0)
                if not trials_bar.disable:  # the workers' finished trials, read from the shared study
                    done = _n_finished(study) - before
                    _BarCallback(trials_bar).best(study)
                    trials_bar.update(max(0, min(done, n_trials) - trials_bar.n))
    trials_bar.close()
    if stop.requested:
        raise KeyboardInterrupt
    failed = [p.name for p in procs if p.exitcode not in (0, None)]
    if failed:
        raise TuneError(f"worker process(es) {', '.join(failed)} failed (see the messages above)")
    return study


class _BarCallback:
    """A study callback advancing a progress bar per finished trial, the best value beside it."""

    def __init__(self, bar):
        self.bar = bar

    def __call__(self, study, trial) -> None:  # noqa: ARG002 - an Optuna callback
        if not self.bar.disable:
            self.best(study)
            self.bar.update(1)

    def best(self, study) -> None:
        try:
            self.bar.set_postfix_str(f"best {study.best_value:.4f}", refresh=False)
        except ValueError:  # no complete trial yet
            pass


def _source(bag: BagData) -> str:
    return "truth" if bag.has_truth else "reference" if bag.reference is not None else "agreement"


def compare_parameters(cfg: TuneConfig, candidates: dict, seeds=(11, 12, 13)) -> dict:
    """Score named parameter sets (complete value dicts) on the bags of ``cfg`` with filter seeds
    the tuning did not use: {name: {"errors": per-bag mean error over the seeds, "error": their mean,
    "score": mean score, "lost": lost bag runs, "wall_s": per evaluation of all bags}}."""
    if cfg.references is None:
        prepare_references(cfg)
    objective = Objective(cfg)
    out = {}
    for name, values in candidates.items():
        errors, scores, walls, lost = [], [], [], 0
        for seed in seeds:
            params = Parameters(dict(values, random_seed=int(seed)))
            t0 = time.perf_counter()
            runs = [evaluate_bag(b, objective.map, params, cfg.weights, objective.scorer) for b in objective.bags]
            walls.append(time.perf_counter() - t0)
            errors.append([r.error for r in runs])
            scores.append(float(np.mean([r.score for r in runs])))
            lost += sum(r.lost for r in runs)
        e = np.asarray(errors, dtype=float)
        out[name] = {"errors": e.mean(axis=0).tolist(), "error": float(e.mean()), "score": float(np.mean(scores)),
                     "lost": int(lost), "wall_s": float(np.mean(walls)),
                     "sources": [_source(b) for b in objective.bags]}
    return out


def baseline_trial(study):
    """The finished trial that evaluated the starting parameters (None if it has not finished)."""
    import optuna

    for t in study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,)):
        if t.user_attrs.get(BASELINE_ATTR):
            return t
    return None
