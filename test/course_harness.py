"""Runs one of the MIT RSS course's unit-test modules, as they are, against this package.

    python test/course_harness.py sensor|motion COURSE_DIR

``COURSE_DIR`` is ``../shared/reference/course`` (never copied here). Its ``test/`` folder becomes the
package ``localization.test`` (the course's fixtures and test modules), the course's
``test/test_params.yaml`` is given to rclpy as the launch files give it, and for the sensor test the
course's ``test_map`` is published on ``/map`` as nav2's map_server publishes it (trinary, rows
flipped, transient local) once the test's subscriptions are up — the course's instructions start the
map after the test. The course's modules print their own verdicts ("All tests passed :)",
"Motion model test passed!"); the calling test reads them. A process of its own: the course's code
uses rclpy's default context and ``exit()``.
"""
from __future__ import annotations

import importlib
import importlib.util
import sys
import time
from pathlib import Path

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node


def register_course_tests(course: Path) -> None:
    """``localization.test`` = the course's ``test/`` folder (its fixtures and test modules)."""
    import localization
    spec = importlib.util.spec_from_file_location("localization.test", course / "test" / "__init__.py",
                                                  submodule_search_locations=[str(course / "test")])
    module = importlib.util.module_from_spec(spec)
    sys.modules["localization.test"] = module
    localization.test = module
    spec.loader.exec_module(module)


def map_server(course: Path) -> Node:
    """A node publishing the course's test map on /map as nav2's map_server does."""
    from nav_msgs.msg import OccupancyGrid

    from localization.core.occupancy_map import OccupancyMap
    from localization.ros.messages import occupancy_grid_msg
    from localization.ros.parameters import MAP_QOS
    node = Node("map_server")
    node.publisher = node.create_publisher(OccupancyGrid, "/map", MAP_QOS)
    node.msg = occupancy_grid_msg(OccupancyMap.from_yaml(course / "test_map" / "test_map.yaml"))
    return node


def run_sensor(course: Path, timeout: float) -> int:
    from localization.test.sensor_model_test import SensorModelTest
    test = SensorModelTest()
    server = map_server(course)
    executor = SingleThreadedExecutor()
    executor.add_node(test)
    executor.add_node(server)
    deadline = time.monotonic() + timeout
    while server.publisher.get_subscription_count() < 1 and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
    server.publisher.publish(server.msg)
    while test.num_passed < 3 and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
    print(f"course sensor tests passed: {test.num_passed} of 3", flush=True)
    return 0 if test.num_passed == 3 else 1


def run_motion() -> int:
    from localization.test.motion_model_test import MotionModelTest
    test = MotionModelTest()
    try:
        test.test_evaluate_motion_model()  # ends with exit() after its verdict
    except SystemExit:
        pass
    return 0


def main(argv: list[str]) -> int:
    which, course = argv[0], Path(argv[1]).resolve()
    register_course_tests(course)
    rclpy.init(args=["--ros-args", "--params-file", str(course / "test" / "test_params.yaml")])
    try:
        return run_sensor(course, timeout=float(argv[2]) if len(argv) > 2 else 60.0) if which == "sensor" \
            else run_motion()
    finally:
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
