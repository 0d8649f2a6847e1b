"""The console scripts agree with each other: how they pick parameters and topics, how they take
``-p`` overrides (``NAME=VALUE`` and the ROS ``NAME:=VALUE``), how they treat an existing output,
what their help says. Only argument handling and the checks done before any work: fast."""
from __future__ import annotations

import argparse

import pytest

from localization.eval.datasets import REAL_BAGS, real_bag_path
from localization.tools import args as args_
from localization.tools import calibrate, demo, replay, simulate, tune

REAL = real_bag_path("bag3")  # the car's bag: /scan and /vesc/odom, no /odom


# --------------------------------------------------------------------------------------------
# -p NAME=VALUE / NAME:=VALUE
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("text, expected", [
    ("num_particles=500", ("num_particles", 500)),
    ("recovery:=false", ("recovery", False)),
    ("recovery:= true", ("recovery", True)),
    ("odom_topic:=/vesc/odom", ("odom_topic", "/vesc/odom")),
    ("sigma_hit=2.5", ("sigma_hit", 2.5)),
])
def test_param_override_takes_both_spellings(text, expected):
    assert args_.param_override(text) == expected


@pytest.mark.parametrize("text, words", [
    ("num_particles", "expected NAME=VALUE or NAME:=VALUE"),
    ("=5", "expected NAME=VALUE or NAME:=VALUE"),
    ("num particles=5", "expected NAME=VALUE or NAME:=VALUE"),
    ("no_such_param:=1", "unknown parameter 'no_such_param'"),
    ("sigma_hit=[1, 2", "not valid YAML"),
])
def test_param_override_refuses_anything_else_in_one_line(text, words):
    with pytest.raises(argparse.ArgumentTypeError) as exc:
        args_.param_override(text)
    assert words in str(exc.value) and "\n" not in str(exc.value)


@pytest.mark.parametrize("tool", [replay, demo])
def test_tools_accept_ros_style_overrides_on_the_command_line(tool):
    ns = tool.build_parser().parse_args((["bag", "--map", "m"] if tool is replay else [])
                                        + ["-p", "recovery:=false", "-p", "num_particles=300"])
    assert dict(ns.overrides) == {"recovery": False, "num_particles": 300}


def test_bad_override_is_a_usage_error(capsys):
    with pytest.raises(SystemExit) as exc:
        replay.main(["bag", "--map", "m", "-p", "recovery"])
    assert exc.value.code == 2
    assert "NAME:=VALUE" in capsys.readouterr().err


def test_topic_list_is_one_comma_separated_value():
    ap = argparse.ArgumentParser()
    ap.add_argument("--topics", type=args_.topic_list)
    ap.add_argument("bag")
    ns = ap.parse_args(["--topics", "/scan,/vesc/odom", "drive.bag"])
    assert ns.topics == ["/scan", "/vesc/odom"] and ns.bag == "drive.bag"  # the bag is not swallowed
    with pytest.raises(argparse.ArgumentTypeError):
        args_.topic_list("/scan,not a topic")


# --------------------------------------------------------------------------------------------
# Parameters and topics: one way for every tool
# --------------------------------------------------------------------------------------------


def test_car_bag_without_params_gets_the_car_parameters(capsys):
    params = args_.parameters_for_bags(None, {"num_particles": 123}, [REAL], None, "some-tool")
    assert params.odom_topic == "/vesc/odom" and params.num_particles == 123
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "some-tool: note:" in err and "real_params" in err
    # an explicit file or odometry topic is used as given, silently
    assert args_.parameters_for_bags("params", {}, [REAL], None).odom_topic == "/odom"
    assert args_.parameters_for_bags(None, {}, [REAL], "/vesc/odom").odom_topic == "/odom"
    assert capsys.readouterr().err == ""


def test_calibrate_picks_parameters_and_topics_as_replay_does(monkeypatch, tmp_path, capsys):
    seen = {}

    def fake_calibrate_bag(bag, occupancy_map, scan_topic, odom_topic, initial_pose, mount, log=None, **timing):
        seen.update(scan=scan_topic, odom=odom_topic, mount=mount)
        raise calibrate.CalibrationError("stop here")
    monkeypatch.setattr(calibrate, "calibrate_bag", fake_calibrate_bag)
    start = ",".join(map(str, REAL_BAGS["bag3"].start))
    assert calibrate.main([str(REAL), "--map", "basement_fixed", f"--initial-pose={start}"]) == 1
    assert seen["scan"] == "/scan" and seen["odom"] == "/vesc/odom"
    err = capsys.readouterr().err
    assert "real_params" in err and "stop here" in err
    # replay picks the same for the same bag
    ns = replay.build_parser().parse_args([str(REAL), "--map", "basement_fixed"])
    assert replay.params_for_bag(ns).odom_topic == "/vesc/odom"


def test_calibrate_missing_topic_names_the_bags_topics(capsys):
    rc = calibrate.main([str(REAL), "--map", "basement_fixed", "--params", "params", "--initial-pose=1,0,1.6"])
    err = capsys.readouterr().err.strip()
    assert rc == 1 and len(err.splitlines()) == 1
    assert "odometry topic /odom not in bag" in err and "/vesc/odom" in err and "--odom-topic" in err


def test_replay_help_says_what_the_default_parameters_are(capsys):
    with pytest.raises(SystemExit):
        replay.main(["--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "real_params" in out and "/vesc/odom" in out


def test_simulate_help_explains_every_option(capsys):
    with pytest.raises(SystemExit):
        simulate.main(["--help"])
    out = " ".join(capsys.readouterr().out.split())
    for option, words in (("--seed SEED", "random seed"), ("--storage {sqlite3,mcap}", "storage format"),
                          ("--overwrite", "replace an existing bag")):
        assert option in out
        assert words in out.rsplit(option, 1)[1][:200], option  # the option's own line, not the usage


# --------------------------------------------------------------------------------------------
# Outputs: refused when they exist, checked before the work
# --------------------------------------------------------------------------------------------


def test_calibrate_checks_out_before_anything_else(tmp_path, capsys, monkeypatch):
    def must_not_run(*a, **k):
        raise AssertionError("calibrated although --out could not be written")
    monkeypatch.setattr(calibrate, "calibrate_bag", must_not_run)
    # the bag does not exist either: the --out problem is reported first
    missing = tmp_path / "no_such_folder" / "calib.yaml"
    assert calibrate.main([str(tmp_path / "nope.bag"), "--map", "basement_fixed", "--out", str(missing)]) == 1
    err = capsys.readouterr().err
    assert "no_such_folder" in err and "does not exist" in err
    existing = tmp_path / "calib.yaml"
    existing.write_text("keep me\n")
    start = ",".join(map(str, REAL_BAGS["bag3"].start))
    assert calibrate.main([str(REAL), "--map", "basement_fixed", f"--initial-pose={start}", "--out",
                           str(existing)]) == 1
    err = capsys.readouterr().err
    assert "exists already" in err and "--overwrite" in err
    assert existing.read_text() == "keep me\n"


def test_output_problem():
    import tempfile
    from pathlib import Path
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        assert args_.output_problem(d / "new", False) is None
        assert args_.output_problem(d, False) is None  # an empty folder is fine
        (d / "f.txt").write_text("x")
        assert "exists already" in args_.output_problem(d, False)
        assert args_.output_problem(d, True) is None
        assert "not a folder" in args_.output_problem(d / "f.txt", True)
        assert "is a folder" in args_.output_problem(d, True, kind="file")
        assert args_.output_problem(d / "f.txt", True, kind="file") is None


def test_demo_refuses_an_existing_out_unless_overwrite(tmp_path, capsys, monkeypatch):
    out = tmp_path / "demo"
    out.mkdir()
    (out / "summary.json").write_text("{}")
    assert demo.main(["--out", str(out), "--skip-sim", "--skip-real"]) == 1
    err = capsys.readouterr().err
    assert "exists already" in err and "--overwrite" in err
    assert (out / "summary.json").read_text() == "{}"
    assert demo.main(["--out", str(out), "--skip-sim", "--skip-real", "--overwrite"]) == 0  # nothing to replay
    assert (out / "summary.json").read_text() != "{}"
    printed = capsys.readouterr().out
    assert "Pioneer" not in printed and "RSS" not in printed  # no real bag of either robot


# --------------------------------------------------------------------------------------------
# localization-tune's arguments
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("value", ["0", "-3", "x"])
def test_tune_trials_below_one_is_a_usage_error(value, capsys):
    with pytest.raises(SystemExit) as exc:
        tune.main(["bag", "--map", "m", "--trials", value])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "--trials" in err and "Traceback" not in err and "Warning" not in err


def test_tune_summary_rounds_per_bag_errors():
    s = {"study": "s", "storage": "j", "n_trials": 3, "n_complete": 3, "n_pruned": 0, "n_failed": 0,
         "n_repeated": 1, "error_sources": ["reference", "truth", "agreement"],
         "baseline_value": 0.1234567, "baseline_errors": [0.0623456789, 0.0601, 0.3456789],
         "best_value": 0.02, "best_errors": [0.0244, 0.0511111, 0.1], "best_trial": 2, "best_params": {"a": 0.5},
         "wall_s_per_trial_mean": 1.0, "elapsed_s": 3.0, "out": "o"}
    text = tune.human_summary(s)
    assert "62 mm, 60 mm, 0.346 (1 - agreement)" in text
    assert "24 mm, 51 mm, 0.100 (1 - agreement)" in text
    assert "0.0623456789" not in text and "1 repeated parameter sets not re-run" in text


# --------------------------------------------------------------------------------------------
# Progress output
# --------------------------------------------------------------------------------------------


def test_progress_is_off_without_a_terminal_and_busy_keeps_the_lines(capsys):
    import time

    from localization.eval.progress import busy, progress_bar, progress_enabled
    assert progress_enabled(None) is False  # pytest's captured stderr is not a terminal
    assert progress_enabled(True) is True
    with busy("matching", enabled=False) as say:
        say("step one")
    assert capsys.readouterr().err == "step one\n"  # the lines without a bar
    with busy("matching", enabled=True) as say:
        say("step two")
        time.sleep(0.7)  # the ticker redraws the elapsed time
    err = capsys.readouterr().err
    assert "step two" in err and "matching [" in err
    bar = progress_bar(range(3), desc="x", enabled=False)
    assert list(bar) == [0, 1, 2] and bar.disable
