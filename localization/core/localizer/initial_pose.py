"""An initial pose (``/initialpose``, a parameter, a persisted pose) checked before it spreads a cloud.

    pose        (x, y, θ) in the map frame; refused when not finite; off the map or in a wall it is
                moved to the nearest free cell (with a warning)
    no map yet  a finite pose waits for the map (``waits_for_map``): it is a pose in that map, so
                whether it lies in free space, and where the nearest free cell is, is known only then;
                it is then checked as one received after the map (the same outcome in either order)
    covariance  3×3 over (x, y, θ), used when ``use_initialpose_covariance`` and it is a usable spread:
                finite, trace > 0, every entry ≤ MAX_INITIAL_VARIANCE; otherwise the independent
                spread (initial_std_xy, initial_std_xy, initial_std_theta) with a warning
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from localization.core.occupancy_map import OccupancyMap

MAX_INITIAL_VARIANCE = 1.0e4  # m², rad²: an initial-pose covariance entry beyond this is not a pose estimate


@dataclass(frozen=True)
class InitialPose:
    pose: np.ndarray  # (3,)
    covariance: np.ndarray | None  # (3, 3), or None: use ``std``
    std: tuple  # (σx, σy, σθ) m, m, rad


def usable_covariance(cov) -> bool:
    """A 3×3 initial-pose covariance that can spread a cloud (finite, not zero, not absurd)."""
    return bool(np.all(np.isfinite(cov)) and np.trace(cov) > 0 and np.abs(cov).max() <= MAX_INITIAL_VARIANCE)


def waits_for_map(pose, occupancy_map: OccupancyMap | None, map_pending: bool) -> str:
    """Why an initial pose must wait for a map before it is checked ("" when it is checked now): no map
    yet, or the map on its way is being prepared. A pose that is not finite never waits: it is refused."""
    if not np.all(np.isfinite(np.asarray(pose, dtype=float))):
        return ""
    if map_pending:
        return "until the map being prepared is ready (it is a pose in that map)"
    if occupancy_map is None:
        return "until a map arrives (it is a pose in that map: then checked against its free space)"
    return ""


def check_initial_pose(pose, covariance, occupancy_map: OccupancyMap | None, params,
                       log: logging.Logger) -> InitialPose | None:
    """The pose and spread to initialise with (see the module docstring); None when unusable."""
    pose = np.asarray(pose, dtype=float).reshape(3)
    if not np.all(np.isfinite(pose)):
        log.warning(f"initial pose {pose.tolist()} is not finite: ignored")
        return None
    if occupancy_map is not None and not occupancy_map.is_free(pose[None, :2])[0]:
        nearest = occupancy_map.nearest_free(pose[:2])
        log.warning(f"initial pose ({pose[0]:.2f}, {pose[1]:.2f}) is not in free space: moved to the nearest free "
                    f"cell ({nearest[0]:.2f}, {nearest[1]:.2f})")
        pose = np.array([nearest[0], nearest[1], pose[2]])
    cov = None
    if covariance is not None and params.use_initialpose_covariance:
        cov = np.asarray(covariance, dtype=float).reshape(3, 3)
        if not usable_covariance(cov):
            log.warning(f"initial pose covariance {np.diag(cov).tolist()} (diagonal) is not a usable spread "
                        "(non-finite, zero, or beyond 1e4): using initial_std_xy / initial_std_theta")
            cov = None
    return InitialPose(pose=pose, covariance=cov,
                       std=(params.initial_std_xy, params.initial_std_xy, params.initial_std_theta))
