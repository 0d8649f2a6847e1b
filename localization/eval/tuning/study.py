"""The study: its configuration, its sampler and pruner, the baseline trial (the starting
parameters, evaluated first) and the lookup of a parameter set an earlier trial evaluated."""
from __future__ import annotations

from dataclasses import dataclass, field

from localization.eval.tuning.score import ScoreWeights
from localization.eval.tuning.storage import make_storage, study_lock

DEFAULT_STUDY = "localization-tune"
BASELINE_ATTR = "baseline"  # user attribute of the enqueued trial that evaluates the starting parameters
DUPLICATE_ATTR = "repeat_of"  # user attribute of a trial whose parameters an earlier trial evaluated: its number
WORKERS_ATTR = "workers_started"  # study attribute (PostgreSQL): worker numbers handed out so far


@dataclass
class TuneConfig:
    """Everything a worker process needs (picklable)."""

    bags: list  # paths
    map: str
    start: dict  # starting parameter values (the complete table)
    space: list  # SpaceEntry
    storage: str  # an Optuna storage URL, or a journal file path
    study: str = DEFAULT_STUDY
    seed: int = 0
    weights: ScoreWeights = field(default_factory=ScoreWeights)
    initial_poses: list | None = None  # per bag: (x, y, yaw) or None
    scan_topic: str | None = None  # default: the start parameters' scan_topic
    odom_topic: str | None = None
    prune: bool = True
    timeout: float | None = None
    references: list | None = None  # per bag: (t, poses) of its reference track, or None (see prepare_references)


def make_study(cfg: TuneConfig, worker: int = 0):
    """Create or load the study (its sampler seeded from ``cfg.seed``, ``worker`` and the trials it has).
    Against PostgreSQL (several machines, each with its own worker numbers) the worker number is
    claimed from the study instead, under ``study_lock``: no two processes draw alike."""
    import optuna

    storage = make_storage(cfg.storage)
    pruner = (optuna.pruners.PercentilePruner(75.0, n_startup_trials=5, n_warmup_steps=0) if cfg.prune
              else optuna.pruners.NopPruner())
    with study_lock(cfg.storage) as shared:
        # a resumed study seeds its sampler past the trials it has: the same seed again would draw the
        # same first (random) parameter sets again
        done = _finished_trials(storage, cfg.study)
        if shared:
            worker = _claim_worker_number(storage, cfg.study)
        sampler = optuna.samplers.TPESampler(seed=cfg.seed + 1000 * worker + 100_003 * done, constant_liar=True)
        return optuna.create_study(storage=storage, study_name=cfg.study, direction="minimize",
                                   sampler=sampler, pruner=pruner, load_if_exists=True)


def _claim_worker_number(storage, study_name: str) -> int:
    """The next worker number of the study (0, 1, …: one per process that opened it, on any machine),
    recorded in the study; creates the study if it does not exist yet. Call it under ``study_lock``."""
    import optuna

    try:
        study_id = storage.get_study_id_from_name(study_name)
    except KeyError:
        study_id = storage.create_new_study([optuna.study.StudyDirection.MINIMIZE], study_name)
    number = int(storage.get_study_user_attrs(study_id).get(WORKERS_ATTR, 0))
    storage.set_study_user_attr(study_id, WORKERS_ATTR, number + 1)
    return number


def _finished_trials(storage, study_name: str) -> int:
    """Finished trials of a study in ``storage`` (0 when there is no such study yet)."""
    try:
        study_id = storage.get_study_id_from_name(study_name)
    except KeyError:
        return 0
    return sum(t.state.is_finished() for t in storage.get_all_trials(study_id, deepcopy=False))


def earlier_trial_with(study, params: dict, number: int):
    """A complete trial before ``number`` that evaluated exactly ``params`` (None if there is none)."""
    import optuna

    for t in study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,)):
        if t.number != number and t.params == params and DUPLICATE_ATTR not in t.user_attrs:
            return t
    return None


def start_values(cfg: TuneConfig) -> dict:
    """The starting parameters' values of the tuned names (the baseline trial's parameters). A start
    value Optuna cannot record in the entry's distribution (not among the choices, <= 0 on a log
    range) is not a trial parameter: the baseline uses it as is."""
    out = {}
    for e in cfg.space:
        v = cfg.start[e.name]
        if (e.choices is not None and v not in e.choices) or (e.choices is None and e.log and not v > 0):
            continue
        out[e.name] = v
    return out


def enqueue_baseline(study, cfg: TuneConfig) -> None:
    """Evaluate the starting parameters first (once per study: again only if it failed; under
    ``study_lock``, so tuners starting at once against PostgreSQL queue it once)."""
    import optuna

    live = (optuna.trial.TrialState.COMPLETE, optuna.trial.TrialState.RUNNING, optuna.trial.TrialState.WAITING)
    with study_lock(cfg.storage):
        if any(t.user_attrs.get(BASELINE_ATTR) for t in study.get_trials(deepcopy=False, states=live)):
            return
        study.enqueue_trial(start_values(cfg), user_attrs={BASELINE_ATTR: True}, skip_if_exists=True)


def baseline_trial(study):
    """The finished trial that evaluated the starting parameters (None if it has not finished)."""
    import optuna

    for t in study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,)):
        if t.user_attrs.get(BASELINE_ATTR):
            return t
    return None
