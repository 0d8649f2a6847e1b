"""Does every mechanism earn its place? Each one switched off in turn, over several filter seeds, one table.

    python -m localization.benchmarks.ablation                    # everything, seeds 0 1 2, 2 workers
    python -m localization.benchmarks.ablation --only rss,perturbed --seeds 0,1,2 --markdown docs/ablation.md
    python -m localization.benchmarks.ablation --only rss --bags bag1 --seeds 0 --mechanisms tempered  # a smoke run
    python -m localization.benchmarks.ablation --perturbed trial2_2mps_scale1.02 --starts 2 --results runs.jsonl

What is replayed (each with the baseline's parameters, then once per mechanism with its one override):

- ``rss``: the three RSS 2022 bags held out, as ``localization-demo --only heldout`` replays them:
  ``config/real_params.yaml`` with each bag's fold (the calibration of the other two bags), from the
  bag's start pose, scored against the yardstick (the reference track, cached on disk). The folds
  come from a ``localization-demo --only heldout`` run (its ``summary.json``; ``--demo-summary``
  reuses one);
- ``pioneer``: the three Pioneer bags held out: ``localization-demo --only pioneer`` itself, once
  per row and seed (its figures, ``summary.json``'s ``<bag>@heldout``);
- ``perturbed``: the demo's perturbed-world trials (``config/params.yaml``; the three report trials
  in the standard perturbation, trials 1 and 3 at 2 m/s at scale 1.01, trial 2 at 2 m/s at scale
  1.01 and 1.02; the demo's ``_fixed`` rows are this table's range-scale row), recorded once into
  the cache (``datasets.sim_bag``);
- ``global``: the robustness benchmark's global starts (``global_init: scan``) and kidnappings on the
  basement loop (``benchmarks.robustness``: the same routes, starts and teleports), each recording
  simulated once and kept in the cache (``ablation/recordings``).

A seed is the filter's ``random_seed`` (the global and kidnap runs: the benchmark's seed + 1000 x
seed); the data are the same for every seed. A mechanism whose switch is already off in a group's
parameter file, or that the group's data give nothing to act on (deskew without sweep timing, the
tempered first update after a global start), is not replayed there: its cells are the baseline's
(``=``). The jobs and the switches: ``ablation_jobs``; the table, its columns and the rule that says a
figure moved: ``ablation_table``.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import sys
import tempfile
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import replace
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from localization.benchmarks import ablation_table as T
from localization.benchmarks.ablation_jobs import (
    COST_GUESS,
    MECHANISMS,
    NOT_ABLATED,
    SIM_GROUPS,
    Job,
    labels,
    perturbed_runs,
    plan,
    record,
    run_demo,
    run_job,
    spread_starts,
)

PROG = "python -m localization.benchmarks.ablation"
ONLY = ("rss", "pioneer", "perturbed", "global")  # "global": the global starts and the kidnappings


# --------------------------------------------------------------------------------------------
# The run
# --------------------------------------------------------------------------------------------


def job_key(job: Job) -> str:
    return json.dumps([job.group, job.label, job.mechanism, job.seed, [list(kv) for kv in job.overrides], job.runs])


def load_results(path: Path | None, jobs: list) -> dict:
    """key -> (job, figures, None, seconds): the jobs of ``jobs`` a results file already holds (without error)."""
    wanted = {job_key(j): j for j in jobs}
    done = {}
    with contextlib.suppress(OSError):
        for line in Path(path).read_text().splitlines() if path is not None else []:
            with contextlib.suppress(ValueError, KeyError, TypeError):
                entry = json.loads(line)
                if entry["key"] in wanted and not entry.get("error"):
                    done[entry["key"]] = (wanted[entry["key"]], tuple(entry["figures"]), None, entry["seconds"])
    return done


def append_result(path: Path, result: tuple) -> None:
    job, figures, error, seconds = result
    with open(path, "a") as f:
        f.write(json.dumps({"key": job_key(job), "figures": list(figures), "error": error, "seconds": seconds})
                + "\n")


def say(line: str) -> None:
    print(f"{datetime.now():%H:%M:%S} {line}", file=sys.stderr, flush=True)


def rss_folds(summary_file: Path | None, jobs: int) -> tuple:
    """bag -> its held-out fold's overrides, and the demo's seed-0 held-out metrics (for the check)."""
    if summary_file is not None:
        summary = json.loads(Path(summary_file).read_text())
    else:
        say("localization-demo --only heldout (the folds: each bag with the calibration of the other two) ...")
        with tempfile.TemporaryDirectory(prefix="ablation-heldout-") as tmp:
            summary = run_demo("heldout", {}, 0, jobs, Path(tmp) / "out")
    folds = {b: {k: v for k, v in f.items() if k != "calibrated_on"} for b, f in summary["heldout_folds"].items()}
    return folds, {k.split("@")[0]: v for k, v in summary.items() if k.endswith("@heldout")}


LOADS: list = []  # the 1-minute load average each time a task finished (this process)


def run_pool(items: list, fn, workers: int, what: str, on_result=None) -> list:
    """``fn(item)`` for every item on ``workers`` processes, the costliest first; one progress line each and
    ``on_result(result)`` as each finishes."""
    results, t0 = [], time.perf_counter()
    cost = [COST_GUESS.get(getattr(i, "group", i[0] if isinstance(i, tuple) else ""), 30.0) for i in items]
    order = [items[k] for k in np.argsort(-np.asarray(cost, dtype=float), kind="stable")]
    with ProcessPoolExecutor(max_workers=max(1, workers)) as pool:
        pending = {pool.submit(fn, item) for item in order}
        while pending:
            done, pending = wait(pending, return_when=FIRST_COMPLETED)
            for future in done:
                results.append(future.result())
                LOADS.append(os.getloadavg()[0])
                if on_result is not None:
                    on_result(results[-1])
                elapsed = time.perf_counter() - t0
                left = elapsed / len(results) * (len(items) - len(results))
                r = results[-1]
                name = f"{r[0].group} {r[0].label} {r[0].mechanism} seed {r[0].seed} in {r[3]:.0f} s" \
                    if isinstance(r, tuple) and isinstance(r[0], Job) else str(r)
                error = f" ERROR {r[2]}" if isinstance(r, tuple) and len(r) > 2 and r[2] else ""
                say(f"{what} {len(results)}/{len(items)}: {name}{error} [{elapsed:.0f} s, ~{left:.0f} s left]")
    return results


def outcomes_of(results: list, skipped: dict) -> list:
    """One ``Outcome`` per job run, and the baseline's copied for each (group, mechanism) not run."""
    out = [T.Outcome(job.group, job.mechanism, job.seed, figures, error=error) for job, figures, error, _ in results]
    for (group, mechanism) in skipped:
        out += [replace(o, mechanism=mechanism, inert=True) for o in out
                if o.group == group and o.mechanism == "baseline" and not o.inert]
    return out


def demo_check(results: list, demo: dict) -> list:
    """The baseline's seed-0 RSS figures beside the demo's own held-out run (they should agree)."""
    lines = []
    for job, figures, error, _ in results:
        if job.group == "rss" and job.mechanism == "baseline" and job.seed == 0 and not error and job.label in demo:
            ref = demo[job.label].get("reference_error_m") or {}
            f = figures[0]
            lines.append(f"{job.label}: median {f['median']:.4f} p95 {f['p95']:.4f} here, "
                         f"{ref.get('median', math.nan):.4f} {ref.get('p95', math.nan):.4f} in the demo's run")
    return lines


def table_rows(mechanisms: list) -> list:
    def switch(key):
        return ", ".join(f"`{k}: {json.dumps(v)}`" for k, v in MECHANISMS[key].overrides)
    return [("baseline", "baseline", "(the shipped files)")] + [(k, MECHANISMS[k].title, switch(k)) for k in mechanisms]


def scope_text(args, pick: dict, groups: list) -> str:
    """What was replayed, in one sentence per part."""
    parts = []
    if "rss" in groups:
        parts.append(f"RSS held out: {', '.join(pick['rss'] or labels('rss', args.runs))}")
    if "pioneer" in groups:
        parts.append("Pioneer held out: trace0, trace1, lgfloor2 (localization-demo --only pioneer)")
    if "perturbed" in groups:
        runs = pick["perturbed"] or labels("perturbed", args.runs)
        parts.append(f"perturbed world: {', '.join(runs)}")
    if "global" in groups:
        starts = pick["global"]
        parts.append(f"global starts and kidnappings: {len(starts)} of the robustness benchmark's {args.runs} "
                     f"(runs {', '.join(starts)})")
    return "; ".join(parts) + f"; filter seeds {', '.join(map(str, args.seeds))}."


def markdown_doc(command: str, rows: list, skipped: dict, notes: dict, seconds: float, loads: str,
                 scope: str, check: list, errors: list) -> str:
    lines = ["# Ablation: every mechanism switched off in turn", "",
             f"    {command}", "",
             f"Run {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC, {seconds / 60:.0f} min on 2 shared cores; load "
             f"average {loads}. Replayed: {scope}", "",
             T.render_markdown(rows), "", "Each cell: mean ± sample standard deviation over the seeds. A figure "
             "*moves* (bold) when the row's mean lies outside the baseline's min–max over the same seeds (the "
             "second row), widened by half the last printed digit; counts are not widened. `=`: not replayed, "
             "the baseline's (below).", "", "Columns:", "", T.column_notes(rows)]
    if skipped:
        lines += ["", "Not replayed (the switch changes nothing there):", ""]
        lines += [f"- {MECHANISMS[m].title}, {g}: {why}" for (g, m), why in sorted(skipped.items())]
    lines += ["", "Switches, and what has none:", ""]
    lines += [f"- {MECHANISMS[k].title}: {note}" for k, note in notes.items()]
    lines += [f"- {k}: {v}" for k, v in NOT_ABLATED.items()]
    if check:
        lines += ["", "The baseline's seed 0 beside `localization-demo --only heldout` (the same replays):", ""]
        lines += [f"- {c}" for c in check]
    if errors:
        lines += ["", "Failed jobs:", ""] + [f"- {e}" for e in errors]
    return "\n".join(lines) + "\n"


def parse_list(text: str, known) -> list:
    items = [t.strip() for t in text.split(",") if t.strip()]
    bad = [t for t in items if t not in known]
    if bad:
        raise argparse.ArgumentTypeError(f"unknown {', '.join(bad)} (known: {', '.join(known)})")
    return items


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n")[0])
    ap.add_argument("--only", type=lambda s: parse_list(s, ONLY), default=list(ONLY),
                    help=f"comma-separated parts (default all): {', '.join(ONLY)} (global: the global starts and "
                         "the kidnappings)")
    ap.add_argument("--mechanisms", type=lambda s: parse_list(s, MECHANISMS), default=list(MECHANISMS),
                    help=f"comma-separated (default all): {', '.join(MECHANISMS)}")
    ap.add_argument("--seeds", type=lambda s: [int(v) for v in s.split(",") if v.strip()], default=[0, 1, 2],
                    help="comma-separated filter seeds (default 0,1,2)")
    ap.add_argument("--jobs", type=int, default=2, help="worker processes (default 2)")
    ap.add_argument("--runs", type=int, default=10, help="global starts and kidnappings on the loop (default 10)")
    ap.add_argument("--bags", type=lambda s: parse_list(s, ("bag1", "bag2", "bag3")),
                    help="comma-separated RSS bags (default all three)")
    ap.add_argument("--perturbed", type=lambda s: parse_list(s, perturbed_runs()),
                    help=f"comma-separated perturbed-world runs (default all): {', '.join(perturbed_runs())}")
    ap.add_argument("--starts", type=int, help="only this many of the --runs global starts and kidnappings, spread "
                    "along the loop (default all)")
    ap.add_argument("--results", type=Path, metavar="FILE", help="JSON lines: every finished replay is appended; "
                    "replays the file already holds (same job, same parameters) are not run again")
    ap.add_argument("--demo-summary", type=Path, help="the folds from this localization-demo --only heldout "
                    "summary.json instead of running it")
    ap.add_argument("--markdown", type=Path, metavar="FILE", help="also write the table and its notes as markdown")
    return ap


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    t0, load0 = time.perf_counter(), f"{os.getloadavg()[0]:.1f}"
    groups = [g for part in args.only for g in (("global", "kidnap") if part == "global" else (part,))]
    folds, demo = rss_folds(args.demo_summary, args.jobs) if "rss" in groups else ({}, {})
    pick = {"rss": args.bags, "perturbed": args.perturbed, "global": spread_starts(args.runs, args.starts),
            "kidnap": spread_starts(args.runs, args.starts)}
    jobs, skipped = plan(groups, args.mechanisms, args.seeds, folds, args.runs, pick)
    done = load_results(args.results, jobs)
    todo = [j for j in jobs if job_key(j) not in done]
    recordings = sorted({(j.group, j.label) + ((j.runs,) if j.group in ("global", "kidnap") else ())
                         for j in jobs if j.group in SIM_GROUPS})
    say(f"{len(jobs)} replays ({len(groups)} parts x {1 + len(args.mechanisms)} rows x {len(args.seeds)} seeds, "
        f"{len(skipped)} part-rows not needed; {len(done)} already in {args.results}), {len(recordings)} "
        f"recordings, {args.jobs} workers")
    if recordings:
        run_pool(recordings, record, args.jobs, "recording")
    save = None if args.results is None else (lambda r: append_result(args.results, r))
    results = list(done.values()) + run_pool(todo, run_job, args.jobs, "replay", save)
    outcomes = outcomes_of(results, skipped)
    rows = T.build_rows(outcomes, table_rows(args.mechanisms), args.seeds)
    errors = [f"{j.group} {j.label} {j.mechanism} seed {j.seed}: {e}" for j, _, e, _ in results if e]
    check = demo_check(results, demo)
    seconds, load1 = time.perf_counter() - t0, f"{os.getloadavg()[0]:.1f}"
    scope = scope_text(args, pick, groups)
    during = f"{min(LOADS):.1f}–{max(LOADS):.1f} during, " if LOADS else ""
    loads = f"{load0} at the start, {during}{load1} at the end"
    print(f"\nAblation ({scope} {seconds / 60:.0f} min; load average {loads})\n")
    print(T.render_text(rows))
    for (g, m), why in sorted(skipped.items()):
        print(f"= {MECHANISMS[m].title}, {g}: not replayed, {why}")
    for line in check + errors:
        print(line)
    if args.markdown:
        command = " ".join([PROG, *(sys.argv[1:] if argv is None else argv)])
        notes = {k: MECHANISMS[k].note for k in args.mechanisms if MECHANISMS[k].note}
        args.markdown.write_text(markdown_doc(command, rows, skipped, notes, seconds, loads, scope, check, errors))
    return 1 if errors else 0


if __name__ == "__main__":
    sys.exit(main())
