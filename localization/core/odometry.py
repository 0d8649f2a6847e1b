"""Odometry in the core: the twist a wheel-odometry message reports, at its stamp."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass
class TwistData:
    """nav_msgs/Odometry's twist (robot frame) and stamp, in float seconds."""

    stamp: float  # s
    vx: float  # m/s
    vy: float  # m/s
    wz: float  # rad/s
    frame_id: str = ""
