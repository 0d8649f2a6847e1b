"""localization-demo's held-out protocol (each real bag scored with parameters calibrated on the
other bags only), its Pioneer figures and its ``--only`` options."""
from __future__ import annotations

import numpy as np
import pytest

from localization.tools import demo as D


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
    from localization.core.recovery import HOLDING, TRACKING

    class Loc:
        status = TRACKING
    c, loc = D.StatusCounter(), Loc()
    for s in (TRACKING, HOLDING, HOLDING, TRACKING):
        loc.status = s
        c(None, loc)
    assert (c.scans, c.holding) == (4, 2)
