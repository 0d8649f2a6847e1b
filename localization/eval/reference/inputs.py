"""What the yardstick reads: a bag's odometry and scans, and each scan's beams as the matcher takes
them (cleaned ranges, beam angles, per-beam time within the sweep)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from localization.core.scan import beam_angles, clean_ranges, sweep_increment
from localization.eval.datasets import bag_odometry, read_scans  # noqa: F401 - read_scans re-exported


def read_odometry(bag_path, odom_topic: str, odom_frame: str = "odom",
                  base_frame: str = "base_link") -> tuple[np.ndarray, np.ndarray]:
    """Stamps (M,) and reported twists (M, 3: vx, vy, ωz) of the bag's odometry in stamp order: the
    Odometry topic, else TF ``odom_frame → base_frame`` (``datasets.bag_odometry``)."""
    return bag_odometry(bag_path, odom_topic, odom_frame, base_frame).arrays()


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
