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
