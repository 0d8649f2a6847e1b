"""localization-calibrate (issue 10, part 4) on the simulated "calibration" trial: known odometry
latency, speed and yaw-rate scale, yaw-rate bias, laser mount and lidar range scale; the
calibrator must recover each as the correction the localizer applies."""
from __future__ import annotations

import json
import math

import pytest
import yaml

from localization.eval.calibration import KEYS, CalibrationError, calibrate
from localization.eval.datasets import sim_bag, trial_config
from localization.tools.calibrate import main

DURATION = 20.0  # s of the trial: turns and speed changes enough for every parameter

# targets of issue 10
TOLERANCE = {"odom_time_offset_s": 0.005, "laser_offset_x": 0.02, "laser_offset_y": 0.02,
             "laser_offset_yaw": math.radians(0.5)}
RELATIVE = {"odom_speed_scale": 0.005, "odom_yaw_rate_scale": 0.01, "lidar_scale_to_map_scale": 0.005}


def expected(cfg) -> dict:
    """The corrections that undo the simulator's effects (conventions of localization.eval.calibration)."""
    return {"odom_time_offset_s": -cfg.odom_latency,
            "odom_speed_scale": 1.0 / cfg.speed_scale,
            "odom_yaw_rate_scale": 1.0 / cfg.yaw_rate_scale,
            "odom_yaw_rate_bias": -cfg.yaw_rate_bias / cfg.yaw_rate_scale,
            "laser_offset_x": cfg.laser_offset[0], "laser_offset_y": cfg.laser_offset[1],
            "laser_offset_yaw": cfg.laser_offset[2],
            "lidar_scale_to_map_scale": 1.0 / cfg.range_scale}


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
