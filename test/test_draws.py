"""The compiled standard normal draws are numpy's, bit for bit, and leave the generator where numpy leaves it."""
import numpy as np
import pytest

from localization.core import draws
from localization.core.draws import COMPILED_MIN_SIZE, standard_normal_into


@pytest.mark.parametrize("seed", [0, 1, 12345])
@pytest.mark.parametrize("shape", [(0,), (1,), (COMPILED_MIN_SIZE - 1,), (COMPILED_MIN_SIZE,), (2000, 3),
                                   (3, 2000, 3), (400_003,)])
def test_values_and_generator_state_equal_numpys(seed, shape):
    ours, numpys = np.random.default_rng(seed), np.random.default_rng(seed)
    out = np.full(shape, np.nan)
    assert standard_normal_into(ours, out) is out
    np.testing.assert_array_equal(out, numpys.standard_normal(shape))
    assert ours.bit_generator.state == numpys.bit_generator.state  # the next draws are the same too
    assert ours.random() == numpys.random()


def test_large_draws_run_compiled():
    """Arrays from COMPILED_MIN_SIZE up go to the compiled loop (the figure it saves is in docs/performance.md)."""
    if draws._fill_standard_normal is None:
        pytest.skip("numba is not installed")  # pinned in requirements.txt: not skipped in this project's runs
    calls = []
    compiled = draws._fill_standard_normal

    def counting(rng, flat):
        calls.append(flat.size)
        return compiled(rng, flat)
    draws._fill_standard_normal = counting
    try:
        standard_normal_into(np.random.default_rng(0), np.empty((2000, 3)))
        standard_normal_into(np.random.default_rng(0), np.empty(10))
    finally:
        draws._fill_standard_normal = compiled
    assert calls == [6000]


def test_other_generators_go_to_numpy_with_the_same_values():
    ours, numpys = (np.random.Generator(np.random.MT19937(3)) for _ in range(2))
    np.testing.assert_array_equal(standard_normal_into(ours, np.empty(5000)), numpys.standard_normal(5000))
    assert ours.random() == numpys.random()
