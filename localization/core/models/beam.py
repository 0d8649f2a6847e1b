"""Beam sensor model over ray-cast expected scans.

For one beam with measured range z and expected (ray-cast) range d, both in table cells of
``table_resolution`` metres (0.05 m by default, whatever the map's resolution), and k the row of
z_max:

    p(z | d) = α_hit·p_hit + α_short·p_short + α_max·p_max + α_rand·p_rand

    p_hit   = N(z; d, σ²), σ = sigma_hit / table_resolution, normalised over z for each d (before mixing)
    p_short = 2/d · (1 − z/d)  for 0 ≤ z ≤ d, d ≠ 0; else 0
    p_max   = 1  at z = k (one cell wide); else 0
    p_rand  = 1 / k

The mix is tabulated (rows z, columns d, 0 … k each) and every column normalised to sum to 1
(``sensor_model_table``: the course's table, k = table_width − 1 = 200). A scan's likelihood is
the product over beams, computed as a sum of logs so 100 beams never underflow, then "squashed":

    log w = (Σ_b log p(z_b | d_b)) / squash_factor

Particles off the map or in an occupied cell get log weight −inf.

z_max is the sensor's range, not the table's: ``laser_max_range`` when > 0, else the scan's
``range_max`` (``log_likelihood(..., range_max=)``), capped at what the table covers,
(table_width − 1) · table_resolution = 10 m by default (``sensors.resolve_max_range``). Its row is
k = round(z_max · lidar_scale_to_map_scale / table_resolution), and the table above is built for
that k (and cached per k). Measured readings at or beyond z_max, and NaN/inf ones ("no return";
``scan.downsample_scan`` turns readings outside [range_min, range_max] into inf), fall in row k:
they are scored by p_max. Expected ranges beyond z_max are clipped to it: a particle that sees
open space beyond z_max expects a max-range reading. So a 5.6 m lidar's no-return beam supports a
particle seeing no wall within 5.6 m, and counts against one seeing a wall at 3 m.

Units: expected ranges are cast in map metres, to the free-space edge; a measured range z (lidar
metres) becomes z' = s·z − o in map metres, s = ``lidar_scale_to_map_scale`` (1 for a lidar and map
that agree; the course's code divided both ranges by it, which only re-binned the table) and
o = ``map_wall_depth``: maps draw walls a few cells thick, a beam ends on the real surface inside
them, o behind the edge (0 by default; both are what ``localization-calibrate`` estimates). Returns
at or beyond z_max stay there. Both ranges are then binned at ``table_resolution``. The ray
caster casts no further than the table covers.

With the lookup-table caster (the default) one compiled pass per particle does it all — laser
pose, table row, interpolated range, table index, log sum — with no (N, B) temporaries
(``beam_kernels.fused_kernel``); ``log_likelihood_numpy`` is its numpy reference, asserted equal in the tests.

Beam skipping (``do_beamskip``; the rule in ``localization.core.models.sensor``): a particle explains beam
b when |z_b − d_b| ≤ ``beam_skip_distance`` (both in table cells, z_b as scored above); beams that
at most ``beam_skip_threshold`` of the particles explain are left out of every particle's sum. A
return the map cannot have, e.g. through a window, is scored on the hit Gaussian's tail, where it
favours whichever pose expects the longest range; left out, it favours none. The fused kernel then
also writes each particle's table columns (``cols_out``, (N, B)) and the sum over the used beams is
taken in numpy.

Deskew (a sweeping lidar): beam b is measured from the laser pose L_b = L ⊕ δ_b, where L is the
laser pose at the scan's reference time and δ_b = (dx_b, dy_b, dθ_b) the laser's own motion until
beam b's time, in the laser frame (the same for every particle: ``offsets``). Each beam is cast
from its own origin: dθ_b turns the beam, and (dx_b, dy_b) (a few cm) is added to the laser's
offset (u, v) from its table cell's centre, which the table query already handles (the wall line
through the two bins' hit points, ``raycast.kernels.wall_line_range``) — no extra ray casting.
"""
from __future__ import annotations

from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, fields, replace

import numpy as np

from localization.core.cost import CostMeter
from localization.core.geometry import compose
from localization.core.models import beam_kernels as kernels
from localization.core.models.sensor import (
    LaserMount,
    Preparation,
    RangeProbe,
    beam_mask,
    resolve_max_range,
    skips_beams,
    sweep_offsets,
)
from localization.core.occupancy_map import OccupancyMap
from localization.core.parameters import default
from localization.core.raycast import TABLE_CASTERS, LookupTableRayCaster, RayCaster, make_ray_caster, tiled
from localization.core.raycast.kernels import HAVE_NUMBA


@dataclass(frozen=True)
class BeamModelParams:
    """The beam model's parameters; names and meanings as in the parameter table
    (``localization.core.parameters``), defaults the course's (``course=True``)."""

    alpha_hit: float = default("alpha_hit", course=True)
    alpha_short: float = default("alpha_short", course=True)
    alpha_max: float = default("alpha_max", course=True)
    alpha_rand: float = default("alpha_rand", course=True)
    sigma_hit: float = default("sigma_hit", course=True)  # m
    table_width: int = default("table_width", course=True)  # table cells: rows and columns 0 … table_width - 1
    table_resolution: float = default("table_resolution", course=True)  # m per table cell
    laser_max_range: float = default("laser_max_range", course=True)  # m; <= 0: the scan's range_max
    squash_factor: float = default("squash_factor", course=True)
    num_beams_per_particle: int = default("num_beams_per_particle", course=True)
    scan_field_of_view: float = default("scan_field_of_view", course=True)  # rad
    lidar_scale_to_map_scale: float = default("lidar_scale_to_map_scale", course=True)
    map_wall_depth: float = default("map_wall_depth", course=True)  # m: a return ends this far behind the free edge
    laser_offset_x: float = default("laser_offset_x", course=True)  # m, in base_link
    laser_offset_y: float = default("laser_offset_y", course=True)  # m
    laser_offset_yaw: float = default("laser_offset_yaw", course=True)  # rad
    ray_caster: str = default("ray_caster", course=True)
    scan_theta_discretization: int = default("scan_theta_discretization", course=True)
    range_table_lazy_cells: int = default("range_table_lazy_cells", course=True)  # larger maps: table per tile
    num_threads: int = default("num_threads", course=True)  # the fused pass over blocks of particles
    do_beamskip: bool = default("do_beamskip", course=True)  # leave out beams few particles explain
    beam_skip_distance: float = default("beam_skip_distance", course=True)  # m: |s·z − o − d| that explains a beam
    beam_skip_threshold: float = default("beam_skip_threshold", course=True)  # share of particles
    beam_skip_error_threshold: float = default("beam_skip_error_threshold", course=True)  # share of beams
    beam_skip_max_spread: float = default("beam_skip_max_spread", course=True)  # m: only a one-hypothesis cloud

    @classmethod
    def from_parameters(cls, params) -> "BeamModelParams":
        """From a ``Parameters`` mapping (the node's, replay's): same names."""
        return cls(**{f.name: params[f.name] for f in fields(cls)})


# the course's attribute names (sm.alpha_hit, sm.sigma_hit, ...): read from and written to ``params``;
# ``ray_caster`` stays the caster object (its name is ``ray_caster_kind``)
_PARAM_ATTRIBUTES = frozenset(f.name for f in fields(BeamModelParams)) - {"ray_caster"}


def beam_mixture_table(p: BeamModelParams, k: int) -> np.ndarray:
    """The (k + 1, k + 1) table of the module docstring for z_max row k: rows z, columns d (table
    cells of ``table_resolution`` metres), every column normalised."""
    n = int(k) + 1
    if n < 2:
        raise ValueError(f"the table needs at least 2 rows, got {n}")
    if not (p.sigma_hit > 0 and p.table_resolution > 0):
        raise ValueError(f"sigma_hit ({p.sigma_hit}) and table_resolution ({p.table_resolution}) must be > 0")
    sigma = p.sigma_hit / p.table_resolution  # table cells
    z = np.arange(n, dtype=float)[:, None]  # rows: measured range
    d = np.arange(n, dtype=float)[None, :]  # columns: expected range
    p_hit = np.exp(-0.5 * ((z - d) / sigma) ** 2) / np.sqrt(2.0 * np.pi * sigma ** 2)
    p_hit = p_hit / p_hit.sum(axis=0, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        p_short = np.where((z <= d) & (d > 0), 2.0 / d * (1.0 - z / d), 0.0)
    p_max = np.where(z == n - 1, 1.0, 0.0) * np.ones_like(d)
    p_rand = np.full((n, n), 1.0 / (n - 1))
    table = (p.alpha_hit * p_hit + p.alpha_short * p_short + p.alpha_max * p_max + p.alpha_rand * p_rand)
    column_sums = table.sum(axis=0, keepdims=True)
    if not np.any(column_sums > 0):
        raise ValueError("sensor model alphas are all zero; at least one must be > 0")
    # A column can only sum to 0 when p_short is the sole component (d = 0): it stays 0.
    return np.divide(table, column_sums, out=np.zeros_like(table), where=column_sums > 0)


SKIP_CHECK_PASSES = 6  # numpy passes of skips_beams over the cloud: isfinite, all, the selection, the std
SKIPPED_SUM_PASSES = 8  # numpy passes of _skipped_sum_numpy over the (N, B) columns (compiled: 2)

MIN_PARTICLES_PER_THREAD = 256  # fewer particles per thread: the threads' start costs more than they save


def kernel_threads(num_threads: int, num_particles: int) -> int:
    """Threads for a fused pass over ``num_particles`` (``num_threads`` asked, at most numba's pool and one
    per MIN_PARTICLES_PER_THREAD particles); numba's pool is set to that many for the call."""
    threads = min(int(num_threads), num_particles // MIN_PARTICLES_PER_THREAD)
    if threads <= 1 or not HAVE_NUMBA:
        return 1
    import numba
    threads = min(threads, numba.config.NUMBA_NUM_THREADS)
    if threads > 1:
        numba.set_num_threads(threads)
    return threads


class BeamModel(LaserMount):
    """The beam model (the course's ``SensorModel``). ``BeamModel(**overrides)`` or
    ``BeamModel(params)``; ``laser_offset=(x, y, yaw)`` is accepted for the three offsets.

    The course's attributes (``sm.alpha_hit``, ``sm.sigma_hit`` (m), ``sm.squash_factor``, ...)
    read and write ``params`` (a new frozen dataclass per write); a write drops the tables, rebuilt
    on use (``precompute_sensor_model()``, as the course's code calls it, rebuilds at once)."""

    supports_deskew = True  # log_likelihood takes per-beam laser offsets (a deskewed sweep)
    supports_range_scale = True  # casts ranges: the range scale can be learnt online (range_probe)
    accepts_out = True  # log_likelihood(..., out=) writes into a caller's array (the filter reuses one)

    def __init__(self, params: BeamModelParams | None = None, *, occupancy_map: OccupancyMap | None = None,
                 laser_offset=None, **overrides):
        if laser_offset is not None:
            ox, oy, oyaw = (float(v) for v in laser_offset)
            overrides.update(laser_offset_x=ox, laser_offset_y=oy, laser_offset_yaw=oyaw)
        self.params = replace(params or BeamModelParams(), **overrides)
        self.map: OccupancyMap | None = None
        self.ray_caster: RayCaster | None = None
        self._tables: dict = {}  # z_max row k -> (table, log table) of rows/columns 0 … k
        self.last_beams_used: int | None = None  # beams used by the last evaluation (do_beamskip leaves some out)
        self.cost = CostMeter()  # beam skipping's extra work (``core.cost``; a localizer shares its meter)
        self._rows = None  # the log table rows of the last scan's beams (an array reused)
        self._cols = None  # beam skipping: each particle's table columns (an array reused)
        self.precompute_sensor_model()
        if occupancy_map is not None:
            self.set_map(occupancy_map)

    def __getattr__(self, name):  # only for names not found normally: the course's parameter attributes
        if name in _PARAM_ATTRIBUTES:
            return getattr(self.__dict__["params"], name)
        raise AttributeError(f"{type(self).__name__!s} has no attribute {name!r}")

    def __setattr__(self, name, value):
        if name in _PARAM_ATTRIBUTES:
            self.params = replace(self.params, **{name: value})
            self._tables = {}  # rebuilt on use with the new value
        else:
            object.__setattr__(self, name, value)

    @property
    def ray_caster_kind(self) -> str:
        return self.params.ray_caster

    # ------------------------------------------------------------------ the laser
    # the laser pose: LaserMount (laser_offset, set_laser_offset)

    # ------------------------------------------------------------------ the table
    @property
    def z_max(self) -> int:
        """The table's last row and column (cells): table_width − 1 (the course's z_max)."""
        return self.params.table_width - 1

    @property
    def table_range(self) -> float:
        """The farthest range the table covers (map metres): z_max cells of table_resolution."""
        return self.z_max * self.params.table_resolution

    def mixture_table(self, k: int) -> np.ndarray:
        """The (k + 1, k + 1) table for z_max row k (``beam_mixture_table``)."""
        return beam_mixture_table(self.params, k)

    def precompute_sensor_model(self) -> np.ndarray:
        """(Re)build ``sensor_model_table`` (z_max = table_width − 1) from the current alphas,
        sigma_hit, table_width and table_resolution; tables of other z_max rows are rebuilt on use."""
        table = self.mixture_table(self.z_max)
        with np.errstate(divide="ignore"):
            self._tables = {self.z_max: (table, np.log(table))}
        return table

    @property
    def sensor_model_table(self) -> np.ndarray:
        """The course's table: rows z, columns d, 0 … table_width − 1 cells."""
        return self._table(self.z_max)[0]

    def log_table(self, k: int | None = None) -> np.ndarray:
        """log of the table for z_max row ``k`` (default: the table's own, table_width − 1)."""
        return self._table(self.z_max if k is None else int(k))[1]

    def _table(self, k: int):
        tables = self._tables  # one read: another thread may replace the dict (precompute_sensor_model)
        entry = tables.get(k)
        if entry is None:
            table = self.mixture_table(k)
            with np.errstate(divide="ignore"):
                entry = tables[k] = (table, np.log(table))
        return entry

    # ------------------------------------------------------------------ z_max
    @property
    def max_range(self) -> float:
        """z_max (lidar metres) when the scan gives no range_max: ``laser_max_range`` if > 0, else
        the table's reach (see ``max_range_for``)."""
        return self.max_range_for(None)

    def max_range_for(self, range_max: float | None) -> float:
        """z_max (lidar metres) for a scan with this ``range_max``: ``laser_max_range`` if > 0, else
        ``range_max`` if usable, capped at the table's reach (table_range / lidar_scale_to_map_scale)."""
        reach = self.table_range / self.params.lidar_scale_to_map_scale
        return min(resolve_max_range(self.params.laser_max_range, range_max, reach), reach)

    def z_max_row(self, range_max: float | None = None) -> int:
        """The table row k of z_max (see ``max_range_for``), in [1, table_width − 1]."""
        p = self.params
        k = int(np.rint(self.max_range_for(range_max) * p.lidar_scale_to_map_scale / p.table_resolution))
        return min(max(k, 1), self.z_max)

    def set_range_scale(self, scale: float) -> None:
        """Use ``scale`` as lidar_scale_to_map_scale (an online estimate, ``core.localizer.range_scale``); the
        tables, which do not depend on it, are kept."""
        self.params = replace(self.params, lidar_scale_to_map_scale=float(scale))

    def range_probe(self, angles, offsets=None, range_max=None) -> RangeProbe:
        """The beams cast as ``log_likelihood`` casts them (compiled with the lookup-table caster: ``cast_rows``,
        whose numpy reference is ``expected_ranges``), z_max, the table's reach and the wall depth."""
        offsets = sweep_offsets(offsets, np.size(angles))
        cast = self._compiled_cast(angles, offsets) if self._fused else (
            lambda poses: self.expected_ranges(poses, angles, offsets))
        return RangeProbe(cast, self.max_range_for(range_max), self.table_range, self.params.map_wall_depth)

    def _compiled_cast(self, angles, offsets):
        """``poses (k, 3) -> (k, B)``: ``expected_ranges(poses, angles, offsets)`` by the fused kernel's own
        arithmetic (``beam_kernels.probe_cast``)."""
        p = self.params
        laser = (float(p.laser_offset_x), float(p.laser_offset_y), float(p.laser_offset_yaw))
        return kernels.probe_cast(self.ray_caster, laser, self.map.resolution, angles, offsets)

    # ------------------------------------------------------------------ the map
    def preparation(self, occupancy_map: OccupancyMap) -> Preparation:
        """Whether ``prepare`` will build a range table (seconds: prepare off-thread), and a note."""
        p = self.params
        free = int(np.count_nonzero(occupancy_map.free))
        size = (f"map {occupancy_map.width}x{occupancy_map.height} cells ({free} free) x "
                f"{p.scan_theta_discretization} headings")
        if p.ray_caster not in TABLE_CASTERS:
            return Preparation(False, f"ray caster {p.ray_caster}: nothing to precompute for the {size}")
        if tiled(occupancy_map, p.range_table_lazy_cells):
            return Preparation(False, f"range table: built tile by tile where the particles are, for the {size} "
                                      f"(more than range_table_lazy_cells = {p.range_table_lazy_cells} cells)")
        source = LookupTableRayCaster.cached_source(occupancy_map, self.table_range, p.scan_theta_discretization)
        if source:
            return Preparation(False, f"range table: loading it from the {'cache' if source == 'disk' else 'memory'} "
                                      f"for the {size}")
        seconds = LookupTableRayCaster.build_estimate(occupancy_map, p.scan_theta_discretization)
        return Preparation(True, f"range table: building it for the {size}, expected ~{seconds:.0f} s (cached for "
                                 "the next start)")

    def prepare(self, occupancy_map: OccupancyMap, kind: str | None = None) -> RayCaster:
        """The ray caster (``kind``, default ``ray_caster``) of a map, casting up to ``table_range``:
        the slow part of ``set_map`` (a range table built or loaded), without touching the model,
        so a caller may make it on another thread and then call ``set_map(occupancy_map, caster)``."""
        p = self.params
        return make_ray_caster(kind or p.ray_caster, occupancy_map, self.table_range, p.scan_theta_discretization,
                               p.range_table_lazy_cells)

    def set_map(self, occupancy_map: OccupancyMap, prepared=None) -> None:
        """Use a (new) map with ``prepared``: a ready caster from ``prepare`` (None: built here; a
        caster name: that caster built here)."""
        if prepared is None or isinstance(prepared, str):
            prepared = self.prepare(occupancy_map, prepared)
        self.map = occupancy_map
        self.ray_caster = prepared
        if self._fused:  # compile (or load from numba's cache) now, not on the first scan
            self.log_likelihood(np.zeros((1, 3)), np.zeros(1), np.zeros(1))

    @property
    def _fused(self) -> bool:
        return isinstance(self.ray_caster, LookupTableRayCaster) and self.ray_caster.use_numba

    def scratch(self) -> AbstractContextManager:
        """Temporary memory scope: the tiles of a tiled range table built inside it are given back."""
        return nullcontext() if self.ray_caster is None else self.ray_caster.scratch()

    def locality_order(self, xy) -> np.ndarray:
        """Positions (K, 2) ordered by the range table's tile (tiled tables; else the identity)."""
        if self.ray_caster is None:
            return np.arange(len(np.asarray(xy).reshape(-1, 2)))
        return self.ray_caster.locality_order(xy)

    # ------------------------------------------------------------------ evaluation
    def default_angles(self, num_beams: int) -> np.ndarray:
        """The course convention: beams evenly over ``scan_field_of_view`` centred on the heading."""
        half = 0.5 * self.params.scan_field_of_view
        return np.linspace(-half, half, num_beams)

    def expected_ranges(self, particles, angles, offsets=None) -> np.ndarray:
        """Ray-cast ranges (map metres, at most ``table_range``), (N, B), from each particle's laser
        pose (``offsets`` (B, 3): each beam cast from the laser pose ⊕ its offset, see the module
        docstring)."""
        laser = self.laser_offset
        sensor = compose(np.atleast_2d(particles), laser) if laser.any() else particles
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

    def to_cells(self, ranges_m, k: int | None = None) -> np.ndarray:
        """Map metres -> integer table indices in [0, k] (default k: table_width − 1); NaN/inf
        and ranges beyond the row k count as k."""
        k = self.z_max if k is None else int(k)
        cells = np.asarray(ranges_m, dtype=float) * (1.0 / self.params.table_resolution)
        return np.rint(np.fmax(np.fmin(cells, k), 0.0)).astype(np.intp)  # fmin: NaN (no return) -> k

    def measured_to_cells(self, ranges, k: int | None = None) -> np.ndarray:
        """Measured ranges (lidar metres) -> table rows in [0, k]: s·z − o in map metres (s =
        lidar_scale_to_map_scale, o = map_wall_depth: the corrections ``localization-calibrate``
        estimates); returns at or beyond z_max (and no-returns) stay in row k."""
        p = self.params
        k = self.z_max if k is None else int(k)
        z = np.asarray(ranges, dtype=float) * p.lidar_scale_to_map_scale
        if p.map_wall_depth:
            with np.errstate(invalid="ignore"):
                z = np.where(z < (k - 0.5) * p.table_resolution, np.maximum(z - p.map_wall_depth, 0.0), z)
        return self.to_cells(z, k)

    def _inputs(self, particles, observation, angles, offsets=None):
        if self.map is None:
            raise RuntimeError("the sensor model has no map yet: call set_map() first")
        particles = np.ascontiguousarray(np.atleast_2d(np.asarray(particles, dtype=float)))
        observation = np.asarray(observation, dtype=float).ravel()
        if angles is None:
            angles = self.default_angles(observation.size)
        return particles, observation, np.asarray(angles, dtype=float).ravel(), sweep_offsets(offsets, observation.size)

    def log_likelihood(self, particles, observation, angles=None, offsets=None, range_max=None,
                       out=None) -> np.ndarray:
        """Squashed log weights (N,): sum over beams of log p(z|d), divided by squash_factor;
        −inf for particles off the map or in an occupied cell. ``offsets`` (B, 3): per-beam laser
        motion (dx, dy, dθ) during a sweep, in the laser frame (deskew; see the module docstring);
        ``range_max``: the scan's (lidar metres), z_max when ``laser_max_range`` <= 0; ``out`` (N,): an
        array to write them into (the compiled pass; None: a new one)."""
        particles, observation, angles, offsets = self._inputs(particles, observation, angles, offsets)
        if not self._fused:
            return self.log_likelihood_numpy(particles, observation, angles, offsets, range_max)
        p = self.params
        k = self.z_max_row(range_max)
        self.ray_caster.prepare(particles, self.laser_offset)  # a large map's table: build the tiles in use
        z = self.measured_to_cells(observation, k)
        log_table = self.log_table(k)
        log_rows = self._rows
        if log_rows is None or log_rows.shape != (z.size, log_table.shape[1]):
            log_rows = self._rows = np.empty((z.size, log_table.shape[1]))
        np.take(log_table, z, axis=0, out=log_rows)  # each beam's log table row (kept from scan to scan)
        if out is None or out.shape != (particles.shape[0],):
            out = np.empty(particles.shape[0])
        ox, oy, oth = p.laser_offset_x, p.laser_offset_y, p.laser_offset_yaw
        if offsets is None:
            du = dv = np.zeros(angles.size)
        else:
            angles = angles + offsets[:, 2]
            du = np.ascontiguousarray(offsets[:, 0] / self.map.resolution)  # cells, laser frame
            dv = np.ascontiguousarray(offsets[:, 1] / self.map.resolution)
        skip = self._skips(particles)
        cols = self._cols
        if cols is None or cols.shape != (particles.shape[0] if skip else 0, angles.size):
            cols = self._cols = np.empty((particles.shape[0] if skip else 0, angles.size), dtype=np.int32)
        args = (particles, float(ox), float(oy), float(oth), *self.ray_caster.kernel_args(angles), du, dv,
                1.0 / p.table_resolution, float(k), log_rows, float(p.squash_factor), out, cols)
        threads = kernel_threads(p.num_threads, particles.shape[0])
        if threads > 1:
            kernels.fused_kernel_parallel(threads, *args)
        else:
            kernels.fused_kernel(*args)
        if skip:
            return self._skipped_sum(log_rows, z, cols, out)
        self.last_beams_used = angles.size
        return out

    def _skips(self, particles) -> bool:
        """Whether beam skipping applies to ``particles`` (``sensor.skips_beams``; its passes counted)."""
        if self.params.do_beamskip:
            self.cost.sweep("beam_skip", SKIP_CHECK_PASSES)
        return skips_beams(particles, self.params)

    def _skipped_sum(self, log_rows, z, cols, out) -> np.ndarray:
        """``_skipped_sum_numpy`` in two compiled passes over the columns (the votes, the sum over the used
        beams), written into ``out`` (the fused kernel's: finite for the particles that can see)."""
        p = self.params
        self.cost.cast("beam_skip", 2 * cols.size)
        votes = np.empty(z.size, dtype=np.int64)
        kernels.skip_votes(cols, z, p.beam_skip_distance / p.table_resolution, out, votes)
        used = beam_mask(p, votes, int(np.count_nonzero(np.isfinite(out))))
        self.last_beams_used = int(used.sum())
        kernels.masked_sum(log_rows, cols, used, float(p.squash_factor), out)
        return out

    def _skipped_sum_numpy(self, log_rows, z, cols, valid) -> np.ndarray:
        """Squashed log weights (N,) over the beams beam skipping uses (module docstring): ``log_rows`` (B, k + 1),
        ``z`` (B,) measured rows, ``cols`` (N, B) expected columns, ``valid`` (N,) particles that can see."""
        p = self.params
        self.cost.cast("beam_skip", SKIPPED_SUM_PASSES * cols.size)
        seeing = cols[valid]
        agree = np.abs(seeing - z[None, :]) <= p.beam_skip_distance / p.table_resolution
        used = beam_mask(p, agree.sum(axis=0), int(valid.sum()))
        self.last_beams_used = int(used.sum())
        out = np.full(cols.shape[0], -np.inf)
        out[valid] = log_rows[np.flatnonzero(used)[None, :], seeing[:, used]].sum(axis=1) / p.squash_factor
        return out

    def log_likelihood_numpy(self, particles, observation, angles=None, offsets=None, range_max=None) -> np.ndarray:
        """``log_likelihood`` in numpy over the caster's ``cast``: the reference of the fused kernel."""
        particles, observation, angles, offsets = self._inputs(particles, observation, angles, offsets)
        k = self.z_max_row(range_max)
        z = self.measured_to_cells(observation, k)
        d = self.to_cells(self.expected_ranges(particles, angles, offsets), k)
        bad = self.map.is_occupied_or_outside(particles[:, :2])
        if self._skips(particles):
            return self._skipped_sum_numpy(self.log_table(k)[z], z, d, ~bad)
        log_w = self.log_table(k)[z[None, :], d].sum(axis=1) / self.params.squash_factor
        log_w[bad] = -np.inf
        self.last_beams_used = z.size
        return log_w

    def evaluate(self, particles, observation, angles=None, range_max=None) -> np.ndarray:
        """Weights (N,): Π_b p(z_b | d_b) ^ (1/squash_factor). Never NaN; 0 where impossible."""
        with np.errstate(under="ignore"):
            return np.exp(self.log_likelihood(particles, observation, angles, range_max=range_max))

