"""``localization-replay``: the command line of ``localization.eval.replay`` (see its docstring)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from localization.core.parameters import ParameterError, Parameters
from localization.eval.replay import (
    PROG,
    ReplayError,
    ReplayOptions,
    compute_metrics,
    default_out_dir,
    run_replay,
    summary_table,
    write_outputs,
)
from localization.tools import args as args_


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog=PROG, description="Replay a bag through the localizer as fast as possible "
                                 "and measure how well it localizes.",
                                 epilog="Values starting with '-' need '=': --initial-pose=-6.0,20.0,-2.24")
    ap.add_argument("bag", type=Path, help="rosbag2 directory, .db3, .mcap or ROS 1 .bag")
    ap.add_argument("--map", required=True, type=args_.map_name_or_yaml,
                    help="map_server YAML (or a map name in the maps directory)")
    ap.add_argument("--params", type=Path, help="ROS 2 parameter file, or a name in the package's config/ (params, "
                    "real_params); default: the built-in defaults")
    ap.add_argument("-p", "--param", dest="overrides", action="append", type=args_.param_override, default=[],
                    metavar="NAME=VALUE", help="override one parameter (repeatable)")
    ap.add_argument("--particles", type=int, help="shortcut for -p num_particles=N")
    ap.add_argument("--out", type=Path, help="output folder (default: a new replay-<bag>-<time> folder here)")
    ap.add_argument("--initial-pose", type=args_.pose, metavar="X,Y,YAW", help="initial pose (map frame)")
    ap.add_argument("--global", dest="force_global", action="store_true", help="start with global localization")
    ap.add_argument("--seed", type=int, default=0, help="random seed (default 0; -1: nondeterministic)")
    ap.add_argument("--scan-topic", help="default: the scan_topic parameter (/scan)")
    ap.add_argument("--odom-topic", help="default: the odom_topic parameter (/odom)")
    ap.add_argument("--truth-topic", help="ground truth topic (Odometry, PoseStamped, PoseWithCovarianceStamped or "
                                          "TFMessage); default /tf map -> base_link when present")
    ap.add_argument("--truth-frames", default="map,base_link", metavar="PARENT,CHILD",
                    help="frames of the TF ground truth (default map,base_link)")
    ap.add_argument("--no-plots", action="store_true", help="skip trajectory.png and error.png")
    ap.add_argument("--mcap", action="store_true", help="also write the run as an MCAP bag (run_mcap/: map, scans, "
                    "particles, estimate, truth or reference track, TF) for Foxglove Studio or ros2 bag play")
    ap.add_argument("--force", "--overwrite", dest="force", action="store_true",
                    help="write into an --out folder that exists already (its files are replaced)")
    ap.add_argument("--reference", dest="reference", action="store_true", default=None,
                    help="score the estimate against a scan-to-map reference track (default: when the bag has no "
                         "ground truth)")
    ap.add_argument("--no-reference", dest="reference", action="store_false")
    ap.add_argument("--progress", dest="progress", action="store_true", default=None,
                    help="show the progress bar (default: when stderr is a terminal)")
    ap.add_argument("--no-progress", dest="progress", action="store_false")
    ap.add_argument("--quiet", action="store_true", help="no summary table")
    return ap


def params_from_args(args, params_file=None) -> Parameters:
    overrides = dict(args.overrides)
    if args.particles is not None:
        overrides["num_particles"] = args.particles
    overrides["random_seed"] = args.seed
    try:
        return args_.load_parameters(params_file or args.params, overrides)
    except ParameterError as exc:
        raise ReplayError(str(exc)) from None


def params_for_bag(args, params: Parameters) -> Parameters:
    """Without ``--params``, a bag that has the car's odometry topic (``/vesc/odom``, not the
    simulator's ``/odom``) is replayed with the car's parameters (config/real_params.yaml), saying so."""
    if args.params is not None or args.odom_topic or not Path(args.bag).exists():
        return params
    from localization.bags import BagError, open_bag
    try:
        with open_bag(args.bag) as bag:
            topics = set(bag.topic_infos)
    except BagError:
        return params
    real = params_from_args(args, "real_params")
    if params.odom_topic in topics or real.odom_topic not in topics:
        return params
    print(f"{PROG}: note: no --params given and the bag has {real.odom_topic}, not {params.odom_topic}: using the "
          "car's parameters (config/real_params.yaml); pass --params params for the simulator's", file=sys.stderr)
    return real


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        params = params_from_args(args)
        params = params_for_bag(args, params)
        frames = tuple(f.strip() for f in args.truth_frames.split(","))
        if len(frames) != 2 or not all(frames):
            raise ReplayError(f"--truth-frames needs PARENT,CHILD, got {args.truth_frames!r}")
        if not Path(args.bag).exists():
            raise ReplayError(f"bag not found: {args.bag}")
        out = args.out if args.out is not None else default_out_dir(args.bag)
        if out.exists() and (not out.is_dir() or any(out.iterdir())) and not args.force:
            raise ReplayError(f"output folder {out} exists already: choose another --out, or pass --force to "
                              "replace its files")
        recorder = None
        if args.mcap:
            from localization.eval.export import ReplayRecorder
            recorder = ReplayRecorder()
        opts = ReplayOptions(args.bag, args.map, params, args.initial_pose, args.force_global, args.scan_topic,
                             args.odom_topic, args.truth_topic, frames,
                             sys.stderr.isatty() if args.progress is None else args.progress,
                             reference=args.reference, on_scan=recorder)
        res = run_replay(opts)
        metrics = compute_metrics(res)
        write_outputs(res, metrics, out, plots=not args.no_plots)
        if recorder is not None:
            from localization.eval.export import BagError, write_run_mcap
            try:
                write_run_mcap(Path(out) / "run_mcap", res, recorder, params.map_frame)
            except BagError as exc:
                raise ReplayError(str(exc)) from None
    except ReplayError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130
    if not args.quiet:
        print(summary_table(metrics, out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
