"""Laser scans in the core: the full scan as received (``ScanData``, the fields of a
sensor_msgs/LaserScan) and the downsampled beams the sensor model uses (``Scan``).

    beam i:  angle_i = angle_min + i · angle_increment,   time_i = t_0 + i · time_increment

(``scan_time`` the sweep period). Which beam the header stamp s describes is a property of the driver
(``scan_stamp``, docs/timing.md), and ``scan_stamp_offset`` o (s) is how much later than that beam the
stamp was taken (a latency the driver did not subtract), so with n beams and Δ = time_increment::

    first_beam (REP / LaserScan spec, default):  t_0 = s − o
    last_beam  (urg_node with calibrate_time false, rplidar_ros):  t_0 = s − o − (n − 1) Δ
    mid-sweep time (the scan's time, ``scan_time``):  t_0 + ½ (n − 1) Δ

Invalid ranges (NaN, ±inf, outside [range_min, range_max]) become ``inf``: a max-range reading.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

MAX_SWEEP_S = 0.5  # s: a scan whose beams span longer (time_increment × beams) has no usable sweep timing


@dataclass
class ScanData:
    """A full scan as received (sensor_msgs/LaserScan's fields, stamps in float seconds)."""

    stamp: float  # s, time of the first beam
    ranges: np.ndarray  # m
    angle_min: float  # rad
    angle_max: float  # rad
    angle_increment: float  # rad
    range_min: float  # m
    range_max: float  # m
    time_increment: float = 0.0  # s between beams (0: unknown)
    scan_time: float = 0.0  # s between scans (0: unknown)
    frame_id: str = ""


@dataclass
class Scan:
    """The beams used by the sensor model, in the laser frame: ranges (metres; ``inf`` = no
    return) at angles (rad)."""

    ranges: np.ndarray
    angles: np.ndarray
    indices: np.ndarray | None = None  # which beams of the full scan (downsample_scan)


def beam_angles(num_ranges: int, angle_min: float, angle_max: float, angle_increment: float) -> np.ndarray:
    """Angles of all beams. The increment is trusted when it agrees with angle_min/max;
    otherwise the beams are spread evenly over [angle_min, angle_max]."""
    if num_ranges <= 1:
        return np.full(num_ranges, float(angle_min))
    span = (num_ranges - 1) * angle_increment
    consistent = abs(angle_min + span - angle_max) <= abs(angle_increment)
    if np.isfinite(angle_increment) and angle_increment != 0 and consistent:
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


def downsample_scan(scan: ScanData, num_beams: int, range_min: float | None = None,
                    range_max: float | None = None, angle_step: int = 0) -> Scan:
    """Pick ``num_beams`` evenly spread beams of a full scan, or with ``angle_step`` > 0 every
    ``angle_step``-th beam from the first (the course's stride); invalid ranges count as max range
    (``range_min``/``range_max`` replace the scan's own limits when given)."""
    ranges = np.asarray(scan.ranges, dtype=float).ravel()
    idx, angles = _chosen_beams(ranges.size, float(scan.angle_min), float(scan.angle_max),
                                float(scan.angle_increment), int(num_beams), int(angle_step))
    lo = scan.range_min if range_min is None else range_min
    hi = scan.range_max if range_max is None else range_max
    # copies: the kept arrays stay as made whatever a caller does with its own
    return Scan(clean_ranges(ranges[idx], lo, hi), angles.copy(), idx.copy())


@functools.lru_cache(maxsize=16)
def _chosen_beams(num_ranges: int, angle_min: float, angle_max: float, angle_increment: float, num_beams: int,
                  angle_step: int) -> tuple[np.ndarray, np.ndarray]:
    """``downsample_scan``'s beam indices and their angles: the same for every scan of a lidar, so they are made
    once (and handed out as copies)."""
    idx = np.arange(0, num_ranges, angle_step) if angle_step > 0 else downsample_indices(num_ranges, num_beams)
    return idx, beam_angles(num_ranges, angle_min, angle_max, angle_increment)[idx]


def sweep_increment(scan: ScanData) -> float:
    """time_increment (s) if usable (finite, > 0, the sweep at most MAX_SWEEP_S), else 0."""
    ti = scan.time_increment
    ok = isinstance(ti, (int, float)) and math.isfinite(ti) and ti > 0 and ti * np.size(scan.ranges) <= MAX_SWEEP_S
    return float(ti) if ok else 0.0


SCAN_STAMPS = ("first_beam", "last_beam")  # which beam a scan's header stamp describes (module doc)


def first_beam_time(scan: ScanData, stamp: str = "first_beam", offset: float = 0.0) -> float:
    """Time t_0 (s, scan clock) of the scan's first beam under the stamp convention (module doc);
    without usable sweep timing both conventions give s − o."""
    if stamp not in SCAN_STAMPS:
        raise ValueError(f"scan stamp convention {stamp!r}: expected one of {', '.join(SCAN_STAMPS)}")
    t0 = scan.stamp - offset
    if stamp == "last_beam":
        t0 -= sweep_increment(scan) * (np.size(scan.ranges) - 1)
    return t0


def beam_times(scan: ScanData, idx, stamp: str = "first_beam", offset: float = 0.0) -> np.ndarray | None:
    """Each chosen beam's own time t_i = t_0 + i · time_increment (s, scan clock; module doc) for the
    beam indices ``idx``; None for a scan without usable sweep timing (every beam at the stamp)."""
    sweep = sweep_increment(scan)
    if not sweep > 0:
        return None
    return first_beam_time(scan, stamp, offset) + np.asarray(idx) * sweep


def scan_time(scan: ScanData, stamp: str = "first_beam", offset: float = 0.0) -> float:
    """The time a scan describes (s, scan clock): the middle of its sweep, t_0 + ½ (n − 1) Δ (module
    doc), i.e. the stamp itself for a scan without per-beam timing; also the pose a rigid match of a
    skewed scan recovers. ``stamp``/``offset``: the parameters scan_stamp / scan_stamp_offset."""
    return first_beam_time(scan, stamp, offset) + 0.5 * sweep_increment(scan) * (np.size(scan.ranges) - 1)
