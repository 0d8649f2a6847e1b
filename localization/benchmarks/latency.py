"""End-to-end latency of the live ``particle_filter`` node: scan stamp → published pose.

    python -m localization.benchmarks.latency [--particles 4000] [--duration 20] [--json]
    python -m localization.benchmarks.latency --car [--duration 60]   (the file's particles and update policy)
    python -m localization.benchmarks.speed --latency-only    (the same, from the speed benchmark)

Starts the node in its own process (``config/real_params.yaml``, ``--particles``, and
``update_min_distance`` / ``update_min_angle`` 0 so that every scan updates the filter: the worst
case), publishes the ``basement_fixed`` map and an initial pose, then replays the
three real RSS 2022 racecar bags (1081-beam Hokuyo scans at ~40 Hz, VESC odometry at 50 Hz) into
it **at real time**, cyclically until ``--duration`` seconds have been streamed, re-sending each
bag's start pose before it. Each message goes out at its header stamp's time (``--pace stamps``:
when its driver had it, a scan every 25 ms); ``--pace recorded`` sends it when the bag's recorder
received it instead, with the recorder's bursts (a third of the scans 0.2–0.5 ms after the one before,
so they wait for its sensor update). Every scan and odometry message is restamped with the wall clock
just before it is published, so

    latency = (wall time the corrected pose of that scan is received on /pf/pose) − scan stamp

(the node stamps a correction with the time it describes, the scan's mid-sweep time, and
/pf/pose/odom with each odometry message's time + ``odom_time_offset``; both are matched here
to the message they came from, to the microsecond)

covers DDS both ways, queueing in the node, the sensor update and the pose/particles/TF output.
Prints median / p95 / max latency, the fraction of scans that produced a sensor update and a
pose (the target: every scan), the odometry → pose latency too, the node's peak memory (VmHWM),
and where the time went inside the node, read from its shutdown log line (``scan -> pose: total,
wait, deserialize, convert, update, publish`` median/p95 in ms: queued for the sensor-update
thread, CDR bytes → ScanData, its stamp kept and the laser pose, sensor update + resampling, outputs; see
``core.watchdog.Watchdog.run_summary``; ``wait`` is 0 unless ``-p sensor_update_thread:=true``).
A node that cannot keep up shows a latency growing through
the run (compare the first and second half) and scans without a pose.

ROS discovery is kept on this host (``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``) in a random
``ROS_DOMAIN_ID`` unless one is set, so concurrent test runs do not cross-talk.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

BAG_TOPICS = ("/scan", "/vesc/odom")
PARKED_ODOMETRY = 5  # still odometry messages (50 Hz) after each bag: its last scan is reached, as on a car


def _stamp_ns(stamp) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def _set_stamp(header, t_ns: int) -> None:
    header.stamp.sec, header.stamp.nanosec = t_ns // 1_000_000_000, t_ns % 1_000_000_000


def _load_bags(pace: str = "stamps"):
    """[(name, start pose, [(t_rel_s, topic, rclpy message)])] for the real RSS 2022 bags, in the order
    and at the times of ``pace``: "stamps", each message's header stamp (when its driver had it: the
    Hokuyo's scans every 25 ms, the VESC's odometry every 20 ms); "recorded", when the bag's recorder
    received it (the recorder took them in bursts about every 43 ms, up to 37 ms late: a third of the
    scans came 0.2–0.5 ms after the one before)."""
    from nav_msgs.msg import Odometry
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import LaserScan

    from localization.bags import read_messages
    from localization.eval.datasets import REAL_BAGS, real_bag_path

    types = {"/scan": LaserScan, "/vesc/odom": Odometry}
    bags = []
    for name, info in REAL_BAGS.items():
        msgs = []
        for m in read_messages(real_bag_path(name), list(BAG_TOPICS)):
            msg = deserialize_message(m.raw_cdr, types[m.topic])
            t = _stamp_ns(msg.header.stamp) if pace == "stamps" else m.t_ns
            msgs.append((t, m.topic, msg))
        msgs.sort(key=lambda item: item[0])  # stable: a stamp tie keeps the recorded order
        t0 = msgs[0][0]
        bags.append((name, info.start, [((t - t0) * 1e-9, topic, msg) for t, topic, msg in msgs]))
    return bags


def _peak_rss_mb(pid: int) -> dict:
    out = {}
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            key, _, value = line.partition(":")
            if key in ("VmHWM", "VmRSS"):
                out[key] = int(value.split()[0]) / 1024.0
    except OSError:
        pass
    return {"node_peak_rss_mb": out.get("VmHWM"), "node_rss_mb": out.get("VmRSS")}


def _cpu_seconds(pid: int, user_only: bool = False) -> float | None:
    """User + system (``user_only``: user) CPU time (s) the process has used so far (/proc/PID/stat), None when
    unreadable."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + (0 if user_only else int(fields[12]))) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return None


class _Sampler(threading.Thread):
    """Every ``period`` seconds: (seconds since start, the node's RSS in MB, its CPU seconds, its user CPU seconds)."""

    def __init__(self, pid: int, period: float = 5.0):
        super().__init__(daemon=True)
        self.pid, self.period = pid, period
        self.samples: list[tuple[float, float | None, float | None, float | None]] = []
        self.t0 = time.monotonic()
        self.stop = threading.Event()

    def sample(self) -> None:
        self.samples.append((time.monotonic() - self.t0, _peak_rss_mb(self.pid)["node_rss_mb"],
                             _cpu_seconds(self.pid), _cpu_seconds(self.pid, user_only=True)))

    def run(self) -> None:
        self.sample()
        while not self.stop.wait(self.period):
            self.sample()


def _windows(lat: np.ndarray, when: np.ndarray, samples, window: float) -> list[dict]:
    """Per ``window`` seconds of stream: scan -> pose latency median/p95, and the node's RSS at its end."""
    out = []
    for k in range(int(np.ceil(when.max() / window)) if when.size else 0):
        sel = (when >= k * window) & (when < (k + 1) * window)
        rss = [r for t, r, *_ in samples if r is not None and t <= (k + 1) * window]
        out.append({"start_s": k * window, "scans": int(sel.sum()),
                    "latency_ms_median": float(np.median(lat[sel])) if sel.any() else None,
                    "latency_ms_p95": float(np.percentile(lat[sel], 95)) if sel.any() else None,
                    "rss_mb_end": rss[-1] if rss else None})
    return out


def _us(stamp_ns: int, offset_s: float) -> int:
    """The time ``stamp + offset`` in whole microseconds (the node computes it in float seconds)."""
    return stamp_ns // 1000 + round(offset_s * 1e6)


def _match(us: int, sent: dict):
    """The key of ``sent`` within 2 µs of ``us`` (float seconds round either way), or None."""
    for key in (us, us - 1, us + 1, us - 2, us + 2):
        if key in sent:
            return key
    return None


def measure_latency(particles: int | None = 4000, duration: float = 20.0, ray_caster: str | None = None,
                    params_file=None, ready_timeout: float = 180.0, progress=None, extra_params=(),
                    every_scan: bool = True, window: float = 300.0, pace: str = "stamps") -> dict:
    """Run the node, stream the real bags into it at real time, return the latency statistics.
    ``particles`` None: the parameter file's; ``every_scan`` False: the file's update policy (as on
    the car) instead of a sensor update for every scan; ``window``: seconds per row of ``windows``;
    ``pace``: each message sent at its header stamp ("stamps") or its recorder's time ("recorded")."""
    say = progress or (lambda msg: None)
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    os.environ.setdefault("ROS_DOMAIN_ID", str(random.Random().randint(101, 200)))
    try:
        import rclpy
        from geometry_msgs.msg import PoseArray, PoseWithCovarianceStamped
        from nav_msgs.msg import Odometry
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
        from sensor_msgs.msg import LaserScan
    except ImportError as exc:
        return {"error": f"rclpy is not available: {exc}"}
    from localization.core.geometry import yaw_to_quaternion
    from localization.core.occupancy_map import OccupancyMap, resolve_map_path
    from localization.core.paths import config_dir
    from localization.ros import messages

    say("loading the bags and the map ...")
    try:
        bags = _load_bags(pace)
    except Exception as exc:  # noqa: BLE001 - report, do not crash the benchmark
        return {"error": f"cannot read the real bags: {exc}"}
    map_msg = messages.occupancy_grid_msg(OccupancyMap.from_yaml(resolve_map_path("basement_fixed")))
    params_file = Path(params_file) if params_file else config_dir() / "real_params.yaml"

    log = tempfile.NamedTemporaryFile(prefix="latency-node-", suffix=".log", delete=False)
    # every scan updates the filter (no minimum travel between updates): the worst case
    from localization.core.parameters import Parameters
    if particles is None:
        particles = Parameters.from_yaml(params_file).num_particles
    cmd = [sys.executable, "-m", "localization.particle_filter", "--ros-args", "--params-file", str(params_file),
           "-p", f"num_particles:={particles}", "-p", "random_seed:=0", "-p", "odom_topic:=/vesc/odom",
           "-p", "scan_topic:=/scan"]
    if every_scan:
        cmd += ["-p", "update_min_distance:=0.0", "-p", "update_min_angle:=0.0"]
    if ray_caster:
        cmd += ["-p", f"ray_caster:={ray_caster}"]
    else:
        ray_caster = Parameters.from_yaml(params_file).ray_caster
    for item in extra_params:  # NAME:=VALUE (the last word on the particle count is the node's)
        cmd += ["-p", item]
        name, _, value = item.partition(":=")
        if name == "num_particles" and value.isdigit():
            particles = int(value)
    say(f"starting the node ({particles} particles, {ray_caster}) ...")
    node_proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=dict(os.environ))

    rclpy.init(args=[])  # this process's own command line is not ROS arguments (-p NAME:=VALUE goes to the node)
    node = rclpy.create_node("latency_bench")
    map_qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    pub_map = node.create_publisher(type(map_msg), "/map", map_qos)
    pub_init = node.create_publisher(PoseWithCovarianceStamped, "/initialpose", 10)
    pub_scan = node.create_publisher(LaserScan, "/scan", qos_profile_sensor_data)
    pub_odom = node.create_publisher(Odometry, "/vesc/odom", 50)
    poses = []  # (receive wall ns, stamp ns, the node's publish wall ns: the DDS source timestamp)
    poses_lock = threading.Lock()
    clouds = threading.Event()

    def on_pose_or_cloud(msg, info):
        now = time.time_ns()
        clouds.set()
        if isinstance(msg, (Odometry, PoseWithCovarianceStamped)):
            with poses_lock:
                poses.append((now, _stamp_ns(msg.header.stamp), int(info.get("source_timestamp") or 0)))

    node.create_subscription(Odometry, "/pf/pose/odom", on_pose_or_cloud, 100)
    node.create_subscription(PoseWithCovarianceStamped, "/pf/pose", on_pose_or_cloud, 100)
    # raw: the cloud only signals readiness; decoding 500 poses per scan would load this process
    node.create_subscription(PoseArray, "/pf/particles", on_pose_or_cloud, 5, raw=True)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()

    still = Odometry()  # a parked car: makes a ready node publish a pose even without particle output
    still.header.frame_id, still.child_frame_id = "odom", "base_link"
    still.pose.pose.orientation.w = 1.0

    def initial_pose(pose) -> bool:
        """Send an initial pose (and two still odometry messages) until the node answers with a
        particle cloud or a pose."""
        msg = PoseWithCovarianceStamped()
        msg.header.frame_id = "map"
        msg.pose.pose.position.x, msg.pose.pose.position.y = float(pose[0]), float(pose[1])
        q = yaw_to_quaternion(pose[2])
        msg.pose.pose.orientation.z, msg.pose.pose.orientation.w = float(q[2]), float(q[3])
        cov = np.zeros((6, 6))
        cov[0, 0] = cov[1, 1] = 0.3 ** 2
        cov[5, 5] = 0.1 ** 2
        msg.pose.covariance = cov.ravel().tolist()
        clouds.clear()
        for _ in range(int(ready_timeout)):
            _set_stamp(msg.header, time.time_ns())
            pub_init.publish(msg)
            for _ in range(2):
                time.sleep(0.02)
                _set_stamp(still.header, time.time_ns())
                pub_odom.publish(still)
            if clouds.wait(1.0):
                return True
            if node_proc.poll() is not None:
                return False
        return False

    scans_sent, odoms_sent = {}, {}  # µs of the time the output describes -> (header stamp ns, stream time s)
    from localization.core.scan import scan_time
    from localization.ros.conversions import scan_from_msg
    node_params = Parameters.from_yaml(params_file)
    odom_offset = node_params.odom_time_offset

    def sweep_offset(msg) -> float:  # the scan's time under the node's stamp convention, minus its stamp
        scan = scan_from_msg(msg)
        return scan_time(scan, node_params.scan_stamp, node_params.scan_stamp_offset) - scan.stamp
    result = {"particles": particles, "ray_caster": ray_caster, "scan_hz": 40.0, "odom_hz": 50.0,
              "every_scan": every_scan, "extra_params": list(extra_params), "pace": pace,
              "load_average_start": os.getloadavg()[0]}
    sampler = None
    try:
        say("waiting for the node (map + initial pose; a cold start builds the range table) ...")
        t_wait = time.perf_counter()
        pub_map.publish(map_msg)
        if not initial_pose(bags[0][1]):
            tail = Path(log.name).read_text()[-2000:]
            return {"error": f"the node did not become ready within {ready_timeout:.0f} s; its log ends:\n{tail}"}
        result["node_ready_s"] = time.perf_counter() - t_wait
        say(f"streaming the real bags at real time for {duration:g} s ...")
        sampler = _Sampler(node_proc.pid)
        sampler.start()
        streamed = 0.0
        rounds = 0
        while streamed < duration:
            for name, start, msgs in bags:
                if streamed >= duration:
                    break
                if rounds > 0 or name != bags[0][0]:
                    initial_pose(start)
                time.sleep(0.2)
                t0 = time.monotonic()
                for t_rel, topic, msg in msgs:
                    if streamed + t_rel >= duration:
                        break
                    delay = t0 + t_rel - time.monotonic()
                    if delay > 0:
                        time.sleep(delay)
                    stamp = time.time_ns()
                    _set_stamp(msg.header, stamp)
                    if topic == "/scan":  # keyed by the time its correction describes (µs)
                        scans_sent[_us(stamp, sweep_offset(msg))] = (stamp, streamed + t_rel)
                        pub_scan.publish(msg)
                    else:  # keyed by the time its pose describes (µs)
                        odoms_sent[_us(stamp, odom_offset)] = (stamp, streamed + t_rel)
                        pub_odom.publish(msg)
                for _ in range(PARKED_ODOMETRY):  # the car stops; its odometry goes on, as a VESC's does
                    time.sleep(0.02)
                    _set_stamp(still.header, time.time_ns())
                    pub_odom.publish(still)
                streamed += min(msgs[-1][0], duration - streamed)
            rounds += 1
        time.sleep(1.0)  # let the last outputs arrive
        sampler.stop.set()
        sampler.sample()
        result.update(_peak_rss_mb(node_proc.pid))
        result["load_average_end"] = os.getloadavg()[0]
    finally:
        if sampler is not None:
            sampler.stop.set()
        if node_proc.poll() is None:
            node_proc.send_signal(signal.SIGINT)
            try:
                node_proc.wait(10)
            except subprocess.TimeoutExpired:
                node_proc.kill()
                node_proc.wait()
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
        log.close()

    with poses_lock:
        received = list(poses)
    scan_lat, scan_when, odom_lat, scan_pub, odom_pub = [], [], [], [], []
    for recv, stamp, published in received:
        key = _match(stamp // 1000, scans_sent)
        if key is not None:
            sent, when = scans_sent.pop(key)
            scan_lat.append((recv - sent) * 1e-6)
            scan_pub.append((published - sent) * 1e-6 if published else np.nan)
            scan_when.append(when)
            continue
        key = _match(stamp // 1000, odoms_sent)
        if key is not None:
            sent = odoms_sent.pop(key)[0]
            odom_lat.append((recv - sent) * 1e-6)
            odom_pub.append((published - sent) * 1e-6 if published else np.nan)
    if not scan_lat:
        return {**result, "error": f"no pose came back for any scan; node log: {log.name}"}
    node_log = Path(log.name).read_text(errors="replace")
    breakdown = [line.split("scan -> pose: ", 1)[1].strip() for line in node_log.splitlines()
                 if "scan -> pose: " in line]
    result["node_breakdown"] = breakdown[-1] if breakdown else None
    counts = [line.split("]: scans: ", 1)[1].split(";", 1)[0] for line in node_log.splitlines() if "]: scans: " in line]
    result["node_scan_counts"] = counts[-1] if counts else None  # the node's own: received, processed, not used
    lat, when = np.asarray(scan_lat), np.asarray(scan_when)
    half = when < np.median(when)
    samples = sampler.samples
    cpu = [(t, c) for t, _, c, _ in samples if c is not None]
    user = [(t, u) for t, _, _, u in samples if u is not None]
    rss = [(t, r) for t, r, _, _ in samples if r is not None]
    after_first_minute = [r for t, r in rss if t >= 60.0]
    result.update(
        node_cpu_share=(cpu[-1][1] - cpu[0][1]) / (cpu[-1][0] - cpu[0][0]) if len(cpu) > 1 else None,
        node_user_cpu_share=(user[-1][1] - user[0][1]) / (user[-1][0] - user[0][0]) if len(user) > 1 else None,
        rss_growth_after_first_minute_mb=(after_first_minute[-1] - after_first_minute[0])
        if len(after_first_minute) > 1 else None,
        windows=_windows(lat, when, samples, window))
    result.update(
        duration_s=duration, scans_sent=len(scan_lat) + len(scans_sent), poses_from_scans=len(scan_lat),
        scans_skipped=len(scans_sent), processed_fraction=len(scan_lat) / max(1, len(scan_lat) + len(scans_sent)),
        latency_ms_median=float(np.median(lat)), latency_ms_p95=float(np.percentile(lat, 95)),
        latency_ms_max=float(lat.max()),
        latency_ms_median_first_half=float(np.median(lat[half])) if half.any() else None,
        latency_ms_median_second_half=float(np.median(lat[~half])) if (~half).any() else None,
        odom_latency_ms_median=float(np.median(odom_lat)) if odom_lat else None,
        odom_latency_ms_p95=float(np.percentile(odom_lat, 95)) if odom_lat else None,
        odom_poses=len(odom_lat), node_log=log.name,
        **_node_side("latency", scan_pub), **_node_side("odom_latency", odom_pub),
    )
    return result


def _node_side(name: str, values: list) -> dict:
    """Median / p95 (ms) of stamp -> the node's publishing of the pose (the DDS source timestamp of the pose
    message, the node's wall clock: the same machine's): the latency without this process's own receiving."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if not v.size:
        return {}
    return {f"{name}_published_ms_median": float(np.median(v)), f"{name}_published_ms_p95": float(np.percentile(v, 95))}


def format_latency(lat: dict) -> str:
    if "error" in lat:
        return f"latency: not measured ({lat['error']})"
    policy = "every scan updating" if lat["every_scan"] else "the file's update policy"
    return (f"latency (live node, {lat['particles']} particles, {lat['ray_caster']}, {policy}, "
            f"{lat['scan_hz']:g} Hz scans + {lat['odom_hz']:g} Hz odometry at real time for {lat['duration_s']:g} s, "
            f"sent at their {'header stamps' if lat.get('pace', 'stamps') == 'stamps' else 'recorded times'}): "
            f"scan stamp -> pose received here median {lat['latency_ms_median']:.1f} ms, "
            f"p95 {lat['latency_ms_p95']:.1f} ms, "
            f"max {lat['latency_ms_max']:.1f} ms (published by the node: median "
            f"{lat.get('latency_published_ms_median', math.nan):.1f} ms, p95 "
            f"{lat.get('latency_published_ms_p95', math.nan):.1f} ms); "
            f"{lat['poses_from_scans']} of {lat['scans_sent']} scans produced a "
            f"sensor update and a pose ({100 * lat['processed_fraction']:.1f} %; {lat['scans_skipped']} dropped or "
            "lost)")


def _pct(share) -> str:
    return "n/a" if share is None else f"{100 * share:.1f} %"


def format_result(r: dict) -> str:
    text = format_latency(r)
    if "error" not in r:
        text += (f"\n  first half median {r['latency_ms_median_first_half']:.1f} ms, second half "
                 f"{r['latency_ms_median_second_half']:.1f} ms (growing = queueing); odometry -> pose median "
                 f"{r['odom_latency_ms_median']:.1f} ms, p95 {r['odom_latency_ms_p95']:.1f} ms over "
                 f"{r['odom_poses']} messages (published by the node: p95 "
                 f"{r.get('odom_latency_published_ms_p95', math.nan):.1f} ms)"
                 f"\n  node peak RSS {r['node_peak_rss_mb']:.0f} MB; node CPU "
                 f"{_pct(r['node_cpu_share'])} of one core (CPU seconds per second of real-time stream; user "
                 f"{_pct(r.get('node_user_cpu_share'))}); ready "
                 f"{r['node_ready_s']:.1f} s after start; load average {r['load_average_start']:.1f} -> "
                 f"{r['load_average_end']:.1f}; extra parameters {r['extra_params'] or 'none'}"
                 f"\n  where the time went inside the node (scan received -> pose published; wait = queued for "
                 f"the sensor-update thread (0 unless sensor_update_thread), deserialize = CDR -> ScanData, "
                 f"convert = stamp kept + laser pose, "
                 f"update = waiting for the odometry that reaches the scan's time + sensor update + resampling, "
                 f"publish = the correction on /pf/pose):\n    {r.get('node_breakdown') or 'not reported'}")
    return text


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m localization.benchmarks.latency", description=__doc__.split("\n\n")[0])
    ap.add_argument("--particles", type=int, default=4000)
    ap.add_argument("--car", action="store_true",
                    help="the parameter file as the car runs it: its particle count and update policy (not every "
                         "scan updating); for the node's CPU share")
    ap.add_argument("--duration", type=float, default=20.0, help="seconds of stream (default 20)")
    ap.add_argument("--ray-caster", default=None, help="default: the parameter file's",
                    choices=["lookup_table", "lookup_table_exact", "distance_transform", "exact"])
    ap.add_argument("--params", type=Path, help="parameter file (default config/real_params.yaml)")
    ap.add_argument("-p", "--param", dest="extra", action="append", default=[], metavar="NAME:=VALUE",
                    help="extra node parameter (repeatable), e.g. -p max_particles_published:=0")
    ap.add_argument("--pace", choices=["stamps", "recorded"], default="stamps",
                    help="send each message at its header stamp, as its driver had it (default), or at the time the "
                         "bag's recorder received it (in bursts: two scans 0.2-0.5 ms apart, a third of the time)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    progress = None if args.json else (lambda msg: print(msg, file=sys.stderr, flush=True))
    r = measure_latency(None if args.car else args.particles, args.duration, args.ray_caster, args.params,
                        progress=progress, extra_params=args.extra, every_scan=not args.car, pace=args.pace)
    print(json.dumps(r) if args.json else format_result(r))
    return 1 if "error" in r else 0


if __name__ == "__main__":
    sys.exit(main())
