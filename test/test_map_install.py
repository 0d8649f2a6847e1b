"""The node's map installer asks the sensor model whether preparing a map is slow (its
``preparation``) and prepares it off the executor's thread only then; a broken map is refused."""
from __future__ import annotations

import threading
from collections import Counter
from types import SimpleNamespace

import pytest

pytest.importorskip("rclpy")

from helpers import corridor_map  # noqa: E402

from localization.core.models.sensor import Preparation  # noqa: E402
from localization.ros.messages import occupancy_grid_msg  # noqa: E402


class FakeLocalizer:
    def __init__(self, slow: bool):
        self.slow, self.has_map, self.ready, self.map_pending = slow, False, False, False
        self.prepared_on = None
        self.installed = threading.Event()

    def map_preparation(self, occupancy_map):
        return Preparation(self.slow, "range table: building it")

    def begin_map_preparation(self, pending=True):
        self.map_pending = pending

    def prepare_ray_caster(self, occupancy_map):
        self.prepared_on = threading.current_thread().name
        return object()

    def set_map(self, occupancy_map, caster):
        self.has_map, self.ready, self.map_pending = True, True, False
        self.installed.set()


class Log:
    def __init__(self):
        self.lines = []

    def info(self, line):
        self.lines.append(("info", line))

    def warning(self, line):
        self.lines.append(("warning", line))

    def error(self, line):
        self.lines.append(("error", line))


class Watchdog:
    def __init__(self):
        self.events = []

    def __getattr__(self, name):  # map_building, map_ready, map_failed
        return lambda *args: self.events.append(name)


def _installer(slow: bool):
    from localization.ros.map_install import MapInstaller
    loc, log, counts, installed = FakeLocalizer(slow), Log(), Counter(), []
    params = SimpleNamespace(map_topic="/map", map_frame="map")
    inst = MapInstaller(params, loc, Watchdog(), log, counts, lambda m, replacing: installed.append(replacing))
    return inst, loc, log, counts, installed


@pytest.mark.parametrize("slow", [True, False])
def test_the_sensor_model_decides_where_the_map_is_prepared(slow):
    inst, loc, log, counts, installed = _installer(slow)
    try:
        inst.receive(occupancy_grid_msg(corridor_map()))
        assert loc.installed.wait(10.0)
        assert inst.worker is not None and _wait(lambda: counts["map"] == 1)
        assert installed == [False]
        here = threading.current_thread().name
        assert (loc.prepared_on == "map_preparation") is slow and (loc.prepared_on == here) is not slow
        noted = any("range table: building it; odometry is kept meanwhile" in line for _, line in log.lines)
        assert noted is slow and ("map_building" in inst.watchdog.events) is slow
    finally:
        inst.stop()


def test_a_map_without_free_space_is_refused_in_one_line():
    inst, loc, log, counts, installed = _installer(False)
    try:
        msg = occupancy_grid_msg(corridor_map())
        msg.data = [100] * len(msg.data)
        inst.receive(msg)
        assert counts["map"] == 1 and not loc.has_map and not installed
        assert [kind for kind, _ in log.lines] == ["error"] and "no free cell" in log.lines[0][1]
    finally:
        inst.stop()


def _wait(predicate, timeout=10.0) -> bool:
    import time
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.01)
    return predicate()
