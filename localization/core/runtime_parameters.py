"""Which parameters may change while the node runs, how a change is checked, and what applying it takes.

A change is checked by the parameter table's own rules (``Parameters``: the whole set with the new
values must be valid) and refused with the reason; a parameter that cannot change at runtime is
refused with why (``read_only_reason``; the node declares it read-only with that reason). What
applying a change takes (``How``):

    LIVE     nothing: the core and the node read the value where they use it (one shared Parameters)
    NODE     the node's watchdog timeouts
    FILTER   the particle count (an initialised cloud is resampled to it), the resampling threshold, roughening
    MOTION   the motion model's noise
    SENSOR   the beam model's parameters: its likelihood tables are rebuilt (milliseconds)
    TABLE    the beam model's range table for the map (ray caster, its size and resolution): built or loaded
             off the hot path, then swapped in (``Change.needs_preparation``)

Every change is applied between two updates, under the localizer's lock
(``Localizer.reconfigure``, ``core.localizer.reconfigure``).
"""
from __future__ import annotations

import enum
from dataclasses import dataclass

from localization.core.parameters import BY_NAME, ParameterError, Parameters


class How(enum.Enum):
    LIVE = "read where used"
    NODE = "node"
    FILTER = "filter"
    MOTION = "motion model"
    SENSOR = "sensor model"
    TABLE = "range table"


_HOW = {
    How.LIVE: ("max_particles_published", "num_beams_per_particle", "angle_step", "initial_std_xy",
               "initial_std_theta", "use_initialpose_covariance", "initial_update_stages", "recovery_particles",
               "recovery_jump_glide", "global_seed_step", "global_seed_headings", "global_seed_beams",
               "global_seed_candidates", "global_seed_temperature", "global_seed_uniform"),
    How.NODE: ("odom_timeout", "scan_timeout", "map_timeout", "tf_timeout"),
    How.FILTER: ("num_particles", "resample_ess_fraction", "roughening_xy", "roughening_theta"),
    How.MOTION: ("motion_a_trans", "motion_a_lateral", "motion_a_rot", "motion_a_rot_to_trans",
                 "motion_a_trans_to_rot", "motion_floor_xy", "motion_floor_theta"),
    How.SENSOR: ("alpha_hit", "alpha_short", "alpha_max", "alpha_rand", "sigma_hit", "squash_factor",
                 "laser_max_range", "do_beamskip", "beam_skip_distance", "beam_skip_threshold",
                 "beam_skip_error_threshold", "beam_skip_max_spread"),
    How.TABLE: ("ray_caster", "table_width", "table_resolution", "scan_theta_discretization", "range_table_lazy_cells"),
}
RUNTIME: dict[str, How] = {name: how for how, names in _HOW.items() for name in names}
BEAM_ONLY = (How.SENSOR, How.TABLE)  # the beam model changes its own; the likelihood field precomputes from them

DEFAULT_REASON = ("read once when the node starts: it shapes its subscriptions, publishers, timers, threads or "
                  "the localizer's parts; restart the node (or cleanup and configure the lifecycle node) to change it")
REASONS = {
    "sensor_model": "the sensor model is built once at start",
    "random_seed": "the random generator is seeded once at start",
    "laser_offset_x": "the laser pose comes from TF, else from these, once at start",
    "laser_offset_y": "the laser pose comes from TF, else from these, once at start",
    "laser_offset_yaw": "the laser pose comes from TF, else from these, once at start",
    "lidar_scale_to_map_scale": "the range scale starts from it (and is learnt online with range_scale_estimation)",
}


def read_only_reason(name: str) -> str:
    """Why ``name`` cannot change while the node runs ("" when it can)."""
    if name in RUNTIME:
        return ""
    return REASONS.get(name, DEFAULT_REASON)


@dataclass(frozen=True)
class Change:
    """A checked change: the whole new parameter set and what differs from the current one."""

    params: Parameters
    changed: dict  # name -> (old, new), in the order given

    @property
    def hows(self) -> set:
        return {RUNTIME[name] for name in self.changed}

    @property
    def needs_preparation(self) -> bool:
        """Seconds of work before it can be applied: a range table, or filter kernels to compile."""
        return How.TABLE in self.hows or "do_beamskip" in self.changed

    def describe(self) -> str:
        return ", ".join(f"{name} {old!r} -> {new!r}" for name, (old, new) in self.changed.items()) or "nothing"


def check_change(current: Parameters, values: dict) -> Change:
    """The change ``values`` (name -> value) makes to ``current``; ParameterError with the reason when a
    parameter cannot change while the node runs or a value breaks the table's rules."""
    problems = []
    for name in values:
        if name not in BY_NAME:
            problems.append(f"unknown parameter {name!r}")
        elif name not in RUNTIME:
            problems.append(f"{name} cannot change while the node runs: {read_only_reason(name)}")
        elif RUNTIME[name] in BEAM_ONLY and current.sensor_model != "beam":
            problems.append(f"{name} cannot change while the node runs with the {current.sensor_model} model "
                            "(it precomputes from it at start; only the beam model's can change)")
    if problems:
        raise ParameterError("; ".join(problems))
    try:
        new = Parameters({**current, **values})
    except ParameterError as exc:
        raise ParameterError(str(exc).removeprefix("invalid parameters: ")) from None
    return Change(new, {name: (current[name], new[name]) for name in values if current[name] != new[name]})
