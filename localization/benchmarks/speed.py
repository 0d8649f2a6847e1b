"""``python -m localization.benchmarks.speed``: real-time performance of the filter on one CPU core.

Prints, on the Stata basement map (or ``--map``), for (N particles, B beams) in
{(200, 100), (2000, 60), (4000, 60), (10000, 60), (10000, 100)}:

- ray cast (ms, median / 95th percentile) of ``LookupTableRayCaster.cast`` and rays/s;
- the full sensor update (ms, median / p95): downsample a 1081-beam scan → ray cast → table
  lookup → log-sum → normalise → resample (every scan, as ``resample_ess_fraction`` = 1);
- the motion update (ms, median / p95) for one 50 Hz odometry message;
- the same ray casts through ``ExactRayCaster`` (the exact numpy marcher) in the same run: the
  ratio to beat;

then the lookup table's accuracy against the exact caster (|Δrange| in cells over uniformly
random free poses and headings, 60 beams over 270°), the price and accuracy of the exact finish
(``ray_caster: lookup_table_exact``, the simulator's ``config/params.yaml``: the table plus a
short exact march per beam; the workloads above are the plain ``lookup_table``, the default and
the car's), and init time / peak memory of a fresh
node-like process (``Localizer`` + map + lookup table + first odometry and scan): "cold" with an
empty table cache *and* an empty numba cache (so table build and JIT compilation are counted),
"cached" when both are warm. Particles are drawn uniformly over the free space before every
timed update: the worst case for memory access (a converged cloud is faster).

``--json`` prints one JSON object instead; ``--quick`` is a small smoke run (two workloads,
few repetitions, and "cold" probes that start with only the table caches empty: their kernels come
from numba's cache; its numbers are not the benchmark). ``--latency`` adds (or, with
``--latency-only``, runs only) the end-to-end latency of the live ROS node: a 40 Hz scan + 50 Hz
odometry stream replayed into ``particle_filter`` at real time (see ``benchmarks.latency``).
It also prints both sensor models (beam, likelihood field) and adaptive vs fixed particle
counts (``benchmarks.sensor_speed``, JSON keys ``likelihood_field``, ``adaptive``), and the sensor
update with scan deskew on vs off (``benchmarks.deskew_speed``, JSON key ``deskew``).
The default run also prints the large-map figures (the Stata basement tiled 3 × 3: init cold and
cached, peak memory, accuracy; ``localization.benchmarks.large_map``, JSON key ``large_map``,
~1-2 min); ``--no-large-map`` skips them, ``--large-map-only`` runs only them.

Timings on a shared VM vary up to 2x run to run: compare numbers from one run.
"""
from __future__ import annotations

import argparse
import gc
import json
import os
import resource
import subprocess
import sys
import tempfile
import time

T_PROCESS = time.perf_counter()  # for the init probe: before the heavy imports below

import numpy as np  # noqa: E402

from localization.benchmarks.latency import format_latency, measure_latency  # noqa: E402
from localization.core.odometry import TwistData  # noqa: E402
from localization.core.scan import ScanData  # noqa: E402

WORKLOADS = [(200, 100), (2000, 60), (4000, 60), (10000, 60), (10000, 100)]
QUICK_WORKLOADS = [(200, 100), (2000, 60)]
TARGETS_MS = {(4000, 60): 6.0, (10000, 60): 15.0, (10000, 100): 25.0}  # full sensor update, median
PROTOTYPE_MS = {(4000, 60): 6.1, (10000, 60): 15.5, (10000, 100): 23.6}  # the first numpy lookup prototype
MOTION_TARGET_MS = 1.0
FULL_SCAN_BEAMS = 1081  # Hokuyo UST-10LX: 270° in 0.25° steps
SCAN_HALF_ANGLE = 2.356194490192345
ODOM_DT = 0.02  # 50 Hz


def _rss_peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: kB


def _stats(samples) -> tuple[float, float]:
    a = np.asarray(samples) * 1e3
    return float(np.median(a)), float(np.percentile(a, 95))


def _full_scan(exact, occupancy_map, rng):
    """A synthetic full scan (1081 beams over 270°) from a random free pose, with range noise
    and a few dropouts, as the Localizer receives it."""
    pose = occupancy_map.sample_free_poses(1, rng)
    angles = np.linspace(-SCAN_HALF_ANGLE, SCAN_HALF_ANGLE, FULL_SCAN_BEAMS)
    ranges = exact.cast(pose, angles)[0] + rng.normal(0.0, 0.02, FULL_SCAN_BEAMS)
    ranges[rng.random(FULL_SCAN_BEAMS) < 0.02] = np.inf
    increment = (angles[-1] - angles[0]) / (FULL_SCAN_BEAMS - 1)
    return ranges, angles[0], angles[-1], increment, 0.02, 30.0


# --------------------------------------------------------------------------------------------
# the init probe: a fresh node-like process
# --------------------------------------------------------------------------------------------
def probe_init(map_name: str, theta_bins: int, particles: int, beams: int) -> dict:
    """Time a node-like start in this (fresh) process: imports, map load, Localizer + set_map
    (lookup table built or loaded, kernels compiled or loaded), first odometry and first scan."""
    t0 = time.perf_counter()
    from localization.core.localizer import Localizer
    from localization.core.occupancy_map import OccupancyMap, resolve_map_path
    from localization.core.parameters import Parameters
    from localization.core.raycast.exact import ExactRayCaster
    t1 = time.perf_counter()
    occupancy_map = OccupancyMap.from_yaml(resolve_map_path(map_name))
    t2 = time.perf_counter()
    params = Parameters(num_particles=particles, num_beams_per_particle=beams,  # the default (lookup-table) caster
                        scan_theta_discretization=theta_bins, random_seed=0)
    loc = Localizer(params)
    caster = loc.prepare_ray_caster(occupancy_map)  # what set_map does, the caster kept for its figures
    loc.set_map(occupancy_map, caster)
    t3 = time.perf_counter()
    rng = np.random.default_rng(0)
    pose = occupancy_map.sample_free_poses(1, rng)[0]
    loc.set_initial_pose(pose, stamp=0.0)
    loc.on_odometry(TwistData(0.0, 1.0, 0.0, 0.1))
    loc.on_odometry(TwistData(ODOM_DT, 1.0, 0.0, 0.1))
    t4 = time.perf_counter()
    scan = _full_scan(ExactRayCaster(occupancy_map, caster.max_range), occupancy_map, rng)
    t5 = time.perf_counter()
    loc.on_scan(ScanData(ODOM_DT, *scan))
    t6 = time.perf_counter()
    return {
        "import_s": t1 - t0 + (t0 - T_PROCESS), "map_load_s": t2 - t1, "set_map_s": t3 - t2,
        "first_updates_s": (t4 - t3) + (t6 - t5), "init_s": (t3 - t2) + (t4 - t3) + (t6 - t5),
        "ready_s": (t6 - T_PROCESS) - (t5 - t4), "table_from_cache": bool(caster.loaded_from_cache),
        "ray_caster": params.ray_caster,
        "table_build_s": caster.build_seconds, "table_mb": caster.nbytes / 2**20, "peak_rss_mb": _rss_peak_mb(),
        # the short-lived process that compiled the kernels into numba's cache (0: none ran)
        "compile_child_peak_rss_mb": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0,
    }


def _run_probe(map_name, theta_bins, particles, beams, table_cache, numba_cache) -> dict:
    """One init probe in a fresh process; ``numba_cache`` None: numba's own cache (kernels compiled already)."""
    env = dict(os.environ, LOCALIZATION_CACHE_DIR=table_cache,
               **({} if numba_cache is None else {"NUMBA_CACHE_DIR": numba_cache}))
    cmd = [sys.executable, "-m", "localization.benchmarks.speed", "--probe-init", "--map", map_name,
           "--bins", str(theta_bins), "--probe-particles", str(particles), "--probe-beams", str(beams)]
    t0 = time.perf_counter()
    out = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    if out.returncode != 0:
        raise RuntimeError(f"init probe failed ({out.returncode}):\n{out.stderr}")
    result = json.loads(out.stdout.strip().splitlines()[-1])
    result["process_wall_s"] = wall
    return result


# --------------------------------------------------------------------------------------------
# the benchmark
# --------------------------------------------------------------------------------------------
def run(map_name="stata_basement", theta_bins=None, quick=False, seed=0, progress=None) -> dict:
    from localization.core.filter.mcl import MonteCarloLocalizer
    from localization.core.geometry import compose, integrate_twist
    from localization.core.localizer import build_filter
    from localization.core.occupancy_map import OccupancyMap, resolve_map_path
    from localization.core.parameters import Parameters
    from localization.core.raycast.exact import ExactRayCaster
    from localization.core.raycast.lookup_table import LookupTableRayCaster
    from localization.core.scan import downsample_scan

    say = progress or (lambda msg: None)
    params = Parameters(ray_caster="lookup_table", random_seed=seed,
                        **({"scan_theta_discretization": theta_bins} if theta_bins else {}))
    theta_bins = params.scan_theta_discretization
    occupancy_map = OccupancyMap.from_yaml(resolve_map_path(map_name))
    rng = np.random.default_rng(seed)
    cold_jit = not quick  # --quick: the cold probes load the kernels from numba's own cache
    result = {"map": map_name, "theta_bins": theta_bins, "quick": quick, "cold_jit": cold_jit, "cpus": os.cpu_count(),
              "load_average_start": os.getloadavg()[0]}

    # init: fresh processes, cold (empty table cache; empty numba cache too unless quick) then cached
    say("init probes (fresh processes: cold, then cached) ...")
    template = build_filter(params)  # the filter as the node builds it
    sensor_model, motion_model = template.sensor_model, template.motion_model
    with tempfile.TemporaryDirectory(prefix="localization-bench-") as tmp:
        tables, jit = os.path.join(tmp, "tables"), os.path.join(tmp, "numba") if cold_jit else None
        cold = _run_probe(map_name, theta_bins, 4000, 60, tables, jit)
        cached = _run_probe(map_name, theta_bins, 4000, 60, tables, jit)
        # the probes' table: the benchmark neither needs nor touches the user's cache
        caster = LookupTableRayCaster.for_map(occupancy_map, sensor_model.table_range, theta_bins, cache_dir=tables)
    result.update(init_cold_s=cold["init_s"], init_cached_s=cached["init_s"],
                  peak_rss_mb=max(cold["peak_rss_mb"], cached["peak_rss_mb"]), init_cold=cold, init_cached=cached)
    sensor_model.set_map(occupancy_map, caster)
    exact = ExactRayCaster(occupancy_map, sensor_model.max_range)
    offset = sensor_model.laser_offset
    delta = integrate_twist(2.0, 0.0, 0.5, ODOM_DT)

    reps = 5 if quick else 40
    exact_reps = 1 if quick else 3
    workloads = QUICK_WORKLOADS if quick else WORKLOADS
    rows = []
    gc_was_enabled = gc.isenabled()
    for n, b in workloads:
        say(f"workload {n} x {b} ...")
        pf = MonteCarloLocalizer(motion_model, sensor_model, n, params.resample_ess_fraction,
                                 (params.roughening_xy, params.roughening_xy, params.roughening_theta), rng)
        scans = [_full_scan(exact, occupancy_map, rng) for _ in range(4)]
        angles = downsample_scan(ScanData(0.0, *scans[0]), b).angles
        cast_t, update_t, motion_t, update_cpu = [], [], [], []
        for rep in range(reps + 2):  # the first two are warm-up
            sensors = compose(occupancy_map.sample_free_poses(n, rng), offset)
            gc.disable()
            t0 = time.perf_counter()
            caster.cast(sensors, angles)
            t1 = time.perf_counter()
            pf.initialize_uniform(occupancy_map)
            t2, c2 = time.perf_counter(), time.thread_time()
            scan = downsample_scan(ScanData(0.0, *scans[rep % len(scans)]), b)
            pf.sensor_update(scan.ranges, scan.angles)
            t3, c3 = time.perf_counter(), time.thread_time()
            pf.motion_update(delta)
            t4 = time.perf_counter()
            if gc_was_enabled:
                gc.enable()
            if rep >= 2:
                cast_t.append(t1 - t0)
                update_t.append(t3 - t2)
                update_cpu.append(c3 - c2)
                motion_t.append(t4 - t3)
        exact_t = []
        for _ in range(exact_reps):
            sensors = compose(occupancy_map.sample_free_poses(n, rng), offset)
            t0 = time.perf_counter()
            exact.cast(sensors, angles)
            exact_t.append(time.perf_counter() - t0)
        cast_med, cast_p95 = _stats(cast_t)
        upd_med, upd_p95 = _stats(update_t)
        mot_med, mot_p95 = _stats(motion_t)
        exact_med, _ = _stats(exact_t)
        rows.append({
            "particles": n, "beams": b,
            "raycast_ms_median": cast_med, "raycast_ms_p95": cast_p95,
            "sensor_update_ms_median": upd_med, "sensor_update_ms_p95": upd_p95,
            "motion_update_ms_median": mot_med, "motion_update_ms_p95": mot_p95,
            "rays_per_s": n * b / (cast_med / 1e3),
            "exact_raycast_ms_median": exact_med, "exact_rays_per_s": n * b / (exact_med / 1e3),
            "speedup_vs_exact": exact_med / cast_med,
            "sensor_update_cpu_ms_median": _stats(update_cpu)[0],
        })
    result["workloads"] = rows

    # accuracy of the lookup table against the exact caster
    say("accuracy ...")
    count = 1000 if quick else 5000
    poses = occupancy_map.sample_free_poses(count, rng)
    angles = np.linspace(-SCAN_HALF_ANGLE, SCAN_HALF_ANGLE, 60)
    exact_ranges = exact.cast(poses, angles)
    diff = np.abs(caster.cast(poses, angles) - exact_ranges) / occupancy_map.resolution
    result["fast_vs_exact"] = {
        "median_abs_cells": float(np.median(diff)), "p95_abs_cells": float(np.percentile(diff, 95)),
        "p99_abs_cells": float(np.percentile(diff, 99)), "within_1_cell": float(np.mean(diff <= 1.0)),
        "poses": count, "beams": angles.size, "interpolation": caster.interpolation,
    }

    # the exact finish (refine; ray_caster lookup_table_exact): its price and its accuracy
    say("exact finish (refine) ...")
    refined = LookupTableRayCaster(occupancy_map, caster.max_range, theta_bins, table=caster.table, refine=1.0)
    refined.warm_up()
    diff = np.abs(refined.cast(poses, angles) - exact_ranges) / occupancy_map.resolution
    finish = {"refine_cells": refined.refine, "median_abs_cells": float(np.median(diff)),
              "p95_abs_cells": float(np.percentile(diff, 95)), "exact_fraction": float(np.mean(diff < 1e-6)),
              "workloads": []}
    sensor_model.set_map(occupancy_map, refined)
    for n, b in ([(2000, 60)] if quick else [(4000, 60), (10000, 60)]):
        pf = MonteCarloLocalizer(motion_model, sensor_model, n, params.resample_ess_fraction,
                                 (params.roughening_xy, params.roughening_xy, params.roughening_theta), rng)
        scans = [_full_scan(exact, occupancy_map, rng) for _ in range(4)]
        update_t = []
        for rep in range(max(3, reps // 4) + 1):
            pf.initialize_uniform(occupancy_map)
            t0 = time.perf_counter()
            scan = downsample_scan(ScanData(0.0, *scans[rep % len(scans)]), b)
            pf.sensor_update(scan.ranges, scan.angles)
            if rep:
                update_t.append(time.perf_counter() - t0)
        finish["workloads"].append({"particles": n, "beams": b, "sensor_update_ms_median": _stats(update_t)[0]})
    sensor_model.set_map(occupancy_map, caster)
    result["exact_finish"] = finish
    say("sensor models and adaptive particle counts ...")
    from localization.benchmarks.sensor_speed import bench_models
    result.update(bench_models(occupancy_map, exact, params, quick, rng, _full_scan))
    say("scan deskew ...")  # the sensor update with per-beam laser offsets vs without
    from localization.benchmarks.deskew_speed import bench_deskew
    result.update(bench_deskew(sensor_model, occupancy_map, exact, params, quick, rng))
    result["bench_peak_rss_mb"] = _rss_peak_mb()
    result["load_average_end"] = os.getloadavg()[0]
    return result


def format_report(r: dict) -> str:
    lines = [f"localization.benchmarks.speed — map {r['map']}, lookup table {r['theta_bins']} heading bins, one thread"
             + ("  [--quick: smoke run, not the benchmark]" if r.get("quick") else ""),
             "particles drawn uniformly over free space before every update (worst case); times in ms; "
             f"1-min load average {r['load_average_start']:.1f} at the start, {r['load_average_end']:.1f} at the end "
             f"on {r['cpus']} CPUs (another process on the core inflates every number)", ""]
    head = (f"{'N':>6} {'B':>4} | {'ray cast med/p95':>17} {'Mrays/s':>8} | {'sensor update med/p95':>21} "
            f"{'target':>7} | {'motion med/p95':>15} | {'exact cast':>10} {'ratio':>7}")
    lines += [head, "-" * len(head)]
    for w in r["workloads"]:
        key = (w["particles"], w["beams"])
        target = f"<={TARGETS_MS[key]:g}" if key in TARGETS_MS else ""
        lines.append(
            f"{w['particles']:>6} {w['beams']:>4} | {w['raycast_ms_median']:8.2f} /{w['raycast_ms_p95']:7.2f} "
            f"{w['rays_per_s'] / 1e6:8.1f} | {w['sensor_update_ms_median']:10.2f} /{w['sensor_update_ms_p95']:9.2f} "
            f"{target:>7} | {w['motion_update_ms_median']:6.3f} /{w['motion_update_ms_p95']:6.3f} | "
            f"{w['exact_raycast_ms_median']:10.1f} {w['speedup_vs_exact']:6.0f}x")
    lines.append("sensor update, CPU time of the thread (robust to other load), median: " + ", ".join(
        f"{w['particles']} x {w['beams']} {w['sensor_update_cpu_ms_median']:.2f} ms" for w in r["workloads"]))
    lines.append("")
    verdicts = []
    for w in r["workloads"]:
        key = (w["particles"], w["beams"])
        if key in TARGETS_MS:
            ok = w["sensor_update_ms_median"] <= TARGETS_MS[key]
            verdicts.append(f"  sensor update {key[0]} x {key[1]}: {w['sensor_update_ms_median']:.2f} ms "
                            f"(target <= {TARGETS_MS[key]:g}; numpy prototype {PROTOTYPE_MS[key]:g})"
                            f"  {'OK' if ok else 'MISSED'}")
        if key[0] == 10000 and key[1] == 60:
            ok = w["motion_update_ms_median"] <= MOTION_TARGET_MS
            verdicts.append(f"  motion update 10000: {w['motion_update_ms_median']:.3f} ms median, "
                            f"{w['motion_update_ms_p95']:.3f} p95 (target <= 1)  {'OK' if ok else 'MISSED'}")
    a = r["fast_vs_exact"]
    verdicts.append(f"  lookup table vs exact ({a['poses']} uniform free poses x {a['beams']} beams, "
                    f"{a['interpolation']!r} interpolation): median |dr| {a['median_abs_cells']:.3f} cells "
                    f"(target <= 1), p95 {a['p95_abs_cells']:.2f} cells (target <= 3), p99 {a['p99_abs_cells']:.1f}, "
                    f"{100 * a['within_1_cell']:.1f}% within 1 cell  "
                    f"{'OK' if a['median_abs_cells'] <= 1 and a['p95_abs_cells'] <= 3 else 'MISSED'}")
    f = r["exact_finish"]
    verdicts.append("  with the exact finish (ray_caster lookup_table_exact, config/params.yaml for simulation; "
                    "refine = 1 cell): " + ", ".join(
        f"{x['particles']} x {x['beams']} sensor update {x['sensor_update_ms_median']:.2f} ms" for x in f["workloads"])
        + f"; {100 * f['exact_fraction']:.1f}% of beams exact, p95 |dr| {f['p95_abs_cells']:.2f} cells")
    c, w = r["init_cold"], r["init_cached"]
    compiled = "JIT compile" if r["cold_jit"] else "kernels from numba's cache (--quick)"
    verdicts.append(f"  init cold: {c['init_s']:.2f} s (table build {c['table_build_s']:.2f} s + {compiled}; "
                    f"target <= 10)  {'OK' if c['init_s'] <= 10 else 'MISSED'}")
    verdicts.append(f"  init cached: {w['init_s']:.2f} s (table from disk: {w['table_from_cache']}; "
                    f"target <= 1)  {'OK' if w['init_s'] <= 1 else 'MISSED'}")
    verdicts.append(f"    (init = set_map + first odometry + first scan; before it: imports {w['import_s']:.2f} s, "
                    f"map YAML/PNG load {w['map_load_s']:.2f} s; process start to first pose: cold "
                    f"{c['ready_s']:.2f} s, cached {w['ready_s']:.2f} s)")
    verdicts.append(f"  peak memory of a node-like process (4000 particles, table {c['table_mb']:.0f} MB): "
                    f"cold {c['peak_rss_mb']:.0f} MB (its short-lived kernel-compiling child "
                    f"{c.get('compile_child_peak_rss_mb', 0):.0f} MB, before the table), "
                    f"cached {w['peak_rss_mb']:.0f} MB "
                    f"(target <= 300 on the Stata basement)  {'OK' if r['peak_rss_mb'] <= 300 else 'MISSED'}")
    verdicts.append(f"  (this benchmark process peaked at {r['bench_peak_rss_mb']:.0f} MB: the exact caster's "
                    "temporaries)")
    lines += ["targets:"] + verdicts
    if "likelihood_field" in r:  # sensor models, adaptive vs fixed counts (benchmarks.sensor_speed)
        from localization.benchmarks.sensor_speed import format_models
        lines += [""] + format_models(r)
    if "deskew" in r:  # benchmarks.deskew_speed
        from localization.benchmarks.deskew_speed import format_deskew
        lines += [""] + format_deskew(r)
    if "latency" in r:
        lines += ["", format_latency(r["latency"])]
    if "large_map" in r:
        from localization.benchmarks.large_map import format_report as format_large_map
        lines += ["", format_large_map(r["large_map"])]
    return "\n".join(lines)


JSON_WORKLOAD_KEYS = ("particles", "beams", "raycast_ms_median", "sensor_update_ms_median", "sensor_update_ms_p95",
                      "motion_update_ms_median", "rays_per_s", "exact_raycast_ms_median")


def to_json(r: dict) -> dict:
    out = {
        "workloads": [{k: w[k] for k in JSON_WORKLOAD_KEYS}
                      | {k: v for k, v in w.items() if k not in JSON_WORKLOAD_KEYS}
                      for w in r["workloads"]],
        "init_cold_s": r["init_cold_s"], "init_cached_s": r["init_cached_s"], "peak_rss_mb": r["peak_rss_mb"],
        "fast_vs_exact": r["fast_vs_exact"], "exact_finish": r["exact_finish"],
        "map": r["map"], "theta_bins": r["theta_bins"], "quick": r["quick"], "cold_jit": r["cold_jit"],
        "load_average": [r["load_average_start"], r["load_average_end"]],
        "init_cold": r["init_cold"], "init_cached": r["init_cached"], "bench_peak_rss_mb": r["bench_peak_rss_mb"],
    }
    for key in ("likelihood_field", "adaptive", "deskew"):  # benchmarks.sensor_speed, benchmarks.deskew_speed
        if key in r:
            out[key] = r[key]
    if "latency" in r:
        out["latency"] = r["latency"]
    if "large_map" in r:
        out["large_map"] = r["large_map"]
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m localization.benchmarks.speed", description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", action="store_true", help="print one JSON object instead of the report")
    ap.add_argument("--quick", action="store_true", help="a small smoke run (2 workloads, few repetitions)")
    ap.add_argument("--map", default="stata_basement", help="map name or YAML path (default stata_basement)")
    ap.add_argument("--bins", type=int, default=None, help="heading bins of the table "
                    "(default: the scan_theta_discretization parameter)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--latency", action="store_true", help="also measure the live node's end-to-end latency")
    ap.add_argument("--latency-only", action="store_true", help="only measure the live node's latency")
    ap.add_argument("--latency-particles", type=int, default=4000)
    ap.add_argument("--latency-duration", type=float, default=20.0, help="seconds of replayed stream")
    ap.add_argument("--no-large-map", action="store_true", help="skip the large-map figures (3 x 3 tiled basement)")
    ap.add_argument("--large-map-only", action="store_true", help="only the large-map figures")
    ap.add_argument("--probe-init", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--probe-particles", type=int, default=4000, help=argparse.SUPPRESS)
    ap.add_argument("--probe-beams", type=int, default=60, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)

    if args.probe_init:
        from localization.core.parameters import Parameters
        bins = args.bins or Parameters().scan_theta_discretization
        print(json.dumps(probe_init(args.map, bins, args.probe_particles, args.probe_beams)))
        return 0
    progress = None if args.json else (lambda msg: print(msg, file=sys.stderr, flush=True))
    if args.latency_only:
        lat = measure_latency(particles=args.latency_particles, duration=args.latency_duration, progress=progress)
        print(json.dumps(lat) if args.json else format_latency(lat))
        return 0
    from localization.benchmarks import large_map
    big_map = {"drive_s": 5.0 if args.quick else 20.0, "progress": progress, "cold_jit": not args.quick}
    if args.large_map_only:
        big = large_map.run(**big_map)
        print(json.dumps({"large_map": big}) if args.json else large_map.format_report(big))
        return 0
    result = run(args.map, args.bins, args.quick, args.seed, progress)
    if args.latency:
        result["latency"] = measure_latency(particles=args.latency_particles, duration=args.latency_duration,
                                            progress=progress)
    if not args.no_large_map:
        result["large_map"] = large_map.run(**big_map)
    print(json.dumps(to_json(result)) if args.json else format_report(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
