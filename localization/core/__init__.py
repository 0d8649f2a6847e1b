"""The ROS-free core: numpy/numba only, no rclpy, no message packages, no bag library.

Lowest first: ``paths``, ``geometry``, ``parameters``, ``occupancy_map``, ``scan``, ``odometry``,
``raycast/`` (exact, distance transform, lookup table and its kernels and cache), ``sensors/``
(the sensor-model protocol and the beam model), ``motion``, ``filter/`` (MCL, resampling),
``health``, ``localizer`` (the message stream -> estimates).
"""
