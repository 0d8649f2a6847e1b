"""``python -m localization.eval.reference``: the yardstick's own figures for the data sets' bags."""
from __future__ import annotations

from localization.eval.reference.track import reference_for_bag


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
