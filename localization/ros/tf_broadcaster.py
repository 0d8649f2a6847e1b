"""Broadcast TF transforms (e.g. map -> base_link_pf), with or without tf2_ros.

On a full ROS 2 install ``tf2_ros`` is importable and its ``TransformBroadcaster`` /
``StaticTransformBroadcaster`` do the work.

A virtual environment built from the ROS 2 PyPI wheels has no tf2_ros (nor tf2_msgs) wheel. There
the fallback publishes ``tf2_msgs/msg/TFMessage`` itself, with the QoS tf2_ros uses, so any TF
listener sees the same thing:

* dynamic: topic ``/tf``, reliable, volatile, keep last 100;
* static: topic ``/tf_static``, reliable, transient local, keep last 1.

For static transforms, each ``send`` (with either backend) re-publishes every static transform sent
so far, one per child frame, as C++ tf2_ros does (the Python one does not): the latched topic keeps
one message, which must carry the whole set for a late-joining listener.

The fallback needs the ``tf2_msgs`` Python message type, which ``scripts/build_tf2_msgs.sh``
builds from ``interfaces/tf2_msgs`` into the active venv (same definition and type hash as the
official Jazzy tf2_msgs). A publisher of any other type would not be matched by TF subscribers.
"""
from __future__ import annotations

from collections.abc import Iterable

from geometry_msgs.msg import TransformStamped
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

try:
    import tf2_ros
except ImportError:
    tf2_ros = None

TF_TOPIC = "/tf"
TF_STATIC_TOPIC = "/tf_static"
TF_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=100,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)
TF_STATIC_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)


def _tf_message_type():
    try:
        from tf2_msgs.msg import TFMessage
    except ImportError as exc:
        raise ImportError(
            "Neither tf2_ros nor tf2_msgs is importable, so TF cannot be published. On a ROS 2 "
            "install, source it (or install ros-jazzy-tf2-ros); in a pip virtual environment, "
            "run scripts/build_tf2_msgs.sh with the venv active to build tf2_msgs into it."
        ) from exc
    return TFMessage


class TransformBroadcaster:
    """Send ``TransformStamped`` messages on /tf (or /tf_static when ``static=True``)."""

    def __init__(self, node: Node, static: bool = False):
        self.node = node
        self.static = static
        self._tf2 = None
        self._publisher = None
        self._static_transforms: dict[str, TransformStamped] = {}
        if tf2_ros is not None:
            cls = tf2_ros.StaticTransformBroadcaster if static else tf2_ros.TransformBroadcaster
            self._tf2 = cls(node)
        else:
            self._msg_type = _tf_message_type()
            topic, qos = (TF_STATIC_TOPIC, TF_STATIC_QOS) if static else (TF_TOPIC, TF_QOS)
            self._publisher = node.create_publisher(self._msg_type, topic, qos)

    @property
    def backend(self) -> str:
        """``"tf2_ros"`` or ``"tf2_msgs"`` (the fallback publisher)."""
        return "tf2_ros" if self._tf2 is not None else "tf2_msgs"

    @property
    def publisher(self):
        """The rclpy ``Publisher`` of ``TFMessage`` (e.g. for ``get_subscription_count()``)."""
        return self._tf2.pub_tf if self._tf2 is not None else self._publisher

    def send(self, transforms: Iterable[TransformStamped]) -> None:
        transforms = list(transforms)
        if self.static:
            self._static_transforms.update((t.child_frame_id, t) for t in transforms)
            transforms = list(self._static_transforms.values())
        if self._tf2 is not None:
            self._tf2.sendTransform(transforms)
        else:
            self._publisher.publish(self._msg_type(transforms=transforms))

    def send_serialized(self, tf_message: bytes) -> None:
        """Publish a serialized tf2_msgs/TFMessage (``ros.cdr.tf_message_cdr``) on /tf as it is."""
        self.publisher.publish(tf_message)

    def destroy(self) -> None:
        """Destroy the underlying publisher (the node stays alive)."""
        if self.publisher is not None:
            self.node.destroy_publisher(self.publisher)
        self._tf2 = self._publisher = None
