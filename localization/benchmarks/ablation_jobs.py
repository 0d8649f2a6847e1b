"""The ablation's jobs (``python -m localization.benchmarks.ablation``): the mechanisms and their switches,
which parts a switch cannot change, the job table, and running one job in a worker process: an RSS bag held
out, the Pioneer bags (``localization-demo --only pioneer``), a perturbed-world trial, a global start or a
kidnapping of the robustness benchmark. Each job returns its figures, one flat dict per bag or run (the keys
``ablation_table``'s columns read)."""
from __future__ import annotations

import contextlib
import json
import logging
import pickle
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from localization.core.parameters import Parameters
from localization.core.paths import atomic_write, cache_dir, config_dir


@dataclass(frozen=True)
class Mechanism:
    title: str
    overrides: tuple  # (parameter, value) pairs that switch it off
    note: str = ""


MECHANISMS = {
    "tempered": Mechanism("tempered first update", (("initial_update_stages", 1),)),
    "glide": Mechanism("jump glide", (("recovery_switch_step", 0.0),),
                       "a switch or a kept jump is published at once"),
    "challenger": Mechanism("challenger", (("recovery_confirm_updates", 10 ** 9),),
                            "no switch of its own: a challenger never wins (it is still started and updated while "
                            "holding, so its cost stays)"),
    "jump_refusal": Mechanism("jump refusal", (("recovery_jump_glide", 0.0),),
                              "no tracking update is judged a jump (none undone, none glided)"),
    "range_scale": Mechanism("online range scale", (("range_scale_estimation", False),)),
    "beamskip": Mechanism("beam skipping", (("do_beamskip", False),)),
    "grip": Mechanism("grip limit", (("odom_max_acceleration", 0.0),)),
    "deskew": Mechanism("deskew", (("deskew", False),)),
}
#: mechanisms with nothing to switch off here
NOT_ABLATED = {"adaptive particles (KLD)": "adaptive_particles is false by default and in every robot file"}

PARAMS_FILE = {"rss": "real_params.yaml", "pioneer": "pioneer_params.yaml", "perturbed": "params.yaml",
               "global": "params.yaml", "kidnap": "params.yaml"}
SIM_GROUPS = ("perturbed", "global", "kidnap")
COST_GUESS = {"pioneer": 400.0, "global": 60.0, "kidnap": 60.0, "perturbed": 45.0, "rss": 25.0}  # s: order only
GLOBAL_DRIVE_S = 20.0  # s of driving after a global start (robustness.bench_global)
KIDNAP_AT_S, KIDNAP_AFTER_S = 8.0, 17.0  # s (robustness.bench_kidnap)


def inert(group: str, mechanism: str) -> str | None:
    """Why switching ``mechanism`` off changes nothing for ``group`` (None: it may)."""
    if mechanism == "baseline":
        return None
    base = Parameters.from_yaml(config_dir() / PARAMS_FILE[group])
    if all(base[k] == v for k, v in MECHANISMS[mechanism].overrides):
        return f"already off in {PARAMS_FILE[group]}"
    if mechanism == "deskew" and group in SIM_GROUPS:
        return "the simulated scans have no sweep timing"
    if mechanism == "tempered" and group == "global":
        return "a global start has no initial pose to temper"
    return None


# --------------------------------------------------------------------------------------------
# Jobs
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Job:
    group: str
    label: str  # bag, trial run or start index
    mechanism: str  # "baseline" or a key of MECHANISMS
    seed: int
    overrides: tuple = ()  # on top of the group's parameter file: the fold, the switch, the seed
    runs: int = 10  # global / kidnap: how many starts the route is split into

    @property
    def switch(self) -> dict:
        return {} if self.mechanism == "baseline" else dict(MECHANISMS[self.mechanism].overrides)


def perturbed_runs() -> dict:
    """label -> (trial, SimConfig changes): the demo's perturbed-world replays without its ``_fixed`` rows."""
    from localization.eval.datasets import REPORT_TRIALS
    from localization.sim.perturb import STANDARD_PERTURBATION as P
    runs = {f"{name}_perturbed": (name, (("world", P),)) for name in REPORT_TRIALS}
    for name in REPORT_TRIALS:
        if name != "trial2_noise0.3":
            runs[f"{name.split('_')[0]}_2mps_scale{P.scale:g}"] = (name, (("speed", 2.0), ("world", P)))
    for scale in (1.01, 1.02):
        runs[f"trial2_2mps_scale{scale:g}"] = ("trial2_noise0.3", (("speed", 2.0), ("world", replace(P, scale=scale))))
    return runs


def labels(group: str, runs: int) -> list:
    """The jobs of a part: its bags, trial runs or start indices (the Pioneer part: one demo run)."""
    from localization.eval.datasets import REAL_BAGS
    if group in ("global", "kidnap"):
        return [str(r) for r in range(runs)]
    return {"rss": list(REAL_BAGS), "pioneer": ["heldout"], "perturbed": list(perturbed_runs())}[group]


def spread_starts(runs: int, starts: int | None) -> list:
    """``starts`` of the ``runs`` global starts or kidnappings, spread evenly along the loop (None: all)."""
    n = runs if starts is None else max(1, min(starts, runs))
    return [str(k * runs // n) for k in range(n)]


def plan(groups: list, mechanisms: list, seeds: list, folds: dict, runs: int, pick: dict | None = None) -> tuple:
    """(jobs to run, (group, mechanism) -> why it is not run); ``pick``: group -> the labels to run (else all).
    Within a part the rows alternate (seed, then bag or run, then row), so that a change of the machine's load
    during the run falls on every row alike (the cost columns are wall-clock times)."""
    pick = pick or {}
    jobs, skipped = [], {}
    for group in groups:
        rows = []
        for mechanism in ["baseline", *mechanisms]:
            why = inert(group, mechanism)
            if why is None:
                rows.append(mechanism)
            else:
                skipped[(group, mechanism)] = why
        for seed in seeds:
            for label in pick.get(group) or labels(group, runs):
                for mechanism in rows:
                    switch = {} if mechanism == "baseline" else dict(MECHANISMS[mechanism].overrides)
                    over = {**folds.get(label, {}), **switch, "random_seed": seed}
                    jobs.append(Job(group, label, mechanism, seed, tuple(over.items()), runs))
    return jobs, skipped


# --------------------------------------------------------------------------------------------
# Running one job (in a worker process)
# --------------------------------------------------------------------------------------------


def run_job(job: Job) -> tuple:
    """(job, figures: one dict per bag or run, error or None, seconds)."""
    t0 = time.perf_counter()
    logging.getLogger("localization").setLevel(logging.ERROR)  # the replays' own warnings: not in the table
    try:
        figures = RUNNERS[job.group](job)
        return job, tuple(figures), None, time.perf_counter() - t0
    except Exception as exc:  # one failed job is one "n/a" cell and a line in the log, not a lost run
        return job, (), f"{type(exc).__name__}: {exc}", time.perf_counter() - t0


def _replay_figures(metrics: dict) -> dict:
    return {"jump": metrics.get("max_jump_m"), "ms": (metrics.get("sensor_update_ms") or {}).get("median_ms"),
            "recoveries": metrics.get("recoveries"), "refused": metrics.get("refused_jumps")}


def run_rss(job: Job) -> list:
    from localization.eval.datasets import REAL_BAGS, real_bag_path
    from localization.eval.replay import ReplayOptions, compute_metrics, run_replay
    rb = REAL_BAGS[job.label]
    params = Parameters.from_yaml(config_dir() / rb.params, **dict(job.overrides))
    res = run_replay(ReplayOptions(real_bag_path(job.label), rb.map, params, rb.start, force_global=rb.start is None,
                                   label=job.label, scan_topic=rb.scan_topic, odom_topic=rb.odom_topic,
                                   log=lambda line: None))
    m = compute_metrics(res)
    ref = m.get("reference_error_m") or {}
    return [{"label": job.label, "median": ref.get("median"), "p95": ref.get("p95"),
             "along": (m.get("along_track_error_m") or {}).get("mean"), "false": m.get("reference_false_recoveries"),
             **_replay_figures(m)}]


def demo_command() -> list:
    """``localization-demo`` beside this interpreter (the venv's), else on PATH."""
    here = Path(sys.executable).parent / "localization-demo"
    return [str(here) if here.exists() else (shutil.which("localization-demo") or "localization-demo")]


def run_demo(only: str, overrides: dict, seed: int, jobs: int, out: Path) -> dict:
    """``localization-demo --only ONLY`` with ``-p`` overrides; its summary.json (RuntimeError: none)."""
    cmd = [*demo_command(), "--only", only, "--seed", str(seed), "--jobs", str(jobs), "--out", str(out),
           "--overwrite", *(a for k, v in overrides.items() for a in ("-p", f"{k}={json.dumps(v)}"))]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    try:
        return json.loads((out / "summary.json").read_text())
    except (OSError, ValueError):
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-1:] or [f"exit status {proc.returncode}"]
        raise RuntimeError(f"localization-demo --only {only} wrote no summary: {tail[0]}") from None


def run_pioneer(job: Job) -> list:
    from localization.eval.datasets import PIONEER_BAGS
    over = {k: v for k, v in job.overrides if k != "random_seed"}
    with tempfile.TemporaryDirectory(prefix="ablation-pioneer-") as tmp:
        summary = run_demo("pioneer", over, job.seed, 1, Path(tmp) / "out")
    out = []
    for bag in PIONEER_BAGS:
        m = summary.get(f"{bag}@heldout") or {}
        if "error" in m or not m:
            raise RuntimeError(f"{bag}@heldout: {m.get('error', 'missing from the demo summary')}")
        p = m.get("pioneer") or {}
        out.append({"label": bag, "agree": p.get("confident_agreement_median"),
                    "err": p.get("error_vs_yardstick_median_m"), "end": p.get("end_agreement_median"),
                    "false": p.get("false_recoveries"), **_replay_figures(m),
                    "jump": p.get("max_jump_after_converge_m"), "converge_s": p.get("time_to_converge_s")})
    return out


def run_perturbed(job: Job) -> list:
    from localization.eval.datasets import SIM_TRIALS, sim_bag
    from localization.eval.replay import ReplayOptions, compute_metrics, run_replay
    trial, changes = perturbed_runs()[job.label]
    params = Parameters.from_yaml(config_dir() / PARAMS_FILE["perturbed"], **dict(job.overrides))
    res = run_replay(ReplayOptions(sim_bag(trial, **dict(changes)), SIM_TRIALS[trial].config.map, params,
                                   label=job.label, log=lambda line: None))
    m = compute_metrics(res)
    ct = m.get("ct_error_m") or {}
    return [{"label": job.label, "mean": ct.get("mean"), "p95": ct.get("p95"), "false": m.get("false_recoveries"),
             **_replay_figures(m)}]


def loop_recording(kind: str, r: int, runs: int):
    """The robustness benchmark's recording of global start or kidnapping ``r`` of ``runs`` (its config,
    route, start and teleport), simulated once and kept in the cache."""
    from localization.benchmarks.robustness import loop_config, loop_path, loop_pose
    from localization.core.occupancy_map import load_map
    from localization.eval.datasets import cache_key
    from localization.sim import simulate
    path = loop_path()
    if kind == "global":
        cfg = loop_config(int(r * len(path) / runs) + 37, GLOBAL_DRIVE_S + 2.0, seed=100 + r)
    else:  # teleported to a loop point 40-90 m further on, >= 12 m away in a straight line (bench_kidnap)
        start, rng = int(r * len(path) / runs) + 11, np.random.default_rng(200 + r)
        for _ in range(100):
            target = loop_pose(start + int(rng.uniform(800, 1800)))
            if np.hypot(*(np.array(target[:2]) - path[(start + int(KIDNAP_AT_S * 2.0 / 0.05)) % len(path)])) >= 12:
                break
        cfg = loop_config(start, KIDNAP_AT_S + KIDNAP_AFTER_S, seed=200 + r, kidnap_at=KIDNAP_AT_S, kidnap_to=target)
    occ = load_map(cfg.map)
    entry = cache_dir() / "ablation" / "recordings" / f"{kind}{r}of{runs}-{cache_key(cfg)}.pkl"
    with contextlib.suppress(OSError, EOFError, pickle.UnpicklingError, AttributeError):
        return pickle.loads(entry.read_bytes()), occ
    rec = simulate(cfg, occ)
    with contextlib.suppress(OSError), atomic_write(entry) as f:
        f.write(pickle.dumps(rec))
    return rec, occ


class SwitchWatch:
    """``on_scan`` hook: where the cloud is each time the localizer switches it (``Localizer.recoveries`` goes up
    with the cloud in one place; a re-spread over the map is not a switch), as the distance (m) from the truth
    at that scan's time. A switch more than 1 m from the truth is a false recovery."""

    def __init__(self, truth_t, truth_poses, one_place_std: float):
        self.truth_t, self.truth_poses, self.one_place_std = truth_t, truth_poses, one_place_std
        self.seen = 0
        self.distances: list = []

    def __call__(self, scan, localizer) -> None:
        from localization.eval import metrics as M
        if localizer.recoveries <= self.seen:
            return
        self.seen = localizer.recoveries
        xy = localizer.particles()[:, :2]
        if np.max(np.std(xy, axis=0)) >= self.one_place_std:
            return
        truth = M.interpolate_poses([localizer.scan_time(scan)], self.truth_t, self.truth_poses)[0]
        self.distances.append(float(np.hypot(*(xy.mean(axis=0) - truth[:2]))))

    @property
    def false(self) -> int:
        from localization.eval.metrics import FALSE_RECOVERY_M
        return sum(d > FALSE_RECOVERY_M for d in self.distances)


def _loop_run(job: Job, seed_base: int):
    """A global start or kidnapping fed to the Localizer as ``robustness.run_recording`` feeds it, its switches
    watched: (recording, comparison with the truth, ``SwitchWatch``, recoveries, published estimates (t, poses))."""
    from localization.core.localizer import Localizer
    from localization.eval import metrics as M
    from localization.eval.feed import Feeder, recording_events
    rec, occ = loop_recording(job.group, int(job.label), job.runs)
    over = {**dict(job.overrides), "random_seed": seed_base + int(job.label) + 1000 * job.seed}
    params = Parameters.from_yaml(config_dir() / PARAMS_FILE[job.group], **over)
    loc = Localizer(params, logging.getLogger("localization.ablation"))
    loc.set_map(occ)
    t_start = float(rec.odometry.t[0])
    if job.group == "global":
        loc.initialize_global(t_start)
    else:
        loc.set_initial_pose(rec.initial_pose, None, t_start)
    watch = SwitchWatch(rec.truth_t, rec.truth_poses, params.global_converged_std)
    est_t, est_poses = Feeder(loc).run(recording_events(rec), on_scan=watch).estimates()
    cmp = M.compare_to_truth(est_t, est_poses, rec.truth_t, rec.truth_poses)
    return rec, cmp, watch, loc.recoveries, (est_t, est_poses)


def run_global(job: Job) -> list:
    from localization.benchmarks.robustness import settle_time
    rec, cmp, watch, recoveries, _ = _loop_run(job, 100)
    return [{"label": job.label, "converged_s": settle_time(cmp, float(rec.odometry.t[0])), "false": watch.false,
             "recoveries": recoveries}]


def run_kidnap(job: Job) -> list:
    from localization.benchmarks.robustness import settle_time
    from localization.eval import metrics as M
    rec, cmp, watch, recoveries, (est_t, est_poses) = _loop_run(job, 200)
    return [{"label": job.label, "back_s": settle_time(cmp, KIDNAP_AT_S), "false": watch.false,
             "recoveries": recoveries, "switch_m": watch.distances,
             "jump_after": M.max_jump(est_poses[est_t >= KIDNAP_AT_S])}]


RUNNERS = {"rss": run_rss, "pioneer": run_pioneer, "perturbed": run_perturbed, "global": run_global,
           "kidnap": run_kidnap}


def record(item: tuple) -> str:
    """A recording the jobs share, made once before them (in a worker): a perturbed trial's bag or a loop run."""
    kind, *rest = item
    if kind == "perturbed":
        from localization.eval.datasets import sim_bag
        trial, changes = perturbed_runs()[rest[0]]
        sim_bag(trial, **dict(changes))
    else:
        loop_recording(kind, int(rest[0]), rest[1])
    return ":".join(str(v) for v in item)
