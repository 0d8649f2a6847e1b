"""``localization-replay``: the command line of ``localization.eval.replay`` (see its docstring)."""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from localization.core.parameters import ParameterError, Parameters
from localization.eval.progress import progress_enabled
from localization.eval.replay import (
    PROG,
    ReplayError,
    ReplayOptions,
    compute_metrics,
    default_out_dir,
    load_map,
    run_replay,
    summary_table,
    write_outputs,
)
from localization.ros.live_view import DEFAULT_PORT as LIVE_PORT
from localization.tools import args as args_


def build_parser() -> argparse.ArgumentParser:
    ap = args_.Parser(prog=PROG, description="Replay a bag through the localizer as fast as possible and measure "
                      "how well it localizes.")
    ap.add_argument("bag", type=Path, help="rosbag2 directory, .db3, .mcap or ROS 1 .bag")
    ap.add_argument("--map", required=True, type=args_.map_name_or_yaml,
                    help="map_server YAML (or a map name in the maps directory)")
    ap.add_argument("--params", type=Path, help=args_.PARAMS_HELP)
    ap.add_argument("-p", "--param", dest="overrides", action="append", type=args_.param_override, default=[],
                    metavar="NAME=VALUE", help="override one parameter (repeatable; NAME:=VALUE works too)")
    ap.add_argument("--particles", type=int, help="shortcut for -p num_particles=N")
    ap.add_argument("--threads", type=int, default=None, metavar="N",
                    help="CPU threads of the sensor update (num_threads; the same results as one thread); default: "
                         "every core of this machine, whatever the parameter file gives the robot's computer "
                         "(-p num_threads:=N wins)")
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
                    help="show progress bars on stderr (default: when stderr is a terminal and not --quiet)")
    ap.add_argument("--no-progress", dest="progress", action="store_false")
    ap.add_argument("--quiet", action="store_true", help="no summary table, no progress bars")
    ap.add_argument("--foxglove", nargs="?", const=LIVE_PORT, type=_port, metavar="PORT",
                    help=f"serve a live view (map, scan, particles, estimate, reference track, TF) over the "
                         f"Foxglove WebSocket protocol on 127.0.0.1:PORT (default {LIVE_PORT}; open it in the "
                         "Foxglove app: Open connection, ws://127.0.0.1:PORT); the replay runs at --rate x real "
                         "time and the view stays up at the end until Ctrl-C (needs pip install foxglove-sdk)")
    ap.add_argument("--foxglove-host", default="127.0.0.1", metavar="ADDRESS",
                    help="address the live view binds to (default 127.0.0.1: this machine only)")
    ap.add_argument("--rate", type=args_.non_negative_float, default=1.0,
                    help="with --foxglove: bag seconds replayed per second (default 1; 0: as fast as possible)")
    return ap


def params_from_args(args, params_file=None) -> Parameters:
    try:
        return args_.load_parameters(params_file or args.params, overrides_from_args(args))
    except ParameterError as exc:
        raise ReplayError(str(exc)) from None


def overrides_from_args(args) -> dict:
    overrides = dict(args.overrides)
    if args.particles is not None:
        overrides["num_particles"] = args.particles
    if "num_threads" not in overrides:
        overrides["num_threads"] = args.threads if args.threads is not None else min(os.cpu_count() or 1, 256)
    overrides["random_seed"] = args.seed
    return overrides


def params_for_bag(args) -> Parameters:
    """``--params``, else the defaults or the car's parameters, as ``tools.args.parameters_for_bags`` picks."""
    try:
        return args_.parameters_for_bags(args.params, overrides_from_args(args), [args.bag], args.odom_topic, PROG)
    except ParameterError as exc:
        raise ReplayError(str(exc)) from None


def _port(text: str) -> int:
    try:
        port = int(text)
    except ValueError:
        port = -1
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"expected a port number 0-65535 (0: any free port), got {text!r}")
    return port


def _hooks(*hooks):
    """One ``on_scan(scan, localizer)`` calling each of ``hooks`` that is not None (or None)."""
    hooks = [h for h in hooks if h is not None]
    if len(hooks) <= 1:
        return hooks[0] if hooks else None

    def both(scan, localizer):
        for h in hooks:
            h(scan, localizer)
    return both


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    live = None
    try:
        params = params_for_bag(args)
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
        if args.foxglove is not None:
            live = start_live_view(args, params)
        progress = False if args.quiet and args.progress is None else progress_enabled(args.progress)
        opts = ReplayOptions(args.bag, args.map, params, args.initial_pose, args.force_global, args.scan_topic,
                             args.odom_topic, args.truth_topic, frames, progress,
                             reference=args.reference, on_scan=_hooks(recorder, live))
        res = run_replay(opts)
        metrics = compute_metrics(res)
        write_outputs(res, metrics, out, plots=not args.no_plots)
        if live is not None:
            live.finish(res)
        if recorder is not None:
            from localization.eval.export import BagError, write_run_mcap
            try:
                write_run_mcap(Path(out) / "run_mcap", res, recorder, params.map_frame)
            except BagError as exc:
                raise ReplayError(str(exc)) from None
    except ReplayError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        if live is not None:
            live.close()
        return 1
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        if live is not None:
            live.close()
        return 130
    if not args.quiet:
        print(summary_table(metrics, out))
    if live is not None:
        return hold_live_view(live)
    return 0


def start_live_view(args, params: Parameters):
    """The ``--foxglove`` live view (``localization.ros.live_view``), paced at ``--rate``."""
    from localization.ros.live_view import LiveView, LiveViewError
    try:
        live = LiveView(port=args.foxglove, host=args.foxglove_host, map_frame=params.map_frame,
                        base_frame=params.particle_filter_frame, rate=args.rate)
    except LiveViewError as exc:
        raise ReplayError(str(exc)) from None
    live.set_map(load_map(args.map))
    print(f"{PROG}: live view on ws://{args.foxglove_host}:{live.port} (Foxglove app: Open connection > "
          f"Foxglove WebSocket > ws://{args.foxglove_host}:{live.port})", file=sys.stderr)
    return live


def hold_live_view(live) -> int:
    """Keep serving the last state (map, reference track, final cloud) until Ctrl-C."""
    print(f"{PROG}: replay done; the live view stays up on port {live.port}: Ctrl-C to quit", file=sys.stderr)
    try:
        live.wait()
    except KeyboardInterrupt:
        pass
    finally:
        live.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
