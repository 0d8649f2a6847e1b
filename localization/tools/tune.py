"""``localization-tune``: tune the filter's parameters from recorded bags (Optuna; see
``localization.eval.tuning`` for the score and docs/tuning.md for a tutorial).

Usage::

    localization-tune BAG [BAG ...] --map MAP [--params START.yaml] [--space SPACE.yaml] [--trials N]
                      [--jobs J] [--storage URL] [--study NAME] [--timeout S] [--out DIR] [--json]
                      [--initial-pose X,Y,YAW ...] [--scan-topic T] [--odom-topic T] [--seed N]
                      [--no-prune] [--lost-penalty P] [--time-weight W] [--max-realtime R]
    localization-tune BAG [BAG ...] --map MAP --params START.yaml --compare OTHER.yaml [--compare-seeds S,S,...]

Each trial lays one draw of the search space over the starting parameters, replays every bag
through the core and scores it (mean position error against ground truth, 1 − median scan–map
agreement without it, plus penalties for a lost track and for time over real time). Trial 0 of a
new study evaluates the starting parameters (the baseline).

The study lives in ``--storage``: by default the journal file ``DIR/study.journal``; an Optuna URL
(``sqlite:///tune.db``, ``postgresql://user:pw@host/db`` with the ``[distributed]`` extra) lets the same
command on several machines share one study. Running again with the same ``--study`` and storage
continues the study: ``--trials`` more trials. ``--jobs J`` runs J worker processes here.

``--compare OTHER.yaml`` runs no study: it scores the starting parameters and OTHER (e.g. a
``best_params.yaml``) on the bags with filter seeds the tuning did not use (default 11, 12, 13).

Outputs in ``--out`` (default ``./tune-results``): ``best_params.yaml`` (a complete parameter file
for ``--params`` and the node), ``trials.csv``, ``optimization_history.png``, ``param_importances.png``.

Exit status: 0 success; 1 bad input (bag, map, parameters, search space, storage: one line
``localization-tune: error: ...`` on stderr); 2 bad command-line arguments.
"""
from __future__ import annotations

import argparse
import csv
import json
import math
import sys
import time
import warnings
from datetime import datetime
from pathlib import Path

from localization.core.parameters import NODE_NAME, PARAMETERS, ParameterError, Parameters
from localization.eval.datasets import REAL_BAGS
from localization.eval.progress import progress_enabled
from localization.eval.replay import ReplayError
from localization.eval.tuning import (
    BASELINE_ATTR,
    DEFAULT_STUDY,
    DUPLICATE_ATTR,
    ScoreWeights,
    TuneConfig,
    TuneError,
    baseline_trial,
    check_bags,
    compare_parameters,
    load_space,
    run_workers,
)
from localization.tools import args as args_

PROG = "localization-tune"


def build_parser() -> argparse.ArgumentParser:
    ap = args_.Parser(prog=PROG, description="Tune the localizer's parameters from recorded bags (Optuna: local "
                      "worker processes or a shared study storage).")
    ap.add_argument("bags", nargs="+", type=Path, metavar="BAG", help="rosbag2 directory, .db3, .mcap or ROS 1 .bag")
    ap.add_argument("--map", required=True, type=args_.map_name_or_yaml,
                    help="map_server YAML (or a map name in the maps directory)")
    ap.add_argument("--params", help="starting parameter file, or a name in the package's config/ ("
                    + args_.params_names() + "); default: the built-in defaults, or config/real_params.yaml when the "
                    "bags have the car's odometry topic (/vesc/odom) and not /odom (said on stderr)")
    ap.add_argument("--space", help="search space YAML (default: the package's config/tune_space.yaml)")
    ap.add_argument("--trials", type=_at_least_one, default=40,
                    help="trials to run now, at least 1 (added to the study's; default 40)")
    ap.add_argument("--jobs", type=_at_least_one, default=1, help="worker processes on this machine (default 1)")
    ap.add_argument("--storage", help="Optuna storage URL (sqlite:///f.db, postgresql://user:pw@host/db: pip install "
                    "'localization[distributed]') or a journal file path (default: DIR/study.journal)")
    ap.add_argument("--study", default=DEFAULT_STUDY, help=f"study name (default {DEFAULT_STUDY})")
    ap.add_argument("--timeout", type=args_.positive_float, help="stop starting new trials after S seconds")
    ap.add_argument("--out", type=Path, default=Path("tune-results"), help="output folder (default ./tune-results)")
    ap.add_argument("--json", action="store_true", help="print one JSON object (best_value, baseline_value, ...)")
    ap.add_argument("--initial-pose", dest="initial_poses", action="append", type=args_.pose, metavar="X,Y,YAW",
                    help="initial pose of a bag (repeat once per bag, in bag order); default: the bag's "
                         "/initialpose, else the known start of an RSS 2022 bag, else global localization")
    ap.add_argument("--scan-topic", help="default: the scan_topic parameter")
    ap.add_argument("--odom-topic", help="default: the odom_topic parameter")
    ap.add_argument("--seed", type=int, default=0, help="seed of the sampler and of the filter in every trial")
    ap.add_argument("--no-prune", action="store_true", help="never stop a trial after its first bags")
    ap.add_argument("--lost-penalty", type=args_.non_negative_float, default=ScoreWeights.lost_penalty,
                    help="added to a bag's score when the track is lost (default %(default)s)")
    ap.add_argument("--time-weight", type=args_.non_negative_float, default=ScoreWeights.time_weight,
                    help="added per unit of filter time / bag duration above 1 (default %(default)s)")
    ap.add_argument("--max-realtime", type=args_.positive_float, default=ScoreWeights.max_realtime,
                    help="cut a bag (and count it lost) past this many times real time (default %(default)s)")
    ap.add_argument("--quiet", action="store_true", help="nothing on stderr but errors (no progress bar, no "
                    "per-trial lines)")
    ap.add_argument("--compare", metavar="PARAMS", help="do not tune: score the starting parameters and this "
                    "parameter file (e.g. DIR/best_params.yaml) on the bags with --compare-seeds")
    ap.add_argument("--compare-seeds", type=args_.floats, default=(11, 12, 13), metavar="S,S,...",
                    help="filter seeds of --compare (default 11,12,13: not the tuning's)")
    return ap


def _at_least_one(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {n}")
    return n


def _initial_poses(args) -> list:
    """One entry per bag: the given pose, the known start of an RSS 2022 bag, or None."""
    given = args.initial_poses or []
    if given and len(given) != len(args.bags):
        raise TuneError(f"--initial-pose given {len(given)} times for {len(args.bags)} bags: give one per bag")
    if given:
        return [tuple(p) for p in given]
    known = {b.filename: b.start for b in REAL_BAGS.values()}
    return [known.get(Path(b).name) for b in args.bags]


def make_config(args) -> TuneConfig:
    for b in args.bags:
        if not Path(b).exists():
            raise TuneError(f"bag not found: {b}")
    space = load_space(args.space)
    start = args_.parameters_for_bags(args.params, {}, args.bags, args.odom_topic, PROG,
                                      say=(lambda _line: None) if args.quiet else None)
    return TuneConfig(bags=[str(b) for b in args.bags], map=args.map, start=dict(start), space=space,
                      storage=args.storage or str(args.out / "study.journal"), study=args.study, seed=args.seed,
                      weights=ScoreWeights(args.lost_penalty, args.time_weight, args.max_realtime),
                      initial_poses=_initial_poses(args), scan_topic=args.scan_topic, odom_topic=args.odom_topic,
                      prune=not args.no_prune, timeout=args.timeout)


def check_inputs(cfg: TuneConfig) -> None:
    """Fail early, in this process, on a missing map or a bag without the topics (one line)."""
    from localization.eval.replay import load_map

    load_map(cfg.map)
    check_bags(cfg)


# --------------------------------------------------------------------------------------------
# Outputs
# --------------------------------------------------------------------------------------------


def best_parameters(cfg: TuneConfig, study) -> Parameters:
    values = dict(cfg.start)
    values.update(study.best_trial.params)
    return Parameters(values)


def write_best_params(path: Path, params: Parameters, header: str) -> Path:
    import yaml

    body = yaml.safe_dump({NODE_NAME: {"ros__parameters": {p.name: params[p.name] for p in PARAMETERS}}},
                          sort_keys=False, default_flow_style=False)
    path.write_text("".join(f"# {line}\n" for line in header.splitlines()) + body)
    return path


def _fmt(v):
    if v is None:
        return ""
    if isinstance(v, float):
        return "" if math.isnan(v) else f"{v:.6g}"
    return v


def write_trials_csv(path: Path, study, n_bags: int, space_names: list) -> Path:
    trials = study.get_trials(deepcopy=False)
    cols = (["number", "state", "value", "baseline", "repeat_of", "wall_s", "mean_error"]
            + [f"{k}_{b}" for b in range(n_bags) for k in ("error", "lost", "realtime")] + space_names)
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(cols)
        for t in trials:
            ua = t.user_attrs
            row = [t.number, t.state.name, t.value, bool(ua.get(BASELINE_ATTR)), ua.get(DUPLICATE_ATTR),
                   ua.get("wall_s"), ua.get("mean_error")]
            row += [ua.get(f"{k}_{b}") for b in range(n_bags) for k in ("error", "lost", "realtime")]
            row += [t.params.get(n) for n in space_names]
            w.writerow([_fmt(v) for v in row])
    return path


def write_plots(out: Path, study) -> dict:
    """optimization_history.png and param_importances.png (skipped, with a note, when the study
    cannot give them yet, e.g. fewer than two finished trials)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import optuna.visualization.matplotlib as vm
    from optuna.importance import PedAnovaImportanceEvaluator

    files, notes = {}, []
    for name, plot in (("optimization_history", lambda: vm.plot_optimization_history(study)),
                       ("param_importances", lambda: vm.plot_param_importances(
                           study, evaluator=PedAnovaImportanceEvaluator()))):
        try:
            with warnings.catch_warnings():  # few trials: PED-ANOVA warns that importances are rough
                warnings.simplefilter("ignore")
                ax = plot()
            fig = ax.figure if hasattr(ax, "figure") else ax.flat[0].figure
            fig.tight_layout()
            fig.savefig(out / f"{name}.png", dpi=100)
            plt.close(fig)
            files[name] = str(out / f"{name}.png")
        except Exception as exc:  # noqa: BLE001 - a plot that cannot be drawn yet is not an error
            notes.append(f"{name}.png skipped: {' '.join(str(exc).split())[:200]}")
            plt.close("all")
    return {"files": files, "notes": notes}


def summarize(cfg: TuneConfig, study, out: Path, elapsed: float, files: dict) -> dict:
    import optuna

    states = optuna.trial.TrialState
    trials = study.get_trials(deepcopy=False)
    complete = [t for t in trials if t.state == states.COMPLETE]
    base = baseline_trial(study)
    n_bags = len(cfg.bags)
    best = study.best_trial if complete else None

    def per_bag(t, key):
        return None if t is None else [t.user_attrs.get(f"{key}_{b}") for b in range(n_bags)]

    walls = [t.user_attrs["wall_s"] for t in trials if "wall_s" in t.user_attrs]
    return {
        "study": cfg.study, "storage": cfg.storage, "out": str(out),
        "n_trials": len(trials), "n_complete": len(complete),
        "n_pruned": sum(t.state == states.PRUNED for t in trials),
        "n_failed": sum(t.state == states.FAIL for t in trials),
        "n_repeated": sum(DUPLICATE_ATTR in t.user_attrs for t in trials),
        "best_value": None if best is None else best.value,
        "best_trial": None if best is None else best.number,
        "best_params": None if best is None else best.params,
        "error_sources": per_bag(base or best, "source"),
        "best_errors": per_bag(best, "error"), "best_lost": per_bag(best, "lost"),
        "best_realtime": per_bag(best, "realtime"),
        "baseline_value": None if base is None else base.value,
        "baseline_params": None if base is None else base.params,
        "baseline_errors": per_bag(base, "error"), "baseline_lost": per_bag(base, "lost"),
        "baseline_realtime": per_bag(base, "realtime"),
        "bags": cfg.bags,
        "wall_s_per_trial_mean": (sum(walls) / len(walls)) if walls else None,
        "elapsed_s": elapsed,
        "files": files,
    }


def bag_errors(errors, sources=None) -> str:
    """Per-bag errors rounded for reading: millimetres for metres (truth or reference track), three
    decimals for 1 − agreement (not metres)."""
    if errors is None:
        return "n/a"
    sources = sources or ["truth"] * len(errors)
    out = []
    for e, src in zip(errors, sources):
        if e is None or (isinstance(e, float) and not math.isfinite(e)):
            out.append("n/a")
        elif src == "agreement":
            out.append(f"{e:.3f} (1 - agreement)")
        else:
            out.append(f"{1000 * e:.0f} mm")
    return ", ".join(out)


def human_summary(s: dict) -> str:
    def num(v, spec=".4f"):
        return "n/a" if v is None else f"{v:{spec}}"

    src = s["error_sources"]
    lines = [f"study {s['study']} ({s['storage']}): {s['n_trials']} trials ({s['n_complete']} complete, "
             f"{s['n_pruned']} pruned, {s['n_failed']} failed"
             + (f", {s['n_repeated']} repeated parameter sets not re-run" if s.get("n_repeated") else "") + ")",
             f"bag errors scored against: {', '.join(map(str, src)) if src else 'n/a'}",
             f"baseline score {num(s['baseline_value'])}  errors {bag_errors(s['baseline_errors'], src)}",
             f"best score     {num(s['best_value'])}  errors {bag_errors(s['best_errors'], src)}  "
             f"(trial {s['best_trial']})",
             f"wall time per trial {num(s['wall_s_per_trial_mean'], '.2f')} s; this run {s['elapsed_s']:.0f} s"]
    if s["best_params"]:
        lines.append("best parameters: " + ", ".join(f"{k}={_fmt(v)}" for k, v in s["best_params"].items()))
    lines.append(f"outputs: {s['out']}")
    return "\n".join(lines)


def compare(cfg: TuneConfig, args) -> int:
    """``--compare``: the starting parameters and another file, scored on the bags (no study)."""
    other = args_.load_parameters(args.compare, {})
    seeds = [int(s) for s in args.compare_seeds]
    result = compare_parameters(cfg, {"start": cfg.start, "compare": dict(other)}, seeds)
    result = {"bags": cfg.bags, "seeds": seeds, "start_params": args.params, "compare_params": args.compare,
              **result}
    if args.json:
        print(json.dumps(result))
    else:
        for name in ("start", "compare"):
            r = result[name]
            metres = "agreement" not in r["sources"]  # the mean is in metres only when every bag's error is
            print(f"{name:<8} {args.params if name == 'start' else args.compare}: error per bag "
                  f"{bag_errors(r['errors'], r['sources'])} ({', '.join(r['sources'])}), mean "
                  f"{bag_errors([r['error']], ['truth' if metres else 'agreement'])}; "
                  f"score {r['score']:.4f}; {r['lost']} lost; {r['wall_s']:.1f} s per evaluation")
    return 0


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    t0 = time.perf_counter()
    try:
        cfg = make_config(args)
        check_inputs(cfg)
        if args.compare:
            return compare(cfg, args)
        args.out.mkdir(parents=True, exist_ok=True)
        study = run_workers(cfg, args.trials, args.jobs, progress=not args.quiet,
                            bar=False if args.quiet else progress_enabled())
        files = {}
        if any(t.state.name == "COMPLETE" for t in study.get_trials(deepcopy=False)):
            best = best_parameters(cfg, study)
            header = (f"{PROG}: best of study {cfg.study!r} (trial {study.best_trial.number}, score "
                      f"{study.best_value:.4f})\non {', '.join(cfg.bags)}, map {cfg.map}, from "
                      f"{args.params or 'the built-in defaults'}; {datetime.now().isoformat(timespec='seconds')}")
            files["best_params"] = str(write_best_params(args.out / "best_params.yaml", best, header))
        files["trials"] = str(write_trials_csv(args.out / "trials.csv", study, len(cfg.bags),
                                               [e.name for e in cfg.space]))
        plots = write_plots(args.out, study)
        files.update(plots["files"])
        summary = summarize(cfg, study, args.out, time.perf_counter() - t0, files)
        summary["notes"] = plots["notes"]
    except (TuneError, ReplayError, ParameterError) as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted (the study keeps every finished trial; run again to continue)", file=sys.stderr)
        return 130
    if args.json:
        print(json.dumps(summary, default=str))
    else:
        print(human_summary(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
