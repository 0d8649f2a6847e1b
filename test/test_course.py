"""The MIT RSS course's package, drop-in: its own unit tests as they are, its parameter files, its
launch name, sigma_hit in its units, and the racecar_simulator ray caster its probabilities need.

The course's files are read from ``../shared/reference/course`` (never copied into the project).
"""
from __future__ import annotations

import importlib.util
import json
import logging
import os
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from localization.core.occupancy_map import OccupancyMap
from localization.core.parameters import Parameters
from localization.core.raycast import make_ray_caster
from localization.core.raycast.scan_simulator import (
    ScanSimulatorRayCaster,
    course_occupied,
    distance_field,
    distance_field_numpy,
)
from localization.sensor_model import SensorModel

ROOT = Path(__file__).resolve().parents[1]
HARNESS = Path(__file__).with_name("course_harness.py")
STAFF = dict(alpha_hit=0.74, alpha_short=0.07, alpha_max=0.07, alpha_rand=0.12, sigma_hit=8.0, table_width=201)


@pytest.fixture(scope="module")
def course(shared_dir) -> Path:
    path = shared_dir / "reference" / "course"
    assert (path / "test" / "sensor_model_test.py").is_file(), f"the course's files are missing in {path}"
    return path


@pytest.fixture(scope="module")
def fixtures(course):
    """The course's test fixtures (``localization.test`` in the course's package)."""
    spec = importlib.util.spec_from_file_location("course_fixtures", course / "test" / "__init__.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def test_map(course) -> OccupancyMap:
    return OccupancyMap.from_yaml(course / "test_map" / "test_map.yaml")


def _run_course_test(which: str, course: Path) -> str:
    out = subprocess.run([sys.executable, str(HARNESS), which, str(course)], capture_output=True, text=True,
                         timeout=300, env=os.environ.copy(), cwd=ROOT)
    return out.stdout + out.stderr


# ------------------------------------------------------------------ the course's own unit tests
def test_the_course_sensor_model_tests_pass_as_they_are(course):
    log = _run_course_test("sensor", course)
    for verdict in ("Map callback test passed :)", "Precompute test passed :)", "Evaluate test passed :)",
                    "All tests passed :)", "course sensor tests passed: 3 of 3"):
        assert verdict in log, log
    assert "failed" not in log and "errored" not in log, log


def test_the_course_motion_model_test_passes_as_it_is(course):
    log = _run_course_test("motion", course)
    assert "Motion model test passed!" in log, log
    assert "errored" not in log and "not quite right" not in log, log


# ------------------------------------------------------------------ the facade in the course's units
def test_sigma_hit_in_table_cells_gives_the_course_table(fixtures):
    sm = SensorModel()
    assert sm.sigma_hit == pytest.approx(8.0) and sm.table_width == 201  # the course's values by default
    for name, value in STAFF.items():
        setattr(sm, name, value)
    sm.precompute_sensor_model()
    expected = np.array(fixtures.TEST_PRECOMPUTED_TABLE)
    assert sm.sensor_model_table.shape == expected.shape
    assert np.abs(sm.sensor_model_table - expected).max() <= 1e-9
    sm.sigma_hit = 4.0  # a value in cells, not metres: a different table after precompute
    sm.precompute_sensor_model()
    assert np.abs(sm.sensor_model_table - expected).max() > 1e-3


def test_the_facade_gives_the_staff_probabilities_for_every_particle(fixtures, test_map):
    sm = SensorModel(ray_caster="scan_simulator", num_beams_per_particle=100, scan_theta_discretization=500)
    assert sm.evaluate(np.zeros((1, 3)), np.ones(100)) is None  # no map yet: the course returns nothing
    for name, value in STAFF.items():
        setattr(sm, name, value)
    sm.set_map(test_map)
    sm.precompute_sensor_model()
    assert np.allclose(sm.map, fixtures.TEST_MAP_ARRAY, atol=0.01) and sm.map_set
    got = sm.evaluate(np.array(fixtures.TEST_PARTICLES_2), np.array(fixtures.TEST_SENSOR_MODEL_INPUT_SCANS))
    expected = np.array(fixtures.TEST_SENSOR_MODEL_OUTPUT_PROBABILITIES)
    assert got.shape == expected.shape == (50,)
    assert np.all(np.abs(got - expected) <= 0.01 * np.abs(expected)), np.abs(got / expected - 1).max()
    # the project's caster is not the course's: its ranges end on the cell edge, not near its centre
    other = SensorModel(ray_caster="exact", **{k: v for k, v in (("num_beams_per_particle", 100),)})
    for name, value in STAFF.items():
        setattr(other, name, value)
    other.set_map(test_map)
    other_p = other.evaluate(np.array(fixtures.TEST_PARTICLES_2), np.array(fixtures.TEST_SENSOR_MODEL_INPUT_SCANS))
    assert not np.all(np.abs(other_p - expected) <= 0.01 * np.abs(expected))


def test_the_facade_takes_a_map_message_as_the_course_does(test_map):
    from localization.ros.messages import occupancy_grid_msg
    sm = SensorModel(ray_caster="scan_simulator")
    sm.map_callback(occupancy_grid_msg(test_map))
    assert sm.map_set and sm.resolution == pytest.approx(0.0504)
    assert sm.map.shape == (test_map.data.size,) and set(np.unique(sm.map)) <= {0.0, 1.0}  # unknown -1 -> 0


# ------------------------------------------------------------------ the course's ray caster
def _random_map(rng, h=37, w=53, yaw=0.0):
    data = np.where(rng.random((h, w)) < 0.12, 100, 0).astype(np.int8)
    data[rng.random((h, w)) < 0.05] = -1
    data[5:8, :30] = 100
    return OccupancyMap(data, 0.05, (-1.0, 0.5, yaw))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_distance_field_matches_its_numpy_reference(seed):
    m = _random_map(np.random.default_rng(seed))
    occupied = course_occupied(m.data)
    assert not occupied[m.data == -1].any()  # the course counts unknown as free
    np.testing.assert_array_equal(distance_field(occupied, m.resolution), distance_field_numpy(occupied, m.resolution))
    empty = np.zeros((4, 6), dtype=bool)  # no wall: the padded border is the nearest one
    np.testing.assert_allclose(distance_field(empty, 1.0)[0], [1, 1, 1, 1, 1, 1])


@pytest.mark.parametrize("yaw", [0.0, 3.14, -0.7])
def test_ray_march_matches_its_numpy_reference(yaw):
    rng = np.random.default_rng(4)
    m = _random_map(rng, yaw=yaw)
    caster = ScanSimulatorRayCaster(m, max_range=10.0, theta_bins=500)
    free = m.grid_to_world(np.argwhere(~course_occupied(m.data))[:, ::-1] + 0.5)
    xy = free[rng.integers(0, len(free), 300)] + rng.uniform(-0.02, 0.02, (300, 2))
    thetas = rng.uniform(-10, 10, 300)
    compiled = caster.cast_rays(np.c_[xy, np.zeros(300)], thetas)
    np.testing.assert_allclose(compiled, caster.march_numpy(xy[:, 0], xy[:, 1], thetas), rtol=0, atol=1e-12)
    assert np.all(compiled >= 0) and np.all(compiled <= 10.0)
    poses = np.c_[xy[:20], thetas[:20]]
    angles = np.linspace(-2.355, 2.355, 9)
    grid = caster.cast(poses, angles)
    assert grid.shape == (20, 9)
    np.testing.assert_array_equal(grid[3], caster.cast_rays(np.repeat(poses[3:4], 9, axis=0), angles))


def test_ray_caster_by_name_and_headings_in_bins():
    m = OccupancyMap(np.pad(np.zeros((40, 40), dtype=np.int8), 1, constant_values=100), 0.1)
    caster = make_ray_caster("scan_simulator", m, 20.0, theta_bins=4)
    assert isinstance(caster, ScanSimulatorRayCaster)
    # 4 bins: 0.6 rad rounds to heading 0 (the east wall), 1.0 rad to pi/2 (the north wall); ranges end at
    # the wall cell's centre (cell 20 -> 41 east, cell 10 -> 41 north)
    r = caster.cast_rays(np.array([[2.05, 1.05, 0.0], [2.05, 1.05, 0.0]]), np.array([0.6, 1.0]))
    assert r[0] == pytest.approx(2.1, abs=0.011) and r[1] == pytest.approx(3.1, abs=0.011)
    assert make_ray_caster("scan_simulator", m, 0.5, theta_bins=4).cast_rays(
        np.array([[2.05, 2.05, 0.0]]), np.array([0.0]))[0] == 0.5  # clipped to max_range


# ------------------------------------------------------------------ the course's parameter files
@pytest.mark.parametrize("name, angle_step, frame", [("params.yaml", 0, "base_link_pf"),
                                                     ("real_params.yaml", 11, "base_link")])
def test_the_course_parameter_files_are_accepted(course, caplog, name, angle_step, frame):
    with caplog.at_level(logging.INFO, logger="localization.parameters"):
        p = Parameters.from_yaml(course / name)
    assert p.angle_step == angle_step and p.particle_filter_frame == frame
    assert p.scan_theta_discretization == 500 and type(p.scan_theta_discretization) is int
    with pytest.raises(Exception, match="unknown parameter 'angle_stride'"):
        Parameters.from_yaml(course / name, angle_stride=3)  # everything else stays strict
    with pytest.raises(Exception, match="scan_theta_discretization"):
        Parameters(scan_theta_discretization=500.5)


def test_the_node_declares_the_course_parameter_files(course):
    """The node's ROS path: the file's values as rcl hands them over (500.0 a double, "/base_link")."""
    import rclpy
    import yaml
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    from localization.ros.parameters import declare_parameters
    values = yaml.safe_load((course / "real_params.yaml").read_text())["particle_filter"]["ros__parameters"]
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    try:
        node = Node("particle_filter", context=ctx,
                    parameter_overrides=[Parameter(k, value=v) for k, v in values.items()])
        params = declare_parameters(node)
        assert params.angle_step == 11 and params.scan_theta_discretization == 500
        assert params.odom_topic == "/vesc/odom" and params.particle_filter_frame == "base_link"
        node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)


def test_angle_step_takes_every_nth_beam():
    from localization.core.scan import ScanData, downsample_scan
    scan = ScanData(0.0, np.arange(1081) * 0.01 + 0.1, -2.356, 2.356, 4.712 / 1080, 0.02, 30.0)
    beams = downsample_scan(scan, 100, angle_step=11)
    np.testing.assert_array_equal(beams.indices, np.arange(0, 1081, 11))
    assert beams.ranges.size == 99  # the course's num_beams_per_particle for this stride
    assert downsample_scan(scan, 100).ranges.size == 100  # 0: num_beams_per_particle spread evenly


@pytest.mark.parametrize("name, extra", [("params.yaml", ["--odom-topic", "/vesc/odom"]), ("real_params.yaml", [])])
def test_the_course_parameter_files_replay_a_real_bag(tmp_path, course, name, extra):
    from localization.eval.datasets import REAL_BAGS, real_bag_path
    from localization.tools import replay as R
    rb = REAL_BAGS["bag3"]
    out = tmp_path / "out"
    code = R.main([str(real_bag_path("bag3")), "--map", rb.map, "--params", str(course / name), "--out", str(out),
                   "--initial-pose", ",".join(map(str, rb.start)), "--no-plots", "--no-reference", "--quiet",
                   *extra])
    assert code == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["odom_topic"] == "/vesc/odom" and m["sensor_updates"] > 40
    assert m["scan_map_agreement"]["median"] >= 0.6, m["scan_map_agreement"]
    rows = np.loadtxt(out / "poses.csv", delimiter=",", skiprows=1, usecols=(0, 1, 2, 3))
    assert np.all(np.isfinite(rows)) and np.all(np.diff(rows[:, 0]) >= 0)
    assert np.hypot(*(rows[-1, 1:3] - rows[0, 1:3])) > 3.0  # the car drives up the corridor


# ------------------------------------------------------------------ the course's launch name
def test_the_course_launch_file_starts_the_node_with_the_package_parameter_file():
    launch = ET.parse(ROOT / "launch" / "localize.launch.xml").getroot()
    node = launch.find("node")
    assert node.get("pkg") == "localization" and node.get("exec") == "particle_filter"
    assert node.get("name") == "particle_filter"
    assert "particle_filter = localization.particle_filter:main" in (ROOT / "setup.py").read_text()
    default = launch.find("arg[@name='params_file']").get("default")
    params_file = Path(default.replace("$(find-pkg-share localization)", str(ROOT)))
    assert params_file.is_file() and node.find("param").get("from") == "$(var params_file)"
    Parameters.from_yaml(params_file)  # valid for the node
    assert 'glob("launch/*.xml")' in (ROOT / "setup.py").read_text()  # installed with the package
