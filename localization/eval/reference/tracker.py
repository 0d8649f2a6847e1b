"""Step 1 of the package doc, one scan after another: the running estimate moved on by the odometry,
each scan matched within its uncertainty, the match taken as a measurement with its information,
and after a gap a match away from the prediction followed only when several agree."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from localization.core.geometry import compose, relative, wrap_angle
from localization.core.matching import CorrelativeMatcher
from localization.eval.reference.constants import (
    CHI2_3_999,
    MAX_WINDOW,
    MIN_WINDOW,
    RELOCALIZE_GAP_S,
    RELOCALIZE_NOISE,
    RELOCALIZE_SCANS,
)
from localization.eval.reference.geometry import relative_difference
from localization.eval.reference.information import _safe_inverse, match_information
from localization.eval.reference.odometry import dead_reckon, odometry_twist_at


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


def _empty_matches(K):
    return {"poses": np.full((K, 3), np.nan), "information": np.zeros((K, 3, 3)), "score": np.full(K, np.nan),
            "median_range": np.full(K, np.nan), "inlier_fraction": np.zeros(K), "usable": np.zeros(K, dtype=bool),
            "filtered": np.full((K, 3), np.nan)}


class _Tracker:
    """Matches scans one after another (package doc, step 1)."""

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
        k_start (or at ``k_prev``, then moved on by the odometry); fills ``out`` (a dict of arrays).
        Per scan: predict, match (``match_near_edge``), judge a match after a gap (``after_gap``),
        take it as a measurement (``take``)."""
        K = len(self.beams) if k_stop is None else k_stop
        x, P = np.asarray(x0, dtype=float), np.asarray(P0, dtype=float)
        pending: list = []  # the matches kept out since the gap (``after_gap``)
        last_ok = None  # time of the last match used
        for k in range(k_start, K):
            if k > k_start or k_prev is not None:
                x, P = self.predict(k - 1 if k > k_start else k_prev, k, x, P)
            window = first_window if (k == k_start and first_window is not None) else self.window(P)
            r, info, seed = self.match_near_edge(k, x, window)
            ok = self.usable(r, info, seed, window)
            if r is not None:
                out["score"][k] = r.score
            gap = self.t[k] - last_ok if last_ok is not None else 0.0
            if ok and k > k_start and gap > RELOCALIZE_GAP_S:
                r, info, ok, x, P, pending = self.after_gap(k, r, info, x, P, pending)
            if ok:
                last_ok = self.t[k]
                x, P = self.take(k, r, info, x, P, out)
            out["filtered"][k] = x
        return x, P

    def match_near_edge(self, k, x, window):
        """The match of scan k around the seed ``x``; one on the window's edge that is not usable is
        matched once more around itself. Returns (match, information, the seed its window was around)."""
        r, info = self.match(k, x, window)
        if r is None or not r.at_window_edge or self.usable(r, info, x, window):
            return r, info, x
        r2, info2 = self.match(k, r.pose, window)
        if r2 is None:
            return r, info, x
        return r2, info2, r.pose

    def after_gap(self, k, r, info, x, P, pending):
        """A usable match after a gap (package doc, step 1): one within the χ² gate of the prediction
        (x, P) is used; beyond it, a match in the smallest window around the prediction that passes the
        gate is used instead; else the match is kept out (``pending``, the last RELOCALIZE_SCANS) and
        followed only when it is plausible (χ² with P × RELOCALIZE_NOISE²) and the kept-out matches
        agree with each other through the odometry: the estimate restarts from it.
        Returns (match, information, use it, x, P, pending)."""
        chi2 = self._chi2(r, info, x, P)
        if not chi2 > CHI2_3_999:
            return r, info, True, x, P, []
        near, near_info = self.match(k, x, MIN_WINDOW)  # a match where the odometry says?
        if self.usable(near, near_info, x, MIN_WINDOW) and self._chi2(near, near_info, x, P) <= CHI2_3_999:
            return near, near_info, True, x, P, []
        self.gated.append((k, chi2))
        pending = (pending + [(k, r.pose, info)])[-RELOCALIZE_SCANS:]
        plausible = self._chi2(r, info, x, P * RELOCALIZE_NOISE ** 2) <= CHI2_3_999
        if not (plausible and self._consistent(pending)):
            return r, info, False, x, P, pending
        # map and odometry agree on another place: restart there
        drift = np.diag(self.noise.sigmas(np.zeros(3), 1.0) ** 2)
        return r, info, True, r.pose, _safe_inverse(info.information) + drift, []

    def take(self, k, r, info, x, P, out):
        """Record scan k's match in ``out`` and update the running estimate with it."""
        out["poses"][k] = r.pose
        out["information"][k] = info.information
        out["median_range"][k] = info.median_range
        out["inlier_fraction"][k] = info.inlier_fraction
        out["usable"][k] = True
        x, P, _ = self.update(x, P, r.pose, info.information)
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
