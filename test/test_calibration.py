"""localization-calibrate on the simulated "calibration" trial: known odometry latency, speed and
yaw-rate scale, yaw-rate bias, laser mount and lidar range scale; the calibrator must recover each
as the correction the localizer applies, with skids and wheel spin rejected rather than fitted; the
scan stamp convention read from a bag's record times; a real Pioneer calibrated from its bag."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import yaml

from localization.eval.calibration import KEYS, CalibrationError, calibrate
from localization.eval.datasets import sim_bag, trial_config
from localization.tools.calibrate import main

DURATION = 20.0  # s of the trial: turns and speed changes enough for every parameter

# the calibrator's targets
TOLERANCE = {"odom_time_offset_s": 0.005, "laser_offset_x": 0.02, "laser_offset_y": 0.02,
             "laser_offset_yaw": math.radians(0.5), "map_wall_depth": 0.005}
RELATIVE = {"odom_speed_scale": 0.005, "odom_yaw_rate_scale": 0.01, "lidar_scale_to_map_scale": 0.005}


def expected(cfg) -> dict:
    """The corrections that undo the simulator's effects (conventions of localization.eval.calibration)."""
    return {"odom_time_offset_s": -cfg.odom_latency,
            "odom_speed_scale": 1.0 / cfg.speed_scale,
            "odom_yaw_rate_scale": 1.0 / cfg.yaw_rate_scale,
            "odom_yaw_rate_bias": -cfg.yaw_rate_bias / cfg.yaw_rate_scale,
            "laser_offset_x": cfg.laser_offset[0], "laser_offset_y": cfg.laser_offset[1],
            "laser_offset_yaw": cfg.laser_offset[2],
            "lidar_scale_to_map_scale": 1.0 / cfg.range_scale,
            "map_wall_depth": 0.0}  # the simulator's lidar ends its beams on the free-space edge


@pytest.fixture(scope="module")
def calibration_run(tmp_path_factory):
    bag = sim_bag("calibration", duration=DURATION)
    out = tmp_path_factory.mktemp("cal") / "car.yaml"
    import contextlib
    import io
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = main([str(bag), "--map", "stata_basement", "--odom-topic", "/odom", "--json", "--out", str(out)])
    return code, buf.getvalue(), out


def test_cli_json_has_exactly_the_keys(calibration_run):
    code, stdout, _ = calibration_run
    assert code == 0
    d = json.loads(stdout)
    assert set(KEYS) <= set(d)
    assert all(isinstance(d[k], float) and math.isfinite(d[k]) for k in KEYS)
    assert set(d["uncertainty"]) == set(KEYS) and all(v > 0 for v in d["uncertainty"].values())


def test_recovers_the_simulated_car(calibration_run):
    _, stdout, _ = calibration_run
    d = json.loads(stdout)
    cfg = trial_config("calibration", duration=DURATION)
    want = expected(cfg)
    assert cfg.odom_latency > 0 and cfg.range_scale != 1.0 and cfg.laser_offset[1] != 0  # the trial has effects
    for k, tol in TOLERANCE.items():
        assert abs(d[k] - want[k]) <= tol, (k, d[k], want[k])
    for k, tol in RELATIVE.items():
        assert abs(d[k] / want[k] - 1.0) <= tol, (k, d[k], want[k])
    assert abs(d["odom_yaw_rate_bias"] - want["odom_yaw_rate_bias"]) <= 0.01
    # the stated uncertainty is honest: errors within 4 sigma
    for k in KEYS:
        assert abs(d[k] - want[k]) <= 4 * d["uncertainty"][k] + 1e-4, (k, d[k], want[k], d["uncertainty"][k])


def test_out_writes_a_parameter_fragment(calibration_run):
    _, stdout, out = calibration_run
    d = json.loads(stdout)
    doc = yaml.safe_load(out.read_text())
    p = doc["particle_filter"]["ros__parameters"]
    assert p["odom_time_offset"] == pytest.approx(d["odom_time_offset_s"], rel=1e-5)
    assert p["lidar_scale_to_map_scale"] == pytest.approx(d["lidar_scale_to_map_scale"], rel=1e-5)
    assert {"odom_speed_scale", "odom_yaw_rate_scale", "odom_yaw_rate_bias", "laser_offset_x", "laser_offset_y",
            "laser_offset_yaw"} <= set(p)


def test_too_little_data_is_one_clear_error():
    with pytest.raises(CalibrationError, match="too few"):
        calibrate([], [], [], None, (0.0, 0.0, 0.0))


def test_cli_missing_bag(tmp_path, capsys):
    assert main([str(tmp_path / "nope"), "--map", "stata_basement"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "bag not found" in err[0]


# ------------------------------------------------------------------ slips, channels, stamps, a Pioneer


def _channels_loop(odom_t, twist, a, b, c, dv, dw):
    """Reference of dead_reckon_channels at its own breakpoints: one piece at a time."""
    from localization.core.geometry import compose, integrate_twist
    tv, tr = odom_t + dv, odom_t + dw
    br = np.unique(np.concatenate([tv, tr]))
    out = [np.zeros(3)]
    for lo, hi in zip(br[:-1], br[1:]):
        m = 0.5 * (lo + hi)
        kv = min(max(int(np.searchsorted(tv, m)), 1), len(tv) - 1)
        kw = min(max(int(np.searchsorted(tr, m)), 1), len(tr) - 1)
        out.append(compose(out[-1], integrate_twist(a * twist[kv, 0], a * twist[kv, 1], b * twist[kw, 2] + c,
                                                    hi - lo)))
    return br, np.array(out)


def test_dead_reckon_channels_equals_its_loop_and_the_shifted_dead_reckon():
    from localization.eval.calibration import dead_reckon_channels
    from localization.eval.reference import dead_reckon
    rng = np.random.default_rng(4)
    t = np.cumsum(rng.uniform(0.015, 0.025, 300))
    tw = rng.normal(size=(300, 3)) * [2.0, 0.05, 1.0]
    br, ref = _channels_loop(t, tw, 1.04, 0.9, 0.01, -0.045, 0.15)
    np.testing.assert_allclose(dead_reckon_channels(t, tw, br, 1.04, 0.9, 0.01, -0.045, 0.15), ref, atol=1e-9)
    q = np.sort(rng.uniform(t[0] - 0.2, t[-1] + 0.2, 500))
    np.testing.assert_allclose(dead_reckon_channels(t, tw, q, 1.04, 0.9, 0.01, 0.03, 0.03),
                               dead_reckon(t, tw, q - 0.03, 1.04, 0.9, 0.01), atol=1e-9)


def test_skid_and_wheel_spin_are_rejected_not_fitted():
    """The calibration trial with the odometry reading 0 for 0.4 s twice while the car keeps going
    (a braking skid) and 1.8 x the speed for 0.2 s (wheel spin): the rejected stretches cover them, and
    the offset and speed scale stay those of the simulated car."""
    from localization.core.occupancy_map import load_map
    from localization.core.scan import ScanData
    from localization.eval.calibration import calibrate
    from localization.sim import simulate
    cfg = trial_config("calibration", duration=DURATION)
    m = load_map(cfg.map)
    rec = simulate(cfg, m)
    ot, tw = rec.odometry.t, rec.odometry.twist.copy()
    windows = [(6.0, 6.4), (13.0, 13.4)]
    for lo, hi in windows:
        tw[(ot >= lo) & (ot < hi), 0] = 0.0
    spin = (ot >= 17.0) & (ot < 17.2)
    tw[spin, 0] *= 1.8
    assert np.all(rec.odometry.twist[(ot >= 6.0) & (ot < 6.4), 0] > 1.5)  # the car does drive there
    scans = [ScanData(float(t), r, cfg.angle_min, cfg.angle_max, rec.scan_angle_increment, cfg.range_min,
                      cfg.range_max, rec.scan_time_increment) for t, r in zip(rec.scan_t, rec.scan_ranges)]
    res = calibrate(scans, ot, tw, m, rec.initial_pose, mount0=(0.275, 0.0, 0.0))
    want = expected(cfg)
    assert abs(res.values["odom_time_offset_s"] - want["odom_time_offset_s"]) <= 0.008, res.as_dict()
    assert abs(res.values["odom_speed_scale"] / want["odom_speed_scale"] - 1.0) <= 0.01, res.as_dict()
    t0 = float(rec.scan_t[0])
    intervals = [(a + t0, b + t0) for a, b in res.rejected["intervals_s"]]
    for lo, hi in windows + [(17.0, 17.2)]:
        assert any(a <= hi and b >= lo for a, b in intervals), (lo, hi, intervals)
    assert 0.8 <= res.rejected["seconds"] <= 6.0, res.rejected


def _stamp_bag(path, lead_s: float, sweep_s: float):
    from localization.bags import BagWriter, make_laser_scan
    n = 1081
    with BagWriter(path) as w:
        for k in range(50):
            stamp = 1_700_000_000_000_000_000 + k * 25_000_000
            rec = stamp + int(lead_s * 1e9) + (k % 5) * 1_000_000  # transport jitter on top
            w.write("/scan", rec, make_laser_scan(w.typestore, stamp, "laser", np.ones(n), angle_min=-2.35,
                                                  angle_max=2.35, angle_increment=4.7 / (n - 1), range_min=0.02,
                                                  range_max=30.0, time_increment=sweep_s / (n - 1)))


@pytest.mark.parametrize("lead, convention", [(-0.0002, "last_beam"), (0.005, "last_beam"), (0.021, "first_beam")])
def test_scan_stamp_convention_from_the_record_times(tmp_path, lead, convention):
    """Record time − stamp below the sweep (18.75 ms) means the stamp is at or after the last beam."""
    from localization.eval.calibration import check_scan_stamps
    path = tmp_path / "stamps"
    _stamp_bag(path, lead, 0.01875)
    check = check_scan_stamps(path, "/scan")
    assert check.convention == convention and check.lead_p1_s == pytest.approx(lead, abs=1e-6)
    assert check.sweep_s == pytest.approx(0.01875)
    line = check.message("first_beam")
    assert convention in line and (convention == "first_beam" or "the parameters say first_beam" in line)


@pytest.mark.parametrize("name", ["bag1", "bag2", "bag3", "trace0", "trace1", "lgfloor2"])
def test_real_bags_stamp_conventions(name):
    """The conventions the data sets state are what the bags' record times say (docs/timing.md)."""
    from localization.eval.calibration import check_scan_stamps
    from localization.eval.datasets import real_bag, real_bag_path
    rb = real_bag(name)
    check = check_scan_stamps(real_bag_path(name), rb.scan_topic)
    assert check.convention == rb.scan_stamp, check
    if rb.folder == "rss2022":
        assert -0.001 < check.lead_p1_s < 0.0  # urg_node: the stamp ~0.2 ms after the bag recorded the scan


def test_calibrates_a_pioneer_from_its_bag():
    """trace0 (Pioneer 3-DX, URG-04LX: 726 beams, 5.6 m, 10 Hz; odometry 10 Hz): the calibrator finds
    the laser where the bag's TF puts it (x = 0.135 m), a range scale of 1 and a yaw-rate scale near 1."""
    from localization.core.occupancy_map import load_map
    from localization.eval.calibration import calibrate_bag
    from localization.eval.datasets import real_bag, real_bag_path
    rb = real_bag("trace0")
    res = calibrate_bag(real_bag_path("trace0"), load_map(rb.map), rb.scan_topic, rb.odom_topic, rb.start,
                        (0.135, 0.0, 0.0), scan_stamp="last_beam")
    d = res.as_dict()
    assert res.good_scans > 0.7 * res.scans, d  # the later part of the drive: a changed building
    assert abs(d["laser_offset_x"] - 0.135) < 0.03 and abs(d["laser_offset_y"]) < 0.03, d
    assert abs(d["lidar_scale_to_map_scale"] - 1.0) < 0.015 and abs(d["odom_speed_scale"] - 1.0) < 0.05, d
    assert 0.9 < d["odom_yaw_rate_scale"] < 1.2 and abs(d["odom_time_offset_s"]) < 0.15, d
    assert 0 < d["rejected"]["share"] < 0.3 and d["wall_surface"]["offset_m"] == pytest.approx(0.02, abs=0.015)
