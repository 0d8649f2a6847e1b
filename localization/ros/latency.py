"""Latency bookkeeping: each scan's way through the node, until its correction is published.

Per scan (monotonic times): ``put`` (arrived, or queued for the sensor-update thread), ``start``
(its handling began), ``deserialized`` (CDR bytes -> ScanData), ``converted`` (stamp kept, laser pose). When the
correction at the scan's time t_s is published, the phases go to the watchdog (/diagnostics):

    wait = start - put,  deserialize = deserialized - start,  convert = converted - deserialized,
    update = ready - converted (sensor update, resampling, any wait for odometry),  publish = now - ready
"""
from __future__ import annotations

import threading

SCAN_TIMES_KEPT = 64  # scans whose way through the node is remembered until their correction


class LatencyBook:
    """The way of the last SCAN_TIMES_KEPT scans, by scan time t_s (thread safe)."""

    def __init__(self, kept: int = SCAN_TIMES_KEPT):
        self._kept = kept
        self._ways: dict[float, tuple] = {}  # t_s -> (put, start, deserialized, converted)
        self._lock = threading.Lock()

    def scan_converted(self, t_s: float, put: float, start: float, deserialized: float, converted: float) -> None:
        """Remember a usable scan's way so far (oldest forgotten beyond the kept number)."""
        with self._lock:
            self._ways[t_s] = (put, start, deserialized, converted)
            while len(self._ways) > self._kept:
                del self._ways[next(iter(self._ways))]

    def phases(self, t_s: float, ready: float, now: float) -> dict | None:
        """The phases (s) of the scan at t_s whose correction was ready at ``ready`` and published by
        ``now``; None when its way is not known (forgotten, or a correction without a scan of its own)."""
        with self._lock:
            way = self._ways.pop(t_s, None)
        if way is None:
            return None
        put, start, deserialized, converted = way
        return {"wait": start - put, "deserialize": deserialized - start, "convert": converted - deserialized,
                "update": ready - converted, "publish": now - ready}

    def clear(self) -> None:
        with self._lock:
            self._ways.clear()
