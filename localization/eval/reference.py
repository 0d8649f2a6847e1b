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
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from localization.core.geometry import compose, integrate_twists, relative, wrap_angle
from localization.core.matching import CorrelativeMatcher, MatcherConfig, endpoints_base
from localization.core.matching.grids import signed_distance
from localization.core.occupancy_map import OccupancyMap
from localization.core.scan import beam_angles, clean_ranges, scan_time, sweep_increment
from localization.eval.datasets import bag_odometry, read_scans  # noqa: F401 - read_scans re-exported
from localization.eval.metrics import FALSE_RECOVERY_M, false_recoveries, interpolate_poses

LAG_SEARCH_S = 0.25  # ± seconds searched for the best lag
LAG_STEP_S = 0.002
STANDSTILL_SPEED = 0.1  # m/s: below, the direction of travel is the reference heading
STANDSTILL_TURN = 0.1  # rad/s: odometry below this and STANDSTILL_SPEED reports the wheels standing

START_WINDOW = (1.0, 0.5)  # m, rad: the first scan is searched this far around a given start pose
MIN_WINDOW = (0.25, 0.1)  # m, rad: the tracking search window is never smaller ...
MAX_WINDOW = (1.5, 0.6)  # m, rad: ... nor larger
CHI2_3_999 = 16.27  # χ² (3 dof) exceeded with probability 0.001: a match inconsistent with the track
CHI2_MEDIANS = {1: 0.4549, 2: 1.3863, 3: 2.3660}  # medians of χ² with 1, 2, 3 dof
GLOBAL_FOLLOW_S = 4.0  # s: a global hypothesis is followed at least this long ...
GLOBAL_TRAVEL_M = 3.0  # m: ... and until the odometry has moved this far (unless it is the last one left)
GLOBAL_HYPOTHESES = 8
RELOCALIZE_SCANS = 5  # after a gap, matches away from the prediction are followed only when this many agree ...
RELOCALIZE_GAP_S = 0.5  # s: ... a gap: this long without a match used
RELOCALIZE_NOISE = 3.0  # ... with each other through the odometry, its σ × this
FIT_TOLERANCE_M = 0.10  # m: a return "fits" when it ends this close to the map's free-space edge (as the agreement)
FIT_SHARE = 0.5  # a scan is scored only where its smoothed pose fits at least this share of the bag's normal fit
FIT_NORMAL_PERCENTILE = 90  # the bag's normal fit: this percentile over its accepted matches
CONSISTENCY_WINDOW_S = 4.0  # s: the smoothed track must follow the odometry over windows this long ...
CONSISTENCY_SIGMAS = 3.0  # ... within this many σ of the nominal odometry noise model plus a map cell,
CONSISTENCY_FIT_SHARE = 0.85  # ... unless the odometry covered less and the scan fits this share of the normal fit
ELSEWHERE_WINDOW = (2.5, 0.4)  # m, rad: every ELSEWHERE_EVERY_S the map is searched this far around the track ...
ELSEWHERE_EVERY_S = 0.5  # s
ELSEWHERE_MARGIN = 0.15  # ... and a pose that fits this much better than the track's leaves its scans unscored
ELSEWHERE_BEAMS = 120  # beams (evenly decimated) of that search
PARAM_NAMES = ("speed_scale", "time_offset_s")  # the odometry's unknowns (a, δ)
NP = 1  # of them solved with the poses (a); δ by its profile (module doc, step 3)
SCALE_PRIOR, SCALE_BOUNDS = 0.3, (0.5, 2.0)  # σ of the prior on a − 1; beyond the bounds the smoothing failed
OFFSET_PRIOR = 0.2  # s: σ of the prior on δ
OFFSET_RANGE, OFFSET_STEP_S, OFFSET_FIT_S = 0.3, 0.002, 0.05  # s: δ searched in ± range, fitted ± fit around the best


# --------------------------------------------------------------------------------------------
# Reading a bag
# --------------------------------------------------------------------------------------------


def read_odometry(bag_path, odom_topic: str, odom_frame: str = "odom",
                  base_frame: str = "base_link") -> tuple[np.ndarray, np.ndarray]:
    """Stamps (M,) and reported twists (M, 3: vx, vy, ωz) of the bag's odometry in stamp order: the
    Odometry topic, else TF ``odom_frame → base_frame`` (``datasets.bag_odometry``)."""
    return bag_odometry(bag_path, odom_topic, odom_frame, base_frame).arrays()


# --------------------------------------------------------------------------------------------
# Dead reckoning
# --------------------------------------------------------------------------------------------


def odometry_chain(odom_t, twist, a=1.0, b=1.0, c=0.0) -> np.ndarray:
    """Odometry poses (M, 3) at the stamps, from 0 at the first: twist k (corrected: a·(vx, vy),
    b·ωz + c) held over (t_{k−1}, t_k], composed in closed form (θ_k = Σ dθ, p_k = Σ R(θ_{j−1}) d_j)."""
    t = np.asarray(odom_t, dtype=float)
    tw = np.asarray(twist, dtype=float).reshape(-1, 3)
    M = len(t)
    poses = np.zeros((M, 3))
    if M < 2:
        return poses
    steps = integrate_twists(a * tw[1:, 0], a * tw[1:, 1], b * tw[1:, 2] + c, np.diff(t))
    th = np.concatenate([[0.0], np.cumsum(steps[:, 2])])
    cs, sn = np.cos(th[:-1]), np.sin(th[:-1])
    poses[1:, 0] = np.cumsum(cs * steps[:, 0] - sn * steps[:, 1])
    poses[1:, 1] = np.cumsum(sn * steps[:, 0] + cs * steps[:, 1])
    poses[:, 2] = wrap_angle(th)
    return poses


def odometry_chain_loop(odom_t, twist, a=1.0, b=1.0, c=0.0) -> np.ndarray:
    """Reference of ``odometry_chain``: the same composition one step at a time (tests)."""
    t = np.asarray(odom_t, dtype=float)
    tw = np.asarray(twist, dtype=float).reshape(-1, 3)
    poses = np.zeros((len(t), 3))
    for k in range(1, len(t)):
        step = integrate_twists(a * tw[k, 0], a * tw[k, 1], b * tw[k, 2] + c, t[k] - t[k - 1])
        poses[k] = compose(poses[k - 1], step)
    return poses


def odometry_inputs(odom_t, twist, query_t):
    """The stamps (M,), twists (M, 3) and query times as float arrays (dead reckoning's inputs)."""
    return (np.asarray(odom_t, dtype=float), np.asarray(twist, dtype=float).reshape(-1, 3),
            np.asarray(query_t, dtype=float))


def dead_reckon(odom_t, twist, query_t, a=1.0, b=1.0, c=0.0, chain=None) -> np.ndarray:
    """Odometry pose (odom frame, 0 at the first stamp) at ``query_t`` (odometry clock): the chain
    at the stamp before, moved on by the twist of the period holding the query (beyond the last
    stamp the last twist goes on, before the first one the first period's twist is run backwards:
    a robot already moving when the bag starts). ``chain``: ``odometry_chain`` of the same
    (a, b, c), when already computed."""
    t, tw, q = odometry_inputs(odom_t, twist, query_t)
    M = len(t)
    if M < 2:
        return np.zeros(q.shape + (3,))
    poses = odometry_chain(t, tw, a, b, c) if chain is None else chain
    k = np.clip(np.searchsorted(t, q, side="left"), 1, M - 1)  # the period (t_{k-1}, t_k] holding q
    dt = q - t[k - 1]  # < 0 only before the first stamp
    return compose(poses[k - 1], integrate_twists(a * tw[k, 0], a * tw[k, 1], b * tw[k, 2] + c, dt))


def odometry_twist_at(odom_t, twist, query_t) -> np.ndarray:
    """The reported twist (…, 3) of the period holding each query time (the last one beyond)."""
    t = np.asarray(odom_t, dtype=float)
    tw = np.asarray(twist, dtype=float).reshape(-1, 3)
    if len(t) < 2:
        return np.zeros(np.shape(query_t) + (3,)) if len(t) == 0 else np.broadcast_to(tw[0], np.shape(query_t) + (3,))
    k = np.clip(np.searchsorted(t, np.asarray(query_t, dtype=float), side="left"), 1, len(t) - 1)
    return tw[k]


@dataclass(frozen=True)
class OdometryNoise:
    """Standard deviation of the odometry's motion between two scans (module doc, step 3)."""

    xy_per_m: float = 0.05  # m per m travelled
    xy_per_rad: float = 0.02  # m per rad turned
    xy_per_sqrt_s: float = 0.01  # m per √s
    theta_per_rad: float = 0.05  # rad per rad turned
    theta_per_m: float = 0.05  # rad per m travelled
    theta_per_sqrt_s: float = 0.01  # rad per √s
    along: float = 1.0  # multiplies σ of dx (the odometry's own forward axis) ...
    across: float = 1.0  # ... and of dy

    def scaled(self, x: float, y: float, theta: float) -> "OdometryNoise":
        """The same model with σ_x × x, σ_y × y and every heading term × theta."""
        return replace(self, along=self.along * x, across=self.across * y, theta_per_rad=self.theta_per_rad * theta,
                       theta_per_m=self.theta_per_m * theta, theta_per_sqrt_s=self.theta_per_sqrt_s * theta)

    def sigmas(self, delta, dt) -> np.ndarray:
        """(…, 3) σ of (dx, dy, dθ) for relative motions ``delta`` (…, 3) over ``dt`` (…) s."""
        d = np.asarray(delta, dtype=float)
        s = np.hypot(d[..., 0], d[..., 1])
        r = np.abs(d[..., 2])
        root = np.sqrt(np.clip(np.asarray(dt, dtype=float), 0.0, None))
        sxy = self.xy_per_m * s + self.xy_per_rad * r + self.xy_per_sqrt_s * root + 1e-4
        sth = self.theta_per_rad * r + self.theta_per_m * s + self.theta_per_sqrt_s * root + 1e-4
        return np.stack([sxy * self.along, sxy * self.across, sth], axis=-1)


# --------------------------------------------------------------------------------------------
# The information of a match
# --------------------------------------------------------------------------------------------


def edge_distance(occupancy_map: OccupancyMap, points) -> tuple[np.ndarray, np.ndarray]:
    """Distance (m, > 0 in free space) of world points (N, 2) to the map's free-space edge
    (``grids.signed_distance``, bilinear) and its gradient (N, 2) in the world frame."""
    sdf = signed_distance(occupancy_map)
    res = occupancy_map.resolution
    g = occupancy_map.world_to_grid_continuous(np.asarray(points, dtype=float).reshape(-1, 2))
    h, w = sdf.shape
    x, y = g[:, 0] - 0.5, g[:, 1] - 0.5
    c0 = np.clip(np.floor(x).astype(np.int64), 0, w - 2)
    r0 = np.clip(np.floor(y).astype(np.int64), 0, h - 2)
    fx, fy = np.clip(x - c0, 0, 1), np.clip(y - r0, 0, 1)
    s00, s01 = sdf[r0, c0], sdf[r0, c0 + 1]
    s10, s11 = sdf[r0 + 1, c0], sdf[r0 + 1, c0 + 1]
    d = ((1 - fy) * ((1 - fx) * s00 + fx * s01) + fy * ((1 - fx) * s10 + fx * s11)) * res
    gu = (1 - fy) * (s01 - s00) + fy * (s11 - s10)
    gv = (1 - fx) * (s10 - s00) + fx * (s11 - s01)
    cy, sy = math.cos(occupancy_map.origin[2]), math.sin(occupancy_map.origin[2])
    grad = np.stack([gu * cy - gv * sy, gu * sy + gv * cy], axis=1)
    return d, grad


@dataclass
class MatchInformation:
    """What one match tells (module doc, step 2)."""

    information: np.ndarray  # (3, 3) Λ of (x, y, θ) in the map frame, 1/m², 1/(m rad), 1/rad²
    inliers: int  # beams ending on a wall
    segments: int  # wall segments they form
    sigma_range: float  # m, σ_r
    median_range: float  # m, r̃ of the inliers
    inlier_fraction: float  # of the valid beams

    @property
    def covariance(self) -> np.ndarray:
        return _safe_inverse(self.information)


def _safe_inverse(info) -> np.ndarray:
    """Λ⁻¹ with a faint prior (100 m, 100 m, 10 rad) keeping a degenerate Λ invertible."""
    return np.linalg.inv(np.asarray(info, dtype=float) + np.diag([1e-4, 1e-4, 1e-2]))


def match_information(occupancy_map: OccupancyMap, ranges, angles, mount, pose, angle_increment: float,
                      range_scale: float = 1.0, max_range: float = np.inf, beam_dt=None,
                      twist=None) -> MatchInformation:
    """Λ of a base pose for one scan (module doc, step 2); the endpoints as the matcher makes them
    (``endpoints_base``: valid beams in scan order, deskewed with ``beam_dt`` and ``twist``)."""
    res = occupancy_map.resolution
    q, r = endpoints_base(ranges, angles, mount, range_scale, max_range, beam_dt, twist)
    empty = MatchInformation(np.zeros((3, 3)), 0, 0, float("nan"), float("nan"), 0.0)
    if len(q) < 3:
        return empty
    x, y, th = (float(v) for v in pose)
    c, s = math.cos(th), math.sin(th)
    rx, ry = c * q[:, 0] - s * q[:, 1], s * q[:, 0] + c * q[:, 1]  # endpoint − base, map frame
    d, grad = edge_distance(occupancy_map, np.stack([x + rx, y + ry], axis=1))
    near = np.abs(d) <= 3 * res
    if np.count_nonzero(near) < 3:
        return MatchInformation(np.zeros((3, 3)), 0, 0, float("nan"), float("nan"), 0.0)
    dn = d[near]
    sigma_r = max(1.4826 * float(np.median(np.abs(dn - np.median(dn)))), 0.1 * res)
    gnorm = np.hypot(grad[:, 0], grad[:, 1])
    inl = (np.abs(d) <= max(3 * sigma_r, res)) & (gnorm > 0.3)
    idx = np.flatnonzero(inl)
    m = idx.size
    if m < 3:
        return MatchInformation(np.zeros((3, 3)), int(m), 0, sigma_r, float("nan"), m / len(q))
    n = grad[idx] / gnorm[idx, None]
    J = np.stack([n[:, 0], n[:, 1], n[:, 0] * -ry[idx] + n[:, 1] * rx[idx]], axis=1)
    # segments: consecutive inliers close together on a wall of the same orientation
    px, py = x + rx[idx], y + ry[idx]
    gap = np.hypot(np.diff(px), np.diff(py))
    limit = np.maximum(2 * res, 3 * r[idx[:-1]] * abs(angle_increment))
    same = (gap <= limit) & (np.sum(n[1:] * n[:-1], axis=1) >= 0.8)
    label = np.concatenate([[0], np.cumsum(~same)])
    nseg = int(label[-1]) + 1
    sum_j = np.zeros((nseg, 3))
    np.add.at(sum_j, label, J)
    count = np.bincount(label, minlength=nseg).astype(float)
    sigma_m2 = res * res / 12.0
    cs = sigma_m2 / (sigma_r ** 2 + count * sigma_m2)
    info = (J.T @ J - (sum_j * cs[:, None]).T @ sum_j) / sigma_r ** 2
    info = 0.5 * (info + info.T)
    return MatchInformation(info, int(m), nseg, sigma_r, float(np.median(r[idx])), m / len(q))


def constrained_axes(info, median_range: float, res: float, directions=None) -> np.ndarray:
    """Which of x, y, θ (and, with ``directions`` (2,) unit travel direction, along and across it)
    a match with information ``info`` pins down (module doc, step 2): (3,) or (5,) bool."""
    cov = _safe_inverse(info)
    tau = 0.5 * res
    tau_th = tau / median_range if np.isfinite(median_range) and median_range > 0 else 0.0
    out = [cov[0, 0] <= tau ** 2, cov[1, 1] <= tau ** 2, cov[2, 2] <= tau_th ** 2]
    if directions is not None:
        u = np.asarray(directions, dtype=float)
        nrm = np.array([-u[1], u[0]])
        out += [u @ cov[:2, :2] @ u <= tau ** 2, nrm @ cov[:2, :2] @ nrm <= tau ** 2]
    return np.array(out, dtype=bool)


# --------------------------------------------------------------------------------------------
# 1. Matching every scan
# --------------------------------------------------------------------------------------------


@dataclass
class ScanBeams:
    """One scan's beams as the matcher takes them."""

    ranges: np.ndarray
    angles: np.ndarray
    angle_increment: float
    beam_dt: np.ndarray | None  # s of each beam after the scan's time (mid-sweep); None: no sweep timing


def scan_beams(scans, deskew: bool = True, shorten: float = 0.0) -> list[ScanBeams]:
    """The matcher's view of each scan; ``deskew`` False: no per-beam timing (a rigid scan);
    ``shorten`` (lidar metres) is taken off every return (the wall surface's depth behind the map's
    free-space edge, over the range scale: s·(z − o/s) = s·z − o)."""
    cache: dict = {}
    out = []
    for s in scans:
        n = np.asarray(s.ranges).size
        key = (n, s.angle_min, s.angle_max, s.angle_increment)
        if key not in cache:
            cache[key] = beam_angles(*key)
        angles = cache[key]
        inc = float(angles[1] - angles[0]) if n > 1 else float(s.angle_increment)
        ti = sweep_increment(s) if deskew else 0.0
        beam_dt = (np.arange(n) - 0.5 * (n - 1)) * ti if ti > 0 else None
        ranges = clean_ranges(s.ranges, s.range_min, s.range_max)
        if shorten:
            ranges = np.maximum(ranges - shorten, 0.0)
        out.append(ScanBeams(ranges, angles, inc, beam_dt))
    return out


@dataclass
class Matches:
    """Per scan: the match Z_k (NaN: none usable), its information, score and what it constrains."""

    poses: np.ndarray  # (K, 3)
    information: np.ndarray  # (K, 3, 3)
    score: np.ndarray  # (K,) matcher score (mean endpoint likelihood)
    median_range: np.ndarray  # (K,) m
    inlier_fraction: np.ndarray  # (K,)
    usable: np.ndarray  # (K,) bool
    filtered: np.ndarray  # (K, 3) the running estimate after each scan (the smoother's start)
    start: str = ""  # how the first pose was found


class _Tracker:
    """Matches scans one after another (module doc, step 1)."""

    def __init__(self, occupancy_map, mount, beams, t, odometry, config, range_scale, noise, odometry_fit=(1.0, 0.0)):
        self.gated: list = []  # (scan, χ²) of the matches kept out after a gap
        self.map = occupancy_map
        self.matcher = CorrelativeMatcher(occupancy_map, config)
        self.mount = tuple(float(v) for v in mount)
        self.beams, self.t = beams, t
        self.odo_t, self.odo_tw = odometry
        a, delta = odometry_fit  # the speed scale and time offset the smoothing found (second pass)
        self.B = dead_reckon(self.odo_t, self.odo_tw, np.asarray(t, dtype=float) - delta, a)
        self.twist = odometry_twist_at(self.odo_t, self.odo_tw, t)
        self.range_scale = range_scale
        self.noise = noise
        self.max_range = self.matcher.config.max_range

    def match(self, k, seed, window):
        b = self.beams[k]
        skew = {} if b.beam_dt is None else {"beam_dt": b.beam_dt, "twist": self.twist[k]}
        r = self.matcher.match(b.ranges, b.angles, self.mount, seed, window[0], window[1], self.range_scale, **skew)
        if r is None:
            return None, None
        info = match_information(self.map, b.ranges, b.angles, self.mount, r.pose, b.angle_increment,
                                 self.range_scale, self.max_range, b.beam_dt, skew.get("twist"))
        return r, info

    def usable(self, r, info, seed, window) -> bool:
        if r is None or info.inliers < 10 or info.segments < 2:
            return False
        if not bool(self.map.is_free(np.asarray(r.pose[:2], dtype=float))):
            return False  # the robot stands in known free space, never in a wall or beyond the map
        if not r.at_window_edge:
            return True
        # on the window's edge: fine only along a direction the match does not constrain (a corridor)
        cov = _safe_inverse(info.information)
        d = np.asarray(r.pose[:2]) - np.asarray(seed[:2])
        moved_xy = np.hypot(*d) >= window[0] - 1.5 * self.map.resolution
        moved_th = abs(float(wrap_angle(r.pose[2] - seed[2]))) >= window[1] - 2 * r.angle_step
        if moved_th and cov[2, 2] <= (0.5 * self.map.resolution / max(info.median_range, 1e-3)) ** 2:
            return False
        if moved_xy:
            u = d / max(np.hypot(*d), 1e-12)
            return bool(u @ cov[:2, :2] @ u > (0.5 * self.map.resolution) ** 2)
        return True

    def window(self, P):
        sxy = math.sqrt(max(np.linalg.eigvalsh(P[:2, :2]).max(), 0.0))
        return (float(np.clip(3 * sxy, MIN_WINDOW[0], MAX_WINDOW[0])),
                float(np.clip(3 * math.sqrt(max(P[2, 2], 0.0)), MIN_WINDOW[1], MAX_WINDOW[1])))

    def predict(self, k0, k1, x, P):
        step = relative(self.B[k0], self.B[k1])
        sig = self.noise.sigmas(step, self.t[k1] - self.t[k0])
        c, s = math.cos(x[2]), math.sin(x[2])
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        # the uncertainty of the heading moves the predicted position sideways
        G = np.eye(3)
        G[0, 2], G[1, 2] = -(s * step[0] + c * step[1]), c * step[0] - s * step[1]
        return compose(x, step), G @ P @ G.T + R @ np.diag(sig ** 2) @ R.T

    @staticmethod
    def update(x, P, z, info):
        """Information-weighted update; an innovation beyond the χ² gate says the odometry moved the
        robot less well than P⁻ assumed: P⁻ is widened by χ²/gate first (a strong match wins)."""
        e = relative_difference(z, x)
        chi2 = float(e @ np.linalg.inv(P + _safe_inverse(info)) @ e)
        if chi2 > CHI2_3_999:
            P = P * (chi2 / CHI2_3_999)
        Pn = np.linalg.inv(np.linalg.inv(P) + info)
        xn = np.asarray(x, dtype=float) + Pn @ (info @ e)
        xn[2] = float(wrap_angle(xn[2]))
        return xn, 0.5 * (Pn + Pn.T), chi2

    def run(self, k_start, x0, P0, out, k_stop=None, first_window=None, k_prev=None):
        """Track from scan k_start to k_stop (exclusive), the seed x0 with covariance P0 at scan
        k_start (or at ``k_prev``, then moved on by the odometry); fills ``out`` (a dict of arrays)."""
        K = len(self.beams) if k_stop is None else k_stop
        x, P = np.asarray(x0, dtype=float), np.asarray(P0, dtype=float)
        pending: list = []
        last_ok = None  # time of the last match used
        for k in range(k_start, K):
            if k > k_start or k_prev is not None:
                x, P = self.predict(k - 1 if k > k_start else k_prev, k, x, P)
            window = first_window if (k == k_start and first_window is not None) else self.window(P)
            r, info = self.match(k, x, window)
            if r is not None and r.at_window_edge and not self.usable(r, info, x, window):
                r2, info2 = self.match(k, r.pose, window)  # once more around the edge
                if r2 is not None:
                    r, info, x_seed = r2, info2, r.pose
                else:
                    x_seed = x
            else:
                x_seed = x
            ok = self.usable(r, info, x_seed, window)
            if r is not None:
                out["score"][k] = r.score
            gap = self.t[k] - last_ok if last_ok is not None else 0.0
            if ok and k > k_start and gap > RELOCALIZE_GAP_S:
                chi2 = self._chi2(r, info, x, P)
                if chi2 > CHI2_3_999:
                    near, near_info = self.match(k, x, MIN_WINDOW)  # a match where the odometry says?
                    if self.usable(near, near_info, x, MIN_WINDOW) and self._chi2(near, near_info, x, P) <= CHI2_3_999:
                        r, info, pending = near, near_info, []
                    else:
                        self.gated.append((k, chi2))
                        ok, pending = False, (pending + [(k, r.pose, info)])[-RELOCALIZE_SCANS:]
                        plausible = self._chi2(r, info, x, P * RELOCALIZE_NOISE ** 2) <= CHI2_3_999
                        if plausible and self._consistent(pending):  # map and odometry agree on another place
                            drift = np.diag(self.noise.sigmas(np.zeros(3), 1.0) ** 2)
                            x, P, ok, pending = r.pose, _safe_inverse(info.information) + drift, True, []
                else:
                    pending = []
            if ok:
                last_ok = self.t[k]
                out["poses"][k] = r.pose
                out["information"][k] = info.information
                out["median_range"][k] = info.median_range
                out["inlier_fraction"][k] = info.inlier_fraction
                x, P, _ = self.update(x, P, r.pose, info.information)
                out["usable"][k] = True
            out["filtered"][k] = x
        return x, P

    @staticmethod
    def _chi2(r, info, x, P) -> float:
        e = relative_difference(r.pose, x)
        return float(e @ np.linalg.inv(P + _safe_inverse(info.information)) @ e)

    def _consistent(self, pending) -> bool:
        """RELOCALIZE_SCANS matches in a row, each rejected by the prediction, that agree with each
        other through the odometry (χ² of their relative motion against the odometry's)."""
        if len(pending) < RELOCALIZE_SCANS:
            return False
        for (k0, z0, i0), (k1, z1, i1) in zip(pending[:-1], pending[1:]):
            step = relative(self.B[k0], self.B[k1])
            S = _safe_inverse(i0.information) + _safe_inverse(i1.information) \
                + np.diag((RELOCALIZE_NOISE * self.noise.sigmas(step, self.t[k1] - self.t[k0])) ** 2)
            e = relative_difference(compose(z0, step), z1)
            if float(e @ np.linalg.inv(S) @ e) > CHI2_3_999:
                return False
        return True


def relative_difference(a, b) -> np.ndarray:
    """a − b for poses (…, 3), the angle wrapped."""
    d = np.asarray(a, dtype=float) - np.asarray(b, dtype=float)
    d[..., 2] = wrap_angle(d[..., 2])
    return d


def _empty_matches(K):
    return {"poses": np.full((K, 3), np.nan), "information": np.zeros((K, 3, 3)), "score": np.full(K, np.nan),
            "median_range": np.full(K, np.nan), "inlier_fraction": np.zeros(K), "usable": np.zeros(K, dtype=bool),
            "filtered": np.full((K, 3), np.nan)}


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
    """Step 1 of the module doc for every scan (``t``: their times on the odometry's clock).
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


# --------------------------------------------------------------------------------------------
# 2. Smoothing
# --------------------------------------------------------------------------------------------


@dataclass
class Smoothed:
    poses: np.ndarray  # (K, 3)
    covariance: np.ndarray  # (K, 3, 3)
    params: np.ndarray  # (2,) a, δ
    param_sigma: np.ndarray  # (2,)
    accepted: np.ndarray  # (K,) bool: matches kept after the χ² gate
    chi2: np.ndarray  # (K,) of every usable match against the smoothed track
    scales: dict  # noise scales s_m, s_x, s_y, s_θ
    nfev: int


class _Graph:
    """The least-squares problem of step 3 (module doc): residuals and their sparse Jacobian."""

    def __init__(self, t, Z, info, use, odometry, noise, scales, offset: float = 0.0):
        self.t = np.asarray(t, dtype=float)
        self.offset = float(offset)  # δ, held
        self.K = len(self.t)
        self.Z = Z
        self.idx = np.flatnonzero(use)
        Lam = info[self.idx] / scales["match"] ** 2 + np.diag([1e-8, 1e-8, 1e-8])
        self.Lt = np.transpose(np.linalg.cholesky(Lam), (0, 2, 1))  # r = Lᵀ e, ‖r‖² = eᵀΛe
        self.odo_t, self.odo_tw = odometry
        self.noise, self.scales = noise, scales
        self.sig = None
        K, nm = self.K, len(self.idx)
        # the Jacobian's pattern: odometry factor j (rows 3j..3j+2) on poses j, j+1 and the NP unknowns,
        # match i on its pose, the priors on the unknowns
        j = np.arange(K - 1)
        cols_odo = np.concatenate([3 * j[:, None] + np.arange(6), np.broadcast_to(3 * K + np.arange(NP), (K - 1, NP))],
                                  axis=1)  # (K−1, 6 + NP)
        rows = [np.repeat(3 * j[:, None] + np.arange(3), 6 + NP, axis=1).reshape(-1),
                3 * (K - 1) + np.repeat(3 * np.arange(nm)[:, None] + np.arange(3), 3, axis=1).reshape(-1),
                3 * (K - 1) + 3 * nm + np.arange(NP)]
        cols = [np.repeat(cols_odo[:, None, :], 3, axis=1).reshape(-1),
                np.tile(3 * self.idx[:, None] + np.arange(3), (1, 3)).reshape(-1),
                3 * K + np.arange(NP)]
        self.rows, self.cols = np.concatenate(rows), np.concatenate(cols)
        self.shape = (3 * (K - 1) + 3 * nm + NP, 3 * K + NP)

    def predicted(self, p) -> np.ndarray:
        B = dead_reckon(self.odo_t, self.odo_tw, self.t - self.offset, p[0])
        return relative(B[:-1], B[1:])

    def set_sigmas(self, p):
        pred = self.predicted(p)
        s = self.noise.sigmas(pred, np.diff(self.t))
        s *= np.array([self.scales["odo_x"], self.scales["odo_y"], self.scales["odo_theta"]])
        self.sig = s

    def split(self, z):
        return z[:3 * self.K].reshape(self.K, 3), z[3 * self.K:]

    def parts(self, z):
        X, p = self.split(z)
        r_odo = relative_difference(relative(X[:-1], X[1:]), self.predicted(p)) / self.sig
        e = relative_difference(X[self.idx], self.Z[self.idx])
        r_m = np.einsum("kij,kj->ki", self.Lt, e)
        r_p = (p - 1.0) / SCALE_PRIOR
        return r_odo, r_m, r_p

    def residuals(self, z):
        r_odo, r_m, r_p = self.parts(z)
        return np.concatenate([r_odo.ravel(), r_m.ravel(), r_p])

    def offset_profile(self, X, offsets) -> tuple[np.ndarray, np.ndarray]:
        """Cost of the odometry factors over time offsets δ with the poses X held, a in closed form
        for each (the translation is linear in a): (cost (G,), a (G,)). The loss is Cauchy's,
        ½ c² log(1 + r²/c²) with c = 3: bounded, so a skid or a wheel spin (the odometry far off for
        a while) cannot pull the lowest point to an offset that hides it.

        The dead-reckoned motion between two scans is piecewise smooth in δ, with a kink wherever a
        scan's time crosses an odometry stamp; with noisy twists the kinks make local minima, so δ
        is started from the best of this profile rather than from 0."""
        rel = relative(X[:-1], X[1:])
        chain = odometry_chain(self.odo_t, self.odo_tw)
        w = 1.0 / self.sig ** 2
        cost, scale = np.zeros(len(offsets)), np.ones(len(offsets))
        for i, d in enumerate(offsets):  # a profile over a grid of offsets: each a vectorised pass over the scans
            B = dead_reckon(self.odo_t, self.odo_tw, self.t - d, chain=chain)
            pred = relative(B[:-1], B[1:])
            den = float(np.sum(w[:, :2] * pred[:, :2] ** 2))
            a = float(np.clip(np.sum(w[:, :2] * pred[:, :2] * rel[:, :2]) / den, *SCALE_BOUNDS)) if den > 0 else 1.0
            pred[:, :2] *= a
            r2 = (relative_difference(rel, pred) / self.sig) ** 2 / 9.0
            cost[i] = 4.5 * np.sum(np.log1p(r2)) + 0.5 * ((a - 1.0) / SCALE_PRIOR) ** 2 \
                + 0.5 * (d / OFFSET_PRIOR) ** 2
            scale[i] = a
        return cost, scale

    def jacobian(self, z):
        """The residuals' Jacobian (sparse, CSR): poses in closed form, the odometry unknowns by
        forward differences of the dead-reckoned odometry."""
        from scipy.sparse import csr_matrix
        X, p = self.split(z)
        K = self.K
        ca, sa = np.cos(X[:-1, 2]), np.sin(X[:-1, 2])
        dx, dy = X[1:, 0] - X[:-1, 0], X[1:, 1] - X[:-1, 1]
        D = np.zeros((K - 1, 3, 6 + NP))
        # rel_xy = R(−θa) (pb − pa): ∂/∂pa = −R(−θa), ∂/∂θa = R'(−θa)(pb − pa), ∂/∂pb = R(−θa)
        D[:, 0, 0], D[:, 0, 1], D[:, 0, 2] = -ca, -sa, -sa * dx + ca * dy
        D[:, 1, 0], D[:, 1, 1], D[:, 1, 2] = sa, -ca, -ca * dx - sa * dy
        D[:, 0, 3], D[:, 0, 4] = ca, sa
        D[:, 1, 3], D[:, 1, 4] = -sa, ca
        D[:, 2, 2], D[:, 2, 5] = -1.0, 1.0
        pred = self.predicted(p)
        for i, h in enumerate((1e-6,)):
            q = p.copy()
            q[i] += h
            D[:, :, 6 + i] = -relative_difference(self.predicted(q), pred) / h
        D /= self.sig[:, :, None]
        data = np.concatenate([D.reshape(-1), self.Lt.reshape(-1),
                               np.full(NP, 1.0 / SCALE_PRIOR)])
        return csr_matrix((data, (self.rows, self.cols)), shape=self.shape)


def _redundancy(graph: _Graph, jac, cov, cov_next) -> tuple[np.ndarray, np.ndarray]:
    """Redundancy numbers (Förstner): per odometry row (K−1, 3) and per match (nm,), r = dof − tr(J Σ Jᵀ),
    J the factor's whitened rows, Σ the covariance of the poses it touches (the odometry unknowns'
    share neglected)."""
    from scipy.sparse import csr_matrix
    J = csr_matrix(jac)
    K = graph.K
    dense = J[:3 * (K - 1), :3 * K]
    rows = np.zeros((K - 1, 3, 6))
    coo = dense.tocoo()
    j = coo.row // 3
    c = coo.col - 3 * j
    ok = (c >= 0) & (c < 6)
    rows[j[ok], coo.row[ok] % 3, c[ok]] = coo.data[ok]
    S = np.zeros((K - 1, 6, 6))
    S[:, :3, :3], S[:, 3:, 3:] = cov[:-1], cov[1:]
    S[:, :3, 3:] = cov_next
    S[:, 3:, :3] = np.transpose(cov_next, (0, 2, 1))
    r_odo = 1.0 - np.einsum("kai,kij,kaj->ka", rows, S, rows)
    m = len(graph.idx)
    Jm = np.zeros((m, 3, 3))
    mc = J[3 * (K - 1):3 * (K - 1) + 3 * m].tocoo()
    i = mc.row // 3
    Jm[i, mc.row % 3, mc.col - 3 * graph.idx[i]] = mc.data
    r_m = 3.0 - np.einsum("kai,kij,kaj->k", Jm, cov[graph.idx], Jm)
    return np.clip(r_odo, 0.0, 1.0), np.clip(r_m, 0.0, 3.0)


def _variance_factor(chi2, redundancy, gate) -> float:
    """Σχ² / Σr (variance component estimation) over the factors within ``gate`` × the factor itself
    (iterated: the gate follows the estimate, so a heavy tail neither sets nor escapes it); 1
    without redundancy."""
    f = 1.0
    for _ in range(20):
        keep = chi2 <= gate * f
        den = float(np.sum(redundancy[keep]))
        if den <= 1.0:
            return f
        new = float(np.sum(chi2[keep]) / den)
        if abs(new - f) <= 1e-3 * f:
            return new
        f = new
    return f


def smooth_track(t, matches: Matches, odometry, noise: OdometryNoise | None = None, log=None) -> Smoothed:
    """Steps 3 and 4 of the module doc."""
    from scipy.optimize import least_squares
    say = log or (lambda *_: None)
    noise = noise or OdometryNoise()
    t = np.asarray(t, dtype=float)
    K = len(t)
    use = matches.usable.copy()
    scales = {"match": 1.0, "odo_x": 1.0, "odo_y": 1.0, "odo_theta": 1.0}
    x0 = np.where(np.isfinite(matches.filtered), matches.filtered, 0.0)
    # scans before the first estimate: carried back by the odometry
    first = int(np.argmax(np.all(np.isfinite(matches.filtered), axis=1)))
    if first > 0:
        B = dead_reckon(*odometry, t)
        x0[:first] = compose(matches.filtered[first], relative(B[first], B[:first]))
    z = np.concatenate([x0.ravel(), [1.0]])
    nfev = 0
    offset, offset_sigma = 0.0, OFFSET_PRIOR
    for stage in range(3):  # solve; then twice: the bag's own noise scales, the χ² gate, solve again
        graph = _Graph(t, matches.poses, matches.information, use, odometry, noise, scales, offset)
        graph.set_sigmas(z[3 * K:])
        offset, offset_sigma, z[3 * K] = fit_offset(graph, z[:3 * K].reshape(K, 3))
        graph = _Graph(t, matches.poses, matches.information, use, odometry, noise, scales, offset)
        graph.set_sigmas(z[3 * K:])
        sol = least_squares(graph.residuals, z, jac=graph.jacobian, loss="soft_l1", f_scale=3.0, x_scale="jac",
                            method="trf", max_nfev=200, xtol=1e-10, ftol=1e-10,
                            tr_options={"atol": 1e-10, "btol": 1e-10})
        if not np.all(np.isfinite(sol.x)) or not SCALE_BOUNDS[0] <= sol.x[3 * K] <= SCALE_BOUNDS[1]:
            raise ValueError(f"the smoothing diverged (odometry speed scale {sol.x[3 * K]:.3g}): odometry unusable")
        z, nfev = sol.x, nfev + sol.nfev
        cov, cov_next, pcov = _marginal_covariances(sol.jac, K)
        if stage == 2:
            break
        r_odo, r_m, _ = graph.parts(z)
        red_odo, red_m = _redundancy(graph, sol.jac, cov, cov_next)
        chi_m = np.sum(r_m ** 2, axis=1)
        f_m = _variance_factor(chi_m, red_m, CHI2_3_999)
        for i, key in enumerate(("odo_x", "odo_y", "odo_theta")):
            scales[key] *= math.sqrt(np.clip(_variance_factor(r_odo[:, i] ** 2, red_odo[:, i], 9.0), 0.01, 100.0))
        scales["match"] *= math.sqrt(np.clip(f_m, 0.01, 100.0))
        scales["match"] = max(scales["match"], 1.0)  # never more certain than the beams say
        bad = graph.idx[chi_m / max(f_m, 1.0) > CHI2_3_999]
        use[bad] = False
        say(f"smoothing: {sol.nfev} evaluations; noise scales: matches {scales['match']:.2f}, odometry x "
            f"{scales['odo_x']:.2f}, y {scales['odo_y']:.2f}, heading {scales['odo_theta']:.2f}; {bad.size} matches "
            f"rejected; odometry time offset {offset * 1e3:+.1f} ms")
    X, p = graph.split(z)
    chi2 = np.full(K, np.nan)
    cand = np.flatnonzero(matches.usable)
    if cand.size:
        e = relative_difference(X[cand], matches.poses[cand])
        Lam = matches.information[cand] / scales["match"] ** 2
        chi2[cand] = np.einsum("ki,kij,kj->k", e, Lam, e)
    psig = np.array([math.sqrt(max(float(pcov[0, 0]), 0.0)), offset_sigma])
    return Smoothed(poses=X.copy(), covariance=cov, params=np.array([p[0], offset]), param_sigma=psig,
                    accepted=use & (np.nan_to_num(chi2, nan=np.inf) <= CHI2_3_999), chi2=chi2, scales=dict(scales),
                    nfev=int(nfev))


def fit_offset(graph: _Graph, X) -> tuple[float, float, float]:
    """δ (s), its σ and the speed scale a at δ from the profile of the odometry factors (module doc,
    step 3): the lowest point of the profile over ± OFFSET_RANGE, then a parabola fitted within
    ± OFFSET_FIT_S of it (its vertex, σ = (½ / curvature)^½; the lowest point itself and the fit's
    half-width when the profile is not convex there)."""
    grid = np.arange(-OFFSET_RANGE, OFFSET_RANGE + 1e-9, OFFSET_STEP_S)
    cost, scale = graph.offset_profile(X, grid)
    i = int(np.argmin(cost))
    near = np.abs(grid - grid[i]) <= OFFSET_FIT_S + 1e-9
    c2, c1, _ = np.polyfit(grid[near] - grid[i], cost[near], 2)
    if c2 <= 0:
        return float(grid[i]), OFFSET_FIT_S, float(scale[i])
    vertex = float(np.clip(-c1 / (2 * c2), -OFFSET_FIT_S, OFFSET_FIT_S)) + float(grid[i])
    return vertex, math.sqrt(0.5 / c2), float(np.interp(vertex, grid, scale))


def _marginal_covariances(jac, K: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Blocks of Σ = (JᵀJ)⁻¹: Σ_kk (K, 3, 3) of the poses, Σ_k,k+1 (K − 1, 3, 3) and the NP × NP block of
    the odometry unknowns. With H = JᵀJ = [[A, B], [Bᵀ, C]] (A block-tridiagonal: a factor touches
    at most two consecutive poses), S = C − Bᵀ A⁻¹ B and U = A⁻¹ B (a banded solve)::

        Σ_params = S⁻¹,   Σ_kl = (A⁻¹)_kl + U_k S⁻¹ U_lᵀ

    and the blocks of A⁻¹ by the block-tridiagonal recursion (``block_tridiagonal_inverse``)."""
    from scipy.linalg import solveh_banded
    from scipy.sparse import csr_matrix
    J = csr_matrix(jac)
    H = (J.T @ J).tocoo()
    n = 3 * K
    r, c, v = H.row, H.col, H.data
    pose = (r < n) & (c < n)
    rb, cb = r // 3, c // 3
    diag = np.zeros((K, 3, 3))
    up = np.zeros((max(K - 1, 0), 3, 3))
    d = pose & (rb == cb)
    np.add.at(diag, (rb[d], r[d] % 3, c[d] % 3), v[d])
    u = pose & (cb == rb + 1)
    np.add.at(up, (rb[u], r[u] % 3, c[u] % 3), v[u])
    diag += np.eye(3) * 1e-12
    Bm = np.zeros((n, NP))
    b = (r < n) & (c >= n)
    np.add.at(Bm, (r[b], c[b] - n), v[b])
    Cm = np.zeros((NP, NP))
    cc = (r >= n) & (c >= n)
    np.add.at(Cm, (r[cc] - n, c[cc] - n), v[cc])
    # A in upper banded form (bandwidth 5: a 3 × 3 block and its right neighbour)
    ab = np.zeros((6, n))
    dense_rows = np.arange(n)
    for off in range(6):
        i = dense_rows[:n - off]
        j = i + off
        same = (i // 3) == (j // 3)
        val = np.where(same, diag[i // 3, i % 3, j % 3], 0.0)
        nb = ~same & ((j // 3) == (i // 3) + 1)
        val = np.where(nb, up[np.minimum(i // 3, max(K - 2, 0)), i % 3, j % 3] if K > 1 else 0.0, val)
        ab[5 - off, off:] = val
    U = solveh_banded(ab, Bm)
    S = Cm - Bm.T @ U
    Sinv = np.linalg.inv(S)
    Ainv_diag, Ainv_next = block_tridiagonal_inverse(diag, up)
    Uk = U.reshape(K, 3, NP)
    cov = Ainv_diag + np.einsum("kia,ab,kjb->kij", Uk, Sinv, Uk)
    nxt = Ainv_next + np.einsum("kia,ab,kjb->kij", Uk[:-1], Sinv, Uk[1:])
    return cov, nxt, Sinv


def block_tridiagonal_inverse(diag, up) -> tuple[np.ndarray, np.ndarray]:
    """Diagonal blocks (K, b, b) and first upper blocks (K − 1, b, b) of A⁻¹ for a symmetric positive
    definite block-tridiagonal A (diagonal blocks ``diag``, upper blocks ``up``: A_k,k+1)::

        D_0 = A_00,  D_k = A_kk − A_k,k−1 D_k−1⁻¹ A_k−1,k                      (forward)
        Σ_K−1 = D_K−1⁻¹,  Σ_k,k+1 = −D_k⁻¹ A_k,k+1 Σ_k+1,k+1,
        Σ_kk = D_k⁻¹ − Σ_k,k+1 A_k+1,k D_k⁻¹                                  (backward)

    One pass each way over the K blocks (3 × 3 matrices: a loop over scans, not beams)."""
    K = len(diag)
    Dinv = np.zeros_like(diag)
    D = diag[0]
    Dinv[0] = np.linalg.inv(D)
    for k in range(1, K):
        D = diag[k] - up[k - 1].T @ Dinv[k - 1] @ up[k - 1]
        Dinv[k] = np.linalg.inv(D)
    cov = np.zeros_like(diag)
    nxt = np.zeros_like(up)
    cov[K - 1] = Dinv[K - 1]
    for k in range(K - 2, -1, -1):
        nxt[k] = -Dinv[k] @ up[k] @ cov[k + 1]
        cov[k] = Dinv[k] - nxt[k] @ up[k].T @ Dinv[k]
    return 0.5 * (cov + np.transpose(cov, (0, 2, 1))), nxt


# --------------------------------------------------------------------------------------------
# The reference track
# --------------------------------------------------------------------------------------------


@dataclass
class ReferenceTrack:
    """One entry per scan (module doc)."""

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
    twists (M, 3)) on the same clock, the laser at ``mount`` in base_link (module doc). The first
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


def odometry_consistency(t, poses, odometry, speed_scale: float, offset: float, noise: OdometryNoise,
                         tolerance: float, window: float = CONSISTENCY_WINDOW_S) -> tuple[np.ndarray, np.ndarray]:
    """Two (K,) bool arrays: (consistent) no window of ``window`` s containing scan k has the track
    ``poses`` cover a distance different from the odometry's by more than CONSISTENCY_SIGMAS σ +
    ``tolerance`` (m); (skid) every such window has the odometry covering less and standing still in
    it (module doc)."""
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
    the map explains that scan clearly better somewhere the track is not (module doc, step 4)."""
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


def track_twists(t, poses) -> np.ndarray:
    """Base-frame twist (K, 3: v_x, v_y, ω) of a pose track at each entry, from its neighbours
    (central differences; one-sided at the ends): X_{k−1}⁻¹ ⊕ X_{k+1} / (t_{k+1} − t_{k−1})."""
    t = np.asarray(t, dtype=float)
    p = np.asarray(poses, dtype=float).reshape(-1, 3)
    K = len(t)
    if K < 2:
        return np.zeros((K, 3))
    i0, i1 = np.clip(np.arange(K) - 1, 0, K - 1), np.clip(np.arange(K) + 1, 0, K - 1)
    dt = np.where(t[i1] > t[i0], t[i1] - t[i0], np.inf)
    return relative(p[i0], p[i1]) / dt[:, None]


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
    itself against ground truth when there is one), plus the yardstick's own figures."""
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
        # times the estimate went to another place: runs of scored scans > FALSE_RECOVERY_M from the yardstick
        "reference_false_recoveries": false_recoveries(err.t, err.position, FALSE_RECOVERY_M),
        "reference_score_median": float(np.nanmedian(ref.score)) if np.isfinite(ref.score).any() else None,
        "reference_yardstick": ref.summary(),
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
    """Along- and cross-track error vs time (scored scans), scans whose match leaves an axis free
    marked; the reference's own σ along and across the track."""
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
        ax.plot(amb_t, np.zeros_like(amb_t), "|", color="tab:orange", ms=10, label="match leaves an axis free")
    ax.set_ylabel("error vs reference (m)")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title(title)
    ax = axes[1]
    ax.plot(err.t - t0, err.position, color="black", lw=1.0, label="position error")
    ax.plot(ref.t - t0, ref.std_along, color="tab:green", lw=0.8, alpha=0.8, label="reference σ along track")
    ax.plot(ref.t - t0, ref.std_cross, color="tab:purple", lw=0.8, alpha=0.8, label="reference σ across track")
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



# --------------------------------------------------------------------------------------------
# The yardstick's figures for the data sets
# --------------------------------------------------------------------------------------------


def main(argv=None) -> int:
    """``python -m localization.eval.reference [BAG ...]``: the yardstick's own figures (``summary``)
    for named data-set bags (``eval.datasets``: bag1..3, trace0, trace1, lgfloor2), one JSON line
    each; the scan stamp convention the data set gives (read from the bags' record times,
    ``calibration.check_scan_stamps``), the laser mount from the bag's TF (else the RACECAR's 0.275 m)."""
    import argparse
    import json
    import time

    from localization.core.occupancy_map import load_map
    from localization.eval.datasets import PIONEER_BAGS, REAL_BAGS, bag_laser_mount, real_bag, real_bag_path

    ap = argparse.ArgumentParser(prog="python -m localization.eval.reference")
    ap.add_argument("bags", nargs="*", default=[*REAL_BAGS, *PIONEER_BAGS])
    args = ap.parse_args(argv)
    for name in args.bags:
        rb, path = real_bag(name), real_bag_path(name)
        stamp = rb.scan_stamp
        mount = bag_laser_mount(path, rb.scan_topic, (0.275, 0.0, 0.0))
        t0 = time.perf_counter()
        ref = reference_for_bag(path, load_map(rb.map), rb.scan_topic, mount, odom_topic=rb.odom_topic,
                                initial_pose=rb.start, scan_stamp=stamp)
        print(json.dumps({"bag": name, "scan_stamp": stamp, "mount": mount, "start": ref.counts.get("start"),
                          "seconds": round(time.perf_counter() - t0, 1), **ref.summary()}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
