"""Running the demo's work in worker processes: one replay (``run_job``), one simulated recording
(``record_job``) or one calibration (``calibrate_job``, kept on disk by the bag's content, its arguments
and the code), each line it logs prefixed with its bag or trial; ``demo_tasks`` wires them into one task
graph for ``schedule.run_tasks``."""
from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import sys
import time
from pathlib import Path

from localization.core.parameters import Parameters
from localization.core.paths import atomic_write, cache_dir, config_dir
from localization.eval.datasets import PIONEER_BAGS, REAL_BAGS, SIM_TRIALS, real_bag, real_bag_path, sim_bag
from localization.tools.demo import schedule
from localization.tools.demo.jobs import HELDOUT, PIONEER_HELDOUT, Job, Result
from localization.tools.demo.pioneer import StatusCounter, pioneer_metrics

PROG = "localization-demo"
PACKAGE = Path(__file__).resolve().parents[2]
#: the code a calibration's values depend on (a change anywhere here computes them again)
CALIBRATION_CODE = ("core", "eval/calibration", "eval/reference", "eval/datasets.py", "bags")


def say(label: str, line: str) -> None:
    """One line on stderr naming the job it is about."""
    print(f"{PROG}: {label}: {line}", file=sys.stderr, flush=True)


@contextlib.contextmanager
def labelled_log(label: str):
    """The localizer's own log lines (lost, recovery, ...: the ``localization`` logger, WARNING and above as
    before) prefixed with the job's label while it runs."""
    logger = logging.getLogger("localization")
    handler = logging.StreamHandler(sys.stderr)
    handler.setLevel(logging.WARNING)
    handler.setFormatter(logging.Formatter(f"{PROG}: {label}: %(message)s"))
    logger.addHandler(handler)
    try:
        yield
    finally:
        logger.removeHandler(handler)


# --------------------------------------------------------------------------------------------
# Replays and recordings
# --------------------------------------------------------------------------------------------


def record_job(recording: tuple) -> str:
    """A simulated trial's bag, (trial, SimConfig changes): from the cache, recorded first when missing."""
    trial, changes = recording
    return str(sim_bag(trial, log=lambda line: say(trial, line), **dict(changes)))


def recording_key(job: Job) -> str:
    """The task key of a simulated job's recording: one per trial and SimConfig changes."""
    words = [f"{k}{v.label() if hasattr(v, 'label') else v}" for k, v in sorted(job.recording)]
    return "record:" + "-".join([job.trial, *words])


def run_job(job: Job) -> Result:
    """One replay (in a worker process): its metrics (Pioneer bags: with ``pioneer_metrics``), its outputs
    written when the job has a folder; a replay that cannot run is its error line."""
    from localization.eval.replay import ReplayError, ReplayOptions, compute_metrics, run_replay, write_outputs
    t0 = time.perf_counter()
    notes: list = []  # the same laser mount for every replay of a robot: printed once each (``distinct_notes``)
    with labelled_log(job.summary_key):  # bag2@heldout, not only bag2
        try:
            holding = StatusCounter()
            bag = Path(job.bag) if job.bag is not None else Path(record_job((job.trial, job.recording)))
            opts = ReplayOptions(bag, job.map, job.load_parameters(), job.initial_pose,
                                 force_global=job.force_global, label=job.label, scan_topic=job.scan_topic,
                                 odom_topic=job.odom_topic, on_scan=holding if job.pioneer else None, log=notes.append)
            res = run_replay(opts)
            metrics = compute_metrics(res)
            if job.pioneer:
                metrics["pioneer"] = pioneer_metrics(res, holding)
            if job.out:
                write_outputs(res, metrics, Path(job.out), plots=job.plots)
        except ReplayError as exc:
            return Result(job, error=str(exc), notes=tuple(notes))
    return Result(job, metrics, seconds=time.perf_counter() - t0, notes=tuple(notes))


def compile_kernels(plan: list) -> None:
    """The compiled kernels every job's parameters use, put into numba's cache once before the workers
    start (``core.compile_cache.ensure_compiled``: at once when they are there; workers starting cold
    side by side would each compile them)."""
    from localization.core.compile_cache import ensure_compiled, kernels_for
    seen: set = set()
    for job in plan:
        params = job.load_parameters()
        kernels = tuple(kernels_for(params))
        if kernels not in seen:
            seen.add(kernels)
            ensure_compiled(params)


def distinct_notes(results: list) -> list:
    """Each line the replays said about their inputs once, with the replays that said it (the laser mount
    of a robot's bags is the same line for each of its replays)."""
    said: dict = {}
    for r in results:
        for note in r.notes:
            said.setdefault(note, []).append(r.job.label)
    return [f"{PROG}: {note} ({labels[0]}" + (f" and {len(labels) - 1} more replays)" if len(labels) > 1 else ")")
            for note, labels in said.items()]


def run_all(jobs: list, workers: int) -> list:
    """Every job's ``Result``, in the jobs' order (``workers`` processes, the longest first)."""
    costs = schedule.load_costs()
    tasks = [schedule.Task(f"replay:{k}:{j.summary_key}", run_job, j, cost=costs.get(f"replay:{j.summary_key}", 1.0))
             for k, j in enumerate(jobs)]
    done = schedule.run_tasks(tasks, workers)
    return [done[t.key] for t in tasks]


# --------------------------------------------------------------------------------------------
# Calibrations
# --------------------------------------------------------------------------------------------


def _calibration_arguments(name: str) -> dict:
    rb = real_bag(name)
    params = Parameters.from_yaml(config_dir() / rb.params)
    return {"scan_topic": rb.scan_topic, "odom_topic": rb.odom_topic, "initial_pose": rb.start,
            "mount0": (params.laser_offset_x, params.laser_offset_y, params.laser_offset_yaw),
            "scan_stamp": rb.scan_stamp, "scan_stamp_offset": params.scan_stamp_offset,
            "odom_frame": rb.odom_frame, "base_frame": rb.base_frame}


def calibration_key(name: str, occupancy_map, arguments: dict) -> str:
    """Digest of what a bag's calibration depends on: the bag's bytes, the map's cells, the arguments and
    the source of ``CALIBRATION_CODE``."""
    h = hashlib.sha1()
    h.update(real_bag_path(name).read_bytes())
    h.update(occupancy_map.digest.encode())
    h.update(json.dumps(arguments, sort_keys=True, default=str).encode())
    for entry in CALIBRATION_CODE:
        path = PACKAGE / entry
        for src in sorted(path.rglob("*.py")) if path.is_dir() else [path]:
            h.update(str(src.relative_to(PACKAGE)).encode())
            h.update(src.read_bytes())
    return h.hexdigest()[:20]


def calibrate_job(name: str) -> dict:
    """``localization-calibrate`` on a real bag (RSS 2022 or Pioneer; in a worker process): the mount
    guess, stamp convention, odometry source and start pose as for its replay; returns {name, values}
    (the values kept in the cache: the same bag, arguments and code reuse them) or {name, error}."""
    from localization.bags import BagError
    from localization.core.occupancy_map import load_map
    from localization.eval.calibration import CalibrationError, calibrate_bag
    rb = real_bag(name)
    occupancy_map, arguments = load_map(rb.map), _calibration_arguments(name)
    path = cache_dir() / "demo" / "calibration" / f"{name}-{calibration_key(name, occupancy_map, arguments)}.json"
    with contextlib.suppress(OSError, ValueError):
        return {"name": name, "values": json.loads(path.read_text())}
    with labelled_log(name):
        try:
            res = calibrate_bag(real_bag_path(name), occupancy_map, **arguments)
        except (CalibrationError, BagError) as exc:
            return {"name": name, "error": str(exc)}
    values = {k: float(v) for k, v in res.values.items()}
    with contextlib.suppress(OSError), atomic_write(path) as f:
        f.write(json.dumps(values).encode())  # floats as repr: read back exactly
    return {"name": name, "values": values}


class CalibrationFailed(RuntimeError):
    """A bag's calibration failed: no held-out fold can use it."""


# --------------------------------------------------------------------------------------------
# The task graph
# --------------------------------------------------------------------------------------------


def guess_cost(key: str) -> float:
    """Seconds a task takes when no run has measured it: about its bag's length (only the order uses it)."""
    kind, _, name = key.partition(":")
    name = name.split("@")[0]
    bag = REAL_BAGS.get(name) or PIONEER_BAGS.get(name)
    if bag is not None:
        return bag.duration * (3.0 if kind == "calibrate" else 1.0)
    trial = SIM_TRIALS.get(name.split("-")[0])
    return 20.0 if kind == "record" else float((trial.config.duration if trial else None) or 40.0)


def demo_tasks(plan: list, calibrated: list, make_fold, costs: dict) -> list:
    """The task graph of a demo run: a calibration per bag of ``calibrated``, a recording per simulated
    trial and world, a replay per job of ``plan``; a simulated replay needs its recording, a held-out
    replay the calibrations of the other bags of its robot (its fold, ``make_fold(job, done)`` -> the
    job with its fold's values)."""
    def cost(key):
        return costs.get(key, guess_cost(key))
    tasks = [schedule.Task(f"calibrate:{b}", calibrate_job, b, cost=cost(f"calibrate:{b}")) for b in calibrated]
    recordings = {recording_key(j): (j.trial, j.recording) for j in plan if j.trial is not None}
    tasks += [schedule.Task(k, record_job, r, cost=cost(k)) for k, r in recordings.items()]
    for job in plan:
        key = f"replay:{job.summary_key}"
        if job.table in (HELDOUT, PIONEER_HELDOUT):
            robot = REAL_BAGS if job.table == HELDOUT else PIONEER_BAGS
            needs = tuple(f"calibrate:{b}" for b in robot if b != job.label)
            tasks.append(schedule.Task(key, run_job, needs=needs, cost=cost(key),
                                       make=lambda done, job=job: make_fold(job, done)))
        else:
            needs = (recording_key(job),) if job.trial is not None else ()
            tasks.append(schedule.Task(key, run_job, job, needs=needs, cost=cost(key)))
    return tasks
