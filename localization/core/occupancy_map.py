"""The occupancy grid map: cell states, world <-> grid transforms, free space.

Same semantics as a ``nav_msgs/OccupancyGrid``: ``data[row, col]`` with row 0 at the bottom
(the map's origin), values 0..100 (probability of occupancy in percent) and -1 for unknown.
The origin pose ``(x, y, yaw)`` is the world pose of the corner of cell (0, 0); its yaw rotates
the whole grid (the Stata basement maps have yaw 3.14), so every transform applies it.

Cell classes used by the rest of the package:
- *occupied*: value >= ``OCCUPIED_THRESHOLD`` (the car cannot be there; rays stop);
- *free*: 0 <= value < ``OCCUPIED_THRESHOLD`` ... only values below ``FREE_THRESHOLD`` count as
  free space for sampling particles;
- *unknown*: -1. Rays stop at unknown cells too (as in nav2 AMCL's ``map_calc_range``): beyond
  the mapped walls there is nothing the map can predict.
"""
from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from localization.core.geometry import yaw_of
from localization.core.paths import resolve_map_path

OCCUPIED_THRESHOLD = 50
FREE_THRESHOLD = 50


class MapError(ValueError):
    """An unreadable or inconsistent map."""


ORIGIN_DECIMALS = 9  # the origin (m, m, rad) is hashed rounded to 1e-9


def quantized_geometry(resolution: float, origin) -> list[float]:
    """[resolution, x, y, yaw] as hashed: the resolution as the shortest decimal that names its float32
    value (nav_msgs/MapMetaData carries a float32: 0.0504 arrives as 0.05040000006556511 and is 0.0504
    again here), the origin rounded to ORIGIN_DECIMALS. A resolution or origin read from YAML as a
    short decimal is unchanged, so digests of YAML maps stay what they were."""
    return [float(str(np.float32(resolution))), *(round(float(v), ORIGIN_DECIMALS) for v in origin)]


@dataclass
class OccupancyMap:
    data: np.ndarray  # (height, width) int8, row 0 at the bottom, -1 unknown
    resolution: float  # metres per cell
    origin: tuple = (0.0, 0.0, 0.0)  # world pose (x, y, yaw) of the corner of cell (0, 0)
    frame_id: str = "map"
    source: Path | None = field(default=None, compare=False)  # the YAML it was read from, if any
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self):
        data = np.asarray(self.data)
        if data.ndim != 2 or data.size == 0:
            raise MapError(f"map data must be a non-empty 2D grid, got shape {data.shape}")
        if not (np.isfinite(self.resolution) and self.resolution > 0):
            raise MapError(f"map resolution must be a positive number, got {self.resolution!r}")
        origin = tuple(float(v) for v in self.origin)
        if len(origin) != 3 or not all(math.isfinite(v) for v in origin):
            raise MapError(f"map origin must be three finite numbers (x, y, yaw), got {self.origin!r}")
        self.data = np.ascontiguousarray(data, dtype=np.int8)
        self.resolution = float(self.resolution)
        self.origin = origin

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_msg(cls, msg) -> "OccupancyMap":
        """From a ``nav_msgs/OccupancyGrid`` (or anything with the same fields)."""
        info = msg.info
        width, height = int(info.width), int(info.height)
        data = np.asarray(msg.data, dtype=np.int8)
        if width <= 0 or height <= 0:
            raise MapError(f"map has no cells ({width} x {height})")
        if data.size != width * height:
            raise MapError(f"map data has {data.size} cells but width x height = {width} x {height} = {width * height}")
        o = info.origin
        yaw = yaw_of(o.orientation)
        frame = getattr(getattr(msg, "header", None), "frame_id", "") or "map"
        return cls(data.reshape(height, width), float(info.resolution),
                   (float(o.position.x), float(o.position.y), yaw), frame)

    @classmethod
    def from_yaml(cls, path) -> "OccupancyMap":
        """From a map_server YAML + image, with nav2 map_server's semantics
        (``mode`` trinary/scale/raw, ``negate``, ``occupied_thresh``, ``free_thresh``)."""
        import yaml
        from PIL import Image

        path = Path(path)
        try:
            meta = yaml.safe_load(path.read_text())
        except (OSError, yaml.YAMLError) as exc:
            raise MapError(f"cannot read map YAML {path}: {exc}") from exc
        if not isinstance(meta, dict):
            raise MapError(f"map YAML {path} is not a mapping")
        try:
            image_path = path.parent / str(meta["image"])
            resolution = float(meta["resolution"])
            origin = [float(v) for v in meta["origin"]]
        except (KeyError, TypeError, ValueError) as exc:
            raise MapError(f"map YAML {path} lacks a valid image/resolution/origin: {exc}") from exc
        negate = bool(int(meta.get("negate", 0)))
        occ_th = float(meta.get("occupied_thresh", 0.65))
        free_th = float(meta.get("free_thresh", 0.196))
        mode = str(meta.get("mode", "trinary"))
        try:
            with Image.open(image_path) as img:
                pixels = np.asarray(img)
        except OSError as exc:
            raise MapError(f"cannot read map image {image_path}: {exc}") from exc
        grid = grid_from_image(pixels, negate, occ_th, free_th, mode)
        if len(origin) == 2:
            origin.append(0.0)
        return cls(grid[::-1].copy(), resolution, tuple(origin[:3]), source=path)

    # ------------------------------------------------------------------ properties
    @property
    def height(self) -> int:
        return self.data.shape[0]

    @property
    def width(self) -> int:
        return self.data.shape[1]

    @property
    def occupied(self) -> np.ndarray:
        """Boolean grid: cells that are occupied."""
        return self._cached("occupied", lambda: self.data >= OCCUPIED_THRESHOLD)

    @property
    def free(self) -> np.ndarray:
        """Boolean grid: known free cells."""
        return self._cached("free", lambda: (self.data >= 0) & (self.data < FREE_THRESHOLD))

    @property
    def free_cells(self) -> np.ndarray:
        """(K, 2) int array of (row, col) of the free cells."""
        return self._cached("free_cells", lambda: np.argwhere(self.free))

    @property
    def digest(self) -> str:
        """A content hash (cells, resolution, origin): a key for caches derived from the map. The
        resolution and origin are hashed quantized (``quantized_geometry``), so the map read from its
        YAML and the same map received as a nav_msgs/OccupancyGrid (float32 resolution, yaw through a
        quaternion) have one digest, hence one range table."""
        def compute():
            h = hashlib.sha1(self.data.tobytes())
            h.update(np.asarray([*quantized_geometry(self.resolution, self.origin), *self.data.shape],
                                dtype=float).tobytes())
            return h.hexdigest()[:16]
        return self._cached("digest", compute)

    def _cached(self, key, compute):
        if key not in self._cache:
            self._cache[key] = compute()
        return self._cache[key]

    # ------------------------------------------------------------------ transforms
    def world_to_grid_continuous(self, xy) -> np.ndarray:
        """World (x, y) -> continuous grid coordinates (col, row) in cells (cell centres at +0.5)."""
        xy = np.asarray(xy, dtype=float)
        ox, oy, yaw = self.origin
        c, s = math.cos(yaw), math.sin(yaw)
        dx, dy = xy[..., 0] - ox, xy[..., 1] - oy
        out = np.empty(xy.shape[:-1] + (2,))
        out[..., 0] = (c * dx + s * dy) / self.resolution
        out[..., 1] = (-s * dx + c * dy) / self.resolution
        return out

    def world_to_grid(self, xy) -> np.ndarray:
        """World (x, y) -> integer (col, row) indices (may lie outside the grid; a non-finite
        coordinate maps to -1, i.e. outside)."""
        g = self.world_to_grid_continuous(xy)
        g = np.where(np.isfinite(g), np.clip(g, -2.0**40, 2.0**40), -1.0)
        return np.floor(g).astype(np.int64)

    def grid_to_world(self, colrow) -> np.ndarray:
        """Integer (col, row) indices -> world (x, y) of the cell centres."""
        cr = np.asarray(colrow, dtype=float) + 0.5
        ox, oy, yaw = self.origin
        c, s = math.cos(yaw), math.sin(yaw)
        gx, gy = cr[..., 0] * self.resolution, cr[..., 1] * self.resolution
        out = np.empty(cr.shape[:-1] + (2,))
        out[..., 0] = ox + c * gx - s * gy
        out[..., 1] = oy + s * gx + c * gy
        return out

    def world_to_grid_pose(self, poses) -> np.ndarray:
        """World poses (x, y, θ) -> grid poses (col, row, θ - origin yaw), continuous, in cells."""
        poses = np.asarray(poses, dtype=float)
        out = np.empty(poses.shape)
        out[..., :2] = self.world_to_grid_continuous(poses[..., :2])
        out[..., 2] = poses[..., 2] - self.origin[2]
        return out

    def in_bounds(self, colrow) -> np.ndarray:
        colrow = np.asarray(colrow)
        return ((colrow[..., 0] >= 0) & (colrow[..., 0] < self.width)
                & (colrow[..., 1] >= 0) & (colrow[..., 1] < self.height))

    def lookup(self, xy, grid: np.ndarray, outside=False) -> np.ndarray:
        """Value of a per-cell boolean ``grid`` at world points; ``outside`` off the map."""
        cr = self.world_to_grid(xy)
        inside = self.in_bounds(cr)
        out = np.full(cr.shape[:-1], outside, dtype=grid.dtype)
        out[inside] = grid[cr[..., 1][inside], cr[..., 0][inside]]
        return out

    def is_free(self, xy) -> np.ndarray:
        """True where world points lie in known free cells."""
        return self.lookup(xy, self.free, outside=False)

    def is_occupied_or_outside(self, xy) -> np.ndarray:
        """True where world points lie in occupied cells or off the map."""
        return self.lookup(xy, self.occupied, outside=True)

    def sample_free_poses(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """``n`` poses (x, y, θ) uniform over the free cells (continuous within each cell),
        headings uniform in [-π, π). Raises MapError when there is no free cell."""
        cells = self.free_cells
        if len(cells) == 0:
            raise MapError("the map has no free cells to spread poses over")
        pick = cells[rng.integers(0, len(cells), n)]
        colrow = pick[:, ::-1] + rng.uniform(-0.5, 0.5, (n, 2))
        poses = np.empty((n, 3))
        poses[:, :2] = self.grid_to_world(colrow)
        poses[:, 2] = rng.uniform(-np.pi, np.pi, n)
        return poses

    def nearest_free(self, xy) -> np.ndarray:
        """World (x, y) of the free cell centre nearest to a world point (on or off the map)."""
        cells = self.free_cells
        if len(cells) == 0:
            raise MapError("map has no free cell")
        cr = np.clip(self.world_to_grid(np.asarray(xy, dtype=float)), 0, [self.width - 1, self.height - 1])
        def compute():
            from scipy.ndimage import distance_transform_edt
            return distance_transform_edt(~self.free, return_distances=False, return_indices=True)
        rows, cols = self._cached("nearest_free_index", compute)
        return self.grid_to_world(np.array([cols[cr[1], cr[0]], rows[cr[1], cr[0]]]))

    def near_obstacle(self, radius: float) -> np.ndarray:
        """Per-cell: is the centre of an occupied cell within ``radius`` metres of this cell's
        centre? (``distance_to_obstacle() <= radius``, computed by a binary dilation: cheaper than the EDT.)"""
        def compute():
            # the disk as rows: for each row offset ±di, a horizontal run of half-width w(di) (shifted
            # ORs), shifted by ±di; the cells of binary_dilation(structure=disk), faster on large maps
            # and with one run grid alive at a time
            reach = int(math.floor(radius / self.resolution + 1e-9))
            if reach < 0:
                return np.zeros(self.data.shape, dtype=bool)
            occ = self.occupied
            h = occ.shape[0]
            out = np.zeros(occ.shape, dtype=bool)
            cols = np.arange(reach + 1)
            run, run_w = occ.copy(), 0
            for di in range(reach, -1, -1):  # w(di) grows as |di| shrinks: widen one run in place
                w = int(cols[(di * di + cols * cols) * self.resolution ** 2 <= radius * radius + 1e-12].max())
                for dj in range(run_w + 1, w + 1):
                    run[:, dj:] |= occ[:, :-dj]
                    run[:, :-dj] |= occ[:, dj:]
                run_w = max(run_w, w)
                out[di:] |= run[:h - di]
                if di:
                    out[:h - di] |= run[di:]
            return out
        return self._cached(("near_obstacle", float(radius)), compute)

    def distance_to_obstacle(self) -> np.ndarray:
        """Per-cell Euclidean distance (metres) to the nearest occupied cell."""
        def compute():
            from scipy.ndimage import distance_transform_edt
            if not self.occupied.any():
                return np.full(self.data.shape, np.inf)
            return distance_transform_edt(~self.occupied) * self.resolution
        return self._cached("distance_to_obstacle", compute)


def grid_from_image(pixels, negate, occupied_thresh, free_thresh, mode="trinary") -> np.ndarray:
    """map_server's conversion of an image array (grey (H, W) or colour (H, W, C), top row first): a
    colour pixel is the mean of its colour channels (alpha ignored), then ``occupancy_from_pixels``.
    An 8-bit image is converted through a table over every value its pixels can take (the sum of the
    colour channels), with the same result as the float pass over the image and a fraction of its cost."""
    colour = pixels.ndim == 3 and pixels.shape[2] >= 3
    if pixels.dtype == np.uint8:
        if colour:
            index = pixels[..., 0].astype(np.uint16)
            index += pixels[..., 1]
            index += pixels[..., 2]
            levels = np.arange(3 * 255 + 1) / 3.0
        else:
            index, levels = (pixels if pixels.ndim == 2 else pixels[..., 0]), np.arange(256.0)
        return occupancy_from_pixels(levels, negate, occupied_thresh, free_thresh, mode)[index]
    if pixels.ndim == 3:
        pixels = pixels[..., :3].mean(axis=2) if colour else pixels[..., 0]
    return occupancy_from_pixels(pixels.astype(float), negate, occupied_thresh, free_thresh, mode)


def occupancy_from_pixels(pixels, negate, occupied_thresh, free_thresh, mode="trinary") -> np.ndarray:
    """map_server's image -> occupancy conversion (``pixels`` 0..255, top row first)."""
    if mode == "raw":
        return np.where(pixels > 100, -1, pixels).astype(np.int8)
    p = pixels / 255.0 if negate else (255.0 - pixels) / 255.0
    grid = np.full(p.shape, -1, dtype=np.int8)
    grid[p > occupied_thresh] = 100
    grid[p < free_thresh] = 0
    if mode == "scale":
        between = (p >= free_thresh) & (p <= occupied_thresh)
        grid[between] = np.rint(99.0 * (p[between] - free_thresh) / (occupied_thresh - free_thresh)).astype(np.int8)
    elif mode != "trinary":
        raise MapError(f"unknown map mode {mode!r} (trinary, scale or raw)")
    return grid


def load_map(name_or_path) -> OccupancyMap:
    """A map_server map by YAML path or bare name (``stata_basement``: see ``paths.resolve_map_path``).
    Raises MapError (one line: what is wrong) for a missing or unreadable map."""
    path = resolve_map_path(name_or_path)
    if path.suffix not in (".yaml", ".yml"):
        raise MapError(f"map {name_or_path} is not a map_server YAML file (give the .yaml, not the image, "
                       "or a map name such as stata_basement)")
    if not path.is_file():
        raise MapError(f"map not found: {path}")
    return OccupancyMap.from_yaml(path)
