"""The parameter surface a newcomer reads: every parameter in one group with a one-line description,
``--help`` and docs/node.md generated from the table, robot files holding only their robot's values."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from localization.core import parameters as P
from localization.core.parameters import BY_NAME, GROUPS, PARAMETERS, Param, Parameters
from localization.core.paths import config_dir

REPO = Path(__file__).resolve().parents[1]
ROBOT_FILES = ("real_params.yaml", "pioneer_params.yaml")
MAX_ROBOT_KEYS = 25
MAX_DESCRIPTION = 100  # characters: one line of --help


def test_every_parameter_is_in_exactly_one_known_group_and_every_group_is_used():
    assert len(BY_NAME) == len(PARAMETERS), "a name declared twice"
    assert all(p.group in GROUPS for p in PARAMETERS), [p.name for p in PARAMETERS if p.group not in GROUPS]
    members = {g: [p.name for p in PARAMETERS if p.group == g] for g in GROUPS}
    assert all(members.values()), [g for g, names in members.items() if not names]
    assert sum(len(names) for names in members.values()) == len(PARAMETERS)
    assert set(GROUPS) == {"topics and frames", "robot", "odometry calibration", "sensor model", "filter", "recovery",
                           "performance", "output"}
    with pytest.raises(ValueError, match="unknown parameter group"):
        P._grouped("topics", Param("x", 1, "an x"))


def test_every_parameter_has_a_one_line_description_and_a_rule():
    for p in PARAMETERS:
        assert p.description and "\n" not in p.description, p.name
        assert len(p.description) <= MAX_DESCRIPTION, f"{p.name}: {len(p.description)} characters"
        assert p.rule and p.check is not None, p.name


def test_help_text_lists_every_parameter_under_its_group_with_default_rule_and_description():
    text = P.help_text()
    group, seen = None, {}
    lines = text.splitlines()
    for i, line in enumerate(lines):
        if line and not line.startswith(" "):
            title = line.split(":")[0].lower()
            assert title in GROUPS, line
            group = title
        elif line.startswith("  ") and not line.startswith("      "):
            name = line.split(" = ")[0].strip()
            p = BY_NAME[name]
            assert name not in seen and p.group == group, name
            assert line == f"  {name} = {P.show_value(p.default)}  [{p.rule}]"
            assert lines[i + 1] == f"      {p.description}"
            seen[name] = group
    assert list(seen) == [p.name for g in GROUPS for p in PARAMETERS if p.group == g]
    assert len(seen) == len(PARAMETERS)


def test_particle_filter_help_prints_every_parameter_with_its_description():
    """A pip-only user has no ``ros2 param describe``: ``--help`` is their reference."""
    out = subprocess.run([sys.executable, "-m", "localization.particle_filter", "--help"], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.startswith("usage:"), out.stderr
    assert P.help_text() in out.stdout


def test_show_value_writes_defaults_as_a_parameter_file_does():
    assert [P.show_value(v) for v in (True, False, "", "/map", 0.05, 2000, -1.0)] == [
        "true", "false", '""', "/map", "0.05", "2000", "-1.0"]
    assert P.show_value(BY_NAME["kld_bin_theta"].default) == "0.1745329252"


def test_docs_node_md_holds_the_generated_table():
    text = (REPO / "docs" / "node.md").read_text()
    assert text.count(P.MARKDOWN_BEGIN) == 1 and text.count(P.MARKDOWN_END) == 1
    between = text.split(P.MARKDOWN_BEGIN)[1].split(P.MARKDOWN_END)[0].strip("\n")
    assert between == P.markdown(), "docs/node.md is stale: python -m localization.core.parameters --markdown"
    for p in PARAMETERS:
        assert f"| `{p.name}` |" in between, p.name


def test_the_markdown_writer_replaces_only_the_marked_section(tmp_path, capsys):
    doc = tmp_path / "doc.md"
    doc.write_text(f"# head\n\n{P.MARKDOWN_BEGIN}\nold table\n{P.MARKDOWN_END}\n\ntail\n")
    assert P.main(["--markdown", str(doc)]) == 0
    text = doc.read_text()
    assert text.startswith("# head\n\n") and text.endswith("\n\ntail\n") and "old table" not in text
    assert P.markdown() in text
    doc.write_text("no markers here\n")
    with pytest.raises(ValueError, match="section"):
        P.main(["--markdown", str(doc)])
    capsys.readouterr()
    assert P.main([]) == 0
    assert capsys.readouterr().out.strip() == P.help_text()


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
