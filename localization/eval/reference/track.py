"""The reference track of a bag (package doc): steps 1–3 twice, then the scoring checks of step 4, one
entry per scan."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from localization.core.geometry import compose
from localization.core.matching import MatcherConfig
from localization.core.occupancy_map import OccupancyMap
from localization.core.scan import scan_time
from localization.eval.reference.checks import better_fit_elsewhere, odometry_consistency, pose_fit
from localization.eval.reference.constants import (
    CONSISTENCY_FIT_SHARE,
    FIT_NORMAL_PERCENTILE,
    FIT_SHARE,
    MIN_WINDOW,
    PARAM_NAMES,
    START_WINDOW,
)
from localization.eval.reference.geometry import track_twists, travel_directions
from localization.eval.reference.information import constrained_axes
from localization.eval.reference.inputs import read_odometry, read_scans, scan_beams
from localization.eval.reference.matching import track_matches
from localization.eval.reference.odometry import OdometryNoise
from localization.eval.reference.smoother import Smoothed, smooth_track
from localization.eval.reference.tracker import Matches, _empty_matches


@dataclass
class ReferenceTrack:
    """One entry per scan (package doc)."""

    t: np.ndarray  # (K,) s, the time each pose describes: mid-sweep, scan clock
    poses: np.ndarray  # (K, 3) smoothed base_link pose in the map
    laser_poses: np.ndarray  # (K, 3) poses ⊕ mount
    matched: np.ndarray  # (K, 3) the scan's own match Z_k (NaN: none usable)
    information: np.ndarray  # (K, 3, 3) Λ_k of the match (0: none)
    covariance: np.ndarray  # (K, 3, 3) of the smoothed pose
    std_along: np.ndarray  # (K,) m
    std_cross: np.ndarray  # (K,) m
    score: np.ndarray  # (K,) matcher score
    usable: np.ndarray  # (K,) bool: a match entered the smoothing
    accepted: np.ndarray  # (K,) bool: ... and agrees with the smoothed track (χ² gate)
    constrained: np.ndarray  # (K, 5) bool: the accepted match pins x, y, θ, along, across
    good: np.ndarray  # (K,) bool: scored (smoothed σ along and across ≤ one map cell, within the matches' span,
    #                   in free space, and the scan fits the map there: ``fit``)
    odometry: dict = field(default_factory=dict)  # speed/yaw-rate scale, yaw-rate bias, time offset, with σ
    counts: dict = field(default_factory=dict)
    resolution: float = 0.05  # m, of the map
    fit: np.ndarray | None = None  # (K,) share of the scan's returns ending within FIT_TOLERANCE_M of the edge

    def good_track(self) -> tuple[np.ndarray, np.ndarray]:
        return self.t[self.good], self.poses[self.good]

    @property
    def std_xy(self) -> np.ndarray:
        """(K,) m: the smoothed position's σ along its worst direction."""
        return np.sqrt(np.clip(np.linalg.eigvalsh(self.covariance[:, :2, :2])[:, -1], 0, None))

    @property
    def ambiguous(self) -> np.ndarray:
        """(K,) bool: accepted matches that leave x or y (along or across the track) free."""
        return self.accepted & ~np.all(self.constrained[:, 3:5], axis=1)

    def summary(self) -> dict:
        """The yardstick's own figures: matched share, constrained share per axis, σ along/across."""
        K = max(len(self.t), 1)

        def q(x):
            x = np.asarray(x, dtype=float)
            x = x[np.isfinite(x)]
            return {"median": float(np.median(x)), "p95": float(np.percentile(x, 95))} if x.size else \
                {"median": None, "p95": None}
        names = ("x", "y", "theta", "along", "cross")
        return {"scans": int(len(self.t)), "matched_share": float(self.accepted.sum() / K),
                "usable_share": float(self.usable.sum() / K),
                "constrained_share": {n: float(self.constrained[:, i].sum() / K) for i, n in enumerate(names)},
                "std_along_m": q(self.std_along), "std_cross_m": q(self.std_cross),
                "scored_share": float(self.good.sum() / K),
                "outside_free_space_share": float(self.counts.get("outside_free_space", 0) / K),
                "poor_fit_share": float(self.counts.get("poor_fit", 0) / K),
                "odometry_inconsistent_share": float(self.counts.get("odometry_inconsistent", 0) / K),
                "better_fit_elsewhere_share": float(self.counts.get("better_fit_elsewhere", 0) / K),
                "odometry": dict(self.odometry)}


def build_reference(scans, occupancy_map: OccupancyMap, mount, odometry, initial_pose=None,
                    config: MatcherConfig | None = None, range_scale: float = 1.0, scan_stamp: str = "first_beam",
                    scan_stamp_offset: float = 0.0, noise: OdometryNoise | None = None, second_pass: bool = True,
                    log=None, deskew: bool = True, wall_depth: float = 0.0) -> ReferenceTrack:
    """The reference track of ``scans`` (``ScanData``) with ``odometry`` = (stamps (M,), reported
    twists (M, 3)) on the same clock, the laser at ``mount`` in base_link (package doc). The first
    scan is searched around ``initial_pose``, else globally. Scans with sweep timing are deskewed
    (``deskew``): in the first pass with the odometry's twist, in the second (``second_pass``: every
    scan matched again, gated on the prediction with the bag's own odometry noise) along the
    smoothed track's own motion. ``range_scale`` and ``wall_depth`` (m) turn a return z into map
    metres as the filter does: s·z − o (``lidar_scale_to_map_scale``, ``map_wall_depth``)."""
    say = log or (lambda *_: None)
    t = np.array([scan_time(s, scan_stamp, scan_stamp_offset) for s in scans], dtype=float)
    odo_t = np.asarray(odometry[0], dtype=float)
    odo_tw = np.asarray(odometry[1], dtype=float).reshape(-1, 3)
    order = np.argsort(odo_t, kind="stable")
    odo = (odo_t[order], odo_tw[order])
    if len(scans) < 2 or len(odo[0]) < 2:
        raise ValueError(f"a reference track needs scans and odometry ({len(scans)} scans, {len(odo[0])} odometry)")
    noise = noise or OdometryNoise()
    mt = track_matches(occupancy_map, scans, t, odo, mount, initial_pose, config, range_scale, noise, log, deskew,
                       wall_depth=wall_depth)
    say(f"matched {int(mt.usable.sum())} of {len(scans)} scans ({mt.start}); smoothing ...")
    if mt.usable.sum() < 3:
        say(f"reference track: only {int(mt.usable.sum())} scans matched the map ({mt.start}): nothing to score")
        return _unmatched(t, mt, mount, occupancy_map.resolution)
    try:
        sm = smooth_track(t, mt, odo, noise, log)
        if second_pass:
            # the second pass: the odometry's time offset, speed scale and noise as the bag measured
            # them, deskewed along the smoothed track's own motion, from the smoothed start
            noise2 = noise.scaled(sm.scales["odo_x"], sm.scales["odo_y"], sm.scales["odo_theta"])
            start = sm.poses[int(np.argmax(sm.accepted))] if initial_pose is None else initial_pose
            k_start = int(np.argmax(sm.accepted)) if initial_pose is None else 0
            mt2 = track_matches(occupancy_map, scans[k_start:], t[k_start:], odo, mount, start, config, range_scale,
                                noise2, log, deskew, twists=track_twists(t, sm.poses)[k_start:],
                                start_window=START_WINDOW if initial_pose is not None else MIN_WINDOW,
                                odometry_fit=tuple(sm.params), wall_depth=wall_depth)
            mt2.start = mt.start
            mt = _prepend(mt2, k_start, sm.poses[:k_start]) if k_start else mt2
            say(f"second pass: {int(mt.usable.sum())} of {len(scans)} scans matched")
            sm = smooth_track(t, mt, odo, noise, log)
    except (ValueError, np.linalg.LinAlgError) as exc:
        say(f"reference track: {exc}; nothing to score")
        return _unmatched(t, mt, mount, occupancy_map.resolution)
    fit_beams = scan_beams(scans, False, wall_depth / range_scale)
    fit = pose_fit(occupancy_map, fit_beams, sm.poses, mount, range_scale)
    # the nominal noise model, not the bag's own scales: those are inflated by the very stretches checked here
    consistent, skid = odometry_consistency(t, sm.poses, odo, sm.params[0], sm.params[1], noise,
                                            occupancy_map.resolution)
    elsewhere = better_fit_elsewhere(occupancy_map, fit_beams, t, sm.poses, fit, mount, range_scale)
    return _track(t, mt, sm, mount, occupancy_map, fit, consistent, skid, elsewhere)


def reference_for_bag(bag_path, occupancy_map: OccupancyMap, scan_topic: str, mount, *, odom_topic: str = "/odom",
                      initial_pose=None, config: MatcherConfig | None = None, range_scale: float = 1.0,
                      scan_stamp: str = "first_beam", scan_stamp_offset: float = 0.0, odom_frame: str = "odom",
                      base_frame: str = "base_link", log=None, wall_depth: float = 0.0) -> ReferenceTrack:
    """The reference track of a bag: its scans on ``scan_topic`` and its odometry (``odom_topic``,
    else TF ``odom_frame → base_frame``); raises BagError (one line) when either is missing."""
    from localization.bags import BagError
    scans = read_scans(bag_path, scan_topic)
    odo = read_odometry(bag_path, odom_topic, odom_frame, base_frame)
    if len(scans) < 2 or len(odo[0]) < 2:
        raise BagError(f"bag {bag_path}: {len(scans)} scans on {scan_topic} and {len(odo[0])} odometry messages: "
                       "too few for a reference track")
    return build_reference(scans, occupancy_map, mount, odo, initial_pose, config, range_scale, scan_stamp,
                           scan_stamp_offset, log=log, wall_depth=wall_depth)


def _prepend(mt: Matches, k: int, poses) -> Matches:
    """The matches of scans k… with the first k scans unmatched (their poses ``poses``)."""
    out = _empty_matches(k + len(mt.usable))
    for key in out:
        out[key][k:] = getattr(mt, key)
    out["filtered"][:k] = poses
    return Matches(start=mt.start, **out)


def _directions(t, poses) -> np.ndarray:
    d, _ = travel_directions(t, poses)
    return d


def _track(t, mt: Matches, sm: Smoothed, mount, occupancy_map: OccupancyMap, fit=None,
           consistent=None, skid=None, elsewhere=None) -> ReferenceTrack:
    res = occupancy_map.resolution
    K = len(t)
    d = _directions(t, sm.poses)
    nrm = np.stack([-d[:, 1], d[:, 0]], axis=1)
    Sxy = sm.covariance[:, :2, :2]
    std_along = np.sqrt(np.clip(np.einsum("ki,kij,kj->k", d, Sxy, d), 0, None))
    std_cross = np.sqrt(np.clip(np.einsum("ki,kij,kj->k", nrm, Sxy, nrm), 0, None))
    constrained = np.zeros((K, 5), dtype=bool)
    for k in np.flatnonzero(sm.accepted):
        constrained[k] = constrained_axes(mt.information[k], mt.median_range[k], res, d[k])
    acc = np.flatnonzero(sm.accepted)
    inside = np.zeros(K, dtype=bool)
    if acc.size:
        inside[acc[0]:acc[-1] + 1] = True
    free = occupancy_map.is_free(sm.poses[:, :2])  # a smoothed pose in a wall: the track is wrong there
    # the scan must fit the map at the smoothed pose: half the bag's normal fit or more (a changed room, or a
    # track carried off by the odometry or a look-alike match, is not a pose to score against)
    fit = np.full(K, np.nan) if fit is None else np.asarray(fit, dtype=float)
    normal = fit[sm.accepted & np.isfinite(fit)]
    fit_or_0 = np.nan_to_num(fit, nan=0.0)
    normal_fit = np.percentile(normal, FIT_NORMAL_PERCENTILE) if normal.size else None  # None: no fit known
    fits = np.ones(K, dtype=bool) if normal_fit is None else fit_or_0 >= FIT_SHARE * normal_fit
    consistent = np.ones(K, dtype=bool) if consistent is None else np.asarray(consistent, dtype=bool)
    if normal_fit is not None and skid is not None:  # a skid: the odometry stopped short where the scans fit well
        consistent = consistent | (np.asarray(skid, dtype=bool) & (fit_or_0 >= CONSISTENCY_FIT_SHARE * normal_fit))
    elsewhere = np.zeros(K, dtype=bool) if elsewhere is None else np.asarray(elsewhere, dtype=bool)
    good = inside & free & fits & consistent & ~elsewhere & (std_along <= res) & (std_cross <= res)
    odometry = {n: float(v) for n, v in zip(PARAM_NAMES, sm.params)}
    odometry.update({f"{n}_sigma": float(v) for n, v in zip(PARAM_NAMES, sm.param_sigma)})
    odometry["noise_scales"] = {k: float(v) for k, v in sm.scales.items()}
    counts = {"scans": int(K), "good": int(good.sum()), "usable": int(mt.usable.sum()),
              "accepted": int(sm.accepted.sum()), "rejected": int((mt.usable & ~sm.accepted).sum()),
              "ambiguous": int((sm.accepted & ~np.all(constrained[:, 3:5], axis=1)).sum()),
              "low_score": int((mt.usable & ~sm.accepted).sum()), "unmatched": int((~mt.usable).sum()),
              "outside_free_space": int((~free).sum()), "poor_fit": int((~fits).sum()),
              "odometry_inconsistent": int((~consistent).sum()), "better_fit_elsewhere": int(elsewhere.sum()),
              "start": mt.start, "function_evaluations": sm.nfev}
    return ReferenceTrack(t=t, poses=sm.poses, laser_poses=compose(sm.poses, np.asarray(mount, dtype=float)),
                          matched=np.where(mt.usable[:, None], mt.poses, np.nan), information=mt.information,
                          covariance=sm.covariance, std_along=std_along, std_cross=std_cross, score=mt.score,
                          usable=mt.usable, accepted=sm.accepted, constrained=constrained, good=good,
                          odometry=odometry, counts=counts, resolution=res, fit=fit)


def _unmatched(t, mt: Matches, mount, res: float) -> ReferenceTrack:
    K = len(t)
    nan = np.full((K, 3), np.nan)
    counts = {"scans": int(K), "good": 0, "usable": int(mt.usable.sum()), "accepted": 0, "rejected": 0,
              "ambiguous": 0, "low_score": 0, "unmatched": int(K), "start": mt.start}
    return ReferenceTrack(t=t, poses=nan, laser_poses=nan.copy(), matched=nan.copy(), information=mt.information,
                          covariance=np.full((K, 3, 3), np.nan), std_along=np.full(K, np.nan),
                          std_cross=np.full(K, np.nan), score=mt.score, usable=np.zeros(K, dtype=bool),
                          accepted=np.zeros(K, dtype=bool), constrained=np.zeros((K, 5), dtype=bool),
                          good=np.zeros(K, dtype=bool), odometry={}, counts=counts, resolution=res)
