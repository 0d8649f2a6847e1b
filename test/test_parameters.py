"""One source of defaults: every model's parameter struct agrees with the parameter table, except
where the course's classes deliberately keep the course's values (``COURSE_DEFAULTS``, stated once)."""
from __future__ import annotations

from dataclasses import fields

import numpy as np
import pytest
from helpers import corridor_map

from localization.core.localizer import build_filter
from localization.core.localizer.health import HealthMonitor
from localization.core.models.beam import BeamModel as SensorModel
from localization.core.models.beam import BeamModelParams
from localization.core.models.motion import MotionModel, MotionNoiseParams
from localization.core.parameters import BY_NAME, COURSE_DEFAULTS, ParameterError, Parameters, default
from localization.core.raycast import LookupTableRayCaster

STRUCTS = {BeamModelParams: "", MotionNoiseParams: "motion_"}


@pytest.mark.parametrize("struct, prefix", STRUCTS.items())
def test_model_structs_take_their_defaults_from_the_table(struct, prefix):
    checked = 0
    for f in fields(struct):
        name = prefix + f.name
        if name not in BY_NAME:
            continue  # a model constant that is no node parameter (e.g. still_trans)
        expected = COURSE_DEFAULTS.get(name, BY_NAME[name].default)
        assert f.default == expected, f"{struct.__name__}.{f.name} = {f.default!r}, table/course says {expected!r}"
        checked += 1
    assert checked >= 7


def test_course_defaults_differ_from_the_node_on_purpose_and_only_there():
    # each entry is a real difference from the node's default, and names a real parameter
    for name, value in COURSE_DEFAULTS.items():
        assert name in BY_NAME and value != BY_NAME[name].default
    assert SensorModel().sigma_hit == 0.4 and Parameters().sigma_hit == 0.2  # m: 8 and 4 cells of 0.05 m
    assert SensorModel().sigma_hit / SensorModel().table_resolution == pytest.approx(8.0)  # the course's 8 cells
    assert MotionModel().floor_xy == COURSE_DEFAULTS["motion_floor_xy"]
    assert default("sigma_hit") == 0.2 and default("sigma_hit", course=True) == 0.4


def test_build_filter_maps_every_parameter_by_name():
    params = Parameters(sigma_hit=0.15, motion_floor_xy=0.011, laser_offset_y=0.05, squash_factor=3.5,
                        ray_caster="exact")
    pf = build_filter(params)
    assert pf.sensor_model.sigma_hit == 0.15 and pf.sensor_model.squash_factor == 3.5
    assert np.allclose(pf.sensor_model.laser_offset, [params.laser_offset_x, 0.05, 0.0])
    assert pf.motion_model.floor_xy == 0.011 and pf.num_particles == params.num_particles


def test_health_monitor_defaults_come_from_the_table():
    m, p = HealthMonitor(), Parameters()
    assert (m.fast_alpha, m.slow_alpha, m.lost_floor, m.lost_ratio, m.lost_updates) == (
        p.health_fast_alpha, p.health_slow_alpha, p.health_lost_floor, p.health_lost_ratio, p.health_lost_updates)


def test_sensor_model_defaults_to_the_lookup_table(tmp_path, monkeypatch):
    monkeypatch.setenv("LOCALIZATION_CACHE_DIR", str(tmp_path))
    sm = SensorModel(table_width=61)
    sm.set_map(corridor_map())
    assert isinstance(sm.ray_caster, LookupTableRayCaster)
    assert list(tmp_path.glob("range_table_*.npz")), "the table is cached on disk"
    slow = SensorModel(table_width=61, ray_caster="exact", occupancy_map=corridor_map())
    assert type(slow.ray_caster).__name__ == "ExactRayCaster"


def test_limits_once_hidden_in_the_localizer_are_parameters():
    for name in ("odom_max_gap", "odom_max_speed", "odom_max_yaw_rate", "max_impossible_scans"):
        assert name in BY_NAME
    with pytest.raises(ParameterError):
        Parameters(odom_max_speed=-1.0)


def test_deprecated_sigma_hit_cells_converts_with_one_warning(caplog, tmp_path):
    """sigma_hit is in metres; the cell-valued sigma_hit_cells still works, times table_resolution, whatever
    the order the values come in, with one warning; an old cell value given as sigma_hit is refused."""
    with caplog.at_level("WARNING", logger="localization.parameters"):
        p = Parameters(sigma_hit_cells=3, table_resolution=0.0504)
    assert p.sigma_hit == pytest.approx(3 * 0.0504) and "sigma_hit_cells" not in p
    assert sum("sigma_hit_cells is deprecated" in r.message for r in caplog.records) == 1
    f = tmp_path / "old.yaml"
    f.write_text("particle_filter:\n  ros__parameters:\n    sigma_hit_cells: 4.0\n")
    assert Parameters.from_yaml(f).sigma_hit == pytest.approx(0.2)
    with pytest.raises(ParameterError, match="sigma_hit=4.0 must be > 0"):
        Parameters(sigma_hit=4.0)  # 4 m: an old value in cells
    with pytest.raises(ParameterError, match="sigma_hit=-0.05"):
        Parameters(sigma_hit_cells=-1.0)
