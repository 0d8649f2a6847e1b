"""A perturbed world for the simulated lidar: the map the filter localizes in, changed the way a real
building differs from its map (``MapPerturbation``, ``perturb_map``; ``STANDARD_PERTURBATION``), and the
truth in the map's frame (``world_to_map``).

The simulator plans the route on the given map but ray casts the scans in ``perturb_map(map, world)``,
so a simulated error is no longer measured on the filter's own grid. The perturbed grid W is built
from the map M in this order (cell centres p, distances in metres)::

    scale:   W(p) = M(c + (p − c) / s)           c = ``scale_centre``: centroid of ``keep_free`` (else the map centre)
    glass:   patches of radius GLASS_RADIUS_M around random wall cells: occupied and unknown → free
    boxes:   squares of side U(BOX_SIDE_M) with a centre at distance U(BOX_WALL_GAP_M) from a wall
    people:  discs of radius PERSON_RADIUS_M anywhere in free space
    keep:    every cell with dist(p, keep_free) ≤ clearance keeps its value in M (or in the scaled M)

Wall cells are occupied cells with a free 4-neighbour. Boxes and people are placed only where
dist(p, keep_free) > clearance + their half size, so nothing is put on the planned path. A glass
patch makes the lidar's beams pass through the wall until the next occupied or unknown cell (the
simulator's ray caster stops at both).

Truth in the map frame (``world_to_map``)::

    q = c + (p − c) / s,    θ_q = θ_p

A robot at world pose (p, θ_p) sees what the map shows at (q, θ_p) (the scale rule above). A localizer
in the map M can only report q, so q is the truth its estimates are scored against: the simulator's
``Recording.truth_poses`` and the bag's /tf map → base_link. The world pose p is kept as the
world-frame truth (``Recording.world_truth_poses``, the bag's /truth/world when the world is perturbed);
scoring against it adds (1 − 1/s)·|p − c|, which no localizer following the map can remove. At s = 1
(no scale error, or no perturbation) q is p itself, bit for bit.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from localization.core.occupancy_map import OCCUPIED_THRESHOLD, OccupancyMap

__all__ = ["BOX_SIDE_M", "BOX_WALL_GAP_M", "GLASS_RADIUS_M", "PERSON_RADIUS_M", "STANDARD_PERTURBATION",
           "MapPerturbation", "perturb_map", "scale_centre", "world_to_map"]

BOX_SIDE_M = (0.4, 0.8)  # m: side of a furniture box, uniform in this range
BOX_WALL_GAP_M = (0.3, 0.8)  # m: distance of a box centre from the nearest wall, uniform in this range
PERSON_RADIUS_M = 0.15  # m: radius of a person's disc (0.3 m across)
GLASS_RADIUS_M = 0.3  # m: radius of one glass patch


@dataclass(frozen=True)
class MapPerturbation:
    """How the simulated world differs from the map."""

    boxes: int = 0  # furniture boxes (BOX_SIDE_M squares) added in free space near walls
    people: int = 0  # people: occupied discs of radius PERSON_RADIUS_M in free space
    glass_fraction: float = 0.0  # fraction (0..1) of wall cells that return nothing (made free)
    scale: float = 1.0  # world size / map size (e.g. 1.01: the building is 1 % larger than its map)
    clearance: float = 0.6  # m: cells this close to ``keep_free`` points keep the map's value
    seed: int = 0

    def label(self) -> str:
        """A short name of the perturbation (for file names and tables), e.g. ``b6p4g0.05s1.01c0.6seed1``."""
        return (f"b{self.boxes}p{self.people}g{self.glass_fraction:g}s{self.scale:g}c{self.clearance:g}"
                f"seed{self.seed}")


#: The standard perturbed world of the simulated trials (``localization-demo``, ``test/test_sim_perturbed.py``):
#: 6 boxes, 4 people, 5 % of the walls glass, the building 1 % larger than its map.
STANDARD_PERTURBATION = MapPerturbation(boxes=6, people=4, glass_fraction=0.05, scale=1.01, seed=1)


def _keep_points(keep_free) -> np.ndarray:
    """``keep_free`` as finite (N, 2) points."""
    keep = np.zeros((0, 2)) if keep_free is None else np.asarray(keep_free, dtype=float).reshape(-1, 2)
    return keep[np.all(np.isfinite(keep), axis=1)]


def scale_centre(occupancy_map: OccupancyMap, keep_free=None) -> np.ndarray:
    """The centre c (x, y) the world is scaled about: the centroid of the finite ``keep_free`` points
    (the planned path), else the map's centre."""
    keep = _keep_points(keep_free)
    m = occupancy_map
    return keep.mean(axis=0) if len(keep) else m.grid_to_world(np.array([m.width, m.height]) / 2.0 - 0.5)


def world_to_map(poses, scale: float, centre) -> np.ndarray:
    """World poses (N, 3) (x, y, θ) as the map shows them: q = c + (p − c) / s, θ unchanged (a new
    array; at ``scale`` 1 an exact copy)."""
    out = np.array(poses, dtype=float, copy=True)
    if scale != 1.0:
        c = np.asarray(centre, dtype=float)
        out[..., :2] = c + (out[..., :2] - c) / scale
    return out


def _distance_to(mask: np.ndarray, resolution: float) -> np.ndarray:
    """Per-cell distance (m) to the nearest True cell of ``mask`` (inf if none)."""
    from scipy.ndimage import distance_transform_edt
    if not mask.any():
        return np.full(mask.shape, np.inf)
    return distance_transform_edt(~mask) * resolution


def _cell_centres(m: OccupancyMap) -> np.ndarray:
    rows, cols = np.indices(m.data.shape)
    return m.grid_to_world(np.stack([cols, rows], axis=-1))


def _scaled(m: OccupancyMap, scale: float, centre) -> np.ndarray:
    """Grid of the world ``scale`` times the map about ``centre`` (nearest cell; off the map: unknown)."""
    src = np.asarray(centre, dtype=float) + (_cell_centres(m) - centre) / scale
    cr = m.world_to_grid(src)
    inside = m.in_bounds(cr)
    out = np.full(m.data.shape, -1, dtype=np.int8)
    out[inside] = m.data[cr[..., 1][inside], cr[..., 0][inside]]
    return out


def _pick(rng: np.random.Generator, candidates: np.ndarray, n: int) -> np.ndarray:
    """``n`` (row, col) cells drawn without replacement from a boolean grid (fewer if it has fewer)."""
    cells = np.argwhere(candidates)
    return cells[rng.choice(len(cells), size=min(n, len(cells)), replace=False)] if n > 0 and len(cells) else \
        np.zeros((0, 2), dtype=np.int64)


def perturb_map(occupancy_map: OccupancyMap, perturbation: MapPerturbation, keep_free=None) -> OccupancyMap:
    """The world of ``perturbation`` built from ``occupancy_map`` (a new map; the input is unchanged).
    ``keep_free``: (N, 2) world points (x, y), e.g. the planned trajectory, kept clear by
    ``perturbation.clearance``."""
    p = perturbation
    if not (math.isfinite(p.scale) and p.scale > 0):
        raise ValueError(f"scale must be a positive number, got {p.scale!r}")
    if not 0.0 <= p.glass_fraction <= 1.0:
        raise ValueError(f"glass_fraction must lie in [0, 1], got {p.glass_fraction!r}")
    m = occupancy_map
    res = m.resolution
    rng = np.random.default_rng(p.seed)
    keep = _keep_points(keep_free)

    if p.scale != 1.0:
        base = _scaled(m, p.scale, scale_centre(m, keep))
    else:
        base = m.data.copy()
    data = base.copy()
    occupied = data >= OCCUPIED_THRESHOLD
    free = (data >= 0) & ~occupied

    path = np.zeros(data.shape, dtype=bool)
    if len(keep):
        cr = m.world_to_grid(keep)
        cr = cr[m.in_bounds(cr)]
        path[cr[:, 1], cr[:, 0]] = True
    to_path = _distance_to(path, res)

    if p.glass_fraction > 0.0:
        nb_free = np.zeros_like(free)
        nb_free[1:] |= free[:-1]
        nb_free[:-1] |= free[1:]
        nb_free[:, 1:] |= free[:, :-1]
        nb_free[:, :-1] |= free[:, 1:]
        wall = occupied & nb_free
        per_patch = max(2.0 * GLASS_RADIUS_M / res, 1.0)  # wall cells one patch covers on a straight wall
        seeds = np.zeros_like(wall)
        pick = _pick(rng, wall, int(math.ceil(p.glass_fraction * wall.sum() / per_patch)))
        seeds[pick[:, 0], pick[:, 1]] = True
        glass = _distance_to(seeds, res) <= GLASS_RADIUS_M
        data[glass & (occupied | (data < 0))] = 0

    to_wall = _distance_to(occupied, res)
    if p.boxes > 0:
        centres = _pick(rng, free & (to_wall >= BOX_WALL_GAP_M[0]) & (to_wall <= BOX_WALL_GAP_M[1])
                        & (to_path > p.clearance + BOX_SIDE_M[1] / math.sqrt(2.0)), p.boxes)
        for (r, c), side in zip(centres, rng.uniform(*BOX_SIDE_M, len(centres))):  # a few boxes
            h = max(int(round(side / res / 2.0)), 1)
            data[max(r - h, 0):r + h + 1, max(c - h, 0):c + h + 1] = 100

    if p.people > 0:
        seeds = np.zeros(data.shape, dtype=bool)
        pick = _pick(rng, free & (to_path > p.clearance + PERSON_RADIUS_M), p.people)
        seeds[pick[:, 0], pick[:, 1]] = True
        data[_distance_to(seeds, res) <= PERSON_RADIUS_M] = 100

    near = to_path <= p.clearance
    data[near] = base[near]
    return OccupancyMap(data, res, m.origin, m.frame_id)
