"""Every parameter of the localizer, declared once: name, default, description, check.

The node declares exactly these as ROS parameters; ``localization-replay`` and the simulator
read the same names from a ROS 2 parameter file (``config/params.yaml``,
``config/real_params.yaml``). ``Parameters`` is a plain, validated mapping (no ROS).
"""
from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
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


def _positive(v):
    return isinstance(v, (int, float)) and math.isfinite(v) and v > 0


def _non_negative(v):
    return isinstance(v, (int, float)) and math.isfinite(v) and v >= 0


def _fraction(v):
    return isinstance(v, (int, float)) and 0.0 <= v <= 1.0


def _finite(v):
    return isinstance(v, (int, float)) and math.isfinite(v)


def _topic(v):
    return isinstance(v, str) and len(v) > 0 and " " not in v


def _one_of(*options):
    return lambda v: v in options


def _alpha(v):
    return _finite(v) and (v >= 0 or v == -1)


#: robot_model_type's accepted names -> the motion model's robot model (core/motion.py ROBOT_MODELS); nav2_amcl's
#: plugin names (Humble and later) and its earlier short names included
ROBOT_MODEL_TYPES = {
    "ackermann": "ackermann",
    "differential": "differential",
    "omni": "omni",
    "omnidirectional": "omni",
    "nav2_amcl::DifferentialMotionModel": "differential",
    "nav2_amcl::OmniMotionModel": "omni",
}


PARAMETERS = [
    # --- topics and frames
    Param("map_topic", "/map", "nav_msgs/OccupancyGrid input (reliable, transient local)", _topic, "a topic name"),
    Param("scan_topic", "/scan", "sensor_msgs/LaserScan input (sensor-data QoS)", _topic, "a topic name"),
    Param("odom_topic", "/odom", "nav_msgs/Odometry input: twist x dt moves the particles", _topic, "a topic name"),
    Param("initialpose_topic", "/initialpose", "geometry_msgs/PoseWithCovarianceStamped input", _topic, "a topic name"),
    Param("map_frame", "map", "the fixed frame of the map and of every output", _topic, "a frame id"),
    Param("odom_frame", "odom", "odometry frame (used when publish_tf is map_to_odom)", _topic, "a frame id"),
    Param("particle_filter_frame", "base_link_pf", "child frame of the estimate (Odometry and TF)", _topic,
          "a frame id"),
    Param("publish_tf", "map_to_particle_filter_frame", "which transform to broadcast: map_to_particle_filter_frame, "
          "map_to_odom (REP-105, on the car) or none",
          _one_of("map_to_particle_filter_frame", "map_to_odom", "none"),
          "map_to_particle_filter_frame, map_to_odom or none"),
    Param("max_particles_published", 500, "at most this many particles go out on /pf/particles",
          lambda v: isinstance(v, int) and v >= 0, "an integer >= 0"),
    # --- filter
    Param("num_particles", 2000, "number of particles", lambda v: isinstance(v, int) and 1 <= v <= 1_000_000,
          "an integer in [1, 1000000]"),
    Param("resample_ess_fraction", 1.0, "resample when the effective sample size falls below this fraction of "
          "num_particles; 1.0 = every scan (the course's choice: simple, but it discards diversity on "
          "uninformative scans), 0.5 is a common, more conservative choice", _fraction, "in [0, 1]"),
    Param("roughening_xy", 0.01, "std (m) of the jitter added to x and y after resampling", _non_negative, ">= 0"),
    Param("roughening_theta", 0.005, "std (rad) of the jitter added to theta after resampling", _non_negative, ">= 0"),
    Param("update_min_distance", 0.005, "a scan updates the filter only after this much travel (m) since the last "
          "update (the first scan after an initialisation always does)", _non_negative, ">= 0"),
    Param("update_min_angle", 0.005, "... or this much rotation (rad)", _non_negative, ">= 0"),
    Param("odom_max_gap", 1.0, "odometry silent (or stamps jumping) for longer than this (s) resets the motion "
          "reference instead of moving the particles", _positive, "> 0"),
    Param("odom_max_speed", 20.0, "odometry faster than this (m/s) is a broken message and ignored", _positive, "> 0"),
    Param("odom_max_yaw_rate", 20.0, "odometry turning faster than this (rad/s) is ignored", _positive, "> 0"),
    Param("odom_max_acceleration", 0.0, "the fastest change of forward speed (m/s^2) the base's tyres can make "
          "(their grip, about mu x 9.81); odometry changing speed faster slips or skids (locked wheels report a "
          "stop while the robot slides on): the particles spread along track over the difference from the speed "
          "changing at this rate (mean half of it, std half of it) and the update policy counts it as travel "
          "(0: odometry never slips)", _non_negative, ">= 0"),
    Param("max_impossible_scans", 3, "this many scans in a row giving every particle likelihood 0 re-spread the "
          "particles over the free space", lambda v: isinstance(v, int) and v >= 1, "an integer >= 1"),
    Param("random_seed", -1, "seed of every random draw; -1 = nondeterministic", lambda v: isinstance(v, int),
          "an integer"),
    # --- initialisation
    Param("initial_std_xy", 0.5, "std (m) of the initial cloud when /initialpose has no covariance", _non_negative,
          ">= 0"),
    Param("initial_std_theta", 0.2, "std (rad) of the initial heading spread", _non_negative, ">= 0"),
    Param("initial_update_stages", 8, "the first scan after an initial pose updates the cloud in up to this many "
          "tempered stages (likelihood^beta, the betas summing to 1, each keeping half the cloud effective; "
          "resampled and jittered between stages): the cloud settles onto where that one scan points instead of "
          "onto the few initial particles nearest to it. 1: one plain update", lambda v: isinstance(v, int) and v >= 1,
          "an integer >= 1"),
    Param("use_initialpose_covariance", True, "spread the cloud with the covariance of /initialpose when it has one",
          lambda v: isinstance(v, bool), "true or false"),
    Param("global_localization", False, "start with particles spread uniformly over free space (no initial pose "
          "needed)", lambda v: isinstance(v, bool), "true or false"),
    # --- global localization and recovery (localization/health.py)
    Param("global_num_particles", 40000, "particles used while globally localizing or recovering (uniform spread "
          "over free space); the cloud shrinks back to num_particles once it has converged",
          lambda v: isinstance(v, int) and 1 <= v <= 1_000_000, "an integer in [1, 1000000]"),
    Param("global_converged_std", 0.5, "a global spread has converged when the cloud's position std (m, largest "
          "axis) falls below this", _positive, "> 0"),
    Param("recovery", True, "detect a lost filter (scan-map agreement, see health_*): hold the pose on odometry "
          "(the scans update only the search, not the cloud) and search the map for a place the scans fit clearly "
          "better; switch there only once confirmed (recovery_*). Never a jump on one scan",
          lambda v: isinstance(v, bool), "true or false"),
    Param("recovery_search_period", 2.0, "while lost: seconds (scan clock) between two searches of the map for a "
          "challenger (a scan-seeded second cloud)", _positive, "> 0"),
    Param("recovery_particles", 2000, "particles of a challenger cloud", lambda v: isinstance(v, int) and v >= 10,
          "an integer >= 10"),
    Param("recovery_margin", 0.15, "a challenger wins an update when its scan-map agreement beats the estimate's "
          "by this much (and reaches health_lost_floor); a tracking jump (recovery_jump_glide) must beat the "
          "published pose's by as much", _fraction, "in [0, 1]"),
    Param("recovery_confirm_updates", 20, "a challenger replaces the cloud after winning this many updates in a row",
          lambda v: isinstance(v, int) and v >= 1, "an integer >= 1"),
    Param("recovery_confirm_distance", 1.0, "... while the robot travelled at least this far (m)", _non_negative,
          ">= 0"),
    Param("recovery_switch_step", 0.25, "after a switch the published pose moves to the new place by at most this "
          "far (m) per sensor update, its covariance widened by the distance still to go (0: in one step)",
          _non_negative, ">= 0"),
    Param("recovery_switch_turn", 0.2, "... and turns by at most this much (rad) per sensor update", _non_negative,
          ">= 0"),
    Param("recovery_switch_glide_max", 0.0, "a switch to a place farther than this (m) from the published pose is "
          "published at once, for a robot that may be carried elsewhere (0: every switch glides, however far)",
          _non_negative, ">= 0"),
    Param("recovery_jump_glide", 0.25, "while tracking, a sensor update that moves the estimate farther than this (m) "
          "from the published pose carried by odometry, and outside three standard deviations of that pose's "
          "position covariance in the direction of the move (a cloud that changed its mind between two places, not "
          "one converging), is kept only when "
          "the scan's map agreement there beats the published pose's by recovery_margin (else the update is "
          "undone) and is published as a glide, as after a switch (0: no such check, at once)", _non_negative,
          ">= 0"),
    Param("recovery_challenger_timeout", 8.0, "a challenger that has not won within this long (s, scan clock) is "
          "dropped", _positive, "> 0"),
    Param("health_fast_alpha", 0.2, "weight of each new scan-map agreement in the fast average (the published "
          "health)", lambda v: _fraction(v) and v > 0, "in (0, 1]"),
    Param("health_slow_alpha", 0.02, "weight of each new agreement in the slow average",
          lambda v: _fraction(v) and v > 0,
          "in (0, 1]"),
    Param("health_lost_floor", 0.35, "lost when the fast average stays below this agreement ...", _fraction,
          "in [0, 1]"),
    Param("health_lost_ratio", 0.5, "... or below this fraction of the slow average ...", _fraction, "in [0, 1]"),
    Param("health_lost_updates", 20, "... for this many sensor updates in a row",
          lambda v: isinstance(v, int) and v >= 1, "an integer >= 1"),
    # --- motion model (core/motion.py: a random walk in the distance travelled and the angle turned)
    Param("deterministic", False, "no motion noise: exact odometry composition", lambda v: isinstance(v, bool),
          "true or false"),
    Param("robot_model_type", "ackermann", "the base's kinematics: ackermann (a car: keeps the odometry's sideways "
          "motion, noise along/across its heading), differential (turns on the spot; sideways odometry vy is "
          "ignored), omni (moves sideways; noise along/across its direction of travel); nav2's names "
          "nav2_amcl::DifferentialMotionModel, nav2_amcl::OmniMotionModel, omnidirectional are accepted",
          _one_of(*ROBOT_MODEL_TYPES), "one of " + ", ".join(ROBOT_MODEL_TYPES)),
    Param("motion_a_trans", 0.05, "along-track noise std (m) per square root of a metre travelled (m/sqrt(m)): "
          "variance grows by motion_a_trans^2 per metre", _non_negative, ">= 0"),
    Param("motion_a_lateral", 0.04, "across-track noise std (m) per square root of a metre travelled (m/sqrt(m))",
          _non_negative, ">= 0"),
    Param("motion_a_rot", 0.1, "heading noise std (rad) per square root of a radian turned (rad/sqrt(rad))",
          _non_negative, ">= 0"),
    Param("motion_a_rot_to_trans", 0.02, "position noise std (m, along and across) per square root of a radian "
          "turned (m/sqrt(rad))", _non_negative, ">= 0"),
    Param("motion_a_trans_to_rot", 0.05, "heading noise std (rad) per square root of a metre travelled "
          "(rad/sqrt(m))", _non_negative, ">= 0"),
    Param("motion_floor_xy", 0.02, "position noise std (m, along and across) per square root of the motion "
          "(metres travelled + radians turned)", _non_negative, ">= 0"),
    Param("motion_floor_theta", 0.02, "heading noise std (rad) per square root of the motion (metres travelled "
          "+ radians turned)", _non_negative, ">= 0"),
    # nav2_amcl's names: set (>= 0), each replaces the motion_* value it maps to, converted from nav2's
    # per-update variances (core/motion.py, nav2_alphas_to_noise); -1 = not set
    Param("alpha1", -1.0, "nav2_amcl: rotation noise from rotation; sets motion_a_rot = sqrt(alpha1 x 0.2 rad); "
          "-1: not set", _alpha, "-1 (not set) or >= 0"),
    Param("alpha2", -1.0, "nav2_amcl: rotation noise from translation; sets motion_a_trans_to_rot = sqrt(alpha2 x "
          "0.25 m), x2 inside for ackermann/differential (nav2 draws it twice per update); -1: not set", _alpha,
          "-1 (not set) or >= 0"),
    Param("alpha3", -1.0, "nav2_amcl: translation noise from translation; sets motion_a_trans = sqrt(alpha3 x 0.25 "
          "m); -1: not set", _alpha, "-1 (not set) or >= 0"),
    Param("alpha4", -1.0, "nav2_amcl: translation noise from rotation; sets motion_a_rot_to_trans = sqrt(alpha4 x "
          "0.2 rad); -1: not set", _alpha, "-1 (not set) or >= 0"),
    Param("alpha5", -1.0, "nav2_amcl: strafe noise from translation (omni only); sets motion_a_lateral = "
          "sqrt(alpha5 x 0.25 m); -1: not set", _alpha, "-1 (not set) or >= 0"),
    # --- sensor model
    Param("num_beams_per_particle", 100, "beams of each scan used by the sensor model",
          lambda v: isinstance(v, int) and 1 <= v <= 10000, "an integer in [1, 10000]"),
    Param("angle_step", 0, "take every angle_step-th beam of the scan, from the first (the course's downsampling "
          "stride: 11 gives 99 of a Hokuyo's 1081 beams); 0: num_beams_per_particle beams spread evenly over the scan",
          lambda v: isinstance(v, int) and 0 <= v <= 10000, "an integer in [0, 10000]"),
    Param("scan_field_of_view", 4.71, "field of view (rad) assumed when a scan carries no angles (the course's "
          "convention)", lambda v: _positive(v) and v <= 2 * math.pi + 1e-6, "in (0, 2 pi]"),
    Param("scan_theta_discretization", 144, "heading bins of the precomputed range table (lookup_table "
          "casters); 144 = 2.5 degrees. More bins: sharper wall edges far ahead, more memory (trade-off measured "
          "in docs/performance.md); lookup_table_exact removes the smearing at a higher update cost",
          lambda v: isinstance(v, int) and 8 <= v <= 2048, "an integer in [8, 2048]"),
    Param("lidar_scale_to_map_scale", 1.0, "scale from lidar metres to map metres", _positive, "> 0"),
    Param("map_wall_depth", 0.0, "how far (m) behind the map's free-space edge a lidar return ends on a wall: maps "
          "draw walls a few cells thick and the surface lies inside them. The beam model scores each return as "
          "s·z − map_wall_depth (s: lidar_scale_to_map_scale) against the ray cast to the edge; localization-calibrate "
          "estimates it (\"wall surface ... behind the free-space edge\")",
          lambda v: _finite(v) and 0.0 <= v <= 0.5, "in [0, 0.5]"),
    Param("range_scale_estimation", True, "beam model: learn the lidar-to-map range scale while the filter tracks "
          "(core/range_scale.py): after each sensor update of a converged cloud, the scale is fitted jointly with a "
          "small correction of the estimate over the beams within a few centimetres of the map, low-pass filtered "
          "(range_scale_alpha), kept within range_scale_bound of lidar_scale_to_map_scale (its start value), and "
          "replaces lidar_scale_to_map_scale. For a building a little larger or smaller than its map, or a lidar "
          "whose ranges read long or short; false: lidar_scale_to_map_scale as configured. The likelihood field "
          "does not use it",
          lambda v: isinstance(v, bool), "true or false"),
    Param("range_scale_alpha", 0.02, "range_scale_estimation: weight of each scan's ratio in the estimate (a time "
          "constant of 1 / range_scale_alpha sensor updates)", lambda v: _fraction(v) and v > 0, "in (0, 1]"),
    Param("range_scale_bound", 0.05, "range_scale_estimation: the estimate stays within lidar_scale_to_map_scale x "
          "(1 +- this)", lambda v: _finite(v) and 0.0 <= v <= 0.5, "in [0, 0.5]"),
    Param("laser_offset_x", 0.275, "laser position ahead of base_link (m); racecar: 0.275", _finite, "finite"),
    Param("laser_offset_y", 0.0, "laser position left of base_link (m)", _finite, "finite"),
    Param("laser_offset_yaw", 0.0, "laser yaw relative to base_link (rad)", _finite, "finite"),
    Param("alpha_hit", 0.74, "weight of the Gaussian hit component", _non_negative, ">= 0"),
    Param("alpha_short", 0.07, "weight of the short-reading component", _non_negative, ">= 0"),
    Param("alpha_max", 0.07, "weight of the max-range component", _non_negative, ">= 0"),
    Param("alpha_rand", 0.12, "weight of the uniform random component", _non_negative, ">= 0"),
    Param("sigma_hit", 0.2, "std (m) of the hit component (Gaussian around the expected range); before 2026-11 "
          "this was in map cells: give cells as sigma_hit_cells (converted with table_resolution)",
          lambda v: _positive(v) and v <= 1.0, "> 0 and <= 1 (metres)"),
    Param("squash_factor", 2.2, "likelihoods are raised to 1/squash_factor", _positive, "> 0"),
    Param("table_width", 201, "beam model table size in table cells (rows: measured range, columns: expected "
          "range, each column normalised); it covers ranges up to (table_width - 1) x table_resolution m, which "
          "also bounds z_max and the ray casts",
          lambda v: isinstance(v, int) and 2 <= v <= 4096, "an integer in [2, 4096]"),
    Param("table_resolution", 0.05, "beam model table cell (m): measured and expected ranges are binned to it "
          "(independent of the map's resolution)", lambda v: _positive(v) and v <= 1.0, "> 0 and <= 1"),
    Param("ray_caster", "lookup_table", "lookup_table (fast, cached on disk), lookup_table_exact (the table "
          "plus an exact finish per beam: slower, as accurate as exact), distance_transform or exact",
          _one_of("lookup_table", "lookup_table_exact", "distance_transform", "exact"),
          "lookup_table, lookup_table_exact, distance_transform or exact"),
    # --- node interface: nav2-style options, watchdogs and diagnostics, pose persistence
    Param("pose_topic", "/pf/pose", "geometry_msgs/PoseWithCovarianceStamped output of the estimate (as nav2_amcl's "
          "/amcl_pose), beside /pf/pose/odom", _topic, "a topic name"),
    Param("set_initial_pose", False, "start from initial_pose.x/.y/.yaw (as nav2_amcl) instead of waiting for "
          "/initialpose", lambda v: isinstance(v, bool), "true or false"),
    Param("initial_pose.x", 0.0, "initial pose x (m, map frame) used when set_initial_pose is true", _finite, "finite"),
    Param("initial_pose.y", 0.0, "initial pose y (m, map frame)", _finite, "finite"),
    Param("initial_pose.yaw", 0.0, "initial pose heading (rad, map frame)", _finite, "finite"),
    Param("base_frame", "base_link", "the robot's frame: the laser pose is looked up in TF as base_frame -> the "
          "scan's frame", _topic, "a frame id"),
    Param("laser_pose_from_tf", True, "read the laser pose from TF (base_frame -> scan frame, /tf_static or /tf) when "
          "available; laser_offset_* otherwise", lambda v: isinstance(v, bool), "true or false"),
    Param("odom_timeout", 0.5, "warn (on /diagnostics and in the log) when scans arrive but no odometry came for "
          "this long (s)", _positive, "> 0"),
    Param("scan_timeout", 0.5, "warn when odometry arrives but no scan came for this long (s)", _positive, "> 0"),
    Param("map_timeout", 5.0, "warn when no map has arrived this long (s) after the start", _positive, "> 0"),
    Param("tf_timeout", 1.0, "warn (and use laser_offset_*) when the laser pose is not in TF this long (s) after "
          "the first scan", _positive, "> 0"),
    Param("sensor_update_thread", False, "run the sensor update on its own thread (a short FIFO of scans) instead "
          "of in the scan callback: odometry poses keep flowing during an update, at the cost of a GIL hand-over "
          "per scan (see docs/node.md, Threading)", lambda v: isinstance(v, bool), "true or false"),
    Param("foxglove_port", -1, "serve a live view (map, scan, particles, estimate, TF) over the Foxglove WebSocket "
          "protocol on this port (needs foxglove-sdk); 0: any free port; -1: off",
          lambda v: isinstance(v, int) and -1 <= v <= 65535, "an integer in [-1, 65535]"),
    Param("foxglove_host", "127.0.0.1", "address the live view listens on (127.0.0.1: this machine only)",
          lambda v: isinstance(v, str) and len(v) > 0, "an address"),
    Param("diagnostics_period", 1.0, "period (s) of /diagnostics (diagnostic_msgs/DiagnosticArray)", _positive, "> 0"),
    Param("persist_pose", False, "write the estimate and its covariance to persist_pose_file every "
          "persist_pose_period s, and start from it when no initial pose is set", lambda v: isinstance(v, bool),
          "true or false"),
    Param("persist_pose_file", "", "file of the persisted pose; empty: last_pose.yaml in the cache directory "
          "($LOCALIZATION_CACHE_DIR or ~/.cache/localization)", lambda v: isinstance(v, str), "a path or empty"),
    Param("persist_pose_period", 3.0, "seconds between two writes of the persisted pose", _positive, "> 0"),
    # --- global localization in seconds and large maps: core/filter/global_init.py,
    # core/raycast/lookup_table.py (tiles built on demand)
    Param("global_init", "scan", "how a global spread (start, service, recovery) places its particles: scan "
          "(importance sampling of poses from the first scan over a coarse lattice, see global_seed_*) or uniform "
          "(uniform over the free space)", _one_of("scan", "uniform"), "scan or uniform"),
    Param("global_seed_step", 0.2, "global_init scan: lattice spacing (m) of the candidate positions", _positive,
          "> 0"),
    Param("global_seed_headings", 72, "global_init scan: candidate headings per lattice position",
          lambda v: isinstance(v, int) and 1 <= v <= 3600, "an integer in [1, 3600]"),
    Param("global_seed_beams", 30, "global_init scan: beams of the scan used to score the lattice",
          lambda v: isinstance(v, int) and 1 <= v <= 10000, "an integer in [1, 10000]"),
    Param("global_seed_candidates", 4000, "global_init scan: best lattice poses the particles are drawn around",
          lambda v: isinstance(v, int) and 1 <= v <= 10_000_000, "an integer in [1, 10000000]"),
    Param("global_seed_temperature", 4.0, "global_init scan: candidate weights exp(log-likelihood / this); larger "
          "keeps more look-alike places alive", _positive, "> 0"),
    Param("global_seed_uniform", 0.1, "global_init scan: fraction of the particles still spread uniformly",
          _fraction, "in [0, 1]"),
    Param("range_table_lazy_cells", 10_000_000, "maps with more cells than this build the lookup table tile by "
          "tile where particles are (memory grows with the area driven, not with the map); 0: always",
          lambda v: isinstance(v, int) and v >= 0, "an integer >= 0"),
    # --- likelihood-field sensor model and KLD-adaptive particle count:
    # core/sensors/likelihood_field.py, core/filter/kld.py (names as nav2_amcl's, lf_ where the beam model has one)
    Param("sensor_model", "beam", "beam (the course's beam model over ray-cast ranges) or likelihood_field (each "
          "beam's end point scored by its distance to the nearest occupied cell, as nav2_amcl's likelihood_field; "
          "docs/models.md says when to use which)", _one_of("beam", "likelihood_field"), "beam or likelihood_field"),
    Param("lf_z_hit", 0.5, "likelihood_field: weight of the Gaussian of the end point's distance to the nearest "
          "obstacle", _non_negative, ">= 0"),
    Param("lf_z_rand", 0.5, "likelihood_field: weight of the uniform density 1 / laser_max_range", _non_negative,
          ">= 0"),
    Param("lf_sigma_hit", 0.1, "likelihood_field: std (m) of that Gaussian (nav2's default 0.2 is worse on the "
          "Stata trials and the RSS 2022 bags, docs/models.md)", _positive, "> 0"),
    Param("laser_likelihood_max_dist", 2.0, "likelihood_field: distances to the nearest obstacle are capped at this "
          "(m); end points off the map count as this far", _positive, "> 0"),
    Param("laser_max_range", -1.0, "z_max, the range (m) of a reading with no return, for both sensor models: > 0: "
          "this value (the lidar's maximum range); <= 0: each scan's own range_max (as nav2_amcl's -1). The beam "
          "model scores readings at or beyond z_max, and NaN/inf ones, as max-range readings at z_max, clips "
          "expected ranges there and caps z_max at its table's reach (table_width - 1) x table_resolution; the "
          "likelihood field skips those beams and uses z_max in its uniform density lf_z_rand / z_max",
          _finite, "finite (<= 0: the scan's range_max)"),
    Param("do_beamskip", False, "leave out of each sensor update the beams that agree with the map for at most "
          "beam_skip_threshold of the particles (returns from things the map does not have: people, boxes, windows "
          "the beam passes through), as nav2_amcl; both sensor models", lambda v: isinstance(v, bool),
          "true or false"),
    Param("beam_skip_distance", 0.5, "do_beamskip: a beam agrees with the map for a particle when its end point lies "
          "closer than this (m) to an obstacle (likelihood_field), or its measured range lies within this of the "
          "range ray cast from the particle (beam model)", _positive, "> 0"),
    Param("beam_skip_threshold", 0.3, "do_beamskip: a beam is used when more than this fraction of the particles "
          "agree on it", _fraction, "in [0, 1]"),
    Param("beam_skip_error_threshold", 0.9, "do_beamskip: when this fraction of the beams would be skipped the "
          "cloud is off: all beams are used", _fraction, "in [0, 1]"),
    Param("beam_skip_max_spread", 1.0, "do_beamskip: beams are skipped only while the particles' position standard "
          "deviation (the larger of x and y, m) is at most this: a spread cloud may hold several hypotheses, and "
          "a beam only the right one explains would be skipped", _positive, "> 0"),
    Param("adaptive_particles", False, "KLD-adaptive particle count (Fox 2003, as nav2_amcl): every resampling draws "
          "as many particles as the cloud's spread over bins of kld_bin_xy x kld_bin_theta needs, in "
          "[min_particles, max_particles]; global localization and recovery start at max_particles. false: "
          "num_particles always", lambda v: isinstance(v, bool), "true or false"),
    Param("min_particles", 500, "adaptive_particles: fewest particles", lambda v: isinstance(v, int) and v >= 1,
          "an integer >= 1"),
    Param("max_particles", 40000, "adaptive_particles: most particles, and the count a global spread (start, "
          "service, recovery) keeps until it converges (as global_num_particles without adaptive_particles)",
          lambda v: isinstance(v, int) and 1 <= v <= 1_000_000, "an integer in [1, 1000000]"),
    Param("pf_err", 0.05, "adaptive_particles: KLD bound epsilon between the sampled and the true distribution",
          lambda v: _positive(v) and v < 1, "in (0, 1)"),
    Param("pf_z", 0.99, "adaptive_particles: upper standard normal quantile z_(1-delta) of the KLD bound (nav2_amcl's "
          "pf_z, used as the quantile value)", _positive, "> 0"),
    Param("kld_bin_xy", 0.5, "adaptive_particles: histogram bin size (m) in x and y", _positive, "> 0"),
    Param("kld_bin_theta", 0.17453292519943295, "adaptive_particles: histogram bin size (rad) in heading (10 deg)",
          _positive, "> 0"),
    # --- time-correct localization: odometry on the scan's clock, the scan stamp convention and scan deskew
    # (core/odometry.py OdometryBuffer, core/localizer.py, core/sensors/beam.py); values from localization-calibrate
    Param("align_odometry", True, "propagate the particles through the odometry history to each scan's own time "
          "(interpolating between messages, extrapolating the last twist; a swept scan: the middle of its sweep) and "
          "stamp the estimate with that time; false: each scan is used at the latest odometry",
          lambda v: isinstance(v, bool), "true or false"),
    Param("odom_time_offset", 0.0, "odometry clock vs scan clock (s): an odometry message stamped t describes the "
          "motion up to t + odom_time_offset (odometry reporting 40 ms late: -0.04)",
          lambda v: _finite(v) and abs(v) <= 1.0, "in [-1, 1]"),
    Param("scan_max_wait", 0.5, "a scan newer than the newest odometry waits this long (s, on the scan clock) for "
          "the odometry that covers its time (as a TF message filter); then it is used with the last twist "
          "extrapolated, with a warning. Must exceed how late the odometry arrives (-odom_time_offset plus its "
          "period)", lambda v: _positive(v) and v <= 10.0, "in (0, 10]"),
    Param("scan_queue_size", 20, "at most this many scans wait for odometry (the oldest leaves early, extrapolated, "
          "when more arrive)", lambda v: isinstance(v, int) and 1 <= v <= 1000, "an integer in [1, 1000]"),
    Param("update_every_n_scans", 0, "besides motion (update_min_distance / update_min_angle), every n-th scan "
          "updates the filter even when the robot stands; 0: only on motion", lambda v: isinstance(v, int) and v >= 0,
          "an integer >= 0"),
    Param("scan_stamp", "first_beam", "which beam a scan's header stamp describes: first_beam (the LaserScan "
          "definition; sick_scan) or last_beam (urg_node with calibrate_time false, rplidar_ros: the stamp is taken "
          "when the scan is complete); the scan's time is then the middle of its sweep (docs/timing.md; "
          "localization-calibrate checks it against the bag's record times)", _one_of("first_beam", "last_beam"),
          "first_beam or last_beam"),
    Param("scan_stamp_offset", 0.0, "s by which the header stamp is later than the beam scan_stamp names (a "
          "driver latency it did not subtract); the first beam's time is stamp - scan_stamp_offset (first_beam) "
          "or that minus the sweep (last_beam)", lambda v: _finite(v) and abs(v) <= 1.0, "in [-1, 1]"),
    Param("odom_speed_scale", 1.0, "speed used = odom_speed_scale x reported speed", _positive, "> 0"),
    Param("odom_yaw_rate_scale", 1.0, "yaw rate used = odom_yaw_rate_scale x reported yaw rate + odom_yaw_rate_bias",
          _positive, "> 0"),
    Param("odom_yaw_rate_bias", 0.0, "rad/s added to the scaled reported yaw rate", _finite, "finite"),
    Param("deskew", True, "when a scan has time_increment > 0 (a sweeping lidar), cast each beam from the laser pose "
          "at its own time, moved by the odometry twist over the sweep (beam sensor model)",
          lambda v: isinstance(v, bool), "true or false"),
]

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
