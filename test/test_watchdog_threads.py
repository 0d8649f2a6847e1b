"""The watchdog is written by the sensor-update thread and read by the executor's (/diagnostics): its windows of
updates and dropped scans stay consistent under both (a comprehension over a deque another thread appends to
raised 'deque mutated during iteration' in the diagnostics timer and ended the node)."""
from __future__ import annotations

import sys
import threading

from localization.core.watchdog import PHASES, Watchdog


def test_the_diagnostics_read_while_the_sensor_update_thread_records():
    dog = Watchdog(0.0)
    stop, errors, t = threading.Event(), [], [0.0]

    def record():
        while not stop.is_set():
            t[0] += 0.001
            dog.scan_processed(t[0], updated=True, phases={k: 0.001 for k in PHASES})
            dog.scans_not_used(t[0], 1, "dropped by the full sensor-update queue")

    switch = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)  # hand the GIL over as often as possible
    writer = threading.Thread(target=record)
    writer.start()
    try:
        for _ in range(50):  # without the lock the first few reads already raise
            try:
                now = t[0]
                dog.latency(now)
                dog.update_rate(now)
                dog.problems(now, ready=True)
                dog.run_summary()
            except RuntimeError as exc:  # noqa: PERF203 - the failure this guards against
                errors.append(exc)
    finally:
        stop.set()
        writer.join()
        sys.setswitchinterval(switch)
    assert not errors, errors[:1]
    assert dog.sensor_updates > 0 and dog.latency(t[0])["total"][0] > 0
