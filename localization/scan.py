"""Laser scan preprocessing: downsampling and invalid-range handling (no ROS types)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Scan:
    """A planar scan in the laser frame: ranges (metres; ``inf`` = no return) at angles (rad)."""

    ranges: np.ndarray
    angles: np.ndarray
    stamp: float = 0.0  # seconds


def beam_angles(num_ranges: int, angle_min: float, angle_max: float, angle_increment: float) -> np.ndarray:
    """Angles of all beams. The increment is trusted when it agrees with angle_min/max;
    otherwise the beams are spread evenly over [angle_min, angle_max]."""
    if num_ranges <= 1:
        return np.full(num_ranges, float(angle_min))
    span = (num_ranges - 1) * angle_increment
    if np.isfinite(angle_increment) and angle_increment != 0 and abs(angle_min + span - angle_max) <= abs(angle_increment):
        return angle_min + np.arange(num_ranges) * angle_increment
    return np.linspace(angle_min, angle_max, num_ranges)


def downsample_indices(num_ranges: int, num_beams: int) -> np.ndarray:
    """``num_beams`` indices spread evenly over ``num_ranges`` beams (first and last included)."""
    if num_ranges <= 0:
        return np.empty(0, dtype=np.int64)
    num_beams = max(1, min(int(num_beams), num_ranges))
    return np.unique(np.rint(np.linspace(0, num_ranges - 1, num_beams)).astype(np.int64))


def clean_ranges(ranges, range_min: float, range_max: float) -> np.ndarray:
    """NaN, ±inf and ranges outside [range_min, range_max] become ``inf`` (max range)."""
    r = np.asarray(ranges, dtype=float)
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(r) & (r >= range_min) & (r <= range_max)
    return np.where(valid, r, np.inf)


def downsample_scan(ranges, angle_min, angle_max, angle_increment, range_min, range_max, num_beams) -> Scan:
    """Pick ``num_beams`` evenly spread beams of a full scan; invalid ranges count as max range."""
    ranges = np.asarray(ranges, dtype=float).ravel()
    idx = downsample_indices(ranges.size, num_beams)
    angles = beam_angles(ranges.size, angle_min, angle_max, angle_increment)[idx]
    return Scan(clean_ranges(ranges[idx], range_min, range_max), angles)
