"""localization-demo's job table: which replays a command line plans (each a frozen ``Job`` feeding one
table), with what parameters; what its workers print (the bag in front of every localizer line, a
replay's notes once each). No replay is run."""
from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import pytest

from localization.eval.datasets import PIONEER_BAGS, REAL_BAGS, REPORT_TRIALS
from localization.tools.demo import cli, heldout, jobs, worker
from localization.tools.demo.jobs import Job, Parts, Result


def _parts(*argv) -> Parts:
    return Parts.from_args(cli.build_parser().parse_args(list(argv)))


CALIBRATED = {b: {"odom_time_offset_s": 0.01 * i, "odom_speed_scale": 1.0 + 0.01 * (i % 3), "odom_yaw_rate_scale": 1.0,
                  "odom_yaw_rate_bias": 0.0, "laser_offset_x": 0.2, "lidar_scale_to_map_scale": 1.0,
                  "map_wall_depth": 0.01} for i, b in enumerate([*REAL_BAGS, *PIONEER_BAGS])}


def _tables(plan) -> dict:
    counts: dict = {}
    for job in plan:
        counts[job.table] = counts.get(job.table, 0) + 1
    return counts


def test_the_full_demo_plans_every_table(tmp_path):
    plan = jobs.plan(_parts(), REPORT_TRIALS, {"random_seed": 0}, tmp_path)
    assert _tables(plan) == {"sim": 3 + 9, "fast": 2, "real": 3, "heldout": 3, "pioneer": 3, "pioneer_heldout": 3}
    assert len({j.summary_key for j in plan}) == len(plan)  # one summary.json entry each
    assert all(j.seed == 0 for j in plan)
    with pytest.raises(dataclasses.FrozenInstanceError):
        plan[0].label = "other"
    by_key = {j.summary_key: j for j in plan}
    done = {f"calibrate:{b}": {"name": b, "values": v} for b, v in CALIBRATED.items()}
    held = cli.with_fold(by_key["bag2@heldout"], done)  # its fold, once the other bags are calibrated
    fold = heldout.fold_of("bag2", list(REAL_BAGS), CALIBRATED.__getitem__, cli.FOLD_KEYS["heldout"])
    assert held.overrides["odom_time_offset"] == fold["odom_time_offset"] and not held.plots
    assert fold["calibrated_on"] == ["bag1", "bag3"] and held.summary_key == "bag2@heldout"
    assert held.out == str(tmp_path / "heldout" / "bag2") and held.params_file == "real_params.yaml"
    assert "odom_time_offset" not in by_key["bag2"].overrides  # the all-bags replay: the file's own values
    lg = cli.with_fold(by_key["lgfloor2@heldout"], done)
    assert lg.force_global and lg.overrides["scan_stamp"] == "first_beam" and lg.pioneer
    assert lg.overrides["odom_speed_scale"] == pytest.approx(1.005)  # the mean of trace0's and trace1's
    assert "map_wall_depth" not in lg.overrides  # pinned for the Pioneer
    fixed = by_key["trial2_2mps_scale1.02_fixed"]
    assert fixed.world.scale == 1.02 and fixed.overrides["range_scale_estimation"] is False
    assert dict(fixed.recording)["speed"] == 2.0 and fixed.bag is None and fixed.trial == "trial2_noise0.3"
    assert by_key["trial1_noise0"].world is None and by_key["fast_unaligned"].table == "fast"


@pytest.mark.parametrize("argv, tables", [
    (["--only", "heldout"], {"real": 3, "heldout": 3}),
    (["--only", "pioneer"], {"pioneer": 3, "pioneer_heldout": 3}),
    (["--skip-real"], {"sim": 12, "fast": 2}),  # no RSS 2022 bag and no Pioneer bag either: both are real bags
    (["--skip-sim", "--skip-heldout", "--skip-pioneer"], {"real": 3}),
    (["--skip-perturbed", "--skip-fast", "--loop", "--skip-real"], {"sim": 4}),
    (["--skip-sim", "--skip-pioneer", "--motion-sweep"], {"real": 3, "sweep": 12, "heldout": 3}),
])
def test_options_choose_the_parts(argv, tables, tmp_path):
    parts = _parts(*argv)
    assert _tables(jobs.plan(parts, REPORT_TRIALS, {"random_seed": 0}, tmp_path)) == tables
    assert bool(parts.calibrated_bags) == ("heldout" in tables or "pioneer_heldout" in tables)


def test_the_sweep_scales_the_motion_noise_and_writes_nothing(tmp_path):
    sweep = [j for j in jobs.plan(_parts("--skip-sim", "--skip-pioneer", "--skip-heldout", "--motion-sweep", "0.5"),
                                  REPORT_TRIALS, {"random_seed": 4}, tmp_path) if j.table == "sweep"]
    base = Job("bag1", "real", "basement_fixed", "real_params.yaml").load_parameters()
    assert [j.label for j in sweep] == list(REAL_BAGS) and {j.summary_key for j in sweep} == {
        f"{b}@0.5" for b in REAL_BAGS}
    for j in sweep:
        assert j.out is None and j.overrides["motion_a_trans"] == pytest.approx(0.5 * base["motion_a_trans"])
        assert j.seed == 4


def test_a_replays_notes_are_printed_once_with_the_replays_that_said_them():
    mount = "laser pose in base_link from the bag's TF (laser): x 0.275 m, y 0.000 m, yaw 0.0 deg"
    results = [Result(Job(f"trial{k}", "sim", "stata_basement", "params.yaml"), notes=(mount,)) for k in range(26)]
    results.append(Result(Job("lgfloor2", "pioneer", "lgfloor", "pioneer_params.yaml"),
                          notes=("odometry from TF", "laser pose x 0.135 m")))
    lines = worker.distinct_notes(results)
    assert len(lines) == 3 and sum(mount in line for line in lines) == 1
    assert lines[0].endswith("(trial0 and 25 more replays)") and lines[2].endswith("(lgfloor2)")


def test_the_localizers_lines_name_the_job(capsys):
    log = logging.getLogger("localization")
    with worker.labelled_log("bag2"):
        log.warning("lost: the scans fit the map nowhere near the estimate")
        log.info("not shown: below WARNING, as without the demo")
    log.warning("after the job")  # no handler of the demo's any more
    err = capsys.readouterr().err.splitlines()
    assert "localization-demo: bag2: lost: the scans fit the map nowhere near the estimate" in err
    assert not any("not shown" in line for line in err)
    assert not any(line.startswith("localization-demo: bag2: after") for line in err)


def test_main_is_short():
    import inspect
    assert len(inspect.getsource(cli.main).splitlines()) <= 40
    assert all(len(Path(m.__file__).read_text().splitlines()) <= 500 for m in (cli, jobs, worker))


def test_kernels_are_compiled_once_per_kernel_set_before_the_workers(monkeypatch, tmp_path):
    from localization.core import compile_cache
    seen = []
    monkeypatch.setattr(compile_cache, "ensure_compiled", lambda params, logger=None: seen.append(params) or "cached")
    plan = jobs.plan(_parts(), REPORT_TRIALS, {"random_seed": 0}, tmp_path)
    worker.compile_kernels(plan)
    sets = [tuple(compile_cache.kernels_for(p)) for p in seen]
    assert len(sets) == len(set(sets)) >= 1  # each set once
    assert set(sets) == {tuple(compile_cache.kernels_for(j.load_parameters())) for j in plan}
