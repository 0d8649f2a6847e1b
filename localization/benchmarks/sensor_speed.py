"""Sensor models (beam vs likelihood field) and adaptive vs fixed particle counts: the speed
figures ``python -m localization.benchmarks.speed`` prints in the same run (JSON keys
``likelihood_field`` and ``adaptive``).

- both models' evaluation (``log_likelihood``) and full sensor update (downsample, evaluate,
  normalise, resample) on particles spread uniformly over the free space (the worst case for
  memory access), for (N, B) in {(4000, 60), (10000, 60), (10000, 100)}; target: the likelihood
  field's evaluation of 10 000 particles x 100 beams <= 5 ms (median, one core);
- one sensor update + resampling of a tight (tracking: 0.1 m, 0.05 rad) and a spread (global:
  uniform) cloud, fixed count vs KLD-adaptive (``adaptive_particles``): the particle count it
  leaves and its time. The accuracy of each is ``localization.benchmarks.models``.

On its own: ``python -m localization.benchmarks.sensor_speed [--quick] [--json] [--map NAME]``
(the default ``lookup_table`` caster, its table from the user's cache).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

from localization.core.geometry import compose
from localization.core.scan import ScanData

LF_TARGET_MS = {(10000, 100): 5.0}  # likelihood field log_likelihood, median, one core
FULL_SCAN_BEAMS = 1081  # Hokuyo UST-10LX: 270° in 0.25° steps
SCAN_HALF_ANGLE = 2.356194490192345  # rad


def _median_ms(samples) -> float:
    return float(np.median(np.asarray(samples) * 1e3))


def full_scan(exact, occupancy_map, rng):
    """A synthetic full scan (1081 beams over 270°, range_max 30 m) from a random free pose, with range
    noise and 2 % dropouts (as ``speed._full_scan``, which the speed benchmark passes instead)."""
    pose = occupancy_map.sample_free_poses(1, rng)
    angles = np.linspace(-SCAN_HALF_ANGLE, SCAN_HALF_ANGLE, FULL_SCAN_BEAMS)
    ranges = exact.cast(pose, angles)[0] + rng.normal(0.0, 0.02, FULL_SCAN_BEAMS)
    ranges[rng.random(FULL_SCAN_BEAMS) < 0.02] = np.inf
    return ranges, angles[0], angles[-1], (angles[-1] - angles[0]) / (FULL_SCAN_BEAMS - 1), 0.02, 30.0


def bench_models(occupancy_map, exact, params, quick: bool, rng, full_scan) -> dict:
    """The figures of the module docstring, as ``{"likelihood_field": ..., "adaptive": ...}``;
    ``full_scan(exact, occupancy_map, rng)``: a synthetic 1081-beam scan (``speed._full_scan``)."""
    from localization.core.filter.kld import KLDSampler
    from localization.core.filter.mcl import MonteCarloLocalizer
    from localization.core.localizer import build_filter
    from localization.core.parameters import Parameters
    from localization.core.scan import downsample_scan

    reps = 5 if quick else 30
    workloads = [(2000, 60)] if quick else [(4000, 60), (10000, 60), (10000, 100)]
    beam_filter = build_filter(Parameters(params, sensor_model="beam"))
    lf_filter = build_filter(Parameters(params, sensor_model="likelihood_field"))
    models = {"beam": beam_filter.sensor_model, "likelihood_field": lf_filter.sensor_model}
    for m in models.values():
        m.set_map(occupancy_map)
    rough = (params.roughening_xy, params.roughening_xy, params.roughening_theta)
    scans = [full_scan(exact, occupancy_map, rng) for _ in range(4)]
    rows = []
    for n, b in workloads:
        row = {"particles": n, "beams": b}
        for name, model in models.items():
            pf = MonteCarloLocalizer(beam_filter.motion_model, model, n, params.resample_ess_fraction, rough, rng)
            eval_t, eval_cpu, update_t = [], [], []
            for rep in range(reps + 2):  # the first two are warm-up
                particles = occupancy_map.sample_free_poses(n, rng)
                scan = downsample_scan(ScanData(0.0, *scans[rep % len(scans)]), b)
                t0, c0 = time.perf_counter(), time.thread_time()
                model.log_likelihood(particles, scan.ranges, scan.angles)
                t1, c1 = time.perf_counter(), time.thread_time()
                pf.initialize_uniform(occupancy_map)
                t2 = time.perf_counter()
                full = downsample_scan(ScanData(0.0, *scans[rep % len(scans)]), b)
                pf.sensor_update(full.ranges, full.angles)
                t3 = time.perf_counter()
                if rep >= 2:
                    eval_t.append(t1 - t0)
                    eval_cpu.append(c1 - c0)
                    update_t.append(t3 - t2)
            row[f"{name}_eval_ms_median"] = _median_ms(eval_t)
            row[f"{name}_eval_cpu_ms_median"] = _median_ms(eval_cpu)  # thread CPU time: robust to other load
            row[f"{name}_update_ms_median"] = _median_ms(update_t)
        rows.append(row)
    lf = {"workloads": rows, "field_mb": models["likelihood_field"].nbytes / 2**20,
          "targets_ms": {f"{n}x{b}": t for (n, b), t in LF_TARGET_MS.items()}}

    # adaptive vs fixed: one sensor update + resampling of a tight and a spread cloud, both models
    kld = KLDSampler.from_parameters(params)
    pose = occupancy_map.sample_free_poses(1, rng)[0]
    angles = np.linspace(-SCAN_HALF_ANGLE, SCAN_HALF_ANGLE, FULL_SCAN_BEAMS)
    ranges = exact.cast(compose(pose[None], models["beam"].laser_offset), angles)[0]
    scan = downsample_scan(ScanData(0.0, ranges, angles[0], angles[-1], angles[1] - angles[0], 0.02, 30.0),
                           params.num_beams_per_particle)
    adaptive = {"min_particles": kld.params.min_particles, "max_particles": kld.params.max_particles,
                "fixed_particles": params.num_particles, "global_particles": params.global_num_particles,
                "cases": []}
    for name, model in models.items():
        for cloud in ("tight", "spread"):
            for mode in ("fixed", "adaptive"):
                n0 = (params.num_particles if cloud == "tight" else
                      kld.params.max_particles if mode == "adaptive" else params.global_num_particles)
                pf = MonteCarloLocalizer(beam_filter.motion_model, model, n0, 1.0, rough, rng,
                                         kld if mode == "adaptive" else None)
                times, counts = [], []
                for _ in range(max(3, reps // 5)):
                    pf.resize(n0)
                    if cloud == "tight":
                        pf.initialize_gaussian(pose, std=(0.1, 0.1, 0.05))
                    else:
                        pf.initialize_uniform(occupancy_map)
                    t0 = time.perf_counter()
                    pf.sensor_update(scan.ranges, scan.angles)
                    times.append(time.perf_counter() - t0)
                    counts.append(pf.num_particles)
                adaptive["cases"].append({"sensor_model": name, "cloud": cloud, "mode": mode, "particles_before": n0,
                                          "particles_after": int(np.median(counts)),
                                          "update_ms_median": _median_ms(times)})
    return {"likelihood_field": lf, "adaptive": adaptive}


def format_models(r: dict) -> list:
    """Report lines of ``bench_models``' figures (``r``: the speed benchmark's result)."""
    lf, ad = r["likelihood_field"], r["adaptive"]
    lines = ["sensor models, particles spread uniformly (ms, median): model evaluation (log_likelihood) / full "
             f"sensor update; the likelihood field's grid: {lf['field_mb']:.1f} MB",
             f"{'N':>6} {'B':>4} | {'beam eval / update':>20} | {'likelihood_field eval / update':>31}"]
    verdicts = []
    for w in lf["workloads"]:
        lines.append(f"{w['particles']:>6} {w['beams']:>4} | {w['beam_eval_ms_median']:8.2f} / "
                     f"{w['beam_update_ms_median']:8.2f} | {w['likelihood_field_eval_ms_median']:17.2f} / "
                     f"{w['likelihood_field_update_ms_median']:8.2f}")
        target = LF_TARGET_MS.get((w["particles"], w["beams"]))
        if target is not None:
            ok = w["likelihood_field_eval_ms_median"] <= target
            verdicts.append(f"  likelihood field evaluation {w['particles']} x {w['beams']}: "
                            f"{w['likelihood_field_eval_ms_median']:.2f} ms (thread CPU time "
                            f"{w['likelihood_field_eval_cpu_ms_median']:.2f} ms; target <= {target:g})  "
                            f"{'OK' if ok else 'MISSED'}")
    lines += verdicts
    lines += ["", f"adaptive particle count (KLD, min {ad['min_particles']}, max {ad['max_particles']}) vs fixed "
              f"({ad['fixed_particles']} tracking, {ad['global_particles']} global): one sensor update + resampling",
              f"{'model':<17} {'cloud':<7} {'mode':<9} {'particles before -> after':>26} {'update ms':>10}"]
    for c in ad["cases"]:
        lines.append(f"{c['sensor_model']:<17} {c['cloud']:<7} {c['mode']:<9} "
                     f"{c['particles_before']:>12} -> {c['particles_after']:<11} {c['update_ms_median']:10.2f}")
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m localization.benchmarks.sensor_speed",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", action="store_true", help="print one JSON object instead of the report")
    ap.add_argument("--quick", action="store_true", help="a small smoke run (one workload, few repetitions)")
    ap.add_argument("--map", default="stata_basement", help="map name or YAML path (default stata_basement)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    os.environ.setdefault("NUMBA_NUM_THREADS", "1")
    from localization.core.occupancy_map import OccupancyMap, resolve_map_path
    from localization.core.parameters import Parameters
    from localization.core.raycast.exact import ExactRayCaster

    occupancy_map = OccupancyMap.from_yaml(resolve_map_path(args.map))
    params = Parameters(ray_caster="lookup_table", random_seed=args.seed)
    exact = ExactRayCaster(occupancy_map, 30.0)
    r = bench_models(occupancy_map, exact, params, args.quick, np.random.default_rng(args.seed), full_scan)
    print(json.dumps(r) if args.json else "\n".join(format_models(r)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
