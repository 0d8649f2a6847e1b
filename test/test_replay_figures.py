"""The replay's summary says what its figures count: the largest jump once the filter tracks (not a global
start's convergence), the yardstick's scans split into parts that add up, and why a yardstick scored
nothing. From made-up series: no bag needed."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from localization.eval import metrics as M
from localization.eval.replay import jump_text, partition_text, summary_table, unscored_reason


def _drive(n=100, dt=0.1):
    """A track at 1 m/s with a 12 m jump at index 20 (a global start's cloud converging)."""
    t = np.arange(n) * dt
    poses = np.column_stack([0.1 * np.arange(n), np.zeros(n), np.zeros(n)])
    poses[:20, 0] -= 12.0
    return t, poses


def test_a_global_start_counts_jumps_from_the_first_scan_fitting_the_map():
    t, poses = _drive()
    agreement = np.where(t < 2.5, 0.3, 0.9)  # fits the map from t = 2.5 s on, after the convergence at t = 2.0
    settled = M.settled_time(False, 0.0, t, agreement)
    assert settled == pytest.approx(2.5)
    m = M.jump_figures(t, poses, settled, 0.0, from_pose=False)
    assert m["max_jump_m"] == pytest.approx(0.1) and m["max_jump_with_convergence_m"] == pytest.approx(12.1)
    assert m["max_jump_from_s"] == pytest.approx(2.5) and "first scan fitting the map" in m["max_jump_counts"]
    text = jump_text(m)
    assert text.startswith("0.100 m") and "from 2.5 s on" in text and "12.100 m with the convergence" in text


def test_a_start_pose_counts_every_jump_as_before():
    t, poses = _drive()
    m = M.jump_figures(t, poses, M.settled_time(True, 0.0, t, np.zeros(t.size)), 0.0, from_pose=True)
    assert m["max_jump_m"] == pytest.approx(M.max_jump(poses)) == pytest.approx(12.1)
    assert "start pose" in jump_text(m)


def test_a_global_start_that_never_fits_says_so():
    t, poses = _drive()
    agreement = np.full(t.size, 0.5)
    agreement[3] = np.nan
    settled = M.settled_time(False, 0.0, t, agreement)
    assert settled is None
    m = M.jump_figures(t, poses, settled, 0.0, from_pose=False)
    assert m["max_jump_m"] is None
    text = jump_text(m)
    assert text.startswith("n/a: no scan fitted the map") and "12.100 m over every estimate" in text


@pytest.mark.parametrize("seed", range(5))
def test_the_yardstick_parts_add_up_to_its_scans(seed):
    rng = np.random.default_rng(seed)
    n = 300
    usable = rng.random(n) < 0.8
    accepted = usable & (rng.random(n) < 0.9)
    good = (accepted & (rng.random(n) < 0.8)) | (rng.random(n) < 0.05)  # confident through odometry alone too
    scored = int(good.sum()) - 7
    parts = M.yardstick_partition(good, usable, accepted, scored)
    assert sum(parts.values()) == n and list(parts) == list(M.YARDSTICK_PARTS)
    assert parts["scored"] == scored and parts["confident_unscored"] == 7
    assert parts["unmatched"] == int((~good & ~usable).sum())
    # the old figures did not add up: scored + ambiguous + unmatched/low score counted scans twice or not at all
    text = partition_text(parts)
    assert text.startswith(f"{n} = {scored} scored") and text.count("+") == sum(v > 0 for v in parts.values()) - 1
    assert M.yardstick_partition(good, usable, accepted, 10 ** 6)["scored"] == int(good.sum())  # never more


def _ref(n=50, usable=0, good=0, **counts):
    return SimpleNamespace(t=np.arange(n) * 0.1, good=np.arange(n) < good,
                           counts={"scans": n, "usable": usable, "accepted": usable, "start": "global match",
                                   **counts})


def test_a_yardstick_that_scored_nothing_says_why():
    assert "only 2 of 50 scans matched the map (global match)" in unscored_reason(_ref(usable=2))
    why = unscored_reason(_ref(usable=40, poor_fit=30, outside_free_space=5))
    assert "40 of 50 matches kept" in why and "a poor fit 30" in why and "outside the map's free space 5" in why
    assert "uncertain" in unscored_reason(_ref(usable=40))
    assert "cover none of the 12 confident scans" in unscored_reason(_ref(usable=40, good=12))
    assert unscored_reason(_ref(usable=40), "smoothing failed") == "smoothing failed"


def _metrics(**over):
    stats = {"mean": 0.05, "median": 0.04, "p95": 0.1, "max": 0.2, "rms": 0.06, "p05": 0.7, "min": 0.5}
    m = {"bag": "b", "initial_pose_source": "global", "scans": 10, "odometry": 10, "estimates": 20,
         "sensor_updates": 10, "has_truth": False, "scan_map_agreement": stats, "health": stats,
         "recoveries": 0, "max_jump_m": 0.1, "sensor_update_ms": {"median_ms": 1.0, "p95_ms": 2.0},
         "motion_update_ms": {"median_ms": 0.1, "p95_ms": 0.2}, "num_particles": 100, "num_beams_per_particle": 100,
         "ray_caster": "lookup_table", "effective_update_rate_hz": 100.0, "realtime_factor": 2.0,
         "bag_duration_s": 1.0, "wall_time_s": 0.5, "particles": None}
    m.update(over)
    return m


def test_summary_table_gives_the_reason_and_the_parts():
    text = summary_table(_metrics(reference_error_m={"median": None, "p95": None, "max": None},
                                  reference_unscored_reason="only 2 of 50 scans matched the map (global match)",
                                  reference_partition={"scored": 0, "confident_unscored": 0, "not_confident": 2,
                                                       "rejected": 0, "unmatched": 48}))
    row = next(line for line in text.splitlines() if line.startswith("vs reference track"))
    assert "n/a: only 2 of 50 scans matched the map" in row
    parts = next(line for line in text.splitlines() if line.startswith("yardstick scans"))
    assert "50 = 0 scored + 2 matched but not confident + 48 unmatched" in parts
    text = summary_table(_metrics(reference_unscored_reason="the yardstick could not start: too few scans"))
    assert "n/a: the yardstick could not start: too few scans" in text


def test_published_errors_are_reference_metrics_own_figures():
    from localization.eval.reference import ReferenceTrack, reference_metrics
    from localization.eval.replay import published_errors
    rng = np.random.default_rng(3)
    k = 200
    t = np.arange(k) * 0.025
    poses = np.column_stack([0.5 * t, 0.1 * np.sin(t), 0.05 * t])
    cov = np.tile(np.eye(3) * 1e-4, (k, 1, 1))
    good = rng.random(k) < 0.8
    ref = ReferenceTrack(t=t, poses=poses, laser_poses=poses, matched=poses, information=cov, covariance=cov,
                         std_along=np.full(k, 0.01), std_cross=np.full(k, 0.01), score=rng.random(k),
                         usable=good | (rng.random(k) < 0.5), accepted=good, constrained=np.ones((k, 5), dtype=bool),
                         good=good, counts={"scans": k})
    est_t = np.arange(0.01, 5.0, 0.02)  # the published poses: their own times, off the scans'
    est = np.column_stack([0.5 * est_t + 0.01, 0.1 * np.sin(est_t) - 0.02, 0.05 * est_t])
    full = reference_metrics(ref, est_t, est)
    mine = published_errors(ref, est_t, est)
    assert mine["published_reference_error_m"] == full["reference_error_m"]
    assert mine["published_along_track_error_m"] == full["along_track_error_m"]
    assert mine["published_reference_error_m"]["median"] > 0
