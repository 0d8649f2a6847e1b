"""Ray casting in an occupancy map: expected ranges for N sensor poses x B beam angles.

A ray starts at the sensor position and stops at the first cell that is not known free
(occupied, unknown or off the map — as nav2 AMCL's ``map_calc_range``). Ranges are in metres,
clipped to ``max_range``; a sensor standing in a blocking cell sees 0.

Casters (all vectorised over every ray at once, none loops over particles or beams in Python):

- ``ExactRayCaster``: Amanatides–Woo grid traversal: the exact distance to the boundary of the
  first blocking cell. The reference the others are checked against.
- ``DistanceTransformRayCaster``: sphere tracing over a Euclidean distance transform: each step
  jumps by the clearance to the nearest blocking cell, then a short bisection refines the hit.

The lookup-table caster for real-time use lives in ``range_table``.
"""
from __future__ import annotations

import numpy as np

from .occupancy_map import OccupancyMap


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


class DistanceTransformRayCaster(RayCaster):
    """Sphere tracing: step by (clearance - 1 cell), at least ``min_step`` cells, until a
    blocking cell is entered, then bisect the last step ``refine`` times."""

    def __init__(self, occupancy_map: OccupancyMap, max_range: float, min_step: float = 0.5, refine: int = 3):
        super().__init__(occupancy_map, max_range)
        from scipy.ndimage import distance_transform_edt
        self.min_step = float(min_step)
        self.refine = int(refine)
        clearance = distance_transform_edt(~self.blocking)  # cells, centre to nearest blocking centre
        self.step = np.maximum(clearance - 1.0, self.min_step).astype(np.float32)

    def _cast_grid(self, ox, oy, dx, dy):
        n = ox.size
        h, w = self.blocking.shape
        result = np.full(n, self.max_cells)
        t = np.zeros(n)
        t_prev = np.zeros(n)
        hit = self._blocked(ox, oy)
        result[hit] = 0.0
        live = np.flatnonzero(~hit)
        ends = []
        while live.size:
            x = ox[live] + t[live] * dx[live]
            y = oy[live] + t[live] * dy[live]
            ix = np.clip(np.floor(x).astype(np.int64), 0, w - 1)
            iy = np.clip(np.floor(y).astype(np.int64), 0, h - 1)
            blocked = self.blocking[iy, ix]
            ends.append(live[blocked])
            live = live[~blocked]
            if not live.size:
                break
            t_prev[live] = t[live]
            t[live] += self.step[iy[~blocked], ix[~blocked]]
            live = live[t[live] < self.max_cells + 1.0]
        ended = np.concatenate(ends) if ends else np.empty(0, dtype=np.int64)
        ended = ended[t[ended] > 0]
        lo, hi = t_prev[ended], t[ended]
        for _ in range(self.refine):
            mid = 0.5 * (lo + hi)
            b = self._blocked(ox[ended] + mid * dx[ended], oy[ended] + mid * dy[ended])
            hi = np.where(b, mid, hi)
            lo = np.where(b, lo, mid)
        result[ended] = 0.5 * (lo + hi)
        return result
