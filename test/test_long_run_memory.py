"""What a long run keeps is bounded: the localizer's outboxes (the node never takes the update costs that
replay takes) and the watchdog's whole-run latency record (allocated once, its rows reused)."""
from __future__ import annotations

import numpy as np

from localization.core import watchdog as W
from localization.core.localizer.timeline import Outbox


def test_an_outbox_nobody_takes_keeps_only_its_newest_items():
    box = Outbox(size=100)
    for k in range(5000):
        box.put(k)
    assert box.take() == list(range(4900, 5000))
    assert box.take() == []
    box.put("a")
    assert box.take() == ["a"]


def test_the_whole_run_latency_record_is_one_array_that_does_not_grow(monkeypatch):
    monkeypatch.setattr(W, "RUN_MAX", 50)
    dog = W.Watchdog(0.0)
    record = dog._run
    for k in range(120):  # more updates than the record holds: the oldest rows are reused
        dog.sensor_update(float(k), {name: 0.001 * (k % 7 + 1) for name in W.PHASES})
    assert dog._run is record and record.shape == (50, len(W.PHASES))
    summary = dog.run_summary()
    assert "over 50 sensor updates" in summary
    # the rows hold the last 50 updates' phases (k = 70..119): 1..7 ms each, 5 phases
    totals = np.sort(record.sum(axis=1) * 1e3)
    expected = np.sort([5.0 * (k % 7 + 1) for k in range(70, 120)])
    np.testing.assert_allclose(totals, expected, rtol=1e-5)
