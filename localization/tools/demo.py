"""``localization-demo``: the main job in one command.

1. Records (or reuses from the cache) the three simulated Stata basement trials of the
   reference lab report (odometry noise 0, 0.3, 0.6; ``localization.datasets``), and with
   ``--loop`` the longer loop with biased odometry; each twice: scans drawn from the map itself and
   from the perturbed world ``STANDARD_PERTURBATION`` (6 boxes, 4 people, 5 % glass, scale 1.01;
   ``localization.sim.perturb``), plus every report trial at 2 m/s in that world and trial 2 at 2 m/s at
   scale 1.02 too, trial 2's 2 m/s drives also replayed with the range scale fixed at its configured
   value instead of learnt online (``_fixed``: ``range_scale_estimation`` false)
   (``--skip-perturbed``: the clean rows only). Errors are against the truth in the map frame
   (q = c + (p − c) / s, what a localizer in the map can report), the error against the car's pose in
   the world beside it; false recoveries: switches to a place > 1 m from the truth after the first second.
2. Replays each with ``localization-replay``'s code (``config/params.yaml``, the simulator's parameters)
   and the three real
   RSS 2022 bags from their approximate start poses with ``config/real_params.yaml``.
3. Prints a table like the report's (trial, noise level -> CT error; real bags -> scan-map
   agreement) and where the plots are.
4. The fast trial (6-7 m/s, odometry 40 ms late, lidar sweep timing): mean error and
   along-/cross-track error against the ground truth with odometry aligned to each scan and the
   scan deskewed (``odom_time_offset`` = -0.04, the latency the calibrator measures) and with
   both off (``align_odometry`` and ``deskew`` false: no time alignment at all). ``--skip-fast``.

5. Held-out real-bag figures: each RSS 2022 bag replayed with the odometry and lidar calibration of
   the OTHER two bags (``localization-calibrate`` on each of them, the mean of every value
   ``real_params.yaml`` takes from calibration: ``HELDOUT_KEYS``, i.e. the odometry time offset,
   speed scale, yaw-rate scale and bias, ``laser_offset_x``, the range scale and the wall depth;
   everything else from ``real_params.yaml``), next to the all-bags figures of step 2
   (``real_params.yaml``, calibrated on all three, the held-out bag included). The error is against
   the yardstick (``localization.eval.reference``); the held-out table is the honest one.
   ``--only heldout``.
6. The Pioneer 3-DX bags (``config/pioneer_params.yaml``, map lgfloor; trace0 from its start pose,
   trace1 and lgfloor2 globally; lgfloor2's odometry from TF and its scans stamped at the first
   beam): time to converge, largest jump, recoveries, scan–map agreement where the yardstick is
   confident and the share of scans the localizer said disagree with the map; with
   ``pioneer_params.yaml`` (its odometry calibrated on trace0) and held out as in step 5 (the laser
   mount from the bags' TF and the wall depth stay the file's: ``HELDOUT_PINNED``). ``--only pioneer``.

7. ``--heldout-tuning`` (with step 5): the values ``real_params.yaml`` took from the RSS bags' errors
   rather than from calibration, the motion noise and the beam model's hit width, chosen per fold
   too: each grid point of ``TUNING_GRID`` is replayed on the fold's two training bags (with the
   fold's calibration), the point with the lowest mean ``target_ratio`` there is then replayed on the
   held-out bag. No value of that replay has seen its bag. About five minutes on two cores.

``--motion-sweep`` adds a table of the real bags' scan-map agreement as the motion-noise
parameters of ``real_params.yaml`` are scaled (how much the filter should trust the odometry).

Replays run in parallel worker processes (``--jobs``, default: the number of CPUs, at most 4).
``--out`` (default ``./demo-results``) must not hold anything yet unless ``--overwrite`` (its
files are then replaced).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from localization.core.parameters import Parameters
from localization.core.paths import config_dir
from localization.eval.calibration import PARAM_NAMES as CALIBRATED_PARAMS
from localization.eval.datasets import (
    PIONEER_BAGS,
    REAL_BAGS,
    REPORT_TRIALS,
    SIM_TRIALS,
    real_bag,
    real_bag_path,
    sim_bag,
)
from localization.sim.perturb import STANDARD_PERTURBATION
from localization.tools import args as args_

PROG = "localization-demo"

#: Mean CT error (m) the reference lab report measured on its three simulated trials.
REFERENCE_CT = {"trial1_noise0": 0.224, "trial2_noise0.3": 0.183, "trial3_noise0.6": 0.261}

MOTION_NOISE_PARAMS = ("motion_a_trans", "motion_a_lateral", "motion_a_rot", "motion_a_rot_to_trans",
                       "motion_a_trans_to_rot", "motion_floor_xy", "motion_floor_theta")


def _replay_job(job: dict) -> dict:
    """Run one replay (in a worker process); returns its metrics plus bookkeeping (``job["pioneer"]``:
    with ``pioneer_metrics``)."""
    from localization.eval.replay import ReplayError, ReplayOptions, compute_metrics, run_replay, write_outputs
    t0 = time.perf_counter()
    try:
        params = Parameters.from_yaml(job["params_file"], **job["overrides"]) if job.get("params_file") \
            else Parameters(job["overrides"])
        holding = StatusCounter()
        opts = ReplayOptions(Path(job["bag"]), job["map"], params, job.get("initial_pose"),
                             force_global=job.get("force_global", False),
                             label=job["label"], scan_topic=job.get("scan_topic"), odom_topic=job.get("odom_topic"),
                             on_scan=holding if job.get("pioneer") else None,
                             log=lambda line: print(f"{PROG}: {job['label']}: {line}", file=sys.stderr, flush=True))
        res = run_replay(opts)
        metrics = compute_metrics(res)
        if job.get("pioneer"):
            metrics["pioneer"] = pioneer_metrics(res, holding)
        if job.get("out"):
            write_outputs(res, metrics, Path(job["out"]), plots=job.get("plots", True))
    except ReplayError as exc:
        return {"job": job, "error": str(exc)}
    return {"job": job, "metrics": metrics, "seconds": time.perf_counter() - t0}


def _run_all(jobs: list, workers: int) -> list:
    if workers <= 1 or len(jobs) <= 1:
        return [_replay_job(j) for j in jobs]
    with ProcessPoolExecutor(max_workers=workers) as pool:
        return list(pool.map(_replay_job, jobs))


def _f(v, spec=".3f"):
    return "  n/a" if v is None else f"{v:{spec}}"


def _table(header: str, results: list, width: int, row) -> str:
    """The header, then ``row(label, metrics)`` per replay (or its error)."""
    lines = [header]
    for r in results:
        name = r["job"]["label"]
        lines.append(f"{name:<{width}} error: {r['error']}" if "error" in r else row(name, r["metrics"]))
    return "\n".join(lines)


#: parameter overrides of the ``_fixed`` rows: the range scale as configured, not learnt while the filter tracks
FIXED_SCALE = {"range_scale_estimation": False}


def perturbed_runs(trials) -> dict:
    """The simulated trials' perturbed-world replays beside the clean ones, label -> (trial, ``SimConfig``
    overrides, parameter overrides): ``trials`` in ``STANDARD_PERTURBATION`` at their own speeds and at 2 m/s
    (label ``trialN_2mps_scale1.01``), and trial 2 at 2 m/s at scale 1.01 and 1.02 also with ``FIXED_SCALE``
    (label ``_fixed``)."""
    runs = {f"{name}_perturbed": (name, {"world": STANDARD_PERTURBATION}, {}) for name in trials}
    for name in trials:
        if name.startswith("trial") and name != "trial2_noise0.3":  # the report's trials (trial 2: below)
            drive = {"speed": 2.0, "world": STANDARD_PERTURBATION}
            runs[f"{name.split('_')[0]}_2mps_scale{STANDARD_PERTURBATION.scale:g}"] = (name, drive, {})
    for scale in (1.01, 1.02):
        drive = {"speed": 2.0, "world": replace(STANDARD_PERTURBATION, scale=scale)}
        runs[f"trial2_2mps_scale{scale:g}"] = ("trial2_noise0.3", drive, {})
        runs[f"trial2_2mps_scale{scale:g}_fixed"] = ("trial2_noise0.3", drive, FIXED_SCALE)
    return runs


def _world(job: dict) -> str:
    w = job.get("world")
    return "map" if w is None else f"perturbed s{w['scale']:g}"


def sim_table(results: list) -> str:
    """The simulated trials, clean-map rows then perturbed-world rows: CT error against the truth in the map
    frame, mean error against the world-frame truth (the same as the map frame's in the clean world),
    recoveries and false recoveries."""
    def row(name, m):
        ct, conv, head = m["ct_error_m"], m["time_to_converge_s"], m["heading_error_mean_abs_rad"]
        trial = by_label[name]
        world = (m.get("world_ct_error_m") or ct)["mean"]
        return (f"{name:<{width}} {_world(trial):<15} {SIM_TRIALS[trial.get('trial', name)].odom_noise:>5.1f} "
                f"{_f(ct['mean']):>8} {_f(ct['median']):>7} {_f(ct['p95']):>6} {_f(ct['max']):>6} "
                f"{_f(None if head is None else head * 57.29578, '.2f'):>7}° "
                f"{'never' if conv is None else f'{conv:.3f} s':>9} {_f(world):>8} "
                f"{m.get('recoveries', 0):>5} {_f(m.get('false_recoveries'), 'd'):>5} "
                f"{_f(m['scan_map_agreement']['median']):>6} {_f(REFERENCE_CT.get(trial.get('trial', name))):>7}")
    by_label = {r["job"]["label"]: r["job"] for r in results}
    width = max([22, *(len(k) for k in by_label)])
    ordered = [r for r in results if r["job"].get("world") is None] + \
        [r for r in results if r["job"].get("world") is not None]
    return _table(f"{'trial':<{width}} {'world':<15} {'noise':>5} {'mean CT':>8} {'median':>7} {'p95':>6} {'max':>6} "
                  f"{'heading':>8} {'converge':>9} {'vs world':>8} {'recov':>5} {'false':>5} {'agree':>6} "
                  f"{'report':>7}", ordered, width, row)


FAST_TRIAL = "fast"
#: the fast trial's replays: label -> parameter overrides
FAST_RUNS = {"fast_aligned": {"odom_time_offset": -0.04},
             "fast_unaligned": {"align_odometry": False, "deskew": False}}


def fast_table(results: list) -> str:
    def row(name, m):
        ct = m["ct_error_m"]
        along, cross = m.get("truth_along_track_error_m") or {}, m.get("truth_abs_cross_track_error_m") or {}
        return (f"{name:<16} {_f(ct['mean']):>8} {_f(ct['median']):>7} {_f(ct['p95']):>6} {_f(ct['max']):>6} "
                f"{_f(along.get('mean'), '+.4f'):>11} {_f(cross.get('mean'), '.4f'):>10}")
    return _table(f"{'run':<16} {'mean':>8} {'median':>7} {'p95':>6} {'max':>6} {'mean along':>11} "
                  f"{'|cross|':>10}", results, 16, row)


def real_table(results: list) -> str:
    def row(name, m):
        ag = m["scan_map_agreement"]
        ref = m.get("reference_error_m") or {}
        along = (m.get("along_track_error_m") or {}).get("mean")
        return (f"{name:<6} {m['bag_duration_s']:>7.1f}s {m['sensor_updates']:>7} {_f(ag['median']):>9} "
                f"{_f(ag['mean']):>6} {m['max_jump_m']:>7.2f}m {_f(ref.get('median')):>7} {_f(ref.get('p95')):>6} "
                f"{_f(ref.get('max')):>6} {'n/a' if along is None else f'{along:+.3f}':>7}")
    return _table(f"{'bag':<6} {'duration':>8} {'updates':>7} {'agreement':>9} {'mean':>6} {'max jump':>8} "
                  f"{'ref med':>7} {'p95':>6} {'max':>6} {'along':>7}", results, 6, row)


# --------------------------------------------------------------------------------------------
# Held-out calibration (step 5)
# --------------------------------------------------------------------------------------------

#: calibration result name -> parameter: the values a held-out fold takes from the other bags' calibration
#: (every value a robot's parameter file takes from ``localization-calibrate``; the parameter files keep the
#: laser's y and yaw at 0)
HELDOUT_KEYS = {k: p for k, p in CALIBRATED_PARAMS.items() if p not in ("laser_offset_y", "laser_offset_yaw")}
#: parameter file -> the HELDOUT_KEYS its robot does not take from calibration: the Pioneer's laser mount comes
#: from its bags' TF and its wall depth is pinned at 0 (pioneer_params.yaml says why)
HELDOUT_PINNED = {"pioneer_params.yaml": ("laser_offset_x", "map_wall_depth")}


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
    keys = HELDOUT_KEYS if keys is None else keys
    bags = list(bags)
    if len(bags) < 2:
        raise ValueError(f"held-out folds need at least two bags, got {bags}")
    values: dict = {}
    folds = {}
    for k in bags:
        others = [b for b in bags if b != k]
        for b in others:
            if b not in values:
                values[b] = calibrate(b)
        fold = {param: float(sum(float(values[b][key]) for b in others) / len(others))
                for key, param in keys.items()}
        fold["calibrated_on"] = others
        folds[k] = fold
    return folds


def fold_overrides(fold: dict) -> dict:
    """A held-out fold's parameter overrides (without its ``"calibrated_on"`` bags)."""
    return {p: v for p, v in fold.items() if p != "calibrated_on"}


def _calibrate_job(name: str) -> dict:
    """``localization-calibrate`` on a real bag (RSS 2022 or Pioneer; in a worker process): the mount
    guess, stamp convention, odometry source and start pose as for its replay; returns {name, values}
    or {name, error}."""
    from localization.bags import BagError
    from localization.core.occupancy_map import load_map
    from localization.eval.calibration import CalibrationError, calibrate_bag
    rb = real_bag(name)
    params = Parameters.from_yaml(config_dir() / rb.params)
    try:
        res = calibrate_bag(real_bag_path(name), load_map(rb.map), rb.scan_topic, rb.odom_topic, rb.start,
                            (params.laser_offset_x, params.laser_offset_y, params.laser_offset_yaw),
                            scan_stamp=rb.scan_stamp, scan_stamp_offset=params.scan_stamp_offset,
                            odom_frame=rb.odom_frame, base_frame=rb.base_frame)
    except (CalibrationError, BagError) as exc:
        return {"name": name, "error": str(exc)}
    return {"name": name, "values": {k: float(v) for k, v in res.values.items()}}


def calibrate_all(names, workers: int) -> dict:
    """Calibrate each real bag once (in parallel); name -> values. Raises RuntimeError on a failure."""
    names = list(names)
    if workers <= 1 or len(names) <= 1:
        out = [_calibrate_job(n) for n in names]
    else:
        with ProcessPoolExecutor(max_workers=min(workers, len(names))) as pool:
            out = list(pool.map(_calibrate_job, names))
    bad = [f"{r['name']}: {r['error']}" for r in out if "error" in r]
    if bad:
        raise RuntimeError("calibration failed: " + "; ".join(bad))
    return {r["name"]: r["values"] for r in out}


#: parameter -> (column title, format) of the calibration table
CALIBRATION_COLUMNS = {"odom_time_offset": ("time offset", "{:+.4f}s"), "odom_speed_scale": ("speed scale", "{:.4f}"),
                       "odom_yaw_rate_scale": ("yaw scale", "{:.4f}"), "odom_yaw_rate_bias": ("yaw bias", "{:+.4f}"),
                       "laser_offset_x": ("laser x", "{:.3f}m"), "lidar_scale_to_map_scale": ("range scale", "{:.4f}"),
                       "map_wall_depth": ("wall depth", "{:.3f}m")}


def calibration_table(values: dict, folds: dict, keys: dict | None = None) -> str:
    """Two rows per bag: its own calibration, and its held-out fold (the mean over the other bags)."""
    keys = HELDOUT_KEYS if keys is None else keys
    params = list(keys.values())
    lines = [f"{'bag':<9} {'':<9} " + " ".join(f"{CALIBRATION_COLUMNS[p][0]:>12}" for p in params)]
    for name, fold in folds.items():
        v = values.get(name)
        own = (" ".join(f"{CALIBRATION_COLUMNS[p][1].format(float(v[k])):>12}" for k, p in keys.items()) if v
               else "(not calibrated)")
        held = " ".join(f"{CALIBRATION_COLUMNS[p][1].format(float(fold[p])):>12}" for p in params)
        lines.append(f"{name:<9} {'alone':<9} {own}")
        lines.append(f"{'':<9} {'held-out':<9} {held}   (from {', '.join(fold['calibrated_on'])})")
    return "\n".join(lines)


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
                if job["label"] != k:
                    out.append({**job, "overrides": {**overrides, **cal, **tuning_overrides(base, point)},
                                "out": None, "plots": False, "fold": k, "point": point})
    return out


def heldout_tuning(jobs: list, folds: dict, params_file, overrides: dict, workers: int, out: Path) -> tuple:
    """Both phases (module docstring, step 7); returns (table text, summary dict, results)."""
    base = Parameters.from_yaml(params_file)
    grid = _run_all(tuning_jobs(jobs, folds, base, overrides), workers)
    scores: dict = {}
    for r in grid:
        ratio = target_ratio(r["metrics"]) if "metrics" in r else float("inf")
        scores.setdefault((r["job"]["fold"], r["job"]["point"]), []).append(ratio)
    chosen = choose_points(scores)
    finals = []
    for job in jobs:
        k = job["label"]
        finals.append({**job, "overrides": {**overrides, **fold_overrides(folds[k]),
                                            **tuning_overrides(base, chosen[k][0])},
                       "out": str(out / "heldout_tuned" / k), "plots": False})
    final = _run_all(finals, workers)
    file_point = (1.0, float(base["sigma_hit"]))
    lines = [f"{'bag':<6} {'chosen motion x':>15} {'sigma_hit':>9} {'train ratio':>11} {'file point':>10} "
             f"{'median':>7} {'p95':>6} {'along':>7} {'ratio':>6}"]
    summary = {}
    for r in final:
        k = r["job"]["label"]
        point, train = chosen[k]
        own = scores.get((k, file_point))
        own = float(np.mean(own)) if own else None
        m = r.get("metrics", {})
        median, p95, along = yardstick_errors(m)
        lines.append(f"{k:<6} {point[0]:>15.2f} {point[1]:>9.4f} {train:>11.3f} {_f(own):>10} {_f(median):>7} "
                     f"{_f(p95):>6} {_f(along, '+.3f'):>7} {_f(target_ratio(m) if m else None, '.2f'):>6}")
        summary[k] = {"motion_scale": point[0], "sigma_hit": point[1], "training_ratio": train,
                      "file_point_training_ratio": own,
                      "tuned_on": folds[k]["calibrated_on"], "metrics": m or {"error": r.get("error")},
                      "grid": {f"{pt[0]}x {pt[1]}": float(np.mean(v)) for (f, pt), v in scores.items() if f == k}}
    return "\n".join(lines), summary, grid + final


def yardstick_table(results: list) -> str:
    """Error against the yardstick: median, p95, mean along-track (m), and the agreement."""
    def row(name, m):
        ref = m.get("reference_error_m") or {}
        along = (m.get("along_track_error_m") or {}).get("mean")
        return (f"{name:<6} {_f(ref.get('median')):>7} {_f(ref.get('p95')):>6} "
                f"{'n/a' if along is None else f'{along:+.3f}':>11} {_f(ref.get('max')):>6} "
                f"{_f(m['scan_map_agreement']['median']):>9} {m.get('reference_scored', 0):>7} "
                f"{m.get('recoveries', 0):>6} {m.get('reference_false_recoveries', 0):>6}")
    return _table(f"{'bag':<6} {'median':>7} {'p95':>6} {'mean along':>11} {'max':>6} {'agreement':>9} "
                  f"{'scored':>7} {'recov':>6} {'false':>6}", results, 6, row)


# --------------------------------------------------------------------------------------------
# The Pioneer bags (step 6)
# --------------------------------------------------------------------------------------------

CONVERGED_M = 0.5  # m: converged once the estimate stays this close to the yardstick's confident poses ...
CONVERGED_HOLD_S = 5.0  # s: ... for this long
EARLY_REFERENCE_S = 10.0  # s: the yardstick must be confident this soon after the start to time convergence
END_WINDOW_S = 10.0  # s: the end of a bag, for its end agreement
HEALTHY_AGREEMENT = 0.8  # else: converged at the first scan whose agreement reaches this


class StatusCounter:
    """``on_scan`` hook: counts the scans after which ``Localizer.status`` says the scans disagree with the map."""

    def __init__(self):
        self.scans = 0
        self.holding = 0

    def __call__(self, scan, localizer) -> None:
        from localization.core.recovery import HOLDING
        self.scans += 1
        self.holding += int(localizer.status == HOLDING)


def converge_time(t, err, threshold: float, t_start: float, hold: float = CONVERGED_HOLD_S):
    """Seconds from ``t_start`` to the first time t_i from which ``err`` stays ≤ ``threshold`` for
    ``hold`` seconds, or to the end of the series if that comes sooner (None: never; NaN errors are
    not scored)."""
    t, err = np.asarray(t, dtype=float), np.asarray(err, dtype=float)
    ok = np.isfinite(err)
    t, err = t[ok], err[ok]
    if t.size == 0:
        return None
    bad = err > threshold
    # next_bad[i]: time of the first bad sample at or after i (inf: none)
    bad_t = np.where(bad, t, np.inf)
    next_bad = np.minimum.accumulate(bad_t[::-1])[::-1]
    good = ~bad & ((next_bad - t >= hold) | ~np.isfinite(next_bad))
    if not good.any():
        return None
    return float(max(t[np.argmax(good)] - t_start, 0.0))


def pioneer_metrics(res, holding: StatusCounter | None = None) -> dict:
    """Convergence, jumps, recoveries, agreement where the yardstick is confident, lost share."""
    from localization.eval import metrics as M
    p = res.options.params
    t0 = res.init_t if res.init_t is not None else (float(res.scan_t[0]) if len(res.scan_t) else 0.0)
    out = {"max_jump_m": M.max_jump(res.est_poses), "recoveries": int(res.counts.get("recoveries", 0)),
           "refused_jumps": int(res.counts.get("refused_jumps", 0))}
    if len(res.agreement_t):  # where the bag ends: do the scans fit the map there (the yardstick may not know)?
        end = np.asarray(res.agreement_t) >= res.agreement_t[-1] - END_WINDOW_S
        out["end_agreement_median"] = float(np.nanmedian(np.asarray(res.agreement)[end]))
    ref = res.reference
    conv, how, conf_agree = None, None, None
    if ref is not None and ref.good.any() and len(res.scan_t) >= 2:
        rt, rp = ref.good_track()
        order = np.argsort(res.scan_t, kind="stable")
        est = M.interpolate_poses(rt, res.scan_t[order], res.scan_poses[order])
        err = np.hypot(est[:, 0] - rp[:, 0], est[:, 1] - rp[:, 1])
        if rt[0] - t0 <= EARLY_REFERENCE_S:
            conv, how = converge_time(rt, err, CONVERGED_M, t0), "yardstick"
        if len(res.agreement_t):
            idx = np.clip(np.searchsorted(res.agreement_t, rt), 0, len(res.agreement_t) - 1)
            near = np.abs(res.agreement_t[idx] - rt) < 1e-6
            conf_agree = float(np.median(res.agreement[idx[near]])) if near.any() else None
        out["confident_scans"] = int(ref.good.sum())
        out["error_vs_yardstick_median_m"] = float(np.nanmedian(err)) if np.isfinite(err).any() else None
        out["off_share"] = out["last_off_s"] = out["false_recoveries"] = None
        if conv is not None:  # once converged: where the estimate is off (how much, until when) and far off
            since = rt >= t0 + conv
            far = np.flatnonzero(since & (err > CONVERGED_M))
            out["off_share"] = float(far.size / max(np.count_nonzero(since & np.isfinite(err)), 1))
            out["last_off_s"] = float(rt[far[-1]] - t0) if far.size else None
            out["false_recoveries"] = M.false_recoveries(rt[since], err[since], M.FALSE_RECOVERY_M, 0.0)
    if how is None:
        hit = np.flatnonzero(np.asarray(res.agreement) >= HEALTHY_AGREEMENT)
        conv = float(res.agreement_t[hit[0]] - t0) if hit.size else None
        how = f"agreement >= {HEALTHY_AGREEMENT}"
    out.update(time_to_converge_s=conv, converge_by=how, confident_agreement_median=conf_agree)
    # jumps once converged (a global start's first estimates are the mean of a spread cloud: not jumps)
    after = res.est_t >= t0 + conv if conv is not None else np.zeros(len(res.est_t), dtype=bool)
    out["max_jump_after_converge_m"] = M.max_jump(res.est_poses[after]) if conv is not None else None
    h = np.asarray(res.health, dtype=float)
    h = h[np.isfinite(h)]
    out["health_lost_share"] = float(np.mean(h < p.health_lost_floor)) if h.size else None
    out["holding_share"] = (holding.holding / holding.scans) if holding is not None and holding.scans else None
    return out


def pioneer_table(results: list) -> str:
    def row(name, m):
        pm = m.get("pioneer") or {}
        conv = pm.get("time_to_converge_s")
        start = "global" if m["initial_pose_source"].startswith("global") else "start pose"
        return (f"{name:<9} {start:<13} {'never' if conv is None else f'{conv:.1f} s':>9} "
                f"{pm.get('converge_by', ''):<16} {pm.get('max_jump_m', 0.0):>7.2f}m "
                f"{_f(pm.get('max_jump_after_converge_m')):>10} {pm.get('recoveries', 0):>5} "
                f"{'n/a' if pm.get('false_recoveries') is None else pm['false_recoveries']:>5} "
                f"{pm.get('refused_jumps', 0):>6} "
                f"{_f(pm.get('confident_agreement_median')):>9} {_f(pm.get('error_vs_yardstick_median_m')):>7} "
                f"{_f(pm.get('off_share')):>6} "
                f"{_f(pm.get('holding_share')):>8} {_f(pm.get('health_lost_share')):>8} "
                f"{_f(pm.get('end_agreement_median')):>7}")
    return _table(f"{'bag':<9} {'start':<13} {'converge':>9} {'(by)':<16} {'max jump':>8} {'after conv':>10} "
                  f"{'recov':>5} {'false':>5} {'undone':>6} "
                  f"{'agreement':>9} {'ref med':>7} {'off':>6} {'disagree':>8} {'health<':>8} {'end agr':>7}",
                  results, 9, row)


ONLY = ("heldout", "pioneer")


def build_parser() -> argparse.ArgumentParser:
    ap = args_.Parser(prog=PROG, description="Record (or reuse) the simulated Stata basement trials, "
                                 "replay them and the real RSS 2022 bags, print the results table.")
    ap.add_argument("--out", type=Path, default=Path("demo-results"), help="where the replays' outputs go "
                    "(default ./demo-results; must be empty or new unless --overwrite)")
    ap.add_argument("--overwrite", action="store_true", help="replace the files of an existing --out folder")
    ap.add_argument("--particles", type=int, help="override num_particles (default: the parameters' 2000)")
    ap.add_argument("-p", "--param", dest="overrides", action="append", default=[], metavar="NAME=VALUE",
                    type=args_.param_override,
                    help="override a parameter in every replay (repeatable; NAME:=VALUE works too)")
    ap.add_argument("--jobs", type=int, default=min(os.cpu_count() or 1, 4), help="parallel replays")
    ap.add_argument("--loop", action="store_true", help="also replay the long loop with biased odometry")
    ap.add_argument("--skip-sim", action="store_true", help="only the real bags")
    ap.add_argument("--skip-real", action="store_true", help="only the simulated trials (no RSS 2022 or Pioneer "
                    "bag)")
    ap.add_argument("--skip-fast", action="store_true", help="skip the fast trial (aligned vs unaligned)")
    ap.add_argument("--skip-perturbed", action="store_true", help="only the clean-map simulated trials (no "
                    "perturbed-world rows)")
    ap.add_argument("--skip-heldout", action="store_true", help="skip the held-out calibration of the real bags")
    ap.add_argument("--skip-pioneer", action="store_true", help="skip the Pioneer bags")
    ap.add_argument("--heldout-tuning", action="store_true", help="with the held-out replays: also choose the "
                    "motion noise and sigma_hit per fold on the other two bags (a grid, about five minutes) and "
                    "replay each bag with its fold's choice")
    ap.add_argument("--only", choices=ONLY, help="run only this part: heldout (the RSS bags with all-bags and "
                    "held-out calibration, a few minutes) or pioneer (the three Pioneer bags)")
    ap.add_argument("--duration", type=float, help="truncate the simulated trials to this many seconds")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--motion-sweep", nargs="*", type=float, metavar="SCALE",
                    help="also replay the real bags with real_params.yaml's motion noise scaled by these factors "
                         "(default 0.25 0.5 1 2)")
    return ap


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    args.skip_pioneer = args.skip_pioneer or args.skip_real  # the Pioneer bags are real bags too
    if args.only is not None:  # one part alone
        args.skip_sim = True
        args.skip_real = args.only != "heldout"
        args.skip_heldout = False  # the part's own held-out replays (RSS or Pioneer)
        args.skip_pioneer = args.only != "pioneer"
        args.motion_sweep = None
    overrides = {"random_seed": args.seed, **dict(args.overrides)}
    if args.particles is not None:
        overrides["num_particles"] = args.particles
    try:
        Parameters(overrides)
    except ValueError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    out = args.out.resolve()
    problem = args_.output_problem(out, args.overwrite, kind="folder")
    if problem:
        print(f"{PROG}: error: --out: {problem}", file=sys.stderr)
        return 1
    sim_params, real_params = config_dir() / "params.yaml", config_dir() / "real_params.yaml"

    sim_jobs, real_jobs, sweep_jobs, heldout_jobs, pioneer_jobs, pioneer_heldout_jobs = [], [], [], [], [], []
    folds, calibrated, pioneer_folds = {}, {}, {}
    heldout_bags = ([] if args.skip_heldout else
                    [*([] if args.skip_real else REAL_BAGS), *([] if args.skip_pioneer else PIONEER_BAGS)])
    if heldout_bags:
        print(f"calibrating {', '.join(heldout_bags)} (localization-calibrate, each once) for the held-out folds ...",
              file=sys.stderr)
        try:
            calibrated = calibrate_all(heldout_bags, args.jobs)
        except RuntimeError as exc:
            print(f"{PROG}: error: {exc}", file=sys.stderr)
            return 1
    if not args.skip_sim:
        names = list(REPORT_TRIALS) + (["loop_noise0.3_biased"] if args.loop else [])
        runs = {name: (name, {}, {}) for name in names}
        if not args.skip_perturbed:
            runs.update(perturbed_runs(names))
        for label, (name, changes, params) in runs.items():
            extra = {**changes, **({"duration": args.duration} if args.duration else {})}
            bag = sim_bag(name, log=lambda s: print(s, file=sys.stderr), **extra)
            world = changes.get("world")
            sim_jobs.append({"label": label, "trial": name, "bag": str(bag), "map": SIM_TRIALS[name].config.map,
                             "params_file": str(sim_params), "overrides": {**overrides, **params},
                             "out": str(out / label), "world": None if world is None else asdict(world)})
    if not args.skip_sim and not args.skip_fast:
        extra = {"duration": args.duration} if args.duration else {}
        bag = sim_bag(FAST_TRIAL, log=lambda s: print(s, file=sys.stderr), **extra)
        for label, ov in FAST_RUNS.items():
            sim_jobs.append({"label": label, "bag": str(bag), "map": SIM_TRIALS[FAST_TRIAL].config.map,
                             "params_file": str(sim_params), "overrides": {**overrides, **ov}, "out": str(out / label),
                             "fast": True})
    if not args.skip_real:
        for name, rb in REAL_BAGS.items():
            path = real_bag_path(name)
            real_jobs.append({"label": name, "bag": str(path), "map": rb.map, "params_file": str(real_params),
                              "overrides": overrides, "initial_pose": rb.start, "scan_topic": rb.scan_topic,
                              "odom_topic": rb.odom_topic, "out": str(out / name)})
        if not args.skip_heldout:
            folds = heldout_folds(REAL_BAGS, calibrated.__getitem__, heldout_keys(real_params))
            for job in real_jobs:
                heldout_jobs.append({**job, "overrides": {**overrides, **fold_overrides(folds[job["label"]])},
                                     "out": str(out / "heldout" / job["label"]), "plots": False})
        if args.motion_sweep is not None:
            scales = args.motion_sweep or [0.25, 0.5, 1.0, 2.0]
            base = Parameters.from_yaml(real_params)
            for s in scales:
                ov = dict(overrides)
                ov.update({k: float(base[k]) * s for k in MOTION_NOISE_PARAMS})
                for job in real_jobs:
                    sweep_jobs.append({**job, "overrides": ov, "out": None, "scale": s, "plots": False})

    if not args.skip_pioneer:
        for name, rb in PIONEER_BAGS.items():
            # the bag's own stamp convention (lgfloor2 stamps the first beam; pioneer_params.yaml says last_beam)
            pioneer_jobs.append({"label": name, "bag": str(real_bag_path(name)), "map": rb.map,
                                 "params_file": str(config_dir() / rb.params),
                                 "overrides": {**overrides, "scan_stamp": rb.scan_stamp}, "initial_pose": rb.start,
                                 "force_global": rb.start is None, "scan_topic": rb.scan_topic,
                                 "odom_topic": rb.odom_topic, "out": str(out / name), "pioneer": True})
        if not args.skip_heldout:
            keys = heldout_keys(PIONEER_BAGS["trace0"].params)
            pioneer_folds = heldout_folds(PIONEER_BAGS, calibrated.__getitem__, keys)
            for job in pioneer_jobs:
                fold = fold_overrides(pioneer_folds[job["label"]])
                pioneer_heldout_jobs.append({**job, "overrides": {**job["overrides"], **fold},
                                             "out": str(out / "heldout" / job["label"]), "plots": False})

    t0 = time.perf_counter()
    print(f"replaying {len(sim_jobs)} simulated trials, {len(real_jobs)} real bags, {len(heldout_jobs)} held-out "
          f"replays, {len(pioneer_jobs)} Pioneer bags and {len(pioneer_heldout_jobs)} held out "
          f"({len(sweep_jobs)} sweep runs) with {args.jobs} worker(s) ...",
          file=sys.stderr)
    groups = [sim_jobs, real_jobs, sweep_jobs, heldout_jobs, pioneer_jobs, pioneer_heldout_jobs]
    results = _run_all([j for g in groups for j in g], args.jobs)
    split, k = [], 0
    for g in groups:
        split.append(results[k:k + len(g)])
        k += len(g)
    sim_all, real_res, sweep_res, heldout_res, pioneer_res, pioneer_heldout_res = split
    fast_res = [r for r in sim_all if r["job"].get("fast")]
    sim_res = [r for r in sim_all if not r["job"].get("fast")]

    n = overrides.get("num_particles", Parameters().num_particles)
    if sim_res:
        w = STANDARD_PERTURBATION
        print(f"\nSimulated Stata basement trials (stata_basement, config/params.yaml, {n} particles); CT error in "
              "metres against the truth in the map frame (q = c + (p - c)/s: where the map shows what the car sees), "
              "over all estimates; vs world = mean error against the car's pose in the world; recov = recoveries "
              "(a challenger replaced the cloud); false = switches to a place > 1 m from the truth after the first "
              "second; 'report' = the reference lab report's mean CT error. world: map = scans drawn from the map, "
              f"perturbed = from the map with {w.boxes} boxes, {w.people} people, {w.glass_fraction:.0%} glass "
              "walls, scale s about the route's centroid (localization.sim.perturb.STANDARD_PERTURBATION); "
              "trialN_2mps_*: trial N at 2 m/s (the others at their own speeds); the filter learns the range scale "
              "while it tracks; *_fixed: the same with range_scale_estimation false (the configured scale, 1.0) "
              "(targets: mean <= 0.03, no false recovery)")
        print(sim_table(sim_res))
    if fast_res:
        print(f"\nFast trial (6-7 m/s, odometry 40 ms late, lidar sweep timing; config/params.yaml, {n} particles): "
              "error vs ground truth in metres (targets: mean <= 0.03, |mean along| <= 0.01 aligned); aligned = "
              "odometry on each scan's clock (odom_time_offset -0.04) + deskew, unaligned = both off")
        print(fast_table(fast_res))
    if real_res:
        print(f"\nReal RSS 2022 bags (basement_fixed, config/real_params.yaml, {n} particles, from the approximate "
              "start poses): agreement = median fraction of beams ending within 0.10 m of a wall; error vs the "
              "reference track (scan-to-map matches, no ground truth) in metres: median, p95, max, mean along-track "
              "(targets: median <= 0.035, p95 <= 0.08, |along| <= 0.02)")
        print(real_table(real_res))
    if sweep_res:
        print("\nReal bags: median scan-map agreement vs motion noise (real_params.yaml's motion_* scaled by)")
        scales = sorted({r["job"]["scale"] for r in sweep_res})
        print(f"{'scale':>6} " + " ".join(f"{b:>6}" for b in REAL_BAGS) + f" {'mean':>6}")
        for s in scales:
            vals = [r["metrics"]["scan_map_agreement"]["median"] if "metrics" in r else None
                    for r in sweep_res if r["job"]["scale"] == s]
            ok = [v for v in vals if v is not None]
            print(f"{s:>6.2f} " + " ".join(f"{_f(v):>6}" for v in vals)
                  + f" {_f(sum(ok) / len(ok) if ok else None):>6}")
    if heldout_res:
        print("\nCalibration of each RSS 2022 bag (localization-calibrate) and the held-out folds: each bag's "
              "calibrated values = the mean over the other two")
        print(calibration_table(calibrated, folds, heldout_keys(real_params)))
        print(f"\nRSS 2022 bags vs the yardstick (scan-to-map reference track), error in metres; {n} particles, "
              f"seed {args.seed}, from the approximate start poses")
        print("all-bags parameters (config/real_params.yaml, calibrated on all three bags, this one included):")
        print(yardstick_table(real_res))
        print("HELD-OUT (odometry timing, speed scale, yaw-rate scale and bias, laser x, range scale and wall depth "
              "calibrated on the other two bags only; the rest from real_params.yaml):")
        print(yardstick_table(heldout_res))
    tuned_summary, tuned_res = {}, []
    if heldout_res and args.heldout_tuning:
        print(f"\nchoosing the motion noise and sigma_hit per fold ({len(tuning_points())} grid points on each fold's "
              "two training bags) ...", file=sys.stderr)
        table, tuned_summary, tuned_res = heldout_tuning(real_jobs, folds, real_params, overrides, args.jobs, out)
        print("\nHELD-OUT CALIBRATION AND TUNING: the motion noise (real_params.yaml's motion_* x a factor) and "
              f"sigma_hit chosen per fold from {TUNING_GRID} on the other two bags (lowest mean of max(median/0.035, "
              "p95/0.08, |along|/0.02) there, with the fold's calibration), then the held-out bag replayed with "
              "them; train ratio = that mean for the chosen point, file point = for real_params.yaml's own (x1, "
              "its sigma_hit); error vs the yardstick in metres:")
        print(table)
    if pioneer_res:
        print(f"\nPioneer 3-DX bags (lgfloor, config/pioneer_params.yaml, {n} particles, seed {args.seed}): converge = "
              f"first time from which the estimate stays within {CONVERGED_M} m of the yardstick's confident poses for "
              f"{CONVERGED_HOLD_S:.0f} s "
              f"(or, without a confident pose in the first {EARLY_REFERENCE_S:.0f} s, the first agreement >= "
              f"{HEALTHY_AGREEMENT}); after conv = largest jump between consecutive estimates once converged; "
              "recov = recoveries (a challenger replaced the cloud, or an impossible cloud was re-spread); false = "
              "times the estimate went to a place > 1 m from the yardstick once converged; undone = sensor updates "
              "undone because they jumped to a place the scan fits no clearly better; off = share of confident "
              f"scans > {CONVERGED_M} m from the yardstick once converged; "
              "agreement = median scan-map agreement where the "
              "yardstick is confident; ref med = median error vs the yardstick there (m); disagree = share of scans "
              "after which Localizer.status said the scans disagree with the map; health< = share of sensor "
              f"updates with health below health_lost_floor; end agr = median scan-map agreement over the last "
              f"{END_WINDOW_S:.0f} s (where the yardstick may not be confident)")
        print("config/pioneer_params.yaml (its odometry calibrated on trace0: training figures for trace0):")
        print(pioneer_table(pioneer_res))
    if pioneer_heldout_res:
        print("HELD-OUT (odometry timing, speed scale, yaw-rate scale and bias and range scale calibrated on the other "
              "two Pioneer bags only; the rest from pioneer_params.yaml):")
        print(pioneer_table(pioneer_heldout_res))
        print("\nCalibration of each Pioneer bag (localization-calibrate) and the held-out folds (the mean over the "
              "other two):")
        print(calibration_table(calibrated, pioneer_folds, heldout_keys(PIONEER_BAGS["trace0"].params)))
    out.mkdir(parents=True, exist_ok=True)
    summary = {r["job"]["label"] + (f"@{r['job']['scale']}" if "scale" in r["job"] else "")
               + ("@heldout" if r["job"] in heldout_jobs or r["job"] in pioneer_heldout_jobs else ""):
               r.get("metrics", {"error": r.get("error")}) for r in results}
    if tuned_summary:
        summary["heldout_tuned"] = tuned_summary
    if folds or pioneer_folds:
        summary["heldout_folds"] = {**folds, **pioneer_folds}
        summary["calibration"] = calibrated
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(f"\nplots and metrics: {out}/<trial or bag>/(trajectory.png, error.png, metrics.json, poses.csv); "
          f"summary: {out / 'summary.json'}  [{time.perf_counter() - t0:.0f} s]")
    return 1 if any("error" in r for r in results + tuned_res) else 0


if __name__ == "__main__":
    sys.exit(main())
