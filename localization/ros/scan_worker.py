"""The sensor-update thread: a one-slot mailbox in front of a worker thread.

The scan subscription callback only ``put``s the message; the worker runs the sensor update (the
compiled kernels release the GIL) and publishes. A scan that arrives while the previous one is
still being processed replaces any scan still waiting (``dropped`` counts those), so scans never
queue behind a slow update.
"""
from __future__ import annotations

import threading


class LatestScanWorker:
    """A thread that handles the newest scan left by ``put``: a one-slot mailbox, so a scan that
    arrives while the previous one is still being processed replaces any scan still waiting
    (``dropped`` counts those) instead of queueing behind it."""

    def __init__(self, handle, log_error, name: str = "sensor_update"):
        self._handle, self._log_error = handle, log_error
        self._cond = threading.Condition()
        self._pending = None
        self._stop = False
        self.dropped = 0
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def put(self, item) -> None:
        with self._cond:
            if self._pending is not None:
                self.dropped += 1
            self._pending = item
            self._cond.notify()

    def _run(self) -> None:
        while True:
            with self._cond:
                while self._pending is None and not self._stop:
                    self._cond.wait()
                if self._stop:
                    return
                item, self._pending = self._pending, None
            try:
                self._handle(item)
            except Exception as exc:  # noqa: BLE001 - a bad scan must never kill the thread
                self._log_error(f"sensor update failed: {exc!r}")

    def stop(self, timeout: float = 5.0) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify()
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout)
