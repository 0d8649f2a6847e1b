"""Calibration of a car from one bag: odometry timing and scales, laser mount, lidar range scale.

Every value is the correction the localizer applies (the parameters of the same names):

- ``odom_time_offset`` δ (s): odometry stamped τ describes the motion at τ + δ (odometry reported
  40 ms late → δ = −0.04);
- ``odom_speed_scale`` a: speed used = a × reported (vx, vy);
- ``odom_yaw_rate_scale`` b, ``odom_yaw_rate_bias`` c: yaw rate used = b × reported ωz + c;
- ``laser_offset_x/y/yaw`` m = (m_x, m_y, m_ψ): the laser's pose in base_link;
- ``lidar_scale_to_map_scale`` s: map metres per measured range unit.

1. Reference track (``localization.eval.reference``): each scan matched to the map, seeded by the
   previous good match carried forward with the odometry; only good (unambiguous) matches kept.
   The laser poses L_k = B_k ⊕ m do not depend on the mount assumed while matching.
2. Range scale: per good scan (every second scan), Gauss–Newton over (x, y, θ, s) of the laser pose and the range
   multiplier on the map's signed distance (``CorrelativeMatcher.refine_scale``); s = the median
   over scans, σ_s = the larger of 1.2533 · std / √N and the spread of the medians of 10
   consecutive blocks / √10 (neighbouring scans share walls). Then the track is matched again
   with ranges × s.
3. Odometry and mount: with B(t) = G_abc(t − δ) the dead-reckoned odometry (reported twists
   corrected by a, b, c, each integrated exactly as a constant twist over its period, which ends
   at its stamp), the predicted relative laser motion between scans k and k' (Δt ≈ 0.4 s)::

       ΔL̂ = m⁻¹ ⊕ (B(t_k) ⊖ B(t_k')) ⊕ m,      r = (ΔL − ΔL̂) / (σ_xy, σ_xy, σ_θ)

   is fit to the observed ΔL = L_k ⊖ L_k' by robust least squares (soft-L1) over
   p = (δ, a, b, c, m_x, m_y, m_ψ). Uncertainty: σ_p = sqrt(diag((JᵀJ)⁻¹) · s²_res · n_overlap),
   with n_overlap the number of pairs overlapping each one (they share scans, so their errors are
   correlated; the inflation keeps the figure honest).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from localization.core.geometry import compose, inverse, relative, wrap_angle
from localization.core.matching import CorrelativeMatcher, MatcherConfig
from localization.core.occupancy_map import OccupancyMap
from localization.core.scan import beam_angles, clean_ranges
from localization.eval.reference import build_reference, dead_reckon, read_odometry, read_scans

KEYS = ("odom_time_offset_s", "odom_speed_scale", "odom_yaw_rate_scale", "odom_yaw_rate_bias", "laser_offset_x",
        "laser_offset_y", "laser_offset_yaw", "lidar_scale_to_map_scale")
#: metrics key -> node parameter name
PARAM_NAMES = {"odom_time_offset_s": "odom_time_offset", "odom_speed_scale": "odom_speed_scale",
               "odom_yaw_rate_scale": "odom_yaw_rate_scale", "odom_yaw_rate_bias": "odom_yaw_rate_bias",
               "laser_offset_x": "laser_offset_x", "laser_offset_y": "laser_offset_y",
               "laser_offset_yaw": "laser_offset_yaw", "lidar_scale_to_map_scale": "lidar_scale_to_map_scale"}

PAIR_SPACING_S = 0.4
SIGMA_XY = 0.01  # m: residual scale of a relative laser translation
SIGMA_THETA = 0.005  # rad


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

    def as_dict(self) -> dict:
        return {**{k: float(self.values[k]) for k in KEYS},
                "uncertainty": {k: float(self.uncertainty[k]) for k in KEYS},
                "scans": self.scans, "good_scans": self.good_scans, "pairs": self.pairs,
                "residual_rms": self.residual_rms}

    def parameter_yaml(self, node: str = "particle_filter") -> str:
        lines = [f"# localization-calibrate: {self.good_scans} of {self.scans} scans matched, {self.pairs} pairs",
                 f"{node}:", "  ros__parameters:"]
        for k in KEYS:
            lines.append(f"    {PARAM_NAMES[k]}: {self.values[k]:.6g}  # ± {self.uncertainty[k]:.2g}")
        return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------------------------
# Estimation
# --------------------------------------------------------------------------------------------


def _pairs(t, spacing):
    i0, i1 = [], []
    j = 0
    for i in range(len(t)):
        j = max(j, i + 1)
        while j < len(t) and t[j] - t[i] < spacing:
            j += 1
        if j < len(t) and t[j] - t[i] <= 1.5 * spacing:
            i0.append(i)
            i1.append(j)
    return np.asarray(i0, dtype=int), np.asarray(i1, dtype=int)


def fit_odometry(laser_t, laser_poses, odom_t, twist, mount0=(0.275, 0.0, 0.0), spacing: float = PAIR_SPACING_S):
    """Least-squares (δ, a, b, c, m_x, m_y, m_ψ) from relative laser motions (module doc, step 3).
    Returns (values (7,), sigmas (7,), pairs, residual rms dict)."""
    from scipy.optimize import least_squares

    lt = np.asarray(laser_t, dtype=float)
    lp = np.asarray(laser_poses, dtype=float)
    i0, i1 = _pairs(lt, spacing)
    if len(i0) < 20:
        raise CalibrationError(f"only {len(i0)} pairs of good scans {spacing} s apart: too few to calibrate")
    obs = relative(lp[i0], lp[i1])
    t_rel = odom_t[0]
    ot = np.asarray(odom_t, dtype=float) - t_rel
    qa, qb = lt[i0] - t_rel, lt[i1] - t_rel
    scale = np.array([SIGMA_XY, SIGMA_XY, SIGMA_THETA])

    def residuals(p):
        delta, a, b, c, mx, my, myaw = p
        B0 = dead_reckon(ot, twist, qa - delta, a, b, c)
        B1 = dead_reckon(ot, twist, qb - delta, a, b, c)
        dB = relative(B0, B1)
        m = np.array([mx, my, myaw])
        pred = compose(compose(inverse(m), dB), m)
        r = obs - pred
        r[:, 2] = wrap_angle(r[:, 2])
        return (r / scale).ravel()

    p0 = np.array([0.0, 1.0, 1.0, 0.0, *mount0], dtype=float)
    lo = np.array([-0.5, 0.5, 0.5, -1.0, -2.0, -2.0, -math.pi])
    hi = np.array([0.5, 2.0, 2.0, 1.0, 2.0, 2.0, math.pi])
    sol = least_squares(residuals, np.clip(p0, lo + 1e-9, hi - 1e-9), bounds=(lo, hi), loss="soft_l1", f_scale=2.0,
                        x_scale=np.array([0.01, 0.01, 0.01, 0.01, 0.01, 0.01, 0.01]),
                        diff_step=np.array([1e-4, 1e-5, 1e-5, 1e-5, 1e-5, 1e-5, 1e-5]))
    r = residuals(sol.x).reshape(-1, 3) * scale
    J = sol.jac
    n, p = J.shape
    s2 = 2.0 * sol.cost / max(n - p, 1)
    try:
        cov = np.linalg.inv(J.T @ J) * s2
    except np.linalg.LinAlgError:
        cov = np.full((p, p), np.inf)
    period = float(np.median(np.diff(lt))) if len(lt) > 1 else spacing
    overlap = max(1.0, spacing / max(period, 1e-3))
    sig = np.sqrt(np.clip(np.diag(cov), 0, None) * overlap)
    rms = {"xy_m": float(np.sqrt(np.mean(r[:, :2] ** 2))), "theta_rad": float(np.sqrt(np.mean(r[:, 2] ** 2)))}
    return sol.x, sig, len(i0), rms


def fit_range_scale(matcher: CorrelativeMatcher, scans, laser_poses, good, max_scans: int = 300):
    """Median range multiplier over good scans (module doc, step 2) and its 1 σ."""
    idx = np.flatnonzero(good)
    if idx.size > max_scans:
        idx = idx[np.unique(np.linspace(0, idx.size - 1, max_scans).astype(int))]
    values = []
    for k in idx:
        s = scans[k]
        n = np.asarray(s.ranges).size
        ranges = clean_ranges(s.ranges, s.range_min, s.range_max)
        est = matcher.refine_scale(ranges, beam_angles(n, s.angle_min, s.angle_max, s.angle_increment),
                                   laser_poses[k])
        if est is not None:
            values.append(est)
    v = np.asarray(values, dtype=float)
    if v.size < 5:
        raise CalibrationError(f"only {v.size} scans gave a range scale: too few")
    # neighbouring scans see the same walls: their errors are correlated. The spread of the
    # medians of (up to) 10 consecutive blocks is the honest figure when it is the larger.
    sigma = 1.2533 * v.std() / math.sqrt(v.size)
    blocks = np.array_split(v, min(10, v.size // 5))
    if len(blocks) >= 3:
        sigma = max(sigma, float(np.std([np.median(b) for b in blocks], ddof=1) / math.sqrt(len(blocks))))
    return float(np.median(v)), float(sigma), int(v.size)


def calibrate(scans, odom_t, twist, occupancy_map: OccupancyMap, initial_pose, mount0=(0.275, 0.0, 0.0),
              config: MatcherConfig | None = None, log=None) -> CalibrationResult:
    """Calibrate from scans (``ScanData``), odometry (stamps, twists (M, 3)) and a map."""
    say = log or (lambda *_: None)
    if len(scans) < 20:
        raise CalibrationError(f"only {len(scans)} scans: too few to calibrate")
    if len(odom_t) < 10:
        raise CalibrationError(f"only {len(odom_t)} odometry messages: too few to calibrate")
    odom = (np.asarray(odom_t, dtype=float), np.asarray(twist, dtype=float))
    matcher = CorrelativeMatcher(occupancy_map, config)
    say(f"matching {len(scans)} scans ...")
    every = scans[::2]  # the range scale needs fewer scans: every second one, seeded through the odometry
    ref = build_reference(every, occupancy_map, mount0, initial_pose=initial_pose, config=config, odometry=odom,
                          deskew_pass=False)
    if ref.counts["good"] < 10:
        raise CalibrationError(f"only {ref.counts['good']} of {len(every)} scans matched the map well: check "
                               "the map and --initial-pose")
    s, s_sig, _ = fit_range_scale(matcher, every, ref.laser_poses, ref.good)
    say(f"range scale {s:.5f} ± {s_sig:.5f}; matching again with it ...")
    ref = build_reference(scans, occupancy_map, mount0, initial_pose=initial_pose, config=config, range_scale=s,
                          odometry=odom)
    lt, lp = ref.t[ref.good], ref.laser_poses[ref.good]
    say(f"fitting odometry and mount on {len(lt)} good scans ...")
    x, sig, pairs, rms = fit_odometry(lt, lp, odom[0], odom[1], mount0)
    values = dict(zip(KEYS[:7], (float(v) for v in x)))
    values["laser_offset_yaw"] = float(wrap_angle(values["laser_offset_yaw"]))
    values["lidar_scale_to_map_scale"] = s
    unc = dict(zip(KEYS[:7], (float(v) for v in sig)))
    unc["lidar_scale_to_map_scale"] = s_sig
    return CalibrationResult(values=values, uncertainty=unc, scans=len(scans), good_scans=int(ref.good.sum()),
                             pairs=pairs, residual_rms=rms)


def calibrate_bag(bag_path, occupancy_map: OccupancyMap, scan_topic: str = "/scan", odom_topic: str = "/odom",
                  initial_pose=None, mount0=(0.275, 0.0, 0.0), config: MatcherConfig | None = None,
                  log=None) -> CalibrationResult:
    scans = read_scans(bag_path, scan_topic)
    odom_t, twist = read_odometry(bag_path, odom_topic)
    if initial_pose is None:
        initial_pose = initial_pose_from_bag(bag_path)
    if initial_pose is None:
        raise CalibrationError("no initial pose: give --initial-pose X,Y,YAW (the bag has no /initialpose)")
    return calibrate(scans, odom_t, twist, occupancy_map, initial_pose, mount0, config, log)


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
