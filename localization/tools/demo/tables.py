"""The demo's tables: one function per table (rows from ``Result`` s), and ``report`` printing them in order
under one-line titles. What each column means: docs/replay.md, "What the demo prints"."""
from __future__ import annotations

import numpy as np

from localization.eval.datasets import REAL_BAGS, SIM_TRIALS
from localization.tools.demo.heldout import (
    CALIBRATION_COLUMNS,
    HELDOUT_KEYS,
    TUNING_GRID,
    Tuning,
    target_ratio,
    yardstick_errors,
)
from localization.tools.demo.jobs import FAST, HELDOUT, PIONEER, PIONEER_HELDOUT, REAL, SIM, SWEEP

#: Mean CT error (m) the reference lab report measured on its three simulated trials.
REFERENCE_CT = {"trial1_noise0": 0.224, "trial2_noise0.3": 0.183, "trial3_noise0.6": 0.261}


def _f(v, spec=".3f"):
    return "  n/a" if v is None else f"{v:{spec}}"


def _table(header: str, results: list, width: int, row) -> str:
    """The header, then ``row(label, metrics)`` per replay (or its error)."""
    lines = [header]
    for r in results:
        name = r.job.label
        lines.append(f"{name:<{width}} error: {r.error}" if r.error is not None else row(name, r.metrics))
    return "\n".join(lines)


def _world(job) -> str:
    w = job.world
    return "map" if w is None else f"perturbed s{w.scale:g}"


def sim_table(results: list) -> str:
    """The simulated trials, clean-map rows then perturbed-world rows: CT error against the truth in the map
    frame, mean error against the world-frame truth (the same as the map frame's in the clean world),
    recoveries and false recoveries."""
    def row(name, m):
        ct, conv, head = m["ct_error_m"], m["time_to_converge_s"], m["heading_error_mean_abs_rad"]
        job = by_label[name]
        trial = job.trial or name
        world = (m.get("world_ct_error_m") or ct)["mean"]
        return (f"{name:<{width}} {_world(job):<15} {SIM_TRIALS[trial].odom_noise:>5.1f} "
                f"{_f(ct['mean']):>8} {_f(ct['median']):>7} {_f(ct['p95']):>6} {_f(ct['max']):>6} "
                f"{_f(None if head is None else head * 57.29578, '.2f'):>7}° "
                f"{'never' if conv is None else f'{conv:.3f} s':>9} {_f(world):>8} "
                f"{m.get('recoveries', 0):>5} {_f(m.get('false_recoveries'), 'd'):>5} "
                f"{_f(m['scan_map_agreement']['median']):>6} {_f(REFERENCE_CT.get(trial)):>7}")
    by_label = {r.job.label: r.job for r in results}
    width = max([22, *(len(k) for k in by_label)])
    ordered = [r for r in results if r.job.world is None] + [r for r in results if r.job.world is not None]
    return _table(f"{'trial':<{width}} {'world':<15} {'noise':>5} {'mean CT':>8} {'median':>7} {'p95':>6} {'max':>6} "
                  f"{'heading':>8} {'converge':>9} {'vs world':>8} {'recov':>5} {'false':>5} {'agree':>6} "
                  f"{'report':>7}", ordered, width, row)


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


def sweep_table(results: list) -> str:
    """Median scan-map agreement of each RSS bag (and their mean) per motion-noise factor."""
    lines = [f"{'scale':>6} " + " ".join(f"{b:>6}" for b in REAL_BAGS) + f" {'mean':>6}"]
    for s in sorted({r.job.scale for r in results}):
        vals = [r.metrics["scan_map_agreement"]["median"] if r.metrics is not None else None
                for r in results if r.job.scale == s]
        ok = [v for v in vals if v is not None]
        lines.append(f"{s:>6.2f} " + " ".join(f"{_f(v):>6}" for v in vals)
                     + f" {_f(sum(ok) / len(ok) if ok else None):>6}")
    return "\n".join(lines)


def yardstick_table(results: list) -> str:
    """Error against the yardstick: median, p95, mean along-track (m), and the agreement."""
    def row(name, m):
        ref = m.get("reference_error_m") or {}
        along = (m.get("along_track_error_m") or {}).get("mean")
        return (f"{name:<6} {_f(ref.get('median')):>7} {_f(ref.get('p95')):>6} "
                f"{'n/a' if along is None else f'{along:+.3f}':>11} {_f(ref.get('max')):>6} "
                f"{_f(m['scan_map_agreement']['median']):>9} {m.get('reference_scored', 0):>7} "
                f"{m.get('recoveries', 0):>6} {m.get('reference_false_recoveries', 0):>6}")
    return _table(f"{'bag':<6} {'median':>7} {'p95':>6} {'mean along':>11} {'max':>6} {'agreement':>9} "
                  f"{'scored':>7} {'recov':>6} {'false':>6}", results, 6, row)


def calibration_table(values: dict, folds: dict, keys: dict | None = None) -> str:
    """Two rows per bag: its own calibration, and its held-out fold (the mean over the other bags)."""
    keys = HELDOUT_KEYS if keys is None else keys
    params = list(keys.values())
    lines = [f"{'bag':<9} {'':<9} " + " ".join(f"{CALIBRATION_COLUMNS[p][0]:>12}" for p in params)]
    for name, fold in folds.items():
        v = values.get(name)
        own = (" ".join(f"{CALIBRATION_COLUMNS[p][1].format(float(v[k])):>12}" for k, p in keys.items()) if v
               else "(not calibrated)")
        held = " ".join(f"{CALIBRATION_COLUMNS[p][1].format(float(fold[p])):>12}" for p in params)
        lines.append(f"{name:<9} {'alone':<9} {own}")
        lines.append(f"{'':<9} {'held-out':<9} {held}   (from {', '.join(fold['calibrated_on'])})")
    return "\n".join(lines)


def pioneer_table(results: list) -> str:
    def row(name, m):
        pm = m.get("pioneer") or {}
        conv = pm.get("time_to_converge_s")
        start = "global" if m["initial_pose_source"].startswith("global") else "start pose"
        return (f"{name:<9} {start:<13} {'never' if conv is None else f'{conv:.1f} s':>9} "
                f"{pm.get('converge_by', ''):<16} {pm.get('max_jump_m', 0.0):>7.2f}m "
                f"{_f(pm.get('max_jump_after_converge_m')):>10} {pm.get('recoveries', 0):>5} "
                f"{'n/a' if pm.get('false_recoveries') is None else pm['false_recoveries']:>5} "
                f"{pm.get('refused_jumps', 0):>6} "
                f"{_f(pm.get('confident_agreement_median')):>9} {_f(pm.get('error_vs_yardstick_median_m')):>7} "
                f"{_f(pm.get('off_share')):>6} "
                f"{_f(pm.get('holding_share')):>8} {_f(pm.get('health_lost_share')):>8} "
                f"{_f(pm.get('end_agreement_median')):>7}")
    return _table(f"{'bag':<9} {'start':<13} {'converge':>9} {'(by)':<16} {'max jump':>8} {'after conv':>10} "
                  f"{'recov':>5} {'false':>5} {'undone':>6} "
                  f"{'agreement':>9} {'ref med':>7} {'off':>6} {'disagree':>8} {'health<':>8} {'end agr':>7}",
                  results, 9, row)


def tuning_table(tuning: Tuning) -> str:
    """Per bag: its fold's chosen point, the training ratio there and at the file's point, and the held-out
    replay's error vs the yardstick."""
    lines = [f"{'bag':<6} {'chosen motion x':>15} {'sigma_hit':>9} {'train ratio':>11} {'file point':>10} "
             f"{'median':>7} {'p95':>6} {'along':>7} {'ratio':>6}"]
    for r in tuning.final:
        k = r.job.label
        point, train = tuning.chosen[k]
        own = tuning.scores.get((k, tuning.file_point))
        own = float(np.mean(own)) if own else None
        m = r.metrics or {}
        median, p95, along = yardstick_errors(m)
        lines.append(f"{k:<6} {point[0]:>15.2f} {point[1]:>9.4f} {train:>11.3f} {_f(own):>10} {_f(median):>7} "
                     f"{_f(p95):>6} {_f(along, '+.3f'):>7} {_f(target_ratio(m) if m else None, '.2f'):>6}")
    return "\n".join(lines)


def by_table(results: list) -> dict:
    """table -> its results, in job order."""
    out: dict = {}
    for r in results:
        out.setdefault(r.job.table, []).append(r)
    return out


def report(results: list, calibration: dict, folds: dict, keys: dict, title: str, tuning: Tuning | None) -> str:
    """Every table of ``results`` in order, each section under a one-line title after a blank line (``title``:
    the run, e.g. "2000 particles, seed 0"); ``calibration``: bag -> its calibrated values; ``folds``: bag ->
    its held-out fold; ``keys``: table -> the calibrated keys of its folds; ``tuning``: the held-out tuning's
    outcome (None: not run)."""
    t = by_table(results)
    rss_folds = {b: f for b, f in folds.items() if b in REAL_BAGS}
    pioneer_folds = {b: f for b, f in folds.items() if b not in REAL_BAGS}
    sections = []
    if t.get(SIM):
        sections.append(f"Simulated Stata basement trials (config/params.yaml, {title}): CT error (m) vs the map-frame "
                        f"truth; targets: mean <= 0.03, no false recovery\n{sim_table(t[SIM])}")
    if t.get(FAST):
        sections.append(f"Fast trial (6-7 m/s, odometry 40 ms late, sweep timing; {title}): error (m) vs the truth; "
                        f"targets: mean <= 0.03, |mean along| <= 0.01 aligned\n{fast_table(t[FAST])}")
    if t.get(REAL):
        sections.append(f"Real RSS 2022 bags (config/real_params.yaml, {title}): error (m) vs the yardstick; "
                        f"targets: median <= 0.035, p95 <= 0.08, |along| <= 0.02\n{real_table(t[REAL])}")
    if t.get(SWEEP):
        sections.append("Real bags: median scan-map agreement vs motion noise (real_params.yaml's motion_* scaled "
                        f"by)\n{sweep_table(t[SWEEP])}")
    if t.get(HELDOUT):
        sections.append("Calibration of each RSS 2022 bag and its held-out fold (the mean over the other two):\n"
                        + calibration_table(calibration, rss_folds, keys[HELDOUT]))
        sections.append(f"RSS 2022 bags vs the yardstick, error (m); {title}\nall-bags parameters "
                        "(config/real_params.yaml, calibrated on all three bags, this one included):\n"
                        f"{yardstick_table(t.get(REAL, []))}\nHELD-OUT (calibrated on the other two bags only):\n"
                        f"{yardstick_table(t[HELDOUT])}")
    if tuning is not None:
        sections.append(f"HELD-OUT CALIBRATION AND TUNING (motion noise x and sigma_hit chosen per fold from "
                        f"{TUNING_GRID} on its two training bags):\n{tuning_table(tuning)}")
    if t.get(PIONEER) or t.get(PIONEER_HELDOUT):
        pioneer = [f"Pioneer 3-DX bags (lgfloor, {title})"]
        if t.get(PIONEER):
            pioneer.append("config/pioneer_params.yaml (its odometry calibrated on trace0: training figures for "
                           f"trace0):\n{pioneer_table(t[PIONEER])}")
        if t.get(PIONEER_HELDOUT):
            pioneer.append("HELD-OUT (calibrated on the other two Pioneer bags only):\n"
                           + pioneer_table(t[PIONEER_HELDOUT]))
        sections.append("\n".join(pioneer))
        if t.get(PIONEER_HELDOUT):
            sections.append("Calibration of each Pioneer bag and its held-out fold (the mean over the other two):\n"
                            + calibration_table(calibration, pioneer_folds, keys[PIONEER_HELDOUT]))
    return "".join(f"\n{s}\n" for s in sections)
