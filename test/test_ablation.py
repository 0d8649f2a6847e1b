"""The ablation table's logic on made-up results: the rule that says a figure moved beyond the baseline's
seed-to-seed spread, the cells, the rows, the text and markdown tables, and the plan (which parts a switch
cannot change). No replay runs here."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from localization.benchmarks import ablation as A
from localization.benchmarks import ablation_jobs as J
from localization.benchmarks import ablation_table as T
from localization.core.parameters import Parameters

ERROR = T.Column("err", "err", ("rss",), T.mean_of("median"), "lower", "an error", decimals=3)
AGREE = T.Column("agr", "agr", ("rss",), T.mean_of("agree"), "higher", "an agreement", decimals=3)
COUNT = T.Column("ok", "ok", ("global",), T.within("converged_s", 5.0), "higher", "runs in time", count=True)


def test_a_mean_outside_the_baseline_range_moves_and_says_which_way():
    base = T.Stat((0.020, 0.022, 0.021))
    assert T.moved(base, T.Stat((0.024, 0.025, 0.026)), ERROR) == "worse"
    assert T.moved(base, T.Stat((0.015, 0.016, 0.017)), ERROR) == "better"
    assert T.moved(base, T.Stat((0.015, 0.016, 0.017)), AGREE) == "worse"  # higher is better there
    assert T.moved(base, T.Stat((0.019, 0.021, 0.023)), ERROR) is None  # mean 0.021: inside 0.020-0.022
    # outside the range by less than half the last printed digit (0.0005): the table could not show it
    assert T.moved(base, T.Stat((0.0223, 0.0224, 0.0225)), ERROR) is None
    assert T.moved(base, T.Stat((0.0226, 0.0228, 0.0230)), ERROR) == "worse"


def test_counts_are_not_widened_and_inert_or_incomplete_cells_never_move():
    ten = T.Stat((10.0, 10.0, 10.0))
    assert T.moved(ten, T.Stat((10.0, 10.0, 9.0)), COUNT) == "worse"
    assert T.moved(ten, T.Stat((10.0, 10.0, 10.0)), COUNT) is None
    base = T.Stat((0.020, 0.022, 0.021))
    assert T.moved(base, T.Stat((0.05, 0.05, 0.05), inert=True), ERROR) is None
    assert T.moved(base, T.Stat((0.05, None, 0.05)), ERROR) is None
    assert T.moved(T.Stat((0.020, None, 0.021)), T.Stat((0.05, 0.05, 0.05)), ERROR) is None


def test_cells_print_mean_and_sample_sd_or_say_why_not():
    assert T.fmt_cell(T.Stat((0.020, 0.022, 0.021)), ERROR) == "0.021 ± 0.001"
    assert T.fmt_cell(T.Stat((10.0, 10.0, 9.0)), COUNT) == "9.67 ± 0.58"
    assert T.fmt_cell(T.Stat((0.02, 0.02, 0.02), inert=True), ERROR) == "="
    assert T.fmt_cell(T.Stat((None, None)), ERROR) == "n/a"
    assert T.fmt_cell(T.Stat((0.020, None, 0.022)), ERROR) == "0.021 ± 0.001 (2/3 seeds)"
    assert T.fmt_cell(T.Stat((math.inf, 2.0, 3.0)), ERROR).startswith("never ± n/a")
    assert T.fmt_range(T.Stat((0.020, 0.022, 0.021)), ERROR) == "0.020–0.022"


def test_reductions_over_a_parts_jobs():
    figs = [{"median": 0.02, "along": -0.01, "converged_s": 0.5}, {"median": 0.04, "along": 0.03, "converged_s": None},
            {"median": None, "along": 0.02, "converged_s": 7.0}]
    assert T.mean_of("median")(figs) == pytest.approx(0.03)
    assert T.mean_of("along", absolute=True)(figs) == pytest.approx(0.02)
    assert T.max_of("median")(figs) == 0.04 and T.min_of("median")(figs) == 0.02
    assert T.within("converged_s", 5.0)(figs) == 1.0
    assert T.median_time("converged_s")(figs) == 7.0
    assert T.sum_of("false")(figs) is None and T.sum_of("median")(figs) == pytest.approx(0.06)


def outcomes():
    """Two parts over seeds 0-2: 'slow' moves the RSS error, 'same' is inert on the global part."""
    out = []
    for seed in (0, 1, 2):
        out.append(T.Outcome("rss", "baseline", seed, ({"median": 0.020 + 0.001 * seed, "false": 0},)))
        out.append(T.Outcome("rss", "slow", seed, ({"median": 0.030 + 0.001 * seed, "false": 0},)))
        out.append(T.Outcome("rss", "same", seed, ({"median": 0.021 + 0.0005 * seed, "false": 0},)))
        for o in (T.Outcome("global", "baseline", seed, ({"converged_s": 1.0, "false": 0},)),):
            out += [o, T.Outcome("global", "slow", seed, ({"converged_s": 9.0 if seed else 1.0, "false": 1},)),
                    T.Outcome("global", "same", seed, o.figures, inert=True)]
    return out


ROWS = [("baseline", "baseline", "(files)"), ("slow", "slow thing", "`x: 1`"), ("same", "same thing", "`y: 0`")]


def test_rows_hold_one_stat_per_shown_column_and_their_moves():
    rows = T.build_rows(outcomes(), ROWS, [0, 1, 2])
    base, slow, same = rows
    assert set(base.cells) == {"rss_median", "rss_p95", "rss_along", "glob_ok", "false", "jump", "ms_rss"}
    assert base.cells["rss_median"].values == pytest.approx((0.020, 0.021, 0.022))
    assert slow.moves == {"rss_median": "worse", "glob_ok": "worse", "false": "worse"}
    assert same.moves == {} and same.cells["glob_ok"].inert and not same.cells["rss_median"].inert
    assert not same.cells["false"].inert  # one of its parts ran
    assert base.cells["rss_p95"].finite == []  # no figure: n/a, never a move
    assert T.moves_text(slow).startswith("RSS med (worse)") and T.moves_text(same) == "none"


def test_a_failed_job_blanks_its_seed():
    out = [o if not (o.mechanism == "slow" and o.seed == 1 and o.group == "rss") else
           T.Outcome("rss", "slow", 1, (), error="boom") for o in outcomes()]
    slow = T.build_rows(out, ROWS, [0, 1, 2])[1]
    assert slow.cells["rss_median"].values[1] is None and "rss_median" not in slow.moves


def test_text_and_markdown_tables():
    rows = T.build_rows(outcomes(), ROWS, [0, 1, 2])
    text = T.render_text(rows)
    lines = text.splitlines()
    assert lines[0].startswith("row") and "moves beyond the baseline's spread" in lines[0]
    assert lines[2].strip().startswith("baseline min–max") and "0.020–0.022" in lines[2]
    assert "0.031 ± 0.001*" in text and "none" in lines[4]
    md = T.render_markdown(rows).splitlines()
    assert len({line.count("|") for line in md}) == 1  # every row has every column
    assert "**0.031 ± 0.001**" in md[4] and "| = |" in md[5] and "0.020–0.022" in md[3]
    assert "RSS med" in T.column_notes(rows) and "Pio agree" not in T.column_notes(rows)


def test_every_switch_is_a_valid_parameter_and_differs_from_the_defaults_somewhere():
    for mech in J.MECHANISMS.values():
        Parameters(dict(mech.overrides))  # valid names and values
        assert any(J.inert(g, key) is None for key, m in J.MECHANISMS.items() if m is mech for g in J.PARAMS_FILE)


def test_inert_parts_are_the_ones_a_switch_cannot_change():
    assert J.inert("rss", "beamskip") == "already off in real_params.yaml"
    assert J.inert("perturbed", "grip") == "already off in params.yaml"
    assert J.inert("pioneer", "grip") == "already off in pioneer_params.yaml"
    assert "sweep timing" in J.inert("kidnap", "deskew")
    assert "global start" in J.inert("global", "tempered")
    assert J.inert("rss", "range_scale") is None and J.inert("rss", "grip") is None
    assert J.inert("kidnap", "tempered") is None and J.inert("perturbed", "beamskip") is None


def test_the_plan_leaves_out_inert_parts_and_carries_fold_switch_and_seed():
    folds = {"bag1": {"odom_time_offset": 0.13}}
    jobs, skipped = J.plan(["rss", "perturbed"], ["grip", "beamskip"], [0, 1], folds, 10, None)
    assert skipped == {("rss", "beamskip"): "already off in real_params.yaml",
                       ("perturbed", "grip"): "already off in params.yaml"}
    rss = [j for j in jobs if j.group == "rss"]
    assert len(rss) == 3 * 2 * 2 and {j.mechanism for j in rss} == {"baseline", "grip"}
    grip = next(j for j in rss if j.label == "bag1" and j.mechanism == "grip" and j.seed == 1)
    assert dict(grip.overrides) == {"odom_time_offset": 0.13, "odom_max_acceleration": 0.0, "random_seed": 1}
    assert len([j for j in jobs if j.group == "perturbed"]) == 7 * 2 * 2
    assert [(j.label, j.mechanism, j.seed) for j in rss[:4]] == [("bag1", "baseline", 0), ("bag1", "grip", 0),
                                                                  ("bag2", "baseline", 0), ("bag2", "grip", 0)]
    picked, _ = J.plan(["rss", "global"], [], [0], {}, 10, {"rss": ["bag2"], "global": J.spread_starts(10, 2)})
    assert [(j.group, j.label) for j in picked] == [("rss", "bag2"), ("global", "0"), ("global", "5")]
    assert J.spread_starts(10, None) == [str(r) for r in range(10)] and J.spread_starts(10, 3) == ["0", "3", "6"]


def test_skipped_parts_copy_the_baseline_as_inert():
    job = J.Job("rss", "bag1", "baseline", 0)
    out = A.outcomes_of([(job, ({"median": 0.02},), None, 1.0)], {("rss", "beamskip"): "off"})
    assert [(o.mechanism, o.inert) for o in out] == [("baseline", False), ("beamskip", True)]
    assert out[1].figures == out[0].figures


def test_the_perturbed_runs_are_the_demos_without_its_fixed_scale_rows():
    from localization.eval.datasets import REPORT_TRIALS
    from localization.tools.demo import perturbed_runs
    demo = {k: (trial, changes) for k, (trial, changes, params) in perturbed_runs(REPORT_TRIALS).items()
            if not params}
    assert {k: (t, dict(c)) for k, (t, c) in J.perturbed_runs().items()} == demo


def test_a_results_file_gives_back_the_jobs_it_holds_and_only_those(tmp_path):
    path = tmp_path / "runs.jsonl"
    a, b = J.Job("rss", "bag1", "baseline", 0, (("random_seed", 0),)), J.Job("rss", "bag1", "baseline", 1)
    A.append_result(path, (a, ({"median": 0.02, "false": 0},), None, 3.0))
    A.append_result(path, (b, (), "RuntimeError: boom", 1.0))  # a failed job is run again
    path.write_text(path.read_text() + "not json\n")
    changed = J.Job("rss", "bag1", "baseline", 0, (("random_seed", 0), ("deskew", False)))
    done = A.load_results(path, [a, b, changed])
    assert list(done) == [A.job_key(a)] and done[A.job_key(a)] == (a, ({"median": 0.02, "false": 0},), None, 3.0)
    assert A.load_results(None, [a]) == {} and A.load_results(tmp_path / "none.jsonl", [a]) == {}


class FakeLocalizer:
    def __init__(self):
        self.recoveries, self.cloud, self.t = 0, np.zeros((4, 3)), 0.0

    def particles(self):
        return self.cloud.copy()

    def scan_time(self, scan):
        return self.t


def test_the_switch_watch_scores_each_switch_against_the_truth_and_ignores_re_spreads():
    truth_t, truth = np.array([0.0, 10.0]), np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]])
    watch, loc = J.SwitchWatch(truth_t, truth, 0.5), FakeLocalizer()
    loc.t, loc.cloud[:, 0] = 2.0, 2.1  # no switch yet: nothing
    watch(None, loc)
    loc.recoveries = 1  # a switch to (2.1, 0) at t = 2 s, the truth (2, 0): right
    watch(None, loc)
    watch(None, loc)  # the same switch seen again: counted once
    loc.recoveries, loc.t = 2, 5.0  # a switch 3 m off: false
    loc.cloud[:, :2] = [8.0, 0.0] + np.array([[0.1, 0.0], [-0.1, 0.0], [0.0, 0.1], [0.0, -0.1]])
    watch(None, loc)
    loc.recoveries, loc.cloud[:, 0] = 3, [-20.0, 20.0, -5.0, 5.0]  # a re-spread over the map: not a switch
    watch(None, loc)
    assert watch.distances == pytest.approx([0.1, 3.0]) and watch.false == 1


def test_the_table_in_the_docs_has_every_mechanism_every_part_and_three_seeds():
    """docs/ablation.md is the tool's table: a row per mechanism the tool switches, a column group per part,
    each cell a mean ± spread over seeds 0, 1, 2 (a new mechanism without a row fails here)."""
    text = (Path(__file__).resolve().parents[1] / "docs" / "ablation.md").read_text()
    rows = {line.split("|")[1].strip(): line for line in text.splitlines() if line.startswith("| ")}
    for mechanism in J.MECHANISMS.values():
        assert mechanism.title in rows, mechanism.title
    header = rows["row"]
    for part in ("RSS med", "Pio err", "Pert mean", "Global ok", "Kidnap ok", "ms RSS"):
        assert part in header, part
    assert "--seeds 0,1,2" in text and "± " in rows["baseline"]
