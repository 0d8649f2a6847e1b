"""``localization-demo``: the main job in one command.

1. Records (or reuses from the cache) the three simulated Stata basement trials of the
   reference lab report (odometry noise 0, 0.3, 0.6; ``localization.datasets``), and with
   ``--loop`` the longer loop with biased odometry.
2. Replays each with ``localization-replay``'s code (``config/params.yaml``, the simulator's parameters)
   and the three real
   RSS 2022 bags from their approximate start poses with ``config/real_params.yaml``.
3. Prints a table like the report's (trial, noise level -> CT error; real bags -> scan-map
   agreement) and where the plots are.
4. The fast trial (6-7 m/s, odometry 40 ms late, lidar sweep timing): mean error and
   along-/cross-track error against the ground truth with odometry aligned to each scan and the
   scan deskewed (``odom_time_offset`` = -0.04, the latency the calibrator measures) and with
   both off (``align_odometry`` and ``deskew`` false: no time alignment at all). ``--skip-fast``.

``--motion-sweep`` adds a table of the real bags' scan-map agreement as the motion-noise
parameters of ``real_params.yaml`` are scaled (how much the filter should trust the odometry).

Replays run in parallel worker processes (``--jobs``, default: the number of CPUs, at most 4).
``--out`` (default ``./demo-results``) must not hold anything yet unless ``--overwrite`` (its
files are then replaced).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from localization.core.parameters import Parameters
from localization.core.paths import config_dir
from localization.eval.datasets import REAL_BAGS, REPORT_TRIALS, SIM_TRIALS, real_bag_path, sim_bag
from localization.tools import args as args_

PROG = "localization-demo"

#: Mean CT error (m) the reference lab report measured on its three simulated trials.
REFERENCE_CT = {"trial1_noise0": 0.224, "trial2_noise0.3": 0.183, "trial3_noise0.6": 0.261}

MOTION_NOISE_PARAMS = ("motion_a_trans", "motion_a_lateral", "motion_a_rot", "motion_a_rot_to_trans",
                       "motion_a_trans_to_rot", "motion_floor_xy", "motion_floor_theta")


def _replay_job(job: dict) -> dict:
    """Run one replay (in a worker process); returns its metrics plus bookkeeping."""
    from localization.eval.replay import ReplayError, ReplayOptions, compute_metrics, run_replay, write_outputs
    t0 = time.perf_counter()
    try:
        params = Parameters.from_yaml(job["params_file"], **job["overrides"]) if job.get("params_file") \
            else Parameters(job["overrides"])
        opts = ReplayOptions(Path(job["bag"]), job["map"], params, job.get("initial_pose"),
                             label=job["label"], scan_topic=job.get("scan_topic"), odom_topic=job.get("odom_topic"))
        res = run_replay(opts)
        metrics = compute_metrics(res)
        if job.get("out"):
            write_outputs(res, metrics, Path(job["out"]), plots=job.get("plots", True))
    except ReplayError as exc:
        return {"job": job, "error": str(exc)}
    return {"job": job, "metrics": metrics, "seconds": time.perf_counter() - t0}


def _run_all(jobs: list, workers: int) -> list:
    if workers <= 1 or len(jobs) <= 1:
        return [_replay_job(j) for j in jobs]
    with ProcessPoolExecutor(max_workers=workers) as pool:
        return list(pool.map(_replay_job, jobs))


def _f(v, spec=".3f"):
    return "  n/a" if v is None else f"{v:{spec}}"


def _table(header: str, results: list, width: int, row) -> str:
    """The header, then ``row(label, metrics)`` per replay (or its error)."""
    lines = [header]
    for r in results:
        name = r["job"]["label"]
        lines.append(f"{name:<{width}} error: {r['error']}" if "error" in r else row(name, r["metrics"]))
    return "\n".join(lines)


def sim_table(results: list) -> str:
    def row(name, m):
        ct, conv, head = m["ct_error_m"], m["time_to_converge_s"], m["heading_error_mean_abs_rad"]
        return (f"{name:<22} {SIM_TRIALS[name].odom_noise:>5.1f} {_f(ct['mean']):>8} {_f(ct['median']):>7} "
                f"{_f(ct['p95']):>6} {_f(ct['max']):>6} {_f(ct['rms']):>6} "
                f"{_f(None if head is None else head * 57.29578, '.2f'):>7}° "
                f"{'never' if conv is None else f'{conv:.3f} s':>9} "
                f"{_f(m['scan_map_agreement']['median']):>6} {_f(REFERENCE_CT.get(name)):>7}")
    return _table(f"{'trial':<22} {'noise':>5} {'mean CT':>8} {'median':>7} {'p95':>6} {'max':>6} {'rms':>6} "
                  f"{'heading':>8} {'converge':>9} {'agree':>6} {'report':>7}", results, 22, row)


FAST_TRIAL = "fast"
#: the fast trial's replays: label -> parameter overrides
FAST_RUNS = {"fast_aligned": {"odom_time_offset": -0.04},
             "fast_unaligned": {"align_odometry": False, "deskew": False}}


def fast_table(results: list) -> str:
    def row(name, m):
        ct = m["ct_error_m"]
        along, cross = m.get("truth_along_track_error_m") or {}, m.get("truth_abs_cross_track_error_m") or {}
        return (f"{name:<16} {_f(ct['mean']):>8} {_f(ct['median']):>7} {_f(ct['p95']):>6} {_f(ct['max']):>6} "
                f"{_f(along.get('mean'), '+.4f'):>11} {_f(cross.get('mean'), '.4f'):>10}")
    return _table(f"{'run':<16} {'mean':>8} {'median':>7} {'p95':>6} {'max':>6} {'mean along':>11} "
                  f"{'|cross|':>10}", results, 16, row)


def real_table(results: list) -> str:
    def row(name, m):
        ag = m["scan_map_agreement"]
        ref = m.get("reference_error_m") or {}
        along = (m.get("along_track_error_m") or {}).get("mean")
        return (f"{name:<6} {m['bag_duration_s']:>7.1f}s {m['sensor_updates']:>7} {_f(ag['median']):>9} "
                f"{_f(ag['mean']):>6} {m['max_jump_m']:>7.2f}m {_f(ref.get('median')):>7} {_f(ref.get('p95')):>6} "
                f"{_f(ref.get('max')):>6} {'n/a' if along is None else f'{along:+.3f}':>7}")
    return _table(f"{'bag':<6} {'duration':>8} {'updates':>7} {'agreement':>9} {'mean':>6} {'max jump':>8} "
                  f"{'ref med':>7} {'p95':>6} {'max':>6} {'along':>7}", results, 6, row)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog=PROG, description="Record (or reuse) the simulated Stata basement trials, "
                                 "replay them and the real RSS 2022 bags, print the results table.")
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
    ap.add_argument("--skip-real", action="store_true", help="only the simulated trials")
    ap.add_argument("--skip-fast", action="store_true", help="skip the fast trial (aligned vs unaligned)")
    ap.add_argument("--duration", type=float, help="truncate the simulated trials to this many seconds")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--motion-sweep", nargs="*", type=float, metavar="SCALE",
                    help="also replay the real bags with real_params.yaml's motion noise scaled by these factors "
                         "(default 0.25 0.5 1 2)")
    return ap


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    overrides = {"random_seed": args.seed, **dict(args.overrides)}
    if args.particles is not None:
        overrides["num_particles"] = args.particles
    try:
        Parameters(overrides)
    except ValueError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    out = args.out.resolve()
    problem = args_.output_problem(out, args.overwrite, kind="folder")
    if problem:
        print(f"{PROG}: error: --out: {problem}", file=sys.stderr)
        return 1
    sim_params, real_params = config_dir() / "params.yaml", config_dir() / "real_params.yaml"

    sim_jobs, real_jobs, sweep_jobs = [], [], []
    if not args.skip_sim:
        names = list(REPORT_TRIALS) + (["loop_noise0.3_biased"] if args.loop else [])
        for name in names:
            extra = {"duration": args.duration} if args.duration else {}
            bag = sim_bag(name, log=lambda s: print(s, file=sys.stderr), **extra)
            sim_jobs.append({"label": name, "bag": str(bag), "map": SIM_TRIALS[name].config.map,
                             "params_file": str(sim_params), "overrides": overrides, "out": str(out / name)})
    if not args.skip_sim and not args.skip_fast:
        extra = {"duration": args.duration} if args.duration else {}
        bag = sim_bag(FAST_TRIAL, log=lambda s: print(s, file=sys.stderr), **extra)
        for label, ov in FAST_RUNS.items():
            sim_jobs.append({"label": label, "bag": str(bag), "map": SIM_TRIALS[FAST_TRIAL].config.map,
                             "params_file": str(sim_params), "overrides": {**overrides, **ov}, "out": str(out / label),
                             "fast": True})
    if not args.skip_real:
        for name, rb in REAL_BAGS.items():
            path = real_bag_path(name)
            real_jobs.append({"label": name, "bag": str(path), "map": rb.map, "params_file": str(real_params),
                              "overrides": overrides, "initial_pose": rb.start, "scan_topic": rb.scan_topic,
                              "odom_topic": rb.odom_topic, "out": str(out / name)})
        if args.motion_sweep is not None:
            scales = args.motion_sweep or [0.25, 0.5, 1.0, 2.0]
            base = Parameters.from_yaml(real_params)
            for s in scales:
                ov = dict(overrides)
                ov.update({k: float(base[k]) * s for k in MOTION_NOISE_PARAMS})
                for job in real_jobs:
                    sweep_jobs.append({**job, "overrides": ov, "out": None, "scale": s, "plots": False})

    t0 = time.perf_counter()
    print(f"replaying {len(sim_jobs)} simulated trials and {len(real_jobs)} real bags "
          f"({len(sweep_jobs)} sweep runs) with {args.jobs} worker(s) ...", file=sys.stderr)
    results = _run_all(sim_jobs + real_jobs + sweep_jobs, args.jobs)
    fast_res = [r for r in results[:len(sim_jobs)] if r["job"].get("fast")]
    sim_res = [r for r in results[:len(sim_jobs)] if not r["job"].get("fast")]
    real_res = results[len(sim_jobs):len(sim_jobs) + len(real_jobs)]
    sweep_res = results[len(sim_jobs) + len(real_jobs):]

    n = overrides.get("num_particles", Parameters().num_particles)
    if sim_res:
        print(f"\nSimulated Stata basement trials (stata_basement, config/params.yaml, {n} particles); "
              f"CT error in metres, 'report' = the reference lab report's mean CT error")
        print(sim_table(sim_res))
    if fast_res:
        print(f"\nFast trial (6-7 m/s, odometry 40 ms late, lidar sweep timing; config/params.yaml, {n} particles): "
              "error vs ground truth in metres (targets: mean <= 0.03, |mean along| <= 0.01 aligned); aligned = "
              "odometry on each scan's clock (odom_time_offset -0.04) + deskew, unaligned = both off")
        print(fast_table(fast_res))
    if real_res:
        print(f"\nReal RSS 2022 bags (basement_fixed, config/real_params.yaml, {n} particles, from the approximate "
              "start poses): agreement = median fraction of beams ending within 0.10 m of a wall; error vs the "
              "reference track (scan-to-map matches, no ground truth) in metres: median, p95, max, mean along-track "
              "(targets: median <= 0.05, p95 <= 0.15, |along| <= 0.02)")
        print(real_table(real_res))
    if sweep_res:
        print("\nReal bags: median scan-map agreement vs motion noise (real_params.yaml's motion_* scaled by)")
        scales = sorted({r["job"]["scale"] for r in sweep_res})
        print(f"{'scale':>6} " + " ".join(f"{b:>6}" for b in REAL_BAGS) + f" {'mean':>6}")
        for s in scales:
            vals = [r["metrics"]["scan_map_agreement"]["median"] if "metrics" in r else None
                    for r in sweep_res if r["job"]["scale"] == s]
            ok = [v for v in vals if v is not None]
            print(f"{s:>6.2f} " + " ".join(f"{_f(v):>6}" for v in vals)
                  + f" {_f(sum(ok) / len(ok) if ok else None):>6}")
    out.mkdir(parents=True, exist_ok=True)
    summary = {r["job"]["label"] + (f"@{r['job']['scale']}" if "scale" in r["job"] else ""):
               r.get("metrics", {"error": r.get("error")}) for r in results}
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(f"\nplots and metrics: {out}/<trial or bag>/(trajectory.png, error.png, metrics.json, poses.csv); "
          f"summary: {out / 'summary.json'}  [{time.perf_counter() - t0:.0f} s]")
    return 1 if any("error" in r for r in results) else 0


if __name__ == "__main__":
    sys.exit(main())
