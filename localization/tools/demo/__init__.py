"""``localization-demo``: the main job in one command (docs/replay.md, "The main job", says what each table
shows and how it is measured).

1. Calibrates each real bag once (``localization-calibrate``) for the held-out folds.
2. Replays, in parallel worker processes (``--jobs``), the job table (``jobs.plan``): the simulated Stata
   basement trials of the reference lab report, clean and in the perturbed world, recorded into the cache
   first when missing (``localization.eval.datasets.sim_bag``); the fast trial with and without time
   alignment; the three RSS 2022 bags with real_params.yaml and held out (each with the calibration of the
   other two); the Pioneer bags likewise; ``--motion-sweep`` and ``--heldout-tuning`` on request.
3. Prints one table per part and writes every replay's outputs and ``summary.json`` into ``--out``.

Modules: ``jobs`` (the job table), ``worker`` (one replay or calibration in a worker process), ``heldout``
(folds and the held-out tuning), ``pioneer`` (the Pioneer figures), ``tables`` (the printed tables),
``cli`` (the command line).
"""
from localization.tools.demo.cli import ONLY, PROG, build_parser, folds_of, heldout_tuning, main
from localization.tools.demo.heldout import (
    CALIBRATION_COLUMNS,
    HELDOUT_KEYS,
    HELDOUT_PINNED,
    TUNING_GRID,
    YARDSTICK_TARGETS,
    choose_points,
    fold_of,
    fold_overrides,
    heldout_folds,
    heldout_keys,
    target_ratio,
    tune_folds,
    tuning_jobs,
    tuning_overrides,
    tuning_points,
    yardstick_errors,
)
from localization.tools.demo.jobs import (
    FAST_RUNS,
    FAST_TRIAL,
    FIXED_SCALE,
    MOTION_NOISE_PARAMS,
    Job,
    Parts,
    Result,
    perturbed_runs,
    plan,
)
from localization.tools.demo.pioneer import (
    CONVERGED_HOLD_S,
    CONVERGED_M,
    EARLY_REFERENCE_S,
    END_WINDOW_S,
    HEALTHY_AGREEMENT,
    StatusCounter,
    converge_time,
    pioneer_metrics,
)
from localization.tools.demo.tables import (
    REFERENCE_CT,
    calibration_table,
    fast_table,
    pioneer_table,
    real_table,
    report,
    sim_table,
    sweep_table,
    tuning_table,
    yardstick_table,
)
from localization.tools.demo.worker import calibrate_job, demo_tasks, run_all, run_job

__all__ = ["CALIBRATION_COLUMNS", "CONVERGED_HOLD_S", "CONVERGED_M", "EARLY_REFERENCE_S", "END_WINDOW_S", "FAST_RUNS",
           "FAST_TRIAL", "FIXED_SCALE", "HEALTHY_AGREEMENT", "HELDOUT_KEYS", "HELDOUT_PINNED", "MOTION_NOISE_PARAMS",
           "ONLY", "PROG", "REFERENCE_CT", "TUNING_GRID", "YARDSTICK_TARGETS", "Job", "Parts", "Result",
           "StatusCounter", "build_parser", "calibrate_job", "calibration_table", "choose_points", "converge_time",
           "demo_tasks", "fast_table", "fold_of", "fold_overrides", "folds_of", "heldout_folds", "heldout_keys",
           "heldout_tuning", "main", "perturbed_runs", "pioneer_metrics", "pioneer_table", "plan", "real_table",
           "report", "run_all", "run_job", "sim_table", "sweep_table", "target_ratio", "tune_folds", "tuning_jobs",
           "tuning_overrides", "tuning_points", "tuning_table", "yardstick_errors", "yardstick_table"]
