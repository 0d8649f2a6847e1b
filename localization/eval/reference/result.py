"""The reference track: one entry per scan, what the yardstick found there and whether it is scored."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class ReferenceTrack:
    """One entry per scan (package doc)."""

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
