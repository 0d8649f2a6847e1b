"""``localization-replay``: run the localizer over a recorded bag as fast as the CPU allows.

Usage::

    localization-replay BAG --map MAP.yaml [--params FILE] [--out DIR] [--initial-pose X,Y,YAW]
                        [--global] [--seed N] [--scan-topic T] [--odom-topic T] [--truth-topic T]
                        [--particles N] [-p NAME=VALUE ...] [--no-plots] [--progress/--no-progress]

``BAG``: a rosbag2 directory (sqlite3 or MCAP), a bare ``.db3`` / ``.mcap`` file, or a ROS 1
``.bag``. Every scan, odometry and initial-pose message goes, in bag-time order, through exactly
what the node does with it: the duck-typed converters of ``localization.conversions`` and the
``Localizer`` (``on_odometry``, ``on_scan``, ``set_initial_pose``), fed by the one loop the tuner
and the benchmarks use too (``localization.eval.feed``). Stamps come from the messages, so the
result does not depend on how fast the replay runs.

Initial pose: ``--initial-pose``, else every ``/initialpose`` message of the bag (as the node
would receive it), else global localization (``--global`` forces it).

Ground truth (optional): TF ``map -> base_link`` on ``/tf`` (what ``localization-simulate``
records, like the racecar simulator), or ``--truth-topic`` carrying nav_msgs/Odometry,
geometry_msgs/PoseStamped, PoseWithCovarianceStamped or tf2_msgs/TFMessage. A simulated bag's /tf is
the truth in the map frame (``localization.sim.perturb``: q = c + (p − c) / s, what the map shows where
the car is); a bag drawn from a perturbed world also carries the world-frame truth on ``/truth/world``,
scored as the second figure ``world_ct_error_m``.

Outputs in ``--out`` (default: a new ``replay-<bag>-<time>`` folder in the current directory):

- ``poses.csv``: ``t,x,y,theta``, one row per estimate the node would publish: the pose carried to
  each odometry message's time, and a sensor-corrected estimate when it is newer than the row
  before (t, scan clock, never goes backwards);
- ``corrections.csv``: ``t,x,y,theta``, every sensor-corrected estimate at its scan's time;
- ``metrics.json``: CT error statistics, heading error, time to converge and false recoveries
  (``metrics.false_recoveries``) (with truth; ``world_ct_error_m`` against the world-frame truth),
  scan–map agreement, update timing, effective update rate (see ``localization.metrics``);
- ``agreement.csv`` (and ``errors.csv`` with truth): the time series behind the figures (agreement
  of the estimate at each scan's time, t = that time on the scan clock, ``localization.eval.feed``);
- ``trajectory.png`` (map, truth, estimate) and ``error.png`` (errors and agreement vs time);
- with a reference track (``--reference``; by default when the bag has no ground truth): the
  estimate at each scan's time scored against every scan matched to the map
  (``localization.eval.reference``; ``published_*``: the poses as published, interpolated):
  ``reference_error_m``, ``along_track_error_m``, ``cross_track_error_m``, ``best_lag_s`` ... in
  metrics.json, and ``reference.png`` (along/cross-track error vs time).

Exit status: 0 success; 1 when the bag, map, parameters or a topic are missing or unusable
(one line ``localization-replay: error: ...`` on stderr); 2 bad command-line arguments.
"""
from localization.eval.replay.outputs import (
    compute_metrics,
    jump_text,
    partition_text,
    published_errors,
    summary_table,
    unscored_reason,
    write_outputs,
)
from localization.eval.replay.run import (
    LASER_SCAN,
    ODOMETRY,
    POSE_COV,
    POSE_STAMPED,
    PROG,
    TF_MESSAGE,
    TRUTH_TYPES,
    ReplayError,
    ReplayOptions,
    ReplayResult,
    bag_events,
    bag_label,
    check_topics,
    default_out_dir,
    laser_mount_params,
    load_map,
    run_replay,
    tf_odometry,
)

__all__ = ["LASER_SCAN", "ODOMETRY", "POSE_COV", "POSE_STAMPED", "PROG", "TF_MESSAGE", "TRUTH_TYPES", "ReplayError",
           "ReplayOptions", "ReplayResult", "bag_events", "bag_label", "check_topics", "compute_metrics",
           "default_out_dir", "jump_text", "laser_mount_params", "load_map", "partition_text", "published_errors",
           "run_replay", "summary_table", "tf_odometry", "unscored_reason", "write_outputs"]
