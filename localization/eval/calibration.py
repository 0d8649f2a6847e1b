"""Calibration of a robot from one bag: odometry timing and scales, laser mount, lidar range scale,
with the odometry's slips and skids found and left out; and a check of the scan stamp convention.

Every value is the correction the localizer applies (the parameters of the same names):

- ``odom_time_offset`` δ (s): odometry stamped τ describes the motion at τ + δ (odometry reported
  40 ms late → δ = −0.04);
- ``odom_speed_scale`` a: speed used = a × reported (vx, vy);
- ``odom_yaw_rate_scale`` b, ``odom_yaw_rate_bias`` c: yaw rate used = b × reported ωz + c;
- ``laser_offset_x/y/yaw`` m = (m_x, m_y, m_ψ): the laser's pose in base_link;
- ``lidar_scale_to_map_scale`` s: map metres per measured range unit;
- ``map_wall_depth`` o (m): how far behind the map's free-space edge a return ends on a wall.

1. The yardstick (``localization.eval.reference``) with the mount guess m₀: the scan-to-map matches
   Z_k of the scans it accepts (matched to the map alone: no odometry in them), as laser poses
   L_k = Z_k ⊕ m₀, which do not depend on the m₀ assumed while matching.
2. Range scale: per accepted scan whose match pins every axis (at most 300, evenly spread),
   Gauss–Newton over the laser pose, the range scale s and the wall surface's depth o
   (``range_model_scan``) on the residuals d(p_i) + o, d the signed distance to the edge of the free
   space (``reference.edge_distance``) at the endpoint p_i = L ⊕ s r_i (cos α_i, sin α_i). Map walls
   are drawn 2–3 cells thick and a beam ends on the real surface, about 2 cm behind the free cells'
   edge: without o (or scoring endpoints on the occupied cells' centres) that constant depth is
   fitted as a scale, s ≈ 1 − o / r̃ (r̃ the median range: −0.7 % at 3 m). s and o are the medians
   over scans, each σ the larger of 1.2533 · std / √N and the spread of the medians of 10
   consecutive blocks / √10 (neighbouring scans share walls). When s and o move an endpoint at r̃ by
   more than a quarter cell, |s − 1| r̃ + o > res/4, the yardstick is built again with returns s·r − o
   (as the filter scores them).
3. Slips and skids. Pairs (k, k') of accepted scans Δt ≈ 0.4 s apart; with the current fit (start:
   the yardstick's own a and δ), the scan-matched and the odometry's motion over the pair::

       e_v = (ΔL_x − ΔL̂_x) / Δt   (forward speed, m/s),   e_ω = (ΔL_θ − ΔL̂_θ) / Δt   (rad/s)

   the speed taken at the odometry's own stamps (δ_v = 0: a skid is a disagreement no time offset
   may explain away), the yaw rate at the fitted offset. A pair is rejected when
   |e_v| > max(4 · 1.4826 MAD(e_v), 0.1 v₉₅) or |e_ω| > max(4 · 1.4826 MAD(e_ω), 0.1 ω₉₅), v₉₅ and
   ω₉₅ the 95th percentiles of the scan-matched speed and yaw rate (the bound scales with the
   robot: ~0.2 m/s on the RSS car at up to 3 m/s, ~0.1 m/s on the Pioneer at 0.5 m/s): wheels
   locked while the robot slides (the braking skid at the end of a drive), wheel spin, a wheel
   slipping in a turn. Fit, reject, fit again, three times; reported: the pairs and the seconds of
   the bag rejected.
4. Odometry and mount: with B(t) the odometry dead-reckoned with (a, b, c) on the scan clock
   (``dead_reckon_channels``: the speed and the yaw rate shifted by their offsets, each twist held
   over its period, which ends at its stamp), the predicted relative laser motion of a pair::

       ΔL̂ = m⁻¹ ⊕ (B(t_k) ⊖ B(t_k')) ⊕ m,      r = (ΔL − ΔL̂) / (σ_xy, σ_xy, σ_θ)

   fitted to the observed ΔL = L_k ⊖ L_k' over the kept pairs by robust least squares (soft-L1)
   over p = (δ, a, b, c, m_x, m_y, m_ψ) (one offset δ for both, as the localizer applies it).
   Also fitted with separate offsets for the speed and the yaw rate (δ_v, δ_ω), reported
   alongside: a car whose yaw rate comes from the steering command leads the real turn, while its
   wheel speed lags (docs/replay.md). Uncertainty: σ_p = sqrt(diag((JᵀJ)⁻¹) · s²_res · n_overlap),
   n_overlap the number of pairs overlapping each one (they share scans, so their errors are
   correlated; the inflation keeps the figure honest).

Scan stamps (``check_scan_stamps``): a driver publishes a scan once its last beam is measured, so
the bag's record time minus the header stamp is at least the sweep (n − 1)Δ when the stamp is the
first beam's time. Its lower envelope (1st percentile) below the sweep — negative values above
all — says the stamp is at or after the last beam (``scan_stamp: last_beam``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from localization.core.geometry import compose, integrate_twists, inverse, relative, wrap_angle
from localization.core.matching import MatcherConfig
from localization.core.occupancy_map import OccupancyMap
from localization.core.scan import beam_angles, clean_ranges
from localization.eval.reference import ReferenceTrack, build_reference, odometry_inputs, read_odometry, read_scans

KEYS = ("odom_time_offset_s", "odom_speed_scale", "odom_yaw_rate_scale", "odom_yaw_rate_bias", "laser_offset_x",
        "laser_offset_y", "laser_offset_yaw", "lidar_scale_to_map_scale", "map_wall_depth")
#: metrics key -> node parameter name
PARAM_NAMES = {"odom_time_offset_s": "odom_time_offset", "odom_speed_scale": "odom_speed_scale",
               "odom_yaw_rate_scale": "odom_yaw_rate_scale", "odom_yaw_rate_bias": "odom_yaw_rate_bias",
               "laser_offset_x": "laser_offset_x", "laser_offset_y": "laser_offset_y",
               "laser_offset_yaw": "laser_offset_yaw", "lidar_scale_to_map_scale": "lidar_scale_to_map_scale",
               "map_wall_depth": "map_wall_depth"}

PAIR_SPACING_S = 0.4
SIGMA_XY = 0.01  # m: residual scale of a relative laser translation
SIGMA_THETA = 0.005  # rad
SLIP_MAD_FACTOR = 4.0  # a pair slips when its speed or yaw-rate disagreement exceeds this many robust σ ...
SLIP_SPEED_FRACTION = 0.1  # ... and this fraction of the robot's 95th-percentile speed (yaw rate)
SLIP_ROUNDS = 3
MAX_RANGE_SCANS = 300


class CalibrationError(RuntimeError):
    """Not enough data to calibrate (one line saying why)."""


@dataclass
class CalibrationResult:
    values: dict  # KEYS -> float
    uncertainty: dict  # KEYS -> float (1 σ)
    scans: int = 0
    good_scans: int = 0
    pairs: int = 0
    residual_rms: dict = field(default_factory=dict)
    rejected: dict = field(default_factory=dict)  # slips and skids left out (module doc, step 3)
    channel_offsets: dict = field(default_factory=dict)  # δ_v, δ_ω (s) with their σ
    wall_surface: dict = field(default_factory=dict)  # o (m): where beams end behind the free-space edge
    yardstick: dict = field(default_factory=dict)  # the reference track's own figures

    def as_dict(self) -> dict:
        return {**{k: float(self.values[k]) for k in KEYS},
                "uncertainty": {k: float(self.uncertainty[k]) for k in KEYS},
                "scans": self.scans, "good_scans": self.good_scans, "pairs": self.pairs,
                "residual_rms": self.residual_rms, "rejected": self.rejected,
                "channel_offsets": self.channel_offsets, "wall_surface": self.wall_surface,
                "yardstick": self.yardstick}

    def parameter_yaml(self, node: str = "particle_filter") -> str:
        r = self.rejected
        lines = [f"# localization-calibrate: {self.good_scans} of {self.scans} scans matched, {self.pairs} pairs "
                 f"({r.get('pairs', 0)} rejected as slip or skid, {r.get('seconds', 0.0):.1f} s)",
                 f"{node}:", "  ros__parameters:"]
        for k in KEYS:
            lines.append(f"    {PARAM_NAMES[k]}: {self.values[k]:.6g}  # ± {self.uncertainty[k]:.2g}")
        return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------------------------
# Dead reckoning with the speed and the yaw rate on their own clocks
# --------------------------------------------------------------------------------------------


def dead_reckon_channels(odom_t, twist, query_t, a=1.0, b=1.0, c=0.0, delta_v=0.0, delta_w=0.0) -> np.ndarray:
    """Odometry poses (…, 3) at ``query_t`` (scan clock, 0 at the first breakpoint): the speed
    message k held over (t_{k−1} + δ_v, t_k + δ_v], the yaw rate over (t_{k−1} + δ_ω, t_k + δ_ω]
    (corrected: a·(vx, vy), b·ωz + c); between the union of both sets of breakpoints both are
    constant, so each piece is one exact arc (``integrate_twists``), composed in closed form.
    The last twists are extrapolated, the first run backwards before the first breakpoint.
    With δ_v = δ_ω = δ this is ``reference.dead_reckon(odom_t, twist, query_t − δ)``."""
    t, tw, q = odometry_inputs(odom_t, twist, query_t)
    M = len(t)
    if M < 2:
        return np.zeros(q.shape + (3,))
    tv, tr = t + delta_v, t + delta_w
    br = np.unique(np.concatenate([tv, tr]))
    mid = 0.5 * (br[:-1] + br[1:])

    def held(stamps, x):  # the message whose period holds x (the first / last beyond the ends)
        return np.clip(np.searchsorted(stamps, x, side="left"), 1, M - 1)

    kv, kw = held(tv, mid), held(tr, mid)
    steps = integrate_twists(a * tw[kv, 0], a * tw[kv, 1], b * tw[kw, 2] + c, np.diff(br))
    th = np.concatenate([[0.0], np.cumsum(steps[:, 2])])
    cs, sn = np.cos(th[:-1]), np.sin(th[:-1])
    chain = np.zeros((len(br), 3))
    chain[1:, 0] = np.cumsum(cs * steps[:, 0] - sn * steps[:, 1])
    chain[1:, 1] = np.cumsum(sn * steps[:, 0] + cs * steps[:, 1])
    chain[:, 2] = wrap_angle(th)
    j = np.clip(np.searchsorted(br, q, side="left"), 1, len(br) - 1)  # the piece (br_{j-1}, br_j] holding q
    dt = q - br[j - 1]  # < 0 only before the first breakpoint
    qv, qw = kv[j - 1], kw[j - 1]
    return compose(chain[j - 1], integrate_twists(a * tw[qv, 0], a * tw[qv, 1], b * tw[qw, 2] + c, dt))


# --------------------------------------------------------------------------------------------
# Estimation
# --------------------------------------------------------------------------------------------


def _pairs(t, spacing):
    """Index pairs (i, j) with t_j − t_i the first step ≥ spacing (at most 1.5 spacing)."""
    t = np.asarray(t, dtype=float)
    j = np.searchsorted(t, t + spacing, side="left")
    ok = j < len(t)
    i = np.flatnonzero(ok)
    j = j[ok]
    keep = t[j] - t[i] <= 1.5 * spacing
    return i[keep], j[keep]


@dataclass
class _PairFit:
    x: np.ndarray  # (8,) δ_v, δ_ω, a, b, c, m_x, m_y, m_ψ
    sigma: np.ndarray
    residual: np.ndarray  # (P, 3) in m, m, rad
    cost: float


def _fit_pairs(lt, lp, odom_t, twist, i0, i1, p0, split: bool) -> _PairFit:
    """Robust least squares over the pairs (module doc, step 4); ``split``: δ_v and δ_ω apart."""
    from scipy.optimize import least_squares
    obs = relative(lp[i0], lp[i1])
    scale = np.array([SIGMA_XY, SIGMA_XY, SIGMA_THETA])

    def unpack(p):
        return (p[0], p[1], *p[2:]) if split else (p[0], p[0], *p[1:])

    def residuals(p):
        dv, dw, a, b, c, mx, my, myaw = unpack(p)
        B = dead_reckon_channels(odom_t, twist, np.concatenate([lt[i0], lt[i1]]), a, b, c, dv, dw)
        n = len(i0)
        m = np.array([mx, my, myaw])
        pred = compose(compose(inverse(m), relative(B[:n], B[n:])), m)
        r = obs - pred
        r[:, 2] = wrap_angle(r[:, 2])
        return (r / scale).ravel()

    x0 = np.asarray(p0, dtype=float) if split else np.delete(np.asarray(p0, dtype=float), 1)
    lo = np.array([-0.5, -0.5, 0.5, 0.5, -1.0, -2.0, -2.0, -math.pi])
    hi = np.array([0.5, 0.5, 2.0, 2.0, 1.0, 2.0, 2.0, math.pi])
    if not split:
        lo, hi = np.delete(lo, 1), np.delete(hi, 1)
    sol = least_squares(residuals, np.clip(x0, lo + 1e-9, hi - 1e-9), bounds=(lo, hi), loss="soft_l1", f_scale=2.0,
                        x_scale=np.full(len(x0), 0.01), diff_step=np.r_[[1e-4] * (2 if split else 1),
                                                                         [1e-5] * 6])
    r = residuals(sol.x).reshape(-1, 3) * scale
    J = sol.jac
    n, k = J.shape
    s2 = 2.0 * sol.cost / max(n - k, 1)
    try:
        cov = np.linalg.inv(J.T @ J) * s2
    except np.linalg.LinAlgError:
        cov = np.full((k, k), np.inf)
    period = float(np.median(np.diff(lt))) if len(lt) > 1 else PAIR_SPACING_S
    overlap = max(1.0, PAIR_SPACING_S / max(period, 1e-3))
    sig = np.sqrt(np.clip(np.diag(cov), 0, None) * overlap)
    x = sol.x if split else np.insert(sol.x, 1, sol.x[0])
    sig = sig if split else np.insert(sig, 1, sig[0])
    return _PairFit(x=x, sigma=sig, residual=r, cost=float(sol.cost))


def slip_mask(lt, lp, odom_t, twist, i0, i1, fit: np.ndarray) -> tuple[np.ndarray, dict]:
    """Pairs (bool, True = kept) whose scan-matched forward speed and yaw rate agree with the
    odometry's under ``fit`` (module doc, step 3), and the bounds used. The speed is compared at
    the odometry's own stamps (δ_v = 0): a skid (wheels locked while the robot slides) is a
    disagreement a time offset must not be allowed to explain away."""
    dv, dw, a, b, c, mx, my, myaw = fit
    B = dead_reckon_channels(odom_t, twist, np.concatenate([lt[i0], lt[i1]]), a, b, c, 0.0, dw)
    n = len(i0)
    m = np.array([mx, my, myaw])
    pred = compose(compose(inverse(m), relative(B[:n], B[n:])), m)
    obs = relative(lp[i0], lp[i1])
    dt = lt[i1] - lt[i0]
    e_v = (obs[:, 0] - pred[:, 0]) / dt
    e_w = wrap_angle(obs[:, 2] - pred[:, 2]) / dt
    speed = np.hypot(obs[:, 0], obs[:, 1]) / dt
    rate = np.abs(obs[:, 2]) / dt

    def bound(e, level):
        mad = 1.4826 * float(np.median(np.abs(e - np.median(e))))
        return max(SLIP_MAD_FACTOR * mad, SLIP_SPEED_FRACTION * float(np.percentile(level, 95)), 1e-6)

    bv, bw = bound(e_v, speed), bound(e_w, rate)
    keep = (np.abs(e_v) <= bv) & (np.abs(e_w) <= bw)
    return keep, {"speed_bound_mps": bv, "yaw_rate_bound_radps": bw}


def fit_odometry(laser_t, laser_poses, odom_t, twist, mount0=(0.275, 0.0, 0.0), spacing: float = PAIR_SPACING_S,
                 start=(0.0, 1.0), log=None):
    """(δ, a, b, c, m_x, m_y, m_ψ), their σ, the pairs used, residual rms, the rejected pairs (dict)
    and the per-channel offsets (module doc, steps 3–4). ``start``: (δ, a) to begin from."""
    say = log or (lambda *_: None)
    lt = np.asarray(laser_t, dtype=float)
    lp = np.asarray(laser_poses, dtype=float)
    ot = np.asarray(odom_t, dtype=float)
    t_rel = ot[0]
    ot, lt = ot - t_rel, lt - t_rel
    i0, i1 = _pairs(lt, spacing)
    if len(i0) < 20:
        raise CalibrationError(f"only {len(i0)} pairs of matched scans {spacing} s apart: too few to calibrate")
    p = np.array([start[0], start[0], start[1], 1.0, 0.0, *mount0], dtype=float)
    keep = np.ones(len(i0), dtype=bool)
    bounds: dict = {}
    fit = None
    for _ in range(SLIP_ROUNDS):
        if keep.sum() < 20:
            raise CalibrationError(f"only {int(keep.sum())} of {len(i0)} scan pairs agree with the odometry: too few")
        fit = _fit_pairs(lt, lp, ot, twist, i0[keep], i1[keep], p, split=False)
        p = fit.x
        new_keep, bounds = slip_mask(lt, lp, ot, twist, i0, i1, p)
        if np.array_equal(new_keep, keep):
            break
        keep = new_keep
    fit = _fit_pairs(lt, lp, ot, twist, i0[keep], i1[keep], p, split=False)
    split = _fit_pairs(lt, lp, ot, twist, i0[keep], i1[keep], fit.x, split=True)
    intervals = _union(lt[i0[~keep]], lt[i1[~keep]])
    covered = float(sum(e - s for s, e in intervals))
    rejected = {"pairs": int((~keep).sum()), "of": int(len(i0)), "share": float((~keep).mean()),
                "seconds": covered, "intervals_s": [[s - lt[0], e - lt[0]] for s, e in intervals], **bounds}
    say(f"slip/skid: {rejected['pairs']} of {len(i0)} scan pairs rejected ({100 * rejected['share']:.1f} %, "
        f"{covered:.1f} s of the bag; bounds {bounds['speed_bound_mps']:.3f} m/s, "
        f"{bounds['yaw_rate_bound_radps']:.3f} rad/s)")
    r = fit.residual
    rms = {"xy_m": float(np.sqrt(np.mean(r[:, :2] ** 2))), "theta_rad": float(np.sqrt(np.mean(r[:, 2] ** 2)))}
    values = np.delete(fit.x, 1)
    sigmas = np.delete(fit.sigma, 1)
    channels = {"speed_s": float(split.x[0]), "speed_sigma_s": float(split.sigma[0]),
                "yaw_rate_s": float(split.x[1]), "yaw_rate_sigma_s": float(split.sigma[1])}
    return values, sigmas, int(keep.sum()), rms, rejected, channels


def _union(starts, ends) -> list:
    """The union of the intervals [starts_i, ends_i] as sorted, disjoint [start, end] pairs."""
    out: list = []
    for s, e in sorted(zip(np.asarray(starts, dtype=float), np.asarray(ends, dtype=float))):
        if out and s <= out[-1][1]:
            out[-1][1] = max(out[-1][1], e)
        else:
            out.append([float(s), float(e)])
    return out


def range_model_scan(occupancy_map: OccupancyMap, ranges, angles, laser_pose, iterations: int = 15):
    """(s, o) of one scan (module doc, step 2): Gauss–Newton over the laser pose (x, y, θ), the range
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
    """Range scale s and wall surface depth o (m) over the good scans (module doc, step 2): medians,
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


def _matched_laser(ref: ReferenceTrack, mount):
    """Times and laser poses of the accepted scan-to-map matches (no odometry in them)."""
    ok = ref.accepted & np.all(np.isfinite(ref.matched), axis=1)
    return ref.t[ok], compose(ref.matched[ok], np.asarray(mount, dtype=float)), ok


def calibrate(scans, odom_t, twist, occupancy_map: OccupancyMap, initial_pose, mount0=(0.275, 0.0, 0.0),
              config: MatcherConfig | None = None, log=None, scan_stamp: str = "first_beam",
              scan_stamp_offset: float = 0.0) -> CalibrationResult:
    """Calibrate from scans (``ScanData``), odometry (stamps, twists (M, 3)) and a map (module doc);
    ``initial_pose`` None: the yardstick starts with a global match."""
    say = log or (lambda *_: None)
    if len(scans) < 20:
        raise CalibrationError(f"only {len(scans)} scans: too few to calibrate")
    if len(odom_t) < 10:
        raise CalibrationError(f"only {len(odom_t)} odometry messages: too few to calibrate")
    odom = (np.asarray(odom_t, dtype=float), np.asarray(twist, dtype=float).reshape(-1, 3))
    say(f"reference track of {len(scans)} scans ...")
    kw = {"config": config, "scan_stamp": scan_stamp, "scan_stamp_offset": scan_stamp_offset, "log": log}
    ref = build_reference(scans, occupancy_map, mount0, odom, initial_pose, **kw)
    if ref.counts.get("accepted", 0) < 20:
        raise CalibrationError(f"only {ref.counts.get('accepted', 0)} of {len(scans)} scans matched the map: check "
                               "the map, --initial-pose and the laser mount")
    lt, lp, ok = _matched_laser(ref, mount0)
    pinned = ok & np.all(ref.constrained[:, :3], axis=1)
    s, s_sig, o, o_sig, n_s = fit_range_model(occupancy_map, scans, compose(np.where(ok[:, None], ref.matched, 0.0),
                                                                            np.asarray(mount0, dtype=float)), pinned)
    median_range = _median_range(scans)
    say(f"range scale {s:.5f} ± {s_sig:.5f}, wall surface {100 * o:.2f} ± {100 * o_sig:.2f} cm behind the "
        f"free-space edge ({n_s} scans)")
    depth = float(np.clip(o, 0.0, 0.5))  # map_wall_depth's range: a return never ends before the edge
    if abs(s - 1.0) * median_range + depth > 0.25 * occupancy_map.resolution:
        say("matching again with the range scale and the wall surface ...")
        ref = build_reference(scans, occupancy_map, mount0, odom, initial_pose, range_scale=s,
                              wall_depth=depth, **kw)
        lt, lp, ok = _matched_laser(ref, mount0)
    say(f"fitting odometry and mount on {len(lt)} matched scans ...")
    start = (ref.odometry.get("time_offset_s", 0.0), ref.odometry.get("speed_scale", 1.0))
    x, sig, pairs, rms, rejected, channels = fit_odometry(lt, lp, odom[0], odom[1], mount0, start=start, log=log)
    values = dict(zip(KEYS[:7], (float(v) for v in x)))
    values["laser_offset_yaw"] = float(wrap_angle(values["laser_offset_yaw"]))
    values["lidar_scale_to_map_scale"] = s
    values["map_wall_depth"] = depth
    unc = dict(zip(KEYS[:7], (float(v) for v in sig)))
    unc["lidar_scale_to_map_scale"] = s_sig
    unc["map_wall_depth"] = o_sig
    return CalibrationResult(values=values, uncertainty=unc, scans=len(scans), good_scans=int(ok.sum()),
                             pairs=pairs, residual_rms=rms, rejected=rejected, channel_offsets=channels,
                             wall_surface={"offset_m": o, "sigma_m": o_sig}, yardstick=ref.summary())


def _median_range(scans) -> float:
    sample = scans[:: max(1, len(scans) // 50)]
    r = np.concatenate([clean_ranges(s.ranges, s.range_min, s.range_max) for s in sample])
    r = r[np.isfinite(r)]
    return float(np.median(r)) if r.size else 1.0


def calibrate_bag(bag_path, occupancy_map: OccupancyMap, scan_topic: str = "/scan", odom_topic: str = "/odom",
                  initial_pose=None, mount0=(0.275, 0.0, 0.0), config: MatcherConfig | None = None,
                  log=None, *, scan_stamp: str = "first_beam", scan_stamp_offset: float = 0.0,
                  odom_frame: str = "odom", base_frame: str = "base_link") -> CalibrationResult:
    """``calibrate`` on a bag: scans on ``scan_topic``, odometry on ``odom_topic`` (else TF
    ``odom_frame → base_frame``); start pose ``initial_pose``, else the bag's /initialpose, else a
    global match. The scan stamp convention is checked against the bag's record times (a log line)."""
    say = log or (lambda *_: None)
    scans = read_scans(bag_path, scan_topic)
    odom_t, twist = read_odometry(bag_path, odom_topic, odom_frame, base_frame)
    if initial_pose is None:
        initial_pose = initial_pose_from_bag(bag_path)
    if initial_pose is None:
        say("no start pose (--initial-pose, /initialpose): the reference track starts with a global match")
    try:
        check = check_scan_stamps(bag_path, scan_topic)
        say(check.message(scan_stamp))
    except ValueError:
        pass
    return calibrate(scans, odom_t, twist, occupancy_map, initial_pose, mount0, config, log, scan_stamp,
                     scan_stamp_offset)


def initial_pose_from_bag(bag_path, topic: str = "/initialpose"):
    """The first /initialpose (PoseWithCovarianceStamped) of the bag, or None."""
    from localization.bags import open_bag
    from localization.ros.conversions import pose_from_pose_with_covariance
    with open_bag(bag_path) as bag:
        info = bag.topic_infos.get(topic)
        if info is None or info.msgtype != "geometry_msgs/msg/PoseWithCovarianceStamped":
            return None
        for m in bag.messages([topic]):
            return np.asarray(pose_from_pose_with_covariance(m.msg).pose, dtype=float)
    return None


# --------------------------------------------------------------------------------------------
# The scan stamp convention
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class StampCheck:
    """Record time − header stamp of a bag's scans (module doc, last paragraph)."""

    scans: int
    lead_p1_s: float  # 1st percentile of record − stamp (s): the lower envelope
    lead_median_s: float
    sweep_s: float  # (n − 1) × time_increment; 0 when the scans carry no sweep timing
    convention: str  # "first_beam", "last_beam" or "unknown"

    def message(self, configured: str | None = None) -> str:
        line = (f"scan stamps: record time - stamp {1e3 * self.lead_p1_s:+.2f} ms (1st percentile), "
                f"{1e3 * self.lead_median_s:+.2f} ms (median), sweep {1e3 * self.sweep_s:.1f} ms: ")
        if self.convention == "last_beam":
            line += "the stamp is at or after the last beam (scan_stamp: last_beam)"
        elif self.convention == "first_beam":
            line += "consistent with a stamp at the first beam (scan_stamp: first_beam)"
        else:
            line += "no sweep timing (time_increment 0): the convention does not matter"
        if configured and self.convention in ("first_beam", "last_beam") and configured != self.convention:
            line += f"; the parameters say {configured}"
        return line


def check_scan_stamps(bag_path, scan_topic: str) -> StampCheck:
    """Compare a bag's scan header stamps with its record times (module doc); raises ValueError
    (BagError) without scans."""
    from localization.bags import BagError, open_bag
    lead, sweeps = [], []
    with open_bag(bag_path) as bag:
        if scan_topic not in bag.topic_infos:
            raise BagError(f"scan topic {scan_topic} not in bag {bag_path}")
        for m in bag.messages([scan_topic]):
            h = m.msg.header.stamp
            lead.append(m.t_ns * 1e-9 - (h.sec + 1e-9 * h.nanosec))
            n = len(m.msg.ranges)
            ti = float(m.msg.time_increment)
            sweeps.append(ti * (n - 1) if math.isfinite(ti) and ti > 0 else 0.0)
    if not lead:
        raise BagError(f"no scans on {scan_topic} in bag {bag_path}")
    lead_a = np.asarray(lead, dtype=float)
    sweep = float(np.median(sweeps))
    p1 = float(np.percentile(lead_a, 1))
    if sweep <= 0:
        convention = "unknown"
    else:
        convention = "first_beam" if p1 >= sweep else "last_beam"
    return StampCheck(scans=len(lead), lead_p1_s=p1, lead_median_s=float(np.median(lead_a)), sweep_s=sweep,
                      convention=convention)

