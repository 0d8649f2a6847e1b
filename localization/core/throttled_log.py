"""One clear log line per kind of problem, not a flood: each key at most once per period (wall clock)."""
from __future__ import annotations

import logging
import time

import numpy as np


class ThrottledLog:
    """Log each kind of message at most once per ``period`` seconds (wall clock), counting the
    repeats, so a broken sensor at 40 Hz gives one clear line, not a flood."""

    def __init__(self, logger: logging.Logger, period: float = 5.0):
        self.logger, self.period = logger, period
        self._last: dict[str, tuple[float, int]] = {}

    def __call__(self, key: str, message: str, level: int = logging.WARNING) -> None:
        now = time.monotonic()
        last, repeats = self._last.get(key, (-np.inf, 0))
        if now - last >= self.period:
            suffix = f" ({repeats} more since the last report)" if repeats else ""
            self.logger.log(level, message + suffix)
            self._last[key] = (now, 0)
        else:
            self._last[key] = (last, repeats + 1)
