"""The course's ray caster: racecar_simulator's ``ScanSimulator2D``, reproduced.

The MIT RSS course's staff solution casts its expected scans with racecar_simulator's
``ScanSimulator2D`` (``scan_simulator_2d.cpp``, ``distance_transform.cpp``). Matching the course's
probabilities needs the same ranges, so this caster does what that code does:

1. The map. ``m = clip(data / 100, 0, 1)`` (unknown −1 becomes 0: free); a cell is free when
   ``0 ≤ m ≤ 0.5``, else occupied.
2. The distance field. D(cell) = resolution · √min(E², 99999), E the Euclidean distance (cells,
   centre to centre) to the nearest occupied cell, where the grid is padded with one occupied cell
   on every side (outside the map is a wall one cell out). Felzenszwalb–Huttenlocher's two passes of
   the lower envelope of parabolas, free cells starting at 99999, occupied at 0.
3. The heading. The world beam angle θ becomes the bin i = round(n·θ / 2π) of n =
   ``scan_theta_discretization`` bins over the circle (``int(t + 0.5)`` of t wrapped into [0, n)),
   the ray's direction is (cos 2πi/n, sin 2πi/n).
4. Ray marching. From the sensor position p, with d = D(p) and r = d: while d > ε (0.01 m):
   p += d·(c, s), d = D(p), r += d. A point off the map has D = 0. The range is r.

Differences from the other casters (``exact.py``): unknown cells are free, the range is the
sphere-traced distance to within ε of a wall's cell centre (not to the cell's edge), and headings
are rounded to the bins. The sensor on an occupied cell sees 0. Ranges are clipped to ``max_range``.

``distance_field`` and ``march`` are compiled (numba); ``distance_field_numpy`` and
``march_numpy`` are their numpy references, asserted equal in the tests.
"""
from __future__ import annotations

import math

import numpy as np

from localization.core.occupancy_map import OccupancyMap
from localization.core.raycast.exact import RayCaster
from localization.core.raycast.kernels import HAVE_NUMBA

FREE_START = 99999.0  # the squared distance a free cell starts at (racecar_simulator's value)
EPSILON = 0.01  # m: marching stops when the distance to the nearest wall is at most this
FREE_THRESHOLD = 0.5  # a cell with m = clip(data / 100, 0, 1) above this is occupied
MAX_STEPS = 100_000  # a bound on marching steps (the march ends long before on any map)

if HAVE_NUMBA:
    from numba import njit
else:  # pragma: no cover
    def njit(*args, **kwargs):
        return lambda f: f


def course_occupied(data: np.ndarray, free_threshold: float = FREE_THRESHOLD) -> np.ndarray:
    """The course's occupied cells of an occupancy grid (int8 −1 … 100): m = clip(data / 100, 0, 1) > threshold."""
    m = np.clip(np.asarray(data, dtype=float) / 100.0, 0.0, 1.0)
    return ~((m >= 0.0) & (m <= free_threshold))


@njit(cache=True, nogil=True)
def _envelope_1d(f, out):  # pragma: no cover - compiled
    """out[q] = min_p (f[p] + (q − p)²): racecar_simulator's ``distance_squared_1d``, step for step."""
    n = f.size
    v = np.zeros(n, dtype=np.int64)  # grid locations of the parabolas in the lower envelope
    z = np.empty(n + 1)  # their boundaries
    z[0] = -np.inf
    z[1] = np.inf
    k = 0
    for q in range(1, n):
        k += 1
        while True:
            k -= 1
            p = v[k]
            s = ((f[q] + q * q) - (f[p] + p * p)) / (2.0 * (q - p))
            if not s <= z[k]:
                break
        k += 1
        v[k] = q
        z[k] = s
        z[k + 1] = np.inf
    k = 0
    for q in range(n):
        while z[k + 1] < q:
            k += 1
        d = q - v[k]
        out[q] = d * d + f[v[k]]


@njit(cache=True, nogil=True)
def _distance_field_kernel(occupied, resolution):  # pragma: no cover - compiled
    h, w = occupied.shape
    grid = np.empty((h, w))
    for r in range(h):
        for c in range(w):
            grid[r, c] = 0.0 if occupied[r, c] else FREE_START
    col = np.zeros(h + 2)
    col_out = np.empty(h + 2)
    for c in range(w):  # columns, padded with an occupied cell at each end
        col[0] = 0.0
        col[h + 1] = 0.0
        for r in range(h):
            col[r + 1] = grid[r, c]
        _envelope_1d(col, col_out)
        for r in range(h):
            grid[r, c] = col_out[r + 1]
    row = np.zeros(w + 2)
    row_out = np.empty(w + 2)
    for r in range(h):  # then rows
        row[0] = 0.0
        row[w + 1] = 0.0
        for c in range(w):
            row[c + 1] = grid[r, c]
        _envelope_1d(row, row_out)
        for c in range(w):
            grid[r, c] = resolution * math.sqrt(row_out[c + 1])
    return grid


def distance_field(occupied: np.ndarray, resolution: float) -> np.ndarray:
    """D (h, w) in metres (module docstring, step 2) for a boolean occupied grid (row 0 at the bottom)."""
    return _distance_field_kernel(np.ascontiguousarray(occupied, dtype=np.bool_), float(resolution))


def distance_field_numpy(occupied: np.ndarray, resolution: float) -> np.ndarray:
    """``distance_field`` through scipy's exact Euclidean distance transform (nearest occupied cell,
    its integer offset squared): the reference of the compiled passes."""
    from scipy.ndimage import distance_transform_edt
    padded = np.pad(np.asarray(occupied, dtype=bool), 1, constant_values=True)
    _, (iy, ix) = distance_transform_edt(~padded, return_indices=True)
    rows, cols = np.indices(padded.shape)
    squared = ((rows - iy) ** 2 + (cols - ix) ** 2).astype(float)[1:-1, 1:-1]
    return resolution * np.sqrt(np.minimum(squared, FREE_START))


def _trig_tables(theta_bins: int):
    i = np.arange(theta_bins + 1, dtype=float)
    theta = (2.0 * math.pi * i) / float(theta_bins)
    return np.sin(theta), np.cos(theta)


@njit(cache=True, nogil=True)
def _lookup(field, x, y, ox, oy, oc, os_, resolution):  # pragma: no cover - compiled
    xt = x - ox
    yt = y - oy
    xr = xt * oc + yt * os_
    yr = -xt * os_ + yt * oc
    h, w = field.shape
    if xr < 0.0 or xr >= w * resolution or yr < 0.0 or yr >= h * resolution:
        return 0.0
    return field[int(math.floor(yr / resolution)), int(math.floor(xr / resolution))]


@njit(cache=True, nogil=True)
def _march_kernel(xs, ys, thetas, field, ox, oy, oc, os_, resolution, sines, cosines, theta_bins, epsilon,
                  out):  # pragma: no cover - compiled
    n_bins = float(theta_bins)
    for k in range(xs.size):
        t = n_bins * thetas[k] / (2.0 * math.pi)
        t = np.fmod(t, n_bins)
        while t < 0.0:
            t += n_bins
        i = int(t + 0.5)
        s = sines[i]
        c = cosines[i]
        x = xs[k]
        y = ys[k]
        d = _lookup(field, x, y, ox, oy, oc, os_, resolution)
        total = d
        steps = 0
        while d > epsilon and steps < MAX_STEPS:
            x += d * c
            y += d * s
            d = _lookup(field, x, y, ox, oy, oc, os_, resolution)
            total += d
            steps += 1
        out[k] = total


class ScanSimulatorRayCaster(RayCaster):
    """racecar_simulator's ``ScanSimulator2D`` (module docstring) behind the ``RayCaster`` interface."""

    def __init__(self, occupancy_map: OccupancyMap, max_range: float, theta_bins: int = 500,
                 epsilon: float = EPSILON):
        super().__init__(occupancy_map, max_range)
        self.theta_bins = int(theta_bins)
        if self.theta_bins < 1:
            raise ValueError(f"theta_bins must be >= 1, got {theta_bins}")
        self.epsilon = float(epsilon)
        self.course_occupied = course_occupied(occupancy_map.data)
        self.field = distance_field(self.course_occupied, occupancy_map.resolution)
        self.sines, self.cosines = _trig_tables(self.theta_bins)
        ox, oy, yaw = occupancy_map.origin
        self._frame = (float(ox), float(oy), math.cos(yaw), math.sin(yaw), float(occupancy_map.resolution))

    def cast(self, sensor_poses, angles) -> np.ndarray:
        poses = np.atleast_2d(np.asarray(sensor_poses, dtype=float))
        angles = np.asarray(angles, dtype=float).ravel()
        n, b = len(poses), angles.size
        thetas = (poses[:, 2:3] + angles[None, :]).ravel()
        return self._march(np.repeat(poses[:, 0], b), np.repeat(poses[:, 1], b), thetas).reshape(n, b)

    def cast_rays(self, sensor_poses, angles) -> np.ndarray:
        poses = np.atleast_2d(np.asarray(sensor_poses, dtype=float))
        return self._march(poses[:, 0], poses[:, 1], poses[:, 2] + np.asarray(angles, dtype=float).ravel())

    def _march(self, xs, ys, thetas) -> np.ndarray:
        out = np.empty(xs.size)
        _march_kernel(np.ascontiguousarray(xs, dtype=float), np.ascontiguousarray(ys, dtype=float),
                      np.ascontiguousarray(thetas, dtype=float), self.field, *self._frame, self.sines,
                      self.cosines, self.theta_bins, self.epsilon, out)
        return np.minimum(out, self.max_range)

    def march_numpy(self, xs, ys, thetas) -> np.ndarray:
        """``_march`` in numpy, every ray stepped together: the reference of the compiled march."""
        ox, oy, oc, os_, res = self._frame
        h, w = self.field.shape
        n = float(self.theta_bins)
        t = np.fmod(n * np.asarray(thetas, dtype=float) / (2.0 * math.pi), n)
        t = np.where(t < 0.0, t + n, t)
        i = (t + 0.5).astype(np.int64)
        s, c = self.sines[i], self.cosines[i]
        x = np.array(xs, dtype=float)
        y = np.array(ys, dtype=float)

        def lookup(x, y):
            xt, yt = x - ox, y - oy
            xr, yr = xt * oc + yt * os_, -xt * os_ + yt * oc
            inside = (xr >= 0.0) & (xr < w * res) & (yr >= 0.0) & (yr < h * res)
            col = np.where(inside, np.floor(xr / res), 0).astype(np.int64)
            row = np.where(inside, np.floor(yr / res), 0).astype(np.int64)
            return np.where(inside, self.field[row, col], 0.0)

        d = lookup(x, y)
        total = d.copy()
        live = np.flatnonzero(d > self.epsilon)
        steps = 0
        while live.size and steps < MAX_STEPS:
            x[live] += d[live] * c[live]
            y[live] += d[live] * s[live]
            d[live] = lookup(x[live], y[live])
            total[live] += d[live]
            live = live[d[live] > self.epsilon]
            steps += 1
        return np.minimum(total, self.max_range)
