"""The sensor-model interface (``localization.core.models.sensor.SensorModel``): both models implement all of
it, and the filter, global initialisation and the localizer use nothing else."""
from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest
from helpers import corridor_map

from localization.core.filter.mcl import MonteCarloLocalizer
from localization.core.geometry import compose
from localization.core.localizer import build_filter
from localization.core.models.beam import BeamModel
from localization.core.models.likelihood_field import LikelihoodFieldModel
from localization.core.models.motion import MotionModel
from localization.core.models.sensor import Preparation, SensorModel, resolve_max_range
from localization.core.parameters import Parameters
from localization.core.raycast import ExactRayCaster, TiledLookupTableRayCaster

KINDS = ("beam", "likelihood_field")
ANGLES = np.linspace(-2.0, 2.0, 41)
TRUTH = np.array([4.0, 1.5, 0.2])


@pytest.fixture
def table_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("LOCALIZATION_CACHE_DIR", str(tmp_path))
    return tmp_path


def make(kind: str, **overrides):
    values = dict(sensor_model=kind, ray_caster="lookup_table", scan_theta_discretization=16)
    params = Parameters({**values, **overrides})
    return build_filter(params).sensor_model


def scan(m, offset=(0.0, 0.0, 0.0)):
    return ExactRayCaster(m, 10.0).cast(compose(TRUTH, np.asarray(offset))[None], ANGLES)[0]


@pytest.mark.parametrize("kind", KINDS)
def test_both_models_implement_the_protocol(kind, table_cache):
    model = make(kind)
    assert isinstance(model, SensorModel)
    assert isinstance(type(model).supports_deskew, bool)  # a class attribute, no probing
    assert isinstance(type(model).supports_range_scale, bool)
    assert dataclasses.is_dataclass(model.params)
    with pytest.raises(dataclasses.FrozenInstanceError):
        model.params.squash_factor = 1.0
    assert isinstance(model.max_range, float) and model.max_range > 0
    with pytest.raises(AttributeError):
        model.laser_offset = np.zeros(3)  # read-only: set_laser_offset
    assert not isinstance(object(), SensorModel)


@pytest.mark.parametrize("kind", KINDS)
def test_prepare_then_set_map_is_set_map(kind, table_cache):
    m = corridor_map()
    first, second = make(kind), make(kind)
    prepared = first.prepare(m)
    first.set_map(m, prepared)
    second.set_map(m)
    particles = np.array([TRUTH, TRUTH + [0.2, 0.1, 0.0], [5.0, 0.52, 0.0], [-3.0, 1.0, 0.0]])
    ranges = scan(m, first.laser_offset)
    a = first.log_likelihood(particles, ranges, ANGLES)
    assert a.shape == (4,) and not np.isnan(a).any()
    assert np.isfinite(a[:2]).all() and np.isneginf(a[2:]).all()  # in a wall, off the map: impossible
    assert np.array_equal(a, second.log_likelihood(particles, ranges, ANGLES))
    assert a[0] > a[1]


def test_preparation_tells_a_table_build_from_a_cached_table(table_cache):
    m = corridor_map()
    beam = make("beam")
    before = beam.preparation(m)
    assert isinstance(before, Preparation) and before.slow
    assert "building" in before.note and "200x60 cells" in before.note and "16 headings" in before.note
    beam.set_map(m)  # builds the table and caches it on disk
    after = beam.preparation(m)
    assert not after.slow and "loading" in after.note
    assert not make("beam", ray_caster="exact").preparation(m).slow
    tiles = make("beam", range_table_lazy_cells=0).preparation(m)
    assert not tiles.slow and "tile by tile" in tiles.note
    lf = make("likelihood_field").preparation(m)
    assert not lf.slow and "likelihood field" in lf.note


@pytest.mark.parametrize("kind", KINDS)
def test_set_laser_offset_moves_the_laser(kind, table_cache):
    m = corridor_map()
    model = make(kind)
    model.set_map(m)
    offset = np.array([0.3, -0.05, 0.1])
    model.set_laser_offset(offset)
    got = model.laser_offset
    assert np.allclose(got, offset)
    got[0] = 9.0  # a copy: the model keeps its own
    assert np.allclose(model.laser_offset, offset)
    ranges = scan(m, offset)
    with_offset = model.log_likelihood(TRUTH[None], ranges, ANGLES)
    model.set_laser_offset((0.0, 0.0, 0.0))
    laser = compose(TRUTH, offset)
    assert with_offset == pytest.approx(model.log_likelihood(laser[None], ranges, ANGLES), abs=0.5)
    assert model.log_likelihood(TRUTH[None], ranges, ANGLES)[0] < with_offset[0] - 1.0


@pytest.mark.parametrize("kind", KINDS)
def test_deskew_offsets_and_range_max(kind, table_cache):
    m = corridor_map()
    model = make(kind)
    model.set_map(m)
    particles = np.array([TRUTH, TRUTH + [0.1, 0.05, 0.02]])
    ranges = scan(m, model.laser_offset)
    rigid = model.log_likelihood(particles, ranges, ANGLES)
    zero = model.log_likelihood(particles, ranges, ANGLES, offsets=np.zeros((ANGLES.size, 3)))
    assert model.supports_deskew and np.array_equal(rigid, zero)
    moved = np.zeros((ANGLES.size, 3))
    moved[:, 0] = np.linspace(0.0, 0.2, ANGLES.size)
    assert not np.array_equal(rigid, model.log_likelihood(particles, ranges, ANGLES, offsets=moved))
    short = model.log_likelihood(particles, ranges, ANGLES, range_max=3.0)
    assert np.isfinite(short).all() and not np.allclose(short, rigid)


def test_resolve_max_range():
    assert resolve_max_range(4.0, 30.0, 10.0) == 4.0
    assert resolve_max_range(-1.0, 30.0, 10.0) == 30.0
    assert resolve_max_range(0.0, None, 10.0) == 10.0
    assert resolve_max_range(-1.0, float("inf"), 10.0) == 10.0 and resolve_max_range(-1.0, 0.0, 10.0) == 10.0


def test_sensor_update_passes_the_scans_range_max(table_cache):
    m = corridor_map()
    model = LikelihoodFieldModel(laser_max_range=-1.0, laser_offset=(0.0, 0.0, 0.0), occupancy_map=m)
    ranges = scan(m)
    particles = np.array([TRUTH, TRUTH + [0.3, 0.1, 0.05], TRUTH + [-0.4, 0.2, -0.1]])
    for range_max in (3.0, 8.0):
        pf = MonteCarloLocalizer(MotionModel(), model, 3, resample_ess_fraction=0.0, rng=0)
        pf.set_particles(particles)
        result = pf.sensor_update(ranges, ANGLES, range_max=range_max)
        ll = model.log_likelihood(particles, ranges, ANGLES, range_max=range_max)
        want = np.exp(ll - ll.max())
        assert result.ok and np.allclose(pf.weights, want / want.sum())
    assert not np.allclose(model.log_likelihood(particles, ranges, ANGLES, range_max=3.0),
                           model.log_likelihood(particles, ranges, ANGLES, range_max=8.0))


def test_scratch_gives_back_the_tiles_built_inside_it(table_cache):
    m = corridor_map(width_cells=300)
    beam = BeamModel(ray_caster="lookup_table", range_table_lazy_cells=0, scan_theta_discretization=16,
                     table_width=61, occupancy_map=m)
    caster = beam.ray_caster
    assert isinstance(caster, TiledLookupTableRayCaster)
    ranges = scan(m, beam.laser_offset)
    beam.log_likelihood(TRUTH[None], ranges, ANGLES)  # tracking: its tile stays
    kept = caster.built.copy()
    far = np.array([[13.0, 1.5, 0.0]])
    with beam.scratch():
        inside = beam.log_likelihood(far, ranges, ANGLES)
        assert (caster.built & ~kept).any()
    assert np.array_equal(caster.built, kept)
    assert np.array_equal(inside, beam.log_likelihood(far, ranges, ANGLES))  # rebuilt on demand: the same rows
    xy = np.array([[13.0, 1.5], [1.0, 1.5], [13.1, 1.6], [1.1, 1.4]])
    order = beam.locality_order(xy)
    assert sorted(order.tolist()) == [0, 1, 2, 3]
    assert np.all(np.diff(caster.tile_ids(xy[order])) >= 0)
    lf = LikelihoodFieldModel(occupancy_map=m)
    with lf.scratch():
        lf.log_likelihood(far, ranges, ANGLES)
    assert lf.locality_order(xy).tolist() == [0, 1, 2, 3]


def test_the_range_scale_is_in_the_protocol_and_the_likelihood_field_declines_it(table_cache):
    """The beam model's probe casts the beams as its likelihood does and takes a new scale; the likelihood
    field casts no ranges: it says so in its class attribute and refuses both calls."""
    m = corridor_map()
    beam = make("beam", range_scale_estimation=True)
    beam.set_map(m)
    assert beam.supports_range_scale
    offsets = np.zeros((ANGLES.size, 3))
    offsets[:, 0] = np.linspace(0.0, 0.1, ANGLES.size)
    probe = beam.range_probe(ANGLES, offsets, range_max=30.0)
    poses = np.array([TRUTH, TRUTH + [0.1, 0.0, 0.0]])
    # the compiled probe against the numpy cast (its reference): equal but for rounding
    np.testing.assert_allclose(probe.cast(poses), beam.expected_ranges(poses, ANGLES, offsets), rtol=0, atol=1e-12)
    assert probe.reach == beam.table_range and probe.z_max == beam.max_range_for(30.0)
    assert probe.wall_depth == beam.params.map_wall_depth
    beam.set_range_scale(1.02)
    assert beam.params.lidar_scale_to_map_scale == 1.02
    lf = make("likelihood_field")
    assert not lf.supports_range_scale
    with pytest.raises(ValueError):
        lf.range_probe(ANGLES)
    with pytest.raises(ValueError):
        lf.set_range_scale(1.02)


def test_nothing_probes_or_pokes_a_sensor_model():
    """No getattr probing of sensor-model members and no attribute written from outside a model."""
    root = Path(__file__).resolve().parents[1] / "localization"
    probe = re.compile(r"getattr\([^)]*[\"'](supports_\w+|ray_caster|laser_offset|last_beams_used)[\"']")
    poke = re.compile(r"sensor(_model)?\.(laser_offset\w*|map|ray_caster|sigma_hit|z_max)\s*=[^=]")
    found = [f"{path.relative_to(root)}:{n}: {line.strip()}" for path in root.rglob("*.py")
             for n, line in enumerate(path.read_text().splitlines(), 1) if probe.search(line) or poke.search(line)]
    assert found == []
