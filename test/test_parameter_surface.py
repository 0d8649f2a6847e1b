"""The parameter surface a newcomer reads: the robot files hold only their robot's values."""
from __future__ import annotations

import pytest
import yaml

from localization.core.parameters import BY_NAME, Parameters
from localization.core.paths import config_dir

ROBOT_FILES = ("real_params.yaml", "pioneer_params.yaml")
MAX_ROBOT_KEYS = 25


def _section(name: str) -> dict:
    doc = yaml.safe_load((config_dir() / name).read_text())
    return doc["particle_filter"]["ros__parameters"]


@pytest.mark.parametrize("name", ROBOT_FILES)
def test_robot_file_is_short_and_every_key_differs_from_its_default(name):
    section = _section(name)
    assert 0 < len(section) <= MAX_ROBOT_KEYS, f"{name} sets {len(section)} keys"
    assert set(section) <= set(BY_NAME), set(section) - set(BY_NAME)
    defaults = Parameters()
    given = Parameters(section)  # valid, values in the table's types
    redundant = [k for k in section if given[k] == defaults[k]]
    assert not redundant, f"{name} repeats table defaults: {redundant}"

