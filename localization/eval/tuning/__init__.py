"""Tuning the filter from recorded bags with Optuna: the search space, the objective, the study.

Modules by job: ``space`` (the search space file), ``score`` (one bag replayed and scored),
``storage`` (where the study lives), ``study`` (the study, its baseline trial), ``objective`` (what a
trial runs), ``workers`` (worker processes, progress). Every public name is importable from here.

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

from localization.eval.tuning.errors import SpaceError, TuneError
from localization.eval.tuning.objective import Objective, check_bags, compare_parameters, prepare_references
from localization.eval.tuning.score import (
    LOST_FINAL_ERROR_M,
    MIN_REFERENCE_MATCHES,
    NO_ESTIMATE_ERROR_M,
    BagData,
    BagScore,
    ScoreWeights,
    build_bag_reference,
    evaluate_bag,
    load_bag,
    replay_bag,
    score_without_truth,
)
from localization.eval.tuning.space import SpaceEntry, default_space_path, load_space, space_from_dict
from localization.eval.tuning.storage import make_storage
from localization.eval.tuning.study import (
    BASELINE_ATTR,
    DEFAULT_STUDY,
    DUPLICATE_ATTR,
    TuneConfig,
    baseline_trial,
    earlier_trial_with,
    enqueue_baseline,
    make_study,
    start_values,
)
from localization.eval.tuning.workers import GracefulStop, print_trial, run_worker, run_workers, split_trials

__all__ = [
    "BASELINE_ATTR", "DEFAULT_STUDY", "DUPLICATE_ATTR", "LOST_FINAL_ERROR_M", "MIN_REFERENCE_MATCHES",
    "NO_ESTIMATE_ERROR_M", "BagData", "BagScore", "GracefulStop", "Objective", "ScoreWeights", "SpaceEntry",
    "SpaceError", "TuneConfig", "TuneError", "baseline_trial", "build_bag_reference", "check_bags",
    "compare_parameters", "default_space_path", "earlier_trial_with", "enqueue_baseline", "evaluate_bag", "load_bag",
    "load_space", "make_storage", "make_study", "prepare_references", "print_trial", "replay_bag", "run_worker",
    "run_workers", "score_without_truth", "space_from_dict", "split_trials", "start_values",
]
