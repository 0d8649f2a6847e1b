"""What a replay produces: its metrics (``compute_metrics``), its files (``write_outputs``) and the summary
table ``localization-replay`` prints (``summary_table``)."""
from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np

from localization.core.cost import cost_summary
from localization.core.geometry import wrap_angle
from localization.eval import metrics as M
from localization.eval.replay.run import ReplayError, ReplayResult, bag_label

# --------------------------------------------------------------------------------------------
# Metrics and outputs
# --------------------------------------------------------------------------------------------


def compute_metrics(res: ReplayResult) -> dict:
    p = res.options.params
    out = {
        "bag": str(res.bag_path),
        "map": str(res.map_path),
        "scan_topic": res.scan_topic,
        "odom_topic": res.odom_topic,
        "num_particles": p.num_particles,
        "num_beams_per_particle": p.num_beams_per_particle,
        "ray_caster": p.ray_caster,
        "random_seed": p.random_seed,
        "initial_pose_source": res.initial_pose_source,
        "initial_pose": None if res.initial_pose is None else [float(v) for v in res.initial_pose],
        "estimates": int(len(res.est_t)),
        **{k: int(v) for k, v in res.counts.items()},
        "bag_duration_s": res.bag_duration,
        "wall_time_s": res.wall_time,
        "realtime_factor": res.bag_duration / res.wall_time if res.wall_time > 0 else None,
        "sensor_update_ms": M.timing_stats(res.sensor_times),
        "motion_update_ms": M.timing_stats(res.motion_times),
        # beams cast and passes over the cloud per sensor update (core.cost): what the tests budget
        "update_cost": cost_summary(res.costs),
        # sensor updates per second of filter time (all on_scan + on_odometry calls): the scan
        # rate this filter could keep up with live on this CPU
        "effective_update_rate_hz": (res.counts["sensor_updates"] / res.filter_time) if res.filter_time > 0 else None,
        "scan_map_agreement": M.agreement_stats(res.agreement),
        "agreement_tolerance_m": M.AGREEMENT_TOLERANCE_M,
        **_jumps(res),
        "has_truth": res.has_truth,
        "truth_source": res.truth_source,
        "laser_source": res.laser_source,
        "laser_offset": [float(v) for v in (res.laser_offset or (p.laser_offset_x, p.laser_offset_y,
                                                                  p.laser_offset_yaw))],
        "health": M.agreement_stats(res.health),  # the filter's own health figure (fast average)
        "sensor_model": p.sensor_model,
        "adaptive_particles": p.adaptive_particles,
        # particle count over the sensor updates (changes with adaptive_particles and global spreads)
        "particles": ({"min": int(res.particles.min()), "median": float(np.median(res.particles)),
                       "mean": float(res.particles.mean()), "max": int(res.particles.max())}
                      if res.particles.size else None),
    }
    if res.has_truth:
        cmp = M.compare_to_truth(res.est_t, res.est_poses, res.truth_t, res.truth_poses)
        out["ct_error_m"] = M.error_stats(cmp.ct_error)
        out["heading_error_mean_abs_rad"] = float(cmp.heading_error.mean()) if cmp.heading_error.size else None
        t_start = res.init_t if res.init_t is not None else (float(res.est_t[0]) if len(res.est_t) else None)
        out["time_to_converge_s"] = M.time_to_converge(cmp.t, cmp.ct_error, M.CONVERGENCE_THRESHOLD_M, t_start)
        if res.initial_pose is not None and len(res.truth_t):
            truth0 = M.interpolate_poses([res.init_t], res.truth_t, res.truth_poses)[0]
            if np.all(np.isfinite(truth0)):
                out["initial_pose_error_m"] = float(np.hypot(*(np.asarray(res.initial_pose)[:2] - truth0[:2])))
                out["initial_pose_heading_error_rad"] = float(abs(wrap_angle(res.initial_pose[2] - truth0[2])))
        out["converge_threshold_m"] = M.CONVERGENCE_THRESHOLD_M
        out["scored_estimates"] = int(cmp.t.size)
        # switches to a place > 1 m from the (map-frame) truth after the first second
        out["false_recoveries"] = M.false_recoveries(cmp.t, cmp.ct_error, t_start=t_start)
        if len(res.world_truth_t):  # a perturbed world: the error against the car's pose in the world as well
            world = M.compare_to_truth(res.est_t, res.est_poses, res.world_truth_t, res.world_truth_poses)
            out["world_ct_error_m"] = M.error_stats(world.ct_error)
        from localization.eval.reference import truth_decomposition  # along-/cross-track vs truth
        out.update(truth_decomposition(res.est_t, res.est_poses, res.truth_t, res.truth_poses))
    if res.reference is not None:
        from localization.eval.reference import reference_metrics
        # the reference is per scan, at the scan's time: compared with the estimate at that time
        out.update(reference_metrics(res.reference, res.scan_t, res.scan_poses,
                                     res.truth_t if res.has_truth else None, res.truth_poses))
        out.update(published_errors(res.reference, res.est_t, res.est_poses))  # the poses as published
        ref = res.reference
        scored = out["reference_scored"]
        out["reference_partition"] = M.yardstick_partition(ref.good, ref.usable, ref.accepted, scored)
        out["reference_unscored_reason"] = None if scored else unscored_reason(ref, res.reference_problem)
    elif res.reference_problem is not None:
        out["reference_unscored_reason"] = res.reference_problem
    return out


def published_errors(ref, est_t, est_poses) -> dict:
    """The published poses' error and along-track error against the yardstick: ``reference_metrics``' two
    figures for them, without its lag search and the yardstick's own summary (computed for the scan track)."""
    from localization.eval.reference import error_metrics, track_errors
    extra, position = error_metrics(track_errors(est_t, est_poses, *ref.good_track()))
    return {"published_reference_error_m": position, "published_along_track_error_m": extra["along_track_error_m"]}


def _jumps(res: ReplayResult) -> dict:
    """The largest jump between consecutive estimates once the filter tracks (``metrics.jump_figures``)."""
    from_pose = res.initial_pose is not None
    t_start = res.init_t if res.init_t is not None else (float(res.est_t[0]) if len(res.est_t) else 0.0)
    settled = M.settled_time(from_pose, t_start, res.agreement_t, res.agreement)
    return M.jump_figures(res.est_t, res.est_poses, settled, t_start, from_pose)


def unscored_reason(ref, problem: str | None = None) -> str:
    """Why the yardstick scored no scan: what it said (``problem``), else what its counts show."""
    if problem:
        return problem
    c, n = ref.counts, len(ref.t)
    if c.get("usable", 0) < 3:
        return (f"only {c.get('usable', 0)} of {n} scans matched the map ({c.get('start', 'no start')}): check "
                "the map, the start pose and the laser mount")
    if not np.any(ref.good):
        causes = {"outside the map's free space": c.get("outside_free_space", 0), "a poor fit": c.get("poor_fit", 0),
                  "odometry disagreeing": c.get("odometry_inconsistent", 0),
                  "a better fit elsewhere": c.get("better_fit_elsewhere", 0)}
        named = ", ".join(f"{k} {v}" for k, v in causes.items() if v) or "every pose uncertain beyond a map cell"
        return f"no scan's reference pose is confident ({c.get('accepted', 0)} of {n} matches kept; {named})"
    return f"the estimates cover none of the {int(np.sum(ref.good))} confident scans"


def _write_poses(path: Path, stamps, poses) -> Path:
    """One pose per row: t (s, scan clock), x, y (m), theta (rad)."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t", "x", "y", "theta"])
        for t, (x, y, th) in zip(stamps, poses):
            w.writerow([f"{t:.6f}", f"{x:.5f}", f"{y:.5f}", f"{th:.6f}"])
    return path


def write_outputs(res: ReplayResult, metrics: dict, out_dir: Path, plots: bool = True) -> dict:
    """poses.csv, corrections.csv, metrics.json, agreement.csv, errors.csv (with truth), trajectory.png, error.png."""
    out_dir = Path(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ReplayError(f"cannot create output folder {out_dir}: {exc}") from None
    files = {}
    files["poses"] = _write_poses(out_dir / "poses.csv", res.est_t, res.est_poses)
    files["corrections"] = _write_poses(out_dir / "corrections.csv", res.corrected_t, res.corrected_poses)
    with open(out_dir / "agreement.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t", "agreement"])
        for t, a in zip(res.agreement_t, res.agreement):
            w.writerow([f"{t:.6f}", f"{a:.4f}"])
    cmp = None
    if res.has_truth:
        cmp = M.compare_to_truth(res.est_t, res.est_poses, res.truth_t, res.truth_poses)
        with open(out_dir / "errors.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["t", "ct_error", "heading_error"])
            for t, e, h in zip(cmp.t, cmp.ct_error, cmp.heading_error):
                w.writerow([f"{t:.6f}", f"{e:.5f}", f"{h:.6f}"])
    (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
    files["metrics"] = out_dir / "metrics.json"
    if plots:
        from localization.eval.plots import plot_errors, plot_trajectory
        from localization.eval.reference import track_errors
        title = res.options.label or bag_label(res.bag_path)
        files["trajectory"] = plot_trajectory(out_dir / "trajectory.png", res.occupancy_map, res.est_poses,
                                              res.truth_poses if res.has_truth else None, res.initial_pose,
                                              title=title, reference_poses=None if res.reference is None
                                              else res.reference.good_track()[1])
        t0 = res.init_t if res.init_t is not None else (
            float(res.est_t[0]) if len(res.est_t) else (float(res.agreement_t[0]) if len(res.agreement_t) else 0.0))
        files["error"] = plot_errors(out_dir / "error.png", t0,
                                     cmp.t if cmp is not None else None, cmp.ct_error if cmp is not None else None,
                                     cmp.heading_error if cmp is not None else None,
                                     res.agreement_t, res.agreement, title=title,
                                     particles_t=res.particles_t, particles=res.particles,
                                     track=track_errors(res.est_t, res.est_poses, res.truth_t, res.truth_poses)
                                     if res.has_truth else None)
        if res.reference is not None:
            from localization.eval.reference import plot_reference
            files["reference"] = plot_reference(out_dir / "reference.png", res.reference, res.est_t, res.est_poses,
                                                 t0, title=title)
    return files


def _fmt(v, spec=".3f", unit=""):
    return "n/a" if v is None else f"{v:{spec}}{unit}"


def partition_text(parts: dict) -> str:
    """``280 = 250 scored + 12 matched but not confident + 18 unmatched``: the parts that are not empty."""
    named = [f"{parts[k]} {label}" for k, label in M.YARDSTICK_PARTS.items() if parts.get(k) or k == "scored"]
    return f"{sum(parts.values())} = " + " + ".join(named)


def jump_text(m: dict) -> str:
    """The largest jump between consecutive estimates and what it counts (``metrics.jump_figures``)."""
    counts = m.get("max_jump_counts")
    if m.get("max_jump_m") is None:
        return f"n/a: {counts}; {_fmt(m.get('max_jump_with_convergence_m'))} m over every estimate"
    text = f"{m['max_jump_m']:.3f} m between consecutive estimates"
    if m.get("max_jump_from_s"):
        text += (f" from {m['max_jump_from_s']:.1f} s on ({counts}); "
                 f"{_fmt(m.get('max_jump_with_convergence_m'))} m with the convergence")
    elif counts:
        text += f" ({counts})"
    return text


def summary_table(metrics: dict, out_dir: Path | None = None) -> str:
    m = metrics
    rows = [("bag", m["bag"]),
            ("initial pose", m["initial_pose_source"]),
            ("messages", f"{m['scans']} scans, {m['odometry']} odometry -> {m['estimates']} estimates "
                         f"({m['sensor_updates']} sensor updates)")]
    if m.get("has_truth"):
        ct = m["ct_error_m"]
        rows += [("CT error (m)", f"mean {_fmt(ct['mean'])}  median {_fmt(ct['median'])}  p95 {_fmt(ct['p95'])}  "
                                  f"max {_fmt(ct['max'])}  rms {_fmt(ct['rms'])}"),
                 ("heading error", "mean |err| " + _fmt(
                     None if m["heading_error_mean_abs_rad"] is None else math.degrees(m["heading_error_mean_abs_rad"]),
                     ".2f", " deg")),
                 ("converged", ("never" if m["time_to_converge_s"] is None else "at the first estimate"
                                if m["time_to_converge_s"] < 0.05 else f"after {m['time_to_converge_s']:.2f} s")
                  + f" (below {m['converge_threshold_m']} m for good, from the initial pose"
                  + (f" {m['initial_pose_error_m']:.2f} m / {m['initial_pose_heading_error_rad']:.2f} rad off)"
                     if "initial_pose_error_m" in m else ")"))]
    if m.get("reference_unscored_reason"):
        rows.append(("vs reference track", f"n/a: {m['reference_unscored_reason']}"))
    elif m.get("reference_error_m") is not None:
        r, al, cr = m["reference_error_m"], m["along_track_error_m"], m["cross_track_error_m"]
        rows += [("vs reference track", f"median {_fmt(r['median'])}  p95 {_fmt(r['p95'])}  max {_fmt(r['max'])} m"),
                 ("along / cross track", f"along mean {_fmt(al['mean'])} median {_fmt(al['median'])}; "
                                         f"cross mean {_fmt(cr['mean'])} median {_fmt(cr['median'])} m; "
                                         f"best lag {_fmt(m['best_lag_s'], '.3f', ' s')}")]
        if m.get("reference_vs_truth_m"):
            rows.append(("reference vs truth", f"median {_fmt(m['reference_vs_truth_m']['median'], '.4f')} m"))
    if m.get("reference_partition"):
        rows.append(("yardstick scans", partition_text(m["reference_partition"])))
    if m.get("truth_along_track_error_m") is not None:
        al, cr = m["truth_along_track_error_m"], m["truth_cross_track_error_m"]
        rows.append(("along / cross vs truth", f"along mean {_fmt(al['mean'])} median {_fmt(al['median'])}; "
                                               f"cross mean {_fmt(cr['mean'])} median {_fmt(cr['median'])} m"))
    ag = m["scan_map_agreement"]
    rows += [("scan-map agreement", f"median {_fmt(ag['median'])}  mean {_fmt(ag['mean'])}  p05 {_fmt(ag['p05'])}"),
             ("filter health", f"median {_fmt((m.get('health') or {}).get('median'))}  "
                               f"min {_fmt((m.get('health') or {}).get('min'))}; "
                               f"{m.get('recoveries', 0)} recoveries (switches and re-spreads), "
                               f"{m.get('refused_jumps', 0)} updates undone (a jump to a worse fit)"),
             ("max jump", jump_text(m)),
             ("sensor update", f"median {_fmt(m['sensor_update_ms']['median_ms'], '.1f')} ms, "
                               f"p95 {_fmt(m['sensor_update_ms']['p95_ms'], '.1f')} ms "
                               + ("(adaptive particles" if m.get("adaptive_particles")
                                  else f"({m['num_particles']} particles")
                               + f" x {m['num_beams_per_particle']} beams, "
                               + (f"{m['ray_caster']})" if m.get("sensor_model", "beam") == "beam"
                                  else f"{m['sensor_model']})")),
             ("particles", "n/a" if not m.get("particles") else
              f"min {m['particles']['min']}  median {m['particles']['median']:.0f}  max {m['particles']['max']}"
              + (" (adaptive, KLD)" if m.get("adaptive_particles") else "")),
             ("motion update", f"median {_fmt(m['motion_update_ms']['median_ms'], '.2f')} ms, "
                               f"p95 {_fmt(m['motion_update_ms']['p95_ms'], '.2f')} ms"),
             ("update rate", f"{_fmt(m['effective_update_rate_hz'], '.1f')} Hz effective; "
                             f"{_fmt(m['realtime_factor'], '.2f')}x real time "
                             f"({m['bag_duration_s']:.1f} s of bag in {m['wall_time_s']:.1f} s)")]
    if out_dir is not None:
        rows.append(("outputs", str(out_dir)))
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in rows)
