"""localization-demo's simulated trials both ways: clean-map rows and perturbed-world rows (map-frame error,
error against the world-frame truth, recoveries, false recoveries)."""
from __future__ import annotations

import json
from dataclasses import replace

from localization.eval.datasets import sim_bag
from localization.sim.perturb import STANDARD_PERTURBATION
from localization.tools import demo as D
from localization.tools.demo import cli


def _sim(label, trial, world):
    """A simulated trial's replay as the job table has it (``world``: its perturbation, None: the map)."""
    return D.Job(label, "sim", "stata_basement", "params.yaml", trial=trial,
                 recording=() if world is None else (("world", world),))


def _metrics(mean, world=None, recoveries=0, false=0):
    stats = {"mean": mean, "median": mean, "p95": mean, "max": mean, "rms": mean}
    m = {"ct_error_m": stats, "time_to_converge_s": 0.2, "heading_error_mean_abs_rad": 0.01, "recoveries": recoveries,
         "false_recoveries": false, "scan_map_agreement": {"median": 0.9}}
    if world is not None:
        m["world_ct_error_m"] = {**stats, "mean": world}
    return m


def test_perturbed_runs_are_the_standard_world_and_2mps_drives():
    runs = D.perturbed_runs(["trial1_noise0", "trial2_noise0.3"])
    assert runs["trial1_noise0_perturbed"] == ("trial1_noise0", {"world": STANDARD_PERTURBATION}, {})
    assert runs["trial2_noise0.3_perturbed"] == ("trial2_noise0.3", {"world": STANDARD_PERTURBATION}, {})
    for scale in (1.01, 1.02):
        drive = {"speed": 2.0, "world": replace(STANDARD_PERTURBATION, scale=scale)}
        assert runs[f"trial2_2mps_scale{scale:g}"] == ("trial2_noise0.3", drive, {})
        # the same recording with the range scale fixed as configured (not learnt online)
        fixed = {"range_scale_estimation": False}
        assert runs[f"trial2_2mps_scale{scale:g}_fixed"] == ("trial2_noise0.3", drive, fixed)
    # every trial at 2 m/s in the standard world
    assert runs["trial1_2mps_scale1.01"] == ("trial1_noise0", {"speed": 2.0, "world": STANDARD_PERTURBATION}, {})
    assert len(runs) == 7


def test_sim_table_shows_clean_rows_then_perturbed_rows():
    world = STANDARD_PERTURBATION
    results = [
        D.Result(_sim("trial2_noise0.3_perturbed", "trial2_noise0.3", world),
                 _metrics(0.0123, world=0.0456, recoveries=1, false=2)),
        D.Result(_sim("trial2_noise0.3", "trial2_noise0.3", None), _metrics(0.0078)),
        D.Result(_sim("trial2_2mps_scale1.02", "trial2_noise0.3", replace(world, scale=1.02)), error="no bag"),
    ]
    lines = D.sim_table(results).splitlines()
    assert "vs world" in lines[0] and "false" in lines[0] and "recov" in lines[0]
    assert [ln.split()[0] for ln in lines[1:]] == ["trial2_noise0.3", "trial2_noise0.3_perturbed",
                                                   "trial2_2mps_scale1.02"]
    clean, perturbed, failed = lines[1:]
    assert clean.split()[1] == "map" and clean.count("0.008") == 5  # mean, median, p95, max and vs world: one truth
    assert "perturbed s1.01" in perturbed and "0.046" in perturbed and "0.012" in perturbed
    assert perturbed.split()[-4:-2] == ["1", "2"]  # recoveries, false recoveries
    assert "0.183" in perturbed  # the report's trial-2 figure
    assert "error: no bag" in failed


def test_perturbed_recordings_have_their_own_cache_entry():
    clean = sim_bag("trial2_noise0.3", duration=0.5)
    perturbed = sim_bag("trial2_noise0.3", duration=0.5, world=STANDARD_PERTURBATION)
    assert clean != perturbed and STANDARD_PERTURBATION.label() in perturbed.parent.name
    config = json.loads((perturbed.parent / "config.json").read_text())
    assert config["config"]["world"]["scale"] == 1.01


def test_demo_prints_both_row_sets(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(cli, "REPORT_TRIALS", ("trial2_noise0.3",))
    out = tmp_path / "out"
    code = D.main(["--skip-real", "--skip-fast", "--skip-pioneer", "--duration", "2", "--particles", "200",
                   "--jobs", "1", "--out", str(out)])
    assert code == 0
    text = capsys.readouterr().out
    rows = {ln.split()[0]: ln for ln in text.splitlines() if ln.startswith("trial2_")}
    assert list(rows) == ["trial2_noise0.3", "trial2_noise0.3_perturbed", "trial2_2mps_scale1.01",
                          "trial2_2mps_scale1.01_fixed", "trial2_2mps_scale1.02", "trial2_2mps_scale1.02_fixed"]
    assert " map " in rows["trial2_noise0.3"] and "perturbed s1.02" in rows["trial2_2mps_scale1.02_fixed"]
    summary = json.loads((out / "summary.json").read_text())
    assert "world_ct_error_m" not in summary["trial2_noise0.3"]  # the clean world: one truth
    for label in ("trial2_noise0.3_perturbed", "trial2_2mps_scale1.01", "trial2_2mps_scale1.02",
                  "trial2_2mps_scale1.02_fixed"):
        m = summary[label]
        assert m["false_recoveries"] == 0 and m["recoveries"] == 0
        # scored against both truths (which differ by (1 − 1/s)·|p − c|; the errors of a 2-s drive are mostly
        # its convergence: test_sim_perturbed.py compares them)
        assert m["world_ct_error_m"]["mean"] != m["ct_error_m"]["mean"]
        assert m["truth_source"] == "/tf (map -> base_link)"
