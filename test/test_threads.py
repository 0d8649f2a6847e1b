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


@pytest.mark.parametrize("env, layer", [(None, "workqueue"), ("omp", "omp")])
def test_threaded_pass_runs_on_the_chosen_layer(env, layer):
    """The threaded pass runs on numba's work queue (its threads start at once after the node's idle between
    scans); a layer named in NUMBA_THREADING_LAYER is kept."""
    import os
    import subprocess
    import sys
    code = ("import numpy as np, numba\n"
            "from localization.core.models.beam import BeamModel\n"
            "from localization.core.occupancy_map import load_map\n"
            "m = load_map('basement_fixed')\n"
            "p = m.sample_free_poses(2000, np.random.default_rng(0))\n"
            "BeamModel(occupancy_map=m, num_threads=2).log_likelihood(p, np.full(30, 3.0))\n"
            "print(numba.threading_layer())\n")
    environ = {k: v for k, v in os.environ.items() if k != "NUMBA_THREADING_LAYER"}
    if env is not None:
        environ["NUMBA_THREADING_LAYER"] = env
    out = subprocess.run([sys.executable, "-c", code], env=environ, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split()[-1] == layer
