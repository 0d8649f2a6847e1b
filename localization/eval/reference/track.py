"""The reference track of a bag (package doc): steps 1–3 twice, then the scoring checks of step 4, one
entry per scan."""
from __future__ import annotations

import numpy as np

from localization.core.geometry import compose
from localization.core.matching import MatcherConfig
from localization.core.occupancy_map import OccupancyMap
from localization.core.scan import scan_time
from localization.eval.reference import cache as C
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
from localization.eval.reference.result import ReferenceTrack
from localization.eval.reference.smoother import Smoothed, smooth_track
from localization.eval.reference.tracker import Matches, _empty_matches


def build_reference(scans, occupancy_map: OccupancyMap, mount, odometry, initial_pose=None,
                    config: MatcherConfig | None = None, range_scale: float = 1.0, scan_stamp: str = "first_beam",
                    scan_stamp_offset: float = 0.0, noise: OdometryNoise | None = None, second_pass: bool = True,
                    log=None, deskew: bool = True, wall_depth: float = 0.0, cache: bool = True) -> ReferenceTrack:
    """The reference track of ``scans`` (``ScanData``) with ``odometry`` = (stamps (M,), reported
    twists (M, 3)) on the same clock, the laser at ``mount`` in base_link (package doc). The first
    scan is searched around ``initial_pose``, else globally. Scans with sweep timing are deskewed
    (``deskew``): in the first pass with the odometry's twist, in the second (``second_pass``: every
    scan matched again, gated on the prediction with the bag's own odometry noise) along the
    smoothed track's own motion. ``range_scale`` and ``wall_depth`` (m) turn a return z into map
    metres as the filter does: s·z − o (``lidar_scale_to_map_scale``, ``map_wall_depth``).
    ``cache``: reuse the track kept on disk for the same scans, odometry, map and arguments, else
    keep this one there (``cache`` module)."""
    arguments = dict(mount=mount, initial_pose=initial_pose, config=config, range_scale=range_scale,
                     scan_stamp=scan_stamp, scan_stamp_offset=scan_stamp_offset, noise=noise,
                     second_pass=second_pass, deskew=deskew, wall_depth=wall_depth)
    key = C.reference_key({"inputs": C.inputs_fingerprint(scans, odometry)}, occupancy_map, arguments) \
        if cache and len(scans) >= 2 else None
    return C.cached(key, lambda: _build(scans, occupancy_map, odometry, log=log, **arguments), log)


def _build(scans, occupancy_map: OccupancyMap, odometry, mount, initial_pose, config, range_scale, scan_stamp,
           scan_stamp_offset, noise, second_pass, deskew, wall_depth, log=None) -> ReferenceTrack:
    """``build_reference`` without the cache."""
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
                      base_frame: str = "base_link", log=None, wall_depth: float = 0.0,
                      cache: bool = True) -> ReferenceTrack:
    """The reference track of a bag: its scans on ``scan_topic`` and its odometry (``odom_topic``,
    else TF ``odom_frame → base_frame``); raises BagError (one line) when either is missing.
    ``cache``: reuse the track kept on disk for the same bag content, topics, map and arguments
    (without reading the bag), else keep this one there (``cache`` module)."""
    arguments = dict(mount=mount, initial_pose=initial_pose, config=config, range_scale=range_scale,
                     scan_stamp=scan_stamp, scan_stamp_offset=scan_stamp_offset, wall_depth=wall_depth)
    reading = dict(scan_topic=scan_topic, odom_topic=odom_topic, odom_frame=odom_frame, base_frame=base_frame)
    bag = C.bag_fingerprint(bag_path) if cache else None
    key = None if bag is None else C.reference_key({"bag": bag, **reading}, occupancy_map, arguments)
    return C.cached(key, lambda: _read_and_build(bag_path, occupancy_map, log=log, **reading, **arguments), log)


def _read_and_build(bag_path, occupancy_map: OccupancyMap, scan_topic, odom_topic, odom_frame, base_frame,
                    log=None, **arguments) -> ReferenceTrack:
    from localization.bags import BagError
    scans = read_scans(bag_path, scan_topic)
    odo = read_odometry(bag_path, odom_topic, odom_frame, base_frame)
    if len(scans) < 2 or len(odo[0]) < 2:
        raise BagError(f"bag {bag_path}: {len(scans)} scans on {scan_topic} and {len(odo[0])} odometry messages: "
                       "too few for a reference track")
    return build_reference(scans, occupancy_map, odometry=odo, log=log, cache=False, **arguments)


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
