"""Standard-library logging (what the ROS-free core uses) forwarded to a node's ROS logger."""
from __future__ import annotations

import logging

import rclpy
from rclpy.node import Node


class _RclpyHandler(logging.Handler):
    """Forwards standard-library log records (the ROS-free core logs that way) to a ROS logger."""

    def __init__(self, ros_logger):
        super().__init__()
        self.ros_logger = ros_logger

    def emit(self, record: logging.LogRecord) -> None:
        try:
            message, level = self.format(record), record.levelno
            if level >= logging.ERROR:
                self.ros_logger.error(message)
            elif level >= logging.WARNING:
                self.ros_logger.warning(message)
            elif level >= logging.INFO:
                self.ros_logger.info(message)
            else:
                self.ros_logger.debug(message)
        except Exception:  # noqa: BLE001 - logging must never break a callback
            self.handleError(record)


def stdlib_logger(node: Node) -> logging.Logger:
    """A ``logging.Logger`` (own instance, not in the global registry) writing to the node's logger."""
    logger = logging.Logger(f"localization.{node.get_name()}")
    logger.addHandler(_RclpyHandler(node.get_logger()))
    logger.setLevel(logging.DEBUG if node.get_logger().is_enabled_for(rclpy.logging.LoggingSeverity.DEBUG)
                    else logging.INFO)
    return logger
