"""The filter's compiled passes (core/filter/kernels.py) against their numpy references (core/filter/mcl.py),
and a sensor update in steady state that allocates nothing growing with the particles."""
from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
from helpers import corridor_map

from localization.core.filter import kernels as K
from localization.core.filter.mcl import estimate_of, estimate_of_numpy, weigh_numpy
from localization.core.localizer import Localizer
from localization.core.odometry import TwistData
from localization.core.parameters import Parameters
from localization.core.scan import ScanData

pytestmark = pytest.mark.skipif(K.weigh_kernel is None, reason="numba is pinned: the kernels exist")


def cloud(n=3000, seed=0, spread=(0.3, 0.2, 0.4), heading=3.0):
    """Particles around a heading near ±π (the circular mean and the wrap matter) and log weights with -inf."""
    rng = np.random.default_rng(seed)
    particles = np.column_stack([rng.normal(12.0, spread[0], n), rng.normal(-4.0, spread[1], n),
                                 np.angle(np.exp(1j * rng.normal(heading, spread[2], n)))])
    log_w = rng.normal(0.0, 3.0, n)
    log_w[::13] = -np.inf
    return particles, log_w - np.logaddexp.reduce(log_w)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_weighing_equals_its_numpy_reference(seed):
    _, log_w = cloud(seed=seed)
    log_f = np.random.default_rng(seed + 10).normal(-40.0, 5.0, log_w.size)
    log_f[::7] = -np.inf
    out, weights = np.empty_like(log_w), np.empty_like(log_w)
    norm, squares = K.weigh_kernel(log_w, log_f, out, weights)
    ref, ref_norm = weigh_numpy(log_w, log_f)
    assert norm == pytest.approx(ref_norm, rel=1e-13)
    assert np.array_equal(np.isneginf(out), np.isneginf(ref))
    finite = np.isfinite(ref)
    np.testing.assert_allclose(out[finite], ref[finite], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(weights, np.exp(ref), rtol=1e-12, atol=1e-300)
    assert squares == pytest.approx(np.dot(np.exp(ref), np.exp(ref)), rel=1e-12)
    # every particle impossible, or a NaN: nothing to use (the filter keeps its weights)
    assert np.isnan(K.weigh_kernel(log_w, np.full(log_w.size, -np.inf), out, weights)[0])
    assert weigh_numpy(log_w, np.full(log_w.size, -np.inf)) is None
    bad = log_f.copy()
    bad[5] = np.nan
    assert np.isnan(K.weigh_kernel(log_w, bad, out, weights)[0])


@pytest.mark.parametrize("seed, spread", [(0, (0.3, 0.2, 0.4)), (1, (0.02, 0.01, 0.01)), (2, (8.0, 5.0, 3.0))])
def test_the_estimate_equals_its_numpy_reference(seed, spread):
    particles, log_w = cloud(seed=seed, spread=spread)
    fast, ref = estimate_of(particles, log_w), estimate_of_numpy(particles, log_w)
    np.testing.assert_allclose(fast.pose, ref.pose, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(fast.covariance, ref.covariance, rtol=1e-10, atol=1e-14)
    uniform = np.full(len(particles), -np.log(len(particles)))  # after a resampling
    np.testing.assert_allclose(estimate_of(particles, uniform).covariance,
                               estimate_of_numpy(particles, uniform).covariance, rtol=1e-10, atol=1e-14)


def test_a_steady_sensor_update_allocates_nothing_that_grows_with_the_particles():
    """After a few scans, a scan's sensor update (move, weigh, resample, estimate, decide) allocates less than
    one array of the particles' size: the filter writes into arrays it keeps."""
    n = 20000
    loc = Localizer(Parameters(num_particles=n, random_seed=1, ray_caster="lookup_table", num_beams_per_particle=60,
                               update_min_distance=0.0, update_min_angle=0.0, range_scale_estimation=False))
    loc.set_map(corridor_map())
    loc.set_initial_pose([2.0, 1.5, 0.0], np.diag([0.01, 0.01, 0.001]), stamp=1.0)
    angles = np.linspace(-2.0, 2.0, 181)
    ranges = np.minimum(np.abs(1.0 / np.sin(angles + 1e-9)), 6.0)  # walls 1 m to either side, roughly

    def scan(k: int):
        t = 1.0 + 0.025 * k
        loc.on_odometry(TwistData(t, 1.0, 0.0, 0.0))
        return loc.on_scan(ScanData(t, ranges, angles[0], angles[-1], angles[1] - angles[0], 0.05, 10.0))

    for k in range(1, 8):  # the first scans: the tempered update, the arrays made once
        scan(k)
    tracemalloc.start()
    try:
        peaks = []
        for k in range(8, 14):
            tracemalloc.reset_peak()
            before = tracemalloc.get_traced_memory()[0]
            assert scan(k).cost.particles == n  # a sensor update ran
            peaks.append(tracemalloc.get_traced_memory()[1] - before)
    finally:
        tracemalloc.stop()
    assert max(peaks) < n * 8, peaks  # less than one (N,) float array


def test_the_agreement_equals_its_numpy_reference():
    """The scan-map agreement (health.AgreementScorer.score, one compiled pass over the beams) and its numpy
    reference, on a real map, poses in and off it, beams with no return, out of limits and non-finite."""
    from localization.core.localizer.health import AgreementScorer
    from localization.core.occupancy_map import load_map
    stata = load_map("basement_fixed")
    scorer = AgreementScorer(stata, (0.19, 0.01, 0.02), range_scale=0.9993)
    rng = np.random.default_rng(7)
    angles = np.linspace(-2.35, 2.35, 1081)
    poses = np.vstack([stata.sample_free_poses(50, rng), [[1e4, 0.0, 0.0], [np.nan, 0.0, 0.0]]])
    caster_ranges = rng.uniform(0.1, 12.0, (len(poses), angles.size))
    caster_ranges[:, ::11] = np.inf
    caster_ranges[:, 5::13] = np.nan
    scored = 0
    for pose, ranges in zip(poses, caster_ranges):
        fast = scorer.score(pose, ranges, angles, 0.06, 10.0)
        ref = scorer.score_numpy(pose, ranges, angles, 0.06, 10.0)
        assert fast == ref or (np.isnan(fast) and np.isnan(ref))
        scored += bool(fast > 0)
    assert scored > 20
    assert np.isnan(scorer.score(poses[0], np.full(10, np.inf), angles[:10], 0.06, 10.0))


def test_the_motion_noise_factor_equals_its_numpy_reference():
    """MotionModel's noise factor (eigenvectors × √eigenvalues, compiled) is numpy's, bit for bit."""
    from localization.core.models.motion import noise_factor, noise_factor_numpy
    rng = np.random.default_rng(1)
    for k in range(500):
        m = rng.normal(size=(3, 3))
        cov = m @ m.T * 10 ** rng.uniform(-9, 0)
        if k % 5 == 0:  # a still axis, and rounding below zero
            cov[2, :] = cov[:, 2] = 0.0
        factor = noise_factor(cov)
        assert np.array_equal(factor, noise_factor_numpy(cov))
        np.testing.assert_allclose(factor @ factor.T, cov, rtol=1e-9, atol=1e-12 * np.abs(cov).max())


@pytest.mark.parametrize("deterministic,robot", [(False, "ackermann"), (True, "ackermann"), (False, "differential"),
                                                 (False, "omni")])
def test_the_pieces_in_one_pass_move_as_piece_by_piece(deterministic, robot):
    """MotionModel.evaluate_pieces (one compiled call: the noise factors, the draws, one pass over the cloud) moves a
    cloud as evaluate() piece by piece, bit for bit, with the same draws: standing pieces (no noise), a standing piece
    that slips, slips, sideways motion (dropped by a differential base), turns, the heading wrapping."""
    from localization.core.models.motion import MotionModel
    particles, _ = cloud(n=500, seed=3)
    pieces = np.array([[0.04, 0.0, 0.01], [0.0, 0.0, 0.0], [0.05, 0.002, -0.3], [0.03, 0.0, 3.0], [0.0, 0.0, 0.0],
                       [0.02, -0.01, 0.0]])
    slips = np.array([[0.0, 0.0], [0.0, 0.0], [0.01, 1e-4], [0.0, 0.0], [0.002, 1e-6], [0.0, 0.0]])
    one, many = (MotionModel(deterministic, np.random.default_rng(9), robot_model_type=robot) for _ in range(2))
    ref = particles.copy()
    for piece, (slip, var) in zip(pieces, slips):
        one.evaluate(ref, piece, out=ref, slip=slip, slip_var=var)
    fast = many.evaluate_pieces(particles, pieces, slips, noise_out=np.empty((6, 500, 3)))
    assert np.array_equal(fast, ref)
    assert one.rng.random() == many.rng.random()  # the same number of draws
