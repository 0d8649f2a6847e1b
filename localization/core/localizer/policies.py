"""Small named policies of the localizer: when a scan updates the filter, and which scans wait.

``UpdatePolicy`` — a scan updates the filter (sensor update + resampling) when one of its
triggers fires, checked in this order (the first one that fires is the reason given):

    forced    the first scan after an initialisation, or a requested no-motion update
    moved     path length since the last update  s ≥ update_min_distance   (m)
    turned    rotation since the last update     φ ≥ update_min_angle      (rad)
    stopped   the robot has come to a stop (|v| < STANDING_SPEED and |ω| < STANDING_YAW_RATE at the
              scan's time) after moving: one more update where it stands, then none until it moves
    every_n   update_every_n_scans > 0 and that many scans went by without an update

A standing robot's scans otherwise do not update the filter: repeated updates on the same scene
would collapse the cloud onto whatever that one view favours (as nav2_amcl's update_min_d/a).

``ScanQueue`` — a scan newer than the newest odometry waits for the odometry that covers its time,
as a TF message filter waits for a transform: a bounded FIFO (``scan_queue_size``) of scans, each
released when odometry reaches its time t_s, or after it waited ``scan_max_wait`` seconds on the
scan clock (a newer scan or odometry ``scan_max_wait`` past t_s arrived) or was pushed out of a full
queue — then it is used with the last twist extrapolated, and marked late so the caller says so.
Without any odometry (none received yet) scans do not wait.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

STANDING_SPEED = 0.05  # m/s: below this speed and STANDING_YAW_RATE the robot stands
STANDING_YAW_RATE = 0.05  # rad/s


@dataclass(frozen=True)
class UpdatePolicyParams:
    min_distance: float = 0.005  # m: update_min_distance
    min_angle: float = 0.005  # rad: update_min_angle
    every_n_scans: int = 0  # update_every_n_scans (0: off)

    @classmethod
    def from_parameters(cls, p) -> "UpdatePolicyParams":
        return cls(min_distance=p.update_min_distance, min_angle=p.update_min_angle,
                   every_n_scans=p.update_every_n_scans)


class UpdatePolicy:
    def __init__(self, params: UpdatePolicyParams | None = None):
        self.params = params if params is not None else UpdatePolicyParams()
        self._forced = False
        self._stop_updated = False  # an update happened since the robot stopped
        self._scans_without_update = 0

    def force(self) -> None:
        """The next scan updates the filter (after an initialisation, or on request)."""
        self._forced = True

    def reason(self, distance: float, angle: float, speed: float, yaw_rate: float) -> str | None:
        """Why this scan updates the filter (None: it does not). ``distance``/``angle``: travel since the
        last update; ``speed``/``yaw_rate``: the odometry twist at the scan's time."""
        p = self.params
        standing = abs(speed) < STANDING_SPEED and abs(yaw_rate) < STANDING_YAW_RATE
        self._stop_updated = self._stop_updated and standing
        self._scans_without_update += 1
        if self._forced:
            return "forced"
        if distance >= p.min_distance:
            return "moved"
        if angle >= p.min_angle:
            return "turned"
        if standing and not self._stop_updated and (distance > 0 or angle > 0):
            return "stopped"
        if p.every_n_scans > 0 and self._scans_without_update >= p.every_n_scans:
            return "every_n"
        return None

    def updated(self, speed: float, yaw_rate: float) -> None:
        """A sensor update was made with the robot moving at (speed, yaw_rate)."""
        self._forced = False
        self._stop_updated = abs(speed) < STANDING_SPEED and abs(yaw_rate) < STANDING_YAW_RATE
        self._scans_without_update = 0


@dataclass(frozen=True)
class Released:
    """A scan leaving the queue: its time on the scan clock, the scan, and whether it waited in vain."""

    time: float  # s, scan clock
    scan: object
    late: bool  # released before odometry reached its time (extrapolated)
    waited: float  # s on the scan clock between its time and the newest input when released

    def warning(self, max_wait: float) -> str:
        return (f"no odometry reached a scan's time after {self.waited:.2f} s (scan_max_wait {max_wait} s): the last "
                "twist is extrapolated. Odometry is late or stopped: check odom_time_offset, or raise scan_max_wait")


class ScanQueue:
    def __init__(self, max_wait: float = 0.5, size: int = 20):
        self.max_wait = float(max_wait)  # s, scan clock
        self.size = int(size)
        self._items: deque[tuple[float, object]] = deque()
        self._newest = -math.inf  # s: the newest time seen (scans and odometry)

    def __len__(self) -> int:
        return len(self._items)

    def clear(self) -> None:
        self._items.clear()

    def push(self, t: float, scan) -> None:
        self._items.append((float(t), scan))
        self._newest = max(self._newest, float(t))

    def due(self, odometry_until: float) -> bool:
        """Whether the oldest waiting scan may be used now, odometry known up to ``odometry_until``."""
        try:
            t = self._items[0][0]  # another thread may take it meanwhile
        except IndexError:
            return False
        expired = max(self._newest, odometry_until) - t > self.max_wait or len(self._items) > self.size
        return t <= odometry_until or expired

    def release(self, odometry_until: float | None) -> list[Released]:
        """The scans that may be used now, oldest first, given odometry known up to ``odometry_until``
        (scan clock; None: no odometry at all, nothing to wait for)."""
        if odometry_until is not None:
            self._newest = max(self._newest, odometry_until)
        out = []
        while self._items:
            t, scan = self._items[0]
            covered = odometry_until is None or t <= odometry_until
            expired = self._newest - t > self.max_wait or len(self._items) > self.size
            if not (covered or expired):
                break
            self._items.popleft()
            out.append(Released(time=t, scan=scan, late=not covered, waited=self._newest - t))
        return out
