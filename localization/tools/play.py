"""``localization-play``: republish a recorded bag with rclpy (a small ``ros2 bag play``).

Usage::

    localization-play BAG [--rate R] [--topics T [T ...]] [--start-delay S] [--loop] [--clock]
    localization-play [BAG] --map NAME_OR_YAML [--initial-pose X,Y,YAW] [--wait-ready S]

``--map`` publishes a map (a name of the package's maps/, e.g. ``basement_fixed``, or a
map_server YAML) on ``/map`` latched (reliable, transient local, as nav2's map_server), before the
bag; without a bag the map stays available until Ctrl-C. ``--initial-pose X,Y,YAW`` publishes one
``geometry_msgs/PoseWithCovarianceStamped`` on ``/initialpose`` (map frame, std 0.3 m / 0.1 rad)
once a subscriber is there, before the bag. With a bag and ``--initial-pose`` the bag waits (at
most ``--wait-ready`` seconds, default 60) until the localizer is ready to use it: a particle
cloud on ``/pf/particles`` or a ``/diagnostics`` status whose ``state`` is ``localizing`` (a node
started cold builds its range table first; scans played meanwhile could not be used). No
``ros2`` CLI needed.

``BAG`` is a ROS 1 ``.bag``, a rosbag2 directory, or a ``.db3`` / ``.mcap`` file (read with
``localization.bag_io``; no ``ros2 bag`` needed). Every topic (or only those given with
``--topics``) is published at its bag time divided by ``--rate`` (1.0 = real time; 2.0 = twice
as fast), timed against a monotonic clock. Messages go out as their ROS 2 CDR bytes
(``publisher.publish(bytes)``), so nothing is deserialized; ROS 1 messages are converted to CDR
on the fly.

QoS: ``/tf_static`` (and any topic the bag marks as latched) is published reliable +
transient local (keep all of its messages), so late subscribers still get it. Every other topic
is published reliable, volatile, keep last 100: a reliable publisher matches both reliable and
best-effort subscribers (e.g. nodes that subscribe to ``/scan`` with sensor-data QoS).

A topic whose message package cannot be imported in this Python (e.g. ``tf2_msgs`` when only
``common_interfaces`` is installed), or whose first message does not deserialize as that ROS 2
type, is skipped with a warning line on stderr.

``--start-delay`` (default 1 s) gives DDS discovery time to match subscribers before the first
message; ``--end-delay`` (default 0.5 s) keeps the node alive after the last one so reliable
messages are delivered. ``--clock`` also publishes ``/clock`` (rosgraph_msgs/Clock) with the bag
time of each message, for nodes running with ``use_sim_time``. ``--loop`` replays until
interrupted. At the end one summary line (messages per topic) is printed to stdout.

Exit codes: 0 success (also after Ctrl-C), 1 bag missing/unreadable or nothing to publish,
2 bad arguments (argparse) or topics not in the bag. ROS arguments (``--ros-args ...``) are
passed to rclpy.
"""
from __future__ import annotations

import argparse
import importlib
import signal
import sys
import threading
import time
from collections.abc import Sequence

from localization.bags import BagError, open_bag
from localization.bags.writer import LATCHED_TOPICS
from localization.core.paths import split_ros_args
from localization.tools.args import Parser, map_name_or_yaml, non_negative_float, pose, positive_float

PROG = "localization-play"
INITIAL_POSE_COVARIANCE = ((0.3 ** 2, 0.0, 0.0), (0.0, 0.3 ** 2, 0.0), (0.0, 0.0, 0.1 ** 2))  # m², m², rad²
DEFAULT_DEPTH = 100


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog=PROG, description="Republish a ROS 1 or ROS 2 bag with rclpy at bag time / rate.")
    p.add_argument("bag", nargs="?", help="ROS 1 .bag file, rosbag2 directory, or .db3/.mcap file")
    p.add_argument("--map", type=map_name_or_yaml, metavar="NAME_OR_YAML",
                   help="publish this map on /map, latched (a map name such as basement_fixed, or a YAML)")
    p.add_argument("--initial-pose", type=pose, metavar="X,Y,YAW",
                   help="publish one initial pose on /initialpose (map frame)")
    p.add_argument("--rate", type=positive_float, default=1.0, help="playback speed factor (1.0 = real time)")
    p.add_argument("--topics", nargs="+", metavar="T", help="publish only these topics (default: all)")
    p.add_argument("--start-delay", type=non_negative_float, default=1.0, metavar="S",
                   help="seconds to wait for discovery before the first message (default 1.0)")
    p.add_argument("--end-delay", type=non_negative_float, default=0.5, metavar="S",
                   help="seconds to stay alive after the last message (default 0.5)")
    p.add_argument("--wait-ready", type=non_negative_float, default=60.0, metavar="S",
                   help="with a bag and --initial-pose: wait up to S seconds for the localizer to be ready "
                        "(/pf/particles, or /diagnostics state 'localizing') before the bag (default 60; 0: no wait)")
    p.add_argument("--loop", action="store_true", help="replay the bag until interrupted")
    p.add_argument("--clock", action="store_true", help="also publish /clock with the bag time")
    return p


def message_class(msgtype: str):
    """The rclpy message class for ``'pkg/msg/Name'`` (or ``'pkg/Name'``), or raise ImportError."""
    parts = msgtype.split("/")
    if len(parts) == 3:
        pkg, kind, name = parts
    elif len(parts) == 2:
        (pkg, name), kind = parts, "msg"
    else:
        raise ImportError(f"malformed message type {msgtype!r}")
    try:
        module = importlib.import_module(f"{pkg}.{kind}")
    except ImportError as exc:
        raise ImportError(f"Python package '{pkg}' not importable ({exc})") from None
    cls = getattr(module, name, None)
    if cls is None or not hasattr(cls, "_TYPE_SUPPORT"):
        raise ImportError(f"'{pkg}.{kind}' has no message {name}")
    return cls


def _warn(text: str) -> None:
    print(f"{PROG}: warning: {text}", file=sys.stderr, flush=True)


def _error(text: str) -> None:
    print(f"{PROG}: error: {text}", file=sys.stderr, flush=True)


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    own, ros_args = split_ros_args(argv)
    parser = build_parser()
    args = parser.parse_args(own)
    if args.bag is None and args.map is None and args.initial_pose is None:
        parser.error("give a BAG, --map or --initial-pose")
    if args.map is not None:
        from localization.core.occupancy_map import MapError
        from localization.tools.args import load_map
        try:
            args.map_msg = load_map(args.map)
        except MapError as exc:
            _error(str(exc))
            return 1
    if args.bag is None:
        return _play(None, {}, {}, args, ros_args)

    try:
        bag = open_bag(args.bag)
    except BagError as exc:
        _error(str(exc))
        return 1

    with bag:
        infos = bag.topic_infos
        if args.topics:
            unknown = [t for t in args.topics if t not in infos]
            if unknown:
                _error(f"topic(s) not in {bag.path}: {', '.join(unknown)} (bag has: {', '.join(infos) or 'none'})")
                return 2
            selected = list(dict.fromkeys(args.topics))
        else:
            selected = list(infos)

        classes = {}
        for topic in selected:
            try:
                classes[topic] = message_class(infos[topic].msgtype)
            except ImportError as exc:
                _warn(f"skipping {topic} [{infos[topic].msgtype}]: {exc}")
        if not classes:
            _error(f"nothing to publish from {bag.path}")
            return 1
        return _play(bag, infos, classes, args, ros_args)


def _play(bag, infos, classes, args, ros_args) -> int:
    import rclpy
    from rclpy.context import Context
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.serialization import deserialize_message
    from rclpy.signals import SignalHandlerOptions

    stop = threading.Event()

    def on_signal(signum, frame):  # noqa: ARG001
        stop.set()

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    context = Context()
    rclpy.init(args=[PROG, *ros_args] if ros_args else None, context=context,
               signal_handler_options=SignalHandlerOptions.NO)
    node = None
    counts = {t: 0 for t in classes}
    skipped: set[str] = set()
    wall_start = time.monotonic()
    try:
        node = rclpy.create_node("localization_play", context=context, start_parameter_services=False)
        publishers = {}
        for topic, cls in classes.items():
            latched = topic in LATCHED_TOPICS or infos[topic].latched
            if latched:
                qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=max(1, infos[topic].count),
                                 reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
            else:
                qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=DEFAULT_DEPTH,
                                 reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
            publishers[topic] = node.create_publisher(cls, topic, qos)
        clock_pub = clock_cls = None
        if args.clock:
            try:
                clock_cls = message_class("rosgraph_msgs/msg/Clock")
                clock_pub = node.create_publisher(clock_cls, "/clock", QoSProfile(depth=10))
            except ImportError as exc:
                _warn(f"no /clock: {exc}")

        ready = _Readiness(node, context) if bag is not None and args.initial_pose is not None \
            and args.wait_ready > 0 else None
        _publish_map_and_pose(node, args, stop)
        if ready is not None:
            _wait_ready(ready, args.wait_ready, stop)
        if bag is None:
            if args.map is not None:
                print(f"{PROG}: publishing {args.map} on /map (latched) until Ctrl-C", flush=True)
                stop.wait()
            raise KeyboardInterrupt
        if stop.wait(args.start_delay):
            raise KeyboardInterrupt
        checked: set[str] = set()
        topics = list(classes)
        while True:
            t0 = None
            start = time.monotonic()
            for m in bag.messages(topics):
                if m.topic in skipped:
                    continue
                if t0 is None:
                    t0 = m.t_ns
                delay = start + (m.t_ns - t0) * 1e-9 / args.rate - time.monotonic()
                if delay > 0 and stop.wait(delay):
                    raise KeyboardInterrupt
                if stop.is_set():
                    raise KeyboardInterrupt
                raw = m.raw_cdr
                if m.topic not in checked:
                    checked.add(m.topic)
                    try:
                        deserialize_message(raw, classes[m.topic])
                    except Exception as exc:  # noqa: BLE001 - any failure means "incompatible"
                        _warn(f"skipping {m.topic} [{m.msgtype}]: bag data does not match the ROS 2 type ({exc})")
                        skipped.add(m.topic)
                        node.destroy_publisher(publishers.pop(m.topic))
                        continue
                if clock_pub is not None:
                    clock = clock_cls()
                    clock.clock.sec, clock.clock.nanosec = divmod(m.t_ns, 1_000_000_000)
                    clock_pub.publish(clock)
                publishers[m.topic].publish(raw)
                counts[m.topic] += 1
            if not args.loop or not publishers:
                break
        if args.end_delay and not stop.is_set():
            stop.wait(args.end_delay)
    except KeyboardInterrupt:
        pass
    except BagError as exc:
        _error(str(exc))
        return 1
    finally:
        if node is not None:
            node.destroy_node()
        try:
            rclpy.shutdown(context=context)
        except Exception:  # noqa: BLE001 - already shut down
            pass
        for s, handler in previous.items():
            signal.signal(s, handler)

    elapsed = time.monotonic() - wall_start
    parts = [f"{counts[t]} {t}" for t in counts if t not in skipped]
    note = f"; skipped {', '.join(sorted(skipped))}" if skipped else ""
    interrupted = " (interrupted)" if stop.is_set() else ""
    if bag is not None:
        print(f"{PROG}: published {sum(counts.values())} messages ({', '.join(parts)}) from {bag.path.name} "
              f"in {elapsed:.2f} s at rate {args.rate:g}{interrupted}{note}", flush=True)
    return 0


class _Readiness:
    """Subscriptions that tell when a localizer is ready: a particle cloud, or 'localizing' on /diagnostics."""

    def __init__(self, node, context):
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseArray
        from rclpy.executors import SingleThreadedExecutor
        self.event = threading.Event()
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(node)
        self.subs = [node.create_subscription(PoseArray, "/pf/particles", lambda _: self.event.set(), 5, raw=True),
                     node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, 10)]
        self.node = node

    def _on_diagnostics(self, msg) -> None:
        if any(kv.key == "state" and kv.value == "localizing" for st in msg.status for kv in st.values):
            self.event.set()

    def close(self) -> None:
        for sub in self.subs:
            self.node.destroy_subscription(sub)
        self.executor.remove_node(self.node)
        self.executor.shutdown(timeout_sec=1.0)


def _wait_ready(ready: _Readiness, timeout: float, stop) -> None:
    """Spin until the localizer is ready (or ``timeout`` s, or Ctrl-C); one line saying which."""
    t0 = time.monotonic()
    print(f"{PROG}: waiting up to {timeout:g} s for the localizer to be ready (/pf/particles or /diagnostics "
          "'localizing'; --wait-ready 0: no wait)", flush=True)
    try:
        while not ready.event.is_set() and not stop.is_set() and time.monotonic() - t0 < timeout:
            ready.executor.spin_once(timeout_sec=0.1)
    finally:
        ready.close()
    if ready.event.is_set():
        print(f"{PROG}: the localizer is ready after {time.monotonic() - t0:.1f} s: playing the bag", flush=True)
    elif not stop.is_set():
        _warn(f"the localizer was not ready after {timeout:g} s: playing the bag anyway")


def _publish_map_and_pose(node, args, stop) -> None:
    """``--map`` (latched, kept by the publisher while the node lives) and ``--initial-pose`` (once a
    subscriber is matched, at most ``max(start_delay, 5 s)`` waiting)."""
    if getattr(args, "map_msg", None) is not None:
        from nav_msgs.msg import OccupancyGrid

        from localization.ros.messages import occupancy_grid_msg
        from localization.ros.parameters import MAP_QOS
        args.map_pub = node.create_publisher(OccupancyGrid, "/map", MAP_QOS)
        args.map_pub.publish(occupancy_grid_msg(args.map_msg, time.time(), "map"))
    if args.initial_pose is not None:
        from geometry_msgs.msg import PoseWithCovarianceStamped

        from localization.ros.messages import pose_with_covariance_msg
        pub = node.create_publisher(PoseWithCovarianceStamped, "/initialpose", 10)
        deadline = time.monotonic() + max(args.start_delay, 5.0)
        while pub.get_subscription_count() == 0 and time.monotonic() < deadline and not stop.is_set():
            stop.wait(0.05)
        x, y, yaw = args.initial_pose
        pub.publish(pose_with_covariance_msg((x, y, yaw), INITIAL_POSE_COVARIANCE, time.time(), "map"))
        matched = pub.get_subscription_count()
        print(f"{PROG}: initial pose ({x:.2f}, {y:.2f}, {yaw:.2f}) published on /initialpose "
              f"({matched} subscriber{'s' if matched != 1 else ''})", flush=True)


if __name__ == "__main__":
    sys.exit(main())
