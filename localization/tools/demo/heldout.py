"""Held-out figures: each real bag replayed with the calibration of the OTHER bags of its robot (folds), and
``--heldout-tuning``: the values real_params.yaml took from the RSS bags' errors (motion noise, sigma_hit)
chosen per fold on its training bags from a grid (docs/replay.md, "Held-out figures")."""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from localization.core.parameters import Parameters
from localization.eval.calibration import PARAM_NAMES as CALIBRATED_PARAMS
from localization.tools.demo.jobs import MOTION_NOISE_PARAMS, TUNED, TUNING
from localization.tools.demo.worker import run_all

#: calibration result name -> parameter: the values a held-out fold takes from the other bags' calibration
#: (every value a robot's parameter file takes from ``localization-calibrate``; the parameter files keep the
#: laser's y and yaw at 0)
HELDOUT_KEYS = {k: p for k, p in CALIBRATED_PARAMS.items() if p not in ("laser_offset_y", "laser_offset_yaw")}
#: parameter file -> the HELDOUT_KEYS its robot does not take from calibration: the Pioneer's laser mount comes
#: from its bags' TF and its wall depth is pinned at 0 (pioneer_params.yaml says why)
HELDOUT_PINNED = {"pioneer_params.yaml": ("laser_offset_x", "map_wall_depth")}
#: parameter -> (column title, format) of the calibration table
CALIBRATION_COLUMNS = {"odom_time_offset": ("time offset", "{:+.4f}s"), "odom_speed_scale": ("speed scale", "{:.4f}"),
                       "odom_yaw_rate_scale": ("yaw scale", "{:.4f}"), "odom_yaw_rate_bias": ("yaw bias", "{:+.4f}"),
                       "laser_offset_x": ("laser x", "{:.3f}m"), "lidar_scale_to_map_scale": ("range scale", "{:.4f}"),
                       "map_wall_depth": ("wall depth", "{:.3f}m")}


def heldout_keys(params_file: str) -> dict:
    """The HELDOUT_KEYS a held-out fold of a robot with this parameter file takes from calibration."""
    pinned = HELDOUT_PINNED.get(Path(params_file).name, ())
    return {k: p for k, p in HELDOUT_KEYS.items() if p not in pinned}


def heldout_folds(bags, calibrate, keys: dict | None = None) -> dict:
    """For each bag k of ``bags``: the parameter overrides calibrated WITHOUT it, the mean over the
    other bags j ≠ k of ``calibrate(j)[key]`` for each key of ``keys`` (default ``HELDOUT_KEYS``), under
    its parameter name; and ``"calibrated_on"``: those other bags. ``calibrate(name)`` -> dict of
    calibrated values (``CalibrationResult.values``); it is called once per bag, only for bags some fold
    uses."""
    bags = list(bags)
    if len(bags) < 2:
        raise ValueError(f"held-out folds need at least two bags, got {bags}")
    values: dict = {}

    def once(b):
        if b not in values:
            values[b] = calibrate(b)
        return values[b]
    return {k: fold_of(k, bags, once, keys) for k in bags}


def fold_of(bag: str, bags, calibrate, keys: dict | None = None) -> dict:
    """The held-out fold of ``bag`` among ``bags`` (``heldout_folds``): needs only the other bags'
    calibrations, so its replay may start as soon as they are done."""
    keys = HELDOUT_KEYS if keys is None else keys
    others = [b for b in bags if b != bag]
    values = {b: calibrate(b) for b in others}
    fold = {param: float(sum(float(values[b][key]) for b in others) / len(others)) for key, param in keys.items()}
    fold["calibrated_on"] = others
    return fold


def fold_overrides(fold: dict) -> dict:
    """A held-out fold's parameter overrides (without its ``"calibrated_on"`` bags)."""
    return {p: v for p, v in fold.items() if p != "calibrated_on"}


# --------------------------------------------------------------------------------------------
# --heldout-tuning
# --------------------------------------------------------------------------------------------

#: What ``config/real_params.yaml`` took from the RSS bags' errors rather than from calibration: the
#: motion noise (every ``motion_*`` of the file scaled by one factor) and the beam model's hit width
#: ``sigma_hit`` (m; 1.5, 2, 3 and 4 cells of 0.0504 m).
TUNING_GRID = {"motion_scale": (0.35, 0.5, 0.7, 1.0, 1.4), "sigma_hit": (0.0756, 0.1008, 0.1512, 0.2016)}
#: The RSS targets against the yardstick (m): median, p95 and |mean along-track| error.
YARDSTICK_TARGETS = {"median": 0.035, "p95": 0.08, "along": 0.02}


def yardstick_errors(metrics: dict) -> tuple:
    """(median, p95, mean along-track) error (m) of a replay's metrics vs the yardstick; None: not scored."""
    ref = metrics.get("reference_error_m") or {}
    return ref.get("median"), ref.get("p95"), (metrics.get("along_track_error_m") or {}).get("mean")


def target_ratio(metrics: dict) -> float:
    """How a replay scores against the RSS targets: max(median / 0.035, p95 / 0.08, |mean along| / 0.02)
    of its error vs the yardstick (below 1: every target met; inf: not scored)."""
    median, p95, along = yardstick_errors(metrics)
    if median is None or p95 is None or along is None:
        return float("inf")
    t = YARDSTICK_TARGETS
    return max(median / t["median"], p95 / t["p95"], abs(along) / t["along"])


def tuning_points() -> list[tuple[float, float]]:
    """The grid's points (motion scale, sigma_hit)."""
    return [(m, s) for m in TUNING_GRID["motion_scale"] for s in TUNING_GRID["sigma_hit"]]


def tuning_overrides(base: Parameters, point: tuple[float, float]) -> dict:
    """The parameter overrides of a grid point: ``base``'s motion noise scaled, and its hit width."""
    m, s = point
    return {**{k: float(base[k]) * m for k in MOTION_NOISE_PARAMS}, "sigma_hit": float(s)}


def choose_points(scores: dict) -> dict:
    """fold -> (point, its mean target ratio over the fold's training bags), from ``scores``:
    (fold, point) -> the training bags' ratios; the lowest mean wins (the first of equals)."""
    best: dict = {}
    for (fold, point), ratios in scores.items():
        mean = float(np.mean(ratios)) if ratios else float("inf")
        if fold not in best or mean < best[fold][1]:
            best[fold] = (point, mean)
    return best


def tuning_jobs(jobs: list, folds: dict, base: Parameters, overrides: dict) -> list:
    """Phase one of the held-out tuning: every grid point on every fold's training bags (never the fold's
    own bag), with that fold's calibration."""
    out = []
    for k, fold in folds.items():
        cal = fold_overrides(fold)
        for point in tuning_points():
            for job in jobs:
                if job.label != k:
                    settings = {**overrides, **cal, **tuning_overrides(base, point)}
                    out.append(replace(job, table=TUNING, parameters=tuple(settings.items()), out=None,
                                       plots=False, fold=k, point=point))
    return out


@dataclass
class Tuning:
    """The held-out tuning's outcome: the grid's scores, each fold's choice, and the held-out replays."""

    scores: dict  # (fold, point) -> the training bags' target ratios
    chosen: dict  # fold -> (point, mean training ratio)
    file_point: tuple  # real_params.yaml's own point (x1, its sigma_hit)
    grid: list  # the grid's results
    final: list  # each bag replayed with its fold's choice


def tune_folds(jobs: list, folds: dict, params_file, overrides: dict, workers: int, out: Path) -> Tuning:
    """Both phases: the grid on each fold's training bags, then each bag with its fold's choice."""
    base = Parameters.from_yaml(params_file)
    grid = run_all(tuning_jobs(jobs, folds, base, overrides), workers)
    scores: dict = {}
    for r in grid:
        ratio = target_ratio(r.metrics) if r.metrics is not None else float("inf")
        scores.setdefault((r.job.fold, r.job.point), []).append(ratio)
    chosen = choose_points(scores)
    finals = [replace(job, table=TUNED, plots=False, out=str(out / "heldout_tuned" / job.label),
                      parameters=tuple({**overrides, **fold_overrides(folds[job.label]),
                                        **tuning_overrides(base, chosen[job.label][0])}.items()))
              for job in jobs]
    return Tuning(scores, chosen, (1.0, float(base["sigma_hit"])), grid, run_all(finals, workers))


def tuning_summary(tuning: Tuning, folds: dict) -> dict:
    """summary.json's ``heldout_tuned``: per bag the choice, its training ratio, the metrics and the grid."""
    summary = {}
    for r in tuning.final:
        k = r.job.label
        point, train = tuning.chosen[k]
        own = tuning.scores.get((k, tuning.file_point))
        summary[k] = {"motion_scale": point[0], "sigma_hit": point[1], "training_ratio": train,
                      "file_point_training_ratio": float(np.mean(own)) if own else None,
                      "tuned_on": folds[k]["calibrated_on"], "metrics": r.metrics or {"error": r.error},
                      "grid": {f"{pt[0]}x {pt[1]}": float(np.mean(v)) for (f, pt), v in tuning.scores.items()
                               if f == k}}
    return summary
