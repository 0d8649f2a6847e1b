"""Parameters changed while the localizer runs (core.runtime_parameters, core.localizer.reconfigure): checked by
the table's rules and refused with the reason; applied between updates; a range-table change prepared first."""
from __future__ import annotations

import numpy as np
import pytest
from helpers import corridor_map

from localization.core.localizer import Localizer
from localization.core.odometry import TwistData
from localization.core.parameters import ParameterError, Parameters
from localization.core.runtime_parameters import RUNTIME, How, check_change, read_only_reason
from localization.core.scan import ScanData


def _localizer(**overrides) -> Localizer:
    values = dict(num_particles=400, random_seed=1, ray_caster="distance_transform", deterministic=False)
    values.update(overrides)
    loc = Localizer(Parameters(values))
    loc.set_map(corridor_map())
    loc.set_initial_pose([2.0, 1.5, 0.0], np.diag([0.04, 0.04, 0.01]), 0.0)
    return loc


def _drive(loc: Localizer, t0: float, seconds: float) -> float:
    """Odometry at 50 Hz and a scan (ranges 0.9 m: the corridor's walls) every 4th message."""
    t = t0
    for k in range(int(seconds * 50)):
        t = t0 + 0.02 * (k + 1)
        loc.on_odometry(TwistData(t, 0.5, 0.0, 0.0))
        if k % 4 == 3:
            loc.on_scan(ScanData(t, np.full(181, 0.9), -np.pi / 2, np.pi / 2, np.pi / 180, 0.02, 10.0))
    return t


def test_a_change_is_checked_by_the_tables_rules_and_refused_with_the_reason():
    current = Parameters(num_particles=500)
    with pytest.raises(ParameterError, match=r"sigma_hit=-1.0 must be"):
        check_change(current, {"sigma_hit": -1.0})
    with pytest.raises(ParameterError, match="map_topic cannot change while the node runs: read once"):
        check_change(current, {"map_topic": "/other_map"})
    with pytest.raises(ParameterError, match="at least one of alpha_hit"):
        check_change(current, {"alpha_hit": 0.0, "alpha_short": 0.0, "alpha_max": 0.0, "alpha_rand": 0.0})
    with pytest.raises(ParameterError, match="likelihood_field model"):
        check_change(Parameters(sensor_model="likelihood_field"), {"sigma_hit": 0.3})
    change = check_change(current, {"num_particles": 300, "sigma_hit": 0.2, "motion_a_trans": 0.3})
    assert change.changed == {"num_particles": (500, 300), "motion_a_trans": (current.motion_a_trans, 0.3)}
    assert change.hows == {How.FILTER, How.MOTION} and not change.needs_preparation
    assert current.num_particles == 500  # checking changes nothing
    assert read_only_reason("num_particles") == "" and "restart the node" in read_only_reason("scan_topic")
    assert all(name in Parameters() for name in RUNTIME)


def test_the_particle_count_noise_and_sensor_model_change_between_updates():
    loc = _localizer()
    t = _drive(loc, 0.0, 1.0)
    before = loc.particles()
    change = check_change(loc.params, {"num_particles": 300, "sigma_hit": 0.3, "motion_a_trans": 0.25,
                                       "num_beams_per_particle": 40})
    assert loc.prepare_change(change) is None  # nothing slow
    loc.reconfigure(change)
    after = loc.particles()
    assert after.shape == (300, 3) and np.all(np.isfinite(after))
    assert np.allclose(after[:, :2].mean(axis=0), before[:, :2].mean(axis=0), atol=0.05)  # resampled: kept
    assert loc.params.sigma_hit == 0.3 and loc.params.num_beams_per_particle == 40  # what the parts read
    assert loc._model.params.sigma_hit == 0.3 and loc._pf.motion_model.a_trans == 0.25
    table = loc._model.sensor_model_table
    assert np.isclose(table.sum(axis=0), 1.0).all()  # the likelihood table rebuilt with the new sigma_hit
    _drive(loc, t, 1.0)
    assert loc.num_particles == 300 and np.all(np.isfinite(loc.estimate.pose))


def test_a_range_table_change_is_prepared_first_then_swapped_in(tmp_path, monkeypatch):
    from localization.core.raycast import lookup_table
    monkeypatch.setenv("LOCALIZATION_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(lookup_table, "LIVE_TABLES", {})
    loc = _localizer()
    t = _drive(loc, 0.0, 0.5)
    change = check_change(loc.params, {"ray_caster": "lookup_table", "scan_theta_discretization": 16})
    assert change.needs_preparation and How.TABLE in change.hows
    prepared = loc.prepare_change(change)  # off the hot path: the filter is untouched meanwhile
    assert isinstance(prepared.prepared, lookup_table.LookupTableRayCaster)
    assert loc._model.params.ray_caster == "distance_transform"
    _drive(loc, t, 0.2)  # the node keeps localizing while it is prepared
    loc.reconfigure(change, prepared)
    assert loc._model.ray_caster is prepared.prepared and loc._model.params.scan_theta_discretization == 16
    _drive(loc, t + 0.2, 0.5)
    assert np.all(np.isfinite(loc.estimate.pose)) and np.all(np.isfinite(loc.particles()))


def test_the_node_docs_list_exactly_the_parameters_that_can_change_while_it_runs():
    import re
    from pathlib import Path
    text = (Path(__file__).resolve().parents[1] / "docs" / "node.md").read_text()
    section = text.split("### Changing parameters while it runs", 1)[1].split("\n#", 1)[0]
    rows = [line for line in section.splitlines() if line.startswith("| ") and "`" in line]
    listed = {name for row in rows for name in re.findall(r"`([a-z_.]+)`", row.split("|")[2])}
    assert listed == set(RUNTIME)
