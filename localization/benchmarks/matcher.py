"""``python -m localization.benchmarks.matcher``: cost of the correlative scan matcher (the
reference track and the calibrator; offline, not in the node) on one CPU core.

Matches the scans of a simulated trial (1081 beams, 270°; default ``trial1_noise0``, the first
``--scans``) and of a real RSS 2022 bag, each seeded 0.1–0.2 m and 0.05 rad off the truth (the
simulated trial) or the previous match (the real bag), with the default window (±0.4 m,
±0.2 rad, the rotation step sized per scan so the farthest endpoint moves ≤ 1 cell per step,
every valid beam at both levels: no decimation), and prints per scan: the milliseconds (median,
p95), the median rotation step and the accuracy against the simulator's truth. The first scan
(JIT compilation, grid build) is not timed.

``--json`` prints one JSON object. Timings on a shared VM vary up to 2x run to run.
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np

from localization.core.matching import CorrelativeMatcher, MatcherConfig
from localization.core.occupancy_map import load_map
from localization.core.scan import beam_angles, clean_ranges
from localization.eval.datasets import REAL_BAGS, real_bag_path, trial_config
from localization.eval.metrics import interpolate_poses
from localization.eval.reference import read_scans
from localization.sim import simulate


def bench_sim(trial: str, scans: int, config: MatcherConfig) -> dict:
    cfg = trial_config(trial, duration=max(2.0, scans / cfg_rate(trial) + 0.5))
    m = load_map(cfg.map)
    rec = simulate(cfg, m)
    matcher = CorrelativeMatcher(m, config)
    angles = np.linspace(cfg.angle_min, cfg.angle_max, cfg.num_beams)
    truth = interpolate_poses(rec.scan_t, rec.truth_t, rec.truth_poses)
    rng = np.random.default_rng(0)
    times, errs, steps = [], [], []
    n = min(scans, len(rec.scan_t))
    for k in range(n):
        seed = truth[k] + np.r_[rng.uniform(0.1, 0.2) * rng.choice([-1, 1], 2), rng.normal(0, 0.05)]
        t0 = time.perf_counter()
        r = matcher.match(rec.scan_ranges[k], angles, tuple(cfg.laser_offset), seed)
        dt = time.perf_counter() - t0
        if k > 0:
            times.append(dt)
        errs.append(float(np.hypot(*(r.pose[:2] - truth[k, :2]))))
        steps.append(r.angle_step)
    ms = np.asarray(times) * 1e3
    return {"scans": n, "beams": int(cfg.num_beams), "angle_step_median_rad": float(np.median(steps)),
            "ms_median": float(np.median(ms)),
            "ms_p95": float(np.percentile(ms, 95)), "error_median_m": float(np.median(errs)),
            "error_p95_m": float(np.percentile(errs, 95))}


def cfg_rate(trial: str) -> float:
    return trial_config(trial).scan_rate


def bench_real(name: str, config: MatcherConfig) -> dict:
    rb = REAL_BAGS[name]
    m = load_map(rb.map)
    scans = read_scans(real_bag_path(name), rb.scan_topic)
    matcher = CorrelativeMatcher(m, config)
    seed = np.asarray(rb.start, dtype=float)
    times, steps = [], []
    for k, s in enumerate(scans):
        n = np.asarray(s.ranges).size
        angles = beam_angles(n, s.angle_min, s.angle_max, s.angle_increment)
        t0 = time.perf_counter()
        r = matcher.match(clean_ranges(s.ranges, s.range_min, s.range_max), angles, (0.275, 0.0, 0.0), seed,
                          *((1.0, 0.5) if k == 0 else (None, None)))
        dt = time.perf_counter() - t0
        if k > 0:
            times.append(dt)
        if r is not None:
            seed = r.pose
            steps.append(r.angle_step)
    ms = np.asarray(times) * 1e3
    return {"scans": len(scans), "angle_step_median_rad": float(np.median(steps)), "ms_median": float(np.median(ms)),
            "ms_p95": float(np.percentile(ms, 95))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m localization.benchmarks.matcher", description=__doc__.split("\n")[0])
    ap.add_argument("--trial", default="trial1_noise0")
    ap.add_argument("--scans", type=int, default=200)
    ap.add_argument("--real", default="bag1", help="real bag name (bag1, bag2, bag3) or 'none'")
    ap.add_argument("--max-beams", type=int, default=None, help="decimate the scan to this many beams")
    ap.add_argument("--angle-step", type=float, default=None,
                    help="a fixed rotation step (rad); default: sized per scan")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    config = MatcherConfig(max_beams=args.max_beams, angle_step=args.angle_step)
    out = {"config": {"window_xy_m": config.window_xy, "window_theta_rad": config.window_theta,
                      "angle_step_rad": config.angle_step, "coarse_step_cells": config.coarse_step,
                      "max_beams": config.max_beams},
           "sim": bench_sim(args.trial, args.scans, config)}
    if args.real != "none":
        out["real"] = bench_real(args.real, config)
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    s = out["sim"]
    print(f"correlative matcher, window ±{config.window_xy} m ±{config.window_theta} rad, "
          f"{'all' if config.max_beams is None else config.max_beams} beams")
    print(f"  simulated {args.trial}: {s['ms_median']:.1f} ms/scan median, {s['ms_p95']:.1f} ms p95 "
          f"({s['scans']} scans x {s['beams']} beams); error vs truth median {s['error_median_m'] * 1e3:.1f} mm, "
          f"p95 {s['error_p95_m'] * 1e3:.1f} mm; rotation step median {s['angle_step_median_rad'] * 1e3:.2f} mrad")
    if "real" in out:
        r = out["real"]
        print(f"  real {args.real}: {r['ms_median']:.1f} ms/scan median, {r['ms_p95']:.1f} ms p95 "
              f"({r['scans']} scans); rotation step median {r['angle_step_median_rad'] * 1e3:.2f} mrad")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
