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
