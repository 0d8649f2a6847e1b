"""Corrupted inputs: a copy of a bag with a fraction of its scans and odometry broken in every way
a real driver or a replay can break them (NaN, inf, empty or resized scans, absurd speeds, stamps
going backwards ...), to check that the localizer logs and survives each."""
from __future__ import annotations

import math

import numpy as np

from localization.bags import BagWriter, make_laser_scan, make_odometry, open_bag, stamp_to_ns
from localization.core.geometry import yaw_of

SCAN_CORRUPTIONS = ("nan", "inf", "-inf", "negative", "zero", "huge", "all_nan", "empty", "resized",
                    "zero_increment", "reversed", "backwards_stamp")
ODOM_CORRUPTIONS = ("nan", "inf", "absurd", "backwards_stamp", "zero_dt")


def corrupt_bag(src, dst, fraction: float = 0.05, seed: int = 0, scan_topic: str = "/scan",
                odom_topic: str = "/odom") -> dict:
    """Copy bag ``src`` to ``dst`` with ``fraction`` of the scan and odometry messages corrupted
    (the kinds above, in turn). Returns counts per corruption."""
    rng = np.random.default_rng(seed)
    counts: dict = {}
    with open_bag(src) as bag, BagWriter(dst) as w:
        ts = w.typestore
        for name, msgtype in bag.topics.items():
            w.add_topic(name, msgtype)
        k_scan = k_odom = 0
        for m in bag.messages(list(bag.topics)):
            msg = m.msg
            if m.topic == scan_topic and rng.random() < fraction:
                kind = SCAN_CORRUPTIONS[k_scan % len(SCAN_CORRUPTIONS)]
                k_scan += 1
                r = np.array(msg.ranges, dtype=np.float64)
                a0, a1, inc, t_ns = msg.angle_min, msg.angle_max, msg.angle_increment, stamp_to_ns(msg.header.stamp)
                sel = rng.random(r.size) < 0.3
                if kind in ("nan", "inf", "-inf", "negative", "zero", "huge"):
                    r[sel] = {"nan": np.nan, "inf": np.inf, "-inf": -np.inf, "negative": -1.0, "zero": 0.0,
                              "huge": 1e30}[kind]
                elif kind == "all_nan":
                    r[:] = np.nan
                elif kind == "empty":
                    r = r[:0]
                elif kind == "resized":
                    r = r[: r.size // 2]
                elif kind == "zero_increment":
                    inc = 0.0
                elif kind == "reversed":
                    a0, a1, inc, r = a1, a0, -inc, r[::-1]
                elif kind == "backwards_stamp":
                    t_ns -= 5_000_000_000
                msg = make_laser_scan(ts, t_ns, msg.header.frame_id, r, angle_min=a0, angle_max=a1,
                                      angle_increment=inc, range_min=msg.range_min, range_max=msg.range_max)
                counts[f"scan_{kind}"] = counts.get(f"scan_{kind}", 0) + 1
            elif m.topic == odom_topic and rng.random() < fraction:
                kind = ODOM_CORRUPTIONS[k_odom % len(ODOM_CORRUPTIONS)]
                k_odom += 1
                tw, p = msg.twist.twist, msg.pose.pose
                vx, vy, wz = tw.linear.x, tw.linear.y, tw.angular.z
                t_ns = stamp_to_ns(msg.header.stamp)
                if kind == "nan":
                    vx = math.nan
                elif kind == "inf":
                    wz = math.inf
                elif kind == "absurd":
                    vx = 300.0
                elif kind == "backwards_stamp":
                    t_ns -= 3_000_000_000
                elif kind == "zero_dt":
                    t_ns -= 20_000_000  # the previous message's stamp again
                msg = make_odometry(ts, t_ns, msg.header.frame_id, msg.child_frame_id, p.position.x, p.position.y,
                                    yaw_of(p.orientation), vx, vy, wz)
                counts[f"odom_{kind}"] = counts.get(f"odom_{kind}", 0) + 1
            w.write(m.topic, m.t_ns, msg)
    return counts
