"""Odometry in the core: the twist a wheel-odometry message reports, at its stamp, and a short
history of them on the scan's clock (``OdometryBuffer``).

A wheel-odometry message k stamped t_k reports the twist of the period since the previous one;
corrected by the car's calibration (the localizer's parameters)::

    t'_k  = t_k + odom_time_offset                   (its period ends at t'_k on the scan clock)
    vx'   = odom_speed_scale · vx,   vy' = odom_speed_scale · vy
    ωz'   = odom_yaw_rate_scale · ωz + odom_yaw_rate_bias

The corrected twist is constant over (t'_{k−1}, t'_k]. Past the newest message the last twist is
extrapolated for at most ``extrapolation`` seconds (then the robot is taken as standing: odometry
that stopped does not drive the particles on). The oldest message's period has no known start:
its twist holds for the same ``extrapolation`` before its stamp (a recording, or a node, that starts
while the robot drives), and before that nothing is known (no motion). The localizer only
extrapolates a scan that waited ``scan_max_wait`` for odometry in vain, and says so.
The motion between any two times is the composition of the constant-twist arcs
(``geometry.integrate_twist``) of the pieces between them (``segments``, ``motion``); ``twist_at``
is the twist holding at a time (the deskew of a sweep uses it).

Slip and skid. Wheels that lock under braking report a stop while the robot slides on; wheels that
spin report speed the robot does not have. Neither can follow a speed change faster than the tyres'
grip allows (``max_acceleration`` a, about μ·g; 0: off). The buffer follows the speed a grip-limited
robot could have::

    v*_k = clip(vx'_k, v*_{k−1} − a·Δt_k, v*_{k−1} + a·Δt_k),      slip_k = v*_k − vx'_k   [m/s]

Over a slip episode (consecutive periods with slip ≠ 0) the robot may have gone up to
D = ∫ slip dt farther forward (a skid; backward: wheel spin) than the odometry says; how much of it
is unknown (the tyres' real grip), one unknown for the whole episode. ``slip_segments`` gives each
piece its share: a mean of half its slip distance and a variance of ¼·(A_end² − A_start²), with
A = ∫ |slip| dt since the episode began, so that however the episode is cut into pieces the robot
is taken to have gone D/2 ± |D|/2 farther at its end (independent per-piece noise would shrink the
spread as the pieces get finer).
"""
from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

import numpy as np

from localization.core.geometry import compose_floats, integrate_twist_floats, inverse

try:  # the pieces cut in one compiled pass when numba is there (pinned); the numpy reference otherwise
    from numba import njit
except ImportError:  # pragma: no cover
    njit = None


@dataclass
class TwistData:
    """nav_msgs/Odometry's twist (robot frame) and stamp, in float seconds."""

    stamp: float  # s
    vx: float  # m/s
    vy: float  # m/s
    wz: float  # rad/s
    frame_id: str = ""


class OdometryBuffer:
    """The recent odometry messages, corrected and on the scan clock (see the module docstring).

    ``add`` expects stamps increasing (the localizer rejects the others first); ``trim`` drops
    what is no longer needed. Not thread safe by itself: the localizer guards it with a lock."""

    def __init__(self, time_offset: float = 0.0, speed_scale: float = 1.0, yaw_rate_scale: float = 1.0,
                 yaw_rate_bias: float = 0.0, extrapolation: float = 0.1, max_acceleration: float = 0.0):
        self.extrapolation = float(extrapolation)  # s: the last twist holds this long past the newest stamp
        self.max_acceleration = float(max_acceleration)  # m/s²: grip limit of a speed change (0: no slip)
        self.time_offset = float(time_offset)  # s
        self.speed_scale = float(speed_scale)
        self.yaw_rate_scale = float(yaw_rate_scale)
        self.yaw_rate_bias = float(yaw_rate_bias)  # rad/s
        self._t: list[float] = []  # corrected stamps t'_k (end of each period)
        self._twist: list[tuple[float, float, float]] = []  # corrected (vx, vy, ωz) over (t'_{k−1}, t'_k]
        self._slip: list[float] = []  # m/s over (t'_{k−1}, t'_k]: v*_k − vx'_k (0 without max_acceleration)
        self._slipped: list[float] = []  # m: A at t'_{k−1}, the episode's ∫ |slip| dt before period k
        self._after_boundary = False  # the newest message is a history's start marker (no measured speed)
        # the same four histories as arrays for the compiled queries, written as messages come: the store's rows
        # first … end − 1 are the messages in the lists; trim moves its first row, nothing is copied
        self._store = _ArrayHistory()
        self._arrays = None  # (stamps, twists, slips, slipped): views of the store, made once per change

    def __len__(self) -> int:
        return len(self._t)

    @property
    def latest(self) -> float | None:
        """Corrected time of the newest message (None when empty)."""
        return self._t[-1] if self._t else None

    @property
    def oldest(self) -> float | None:
        return self._t[0] if self._t else None

    def add(self, twist: TwistData, boundary: bool = False) -> float:
        """Append a message; returns its corrected time t'. ``boundary``: a marker where a new history
        starts (after a clock jump), not a measured twist: the next message's speed is not judged against it."""
        t = float(twist.stamp) + self.time_offset
        s = self.speed_scale
        vx = s * float(twist.vx)
        slip, slipped = 0.0, 0.0
        if self._t and self.max_acceleration > 0.0 and not self._after_boundary:  # else no known speed before
            dv = self.max_acceleration * (t - self._t[-1])
            before = self._twist[-1][0] + self._slip[-1]  # v* of the newest period
            slip = min(max(vx, before - dv), before + dv) - vx
            if slip != 0.0 and self._slip[-1] != 0.0:  # the episode goes on
                slipped = self._slipped[-1] + abs(self._slip[-1]) * (self._t[-1] - self._t[-2])
        self._t.append(t)
        self._twist.append((vx, s * float(twist.vy), self.yaw_rate_scale * float(twist.wz) + self.yaw_rate_bias))
        self._slip.append(slip)
        self._slipped.append(slipped)
        self._store.append(t, self._twist[-1], slip, slipped)
        self._after_boundary = boundary
        self._arrays = None
        return t

    def reset(self) -> None:
        self._arrays = None
        self._store.drop(len(self._t))
        self._t.clear()
        self._twist.clear()
        self._slip.clear()
        self._slipped.clear()

    def trim(self, before: float, keep: int = 2) -> None:
        """Forget messages whose period ended before ``before`` (keeping the boundary that starts
        the period holding ``before``, and at least ``keep`` messages)."""
        n = bisect.bisect_left(self._t, before) - 1  # self._t[n] < before: still the start
        n = min(n, len(self._t) - keep)
        if n > 0:
            self._arrays = None
            self._store.drop(n)
            del self._t[:n]
            del self._twist[:n]
            del self._slip[:n]
            del self._slipped[:n]

    def _as_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(stamps (K,), twists (K, 3), slips (K,), slipped (K,)) as arrays: the lists' values (views of the
        store, made once until the next change)."""
        if self._arrays is None:
            self._arrays = self._store.views()
        return self._arrays

    def twist_at(self, t: float) -> np.ndarray:
        """Corrected twist (vx, vy, ωz) holding at time t (the newest just past the end, the oldest just
        before the start; zero beyond the extrapolation limit either side, or when empty)."""
        if not self._t or t <= self._t[0] - self.extrapolation or t >= self._t[-1] + self.extrapolation:
            return np.zeros(3)
        k = min(bisect.bisect_left(self._t, t), len(self._t) - 1)
        return np.array(self._twist[k])

    def segments(self, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray]:
        """Pieces of constant twist covering [t0, t1] (t0 ≤ t1), cut at message stamps:
        durations (P,) and twists (P, 3). The oldest message's period has no known start: its twist
        holds for ``extrapolation`` before its stamp, as the newest one's holds after; beyond, the twist is zero."""
        dts, twists, _ = self.slip_segments(t0, t1)
        return dts, twists

    def slip_segments(self, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``segments`` and each piece's slip (P, 2): the mean (m) and the variance (m²) of how much
        farther forward the robot went than its twist says (the module docstring; 0 where the twist is
        extrapolated or unknown). Compiled (``slip_segments_kernel``) when numba is there."""
        if not t1 > t0:
            return np.zeros(0), np.zeros((0, 3)), np.zeros((0, 2))
        if slip_segments_kernel is None or not self._t:
            return self.slip_segments_numpy(t0, t1)
        stamps, twist_rows, slip_rows, slipped_rows = self._as_arrays()
        size = stamps.size + 3  # at most every cut inside, plus the two ends
        dts, twists, slips = np.empty(size), np.empty((size, 3)), np.empty((size, 2))
        count = slip_segments_kernel(stamps, twist_rows, slip_rows, slipped_rows, self.extrapolation,
                                     self.max_acceleration > 0.0, float(t0), float(t1), dts, twists, slips)
        return dts[:count], twists[:count], slips[:count]

    def slip_segments_numpy(self, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``slip_segments`` in numpy: the reference of the compiled kernel."""
        if not t1 > t0:
            return np.zeros(0), np.zeros((0, 3)), np.zeros((0, 2))
        stamps, twist_rows, slip_rows, slipped_rows = self._as_arrays()
        cuts = np.concatenate([[stamps[0] - self.extrapolation], stamps, [stamps[-1] + self.extrapolation]]) \
            if stamps.size else stamps
        inner = cuts[(cuts > t0) & (cuts < t1)]
        edges = np.concatenate([[t0], inner, [t1]])
        dts = np.diff(edges)
        twists = np.zeros((dts.size, 3))
        slips = np.zeros((dts.size, 2))
        if stamps.size:
            mid = 0.5 * (edges[:-1] + edges[1:])
            k = np.minimum(np.searchsorted(stamps, mid, side="left"), stamps.size - 1)
            known = (mid > stamps[0] - self.extrapolation) & (mid < stamps[-1] + self.extrapolation)
            twists[known] = twist_rows[k[known]]
            inside = (np.flatnonzero(known & (mid > stamps[0]) & (mid <= stamps[-1]))  # periods the odometry reported
                      if self.max_acceleration > 0.0 else ())
            if len(inside):
                ki = k[inside]
                speed = slip_rows[ki]  # m/s
                start = slipped_rows[ki]  # m: A at the period's start
                a0 = start + np.abs(speed) * (edges[inside] - stamps[ki - 1])  # A at the piece's start
                a1 = a0 + np.abs(speed) * dts[inside]
                slips[inside, 0] = 0.5 * speed * dts[inside]
                slips[inside, 1] = 0.25 * (a1 * a1 - a0 * a0)
        keep = dts > 0
        return dts[keep], twists[keep], slips[keep]

    def travel(self, t0: float, t1: float) -> tuple[float, float]:
        """Path length (m) and total rotation (rad) between t0 and t1 (t0 ≤ t1): Σ |v|·dt plus twice
        the slip's mean (a skid travels), Σ |ω|·dt."""
        dts, twists, slips = self.slip_segments(t0, t1)
        if not dts.size:
            return 0.0, 0.0
        return (float(np.dot(dts, np.hypot(twists[:, 0], twists[:, 1])) + 2.0 * np.abs(slips[:, 0]).sum()),
                float(np.dot(dts, np.abs(twists[:, 2]))))

    def motion(self, t0: float, t1: float) -> np.ndarray:
        """Robot-frame displacement [dx, dy, dθ] from time t0 to t1 (expressed in the robot frame
        at t0); the inverse motion when t1 < t0."""
        if not (math.isfinite(t0) and math.isfinite(t1)):
            return np.zeros(3)
        if t1 < t0:
            return inverse(self.motion(t1, t0))
        pose = (0.0, 0.0, 0.0)  # the pieces' arcs composed in floats (a few pieces)
        for dt, (vx, vy, wz) in zip(*(a.tolist() for a in self.segments(t0, t1))):
            pose = compose_floats(pose, integrate_twist_floats(vx, vy, wz, dt))
        return np.array(pose)


class _ArrayHistory:
    """The buffer's messages as growing arrays (stamps, twists (·, 3), slips, slipped): ``append`` writes the
    next row, ``drop`` forgets the oldest rows by moving the first one; the rows move to the front only when
    the arrays are full (``views``: the live rows, contiguous)."""

    def __init__(self, capacity: int = 64):
        self.first, self.end = 0, 0
        self.columns = (np.empty(capacity), np.empty((capacity, 3)), np.empty(capacity), np.empty(capacity))

    def append(self, t: float, twist, slip: float, slipped: float) -> None:
        if self.end == len(self.columns[0]):
            self._make_room()
        stamps, twists, slips, slipped_rows = self.columns
        k = self.end
        stamps[k], twists[k], slips[k], slipped_rows[k] = t, twist, slip, slipped
        self.end = k + 1

    def drop(self, count: int) -> None:
        self.first = min(self.first + count, self.end)
        if self.first == self.end:
            self.first = self.end = 0

    def views(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        return tuple(column[self.first:self.end] for column in self.columns)

    def _make_room(self) -> None:
        """The live rows to the front, into arrays twice the size when more than half of the room is live."""
        live, capacity = self.end - self.first, len(self.columns[0])
        columns = self.columns if 2 * live <= capacity else tuple(
            np.empty((2 * capacity,) + c.shape[1:]) for c in self.columns)
        for new, old in zip(columns, self.columns):
            new[:live] = old[self.first:self.end]
        self.columns, self.first, self.end = columns, 0, live


if njit is not None:
    @njit(cache=True, nogil=True)
    def slip_segments_kernel(stamps, twist_rows, slip_rows, slipped_rows, extrapolation, with_slip, t0, t1, dts,
                             twists, slips):  # pragma: no cover - compiled
        """``OdometryBuffer.slip_segments_numpy`` in one pass over the cuts, the same arithmetic: the pieces of
        [t0, t1] (t0 < t1) into ``dts``, ``twists``, ``slips`` (room for every stamp + 3); returns their count."""
        n = stamps.size
        first, last = stamps[0] - extrapolation, stamps[n - 1] + extrapolation
        count = 0
        start = t0
        for c in range(n + 3):  # the cuts inside (t0, t1), then t1
            if c == n + 2:
                end = t1
            else:
                cut = first if c == 0 else (last if c == n + 1 else stamps[c - 1])
                if not (cut > t0 and cut < t1):
                    continue
                end = cut
            dt = end - start
            if dt > 0:
                mid = 0.5 * (start + end)
                k = np.searchsorted(stamps, mid)  # side "left"
                k = n - 1 if k > n - 1 else k
                dts[count] = dt
                known = mid > first and mid < last
                for j in range(3):
                    twists[count, j] = twist_rows[k, j] if known else 0.0
                slips[count, 0] = 0.0
                slips[count, 1] = 0.0
                if with_slip and known and mid > stamps[0] and mid <= stamps[n - 1]:  # a period the odometry reported
                    speed = slip_rows[k]
                    a0 = slipped_rows[k] + abs(speed) * (start - stamps[k - 1])
                    a1 = a0 + abs(speed) * dt
                    slips[count, 0] = 0.5 * speed * dt
                    slips[count, 1] = 0.25 * (a1 * a1 - a0 * a0)
                count += 1
            start = end
        return count
else:  # pragma: no cover
    slip_segments_kernel = None
