"""The demo's task graph (``localization.tools.demo.schedule``): every task runs once, after the tasks it
needs, its argument made from their results; the ready task heading the longest chain goes first; the
demo's graph wires held-out replays to the other bags' calibrations and simulated replays to their
recordings. Small functions in real worker processes: fast."""
from __future__ import annotations

import os
import time

import pytest

from localization.eval.datasets import PIONEER_BAGS, REAL_BAGS, REPORT_TRIALS
from localization.tools.demo import cli, jobs, schedule, worker


def _stamp(arg):
    """(arg, pid, start, end) after a short sleep: which process ran it, and when."""
    t0 = time.time()
    time.sleep(arg[1] if isinstance(arg, tuple) and isinstance(arg[1], float) else 0.05)
    return arg, os.getpid(), t0, time.time()


def test_ranks_are_the_longest_chain_to_the_end():
    tasks = [schedule.Task("a", _stamp, cost=1.0), schedule.Task("b", _stamp, needs=("a",), cost=5.0),
             schedule.Task("c", _stamp, needs=("a",), cost=2.0), schedule.Task("d", _stamp, cost=4.0)]
    assert schedule.ranks(tasks) == {"a": 6.0, "b": 5.0, "c": 2.0, "d": 4.0}


@pytest.mark.parametrize("workers", [1, 2])
def test_every_task_runs_once_after_what_it_needs(workers):
    made = []

    def make(done):
        made.append(sorted(done))
        return ("from", done["cal1"][0], done["cal2"][0])
    tasks = [schedule.Task("cal1", _stamp, "one"), schedule.Task("cal2", _stamp, "two"),
             schedule.Task("held", _stamp, needs=("cal1", "cal2"), make=make),
             *(schedule.Task(f"r{k}", _stamp, k) for k in range(4))]
    finished = []
    done = schedule.run_tasks(tasks, workers, on_done=lambda key, result, s: finished.append(key))
    assert sorted(done) == sorted(t.key for t in tasks) and sorted(finished) == sorted(done)
    assert done["held"][0] == ("from", "one", "two")  # made in this process from what it needed
    assert "cal1" in made[0] and "cal2" in made[0]
    start = {k: v[2] for k, v in done.items()}
    end = {k: v[3] for k, v in done.items()}
    assert start["held"] >= max(end["cal1"], end["cal2"])
    if workers == 1:  # in this process, no pool
        assert {v[1] for v in done.values()} == {os.getpid()}


def test_the_longest_chain_starts_first_and_two_workers_share_the_work():
    # a long task listed last: with two workers it starts at once, beside the short ones
    tasks = [*(schedule.Task(f"short{k}", _stamp, (k, 0.05), cost=0.05) for k in range(6)),
             schedule.Task("long", _stamp, ("long", 0.4), cost=0.4)]
    done = schedule.run_tasks(tasks, 2)
    first = min(v[2] for v in done.values())
    assert done["long"][2] - first < 0.1
    wall = max(v[3] for v in done.values()) - first
    assert wall < 0.4 + 6 * 0.05 - 0.1  # less than one worker doing everything in order
    assert len({v[1] for v in done.values()}) == 2


def test_unknown_needs_are_refused():
    with pytest.raises(ValueError, match="nope"):
        schedule.run_tasks([schedule.Task("a", _stamp, needs=("nope",))], 1)


def test_costs_are_kept_for_the_next_run(monkeypatch, tmp_path):
    monkeypatch.setenv("LOCALIZATION_CACHE_DIR", str(tmp_path))
    assert schedule.load_costs() == {}
    schedule.save_costs({"replay:bag1": 12.5})
    schedule.save_costs({"replay:bag2": 3.0})
    assert schedule.load_costs() == {"replay:bag1": 12.5, "replay:bag2": 3.0}
    schedule.costs_path().write_text("not json")
    assert schedule.load_costs() == {}


def test_the_demo_graph_waits_only_for_what_each_replay_uses(tmp_path):
    parts = jobs.Parts.from_args(cli.build_parser().parse_args([]))
    plan = jobs.plan(parts, REPORT_TRIALS, {"random_seed": 0}, tmp_path)
    tasks = {t.key: t for t in worker.demo_tasks(plan, parts.calibrated_bags, cli.with_fold, {})}
    assert sum(k.startswith("calibrate:") for k in tasks) == len(REAL_BAGS) + len(PIONEER_BAGS)
    recordings = [k for k in tasks if k.startswith("record:")]
    assert len(recordings) == 11  # 12 simulated replays and the fast trial's 2 share 11 recordings
    assert tasks["replay:bag2@heldout"].needs == ("calibrate:bag1", "calibrate:bag3")
    assert tasks["replay:trace0@heldout"].needs == ("calibrate:trace1", "calibrate:lgfloor2")
    assert tasks["replay:bag2"].needs == () and tasks["replay:bag2@heldout"].arg is None
    fixed, learnt = tasks["replay:trial2_2mps_scale1.02_fixed"], tasks["replay:trial2_2mps_scale1.02"]
    assert fixed.needs == learnt.needs and fixed.needs[0] in recordings  # one recording for both
    assert tasks["replay:fast_aligned"].needs == tasks["replay:fast_unaligned"].needs
