"""A 2D MIT RACECAR simulator that records rosbag2 bags (``localization-simulate``).

The simulated car drives a route through a map_server map and everything it "publishes" is
written to a rosbag2 bag (sqlite3 or MCAP, with ``rosbags``) that ``ros2 bag play`` and
``localization-replay`` can play:

============== ================================ ===========================================
topic          type                             what
============== ================================ ===========================================
/scan          sensor_msgs/msg/LaserScan        Hokuyo-like lidar, 1081 beams over 270°, 40 Hz
/odom          nav_msgs/msg/Odometry            odom -> base_link at 50 Hz: (noisy) twist and
                                                the pose integrated from it
/tf            tf2_msgs/msg/TFMessage           ground truth map -> base_link, stamped like
                                                every /scan and /odom message
/tf_static     tf2_msgs/msg/TFMessage           base_link -> laser (latched)
/initialpose   geometry_msgs/msg/                optional: the true start pose plus an offset
               PoseWithCovarianceStamped
============== ================================ ===========================================

The pieces, each next to its math (PythonRobotics style):

1. ``CarModel``: Ackermann (kinematic bicycle) model about the rear axle centre (= base_link);
   or ``DiffDriveModel``: a differential-drive base about its wheel axle centre.
2. ``RouteFollower``: pure pursuit along a waypoint route, speed reduced in turns; the
   differential base's ``TurnAndDriveFollower``: turns on the spot, straight legs.
3. ``simulate_trajectory``: the physics loop at 200 Hz (controls constant within a step).
4. ``Lidar``: exact ray casting in the map + Gaussian range noise.
5. ``odometry_from_trajectory``: twist averaged over each odometry period, noise and bias added,
   odometry pose integrated from the reported twist (as a wheel-odometry driver would); the
   differential base's from its wheel encoders (``wheel_odometry``: ticks, wheel slip).
6. ``write_bag``: messages built with ``localization.bags`` and written in time order.

Everything is deterministic given ``SimConfig.seed``. The trajectory does not depend on the
sensors (the controller follows waypoints, it does not look at the lidar), so the scans are ray
cast afterwards, many at once.

A "kidnapping" (``kidnap_at`` / ``kidnap_to``) teleports the car mid-run: the ground truth
jumps, the odometry does not notice (a teleport is not motion), and the controller continues
along the route from the point nearest to the new pose.
"""
from __future__ import annotations

from localization.sim.config import (
    DIFFERENTIAL_ROUTE,
    DIFFERENTIAL_START,
    PHYSICS_RATE_HZ,
    SENSOR_START_DELAY_NS,
    T0_NS,
    SimConfig,
    SimulationError,
    differential_trial,
)
from localization.sim.perturb import MapPerturbation, perturb_map
from localization.sim.recorder import Recording, code_version, record, simulate, write_bag
from localization.sim.sensors import Lidar, OdometryStream, odometry_from_trajectory, wheel_odometry
from localization.sim.trajectory import Trajectory, clearance_at, clearance_grid, simulate_trajectory
from localization.sim.vehicle import CarModel, DiffDriveModel, RouteFollower, TurnAndDriveFollower, densify

__all__ = ["DIFFERENTIAL_ROUTE", "DIFFERENTIAL_START", "PHYSICS_RATE_HZ", "SENSOR_START_DELAY_NS", "T0_NS",
           "CarModel", "DiffDriveModel", "Lidar", "MapPerturbation", "OdometryStream", "Recording", "RouteFollower",
           "SimConfig", "SimulationError", "Trajectory", "TurnAndDriveFollower", "clearance_at", "clearance_grid",
           "code_version", "densify", "differential_trial", "odometry_from_trajectory", "perturb_map", "record",
           "simulate", "simulate_trajectory", "wheel_odometry", "write_bag"]
