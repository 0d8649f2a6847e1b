"""The sensor-update thread: a short FIFO in front of a worker thread.

The scan subscription callback only ``put``s the message (with the time it arrived); the worker
runs the sensor update (the compiled kernels release the GIL) and publishes. Scans are handled in
arrival order; at most ``depth`` wait. A scan arriving when ``depth`` are already waiting pushes
out the oldest waiting one (``dropped`` counts those): a worker that is briefly late (a slow
resampling, a garbage collection, a busy CPU) catches up on the next scans instead of losing one,
while a worker that is slower than the sensor for good keeps the newest scans, never a growing
backlog. ``depth=1`` is the one-slot mailbox "always the newest scan". ``poke`` asks the thread
for one call of ``on_poke`` without taking a slot (the node's: scans the odometry has since released).

With 40 Hz scans and ``depth`` 3 a scan waits at most 3 × 25 ms behind a stalled update before
being dropped; the average update (a few ms) is far below the 25 ms period, so the queue drains
within one or two periods.
"""
from __future__ import annotations

import threading
import time
from collections import deque

DEFAULT_DEPTH = 3


class ScanQueueWorker:
    """A thread that handles the items left by ``put`` in order, keeping at most ``depth`` waiting
    (the oldest waiting one is dropped, and counted in ``dropped``, when a new one arrives)."""

    def __init__(self, handle, log_error, name: str = "sensor_update", depth: int = DEFAULT_DEPTH, on_poke=None):
        self._handle, self._log_error = handle, log_error
        self._on_poke = on_poke  # called on the thread after ``poke`` (work that is not an item: no slot taken)
        self._poked = False
        self._cond = threading.Condition()
        self._queue: deque = deque()
        self.depth = max(1, int(depth))
        self._stop = False
        self.dropped = 0
        self.handled = 0
        self.queued = 0
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def put(self, item) -> None:
        """Queue ``item``; ``handle(item, t_put)`` gets the monotonic time of this call."""
        now = time.monotonic()
        with self._cond:
            if len(self._queue) >= self.depth:
                self._queue.popleft()
                self.dropped += 1
            self._queue.append((item, now))
            self.queued += 1
            self._cond.notify()

    def poke(self) -> None:
        """Have the thread call ``on_poke`` once it has handled the items waiting (several pokes before it
        gets to it: one call; no item is pushed out)."""
        if self._on_poke is None:
            return
        with self._cond:
            self._poked = True
            self._cond.notify()

    @property
    def idle(self) -> bool:
        """Every item put so far has been handled or dropped."""
        with self._cond:
            return self.handled + self.dropped >= self.queued

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._queue and not self._poked and not self._stop:
                    self._cond.wait()
                if self._stop:
                    return
                poked = not self._queue
                if poked:
                    self._poked = False
                else:
                    item, t_put = self._queue.popleft()
            try:
                if poked:
                    self._on_poke()
                else:
                    self._handle(item, t_put)
            except Exception as exc:  # noqa: BLE001 - a bad scan must never kill the thread
                self._log_error(f"{self._thread.name} failed: {exc!r}")
            if not poked:
                with self._cond:
                    self.handled += 1

    def stop(self, timeout: float = 5.0) -> None:
        with self._cond:
            self._stop = True
            self._queue.clear()
            self._cond.notify()
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout)
