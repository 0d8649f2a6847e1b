"""num_threads: the beam model's fused pass on several threads gives one thread's weights, bit for bit."""
import numpy as np
import pytest

from localization.core.models.beam import MIN_PARTICLES_PER_THREAD, BeamModel, kernel_threads
from localization.core.occupancy_map import load_map


@pytest.fixture(scope="module")
def stata():
    return load_map("basement_fixed")


@pytest.mark.parametrize("beamskip, deskew", [(False, False), (True, False), (False, True)])
def test_two_threads_give_the_weights_of_one(stata, beamskip, deskew):
    rng = np.random.default_rng(3)
    parts = np.vstack([stata.sample_free_poses(3001, rng), [[1e6, 1e6, 0.0], [np.nan, 0.0, 0.0]]])
    if beamskip:  # one hypothesis, so that beam skipping applies
        parts = parts[0] + rng.normal(0.0, [0.05, 0.05, 0.02], parts.shape)
    obs = rng.uniform(0.5, 8.0, 100)
    obs[::7] = np.inf
    offsets = np.c_[np.linspace(0, 0.05, 100), np.zeros(100), np.linspace(0, 0.02, 100)] if deskew else None
    params = dict(occupancy_map=stata, do_beamskip=beamskip, beam_skip_max_spread=1.0)
    one, two = BeamModel(num_threads=1, **params), BeamModel(num_threads=2, **params)
    a = one.log_likelihood(parts, obs, offsets=offsets)
    b = two.log_likelihood(parts, obs, offsets=offsets)
    np.testing.assert_array_equal(a, b)
    assert one.last_beams_used == two.last_beams_used
    assert np.isfinite(a).sum() >= 2000 and not np.isnan(a).any()


def test_thread_count_rule():
    assert kernel_threads(1, 100_000) == 1
    assert kernel_threads(8, MIN_PARTICLES_PER_THREAD) == 1  # too few particles to share
    assert 1 <= kernel_threads(2, 10 * MIN_PARTICLES_PER_THREAD) <= 2
