"""The odometry timeline: every odometry message on the scan clock, and the pose at any time.

One clock. A scan's time t_s is on the lidar's clock (the ROS clock the node runs on). An odometry
message stamped t_k describes the motion up to

    t'_k = t_k + odom_time_offset                      (the scan clock)

and this conversion happens here, once, when the message arrives (``add``); every time the
timeline returns or accepts is t' (the scan clock). The corrected twist u_k holds over
(t'_{k−1}, t'_k] (``odometry.OdometryBuffer``), so the robot's motion between two times is

    Δ(t_a, t_b) = ⊕_pieces integrate_twist(u, dt)       (robot frame at t_a; the inverse when t_b < t_a)

The timeline also keeps the *anchor*: the latest sensor-corrected estimate x̂ and the time t_a it
describes. The pose at any time t is the anchor carried through the odometry,

    x(t) = x̂ ⊕ Δ(t_a, t)                                (``pose_at``; backwards too)

which is what the node publishes on each odometry message (t = t'_k) and what replay scores at a
scan's time. Messages are checked here: non-finite or absurd values are ignored, and a stamp going
backwards or a gap longer than ``odom_max_gap`` starts a new history (the motion across the jump is
lost; one bad stamp between good ones is skipped).

Thread safety: every method holds the timeline's own short lock (``lock``, re-entrant), so odometry may
be added and the pose at its time read on one thread while a sensor update, on another, reads the
history at its scan's time and sets the anchor. Only ``add`` of a message that ``continues`` the
history is meant for that thread (a message that starts a new history waits for the localizer's
lock: the filter's times move with it).
"""
from __future__ import annotations

import functools
import logging
import math
import threading
from collections import deque
from dataclasses import dataclass

import numpy as np

from localization.core.geometry import compose
from localization.core.odometry import OdometryBuffer, TwistData


@dataclass(frozen=True)
class PoseEstimate:
    stamp: float  # s, scan clock: the time the pose describes
    pose: np.ndarray  # (3,) x, y, θ in the map frame
    covariance: np.ndarray  # (3, 3) over x, y, θ


@dataclass(frozen=True)
class OdometryLimits:
    """What an odometry message may say (the parameter table's names)."""

    time_offset: float = 0.0  # s: odom_time_offset
    speed_scale: float = 1.0  # odom_speed_scale
    yaw_rate_scale: float = 1.0  # odom_yaw_rate_scale
    yaw_rate_bias: float = 0.0  # rad/s: odom_yaw_rate_bias
    max_gap: float = 1.0  # s: odom_max_gap
    max_speed: float = 20.0  # m/s: odom_max_speed
    max_yaw_rate: float = 20.0  # rad/s: odom_max_yaw_rate
    extrapolation: float = 0.5  # s: scan_max_wait (how far a late scan may be carried past the odometry)
    keeps_sideways: bool = True  # False (a differential base): a reported sideways speed vy is taken as 0
    max_acceleration: float = 0.0  # m/s²: odom_max_acceleration (a faster speed change is slip; 0: none)

    @classmethod
    def from_parameters(cls, p) -> "OdometryLimits":
        from localization.core.models.motion import robot_model
        return cls(time_offset=p.odom_time_offset, speed_scale=p.odom_speed_scale,
                   yaw_rate_scale=p.odom_yaw_rate_scale, yaw_rate_bias=p.odom_yaw_rate_bias, max_gap=p.odom_max_gap,
                   max_speed=p.odom_max_speed, max_yaw_rate=p.odom_max_yaw_rate, extrapolation=p.scan_max_wait,
                   keeps_sideways=robot_model(p.robot_model_type).keeps_sideways,
                   max_acceleration=p.odom_max_acceleration)


@dataclass(frozen=True)
class OdometryVerdict:
    """What became of one odometry message."""

    accepted: bool
    time: float | None = None  # s, scan clock (t'), when accepted
    restart: float | None = None  # s, scan clock: a new history starts here (first message, or after a jump)
    problem: str = ""  # why it was not used ("" when accepted); key: a short name for throttled logs
    key: str = ""


def _locked(method):
    """``method`` under the timeline's lock (module docstring: thread safety)."""
    @functools.wraps(method)
    def locked(self, *args, **kwargs):
        with self.lock:
            return method(self, *args, **kwargs)
    return locked


class OdometryTimeline:
    def __init__(self, limits: OdometryLimits | None = None):
        self.lock = threading.RLock()  # short: held for one call (module docstring)
        self.limits = limits if limits is not None else OdometryLimits()
        lim = self.limits
        self._buffer = OdometryBuffer(lim.time_offset, lim.speed_scale, lim.yaw_rate_scale, lim.yaw_rate_bias,
                                      lim.extrapolation, lim.max_acceleration)
        self._last_stamp: float | None = None  # odometry clock: the newest accepted message's own stamp
        self._before_jump: float | None = None  # the stamp before a jump (was it one bad stamp?)
        self.anchor: PoseEstimate | None = None  # the latest corrected estimate (scan clock)
        self._said_sideways = False
        self._memo = None  # (anchor, t, pose at t): the newest carried pose

    # ------------------------------------------------------------------ odometry in
    @_locked
    def add(self, twist: TwistData) -> OdometryVerdict:
        """Check one message and add it (its time converted to the scan clock)."""
        lim, stamp = self.limits, twist.stamp
        if not all(math.isfinite(v) for v in (stamp, twist.vx, twist.vy, twist.wz)):
            return OdometryVerdict(False, problem=f"odometry with a non-finite value ignored (t={stamp}, "
                                   f"v=({twist.vx}, {twist.vy}), w={twist.wz})", key="odom-nan")
        if math.hypot(twist.vx, twist.vy) > lim.max_speed or abs(twist.wz) > lim.max_yaw_rate:
            return OdometryVerdict(False, problem=f"odometry with an absurd speed ignored (v=({twist.vx:.1f}, "
                                   f"{twist.vy:.1f}) m/s, w={twist.wz:.1f} rad/s; limits {lim.max_speed} m/s, "
                                   f"{lim.max_yaw_rate} rad/s)", key="odom-absurd")
        last, self._last_stamp = self._last_stamp, stamp
        before, self._before_jump = self._before_jump, None
        if last is not None:
            dt = stamp - last
            if not 0.0 < dt <= lim.max_gap and before is not None and 0.0 < stamp - before <= lim.max_gap:
                last, dt, before = before, stamp - before, None  # one message with a bad stamp: skip it
            if not 0.0 < dt <= lim.max_gap:
                self._before_jump = last
                return OdometryVerdict(False, problem=f"odometry stamp jumped by {dt:+.3f} s (bag loop or sensor "
                                       "restart): motion reference reset", key="odom-jump")
        new_history = last is None or before is not None  # the first message, or the clock jumped at `last`
        restart = None
        if new_history:
            carried = None if self.empty or self.anchor is None else self.pose_at(self.latest)
            self._buffer.reset()
            if last is not None:
                restart = self._buffer.add(TwistData(last, 0.0, 0.0, 0.0), boundary=True)
            if carried is not None:  # the pose before the jump holds at the new history's start
                self.anchor = PoseEstimate(stamp=restart, pose=carried.pose, covariance=carried.covariance)
        if not lim.keeps_sideways and twist.vy != 0.0:  # a differential base cannot move sideways
            if not self._said_sideways and abs(twist.vy) > 1e-3:
                logging.getLogger("localization.motion").warning(
                    "robot_model_type differential: the odometry reports sideways motion (vy %.3g m/s); a "
                    "differential base cannot move sideways: vy is ignored (forced to 0)", twist.vy)
                self._said_sideways = True
            twist = TwistData(twist.stamp, twist.vx, 0.0, twist.wz, twist.frame_id)
        t = self._buffer.add(twist)
        return OdometryVerdict(True, time=t, restart=(t if restart is None else restart) if new_history else None)

    @_locked
    def continues(self, twist: TwistData) -> bool:
        """Whether ``add`` would take this message as the next of the current history (finite, within the
        limits, newer than the newest by at most ``max_gap``, no jump pending): it then only appends."""
        lim, last = self.limits, self._last_stamp
        return (last is not None and self._before_jump is None and not self.empty
                and all(math.isfinite(v) for v in (twist.stamp, twist.vx, twist.vy, twist.wz))
                and math.hypot(twist.vx, twist.vy) <= lim.max_speed and abs(twist.wz) <= lim.max_yaw_rate
                and 0.0 < twist.stamp - last <= lim.max_gap)

    # ------------------------------------------------------------------ queries (scan clock)
    @property
    def latest(self) -> float | None:
        """t' of the newest message (None before any)."""
        return self._buffer.latest

    @property
    def empty(self) -> bool:
        return len(self._buffer) == 0

    @_locked
    def usable(self, t: float | None) -> float | None:
        """t if the history can move a pose from it; after a clock jump (t far outside the history)
        the history's start: the motion across the jump is lost."""
        oldest, latest, gap = self._buffer.oldest, self._buffer.latest, self.limits.max_gap
        if oldest is None:
            return t
        if t is None or not math.isfinite(t) or t < oldest - gap or t > latest + gap:
            return oldest
        return t

    @_locked
    def segments(self, t0: float, t1: float):
        """Constant-twist pieces (durations (P,), twists (P, 3)) covering [t0, t1]."""
        return self._buffer.segments(t0, t1)

    @_locked
    def slip_segments(self, t0: float, t1: float):
        """``segments`` and each piece's slip (P, 2): mean (m) and variance (m²) (``odometry.OdometryBuffer``)."""
        return self._buffer.slip_segments(t0, t1)

    @_locked
    def motion(self, t0: float, t1: float) -> np.ndarray:
        return self._buffer.motion(t0, t1)

    @_locked
    def travel(self, t0: float, t1: float) -> tuple[float, float]:
        return self._buffer.travel(t0, t1)

    @_locked
    def twist_at(self, t: float) -> np.ndarray:
        return self._buffer.twist_at(t)

    # ------------------------------------------------------------------ the anchor and poses at a time
    @_locked
    def set_anchor(self, estimate: PoseEstimate | None) -> None:
        self.anchor = estimate
        self.trim()

    @_locked
    def rebase_anchor(self) -> None:
        """An anchor older than half ``max_gap`` moves to the newest odometry (the same pose, carried):
        the history it needs stays short however long no scan corrects it."""
        a, latest = self.anchor, self.latest
        if a is not None and latest is not None and not latest - 0.5 * self.limits.max_gap <= a.stamp <= (
                latest + self.limits.max_gap):  # old, or on another clock (a pose stamped by the wall clock)
            self.set_anchor(self.pose_at(latest))

    @_locked
    def pose_at(self, t: float) -> PoseEstimate | None:
        """The anchor carried through the odometry to time t (scan clock), backwards too."""
        a = self.anchor
        if a is None or not math.isfinite(t):
            return a
        t_from = self.usable(a.stamp)
        if t_from is None:
            return a
        start, base = t_from, a.pose
        memo = self._memo  # the last pose carried forward from this anchor: go on from it, not from the anchor
        if memo is not None and memo[0] is a and t_from <= memo[1] <= t:
            start, base = memo[1], memo[2]
        pose = compose(base, self.motion(start, t))
        if t >= start:
            self._memo = (a, t, pose)
        return PoseEstimate(stamp=t, pose=pose, covariance=a.covariance)

    @_locked
    def trim(self, keep_from: float | None = None) -> None:
        """Forget odometry no longer needed (older than the anchor and ``keep_from``, minus a gap)."""
        keep = [t for t in (keep_from, None if self.anchor is None else self.anchor.stamp, self.latest)
                if t is not None and math.isfinite(t) and self.usable(t) == t]  # times on this history's clock
        if keep:
            self._buffer.trim(min(keep) - self.limits.max_gap)


class Outbox:
    """Items (sensor-corrected estimates, update costs) waiting to be taken, oldest first; its own lock,
    so the node takes them without waiting for a running sensor update. It keeps the newest ``size``:
    what nobody takes does not pile up over a long run."""

    def __init__(self, size: int = 1000):
        self._lock = threading.Lock()
        self._items: deque = deque(maxlen=size)

    def put(self, item):
        with self._lock:
            self._items.append(item)
        return item

    def take(self) -> list:
        with self._lock:
            out = list(self._items)
            self._items.clear()
        return out
