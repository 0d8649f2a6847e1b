"""The live node's own CPU per second of data, without DDS or an executor: RSS bag1's recorded CDR bytes
handed to ``ParticleFilterNode``'s callbacks in their recorded order.

    python -m localization.benchmarks.node_callbacks [--bag bag1] [--repeat 3] [--json]

The node is built with the robot's parameter file (config/real_params.yaml for the RSS bags; its particles and
update policy), given the map (``on_map``) and the bag's start pose (``on_initialpose``, at the first
odometry's time); then each odometry message goes to ``on_odometry`` and each scan to ``on_scan`` as the
subscriptions deliver them (raw CDR bytes), and their outputs are published (no subscriber: the cloud is not
serialized). Printed: the callbacks' thread CPU time (``time.thread_time``) per second of bag, the node's
share of one core without transport or executor, split into odometry and scan callbacks, and for each the part
spent inside the ``Localizer`` (the core); best of ``--repeat`` runs after a first warm-up run. The live
share, DDS and the executor included, is ``benchmarks.latency --car``'s.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time


def measure(bag: str = "bag1", repeat: int = 3) -> dict:
    import rclpy
    from rclpy.parameter import Parameter

    from localization.bags import read_messages
    from localization.benchmarks.per_scan import thread_timed
    from localization.core.occupancy_map import load_map
    from localization.core.parameters import Parameters
    from localization.core.paths import config_dir
    from localization.eval.datasets import real_bag, real_bag_path
    from localization.ros.messages import occupancy_grid_msg, pose_with_covariance_msg
    from localization.ros.node import ParticleFilterNode

    rb = real_bag(bag)
    params_file = config_dir() / rb.params
    file_params = Parameters.from_yaml(params_file)
    recorded = list(read_messages(real_bag_path(rb.name), [rb.scan_topic, rb.odom_topic]))
    messages = [(m.topic == rb.scan_topic, m.raw_cdr) for m in recorded]
    duration = 1e-9 * (recorded[-1].t_ns - recorded[0].t_ns)
    grid = occupancy_grid_msg(load_map(rb.map))
    start = pose_with_covariance_msg(rb.start, [[0.3 ** 2, 0, 0], [0, 0.3 ** 2, 0], [0, 0, 0.1 ** 2]], 0.0, "map")

    def run(ctx) -> dict:
        overrides = [Parameter("random_seed", value=0), Parameter("scan_topic", value=rb.scan_topic),
                     Parameter("odom_topic", value=rb.odom_topic), Parameter("scan_stamp", value=rb.scan_stamp)]
        node = ParticleFilterNode(context=ctx, cli_args=["--ros-args", "--params-file", str(params_file)],
                                  parameter_overrides=overrides)
        try:
            node.on_map(grid)
            while not node.map_install.idle:
                time.sleep(0.01)
            first = next(k for k, (is_scan, _) in enumerate(messages) if not is_scan)
            node.on_odometry(messages[first][1])  # the start pose is then stamped at its time
            node.on_initialpose(start)
            core = {"odometry": 0.0, "scan": 0.0}
            for owner, name, kind in ((node.localizer, "on_odometry", "odometry"), (node.localizer, "on_scan", "scan")):
                setattr(owner, name, thread_timed(getattr(owner, name), core, kind))
            total = {"odometry": 0.0, "scan": 0.0}
            for is_scan, raw in messages[:first] + messages[first + 1:]:
                kind = "scan" if is_scan else "odometry"
                t0 = time.thread_time()
                node.on_scan(raw) if is_scan else node.on_odometry(raw)
                total[kind] += time.thread_time() - t0
            return {"total": total, "core": core, "scans": node.counts["scan"]}
        finally:
            node.destroy_node()

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    try:
        runs = [run(ctx) for _ in range(repeat + 1)][1:]
    finally:
        rclpy.shutdown(context=ctx)
    best = min(runs, key=lambda r: sum(r["total"].values()))
    share = {k: 100.0 * v / duration for k, v in best["total"].items()}
    core = {k: 100.0 * v / duration for k, v in best["core"].items()}
    return {"bag": bag, "particles": file_params.num_particles, "bag_seconds": duration, "scans": best["scans"],
            "share_percent": sum(share.values()), "by_callback_percent": share, "core_percent": core,
            "load_average": os.getloadavg()[0]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m localization.benchmarks.node_callbacks",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--bag", default="bag1", help="a real RSS bag's name (bag1, bag2, bag3)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    r = measure(args.bag, args.repeat)
    if args.json:
        print(json.dumps(r))
        return 0
    by, core = r["by_callback_percent"], r["core_percent"]
    print(f"{r['bag']} ({r['bag_seconds']:.1f} s, {r['particles']} particles): the node's callbacks take "
          f"{r['share_percent']:.1f} % of one core (thread CPU time per second of bag, best of {args.repeat}; "
          f"load average {r['load_average']:.1f})")
    for kind in ("odometry", "scan"):
        print(f"  {kind:9s} {by[kind]:5.1f} %, of which in the Localizer {core[kind]:5.1f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
