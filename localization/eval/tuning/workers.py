"""Running the study: worker processes on this machine, a graceful stop on Ctrl-C / SIGTERM, one line
or a progress bar per finished trial."""
from __future__ import annotations

import multiprocessing

from localization.eval.tuning.errors import TuneError
from localization.eval.tuning.objective import Objective, prepare_references
from localization.eval.tuning.study import (
    BASELINE_ATTR,
    DUPLICATE_ATTR,
    TuneConfig,
    enqueue_baseline,
    make_study,
)


def _quiet_optuna() -> None:
    import warnings

    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    warnings.filterwarnings("ignore", category=optuna.exceptions.ExperimentalWarning)
    # the baseline trial evaluates the starting values even outside the space's ranges: expected
    warnings.filterwarnings("ignore", message="Fixed parameter .* is out of range")


class GracefulStop:
    """Ctrl-C / SIGTERM as a graceful stop: the running trial finishes and is stored, then
    ``study.stop()``. (A KeyboardInterrupt raised at an arbitrary point could leave the journal
    file's lock behind, and the next writer would wait for it to go stale.) Use as a context
    manager in the main thread; it is also the study callback that stops the study."""

    def __init__(self):
        self.requested = False
        self._previous = {}

    def __enter__(self) -> "GracefulStop":
        import signal
        import threading
        if threading.current_thread() is threading.main_thread():
            for s in (signal.SIGINT, signal.SIGTERM):
                self._previous[s] = signal.signal(s, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        import signal
        for s, handler in self._previous.items():
            signal.signal(s, handler)

    def _handle(self, signum, frame) -> None:  # noqa: ARG002
        self.requested = True

    def __call__(self, study, trial) -> None:  # noqa: ARG002 - an Optuna callback
        if self.requested:
            study.stop()


def run_worker(cfg: TuneConfig, worker: int, n_trials: int, callbacks=()) -> int:
    """Run ``n_trials`` trials of the study in this process; returns how many ran. Raises
    KeyboardInterrupt after a graceful stop on Ctrl-C / SIGTERM."""
    _quiet_optuna()
    objective = Objective(cfg)
    study = make_study(cfg, worker)
    before = len(study.get_trials(deepcopy=False))
    with GracefulStop() as stop:
        # a trial that raises is recorded as failed (Optuna logs its traceback) and the study goes on
        study.optimize(objective, n_trials=n_trials, timeout=cfg.timeout, callbacks=[*callbacks, stop],
                       catch=(Exception,))
    if stop.requested:
        raise KeyboardInterrupt
    return len(study.get_trials(deepcopy=False)) - before


def _worker_main(cfg: TuneConfig, worker: int, n_trials: int, progress: bool) -> None:
    callbacks = [print_trial] if progress else []
    try:
        run_worker(cfg, worker, n_trials, callbacks)
    except KeyboardInterrupt:
        pass

def print_trial(study, trial) -> None:
    """A one-line report per finished trial on stderr."""
    import sys

    import optuna

    state = trial.state
    value = (f"{trial.value:.4f}" if state == optuna.trial.TrialState.COMPLETE and trial.value is not None
             else state.name.lower())
    try:
        best = f"{study.best_value:.4f}"
    except ValueError:
        best = "n/a"
    wall = trial.user_attrs.get("wall_s")
    sys.stderr.write(f"trial {trial.number:4d}: {value:>8} (best {best})"
                     + (f" {wall:.1f} s" if wall is not None else "")
                     + (" [baseline]" if trial.user_attrs.get(BASELINE_ATTR) else "")
                     + (f" [same parameters as trial {trial.user_attrs[DUPLICATE_ATTR]}: not re-run]"
                        if DUPLICATE_ATTR in trial.user_attrs else "") + "\n")
    sys.stderr.flush()


def _n_finished(study) -> int:
    return sum(t.state.is_finished() for t in study.get_trials(deepcopy=False))


def split_trials(n_trials: int, jobs: int) -> list[int]:
    """``n_trials`` spread over ``jobs`` workers (exactly n_trials in all)."""
    return [n_trials // jobs + (1 if k < n_trials % jobs else 0) for k in range(jobs)]


def run_workers(cfg: TuneConfig, n_trials: int, jobs: int = 1, progress: bool = False, bar: bool = False):
    """Create (or load) the study, queue the baseline, run ``n_trials`` trials over ``jobs`` worker
    processes (each its own Python: the filter is CPU-bound) and return the study. ``progress``:
    what happens on stderr (reference tracks, then one line per trial, or with ``bar`` a tqdm bar
    of the trials instead of the lines)."""
    from localization.eval.progress import busy, progress_bar
    _quiet_optuna()
    study = make_study(cfg)
    if cfg.references is None:
        with busy("reference tracks", enabled=progress and bar) as say:
            prepare_references(cfg, log=say if progress else None)
    enqueue_baseline(study, cfg)
    shares = [n for n in split_trials(n_trials, max(1, jobs)) if n > 0]
    lines = progress and not bar
    trials_bar = progress_bar(total=n_trials, desc="trials", unit="trial", enabled=progress and bar)
    before = _n_finished(study)
    if len(shares) <= 1:
        try:
            run_worker(cfg, 0, n_trials, ([print_trial] if lines else []) + [_BarCallback(trials_bar)])
        finally:
            trials_bar.close()
        return study
    ctx = multiprocessing.get_context("spawn")
    procs = [ctx.Process(target=_worker_main, args=(cfg, k, n, lines), name=f"tune-worker-{k}")
             for k, n in enumerate(shares)]
    for p in procs:
        p.start()
    with GracefulStop() as stop:  # the workers get the signal too and stop after their running trial
        for p in procs:
            while p.is_alive():
                p.join(1.0)
                if not trials_bar.disable:  # the workers' finished trials, read from the shared study
                    done = _n_finished(study) - before
                    _BarCallback(trials_bar).best(study)
                    trials_bar.update(max(0, min(done, n_trials) - trials_bar.n))
    trials_bar.close()
    if stop.requested:
        raise KeyboardInterrupt
    failed = [p.name for p in procs if p.exitcode not in (0, None)]
    if failed:
        raise TuneError(f"worker process(es) {', '.join(failed)} failed (see the messages above)")
    return study


class _BarCallback:
    """A study callback advancing a progress bar per finished trial, the best value beside it."""

    def __init__(self, bar):
        self.bar = bar

    def __call__(self, study, trial) -> None:  # noqa: ARG002 - an Optuna callback
        if not self.bar.disable:
            self.best(study)
            self.bar.update(1)

    def best(self, study) -> None:
        try:
            self.bar.set_postfix_str(f"best {study.best_value:.4f}", refresh=False)
        except ValueError:  # no complete trial yet
            pass
