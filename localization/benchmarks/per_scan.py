"""CPU per scan in the core, stage by stage: a real bag fed to the Localizer as replay feeds it.

    python -m localization.benchmarks.per_scan [--bag bag1] [--skip 40] [--repeat 5] [--gap MS [--busy]] [--particles N]
                                               [--json]

RSS bag1 (or another of the real bags) with its robot's parameter file (config/real_params.yaml), a global start
as ``localization-replay`` makes it, seed 0. The scans after the first ``--skip`` (the global spread has
converged: tracking) are timed in thread CPU time (``time.thread_time``: another busy process on the machine
inflates it less than wall time), the whole feed call (odometry calls included) and the parts inside it:
the sensor model's pass (the kernel), the move, the odometry timeline's pose queries, the range scale, the
resampling, the estimate, the recovery's decision (with the scan–map agreement), the gate, the beams, the
deskew. Best of ``--repeat`` runs (the first run warms up). What it costs in counts is in replay's
``update_cost`` (core.cost).

Fed back to back, the scans find the caches and the processor as the last one left them. The live node
idles between scans (a scan every 25 ms, odometry every 20 ms) while other processes run: ``--gap MS``
sleeps that long after each scan (outside the timed calls) to measure the core as the node runs it;
``--busy`` spends the gap in a busy loop instead (the processor never idles): the difference between the two is
what waking from an idle costs the same code on this machine.
``--particles N`` runs N particles and lets every scan update the filter (``update_min_distance`` and
``update_min_angle`` 0), as ``benchmarks.latency --particles`` does.
"""
from __future__ import annotations

import argparse
import functools
import json
import os
import sys
import time


def measure(bag: str = "bag1", skip: int = 40, repeat: int = 5, gap: float = 0.0,
            particles: int | None = None, busy: bool = False) -> dict:
    """{"scans", "sensor_updates", "ms_per_scan", "parts": {name: ms per scan}, "load_average"} (best run);
    ``gap``: seconds slept after each scan (``busy``: spent in a busy loop instead); ``particles``: that many,
    every scan updating (None: the file's)."""
    from localization.bags import open_bag
    from localization.core.localizer import Localizer
    from localization.core.occupancy_map import load_map
    from localization.core.parameters import Parameters
    from localization.core.paths import config_dir
    from localization.core.scan import ScanData
    from localization.eval.datasets import real_bag, real_bag_path
    from localization.eval.feed import START_GLOBAL, Feeder, make_scorer
    from localization.eval.replay.run import bag_events, laser_mount_params

    rb = real_bag(bag)
    every_scan = {} if particles is None else {"num_particles": particles, "update_min_distance": 0.0,
                                               "update_min_angle": 0.0}
    params = Parameters.from_yaml(config_dir() / rb.params, random_seed=0, scan_stamp=rb.scan_stamp, **every_scan)
    occupancy_map = load_map(rb.map)
    with open_bag(real_bag_path(rb.name)) as reader:
        params, _ = laser_mount_params(reader, rb.scan_topic, params)
        events = list(bag_events(reader, [rb.scan_topic, rb.odom_topic], rb.scan_topic, rb.odom_topic, None, None,
                                 ("map", "base_link"), [], []))
    parts: dict[str, float] = {}
    timing = [False]
    wait = busy_wait if busy else time.sleep  # the gap after each scan

    def run():
        loc = Localizer(params)
        loc.set_map(occupancy_map)
        pipeline, pf = loc._pipeline, loc._pf
        for owner, name, label in ((pf, "_log_likelihood", "sensor model (kernel)"), (pipeline, "move_to", "move"),
                                   (loc._timeline, "pose_at", "pose queries"),
                                   (pipeline, "_learn_range_scale", "range scale"),
                                   (pf, "_resample_if_due", "resample"), (pf, "estimate", "estimate"),
                                   (pf, "_weigh", "normalise"), (pipeline.recovery, "decide", "decide (agreement)"),
                                   (pipeline, "_gate", "gate"), (pipeline, "_beams", "beams"),
                                   (pipeline, "_deskew", "deskew")):
            setattr(owner, name, thread_timed(getattr(owner, name), parts, label, lambda: timing[0]))
        feeder = Feeder(loc, make_scorer(occupancy_map, params))
        feeder._start(START_GLOBAL, events[0].stamp)  # as Feeder.run at the first input
        scans, total = 0, 0.0
        for event in events:
            is_scan = isinstance(event, ScanData)
            scans += is_scan
            timing[0] = scans > skip
            t0 = time.thread_time()
            feeder.scan(event) if is_scan else feeder.odometry(event)
            if timing[0]:
                total += time.thread_time() - t0
            if gap and is_scan:
                wait(gap)
        updates = sum(1 for c in getattr(feeder.log, "costs", [])[skip:] if c.particles)
        return total, scans - skip, updates

    best = None
    for k in range(repeat + 1):
        parts.clear()
        total, scans, updates = run()
        if k and (best is None or total < best[0]):
            best = (total, dict(parts), scans, updates)
    total, best_parts, scans, updates = best
    return {"bag": bag, "particles": params.num_particles, "beams": params.num_beams_per_particle, "gap_s": gap,
            "busy": busy, "scans": scans, "sensor_updates": updates, "ms_per_scan": 1e3 * total / scans,
            "parts": {name: 1e3 * v / scans for name, v in sorted(best_parts.items(), key=lambda kv: -kv[1])},
            "load_average": os.getloadavg()[0]}


def busy_wait(seconds: float) -> None:
    """Spend ``seconds`` of wall time in a loop (the processor stays busy, as ``time.sleep`` lets it idle)."""
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        pass


def thread_timed(call, into: dict, key: str, active=lambda: True):
    """``call`` that adds its thread CPU time (``time.thread_time``) to ``into[key]`` while ``active()``."""
    @functools.wraps(call)
    def wrapper(*args, **kwargs):
        if not active():
            return call(*args, **kwargs)
        t0 = time.thread_time()
        try:
            return call(*args, **kwargs)
        finally:
            into[key] = into.get(key, 0.0) + time.thread_time() - t0
    return wrapper


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m localization.benchmarks.per_scan",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--bag", default="bag1", help="a real bag's name (bag1, bag2, bag3, trace0, ...)")
    ap.add_argument("--skip", type=int, default=40, help="scans not timed at the start (the global spread)")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--gap", type=float, default=0.0, metavar="MS",
                    help="milliseconds slept after each scan, as the live node idles between them (default 0)")
    ap.add_argument("--busy", action="store_true",
                    help="spend the gap in a busy loop instead of sleeping (the processor never idles)")
    ap.add_argument("--particles", type=int, default=None, metavar="N",
                    help="N particles, every scan updating the filter (default: the file's count and update policy)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    r = measure(args.bag, args.skip, args.repeat, args.gap / 1e3, args.particles, args.busy)
    if args.json:
        print(json.dumps(r))
        return 0
    print(f"{r['bag']}: {r['scans']} scans after the first {args.skip} ({r['sensor_updates']} sensor updates, "
          f"{r['particles']} particles x {r['beams']} beams): {r['ms_per_scan']:.2f} ms of CPU per scan "
          f"(thread time, best of {args.repeat}; {args.gap:g} ms {'busy' if args.busy else 'slept'} after each scan; "
          f"load average {r['load_average']:.1f}), of which")
    for name, ms in r["parts"].items():
        print(f"  {name:24s} {ms:6.3f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
