"""``localization-simulate``: record a simulated RACECAR (or differential-drive) drive as a rosbag2 bag
(see ``localization.sim``)."""
from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from localization.core.occupancy_map import MapError
from localization.core.paths import find_map, is_map_name, map_not_found
from localization.eval.datasets import SIM_TRIALS
from localization.sim import PHYSICS_RATE_HZ, DiffDriveModel, SimConfig, SimulationError, differential_trial, record
from localization.tools.args import Parser, floats, map_name_or_yaml, pose

PROG = "localization-simulate"


def _waypoints(text: str) -> tuple:
    """``"x,y;x,y;..."`` or a file with one ``x, y`` (or ``x y``) per line."""
    p = Path(text)
    if p.is_file():
        rows = [line.split("#")[0].replace(",", " ").split() for line in p.read_text().splitlines()]
        pts = [tuple(float(v) for v in r[:2]) for r in rows if len(r) >= 2]
    else:
        try:
            pts = [floats(item, 2) for item in text.split(";") if item.strip()]
        except argparse.ArgumentTypeError:
            raise argparse.ArgumentTypeError(f"waypoints must be 'x,y;x,y;...' or a file, got {text!r}") from None
    if len(pts) < 2:
        raise argparse.ArgumentTypeError("a route needs at least two waypoints")
    return tuple(pts)


def build_parser() -> argparse.ArgumentParser:
    ap = Parser(
        prog=PROG, description="Simulate the MIT RACECAR (or a differential-drive base) driving a route in a map "
                               "and record a rosbag2 bag (/scan, /odom, ground truth /tf, /tf_static, /initialpose).",
        epilog=f"trials: {', '.join(SIM_TRIALS)}. Example: {PROG} out_bag --trial trial2_noise0.3.")
    ap.add_argument("out", type=Path, help="bag directory to write (must not exist unless --overwrite)")
    ap.add_argument("--trial", choices=sorted(SIM_TRIALS), help="start from a predefined trial "
                    "(route, start, speed, noise); other options override it")
    ap.add_argument("--robot", choices=("ackermann", "differential"), default=None,
                    help="the vehicle: ackermann (the car, default) or differential (turns on the spot, wheel-encoder "
                         "odometry at 20 Hz, 10 Hz lidar; without --trial it drives the differential trial's route "
                         "in the Stata basement)")
    ap.add_argument("--map", type=map_name_or_yaml, help="map name or YAML (default stata_basement)")
    ap.add_argument("--start", type=pose, metavar="X,Y,YAW", help="true start pose")
    ap.add_argument("--waypoints", type=_waypoints, numbers=True, metavar="'X,Y;X,Y;...'|FILE",
                    help="route to drive")
    ap.add_argument("--closed", action="store_true", default=None, help="the route is a loop (needs --duration)")
    ap.add_argument("--speed", type=float, help="cruise speed m/s (max 8)")
    ap.add_argument("--duration", type=float, help="seconds (default: until the end of the route)")
    ap.add_argument("--seed", type=int, help="random seed of the odometry and lidar noise (default: the trial's, "
                    "else 0): the same seed records the same bag")
    ap.add_argument("--odom-noise", type=float, metavar="K", help="std of the noise on vx, vy (m/s) and wz (rad/s)")
    ap.add_argument("--speed-scale", type=float, help="odometry speed scale bias (e.g. 0.95)")
    ap.add_argument("--yaw-rate-bias", type=float, help="odometry yaw-rate bias (rad/s)")
    ap.add_argument("--yaw-rate-scale", type=float, help="odometry yaw-rate scale (e.g. 1.04)")
    ap.add_argument("--odom-latency", type=float, metavar="S", help="odometry reports the twist S seconds late")
    ap.add_argument("--range-noise", type=float, help="lidar range noise std (m), default 0.01")
    ap.add_argument("--sweep", action="store_true", default=None,
                    help="per-beam sweep timing (time_increment filled, the car moves during the scan)")
    ap.add_argument("--no-initialpose", action="store_true", help="do not record /initialpose")
    ap.add_argument("--initial-offset", type=pose, metavar="DX,DY,DYAW",
                    help="/initialpose = true start + offset (map frame), default 0.3,0.4,0.2")
    ap.add_argument("--kidnap-at", type=float, metavar="T", help="teleport the car T seconds after the start")
    ap.add_argument("--kidnap-to", type=pose, metavar="X,Y,YAW", help="where to teleport it")
    ap.add_argument("--storage", choices=("sqlite3", "mcap"), default="sqlite3",
                    help="rosbag2 storage format of the bag (default sqlite3: a .db3 file; mcap for Foxglove)")
    ap.add_argument("--overwrite", action="store_true", help="replace an existing bag directory at OUT")
    return ap


def config_from_args(args) -> SimConfig:
    if args.trial:
        cfg = SIM_TRIALS[args.trial].config
        if args.robot == "differential":
            cfg = replace(cfg, car=DiffDriveModel(), speed=min(cfg.speed, DiffDriveModel().max_speed))
    else:
        cfg = differential_trial() if args.robot == "differential" else SimConfig()
    changes = {}
    for name, attr in (("map", "map"), ("start", "start"), ("waypoints", "waypoints"), ("closed", "closed"),
                       ("speed", "speed"), ("duration", "duration"), ("seed", "seed"),
                       ("odom_noise", "odom_noise"), ("speed_scale", "speed_scale"),
                       ("yaw_rate_bias", "yaw_rate_bias"), ("range_noise", "range_noise"),
                       ("yaw_rate_scale", "yaw_rate_scale"), ("odom_latency", "odom_latency"), ("sweep", "sweep"),
                       ("initial_offset", "initial_offset"), ("kidnap_at", "kidnap_at"),
                       ("kidnap_to", "kidnap_to")):
        value = getattr(args, name)
        if value is not None:
            changes[attr] = value
    if args.no_initialpose:
        changes["initial_pose"] = False
    cfg = replace(cfg, **changes)
    if not cfg.waypoints:
        raise SimulationError("no route: give --trial or --waypoints")
    if is_map_name(cfg.map) and find_map(str(cfg.map)) is None:
        raise SimulationError(map_not_found(str(cfg.map)))
    if cfg.closed and cfg.duration is None:
        raise SimulationError("a closed route needs --duration")
    if (cfg.kidnap_at is None) != (cfg.kidnap_to is None):
        raise SimulationError("--kidnap-at and --kidnap-to go together")
    if not 0 < cfg.speed <= cfg.car.max_speed:
        raise SimulationError(f"--speed must be in (0, {cfg.car.max_speed}] m/s")
    return cfg


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        cfg = config_from_args(args)
        rec = record(cfg, args.out, storage=args.storage, overwrite=args.overwrite)
    except (SimulationError, MapError, ValueError, OSError) as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 1
    traj = rec.trajectory
    dist = float(np.sum(np.abs(traj.v)) / PHYSICS_RATE_HZ)
    print(f"wrote {args.out}: {rec.duration:.1f} s, {dist:.1f} m driven, {len(rec.scan_t)} scans, "
          f"{len(rec.odometry.t)} odometry, min wall clearance {traj.min_clearance:.2f} m")
    return 0


if __name__ == "__main__":
    sys.exit(main())
