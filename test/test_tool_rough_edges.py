"""What a new user meets first on the command line: a map name that is not there, negative numbers after
``--initial-pose``, the parameter files the help names. Argument handling only: fast."""
from __future__ import annotations

import argparse

import pytest

from localization.core import paths
from localization.core.occupancy_map import MapError
from localization.eval.replay import ReplayError
from localization.eval.replay import load_map as replay_load_map
from localization.tools import args as args_
from localization.tools import calibrate, demo, play, replay, simulate, tune

# --------------------------------------------------------------------------------------------
# A bare map name that no folder has
# --------------------------------------------------------------------------------------------


@pytest.fixture
def extra_maps(monkeypatch, tmp_path):
    (tmp_path / "garage.yaml").write_text("image: garage.png\nresolution: 0.05\norigin: [0, 0, 0]\n")
    monkeypatch.setenv("LOCALIZATION_MAPS_DIR", str(tmp_path))
    return tmp_path


def _assert_names_every_folder_and_map(message: str) -> None:
    assert "no_such_map" in message and "\n" not in message
    for folder in paths.map_search_dirs():
        assert str(folder) in message
    for name in ("basement_fixed", "stata_basement", "garage"):  # the package's, and the extra folder's
        assert name in message
    assert message.index("maps available") > message.index(str(paths.map_search_dirs()[-1]))


def test_map_not_found_names_every_folder_searched_and_the_maps_there(extra_maps):
    assert len(paths.map_search_dirs()) == 3
    _assert_names_every_folder_and_map(paths.map_not_found("no_such_map"))
    assert paths.available_maps()["garage"] == extra_maps / "garage.yaml"
    assert paths.available_maps()["basement_fixed"] == paths.package_maps_dir() / "basement_fixed.yaml"


def test_tools_refuse_a_missing_map_name_with_the_full_list(extra_maps, capsys):
    with pytest.raises(ReplayError) as exc:
        replay_load_map("no_such_map")
    _assert_names_every_folder_and_map(str(exc.value))
    with pytest.raises(MapError) as exc:
        args_.load_map("no_such_map")
    _assert_names_every_folder_and_map(str(exc.value))
    # a YAML path that is not there is still named as given
    with pytest.raises(ReplayError, match="map not found: .*elsewhere.yaml"):
        replay_load_map(extra_maps / "elsewhere.yaml")


def test_simulate_refuses_a_missing_map_name_in_one_line(extra_maps, tmp_path, capsys):
    assert simulate.main([str(tmp_path / "bag"), "--trial", "trial1_noise0", "--map", "no_such_map"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    _assert_names_every_folder_and_map(err)


# --------------------------------------------------------------------------------------------
# Negative numbers after --initial-pose (and --start, --waypoints)
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("value, expected", [("-1,2,0", (-1.0, 2.0, 0.0)), ("-6.0,20.0,-2.24", (-6.0, 20.0, -2.24)),
                                             ("-.5,-1e-3,3", (-0.5, -0.001, 3.0)), ("1,-2,-3", (1.0, -2.0, -3.0))])
def test_negative_initial_pose_needs_no_equals_sign(value, expected):
    assert replay.build_parser().parse_args(["bag", "--map", "m", "--initial-pose", value]).initial_pose == expected
    assert calibrate.build_parser().parse_args(["bag", "--map", "m", "--initial-pose", value]).initial_pose \
        == expected
    assert play.build_parser().parse_args(["bag", "--initial-pose", value]).initial_pose == expected
    ns = tune.build_parser().parse_args(["a", "b", "--map", "m", "--initial-pose", value, "--initial-pose", "-1,0,0"])
    assert ns.initial_poses == [expected, (-1.0, 0.0, 0.0)] and [str(b) for b in ns.bags] == ["a", "b"]
    assert simulate.build_parser().parse_args(["out", "--start", value]).start == expected
    # the '=' spelling still works
    assert replay.build_parser().parse_args(["bag", "--map", "m", f"--initial-pose={value}"]).initial_pose == expected


def test_negative_waypoints_and_what_is_not_a_number_list():
    ns = simulate.build_parser().parse_args(["out", "--waypoints", "-1,2;-3,4.5"])
    assert [tuple(w) for w in ns.waypoints] == [(-1.0, 2.0), (-3.0, 4.5)]
    ap = replay.build_parser()
    with pytest.raises(SystemExit):  # an option after --initial-pose is still an option: no value given
        ap.parse_args(["bag", "--map", "m", "--initial-pose", "--global"])
    # only values of number options are joined; a '--' ends the options
    assert args_.join_negative_values(["--initial-pose", "-1,2,0", "--seed", "-1", "--", "--initial-pose", "-1,2,0"],
                                      {"--initial-pose"}) == ["--initial-pose=-1,2,0", "--seed", "-1", "--",
                                                              "--initial-pose", "-1,2,0"]
    assert replay.build_parser().parse_args(["bag", "--map", "m", "--seed", "-1"]).seed == -1


def test_a_bad_pose_is_still_a_usage_error(capsys):
    with pytest.raises(SystemExit) as exc:
        replay.build_parser().parse_args(["bag", "--map", "m", "--initial-pose", "-1,2"])
    assert exc.value.code == 2 and "X,Y,YAW" in capsys.readouterr().err
    with pytest.raises(argparse.ArgumentTypeError):
        args_.pose("-1,x,0")


# --------------------------------------------------------------------------------------------
# Help texts name the package's parameter files
# --------------------------------------------------------------------------------------------


def test_parameter_files_are_read_from_the_config_folder(monkeypatch, tmp_path):
    assert {"params", "real_params", "pioneer_params"} <= set(paths.parameter_files())
    assert "tune_space" not in paths.parameter_files()  # a search space, not a parameter file
    (tmp_path / "config").mkdir()
    (tmp_path / "config" / "my_robot.yaml").write_text("particle_filter:\n  ros__parameters:\n    num_particles: 9\n")
    (tmp_path / "config" / "notes.yaml").write_text("a: 1\n")
    monkeypatch.setattr(paths, "config_dir", lambda: tmp_path / "config")
    assert paths.parameter_files() == ["my_robot"]


@pytest.mark.parametrize("tool", [replay, calibrate, tune])
def test_help_lists_every_parameter_file(tool, capsys):
    with pytest.raises(SystemExit):
        tool.main(["--help"])
    out = " ".join(capsys.readouterr().out.split())
    for name in paths.parameter_files():
        assert name in out.split("--params", 1)[1], name
    assert "pioneer_params" in out


def test_demo_parser_is_the_tools_parser():
    assert isinstance(demo.build_parser(), args_.Parser)
