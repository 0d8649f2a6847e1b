"""Compile the hot kernels in a short-lived process, so a localizer only loads them.

numba compiles a kernel on its first call and keeps what the compilation allocated (LLVM modules,
type tables) for the life of the process: for the beam model's kernels ~35 MB more than loading
the same machine code from numba's on-disk cache (``cache=True``; docs/performance.md has the
figures). A node that compiles its own kernels on the first start ever carries that for its whole
run, on top of the range table. So, before a localizer prepares its first map,
``ensure_compiled(params)`` checks numba's cache index of each kernel those parameters use; when
one is missing (a fresh install, or changed source) it runs

    python -m localization.core.localizer.compile_kernels '<parameters as JSON>'

which builds a ``Localizer`` with the same parameters on a tiny synthetic map and runs one
odometry and one scan through it (every kernel compiled with the very types the real run uses,
and written to the cache), then exits, returning its memory. The caller then loads the kernels
from the cache. When the cache cannot be written (the check still fails afterwards) the caller
compiles in-process, as before, after one log line. ``LOCALIZATION_KERNELS_IN_PROCESS=1`` turns
the child off (compile in-process).

numba's start has a fixed part too: its first kernel load installs its typing registries, and its check
for a BLAS imports ``scipy.linalg.cython_blas``, which runs all of ``scipy.linalg``'s package ``__init__``
first. ``preload_lapack()`` (called by ``ensure_compiled``) loads scipy's two Cython BLAS/LAPACK modules from
their files alone, before that: numba finds them in ``sys.modules`` and takes the same function pointers
from them (docs/performance.md has the start's figures).
"""
from __future__ import annotations

import importlib
import json
import logging
import os
import subprocess
import sys
import tempfile
import time

log = logging.getLogger(__name__)

# the kernels every scan runs (a recovery's challenger moves piece by piece with _move_kernel: compiled on its first
# use, as the tempered first update's and the global seeder's numpy passes need none), and the piece's covariance and
# factor, which the challenger's plan calls from Python
_MOTION = [("localization.core.models.motion_kernels", "plan_move_kernel"),
           ("localization.core.models.motion_kernels", "covariance_kernel"),
           ("localization.core.models.motion_kernels", "factor_kernel"),
           ("localization.core.odometry", "slip_segments_kernel"),
           ("localization.core.filter.resampling", "resample_kernel"),
           ("localization.core.filter.kernels", "weigh_kernel"),
           ("localization.core.filter.kernels", "estimate_kernel"),
           ("localization.core.localizer.health", "agreement_kernel"),
           ("localization.core.draws", "_fill_standard_normal"),
           ("localization.core.geometry", "_compose_kernel"),
           ("localization.core.geometry", "_integrate_twists_kernel")]
_TABLE = [("localization.core.raycast.kernels", "cast_kernel"), ("localization.core.raycast.kernels", "build_kernel"),
          ("localization.core.raycast.kernels", "chessboard_kernel")]
_BEAM = [("localization.core.models.beam_kernels", "fused_kernel")]
_BEAM_THREADS = [("localization.core.models.beam_kernels", "fused_kernel_parallel")]  # num_threads > 1
_BEAM_SKIP = [("localization.core.models.beam_kernels", "skip_votes"),
              ("localization.core.models.beam_kernels", "masked_sum")]
_RANGE_SCALE = [("localization.core.models.beam_kernels", "cast_rows"),
                ("localization.core.localizer.range_scale", "fit_step_kernel")]
_LIKELIHOOD_FIELD = [("localization.core.models.likelihood_field", "_lf_kernel")]
_BEAMSKIP = [("localization.core.models.likelihood_field", "_lf_beamskip_kernel"),
             ("localization.core.models.likelihood_field", "_masked_sum")]

_checked: set = set()  # kernel sets already made sure of in this process


def kernels_for(params) -> list[tuple[str, str]]:
    """(module, name) of the compiled kernels a localizer with ``params`` runs on every scan."""
    if params.sensor_model == "likelihood_field":
        return _MOTION + _LIKELIHOOD_FIELD + (_BEAMSKIP if params.do_beamskip else [])
    if params.ray_caster in ("lookup_table", "lookup_table_exact"):
        return (_MOTION + _TABLE + _BEAM + (_BEAM_THREADS if _threaded(params) else [])
                + (_RANGE_SCALE if params.range_scale_estimation else []) + (_BEAM_SKIP if params.do_beamskip else []))
    return _MOTION


def _threaded(params) -> bool:
    """Will the sensor update run on several threads (``num_threads`` > 1 and numba's pool has them)?"""
    try:
        import numba
    except ImportError:  # pragma: no cover - numba is pinned
        return False
    return min(int(params.num_threads), numba.config.NUMBA_NUM_THREADS) > 1


LAPACK_MODULES = ("scipy.linalg.cython_blas", "scipy.linalg.cython_lapack")  # in this order: LAPACK's needs BLAS's


def preload_lapack() -> bool:
    """Load ``LAPACK_MODULES``, scipy's Cython BLAS and LAPACK (what numba's linear algebra calls: the motion
    model's ``eigh``), from their extension files without importing the ``scipy.linalg`` package, whose
    ``__init__`` numba's start otherwise runs for them. They are scipy's own modules under their own
    names; a later ``import scipy.linalg`` imports the package and finds them loaded (reached by their own
    import, ``import scipy.linalg.cython_lapack``: the package never sets them as its attributes). True when this
    loaded them; False when there was nothing to do (either already imported) or they are not where scipy
    keeps them (then the normal import loads them when numba asks). Never raises."""
    if "scipy.linalg" in sys.modules or any(name in sys.modules for name in LAPACK_MODULES):
        return False
    try:
        import importlib.machinery
        import importlib.util
        from pathlib import Path
        scipy_spec = importlib.util.find_spec("scipy")
        folder = Path(scipy_spec.origin).parent / "linalg"
        paths = []
        for name in LAPACK_MODULES:
            leaf = name.rsplit(".", 1)[1]
            candidates = (folder / (leaf + suffix) for suffix in importlib.machinery.EXTENSION_SUFFIXES)
            path = next((c for c in candidates if c.is_file()), None)
            if path is None:
                return False
            paths.append(path)
        for name, path in zip(LAPACK_MODULES, paths):
            spec = importlib.util.spec_from_file_location(name, path)
            module = importlib.util.module_from_spec(spec)
            sys.modules[name] = module
            try:
                spec.loader.exec_module(module)
            except BaseException:
                del sys.modules[name]
                raise
    except Exception:  # noqa: BLE001 - scipy missing or laid out otherwise: numba's own import does it
        return False
    return True


def drop_if_older(dispatcher, *sources: str) -> bool:
    """numba's cache checks only the kernel's own source file: a kernel that calls compiled helpers from
    another module (inlined into its machine code) would load a stale compilation after only the helpers
    changed. Drop the kernel's cache index when one of those ``sources`` (file paths) is newer than it, so
    the next call compiles afresh. True when it dropped one; never raises."""
    try:
        index = dispatcher._cache._cache_file._index_path
        if os.path.exists(index) and any(os.path.getmtime(src) > os.path.getmtime(index) for src in sources):
            os.remove(index)
            return True
    except Exception:  # noqa: BLE001 - numba's internals changed, or the cache is not ours to touch
        pass
    return False


def is_cached(module: str, name: str) -> bool | None:
    """Does numba's on-disk cache hold a current compilation of this kernel? None: cannot tell
    (numba missing, no ``cache=True``, or numba's internals changed)."""
    try:
        dispatcher = getattr(importlib.import_module(module), name)
        cache_file = dispatcher._cache._cache_file
        return bool(cache_file._load_index())  # {} when missing or stale (source changed)
    except Exception:  # noqa: BLE001 - any surprise means "unknown": compile in-process
        return None


def ensure_compiled(params, logger=None) -> str:
    """Make sure the kernels ``params`` use are in numba's cache (see the module docstring).
    Returns what happened: "cached", "compiled" (by a child process), "in-process" or "unknown"."""
    logger = logger or log
    preload_lapack()
    kernels = tuple(kernels_for(params))
    if kernels in _checked or os.environ.get("LOCALIZATION_KERNELS_IN_PROCESS") == "1":
        return "in-process"
    _checked.add(kernels)
    state = [is_cached(m, n) for m, n in kernels]
    if any(s is None for s in state):
        return "unknown"
    if all(state):
        return "cached"
    t0 = time.perf_counter()
    logger.info("compiling the filter's kernels into numba's cache (first start after an install or an "
                "update; a separate process, so this one keeps only the compiled code) ...")
    cmd = [sys.executable, "-m", "localization.core.localizer.compile_kernels", json.dumps(dict(params))]
    try:
        with tempfile.TemporaryDirectory(prefix="localization-kernels-") as scratch:
            # the tiny map's range table goes to a scratch cache; the child compiles in-process itself
            env = dict(os.environ, LOCALIZATION_CACHE_DIR=scratch, LOCALIZATION_KERNELS_IN_PROCESS="1")
            out = subprocess.run(cmd, capture_output=True, text=True, timeout=600, check=False, env=env)
        failed = out.returncode != 0
        detail = (out.stderr or "").strip().splitlines()[-1:] if failed else []
    except (OSError, subprocess.SubprocessError) as exc:
        failed, detail = True, [repr(exc)]
    if failed or not all(is_cached(m, n) for m, n in kernels):
        logger.warning("could not compile the kernels into numba's cache (%s); compiling them in this process",
                       detail[0] if detail else "cache not writable?")
        return "in-process"
    logger.info("kernels compiled and cached in %.1f s", time.perf_counter() - t0)
    return "compiled"


def main(argv=None) -> int:
    """``python -m localization.core.compile_cache [PARAMETER_FILE ...]``: the kernels each parameter file uses
    (default: the package's own, ``config/*params.yaml``) compiled into numba's cache, as their first start
    would; ``scripts/bootstrap.sh`` runs it while it builds tf2_msgs. Exit status 1 when a set could not be
    cached."""
    import argparse

    from localization.core.parameters import Parameters
    from localization.core.paths import config_dir
    ap = argparse.ArgumentParser(prog="python -m localization.core.compile_cache", description=main.__doc__)
    ap.add_argument("files", nargs="*", help="parameter files (default: the package's own)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    files = args.files or sorted(str(f) for f in config_dir().glob("*params.yaml"))
    sets = {tuple(kernels_for(p)): p for p in (Parameters.from_yaml(f) for f in files)}  # each set once
    return 0 if all(ensure_compiled(p) in ("cached", "compiled") for p in sets.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
