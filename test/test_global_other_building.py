"""Global localization (no initial pose, ``global_init: scan``) in a building nobody tuned for:
``building_31``, on a closed route built from the map alone (``robustness.auto_loop``), with the
shipped parameters (config/params.yaml). Simulated drives; see docs/performance.md."""
from __future__ import annotations

import logging

import numpy as np
import pytest

from localization.benchmarks import robustness as RB
from localization.core.localizer import Localizer
from localization.core.occupancy_map import load_map
from localization.sim import clearance_at, clearance_grid, simulate

MAP = "building_31"


@pytest.fixture(scope="module")
def occ():
    return load_map(MAP)


@pytest.fixture(scope="module")
def route(occ):
    return RB.auto_loop(occ)


def test_auto_loop_is_a_closed_route_inside_the_building(occ, route):
    path = RB.loop_path(route)
    length = float(np.hypot(*np.diff(route, axis=0, append=route[:1]).T).sum())
    assert 40.0 < length < 200.0
    steps = np.hypot(*np.diff(route, axis=0, append=route[:1]).T)
    assert steps.max() < 1.6  # closed: the last waypoint is ~1 m from the first
    clear = clearance_at(occ, clearance_grid(occ), path)
    assert clear.min() >= 0.25  # on corridor centre lines, not grazing walls
    cr = occ.world_to_grid(path)
    assert RB.enclosed(occ)[cr[:, 1], cr[:, 0]].all()  # not outside the building (free in this PNG)


@pytest.mark.parametrize("fraction,seed", [(0.25, 11), (0.7, 12)])
def test_global_scan_init_converges_in_building_31(occ, route, fraction, seed):
    params = RB.replace_params(RB.bench_params(), global_init="scan", random_seed=seed)
    start = int(fraction * len(RB.loop_path(route)))
    rec = simulate(RB.loop_config(start, 6.0, seed=seed, route=route, map_name=MAP), occ)
    loc = Localizer(params, logging.getLogger("test.global_b31"))
    loc.set_map(occ)
    run = RB.run_recording(rec, loc, init="global")
    cmp = RB.ct_errors(rec, run)
    t_conv = RB.settle_time(cmp, float(rec.odometry.t[0]))
    assert t_conv is not None and t_conv <= 5.0, f"not below {RB.TARGET_M} m for good within 5 s: {t_conv}"
    assert cmp.ct_error[-1] < RB.TARGET_M
    assert float(np.max(cmp.ct_error[cmp.t >= 5.0])) < RB.TARGET_M
