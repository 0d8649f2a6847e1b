"""Quality figures of a localization run (numpy only, no ROS).

With ground truth:

- cross-track (CT) error: the Euclidean xy distance between each estimate and the true pose at
  the estimate's time (truth linearly interpolated; estimates outside the truth's time span are
  not scored) — the reference lab report's metric::

      e_k = sqrt((x̂_k − x_k)² + (ŷ_k − y_k)²)

  summarised as mean, median, 95th percentile, max and RMS;
- heading error |wrap(θ̂_k − θ_k)| (truth yaw interpolated on the unwrapped angle);
- time to converge: from the first estimate until the CT error falls below a threshold
  (0.2 m) *for good* (it stays below for the rest of the run); None if it never does;
- false recoveries: the times the estimate switches to a place more than 1 m from the truth after the
  first second, i.e. the runs of consecutive scored estimates with t ≥ t_start + 1 s and CT error > 1 m
  (a run already under way at t_start + 1 s counts too). A simulated run is scored against the truth in
  the map frame (``localization.sim.perturb``: q = c + (p − c) / s).

Without ground truth, the scan–map agreement: project every valid beam of a scan from the
estimated laser pose; the agreement is the fraction of endpoints lying within ``tolerance``
(0.10 m) of an occupied map cell. Distances are those of ``OccupancyMap.distance_to_obstacle()``
(looked up as the mask ``OccupancyMap.near_obstacle()``), between cell *centres*; the distance
from a point to the nearest occupied cell is taken as that minus half a cell, i.e. an endpoint agrees when its
cell's centre lies within
``tolerance + resolution / 2`` of an occupied cell's centre (without that half cell, a wall
face 2 cells away — 0.1008 m on the 0.0504 m Stata maps — would never count). A well-localized
car in a static mapped corridor scores close to 1; a wrong pose scores low. Beams at or beyond
``range_max`` (no return) and outside ``[range_min, range_max)`` (error codes) are not valid
beams. The scorer (``AgreementScorer``) lives in ``localization.health``, where the Localizer
also uses it to judge whether it is lost; it is re-exported here.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from localization.core.geometry import wrap_angle
from localization.core.localizer.health import AGREEMENT_TOLERANCE_M, AgreementScorer  # noqa: F401 - re-exported

CONVERGENCE_THRESHOLD_M = 0.2
FALSE_RECOVERY_M = 1.0  # m: an estimate this far from the truth is in another place
FALSE_RECOVERY_AFTER_S = 1.0  # s: estimates this soon after the start are not counted (convergence)


# --------------------------------------------------------------------------------------------
# Ground truth comparison
# --------------------------------------------------------------------------------------------


def interpolate_poses(t_query, t, poses) -> np.ndarray:
    """Poses (M, 3) at times ``t_query`` from samples (t, poses): x, y linear, yaw linear on the
    unwrapped angle. NaN outside [t[0], t[-1]]. ``t`` must be increasing."""
    t = np.asarray(t, dtype=float)
    poses = np.asarray(poses, dtype=float).reshape(-1, 3)
    tq = np.asarray(t_query, dtype=float)
    out = np.full((tq.size, 3), np.nan)
    if t.size == 0:
        return out
    inside = (tq >= t[0]) & (tq <= t[-1])
    yaw = np.unwrap(poses[:, 2])
    for j, col in enumerate((poses[:, 0], poses[:, 1], yaw)):
        out[inside, j] = np.interp(tq[inside], t, col)
    out[:, 2] = np.where(inside, wrap_angle(np.nan_to_num(out[:, 2])), np.nan)
    return out


@dataclass
class TruthComparison:
    t: np.ndarray  # (M,) times of the scored estimates
    ct_error: np.ndarray  # (M,) metres
    heading_error: np.ndarray  # (M,) |rad|


def compare_to_truth(est_t, est_poses, truth_t, truth_poses) -> TruthComparison:
    """CT and heading error of each estimate against the interpolated truth."""
    est_t = np.asarray(est_t, dtype=float)
    est_poses = np.asarray(est_poses, dtype=float).reshape(-1, 3)
    order = np.argsort(truth_t, kind="stable")
    truth = interpolate_poses(est_t, np.asarray(truth_t, dtype=float)[order], np.asarray(truth_poses)[order])
    ok = np.all(np.isfinite(truth), axis=1)
    ct = np.hypot(est_poses[ok, 0] - truth[ok, 0], est_poses[ok, 1] - truth[ok, 1])
    head = np.abs(wrap_angle(est_poses[ok, 2] - truth[ok, 2]))
    return TruthComparison(est_t[ok], ct, head)


def error_stats(errors) -> dict:
    """mean, median, p95, max, rms of an error series (NaN-free; empty -> None values)."""
    e = np.asarray(errors, dtype=float)
    if e.size == 0:
        return {"mean": None, "median": None, "p95": None, "max": None, "rms": None}
    return {"mean": float(e.mean()), "median": float(np.median(e)), "p95": float(np.percentile(e, 95)),
            "max": float(e.max()), "rms": float(np.sqrt(np.mean(e * e)))}


def time_to_converge(t, errors, threshold: float = CONVERGENCE_THRESHOLD_M, t_start: float | None = None):
    """Seconds from ``t_start`` (default the first sample) until ``errors`` drop below
    ``threshold`` and stay below it for the rest of the series; None if the last error is not
    below it."""
    t = np.asarray(t, dtype=float)
    e = np.asarray(errors, dtype=float)
    if e.size == 0 or not e[-1] < threshold:
        return None
    above = np.flatnonzero(~(e < threshold))
    t0 = t[0] if t_start is None else t_start
    t_conv = t[0] if above.size == 0 else t[above[-1] + 1]
    return float(max(0.0, t_conv - t0))


def false_recoveries(t, errors, threshold: float = FALSE_RECOVERY_M, after: float = FALSE_RECOVERY_AFTER_S,
                     t_start: float | None = None) -> int:
    """How many times the estimate goes to a place more than ``threshold`` from the truth: the runs of
    consecutive ``errors`` > ``threshold`` among the samples with t ≥ ``t_start`` + ``after`` (``t_start``:
    default the first sample's time; NaN errors are not scored)."""
    t = np.asarray(t, dtype=float)
    e = np.asarray(errors, dtype=float)
    if e.size == 0:
        return 0
    t0 = t[0] if t_start is None else t_start
    keep = (t >= t0 + after) & np.isfinite(e)
    far = e[keep] > threshold
    return int(far[0]) + int(np.count_nonzero(far[1:] & ~far[:-1])) if far.size else 0


def max_jump(poses) -> float:
    """Largest xy distance between consecutive poses (0 for fewer than two)."""
    p = np.asarray(poses, dtype=float).reshape(-1, 3)
    if len(p) < 2:
        return 0.0
    return float(np.hypot(*np.diff(p[:, :2], axis=0).T).max())


SETTLED_AGREEMENT = 0.8  # a global start has settled at the first scan with this scan–map agreement


def settled_time(from_pose: bool, t_start: float, agreement_t, agreement,
                 threshold: float = SETTLED_AGREEMENT) -> float | None:
    """When a run's estimates start to count as tracking (the time, scan clock): ``t_start`` after a start
    pose (``from_pose``); after a global start the first scan whose estimate fits the map (agreement ≥
    ``threshold``), since the estimates before are the mean of a spread cloud converging; None: never."""
    if from_pose:
        return t_start
    a = np.asarray(agreement, dtype=float)
    hit = np.flatnonzero(np.nan_to_num(a, nan=-1.0) >= threshold)
    return float(np.asarray(agreement_t, dtype=float)[hit[0]]) if hit.size else None


def jump_figures(est_t, est_poses, settled: float | None, t_start: float, from_pose: bool) -> dict:
    """The largest jump between consecutive estimates once settled (``settled_time``; a start pose: every
    estimate), when it counts from (s after ``t_start``) and over every estimate including the convergence."""
    t = np.asarray(est_t, dtype=float)
    poses = np.asarray(est_poses, dtype=float).reshape(-1, 3)
    every = max_jump(poses)
    if from_pose:
        return {"max_jump_m": every, "max_jump_from_s": 0.0, "max_jump_counts": "from the start pose",
                "max_jump_with_convergence_m": every}
    if settled is None:
        return {"max_jump_m": None, "max_jump_from_s": None,
                "max_jump_counts": f"no scan fitted the map (agreement >= {SETTLED_AGREEMENT}) after the global start",
                "max_jump_with_convergence_m": every}
    return {"max_jump_m": max_jump(poses[t >= settled]), "max_jump_from_s": float(settled - t_start),
            "max_jump_counts": f"the first scan fitting the map, agreement >= {SETTLED_AGREEMENT}, after the global "
                               "start",
            "max_jump_with_convergence_m": every}


#: how the yardstick's scans split (``yardstick_partition``), each scan in exactly one part, in this order
YARDSTICK_PARTS = {"scored": "scored",
                   "confident_unscored": "confident but no estimate then",
                   "not_confident": "matched but not confident",  # ambiguous, uncertain, off the free space, poor fit
                   "rejected": "matched but rejected",  # the smoothed track disagrees with the match
                   "unmatched": "unmatched"}


def yardstick_partition(good, usable, accepted, scored: int) -> dict:
    """The yardstick's scans split so that the parts add up to the scans: ``scored`` (confident and compared
    with an estimate: at most the confident ones), confident but not compared, then the others by how far
    their match got (accepted into the track, matched but rejected, not matched)."""
    good, usable, accepted = (np.asarray(x, dtype=bool) for x in (good, usable, accepted))
    scored = min(int(scored), int(good.sum()))
    other = ~good
    return {"scored": scored, "confident_unscored": int(good.sum()) - scored,
            "not_confident": int((other & usable & accepted).sum()),
            "rejected": int((other & usable & ~accepted).sum()),
            "unmatched": int((other & ~usable).sum())}


# --------------------------------------------------------------------------------------------
# Scan–map agreement (truth-free)
# --------------------------------------------------------------------------------------------


# AgreementScorer lives in localization.health (the Localizer scores itself with it); re-exported here.


def agreement_stats(values) -> dict:
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return {"median": None, "mean": None, "p05": None, "min": None}
    return {"median": float(np.median(v)), "mean": float(v.mean()), "p05": float(np.percentile(v, 5)),
            "min": float(v.min())}


# --------------------------------------------------------------------------------------------
# Timing
# --------------------------------------------------------------------------------------------


def timing_stats(seconds) -> dict:
    """median and 95th percentile in milliseconds of a list of durations (seconds)."""
    s = np.asarray(seconds, dtype=float) * 1e3
    if s.size == 0:
        return {"median_ms": None, "p95_ms": None, "count": 0}
    return {"median_ms": float(np.median(s)), "p95_ms": float(np.percentile(s, 95)), "count": int(s.size)}
