"""Step 4 of the package doc, where a scan is scored: the scan fits the map at its smoothed pose, the
track follows the odometry, and no place near the track fits the scan clearly better."""
from __future__ import annotations

import numpy as np

from localization.core.geometry import compose, relative
from localization.core.matching import CorrelativeMatcher, MatcherConfig, endpoints_base
from localization.core.occupancy_map import OccupancyMap
from localization.eval.reference.constants import (
    CONSISTENCY_SIGMAS,
    CONSISTENCY_WINDOW_S,
    ELSEWHERE_BEAMS,
    ELSEWHERE_EVERY_S,
    ELSEWHERE_MARGIN,
    ELSEWHERE_WINDOW,
    FIT_TOLERANCE_M,
    STANDSTILL_SPEED,
    STANDSTILL_TURN,
)
from localization.eval.reference.information import edge_distance
from localization.eval.reference.inputs import ScanBeams
from localization.eval.reference.odometry import OdometryNoise, dead_reckon, odometry_twist_at


def odometry_consistency(t, poses, odometry, speed_scale: float, offset: float, noise: OdometryNoise,
                         tolerance: float, window: float = CONSISTENCY_WINDOW_S) -> tuple[np.ndarray, np.ndarray]:
    """Two (K,) bool arrays: (consistent) no window of ``window`` s containing scan k has the track
    ``poses`` cover a distance different from the odometry's by more than CONSISTENCY_SIGMAS σ +
    ``tolerance`` (m); (skid) every such window has the odometry covering less and standing still in
    it (package doc)."""
    t = np.asarray(t, dtype=float)
    poses = np.asarray(poses, dtype=float)
    K = len(t)
    if K < 2:
        return np.ones(K, dtype=bool), np.zeros(K, dtype=bool)
    B = dead_reckon(odometry[0], odometry[1], t - offset, speed_scale)
    k = np.arange(K)
    j = np.minimum(np.searchsorted(t, t + window), K - 1)
    pairs = j > k
    k, j = k[pairs], j[pairs]
    pred = relative(B[k], B[j])
    got = relative(poses[k], poses[j])
    sig = noise.sigmas(pred, t[j] - t[k])
    # the distance covered (chord), not the displacement vector: a yaw-rate scale the yardstick does not fit
    # bends the odometry's path, it hardly changes how far the robot got
    excess = np.hypot(got[:, 0], got[:, 1]) - np.hypot(pred[:, 0], pred[:, 1])  # > 0: the odometry covered less
    gate = CONSISTENCY_SIGMAS * np.hypot(sig[:, 0], sig[:, 1]) + tolerance

    def scans_of(windows):  # every scan k..j of the given windows
        marks = np.zeros(K + 1, dtype=np.int64)
        np.add.at(marks, k[windows], 1)
        np.add.at(marks, j[windows] + 1, -1)
        return np.cumsum(marks)[:K] > 0
    # a skid locks the wheels: the odometry reports the robot standing somewhere in the window
    tw = odometry_twist_at(odometry[0], odometry[1], t - offset)
    standing = (np.hypot(tw[:, 0], tw[:, 1]) < STANDSTILL_SPEED) & (np.abs(tw[:, 2]) < STANDSTILL_TURN)
    stood = np.r_[0, np.cumsum(standing)]
    locked = stood[j + 1] > stood[k]
    lagging = scans_of(excess < -gate)
    skidding = scans_of((excess > gate) & locked)
    ahead = scans_of((excess > gate) & ~locked)  # the track outran rolling wheels: neither a skid nor right
    return ~(lagging | skidding | ahead), skidding & ~lagging & ~ahead


def pose_fit(occupancy_map: OccupancyMap, beams: list[ScanBeams], poses, mount, range_scale: float = 1.0) -> np.ndarray:
    """(K,) share of each scan's returns whose endpoint, seen from ``poses[k]``, lies within
    FIT_TOLERANCE_M of the map's free-space edge (NaN: no return or no pose)."""
    out = np.full(len(beams), np.nan)
    for k, (b, pose) in enumerate(zip(beams, np.asarray(poses, dtype=float))):  # one vectorised call per scan
        if not np.all(np.isfinite(pose)):
            continue
        q, _ = endpoints_base(b.ranges, b.angles, mount, range_scale)
        if len(q):
            d, _ = edge_distance(occupancy_map, compose(pose, np.column_stack([q, np.zeros(len(q))]))[:, :2])
            out[k] = float(np.mean(np.abs(d) <= FIT_TOLERANCE_M))
    return out


def better_fit_elsewhere(occupancy_map: OccupancyMap, beams: list[ScanBeams], t, poses, fit, mount,
                         range_scale: float = 1.0, every: float = ELSEWHERE_EVERY_S) -> np.ndarray:
    """(K,) bool: the scans of each ``every``-second stretch whose first scan with a fit, matched by the
    correlative matcher within ELSEWHERE_WINDOW of its track pose ``poses[k]``, fits the map at the
    match by at least ELSEWHERE_MARGIN more than at the track (``pose_fit``; ``fit`` (K,) the track's):
    the map explains that scan clearly better somewhere the track is not (package doc, step 4)."""
    t = np.asarray(t, dtype=float)
    poses = np.asarray(poses, dtype=float)
    fit = np.asarray(fit, dtype=float)
    out = np.zeros(len(t), dtype=bool)
    ok = np.isfinite(fit) & np.all(np.isfinite(poses), axis=1)
    if not ok.any():
        return out
    config = MatcherConfig(window_xy=ELSEWHERE_WINDOW[0], window_theta=ELSEWHERE_WINDOW[1], max_beams=ELSEWHERE_BEAMS)
    matcher = CorrelativeMatcher(occupancy_map, config)
    stretch = np.floor((t - t[ok][0]) / every).astype(np.int64)
    idx = np.flatnonzero(ok)
    for first in idx[np.unique(stretch[idx], return_index=True)[1]]:  # the first scan with a fit of each stretch
        b = beams[first]
        r = matcher.match(b.ranges, b.angles, mount, poses[first], range_scale=range_scale)
        if r is None:
            continue
        there = pose_fit(occupancy_map, [b], r.pose[None], mount, range_scale)[0]
        if there >= fit[first] + ELSEWHERE_MARGIN:
            out[stretch == stretch[first]] = True
    return out
