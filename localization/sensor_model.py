"""The course's ``SensorModel``: ``from localization.sensor_model import SensorModel``.

The MIT RSS course's interface, in the course's units, over the project's beam model
(``localization.core.sensors.beam.BeamModel``, which works in metres):

- ``SensorModel(node)`` declares and reads the course's parameters from the node (``map_topic``,
  ``num_beams_per_particle``, ``scan_theta_discretization``, ``scan_field_of_view``,
  ``lidar_scale_to_map_scale``) and subscribes to the map, as the skeleton does; its ranges come from
  the course's ray caster (``ray_caster="scan_simulator"``: racecar_simulator's ``ScanSimulator2D``,
  ``core/raycast/scan_simulator.py``), so ``evaluate`` gives the staff solution's probabilities.
  ``SensorModel()`` (no node) takes the same names as keyword arguments and the project's lookup-table
  caster unless ``ray_caster`` says otherwise.
- The course's attributes: ``alpha_hit``, ``alpha_short``, ``alpha_max``, ``alpha_rand``,
  ``sigma_hit`` (in table cells: 8.0), ``table_width`` (201), ``squash_factor`` (2.2),
  ``sensor_model_table`` (rows measured, columns expected range, columns normalised), ``map`` (the
  grid as the course keeps it: ``clip(data / 100, 0, 1)``, flat), ``map_set``, ``resolution``.
- ``precompute_sensor_model()`` rebuilds the table from the attributes; ``map_callback(msg)`` takes a
  ``nav_msgs/OccupancyGrid``; ``evaluate(particles, observation)`` returns (N,) probabilities
  ``Π_b p(z_b | d_b) ^ (1 / squash_factor)`` (None before a map), both ranges binned in map cells.

A table cell is one map cell (the course's binning, ``rint(r / resolution)``); the engine gets
σ_hit = ``sigma_hit`` × resolution metres and table cells of ``resolution`` metres.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from localization.core.models.beam import BeamModel, BeamModelParams, beam_mixture_table
from localization.core.occupancy_map import OccupancyMap
from localization.core.parameters import default

#: The course's parameters read from a node, with the course's values where the node has none.
COURSE_NODE_PARAMETERS = {
    "map_topic": "/map",
    "num_beams_per_particle": 100,
    "scan_theta_discretization": 500,
    "scan_field_of_view": 4.71,
    "lidar_scale_to_map_scale": 1.0,
}
_TYPES = {"map_topic": str, "num_beams_per_particle": int, "scan_theta_discretization": int,
          "scan_field_of_view": float, "lidar_scale_to_map_scale": float}


class SensorModel:
    """The course's sensor model (module docstring)."""

    def __init__(self, node=None, ray_caster: str | None = None, **parameters):
        values = dict(COURSE_NODE_PARAMETERS)
        if node is not None:
            from localization.ros.course_parameters import course_parameter
            values.update({name: course_parameter(node, name, value) for name, value in values.items()})
        unknown = set(parameters) - set(values)
        if unknown:
            raise TypeError(f"unknown SensorModel parameter(s): {sorted(unknown)}")
        values.update(parameters)
        for name, value in values.items():
            setattr(self, name, _TYPES[name](value))
        self.ray_caster = ray_caster or ("scan_simulator" if node is not None else default("ray_caster"))

        self.alpha_hit = default("alpha_hit", course=True)
        self.alpha_short = default("alpha_short", course=True)
        self.alpha_max = default("alpha_max", course=True)
        self.alpha_rand = default("alpha_rand", course=True)
        self.sigma_hit = default("sigma_hit", course=True) / default("table_resolution", course=True)  # cells
        self.table_width = default("table_width", course=True)
        self.squash_factor = default("squash_factor", course=True)

        self.map = None
        self.map_set = False
        self.resolution = None
        self.occupancy_map: OccupancyMap | None = None
        self._engine: BeamModel | None = None
        self.sensor_model_table = np.empty((self.table_width, self.table_width))
        self.precompute_sensor_model()

        if node is not None:
            from nav_msgs.msg import OccupancyGrid
            self.map_subscriber = node.create_subscription(OccupancyGrid, self.map_topic, self.map_callback, 1)

    # ------------------------------------------------------------------ the course's methods
    def precompute_sensor_model(self) -> None:
        """``sensor_model_table`` from the alphas, ``sigma_hit`` (cells) and ``table_width``."""
        cells = replace(self._engine_params(), table_resolution=1.0, sigma_hit=float(self.sigma_hit))
        self.sensor_model_table = beam_mixture_table(cells, self.table_width - 1)
        if self.occupancy_map is not None:
            self._use_engine()

    def evaluate(self, particles, observation):
        """(N,) probabilities of the particles (N, 3) given the measured ranges ``observation`` (B,),
        beams evenly over ``scan_field_of_view``; None before a map."""
        if not self.map_set:
            return None
        engine = self._engine
        particles = np.atleast_2d(np.asarray(particles, dtype=float))
        observation = np.asarray(observation, dtype=float).ravel()
        k = engine.z_max
        expected = engine.to_cells(engine.expected_ranges(particles, engine.default_angles(observation.size)), k)
        measured = engine.measured_to_cells(observation, k)
        with np.errstate(under="ignore"):  # a particle in a wall is scored like any other, as the course does
            return np.exp(engine.log_table(k)[measured[None, :], expected].sum(axis=1) / engine.params.squash_factor)

    def map_callback(self, map_msg) -> None:
        """Use a ``nav_msgs/OccupancyGrid``; ``map`` keeps it as the course does."""
        self.set_map(OccupancyMap.from_msg(map_msg))

    # ------------------------------------------------------------------ without ROS
    def set_map(self, occupancy_map: OccupancyMap) -> None:
        """Use a map (what ``map_callback`` does with a message)."""
        self.map = np.clip(occupancy_map.data.ravel().astype(np.double) / 100.0, 0.0, 1.0)
        self.resolution = occupancy_map.resolution
        self.occupancy_map = occupancy_map
        self._engine = None
        self._use_engine()
        self.map_set = True

    def _use_engine(self) -> None:
        """The engine for the current values; its ray caster kept while the map and its reach are the same."""
        engine = BeamModel(self._engine_params())
        caster = self._engine.ray_caster if self._engine is not None else None
        reusable = caster is not None and caster.max_range == engine.table_range
        engine.set_map(self.occupancy_map, caster if reusable else None)
        self._engine = engine

    def _engine_params(self) -> BeamModelParams:
        """The engine's parameters: the course's values in metres, table cells of the map's resolution."""
        resolution = self.resolution or default("table_resolution", course=True)
        return BeamModelParams(
            alpha_hit=float(self.alpha_hit), alpha_short=float(self.alpha_short), alpha_max=float(self.alpha_max),
            alpha_rand=float(self.alpha_rand), sigma_hit=float(self.sigma_hit) * resolution,
            table_width=int(self.table_width), table_resolution=resolution, laser_max_range=0.0,
            squash_factor=float(self.squash_factor), num_beams_per_particle=self.num_beams_per_particle,
            scan_field_of_view=self.scan_field_of_view, lidar_scale_to_map_scale=self.lidar_scale_to_map_scale,
            map_wall_depth=0.0, laser_offset_x=0.0, laser_offset_y=0.0, laser_offset_yaw=0.0,
            ray_caster=self.ray_caster, scan_theta_discretization=self.scan_theta_discretization,
            do_beamskip=False)


__all__ = ["SensorModel"]
