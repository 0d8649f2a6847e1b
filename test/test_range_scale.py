"""The online range-scale estimate (core/range_scale.py): the per-scan least-squares ratio ŝ through a gate
that drops unmapped obstacles and glass, and the filtered, bounded scale the beam model uses."""
from __future__ import annotations

import logging

import numpy as np
import pytest

from localization.core.localizer import Localizer
from localization.core.parameters import Parameters
from localization.core.range_scale import MAX_SPREAD_M, MIN_BEAMS, RangeScaleEstimator, estimate_scale


def scan_pair(true_scale: float, n: int = 200, outliers: float = 0.2, seed: int = 0, wall_depth: float = 0.0):
    """Ranges ray cast in the map ``d`` (0.5-9 m) and measured ranges ``z`` of a lidar that reads 1/true_scale
    of the map's metres (d + wall_depth = true_scale·z), 1 cm noise; ``outliers`` of the beams hit something
    unmapped (half shorter, half longer: people and glass)."""
    rng = np.random.default_rng(seed)
    d = rng.uniform(0.5, 9.0, n)
    z = (d + wall_depth) / true_scale + rng.normal(0.0, 0.01, n)
    bad = rng.random(n) < outliers
    z[bad] = np.where(rng.random(bad.sum()) < 0.5, z[bad] * rng.uniform(0.2, 0.7, bad.sum()),
                      z[bad] + rng.uniform(1.0, 5.0, bad.sum()))
    return z, d, bad


@pytest.mark.parametrize("true_scale", [0.98, 0.99, 1.0, 1.015])
def test_one_scan_recovers_a_known_scale_past_obstacles_and_glass(true_scale):
    z, d, bad = scan_pair(true_scale)
    s, used = estimate_scale(z, d, 1.0)
    assert s == pytest.approx(true_scale, abs=1e-3)
    assert used <= np.count_nonzero(~bad) + 2 and used >= 0.9 * np.count_nonzero(~bad)  # the gate drops the outliers
    naive = float(np.dot(z, d) / np.dot(z, z))  # no gate: the outliers bias it
    assert abs(naive - true_scale) > 5e-3


def test_the_wall_depth_is_moved_to_the_map_side():
    z, d, _ = scan_pair(0.99, outliers=0.0, wall_depth=0.025)
    assert estimate_scale(z, d, 1.0, wall_depth=0.025)[0] == pytest.approx(0.99, abs=1e-3)
    assert abs(estimate_scale(z, d, 1.0)[0] - 0.99) > 1e-3  # ignoring it biases the scale


def test_no_beam_in_the_gate_gives_nan():
    s, used = estimate_scale([5.0, 6.0], [1.0, 1.5], 1.0)
    assert np.isnan(s) and used == 0


def test_the_filtered_scale_converges_stays_bounded_and_resets():
    est = RangeScaleEstimator(prior=1.0, alpha=0.1, bound=0.05)
    for k in range(80):
        z, d, _ = scan_pair(0.985, seed=k)
        assert est.update(z, d, 0.05, 30.0, 10.0)
    assert est.scale == pytest.approx(0.985, abs=1e-3) and est.updates == 80
    far = RangeScaleEstimator(prior=1.0, alpha=1.0, bound=0.01)
    z, d, _ = scan_pair(0.985, outliers=0.0)
    assert far.update(z, d, 0.05, 30.0, 10.0) and far.scale == pytest.approx(0.99)  # clipped to s0 (1 - bound)
    est.reset()
    assert est.scale == 1.0 and est.updates == 0


def test_a_spread_cloud_or_too_few_beams_do_not_move_the_scale():
    est = RangeScaleEstimator(alpha=1.0)
    z, d, _ = scan_pair(0.98)
    wide = np.diag([(2 * MAX_SPREAD_M) ** 2, 0.01, 0.01])
    assert not est.update(z, d, 0.05, 30.0, 10.0, covariance=wide)
    assert not est.update(z[:MIN_BEAMS - 1], d[:MIN_BEAMS - 1], 0.05, 30.0, 10.0)
    nan_cov = np.full((3, 3), np.nan)
    assert not est.update(z, d, 0.05, 30.0, 10.0, covariance=nan_cov)
    beyond = d > 8.0  # only beams beyond the model's reach (8 m) and the lidar's range_max: none is used
    assert not est.update(np.where(beyond, z, np.inf), d, 0.05, 30.0, 8.0)
    assert est.scale == 1.0 and est.updates == 0


def test_the_likelihood_field_ignores_it_with_one_log_line(caplog):
    with caplog.at_level(logging.WARNING):
        loc = Localizer(Parameters(sensor_model="likelihood_field", range_scale_estimation=True))
    assert loc.range_scale == loc.params.lidar_scale_to_map_scale and not loc.range_scale_online
    assert Localizer(Parameters(range_scale_estimation=True)).range_scale_online
    assert sum("range_scale_estimation" in r.getMessage() for r in caplog.records) == 1
