"""The demo's work as tasks on a pool of worker processes: each task starts as soon as the tasks it needs
are done (a held-out replay after the calibrations of its fold, a simulated replay after its recording),
the ready task heading the longest remaining chain first, so the two cores finish together.

A task's expected cost is what it took last time (``costs.json`` in the demo's cache folder), else a
guess from its bag's length; only the order depends on it, never a figure.
"""
from __future__ import annotations

import json
import time
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path

from localization.core.paths import atomic_write, cache_dir


@dataclass(frozen=True)
class Task:
    """``fn(arg)`` in a worker process; ``arg`` may be made from the results of ``needs`` (``make(done)``,
    in this process, once they are done). ``fn`` must be a module-level function (it is pickled)."""

    key: str
    fn: Callable
    arg: object = None
    needs: tuple = ()
    cost: float = 1.0  # expected seconds
    make: Callable | None = field(default=None, compare=False)


def ranks(tasks: list) -> dict:
    """key -> the cost of the longest chain of tasks from it to the end (its own cost included)."""
    after: dict = {t.key: [] for t in tasks}
    for t in tasks:
        for n in t.needs:
            after[n].append(t.key)
    cost = {t.key: t.cost for t in tasks}
    memo: dict = {}

    def rank(key: str) -> float:
        if key not in memo:
            memo[key] = cost[key] + max((rank(k) for k in after[key]), default=0.0)
        return memo[key]
    return {t.key: rank(t.key) for t in tasks}


def run_tasks(tasks: list, workers: int, on_done: Callable | None = None) -> dict:
    """key -> ``fn(arg)`` of every task, in ``workers`` processes (1: in this one, in the same order);
    ``on_done(key, result, seconds)`` as each finishes. Raises ValueError for a need no task provides."""
    known = {t.key for t in tasks}
    missing = sorted({n for t in tasks for n in t.needs} - known)
    if missing or len(known) < len(tasks):
        raise ValueError(f"tasks need {missing} or repeat a key")
    rank = ranks(tasks)
    pending = sorted(tasks, key=lambda t: -rank[t.key])  # stable: equal ranks keep their order
    done: dict = {}

    def next_ready():
        for t in pending:
            if all(n in done for n in t.needs):
                pending.remove(t)
                return t, (t.make(done) if t.make is not None else t.arg)
        return None

    def finish(key, result, seconds):
        done[key] = result
        if on_done is not None:
            on_done(key, result, seconds)

    if workers <= 1:
        while pending:
            task, arg = next_ready()
            t0 = time.perf_counter()
            finish(task.key, task.fn(arg), time.perf_counter() - t0)
        return done
    running: dict = {}
    with ProcessPoolExecutor(max_workers=workers) as pool:
        while pending or running:
            while len(running) < workers and (ready := next_ready()) is not None:
                task, arg = ready
                running[pool.submit(task.fn, arg)] = (task.key, time.perf_counter())
            finished, _ = wait(running, return_when=FIRST_COMPLETED)
            for future in finished:
                key, t0 = running.pop(future)
                finish(key, future.result(), time.perf_counter() - t0)
    return done


def costs_path() -> Path:
    return cache_dir() / "demo" / "costs.json"


def load_costs() -> dict:
    """key -> seconds each task took in the last run (empty: none recorded, or unreadable)."""
    try:
        costs = json.loads(costs_path().read_text())
    except (OSError, ValueError):
        return {}
    return {k: float(v) for k, v in costs.items() if isinstance(v, (int, float))} if isinstance(costs, dict) else {}


def save_costs(seconds: dict) -> None:
    """Keep what the tasks took (with the entries of tasks not run this time) for the next run's order."""
    try:
        with atomic_write(costs_path()) as f:
            f.write(json.dumps({**load_costs(), **seconds}, indent=1, sort_keys=True).encode())
    except OSError:
        pass  # the order only: the next run guesses from the bags' lengths
