"""A cold start of the live node, checked against replay on the same bag.

    python -m localization.benchmarks.cold_start [--runs 5] [--warm-after-first] [--rate 1] [--json]

Each run starts a fresh ``particle_filter`` process with ``config/real_params.yaml``,
``random_seed`` 0 (replay's default seed) and scans subscribed reliable (no scan lost to the
sensor-data QoS, so the node sees what replay reads), and ``LOCALIZATION_CACHE_DIR`` a new empty
folder: the map arrives over DDS and its range table is built (cold). With ``--warm-after-first``
the runs after the first reuse the first run's cache folder (the table is loaded). Then the
documented one-liner plays the bag into it:

    localization-play BAG --map basement_fixed --initial-pose 0.8,-0.3,1.26

(play waits until the node is ready before the bag). ``/pf/pose/odom`` is recorded. The reference
is ``localization-replay`` on the same bag, map, parameters, initial pose and seed; per run

    error = |p_node(t) − p_replay(t)| at the last odometry time t both have (m)

and whether the stamps on /pf/pose/odom ever went backwards. Prints one line per run (table build
seconds from the node's log, seconds until play saw the node ready, error, poses, stamps
monotonic, the node's exit code) and a summary; ``--json`` prints the results as JSON.
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

BAG = "rss2022/localization_bag1_2022-03-29-19-23-29.bag"
MAP = "basement_fixed"
INITIAL_POSE = (0.8, -0.3, 1.26)  # m, m, rad: the bag's start (bags/README.md)
PARAMS = "real_params"
SEED = 0
STAMP_MATCH_S = 1e-4  # s: node and replay stamps of one odometry message agree to this (float seconds)
NODE_EXIT_TIMEOUT_S = 20.0
DISCOVERY_TIMEOUT_S = 60.0  # s: the node process starting and being discovered (imports take seconds)


@dataclass
class ColdRun:
    cold: bool
    node_exit: int | None
    play_exit: int
    table_build_s: float | None  # from the node's log ("range table built in X s"), None when loaded
    ready_after_s: float | None  # from play's log
    poses: int
    stamps_monotonic: bool
    final_stamp: float | None
    error_m: float | None  # at the last common odometry time
    node_log: str = field(repr=False, default="")
    play_log: str = field(repr=False, default="")


def _env(cache: Path | None = None) -> dict:
    env = dict(os.environ)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env.setdefault("ROS_DOMAIN_ID", str(np.random.default_rng().integers(1, 200)))
    env["PYTHONUNBUFFERED"] = "1"
    if cache is not None:
        env["LOCALIZATION_CACHE_DIR"] = str(cache)
    return env


def replay_poses(bag: Path, out: Path) -> tuple[np.ndarray, np.ndarray]:
    """(t (N,), poses (N, 3)) of ``localization-replay`` (one per odometry message, scan clock)."""
    cmd = [sys.executable, "-m", "localization.tools.replay", str(bag), "--map", MAP, "--params", PARAMS,
           "--initial-pose", ",".join(map(str, INITIAL_POSE)), "--seed", str(SEED), "--out", str(out), "--force",
           "--no-plots", "--no-reference", "--quiet"]
    proc = subprocess.run(cmd, env=_env(), capture_output=True, text=True, timeout=600)
    if proc.returncode != 0:
        raise RuntimeError(f"localization-replay failed ({proc.returncode}): {proc.stderr[-2000:]}")
    with open(out / "poses.csv") as f:
        rows = [[float(v) for v in r.values()] for r in csv.DictReader(f)]
    a = np.asarray(rows)
    return a[:, 0], a[:, 1:4]


class _Recorder:
    """/pf/pose/odom (stamp, x, y, θ) in this process, on its own rclpy context."""

    def __init__(self):
        import rclpy
        from nav_msgs.msg import Odometry
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor

        from localization.core.geometry import quaternion_to_yaw
        from localization.ros.conversions import stamp_to_sec
        self.context = Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node("cold_start_recorder", context=self.context)
        self.lock = threading.Lock()
        self.rows: list[tuple] = []

        def keep(msg):
            p, q = msg.pose.pose.position, msg.pose.pose.orientation
            with self.lock:
                self.rows.append((stamp_to_sec(msg.header.stamp), p.x, p.y, quaternion_to_yaw(q.x, q.y, q.z, q.w)))

        self.node.create_subscription(Odometry, "/pf/pose/odom", keep, 1000)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    def wait_matched(self, timeout: float) -> bool:
        """Until a /pf/pose/odom publisher (the node) is matched, at most ``timeout`` s."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.node.count_publishers("/pf/pose/odom") > 0:
                return True
            time.sleep(0.05)
        return False

    def take(self) -> np.ndarray:
        with self.lock:
            rows, self.rows = self.rows, []
        return np.asarray(rows, dtype=float).reshape(-1, 4)

    def close(self) -> None:
        import rclpy
        self.executor.shutdown(timeout_sec=2.0)
        self.thread.join(timeout=2.0)
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)


def run_once(bag: Path, cache: Path, recorder: _Recorder, reference, rate: float, cold: bool) -> ColdRun:
    """One node process + localization-play; compared with the replay ``reference`` (t, poses)."""
    env = _env(cache)
    node_cmd = [sys.executable, "-m", "localization.particle_filter", "--ros-args", "--params-file", PARAMS,
                "-p", f"random_seed:={SEED}", "-p", "qos_overrides./scan.subscription.reliability:=reliable"]
    play_cmd = [sys.executable, "-m", "localization.tools.play", str(bag), "--map", MAP,
                "--initial-pose=" + ",".join(map(str, INITIAL_POSE)), "--rate", str(rate)]
    recorder.take()
    with tempfile.TemporaryFile("w+") as node_out:
        node = subprocess.Popen(node_cmd, env=env, stdout=node_out, stderr=subprocess.STDOUT, text=True)
        try:
            recorder.wait_matched(DISCOVERY_TIMEOUT_S)  # no pose missed for a slow discovery
            play = subprocess.run(play_cmd, env=env, capture_output=True, text=True, timeout=600)
            time.sleep(0.5)  # the last outputs
        finally:
            node.send_signal(signal.SIGINT)
            try:
                node_exit = node.wait(NODE_EXIT_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                node.kill()
                node.wait()
                node_exit = None
        node_out.seek(0)
        node_log = node_out.read()
    rows = recorder.take()
    built = re.search(r"range table built in ([0-9.]+) s", node_log)
    ready = re.search(r"ready after ([0-9.]+) s", play.stdout)
    t_ref, p_ref = reference
    error = final = None
    if len(rows):
        stamps = rows[:, 0]
        for k in range(len(rows) - 1, -1, -1):  # the last node pose replay also has
            j = int(np.argmin(np.abs(t_ref - stamps[k])))
            if abs(t_ref[j] - stamps[k]) <= STAMP_MATCH_S:
                final, error = float(stamps[k]), float(np.hypot(*(rows[k, 1:3] - p_ref[j, :2])))
                break
    return ColdRun(cold=cold, node_exit=node_exit, play_exit=play.returncode,
                   table_build_s=float(built.group(1)) if built else None,
                   ready_after_s=float(ready.group(1)) if ready else None, poses=len(rows),
                   stamps_monotonic=bool(np.all(np.diff(rows[:, 0]) > 0)) if len(rows) > 1 else True,
                   final_stamp=final, error_m=error, node_log=node_log, play_log=play.stdout + play.stderr)


def run(runs: int = 5, warm_after_first: bool = False, rate: float = 1.0, bag: Path | None = None,
        say=print) -> tuple[list[ColdRun], tuple]:
    """``runs`` node runs (cold each, or only the first) and the replay reference."""
    from localization.core.paths import shared_dir
    bag = bag or shared_dir() / "bags" / BAG
    with tempfile.TemporaryDirectory(prefix="cold_start_") as tmp:
        tmp = Path(tmp)
        reference = replay_poses(bag, tmp / "replay")
        recorder = _Recorder()
        results = []
        try:
            for k in range(runs):
                cold = k == 0 or not warm_after_first
                cache = tmp / ("cache" if warm_after_first else f"cache{k}")
                cache.mkdir(exist_ok=True)
                r = run_once(bag, cache, recorder, reference, rate, cold)
                results.append(r)
                say(format_run(k, r))
        finally:
            recorder.close()
    return results, reference


def format_run(k: int, r: ColdRun) -> str:
    build = f"table built in {r.table_build_s:.1f} s" if r.table_build_s is not None else "table loaded"
    ready = f"ready after {r.ready_after_s:.1f} s" if r.ready_after_s is not None else "never ready"
    error = f"{r.error_m:.4f} m" if r.error_m is not None else "n/a"
    return (f"run {k + 1} ({'cold' if r.cold else 'warm'}): {build}, {ready}; final error vs replay {error}; "
            f"{r.poses} poses on /pf/pose/odom, stamps {'monotonic' if r.stamps_monotonic else 'WENT BACK'}; "
            f"node exit {r.node_exit}, play exit {r.play_exit}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m localization.benchmarks.cold_start",
                                 description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--warm-after-first", action="store_true", help="only the first run starts with an empty cache")
    ap.add_argument("--rate", type=float, default=1.0, help="localization-play --rate")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    results, _ = run(args.runs, args.warm_after_first, args.rate, say=(lambda _: None) if args.json else print)
    errors = [r.error_m for r in results if r.error_m is not None]
    if args.json:
        print(json.dumps([{k: v for k, v in asdict(r).items() if not k.endswith("_log")} for r in results], indent=1))
    else:
        good = sum(1 for r in results if r.error_m is not None and r.error_m <= 0.1 and r.stamps_monotonic)
        print(f"{good} of {len(results)} runs end within 0.1 m of replay with monotonic stamps; final error max "
              f"{max(errors) if errors else float('nan'):.4f} m")
    return 0


if __name__ == "__main__":
    sys.exit(main())
