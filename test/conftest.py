"""Test-suite wide set-up.

Every test run keeps DDS traffic on loopback and uses its own ROS domain, so parallel runs
(and CI next to a developer) never cross-talk. This must happen before rclpy is initialised.
"""
import os
import random

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("ROS_DOMAIN_ID", str(random.Random(os.getpid()).randint(1, 100)))
os.environ.setdefault("MPLBACKEND", "Agg")

from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

SHARED = Path(os.environ.get("LOCALIZATION_SHARED_DIR",
                            Path(__file__).resolve().parents[1] / ".." / "shared")).resolve()


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    assert SHARED.is_dir(), f"shared data not found at {SHARED} (set LOCALIZATION_SHARED_DIR)"
    return SHARED


@pytest.fixture(scope="session")
def maps_dir(shared_dir) -> Path:
    return Path(os.environ.get("LOCALIZATION_MAPS_DIR", shared_dir / "maps"))


# ------------------------------------------------------------------ live-node fixtures (test_node*.py)
@pytest.fixture(scope="module")
def context():
    """An rclpy context of its own (node_harness is imported here: only node tests load rclpy)."""
    import node_harness as h
    import rclpy
    ctx = h.init_context()
    yield ctx
    rclpy.shutdown(context=ctx)


@pytest.fixture
def runner(context):
    """``runner(**parameter_overrides)`` starts a node + probe; everything is shut down after the test."""
    import node_harness as h
    started = []

    def start(**overrides):
        r = h.start_runner(context, **overrides)
        started.append(r)
        return r

    yield start
    for r in started:
        r.close()


@pytest.fixture(scope="module")
def drive():
    import node_harness as h
    return h.synthetic_drive()
