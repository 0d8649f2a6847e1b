"""``python -m localization.benchmarks.course_model``: the course's public ``SensorModel``, as a user
or the course's tests construct it (defaults only), timed on the Stata basement.

    sm = SensorModel(); sm.set_map(load_map("stata_basement"))
    sm.evaluate(particles, observation, angles)          # particles uniform over the free space

Prints the median / p95 of the full ``evaluate`` (weights, not log weights) per workload, on one
core, after a warm-up; ``--json`` prints the same as one object. Targets: 4000 × 60
≤ 6 ms, 10 000 × 100 ≤ 25 ms.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

WORKLOADS = ((4000, 60, 6.0), (10000, 100, 25.0))  # particles, beams, target ms


def measure(map_name: str = "stata_basement", reps: int = 30, seed: int = 0) -> dict:
    os.environ.setdefault("NUMBA_NUM_THREADS", "1")
    import numpy as np

    from localization.core.models.beam import BeamModel as SensorModel  # what localization.sensor_model exports
    from localization.core.occupancy_map import load_map

    occupancy_map = load_map(map_name)
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    sm = SensorModel()
    sm.set_map(occupancy_map)
    setup_s = time.perf_counter() - t0
    rows = []
    for n, b, target in WORKLOADS:
        particles = occupancy_map.sample_free_poses(n, rng)
        angles = np.linspace(-2.356, 2.356, b)
        observation = sm.expected_ranges(particles[:1], angles)[0]
        times = []
        for _ in range(reps + 3):  # three warm-up calls
            t = time.perf_counter()
            w = sm.evaluate(particles, observation, angles)
            times.append(time.perf_counter() - t)
        ms = np.asarray(times[3:]) * 1e3
        rows.append({"particles": n, "beams": b, "median_ms": float(np.median(ms)),
                     "p95_ms": float(np.percentile(ms, 95)), "target_ms": target,
                     "finite_weights": bool(np.all(np.isfinite(w)))})
    return {"map": map_name, "ray_caster": type(sm.ray_caster).__name__, "setup_s": setup_s, "workloads": rows}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m localization.benchmarks.course_model",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--map", default="stata_basement")
    ap.add_argument("--reps", type=int, default=30)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    r = measure(args.map, args.reps)
    if args.json:
        print(json.dumps(r))
        return 0
    print(f"SensorModel() defaults on {r['map']}: {r['ray_caster']}, set_map {r['setup_s']:.2f} s")
    for w in r["workloads"]:
        ok = "ok" if w["median_ms"] <= w["target_ms"] else "MISSED"
        print(f"  {w['particles']:>6} x {w['beams']:<4} evaluate median {w['median_ms']:6.2f} ms, "
              f"p95 {w['p95_ms']:6.2f} ms  (target <= {w['target_ms']:g} ms: {ok})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
