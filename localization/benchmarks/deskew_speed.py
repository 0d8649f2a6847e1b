"""``python -m localization.benchmarks.deskew_speed``: the price and the accuracy of scan deskew.

The sensor update (beam model, fused lookup-table kernel, particles drawn uniformly over the free
space before every update) with per-beam laser offsets δ_b — a 7 m/s, 0.8 rad/s drive over one
18.75 ms UST-10LX sweep — against the same update without them, alternated rep by rep so both see
the same machine load; target: deskew ≤ 1.3 × the rigid update. Then the accuracy: the deskewed
table query against ``ExactRayCaster`` casting every beam from the true laser pose at its own time
(median / p95 |Δrange| over random free poses), next to the rigid query's.
``localization.benchmarks.speed`` prints the same section (JSON key ``deskew``).

Timings on a shared VM vary up to 2x run to run: compare numbers from one run.
"""
from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from localization.core.geometry import compose, integrate_twists, inverse

DESKEW_TARGET_RATIO = 1.3
SWEEP_S = 0.01875  # s: 1081 beams over 270° at 40 Hz
SPEED, YAW_RATE = 7.0, 0.8  # m/s, rad/s during the sweep
WORKLOADS = [(2000, 100), (4000, 60)]


def sweep_offsets(laser_offset, beams: int) -> tuple[np.ndarray, np.ndarray]:
    """(δ_b laser frame, Δ_b robot frame) (B, 3) for beams spread over one sweep around its middle."""
    robot = integrate_twists(SPEED, 0.0, YAW_RATE, np.linspace(-0.5 * SWEEP_S, 0.5 * SWEEP_S, beams))
    laser = np.asarray(laser_offset, dtype=float)
    return compose(inverse(laser), compose(robot, laser)), robot


def bench_deskew(sensor_model, occupancy_map, exact, params, quick: bool, rng) -> dict:
    """Timings and accuracy (see the module docstring); ``sensor_model`` a BeamModel with its
    lookup-table caster set, ``exact`` an ``ExactRayCaster`` of the same map and range."""
    from localization.core.filter.mcl import MonteCarloLocalizer
    from localization.core.models.motion import MotionModel
    reps = 5 if quick else 30
    rows = []
    for n, b in ([(2000, 60)] if quick else WORKLOADS):
        pf = MonteCarloLocalizer(MotionModel(True), sensor_model, n, 1.0, (0.0, 0.0, 0.0), rng)
        angles = np.linspace(-2.356, 2.356, b)
        offsets, _ = sweep_offsets(sensor_model.laser_offset, b)
        pose = occupancy_map.sample_free_poses(1, rng)
        ranges = exact.cast(compose(pose, sensor_model.laser_offset), angles)[0]
        times = {"rigid": [], "deskew": []}
        for rep in range(reps + 1):
            for kind in ("rigid", "deskew") if rep % 2 else ("deskew", "rigid"):
                pf.initialize_uniform(occupancy_map)
                t0 = time.perf_counter()
                pf.sensor_update(ranges, angles, offsets if kind == "deskew" else None)
                if rep:
                    times[kind].append(time.perf_counter() - t0)
        rigid, deskew = (float(np.median(times[k])) * 1e3 for k in ("rigid", "deskew"))
        rows.append({"particles": n, "beams": b, "rigid_ms_median": rigid, "deskew_ms_median": deskew,
                     "ratio": deskew / rigid})
    # accuracy against exact per-beam casting from the true laser poses
    count = 100 if quick else 400
    angles = np.linspace(-2.356, 2.356, 100)
    offsets, robot = sweep_offsets(sensor_model.laser_offset, angles.size)
    poses = occupancy_map.sample_free_poses(count, rng)
    truth_poses = compose(compose(poses[:, None, :], robot[None]), sensor_model.laser_offset)
    truth = exact.cast_rays(truth_poses.reshape(-1, 3), np.tile(angles, count)).reshape(count, -1)
    deskewed = sensor_model.expected_ranges(poses, angles, offsets)
    rigid = sensor_model.expected_ranges(poses, angles)
    ok = truth < sensor_model.max_range - 0.5
    err_d, err_r = np.abs(deskewed - truth)[ok], np.abs(rigid - truth)[ok]
    def stats(e):
        return {"median": float(np.median(e)), "p95": float(np.percentile(e, 95))}

    return {"deskew": {"workloads": rows, "target_ratio": DESKEW_TARGET_RATIO, "speed_m_s": SPEED,
                       "yaw_rate_rad_s": YAW_RATE, "sweep_s": SWEEP_S, "poses": count,
                       "deskewed_vs_exact_m": stats(err_d), "rigid_vs_exact_m": stats(err_r)}}


def format_deskew(r: dict) -> list[str]:
    d = r["deskew"]
    lines = [f"scan deskew (sensor update with per-beam laser offsets: {d['speed_m_s']:g} m/s, "
             f"{d['yaw_rate_rad_s']:g} rad/s over a {1e3 * d['sweep_s']:.2f} ms sweep; lookup table; "
             "uniform particles)"]
    for w in d["workloads"]:
        ok = w["ratio"] <= d["target_ratio"]
        lines.append(f"  {w['particles']:>6} x {w['beams']:<4} sensor update: rigid {w['rigid_ms_median']:.2f} ms, "
                     f"deskew {w['deskew_ms_median']:.2f} ms, ratio {w['ratio']:.2f} "
                     f"(target <= {d['target_ratio']:g})  {'OK' if ok else 'MISSED'}")
    a, b = d["deskewed_vs_exact_m"], d["rigid_vs_exact_m"]
    lines.append(f"  vs exact casting from each beam's true pose ({d['poses']} poses x 100 beams): deskewed median "
                 f"{100 * a['median']:.2f} cm, p95 {100 * a['p95']:.1f} cm; rigid scan median "
                 f"{100 * b['median']:.2f} cm, p95 {100 * b['p95']:.1f} cm")
    return lines


def run(map_name: str = "stata_basement", quick: bool = False, seed: int = 0) -> dict:
    from localization.core.models.beam import BeamModel, BeamModelParams
    from localization.core.occupancy_map import load_map
    from localization.core.parameters import Parameters
    from localization.core.raycast.exact import ExactRayCaster
    params = Parameters(ray_caster="lookup_table", random_seed=seed)
    occupancy_map = load_map(map_name)
    model = BeamModel(BeamModelParams.from_parameters(params), occupancy_map=occupancy_map)
    return bench_deskew(model, occupancy_map, ExactRayCaster(occupancy_map, model.max_range), params, quick,
                        np.random.default_rng(seed))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m localization.benchmarks.deskew_speed",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--quick", action="store_true", help="a small smoke run")
    ap.add_argument("--map", default="stata_basement")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    r = run(args.map, args.quick, args.seed)
    print(json.dumps(r) if args.json else "\n".join(format_deskew(r)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
