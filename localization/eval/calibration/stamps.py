"""The scan stamp convention of a bag, from its record times (``localization.eval.calibration``, last
paragraph): a driver publishes a scan once its last beam is measured."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class StampCheck:
    """Record time − header stamp of a bag's scans (package doc, last paragraph)."""

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
    """Compare a bag's scan header stamps with its record times (package doc); raises ValueError
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

