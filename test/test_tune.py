"""localization-tune: the search space, the score, the study (resume, several worker processes).

Short simulated bags (3 s), few particles and beams, so the whole file runs in well under a minute
or two; the tuning outcome on longer bags is in docs/tuning.md."""
from __future__ import annotations

import csv
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import optuna
import pytest

from localization.core.parameters import BY_NAME, PARAMETERS, Parameters
from localization.eval.datasets import sim_bag
from localization.eval.tuning import (
    SpaceError,
    load_space,
    make_storage,
    space_from_dict,
    split_trials,
)
from localization.tools import tune

BAD_START = """\
particle_filter:
  ros__parameters:
    num_particles: 200
    num_beams_per_particle: 20
    ray_caster: lookup_table
    sigma_hit: 0.025
    squash_factor: 1.0
    motion_a_trans: 0.001
    motion_a_lateral: 0.001
    motion_a_rot: 0.001
    motion_a_rot_to_trans: 0.0
    motion_a_trans_to_rot: 0.0
    motion_floor_xy: 0.0
    motion_floor_theta: 0.0
    roughening_xy: 0.0
    roughening_theta: 0.0
"""

SPACE = """\
motion_a_trans: {low: 0.02, high: 1.0, log: true}
motion_a_rot: {low: 0.05, high: 2.0, log: true}
motion_floor_xy: {low: 0.0, high: 0.05}
sigma_hit: {low: 0.05, high: 0.5, log: true}
squash_factor: {low: 1.0, high: 5.0}
num_beams_per_particle: {low: 10, high: 30, step: 10}
"""


@pytest.fixture(scope="module")
def bags() -> list[str]:
    return [str(sim_bag("trial1_noise0", duration=3.0)), str(sim_bag("trial3_noise0.6", duration=3.0))]


@pytest.fixture()
def start(tmp_path) -> tuple[Path, Path]:
    params, space = tmp_path / "bad.yaml", tmp_path / "space.yaml"
    params.write_text(BAD_START)
    space.write_text(SPACE)
    return params, space


def _args(bags, start, out, *extra) -> list[str]:
    params, space = start
    return [*bags, "--map", "stata_basement", "--params", str(params), "--space", str(space), "--out", str(out),
            "--quiet", *extra]


def _study(out: Path):
    return optuna.load_study(study_name="localization-tune", storage=make_storage(str(out / "study.journal")))


# --------------------------------------------------------------------------------------------
# The tuner and localization-replay: one feed loop, one scorer
# --------------------------------------------------------------------------------------------


def test_tuner_and_replay_score_a_real_bag_alike():
    """The same parameters and seed give the same estimates, the same per-scan agreement (the pose
    at each scan's time, ranges scaled by lidar_scale_to_map_scale) and the same per-bag error in
    the tuner and in localization-replay (real bag, no ground truth)."""
    import numpy as np

    from localization.core.paths import config_dir
    from localization.eval.datasets import REAL_BAGS, real_bag_path
    from localization.eval.feed import make_scorer
    from localization.eval.reference import track_errors
    from localization.eval.replay import ReplayOptions, run_replay
    from localization.eval.tuning import evaluate_bag, load_bag, replay_bag

    rb = REAL_BAGS["bag3"]
    params = Parameters.from_yaml(config_dir() / "real_params.yaml", random_seed=5)
    assert params.lidar_scale_to_map_scale != 1.0  # the range scale matters for this comparison
    res = run_replay(ReplayOptions(real_bag_path("bag3"), rb.map, params, initial_pose=rb.start, reference=False))
    bag = load_bag(real_bag_path("bag3"), scan_topic=params.scan_topic, odom_topic=params.odom_topic,
                   initialpose_topic=params.initialpose_topic, initial_pose=rb.start)
    scorer = make_scorer(res.occupancy_map, params)
    log, _ = replay_bag(bag, res.occupancy_map, params, scorer=scorer)
    est_t, est_poses = log.estimates()
    np.testing.assert_array_equal(est_t, res.est_t)
    np.testing.assert_array_equal(est_poses, res.est_poses)
    assert len(res.agreement) > 200
    np.testing.assert_array_equal(np.asarray(log.agreement_t), res.agreement_t)
    np.testing.assert_array_equal(np.asarray(log.agreement), res.agreement)
    # the per-bag error, truth-free: 1 - median agreement (the tuner) vs the replay's figure
    s = evaluate_bag(bag, res.occupancy_map, params, scorer=scorer)
    assert s.source == "agreement"
    assert abs(s.error - (1.0 - float(np.median(res.agreement)))) <= 1e-9, (s.error, np.median(res.agreement))
    assert s.recoveries == res.counts["recoveries"]
    # against a reference track: the mean position error of the same estimates at the scans' times
    np.testing.assert_array_equal(log.scan_track()[0], res.scan_t)
    np.testing.assert_array_equal(log.scan_track()[1], res.scan_poses)
    ref_t, ref_p = res.scan_t[::4], res.scan_poses[::4] + [0.05, -0.02, 0.0]
    bag.reference = (ref_t, ref_p)
    s_ref = evaluate_bag(bag, res.occupancy_map, params, scorer=scorer)
    expect = float(track_errors(res.scan_t, res.scan_poses, ref_t, ref_p).position.mean())
    assert expect == pytest.approx(math.hypot(0.05, 0.02), abs=1e-9)
    assert s_ref.source == "reference" and abs(s_ref.error - expect) <= 1e-9, (s_ref.error, expect)


# --------------------------------------------------------------------------------------------
# Search space
# --------------------------------------------------------------------------------------------


def test_shipped_space_names_only_table_parameters():
    space = load_space()
    assert len(space) >= 10
    for e in space:
        assert e.name in BY_NAME
        if e.choices is None:
            assert e.low < e.high
            for v in (e.low, e.high):  # both ends are valid values of the parameter
                Parameters({e.name: v})
    names = {e.name for e in space}
    assert {"motion_a_trans", "sigma_hit", "squash_factor", "alpha_hit", "num_particles",
            "num_beams_per_particle"} <= names
    for name in ("odom_time_offset", "odom_speed_scale", "odom_yaw_rate_scale", "odom_yaw_rate_bias"):
        if name in BY_NAME:
            assert name in names, f"{name} is in the parameter table but not in the shipped space"


@pytest.mark.parametrize("doc, words", [
    ({"no_such_param": {"low": 0, "high": 1}}, "unknown parameter 'no_such_param'"),
    ({"sigma_hit": {"low": 5.0, "high": 1.0}}, "must be below high"),
    ({"sigma_hit": {"low": 0.0, "high": 3.0, "log": True}}, "log range needs low > 0"),
    ({"sigma_hit": {"low": -1.0, "high": 3.0}}, "out of the parameter's range"),
    ({"num_particles": {"low": 10.5, "high": 300}}, "integer parameter"),
    ({"ray_caster": {"low": 0, "high": 1}}, "not numeric"),
    ({"ray_caster": {"choices": ["lookup_table", "warp_drive"]}}, "'warp_drive' is not valid"),
    ({"sigma_hit": {"low": 1.0, "hi": 3.0}}, "unknown key"),
    ({"sigma_hit": 3.0}, "expected"),
])
def test_bad_space_is_one_clear_error(doc, words):
    with pytest.raises(SpaceError) as exc:
        space_from_dict(doc)
    assert words in str(exc.value)
    assert "\n" not in str(exc.value)


def test_split_trials_adds_up():
    assert split_trials(7, 2) == [4, 3]
    assert split_trials(1, 3) == [1, 0, 0]
    assert sum(split_trials(20, 3)) == 20


@pytest.mark.parametrize("text, words", [
    ("motion_a_trans: {low: 0.1, high: 0.5}\nnot_a_parameter: {low: 1, high: 2}\n", "unknown parameter"),
    ("motion_a_trans: {low: 0.1, high: [0.5\n", "not valid YAML"),
    ("motion_a_trans: {low: 0.5, high: 0.1}\n", "must be below high"),
    ("- just\n- a list\n", "expected a mapping"),
])
def test_cli_bad_space_file_one_line_exit_1(bags, start, tmp_path, capsys, text, words):
    space = tmp_path / "broken.yaml"
    space.write_text(text)
    params, _ = start
    rc = tune.main([bags[0], "--map", "stata_basement", "--params", str(params), "--space", str(space),
                    "--out", str(tmp_path / "out"), "--trials", "1", "--quiet"])
    err = capsys.readouterr().err.strip()
    assert rc == 1
    assert len(err.splitlines()) == 1, err
    assert err.startswith("localization-tune: error: ") and words in err
    assert not (tmp_path / "out" / "study.journal").exists()


def test_cli_missing_space_file(bags, start, tmp_path, capsys):
    params, _ = start
    rc = tune.main([bags[0], "--map", "stata_basement", "--params", str(params), "--space",
                    str(tmp_path / "nope.yaml"), "--out", str(tmp_path / "out"), "--quiet"])
    err = capsys.readouterr().err.strip()
    assert rc == 1 and len(err.splitlines()) == 1 and "not found" in err


# --------------------------------------------------------------------------------------------
# Tuning
# --------------------------------------------------------------------------------------------


def test_twenty_trials_beat_bad_start(bags, start, tmp_path, capsys):
    out = tmp_path / "out"
    rc = tune.main(_args(bags, start, out, "--trials", "20", "--json"))
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    s = json.loads(captured.out)
    assert s["n_trials"] == 20
    assert s["baseline_value"] is not None and s["best_value"] is not None
    # the deliberately bad start (no motion noise, a razor-thin sensor model) loses the track
    assert s["best_value"] < 0.5 * s["baseline_value"]
    assert max(s["best_errors"]) < min(s["baseline_errors"])
    assert s["error_sources"] == ["truth", "truth"]
    assert set(s["best_params"]) == {e.name for e in load_space(start[1])}
    # best_params.yaml: a complete parameter file with the tuned values
    best = Parameters.from_yaml(out / "best_params.yaml")
    text = (out / "best_params.yaml").read_text()
    for p in PARAMETERS:
        assert f"    {p.name}:" in text, p.name
    for name, value in s["best_params"].items():
        assert best[name] == pytest.approx(value)
    assert best.num_particles == 200  # untuned: from the start file
    rows = list(csv.DictReader(open(out / "trials.csv")))
    assert len(rows) == 20 and rows[0]["baseline"] == "True"
    assert float(rows[0]["value"]) == pytest.approx(s["baseline_value"], rel=1e-4)
    for name in ("optimization_history", "param_importances"):
        assert (out / f"{name}.png").stat().st_size > 1000, s.get("notes")


def test_two_worker_processes_share_one_study(bags, start, tmp_path, capsys):
    out = tmp_path / "out"
    rc = tune.main(_args(bags, start, out, "--trials", "6", "--jobs", "2", "--json"))
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    assert json.loads(captured.out)["n_trials"] == 6
    trials = _study(out).get_trials()
    assert sorted(t.number for t in trials) == list(range(6))
    pids = {t.user_attrs.get("worker_pid") for t in trials}
    assert len(pids) == 2 and os.getpid() not in pids  # two worker processes did the trials


def _cli(bags, start, out, *extra):
    return [sys.executable, "-m", "localization.tools.tune", *_args(bags, start, out, *extra)]


def test_two_commands_on_one_storage_add_up(bags, start, tmp_path):
    """Two independent commands (as on two machines) on one storage: one study, trials add up."""
    storage = tmp_path / "shared.journal"
    procs = [subprocess.Popen(_cli(bags, start, tmp_path / f"out{k}", "--trials", "3", "--storage", str(storage)),
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for k in range(2)]
    for p in procs:
        _, err = p.communicate(timeout=300)
        assert p.returncode == 0, err
    study = optuna.load_study(study_name="localization-tune", storage=make_storage(str(storage)))
    numbers = [t.number for t in study.get_trials()]
    assert sorted(numbers) == list(range(6))


def test_stopped_study_resumes(bags, start, tmp_path):
    out = tmp_path / "out"
    cmd = [a for a in _cli(bags, start, out, "--trials", "1000") if a != "--quiet"]  # per-trial lines wanted
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    seen = 0
    deadline = time.monotonic() + 120
    while seen < 4 and time.monotonic() < deadline:
        line = proc.stderr.readline()
        if not line:
            break
        seen += line.startswith("trial ")
    proc.send_signal(signal.SIGINT)
    proc.communicate(timeout=60)
    assert seen >= 4
    assert proc.returncode == 130
    before = _study(out).get_trials()
    finished = [t for t in before if t.state.is_finished()]
    assert len(finished) >= 4
    assert sum(bool(t.user_attrs.get("baseline")) for t in before) == 1

    rc = tune.main(_args(bags, start, out, "--trials", "3"))
    assert rc == 0
    after = _study(out).get_trials()
    assert len(after) == len(before) + 3
    assert sorted(t.number for t in after) == list(range(len(after)))
    assert sum(bool(t.user_attrs.get("baseline")) for t in after) == 1  # the baseline is not re-run
    assert (out / "best_params.yaml").is_file()


def test_baseline_outside_a_list_of_choices(bags, start, tmp_path, capsys):
    """A start value that is not among a parameter's choices (or 0 on a log range) still gets its
    baseline trial."""
    params, _ = start
    params.write_text(BAD_START.replace("ray_caster: lookup_table", "ray_caster: lookup_table_exact"))
    space = tmp_path / "choices.yaml"
    space.write_text("ray_caster: {choices: [lookup_table]}\nsigma_hit: {low: 0.05, high: 0.5}\n"
                     "motion_a_trans_to_rot: {low: 0.01, high: 1.0, log: true}\n")  # start 0.0: not on a log axis
    rc = tune.main([bags[0], "--map", "stata_basement", "--params", str(params), "--space", str(space),
                    "--out", str(tmp_path / "out"), "--trials", "3", "--quiet", "--json"])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    s = json.loads(captured.out)
    assert s["n_complete"] == 3 and s["baseline_value"] is not None
    assert s["baseline_params"] == {"sigma_hit": 0.025}


def test_compare_scores_two_parameter_files(bags, start, tmp_path, capsys):
    good = tmp_path / "good.yaml"
    good.write_text("particle_filter:\n  ros__parameters:\n    num_particles: 200\n    num_beams_per_particle: 20\n"
                    "    ray_caster: lookup_table\n")
    rc = tune.main(_args(bags, start, tmp_path / "out", "--compare", str(good), "--compare-seeds", "1,2", "--json"))
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    r = json.loads(captured.out)
    assert r["seeds"] == [1, 2] and r["start"]["sources"] == ["truth", "truth"]
    assert len(r["compare"]["errors"]) == 2
    assert r["compare"]["error"] < r["start"]["error"]
    assert not (tmp_path / "out" / "study.journal").exists()  # no study


# --------------------------------------------------------------------------------------------
# Resuming: no parameter set evaluated twice
# --------------------------------------------------------------------------------------------


RESUME_SPACE = "motion_a_trans: {low: 0.02, high: 1.0, log: true}\nsquash_factor: {low: 1.0, high: 5.0}\n"


def test_resumed_study_draws_new_parameter_sets(bags, start, tmp_path):
    start[1].write_text(RESUME_SPACE)
    out = tmp_path / "out"
    assert tune.main(_args(bags[:1], start, out, "--trials", "3")) == 0
    assert tune.main(_args(bags[:1], start, out, "--trials", "3")) == 0  # same --out: the study continues
    trials = _study(out).get_trials()
    sampled = [tuple(sorted(t.params.items())) for t in trials if not t.user_attrs.get("baseline")]
    assert len(trials) == 6
    assert len(set(sampled)) == len(sampled) == 5  # the second command did not draw the first one's again
    assert not any("repeat_of" in t.user_attrs for t in trials)


def test_a_repeated_parameter_set_returns_the_stored_value(bags, start, tmp_path, capsys):
    start[1].write_text(RESUME_SPACE)
    out = tmp_path / "out"
    assert tune.main(_args(bags[:1], start, out, "--trials", "2")) == 0
    study = _study(out)
    first = [t for t in study.get_trials() if not t.user_attrs.get("baseline")][0]
    study.enqueue_trial(first.params)  # as a second machine on a shared study might propose it
    capsys.readouterr()
    assert tune.main(_args(bags[:1], start, out, "--trials", "1", "--json")) == 0
    s = json.loads(capsys.readouterr().out)
    last = _study(out).get_trials()[-1]
    assert last.params == first.params and last.state == optuna.trial.TrialState.COMPLETE
    assert last.user_attrs["repeat_of"] == first.number and last.value == first.value
    assert last.user_attrs["error_0"] == first.user_attrs["error_0"] and last.user_attrs["wall_s"] == 0.0
    assert s["n_trials"] == 3 and s["n_repeated"] == 1
    rows = list(csv.DictReader(open(out / "trials.csv")))
    assert rows[-1]["repeat_of"] == str(first.number) and rows[0]["repeat_of"] == ""
