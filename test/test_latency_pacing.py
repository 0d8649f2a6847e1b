"""The latency benchmark streams the real bags at the times their drivers stamped the messages, not at the
times the bag's recorder received them (the recorder took them in bursts)."""
import numpy as np
import pytest


def _scan_gaps_ms(bags):
    return [np.diff([t for t, topic, _ in msgs if topic == "/scan"]) * 1e3 for _, _, msgs in bags]


def test_streamed_at_header_stamps_the_scans_come_every_25_ms(shared_dir):
    pytest.importorskip("rclpy")
    if not (shared_dir / "bags" / "rss2022").exists():
        pytest.skip("the RSS bags are not available")
    from localization.benchmarks.latency import _load_bags

    by_stamp = _load_bags("stamps")
    for (_, _, msgs), gaps in zip(by_stamp, _scan_gaps_ms(by_stamp), strict=True):
        times = [t for t, _, _ in msgs]
        assert times == sorted(times) and times[0] == 0.0
        assert np.percentile(gaps, 1) > 20.0 and np.median(gaps) == pytest.approx(25.1, abs=0.3)
    recorded = np.concatenate(_scan_gaps_ms(_load_bags("recorded")))
    assert np.mean(recorded < 5.0) > 0.2  # the recorder's bursts: two scans within 5 ms, a third of the time
