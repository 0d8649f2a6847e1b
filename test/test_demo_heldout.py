"""localization-demo's held-out protocol (each real bag scored with parameters calibrated on the
other bags only), its Pioneer figures and its ``--only`` options."""
from __future__ import annotations

import numpy as np
import pytest

from localization.core.parameters import Parameters
from localization.core.paths import config_dir
from localization.tools import demo as D
from localization.tools.demo import heldout


def _jobs(overrides=()):
    """The RSS bags' replays as the job table has them (the fields the tuning reads)."""
    return [D.Job(b, "real", "basement_fixed", "real_params.yaml", tuple(overrides)) for b in ("bag1", "bag2", "bag3")]


def _fake_calibrator(table):
    calls = []

    def calibrate(name):
        calls.append(name)
        return table[name]
    return calibrate, calls


TABLE = {b: {"odom_time_offset_s": 0.1 * 3 ** i, "odom_speed_scale": 1.0 + 0.01 * 3 ** i,
             "odom_yaw_rate_scale": 1.0 - 0.02 * 3 ** i, "odom_yaw_rate_bias": 0.001 * 3 ** i,
             "laser_offset_x": 0.2 + 0.01 * 3 ** i,
             "lidar_scale_to_map_scale": 1.0 - 0.001 * 3 ** i, "map_wall_depth": 0.01 * 2 ** i,
             "laser_offset_y": 9.0}
         for i, b in enumerate(("bag1", "bag2", "bag3"))}  # no bag's fold mean equals the all-bags mean


def test_heldout_fold_never_uses_its_own_bag():
    calibrate, calls = _fake_calibrator(TABLE)
    folds = D.heldout_folds(["bag1", "bag2", "bag3"], calibrate)
    assert sorted(folds) == ["bag1", "bag2", "bag3"]
    for k, fold in folds.items():
        others = [b for b in TABLE if b != k]
        assert fold["calibrated_on"] == others and k not in fold["calibrated_on"]
        for key, param in D.HELDOUT_KEYS.items():
            assert fold[param] == pytest.approx(np.mean([TABLE[b][key] for b in others]))
            assert fold[param] != pytest.approx(np.mean([TABLE[b][key] for b in TABLE]))  # not the all-bags value
        assert "laser_offset_y" not in fold  # only what the parameter file takes from calibration
    assert sorted(calls) == ["bag1", "bag2", "bag3"]  # each bag calibrated once


def test_heldout_fold_of_a_bag_changes_only_with_the_other_bags():
    # the held-out bag's own calibration may be anything: its fold does not move
    wild = {**TABLE, "bag2": {k: (v * 100 if isinstance(v, float) else v) for k, v in TABLE["bag2"].items()}}
    a = D.heldout_folds(["bag1", "bag2", "bag3"], _fake_calibrator(TABLE)[0])
    b = D.heldout_folds(["bag1", "bag2", "bag3"], _fake_calibrator(wild)[0])
    assert a["bag2"] == b["bag2"]
    assert a["bag1"]["odom_time_offset"] != pytest.approx(b["bag1"]["odom_time_offset"])


def test_heldout_keys_are_what_the_robot_calibrates():
    # the RACECAR takes every calibrated odometry and lidar value from its bags: a fold replaces them all
    assert set(D.heldout_keys("real_params.yaml").values()) == {
        "odom_time_offset", "odom_speed_scale", "odom_yaw_rate_scale", "odom_yaw_rate_bias", "laser_offset_x",
        "lidar_scale_to_map_scale", "map_wall_depth"}
    # the Pioneer's laser mount comes from its bags' TF and its wall depth is pinned: a fold leaves them
    pioneer = D.heldout_keys("/somewhere/config/pioneer_params.yaml")
    assert "laser_offset_x" not in pioneer.values() and "map_wall_depth" not in pioneer.values()
    assert "odom_yaw_rate_scale" in pioneer.values()
    folds = D.heldout_folds(["bag1", "bag2", "bag3"], _fake_calibrator(TABLE)[0], pioneer)
    assert "map_wall_depth" not in folds["bag1"] and "odom_yaw_rate_bias" in folds["bag1"]


def test_calibration_table_shows_each_bag_alone_and_held_out():
    folds = D.heldout_folds(["bag1", "bag2", "bag3"], _fake_calibrator(TABLE)[0])
    lines = D.calibration_table(TABLE, folds).splitlines()
    assert len(lines) == 1 + 2 * 3
    assert lines[1].split()[:2] == ["bag1", "alone"] and lines[2].split()[0] == "held-out"
    assert "(from bag2, bag3)" in lines[2]
    assert "yaw scale" in lines[0] and "wall depth" in lines[0]
    assert f"{TABLE['bag1']['odom_yaw_rate_scale']:.4f}" in lines[1]
    assert f"{folds['bag1']['odom_yaw_rate_scale']:.4f}" in lines[2]


def test_heldout_needs_two_bags():
    with pytest.raises(ValueError):
        D.heldout_folds(["bag1"], _fake_calibrator(TABLE)[0])


def test_only_options_parse():
    ap = D.build_parser()
    assert ap.parse_args(["--only", "heldout"]).only == "heldout"
    assert ap.parse_args(["--only", "pioneer"]).only == "pioneer"
    assert ap.parse_args([]).only is None
    with pytest.raises(SystemExit):
        ap.parse_args(["--only", "everything"])


def test_only_refuses_an_occupied_out_before_any_work(tmp_path, capsys):
    (tmp_path / "x").write_text("taken")
    assert D.main(["--only", "pioneer", "--out", str(tmp_path)]) == 1
    assert "--out" in capsys.readouterr().err


def test_converge_time_is_when_the_error_stays_below():
    t = np.arange(10.0)
    err = np.array([3.0, 0.2, 0.9, 0.3, 0.2, 0.1, np.nan, 0.1, 0.2, 0.1])
    assert D.converge_time(t, err, 0.5, 0.0) == pytest.approx(3.0)  # 0.2 at t=1 does not count: 0.9 after it
    assert D.converge_time(t, err, 0.5, 2.5) == pytest.approx(0.5)
    # a later excursion does not undo a convergence that held for `hold` seconds ...
    assert D.converge_time(t, np.r_[err[:-1], 0.8], 0.5, 0.0, hold=5.0) == pytest.approx(3.0)
    # ... a shorter stay does not count
    assert D.converge_time(t, np.r_[err[:-1], 0.8], 0.5, 0.0, hold=7.0) is None
    assert D.converge_time(t, np.full(10, 0.9), 0.5, 0.0) is None  # never within
    assert D.converge_time(t, np.full(10, 0.1), 0.5, 0.0) == 0.0


def test_status_counter_counts_the_holding_scans():
    from localization.core.localizer.recovery import HOLDING, TRACKING

    class Loc:
        status = TRACKING
    c, loc = D.StatusCounter(), Loc()
    for s in (TRACKING, HOLDING, HOLDING, TRACKING):
        loc.status = s
        c(None, loc)
    assert (c.scans, c.holding) == (4, 2)


# ------------------------------------------------------------------ held-out tuning (--heldout-tuning)
def _metrics(median, p95, along):
    return {"reference_error_m": {"median": median, "p95": p95}, "along_track_error_m": {"mean": along}}


def test_target_ratio_is_the_worst_target_share():
    assert D.target_ratio(_metrics(0.0175, 0.04, 0.005)) == pytest.approx(0.5)
    assert D.target_ratio(_metrics(0.01, 0.096, 0.0)) == pytest.approx(1.2)  # p95 over its target
    assert D.target_ratio(_metrics(0.01, 0.02, -0.03)) == pytest.approx(1.5)  # along counts both ways
    assert D.target_ratio({"reference_error_m": None}) == float("inf")  # not scored: never chosen


def test_choose_points_takes_the_lowest_training_mean_per_fold():
    scores = {("bag1", (1.0, 0.15)): [0.9, 0.5], ("bag1", (2.0, 0.10)): [0.6, 0.7],
              ("bag2", (1.0, 0.15)): [0.4, float("inf")], ("bag2", (0.5, 0.20)): [0.8, 0.8]}
    best = D.choose_points(scores)
    assert best["bag1"] == ((2.0, 0.10), pytest.approx(0.65))
    assert best["bag2"] == ((0.5, 0.20), pytest.approx(0.8))  # an unscored training bag rules a point out


def test_tuning_jobs_never_replay_a_fold_on_its_own_bag():
    folds = D.heldout_folds(["bag1", "bag2", "bag3"], _fake_calibrator(TABLE)[0])
    base = Parameters.from_yaml(config_dir() / "real_params.yaml")
    jobs = _jobs({"random_seed": 3}.items())
    out = D.tuning_jobs(jobs, folds, base, {"random_seed": 3})
    points = D.tuning_points()
    assert len(out) == 3 * len(points) * 2
    for job in out:
        k = job.fold
        assert job.label != k and job.label in folds[k]["calibrated_on"]
        ov = job.overrides
        assert ov["odom_time_offset"] == folds[k]["odom_time_offset"]  # the fold's calibration
        m, s = job.point
        assert ov["sigma_hit"] == s and ov["motion_a_trans"] == pytest.approx(base["motion_a_trans"] * m)
        assert ov["random_seed"] == 3 and job.out is None
    assert {(j.fold, j.point) for j in out} == {(k, p) for k in folds for p in points}


def test_heldout_tuning_replays_each_bag_with_its_folds_choice(monkeypatch, tmp_path):
    """A fake replay whose error depends on the grid point and the bag: each fold chooses on its two
    training bags only, and the held-out bag is replayed with that choice and its fold's calibration."""
    folds = D.heldout_folds(["bag1", "bag2", "bag3"], _fake_calibrator(TABLE)[0])
    # bag3 would favour (0.5, 0.2016) on its own; bag1 and bag2 favour (1.4, 0.1008)
    favourite = {"bag1": (1.4, 0.1008), "bag2": (1.4, 0.1008), "bag3": (0.5, 0.2016)}
    calls = []

    def fake_run_all(jobs, workers):
        calls.append(jobs)
        out = []
        for job in jobs:
            point = next(p for p in D.tuning_points()
                         if job.overrides["sigma_hit"] == p[1]
                         and job.overrides["motion_a_trans"] == pytest.approx(0.4 * p[0]))
            far = abs(np.log(point[0] / favourite[job.label][0])) + abs(point[1] - favourite[job.label][1])
            out.append(D.Result(job, _metrics(0.01 + 0.01 * far, 0.02 + 0.05 * far, 0.0)))
        return out

    monkeypatch.setattr(heldout, "run_all", fake_run_all)
    jobs = _jobs()
    table, summary, results = D.heldout_tuning(jobs, folds, config_dir() / "real_params.yaml", {}, 1, tmp_path)
    assert len(calls) == 2 and len(results) == len(calls[0]) + 3
    assert (summary["bag3"]["motion_scale"], summary["bag3"]["sigma_hit"]) == (1.4, 0.1008)  # from bag1, bag2
    assert summary["bag3"]["tuned_on"] == ["bag1", "bag2"]
    # bag1 fold sees bag2 (1.4, 0.1008) and bag3 (0.5, 0.2016): never bag1 itself
    assert all(j.label != j.fold for j in calls[0])
    final = {j.label: j for j in calls[1]}
    assert final["bag2"].overrides["odom_time_offset"] == folds["bag2"]["odom_time_offset"]
    assert final["bag3"].overrides["sigma_hit"] == 0.1008
    assert final["bag3"].out == str(tmp_path / "heldout_tuned" / "bag3")
    assert "bag3" in table and "chosen motion x" in table
