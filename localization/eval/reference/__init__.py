"""The yardstick: a reference track of a bag built without the filter, and the along-/cross-track
error of an estimate against it.

Every scan k is timed at the middle of its sweep, t_k (``core.scan.scan_time`` under the stamp
convention ``scan_stamp`` / ``scan_stamp_offset``, scan clock), and gets a base pose X_k in the map.

1. Matches (``track_matches``). Scan k is matched to the map by the correlative matcher
   (``core.matching``: branch and bound, then its Gauss–Newton finish), its beams moved to t_k with
   the odometry twist there (deskew), seeded by a running estimate: the previous one moved on by
   the dead-reckoned odometry O between the two scans, x̂⁻ = x̂ ⊕ O, P⁻ = P + Q(O), searched within
   ± 3σ of P⁻ (at least ``MIN_WINDOW``); the first scan from the given start pose
   (``START_WINDOW``) or, without one, a global match (a lattice over the free space scored on a
   blurred likelihood, its best poses matched and followed for a few seconds: the one whose
   matches score best wins). The running estimate takes the match as a measurement with its
   information Λ (below): P = (P⁻⁻¹ + Λ)⁻¹, x̂ = x̂⁻ + P Λ (z ⊖ x̂⁻) — across a corridor the match,
   along it the odometry. A match beyond the χ² gate (χ²₃ 0.999 = 16.27) widens P⁻ by χ²/16.27
   first: the odometry's noise is not known yet (a car's steering-based yaw rate may be off by
   1 rad/s), so a clear match wins — except after a gap (RELOCALIZE_GAP_S = 0.5 s without a match
   used), when the window has grown and a look-alike place may be in it: a match beyond the gate is
   then replaced by a match in the smallest window around the prediction when that one passes the
   gate, and otherwise followed only once RELOCALIZE_SCANS (5) such matches in a row agree with
   each other through the odometry (its σ × 3) and the last lies within the prediction's σ × 3
   (χ² with P⁻ × 9): the odometry may drift, it does not jump. A wrong match claims millimetres as
   confidently as a right one (Λ describes its own peak, not the look-alike places around it);
   this, and a pose that must lie in known free space, keep an aliased corridor or a changed room
   out of the track.
   The second pass, after a first smoothing (step 3): every scan matched again from the smoothed
   start with the odometry's time offset, speed scale and noise as the smoothing measured them,
   deskewed along the smoothed track's own motion (not the reported twist, whose noise would then
   enter the matches and pull the time offset toward 0).

2. Information of a match (``match_information``), from the scan's own beams and the map (no
   constant tuned to a lidar). At the match, beam i ends at p_i = (x, y) + R(θ) q_i with distance
   d_i to the map's free-space edge (``grids.signed_distance``, bilinear, in m) and unit gradient
   n_i; its Jacobian is J_i = [n_iᵀ, n_iᵀ R'(θ) q_i]. Inliers: |d_i| ≤ max(3σ_r, res), σ_r the
   robust spread (1.4826 MAD) of the beams within 3 cells of a wall. Consecutive inliers whose
   endpoints lie within max(2 res, 3 r_i Δα) of each other (Δα the scan's angular step, r_i the
   range) on a wall of the same orientation (n_i·n_j ≥ 0.8) form a segment s of m_s beams. The
   beams of a segment share the wall's position error b_s ~ N(0, σ_m²), σ_m = res/√12 (where in its
   cell the wall is), besides their own noise σ_r::

       Λ = Σ_s J_sᵀ (σ_r² I + σ_m² 11ᵀ)⁻¹ J_s = (1/σ_r²) Σ_s [J_sᵀJ_s − c_s (J_sᵀ1)(1ᵀJ_s)],
       c_s = σ_m² / (σ_r² + m_s σ_m²)

   so a wall pins its normal offset no better than σ_m however many beams hit it, and an axis a
   corridor does not constrain gets only what the beams on its ends give: a large variance.
   An axis (x, y, θ; along / across the track) is *constrained* by the match when its standard
   deviation (Λ⁻¹)^½ is at most τ_xy = res/2 (half a map cell), τ_θ = τ_xy / r̃ (r̃: the inliers'
   median range: a heading error of τ_θ moves a typical endpoint by τ_xy).

3. Smoothing (``smooth_track``): batch least squares over every X_k and the odometry's speed scale
   a, at the odometry's time offset δ (odometry stamped τ describes the motion at τ + δ; speed used
   a·v, as the localizer applies odom_speed_scale and odom_time_offset)::

       match k:     r = Lᵀ (X_k ⊖ Z_k),  L Lᵀ = Λ_k / s_m²                (θ wrapped)
       odometry k:  r = (X_{k−1}⁻¹ ⊕ X_k − Ô_k) / σ(Ô_k),  Ô_k = B(t_{k−1} − δ)⁻¹ ⊕ B(t_k − δ)
       prior:       (a − 1)/0.3

   with B the odometry dead-reckoned with a (``dead_reckon``) and σ(Ô) = (σ_xy, σ_xy, σ_θ):
   σ_xy = 0.05 |Ô_xy| + 0.02 m/rad |Ô_θ| + 0.01 m/√s √dt, σ_θ = 0.05 |Ô_θ| + 0.05 rad/m |Ô_xy| +
   0.01 rad/√s √dt, times s_x, s_y, s_θ. ``scipy.optimize.least_squares`` (trf, a sparse Jacobian:
   each factor touches one or two poses and a, given in closed form, a's column by differences)
   with a soft-L1 loss (scale 3). δ is the unknown the Jacobian cannot follow: the motion between
   two scans 25–100 ms apart changes with δ only through the twist's changes, which noisy
   messages dominate, and the cost has a kink wherever a scan's time crosses an odometry stamp
   (local minima every period). So δ comes from its profile: the odometry factors' Cauchy cost over
   δ in 2 ms steps (± 0.3 s; poses held, a in closed form, a prior δ/0.2 s), a parabola fitted ± 50 ms
   around the lowest point: δ its vertex, σ_δ = (½ / its curvature)^½. The bag then sets its own noise
   (variance component estimation): s² = Σχ² / Σr over each group of factors (matches; odometry
   x; y; θ), χ² their squared whitened residuals, r their redundancy numbers
   r = dof − tr(J_f Σ J_fᵀ) (what the rest of the problem does not absorb), factors beyond 3 s
   left out (iterated), s_m ≥ 1 (never more certain than the beams say); matches with χ² > 16.27 s_m² (χ²₃, 0.999)
   are rejected (a wrong match); solved again, twice. (A yaw-rate scale is not an unknown here:
   fitted against noisy reported yaw rates it shrinks toward 0; ``eval.calibration`` fits it over
   longer intervals.)

   Steps 1–3 run twice (the second pass of step 1, then the smoothing again).

4. Uncertainty of the smoothed track: Σ = (JᵀJ)⁻¹ at the solution (Cauchy weights included), its
   3 × 3 diagonal blocks (a sparse LU, solved block by block); with t̂ the direction of travel
   (the heading when standing) and n̂ ⊥ t̂: σ_along = (t̂ᵀ Σ_xy t̂)^½, σ_cross = (n̂ᵀ Σ_xy n̂)^½.
   A scan is *scored* (``good``) when both are at most one map cell, it lies within the span of
   the accepted matches, its smoothed pose is in the map's known free space (a track that
   crosses a wall has locked onto a look-alike place: counted as ``outside_free_space``) and the
   scan fits the map there (``pose_fit``: the share f_k of its returns ending within
   FIT_TOLERANCE_M of the free-space edge is at least FIT_SHARE = ½ of the bag's normal fit, the
   90th percentile of f over its accepted matches; else ``poor_fit``: a changed room, or a track
   the odometry or a look-alike match carried off, where neither it nor anyone knows the truth),
   and the track follows the odometry there (``odometry_consistency``: over every window of
   CONSISTENCY_WINDOW_S = 4 s, scans k → j, the distance the smoothed track covers, |X_k⁻¹ ⊕ X_j|_xy,
   may differ from the odometry's |Ô_xy| (at the fitted a, δ) by at most 3 σ_xy(Ô) + one map cell,
   σ the nominal noise model above (the bag's own scales are inflated by the very stretches this
   checks); distances, not vectors: a yaw-rate scale, which the smoothing does not fit, bends the
   odometry's path; every scan of a window that does
   not is ``inconsistent`` and not scored — unless the odometry covered less than the track, reports
   the wheels standing (speed < STANDSTILL_SPEED and |ω| < STANDSTILL_TURN) somewhere in every such
   window, and the scan fits the map there nearly as well as normal (f_k ≥ CONSISTENCY_FIT_SHARE =
   0.85 of the normal fit): a braking skid, wheels locked while the robot slides on, and the matches
   are right (a track that outruns rolling wheels has been carried off by look-alike matches).
   Wrong matches in a changed room can drag the smoothed track metres away from where the odometry
   says the robot went, and back in one step when the matches are right again), and no place near
   the track fits the scan clearly better (``better_fit_elsewhere``: every ELSEWHERE_EVERY_S = 0.5 s
   the first scan is matched within ELSEWHERE_WINDOW = ± 2.5 m, ± 0.4 rad of its track pose; when
   the match fits by ELSEWHERE_MARGIN = 0.15 more than the track, f_match ≥ f_k + 0.15, the whole
   half second is not scored: a track that odometry and look-alike matches carried through a changed
   room can come out of it on the wrong side of a wall and still fit half as well as normal, while
   the place the robot is fits nearly perfectly).

What it cannot see: an error the map shares (a wall drawn in the wrong place moves the track with
it), a uniform offset of the whole track along a corridor no scan constrains, and where no match
is accepted the track is the odometry's.

Errors of an estimate track x̂(t) against a reference x(t) (the estimate interpolated at the
reference's times), with t̂ the unit direction of travel of the reference and n̂ = t̂ rotated by
+90°::

    e = (x̂ − x, ŷ − y)       position error, |e|
    e_along = e · t̂          > 0: the estimate is ahead of the car, < 0 behind
    e_cross = e · n̂          > 0: left of the car's path

Lag: the time shift τ of the estimate track that minimises the mean position error,
``mean_k |x̂(t_k + τ) − x(t_k)|`` (τ > 0: the estimate describes the car τ seconds late), and, from
the along-track error alone, the least-squares fit e_along ≈ −v τ (v the reference speed).

The stages, one module each, in the order a bag goes through them: ``inputs`` (the bag's odometry and
scans, each scan's beams), ``odometry`` (dead reckoning and its noise), ``information`` (step 2),
``tracker`` (step 1, one scan after another), ``matching`` (step 1 for a whole bag: the start),
``smoother`` (step 3), ``marginals`` (step 4: the smoothed track's uncertainty), ``checks`` (step 4:
where a scan is scored), ``track`` (the reference track of a bag, a ``result.ReferenceTrack``),
``cache`` (the track kept on disk by the bag's content and the yardstick's arguments and code),
``errors`` (along-/cross-track errors), ``plot`` and ``cli``; ``constants`` holds the fixed settings,
``geometry`` the pose-track arithmetic they share.
"""
from __future__ import annotations

from localization.eval.reference.checks import (
    better_fit_elsewhere,
    odometry_consistency,
    pose_fit,
)
from localization.eval.reference.cli import main
from localization.eval.reference.constants import (
    CHI2_3_999,
    CHI2_MEDIANS,
    CONSISTENCY_FIT_SHARE,
    CONSISTENCY_SIGMAS,
    CONSISTENCY_WINDOW_S,
    ELSEWHERE_BEAMS,
    ELSEWHERE_EVERY_S,
    ELSEWHERE_MARGIN,
    ELSEWHERE_WINDOW,
    FIT_NORMAL_PERCENTILE,
    FIT_SHARE,
    FIT_TOLERANCE_M,
    GLOBAL_FOLLOW_S,
    GLOBAL_HYPOTHESES,
    GLOBAL_TRAVEL_M,
    LAG_SEARCH_S,
    LAG_STEP_S,
    MAX_WINDOW,
    MIN_WINDOW,
    NP,
    OFFSET_FIT_S,
    OFFSET_PRIOR,
    OFFSET_RANGE,
    OFFSET_STEP_S,
    PARAM_NAMES,
    RELOCALIZE_GAP_S,
    RELOCALIZE_NOISE,
    RELOCALIZE_SCANS,
    SCALE_BOUNDS,
    SCALE_PRIOR,
    STANDSTILL_SPEED,
    STANDSTILL_TURN,
    START_WINDOW,
)
from localization.eval.reference.errors import (
    TrackErrors,
    best_lag,
    error_metrics,
    lag_from_along,
    reference_metrics,
    track_errors,
    truth_decomposition,
)
from localization.eval.reference.geometry import (
    relative_difference,
    track_twists,
    travel_directions,
)
from localization.eval.reference.information import (
    MatchInformation,
    constrained_axes,
    edge_distance,
    match_information,
)
from localization.eval.reference.inputs import (
    ScanBeams,
    read_odometry,
    read_scans,
    scan_beams,
)
from localization.eval.reference.marginals import (
    _marginal_covariances,
    block_tridiagonal_inverse,
)
from localization.eval.reference.matching import (
    global_candidates,
    track_matches,
)
from localization.eval.reference.odometry import (
    OdometryNoise,
    dead_reckon,
    odometry_chain,
    odometry_chain_loop,
    odometry_inputs,
    odometry_twist_at,
)
from localization.eval.reference.plot import plot_reference
from localization.eval.reference.result import ReferenceTrack
from localization.eval.reference.smoother import (
    Smoothed,
    fit_offset,
    smooth_track,
)
from localization.eval.reference.track import build_reference, reference_for_bag
from localization.eval.reference.tracker import Matches

__all__ = [
    "CHI2_3_999",
    "CHI2_MEDIANS",
    "CONSISTENCY_FIT_SHARE",
    "CONSISTENCY_SIGMAS",
    "CONSISTENCY_WINDOW_S",
    "ELSEWHERE_BEAMS",
    "ELSEWHERE_EVERY_S",
    "ELSEWHERE_MARGIN",
    "ELSEWHERE_WINDOW",
    "FIT_NORMAL_PERCENTILE",
    "FIT_SHARE",
    "FIT_TOLERANCE_M",
    "GLOBAL_FOLLOW_S",
    "GLOBAL_HYPOTHESES",
    "GLOBAL_TRAVEL_M",
    "LAG_SEARCH_S",
    "LAG_STEP_S",
    "MAX_WINDOW",
    "MIN_WINDOW",
    "MatchInformation",
    "Matches",
    "NP",
    "OFFSET_FIT_S",
    "OFFSET_PRIOR",
    "OFFSET_RANGE",
    "OFFSET_STEP_S",
    "OdometryNoise",
    "PARAM_NAMES",
    "RELOCALIZE_GAP_S",
    "RELOCALIZE_NOISE",
    "RELOCALIZE_SCANS",
    "ReferenceTrack",
    "SCALE_BOUNDS",
    "SCALE_PRIOR",
    "STANDSTILL_SPEED",
    "STANDSTILL_TURN",
    "START_WINDOW",
    "ScanBeams",
    "Smoothed",
    "TrackErrors",
    "_marginal_covariances",
    "best_lag",
    "better_fit_elsewhere",
    "block_tridiagonal_inverse",
    "build_reference",
    "constrained_axes",
    "dead_reckon",
    "edge_distance",
    "error_metrics",
    "fit_offset",
    "global_candidates",
    "lag_from_along",
    "main",
    "match_information",
    "odometry_chain",
    "odometry_chain_loop",
    "odometry_consistency",
    "odometry_inputs",
    "odometry_twist_at",
    "plot_reference",
    "pose_fit",
    "read_odometry",
    "read_scans",
    "reference_for_bag",
    "reference_metrics",
    "relative_difference",
    "scan_beams",
    "smooth_track",
    "track_errors",
    "track_matches",
    "track_twists",
    "travel_directions",
    "truth_decomposition",
]
