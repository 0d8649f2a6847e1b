"""``python -m localization.benchmarks.models``: the two sensor models, fixed and KLD-adaptive
particle counts, compared on the same data (the table of docs/models.md).

Configurations (each on top of the scenario's shipped parameter file):

    beam           sensor_model: beam (the course's model, the default)
    lf             sensor_model: likelihood_field
    lf_skip        likelihood_field with do_beamskip
    beam_kld       beam, adaptive_particles (KLD)
    lf_kld         likelihood_field, adaptive_particles

Scenarios:

- the simulated Stata basement trials (``localization.eval.datasets``: trial1_noise0,
  trial2_noise0.3, trial3_noise0.6, the 75 s biased loop, and ``fast``: the loop at up to 7 m/s
  with sweep timing and late odometry), ``config/params.yaml``, fed message by message to the
  ``Localizer`` from the /initialpose of the recording (0.5 m, 0.2 rad off);
- ``clutter``: trial 3 simulated on the map plus unmapped boxes along the walls (0.3 m, one
  per ~2.5 m of wall near the route) and people-like short readings (3 blobs of 2–5° at
  0.5–4 m per scan), localized on the clean map;
- the real RSS 2022 bags (``config/real_params.yaml``, map basement_fixed, /vesc/odom, the
  start poses of /work/shared/bags/README.md), scored by the scan–map agreement (fraction of
  beams within 0.1 m of the map) since they have no ground truth.

Per run: mean / p95 / max position error over the whole run (from the initial pose), the share
of estimates more than 0.2 m off, the time until it stays below 0.2 m, mean particle count,
sensor update time (median ms, this machine, noisy), and recoveries. ``--quick``: trial 1 and 3,
clutter and one real bag, 3 configurations.
``--json``: one JSON object ``{"runs": [...]}``.
"""
from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from localization.benchmarks.robustness import ct_errors, run_recording
from localization.core.localizer import Localizer
from localization.core.occupancy_map import OccupancyMap, load_map
from localization.core.parameters import Parameters
from localization.core.paths import config_dir
from localization.eval import metrics as M
from localization.eval.datasets import REAL_BAGS, real_bag_path, trial_config
from localization.sim import simulate

CONFIGS = {
    "beam": {},
    "lf": {"sensor_model": "likelihood_field"},
    "lf_skip": {"sensor_model": "likelihood_field", "do_beamskip": True},
    "beam_kld": {"adaptive_particles": True},
    "lf_kld": {"sensor_model": "likelihood_field", "adaptive_particles": True},
}
SIM_SCENARIOS = ("trial1_noise0", "trial2_noise0.3", "trial3_noise0.6", "loop_noise0.3_biased", "fast", "clutter")
QUICK_SIM = ("trial1_noise0", "trial3_noise0.6", "clutter")
QUICK_CONFIGS = ("beam", "lf", "lf_kld")


def cluttered_map(occupancy_map: OccupancyMap, route, seed: int = 0, every_m: float = 2.5,
                  size_m: float = 0.3) -> OccupancyMap:
    """A copy of the map with unmapped square boxes along the walls near ``route`` ((K, 2) points):
    box centres 0.25–0.45 m from a wall, 0.4 m or more from the route, one per ``every_m`` of route."""
    rng = np.random.default_rng(seed)
    d = occupancy_map.distance_to_obstacle()
    cand = np.argwhere(occupancy_map.free & (d >= 0.25) & (d <= 0.45))
    xy = occupancy_map.grid_to_world(cand[:, ::-1])
    route = np.asarray(route, dtype=float)
    from scipy.spatial import cKDTree
    dist, _ = cKDTree(route).query(xy)
    cand = cand[(dist >= 0.4) & (dist <= 1.5)]
    length = float(np.sum(np.hypot(*np.diff(route, axis=0).T)))
    picks = cand[rng.choice(len(cand), size=min(len(cand), int(length / every_m)), replace=False)]
    data = occupancy_map.data.copy()
    half = max(1, int(round(0.5 * size_m / occupancy_map.resolution)))
    for r, c in picks:  # a few hundred boxes at most: the loop is over boxes, not particles or beams
        data[max(0, r - half):r + half, max(0, c - half):c + half] = 100
    return OccupancyMap(data, occupancy_map.resolution, occupancy_map.origin)


def add_people(ranges: np.ndarray, increment: float, seed: int = 0, blobs: int = 3) -> np.ndarray:
    """Short readings: per scan, ``blobs`` people-like objects (2–5° wide, 0.5–4 m away) where they
    are in front of the mapped surface."""
    rng = np.random.default_rng(seed)
    out = ranges.copy()
    n_scans, n_beams = out.shape
    width = np.clip((np.radians(rng.uniform(2, 5, (n_scans, blobs))) / increment).astype(int), 1, n_beams)
    start = rng.integers(0, n_beams, (n_scans, blobs))
    dist = rng.uniform(0.5, 4.0, (n_scans, blobs)).astype(out.dtype)
    beam = np.arange(n_beams)
    for b in range(blobs):  # vectorised over scans and beams
        inside = (beam[None, :] >= start[:, b:b + 1]) & (beam[None, :] < start[:, b:b + 1] + width[:, b:b + 1])
        out = np.where(inside, np.minimum(out, dist[:, b:b + 1]), out)
    return out


def _run_sim(rec, params: Parameters, occupancy_map: OccupancyMap) -> dict:
    loc = Localizer(params)
    loc.set_map(occupancy_map)
    t0 = float(rec.odometry.t[0])
    run = run_recording(rec, loc, init="pose")
    log = run.log
    cmp = ct_errors(rec, run)
    conv = M.time_to_converge(cmp.t, cmp.ct_error, M.CONVERGENCE_THRESHOLD_M, t0)
    err = cmp.ct_error  # the whole run, from the (0.5 m off) initial pose
    particles = np.asarray(log.particles, dtype=float)
    return {"converge_s": conv, "ct_mean_m": float(err.mean()), "ct_p95_m": float(np.percentile(err, 95)),
            "ct_max_m": float(err.max()), "above_0.2m_pct": float(100 * np.mean(err > M.CONVERGENCE_THRESHOLD_M)),
            "heading_mean_deg": float(np.degrees(cmp.heading_error.mean())),
            "particles_mean": float(particles.mean()) if particles.size else None,
            "particles_min": int(particles.min()) if particles.size else None,
            "particles_max": int(particles.max()) if particles.size else None,
            "update_ms_median": float(np.median(log.sensor_times) * 1e3) if log.sensor_times else None,
            "recoveries": loc.recoveries, "sensor_updates": log.counts["sensor_updates"]}


def _run_real(name: str, params: Parameters) -> dict:
    from localization.eval.replay import ReplayOptions, compute_metrics, run_replay
    bag = REAL_BAGS[name]
    res = run_replay(ReplayOptions(real_bag_path(name), bag.map, params, initial_pose=bag.start,
                                   odom_topic=bag.odom_topic, scan_topic=bag.scan_topic, reference=False))
    m = compute_metrics(res)
    ag = m["scan_map_agreement"]
    return {"agreement_mean": ag["mean"], "agreement_p05": ag["p05"], "max_jump_m": m["max_jump_m"],
            "particles_mean": (m["particles"] or {}).get("mean"),
            "update_ms_median": m["sensor_update_ms"]["median_ms"], "recoveries": m["recoveries"]}


def recordings(names, log=print):
    """(scenario, Recording, map to localize on) for each simulated scenario."""
    stata = load_map("stata_basement")
    for name in names:
        t0 = time.perf_counter()
        if name == "clutter":
            cfg = trial_config("trial3_noise0.6")
            route = np.vstack([np.asarray(cfg.start[:2])[None], np.asarray(cfg.waypoints)])
            from localization.sim import densify
            sim_map = cluttered_map(stata, densify(route, 0.1), seed=0)
            rec = simulate(cfg, sim_map)
            rec.scan_ranges = add_people(rec.scan_ranges, rec.scan_angle_increment, seed=0)
        else:
            rec = simulate(trial_config(name), stata)
        log(f"simulated {name}: {rec.duration:.1f} s in {time.perf_counter() - t0:.1f} s")
        yield name, rec, stata


def run(quick: bool = False, configs=None, scenarios=None, real=None, log=print) -> list:
    configs = configs or (QUICK_CONFIGS if quick else tuple(CONFIGS))
    scenarios = scenarios if scenarios is not None else (QUICK_SIM if quick else SIM_SCENARIOS)
    real = real if real is not None else (("bag1",) if quick else tuple(REAL_BAGS))
    runs = []
    for name, rec, occ in recordings(scenarios, log):
        for c in configs:
            params = Parameters.from_yaml(config_dir() / "params.yaml", random_seed=0, **CONFIGS[c])
            r = {"scenario": name, "config": c, **_run_sim(rec, params, occ)}
            log(_row(r))
            runs.append(r)
    for name in real:
        for c in configs:
            params = Parameters.from_yaml(config_dir() / "real_params.yaml", random_seed=0, **CONFIGS[c])
            r = {"scenario": f"real_{name}", "config": c, **_run_real(name, params)}
            log(_row(r))
            runs.append(r)
    return runs


def _f(v, spec=".3f"):
    return "   n/a" if v is None else f"{v:{spec}}"


def _row(r: dict) -> str:
    head = f"{r['scenario']:<22} {r['config']:<9}"
    parts = f"particles {_f(r.get('particles_mean'), '7.0f')}  update {_f(r.get('update_ms_median'), '5.1f')} ms"
    if "agreement_mean" in r:
        return (f"{head} agreement mean {_f(r['agreement_mean'])} p05 {_f(r['agreement_p05'])}  "
                f"jump {_f(r['max_jump_m'], '.2f')} m  {parts}  recoveries {r['recoveries']}")
    return (f"{head} CT mean {_f(r['ct_mean_m'])} p95 {_f(r['ct_p95_m'])} max {_f(r['ct_max_m'])} m  "
            f">0.2 m {_f(r['above_0.2m_pct'], '5.1f')} %  converge {_f(r['converge_s'], '.2f')} s  {parts}  "
            f"recoveries {r['recoveries']}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m localization.benchmarks.models", description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer scenarios and configurations")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--configs", nargs="*", choices=tuple(CONFIGS), help="configurations (default: all)")
    ap.add_argument("--scenarios", nargs="*", choices=SIM_SCENARIOS, help="simulated scenarios (default: all)")
    ap.add_argument("--real", nargs="*", choices=tuple(REAL_BAGS), help="real bags (default: all)")
    args = ap.parse_args(argv)
    log = (lambda s: print(s, file=sys.stderr, flush=True)) if args.json else print
    runs = run(args.quick, args.configs, args.scenarios, args.real, log)
    if args.json:
        print(json.dumps({"runs": runs}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
