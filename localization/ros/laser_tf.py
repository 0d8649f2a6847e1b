"""The laser pose in the robot frame, read from TF (``base_frame`` -> the scan's frame).

With ``tf2_ros`` (a full ROS 2 install) a ``Buffer`` + ``TransformListener`` do it. Without it
(the PyPI-wheel venv) ``/tf_static`` (reliable, transient local) and ``/tf`` are subscribed with the
``tf2_msgs/TFMessage`` type built into the venv (see ``tf_broadcaster``), and the chain
child -> parent -> ... -> ``base_frame`` is composed here, in the plane:

    T_base_laser = T_base_a ⊕ T_a_b ⊕ ... ⊕ T_n_laser,   each T = (x, y, yaw of the quaternion)

The laser of a car does not move on it, so the caller stops listening (``close``) once the pose is
found: the node does not keep deserialising its own /tf output.
"""
from __future__ import annotations

import threading

import numpy as np

from localization.core.geometry import compose, quaternion_to_yaw
from localization.ros.tf_broadcaster import TF_QOS, TF_STATIC_QOS, TF_STATIC_TOPIC, TF_TOPIC, tf2_ros

MAX_HOPS = 16


def planar_transform(transform) -> np.ndarray:
    """geometry_msgs/Transform -> (x, y, yaw)."""
    t, q = transform.translation, transform.rotation
    return np.array([float(t.x), float(t.y), float(quaternion_to_yaw(q.x, q.y, q.z, q.w))])


class LaserPoseLookup:
    """``lookup(parent, child)`` -> ((x, y, yaw) or None, why not)."""

    def __init__(self, node, ignore_children=()):
        self.node = node
        self.ignore_children = {c.lstrip("/") for c in ignore_children}  # e.g. the node's own TF output
        self._lock = threading.Lock()
        self._edges: dict[str, tuple[str, np.ndarray]] = {}  # child -> (parent, planar transform)
        self._subs = []
        self.buffer = self.listener = None
        if tf2_ros is not None:
            self.buffer = tf2_ros.Buffer()
            self.listener = tf2_ros.TransformListener(self.buffer, node)
        else:
            from localization.ros.tf_broadcaster import _tf_message_type
            msg_type = _tf_message_type()
            self._subs = [node.create_subscription(msg_type, TF_STATIC_TOPIC, self._on_tf, TF_STATIC_QOS),
                          node.create_subscription(msg_type, TF_TOPIC, self._on_tf, TF_QOS)]

    def _on_tf(self, msg) -> None:
        with self._lock:
            for t in msg.transforms:
                if t.child_frame_id.lstrip("/") in self.ignore_children:
                    continue
                self._edges[t.child_frame_id.lstrip("/")] = (t.header.frame_id.lstrip("/"),
                                                             planar_transform(t.transform))

    @property
    def has_data(self) -> bool:
        if self.buffer is not None:
            import re
            try:
                frames = re.findall(r"Frame (\S+) exists with parent (\S+)", self.buffer.all_frames_as_string())
            except Exception:  # noqa: BLE001
                return False
            return any(child not in self.ignore_children for child, _ in frames)
        with self._lock:
            return bool(self._edges)

    def lookup(self, parent: str, child: str):
        parent, child = parent.lstrip("/"), child.lstrip("/")
        if not child:
            return None, "the scan has no frame_id"
        if parent == child:
            return np.zeros(3), ""
        if self.buffer is not None:
            try:
                import rclpy.time
                t = self.buffer.lookup_transform(parent, child, rclpy.time.Time())
            except Exception as exc:  # noqa: BLE001 - tf2 raises several lookup exception types
                return None, f"{parent} -> {child}: {exc}"
            return planar_transform(t.transform), ""
        with self._lock:
            chain, frame = [], child
            for _ in range(MAX_HOPS):
                edge = self._edges.get(frame)
                if edge is None:
                    break
                chain.append(edge[1])
                frame = edge[0]
                if frame == parent:
                    pose = np.zeros(3)
                    for step in reversed(chain):
                        pose = compose(pose, step)
                    return pose, ""
            known = sorted(set(self._edges) | {p for p, _ in self._edges.values()})
        if not known:
            return None, f"{parent} -> {child}: no TF received on {TF_STATIC_TOPIC} or {TF_TOPIC}"
        return None, f"{parent} -> {child}: no chain of transforms (frames in TF: {', '.join(known[:12])})"

    def stop_dynamic(self) -> None:
        """Stop listening to /tf (keep /tf_static): fallback backend only."""
        if len(self._subs) == 2:
            self.node.destroy_subscription(self._subs.pop())

    def close(self) -> None:
        for sub in self._subs:
            self.node.destroy_subscription(sub)
        self._subs = []
        if self.listener is not None:
            try:
                self.listener.unregister()
            except Exception:  # noqa: BLE001
                pass
            self.listener = None


class LaserPoseSource:
    """Where the node's laser pose comes from: TF (``base_frame`` -> the scan's frame) when it is
    there; ``tf_timeout`` after the first scan without it, the ``laser_offset_*`` parameters. One
    log line says which; a TF arriving later still replaces the parameters (then /tf is no longer
    listened to). ``source``: None (not decided yet), "tf" or "parameters". ``resolve`` may run on the
    sensor-update thread; the subscriptions it ends are destroyed by ``tidy`` on the executor's thread
    (destroying one while the executor waits on it raises in the executor)."""

    def __init__(self, node, params, localizer, watchdog):
        self.node, self.params, self.localizer, self.watchdog = node, params, localizer, watchdog
        self.log = node.get_logger()
        self.source: str | None = None
        self.lookup: LaserPoseLookup | None = None
        self._deferred: list = []  # subscription changes for ``tidy`` (the executor's thread)

    def tidy(self) -> None:
        """The subscription changes ``resolve`` decided (call on the executor's thread)."""
        while self._deferred:
            self._deferred.pop(0)()

    def listen(self) -> None:
        """Start looking the pose up in TF (``laser_pose_from_tf``), unless TF gave it already."""
        p = self.params
        if not p.laser_pose_from_tf or self.source == "tf" or self.lookup is not None:
            return
        own = p.odom_frame if p.publish_tf == "map_to_odom" else p.particle_filter_frame  # the node's own TF
        try:
            self.lookup = LaserPoseLookup(self.node, ignore_children={own})
        except ImportError as exc:
            self.log.warning(f"laser pose: TF not available ({exc}); using laser_offset_* parameters")
            self.source = "parameters"

    def close(self) -> None:
        """Stop listening to TF (the node is deactivated)."""
        self.tidy()
        if self.lookup is not None:
            self.lookup.close()
            self.lookup = None

    @property
    def pending(self) -> bool:
        """Whether a scan should try to resolve the pose: not decided yet, or TF may still replace the parameters."""
        return self.source is None or (self.source == "parameters" and self.lookup is not None)

    def describe(self) -> str:
        """The /diagnostics value."""
        return {"tf": f"TF {self.params.base_frame} -> scan frame",
                "parameters": "laser_offset_* parameters"}.get(self.source, "not decided yet")

    def _use_parameters(self, why: str) -> None:
        p = self.params
        self.source = "parameters"
        self.log.info(f"laser pose from the parameters laser_offset_x/y/yaw ({p.laser_offset_x:.3f}, "
                      f"{p.laser_offset_y:.3f}, {p.laser_offset_yaw:.3f}){why}")

    def resolve(self, frame_id: str, now: float) -> None:
        """A scan in ``frame_id`` arrived at ``now`` (monotonic): decide, or keep waiting for TF."""
        p = self.params
        if self.lookup is None:
            if self.source is None:
                self._use_parameters(" (laser_pose_from_tf false)")
            return
        pose, why = self.lookup.lookup(p.base_frame, frame_id)
        if pose is not None:
            self.localizer.set_laser_offset(pose)
            self.source = "tf"
            self.watchdog.tf_ok()
            self.log.info(f"laser pose from TF {p.base_frame} -> {frame_id}: ({pose[0]:.3f}, {pose[1]:.3f}, "
                          f"{pose[2]:.3f})")
            lookup, self.lookup = self.lookup, None
            self._deferred.append(lookup.close)
            return
        first = self.watchdog.first_scan if self.watchdog.first_scan is not None else now
        if self.source is None and now - first >= p.tf_timeout:
            self._use_parameters(f": no TF {why}")
            self._deferred.append(self.lookup.stop_dynamic)  # a laser mount is static: only /tf_static from now on
            if self.lookup.has_data:  # TF is there but this lookup fails: a broken tree
                self.watchdog.tf_failed(now, f"{why}; using laser_offset_*")
