"""Ray casters: expected ranges (N sensor poses × B beam angles) in an occupancy map.

All share ``RayCaster``'s conventions (``exact.py``): rays stop at the first cell that is not
known free, ranges in metres clipped to ``max_range``, a sensor in a blocking cell sees 0.

==================== ============================== ============================================
name                 class                          what
==================== ============================== ============================================
lookup_table         LookupTableRayCaster           precomputed table, interpolated (real time)
lookup_table_exact   LookupTableRayCaster(refine=1) the table plus an exact finish per beam
distance_transform   DistanceTransformRayCaster     sphere tracing (no precomputation)
exact                ExactRayCaster                 Amanatides–Woo traversal: the reference
scan_simulator       ScanSimulatorRayCaster         the course's racecar_simulator ray marcher
==================== ============================== ============================================

On maps of more than ``range_table_lazy_cells`` cells both table casters are a
``TiledLookupTableRayCaster`` (``tiled_table.py``): the same table, built per tile where the
particles are.
"""
from __future__ import annotations

from localization.core.occupancy_map import OccupancyMap
from localization.core.parameters import default
from localization.core.raycast.distance_transform import DistanceTransformRayCaster
from localization.core.raycast.exact import ExactRayCaster, RayCaster
from localization.core.raycast.lookup_table import DEFAULT_THETA_BINS, LookupTableRayCaster
from localization.core.raycast.scan_simulator import ScanSimulatorRayCaster
from localization.core.raycast.tiled_table import TiledLookupTableRayCaster

RAY_CASTERS = ("lookup_table", "lookup_table_exact", "distance_transform", "exact", "scan_simulator")
TABLE_CASTERS = ("lookup_table", "lookup_table_exact")  # the casters over a precomputed range table

__all__ = ["RAY_CASTERS", "TABLE_CASTERS", "DistanceTransformRayCaster", "ExactRayCaster", "LookupTableRayCaster",
           "RayCaster", "ScanSimulatorRayCaster", "TiledLookupTableRayCaster", "make_ray_caster", "tiled"]


def tiled(occupancy_map: OccupancyMap, lazy_cells: int | None = None) -> bool:
    """Whether a table caster of this map is built tile by tile (more than ``lazy_cells`` cells;
    default: the ``range_table_lazy_cells`` parameter)."""
    lazy_cells = default("range_table_lazy_cells") if lazy_cells is None else int(lazy_cells)
    return occupancy_map.data.size > lazy_cells


def make_ray_caster(kind: str, occupancy_map: OccupancyMap, max_range: float,
                    theta_bins: int = DEFAULT_THETA_BINS, lazy_cells: int | None = None) -> RayCaster:
    """The caster ``kind`` (one of ``RAY_CASTERS``) for a map; lookup tables go through the disk cache,
    except on maps of more than ``lazy_cells`` cells (default: the ``range_table_lazy_cells``
    parameter), whose table is built per tile where the particles are (``tiled_table.py``)."""
    if kind == "exact":
        return ExactRayCaster(occupancy_map, max_range)
    if kind == "distance_transform":
        return DistanceTransformRayCaster(occupancy_map, max_range)
    if kind == "scan_simulator":  # the course's: theta_bins is its scan_theta_discretization
        return ScanSimulatorRayCaster(occupancy_map, max_range, theta_bins=theta_bins)
    if kind in TABLE_CASTERS:
        if tiled(occupancy_map, lazy_cells):
            return TiledLookupTableRayCaster.for_map(occupancy_map, max_range, theta_bins=theta_bins,
                                                     refine=1.0 if kind == "lookup_table_exact" else 0.0)
        return LookupTableRayCaster.for_map(occupancy_map, max_range, theta_bins=theta_bins,
                                            refine=1.0 if kind == "lookup_table_exact" else 0.0)
    raise ValueError(f"unknown ray caster {kind!r} ({', '.join(RAY_CASTERS)})")
