"""Global localization seeded by the scan: importance sampling of poses from a coarse exhaustive match.

A uniform spread of N particles over the free space F (|F| m²) puts N / (|F| · 2π) particles per
m²·rad: on the Stata basement (~780 m²) 40 000 particles leave most (0.3 m × 0.3 m × 10°) boxes
empty, so the true pose is often not represented and the cloud collapses onto whichever
look-alike corridor spot happens to hold a particle. Instead (sensor resetting, Lenser & Veloso
2000; the coarse stage of a correlative matcher, Olson 2009) the first scan proposes the poses:

1. lattice: free positions every ``step`` metres (a sub-grid of the free cells, random phase),
   times ``headings`` headings θ_j = θ_0 + 2πj / H (random θ_0);
2. score every lattice pose with the filter's own sensor model on a subset of ``beams`` beams
   (ℓ = squashed log-likelihood; the model decides what "matches" means: beam model or
   likelihood field alike);
3. keep the ``candidates`` best poses; the proposal q is a mixture over them with weights

       π_k ∝ exp(ℓ_k / T),   T = ``temperature`` (tempered: several look-alike places stay alive)

   and a uniform component of weight ``uniform_fraction`` (a scan the map cannot explain must
   not lock the filter out of the truth);
4. draw N particles from q, each jittered uniformly within its lattice box
   (±step/2 in x and y, ±π/H in θ), with equal weights.

The next sensor update then weighs these particles with the full scan as usual. The proposal
is not the prior (uniform) — the weights are *not* corrected by 1/q: the first update's
likelihood already favours the same places, and the tempering plus the uniform share keep the
hypotheses the single scan cannot tell apart (a self-similar corridor) alive until motion
disambiguates them.

Cost: (|F| / step²) · H poses × ``beams`` beams through the sensor model, in chunks of
``chunk`` poses (bounded memory). The lattice is scored in the model's ``locality_order`` and each
chunk inside a ``scratch()`` scope: with a range table built per tile (large maps) that is tile by
tile, and the tiles built only for a chunk are released after it, so the pass costs the whole
table's build time but only a chunk's tiles of memory. numpy only (the sensor model brings its
compiled kernel).
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from localization.core.models.sensor import SensorModel
from localization.core.occupancy_map import OccupancyMap
from localization.core.parameters import default


@dataclass(frozen=True)
class ScanSeedParams:
    """Parameters of the scan-seeded global initialisation (names as in the parameter table)."""

    global_seed_step: float = default("global_seed_step")  # m: lattice spacing of candidate positions
    global_seed_headings: int = default("global_seed_headings")  # headings per lattice position
    global_seed_beams: int = default("global_seed_beams")  # beams used to score the lattice
    global_seed_candidates: int = default("global_seed_candidates")  # best lattice poses kept
    global_seed_temperature: float = default("global_seed_temperature")  # divides the log-likelihood
    global_seed_uniform: float = default("global_seed_uniform")  # fraction of particles drawn uniformly

    @classmethod
    def from_parameters(cls, params) -> "ScanSeedParams":
        return cls(**{f.name: params[f.name] for f in fields(cls)})


@dataclass
class SeedResult:
    poses: np.ndarray  # (N, 3) the particles
    lattice_poses: int  # poses scored
    candidates: np.ndarray  # (K, 3) the kept lattice poses, best first
    candidate_log_likelihood: np.ndarray  # (K,) their squashed log-likelihoods


def lattice_positions(occupancy_map: OccupancyMap, step: float, rng: np.random.Generator) -> np.ndarray:
    """World (x, y) of the free cells on a sub-grid of spacing ``step`` (m), with a random phase."""
    s = max(1, int(round(step / occupancy_map.resolution)))
    cells = occupancy_map.free_cells  # (K, 2) row, col
    phase = rng.integers(0, s, 2)
    keep = ((cells[:, 0] - phase[0]) % s == 0) & ((cells[:, 1] - phase[1]) % s == 0)
    picked = cells[keep]
    if len(picked) == 0:  # a tiny map: every free cell
        picked = cells
    return occupancy_map.grid_to_world(picked[:, ::-1].astype(float))


def lattice_poses(xy: np.ndarray, theta: np.ndarray, start: int, count: int) -> np.ndarray:
    """Lattice poses ``start`` … ``start + count − 1`` (C-contiguous (count, 3)): pose i is position
    xy[i // H] with heading theta[i % H], H = len(theta). The positions they span are written once per
    heading (a broadcast copy, no index arrays)."""
    h = theta.size
    first, last = start // h, (start + count - 1) // h + 1
    block = np.empty((last - first, h, 3))
    block[:, :, :2] = xy[first:last, None, :]
    block[:, :, 2] = theta
    return block.reshape(-1, 3)[start - first * h:start - first * h + count]


def subset_beams(ranges, angles, count: int):
    """``count`` beams evenly spread over the valid (finite) ones."""
    ranges = np.asarray(ranges, dtype=float).ravel()
    angles = np.asarray(angles, dtype=float).ravel()
    valid = np.flatnonzero(np.isfinite(ranges))
    if valid.size == 0:
        valid = np.arange(ranges.size)
    if count < valid.size:
        valid = valid[np.linspace(0, valid.size - 1, count).round().astype(int)]
    return ranges[valid], angles[valid]


def seed_from_scan(occupancy_map: OccupancyMap, sensor_model: SensorModel, ranges, angles, n: int,
                   rng: np.random.Generator, params: ScanSeedParams | None = None, chunk: int = 100_000,
                   range_max: float | None = None) -> SeedResult:
    """``n`` particles drawn from the scan-driven proposal of the module docstring (``range_max``:
    the scan's, m, as in a sensor update)."""
    p = params or ScanSeedParams()
    xy = lattice_positions(occupancy_map, p.global_seed_step, rng)
    h = max(1, int(p.global_seed_headings))
    theta = rng.uniform(-np.pi, np.pi) + 2.0 * np.pi * np.arange(h) / h
    theta = np.mod(theta + np.pi, 2.0 * np.pi) - np.pi
    total = len(xy) * h
    z, a = subset_beams(ranges, angles, int(p.global_seed_beams))
    k = int(min(max(1, p.global_seed_candidates), total))
    # a range table built per tile (large maps): score the lattice tile by tile and give back the
    # tiles built only for each chunk, so its memory is a chunk's tiles, not the whole map's table
    xy = xy[sensor_model.locality_order(xy)]
    # the k best so far (a running top-k: memory O(chunk + k), not O(lattice))
    best_ll, best = np.empty(0), np.empty(0, dtype=np.int64)
    for start in range(0, total, chunk):  # pose i: position i // h, heading i % h
        idx = np.arange(start, min(total, start + chunk))
        poses = lattice_poses(xy, theta, start, idx.size)
        with sensor_model.scratch():
            scores = sensor_model.log_likelihood(poses, z, a, range_max=range_max)
        scores[~np.isfinite(scores)] = -np.inf
        if scores.size > k:
            top = np.argpartition(-scores, k - 1)[:k]
            scores, idx = scores[top], idx[top]
        best_ll, best = np.concatenate([best_ll, scores]), np.concatenate([best, idx])
        if best_ll.size > k:
            top = np.argpartition(-best_ll, k - 1)[:k]
            best_ll, best = best_ll[top], best[top]
    order = np.lexsort((best, -best_ll))  # best first; equal scores in lattice order
    best, ll = best[order], best_ll[order]
    cand = np.column_stack([xy[best // h], theta[best % h]])
    n_uniform = int(round(np.clip(p.global_seed_uniform, 0.0, 1.0) * n)) if np.isfinite(ll[0]) else n
    n_seeded = n - n_uniform
    out = np.empty((n, 3))
    if n_seeded > 0:
        logits = (ll - ll[0]) / max(p.global_seed_temperature, 1e-9)
        w = np.exp(logits)
        w /= w.sum()
        pick = rng.choice(k, size=n_seeded, p=w)
        half_step, half_bin = 0.5 * p.global_seed_step, np.pi / h
        out[:n_seeded, :2] = cand[pick, :2] + rng.uniform(-half_step, half_step, (n_seeded, 2))
        out[:n_seeded, 2] = cand[pick, 2] + rng.uniform(-half_bin, half_bin, n_seeded)
        out[:n_seeded, 2] = np.mod(out[:n_seeded, 2] + np.pi, 2.0 * np.pi) - np.pi
        # a jitter into a wall or off the map: back to the lattice pose itself
        bad = occupancy_map.is_occupied_or_outside(out[:n_seeded, :2])
        out[:n_seeded][bad] = cand[pick[bad]]
    if n_uniform > 0:
        out[n_seeded:] = occupancy_map.sample_free_poses(n_uniform, rng)
    return SeedResult(poses=out, lattice_poses=total, candidates=cand, candidate_log_likelihood=ll)
