"""Simulated drives fed to the ``Localizer``, shared by the benchmarks (robustness, large map, models,
ablation): the benchmarks' parameters, a recording fed in stamp order, its cross-track errors and
settle time, and the Stata basement loop as a scenario (a start anywhere along it, or along another
closed route)."""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace

import numpy as np

from localization.core.localizer import Localizer
from localization.core.parameters import Parameters
from localization.core.paths import config_dir
from localization.eval import metrics as M
from localization.eval.datasets import _LOOP, trial_config
from localization.eval.feed import Feeder, FeedLog, recording_events
from localization.sim import Recording, SimConfig, densify

TARGET_M = 0.3
STATA = "stata_basement"


def bench_params(**overrides) -> Parameters:
    """The simulator's shipped parameters (config/params.yaml), seeded, plus ``overrides``."""
    values = dict(random_seed=0)
    values.update(overrides)
    return Parameters.from_yaml(config_dir() / "params.yaml", **values)


def replace_params(params: Parameters, **kw) -> Parameters:
    values = dict(params)
    values.update(kw)
    return Parameters(values)


# --------------------------------------------------------------------------------------------
# Feeding a recording to the Localizer (in stamp order, odometry before a scan at the same time)
# --------------------------------------------------------------------------------------------


@dataclass
class RunResult:
    est_t: np.ndarray
    est_poses: np.ndarray
    health_t: np.ndarray
    health: np.ndarray
    recoveries: int
    filter_time: float  # wall seconds inside the Localizer
    messages: int
    cpu_time: float = 0.0  # process CPU seconds of the run (robust to other processes on the machine)
    log: FeedLog | None = None  # everything the Feeder recorded (particle counts, sensor-update times, ...)


def run_recording(rec: Recording, localizer: Localizer, init: str = "pose", t_offset: float = 0.0) -> RunResult:
    """Feed one recording to ``localizer``. ``init``: "pose" (the recording's initial pose),
    "global" (uniform spread), or "none" (keep the localizer's state: a continued drive)."""
    t_start = float(rec.odometry.t[0] + t_offset)
    if init == "pose":
        localizer.set_initial_pose(rec.initial_pose, None, t_start)
    elif init == "global":
        localizer.initialize_global(t_start)
    rec0 = localizer.recoveries
    cpu0 = time.process_time()
    log = Feeder(localizer).feed(recording_events(rec, t_offset))
    est_t, est_p = log.estimates()
    return RunResult(est_t, est_p, np.asarray(log.health_t), np.asarray(log.health), localizer.recoveries - rec0,
                     log.filter_time, log.counts["odometry"] + log.counts["scans"], time.process_time() - cpu0, log)


def ct_errors(rec: Recording, run: RunResult, t_offset: float = 0.0) -> M.TruthComparison:
    return M.compare_to_truth(run.est_t, run.est_poses, rec.truth_t + t_offset, rec.truth_poses)


def settle_time(cmp: M.TruthComparison, t_from: float, threshold: float = TARGET_M):
    """Seconds from ``t_from`` until the CT error is below ``threshold`` for good (None: never)."""
    sel = cmp.t >= t_from
    return M.time_to_converge(cmp.t[sel], cmp.ct_error[sel], threshold, t_from)


# --------------------------------------------------------------------------------------------
# Scenarios on the basement loop
# --------------------------------------------------------------------------------------------


def loop_path(route=None) -> np.ndarray:
    """The basement loop (or ``route``, a closed waypoint route) every 5 cm."""
    return densify(_LOOP if route is None else route, 0.05, closed=True)


def loop_pose(index: int, route=None) -> tuple:
    """A pose on the loop's (or ``route``'s) centre line, heading along it."""
    path = loop_path(route)
    i = index % len(path)
    d = path[(i + 5) % len(path)] - path[i]
    return (float(path[i, 0]), float(path[i, 1]), float(math.atan2(d[1], d[0])))


def loop_config(start_index: int, duration: float, seed: int, route=None, map_name: str = STATA, **kw) -> SimConfig:
    """The basement loop trial (or the closed ``route`` through map ``map_name``) from point
    ``start_index`` of the 5 cm path: 2 m/s, odometry noise 0.1, no bias."""
    base = trial_config("loop_noise0.3_biased")
    if route is not None:
        base = replace(base, map=map_name, waypoints=tuple(map(tuple, np.asarray(route, dtype=float).tolist())))
    return replace(base, start=loop_pose(start_index, route), duration=duration, seed=seed, speed=2.0,
                   odom_noise=0.1, speed_scale=1.0, yaw_rate_bias=0.0, initial_offset=(0.0, 0.0, 0.0), **kw)
