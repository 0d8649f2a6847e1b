"""Robustness benchmarks: global localization, kidnapped robot, a long drive, a corrupted bag.

    python -m localization.benchmarks.robustness            # global, kidnap, normal trials, 5-min drive, corrupted bag
    python -m localization.benchmarks.robustness --quick    # fewer runs, shorter drive (a smoke test)
    python -m localization.benchmarks.robustness --long     # the drive lasts the full 30 minutes
    python -m localization.benchmarks.robustness --only global --map building_31
        # global localization in another building, on a closed route built from its map (auto_loop)

Every run is simulated on the Stata basement map (``localization.simulator``, fixed seeds) and
fed, message by message in stamp order, to the very ``Localizer`` the node and
``localization-replay`` use (the corrupted-bag benchmark goes through ``localization-replay``
itself). Each benchmark prints its figures and one ``PASS`` / ``FAIL`` line per target:

1. global localization: no initial pose, ``global_num_particles``, 10 starts spread along the
   basement loop (the long self-similar corridor included); converged = CT error below 0.3 m from
   then on. Two runs of the 10 starts: ``global_init: scan`` (the default: particles drawn from the
   poses the first scan fits, ``core/filter/global_init.py``), target 10/10 within 5 s of driving;
   and the plain uniform spread (``global_init: uniform``) for comparison, target ≥ 8/10 within 20 s;
2. kidnapping: the car is teleported ≥ 10 m mid-run; target: back below 0.3 m (for good)
   within 15 s in ≥ 8/10 runs; plus no recovery at all in the three normal Stata trials;
3. long drive: the loop driven for 30 min (``--long``; 5 min by default, 2 with ``--quick``),
   simulated in 60 s pieces so memory stays flat; targets: resident memory growth < 10 %
   (after the first piece), no slowdown (process CPU time per message of the last pieces ≤ 1.25 ×
   that of the early ones, median of up to 3 pieces each), no CT error above 0.3 m after convergence;
4. corrupted bag: 5 % of the scans and of the odometry messages of a simulated bag corrupted
   (NaN/inf/negative/zero/huge ranges, empty or resized scans, zero or negative increments,
   NaN/inf/absurd twists, stamps going backwards); targets: the replay completes,
   ``poses.csv`` has no NaN, mean CT error within 20 % of the clean bag's.
"""
from __future__ import annotations

import argparse
import logging
import math
import resource
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from localization.benchmarks.drives import (
    STATA,
    TARGET_M,
    RunResult,
    bench_params,
    ct_errors,
    loop_config,
    loop_path,
    loop_pose,
    replace_params,
    run_recording,
    settle_time,
)
from localization.benchmarks.routes import auto_loop, enclosed
from localization.core.localizer import Localizer
from localization.core.occupancy_map import load_map
from localization.core.parameters import Parameters
from localization.eval.corrupt import corrupt_bag
from localization.eval.datasets import REPORT_TRIALS, trial_config
from localization.sim import simulate

# the drives (``drives``) and routes (``routes``) the benchmarks below use stay importable from here
__all__ = ["KIDNAP_WITHIN_S", "STATA", "TARGET_M", "RunResult", "auto_loop", "bench_corrupted", "bench_false_alarms",
           "bench_global", "bench_kidnap", "bench_long", "bench_params", "ct_errors", "enclosed", "loop_config",
           "loop_path", "loop_pose", "main", "replace_params", "rss_mb", "run_recording", "settle_time"]

KIDNAP_WITHIN_S = 15.0  # s: a kidnapped car is back below TARGET_M within this long


def _fmt_times(times) -> str:
    done = sorted(t for t in times if t is not None)
    if not done:
        return "none converged"
    q = np.percentile(done, [0, 25, 50, 75, 100])
    return "min {:.1f}  p25 {:.1f}  median {:.1f}  p75 {:.1f}  max {:.1f} s".format(*q)


def _line(ok: bool, text: str) -> str:
    return f"{'PASS' if ok else 'FAIL'}  {text}"


def bench_global(occ, runs: int, params: Parameters, drive_s: float = 20.0, log=print, method: str = "scan",
                 target_s: float = 5.0, target_runs: int | None = None, route=None, map_name: str = STATA) -> bool:
    """``runs`` global starts with ``global_init: method``; PASS when ``target_runs`` (default: all)
    converge below 0.3 m within ``target_s`` seconds of driving. The starts are spread along the
    basement loop, or along ``route`` (a closed route through ``occ``, named ``map_name``)."""
    n_path = len(loop_path(route))
    params = replace_params(params, global_init=method)
    target_runs = runs if target_runs is None else target_runs
    times = []
    for r in range(runs):
        start = int(r * n_path / runs) + 37
        rec = simulate(loop_config(start, drive_s + 2.0, seed=100 + r, route=route, map_name=map_name), occ)
        loc = Localizer(replace_params(params, random_seed=100 + r), logging.getLogger("bench.global"))
        loc.set_map(occ)
        run = run_recording(rec, loc, init="global")
        cmp = ct_errors(rec, run)
        t_conv = settle_time(cmp, float(rec.odometry.t[0]))
        times.append(t_conv)
        log(f"  global ({method}) run {r}: start ({rec.cfg.start[0]:6.1f}, {rec.cfg.start[1]:5.1f}) "
            f"converged {'never' if t_conv is None else f'{t_conv:5.1f} s'}  final err {cmp.ct_error[-1]:.2f} m  "
            f"re-spreads {run.recoveries}  filter {run.filter_time:.1f} s")
    ok_runs = sum(t is not None and t <= target_s for t in times)
    log(f"  global ({method}) convergence times: "
        + " ".join("never" if t is None else f"{t:.1f}" for t in times) + f" s; {_fmt_times(times)}")
    ok = ok_runs >= target_runs
    log(_line(ok, f"global localization ({method}): {ok_runs}/{runs} converged below {TARGET_M} m within "
                  f"{target_s:.0f} s (target >= {target_runs}/{runs}; {params.global_num_particles} particles)"))
    return ok



def bench_kidnap(occ, runs: int, params: Parameters, log=print) -> bool:
    path = loop_path()
    n_path = len(path)
    kidnap_at, after = 8.0, 17.0
    times = []
    for r in range(runs):
        start = int(r * n_path / runs) + 11
        # teleport to a loop point 40-90 m further along the route (>= 10 m away in straight line)
        rng = np.random.default_rng(200 + r)
        for _ in range(100):
            j = start + int(rng.uniform(800, 1800))
            target = loop_pose(j)
            if np.hypot(*(np.array(target[:2]) - path[(start + int(kidnap_at * 2.0 / 0.05)) % n_path])) >= 12.0:
                break
        rec = simulate(loop_config(start, kidnap_at + after, seed=200 + r, kidnap_at=kidnap_at, kidnap_to=target), occ)
        loc = Localizer(replace_params(params, random_seed=200 + r), logging.getLogger("bench.kidnap"))
        loc.set_map(occ)
        run = run_recording(rec, loc, init="pose")
        cmp = ct_errors(rec, run)
        t_back = settle_time(cmp, kidnap_at)
        before = cmp.ct_error[(cmp.t > 3.0) & (cmp.t < kidnap_at)]
        jump = float(np.hypot(*(rec.trajectory.poses[rec.trajectory.kidnapped_at_step][:2]
                                - rec.trajectory.poses[rec.trajectory.kidnapped_at_step - 1][:2])))
        times.append(t_back)
        log(f"  kidnap run {r}: teleported {jump:5.1f} m at {kidnap_at:.0f} s; back below {TARGET_M} m "
            f"{'never' if t_back is None else f'after {t_back:5.1f} s'}; recoveries {run.recoveries}; "
            f"err before {before.max() if before.size else float('nan'):.2f} m")
    ok_runs = sum(t is not None and t <= KIDNAP_WITHIN_S for t in times)
    log(f"  recovery times: {_fmt_times(times)}")
    ok = ok_runs >= math.ceil(0.8 * runs)
    log(_line(ok, f"kidnapping: {ok_runs}/{runs} back below {TARGET_M} m within {KIDNAP_WITHIN_S:g} s "
                  "(target >= 8/10)"))
    return ok


def bench_false_alarms(occ, params: Parameters, duration: float | None = None, log=print) -> bool:
    total = 0
    for name in REPORT_TRIALS:
        cfg = trial_config(name) if duration is None else trial_config(name, duration=duration)
        rec = simulate(cfg, occ)
        loc = Localizer(params, logging.getLogger("bench.normal"))
        loc.set_map(occ)
        run = run_recording(rec, loc, init="pose")
        cmp = ct_errors(rec, run)
        total += run.recoveries
        log(f"  normal {name}: {rec.duration:.0f} s, recoveries {run.recoveries}, health min "
            f"{run.health.min() if run.health.size else float('nan'):.2f} median "
            f"{np.median(run.health) if run.health.size else float('nan'):.2f}, CT mean {cmp.ct_error.mean():.3f} m")
    ok = total == 0
    log(_line(ok, f"no false recovery in the three normal Stata trials ({total} recoveries)"))
    return ok


def rss_mb() -> float:
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * resource.getpagesize() / 1e6
    except OSError:
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3


def bench_long(occ, minutes: float, params: Parameters, piece_s: float = 60.0, log=print) -> bool:
    """The loop driven for ``minutes``, simulated piece by piece (each piece starts where the last
    ended); the Localizer keeps running across pieces (stamps continue)."""
    loc = Localizer(params, logging.getLogger("bench.long"))
    loc.set_map(occ)
    pieces = max(2, int(round(minutes * 60.0 / piece_s)))
    start = loop_pose(0)
    rss, per_msg, worst, conv_t = [], [], 0.0, None
    t_offset = 0.0
    for p in range(pieces):
        cfg = loop_config(0, piece_s, seed=300 + p, initial_pose=(p == 0))
        cfg = replace(cfg, start=start)
        rec = simulate(cfg, occ)
        run = run_recording(rec, loc, init="pose" if p == 0 else "none", t_offset=t_offset)
        cmp = ct_errors(rec, run, t_offset)
        if p == 0:
            conv_t = settle_time(cmp, t_offset)
            after = cmp.ct_error[cmp.t >= t_offset + (conv_t or 0.0)] if conv_t is not None else cmp.ct_error
        else:
            after = cmp.ct_error
        worst = max(worst, float(after.max()) if after.size else 0.0)
        rss.append(rss_mb())
        per_msg.append(run.cpu_time / run.messages)
        start = tuple(rec.trajectory.poses[-1])
        t_offset += float(rec.trajectory.t[-1]) + 0.02
        del rec, run
    growth = (max(rss[1:]) - rss[0]) / rss[0]
    k = max(1, min(3, (pieces - 1) // 2))  # medians of k pieces: early (after the first) vs the last ones
    slow = float(np.median(per_msg[-k:]) / np.median(per_msg[1:1 + k]))
    log(f"  long drive: {pieces} x {piece_s:.0f} s = {pieces * piece_s / 60:.0f} min; RSS after piece 1 "
        f"{rss[0]:.0f} MB, max later {max(rss[1:]):.0f} MB, last {rss[-1]:.0f} MB; CPU time per message "
        f"(median of {k} pieces) early {np.median(per_msg[1:1 + k]) * 1e3:.3f} ms, last "
        f"{np.median(per_msg[-k:]) * 1e3:.3f} ms; converged after "
        f"{conv_t if conv_t is not None else float('nan'):.1f} s; worst CT error after that {worst:.3f} m; "
        f"recoveries {loc.recoveries}")
    ok_mem, ok_speed, ok_err = growth < 0.10, slow <= 1.25, worst <= TARGET_M
    log(_line(ok_mem, f"long drive memory growth {growth * 100:.1f} % (target < 10 %)"))
    log(_line(ok_speed, f"long drive no slowdown: CPU time per message, last/early pieces {slow:.2f} "
                         "(target <= 1.25)"))
    log(_line(ok_err, f"long drive max CT error after convergence {worst:.3f} m (target <= {TARGET_M} m)"))
    return ok_mem and ok_speed and ok_err


# --------------------------------------------------------------------------------------------
# Corrupted bags (localization.eval.corrupt)
# --------------------------------------------------------------------------------------------


def bench_corrupted(occ_name: str, params: Parameters, duration: float, workdir: Path, log=print) -> bool:
    from localization.eval.datasets import sim_bag
    from localization.eval.replay import ReplayOptions, compute_metrics, run_replay, write_outputs
    clean = sim_bag("loop_noise0.3_biased", duration=duration)
    bad = workdir / "corrupted"
    counts = corrupt_bag(clean, bad, 0.05, seed=7)
    results = {}
    for label, bag in (("clean", clean), ("corrupted", bad)):
        res = run_replay(ReplayOptions(bag, occ_name, params))
        met = compute_metrics(res)
        write_outputs(res, met, workdir / label, plots=False)
        poses = np.loadtxt(workdir / label / "poses.csv", delimiter=",", skiprows=1, ndmin=2)
        results[label] = (met, poses)
        log(f"  {label} bag: {met['scans']} scans, {met['odometry']} odometry, CT mean "
            f"{met['ct_error_m']['mean']:.3f} m p95 {met['ct_error_m']['p95']:.3f} m, recoveries "
            f"{met.get('recoveries', 0)}, NaN rows in poses.csv {int(np.isnan(poses).any(axis=1).sum())}")
    log(f"  corruptions: {sum(counts.values())} messages ({', '.join(f'{k} {v}' for k, v in sorted(counts.items()))})")
    clean_mean = results["clean"][0]["ct_error_m"]["mean"]
    bad_mean = results["corrupted"][0]["ct_error_m"]["mean"]
    no_nan = not np.isnan(results["corrupted"][1]).any()
    ok_acc = bad_mean <= 1.2 * clean_mean
    log(_line(no_nan, "corrupted bag: replay completed, poses.csv has no NaN"))
    log(_line(ok_acc, f"corrupted bag accuracy: CT mean {bad_mean:.3f} m vs clean {clean_mean:.3f} m "
                      f"(target within 20 %)"))
    return no_nan and ok_acc


# --------------------------------------------------------------------------------------------


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m localization.benchmarks.robustness",
                                 description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="3 runs per scenario, a 2-minute drive, shorter bags")
    ap.add_argument("--long", action="store_true", help="drive the full 30 minutes (default 5)")
    ap.add_argument("--only", choices=("global", "kidnap", "normal", "long", "corrupted"), action="append",
                    help="run only these benchmarks (repeatable)")
    ap.add_argument("--particles", type=int, help="global_num_particles (default: the parameter's default)")
    ap.add_argument("--map", default=STATA, metavar="NAME",
                    help=f"map (default {STATA}); another map runs only the global scenario, on a closed route "
                         "built from the map's free space (auto_loop), with the same parameters")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)
    overrides = {} if args.particles is None else {"global_num_particles": args.particles}
    params = bench_params(**overrides)
    occ = load_map(args.map)
    runs = 3 if args.quick else 10
    only = set(args.only or ("global", "kidnap", "normal", "long", "corrupted"))
    route = None
    if args.map != STATA:
        skipped = sorted(only - {"global"})
        if skipped:
            print(f"skipped on {args.map}: {', '.join(skipped)} (only the global scenario runs on maps other than "
                  f"{STATA})", flush=True)
        only &= {"global"}
        route = auto_loop(occ)
        length = float(np.hypot(*np.diff(route, axis=0, append=route[:1]).T).sum())
        print(f"route on {args.map}: closed, {len(route)} waypoints, {length:.0f} m (auto_loop: corridor centre "
              "lines from the clearance grid)", flush=True)
    t0 = time.perf_counter()
    results = {}
    print(f"robustness benchmarks on {args.map}: {params.num_particles} particles tracking, "
          f"{params.global_num_particles} when global, {params.ray_caster} ray caster", flush=True)
    if "global" in only:
        results["global"] = bench_global(occ, runs, params, log=lambda s: print(s, flush=True), method="scan",
                                         target_s=5.0, route=route, map_name=args.map)
        results["global_uniform"] = bench_global(occ, runs, params, log=lambda s: print(s, flush=True),
                                                 method="uniform", target_s=20.0, target_runs=math.ceil(0.8 * runs),
                                                 route=route, map_name=args.map)
    if "kidnap" in only:
        results["kidnap"] = bench_kidnap(occ, runs, params, log=lambda s: print(s, flush=True))
    if "normal" in only:
        results["normal"] = bench_false_alarms(occ, params, 20.0 if args.quick else None,
                                               log=lambda s: print(s, flush=True))
    if "long" in only:
        minutes = 30.0 if args.long else (2.0 if args.quick else 5.0)
        results["long"] = bench_long(occ, minutes, params, log=lambda s: print(s, flush=True))
    if "corrupted" in only:
        with tempfile.TemporaryDirectory(prefix="robustness-") as tmp:
            results["corrupted"] = bench_corrupted(STATA, params, 30.0 if args.quick else 75.0, Path(tmp),
                                                   log=lambda s: print(s, flush=True))
    print(f"{sum(results.values())}/{len(results)} benchmarks passed in {time.perf_counter() - t0:.0f} s")
    return 0 if all(results.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
