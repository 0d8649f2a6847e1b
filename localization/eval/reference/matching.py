"""Step 1 of the package doc for a whole bag: where the first scan is (around a given start pose, else
a global search whose hypotheses are followed for a few seconds) and the tracker from there."""
from __future__ import annotations

import math

import numpy as np

from localization.core.geometry import relative, wrap_angle
from localization.core.matching import MatcherConfig, endpoints_base
from localization.core.matching.grids import signed_distance
from localization.core.occupancy_map import OccupancyMap
from localization.eval.reference.constants import GLOBAL_FOLLOW_S, GLOBAL_HYPOTHESES, GLOBAL_TRAVEL_M, START_WINDOW
from localization.eval.reference.inputs import ScanBeams, scan_beams
from localization.eval.reference.odometry import OdometryNoise
from localization.eval.reference.tracker import Matches, _empty_matches, _Tracker


def global_candidates(occupancy_map: OccupancyMap, beams: ScanBeams, mount, count: int, rng=None,
                      step: float = 0.4, heading_step: float = 0.1, max_beams: int = 120) -> np.ndarray:
    """The ``count`` best base poses (count, 3) for one scan on a lattice over the free space
    (``step`` m, ``heading_step`` rad), scored by the mean of a likelihood blurred to the lattice
    (σ = step/2) at the endpoints of up to ``max_beams`` beams; one per lattice box."""
    rng = rng or np.random.default_rng(0)
    q, _ = endpoints_base(beams.ranges, beams.angles, mount)
    if len(q) < 10:
        return np.zeros((0, 3))
    q = q[np.unique(np.linspace(0, len(q) - 1, min(max_beams, len(q))).astype(int))]
    res = occupancy_map.resolution
    d = signed_distance(occupancy_map).astype(np.float64) * res
    L = np.exp(-0.5 * (d / (0.5 * step)) ** 2)
    L[d < -step] = 0.0  # deep inside walls
    free = np.argwhere(occupancy_map.free)  # (row, col)
    stride = max(1, int(round(step / res)))
    free = free[(free[:, 0] % stride == 0) & (free[:, 1] % stride == 0)]
    if len(free) == 0:
        return np.zeros((0, 3))
    xy = occupancy_map.grid_to_world(free[:, ::-1])
    headings = np.arange(0.0, 2 * np.pi, heading_step)
    h, w = L.shape
    best = np.full(len(xy), -1.0)
    best_h = np.zeros(len(xy))
    for th in headings:
        c, s = math.cos(th), math.sin(th)
        px = xy[:, 0:1] + c * q[None, :, 0] - s * q[None, :, 1]
        py = xy[:, 1:2] + s * q[None, :, 0] + c * q[None, :, 1]
        g = occupancy_map.world_to_grid(np.stack([px, py], axis=-1))
        inside = (g[..., 0] >= 0) & (g[..., 0] < w) & (g[..., 1] >= 0) & (g[..., 1] < h)
        val = np.where(inside, L[np.clip(g[..., 1], 0, h - 1), np.clip(g[..., 0], 0, w - 1)], 0.0).mean(axis=1)
        better = val > best
        best[better], best_h[better] = val[better], th
    order = np.argsort(-best)[:count]
    return np.column_stack([xy[order], best_h[order]])


def track_matches(occupancy_map: OccupancyMap, scans, t, odometry, mount, initial_pose=None,
                  config: MatcherConfig | None = None, range_scale: float = 1.0,
                  noise: OdometryNoise | None = None, log=None, deskew: bool = True, twists=None,
                  start_window=START_WINDOW, odometry_fit=(1.0, 0.0), wall_depth: float = 0.0) -> Matches:
    """Step 1 of the package doc for every scan (``t``: their times on the odometry's clock).
    ``twists`` (K, 3): deskew with these instead of the odometry's; ``odometry_fit``: (a, δ) for
    the predictions (the second pass); ``wall_depth`` (m): map_wall_depth."""
    say = log or (lambda *_: None)
    beams = scan_beams(scans, deskew, wall_depth / range_scale)
    K = len(beams)
    tracker = _Tracker(occupancy_map, mount, beams, np.asarray(t, dtype=float), odometry, config, range_scale,
                       noise or OdometryNoise(), odometry_fit)
    if twists is not None:
        tracker.twist = np.asarray(twists, dtype=float)
    out = _empty_matches(K)
    if K == 0:
        return Matches(start="no scans", **out)
    if initial_pose is not None:
        P0 = np.diag([start_window[0] ** 2 / 9, start_window[0] ** 2 / 9, start_window[1] ** 2 / 9])
        tracker.run(0, initial_pose, P0, out, first_window=start_window)
        return Matches(start="given start pose", **out)
    # global: the first scan with enough beams proposes poses; each is followed for a few seconds
    k0 = next((k for k, b in enumerate(beams) if np.count_nonzero(np.isfinite(b.ranges)) >= 10), None)
    if k0 is None:
        return Matches(start="no scan with 10 valid beams", **out)
    cands = global_candidates(occupancy_map, beams[k0], mount, 60)
    step_window = (0.4, 0.1)
    scored = []
    for c in cands:
        r, info = tracker.match(k0, c, step_window)
        if r is not None and info.inliers >= 10:
            scored.append((r.score * info.inlier_fraction, r.pose))
    scored.sort(key=lambda s: -s[0])
    poses = []
    for _, pose in scored:  # distinct hypotheses only
        if all(np.hypot(*(pose[:2] - h[:2])) > 0.5 or abs(wrap_angle(pose[2] - h[2])) > 0.3 for h in poses):
            poses.append(pose)
        if len(poses) == GLOBAL_HYPOTHESES:
            break
    if not poses:
        return Matches(start="global: no pose explains the first scan", **out)
    best = _follow_hypotheses(tracker, t, k0, poses, step_window, K)
    say(f"global start: {len(poses)} hypotheses, the best at ({poses[best['index']][0]:.2f}, "
        f"{poses[best['index']][1]:.2f}, {poses[best['index']][2]:.2f}) after {t[best['k'] - 1] - t[k0]:.1f} s "
        f"(mean score {best['value']:.3f})")
    for key, arr in best["out"].items():
        out[key][:] = arr
    tracker.run(best["k"], best["x"], best["P"], out, k_prev=best["k"] - 1)
    return Matches(start=f"global ({len(poses)} hypotheses)", **out)


def _follow_hypotheses(tracker: _Tracker, t, k0: int, poses, window, K: int) -> dict:
    """Follow every start hypothesis in steps of ``GLOBAL_FOLLOW_S`` / 2; after each step drop those whose
    mean usable match score (0 for a scan without a usable match) is below 0.85 × the best; stop when
    one is left, or the odometry has moved ≥ GLOBAL_TRAVEL_M and GLOBAL_FOLLOW_S passed, or at the end."""
    P0 = np.diag([0.1 ** 2, 0.1 ** 2, 0.05 ** 2])
    hyps = [{"index": i, "x": np.asarray(p, dtype=float), "P": P0, "out": _empty_matches(K), "k": k0}
            for i, p in enumerate(poses)]
    k = k0
    while True:
        k_next = int(np.searchsorted(t, t[k] + 0.5 * GLOBAL_FOLLOW_S, side="right"))
        k_next = max(k_next, k + 1)
        for h in hyps:
            h["x"], h["P"] = tracker.run(k, h["x"], h["P"], h["out"], k_stop=min(k_next, K),
                                         first_window=window if k == k0 else None,
                                         k_prev=None if k == k0 else k - 1)
            s = np.nan_to_num(h["out"]["score"][k0:k_next]) * h["out"]["usable"][k0:k_next]
            h["value"], h["k"] = float(s.mean()) if s.size else 0.0, min(k_next, K)
        k = min(k_next, K)
        top = max(h["value"] for h in hyps)
        hyps = [h for h in hyps if h["value"] >= 0.85 * top]
        moved = float(np.hypot(*relative(tracker.B[k0], tracker.B[k - 1])[:2]))
        if len(hyps) == 1 or k >= K or (moved >= GLOBAL_TRAVEL_M and t[k - 1] - t[k0] >= GLOBAL_FOLLOW_S):
            return max(hyps, key=lambda h: h["value"])
