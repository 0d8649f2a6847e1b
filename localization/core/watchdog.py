"""Watchdogs and the node's one diagnostic status (no ROS: the node converts it to
diagnostic_msgs/DiagnosticArray with ``localization.ros.messages.diagnostic_array_msg``).

Every input event is recorded with a monotonic time ``now`` (seconds) given by the caller, so the
logic is testable with a fake clock. ``status(now, ...)`` turns the record into

    level   = max over the checks below (OK 0 < WARN 1 < ERROR 2, the diagnostic_msgs values)
    message = the worst problem, or "localizing" / what the node waits for
    values  = key → text: health, sensor updates/s, scan → pose latency, scans received/processed/
              dropped, particles, seconds since the last scan / odometry / map, state

Checks (``t_x`` = seconds since the last x, or since the reference when x never came):

    no odometry   scans arrive (t_scan ≤ scan_timeout) and t_odom > odom_timeout   → WARN
    no scans      odometry arrives (t_odom ≤ odom_timeout) and t_scan > scan_timeout → WARN
    no input      neither arrives, t > max(odom_timeout, scan_timeout) after start  → WARN
    no map        no map t > map_timeout after start                               → WARN
    TF            the laser pose lookup failed for longer than tf_timeout           → WARN
    scans dropped a scan was not used (no map, range table being built, no initial
                  pose, sensor-update queue full) in the last ``window`` seconds     → WARN
    disagree      localizing and the localizer holds its pose on odometry because the
                  scans disagree with the map (``Localizer.status``)                  → WARN
    lost          localizing and health < health_lost_floor                       → ERROR
    map failed    the map was rejected or its range table could not be built       → ERROR

A WARN names the subscribed topic and the topics of the same type that do exist (the node lists
them), so a ``/odom`` vs ``/vesc/odom`` mix-up reads as such.

Rates and latencies are taken over the last ``window`` seconds (5 s): sensor updates/s = updates
in the window / window; latency = median and 95th percentile of (pose published − scan received),
wall clock, and of its parts (waiting for the worker, deserialization, conversion, sensor update,
publishing). The sensor-update thread records them while the executor's thread reads them for
/diagnostics: the windows are kept under one lock.
"""
from __future__ import annotations

import math
import threading
from collections import Counter, deque
from dataclasses import dataclass, field

import numpy as np

OK, WARN, ERROR = 0, 1, 2  # diagnostic_msgs/DiagnosticStatus levels
LEVEL_NAMES = {OK: "OK", WARN: "WARN", ERROR: "ERROR"}
WINDOW_S = 5.0  # seconds over which rates and latencies are computed
PHASES = ("wait", "deserialize", "convert", "update", "publish")  # parts of the scan -> pose latency
RUN_MAX = 100_000  # sensor updates kept for the whole-run latency summary (the last ~40 min at 40 Hz; 2 MB)


@dataclass
class Problem:
    key: str  # stable identity of the problem (log throttling)
    level: int
    message: str


@dataclass
class Status:
    level: int
    message: str
    values: dict = field(default_factory=dict)  # key -> str
    problems: list = field(default_factory=list)  # [Problem], worst first


def _since(now: float, t: float | None) -> float:
    return math.inf if t is None else max(0.0, now - t)


def _fmt_age(age: float) -> str:
    return "never" if not math.isfinite(age) else f"{age:.2f}"


def _ago(age: float) -> str:
    return "never" if not math.isfinite(age) else f"{age:.1f} s ago"


class Watchdog:
    """Record of the node's inputs and outputs; ``status`` judges it (see the module docstring)."""

    def __init__(self, start: float, *, odom_timeout: float = 0.5, scan_timeout: float = 0.5,
                 map_timeout: float = 5.0, tf_timeout: float = 1.0, scan_topic: str = "/scan",
                 odom_topic: str = "/odom", map_topic: str = "/map", window: float = WINDOW_S,
                 health_lost_floor: float = 0.0):
        self.start = start
        self.health_lost_floor = health_lost_floor
        self.odom_timeout, self.scan_timeout = odom_timeout, scan_timeout
        self.map_timeout, self.tf_timeout = map_timeout, tf_timeout
        self.scan_topic, self.odom_topic, self.map_topic = scan_topic, odom_topic, map_topic
        self.window = window
        self.last_scan = self.last_odom = self.last_map = None
        self.first_scan = self.first_odom = None
        self.scans_received = self.scans_processed = self.sensor_updates = 0
        self.scans_waiting_for_table = self.odom_waiting_for_table = 0
        self.odom_count = 0
        self.map_state = "none"  # none | building | ready | failed
        self.map_detail = ""
        self.tf_failing_since: float | None = None
        self.tf_detail = ""
        # the sensor-update thread records, the executor's reads: the windows below under one lock
        self._lock = threading.RLock()
        self._updates: deque = deque()  # (now, {phase: seconds}) of sensor updates
        self._drops: deque = deque()  # (now, count, reason) of scans not used
        self.scans_dropped = 0  # over the whole run
        # seconds per PHASES part of the run's last RUN_MAX updates: one array, written at once (np.full, not
        # np.zeros, so its pages are resident from the start and the memory does not grow later)
        self._run = np.full((RUN_MAX, len(PHASES)), 0.0, dtype=np.float32)
        self._run_count = 0  # updates recorded over the run (the newest in row (count - 1) % RUN_MAX)
        self._rejected = 0

    # ------------------------------------------------------------------ events
    def scan_received(self, now: float) -> None:
        self.scans_received += 1
        self.last_scan = now
        if self.first_scan is None:
            self.first_scan = now

    def odom_received(self, now: float) -> None:
        self.odom_count += 1
        self.last_odom = now
        if self.first_odom is None:
            self.first_odom = now

    def scan_processed(self, now: float, updated: bool = False, phases: dict | None = None) -> None:
        """A scan went through the localizer; ``updated``: it produced a sensor update (and a pose);
        ``phases``: seconds spent per part (``PHASES``)."""
        self.scans_processed += 1
        if updated:
            self.sensor_update(now, phases)
        self._trim(now)

    def sensor_update(self, now: float, phases: dict | None = None) -> None:
        """A sensor-corrected estimate was published; ``phases``: seconds per part of its scan's way
        (``PHASES``), None when unknown (counted in the rate, not in the latency)."""
        with self._lock:
            self.sensor_updates += 1
            self._updates.append((now, dict(phases or {})))
            if phases:
                self._run[self._run_count % RUN_MAX] = [phases.get(k, 0.0) for k in PHASES]
                self._run_count += 1
            self._trim(now)

    def scans_not_used(self, now: float, count: int, reason: str) -> None:
        """``count`` scans were dropped (not used by the filter) because of ``reason``."""
        if count > 0:
            with self._lock:
                self.scans_dropped += count
                self._drops.append((now, int(count), reason))
                self._trim(now)

    def map_building(self, now: float, detail: str = "") -> None:
        self.last_map = now
        if self.map_state != "ready":
            self.map_state = "building"
        self.map_detail = detail

    def map_ready(self, now: float) -> None:
        self.last_map = now
        self.map_state, self.map_detail = "ready", ""

    def map_failed(self, now: float, detail: str) -> None:
        self.last_map = now
        self.map_state, self.map_detail = "failed", detail

    def tf_ok(self) -> None:
        self.tf_failing_since, self.tf_detail = None, ""

    def tf_failed(self, now: float, detail: str) -> None:
        if self.tf_failing_since is None:
            self.tf_failing_since = now
        self.tf_detail = detail

    def _trim(self, now: float) -> None:
        with self._lock:
            while self._updates and self._updates[0][0] < now - self.window:
                self._updates.popleft()
            while self._drops and self._drops[0][0] < now - self.window:
                self._drops.popleft()

    # ------------------------------------------------------------------ judgement
    def latency(self, now: float) -> dict:
        """{"total": (median, p95), phase: (median, p95)} in seconds over the window (NaN: no update)."""
        with self._lock:
            self._trim(now)
            updates = list(self._updates)
        out = {}
        for name in ("total",) + PHASES:
            if name == "total":
                vals = [sum(p.values()) for _, p in updates if p]
            else:
                vals = [p[name] for _, p in updates if name in p]
            out[name] = (float(np.median(vals)), float(np.percentile(vals, 95))) if vals else (math.nan, math.nan)
        return out

    def run_summary(self) -> str:
        """Where the scan -> pose time went over the whole run: median / p95 (ms) of the total and of
        each part (wait: queued for the sensor-update thread, 0 without one; deserialize: CDR bytes -> ScanData;
        convert: its stamp kept and the laser pose; update: the Localizer's sensor update +
        resampling; publish: the outputs)."""
        with self._lock:
            a = self._run[:min(self._run_count, RUN_MAX)] * 1e3
        if not len(a):
            return "no sensor update"
        parts = [("total", a.sum(axis=1))] + [(name, a[:, i]) for i, name in enumerate(PHASES)]
        return ", ".join(f"{name} {np.median(v):.1f}/{np.percentile(v, 95):.1f}" for name, v in parts) + \
            f" ms (median/p95 over {len(a)} sensor updates)"

    def update_rate(self, now: float) -> float:
        with self._lock:
            self._trim(now)
            count = len(self._updates)
        span = min(self.window, max(now - self.start, 1e-9))
        return count / span

    def problems(self, now: float, *, ready: bool = False, waiting_for: str = "", health: float = math.nan,
                 odom_topics=(), scan_topics=(), holding: bool = False) -> list:
        out = []
        self._trim(now)
        if ready and math.isfinite(health) and health < self.health_lost_floor:
            out.append(Problem("lost", ERROR, f"lost: scan-map agreement {health:.2f} is below health_lost_floor "
                               f"{self.health_lost_floor:.2f} (the scans do not match the map at the estimate)"))
        if ready and holding:
            agreement = "" if not math.isfinite(health) else f" (scan-map agreement {health:.2f})"
            out.append(Problem("disagree", WARN, f"scans disagree with the map{agreement}: holding the pose on "
                               "odometry, searching the map for a place the scans fit"))
        with self._lock:
            drops = list(self._drops)
        if drops:
            reasons = Counter()
            for _, count, reason in drops:
                reasons[reason] += count
            text = "; ".join(f"{n} {reason}" for reason, n in reasons.most_common())
            out.append(Problem("scans-dropped", WARN, f"{sum(reasons.values())} scans not used in the last "
                               f"{self.window:g} s: {text}"))
        t_scan, t_odom = _since(now, self.last_scan), _since(now, self.last_odom)
        scans_arrive = t_scan <= self.scan_timeout
        odom_arrives = t_odom <= self.odom_timeout
        if self.map_state == "failed":
            out.append(Problem("map-failed", ERROR, f"map on {self.map_topic} unusable: {self.map_detail}"))
        if scans_arrive and _since(now, self.last_odom if self.last_odom is not None else self.first_scan) \
                > self.odom_timeout:
            others = [t for t in odom_topics if t != self.odom_topic]
            silent = (f"for {t_odom:.1f} s" if math.isfinite(t_odom)
                      else f"yet ({_since(now, self.first_scan):.1f} s after the first scan)")
            out.append(Problem("no-odom", WARN, f"scans arrive but no odometry on {self.odom_topic} {silent}; "
                               f"nav_msgs/msg/Odometry topics present: {', '.join(others) or 'none'} "
                               "(set odom_topic)"))
        if odom_arrives and _since(now, self.last_scan if self.last_scan is not None else self.first_odom) \
                > self.scan_timeout:
            others = [t for t in scan_topics if t != self.scan_topic]
            silent = (f"for {t_scan:.1f} s" if math.isfinite(t_scan)
                      else f"yet ({_since(now, self.first_odom):.1f} s after the first odometry)")
            out.append(Problem("no-scan", WARN, f"odometry arrives but no scan on {self.scan_topic} {silent}; "
                               f"sensor_msgs/msg/LaserScan topics present: {', '.join(others) or 'none'} "
                               "(set scan_topic)"))
        if not scans_arrive and not odom_arrives and now - self.start > max(self.odom_timeout, self.scan_timeout):
            out.append(Problem("no-input", WARN, f"no scan on {self.scan_topic} and no odometry on "
                               f"{self.odom_topic} (last scan {_ago(t_scan)}, last odometry {_ago(t_odom)})"))
        if self.map_state == "none" and now - self.start > self.map_timeout:
            out.append(Problem("no-map", WARN, f"no map on {self.map_topic} {now - self.start:.1f} s after the "
                               "start (is a map_server running? localization-play --map NAME publishes one)"))
        if self.tf_failing_since is not None and now - self.tf_failing_since > self.tf_timeout:
            out.append(Problem("tf", WARN, f"TF lookup failing: {self.tf_detail}"))
        if not out and not ready and waiting_for and self.map_state == "ready" \
                and now - self.start > self.map_timeout:
            out.append(Problem("not-ready", WARN, f"not localizing: waiting for {waiting_for}"))
        out.sort(key=lambda p: -p.level)
        return out

    def status(self, now: float, *, ready: bool, waiting_for: str = "", health: float = math.nan,
               particles: int = 0, dropped: int = 0, odom_topics=(), scan_topics=(), holding: bool = False) -> Status:
        problems = self.problems(now, ready=ready, waiting_for=waiting_for, health=health, odom_topics=odom_topics,
                                 scan_topics=scan_topics, holding=holding)
        level = problems[0].level if problems else OK
        if problems:
            message = "; ".join(p.message for p in problems)
        else:
            message = "localizing" if ready else f"waiting for {waiting_for or 'input'}"
        lat = self.latency(now)
        values = {
            "state": "localizing" if ready else f"waiting for {waiting_for or 'input'}",
            "health": "unknown" if not math.isfinite(health) else f"{health:.2f}",
            "sensor updates/s": f"{self.update_rate(now):.1f}",
            "scan to pose latency median (ms)": _ms(lat["total"][0]),
            "scan to pose latency p95 (ms)": _ms(lat["total"][1]),
            "scans received": str(self.scans_received),
            "scans processed": str(self.scans_processed),
            "scans dropped": str(dropped + self.scans_dropped),
            "sensor updates": str(self.sensor_updates),
            "scans while the range table was built": str(self.scans_waiting_for_table),
            "particles": str(particles),
            "seconds since last scan": _fmt_age(_since(now, self.last_scan)),
            "seconds since last odometry": _fmt_age(_since(now, self.last_odom)),
            "seconds since last map": _fmt_age(_since(now, self.last_map)),
            "map": self.map_state + (f" ({self.map_detail})" if self.map_detail else ""),
            "scan topic": self.scan_topic,
            "odometry topic": self.odom_topic,
        }
        for phase in PHASES:
            values[f"latency {phase} median (ms)"] = _ms(lat[phase][0])
            values[f"latency {phase} p95 (ms)"] = _ms(lat[phase][1])
        return Status(level=level, message=message, values=values, problems=problems)


def _ms(seconds: float) -> str:
    return "n/a" if not math.isfinite(seconds) else f"{seconds * 1e3:.1f}"


class ProblemLog:
    """Which problems to log now: each when it first appears, then at most every ``period`` seconds
    while it lasts; ``cleared`` lists the keys of problems that went away (log "recovered")."""

    def __init__(self, period: float = 5.0):
        self.period = period
        self._last: dict[str, float] = {}

    def due(self, problems, now: float) -> tuple[list, list]:
        current = {p.key for p in problems}
        cleared = [k for k in self._last if k not in current]
        for k in cleared:
            del self._last[k]
        out = []
        for p in problems:
            last = self._last.get(p.key)
            if last is None or now - last >= self.period:
                self._last[p.key] = now
                out.append(p)
        return out, cleared
