"""``benchmarks.per_scan``: the core's CPU per scan on a real bag, stage by stage, and its ``--gap``."""
from __future__ import annotations

from localization.benchmarks import per_scan


def test_per_scan_times_the_stages_and_sleeps_between_scans_untimed(shared_dir, monkeypatch):
    """With ``gap`` the benchmark sleeps that long after every scan, outside the timed calls: one sleep per
    scan of every run, none inside a timed stage (the thread CPU time cannot count a sleep anyway)."""
    slept = []
    monkeypatch.setattr(per_scan.time, "sleep", lambda s: slept.append(s))
    r = per_scan.measure("bag3", skip=40, repeat=1, gap=0.02)
    runs = 2  # a warm-up run, then ``repeat`` timed ones
    assert r["gap_s"] == 0.02
    assert len(slept) == runs * (r["scans"] + 40) and set(slept) == {0.02}
    assert 0 < r["sensor_updates"] <= r["scans"]
    parts = r["parts"]
    assert parts["sensor model (kernel)"] > 0 and parts["move"] > 0
    assert max(parts.values()) < r["ms_per_scan"]  # each stage is a part of the timed feed calls


def test_per_scan_runs_a_given_particle_count_updating_on_every_scan(shared_dir):
    r = per_scan.measure("bag3", skip=40, repeat=1, particles=600)
    assert r["particles"] == 600
    assert r["sensor_updates"] == r["scans"] > 0  # the file's update policy skips some; this run none


def test_per_scan_busy_spends_the_gap_awake_instead_of_sleeping(shared_dir, monkeypatch):
    """``busy``: the same gap after every scan, spent in ``busy_wait`` (the processor never idles), never slept;
    and ``busy_wait`` itself lets the wall time pass without sleeping."""
    slept, busy = [], []
    monkeypatch.setattr(per_scan.time, "sleep", lambda s: slept.append(s))
    real_busy_wait = per_scan.busy_wait
    monkeypatch.setattr(per_scan, "busy_wait", lambda s: busy.append(s))
    r = per_scan.measure("bag3", skip=40, repeat=1, gap=0.02, busy=True)
    assert r["busy"] is True and not slept
    assert len(busy) == 2 * (r["scans"] + 40) and set(busy) == {0.02}
    t0 = per_scan.time.perf_counter()
    real_busy_wait(0.01)
    assert per_scan.time.perf_counter() - t0 >= 0.01 and not slept
