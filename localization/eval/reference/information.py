"""Step 2 of the package doc: what one match tells. The information Λ of a base pose from the scan's
own beams and the map (walls as segments sharing a position error), and which axes it pins down."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from localization.core.matching import endpoints_base
from localization.core.matching.grids import signed_distance
from localization.core.occupancy_map import OccupancyMap


def edge_distance(occupancy_map: OccupancyMap, points) -> tuple[np.ndarray, np.ndarray]:
    """Distance (m, > 0 in free space) of world points (N, 2) to the map's free-space edge
    (``grids.signed_distance``, bilinear) and its gradient (N, 2) in the world frame."""
    sdf = signed_distance(occupancy_map)
    res = occupancy_map.resolution
    g = occupancy_map.world_to_grid_continuous(np.asarray(points, dtype=float).reshape(-1, 2))
    h, w = sdf.shape
    x, y = g[:, 0] - 0.5, g[:, 1] - 0.5
    c0 = np.clip(np.floor(x).astype(np.int64), 0, w - 2)
    r0 = np.clip(np.floor(y).astype(np.int64), 0, h - 2)
    fx, fy = np.clip(x - c0, 0, 1), np.clip(y - r0, 0, 1)
    s00, s01 = sdf[r0, c0], sdf[r0, c0 + 1]
    s10, s11 = sdf[r0 + 1, c0], sdf[r0 + 1, c0 + 1]
    d = ((1 - fy) * ((1 - fx) * s00 + fx * s01) + fy * ((1 - fx) * s10 + fx * s11)) * res
    gu = (1 - fy) * (s01 - s00) + fy * (s11 - s10)
    gv = (1 - fx) * (s10 - s00) + fx * (s11 - s01)
    cy, sy = math.cos(occupancy_map.origin[2]), math.sin(occupancy_map.origin[2])
    grad = np.stack([gu * cy - gv * sy, gu * sy + gv * cy], axis=1)
    return d, grad


@dataclass
class MatchInformation:
    """What one match tells (package doc, step 2)."""

    information: np.ndarray  # (3, 3) Λ of (x, y, θ) in the map frame, 1/m², 1/(m rad), 1/rad²
    inliers: int  # beams ending on a wall
    segments: int  # wall segments they form
    sigma_range: float  # m, σ_r
    median_range: float  # m, r̃ of the inliers
    inlier_fraction: float  # of the valid beams

    @property
    def covariance(self) -> np.ndarray:
        return _safe_inverse(self.information)


def _safe_inverse(info) -> np.ndarray:
    """Λ⁻¹ with a faint prior (100 m, 100 m, 10 rad) keeping a degenerate Λ invertible."""
    return np.linalg.inv(np.asarray(info, dtype=float) + np.diag([1e-4, 1e-4, 1e-2]))


def match_information(occupancy_map: OccupancyMap, ranges, angles, mount, pose, angle_increment: float,
                      range_scale: float = 1.0, max_range: float = np.inf, beam_dt=None,
                      twist=None) -> MatchInformation:
    """Λ of a base pose for one scan (package doc, step 2); the endpoints as the matcher makes them
    (``endpoints_base``: valid beams in scan order, deskewed with ``beam_dt`` and ``twist``)."""
    res = occupancy_map.resolution
    q, r = endpoints_base(ranges, angles, mount, range_scale, max_range, beam_dt, twist)
    empty = MatchInformation(np.zeros((3, 3)), 0, 0, float("nan"), float("nan"), 0.0)
    if len(q) < 3:
        return empty
    x, y, th = (float(v) for v in pose)
    c, s = math.cos(th), math.sin(th)
    rx, ry = c * q[:, 0] - s * q[:, 1], s * q[:, 0] + c * q[:, 1]  # endpoint − base, map frame
    d, grad = edge_distance(occupancy_map, np.stack([x + rx, y + ry], axis=1))
    near = np.abs(d) <= 3 * res
    if np.count_nonzero(near) < 3:
        return MatchInformation(np.zeros((3, 3)), 0, 0, float("nan"), float("nan"), 0.0)
    dn = d[near]
    sigma_r = max(1.4826 * float(np.median(np.abs(dn - np.median(dn)))), 0.1 * res)
    gnorm = np.hypot(grad[:, 0], grad[:, 1])
    inl = (np.abs(d) <= max(3 * sigma_r, res)) & (gnorm > 0.3)
    idx = np.flatnonzero(inl)
    m = idx.size
    if m < 3:
        return MatchInformation(np.zeros((3, 3)), int(m), 0, sigma_r, float("nan"), m / len(q))
    n = grad[idx] / gnorm[idx, None]
    J = np.stack([n[:, 0], n[:, 1], n[:, 0] * -ry[idx] + n[:, 1] * rx[idx]], axis=1)
    # segments: consecutive inliers close together on a wall of the same orientation
    px, py = x + rx[idx], y + ry[idx]
    gap = np.hypot(np.diff(px), np.diff(py))
    limit = np.maximum(2 * res, 3 * r[idx[:-1]] * abs(angle_increment))
    same = (gap <= limit) & (np.sum(n[1:] * n[:-1], axis=1) >= 0.8)
    label = np.concatenate([[0], np.cumsum(~same)])
    nseg = int(label[-1]) + 1
    sum_j = np.zeros((nseg, 3))
    np.add.at(sum_j, label, J)
    count = np.bincount(label, minlength=nseg).astype(float)
    sigma_m2 = res * res / 12.0
    cs = sigma_m2 / (sigma_r ** 2 + count * sigma_m2)
    info = (J.T @ J - (sum_j * cs[:, None]).T @ sum_j) / sigma_r ** 2
    info = 0.5 * (info + info.T)
    return MatchInformation(info, int(m), nseg, sigma_r, float(np.median(r[idx])), m / len(q))


def constrained_axes(info, median_range: float, res: float, directions=None) -> np.ndarray:
    """Which of x, y, θ (and, with ``directions`` (2,) unit travel direction, along and across it)
    a match with information ``info`` pins down (package doc, step 2): (3,) or (5,) bool."""
    cov = _safe_inverse(info)
    tau = 0.5 * res
    tau_th = tau / median_range if np.isfinite(median_range) and median_range > 0 else 0.0
    out = [cov[0, 0] <= tau ** 2, cov[1, 1] <= tau ** 2, cov[2, 2] <= tau_th ** 2]
    if directions is not None:
        u = np.asarray(directions, dtype=float)
        nrm = np.array([-u[1], u[0]])
        out += [u @ cov[:2, :2] @ u <= tau ** 2, nrm @ cov[:2, :2] @ nrm <= tau ** 2]
    return np.array(out, dtype=bool)
