"""Monte Carlo Localization for car-like robots in a known 2D map (ROS 2 Jazzy).

Layers, lowest first (a module imports only from its own or lower layers):

- ``core/``: the ROS-free filter (numpy/numba);
- ``ros/`` (the node and its adapters) and ``bags/`` (rosbags IO);
- ``sim/``: the simulator;
- ``eval/``: data sets, the message-feeding loop, replay, metrics, plots;
- ``tools/`` (console scripts) and ``benchmarks/``.

``motion_model``, ``sensor_model``, ``occupancy_map`` and ``particle_filter`` keep the course's
module names as thin facades. This file imports nothing heavy.
"""

__version__ = "0.1.0"
