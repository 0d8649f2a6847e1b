"""Ray casting in an occupancy map: expected ranges for N sensor poses x B beam angles.

A ray starts at the sensor position and stops at the first cell that is not known free
(occupied, unknown or off the map — as nav2 AMCL's ``map_calc_range``). Ranges are in metres,
clipped to ``max_range``; a sensor standing in a blocking cell sees 0.

Casters (all vectorised over every ray at once, none loops over particles or beams in Python):

- ``ExactRayCaster``: Amanatides–Woo grid traversal: the exact distance to the boundary of the
  first blocking cell. The reference the others are checked against.
Siblings: ``DistanceTransformRayCaster`` (``distance_transform.py``, sphere tracing) and the
real-time ``LookupTableRayCaster`` (``lookup_table.py``); ``make_ray_caster`` (``__init__``)
builds any of them by name.
"""
from __future__ import annotations

from contextlib import AbstractContextManager, nullcontext

import numpy as np

from localization.core.occupancy_map import OccupancyMap


class RayCaster:
    """Base class: converts world sensor poses to the grid frame and calls ``_cast_grid``."""

    def __init__(self, occupancy_map: OccupancyMap, max_range: float):
        if not max_range > 0:
            raise ValueError(f"max_range must be positive, got {max_range}")
        self.map = occupancy_map
        self.max_range = float(max_range)
        self.max_cells = self.max_range / occupancy_map.resolution
        # Padded "blocking" grid: a one-cell border of blocking cells stops every ray at the edge.
        blocking = ~occupancy_map.free
        self.blocking = np.pad(blocking, 1, constant_values=True)

    def scratch(self) -> AbstractContextManager:
        """A scope whose temporary memory is given back at its end: nothing to give back here
        (``TiledLookupTableRayCaster`` releases the tiles built inside it)."""
        return nullcontext()

    def locality_order(self, xy) -> np.ndarray:
        """A permutation of world positions (K, 2) grouping those that share memory: the identity
        here (``TiledLookupTableRayCaster``: by tile)."""
        return np.arange(len(np.asarray(xy).reshape(-1, 2)))

    def cast(self, sensor_poses, angles) -> np.ndarray:
        """Expected ranges (metres), shape (N, B), for sensor poses (N, 3) in the world frame
        and beam angles (B,) relative to each sensor heading."""
        poses = np.atleast_2d(np.asarray(sensor_poses, dtype=float))
        angles = np.asarray(angles, dtype=float).ravel()
        g = self.map.world_to_grid_pose(poses)
        ox = np.repeat(g[:, 0] + 1.0, angles.size)  # +1: the padding border
        oy = np.repeat(g[:, 1] + 1.0, angles.size)
        th = (g[:, 2:3] + angles[None, :]).ravel()
        cells = self._cast_grid(ox, oy, np.cos(th), np.sin(th))
        return (np.minimum(cells, self.max_cells) * self.map.resolution).reshape(len(poses), angles.size)

    def cast_rays(self, sensor_poses, angles) -> np.ndarray:
        """One ray per row: ranges (K,) for sensor poses (K, 3) and beam angles (K,) (e.g. each
        beam of a sweeping lidar cast from the pose at its own time)."""
        g = self.map.world_to_grid_pose(np.atleast_2d(np.asarray(sensor_poses, dtype=float)))
        th = g[:, 2] + np.asarray(angles, dtype=float).ravel()
        cells = self._cast_grid(g[:, 0] + 1.0, g[:, 1] + 1.0, np.cos(th), np.sin(th))
        return np.minimum(cells, self.max_cells) * self.map.resolution

    def _blocked(self, x, y) -> np.ndarray:
        """Whether continuous padded-grid points lie in blocking cells (outside counts as blocking)."""
        h, w = self.blocking.shape
        ix = np.floor(x).astype(np.int64)
        iy = np.floor(y).astype(np.int64)
        inside = (ix >= 0) & (ix < w) & (iy >= 0) & (iy < h)
        out = np.ones(ix.shape, dtype=bool)
        out[inside] = self.blocking[iy[inside], ix[inside]]
        return out

    def _cast_grid(self, ox, oy, dx, dy) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError


class ExactRayCaster(RayCaster):
    """Amanatides–Woo traversal, all rays stepped together (each numpy step advances every
    live ray by one cell boundary)."""

    def _cast_grid(self, ox, oy, dx, dy):
        n = ox.size
        result = np.full(n, self.max_cells)
        ix = np.floor(ox).astype(np.int64)
        iy = np.floor(oy).astype(np.int64)
        h, w = self.blocking.shape
        start_blocked = self._blocked(ox, oy)
        result[start_blocked] = 0.0
        with np.errstate(divide="ignore", invalid="ignore"):
            step_x = np.where(dx > 0, 1, -1)
            step_y = np.where(dy > 0, 1, -1)
            t_dx = np.where(dx != 0, np.abs(1.0 / dx), np.inf)
            t_dy = np.where(dy != 0, np.abs(1.0 / dy), np.inf)
            t_x = np.where(dx > 0, (ix + 1 - ox) * t_dx, np.where(dx < 0, (ox - ix) * t_dx, np.inf))
            t_y = np.where(dy > 0, (iy + 1 - oy) * t_dy, np.where(dy < 0, (oy - iy) * t_dy, np.inf))
        live = np.flatnonzero(~start_blocked)
        ix, iy, t_x, t_y = ix[live], iy[live], t_x[live], t_y[live]
        step_x, step_y, t_dx, t_dy = step_x[live], step_y[live], t_dx[live], t_dy[live]
        while live.size:
            go_x = t_x < t_y
            t = np.where(go_x, t_x, t_y)
            ix = ix + np.where(go_x, step_x, 0)
            iy = iy + np.where(go_x, 0, step_y)
            t_x = np.where(go_x, t_x + t_dx, t_x)
            t_y = np.where(go_x, t_y, t_y + t_dy)
            inside = (ix >= 0) & (ix < w) & (iy >= 0) & (iy < h)
            hit = ~inside
            hit[inside] = self.blocking[iy[inside], ix[inside]]
            too_far = t >= self.max_cells
            done = hit | too_far
            result[live[hit & ~too_far]] = t[hit & ~too_far]
            keep = ~done
            live, ix, iy, t_x, t_y = live[keep], ix[keep], iy[keep], t_x[keep], t_y[keep]
            step_x, step_y, t_dx, t_dy = step_x[keep], step_y[keep], t_dx[keep], t_dy[keep]
        return result
