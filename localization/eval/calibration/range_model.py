"""The lidar's range scale and the wall surface's depth behind the map's free-space edge, scan by scan
(``localization.eval.calibration``, step 2)."""
from __future__ import annotations

import math

import numpy as np

from localization.core.occupancy_map import OccupancyMap
from localization.core.scan import beam_angles, clean_ranges
from localization.eval.calibration.result import CalibrationError

MAX_RANGE_SCANS = 300


def range_model_scan(occupancy_map: OccupancyMap, ranges, angles, laser_pose, iterations: int = 15):
    """(s, o) of one scan (package doc, step 2): Gauss–Newton over the laser pose (x, y, θ), the range
    scale s and the wall surface's depth o behind the free-space edge, on the residuals
    d(p_i) + o (d: ``reference.edge_distance``, p_i = L ⊕ s r_i (cos α_i, sin α_i)), Cauchy-weighted
    (scale one cell; beyond four cells left out). None when fewer than 20 beams or it does not
    converge near the start."""
    from localization.eval.reference import edge_distance
    r = np.asarray(ranges, dtype=float)
    a = np.asarray(angles, dtype=float)
    ok = np.isfinite(r) & (r > 0)
    r, a = r[ok], a[ok]
    if r.size < 20:
        return None
    res = occupancy_map.resolution
    u = np.stack([r * np.cos(a), r * np.sin(a)], axis=1)  # unscaled endpoints in the laser frame
    g = np.array([*np.asarray(laser_pose, dtype=float), 1.0, 0.0])
    g0 = g.copy()
    for _ in range(iterations):
        x, y, th, sc, off = g
        c, sn = math.cos(th), math.sin(th)
        qx, qy = sc * u[:, 0], sc * u[:, 1]
        rx, ry = c * qx - sn * qy, sn * qx + c * qy
        d, grad = edge_distance(occupancy_map, np.stack([x + rx, y + ry], axis=1))
        e = d + off
        w = 1.0 / (1.0 + (e / res) ** 2)
        w[np.abs(e) > 4 * res] = 0.0
        if np.count_nonzero(w) < 20:
            return None
        J = np.stack([grad[:, 0], grad[:, 1], -grad[:, 0] * ry + grad[:, 1] * rx,
                      (grad[:, 0] * rx + grad[:, 1] * ry) / sc, np.ones_like(e)], axis=1)
        H = (J * w[:, None]).T @ J
        try:
            step = -np.linalg.solve(H + 1e-9 * np.trace(H) * np.eye(5), (J * w[:, None]).T @ e)
        except np.linalg.LinAlgError:
            return None
        step = np.clip(step, [-0.05, -0.05, -0.01, -0.005, -0.01], [0.05, 0.05, 0.01, 0.005, 0.01])
        g += step
        if np.all(np.abs(step) < [1e-5, 1e-5, 1e-6, 1e-6, 1e-5]):
            break
    if np.hypot(*(g[:2] - g0[:2])) > 0.3 or abs(g[3] - 1.0) > 0.2 or abs(g[4]) > 3 * res:
        return None
    return float(g[3]), float(g[4])


def _robust_median(v) -> tuple[float, float]:
    """Median and its σ: the larger of 1.2533 · std / √N and the spread of the medians of up to 10
    consecutive blocks / √blocks (neighbouring scans see the same walls)."""
    v = np.asarray(v, dtype=float)
    sigma = 1.2533 * v.std() / math.sqrt(v.size)
    blocks = np.array_split(v, min(10, v.size // 5))
    if len(blocks) >= 3:
        sigma = max(sigma, float(np.std([np.median(b) for b in blocks], ddof=1) / math.sqrt(len(blocks))))
    return float(np.median(v)), float(sigma)


def fit_range_model(occupancy_map: OccupancyMap, scans, laser_poses, good, max_scans: int = MAX_RANGE_SCANS):
    """Range scale s and wall surface depth o (m) over the good scans (package doc, step 2): medians,
    their σ, and the number of scans used."""
    idx = np.flatnonzero(good)
    if idx.size > max_scans:
        idx = idx[np.unique(np.linspace(0, idx.size - 1, max_scans).astype(int))]
    values = []
    for k in idx:
        sc = scans[k]
        n = np.asarray(sc.ranges).size
        est = range_model_scan(occupancy_map, clean_ranges(sc.ranges, sc.range_min, sc.range_max),
                               beam_angles(n, sc.angle_min, sc.angle_max, sc.angle_increment), laser_poses[k])
        if est is not None:
            values.append(est)
    v = np.asarray(values, dtype=float).reshape(-1, 2)
    if len(v) < 5:
        raise CalibrationError(f"only {len(v)} scans gave a range scale: too few")
    s, s_sig = _robust_median(v[:, 0])
    o, o_sig = _robust_median(v[:, 1])
    return s, s_sig, o, o_sig, int(len(v))
