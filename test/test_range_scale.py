"""The online range-scale estimate (core/localizer/range_scale.py): the per-scan least-squares ratio ŝ through a gate
that drops unmapped obstacles and glass, and the filtered, bounded scale the beam model uses."""
from __future__ import annotations

import logging

import numpy as np
import pytest
from helpers import corridor_map

from localization.core.localizer import Localizer
from localization.core.localizer.range_scale import (
    MAX_SPREAD_M,
    MIN_BEAMS,
    RangeScaleEstimator,
    estimate_scale,
    fit_scale,
    fit_step,
    fit_step_numpy,
    jacobian_poses,
    range_jacobian,
)
from localization.core.models.beam import BeamModel
from localization.core.parameters import Parameters

ORIGIN = np.zeros(3)  # the estimate handed to update() with ranges that do not depend on it


def fixed(d):
    """A ray caster that returns the ranges ``d`` from every pose: J = 0, the fit is the plain ratio."""
    return lambda poses: np.tile(np.asarray(d, dtype=float), (len(poses), 1))


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
    s, used, _ = estimate_scale(z, d, 1.0)
    assert s == pytest.approx(true_scale, abs=1e-3)
    assert used <= np.count_nonzero(~bad) + 2 and used >= 0.9 * np.count_nonzero(~bad)  # the gate drops the outliers
    naive = float(np.dot(z, d) / np.dot(z, z))  # no gate: the outliers bias it
    assert abs(naive - true_scale) > 5e-3


def test_the_wall_depth_is_moved_to_the_map_side():
    z, d, _ = scan_pair(0.99, outliers=0.0, wall_depth=0.025)
    assert estimate_scale(z, d, 1.0, wall_depth=0.025)[0] == pytest.approx(0.99, abs=1e-3)
    assert abs(estimate_scale(z, d, 1.0)[0] - 0.99) > 1e-3  # ignoring it biases the scale


def test_no_beam_in_the_gate_gives_nan():
    s, used, _ = estimate_scale([5.0, 6.0], [1.0, 1.5], 1.0)
    assert np.isnan(s) and used == 0


def test_the_filtered_scale_converges_stays_bounded_and_resets():
    est = RangeScaleEstimator(prior=1.0, alpha=0.1, bound=0.05)
    for k in range(80):
        z, d, _ = scan_pair(0.985, seed=k)
        assert est.update(z, fixed(d), ORIGIN, 0.05, 30.0, 10.0)
    assert est.scale == pytest.approx(0.985, abs=1e-3) and est.updates == 80
    far = RangeScaleEstimator(prior=1.0, alpha=1.0, bound=0.01)
    z, d, _ = scan_pair(0.985, outliers=0.0)
    assert far.update(z, fixed(d), ORIGIN, 0.05, 30.0, 10.0)
    assert far.scale == pytest.approx(0.99)  # clipped to s0 (1 - bound)
    est.reset()
    assert est.scale == 1.0 and est.updates == 0


def test_a_spread_cloud_or_too_few_beams_do_not_move_the_scale():
    est = RangeScaleEstimator(alpha=1.0)
    z, d, _ = scan_pair(0.98)
    wide = np.diag([(2 * MAX_SPREAD_M) ** 2, 0.01, 0.01])
    assert not est.update(z, fixed(d), ORIGIN, 0.05, 30.0, 10.0, covariance=wide)
    assert not est.update(z[:MIN_BEAMS - 1], fixed(d[:MIN_BEAMS - 1]), ORIGIN, 0.05, 30.0, 10.0)
    nan_cov = np.full((3, 3), np.nan)
    assert not est.update(z, fixed(d), ORIGIN, 0.05, 30.0, 10.0, covariance=nan_cov)
    beyond = d > 8.0  # only beams beyond the model's reach (8 m) and the lidar's range_max: none is used
    assert not est.update(np.where(beyond, z, np.inf), fixed(d), ORIGIN, 0.05, 30.0, 8.0)
    assert est.scale == 1.0 and est.updates == 0


def test_the_likelihood_field_ignores_it_with_one_log_line(caplog):
    with caplog.at_level(logging.INFO):
        loc = Localizer(Parameters(sensor_model="likelihood_field", range_scale_estimation=True))
    assert loc.range_scale == loc.params.lidar_scale_to_map_scale and not loc.range_scale_online
    assert Localizer(Parameters(range_scale_estimation=True)).range_scale_online
    assert sum("range_scale_estimation" in r.getMessage() for r in caplog.records) == 1


def corridor_scan(true_scale: float, estimate_error, fov: float = np.radians(270.0), n: int = 181):
    """A 10 m × 2 m corridor closed at both ends (test/helpers.corridor_map), the exact ray caster, a lidar at
    (3, 1.5, 0.1) that reads 1/true_scale of the map's metres, and an estimate off by ``estimate_error``
    (x, y, θ): (z, cast(poses) -> (k, B) ranges, the estimate, the model's reach)."""
    sm = BeamModel(ray_caster="exact", laser_offset_x=0.0)
    sm.set_map(corridor_map())
    angles = np.linspace(-fov / 2, fov / 2, n)
    truth = np.array([3.0, 1.5, 0.1])
    z = sm.expected_ranges(truth[None], angles)[0] / true_scale
    return z, lambda poses: sm.expected_ranges(poses, angles), truth + np.asarray(estimate_error), sm.table_range


def test_the_range_jacobian_is_the_derivative_of_the_ray_cast_range():
    _, cast, pose, _ = corridor_scan(1.0, (0.0, 0.0, 0.0), fov=np.radians(180.0), n=3)  # beams at -90°, 0°, +90°
    ranges = cast(jacobian_poses(pose))
    jacobian, smooth = range_jacobian(ranges)
    assert smooth.all()
    c, s = np.cos(0.1), np.sin(0.1)  # the heading: 0.1 rad
    # the beam ahead meets the end wall: d = (x_wall - x) / cos θ, so ∂d/∂x = -1/cos θ and ∂d/∂θ = d tan θ
    assert jacobian[1, 0] == pytest.approx(-1 / c, abs=0.02) and jacobian[1, 1] == pytest.approx(0.0, abs=0.02)
    assert jacobian[1, 2] == pytest.approx(ranges[0, 1] * s / c, rel=0.05)
    # the beam to the left meets the upper side wall: ∂d/∂y = -1/cos θ, nothing along x
    assert jacobian[2, 1] == pytest.approx(-1 / c, abs=0.02) and jacobian[2, 0] == pytest.approx(0.0, abs=0.02)


def test_a_corner_in_reach_is_not_smooth():
    _, cast, pose, _ = corridor_scan(1.0, (0.0, 0.0, 0.0), n=721)
    _, smooth = range_jacobian(cast(jacobian_poses(pose)))
    assert 0 < np.count_nonzero(~smooth) < 0.1 * smooth.size  # the beams near the corridor's end corners


@pytest.mark.parametrize("error", [(-0.1, 0.0, 0.0), (0.1, 0.0, 0.0), (0.0, 0.05, 0.0), (-0.05, 0.03, 0.01),
                                   (0.06, 0.0, -0.02)])
def test_fitted_with_a_pose_correction_an_estimate_error_does_not_move_the_scale(error):
    z, cast, pose, reach = corridor_scan(0.98, error)
    d = cast(pose[None])[0]
    valid = d < reach - 0.25
    ratio = estimate_scale(z[valid], d[valid], 1.0)[0]  # the estimate taken as the true pose
    assert abs(ratio - 0.98) > 1.5e-3
    joint, used = fit_scale(z, cast, pose, valid, 1.0)
    assert used >= 0.9 * np.count_nonzero(valid)
    assert joint == pytest.approx(0.98, abs=2e-4)
    est = RangeScaleEstimator(alpha=1.0)
    assert est.update(z, cast, pose, 0.05, 30.0, reach) and est.scale == pytest.approx(0.98, abs=2e-4)


def test_one_linear_fit_is_exact_for_a_shift_and_rotation_needs_the_second_step():
    z, cast, pose, reach = corridor_scan(0.98, (0.08, -0.05, 0.0))
    ranges = cast(jacobian_poses(pose))
    jacobian, smooth = range_jacobian(ranges)
    ok = smooth & (ranges[0] < reach - 0.25)
    s, _, correction = estimate_scale(z[ok], ranges[0][ok], 1.0, jacobian=jacobian[ok])
    assert s == pytest.approx(0.98, abs=5e-4) and correction == pytest.approx([-0.08, 0.05, 0.0], abs=5e-3)
    z, cast, pose, reach = corridor_scan(0.98, (0.0, 0.0, 0.02))  # ranges far along the side walls bend with θ
    valid = cast(pose[None])[0] < reach - 0.25
    assert abs(fit_scale(z, cast, pose, valid, 1.0, steps=1)[0] - 0.98) > 2e-3
    assert fit_scale(z, cast, pose, valid, 1.0, steps=2)[0] == pytest.approx(0.98, abs=2e-4)


# ------------------------------------------------------------------ the compiled pieces against their numpy references
@pytest.mark.parametrize("error, wall_depth", [((0.0, 0.0, 0.0), 0.0), ((-0.05, 0.03, 0.01), 0.025),
                                               ((0.08, -0.05, 0.0), 0.0), ((0.0, 0.0, 0.02), 0.01)])
def test_the_compiled_gauss_newton_step_equals_its_numpy_reference(error, wall_depth):
    z, cast, pose, reach = corridor_scan(0.98, error, n=361)
    z = z.copy()
    z[::17] *= 0.7  # returns short of the map (furniture): outside the gate
    ranges = cast(jacobian_poses(pose))
    valid = (ranges[0] > 0) & (ranges[0] < reach - 0.25)
    for scale in (1.0, 0.985):
        s_ref, used_ref, corr_ref = fit_step_numpy(z, ranges, valid, scale, wall_depth)
        s, used, corr = fit_step(z, ranges, valid, scale, wall_depth)
        assert used == used_ref > 100
        assert s == pytest.approx(s_ref, rel=1e-12, abs=1e-12)
        np.testing.assert_allclose(corr, corr_ref, rtol=1e-9, atol=1e-12)
    assert fit_step(z, ranges, np.zeros(z.size, dtype=bool), 1.0)[:2] == (pytest.approx(np.nan, nan_ok=True), 0)


@pytest.mark.parametrize("deskew", [False, True])
@pytest.mark.parametrize("caster", ["lookup_table", "lookup_table_exact"])
def test_the_compiled_probe_casts_as_its_numpy_reference(caster, deskew):
    """The range scale's probe casts its poses with the fused kernel's arithmetic (beam_kernels.cast_rows);
    BeamModel.expected_ranges is its numpy reference."""
    from localization.core.occupancy_map import load_map
    sm = BeamModel(ray_caster=caster, laser_offset_x=0.19, laser_offset_y=0.02, laser_offset_yaw=0.01)
    stata = load_map("basement_fixed")
    sm.set_map(stata)
    rng = np.random.default_rng(4)
    angles = np.linspace(-2.3, 2.3, 100)
    offsets = np.c_[np.linspace(0, 0.06, 100), np.linspace(0, 0.01, 100), np.linspace(0, 0.03, 100)] if deskew \
        else None
    poses = np.vstack([jacobian_poses(p) for p in stata.sample_free_poses(20, rng)] + [[[1e6, 0.0, 0.0]]])
    probe = sm.range_probe(angles, offsets, 30.0)
    got = probe.cast(poses)
    want = sm.expected_ranges(poses, angles, offsets)
    assert got.shape == want.shape == (141, 100) and (got[-1] == 0).all()
    if caster == "lookup_table_exact" and deskew:  # as the fused kernel (test_time_alignment): its exact finish
        assert np.mean(np.abs(got - want) < 1e-9) > 0.95  # marches from each beam's origin, the reference casts
    else:
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)


def test_jacobian_poses_are_the_estimate_and_its_six_shifts_bit_for_bit():
    from localization.core.localizer.range_scale import JACOBIAN_STEP_M, JACOBIAN_STEP_RAD
    steps = np.diag([JACOBIAN_STEP_M, JACOBIAN_STEP_M, JACOBIAN_STEP_RAD])
    for pose in (np.array([1.25, -3.5, 0.7]), np.array([-0.0, 0.0, -0.0]), np.array([1e6, -1e-9, -3.14159])):
        expected = np.vstack([pose, pose + steps[0], pose - steps[0], pose + steps[1], pose - steps[1],
                              pose + steps[2], pose - steps[2]])
        got = jacobian_poses(list(pose))
        assert got.shape == (7, 3) and np.array_equal(got, expected)
        assert np.array_equal(np.signbit(got), np.signbit(expected))  # signed zeros too
