"""The node's ROS parameters and QoS: every entry of the core's parameter table declared with its
description and rule, read-only (with the reason) unless it may change while the node runs
(``core.runtime_parameters``); validation errors collected into one message."""
from __future__ import annotations

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.exceptions import InvalidParameterTypeException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions

from localization.core.parameters import BY_NAME, PARAMETERS, ParameterError, Parameters, coerce_number
from localization.core.runtime_parameters import read_only_reason

MAP_QOS = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
ODOM_QOS = QoSProfile(depth=50, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)
# scan and odometry QoS can be changed with the standard parameters, e.g.
# qos_overrides./scan.subscription.reliability:=reliable
QOS_OVERRIDES = QoSOverridingOptions.with_default_policies()
# sensor-data QoS (best effort, depth 5: scans arriving during a sensor update wait here, 5 × 25 ms
# at 40 Hz; with sensor_update_thread the thread's short queue (scan_worker.py) bounds the wait).
# Depth 1 lost scans whenever the callback thread was briefly busy (docs/node.md).
SCAN_QOS = QoSProfile(depth=5, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.VOLATILE)
_TYPE_NAMES = {bool: "a boolean (true/false)", int: "an integer", float: "a float", str: "a string"}


def declare_parameters(node: Node) -> Parameters:
    """Declare every parameter of ``localization.parameters`` (read-only, with its description)
    and return the validated values; raises ParameterError with every problem found (a wrong type,
    a value against its rule, an unknown name)."""
    overrides = getattr(node, "_parameter_overrides", {}) or {}
    values, problems = {}, []
    for p in PARAMETERS:
        reason = read_only_reason(p.name)  # "" for a parameter that may change while the node runs
        text = f"{p.description} [{p.rule}]" if p.rule else p.description
        desc = ParameterDescriptor(description=text + (f" (read-only while the node runs: {reason})" if reason else
                                                       " (can change while the node runs)"),
                                   read_only=bool(reason))
        try:
            values[p.name] = node.declare_parameter(p.name, p.default, desc).value
        except InvalidParameterTypeException:
            given = overrides[p.name].value if p.name in overrides else None
            value = coerce_number(p.default, given)
            if value is not given and type(value) is type(p.default):  # 500.0 for an integer, 1 for a float
                values[p.name] = node.declare_parameter(p.name, value, desc, ignore_override=True).value
            else:
                problems.append(f"{p.name}={given!r} must be {_TYPE_NAMES[type(p.default)]}"
                                + (f" ({p.rule})" if p.rule else ""))
    unknown = sorted(n for n in overrides if n not in BY_NAME and n != "use_sim_time"
                     and not n.startswith("qos_overrides."))
    if unknown:  # a typo would otherwise leave the intended parameter at its default
        problems.append(f"unknown parameter{'s' if len(unknown) > 1 else ''} {', '.join(unknown)} "
                        f"(particle_filter --help lists them)")
    try:
        params = Parameters(values)
    except ParameterError as exc:
        problems.append(str(exc).removeprefix("invalid parameters: "))
    if problems:
        raise ParameterError("invalid parameters: " + "; ".join(problems))
    return params
