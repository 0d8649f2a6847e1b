"""Monte Carlo Localization for car-like robots in a known 2D map.

The numpy core (``geometry``, ``occupancy_map``, ``ray_casting``, ``motion_model``,
``sensor_model``, ``scan``, ``mcl``, ``localizer``) never imports rclpy: the ROS node, the
replay tool, the simulator, the benchmarks and the tests all drive the very same code.
"""

__version__ = "0.1.0"
