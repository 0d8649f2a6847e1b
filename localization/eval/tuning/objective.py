"""The objective a trial calls (the bags and the map read once per worker), the reference tracks
prepared before the study, and the scoring of named parameter sets with seeds the tuning did not use."""
from __future__ import annotations

import os
import time

import numpy as np

from localization.bags import BagError, open_bag
from localization.core.parameters import ParameterError, Parameters
from localization.eval.feed import make_scorer
from localization.eval.replay import ReplayError, check_topics, load_map
from localization.eval.tuning.score import BagData, build_bag_reference, evaluate_bag, load_bag
from localization.eval.tuning.study import BASELINE_ATTR, DUPLICATE_ATTR, TuneConfig, earlier_trial_with, start_values


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
