"""Helpers for the node tests: synthetic drive data, input message builders, a probe node that
feeds the particle_filter node and records its outputs, and a runner that spins both.

Nothing here runs at import time except cheap definitions; the synthetic data are generated
once per process (``synthetic_drive()``, cached).
"""
from __future__ import annotations

import array
import contextlib
import functools
import threading
import time
from dataclasses import dataclass, field

import numpy as np
import rclpy
from geometry_msgs.msg import PoseArray, PoseWithCovarianceStamped
from nav_msgs.msg import OccupancyGrid, Odometry
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import LaserScan
from std_srvs.srv import Empty
from tf2_msgs.msg import TFMessage

from localization.core.geometry import compose, yaw_to_quaternion
from localization.core.occupancy_map import OccupancyMap, load_map  # noqa: F401
from localization.ros.conversions import stamp_to_sec
from localization.ros.messages import occupancy_grid_msg  # noqa: F401 (re-exported for the tests)
from localization.ros.node import ParticleFilterNode

T0_NS = 1_700_000_000_123_456_789  # stamps carry nanoseconds: outputs must keep them exactly
MAP_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
NUM_BEAMS = 1081
ANGLE_MIN, ANGLE_MAX = -2.356194490192345, 2.356194490192345
ANGLE_INC = (ANGLE_MAX - ANGLE_MIN) / (NUM_BEAMS - 1)
LASER_OFFSET = 0.275
TEST_PARAMS = dict(num_particles=500, ray_caster="distance_transform", random_seed=1, max_particles_published=200)
# lock-step tests wait for every scan: a dropped best-effort sample would stall them
TEST_QOS = {"qos_overrides./scan.subscription.reliability": "reliable"}


def key(stamp) -> tuple[int, int]:
    return int(stamp.sec), int(stamp.nanosec)


def ns_key(t_ns: int) -> tuple[int, int]:
    return t_ns // 1_000_000_000, t_ns % 1_000_000_000


def set_stamp(header, t_ns: int) -> None:
    header.stamp.sec, header.stamp.nanosec = ns_key(t_ns)


# ---------------------------------------------------------------------------------- input messages
def scan_msg(t_ns: int, ranges, frame_id: str = "laser") -> LaserScan:
    msg = LaserScan()
    set_stamp(msg.header, t_ns)
    msg.header.frame_id = frame_id
    msg.angle_min, msg.angle_max, msg.angle_increment = ANGLE_MIN, ANGLE_MAX, ANGLE_INC
    msg.scan_time, msg.time_increment = 0.025, 0.0
    msg.range_min, msg.range_max = 0.02, 30.0
    msg.ranges = array.array("f", np.asarray(ranges, dtype=np.float32).tobytes())
    return msg


def odom_msg(t_ns: int, pose, vx: float, wz: float = 0.0) -> Odometry:
    msg = Odometry()
    set_stamp(msg.header, t_ns)
    msg.header.frame_id, msg.child_frame_id = "odom", "base_link"
    qx, qy, qz, qw = (float(v) for v in yaw_to_quaternion(pose[2]))
    msg.pose.pose.position.x, msg.pose.pose.position.y = float(pose[0]), float(pose[1])
    msg.pose.pose.orientation.z, msg.pose.pose.orientation.w = qz, qw
    msg.twist.twist.linear.x, msg.twist.twist.angular.z = float(vx), float(wz)
    return msg


def initialpose_msg(pose, t_ns: int = T0_NS, frame_id: str = "map", std=(0.3, 0.3, 0.1)) -> PoseWithCovarianceStamped:
    msg = PoseWithCovarianceStamped()
    set_stamp(msg.header, t_ns)
    msg.header.frame_id = frame_id
    qx, qy, qz, qw = (float(v) for v in yaw_to_quaternion(pose[2]))
    msg.pose.pose.position.x, msg.pose.pose.position.y = float(pose[0]), float(pose[1])
    msg.pose.pose.orientation.z, msg.pose.pose.orientation.w = qz, qw
    cov = np.zeros((6, 6))
    cov[0, 0], cov[1, 1], cov[5, 5] = std[0] ** 2, std[1] ** 2, std[2] ** 2
    msg.pose.covariance = [float(v) for v in cov.ravel()]
    return msg


@functools.lru_cache(maxsize=4)
@functools.lru_cache(maxsize=4)
def map_msg(name: str) -> OccupancyGrid:
    return occupancy_grid_msg(load_map(name))


# ---------------------------------------------------------------------------------- synthetic drive
@dataclass
class Drive:
    """A straight drive in the Stata basement corridor: exact ray-cast scans (+ noise) at 40 Hz,
    wheel odometry at 50 Hz that runs 5 % short (as on the real car)."""

    start: np.ndarray
    speed: float
    duration: float
    events: list = field(default_factory=list)  # (t_ns, "odom"|"scan", msg), in stamp order

    def truth(self, t_ns: int) -> np.ndarray:
        return compose(self.start, np.array([self.speed * (t_ns - T0_NS) * 1e-9, 0.0, 0.0]))

    def until(self, seconds: float) -> list:
        return [e for e in self.events if e[0] - T0_NS <= seconds * 1e9 + 1]

    @property
    def initial_guess(self) -> np.ndarray:
        return self.start + np.array([0.25, -0.2, 0.08])  # a clicked pose: a few decimetres off


@functools.lru_cache(maxsize=2)
def synthetic_drive(start=(-6.0, 20.0, -2.24), speed=2.0, duration=3.0, odom_scale=0.95, noise=0.02,
                    seed=0) -> Drive:
    from localization.core.raycast.exact import ExactRayCaster

    drive = Drive(np.array(start, dtype=float), speed, duration)
    rng = np.random.default_rng(seed)
    scan_ns = T0_NS + np.arange(0, int(duration * 40) + 1) * 25_000_000
    odom_ns = T0_NS + 3_000_000 + np.arange(0, int(duration * 50) + 1) * 20_000_000  # offset: distinct stamps
    laser = np.array([compose(drive.truth(t), [LASER_OFFSET, 0.0, 0.0]) for t in scan_ns])
    angles = ANGLE_MIN + np.arange(NUM_BEAMS) * ANGLE_INC
    ranges = ExactRayCaster(load_map("stata_basement"), 30.0).cast(laser, angles)
    ranges = ranges + rng.normal(0.0, noise, ranges.shape)
    for t, r in zip(scan_ns, ranges):
        drive.events.append((int(t), "scan", scan_msg(int(t), r)))
    v_odom = speed * odom_scale
    for t in odom_ns:
        dt = (t - T0_NS) * 1e-9
        drive.events.append((int(t), "odom", odom_msg(int(t), (v_odom * dt, 0.0, 0.0), v_odom)))
    drive.events.sort(key=lambda e: e[0])
    return drive


# ---------------------------------------------------------------------------------- probe node
class Probe(Node):
    """Publishes the node's inputs and records every output message (thread safe)."""

    def __init__(self, context, name="pf_test_probe"):
        super().__init__(name, context=context)
        self.map_pub = self.create_publisher(OccupancyGrid, "/map", MAP_QOS)
        self.initialpose_pub = self.create_publisher(PoseWithCovarianceStamped, "/initialpose", 10)
        self.scan_pub = self.create_publisher(LaserScan, "/scan", 100)
        self.odom_pub = self.create_publisher(Odometry, "/odom", 100)
        self.lock = threading.Lock()
        self.poses: list[Odometry] = []
        self.particles: list[PoseArray] = []
        self.tf: list = []  # TransformStamped
        self.corrections: list[PoseWithCovarianceStamped] = []  # /pf/pose: the sensor-corrected estimates
        self.subs = [
            self.create_subscription(Odometry, "/pf/pose/odom", self._keep(self.poses), 1000),
            self.create_subscription(PoseWithCovarianceStamped, "/pf/pose", self._keep(self.corrections), 1000),
            self.create_subscription(PoseArray, "/pf/particles", self._keep(self.particles), 1000),
            self.create_subscription(TFMessage, "/tf", lambda m: self._add(self.tf, *m.transforms), 1000),
        ]
        self.reinit_client = self.create_client(Empty, "/particle_filter/reinitialize_global_localization")

    def _keep(self, store):
        return lambda msg: self._add(store, msg)

    def _add(self, store, *msgs):
        with self.lock:
            store.extend(msgs)

    def snapshot(self):
        with self.lock:
            return list(self.poses), list(self.particles), list(self.tf)

    def corrections_snapshot(self) -> list:
        with self.lock:
            return list(self.corrections)

    def clear(self):
        with self.lock:
            self.poses.clear(), self.particles.clear(), self.tf.clear(), self.corrections.clear()

    def wait_connected(self, timeout=10.0, outputs=True):
        pubs = [self.map_pub, self.initialpose_pub, self.scan_pub, self.odom_pub]
        ok = wait_until(lambda: all(p.get_subscription_count() > 0 for p in pubs)
                        and (not outputs or all(s.get_publisher_count() > 0 for s in self.subs)), timeout)
        assert ok, "DDS discovery between the probe and the particle_filter node did not complete"


def wait_until(predicate, timeout=10.0, period=0.002) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(period)
    return bool(predicate())


# ---------------------------------------------------------------------------------- runner
class Runner:
    """A particle_filter node (in this process) + a probe, spun by a SingleThreadedExecutor (as in main()) in a
    background thread. ``step`` functions publish one input and wait until the node handled it."""

    def __init__(self, context, **overrides):
        values = dict(TEST_PARAMS)
        values.update(overrides)
        values.update(TEST_QOS)
        self.node = ParticleFilterNode(context=context,
                                       parameter_overrides=[Parameter(k, value=v) for k, v in values.items()])
        self.probe = Probe(context)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        self.executor.add_node(self.probe)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()
        try:
            self.probe.wait_connected(outputs=overrides.get("publish_tf", "x") != "none")
        except BaseException:
            self.close()
            raise

    def close(self):
        if self.executor is None:
            return
        self.executor.shutdown(timeout_sec=5.0)
        self.thread.join(timeout=5.0)
        assert not self.thread.is_alive(), "executor thread did not stop"
        self.probe.destroy_node()
        self.node.destroy_node()
        self.executor = None

    # ---- lock-step inputs
    def _publish_and_wait(self, pub, msg, count_key, timeout=10.0):
        before = self.node.counts[count_key]
        pub.publish(msg)
        assert wait_until(lambda: self.node.counts[count_key] > before, timeout), \
            f"the node did not handle the {count_key} message within {timeout} s"

    def send_map(self, msg):
        self._publish_and_wait(self.probe.map_pub, msg, "map", timeout=20.0)

    def send_initialpose(self, msg):
        self._publish_and_wait(self.probe.initialpose_pub, msg, "initialpose")

    def send_odom(self, msg):
        self._publish_and_wait(self.probe.odom_pub, msg, "odom")

    def send_scan(self, msg):
        self._publish_and_wait(self.probe.scan_pub, msg, "scan")

    def play(self, events):
        for _, kind, msg in events:
            (self.send_odom if kind == "odom" else self.send_scan)(msg)

    def settle(self, seconds=0.3):
        """Let outputs already published reach the probe."""
        time.sleep(seconds)


@contextlib.contextmanager
def lifecycle_running(context, probe_name: str):
    """A LifecycleParticleFilterNode (TEST_PARAMS) and a Probe spun by one executor thread; yields
    (node, probe) and shuts both down after."""
    from localization.ros.lifecycle_node import LifecycleParticleFilterNode
    values = dict(TEST_PARAMS, **TEST_QOS)
    node = LifecycleParticleFilterNode(context=context,
                                       parameter_overrides=[Parameter(k, value=v) for k, v in values.items()])
    probe = Probe(context, name=probe_name)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    executor.add_node(probe)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    try:
        yield node, probe
    finally:
        executor.shutdown(timeout_sec=5.0)
        spinner.join(timeout=5.0)
        probe.destroy_node()
        node.destroy_node()


def start_runner(context, **overrides) -> Runner:
    return Runner(context, **overrides)


def stamp_sec(stamp) -> float:
    return stamp_to_sec(stamp)


def init_context(domain_id: int | None = None):
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    return ctx
