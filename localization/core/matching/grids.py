"""The grids the scan matcher scores against, derived once per map (cached on the map).

All in cells, in the map's grid frame (column u, row v; cell centres at +0.5):

- signed distance to the boundary of the blocking cells (not known free: occupied, unknown),
  positive in free space, negative inside, zero on the cell faces::

      sdf = EDT_free − ½        in a free cell   (EDT_free: distance from its centre to the nearest
      sdf = −(EDT_block − ½)    in a blocking cell         blocking / free cell centre)

  so that bilinear interpolation between a free cell and its blocking neighbour is 0 on the
  face between them — where a lidar beam (and the simulator's exact ray caster) stops;
- likelihood of an endpoint falling in a cell (a Gaussian of that distance, σ in metres)::

      L = exp(−(sdf · res)² / (2 σ²))  ∈ (0, 1]

- the max-pooled likelihood for the coarse level of the search (Olson 2009): with k the coarse
  step in cells and L = 0 off the grid, padded by k − 1 cells on the low side (``pool_pad``)::

      P[v + k − 1, u + k − 1] = max L[v .. v+k−1, u .. u+k−1]      for −(k−1) ≤ v < h, −(k−1) ≤ u < w

  so the sum of P over the endpoints of a scan placed at shift (du, dv) (looked up at
  (du + k − 1, dv + k − 1)) bounds the fine score of every shift (du + i, dv + j), 0 ≤ i, j < k,
  also where the block straddles the grid's low edge (part of it off the grid, part on it).
"""
from __future__ import annotations

import numpy as np

from localization.core.occupancy_map import OccupancyMap


def signed_distance(occupancy_map: OccupancyMap) -> np.ndarray:
    """Signed distance (cells, float32) to the boundary of the blocking cells (see module doc)."""
    def compute():
        from scipy.ndimage import distance_transform_edt
        free = occupancy_map.free
        if free.all() or not free.any():
            return np.full(free.shape, 1e3 if free.all() else -1e3, dtype=np.float32)
        d_free = distance_transform_edt(free)  # free cells: distance to the nearest blocking centre
        d_block = distance_transform_edt(~free)  # blocking cells: distance to the nearest free centre
        return np.where(free, d_free - 0.5, -(d_block - 0.5)).astype(np.float32)
    return occupancy_map._cached("matching_sdf", compute)


def likelihood_grid(occupancy_map: OccupancyMap, sigma: float) -> np.ndarray:
    """L = exp(−d²/2σ²) per cell (float32), d the distance (m) from the cell centre to the boundary."""
    def compute():
        d = signed_distance(occupancy_map).astype(np.float64) * occupancy_map.resolution
        return np.exp(-0.5 * (d / sigma) ** 2).astype(np.float32)
    return occupancy_map._cached(("matching_likelihood", float(sigma)), compute)


def pool_pad(k: int) -> int:
    """Cells of padding on the low side of a grid max-pooled over k × k blocks."""
    return int(k) - 1


def max_pool(grid: np.ndarray, k: int) -> np.ndarray:
    """``P[v + k−1, u + k−1] = max grid[v .. v+k−1, u .. u+k−1]`` for −(k−1) ≤ v < h, −(k−1) ≤ u < w
    (shape (h + k − 1, w + k − 1); cells beyond either edge count as 0)."""
    h, w = grid.shape
    pad = pool_pad(k)
    padded = np.zeros((h + 2 * pad, w + 2 * pad), dtype=grid.dtype)
    padded[pad:pad + h, pad:pad + w] = grid
    H, Wd = h + pad, w + pad
    rows = padded[0:H].copy()
    for j in range(1, k):  # max over k rows, then over k columns (separable)
        np.maximum(rows, padded[j:j + H], out=rows)
    out = rows[:, 0:Wd].copy()
    for i in range(1, k):
        np.maximum(out, rows[:, i:i + Wd], out=out)
    return out


def pooled_likelihood_grid(occupancy_map: OccupancyMap, sigma: float, k: int) -> np.ndarray:
    return occupancy_map._cached(("matching_pooled", float(sigma), int(k)),
                                 lambda: max_pool(likelihood_grid(occupancy_map, sigma), int(k)))
