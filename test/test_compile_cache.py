"""Kernels compiled in a short-lived child process into numba's cache (core/compile_cache.py)."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import pytest

from localization.core import compile_cache as cc
from localization.core.parameters import Parameters

PROBE = """
import json, logging, sys
from localization.core import compile_cache as cc
from localization.core.parameters import Parameters
p = Parameters(json.loads(sys.argv[1]))
before = [cc.is_cached(m, n) for m, n in cc.kernels_for(p)]
print(json.dumps({"before": before, "first": cc.ensure_compiled(p)}))
"""


def run_probe(params: dict, numba_dir) -> dict:
    env = dict(os.environ, NUMBA_CACHE_DIR=str(numba_dir))
    env.pop("LOCALIZATION_KERNELS_IN_PROCESS", None)
    out = subprocess.run([sys.executable, "-c", PROBE, json.dumps(params)], env=env, capture_output=True, text=True,
                         timeout=300, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_every_listed_kernel_exists_and_has_a_disk_cache():
    """kernels_for names real cache=True dispatchers for each sensor model (None would mean a
    renamed kernel or changed numba internals, which would silently compile in-process)."""
    for params in (Parameters(), Parameters(ray_caster="lookup_table_exact"),
                   Parameters(sensor_model="likelihood_field", do_beamskip=True)):
        assert all(cc.is_cached(m, n) is not None for m, n in cc.kernels_for(params))


@pytest.fixture(scope="module")
def car_cache(tmp_path_factory):
    """numba's cache filled from empty by a child for config/real_params.yaml, then probed again: the folder,
    the car file's parameters and both probes' answers. The tests below start from copies of it."""
    from localization.core.paths import config_dir
    folder = tmp_path_factory.mktemp("numba-car")
    params = dict(Parameters.from_yaml(config_dir() / "real_params.yaml"))
    return folder, params, run_probe(params, folder), run_probe(params, folder)


def copy_of(folder, tmp_path):
    shutil.copytree(folder, tmp_path / "numba")
    return tmp_path / "numba"


def test_the_shipped_car_file_compiles_every_kernel_in_the_child(car_cache):
    """config/real_params.yaml (odometry stamps 0.129 s ahead on the scan clock, the range scale learnt online),
    from an empty cache: the child's drive reaches every kernel the car runs, so none is left to compile in the
    node's process, and the next start only loads them."""
    from localization.core.paths import config_dir
    folder, params, first, second = car_cache
    kernels = cc.kernels_for(Parameters(params))
    assert ("localization.core.models.motion_kernels", "plan_move_kernel") in kernels and len(kernels) >= 8
    assert first["before"] == [False] * len(kernels) and first["first"] == "compiled"
    assert second["before"] == [True] * len(kernels) and second["first"] == "cached"
    # what scripts/bootstrap.sh runs ahead: the command finds the car file's kernels cached
    env = dict(os.environ, NUMBA_CACHE_DIR=str(folder))
    env.pop("LOCALIZATION_KERNELS_IN_PROCESS", None)
    out = subprocess.run([sys.executable, "-m", "localization.core.compile_cache",
                          str(config_dir() / "real_params.yaml")],
                         env=env, capture_output=True, text=True, timeout=300, check=False)
    assert out.returncode == 0 and "compiling" not in out.stderr


def test_another_models_kernels_are_compiled_by_a_child_then_only_loaded(car_cache, tmp_path):
    """The likelihood field's kernels are not among the car's: a child compiles them into the cache that
    holds the car's, and the next start only loads them."""
    folder = copy_of(car_cache[0], tmp_path)
    params = {"sensor_model": "likelihood_field"}
    kernels = cc.kernels_for(Parameters(params))
    first = run_probe(params, folder)
    assert not all(first["before"]) and first["first"] == "compiled"
    second = run_probe(params, folder)
    assert second["before"] == [True] * len(kernels) and second["first"] == "cached"


def test_several_threads_compile_the_threaded_kernel_in_the_child_too(car_cache, tmp_path):
    """``num_threads`` > 1 (a multi-core car, ``localization-replay``'s default): the threaded sensor kernel is
    compiled by the child as well, so the first sensor update does not stop the node to compile it."""
    import numba
    params = {**car_cache[1], "num_threads": 2}
    kernels = cc.kernels_for(Parameters(params))
    threaded = ("localization.core.models.beam_kernels", "fused_kernel_parallel")
    if numba.config.NUMBA_NUM_THREADS < 2:  # one core: the update runs on one thread, nothing more to compile
        assert threaded not in kernels
        return
    assert threaded in kernels
    assert threaded not in cc.kernels_for(Parameters())
    folder = copy_of(car_cache[0], tmp_path)
    first = run_probe(params, folder)
    assert first["before"] == [k != threaded for k in kernels] and first["first"] == "compiled"
    assert run_probe(params, folder)["first"] == "cached"


SIGNATURES = """
import json, sys
from numba.core.registry import CPUDispatcher
from localization.core.localizer.compile_kernels import compile_kernels
from localization.core.parameters import Parameters
compile_kernels(Parameters.from_yaml(sys.argv[1]))
seen = {}
for name, mod in list(sys.modules.items()):
    if name.startswith("localization"):
        for attr, obj in vars(mod).items():
            if isinstance(obj, CPUDispatcher) and obj.signatures:
                seen[f"{name}.{attr}"] = [str(s) for s in obj.signatures]
print(json.dumps(seen))
"""


def test_each_kernel_runs_with_one_signature(tmp_path):
    """The drive that fills numba's cache (the car's and the simulator's parameter files) calls every kernel
    with one argument signature, of writable arrays: a second one (a read-only or strided array handed in
    somewhere) would be compiled in the running node, not loaded from the cache."""
    from localization.core.paths import config_dir
    for name in ("real_params.yaml", "params.yaml"):
        env = dict(os.environ, LOCALIZATION_KERNELS_IN_PROCESS="1", LOCALIZATION_CACHE_DIR=str(tmp_path))
        out = subprocess.run([sys.executable, "-c", SIGNATURES, str(config_dir() / name)], capture_output=True,
                             text=True, timeout=600, check=True, env=env)
        seen = json.loads(out.stdout.strip().splitlines()[-1])
        assert len(seen) >= 10, seen
        assert {k: v for k, v in seen.items() if len(v) > 1} == {}
        assert [k for k, v in seen.items() if "True, aligned" in v[0]] == []  # Array(..., readonly=True, ...)


LAPACK_PROBE = """
import json, sys
import numpy as np
from localization.core import compile_cache as cc
from localization.core.localizer import Localizer
from localization.core.models.motion import noise_factor_numpy
from localization.core.models.motion_kernels import factor_kernel
from localization.core.parameters import Parameters
from localization.eval.replay.run import load_map
out = {"scipy_linalg_at_start": "scipy.linalg" in sys.modules}
localizer = Localizer(Parameters.from_yaml(sys.argv[1]))
localizer.set_map(load_map("basement_fixed"))  # ensure_compiled, then the kernels loaded and warmed up
out["preloaded"] = all(name in sys.modules for name in cc.LAPACK_MODULES)
out["scipy_linalg_after_set_map"] = "scipy.linalg" in sys.modules
cov = np.array([[0.04, 0.01, 0.002], [0.01, 0.03, -0.001], [0.002, -0.001, 0.01]])
out["eigh_as_numpy"] = bool(np.array_equal(factor_kernel(cov), noise_factor_numpy(cov)))
out["scipy_linalg_after_eigh"] = "scipy.linalg" in sys.modules
out["again"] = cc.preload_lapack()
import scipy.linalg
out["scipy_eigh"] = bool(np.allclose(scipy.linalg.eigh(cov)[0], np.linalg.eigh(cov)[0]))
import scipy.linalg.cython_lapack as lapack
out["same_module"] = lapack is sys.modules["scipy.linalg.cython_lapack"]
print(json.dumps(out))
"""


def test_numbas_lapack_comes_without_the_scipy_linalg_package():
    """A fresh process preparing the car file's localizer loads scipy's Cython BLAS/LAPACK alone (not
    ``scipy.linalg``'s package, a fixed part of every start): the motion model's compiled ``eigh`` then gives
    numpy's factor exactly, still without the package; a later ``import scipy.linalg`` works and reuses them."""
    from localization.core.paths import config_dir
    out = subprocess.run([sys.executable, "-c", LAPACK_PROBE, str(config_dir() / "real_params.yaml")],
                         capture_output=True, text=True, timeout=300, check=True)
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got == {"scipy_linalg_at_start": False, "preloaded": True, "scipy_linalg_after_set_map": False,
                   "eigh_as_numpy": True, "scipy_linalg_after_eigh": False, "again": False, "scipy_eigh": True,
                   "same_module": True}
