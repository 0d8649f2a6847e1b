"""Stamps: float seconds in the core, ``builtin_interfaces/Time`` on the wire."""
from __future__ import annotations

import threading
from collections import OrderedDict

import numpy as np
from builtin_interfaces.msg import Time

from localization.ros.conversions import parts_to_sec, sec_to_stamp_parts

INT32_MAX = 2**31 - 1  # builtin_interfaces/Time.sec is int32


def time_msg(stamp) -> Time:
    """A ``builtin_interfaces/Time`` from float seconds (or a Time-like message, copied), clamped
    to what the type can carry (rclpy's Python messages accept values that cannot be serialized):
    negative or non-finite times become 0, times beyond int32 seconds the latest stamp."""
    sec, nanosec = stamp_parts(stamp)
    return Time(sec=sec, nanosec=nanosec)


def stamp_parts(stamp) -> tuple[int, int]:
    """(sec, nanosec) of ``time_msg(stamp)``, without building the message; ``stamp``: float seconds, a
    Time-like message or a (sec, nanosec) pair."""
    if isinstance(stamp, tuple) or (hasattr(stamp, "sec") and hasattr(stamp, "nanosec")):
        sec, nanosec = _fields(stamp)
        sec, nanosec = int(sec), min(max(int(nanosec), 0), 999_999_999)
    else:
        t = float(stamp)
        sec, nanosec = sec_to_stamp_parts(t if np.isfinite(t) and t >= 0 else 0.0)
    if sec < 0:
        sec = 0
    elif sec > INT32_MAX:
        sec, nanosec = INT32_MAX, 999_999_999
    return sec, nanosec


def _fields(stamp) -> tuple:
    """(sec, nanosec) as given, of a Time-like message or a (sec, nanosec) pair."""
    return stamp if isinstance(stamp, tuple) else (stamp.sec, stamp.nanosec)


class StampBook:
    """Remembers the exact stamps of recent input messages by their float-seconds value.

    The core keeps stamps as float seconds, which cannot hold a 2022 epoch time to the
    nanosecond; outputs are stamped with the exact input stamp when it is one of the last
    ``size`` remembered, else with the rounded float."""

    def __init__(self, size: int = 256):
        self._size = size
        self._book: OrderedDict[float, tuple[int, int]] = OrderedDict()
        self._lock = threading.Lock()

    def remember(self, stamp) -> float:
        """``stamp``: a Time-like message or a (sec, nanosec) pair; returns it in float seconds."""
        t = parts_to_sec(*_fields(stamp))
        with self._lock:
            self._book[t] = stamp_parts(stamp)
            self._book.move_to_end(t)
            if len(self._book) > self._size:
                self._book.popitem(last=False)
        return t

    def lookup(self, t: float) -> tuple[int, int]:
        """(sec, nanosec): the remembered stamp of time t, else t rounded (``stamp_parts``)."""
        with self._lock:
            exact = self._book.get(t)
        return exact if exact is not None else stamp_parts(t)
