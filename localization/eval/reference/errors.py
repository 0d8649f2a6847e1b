"""Along-/cross-track errors of an estimate track against a reference, the lag, and the metrics.json
figures (package doc, the last part)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from localization.core.geometry import wrap_angle
from localization.eval.metrics import FALSE_RECOVERY_M, false_recoveries, interpolate_poses
from localization.eval.reference.constants import LAG_SEARCH_S, LAG_STEP_S
from localization.eval.reference.geometry import travel_directions

if TYPE_CHECKING:
    from localization.eval.reference.result import ReferenceTrack


@dataclass
class TrackErrors:
    t: np.ndarray  # (M,) reference times scored
    position: np.ndarray  # (M,) m
    along: np.ndarray  # (M,) m, > 0 ahead
    cross: np.ndarray  # (M,) m, > 0 left
    heading: np.ndarray  # (M,) rad, signed wrap(θ̂ − θ)
    speed: np.ndarray  # (M,) m/s of the reference


def track_errors(est_t, est_poses, ref_t, ref_poses, lag: float = 0.0) -> TrackErrors:
    """Errors of the estimate track (interpolated at ``ref_t + lag``) against the reference poses."""
    ref_t = np.asarray(ref_t, dtype=float)
    ref_poses = np.asarray(ref_poses, dtype=float).reshape(-1, 3)
    direction, speed = travel_directions(ref_t, ref_poses)
    est = interpolate_poses(ref_t + lag, est_t, est_poses)
    ok = np.all(np.isfinite(est), axis=1) & np.all(np.isfinite(ref_poses), axis=1)
    e = est[ok, :2] - ref_poses[ok, :2]
    d = direction[ok]
    along = e[:, 0] * d[:, 0] + e[:, 1] * d[:, 1]
    cross = -e[:, 0] * d[:, 1] + e[:, 1] * d[:, 0]
    return TrackErrors(t=ref_t[ok], position=np.hypot(e[:, 0], e[:, 1]), along=along, cross=cross,
                       heading=wrap_angle(est[ok, 2] - ref_poses[ok, 2]), speed=speed[ok])


def best_lag(est_t, est_poses, ref_t, ref_poses, span: float = LAG_SEARCH_S, step: float = LAG_STEP_S):
    """The time shift τ (s) minimising the mean position error of x̂(t + τ) against x(t), or None."""
    best = None
    for lag in np.arange(-span, span + 0.5 * step, step):
        e = track_errors(est_t, est_poses, ref_t, ref_poses, float(lag))
        if e.position.size < max(5, 0.5 * len(ref_t)):
            continue
        m = float(e.position.mean())
        if best is None or m < best[1]:
            best = (float(lag), m)
    return None if best is None else best[0]


def lag_from_along(errors: TrackErrors):
    """Least-squares τ in e_along ≈ −v τ (s), or None without motion."""
    v = errors.speed
    den = float(np.dot(v, v))
    return None if den < 1e-6 else float(-np.dot(errors.along, v) / den)


def _stats(x) -> dict:
    x = np.asarray(x, dtype=float)
    if x.size == 0:
        return {"mean": None, "median": None}
    return {"mean": float(x.mean()), "median": float(np.median(x))}


def error_metrics(errors: TrackErrors, prefix: str = "") -> dict:
    """The metrics.json figures of a ``TrackErrors`` (``prefix`` names the reference, e.g. ``truth_``)."""
    p = errors.position
    pos = {"median": None, "p95": None, "max": None, "mean": None} if p.size == 0 else {
        "median": float(np.median(p)), "p95": float(np.percentile(p, 95)), "max": float(p.max()),
        "mean": float(p.mean())}
    h = np.degrees(np.abs(errors.heading))
    return {
        f"{prefix}along_track_error_m": _stats(errors.along),
        f"{prefix}cross_track_error_m": _stats(errors.cross),
        f"{prefix}abs_cross_track_error_m": _stats(np.abs(errors.cross)),
        f"{prefix}heading_error_deg": {"mean": float(h.mean()) if h.size else None,
                                       "median": float(np.median(h)) if h.size else None},
        f"{prefix}lag_from_along_s": lag_from_along(errors),
    }, pos


def reference_metrics(ref: ReferenceTrack, est_t, est_poses, truth_t=None, truth_poses=None) -> dict:
    """metrics.json entries scoring the estimate against the reference track (and the reference
    itself against ground truth when there is one), plus the yardstick's own figures."""
    rt, rp = ref.good_track()
    err = track_errors(est_t, est_poses, rt, rp)
    extra, pos = error_metrics(err)
    out = {
        "reference_error_m": pos,
        "along_track_error_m": extra["along_track_error_m"],
        "cross_track_error_m": extra["cross_track_error_m"],
        "abs_cross_track_error_m": extra["abs_cross_track_error_m"],
        "heading_error_ref_deg": extra["heading_error_deg"],
        "best_lag_s": best_lag(est_t, est_poses, rt, rp),
        "lag_from_along_s": extra["lag_from_along_s"],
        "reference_scans": ref.counts.get("scans", 0),
        "reference_good": ref.counts.get("good", 0),
        "reference_ambiguous": ref.counts.get("ambiguous", 0),
        "reference_low_score": ref.counts.get("low_score", 0) + ref.counts.get("unmatched", 0),
        "reference_scored": int(err.t.size),
        # times the estimate went to another place: runs of scored scans > FALSE_RECOVERY_M from the yardstick
        "reference_false_recoveries": false_recoveries(err.t, err.position, FALSE_RECOVERY_M),
        "reference_score_median": float(np.nanmedian(ref.score)) if np.isfinite(ref.score).any() else None,
        "reference_yardstick": ref.summary(),
    }
    if truth_t is not None and len(truth_t):
        order = np.argsort(truth_t, kind="stable")
        tt, tp = np.asarray(truth_t, dtype=float)[order], np.asarray(truth_poses, dtype=float)[order]
        vs = track_errors(rt, rp, rt, interpolate_poses(rt, tt, tp))
        out["reference_vs_truth_m"] = {"median": float(np.median(vs.position)) if vs.position.size else None,
                                       "p95": float(np.percentile(vs.position, 95)) if vs.position.size else None}
    return out


def truth_decomposition(est_t, est_poses, truth_t, truth_poses) -> dict:
    """Along-/cross-track error of the estimate against ground truth (metrics.json entries)."""
    order = np.argsort(truth_t, kind="stable")
    tt, tp = np.asarray(truth_t, dtype=float)[order], np.asarray(truth_poses, dtype=float)[order]
    extra, _ = error_metrics(track_errors(est_t, est_poses, tt, tp), "truth_")
    keys = ("along_track_error_m", "cross_track_error_m", "abs_cross_track_error_m", "lag_from_along_s")
    return {f"truth_{k}": extra[f"truth_{k}"] for k in keys}
