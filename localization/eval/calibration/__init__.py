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

Modules by stage: ``result`` (the keys, the parameters they set, ``CalibrationResult``),
``range_model`` (step 2), ``odometry`` (steps 3–4), ``pipeline`` (step 1 and the order: ``calibrate``,
``calibrate_bag``), ``stamps`` (the scan stamp convention). Every public name is importable from here.
"""
from __future__ import annotations

from localization.eval.calibration.odometry import (
    PAIR_SPACING_S,
    SIGMA_THETA,
    SIGMA_XY,
    SLIP_MAD_FACTOR,
    SLIP_ROUNDS,
    SLIP_SPEED_FRACTION,
    dead_reckon_channels,
    fit_odometry,
    slip_mask,
)
from localization.eval.calibration.pipeline import calibrate, calibrate_bag, initial_pose_from_bag
from localization.eval.calibration.range_model import MAX_RANGE_SCANS, fit_range_model, range_model_scan
from localization.eval.calibration.result import KEYS, PARAM_NAMES, CalibrationError, CalibrationResult
from localization.eval.calibration.stamps import StampCheck, check_scan_stamps

__all__ = ["KEYS", "MAX_RANGE_SCANS", "PAIR_SPACING_S", "PARAM_NAMES", "SIGMA_THETA", "SIGMA_XY", "SLIP_MAD_FACTOR",
           "SLIP_ROUNDS", "SLIP_SPEED_FRACTION", "CalibrationError", "CalibrationResult", "StampCheck", "calibrate",
           "calibrate_bag", "check_scan_stamps", "dead_reckon_channels", "fit_odometry", "fit_range_model",
           "initial_pose_from_bag", "range_model_scan", "slip_mask"]
