"""The demo's job table: every replay it runs is one frozen ``Job`` (what it replays, with which parameter
file, overrides and seed, which table it feeds); ``plan`` builds the table from the parts asked for."""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

from localization.core.parameters import Parameters
from localization.core.paths import config_dir
from localization.eval.datasets import PIONEER_BAGS, REAL_BAGS, SIM_TRIALS, real_bag_path
from localization.sim.perturb import STANDARD_PERTURBATION

# the tables a job feeds
SIM, FAST, REAL, SWEEP, HELDOUT, PIONEER, PIONEER_HELDOUT, TUNING, TUNED = (
    "sim", "fast", "real", "sweep", "heldout", "pioneer", "pioneer_heldout", "tuning", "tuned")

SIM_PARAMS = "params.yaml"  # the simulator's parameter file in config/
REAL_PARAMS = "real_params.yaml"  # the RSS 2022 RACECAR's
LOOP_TRIAL = "loop_noise0.3_biased"  # --loop
FAST_TRIAL = "fast"
#: the fast trial's replays: label -> parameter overrides
FAST_RUNS = {"fast_aligned": {"odom_time_offset": -0.04},
             "fast_unaligned": {"align_odometry": False, "deskew": False}}
#: parameter overrides of the ``_fixed`` rows: the range scale as configured, not learnt while the filter tracks
FIXED_SCALE = {"range_scale_estimation": False}
MOTION_NOISE_PARAMS = ("motion_a_trans", "motion_a_lateral", "motion_a_rot", "motion_a_rot_to_trans",
                       "motion_a_trans_to_rot", "motion_floor_xy", "motion_floor_theta")
SWEEP_SCALES = (0.25, 0.5, 1.0, 2.0)  # --motion-sweep without factors


@dataclass(frozen=True)
class Job:
    """One replay: a real bag (``bag``) or a simulated trial (``trial``, recorded with ``recording``: SimConfig
    changes), the parameter file (a name in config/) with ``parameters`` ((name, value) pairs, the seed
    among them), the start, the table it feeds and where its outputs go (None: nowhere)."""

    label: str
    table: str
    map: str
    params_file: str
    parameters: tuple = ()
    bag: str | None = None
    trial: str | None = None
    recording: tuple = ()
    initial_pose: tuple | None = None
    force_global: bool = False
    scan_topic: str | None = None
    odom_topic: str | None = None
    out: str | None = None
    plots: bool = True
    scale: float | None = None  # motion sweep: the factor on the motion noise
    fold: str | None = None  # held-out tuning: the fold whose training bag this replay is
    point: tuple | None = None  # held-out tuning: the grid point (motion scale, sigma_hit)

    @property
    def overrides(self) -> dict:
        return dict(self.parameters)

    @property
    def seed(self):
        return self.overrides.get("random_seed")

    @property
    def world(self):
        """The perturbed world of a simulated trial's recording (``MapPerturbation``), None: the map itself."""
        return dict(self.recording).get("world")

    @property
    def pioneer(self) -> bool:
        return self.table in (PIONEER, PIONEER_HELDOUT)

    @property
    def summary_key(self) -> str:
        """The job's key in summary.json: its label, ``@scale`` in the sweep, ``@heldout`` held out."""
        held = self.table in (HELDOUT, PIONEER_HELDOUT)
        return self.label + (f"@{self.scale}" if self.scale is not None else "") + ("@heldout" if held else "")

    def with_overrides(self, **changes) -> Job:
        return replace(self, parameters=tuple({**self.overrides, **changes}.items()))

    def load_parameters(self) -> Parameters:
        return Parameters.from_yaml(config_dir() / self.params_file, **self.overrides)


@dataclass
class Result:
    """What a job gave: its metrics, or the one-line error that stopped it."""

    job: Job
    metrics: dict | None = None
    error: str | None = None
    seconds: float = 0.0
    notes: tuple = ()  # what the replay said about its inputs (laser mount, odometry source): printed once each


@dataclass(frozen=True)
class Parts:
    """The parts of the demo a command line asks for (``--only``, the ``--skip-*`` options)."""

    sim: bool = True
    perturbed: bool = True
    fast: bool = True
    loop: bool = False
    real: bool = True
    heldout: bool = True
    pioneer: bool = True
    sweep: tuple | None = None  # motion-noise factors of the sweep (None: no sweep)
    tuning: bool = False
    duration: float | None = None  # s: the simulated trials truncated

    @classmethod
    def from_args(cls, args) -> Parts:
        if args.only is not None:  # one part alone, with its own held-out replays
            return cls(sim=False, real=args.only == "heldout", pioneer=args.only == "pioneer",
                       tuning=args.heldout_tuning)
        real = not args.skip_real  # the Pioneer bags are real bags too
        sweep = None if args.motion_sweep is None else tuple(args.motion_sweep or SWEEP_SCALES)
        return cls(sim=not args.skip_sim, perturbed=not args.skip_perturbed, fast=not args.skip_fast, loop=args.loop,
                   real=real, heldout=not args.skip_heldout, pioneer=real and not args.skip_pioneer,
                   sweep=sweep if real else None, tuning=args.heldout_tuning, duration=args.duration)

    @property
    def calibrated_bags(self) -> list:
        """The real bags calibrated once each for the held-out folds."""
        if not self.heldout:
            return []
        return [*(REAL_BAGS if self.real else []), *(PIONEER_BAGS if self.pioneer else [])]


def perturbed_runs(trials) -> dict:
    """The simulated trials' perturbed-world replays beside the clean ones, label -> (trial, ``SimConfig``
    overrides, parameter overrides): ``trials`` in ``STANDARD_PERTURBATION`` at their own speeds and at 2 m/s
    (label ``trialN_2mps_scale1.01``), and trial 2 at 2 m/s at scale 1.01 and 1.02 also with ``FIXED_SCALE``
    (label ``_fixed``)."""
    runs = {f"{name}_perturbed": (name, {"world": STANDARD_PERTURBATION}, {}) for name in trials}
    for name in trials:
        if name.startswith("trial") and name != "trial2_noise0.3":  # the report's trials (trial 2: below)
            drive = {"speed": 2.0, "world": STANDARD_PERTURBATION}
            runs[f"{name.split('_')[0]}_2mps_scale{STANDARD_PERTURBATION.scale:g}"] = (name, drive, {})
    for scale in (1.01, 1.02):
        drive = {"speed": 2.0, "world": replace(STANDARD_PERTURBATION, scale=scale)}
        runs[f"trial2_2mps_scale{scale:g}"] = ("trial2_noise0.3", drive, {})
        runs[f"trial2_2mps_scale{scale:g}_fixed"] = ("trial2_noise0.3", drive, FIXED_SCALE)
    return runs


def sim_jobs(parts: Parts, trials, overrides: dict, out: Path) -> list:
    """The simulated trials (clean, then perturbed) and the fast trial's two replays."""
    names = list(trials) + ([LOOP_TRIAL] if parts.loop else [])
    runs = {name: (name, {}, {}) for name in names}
    if parts.perturbed:
        runs.update(perturbed_runs(names))
    length = {"duration": parts.duration} if parts.duration else {}
    jobs = [Job(label, SIM, SIM_TRIALS[name].config.map, SIM_PARAMS, tuple({**overrides, **params}.items()),
                trial=name, recording=tuple({**changes, **length}.items()), out=str(out / label))
            for label, (name, changes, params) in runs.items()]
    if parts.fast:
        jobs += [Job(label, FAST, SIM_TRIALS[FAST_TRIAL].config.map, SIM_PARAMS, tuple({**overrides, **ov}.items()),
                     trial=FAST_TRIAL, recording=tuple(length.items()), out=str(out / label))
                 for label, ov in FAST_RUNS.items()]
    return jobs


def real_job(name: str, table: str, overrides: dict, out: Path) -> Job:
    """A real bag (RSS 2022 or Pioneer) from its start pose (globally without one), with its robot's file."""
    rb = REAL_BAGS.get(name) or PIONEER_BAGS[name]
    if table in (PIONEER, PIONEER_HELDOUT):
        # the bag's own stamp convention (lgfloor2 stamps the first beam; pioneer_params.yaml says last_beam)
        overrides = {**overrides, "scan_stamp": rb.scan_stamp}
    held = table in (HELDOUT, PIONEER_HELDOUT)
    return Job(name, table, rb.map, rb.params, tuple(overrides.items()), bag=str(real_bag_path(name)),
               initial_pose=rb.start, force_global=rb.start is None, scan_topic=rb.scan_topic,
               odom_topic=rb.odom_topic, out=str(out / "heldout" / name if held else out / name), plots=not held)


def sweep_jobs(scales, overrides: dict) -> list:
    """The RSS bags with real_params.yaml's motion noise scaled by each factor (no outputs)."""
    base = Parameters.from_yaml(config_dir() / REAL_PARAMS)
    return [replace(real_job(name, SWEEP, {**overrides, **{k: float(base[k]) * s for k in MOTION_NOISE_PARAMS}},
                             Path(".")), out=None, plots=False, scale=s)
            for s in scales for name in REAL_BAGS]


def plan(parts: Parts, trials, overrides: dict, out: Path) -> list:
    """Every replay of the demo (the held-out tuning's come later: they depend on these), in table order.
    A held-out job gets its fold's calibrated values once the calibrations are done (``cli.with_fold``)."""
    jobs = sim_jobs(parts, trials, overrides, out) if parts.sim else []
    if parts.real:
        jobs += [real_job(name, REAL, overrides, out) for name in REAL_BAGS]
        if parts.sweep is not None:
            jobs += sweep_jobs(parts.sweep, overrides)
        if parts.heldout:
            jobs += [real_job(name, HELDOUT, overrides, out) for name in REAL_BAGS]
    if parts.pioneer:
        jobs += [real_job(name, PIONEER, overrides, out) for name in PIONEER_BAGS]
        if parts.heldout:
            jobs += [real_job(name, PIONEER_HELDOUT, overrides, out) for name in PIONEER_BAGS]
    return jobs
