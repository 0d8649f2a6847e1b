"""The course's module name: ``from localization.occupancy_map import OccupancyMap``
(the implementation lives in ``localization.core.occupancy_map``)."""
from localization.core.occupancy_map import MapError, OccupancyMap, load_map

__all__ = ["MapError", "OccupancyMap", "load_map"]
