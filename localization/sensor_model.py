"""Beam sensor model over ray-cast expected scans.

For one beam with measured range z and expected (ray-cast) range d, both in map cells:

    p(z | d) = α_hit·p_hit + α_short·p_short + α_max·p_max + α_rand·p_rand

    p_hit   = N(z; d, σ_hit²), normalised over z for each d (before mixing)
    p_short = 2/d · (1 − z/d)  for 0 ≤ z ≤ d, d ≠ 0; else 0
    p_max   = 1  at z = z_max (one cell wide); else 0
    p_rand  = 1 / z_max

The mix is tabulated once in ``sensor_model_table`` (rows z, columns d, ``table_width`` each,
z_max = table_width − 1) and every column normalised to sum to 1. A scan's likelihood is the
product over beams, computed as a sum of logs so 100 beams never underflow, then "squashed":

    w = (Π_b p(z_b | d_b)) ^ (1 / squash_factor)

Particles off the map or in an occupied cell get weight 0 (log weight −inf).
"""
from __future__ import annotations

import numpy as np

from .geometry import compose
from .occupancy_map import OccupancyMap
from .ray_casting import DistanceTransformRayCaster, ExactRayCaster


class SensorModel:
    def __init__(self, alpha_hit=0.74, alpha_short=0.07, alpha_max=0.07, alpha_rand=0.12, sigma_hit=8.0,
                 table_width=201, squash_factor=2.2, num_beams_per_particle=100, scan_field_of_view=4.71,
                 lidar_scale_to_map_scale=1.0, laser_offset=(0.0, 0.0, 0.0), ray_caster="distance_transform",
                 occupancy_map: OccupancyMap | None = None, scan_theta_discretization=144):
        self.alpha_hit = float(alpha_hit)
        self.alpha_short = float(alpha_short)
        self.alpha_max = float(alpha_max)
        self.alpha_rand = float(alpha_rand)
        self.sigma_hit = float(sigma_hit)
        self.table_width = int(table_width)
        self.squash_factor = float(squash_factor)
        self.num_beams_per_particle = int(num_beams_per_particle)
        self.scan_field_of_view = float(scan_field_of_view)
        self.lidar_scale_to_map_scale = float(lidar_scale_to_map_scale)
        self.laser_offset = np.asarray(laser_offset, dtype=float).reshape(3)
        self.ray_caster_kind = ray_caster
        self.scan_theta_discretization = int(scan_theta_discretization)  # heading bins of the lookup table
        self.fast_likelihood = True  # use a caster's fused log_likelihood_sums kernel when it has one
        self.map: OccupancyMap | None = None
        self.ray_caster = None
        self.sensor_model_table = None
        self.precompute_sensor_model()
        if occupancy_map is not None:
            self.set_map(occupancy_map)

    # ------------------------------------------------------------------ the table
    @property
    def z_max(self) -> int:
        return self.table_width - 1

    def precompute_sensor_model(self) -> np.ndarray:
        """(Re)build ``sensor_model_table`` from the current alphas, sigma_hit and table_width."""
        n, z_max = self.table_width, self.table_width - 1
        if n < 2:
            raise ValueError(f"table_width must be at least 2, got {n}")
        z = np.arange(n, dtype=float)[:, None]  # rows: measured range
        d = np.arange(n, dtype=float)[None, :]  # columns: expected range

        p_hit = np.exp(-0.5 * ((z - d) / self.sigma_hit) ** 2) / np.sqrt(2.0 * np.pi * self.sigma_hit ** 2)
        p_hit = p_hit / p_hit.sum(axis=0, keepdims=True)
        with np.errstate(divide="ignore", invalid="ignore"):
            p_short = np.where((z <= d) & (d > 0), 2.0 / d * (1.0 - z / d), 0.0)
        p_max = np.where(z == z_max, 1.0, 0.0) * np.ones_like(d)
        p_rand = np.full((n, n), 1.0 / z_max)

        table = (self.alpha_hit * p_hit + self.alpha_short * p_short
                 + self.alpha_max * p_max + self.alpha_rand * p_rand)
        column_sums = table.sum(axis=0, keepdims=True)
        if not np.any(column_sums > 0):
            raise ValueError("sensor model alphas are all zero; at least one must be > 0")
        # A column can only sum to 0 when p_short is the sole component (d = 0): it stays 0.
        self.sensor_model_table = np.divide(table, column_sums, out=np.zeros_like(table), where=column_sums > 0)
        with np.errstate(divide="ignore"):
            self._log_table = np.log(self.sensor_model_table)
        return self.sensor_model_table

    # ------------------------------------------------------------------ the map
    @property
    def cells_per_metre(self) -> float:
        return 1.0 / (self.map.resolution * self.lidar_scale_to_map_scale)

    @property
    def max_range(self) -> float:
        """The range (metres) of z_max: rays are cast no further."""
        return self.z_max * self.map.resolution * self.lidar_scale_to_map_scale

    def set_map(self, occupancy_map: OccupancyMap, ray_caster=None) -> None:
        """Use a (new) map: builds its ray caster. ``ray_caster`` may be a ready caster."""
        self.map = occupancy_map
        if ray_caster is not None and not isinstance(ray_caster, str):
            self.ray_caster = ray_caster
            return
        kind = ray_caster or self.ray_caster_kind
        if kind == "exact":
            self.ray_caster = ExactRayCaster(occupancy_map, self.max_range)
        elif kind == "distance_transform":
            self.ray_caster = DistanceTransformRayCaster(occupancy_map, self.max_range)
        elif kind in ("lookup_table", "lookup_table_exact"):  # _exact: the table plus an exact finish per beam
            from .range_table import LookupTableRayCaster
            self.ray_caster = LookupTableRayCaster.for_map(occupancy_map, self.max_range,
                                                           theta_bins=self.scan_theta_discretization,
                                                           refine=1.0 if kind == "lookup_table_exact" else 0.0)
        else:
            raise ValueError(f"unknown ray caster {kind!r} (lookup_table, lookup_table_exact, distance_transform "
                             "or exact)")

    # ------------------------------------------------------------------ evaluation
    def default_angles(self, num_beams: int) -> np.ndarray:
        """The course convention: beams evenly over ``scan_field_of_view`` centred on the heading."""
        half = 0.5 * self.scan_field_of_view
        return np.linspace(-half, half, num_beams)

    def expected_ranges(self, particles, angles) -> np.ndarray:
        """Ray-cast ranges (metres), (N, B), from each particle's laser pose."""
        sensor = compose(np.atleast_2d(particles), self.laser_offset) if self.laser_offset.any() else particles
        return self.ray_caster.cast(sensor, angles)

    def to_cells(self, ranges_m) -> np.ndarray:
        """Metres -> integer table indices in [0, z_max]; NaN/inf count as z_max."""
        cells = np.asarray(ranges_m, dtype=float) * self.cells_per_metre
        cells = np.where(np.isnan(cells), self.z_max, cells)
        return np.rint(np.clip(cells, 0, self.z_max)).astype(np.intp)

    def log_likelihood(self, particles, observation, angles=None) -> np.ndarray:
        """Squashed log weights (N,): sum over beams of log p(z|d), divided by squash_factor;
        −inf for particles off the map or in an occupied cell."""
        if self.map is None:
            raise RuntimeError("SensorModel has no map yet: call set_map() first")
        particles = np.atleast_2d(np.asarray(particles, dtype=float))
        observation = np.asarray(observation, dtype=float).ravel()
        if angles is None:
            angles = self.default_angles(observation.size)
        z = self.to_cells(observation)
        fused = getattr(self.ray_caster, "log_likelihood_sums", None) if self.fast_likelihood else None
        if fused is not None:  # lookup table: one compiled pass, no (N, B) temporaries; same result
            return fused(particles, angles, self._log_table[z], self.cells_per_metre, self.squash_factor,
                         self.laser_offset)
        d = self.to_cells(self.expected_ranges(particles, angles))
        log_w = self._log_table[z[None, :], d].sum(axis=1) / self.squash_factor
        impossible = self.map.is_occupied_or_outside(particles[:, :2])
        log_w[impossible] = -np.inf
        return log_w

    def evaluate(self, particles, observation, angles=None) -> np.ndarray:
        """Weights (N,): Π_b p(z_b | d_b) ^ (1/squash_factor). Never NaN; 0 where impossible."""
        with np.errstate(under="ignore"):
            return np.exp(self.log_likelihood(particles, observation, angles))
