"""The course's way of reading a parameter from a node (``SensorModel(node)``, ``MotionModel(node)``):
declare it when the node has not, then read it. Declared with dynamic typing, since the course's
files write numbers either way (``scan_theta_discretization: 500.0``); the caller converts."""
from __future__ import annotations

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node


def course_parameter(node: Node, name: str, default):
    """The value of ``name`` on ``node`` (its parameter files' value, else ``default``)."""
    if not node.has_parameter(name):
        node.declare_parameter(name, default, ParameterDescriptor(dynamic_typing=True))
    value = node.get_parameter(name).value
    return default if value is None else value
