"""A reference track for any bag (no ground truth needed) and the along-/cross-track error of an
estimate against it.

Reference track: every scan matched to the map by the correlative matcher
(``localization.core.matching``), seeded by the filter's estimate at the scan's time (or, without
one, by the previous good match carried forward at its velocity). Each match keeps its score,
covariance and ``ambiguous`` flag; only *good* matches (not ambiguous, score ≥ ``min_score``, and
not on the search window's edge when the deskew pass re-matches) are trusted. A scan swept over
``time_increment`` > 0 is timed at the middle of its sweep (stamp + ½ (n − 1) time_increment): the
pose a rigid match of a skewed scan recovers.

Errors of an estimate track x̂(t) against a reference x(t) (the estimate interpolated at the
reference's times), with t̂ the unit direction of travel of the reference (its velocity,
its heading where it stands still) and n̂ = t̂ rotated by +90°::

    e = (x̂ − x, ŷ − y)       position error, |e|
    e_along = e · t̂          > 0: the estimate is ahead of the car, < 0 behind
    e_cross = e · n̂          > 0: left of the car's path

Lag: the time shift τ of the estimate track that minimises the mean position error,
``mean_k |x̂(t_k + τ) − x(t_k)|`` (τ > 0: the estimate describes the car τ seconds late), and, from
the along-track error alone, the least-squares fit e_along ≈ −v τ (v the reference speed).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from localization.bags import BagError, open_bag
from localization.core.geometry import compose, integrate_twists, relative, wrap_angle
from localization.core.matching import CorrelativeMatcher, MatcherConfig
from localization.core.occupancy_map import OccupancyMap
from localization.core.scan import ScanData, beam_angles, clean_ranges, scan_time
from localization.eval.metrics import interpolate_poses
from localization.ros.conversions import scan_from_msg, twist_from_odometry

MIN_SCORE = 0.3  # mean endpoint likelihood below which a match is not trusted
LAG_SEARCH_S = 0.25  # ± seconds searched for the best lag
LAG_STEP_S = 0.002
STANDSTILL_SPEED = 0.1  # m/s: below, the direction of travel is the reference heading


@dataclass
class ReferenceTrack:
    """One entry per scan (NaN poses where the scan could not be matched)."""

    t: np.ndarray  # (K,) s, time each pose describes (mid-sweep)
    poses: np.ndarray  # (K, 3) base_link in the map
    laser_poses: np.ndarray  # (K, 3)
    score: np.ndarray  # (K,) mean endpoint likelihood
    std_xy: np.ndarray  # (K,) m, std along the worst direction
    ambiguous: np.ndarray  # (K,) bool
    good: np.ndarray  # (K,) bool: trusted matches
    counts: dict = field(default_factory=dict)

    def good_track(self) -> tuple[np.ndarray, np.ndarray]:
        return self.t[self.good], self.poses[self.good]


# --------------------------------------------------------------------------------------------
# Reading a bag
# --------------------------------------------------------------------------------------------


def read_scans(bag_path, scan_topic: str) -> list[ScanData]:
    with open_bag(bag_path) as bag:
        if scan_topic not in bag.topic_infos:
            raise BagError(f"scan topic {scan_topic} not in bag {bag_path}")
        return [scan_from_msg(m.msg) for m in bag.messages([scan_topic])]


def read_odometry(bag_path, odom_topic: str) -> tuple[np.ndarray, np.ndarray]:
    """Stamps (M,) and reported twists (M, 3: vx, vy, ωz) of the odometry, in stamp order."""
    with open_bag(bag_path) as bag:
        if odom_topic not in bag.topic_infos:
            raise BagError(f"odometry topic {odom_topic} not in bag {bag_path}")
        tw = [twist_from_odometry(m.msg) for m in bag.messages([odom_topic])]
    t = np.array([d.stamp for d in tw], dtype=float)
    v = np.array([[d.vx, d.vy, d.wz] for d in tw], dtype=float).reshape(-1, 3)
    order = np.argsort(t, kind="stable")
    return t[order], v[order]


# --------------------------------------------------------------------------------------------
# Dead reckoning
# --------------------------------------------------------------------------------------------


def dead_reckon(odom_t, twist, query_t, a=1.0, b=1.0, c=0.0) -> np.ndarray:
    """Odometry pose (odom frame, starting at 0 at the first stamp) at ``query_t`` (odometry
    clock), twist k (corrected: a·(vx, vy), b·ωz + c) held over (t_{k−1}, t_k]; the last twist
    is extrapolated, the pose is held before the first stamp."""
    t = np.asarray(odom_t, dtype=float)
    tw = np.asarray(twist, dtype=float)
    vx, vy, wz = a * tw[:, 0], a * tw[:, 1], b * tw[:, 2] + c
    M = len(t)
    poses = np.zeros((M, 3))
    if M > 1:
        steps = integrate_twists(vx[1:], vy[1:], wz[1:], np.diff(t))
        for k in range(1, M):  # M ~ 50 per second of bag: cheap
            poses[k] = compose(poses[k - 1], steps[k - 1])
    q = np.asarray(query_t, dtype=float)
    k = np.clip(np.searchsorted(t, q, side="left"), 1, max(M - 1, 1))  # the period (t_{k-1}, t_k] holding q
    if M < 2:
        return np.zeros((q.size, 3))
    dt = np.clip(q - t[k - 1], 0.0, None)
    return compose(poses[k - 1], integrate_twists(vx[k], vy[k], wz[k], dt))


# --------------------------------------------------------------------------------------------
# Building the reference track
# --------------------------------------------------------------------------------------------


def build_reference(scans, occupancy_map: OccupancyMap, mount, est_t=None, est_poses=None,
                    initial_pose=None, config: MatcherConfig | None = None, range_scale: float = 1.0,
                    min_score: float = MIN_SCORE, initial_window=(1.0, 0.5), odometry=None,
                    deskew: bool = True, deskew_pass: bool = True) -> ReferenceTrack:
    """Match every scan. Seeds: the estimate track (``est_t``, ``est_poses``) at the scan's time
    when given; else (or when that match is not good) the track so far carried forward at the
    velocity of its last two poses (with ``odometry`` = (stamps, twists (M, 3)): moved on by the
    dead-reckoned odometry instead); the very first scan without either: ``initial_pose``
    searched in the wider ``initial_window`` (m, rad). The track so far follows the good matches;
    through an ambiguous one it keeps the match across its degenerate direction and the
    prediction along it (a corridor: the match's cross-track position and heading, the predicted
    progress).

    Deskew (scans with ``time_increment`` > 0, ``deskew``): every beam is moved to the middle of
    the sweep along the track's own motion (``integrate_twist`` over each beam's time offset) —
    in the first pass with the twist of the track's last two poses, then (``deskew_pass``) in a
    second pass near each first-pass pose with the twist from both neighbours."""
    matcher = CorrelativeMatcher(occupancy_map, config)
    mount = tuple(float(v) for v in mount)
    K = len(scans)
    t = np.array([scan_time(s) for s in scans], dtype=float)
    poses = np.full((K, 3), np.nan)
    lasers = np.full((K, 3), np.nan)
    score = np.full(K, np.nan)
    std = np.full(K, np.nan)
    amb = np.zeros(K, dtype=bool)
    good = np.zeros(K, dtype=bool)
    chain = np.full((K, 3), np.nan)  # the track the seeds follow
    has_est = est_t is not None and len(est_t) > 0
    est_at = interpolate_poses(t, est_t, est_poses) if has_est else np.full((K, 3), np.nan)
    angles_cache: dict = {}
    last = []  # the last two (t, chain pose, scan index)
    odo = dead_reckon(odometry[0], odometry[1], t) if odometry is not None and len(odometry[0]) > 1 else None
    no_match = 0
    beams = []
    for k, scan in enumerate(scans):
        key = (np.asarray(scan.ranges).size, scan.angle_min, scan.angle_max, scan.angle_increment)
        if key not in angles_cache:
            angles_cache[key] = beam_angles(*key)
        ranges = clean_ranges(scan.ranges, scan.range_min, scan.range_max)
        beams.append((ranges, angles_cache[key]))
        n = ranges.size
        skew = {}
        if deskew and scan.time_increment > 0 and len(last) == 2 and 0 < last[1][0] - last[0][0] <= 0.2:
            skew = {"beam_dt": (np.arange(n) - 0.5 * (n - 1)) * scan.time_increment,
                    "twist": relative(last[0][1], last[1][1]) / (last[1][0] - last[0][0])}
        prediction = None
        if last and odo is not None:
            prediction = compose(last[-1][1], relative(odo[last[-1][2]], odo[k]))
        elif last:
            prediction = _carry_forward(last, t[k])
        seeds = []
        if np.all(np.isfinite(est_at[k])):
            seeds.append((est_at[k], None))
        if prediction is not None:
            seeds.append((prediction, None))
        elif initial_pose is not None and not seeds:
            seeds.append((np.asarray(initial_pose, dtype=float), initial_window))
        best = None
        for seed, window in seeds:
            wxy, wth = window if window is not None else (None, None)
            r = matcher.match(ranges, angles_cache[key], mount, seed, wxy, wth, range_scale, **skew)
            if r is None:
                continue
            ok = (not r.ambiguous) and r.score >= min_score
            if best is None or (ok and not best[1]) or (ok == best[1] and r.score > best[0].score):
                best = (r, ok)
            if ok:
                break
        if best is None:
            no_match += 1
            continue
        r, ok = best
        poses[k], lasers[k], score[k], std[k] = r.pose, r.laser_pose, r.score, r.std_xy_max
        amb[k], good[k] = r.ambiguous, ok
        if ok:
            chain[k] = r.pose
        elif r.ambiguous and r.score >= min_score and prediction is not None:
            chain[k] = _fuse_along_degenerate(r.pose, r.covariance, prediction)
        if np.all(np.isfinite(chain[k])):
            last = (last + [(t[k], chain[k], k)])[-2:]

    if deskew and deskew_pass and any(s.time_increment > 0 for s in scans):
        twists = _track_twists(t, chain)
        for k, scan in enumerate(scans):
            n = np.asarray(scan.ranges).size
            if not (np.all(np.isfinite(poses[k])) and np.all(np.isfinite(twists[k])) and scan.time_increment > 0):
                continue
            beam_dt = (np.arange(n) - 0.5 * (n - 1)) * scan.time_increment
            r = matcher.match(*beams[k], mount, poses[k], DESKEW_WINDOW[0], DESKEW_WINDOW[1], range_scale,
                              beam_dt=beam_dt, twist=twists[k])
            if r is None:
                continue
            poses[k], lasers[k], score[k] = r.pose, r.laser_pose, r.score
            good[k] = good[k] and not r.at_window_edge and r.score >= min_score

    counts = {"scans": int(K), "good": int(good.sum()), "ambiguous": int(amb.sum()),
              "low_score": int(np.sum(~good & ~amb & np.isfinite(score))), "unmatched": int(no_match)}
    return ReferenceTrack(t=t, poses=poses, laser_poses=lasers, score=score, std_xy=std, ambiguous=amb, good=good,
                          counts=counts)


DESKEW_WINDOW = (0.15, 0.05)  # m, rad: the second (deskewed) pass searches this close to the first
MAX_SPEED, MAX_YAW_RATE = 10.0, 4.0  # m/s, rad/s: the track's carried-forward velocity is clipped to these


def _fuse_along_degenerate(pose, covariance, prediction):
    """The match across its worst-determined direction, the prediction along it."""
    w, v = np.linalg.eigh(covariance[:2, :2])
    u = v[:, int(np.argmax(w))]
    out = np.array(pose, dtype=float)
    out[:2] += u * float(np.dot(np.asarray(prediction[:2]) - out[:2], u))
    if np.hypot(*(out[:2] - np.asarray(prediction[:2]))) > 0.2:  # the match disagrees across the corridor too
        return np.array(prediction, dtype=float)
    return out


def _track_twists(t, poses) -> np.ndarray:
    """Base-frame twist (vx, vy, ωz) at each entry of a pose track (NaN rows skipped) from its
    neighbours (central differences within 0.2 s); NaN where there is none."""
    out = np.full((len(t), 3), np.nan)
    ok = np.flatnonzero(np.all(np.isfinite(poses), axis=1))
    if ok.size < 2:
        return out
    for n, k in enumerate(ok):
        a, b = ok[max(n - 1, 0)], ok[min(n + 1, ok.size - 1)]
        dt = t[b] - t[a]
        if 0 < dt <= 0.2:
            out[k] = relative(poses[a], poses[b]) / dt
    return out


def _carry_forward(last, t):
    """The last pose moved on to time t at the velocity of the last two."""
    t1, p1 = last[-1][:2]
    if len(last) < 2:
        return np.array(p1, dtype=float)
    t0, p0 = last[-2][:2]
    dt = t1 - t0
    if dt <= 0:
        return np.array(p1, dtype=float)
    rate = np.array([p1[0] - p0[0], p1[1] - p0[1], float(wrap_angle(p1[2] - p0[2]))]) / dt
    speed = math.hypot(rate[0], rate[1])
    if speed > MAX_SPEED:
        rate[:2] *= MAX_SPEED / speed
    rate[2] = float(np.clip(rate[2], -MAX_YAW_RATE, MAX_YAW_RATE))
    out = np.asarray(p1, dtype=float) + rate * (t - t1)
    out[2] = float(wrap_angle(out[2]))
    return out


def reference_for_bag(bag_path, occupancy_map: OccupancyMap, scan_topic: str, mount, est_t=None, est_poses=None,
                      initial_pose=None, config: MatcherConfig | None = None,
                      range_scale: float = 1.0) -> ReferenceTrack:
    return build_reference(read_scans(bag_path, scan_topic), occupancy_map, mount, est_t, est_poses, initial_pose,
                           config, range_scale)


# --------------------------------------------------------------------------------------------
# Along-track / cross-track errors
# --------------------------------------------------------------------------------------------


def travel_directions(t, poses, standstill: float = STANDSTILL_SPEED) -> tuple[np.ndarray, np.ndarray]:
    """Unit direction of travel (K, 2) and speed (K,) of a pose track (central differences;
    the heading where the speed is below ``standstill``)."""
    t = np.asarray(t, dtype=float)
    p = np.asarray(poses, dtype=float).reshape(-1, 3)
    K = len(t)
    d = np.stack([np.cos(p[:, 2]), np.sin(p[:, 2])], axis=1) if K else np.zeros((0, 2))
    speed = np.zeros(K)
    if K >= 2:
        i0 = np.clip(np.arange(K) - 1, 0, K - 1)
        i1 = np.clip(np.arange(K) + 1, 0, K - 1)
        dt = t[i1] - t[i0]
        dxy = p[i1, :2] - p[i0, :2]
        with np.errstate(invalid="ignore", divide="ignore"):
            vel = dxy / dt[:, None]
        speed = np.where(dt > 0, np.hypot(vel[:, 0], vel[:, 1]), 0.0)
        moving = speed > standstill
        d[moving] = vel[moving] / speed[moving, None]
    return d, speed


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
    itself against ground truth when there is one)."""
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
        "reference_score_median": float(np.nanmedian(ref.score)) if np.isfinite(ref.score).any() else None,
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


# --------------------------------------------------------------------------------------------
# Plot
# --------------------------------------------------------------------------------------------


def plot_reference(path, ref: ReferenceTrack, est_t, est_poses, t0: float = 0.0, title: str = ""):
    """Along- and cross-track error vs time (good matches), ambiguous scans marked."""
    from localization.eval.plots import _pyplot
    plt = _pyplot()
    rt, rp = ref.good_track()
    err = track_errors(est_t, est_poses, rt, rp)
    fig, axes = plt.subplots(2, 1, figsize=(10, 6), sharex=True)
    ax = axes[0]
    ax.plot(err.t - t0, err.along, color="tab:red", lw=1.0, label="along-track (> 0 ahead)")
    ax.plot(err.t - t0, err.cross, color="tab:blue", lw=1.0, label="cross-track (> 0 left)")
    ax.axhline(0.0, color="gray", lw=0.6)
    amb_t = ref.t[ref.ambiguous] - t0
    if amb_t.size:
        ax.plot(amb_t, np.zeros_like(amb_t), "|", color="tab:orange", ms=10, label="ambiguous match")
    ax.set_ylabel("error vs reference (m)")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title(title)
    ax = axes[1]
    ax.plot(err.t - t0, err.position, color="black", lw=1.0, label="position error")
    ax.plot(ref.t - t0, ref.std_xy, color="tab:green", lw=0.8, alpha=0.7, label="reference std (worst direction)")
    ax.set_ylabel("m")
    ax.set_ylim(bottom=0)
    ax.legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel("time since start (s)")
    for a in axes:
        a.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
