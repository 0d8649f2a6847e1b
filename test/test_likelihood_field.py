"""The likelihood-field sensor model: a hand computation on a tiny map, the compiled kernels
against their numpy reference, beam skipping, parameters, and the filter built with it."""
from __future__ import annotations

import math
from dataclasses import fields

import numpy as np
import pytest
from helpers import corridor_map

from localization.core.geometry import compose
from localization.core.localizer import Localizer, build_filter
from localization.core.models.beam import BeamModel
from localization.core.models.likelihood_field import UNKNOWN_RANGE_MAX, LikelihoodFieldModel, LikelihoodFieldParams
from localization.core.occupancy_map import OccupancyMap
from localization.core.parameters import BY_NAME, Parameters
from localization.core.raycast.exact import ExactRayCaster
from localization.core.scan import ScanData

HAND = dict(lf_z_hit=0.5, lf_z_rand=0.5, lf_sigma_hit=0.2, laser_likelihood_max_dist=2.55, laser_max_range=5.0,
            squash_factor=2.0, laser_offset=(0.0, 0.0, 0.0))  # 2.55 m / 255: quanta of exactly 1 cm


def tiny_map(origin=(0.0, 0.0, 0.0)):
    """10 x 10 cells of 0.1 m, all free but one occupied cell at (row 5, col 8)."""
    data = np.zeros((10, 10), dtype=np.int8)
    data[5, 8] = 100
    return OccupancyMap(data, 0.1, origin)


def hand_log_weight():
    """Particle at the centre of cell (row 5, col 2), heading 0; beams:
    0.6 m at 0 rad   -> end in the occupied cell (row 5, col 8):      d = 0
    0.3 m at 0 rad   -> end in (row 5, col 5), 3 cells from the wall:  d = 0.3 m
    0.5 m at pi rad  -> end at x = -0.25, off the map:                 d = cap
    inf, 6.0 m (>= laser_max_range), NaN                                -> skipped"""
    def p(d):
        return 0.5 * math.exp(-d * d / (2 * 0.2 ** 2)) + 0.5 / 5.0
    return (math.log(p(0.0)) + math.log(p(0.3)) + math.log(p(2.55))) / 2.0


RANGES = np.array([0.6, 0.3, 0.5, np.inf, 6.0, np.nan])
ANGLES = np.array([0.0, 0.0, np.pi, 0.3, 0.2, 0.1])
PARTICLE = np.array([[0.25, 0.55, 0.0]])


@pytest.mark.parametrize("use_numba", [True, False])
def test_hand_computation_on_a_tiny_map(use_numba):
    model = LikelihoodFieldModel(**HAND, use_numba=use_numba, occupancy_map=tiny_map())
    got = model.log_likelihood(PARTICLE, RANGES, ANGLES)
    assert got.shape == (1,)
    assert got[0] == pytest.approx(hand_log_weight(), abs=1e-9)
    assert model.evaluate(PARTICLE, RANGES, ANGLES)[0] == pytest.approx(math.exp(hand_log_weight()), rel=1e-9)


@pytest.mark.parametrize("use_numba", [True, False])
def test_z_max_is_the_scans_range_max_unless_laser_max_range_is_set(use_numba):
    """laser_max_range <= 0: the scan's range_max is z_max (beams at or beyond it skipped, z_rand / z_max);
    laser_max_range > 0 wins over the scan's; no range_max at all: UNKNOWN_RANGE_MAX."""
    from_scan = LikelihoodFieldModel(**{**HAND, "laser_max_range": -1.0}, use_numba=use_numba,
                                     occupancy_map=tiny_map())
    assert from_scan.log_likelihood(PARTICLE, RANGES, ANGLES, range_max=5.0)[0] == pytest.approx(
        hand_log_weight(), abs=1e-9)
    assert from_scan.max_range == UNKNOWN_RANGE_MAX and from_scan.max_range_for(5.0) == 5.0
    fixed = LikelihoodFieldModel(**HAND, use_numba=use_numba, occupancy_map=tiny_map())
    assert fixed.log_likelihood(PARTICLE, RANGES, ANGLES, range_max=8.0)[0] == pytest.approx(
        hand_log_weight(), abs=1e-9)
    # with z_max 8 m the 6 m beam counts (its end point off the map: the cap) and z_rand / 8 changes every beam
    wide = from_scan.log_likelihood(PARTICLE, RANGES, ANGLES, range_max=8.0)[0]
    p8 = [0.5 * math.exp(-d * d / (2 * 0.2 ** 2)) + 0.5 / 8.0 for d in (0.0, 0.3, 2.55, 2.55)]
    assert wide == pytest.approx(sum(math.log(v) for v in p8) / 2.0, abs=1e-9)


def test_laser_offset_and_a_rotated_map_give_the_same_hand_value():
    # the same geometry with the laser 0.1 m ahead of base_link: base_link one cell back
    model = LikelihoodFieldModel(**{**HAND, "laser_offset": (0.1, 0.0, 0.0)}, occupancy_map=tiny_map())
    assert model.log_likelihood([[0.15, 0.55, 0.0]], RANGES, ANGLES)[0] == pytest.approx(hand_log_weight(), abs=1e-9)
    # the map rotated by pi about the world origin (as the Stata basement's origin yaw): cell corner (0, 0)
    # at world (1, 1), grid axes pointing to -x, -y; the particle and its heading rotate with it
    rotated = LikelihoodFieldModel(**HAND, occupancy_map=tiny_map(origin=(1.0, 1.0, math.pi)))
    for use_numba in (True, False):
        rotated.use_numba = use_numba
        got = rotated.log_likelihood([[1.0 - 0.25, 1.0 - 0.55, math.pi]], RANGES, ANGLES)[0]
        assert got == pytest.approx(hand_log_weight(), abs=1e-9)


def test_particles_off_the_map_or_in_walls_are_impossible():
    model = LikelihoodFieldModel(**HAND, occupancy_map=tiny_map())
    particles = np.array([[0.85, 0.55, 0.0], [-0.5, 0.5, 0.0], [0.5, 1.5, 0.0], [np.nan, 0.5, 0.0], [0.25, 0.55, 0.0]])
    for use_numba in (True, False):
        model.use_numba = use_numba
        w = model.log_likelihood(particles, RANGES, ANGLES)
        assert np.all(np.isneginf(w[:4])) and np.isfinite(w[4])
    # no usable beam: every valid particle scores 0
    assert model.log_likelihood(PARTICLE, [np.inf, 9.0], [0.0, 0.1])[0] == 0.0


def _random_case(seed, n=3000, beams=60):
    m = corridor_map()
    rng = np.random.default_rng(seed)
    truth = np.array([[4.0, 1.5, 0.1]])
    angles = np.linspace(-2.35, 2.35, beams)
    ranges = ExactRayCaster(m, 8.0).cast(compose(truth, np.array([0.275, 0.0, 0.0])), angles)[0]
    ranges[rng.random(beams) < 0.1] = np.inf
    ranges[:5] = 0.4  # an unmapped obstacle close ahead of the laser on five beams
    particles = np.column_stack([rng.uniform(-0.5, 10.5, n), rng.uniform(0.0, 3.2, n), rng.uniform(-4, 4, n)])
    particles[: n // 2] = truth + rng.normal(0, [0.05, 0.05, 0.02], (n // 2, 3))
    return m, particles, ranges, angles


@pytest.mark.parametrize("beamskip", [False, True])
def test_compiled_kernel_equals_the_numpy_reference(beamskip):
    m, particles, ranges, angles = _random_case(1)
    # half the particles spread over the map: beam_skip_max_spread lifted so that they are skipped all the same
    model = LikelihoodFieldModel(do_beamskip=beamskip, beam_skip_max_spread=100.0, laser_max_range=8.0,
                                 occupancy_map=m)
    fast = model.log_likelihood(particles, ranges, angles)
    used_fast = model.last_beams_used
    ref = model.log_likelihood_numpy(particles, ranges, angles)
    assert np.array_equal(np.isneginf(fast), np.isneginf(ref)) and np.isneginf(fast).any()
    np.testing.assert_allclose(fast[np.isfinite(fast)], ref[np.isfinite(ref)], rtol=1e-12, atol=1e-12)
    assert not np.isnan(fast).any()
    if beamskip:  # half the particles near the truth: the five cluttered beams are skipped, not more
        assert used_fast is not None and used_fast < np.isfinite(ranges).sum()


def test_beam_skipping_waits_for_a_cloud_of_one_hypothesis():
    m, particles, ranges, angles = _random_case(1)  # half near the truth, half spread over the map
    model = LikelihoodFieldModel(do_beamskip=True, laser_max_range=8.0, occupancy_map=m)  # spread limit 1 m
    plain = LikelihoodFieldModel(laser_max_range=8.0, occupancy_map=m)
    np.testing.assert_array_equal(model.log_likelihood(particles, ranges, angles),
                                  plain.log_likelihood(particles, ranges, angles))
    assert model.last_beams_used == np.isfinite(ranges).sum()


def test_beam_skipping_drops_the_unmapped_obstacle_and_keeps_everything_when_the_cloud_is_off():
    m, particles, ranges, angles = _random_case(2)
    model = LikelihoodFieldModel(do_beamskip=True, laser_max_range=8.0, occupancy_map=m)
    finite = np.isfinite(ranges)
    near_truth = particles[: len(particles) // 2]
    votes_mask = model.log_likelihood(near_truth, ranges, angles)
    assert np.all(np.isfinite(votes_mask))
    used = model.last_beams_used
    assert finite.sum() - 5 - 3 <= used <= finite.sum() - 5  # the five cluttered beams go, the wall hits stay
    # skipping the clutter: the truth scores as if the obstacle were not there
    clean = ranges.copy()
    clean[:5] = np.inf
    plain = LikelihoodFieldModel(laser_max_range=8.0, occupancy_map=m)
    assert plain.log_likelihood(near_truth[:1], clean, angles)[0] >= model.log_likelihood(
        near_truth[:1], ranges, angles)[0] - 1.0
    # a cloud far from every wall agreement: too many beams would go, so all are used (nav2's error case)
    lost = np.tile([[5.0, 1.5, 1.3]], (50, 1))
    model.log_likelihood(lost, ranges, angles)
    agreed = model.last_beams_used
    assert agreed < 0.5 * finite.sum()  # most beams of the wrong pose miss the walls ...
    strict = LikelihoodFieldModel(do_beamskip=True, beam_skip_error_threshold=0.5, laser_max_range=8.0,
                                  occupancy_map=m)
    strict.log_likelihood(lost, ranges, angles)
    assert strict.last_beams_used == finite.sum()  # ... so many that the cloud is judged off: all are used


def test_the_true_pose_scores_best():
    m, particles, ranges, angles = _random_case(3)
    model = LikelihoodFieldModel(laser_max_range=8.0, occupancy_map=m)
    truth = np.array([[4.0, 1.5, 0.1]])
    others = truth + np.array([[0.3, 0, 0], [0, 0.3, 0], [0, 0, 0.2], [-0.3, 0.2, -0.1]])
    w = model.log_likelihood(np.vstack([truth, others]), ranges, angles)
    assert w[0] > w[1:].max()


def test_params_defaults_come_from_the_table_and_build_filter_picks_the_model():
    for f in fields(LikelihoodFieldParams):
        assert f.default == BY_NAME[f.name].default, f.name
    assert Parameters().sensor_model == "beam"
    assert isinstance(build_filter(Parameters()).sensor_model, BeamModel)
    pf = build_filter(Parameters(sensor_model="likelihood_field", lf_sigma_hit=0.3, do_beamskip=True,
                                 squash_factor=3.0, laser_offset_x=0.2))
    model = pf.sensor_model
    assert isinstance(model, LikelihoodFieldModel)
    assert model.params.lf_sigma_hit == 0.3 and model.params.do_beamskip and model.params.squash_factor == 3.0
    assert Parameters().laser_max_range <= 0  # z_max from each scan's range_max, as nav2's -1
    assert np.allclose(model.laser_offset, [0.2, 0.0, 0.0]) and model.max_range == UNKNOWN_RANGE_MAX
    model.set_laser_offset((0.1, 0.02, 0.3))
    assert np.allclose(model.laser_offset, [0.1, 0.02, 0.3]) and model.params.laser_offset_y == 0.02
    with pytest.raises(ValueError):
        LikelihoodFieldModel(lf_z_hit=0.0, lf_z_rand=0.0)
    with pytest.raises(RuntimeError):
        LikelihoodFieldModel().log_likelihood(PARTICLE, RANGES, ANGLES)


def test_the_distance_field_is_banded_exactly():
    from scipy.ndimage import distance_transform_edt

    import localization.core.models.likelihood_field as lf_module
    m = corridor_map()
    model = LikelihoodFieldModel(laser_likelihood_max_dist=0.7)
    whole = np.minimum(distance_transform_edt(~m.occupied) * m.resolution, 0.7)
    saved = lf_module.BAND_CELLS
    try:
        lf_module.BAND_CELLS = 5 * m.width  # bands of five rows
        banded = model.distance_field(m)
    finally:
        lf_module.BAND_CELLS = saved
    np.testing.assert_allclose(banded, whole, atol=1e-6)
    field = model.prepare(m)
    assert field.dtype == np.uint8 and np.array_equal(field == 0, m.occupied)


def test_a_localizer_tracks_with_the_likelihood_field():
    m = corridor_map()
    params = Parameters(sensor_model="likelihood_field", num_particles=500, random_seed=3, laser_max_range=8.0,
                        num_beams_per_particle=60, recovery=False)
    loc = Localizer(params)
    loc.set_map(m)
    truth = np.array([4.0, 1.5, 0.0])
    loc.set_initial_pose(truth + [0.2, -0.1, 0.05])
    caster = ExactRayCaster(m, 8.0)
    angles = np.linspace(-2.35, 2.35, 271)
    est = None
    for i in range(15):
        ranges = caster.cast(compose(truth[None], np.array([0.275, 0.0, 0.0])), angles)[0]
        est = loc.on_scan(ScanData(0.1 * i, ranges, angles[0], angles[-1], angles[1] - angles[0], 0.02, 8.0)).estimate
        loc.request_update() if hasattr(loc, "request_update") else setattr(loc, "_force_update", True)
    assert est is not None and np.all(np.isfinite(est.pose)) and np.all(np.isfinite(est.covariance))
    assert abs(est.pose[1] - truth[1]) < 0.1 and abs(est.pose[2]) < 0.1  # across the corridor and heading


def test_deskew_offsets_move_each_beams_origin():
    # beam 0.3 m at 0 rad ends 3 cells from the wall; with the laser 0.3 m further ahead at that beam's time
    # (offset dx = 0.3) it ends in the wall cell itself: the hand value of a 0.6 m beam
    model = LikelihoodFieldModel(**HAND, occupancy_map=tiny_map())
    assert model.supports_deskew
    offsets = np.zeros((RANGES.size, 3))
    offsets[1, 0] = 0.3
    moved = RANGES.copy()
    moved[1] = 0.6
    for use_numba in (True, False):
        model.use_numba = use_numba
        want = model.log_likelihood(PARTICLE, moved, ANGLES)[0]
        assert model.log_likelihood(PARTICLE, RANGES, ANGLES, offsets=offsets)[0] == pytest.approx(want, abs=1e-12)
    # a turn of pi/2 during the sweep on beam 1 (0.3 m): its end point goes 3 cells up instead of right
    turned = np.zeros((RANGES.size, 3))
    turned[1, 2] = np.pi / 2
    rotated = ANGLES.copy()
    rotated[1] = np.pi / 2
    assert model.log_likelihood(PARTICLE, RANGES, ANGLES, offsets=turned)[0] == pytest.approx(
        model.log_likelihood(PARTICLE, RANGES, rotated)[0], abs=1e-12)
