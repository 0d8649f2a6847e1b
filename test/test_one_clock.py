"""One clock in the core: late odometry waits, carried poses follow dead reckoning on the corrected
clock, and what goes out never goes back in time."""
from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np
import pytest
from helpers import corridor_map, localize_recording

from localization.core.geometry import compose, integrate_twist
from localization.core.localizer import Localizer
from localization.core.odometry import TwistData
from localization.core.parameters import Parameters
from localization.core.paths import config_dir
from localization.eval.datasets import trial_config
from localization.eval.feed import Feeder
from localization.sim import recorder as S

_STATA = {}


def load_stata():
    if "m" not in _STATA:
        from localization.core.occupancy_map import load_map
        _STATA["m"] = load_map("stata_basement")
    return _STATA["m"]


def _drive(latency: float):
    """A 3 m/s drive down the diagonal corridor, odometry ``latency`` s late (its stamps)."""
    if latency not in _STATA:
        cfg = replace(trial_config("trial1_noise0"), speed=3.0, duration=5.0, odom_latency=latency, odom_noise=0.1,
                      sweep=True)
        _STATA[latency] = S.simulate(cfg, load_stata())
    return _STATA[latency]


def _localize(rec, seed: int, **params):
    p = Parameters.from_yaml(config_dir() / "params.yaml", num_particles=500, random_seed=seed, **params)
    log, err = localize_recording(rec, p, load_stata())
    return log, float(err.ct_error[err.t > 1.0].mean())


SEEDS = (1, 2, 3)  # the mean error over a few filter seeds (one run's varies by ~10 %)


@pytest.mark.parametrize("latency", [0.15, 0.30])
def test_late_odometry_with_its_offset_localizes_as_well_as_none(latency, caplog):
    if "free" not in _STATA:
        runs = [_localize(_drive(0.0), s) for s in SEEDS]
        _STATA["free"] = float(np.mean([err for _, err in runs])), runs[0][0].counts["sensor_updates"]
    free_err, free_updates = _STATA["free"]
    late_errs = []
    for seed in SEEDS:
        with caplog.at_level(logging.WARNING):
            log, err = _localize(_drive(latency), seed, odom_time_offset=-latency)
        late_errs.append(err)
        # every scan used, as without latency (the update policy may skip one while the car starts from rest)
        assert log.counts["sensor_updates"] >= free_updates - 1 >= log.counts["scans"] - 3, log.counts
        assert np.all(np.diff(log.est_t) >= 0)
    assert caplog.text.count("extrapolated") <= 1  # only the last scans of the recording (flushed at its end)
    assert np.mean(late_errs) <= 1.1 * free_err, (late_errs, free_err)


def test_odometry_later_than_the_wait_is_used_extrapolated_and_said(caplog):
    loc = _corridor(scan_max_wait=0.1)
    for k in range(5):
        loc.on_odometry(TwistData(1.0 + 0.02 * k, 1.0, 0.0, 0.0))
    with caplog.at_level(logging.WARNING):
        assert loc.on_scan(_scan(1.10)).estimate is None  # newer than the odometry: waits
        assert loc.on_scan(_scan(1.25)).estimate is not None  # the first waited 0.15 s > 0.1 s: used, extrapolated
    assert "extrapolated" in caplog.text and loc.waiting_scans == 1


def _corridor(**overrides) -> Localizer:
    loc = Localizer(Parameters(num_particles=200, random_seed=1, ray_caster="distance_transform", deterministic=True,
                               **overrides))
    loc.set_map(corridor_map())
    loc.set_initial_pose([2.0, 1.5, 0.0])
    return loc


def _scan(stamp):
    from localization.core.scan import ScanData
    return ScanData(stamp, np.full(101, 0.9), -1.0, 1.0, 0.02, 0.02, 10.0)


def test_carried_pose_is_dead_reckoning_on_the_corrected_clock():
    """odom_time_offset 0.154, odometry at 50 Hz, 1 s without scans: no sawtooth."""
    loc = _corridor(odom_time_offset=0.154)
    v, w = 2.0, 0.3
    loc.on_odometry(TwistData(10.0, v, 0.0, w))
    loc.request_update()
    loc.on_scan(_scan(10.154))  # at the first odometry's corrected time: the anchor
    (anchor,) = loc.take_corrections()
    worst = 0.0
    for k in range(1, 51):
        t = 10.0 + 0.02 * k
        out = loc.on_odometry(TwistData(t, v, 0.0, w))
        assert out.stamp == pytest.approx(t + 0.154, abs=1e-12)
        reckoned = compose(anchor.pose, integrate_twist(v, 0.0, w, out.stamp - anchor.stamp))
        worst = max(worst, float(np.hypot(*(out.pose[:2] - reckoned[:2]))))
    assert worst < 1e-3, worst


def test_published_stamps_go_forward_with_scans_between_odometry():
    """Carried poses (odometry times) and corrections (scan times) interleave; the feed publishes a
    correction only when it is not older than the last pose out."""
    loc = _corridor()
    feeder = Feeder(loc)
    t_odom = 1.0 + 0.02 * np.arange(100)
    t_scan = 1.0 + 0.025 * np.arange(79) + 0.009
    events = sorted([(t, 0) for t in t_odom] + [(t, 1) for t in t_scan])
    for t, kind in events:
        if kind == 0:
            feeder.odometry(TwistData(float(t), 1.0, 0.0, 0.1))
        else:
            feeder.scan(_scan(float(t)))
    assert feeder.log.counts["sensor_updates"] >= 70
    assert np.all(np.diff(feeder.log.est_t) >= 0)
    ct, _ = feeder.log.corrections()
    assert np.all(np.diff(ct) > 0)
