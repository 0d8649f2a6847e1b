"""Every parameter of the localizer, declared once: name, default, one-line description, rule, group.

The node declares exactly these as ROS parameters; ``localization-replay``, the simulator and the tools read
the same names from a ROS 2 parameter file (``config/*.yaml``). ``Parameters`` is a plain, validated mapping
(no ROS). ``help_text()`` is ``particle_filter --help``'s list; ``markdown()`` is docs/node.md's table.
"""
from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

NODE_NAME = "particle_filter"


@dataclass(frozen=True)
class Param:
    name: str
    default: Any
    description: str
    check: Callable[[Any], bool] | None = None
    rule: str = ""
    group: str = ""  # one of GROUPS


def _finite(v):
    return isinstance(v, (int, float)) and math.isfinite(v)


def _positive(v):
    return _finite(v) and v > 0


def _topic(v):
    return isinstance(v, str) and len(v) > 0 and " " not in v


def _one_of(*options):
    return lambda v: v in options


#: robot_model_type's accepted names -> the motion model's robot model (core/motion.py ROBOT_MODELS); nav2_amcl's
#: plugin names (Humble and later) and its earlier short names included
ROBOT_MODEL_TYPES = {"ackermann": "ackermann", "differential": "differential", "omni": "omni",
                     "omnidirectional": "omni", "nav2_amcl::DifferentialMotionModel": "differential",
                     "nav2_amcl::OmniMotionModel": "omni"}


#: The groups, in the order ``particle_filter --help`` and docs/node.md list them: name -> what it holds.
GROUPS = {
    "topics and frames": "where the node reads and writes, and the TF frames it uses",
    "robot": "the base's kinematics and motion noise, the lidar and its mount",
    "odometry calibration": "how odometry is corrected, timed and checked (localization-calibrate measures it)",
    "sensor model": "how a scan is scored against the map",
    "filter": "particle count, resampling, when a scan updates the filter, the initial pose",
    "recovery": "global localization, the scan-map health check, and what the filter does when lost",
    "performance": "ray casting and threading: speed and memory",
    "output": "what the node publishes, warns about and saves",
}


def _grouped(*items) -> list:
    """The table: each Param joins the group whose name comes before it."""
    params, group = [], None
    for item in items:
        if isinstance(item, str):
            if item not in GROUPS:
                raise ValueError(f"unknown parameter group {item!r}")
            group = item
        else:
            params.append(replace(item, group=group))
    return params


def _int(low: int, high: int | None = None):  # (check, rule) of an integer in [low, high]
    if high is None:
        return (lambda v: isinstance(v, int) and v >= low), f"an integer >= {low}"
    return (lambda v: isinstance(v, int) and low <= v <= high), f"an integer in [{low}, {high}]"


#: (check, rule) pairs the table shares
_TOPIC, _FRAME = (_topic, "a topic name"), (_topic, "a frame id")
_BOOL = (lambda v: isinstance(v, bool), "true or false")
_FIN, _POS, _NONNEG = (_finite, "finite"), (_positive, "> 0"), (lambda v: _finite(v) and v >= 0, ">= 0")
_FRAC, _RATE = (lambda v: _finite(v) and 0 <= v <= 1, "in [0, 1]"), (lambda v: _finite(v) and 0 < v <= 1, "in (0, 1]")
_ALPHA = (lambda v: _finite(v) and (v >= 0 or v == -1), "-1 (not set) or >= 0")
_SECONDS = (lambda v: _finite(v) and abs(v) <= 1, "in [-1, 1]")
_METRES = (lambda v: _positive(v) and v <= 1, "> 0 and <= 1 (metres)")
_HALF = (lambda v: _finite(v) and 0 <= v <= 0.5, "in [0, 0.5]")


PARAMETERS = _grouped(
    "topics and frames",
    Param("map_topic", "/map", "the map input (nav_msgs/OccupancyGrid, reliable, transient local)", *_TOPIC),
    Param("scan_topic", "/scan", "the lidar input (sensor_msgs/LaserScan, sensor-data QoS)", *_TOPIC),
    Param("odom_topic", "/odom", "the odometry input (nav_msgs/Odometry): its twist moves the particles", *_TOPIC),
    Param("initialpose_topic", "/initialpose", "the initial pose input (PoseWithCovarianceStamped)", *_TOPIC),
    Param("pose_topic", "/pf/pose", "each corrected estimate (as nav2_amcl's /amcl_pose)", *_TOPIC),
    Param("map_frame", "map", "the fixed frame of the map and of every output", *_FRAME),
    Param("odom_frame", "odom", "the odometry frame (publish_tf: map_to_odom)", *_FRAME),
    Param("particle_filter_frame", "base_link_pf", "the estimate's child frame (/pf/pose/odom and TF)", *_FRAME),
    Param("base_frame", "base_link", "the robot's frame: the laser pose is looked up in TF from it", *_FRAME),
    "robot",
    Param("robot_model_type", "ackermann", "the base's kinematics: ackermann (a car), differential or omni",
          _one_of(*ROBOT_MODEL_TYPES), "one of " + ", ".join(ROBOT_MODEL_TYPES)),
    Param("deterministic", False, "no motion noise: the particles follow the odometry exactly", *_BOOL),
    Param("motion_a_trans", 0.05, "along-track noise std (m) per sqrt(m) travelled", *_NONNEG),
    Param("motion_a_lateral", 0.04, "across-track noise std (m) per sqrt(m) travelled", *_NONNEG),
    Param("motion_a_rot", 0.1, "heading noise std (rad) per sqrt(rad) turned", *_NONNEG),
    Param("motion_a_rot_to_trans", 0.02, "position noise std (m) per sqrt(rad) turned", *_NONNEG),
    Param("motion_a_trans_to_rot", 0.05, "heading noise std (rad) per sqrt(m) travelled", *_NONNEG),
    Param("motion_floor_xy", 0.02, "position noise std (m) per sqrt(m travelled + rad turned)", *_NONNEG),
    Param("motion_floor_theta", 0.02, "heading noise std (rad) per sqrt(m travelled + rad turned)", *_NONNEG),
    Param("alpha1", -1.0, "nav2_amcl's rotation noise from rotation: sets motion_a_rot", *_ALPHA),
    Param("alpha2", -1.0, "nav2_amcl's rotation noise from translation: sets motion_a_trans_to_rot", *_ALPHA),
    Param("alpha3", -1.0, "nav2_amcl's translation noise from translation: sets motion_a_trans", *_ALPHA),
    Param("alpha4", -1.0, "nav2_amcl's translation noise from rotation: sets motion_a_rot_to_trans", *_ALPHA),
    Param("alpha5", -1.0, "nav2_amcl's strafe noise (omni only): sets motion_a_lateral", *_ALPHA),
    Param("laser_pose_from_tf", True, "read the laser pose from TF (base_frame -> the scan's frame)", *_BOOL),
    Param("laser_offset_x", 0.275, "laser position ahead of base_frame (m) when TF has none", *_FIN),
    Param("laser_offset_y", 0.0, "laser position left of base_frame (m) when TF has none", *_FIN),
    Param("laser_offset_yaw", 0.0, "laser yaw relative to base_frame (rad) when TF has none", *_FIN),
    Param("laser_max_range", -1.0, "the lidar's range (m): a reading this long is no return", _finite,
          "finite (<= 0: the scan's range_max)"),
    Param("scan_field_of_view", 4.71, "field of view (rad) assumed when a scan carries no angles",
          lambda v: _positive(v) and v <= 2 * math.pi + 1e-6, "in (0, 2 pi]"),
    Param("scan_stamp", "first_beam", "which beam a scan's header stamp describes",
          _one_of("first_beam", "last_beam"), "first_beam or last_beam"),
    Param("scan_stamp_offset", 0.0, "how much later (s) than that beam the driver stamped the scan", *_SECONDS),
    "odometry calibration",
    Param("align_odometry", True, "move the particles to each scan's own time (false: the newest odometry)", *_BOOL),
    Param("odom_time_offset", 0.0, "odometry stamped t moves the robot up to t + this (s); 40 ms late: -0.04",
          *_SECONDS),
    Param("odom_speed_scale", 1.0, "speed used = this x the reported speed", *_POS),
    Param("odom_yaw_rate_scale", 1.0, "yaw rate used = this x the reported yaw rate + odom_yaw_rate_bias", *_POS),
    Param("odom_yaw_rate_bias", 0.0, "added to the scaled yaw rate (rad/s)", *_FIN),
    Param("odom_max_acceleration", 0.0, "the tyres' grip (m/s^2): faster speed changes are slip (0: off)", *_NONNEG),
    Param("odom_max_gap", 1.0, "odometry silent longer than this (s) restarts the motion history", *_POS),
    Param("odom_max_speed", 20.0, "odometry faster than this (m/s) is a broken message and ignored", *_POS),
    Param("odom_max_yaw_rate", 20.0, "odometry turning faster than this (rad/s) is ignored", *_POS),
    Param("scan_max_wait", 0.5, "a scan newer than the odometry waits this long (s) for it",
          lambda v: _positive(v) and v <= 10.0, "in (0, 10]"),
    Param("scan_queue_size", 20, "at most this many scans wait for odometry", *_int(1, 1000)),
    "sensor model",
    Param("sensor_model", "beam", "beam (the course's beam model) or likelihood_field (as nav2_amcl)",
          _one_of("beam", "likelihood_field"), "beam or likelihood_field"),
    Param("num_beams_per_particle", 100, "beams of each scan used, spread evenly", *_int(1, 10000)),
    Param("angle_step", 0, "use every n-th beam instead (the course's stride; 0: num_beams_per_particle)",
          *_int(0, 10000)),
    Param("deskew", True, "cast each beam from the laser pose at its own time within the sweep", *_BOOL),
    Param("lidar_scale_to_map_scale", 1.0, "lidar metres x this = map metres", *_POS),
    Param("map_wall_depth", 0.0, "how far (m) behind the map's free-space edge returns end (beam model)", *_HALF),
    Param("range_scale_estimation", True, "learn the lidar-to-map range scale while tracking (beam model)", *_BOOL),
    Param("range_scale_alpha", 0.02, "range_scale_estimation: weight of each update in the learnt scale", *_RATE),
    Param("range_scale_bound", 0.05, "range_scale_estimation: the scale stays within 1 +- this of the start",
          *_HALF),
    Param("alpha_hit", 0.74, "beam model: weight of the Gaussian hit component", *_NONNEG),
    Param("alpha_short", 0.07, "beam model: weight of the short-reading component", *_NONNEG),
    Param("alpha_max", 0.07, "beam model: weight of the max-range component", *_NONNEG),
    Param("alpha_rand", 0.12, "beam model: weight of the uniform component", *_NONNEG),
    Param("sigma_hit", 0.2, "beam model: std (m) of the hit Gaussian (in cells: sigma_hit_cells)", *_METRES),
    Param("squash_factor", 2.2, "each scan's log-likelihood is divided by this", *_POS),
    Param("table_width", 201, "beam model: table cells; it reaches (table_width - 1) x table_resolution",
          *_int(2, 4096)),
    Param("table_resolution", 0.05, "beam model: table cell (m) that ranges are binned to",
          lambda v: _positive(v) and v <= 1.0, "> 0 and <= 1"),
    Param("do_beamskip", False, "leave out beams most particles cannot explain (people, glass), as nav2", *_BOOL),
    Param("beam_skip_distance", 0.5, "do_beamskip: a particle explains a beam within this (m)", *_POS),
    Param("beam_skip_threshold", 0.3, "do_beamskip: use a beam more than this share of particles explain", *_FRAC),
    Param("beam_skip_error_threshold", 0.9, "do_beamskip: use all beams when this share would be skipped", *_FRAC),
    Param("beam_skip_max_spread", 1.0, "do_beamskip: only while the cloud's position std is <= this (m)", *_POS),
    Param("lf_z_hit", 0.5, "likelihood_field: weight of the Gaussian of the distance to a wall", *_NONNEG),
    Param("lf_z_rand", 0.5, "likelihood_field: weight of the uniform density 1 / z_max", *_NONNEG),
    Param("lf_sigma_hit", 0.1, "likelihood_field: std (m) of that Gaussian", *_POS),
    Param("laser_likelihood_max_dist", 2.0, "likelihood_field: distances to a wall are capped at this (m)", *_POS),
    "filter",
    Param("num_particles", 2000, "number of particles while tracking", *_int(1, 1_000_000)),
    Param("resample_ess_fraction", 1.0, "resample when the effective sample size < this x the count", *_FRAC),
    Param("roughening_xy", 0.01, "std (m) of the x, y jitter added after resampling", *_NONNEG),
    Param("roughening_theta", 0.005, "std (rad) of the heading jitter added after resampling", *_NONNEG),
    Param("update_min_distance", 0.005, "a scan updates the filter after this much travel (m) ...", *_NONNEG),
    Param("update_min_angle", 0.005, "... or this much rotation (rad) since the last update", *_NONNEG),
    Param("update_every_n_scans", 0, "also update on every n-th scan while standing (0: only on motion)", *_int(0)),
    Param("random_seed", -1, "seed of every random draw (-1: nondeterministic)", lambda v: isinstance(v, int),
          "an integer"),
    Param("initial_std_xy", 0.5, "std (m) of the initial cloud when /initialpose has no covariance", *_NONNEG),
    Param("initial_std_theta", 0.2, "std (rad) of the initial heading spread", *_NONNEG),
    Param("use_initialpose_covariance", True, "spread the initial cloud with /initialpose's covariance", *_BOOL),
    Param("initial_update_stages", 8, "the first scan after an initial pose updates in this many stages", *_int(1)),
    Param("set_initial_pose", False, "start from initial_pose.x/.y/.yaw, not /initialpose", *_BOOL),
    Param("initial_pose.x", 0.0, "initial x (m, map frame) with set_initial_pose", *_FIN),
    Param("initial_pose.y", 0.0, "initial y (m, map frame) with set_initial_pose", *_FIN),
    Param("initial_pose.yaw", 0.0, "initial heading (rad, map frame) with set_initial_pose", *_FIN),
    Param("adaptive_particles", False, "KLD-adaptive particle count in [min_particles, max_particles]", *_BOOL),
    Param("min_particles", 500, "adaptive_particles: fewest particles", *_int(1)),
    Param("max_particles", 40000, "adaptive_particles: most particles (a global spread keeps them)",
          *_int(1, 1_000_000)),
    Param("pf_err", 0.05, "adaptive_particles: the KLD bound epsilon", lambda v: _positive(v) and v < 1, "in (0, 1)"),
    Param("pf_z", 0.99, "adaptive_particles: the normal quantile of the KLD bound (nav2's pf_z)", *_POS),
    Param("kld_bin_xy", 0.5, "adaptive_particles: histogram bin (m) in x and y", *_POS),
    Param("kld_bin_theta", math.radians(10.0), "adaptive_particles: histogram bin (rad) in heading", *_POS),
    "recovery",
    Param("global_localization", False, "start with particles over the whole map (no initial pose)", *_BOOL),
    Param("global_init", "scan", "place a global spread: scan (poses the next scan fits) or uniform",
          _one_of("scan", "uniform"), "scan or uniform"),
    Param("global_num_particles", 40000, "particles of a global spread until it converges", *_int(1, 1_000_000)),
    Param("global_converged_std", 0.5, "a global spread has converged below this position std (m)", *_POS),
    Param("global_seed_step", 0.2, "global_init scan: lattice spacing (m) of the candidate positions", *_POS),
    Param("global_seed_headings", 72, "global_init scan: candidate headings per position", *_int(1, 3600)),
    Param("global_seed_beams", 30, "global_init scan: beams used to score the lattice", *_int(1, 10000)),
    Param("global_seed_candidates", 4000, "global_init scan: best lattice poses the particles are drawn around",
          *_int(1, 10_000_000)),
    Param("global_seed_temperature", 4.0, "global_init scan: larger keeps more look-alike places alive", *_POS),
    Param("global_seed_uniform", 0.1, "global_init scan: share of the particles still spread uniformly", *_FRAC),
    Param("max_impossible_scans", 3, "this many scans in a row no particle explains re-spread the cloud", *_int(1)),
    Param("recovery", True, "when lost, hold the pose on odometry and search for a better place", *_BOOL),
    Param("recovery_search_period", 2.0, "while lost: seconds between two searches for a challenger", *_POS),
    Param("recovery_particles", 2000, "particles of a challenger cloud", *_int(10)),
    Param("recovery_margin", 0.15, "how much better (scan-map agreement) a challenger or a jump must fit", *_FRAC),
    Param("recovery_confirm_updates", 20, "a challenger wins after fitting better this many updates in a row ...",
          *_int(1)),
    Param("recovery_confirm_distance", 1.0, "... over at least this much travel (m)", *_NONNEG),
    Param("recovery_switch_step", 0.25, "after a switch the pose glides at most this far (m) per update", *_NONNEG),
    Param("recovery_switch_turn", 0.2, "... and turns at most this much (rad) per update", *_NONNEG),
    Param("recovery_switch_glide_max", 0.0, "publish a switch farther than this (m) at once (0: always glide)",
          *_NONNEG),
    Param("recovery_jump_glide", 0.25, "a tracking jump farther than this (m) must fit better (0: no check)",
          *_NONNEG),
    Param("recovery_challenger_timeout", 8.0, "drop a challenger that has not won within this long (s)", *_POS),
    Param("health_fast_alpha", 0.2, "weight of each update in the fast agreement average (/pf/health)", *_RATE),
    Param("health_slow_alpha", 0.02, "weight of each update in the slow agreement average", *_RATE),
    Param("health_lost_floor", 0.35, "lost when the fast agreement stays below this ...", *_FRAC),
    Param("health_lost_ratio", 0.5, "... or below this fraction of the slow agreement ...", *_FRAC),
    Param("health_lost_updates", 20, "... for this many sensor updates in a row", *_int(1)),
    "performance",
    Param("ray_caster", "lookup_table", "lookup_table (fast), lookup_table_exact, distance_transform, exact or "
          "scan_simulator (the course's)",
          _one_of("lookup_table", "lookup_table_exact", "distance_transform", "exact", "scan_simulator"),
          "lookup_table, lookup_table_exact, distance_transform, exact or scan_simulator"),
    Param("scan_theta_discretization", 144, "headings of the range lookup table (144: 2.5 deg)", *_int(8, 2048)),
    Param("range_table_lazy_cells", 10_000_000, "bigger maps build the range table per tile, where needed",
          *_int(0)),
    Param("sensor_update_thread", False, "run the sensor update on its own thread (odometry never waits)", *_BOOL),
    Param("num_threads", 1, "CPU threads of the beam model's sensor update (the same weights as one thread)",
          *_int(1, 256)),
    "output",
    Param("publish_tf", "map_to_particle_filter_frame", "the transform to broadcast",
          _one_of("map_to_particle_filter_frame", "map_to_odom", "none"),
          "map_to_particle_filter_frame, map_to_odom or none"),
    Param("max_particles_published", 500, "at most this many particles go out on /pf/particles", *_int(0)),
    Param("diagnostics_period", 1.0, "period (s) of /diagnostics", *_POS),
    Param("odom_timeout", 0.5, "warn when scans arrive but no odometry came for this long (s)", *_POS),
    Param("scan_timeout", 0.5, "warn when odometry arrives but no scan came for this long (s)", *_POS),
    Param("map_timeout", 5.0, "warn when no map arrived this long (s) after the start", *_POS),
    Param("tf_timeout", 1.0, "use laser_offset_* when TF has no laser pose this long (s)", *_POS),
    Param("persist_pose", False, "save the estimate; start from it when no initial pose is set", *_BOOL),
    Param("persist_pose_file", "", "the saved pose's file (empty: last_pose.yaml in the cache directory)",
          lambda v: isinstance(v, str), "a path or empty"),
    Param("persist_pose_period", 3.0, "seconds between two saves of the pose", *_POS),
    Param("foxglove_port", -1, "serve a Foxglove live view on this port (0: any free port; -1: off)",
          *_int(-1, 65535)),
    Param("foxglove_host", "127.0.0.1", "the address the live view listens on",
          lambda v: isinstance(v, str) and len(v) > 0, "an address"),
)

BY_NAME = {p.name: p for p in PARAMETERS}

#: Frame ids: a leading "/" (ROS 1 style, as the course's files write "/base_link") is dropped, with one note.
FRAME_PARAMETERS = ("map_frame", "odom_frame", "particle_filter_frame", "base_frame")
_NOTED_FRAMES: set = set()

#: Where the course's classes, constructed with no arguments (``SensorModel()``, ``MotionModel()``
#: as the course's starter code and tests do), deliberately keep the course's values instead of
#: the node's tuned defaults above. This is the only place such a difference is stated
#: (``test_parameters.py`` checks every model's defaults against the table and this list).
COURSE_DEFAULTS = {
    "sigma_hit": 0.4,  # m: the course's beam model (8 cells of 0.05 m); the node's 0.2 is tuned on the Stata basement
    "laser_offset_x": 0.0,  # the course's model casts from base_link; the racecar's laser is 0.275 m ahead
    "motion_floor_xy": 0.007,  # the course's MotionModel adds less isotropic noise (per metre or radian)
    "motion_floor_theta": 0.007,
}


@dataclass(frozen=True)
class Deprecated:
    """An old parameter name still accepted: its value becomes ``new`` through ``convert(value,
    params)`` (``params``: the values set so far, e.g. for a unit), with one warning."""

    new: str
    convert: Callable[[Any, dict], Any]
    message: str


#: Old names → their replacement (``Parameters`` converts them after every other value is set).
DEPRECATED = {
    "sigma_hit_cells": Deprecated(
        "sigma_hit", lambda v, values: float(v) * values["table_resolution"] if _finite(v) else v,
        "sigma_hit_cells is deprecated: sigma_hit is in metres now (sigma_hit = sigma_hit_cells x "
        "table_resolution)"),
}


def default(name: str, course: bool = False):
    """The default of parameter ``name`` from the table (``course``: the course's class default)."""
    if course and name in COURSE_DEFAULTS:
        return COURSE_DEFAULTS[name]
    return BY_NAME[name].default


def coerce_number(default, value):
    """A number as a parameter file may write it, in the type of the parameter's ``default``: an integer
    for a float parameter (``1`` for ``1.0``) and a whole float for an integer one (the course's
    ``scan_theta_discretization: 500.0``); anything else unchanged (the rules then judge it)."""
    if isinstance(value, bool) or isinstance(default, bool):
        return value
    if isinstance(default, float) and isinstance(value, int):
        return float(value)
    if isinstance(default, int) and isinstance(value, float) and value.is_integer():
        return int(value)
    return value


def _flatten(values: dict, prefix: str = "") -> dict:
    """Nested YAML mappings as ROS 2 reads them: ``initial_pose: {x: 1.0}`` -> ``initial_pose.x``."""
    flat = {}
    for name, value in values.items():
        if isinstance(value, dict):
            flat.update(_flatten(value, f"{prefix}{name}."))
        else:
            flat[f"{prefix}{name}"] = value
    return flat


class ParameterError(ValueError):
    """An unknown parameter or a value that breaks its rule."""


class Parameters(dict):
    """Validated parameter values, defaults filled in. Attribute access: ``params.num_particles``."""

    def __init__(self, values: dict | None = None, **overrides):
        super().__init__({p.name: p.default for p in PARAMETERS})
        merged = dict(values or {})
        merged.update(overrides)
        # deprecated names last: their conversion may read another value (sigma_hit_cells: table_resolution)
        for name, value in sorted(merged.items(), key=lambda item: item[0] in DEPRECATED):
            self[name] = value
        self._normalise_frames()
        self.validate()

    def _normalise_frames(self) -> None:
        """Frame ids lose a leading "/" (tf2 refuses it); one note per value, the first time it is seen."""
        changed = []
        for name in FRAME_PARAMETERS:
            value = self[name]
            if isinstance(value, str) and value.startswith("/") and value.strip("/"):
                super().__setitem__(name, value.lstrip("/"))
                if (name, value) not in _NOTED_FRAMES:
                    _NOTED_FRAMES.add((name, value))
                    changed.append(f"{name} {value!r} -> {value.lstrip('/')!r}")
        if changed:
            logging.getLogger("localization.parameters").info(
                "frame ids are used without their leading '/': " + ", ".join(changed))

    def __setitem__(self, name, value):
        if name in DEPRECATED:
            old = DEPRECATED[name]
            converted = old.convert(value, self)
            logging.getLogger("localization.parameters").warning(
                f"{old.message}: {name}={value!r} -> {old.new}={converted!r}")
            name, value = old.new, converted
        if name not in BY_NAME:
            raise ParameterError(f"unknown parameter {name!r}")
        value = coerce_number(BY_NAME[name].default, value)
        super().__setitem__(name, value)

    def __getattr__(self, name):
        try:
            return self[name]
        except KeyError:
            raise AttributeError(name) from None

    def validate(self) -> None:
        problems = []
        for p in PARAMETERS:
            value = self[p.name]
            if type(value) is not type(p.default) and not (isinstance(p.default, float) and isinstance(value, int)
                                                           and not isinstance(value, bool)):
                kind = {bool: "a boolean", int: "an integer", float: "a number", str: "a string"}[type(p.default)]
                problems.append(f"{p.name}={value!r} must be {kind}")
            elif p.check is not None and not p.check(value):
                problems.append(f"{p.name}={value!r} must be {p.rule}")
        if not problems and sum(self[a] for a in ("alpha_hit", "alpha_short", "alpha_max", "alpha_rand")) <= 0:
            problems.append("at least one of alpha_hit, alpha_short, alpha_max, alpha_rand must be > 0")
        if problems:
            raise ParameterError("invalid parameters: " + "; ".join(problems))

    @classmethod
    def from_yaml(cls, path, node_name: str = NODE_NAME, **overrides) -> "Parameters":
        """Read a ROS 2 parameter file (``node: ros__parameters: {...}``, ``/**`` also accepted)."""
        import yaml
        try:
            doc = yaml.safe_load(Path(path).read_text()) or {}
        except (OSError, yaml.YAMLError) as exc:
            raise ParameterError(f"cannot read parameter file {path}: {exc}") from exc
        keys = list(doc) if isinstance(doc, dict) else []
        matching = node_sections(keys, node_name)
        if not matching:
            raise ParameterError(section_error(path, keys, node_name))
        values = {}
        for key in matching:  # in file order, as rcl applies them
            values.update(_flatten((doc[key] or {}).get("ros__parameters", {}) or {}))
        values.update(overrides)
        return cls(values)


def node_sections(keys, node_name: str = NODE_NAME, namespace: str = "/") -> list:
    """The keys of a ROS 2 parameter file that apply to the node ``namespace/node_name``, in their
    order: a fully qualified name (the leading ``/`` optional), where ``*`` stands for one name
    token and ``**`` for any number (rcl's rule; ``/**`` applies to every node)."""
    import re
    full = "/".join(t for t in f"{namespace}/{node_name}".split("/") if t)
    out = []
    for key in keys:
        tokens = [t for t in str(key).split("/") if t]
        pattern = "".join("(?:/[^/]+)*" if t == "**" else "/[^/]+" if t == "*" else "/" + re.escape(t)
                          for t in tokens)
        if tokens and re.fullmatch(pattern, "/" + full):
            out.append(key)
    return out


def section_error(path, keys, node_name: str = NODE_NAME) -> str:
    """The one-line error for a parameter file without a section for the node."""
    found = ", ".join(repr(str(k)) for k in keys) or "none"
    return (f"parameter file {path} has no section for the node {node_name!r} (keys found: {found}); "
            f"its parameters go under '{node_name}:' or '/**:', then 'ros__parameters:'")


# ------------------------------------------------------------------ the table as text: --help and docs/node.md
MARKDOWN_BEGIN = "<!-- parameter table: written by python -m localization.core.parameters --markdown -->"
MARKDOWN_END = "<!-- end of the parameter table -->"


def show_value(value) -> str:
    """A default as a parameter file writes it."""
    if isinstance(value, bool) or value == "":
        return {True: "true", False: "false", "": '""'}[value]
    return value if isinstance(value, str) else f"{value:.10g}" if len(repr(value)) > 12 else repr(value)


def help_text() -> str:
    """Every parameter by group: name = default [rule], then its one-line description (``--help``)."""
    lines = []
    for group, about in GROUPS.items():
        lines += [f"{group.capitalize()}: {about}"] + [
            f"  {p.name} = {show_value(p.default)}  [{p.rule}]\n      {p.description}"
            for p in PARAMETERS if p.group == group] + [""]
    return "\n".join(lines).rstrip("\n")


def markdown() -> str:
    """Every parameter by group as markdown tables (docs/node.md holds it between MARKDOWN_BEGIN and _END)."""
    lines = []
    for group, about in GROUPS.items():
        lines += [f"**{group.capitalize()}**: {about}.", "", "| parameter | default | rule | what it does |",
                  "| --- | --- | --- | --- |"] + [
            f"| `{p.name}` | `{show_value(p.default)}` | {p.rule} | {p.description} |"
            for p in PARAMETERS if p.group == group] + [""]
    return "\n".join(lines).rstrip("\n")


def replace_markdown(text: str) -> str:
    """``text`` (a document holding the two markers) with markdown() between them."""
    head, begin, rest = text.partition(MARKDOWN_BEGIN)
    end, tail = rest.partition(MARKDOWN_END)[1:]
    if not begin or not end:
        raise ValueError(f"no {MARKDOWN_BEGIN!r} ... {MARKDOWN_END!r} section")
    return f"{head}{MARKDOWN_BEGIN}\n{markdown()}\n{MARKDOWN_END}{tail}"


def main(argv=None) -> int:
    """Print every parameter by group; --markdown [FILE]: write the table into FILE (docs/node.md)."""
    import argparse
    parser = argparse.ArgumentParser(prog="python -m localization.core.parameters", description=main.__doc__)
    parser.add_argument("--markdown", nargs="?", const=Path(__file__).resolve().parents[2] / "docs" / "node.md",
                        type=Path, metavar="FILE")
    path = parser.parse_args(argv).markdown
    if path is not None:
        path.write_text(replace_markdown(path.read_text()))
    print(help_text() if path is None else f"wrote the parameter table into {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
