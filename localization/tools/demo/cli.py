"""``localization-demo``'s command line: the parts asked for -> the calibrations, the job table, the
replays, the tables and summary.json."""
from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

from localization.core.parameters import Parameters
from localization.core.paths import config_dir
from localization.eval.datasets import PIONEER_BAGS, REAL_BAGS, REPORT_TRIALS
from localization.tools import args as args_
from localization.tools.demo import heldout, jobs, schedule, tables, worker
from localization.tools.demo.jobs import HELDOUT, PIONEER_HELDOUT, REAL, Parts

PROG = worker.PROG
ONLY = ("heldout", "pioneer")


def build_parser():
    ap = args_.Parser(prog=PROG, description="Record (or reuse) the simulated Stata basement trials, replay them "
                      "and the real RSS 2022 and Pioneer bags, print the results tables (docs/replay.md).")
    ap.add_argument("--out", type=Path, default=Path("demo-results"), help="where the replays' outputs go "
                    "(default ./demo-results; must be empty or new unless --overwrite)")
    ap.add_argument("--overwrite", action="store_true", help="replace the files of an existing --out folder")
    ap.add_argument("--particles", type=int, help="override num_particles (default: the parameters' 2000)")
    ap.add_argument("-p", "--param", dest="overrides", action="append", default=[], metavar="NAME=VALUE",
                    type=args_.param_override,
                    help="override a parameter in every replay (repeatable; NAME:=VALUE works too)")
    ap.add_argument("--jobs", type=int, default=min(os.cpu_count() or 1, 4), help="parallel replays")
    ap.add_argument("--loop", action="store_true", help="also replay the long loop with biased odometry")
    ap.add_argument("--skip-sim", action="store_true", help="only the real bags")
    ap.add_argument("--skip-real", action="store_true", help="only the simulated trials (no RSS 2022 or Pioneer "
                    "bag)")
    ap.add_argument("--skip-fast", action="store_true", help="skip the fast trial (aligned vs unaligned)")
    ap.add_argument("--skip-perturbed", action="store_true", help="only the clean-map simulated trials (no "
                    "perturbed-world rows)")
    ap.add_argument("--skip-heldout", action="store_true", help="skip the held-out calibration of the real bags")
    ap.add_argument("--skip-pioneer", action="store_true", help="skip the Pioneer bags")
    ap.add_argument("--heldout-tuning", action="store_true", help="with the held-out replays: also choose the "
                    "motion noise and sigma_hit per fold on the other two bags (a grid, about five minutes) and "
                    "replay each bag with its fold's choice")
    ap.add_argument("--only", choices=ONLY, help="run only this part: heldout (the RSS bags with all-bags and "
                    "held-out calibration, a few minutes) or pioneer (the three Pioneer bags)")
    ap.add_argument("--duration", type=float, help="truncate the simulated trials to this many seconds")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--motion-sweep", nargs="*", type=float, metavar="SCALE",
                    help="also replay the real bags with real_params.yaml's motion noise scaled by these factors "
                         "(default 0.25 0.5 1 2)")
    return ap


#: table -> the calibrated keys of its robot's held-out folds
FOLD_KEYS = {HELDOUT: heldout.heldout_keys(jobs.REAL_PARAMS),
             PIONEER_HELDOUT: heldout.heldout_keys(PIONEER_BAGS["trace0"].params)}


def folds_of(calibrated: dict) -> dict:
    """bag -> its held-out fold, per robot (the RSS bags among themselves, the Pioneer bags among theirs)."""
    rss = [b for b in calibrated if b not in PIONEER_BAGS]
    pioneer = [b for b in calibrated if b in PIONEER_BAGS]
    return {**(heldout.heldout_folds(rss, calibrated.__getitem__, FOLD_KEYS[HELDOUT]) if rss else {}),
            **(heldout.heldout_folds(pioneer, calibrated.__getitem__, FOLD_KEYS[PIONEER_HELDOUT]) if pioneer else {})}


def heldout_tuning(real: list, folds: dict, params_file, overrides: dict, workers: int, out: Path) -> tuple:
    """``--heldout-tuning`` (``heldout.tune_folds``): (table text, summary.json entry, every result)."""
    tuning = heldout.tune_folds(real, folds, params_file, overrides, workers, out)
    return tables.tuning_table(tuning), heldout.tuning_summary(tuning, folds), tuning.grid + tuning.final


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    parts, out = Parts.from_args(args), args.out.resolve()
    overrides = {"random_seed": args.seed, **dict(args.overrides),
                 **({} if args.particles is None else {"num_particles": args.particles})}
    code, problem = refusal(overrides, out, args.overwrite)
    if problem is not None:
        print(f"{PROG}: error: {problem}", file=sys.stderr)
        return code
    t0 = time.perf_counter()
    plan = jobs.plan(parts, REPORT_TRIALS, overrides, out)
    tasks = worker.demo_tasks(plan, parts.calibrated_bags, with_fold, schedule.load_costs())
    say(f"{len(tasks)} tasks ({len(parts.calibrated_bags)} calibrations, recordings from the cache or made, "
        f"{len(plan)} replays) on {args.jobs} worker(s) ...")
    seconds: dict = {}
    worker.compile_kernels(plan)
    try:
        done = schedule.run_tasks(tasks, args.jobs, on_done=lambda k, r, s: progress(k, r, s, seconds, len(tasks)))
    except worker.CalibrationFailed as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 1
    schedule.save_costs(seconds)
    results = [done[f"replay:{j.summary_key}"] for j in plan]
    for line in worker.distinct_notes(results):
        say(line)
    calibrated = {b: done[f"calibrate:{b}"]["values"] for b in parts.calibrated_bags}
    folds, tuned = folds_of(calibrated), None
    if parts.tuning and any(r.job.table == HELDOUT for r in results):
        say(f"choosing the motion noise and sigma_hit per fold ({len(heldout.tuning_points())} grid points on each "
            "fold's two training bags) ...")
        tuned = heldout.tune_folds([r.job for r in results if r.job.table == REAL], folds,
                                   config_dir() / jobs.REAL_PARAMS, overrides, args.jobs, out)
    particles = overrides.get("num_particles", Parameters().num_particles)
    print(tables.report(results, calibrated, folds, FOLD_KEYS, f"{particles} particles, seed {args.seed}", tuned))
    write_summary(out, results, calibrated, folds, tuned)
    print(f"plots and metrics: {out}/<trial or bag>/(trajectory.png, error.png, metrics.json, poses.csv); "
          f"summary: {out / 'summary.json'}  [{time.perf_counter() - t0:.0f} s]")
    return 1 if any(r.error is not None for r in results + ([] if tuned is None else tuned.grid + tuned.final)) else 0


def calibration(done: dict, bag: str) -> dict:
    """A bag's calibrated values among the finished tasks; CalibrationFailed when its calibration failed."""
    r = done[f"calibrate:{bag}"]
    if "error" in r:
        raise worker.CalibrationFailed(f"calibration failed: {bag}: {r['error']}")
    return r["values"]


def with_fold(job, done: dict):
    """A held-out job with its fold's calibrated values (the other bags of its robot, ``heldout.fold_of``)."""
    robot = list(REAL_BAGS if job.table == HELDOUT else PIONEER_BAGS)
    fold = heldout.fold_of(job.label, robot, lambda b: calibration(done, b), FOLD_KEYS[job.table])
    return job.with_overrides(**heldout.fold_overrides(fold))


def progress(key: str, result, seconds: float, kept: dict, total: int) -> None:
    """One line per finished task (stderr), its time kept for the next run's order."""
    kept[key] = seconds
    what = {"calibrate": "calibrated", "record": "recorded", "replay": "replayed"}[key.split(":")[0]]
    failed = getattr(result, "error", None) or (result.get("error") if isinstance(result, dict) else None)
    say(f"{PROG}: [{len(kept)}/{total}] {key.split(':', 1)[1]} {what} in {seconds:.0f} s"
        + (f" (error: {failed})" if failed else ""))


def refusal(overrides: dict, out: Path, overwrite: bool) -> tuple:
    """(exit status, why) when the demo cannot start: a bad parameter (2) or an --out it must not write (1);
    (0, None) when it can. Checked before any work."""
    try:
        Parameters(overrides)
    except ValueError as exc:
        return 2, str(exc)
    problem = args_.output_problem(out, overwrite, kind="folder")
    return (1, f"--out: {problem}") if problem else (0, None)


def say(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def write_summary(out: Path, results: list, calibrated: dict, folds: dict, tuned) -> None:
    """summary.json: every replay's metrics (or error) by ``Job.summary_key``, the tuning, folds and calibration."""
    out.mkdir(parents=True, exist_ok=True)
    summary = {r.job.summary_key: r.metrics if r.metrics is not None else {"error": r.error} for r in results}
    if tuned is not None:
        summary["heldout_tuned"] = heldout.tuning_summary(tuned, folds)
    if folds:
        summary["heldout_folds"] = folds
        summary["calibration"] = calibrated
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
