"""Beam sensor model over ray-cast expected scans.

For one beam with measured range z and expected (ray-cast) range d, both in map cells:

    p(z | d) = α_hit·p_hit + α_short·p_short + α_max·p_max + α_rand·p_rand

    p_hit   = N(z; d, σ_hit²), normalised over z for each d (before mixing)
    p_short = 2/d · (1 − z/d)  for 0 ≤ z ≤ d, d ≠ 0; else 0
    p_max   = 1  at z = z_max (one cell wide); else 0
    p_rand  = 1 / z_max

The mix is tabulated once (``sensor_model_table``: rows z, columns d, ``table_width`` each,
z_max = table_width − 1) and every column normalised to sum to 1. A scan's likelihood is the
product over beams, computed as a sum of logs so 100 beams never underflow, then "squashed":

    log w = (Σ_b log p(z_b | d_b)) / squash_factor

Particles off the map or in an occupied cell get log weight −inf.

Units: expected ranges are cast in map metres; measured ranges are lidar metres and become map
metres times ``lidar_scale_to_map_scale`` (1 for a lidar and map that agree; the course's code
divided both ranges by it, which only re-binned the table — here it is the correction
``localization-calibrate`` estimates). Both are then binned at the map resolution.

With the lookup-table caster (the default) one compiled pass per particle does it all — laser
pose, table row, interpolated range, table index, log sum — with no (N, B) temporaries
(``_fused_kernel``); ``log_likelihood_numpy`` is its numpy reference, asserted equal in the tests.

Deskew (a sweeping lidar): beam b is measured from the laser pose L_b = L ⊕ δ_b, where L is the
laser pose at the scan's reference time and δ_b = (dx_b, dy_b, dθ_b) the laser's own motion until
beam b's time, in the laser frame (the same for every particle: ``offsets``). Each beam is cast
from its own origin: dθ_b turns the beam, and (dx_b, dy_b) (a few cm) is added to the laser's
offset (u, v) from its table cell's centre, which the table query already handles (the wall line
through the two bins' hit points, ``raycast.kernels.beam_ranges``) — no extra ray casting.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import numpy as np

from localization.core.geometry import compose
from localization.core.occupancy_map import OccupancyMap
from localization.core.parameters import default
from localization.core.raycast import LookupTableRayCaster, RayCaster, make_ray_caster
from localization.core.raycast.kernels import C_REFINE, HAVE_NUMBA

if HAVE_NUMBA:
    from numba import njit

    from localization.core.raycast.kernels import beam_ranges, locate, refine


@dataclass(frozen=True)
class BeamModelParams:
    """The beam model's parameters; names and meanings as in the parameter table
    (``localization.core.parameters``), defaults the course's (``course=True``)."""

    alpha_hit: float = default("alpha_hit", course=True)
    alpha_short: float = default("alpha_short", course=True)
    alpha_max: float = default("alpha_max", course=True)
    alpha_rand: float = default("alpha_rand", course=True)
    sigma_hit: float = default("sigma_hit", course=True)  # cells
    table_width: int = default("table_width", course=True)  # cells: z_max = table_width - 1
    squash_factor: float = default("squash_factor", course=True)
    num_beams_per_particle: int = default("num_beams_per_particle", course=True)
    scan_field_of_view: float = default("scan_field_of_view", course=True)  # rad
    lidar_scale_to_map_scale: float = default("lidar_scale_to_map_scale", course=True)
    laser_offset_x: float = default("laser_offset_x", course=True)  # m, in base_link
    laser_offset_y: float = default("laser_offset_y", course=True)  # m
    laser_offset_yaw: float = default("laser_offset_yaw", course=True)  # rad
    ray_caster: str = default("ray_caster", course=True)
    scan_theta_discretization: int = default("scan_theta_discretization", course=True)
    range_table_lazy_cells: int = default("range_table_lazy_cells", course=True)  # larger maps: table per tile

    @classmethod
    def from_parameters(cls, params) -> "BeamModelParams":
        """From a ``Parameters`` mapping (the node's, replay's): same names."""
        return cls(**{f.name: params[f.name] for f in fields(cls)})


class BeamModel:
    """The beam model (the course's ``SensorModel``). ``BeamModel(**overrides)`` or
    ``BeamModel(params)``; ``laser_offset=(x, y, yaw)`` is accepted for the three offsets."""

    supports_deskew = True  # log_likelihood takes per-beam laser offsets (a deskewed sweep)

    def __init__(self, params: BeamModelParams | None = None, *, occupancy_map: OccupancyMap | None = None,
                 laser_offset=None, **overrides):
        if laser_offset is not None:
            ox, oy, oyaw = (float(v) for v in laser_offset)
            overrides.update(laser_offset_x=ox, laser_offset_y=oy, laser_offset_yaw=oyaw)
        self.params = replace(params or BeamModelParams(), **overrides)
        for f in fields(self.params):  # the course's attribute names: self.alpha_hit, self.sigma_hit, ...
            setattr(self, f.name, getattr(self.params, f.name))
        self.laser_offset = np.array([self.laser_offset_x, self.laser_offset_y, self.laser_offset_yaw], dtype=float)
        self.ray_caster_kind = self.params.ray_caster
        self.map: OccupancyMap | None = None
        self.ray_caster: RayCaster | None = None
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
        """Map cells per map metre (expected ranges are cast in map metres)."""
        return 1.0 / self.map.resolution

    @property
    def max_range(self) -> float:
        """The range (map metres) of z_max: rays are cast no further."""
        return self.max_range_in(self.map)

    def max_range_in(self, occupancy_map: OccupancyMap) -> float:
        """``max_range`` on ``occupancy_map`` (z_max cells of it)."""
        return self.z_max * occupancy_map.resolution

    def measured_to_cells(self, ranges) -> np.ndarray:
        """Measured ranges (lidar metres) -> table rows: lidar_scale_to_map_scale turns lidar metres
        into map metres (the correction ``localization-calibrate`` estimates)."""
        return self.to_cells(np.asarray(ranges, dtype=float) * self.lidar_scale_to_map_scale)

    def prepare(self, occupancy_map: OccupancyMap, kind: str | None = None) -> RayCaster:
        """The ray caster (``kind``, default ``ray_caster``) of a map: the slow part of ``set_map`` (a
        range table built or loaded), without touching the model, so a caller may make it on another
        thread and then call ``set_map(occupancy_map, caster)``."""
        return make_ray_caster(kind or self.ray_caster_kind, occupancy_map, self.max_range_in(occupancy_map),
                               self.scan_theta_discretization, self.range_table_lazy_cells)

    def set_map(self, occupancy_map: OccupancyMap, ray_caster=None) -> None:
        """Use a (new) map: builds its ray caster (``ray_caster``: a ready caster from ``prepare``, or
        a caster name)."""
        self.map = occupancy_map
        if ray_caster is None or isinstance(ray_caster, str):
            ray_caster = self.prepare(occupancy_map, ray_caster)
        self.ray_caster = ray_caster
        if self._fused:  # compile (or load from numba's cache) now, not on the first scan
            self.log_likelihood(np.zeros((1, 3)), np.zeros(1), np.zeros(1))

    @property
    def _fused(self) -> bool:
        return isinstance(self.ray_caster, LookupTableRayCaster) and self.ray_caster.use_numba

    # ------------------------------------------------------------------ evaluation
    def default_angles(self, num_beams: int) -> np.ndarray:
        """The course convention: beams evenly over ``scan_field_of_view`` centred on the heading."""
        half = 0.5 * self.scan_field_of_view
        return np.linspace(-half, half, num_beams)

    def expected_ranges(self, particles, angles, offsets=None) -> np.ndarray:
        """Ray-cast ranges (metres), (N, B), from each particle's laser pose (``offsets`` (B, 3):
        each beam cast from the laser pose ⊕ its offset, see the module docstring)."""
        sensor = compose(np.atleast_2d(particles), self.laser_offset) if self.laser_offset.any() else particles
        if offsets is None:
            return self.ray_caster.cast(sensor, angles)
        offsets = np.asarray(offsets, dtype=float).reshape(-1, 3)
        angles = np.asarray(angles, dtype=float).ravel() + offsets[:, 2]
        if isinstance(self.ray_caster, LookupTableRayCaster):  # as the fused kernel: offsets folded into (u, v)
            return self.ray_caster.cast_numpy(sensor, angles, offsets[:, :2])
        origins = compose(np.atleast_2d(sensor)[:, None, :],
                          np.column_stack([offsets[:, :2], np.zeros(len(offsets))])[None])
        return self.ray_caster.cast_rays(origins.reshape(-1, 3), np.tile(angles, len(origins))).reshape(
            len(origins), -1)

    def to_cells(self, ranges_m) -> np.ndarray:
        """Metres -> integer table indices in [0, z_max]; NaN/inf count as z_max."""
        cells = np.asarray(ranges_m, dtype=float) * self.cells_per_metre
        cells = np.where(np.isnan(cells), self.z_max, cells)
        return np.rint(np.clip(cells, 0, self.z_max)).astype(np.intp)

    def _inputs(self, particles, observation, angles, offsets=None):
        if self.map is None:
            raise RuntimeError("the sensor model has no map yet: call set_map() first")
        particles = np.ascontiguousarray(np.atleast_2d(np.asarray(particles, dtype=float)))
        observation = np.asarray(observation, dtype=float).ravel()
        if angles is None:
            angles = self.default_angles(observation.size)
        if offsets is not None:
            offsets = np.asarray(offsets, dtype=float).reshape(-1, 3)
            if offsets.shape[0] != observation.size or not offsets.any() or not np.all(np.isfinite(offsets)):
                offsets = None  # no motion during the sweep (or unusable offsets): a rigid scan
        return particles, observation, np.asarray(angles, dtype=float).ravel(), offsets

    def log_likelihood(self, particles, observation, angles=None, offsets=None) -> np.ndarray:
        """Squashed log weights (N,): sum over beams of log p(z|d), divided by squash_factor;
        −inf for particles off the map or in an occupied cell. ``offsets`` (B, 3): per-beam laser
        motion (dx, dy, dθ) during a sweep, in the laser frame (deskew; see the module docstring)."""
        particles, observation, angles, offsets = self._inputs(particles, observation, angles, offsets)
        if not self._fused:
            return self.log_likelihood_numpy(particles, observation, angles, offsets)
        self.ray_caster.prepare(particles, self.laser_offset)  # a large map's table: build the tiles in use
        log_rows = np.ascontiguousarray(self._log_table[self.measured_to_cells(observation)])
        out = np.empty(particles.shape[0])
        ox, oy, oth = (float(v) for v in self.laser_offset)
        if offsets is None:
            du = dv = np.zeros(angles.size)
        else:
            angles = angles + offsets[:, 2]
            du = np.ascontiguousarray(offsets[:, 0] / self.map.resolution)  # cells, laser frame
            dv = np.ascontiguousarray(offsets[:, 1] / self.map.resolution)
        _fused_kernel(particles, ox, oy, oth, *self.ray_caster.kernel_args(angles), du, dv,
                      float(self.cells_per_metre), float(self.z_max), log_rows, float(self.squash_factor), out)
        return out

    def log_likelihood_numpy(self, particles, observation, angles=None, offsets=None) -> np.ndarray:
        """``log_likelihood`` in numpy over the caster's ``cast``: the reference of the fused kernel."""
        particles, observation, angles, offsets = self._inputs(particles, observation, angles, offsets)
        z = self.measured_to_cells(observation)
        d = self.to_cells(self.expected_ranges(particles, angles, offsets))
        log_w = self._log_table[z[None, :], d].sum(axis=1) / self.squash_factor
        log_w[self.map.is_occupied_or_outside(particles[:, :2])] = -np.inf
        return log_w

    def evaluate(self, particles, observation, angles=None) -> np.ndarray:
        """Weights (N,): Π_b p(z_b | d_b) ^ (1/squash_factor). Never NaN; 0 where impossible."""
        with np.errstate(under="ignore"):
            return np.exp(self.log_likelihood(particles, observation, angles))


if HAVE_NUMBA:
    @njit(cache=True, nogil=True)
    def _fused_kernel(particles, off_x, off_y, off_th, map_ox, map_oy, map_c, map_s, resolution, map_yaw,
                      occupied, index, table, blocking, beam_f, beam_c, beam_s, consts, mode, beam_du, beam_dv,
                      cells_per_metre, z_max, log_rows, squash_factor, out):  # pragma: no cover - compiled
        """out[i] = Σ_b log p(z_b | d_b(particle i)) / squash_factor; −inf for particles off the map
        or in an occupied cell. ``log_rows[b]`` is the log table row of the measured z_b;
        (beam_du[b], beam_dv[b]): beam b's origin offset from the laser, laser frame, cells."""
        n_bins = table.shape[1]
        h, w = occupied.shape
        n_beams = beam_f.size
        fs = np.empty(n_beams)
        q0s = np.empty(n_beams)
        q1s = np.empty(n_beams)
        cells = np.empty(n_beams)
        blind = 0.0  # a laser outside free space sees 0 on every beam
        for b in range(n_beams):
            blind += log_rows[b, 0]
        for i in range(particles.shape[0]):
            px = particles[i, 0]
            py = particles[i, 1]
            pth = particles[i, 2]
            dx = px - map_ox
            dy = py - map_oy
            gx = (map_c * dx + map_s * dy) / resolution
            gy = (-map_s * dx + map_c * dy) / resolution
            if not (gx >= 0.0 and gx < w and gy >= 0.0 and gy < h):  # off the map (or NaN)
                out[i] = -np.inf
                continue
            if occupied[int(math.floor(gy)), int(math.floor(gx))]:
                out[i] = -np.inf
                continue
            c = math.cos(pth)
            s = math.sin(pth)
            cell, f0, u, v, sx, sy, sc, ss = locate(px + c * off_x - s * off_y, py + s * off_x + c * off_y,
                                                    pth + off_th, map_ox, map_oy, map_c, map_s, resolution,
                                                    map_yaw, index, n_bins)
            if cell < 0:
                out[i] = blind / squash_factor
                continue
            beam_ranges(table[cell], f0, u, v, beam_du, beam_dv, beam_f, beam_c, beam_s, consts, mode, fs, q0s,
                        q1s, cells)
            if consts[C_REFINE] > 0.0:
                refine(blocking, sx + 1.0, sy + 1.0, sc, ss, beam_du, beam_dv, beam_c, beam_s, consts, q0s, q1s,
                       cells)
            total = 0.0
            for b in range(n_beams):
                d = (cells[b] * resolution) * cells_per_metre  # metres, then as BeamModel.to_cells
                d = z_max if d > z_max else d
                total += log_rows[b, int(np.rint(d))]
            out[i] = total / squash_factor
else:  # pragma: no cover
    _fused_kernel = None
