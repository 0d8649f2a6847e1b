"""``localization-calibrate``: calibrate a car from one bag (odometry timing and scales, laser
mount, lidar range scale) against a map; see ``localization.eval.calibration``.

Usage::

    localization-calibrate BAG --map MAP [--initial-pose X,Y,YAW] [--scan-topic T] [--odom-topic T]
                           [--params FILE] [--json] [--out params.yaml [--overwrite]] [--quiet]

Initial pose: ``--initial-pose``, else the bag's first ``/initialpose``. The laser mount assumed
while matching (any guess within a few centimetres will do) and the topics come from ``--params``
(laser_offset_*, scan_topic, odom_topic); without it, the parameters are picked as
``localization-replay`` picks them (``tools.args.parameters_for_bags``: the built-in defaults, or
config/real_params.yaml for a bag with the car's ``/vesc/odom`` and no ``/odom``). A topic missing
from the bag is one error line naming the bag's topics of that type. ``--out`` is checked before
the work starts (its folder must exist; an existing file is replaced only with ``--overwrite``).
``--json`` prints one object: the eight values under their names (numbers), their 1 σ under
``uncertainty``. ``--out`` writes a ROS 2 parameter file fragment (``particle_filter:
ros__parameters: {...}``) to merge into the car's parameter file.

Exit status: 0 success; 1 missing/unusable bag, map, topic or too little data (one line on stderr);
2 bad arguments.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from localization.bags import BagError
from localization.core.occupancy_map import MapError
from localization.core.parameters import ParameterError
from localization.eval.calibration import KEYS, CalibrationError, calibrate_bag
from localization.eval.progress import busy
from localization.eval.replay import ReplayError, check_topics
from localization.tools import args as args_

PROG = "localization-calibrate"


def build_parser() -> argparse.ArgumentParser:
    ap = args_.Parser(prog=PROG, description="Estimate odometry time offset, speed and yaw-rate scale, yaw-rate "
                      "bias, laser mount and lidar range scale from a bag and a map.")
    ap.add_argument("bag", type=Path, help="rosbag2 directory, .db3, .mcap or ROS 1 .bag")
    ap.add_argument("--map", required=True, type=args_.map_name_or_yaml,
                    help="map_server YAML (or a map name in the maps directory)")
    ap.add_argument("--initial-pose", type=args_.pose, metavar="X,Y,YAW",
                    help="approximate start pose of base_link (map frame, to ~0.5 m / 0.3 rad); default: the bag's "
                         "/initialpose")
    ap.add_argument("--scan-topic", default=None, help="default: the scan_topic parameter (/scan)")
    ap.add_argument("--odom-topic", default=None, help="default: the odom_topic parameter (/odom)")
    ap.add_argument("--params", type=Path, help=args_.PARAMS_HELP + "; gives the topics and the laser mount guess")
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--out", type=Path, help="write a ROS 2 parameter file fragment here (its folder must exist)")
    ap.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    ap.add_argument("--quiet", action="store_true", help="no progress lines or bar on stderr (--json implies it)")
    return ap


def check_bag_topics(bag, scan_topic: str, odom_topic: str) -> None:
    """The bag has the scan and odometry topics (ReplayError naming the bag's topics of that type
    otherwise, as localization-replay says it)."""
    from localization.bags import open_bag
    with open_bag(bag) as b:
        check_topics(b.topic_infos, b.path, scan_topic, odom_topic, None, "", bag_initial_pose=False)


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        if args.out is not None:
            problem = args_.output_problem(args.out, args.overwrite, kind="file")
            if problem:
                raise CalibrationError(f"--out: {problem}")
        if not Path(args.bag).exists():
            raise CalibrationError(f"bag not found: {args.bag}")
        params = args_.parameters_for_bags(args.params, {}, [args.bag], args.odom_topic, PROG)
        scan_topic, odom_topic = args.scan_topic or params.scan_topic, args.odom_topic or params.odom_topic
        check_bag_topics(args.bag, scan_topic, odom_topic)
        occupancy_map = args_.load_map(args.map)
        mount = (params.laser_offset_x, params.laser_offset_y, params.laser_offset_yaw)
        quiet = args.json or args.quiet
        with busy("calibrating", enabled=False if quiet else None) as say:  # a bar when stderr is a terminal
            res = calibrate_bag(args.bag, occupancy_map, scan_topic, odom_topic, args.initial_pose, mount,
                                log=None if quiet else say, scan_stamp=params.scan_stamp,
                                scan_stamp_offset=params.scan_stamp_offset, odom_frame=params.odom_frame)
        if args.out is not None:
            try:
                Path(args.out).write_text(res.parameter_yaml())
            except OSError as exc:
                raise CalibrationError(f"cannot write {args.out}: {exc}") from None
    except (CalibrationError, BagError, MapError, ParameterError, ReplayError) as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130
    d = res.as_dict()
    if args.json:
        print(json.dumps(d))
    else:
        width = max(len(k) for k in KEYS)
        print(f"{res.good_scans} of {res.scans} scans matched, {res.pairs} scan pairs; residual rms "
              f"{res.residual_rms['xy_m']:.4f} m, {res.residual_rms['theta_rad']:.4f} rad")
        for k in KEYS:
            print(f"{k:<{width}}  {d[k]: .5f}  ± {d['uncertainty'][k]:.5f}")
        r, c = d["rejected"], d["channel_offsets"]
        print(f"rejected as slip/skid: {r['pairs']} of {r['of']} scan pairs ({r['seconds']:.1f} s); time offset of "
              f"the speed alone {c['speed_s']:+.3f} ± {c['speed_sigma_s']:.3f} s, of the yaw rate alone "
              f"{c['yaw_rate_s']:+.3f} ± {c['yaw_rate_sigma_s']:.3f} s")
        if args.out is not None:
            print(f"parameters written to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
